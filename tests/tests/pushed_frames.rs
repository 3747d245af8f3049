//! Frames pushed into the pipeline (`Pipeline::push`, as `run` hands them in) are prepared
//! beside the fusion of the frame before them, and track, fuse and fail exactly as frames
//! processed one by one (`Pipeline::process`).
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_framework::PipelineError;
use capsule_slam_framework::config::Config;
use capsule_slam_framework::pipeline::{FrameRecord, Pipeline};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::Dataset;
use capsule_slam_phantom::writer::write_sequence;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_tests::stages::test_registry;

/// Frames processed, of the phantom's 90.
const FRAMES: usize = 48;

/// Preset 4 with a 4 mm wave, NanEye size, 90 frames: the default tracker warps the map on
/// most of the first 48 (30 of them when written).
fn phantom() -> (tempfile::TempDir, std::path::PathBuf) {
    phantom_of(4, 4.0, 90)
}

/// A phantom written into a new temporary folder (kept while the first value lives), and its path.
fn phantom_of(preset: u8, deform_mm: f64, frames: usize) -> (tempfile::TempDir, std::path::PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let spec = PhantomSpec { frames, size: SizePreset::NanEye, deform_mm, ..PhantomSpec::preset(preset) };
    write_sequence(&Phantom::new(spec).unwrap(), &data, &|_| {}).unwrap();
    (tmp, data)
}

/// The default pipeline with sensor depth and the probe after its preprocessors.
fn pipeline(data: &std::path::Path, probe: &[&str]) -> (Dataset, Pipeline) {
    pipeline_with(data, "sensor", probe)
}

/// The default pipeline with the `depth` stage and the probe after its preprocessors.
fn pipeline_with(data: &std::path::Path, depth: &str, probe: &[&str]) -> (Dataset, Pipeline) {
    let mut sets = vec![format!("pipeline.depth={depth}")];
    if depth == "near-light-sfs" {
        sets.push("plugins.near-light-sfs.albedo_source=map".into());
    }
    sets.extend(probe.iter().map(|s| format!("plugins.test-probe.{s}")));
    let mut cfg = Config::load(None, &sets).unwrap();
    cfg.pipeline.preprocess.push("test-probe".into());
    let ds = Dataset::open(data, &cfg.input, None).unwrap();
    let p = Pipeline::build(&cfg, "test", &test_registry(), &BuildEnv::new(ds.rig(), Some(data.to_owned()))).unwrap();
    (ds, p)
}

fn processed(ds: &Dataset, p: &mut Pipeline) -> Vec<FrameRecord> {
    (0..FRAMES).map(|i| p.process(ds.load(i).unwrap()).unwrap()).collect()
}

fn pushed(ds: &Dataset, p: &mut Pipeline) -> Vec<FrameRecord> {
    let mut out: Vec<FrameRecord> = (0..FRAMES).filter_map(|i| p.push(ds.load(i).unwrap())).map(Result::unwrap).collect();
    out.extend(p.finish().map(Result::unwrap));
    out
}

fn counter(r: &FrameRecord, stage: &str, key: &str) -> Option<f64> {
    r.reports.get(stage).and_then(|s| s.counters.get(key)).copied()
}

/// What tracking and fusion made of each frame, to the bit.
fn same_outcome(a: &[FrameRecord], b: &[FrameRecord]) {
    assert_eq!(a.len(), b.len());
    for (a, b) in a.iter().zip(b) {
        assert_eq!(a.index, b.index);
        assert_eq!(a.t_world_cam, b.t_world_cam, "frame {}", a.index);
        assert_eq!((a.status, a.inliers, a.tracker_iterations), (b.status, b.inliers, b.tracker_iterations), "frame {}", a.index);
        assert_eq!(a.residual_rms.to_bits(), b.residual_rms.to_bits(), "frame {}", a.index);
        assert_eq!(a.warp_m, b.warp_m, "frame {}", a.index);
        assert_eq!((a.fuse, a.map), (b.fuse, b.map), "frame {}", a.index);
    }
}

#[test]
fn pushed_frames_are_prepared_beside_the_fusion_and_end_as_frames_processed_one_by_one() {
    let (_tmp, data) = phantom();
    let (ds, mut one_by_one) = pipeline(&data, &[]);
    let (_, mut streamed) = pipeline(&data, &[]);
    let a = processed(&ds, &mut one_by_one);
    let b = pushed(&ds, &mut streamed);

    same_outcome(&a, &b);
    let warped = b.iter().filter(|r| r.warp_m.is_some_and(|(mean, _)| mean > 0.0)).count();
    assert!(warped > FRAMES / 3, "the warp moved the map on {warped} frames only: too few to test it");
    assert_eq!(one_by_one.snapshot().unwrap(), streamed.snapshot().unwrap());
    assert_eq!(one_by_one.trajectory(), streamed.trajectory());
    for (a, b) in a.iter().zip(&b) {
        // In order, each frame once.
        assert_eq!(counter(a, "test-probe", "previous_frame"), Some(a.index as f64 - 1.0).map(|v| v.max(-1.0)));
        assert_eq!(counter(b, "test-probe", "previous_frame"), counter(a, "test-probe", "previous_frame"));
        // One by one, every frame after the first is preprocessed with the map's prediction;
        // pushed, every frame after the first was preprocessed before that prediction existed,
        // beside the fusion of the frame before it (the probe says it reads none).
        assert_eq!(counter(a, "test-probe", "saw_prediction"), Some(if a.index == 0 { 0.0 } else { 1.0 }));
        assert_eq!(counter(b, "test-probe", "saw_prediction"), Some(0.0));
        // The tracker built the frame's live pyramid there too, timed in the frame's own report.
        if b.index > 0 {
            assert!(counter(b, "nonrigid", "ms_live_pyramid").is_some(), "frame {}", b.index);
        }
    }
}

