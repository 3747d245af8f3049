//! Camera models end to end (issue 18, item 6): a phantom rendered through a lens, read back
//! undistorted, tracked and fused as well as the pinhole phantom; the same frames read as if the
//! lens were a pinhole are not.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::path::Path;

use capsule_slam_framework::camera::CameraFile;
use capsule_slam_framework::config::{Config, UndistortedView};
use capsule_slam_framework::files::{read_camera_file, write_camera_file};
use capsule_slam_framework::lens::LensModel;
use capsule_slam_io::Dataset;
use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::{RunOptions, Summary};
use capsule_slam_tests::runs::{metric, run_with};

/// A capsule-like barrel lens: the image corner 22 % nearer the centre than a pinhole's.
const BARREL: LensModel = LensModel::RadialTangential([-0.3, 0.1, 0.001, -0.002, 0.0, 0.0, 0.0, 0.0]);
const FISHEYE: LensModel = LensModel::Equidistant([0.05, -0.01, 0.002, -0.0005]);

fn run_on(data: &Path, out: &Path, tracker: &str) -> Summary {
    let tracker_set = format!("pipeline.tracker={tracker}");
    // Every fused surfel, the tentative ones at the rim too: the test is about where each
    // pixel's depth lands, not which surfels are written.
    let sets = ["pipeline.depth=sensor", "pipeline.preprocess=[]", tracker_set.as_str(), "input.initial_pose=ground-truth", "output.map_surfels=all"];
    run_with(data, out, &sets, &RunOptions { write_map: true, ..RunOptions::default() })
}

/// Preset 2's path in `frames` frames (100: about 2 mm per frame).
fn phantom(dir: &Path, lens: Option<LensModel>, frames: usize) {
    let spec = PhantomSpec { frames, size: SizePreset::NanEye, noise: 0.0, specular: 0.0, distortion: lens, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), dir, &|_| {}).unwrap();
}

#[test]
fn a_lens_phantom_is_undistorted_as_it_loads_and_fuses_onto_the_wall() {
    let tmp = tempfile::tempdir().unwrap();
    for (name, lens) in [("barrel", BARREL), ("fisheye", FISHEYE)] {
        let data = tmp.path().join(name);
        phantom(&data, Some(lens), 30);
        let file = read_camera_file(&data.join("camera.toml")).unwrap();
        assert_eq!(file.camera().distortion, Some(lens), "camera.toml names the lens");
        let ds = Dataset::open(&data, &Config::default().input, None).unwrap();
        assert!(ds.rig().camera().distortion.is_none(), "the stages see a pinhole camera");
        // Each frame carries the source pixels behind each of its pixels: one at the centre,
        // fewer in the stretched outer ring, none out of view.
        let frame = ds.load(0).unwrap();
        let share = frame.sample_share.expect("an undistorted frame says what each pixel holds");
        let (w, h) = share.size();
        let centre = share.at(w / 2, h / 2);
        let seen: Vec<f32> = share.data().iter().zip(frame.masks.union().unwrap().data()).filter(|(_, m)| !**m).map(|(s, _)| *s).collect();
        let least = seen.iter().copied().fold(f32::INFINITY, f32::min);
        assert!((centre - 1.0).abs() < 0.01 && least < 0.8 && least > 0.0, "{name}: share {centre} at the centre, {least} at least");

        // Exact depth at the true poses: the fused map lies on the wall only if every pixel's
        // depth was put back on its own ray.
        let oracle = run_on(&data, &tmp.path().join(format!("{name}-oracle")), "ground-truth");
        let on_wall = metric(&oracle, "live_surface_rmse_m");
        assert!(on_wall < 1.5e-4, "{name}: the undistorted map is {on_wall} m off the wall");

        // The same frames read as if the lens were a pinhole bend the wall by millimetres.
        let ignored = tmp.path().join(format!("{name}-ignored"));
        capsule_slam_tests::fixtures::copy_dir(&data, &ignored);
        write_camera_file(&ignored.join("camera.toml"), &CameraFile { distortion: None, ..file }).unwrap();
        let bent = metric(&run_on(&ignored, &tmp.path().join(format!("{name}-bent")), "ground-truth"), "live_surface_rmse_m");
        assert!(bent > 10.0 * on_wall.max(1e-4), "{name}: ignoring the lens gives {bent} m, undistorting {on_wall} m");
    }
}

#[test]
fn the_whole_view_keeps_the_lens_outer_field_on_the_wall() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("barrel");
    phantom(&data, Some(BARREL), 30);
    let input = capsule_slam_framework::config::InputConfig { undistorted_view: UndistortedView::Whole, ..Config::default().input };
    let (cropped, whole) = (Dataset::open(&data, &Config::default().input, None).unwrap(), Dataset::open(&data, &input, None).unwrap());
    let (c, w) = (cropped.rig().camera().clone(), whole.rig().camera().clone());
    assert_eq!((c.width, c.height, c.fx), (250, 250, w.fx), "the focal length is kept");
    assert!(w.width > c.width && w.height > c.height, "the canvas grows: {}×{}", w.width, w.height);
    assert!(whole.warnings().is_empty(), "{:?}", whole.warnings());
    let frame = whole.load(0).unwrap();
    assert_eq!(frame.views.reference().size(), (w.width, w.height), "the frames come on the grown canvas");
    // Exact depth at the true poses: the outer field lands on the wall as the centre does, and
    // the map holds more of the wall.
    let sets = |view: &'static str| {
        ["pipeline.depth=sensor", "pipeline.preprocess=[]", "pipeline.tracker=ground-truth", "input.initial_pose=ground-truth", "output.map_surfels=all", view]
    };
    let opts = RunOptions { write_map: true, ..RunOptions::default() };
    let a = run_with(&data, &tmp.path().join("out-source"), &sets("input.undistorted_view=source"), &opts);
    let b = run_with(&data, &tmp.path().join("out-whole"), &sets("input.undistorted_view=whole"), &opts);
    let on_wall = metric(&b, "live_surface_rmse_m");
    assert!(on_wall < 1.5e-4, "the whole view's map is {on_wall} m off the wall");
    assert!(b.surfels as f64 > 1.1 * a.surfels as f64, "surfels: cropped {}, whole view {}", a.surfels, b.surfels);
}

