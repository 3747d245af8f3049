//! Runs a pipeline over a dataset, streaming the output. A failure at frame N stops the run
//! with that error after writing what exists: the trajectory and `frames.csv` up to frame
//! N − 1, the map and a `summary.json` whose status names the failure.

use capsule_slam_eval::report::{EvalOptions, evaluate, evaluate_live, evaluate_warp};
use capsule_slam_framework::error::PipelineError;
use capsule_slam_framework::frame::DepthSource;
use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_io::{Dataset, ply};

use crate::summary::{CounterSums, Summary, frame_row};
use crate::truth::{LiveTruth, live_truth, wall_motion};
use crate::writer::RunWriter;
use capsule_slam_framework::config::MapSurfels;
use capsule_slam_framework::map::{Surfel, SurfelSet};
use capsule_slam_framework::pipeline::{FrameRecord, Pipeline};

/// Options of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RunOptions {
    /// Process at most this many frames.
    pub max_frames: Option<usize>,
    /// Write `map.ply` at the end.
    pub write_map: bool,
    /// Headline figures aligned with scale (monocular runs).
    pub eval_sim3: bool,
    /// With ground truth: score every loop closure the moment it is applied, the map's surface
    /// error and the trajectory's ATE just before and just after it (`closures.csv`). Costs a
    /// map snapshot per frame.
    pub closure_report: bool,
    /// The build, recorded in `summary.json`.
    pub build: crate::summary::BuildStamp,
}

/// The ground-truth surface of an input folder, when it has one.
pub const GT_SURFACE_FILE: &str = "gt_surface.ply";

/// Processes the dataset's frames in order; calls `on_frame` after each.
pub fn run(
    dataset: &Dataset,
    pipeline: &mut Pipeline,
    writer: &mut RunWriter,
    opts: &RunOptions,
    mut on_frame: impl FnMut(&FrameRecord),
) -> Result<Summary, PipelineError> {
    run_observed(dataset, pipeline, writer, opts, |rec, _| on_frame(rec))
}

/// [`run`], with the pipeline (its state after the frame: trajectory, prediction, map, the
/// last frame if kept) shown to `on_frame` after each frame.
pub fn run_observed(
    dataset: &Dataset,
    pipeline: &mut Pipeline,
    writer: &mut RunWriter,
    opts: &RunOptions,
    mut on_frame: impl FnMut(&FrameRecord, &Pipeline),
) -> Result<Summary, PipelineError> {
    let n = opts.max_frames.map_or(dataset.len(), |m| m.min(dataset.len()));
    let mut records = Vec::with_capacity(n);
    let mut counters = CounterSums::default();
    let mut failure: Option<PipelineError> = None;
    let mut failed_at: Option<usize> = None;
    let mut load_warnings: Vec<String> = Vec::new();
    let (truth, truth_warning) = load_truth(dataset);
    // Without a metric scale only a similarity alignment means anything.
    let sim3 = opts.eval_sim3 || !pipeline.metric_scale();
    let eval_opts = EvalOptions { tolerance_s: pipeline.resolved_config().input.association_tolerance_s, sim3, ..EvalOptions::default() };
    let report_closures = opts.closure_report && truth.is_some() && !dataset.ground_truth().is_empty();
    // Frame i is handed in while frame i − 1 is processed (`Pipeline::push`): its preprocessing
    // runs beside the fusion of the frame before it.
    for i in 0..=n {
        // The map and trajectory before frame i − 1, which this step processes.
        let before = if report_closures && i > 0 {
            Some((pipeline.snapshot().map_err(|e| stage_error(pipeline, i - 1, e))?, pipeline.trajectory().to_vec()))
        } else {
            None
        };
        let (rec, load_failure) = hand_in(dataset, pipeline, i, n, &mut load_warnings);
        match rec {
            Some(Ok(rec)) => {
                if let (true, Some(before), Some(truth)) = (rec.loop_closed, &before, &truth) {
                    score_closure(dataset, pipeline, writer, rec.index, before, truth, &eval_opts)?;
                }
                writer.write_frame(&frame_row(&rec))?;
                on_frame(&rec, pipeline);
                counters.add(&rec); // the reports are written (`counters.jsonl`) and summed
                records.push(FrameRecord { reports: Default::default(), ..rec });
            }
            Some(Err(e)) => {
                // A stage's or a frame's load error names its frame; any other: add it.
                failed_at = (!matches!(e, PipelineError::Stage { .. } | PipelineError::LoadAt { .. })).then_some(i - 1);
                failure = Some(e);
                break;
            }
            None => {}
        }
        if let Some(e) = load_failure {
            failure = Some(e);
            break;
        }
    }

    if pipeline.loop_closures() > 0 {
        writer.rewrite_trajectory(pipeline.trajectory())?;
    }
    // A map that cannot be read out fails the run, unless it failed already.
    let whole = pipeline.snapshot().map_err(|e| failure.get_or_insert(stage_error(pipeline, n, e))).ok();
    let map = whole.as_ref().map(|w| written_map(pipeline, w));
    if let (true, Some(set)) = (opts.write_map, &map) {
        writer.write_map(set)?;
    }
    if failure.is_none() {
        failure = no_result(&records, whole.as_ref());
    }
    let mut summary = summarise(pipeline, &records, &counters, truth_warning.into_iter().chain(load_warnings));
    summary.build = opts.build;
    evaluate_run(dataset, pipeline, &records, map.as_ref(), truth.as_ref(), &eval_opts, &mut summary)?;
    depth_score(&records, &mut summary);
    if let (Some(w), Some(m)) = (&whole, &map) {
        note_left_out(dataset, pipeline, (w, m), truth.as_ref(), &eval_opts, &mut summary);
    }
    if let Some(f) = &failure {
        summary.status = failed_status(f, failed_at);
    }
    writer.write_summary(&summary)?;
    match failure {
        Some(e) => Err(e),
        None => Ok(summary),
    }
}

