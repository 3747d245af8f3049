//! Stereo input (issue 19): `camera.toml`'s `[right]` table and `rgb_right.txt`, read into a
//! stereo rig and two views per frame; every problem of the rig reported at once.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::config::InputConfig;
use capsule_slam_framework::files::{read_camera_file, write_camera_file};
use capsule_slam_framework::frame::Views;
use capsule_slam_io::{Dataset, images};
use capsule_slam_tests::fixtures::{camera, gt_pose, render, right_camera, write_dataset, write_stereo_dataset};

#[test]
fn a_stereo_folder_gives_a_calibrated_rig_and_both_views() {
    let tmp = tempfile::tempdir().unwrap();
    write_stereo_dataset(tmp.path(), 4);
    let ds = Dataset::open(tmp.path(), &InputConfig::default(), None).unwrap();
    let Rig::Stereo { left, right, t_right_left } = ds.rig() else { panic!("a mono rig") };
    assert_eq!((left.fx, right.fx, right.cy), (40.0, 41.0, 19.0));
    assert!((ds.rig().baseline_m().unwrap() - 0.005).abs() < 1e-12);
    // OpenCV's convention: the right camera's centre, seen from the left, is 5 mm along +x.
    let centre = t_right_left.inverse() * nalgebra::Point3::origin();
    assert!((centre.coords - nalgebra::Vector3::new(0.005, 0.0, 0.0)).norm() < 1e-12, "{centre}");
    // Each frame carries the right image of its own time (stamped 2 ms later), not the left.
    let f = ds.load(2).unwrap();
    let Views::Stereo { left: l, right: r } = &f.views else { panic!("one view") };
    let right_file = capsule_slam_framework::camera::CameraFile { fx: 41.0, fy: 40.5, cx: 24.0, cy: 19.0, ..camera() };
    let (expected, _) = render(&right_file, &(gt_pose(2) * t_right_left.inverse()));
    assert_eq!(r.data(), expected.data());
    assert_ne!(l.data(), r.data());
}

#[test]
fn a_right_view_missing_from_the_list_drops_its_frame_and_a_missing_file_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    write_stereo_dataset(tmp.path(), 4);
    let list = tmp.path().join("rgb_right.txt");
    let text = std::fs::read_to_string(&list).unwrap();
    let kept: Vec<&str> = text.lines().filter(|l| !l.contains("0001.png")).collect();
    std::fs::write(&list, kept.join("\n")).unwrap();
    let ds = Dataset::open(tmp.path(), &InputConfig::default(), None).unwrap();
    assert_eq!((ds.len(), ds.dropped_without_right(), ds.dropped_without_depth()), (3, 1, 0));
    std::fs::remove_file(tmp.path().join("rgb_right/0002.png")).unwrap();
    let err = ds.load(1).unwrap_err().to_string();
    assert!(err.contains("rgb_right/0002.png"), "{err}");
}

#[test]
fn a_stereo_list_and_a_stereo_camera_need_each_other() {
    let tmp = tempfile::tempdir().unwrap();
    write_stereo_dataset(tmp.path(), 2);
    // The list without the rig.
    write_camera_file(&tmp.path().join("camera.toml"), &camera()).unwrap();
    let err = Dataset::open(tmp.path(), &InputConfig::default(), None).unwrap_err().to_string();
    assert!(err.contains("rgb_right.txt") && err.contains("[right]"), "{err}");
    // The rig without the list.
    let mono = tempfile::tempdir().unwrap();
    write_dataset(mono.path(), 2);
    let mut cam = camera();
    cam.baseline_m = Some(0.005);
    write_camera_file(&mono.path().join("camera.toml"), &cam).unwrap();
    let err = Dataset::open(mono.path(), &InputConfig::default(), None).unwrap_err().to_string();
    assert!(err.contains("rgb_right.txt") && err.contains("missing"), "{err}");
}