#[test]
fn tracking_through_a_lens_matches_the_pinhole_phantom() {
    let tmp = tempfile::tempdir().unwrap();
    let (pinhole, barrel) = (tmp.path().join("pinhole"), tmp.path().join("barrel"));
    phantom(&pinhole, None, 100);
    phantom(&barrel, Some(BARREL), 100);
    let ate = |data: &Path, out: &str| metric(&run_on(data, &tmp.path().join(out), "icp-rgb"), "ate_percent_of_path");
    let pinhole_frame = Dataset::open(&pinhole, &Config::default().input, None).unwrap().load(0).unwrap();
    assert!(pinhole_frame.sample_share.is_none(), "a pinhole frame is not resampled");
    let (a, b) = (ate(&pinhole, "out-pinhole"), ate(&barrel, "out-barrel"));
    // Both track to a hundredth of a percent of the path (0.013 and 0.014 % measured); the
    // lens costs at most a little.
    assert!(a < 0.05 && b < 0.05 && b < 1.5 * a + 0.01, "ATE % of path: pinhole {a}, through the lens {b}");
}

#[test]
fn a_bad_lens_in_camera_toml_names_the_file_and_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let base = "width = 64\nheight = 48\nfx = 40.0\nfy = 40.0\ncx = 31.5\ncy = 23.5\n";
    for (lens, key) in [
        ("distortion = { model = \"kannala\", coefficients = [0.1] }", "distortion.model"),
        ("distortion = { model = \"equidistant\", coefficients = [0.1, 0.0] }", "distortion.coefficients"),
        ("distortion = [0.1, 0.0, 0.0, nan, 0.0]", "distortion:"),
    ] {
        let p = tmp.path().join("camera.toml");
        std::fs::write(&p, format!("{base}{lens}\n")).unwrap();
        let err = read_camera_file(&p).unwrap_err().to_string();
        assert!(err.contains("camera.toml") && err.contains(key), "{lens}: {err}");
    }
}

#[test]
fn the_sample_share_reaches_the_tracker_and_weighs_the_photometric_term() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("barrel");
    let spec = PhantomSpec { frames: 120, size: SizePreset::NanEye, distortion: Some(BARREL), ..PhantomSpec::preset(5) };
    write_sequence(&Phantom::new(spec).unwrap(), &data, &|_| {}).unwrap();
    let cfg = Config::load(None, &["pipeline.depth=sensor".to_owned(), "pipeline.tracker=icp-rgb".to_owned()]).unwrap();
    let ds = Dataset::open(&data, &cfg.input, None).unwrap();
    // The same frames through the same pipeline, with each frame's share as loaded and with it
    // dropped (every pixel counted as a sensor pixel): the poses differ by the photometric
    // term's reweighting alone, and the weighted ones are nearer the truth.
    let poses = |keep_share: bool| {
        let env = capsule_slam_framework::registry::BuildEnv::new(ds.rig(), Some(data.clone()));
        let mut p = capsule_slam_framework::pipeline::Pipeline::build(&cfg, "test", &capsule_slam_tests::stages::test_registry(), &env).unwrap();
        (0..8)
            .map(|i| {
                let mut frame = ds.load(i).unwrap();
                if !keep_share {
                    frame.sample_share = None;
                }
                let gt = frame.gt_t_world_cam.unwrap();
                (p.process(frame).unwrap().t_world_cam, gt)
            })
            .collect::<Vec<_>>()
    };
    let (weighted, unweighted) = (poses(true), poses(false));
    // Error against the ground truth, the estimate aligned at frame 0, summed over the frames:
    // 0.035 mm weighted against 0.044 mm (measured).
    let error = |v: &[(capsule_slam_framework::Iso3, capsule_slam_framework::Iso3)]| -> f64 {
        v.iter().map(|(est, gt)| ((v[0].1 * v[0].0.inverse() * est).inverse() * gt).translation.vector.norm()).sum()
    };
    assert!(error(&weighted) < error(&unweighted), "weighted {} m, unweighted {} m", error(&weighted), error(&unweighted));
    let weighted: Vec<_> = weighted.iter().map(|p| p.0).collect();
    let unweighted: Vec<_> = unweighted.iter().map(|p| p.0).collect();
    assert_eq!(weighted[0], unweighted[0], "the first frame sets the origin");
    let moved = (weighted[7].inverse() * unweighted[7]).translation.vector.norm();
    assert!(moved > 1e-9, "the share changed nothing: {moved} m");
    assert!(moved < 2e-4, "the share moved the pose by {moved} m: more than a reweighting can");
}