/// Hands frame `i` of `n` to the pipeline, or after the last finishes it: the record of the
/// frame before it when one was processed, and frame `i`'s load error when it could not be read.
fn hand_in(
    dataset: &Dataset,
    pipeline: &mut Pipeline,
    i: usize,
    n: usize,
    warnings: &mut Vec<String>,
) -> (Option<Result<FrameRecord, PipelineError>>, Option<PipelineError>) {
    match (i < n).then(|| load(dataset, pipeline, i, warnings)) {
        Some(Ok(frame)) => (pipeline.push(frame), None),
        Some(Err(e)) => (pipeline.finish(), Some(PipelineError::LoadAt { frame: i, source: e })),
        None => (pipeline.finish(), None),
    }
}

/// The mean of the frames' depth AbsRel (depth estimated and scored in the run), into `summary`.
fn depth_score(records: &[FrameRecord], summary: &mut Summary) {
    let abs_rel: Vec<f64> = records.iter().filter_map(|r| r.depth_abs_rel).collect();
    if !abs_rel.is_empty() {
        summary.metrics.insert("depth_abs_rel".into(), abs_rel.iter().sum::<f64>() / abs_rel.len() as f64);
    }
}

/// A loop closure applied at frame `index`: the trajectory's ATE and the map's surface error
/// just `before` it (map and trajectory) and just after, into `closures.csv`.
fn score_closure(
    dataset: &Dataset,
    pipeline: &Pipeline,
    writer: &mut RunWriter,
    index: usize,
    before: &(SurfelSet, Vec<StampedPose>),
    truth: &SurfelSet,
    eval_opts: &EvalOptions,
) -> Result<(), PipelineError> {
    let (map, traj) = before;
    let after = pipeline.snapshot().map_err(|e| stage_error(pipeline, index, e))?;
    let score = |map: &SurfelSet, traj: &[StampedPose]| evaluate(traj, dataset.ground_truth(), Some((&written_map(pipeline, map), truth)), eval_opts);
    let (b, a) = (score(map, traj), score(&after, &pipeline.trajectory()[..traj.len()]));
    writer.write_closure(index, &b, &a)?;
    Ok(())
}

