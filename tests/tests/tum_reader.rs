//! The TUM reader on fixtures written by the tests: association, and every error naming the
//! file and line.

use capsule_slam_framework::config::InputConfig;
use capsule_slam_io::Dataset;
use capsule_slam_tests::fixtures;

fn open(dir: &std::path::Path) -> Result<Dataset, String> {
    Dataset::open(dir, &InputConfig::default(), None).map_err(|e| e.to_string())
}

#[test]
fn frames_associate_depth_and_ground_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let gt = fixtures::write_dataset(tmp.path(), 5);
    let ds = open(tmp.path()).unwrap();
    assert_eq!(ds.len(), 5);
    assert!(ds.has_depth());
    assert_eq!(ds.ground_truth().len(), 5);
    let f = ds.load(3).unwrap();
    assert!((f.timestamp_s - gt[3].timestamp_s).abs() < 1e-9);
    assert!((f.gt_t_world_cam.unwrap().translation.vector - gt[3].t_world_cam.translation.vector).norm() < 1e-8);
    let d = f.depth_m.unwrap();
    // The plane z = 0.05 m seen nearly head-on: depth about 5 cm, 16-bit quantised at 0.2 mm.
    let centre = d.at(24, 20);
    assert!((centre - 0.05).abs() < 0.002, "{centre}");
}

#[test]
fn a_timestamp_gap_drops_the_frame_without_depth() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 5);
    let p = tmp.path().join("depth.txt");
    let text = std::fs::read_to_string(&p).unwrap();
    let kept: Vec<&str> = text.lines().filter(|l| !l.ends_with("0002.png")).collect();
    std::fs::write(&p, kept.join("\n")).unwrap();
    let ds = open(tmp.path()).unwrap();
    assert_eq!(ds.len(), 4);
    assert_eq!(ds.dropped_without_depth(), 1);
}

#[test]
fn a_bad_line_names_file_and_line() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 3);
    let p = tmp.path().join("rgb.txt");
    let mut text = std::fs::read_to_string(&p).unwrap();
    text.push_str("12.5\n");
    std::fs::write(&p, text).unwrap();
    let e = open(tmp.path()).unwrap_err();
    assert!(e.contains("rgb.txt:5") && e.contains("timestamp filename"), "{e}");

    fixtures::write_dataset(tmp.path(), 3);
    let g = tmp.path().join("groundtruth.txt");
    std::fs::write(&g, "1.0 0 0 0 0 0 0\n").unwrap();
    let e = open(tmp.path()).unwrap_err();
    assert!(e.contains("groundtruth.txt:1") && e.contains("8 values"), "{e}");
    std::fs::write(&g, "1.0 0 0 0 0 0 0 abc\n").unwrap();
    assert!(open(tmp.path()).unwrap_err().contains("not a finite number"));
}

#[test]
fn missing_files_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 3);
    std::fs::remove_file(tmp.path().join("depth/0001.png")).unwrap();
    let ds = open(tmp.path()).unwrap();
    let e = ds.load(1).unwrap_err().to_string();
    assert!(e.contains("depth/0001.png") && e.contains("not found"), "{e}");

    std::fs::remove_file(tmp.path().join("camera.toml")).unwrap();
    let e = open(tmp.path()).unwrap_err();
    assert!(e.contains("camera.toml") && e.contains("missing"), "{e}");
    assert!(open(&tmp.path().join("nope")).unwrap_err().contains("not found"));
}

#[test]
fn a_wrong_image_size_is_reported() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 2);
    let mut cam = fixtures::camera();
    cam.width = 50;
    capsule_slam_framework::files::write_camera_file(&tmp.path().join("camera.toml"), &cam).unwrap();
    let e = open(tmp.path()).unwrap().load(0).unwrap_err().to_string();
    assert!(e.contains("48×40") && e.contains("50×40"), "{e}");
}

#[test]
fn a_plain_image_folder_is_accepted() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 3);
    let imgs = tmp.path().join("rgb");
    capsule_slam_framework::files::write_camera_file(&imgs.join("camera.toml"), &fixtures::camera()).unwrap();
    let cfg = InputConfig { frame_rate_hz: 10.0, ..InputConfig::default() };
    let ds = Dataset::open(&imgs, &cfg, None).unwrap();
    assert_eq!(ds.len(), 3);
    assert!(!ds.has_depth());
    let f = ds.load(2).unwrap();
    assert!((f.timestamp_s - 0.2).abs() < 1e-12);
    assert!(f.depth_m.is_none());
}

#[test]
fn a_round_field_of_view_becomes_an_out_of_view_mask() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 1);
    let mut cam = fixtures::camera();
    cam.fov_radius_px = Some(15.0);
    capsule_slam_framework::files::write_camera_file(&tmp.path().join("camera.toml"), &cam).unwrap();
    let f = open(tmp.path()).unwrap().load(0).unwrap();
    let m = f.masks.get(capsule_slam_framework::frame::MASK_OUT_OF_VIEW).unwrap();
    assert!(m.at(0, 0) && !m.at(24, 20));
}
