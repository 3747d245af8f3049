//! The `nonrigid` tracker end to end on phantoms: on a moving wall it beats the rigid
//! `icp-rgb` in trajectory and live surface error, on the rigid twin it tracks as well, and the
//! run reports the warp per frame.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::{RunOptions, Summary};
use capsule_slam_tests::runs::{metric, run_with};

const FRAMES: usize = 90;

/// Preset 4 (fast), NanEye size, with the true surface at the last frame.
fn phantom(dir: &std::path::Path, deform_mm: f64) {
    let spec = PhantomSpec { frames: FRAMES, size: SizePreset::NanEye, deform_mm, surface_every: FRAMES - 1, ..PhantomSpec::preset(4) };
    write_sequence(&Phantom::new(spec).unwrap(), dir, &|_| {}).unwrap();
}

fn tracked(data: &std::path::Path, out: &std::path::Path, tracker: &str) -> Summary {
    // The default pipeline with sensor depth (its preprocessors remove the highlights, which
    // move with the light and read as motion), as docs/results/nonrigid.md's headline table.
    let tracker_set = format!("pipeline.tracker={tracker}");
    run_with(data, out, &["pipeline.depth=sensor", tracker_set.as_str()], &RunOptions { write_map: true, ..RunOptions::default() })
}

#[test]
fn on_a_moving_wall_the_nonrigid_tracker_beats_the_rigid_one_and_on_a_still_wall_matches_it() {
    let tmp = tempfile::tempdir().unwrap();
    let (moving, still) = (tmp.path().join("moving"), tmp.path().join("still"));
    phantom(&moving, 4.0);
    phantom(&still, 0.0);

    let rigid = tracked(&moving, &tmp.path().join("rigid"), "icp-rgb");
    let warped = tracked(&moving, &tmp.path().join("warped"), "nonrigid");
    let (ate_r, ate_w) = (metric(&rigid, "ate_rmse_m"), metric(&warped, "ate_rmse_m"));
    let (live_r, live_w) = (metric(&rigid, "live_surface_rmse_m"), metric(&warped, "live_surface_rmse_m"));
    // Measured at 7.90 → 3.25 mm ATE and 2.68 → 1.82 mm live surface RMSE with 8 iterations
    // (2.98 and 1.60 mm with 5; the issue asks for 2× on both; the live surface is not there yet,
    // docs/results/nonrigid.md); a tracker that did not follow the wall would sit at the rigid
    // figures.
    assert!(ate_w < 0.5 * ate_r, "ATE {:.3} mm against icp-rgb's {:.3} mm", ate_w * 1e3, ate_r * 1e3);
    assert!(live_w < 0.75 * live_r, "live surface {:.3} mm against icp-rgb's {:.3} mm", live_w * 1e3, live_r * 1e3);
    assert_eq!(warped.frames_lost, 0);

    // frames.csv carries the warp and its solver time once the map is predicted.
    let csv = std::fs::read_to_string(tmp.path().join("warped/frames.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (max, solver) = (col("warp_max_mm"), col("warp_solver_ms"));
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    let warped_rows = rows.iter().filter(|r| r[max].parse::<f64>().is_ok_and(|v| v > 0.0) && r[solver].parse::<f64>().is_ok_and(|v| v > 0.0)).count();
    assert!(warped_rows > FRAMES / 2, "{warped_rows} of {FRAMES} frames warped the map");

    // The rigid twin: no worse than icp-rgb by more than 5 % (+ 0.02 mm for rounding).
    let rigid_still = tracked(&still, &tmp.path().join("rigid-still"), "icp-rgb");
    let warped_still = tracked(&still, &tmp.path().join("warped-still"), "nonrigid");
    let (a, b) = (metric(&rigid_still, "ate_rmse_m"), metric(&warped_still, "ate_rmse_m"));
    assert!(b <= 1.05 * a + 2e-5, "still wall: ATE {:.4} mm against icp-rgb's {:.4} mm", b * 1e3, a * 1e3);
    // Once a window of still verdicts says the wall is still, the warp is solved on every
    // `still_probe_every_frames`-th frame only; the poses between are the rigid start's.
    let skipped = warped_still.counters_sum.get("nonrigid.nonrigid_probe_skipped").copied().unwrap_or(0.0);
    // Measured: 21 of 90 on this fast preset (its probes often see a gain), 214–236 of 300 on
    // the seven 320 × 320 rigid presets.
    assert!(skipped >= 10.0, "{skipped} of {FRAMES} frames skipped the warp solve on a still wall");
    assert_eq!(warped.counters_sum.get("nonrigid.nonrigid_probe_skipped"), None, "the moving wall was probed, not solved every frame");
    // Once a window of kept warps says the wall clearly moves, the rigid start stops after the
    // coarse levels on all but every `moving_probe_every_frames`-th frame (the joint solve
    // refines the camera at level 0); never on the still wall.
    let coarse = warped.counters_sum.get("nonrigid.nonrigid_coarse_start").copied().unwrap_or(0.0);
    assert!(coarse >= 20.0, "{coarse} of {FRAMES} frames of the moving wall started from the coarse levels");
    assert_eq!(warped_still.counters_sum.get("nonrigid.nonrigid_coarse_start"), None, "a still wall never starts coarse");
}

/// The first frame whose warp solve had model points to judge (its gain counted).
fn first_judged_solve(out: &std::path::Path) -> Option<u64> {
    let counters = std::fs::read_to_string(out.join("counters.jsonl")).unwrap();
    counters
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .find(|c| c.get("nonrigid.nonrigid_icp_gain").is_some())
        .map(|c| c["frame"].as_u64().unwrap())
}

#[test]
fn with_fill_in_the_young_map_is_warped_from_the_second_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("moving");
    phantom(&data, 4.0);
    let opts = RunOptions { max_frames: Some(30), ..RunOptions::default() };
    // Off: only stable surfels are predicted, so the first solve with model points waits for
    // them (frame 20 measured).
    run_with(&data, &tmp.path().join("off"), &["pipeline.depth=sensor", "plugins.nonrigid.fill_in_below_share=0"], &opts);
    let off = first_judged_solve(&tmp.path().join("off"));
    // On (the default, 0.5): the previous frame fills the prediction's holes, and the warp is
    // fitted from frame 1.
    run_with(&data, &tmp.path().join("on"), &["pipeline.depth=sensor"], &opts);
    let on = first_judged_solve(&tmp.path().join("on"));
    assert_eq!(on, Some(1), "with fill-in the first judged solve is at {on:?}");
    assert!(off.is_none_or(|f| f >= 8), "without fill-in the first judged solve is at {off:?}: the prediction is not that young");
}

/// The first frame from `from` on whose warp was kept (`warp_max_mm` written), and the frames
/// whose probe a risen rigid residual called.
fn first_kept_warp_and_called(out: &std::path::Path, from: usize) -> (Option<usize>, Vec<usize>) {
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let max = header.iter().position(|h| *h == "warp_max_mm").unwrap();
    let kept = csv.lines().skip(1).enumerate().skip(from).find(|(_, l)| l.split(',').nth(max).is_some_and(|v| !v.is_empty())).map(|(i, _)| i);
    let counters = std::fs::read_to_string(out.join("counters.jsonl")).unwrap();
    let called = counters
        .lines()
        .enumerate()
        .filter(|(_, l)| serde_json::from_str::<serde_json::Value>(l).unwrap().get("nonrigid.nonrigid_probe_called").is_some())
        .map(|(i, _)| i)
        .collect();
    (kept, called)
}

#[test]
fn a_still_wall_that_starts_to_move_is_caught_by_its_rigid_residual_between_probes() {
    // Preset 2 at NanEye size: still until frame 80, then a 2 mm wave grows over a second. The
    // wall is judged clearly still by frame 51 and probed at 59, 65, 81 (the interval doubling
    // from 8 to 32), the probe at 81 too early to see the young wave; the next would be at 113.
    const ONSET: usize = 80;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("onset");
    let spec = PhantomSpec { frames: 120, size: SizePreset::NanEye, deform_mm: 2.0, deform_onset_frame: ONSET, surface_every: 119, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), &data, &|_| {}).unwrap();
    let opts = RunOptions::default();
    // The default: the rigid residual rises 1.5× its still mean five frames in (measured
    // 85), the next frame probes, and the warp is kept from frame 90.
    run_with(&data, &tmp.path().join("default"), &["pipeline.depth=sensor"], &opts);
    let (kept, called) = first_kept_warp_and_called(&tmp.path().join("default"), ONSET);
    assert!(kept.is_some_and(|k| k <= ONSET + 12), "the moving wall's first kept warp is at {kept:?}, onset {ONSET}");
    assert!(called.iter().any(|c| (ONSET..=ONSET + 12).contains(c)), "no probe called by the residual after the onset: {called:?}");
    // The doubling alone waits for the next scheduled probe (measured: the warp from 115).
    run_with(&data, &tmp.path().join("interval"), &["pipeline.depth=sensor", "plugins.nonrigid.still_probe_residual_rise=0"], &opts);
    let (alone, called) = first_kept_warp_and_called(&tmp.path().join("interval"), ONSET);
    assert!(called.is_empty());
    assert!(alone.is_none_or(|a| a > ONSET + 20), "without the residual's call the warp came at {alone:?}");
}
