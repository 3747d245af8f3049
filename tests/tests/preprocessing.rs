//! The preprocessors in the pipeline, against the phantom's ground truth:
//! - `reflection`'s mask is honoured downstream: with it, no highlight reaches the map (the
//!   phantom's tissue is never as white as a highlight, so a white surfel is a fused highlight);
//! - `vignetting` agrees with the depth model: the monocular pipeline's depth is as good with the
//!   fall-off divided out as without (the estimator reads what was divided).
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_framework::SurfelSet;
use capsule_slam_framework::config::Config;
use capsule_slam_framework::pipeline::FrameRecord;
use capsule_slam_framework::pipeline::Pipeline;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::Dataset;
use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::RunWriter;
use capsule_slam_run::{RunOptions, run};
use capsule_slam_tests::stages::test_registry;

fn run_with(data: &std::path::Path, out: &std::path::Path, set: &[&str]) -> (Vec<FrameRecord>, SurfelSet) {
    let cfg = Config::load(None, &set.iter().map(|s| (*s).to_owned()).collect::<Vec<_>>()).unwrap();
    let registry = test_registry();
    let ds = Dataset::open(data, &cfg.input, None).unwrap();
    let mut p = Pipeline::build(&cfg, "test", &registry, &BuildEnv::new(ds.rig(), Some(data.to_owned()))).unwrap();
    let mut w = RunWriter::create(out, &p.resolved_config().to_toml_string()).unwrap();
    let mut records = Vec::new();
    run(&ds, &mut p, &mut w, &RunOptions { max_frames: None, write_map: false, eval_sim3: false, ..RunOptions::default() }, |r| records.push(r.clone()))
        .unwrap();
    (records, p.snapshot().unwrap())
}

/// Whiter (saturation 1 − min/max below 0.2) and brighter than any tissue.
fn is_white(c: [u8; 3]) -> bool {
    let (hi, lo) = (c[0].max(c[1]).max(c[2]), c[0].min(c[1]).min(c[2]));
    hi > 60 && f32::from(lo) / f32::from(hi) > 0.8
}

fn white_surfels(map: &SurfelSet) -> usize {
    map.surfels.iter().filter(|s| is_white(s.colour)).count()
}

#[test]
fn masked_highlights_never_reach_the_map() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    // Heavy reflections (preset 7), exact depth and poses: only the colour can go wrong.
    let ph = Phantom::new(PhantomSpec { frames: 30, size: SizePreset::NanEye, ..PhantomSpec::preset(7) }).unwrap();
    write_sequence(&ph, &data, &|_| {}).unwrap();
    // Ground truth: the rendered tissue itself has no white pixel.
    for i in [0, 15, 29] {
        let f = ph.render(i);
        let white = f.diffuse.data().chunks_exact(3).filter(|c| is_white([c[0], c[1], c[2]])).count();
        assert!(white < 10, "frame {i}: the diffuse tissue has {white} white pixels (noise)");
    }
    let oracle = ["pipeline.depth=sensor", "pipeline.tracker=ground-truth"];
    let mut plain_set = oracle.to_vec();
    plain_set.push("pipeline.preprocess=[]");
    let (_, plain) = run_with(&data, &tmp.path().join("plain"), &plain_set);
    let mut with = oracle.to_vec();
    with.push("pipeline.preprocess=[\"reflection\"]");
    let (records, cleaned) = run_with(&data, &tmp.path().join("cleaned"), &with);
    let share: f64 = records.iter().map(|r| r.reports["reflection"].counters["highlight_share"]).sum::<f64>() / records.len() as f64;
    assert!(share > 0.001, "highlights were found ({share})");
    let (before, after) = (white_surfels(&plain), white_surfels(&cleaned));
    assert!(before > 50, "without the preprocessor, highlights are fused ({before} white surfels)");
    assert!(after * 20 < before, "with it, {after} white surfels remain (from {before})");
}

#[test]
fn vignetting_correction_leaves_the_monocular_depth_as_good() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let ph = Phantom::new(PhantomSpec { frames: 12, size: SizePreset::NanEye, ..PhantomSpec::preset(1) }).unwrap();
    write_sequence(&ph, &data, &|_| {}).unwrap();
    let mean_abs_rel = |records: &[FrameRecord]| records.iter().map(|r| r.depth_abs_rel.unwrap()).sum::<f64>() / records.len() as f64;
    let (raw, _) = run_with(&data, &tmp.path().join("raw"), &["pipeline.preprocess=[]"]);
    let a = mean_abs_rel(&raw);
    // Scaled so that nothing clips, the same pixels are used: the same depth, to the 8-bit
    // rounding of the correction.
    for divide in ["lens-and-light", "flat-field"] {
        let set =
            ["pipeline.preprocess=[\"vignetting\"]".to_owned(), format!("plugins.vignetting.divide={divide}"), "plugins.vignetting.scale=no-clip".to_owned()];
        let (corrected, _) = run_with(&data, &tmp.path().join(divide), &set.iter().map(String::as_str).collect::<Vec<_>>());
        let b = mean_abs_rel(&corrected);
        assert!((a - b).abs() < 0.003, "{divide}, no-clip: depth AbsRel {b:.4} against {a:.4} uncorrected");
        assert!(corrected.iter().all(|r| r.reports["vignetting"].counters["linear_scale"] < 0.7));
    }
    // Centre-referenced (the default), the brightened rim clips here and there and is masked:
    // never worse.
    let (corrected, _) = run_with(&data, &tmp.path().join("centre"), &["pipeline.preprocess=[\"vignetting\"]"]);
    let b = mean_abs_rel(&corrected);
    assert!(b < a + 0.003, "centre: depth AbsRel {b:.4} against {a:.4} uncorrected");
    assert!(corrected.iter().all(|r| r.reports["vignetting"].counters["linear_scale"] == 1.0));
}