/// The summary of the records before the evaluation: the pipeline, its scale and the run's
/// warnings.
fn summarise(pipeline: &Pipeline, records: &[FrameRecord], counters: &CounterSums, warnings: impl Iterator<Item = String>) -> Summary {
    let mut summary = Summary::from_records(records, counters);
    summary.metric_scale = pipeline.metric_scale();
    if !summary.metric_scale {
        summary.warnings.push("the depth's scale is unknown (estimated without the calibration its scale rests on, e.g. no light.toml): the trajectory and the map are up to scale, and the figures are Sim(3)-aligned".into());
    }
    summary.warnings.extend(warnings);
    summary.pipeline = serde_json::to_value(pipeline.resolved_config()).unwrap_or(serde_json::Value::Null);
    summary
}

/// `summary.json`'s status of a failed run: `failed at frame N: reason` where a frame failed.
fn failed_status(f: &PipelineError, failed_at: Option<usize>) -> String {
    match (failed_at, f) {
        (Some(i), _) => format!("failed at frame {i}: {f}"),
        (None, PipelineError::LoadAt { .. }) => format!("failed {f}"),
        (None, _) => format!("failed: {f}"),
    }
}

/// Frame `i`; a pipeline that estimates depth reads the input's only to score it, so a depth
/// image that cannot be read costs that score (a warning), not the run.
fn load(
    dataset: &Dataset,
    pipeline: &Pipeline,
    i: usize,
    warnings: &mut Vec<String>,
) -> Result<capsule_slam_framework::CameraFrame, capsule_slam_framework::LoadError> {
    if pipeline.depth_source() != DepthSource::Estimated {
        return dataset.load(i);
    }
    let (frame, warning) = dataset.load_scoring_depth(i)?;
    warnings.extend(warning);
    Ok(frame)
}

/// The failure of a run that processed every frame of `records` but could not do its job: no
/// frame tracked, or an empty map at the end.
fn no_result(records: &[FrameRecord], map: Option<&SurfelSet>) -> Option<PipelineError> {
    let tracked = records.iter().any(|r| r.status == capsule_slam_framework::stage::TrackStatus::Tracked);
    let empty = map.is_some_and(SurfelSet::is_empty);
    (!records.is_empty() && (!tracked || empty)).then(|| PipelineError::NoResult(no_map_reason(records)))
}

/// Why a run that processed `records` tracked no frame or ended with an empty map: how many
/// frames were lost and what to check.
fn no_map_reason(records: &[FrameRecord]) -> String {
    let lost = records.iter().filter(|r| r.status == capsule_slam_framework::stage::TrackStatus::Lost).count();
    let what = if lost == records.len() { "no frame tracked" } else { "the map is empty" };
    format!(
        "{what} after {} frames ({lost} lost): no frame gave usable depth; check the depth images (all zero, saturated or \
         black frames?), the depth range (`min_depth_m`, `max_depth_m` of the tracker and fuser) and the depth stage",
        records.len()
    )
}

/// The figures against the input's ground truth, into `summary`: trajectory and surface
/// error, and the live surface error at the last frame (or a warning why there is none).
fn evaluate_run(
    dataset: &Dataset,
    pipeline: &Pipeline,
    records: &[FrameRecord],
    map: Option<&SurfelSet>,
    truth: Option<&SurfelSet>,
    eval_opts: &EvalOptions,
    summary: &mut Summary,
) -> Result<(), PipelineError> {
    let gt = dataset.ground_truth();
    if gt.is_empty() || records.is_empty() {
        return Ok(());
    }
    let surfaces = match (map, truth) {
        (Some(m), Some(t)) if !m.is_empty() => Some((m, t)),
        _ => None,
    };
    summary.metrics = evaluate(pipeline.trajectory(), gt, surfaces, eval_opts);
    summary.ate_rmse_m = summary.metrics.remove("ate_rmse_m");
    let last = records.last().map_or(0, |r| r.index);
    let live =
        live_truth(dataset, truth, last).unwrap_or_else(|e| LiveTruth::Missing(format!("live surface error off: {e}; the file is read only to score the run")));
    match (map, live) {
        (Some(m), LiveTruth::At(now)) => {
            // Monocular scale is only estimated: its live surface is aligned with Sim(3).
            let live_opts = EvalOptions { sim3: pipeline.depth_source() == DepthSource::Estimated, ..*eval_opts };
            // The input's own camera, its lens included: what the last frame's image saw.
            let camera = dataset.camera_file().camera();
            summary.metrics.extend(evaluate_live(pipeline.trajectory(), gt, m, &now, last as u32, Some(&camera), &live_opts));
        }
        (_, LiveTruth::Missing(why)) => summary.warnings.push(why),
        _ => {}
    }
    if let (Some(m), Some(rest)) = (map, truth) {
        match wall_motion(dataset.dir(), rest, last) {
            Ok((wall, now)) => {
                let opts = EvalOptions { sim3: pipeline.depth_source() == DepthSource::Estimated, ..*eval_opts };
                let figures = evaluate_warp(pipeline.trajectory(), gt, m, &wall, &now, last as u32, &opts);
                if figures.is_empty() {
                    summary.warnings.push(format!(
                        "warp error off: no surfel seen at the last frame {last} was created within {} frames of a true surface; make the sequence with `capsule-slam synth --surface-every N` (N ≤ {})",
                        opts.warp_max_gap_frames, opts.warp_max_gap_frames
                    ));
                }
                summary.metrics.extend(figures);
            }
            Err(why) => summary.warnings.push(format!("warp error off: {why}")),
        }
    }
    Ok(())
}

