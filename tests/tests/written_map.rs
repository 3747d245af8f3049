//! What `map.ply` holds (`output.map_surfels`), scored by the map's figures: by default the
//! surfels seen in at least two frames; the stable ones (confidence at or above the fuser's
//! `stable_confidence`, as ElasticFusion exports its map); or every surfel. A run in which
//! nothing qualifies says so instead of scoring an empty map.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::path::Path;

use capsule_slam_io::ply;
use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::{RunOptions, Summary};
use capsule_slam_tests::runs::{metric, run_with};

/// `surfel-cpu`'s default stable confidence (ElasticFusion's `confThreshold`).
const STABLE: f32 = 10.0;

/// Exact depth at the true poses over the first `frames` frames (all of them: `None`).
fn run_on(data: &Path, out: &Path, extra: &[&str], frames: Option<usize>) -> Summary {
    let mut sets = vec!["pipeline.depth=sensor", "pipeline.preprocess=[]", "pipeline.tracker=ground-truth", "input.initial_pose=ground-truth"];
    sets.extend_from_slice(extra);
    run_with(data, out, &sets, &RunOptions { write_map: true, max_frames: frames, ..RunOptions::default() })
}

/// Preset 2's phantom in `frames` NanEye frames, written to `dir`/seq.
fn phantom(dir: &Path, frames: usize) -> std::path::PathBuf {
    let data = dir.join("seq");
    let spec = PhantomSpec { frames, size: SizePreset::NanEye, ..PhantomSpec::preset(2) };
    write_sequence(&Phantom::new(spec).unwrap(), &data, &|_| {}).unwrap();
    data
}

#[test]
fn each_rule_writes_its_surfels_and_the_figures_score_what_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    let data = phantom(tmp.path(), 30);

    let written = |out: &Path, s: &Summary| {
        let map = ply::read_surfels(&out.join("map.ply")).unwrap();
        assert_eq!(map.len(), s.surfels_written);
        assert!(!map.is_empty() && map.len() < s.surfels, "{} of {} written", map.len(), s.surfels);
        map
    };
    let out = tmp.path().join("confirmed");
    let confirmed = run_on(&data, &out, &[], None);
    let map = written(&out, &confirmed);
    assert!(map.surfels.iter().all(|s| s.t > s.t0), "only surfels seen in two frames or more are written");
    assert!(map.surfels.iter().any(|s| s.confidence < STABLE), "confirmed, not necessarily stable");

    let out = tmp.path().join("stable");
    let stable = run_on(&data, &out, &["output.map_surfels=stable"], None);
    let map_stable = written(&out, &stable);
    assert!(map_stable.surfels.iter().all(|s| s.confidence >= STABLE), "only stable surfels are written");
    assert!(map_stable.len() < map.len());

    let out_all = tmp.path().join("all");
    let all = run_on(&data, &out_all, &["output.map_surfels=all"], None);
    let map_all = ply::read_surfels(&out_all.join("map.ply")).unwrap();
    assert_eq!((map_all.len(), all.surfels_written), (all.surfels, all.surfels));
    assert!(map_all.surfels.iter().any(|s| s.t == s.t0), "the surfels of one frame are there");
    assert!(!all.metrics.contains_key("surface_rmse_all_surfels_m"), "nothing was left out");
    // The same run, scored on all surfels: the figure the others report beside their own.
    for s in [&confirmed, &stable] {
        assert_eq!(metric(s, "surface_rmse_all_surfels_m"), metric(&all, "surface_rmse_m"));
        assert_eq!(s.ate_rmse_m, all.ate_rmse_m, "what is written does not change the tracking");
        assert_ne!(metric(s, "surface_rmse_m"), metric(&all, "surface_rmse_m"));
    }
}

#[test]
fn a_run_in_which_no_surfel_qualifies_says_so_and_writes_an_empty_map() {
    let tmp = tempfile::tempdir().unwrap();
    let data = phantom(tmp.path(), 4);
    // One frame: nothing seen twice; four frames: nothing stable.
    for (frames, rule, word) in [(1, "confirmed", "more than one frame"), (4, "stable", "stable")] {
        let out = tmp.path().join(rule);
        let s = run_on(&data, &out, &[format!("output.map_surfels={rule}").as_str()], Some(frames));
        assert_eq!(s.status, "complete", "the frames were tracked and fused");
        assert!(s.surfels > 0);
        assert_eq!((s.surfels_written, ply::read_surfels(&out.join("map.ply")).unwrap().len()), (0, 0));
        assert!(!s.metrics.contains_key("surface_rmse_m"), "an empty map is not scored");
        assert!(s.warnings.iter().any(|w| w.contains(word) && w.contains("output.map_surfels")), "{:?}", s.warnings);
    }
}