#[test]
fn a_stage_that_reads_the_prediction_still_gets_it_when_frames_are_pushed() {
    let (_tmp, data) = phantom();
    let (ds, mut one_by_one) = pipeline(&data, &["reads_prediction=true"]);
    let (_, mut streamed) = pipeline(&data, &["reads_prediction=true"]);
    let a = processed(&ds, &mut one_by_one);
    let b = pushed(&ds, &mut streamed);
    same_outcome(&a, &b);
    for b in &b {
        assert_eq!(counter(b, "test-probe", "saw_prediction"), Some(if b.index == 0 { 0.0 } else { 1.0 }), "frame {}", b.index);
    }
}

#[test]
fn a_depth_stage_that_reads_the_prediction_gets_it_while_the_preprocessors_run_ahead() {
    // The default monocular pipeline with the map's albedo: `near-light-sfs` then reads the
    // prediction, so only the preprocessors run beside the fusion. Preset 5 with a 2 mm wave at 120 frames,
    // which it tracks (at 90 frames preset 4 moves too fast for shape from shading).
    let (_tmp, data) = phantom_of(5, 2.0, 120);
    let (ds, mut one_by_one) = pipeline_with(&data, "near-light-sfs", &[]);
    let (_, mut streamed) = pipeline_with(&data, "near-light-sfs", &[]);
    let a: Vec<FrameRecord> = (0..FRAMES / 2).map(|i| one_by_one.process(ds.load(i).unwrap()).unwrap()).collect();
    let mut b: Vec<FrameRecord> = (0..FRAMES / 2).filter_map(|i| streamed.push(ds.load(i).unwrap())).map(Result::unwrap).collect();
    b.extend(streamed.finish().map(Result::unwrap));
    same_outcome(&a, &b);
    assert_eq!(
        a.iter().map(|r| r.depth_abs_rel.map(f64::to_bits)).collect::<Vec<_>>(),
        b.iter().map(|r| r.depth_abs_rel.map(f64::to_bits)).collect::<Vec<_>>()
    );
    assert_eq!(one_by_one.snapshot().unwrap(), streamed.snapshot().unwrap());
    for (a, b) in a.iter().zip(&b) {
        assert_eq!(counter(b, "test-probe", "saw_prediction"), Some(0.0), "frame {}: not preprocessed ahead", b.index);
        // The depth stage was given the prediction in its turn, as one by one.
        assert_eq!(counter(b, "near-light-sfs", "map_albedo_share"), counter(a, "near-light-sfs", "map_albedo_share"), "frame {}", b.index);
    }
    assert!(b.iter().any(|r| counter(r, "near-light-sfs", "map_albedo_share").is_some_and(|v| v > 0.01)), "the map's albedo was never read");
    assert!(b.iter().all(|r| r.status == capsule_slam_framework::stage::TrackStatus::Tracked), "a lost frame is not prepared ahead: a test of nothing");
}

#[test]
fn a_pushed_frame_that_fails_to_prepare_fails_in_its_turn_and_frames_stay_in_order() {
    let (_tmp, data) = phantom();
    let (ds, mut p) = pipeline(&data, &["fail_at_frame=5"]);
    let mut records = Vec::new();
    let mut failure = None;
    for i in 0..FRAMES {
        match p.push(ds.load(i).unwrap()) {
            Some(Ok(r)) => records.push(r.index),
            Some(Err(e)) => {
                failure = Some(e);
                break;
            }
            None => {}
        }
    }
    // Frame 5 was prepared (and failed) while frame 4 was fused: frame 4 is recorded, then frame
    // 5's own error is told.
    assert_eq!(records, vec![0, 1, 2, 3, 4]);
    match failure {
        Some(PipelineError::Stage { frame: 5, stage, .. }) => assert_eq!(stage, "test-probe"),
        other => panic!("expected test-probe's error at frame 5, got {other:?}"),
    }

    // A frame processed on its own while a pushed one waits would go before it: refused.
    let (ds, mut p) = pipeline(&data, &[]);
    assert!(p.push(ds.load(0).unwrap()).is_none());
    let err = p.process(ds.load(1).unwrap()).unwrap_err();
    assert!(matches!(err, PipelineError::Order(_)), "{err}");
    assert!(err.to_string().contains("frame 0") && err.to_string().contains("finish"), "{err}");
    assert_eq!(p.finish().unwrap().unwrap().index, 0);
    assert_eq!(p.process(ds.load(1).unwrap()).unwrap().index, 1);
}