/// The input's ground-truth surface, when it has one.
///
/// It only scores the run: a file that cannot be read leaves the surface figures out with a
/// warning (returned) instead of stopping the run.
fn load_truth(dataset: &Dataset) -> (Option<SurfelSet>, Option<String>) {
    let truth_file = dataset.dir().join(GT_SURFACE_FILE);
    if !truth_file.exists() {
        return (None, None);
    }
    match ply::read_surfels(&truth_file) {
        Ok(set) => (Some(set), None),
        Err(e) => (None, Some(format!("surface figures off: {e}; the file is read only to score the run: fix or remove it"))),
    }
}

/// What the written map `map` leaves out of the fuser's `whole` one, into `summary`: the count
/// written, a warning when nothing is left to write, and the surface RMSE of every surfel beside
/// the written map's.
fn note_left_out(
    dataset: &Dataset,
    pipeline: &Pipeline,
    (whole, map): (&SurfelSet, &SurfelSet),
    truth: Option<&SurfelSet>,
    eval_opts: &EvalOptions,
    summary: &mut Summary,
) {
    summary.surfels_written = map.len();
    if map.is_empty() && !whole.is_empty() {
        let why = match (pipeline.resolved_config().output.map_surfels, pipeline.stable_confidence()) {
            (MapSurfels::Stable, Some(c)) => format!("is stable yet (confidence ≥ {c}, about {c} views)"),
            _ => "was seen in more than one frame".to_owned(),
        };
        summary.warnings.push(format!(
            "none of the map's {} surfels {why}: map.ply is empty and the map's figures are off; run more frames or set output.map_surfels = \"all\"",
            whole.len()
        ));
    }
    if let Some(t) = truth
        && whole.len() > map.len()
        && !dataset.ground_truth().is_empty()
        && let Some(rmse) = evaluate(pipeline.trajectory(), dataset.ground_truth(), Some((whole, t)), eval_opts).get("surface_rmse_m")
    {
        summary.metrics.insert("surface_rmse_all_surfels_m".into(), *rmse);
    }
}

/// The part of the pipeline's map `whole` (a [`Pipeline::snapshot`]) that `map.ply` holds and
/// the map's figures score, in the map's canonical order (`output.map_surfels`, with the fuser's
/// stable confidence; a fuser without one counts every surfel as stable): also what plots and
/// recordings of the final map show.
pub fn written_map(pipeline: &Pipeline, whole: &SurfelSet) -> SurfelSet {
    let (rule, stable) = (pipeline.resolved_config().output.map_surfels, pipeline.stable_confidence());
    let keep = |s: &Surfel| match rule {
        MapSurfels::All => true,
        MapSurfels::Confirmed => s.t > s.t0 || stable.is_none_or(|c| s.confidence >= c),
        MapSurfels::Stable => stable.is_none_or(|c| s.confidence >= c),
    };
    SurfelSet { surfels: whole.surfels.iter().filter(|s| keep(s)).copied().collect() }
}

fn stage_error(pipeline: &Pipeline, frame: usize, source: capsule_slam_framework::error::StageError) -> PipelineError {
    PipelineError::Stage { frame, stage: pipeline.resolved_config().pipeline.fuser.clone(), source }
}
