//! What `map.ply` holds: the stable surfels (confidence at or above the fuser's
//! `stable_confidence`, as ElasticFusion exports its map), scored by the map's figures; every
//! surfel with `output.unstable_surfels = true`; and a run too short for any surfel to become
//! stable says so instead of scoring an empty map.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::path::Path;

use capsule_slam_io::ply;
use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::{RunOptions, Summary};
use capsule_slam_tests::runs::{metric, run_with};

/// `surfel-cpu`'s default stable confidence (ElasticFusion's `confThreshold`).
const STABLE: f32 = 10.0;

fn run_on(data: &Path, out: &Path, extra: &[&str]) -> Summary {
    let mut sets = vec!["pipeline.depth=sensor", "pipeline.preprocess=[]", "pipeline.tracker=ground-truth", "input.initial_pose=ground-truth"];
    sets.extend_from_slice(extra);
    run_with(data, out, &sets, &RunOptions { write_map: true, ..RunOptions::default() })
}

#[test]
fn the_written_map_is_the_stable_surfels_and_its_figures_score_it() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("seq");
    let spec = PhantomSpec { frames: 30, size: SizePreset::NanEye, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), &data, &|_| {}).unwrap();

    let out = tmp.path().join("stable");
    let stable = run_on(&data, &out, &[]);
    let map = ply::read_surfels(&out.join("map.ply")).unwrap();
    assert_eq!(map.len(), stable.surfels_written);
    assert!(!map.is_empty() && map.len() < stable.surfels, "{} of {} written", map.len(), stable.surfels);
    assert!(map.surfels.iter().all(|s| s.confidence >= STABLE), "only stable surfels are written");

    let out_all = tmp.path().join("all");
    let all = run_on(&data, &out_all, &["output.unstable_surfels=true"]);
    let map_all = ply::read_surfels(&out_all.join("map.ply")).unwrap();
    assert_eq!((map_all.len(), all.surfels_written), (all.surfels, all.surfels));
    assert!(map_all.surfels.iter().any(|s| s.confidence < STABLE), "the tentative surfels of the last frames are there");
    assert!(!all.metrics.contains_key("surface_rmse_with_unstable_m"), "nothing was left out");
    // The same run, scored on all surfels: the figure the stable run reports beside its own.
    assert_eq!(metric(&stable, "surface_rmse_with_unstable_m"), metric(&all, "surface_rmse_m"));
    assert_eq!(stable.ate_rmse_m, all.ate_rmse_m, "what is written does not change the tracking");
    assert_ne!(metric(&stable, "surface_rmse_m"), metric(&all, "surface_rmse_m"));
}

#[test]
fn a_run_too_short_for_a_stable_surfel_says_so_and_writes_an_empty_map() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("seq");
    let spec = PhantomSpec { frames: 4, size: SizePreset::NanEye, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), &data, &|_| {}).unwrap();
    let out = tmp.path().join("out");
    let s = run_on(&data, &out, &[]);
    assert_eq!(s.status, "complete", "the frames were tracked and fused");
    assert!(s.surfels > 0);
    assert_eq!((s.surfels_written, ply::read_surfels(&out.join("map.ply")).unwrap().len()), (0, 0));
    assert!(!s.metrics.contains_key("surface_rmse_m"), "an empty map is not scored");
    assert!(s.warnings.iter().any(|w| w.contains("stable") && w.contains("output.unstable_surfels")), "{:?}", s.warnings);
}