#[test]
fn every_problem_of_a_right_table_is_named_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("camera.toml");
    let mut cam = camera();
    cam.baseline_m = Some(0.005);
    cam.right = Some(capsule_slam_framework::stereo::RightCameraFile {
        fy: None,
        rotation: Some(vec![1.0, 0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
        translation_m: Some(vec![0.0, 0.0]),
        ..right_camera()
    });
    write_camera_file(&path, &cam).unwrap();
    let err = read_camera_file(&path).unwrap_err().to_string();
    for key in ["right.fy", "right.rotation", "orthonormal", "right.translation_m", "baseline_m"] {
        assert!(err.contains(key), "{key} not named: {err}");
    }
    // A reflection is not a rotation either; an unknown key in [right] is named.
    cam.baseline_m = None;
    cam.right = Some(capsule_slam_framework::stereo::RightCameraFile { rotation: Some(vec![-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]), ..right_camera() });
    write_camera_file(&path, &cam).unwrap();
    let err = read_camera_file(&path).unwrap_err().to_string();
    assert!(err.contains("right.rotation") && err.contains("determinant"), "{err}");
    let text = std::fs::read_to_string(&path).unwrap().replace("[right]", "[right]\nbaseline = 3");
    std::fs::write(&path, text).unwrap();
    let err = read_camera_file(&path).unwrap_err().to_string();
    assert!(err.contains("baseline"), "{err}");
}

#[test]
fn a_right_lens_is_undistorted_as_the_frames_load() {
    let tmp = tempfile::tempdir().unwrap();
    write_stereo_dataset(tmp.path(), 2);
    let mut cam = read_camera_file(&tmp.path().join("camera.toml")).unwrap();
    let right = cam.right.as_mut().unwrap();
    right.distortion = Some(capsule_slam_framework::lens::DistortionSpec::Coefficients(vec![-0.2, 0.05, 0.0, 0.0, 0.0]));
    write_camera_file(&tmp.path().join("camera.toml"), &cam).unwrap();
    let ds = Dataset::open(tmp.path(), &InputConfig::default(), None).unwrap();
    let Rig::Stereo { left, right, .. } = ds.rig() else { panic!("a mono rig") };
    assert!(left.distortion.is_none() && right.distortion.is_none(), "the stages see pinhole cameras");
    let f = ds.load(0).unwrap();
    let Views::Stereo { right: r, .. } = &f.views else { panic!("one view") };
    let raw = images::read_rgb(&tmp.path().join("rgb_right/0000.png"), None).unwrap();
    assert_eq!(r.size(), raw.size());
    assert_ne!(r.data(), raw.data(), "the right view went through its own lens's map");
}

#[test]
fn a_stereo_sequence_runs_through_the_rgbd_pipeline_on_its_left_view() {
    // Until a stereo depth stage exists, the left view and its depth are the frame: the
    // preprocessors see both views, the rest the left one. So the run is the mono run of the
    // same left frames, to the bit.
    let tmp = tempfile::tempdir().unwrap();
    let (stereo, mono) = (tmp.path().join("stereo"), tmp.path().join("mono"));
    write_stereo_dataset(&stereo, 8);
    write_dataset(&mono, 8);
    let run = |data: &std::path::Path, out: &str| {
        let out = tmp.path().join(out);
        let s = capsule_slam_tests::runs::run_with(data, &out, &["pipeline.depth=sensor"], &capsule_slam_run::RunOptions::default());
        (s, std::fs::read_to_string(out.join("trajectory.txt")).unwrap())
    };
    let ((s, stereo_traj), (m, mono_traj)) = (run(&stereo, "out_stereo"), run(&mono, "out_mono"));
    assert_eq!((s.status.as_str(), s.frames), ("complete", 8));
    assert_eq!(s.frames_lost, m.frames_lost);
    assert_eq!(stereo_traj, mono_traj);
}

#[test]
fn the_stereo_phantom_writes_a_rig_whose_views_agree_with_its_geometry() {
    use capsule_slam_framework::stereo::rectify::Side;
    use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
    let tmp = tempfile::tempdir().unwrap();
    let spec = PhantomSpec { frames: 3, size: SizePreset::NanEye, stereo_baseline_mm: Some(5.0), ..PhantomSpec::preset(2) };
    let ph = Phantom::new(spec).unwrap();
    capsule_slam_phantom::writer::write_sequence(&ph, tmp.path(), &|_| {}).unwrap();
    let ds = Dataset::open(tmp.path(), &InputConfig::default(), None).unwrap();
    let rig = ds.rig();
    let Rig::Stereo { left, right, t_right_left } = &rig else { panic!("a mono rig") };
    assert!((rig.baseline_m().unwrap() - 0.005).abs() < 1e-12);
    assert!(matches!(ds.load(1).unwrap().views, Views::Stereo { .. }));
    // The light sits midway between the cameras.
    let light = capsule_slam_framework::files::read_light_file(&tmp.path().join("light.toml")).unwrap();
    assert!((light.position_m[0] - 0.0025).abs() < 1e-12);
    // A wall point seen by the left camera is where the right camera sees it, at the depth it
    // measures there (the right view rendered from its own pose).
    let (l, r) = (ph.render_view(1, Side::Left), ph.render_view(1, Side::Right));
    let (mut agree, mut seen) = (0, 0);
    for y in (10..left.height - 10).step_by(7) {
        for x in (10..left.width - 10).step_by(7) {
            let z = f64::from(l.depth_m.at(x, y));
            let Some(uv) = (z > 0.0).then(|| right.project(&(t_right_left * left.unproject(x as f64, y as f64, z)))).flatten() else { continue };
            let (u, v) = (uv.x.round(), uv.y.round());
            if u < 0.0 || v < 0.0 || u as usize >= right.width || v as usize >= right.height || r.depth_m.at(u as usize, v as usize) <= 0.0 {
                continue;
            }
            seen += 1;
            let z_right = (t_right_left * left.unproject(x as f64, y as f64, z)).z;
            agree += usize::from((f64::from(r.depth_m.at(u as usize, v as usize)) - z_right).abs() < 0.01 * z_right);
        }
    }
    assert!(seen > 500 && agree as f64 > 0.97 * seen as f64, "{agree} of {seen} agree");
    // The right view differs from the left (not a copy), and its highlights are its own.
    assert_ne!(l.rgb.data(), r.rgb.data());
    assert_ne!(l.specular.data(), r.specular.data());
}
