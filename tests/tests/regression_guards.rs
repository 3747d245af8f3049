//! Regression guards (issue 18): the real default pipelines on a short phantom, with bounds a
//! few times what they measure today (not 100×), so that a change that costs accuracy fails
//! here and not only in `docs/results/`. Today's figures are in each assertion's comment.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::path::Path;

use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::{RunOptions, Summary};
use capsule_slam_tests::runs::{metric, run_with};

/// Preset 2's path in 100 frames (about 2 mm per frame) at 250×250, the phantom's own noise
/// and highlights.
fn phantom(dir: &Path, deform_mm: f64) {
    let spec = PhantomSpec { frames: 100, size: SizePreset::NanEye, deform_mm, surface_every: 10, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), dir, &|_| {}).unwrap();
}

/// The default pipeline with `sets` on top.
fn run_default(data: &Path, out: &Path, sets: &[&str]) -> Summary {
    run_with(data, out, sets, &RunOptions { write_map: true, eval_sim3: true, ..RunOptions::default() })
}

#[test]
fn the_default_pipelines_keep_their_accuracy_on_a_short_phantom() {
    let tmp = tempfile::tempdir().unwrap();
    let (rigid, moving) = (tmp.path().join("rigid"), tmp.path().join("moving"));
    phantom(&rigid, 0.0);
    phantom(&moving, 2.0);

    let rgbd = run_default(&rigid, &tmp.path().join("rgbd"), &["pipeline.depth=sensor"]);
    let mono = run_default(&rigid, &tmp.path().join("mono"), &[]);
    let wave = run_default(&moving, &tmp.path().join("wave"), &["pipeline.depth=sensor"]);
    // The same frames without their light.toml: the light is assumed, the scale unknown.
    let bare = tmp.path().join("bare");
    phantom(&bare, 0.0);
    std::fs::remove_file(bare.join("light.toml")).unwrap();
    let uncalibrated = run_default(&bare, &tmp.path().join("uncalibrated"), &[]);
    for s in [&rgbd, &mono, &wave, &uncalibrated] {
        assert_eq!(s.status, "complete");
    }
    assert!(rgbd.metric_scale && mono.metric_scale && !uncalibrated.metric_scale);
    assert!(uncalibrated.warnings.iter().any(|w| w.contains("scale is unknown")), "{:?}", uncalibrated.warnings);
    // (what, measured, bound): measured at the commit that adds this test; each bound about 3×.
    let guards = [
        ("RGB-D ATE % of path", metric(&rgbd, "ate_percent_of_path"), 0.0109, 0.035),
        ("RGB-D surface RMSE m", metric(&rgbd, "surface_rmse_m"), 5.0e-5, 1.5e-4),
        ("monocular Sim(3) ATE % of path", 100.0 * metric(&mono, "ate_rmse_sim3_m") / metric(&mono, "path_length_m"), 0.510, 1.5),
        ("monocular surface RMSE m", metric(&mono, "surface_rmse_m"), 9.2e-4, 2.5e-3),
        ("uncalibrated monocular Sim(3) ATE % of path", metric(&uncalibrated, "ate_percent_of_path"), 0.515, 1.5),
        ("moving wall (2 mm) ATE % of path", metric(&wave, "ate_percent_of_path"), 0.362, 1.0),
        ("moving wall (2 mm) live surface RMSE m", metric(&wave, "live_surface_rmse_m"), 4.7e-4, 1.2e-3),
    ];
    let broken: Vec<String> = guards
        .iter()
        .filter(|g| g.1.is_nan() || g.1 > g.3)
        .map(|(what, got, then, bound)| format!("{what}: {got:.3e} (was {then:.3e}, bound {bound:.3e})"))
        .collect();
    assert!(broken.is_empty(), "accuracy regressed: {broken:#?}");
}
