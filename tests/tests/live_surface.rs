//! The live surface error end to end: a phantom written with its true surface every few frames,
//! the pipeline with exact depth and the ground-truth tracker, and what the run reports.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::{RunOptions, Summary};
use capsule_slam_tests::runs::{metric, run_with};

fn phantom(dir: &std::path::Path, deform_mm: f64) {
    let spec = PhantomSpec { frames: 40, size: SizePreset::NanEye, deform_mm, surface_every: 10, noise: 0.0, specular: 0.0, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), dir, &|_| {}).unwrap();
}

fn oracle_run(data: &std::path::Path, out: &std::path::Path, frames: usize) -> Summary {
    let sets = ["pipeline.depth=sensor", "pipeline.preprocess=[]", "pipeline.tracker=ground-truth", "input.initial_pose=ground-truth"];
    run_with(data, out, &sets, &RunOptions { max_frames: Some(frames), write_map: true, ..RunOptions::default() })
}

#[test]
fn the_live_surface_of_an_oracle_run_lies_on_the_wall_and_a_moving_wall_shows_in_it() {
    let tmp = tempfile::tempdir().unwrap();
    let (rigid, moving) = (tmp.path().join("rigid"), tmp.path().join("moving"));
    phantom(&rigid, 0.0);
    phantom(&moving, 4.0);
    for i in [0, 10, 20, 30, 39] {
        assert!(moving.join(format!("gt_surface_{i:06}.ply")).exists(), "--surface-every 10 writes frame {i}");
    }
    assert!(!rigid.join("gt_surface_000010.ply").exists(), "a rigid wall needs no surface per frame");

    let still = oracle_run(&rigid, &tmp.path().join("out-rigid"), 40);
    let live = metric;
    // Exact depth at the true poses on a still wall (the rest shape is the truth at any frame):
    // the fused surface lies on it.
    assert!(live(&still, "live_surface_rmse_m") < 1e-4, "{}", live(&still, "live_surface_rmse_m"));
    assert!(live(&still, "live_surface_points") > 1000.0);
    assert!(still.warnings.is_empty(), "{:?}", still.warnings);

    // On a 4 mm wave the map averages the wall's phases: the live surface is off the wall as
    // it is at the last frame, by less than the wave.
    let wave = oracle_run(&moving, &tmp.path().join("out-moving"), 40);
    let r = live(&wave, "live_surface_rmse_m");
    assert!(r > 5.0 * live(&still, "live_surface_rmse_m") && r < 0.004, "live surface RMSE {r}");
    assert!(live(&wave, "live_surface_p95_m") >= live(&wave, "live_surface_median_m"));
    // The split into the surfels in the last frame's view and those the camera left beside or
    // behind it: on the still wall both lie on it, and on the wave the two parts make the whole.
    // (In view are the surfels the last frames created from one or few measurements.)
    assert!(live(&still, "live_surface_in_view_rmse_m") < 3e-4 && live(&still, "live_surface_left_rmse_m") < 1e-4);
    let (seen, left) = (live(&wave, "live_surface_in_view_rmse_m"), live(&wave, "live_surface_left_rmse_m"));
    let (n_seen, n_left) = (live(&wave, "live_surface_in_view_points"), live(&wave, "live_surface_left_points"));
    assert!(n_seen > 100.0 && n_left > 100.0, "{n_seen} in view, {n_left} left");
    assert_eq!(n_seen + n_left, live(&wave, "live_surface_points"));
    let whole = ((n_seen * seen * seen + n_left * left * left) / (n_seen + n_left)).sqrt();
    assert!((whole - r).abs() < 1e-9 * r.max(1.0), "the parts {seen} and {left} make {whole}, the whole {r}");
    // At the true poses the alignment on the window's poses alone is the global one (identity):
    // the two figures agree.
    for s in [&still, &wave] {
        let (global, local) = (live(s, "live_surface_rmse_m"), live(s, "live_surface_local_rmse_m"));
        assert!((global - local).abs() < 1e-6, "global {global}, window-aligned {local}");
    }

    // The warp error: a tracker that never warps the map has its whole error in the wall's true
    // motion, which is zero on the still wall and up to twice the wave on the moving one.
    assert_eq!(live(&still, "warp_true_rms_m"), 0.0);
    assert_eq!(live(&still, "warp_error_rmse_m"), 0.0);
    assert_eq!(live(&wave, "warp_estimated_rms_m"), 0.0);
    let (e, t) = (live(&wave, "warp_error_rmse_m"), live(&wave, "warp_true_rms_m"));
    assert!(e == t && t > 1e-4 && t < 0.008, "warp error {e}, true motion {t}");
    let (points, skipped) = (live(&wave, "warp_error_points"), live(&wave, "warp_error_skipped"));
    assert!(points > 500.0 && skipped == 0.0, "{points} stable surfels measured, {skipped} skipped");

    // A run that ends where the moving wall has no true surface says so and reports no figure.
    let short = oracle_run(&moving, &tmp.path().join("out-short"), 25);
    assert!(!short.metrics.contains_key("live_surface_rmse_m"));
    assert!(short.warnings.iter().any(|w| w.contains("frame 24") && w.contains("--surface-every")), "{:?}", short.warnings);
    assert!(!short.metrics.contains_key("warp_error_rmse_m"));
    assert!(short.warnings.iter().any(|w| w.starts_with("warp error off") && w.contains("frame 24")), "{:?}", short.warnings);
}
