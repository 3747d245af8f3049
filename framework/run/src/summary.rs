//! What the run writes: `summary.json` (statistics of the frame records, then the evaluation)
//! and the row of each frame, both made from the pipeline's records here so that the writer only
//! writes what it is given.

use std::collections::BTreeMap;

use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_framework::pipeline::{FrameRecord, StageTimes};
use capsule_slam_framework::stage::TrackStatus;
use serde::Serialize;

/// The build that made a run: what `compare` checks before it reuses a finished cell.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct BuildStamp {
    /// The crate version.
    pub version: &'static str,
    /// The git commit it was built from (`unknown` outside a git checkout).
    pub commit: &'static str,
}

/// `summary.json`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Summary {
    /// `complete`, or `failed at frame N: reason`.
    pub status: String,
    /// The build that ran.
    pub build: BuildStamp,
    /// Frames processed.
    pub frames: usize,
    /// Frames whose tracking was lost.
    pub frames_lost: usize,
    /// Mean wall-clock ms per frame.
    pub ms_per_frame_mean: f64,
    /// 95th percentile ms per frame.
    pub ms_per_frame_p95: f64,
    /// Mean ms per stage.
    pub ms_per_stage_mean: BTreeMap<String, f64>,
    /// Surfels in the final map.
    pub surfels: usize,
    /// Active surfels in the final map.
    pub surfels_active: usize,
    /// Surfels written to `map.ply` and scored (`output.map_surfels`).
    pub surfels_written: usize,
    /// Loop closures applied.
    pub loop_closures: usize,
    /// Whether the depth, the map and the trajectory are in metres: `false` for a depth
    /// estimated without the calibration its scale rests on (a monocular run without
    /// `light.toml`), whose headline figures are then Sim(3)-aligned.
    pub metric_scale: bool,
    /// Mean of every counter the stages reported, keyed `plugin.counter`.
    pub counters_mean: BTreeMap<String, f64>,
    /// Sum of every counter over the frames that reported it (event counts such as
    /// `deformation.accepted`).
    pub counters_sum: BTreeMap<String, f64>,
    /// ATE RMSE after SE(3) alignment, metres, when the input has ground truth.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ate_rmse_m: Option<f64>,
    /// Further metrics (evaluation against ground truth), flattened into the JSON.
    #[serde(flatten)]
    pub metrics: BTreeMap<String, f64>,
    /// The resolved configuration.
    pub pipeline: serde_json::Value,
    /// What the run could not measure, and why (e.g. a figure whose ground truth is missing).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// The running sum and count of every counter the stages reported, keyed `plugin.counter`: what
/// `summary.json` keeps of the frames' reports, so that a run need not hold every frame's
/// reports until its end (a long run's memory would grow with its frames).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CounterSums(BTreeMap<String, (f64, usize)>);

impl CounterSums {
    /// Adds one frame's counters.
    pub fn add(&mut self, r: &FrameRecord) {
        for (k, v) in counters_of(r) {
            let e = self.0.entry(k).or_insert((0.0, 0));
            e.0 += v;
            e.1 += 1;
        }
    }
}

impl Summary {
    /// Timing and count statistics of the records, with the counters summed over them in
    /// `counters` (the records' own reports may have been dropped by then).
    pub fn from_records(records: &[FrameRecord], counters: &CounterSums) -> Self {
        let n = records.len();
        let mut totals: Vec<f64> = records.iter().map(|r| r.total_ms).collect();
        totals.sort_by(f64::total_cmp);
        let mean = |v: &mut dyn Iterator<Item = f64>| if n == 0 { 0.0 } else { v.sum::<f64>() / n as f64 };
        let mut per_stage = BTreeMap::new();
        for (k, (name, _)) in StageTimes::default().named().iter().enumerate() {
            per_stage.insert((*name).to_owned(), mean(&mut records.iter().map(|r| r.ms.named()[k].1)));
        }
        let p95 = if n == 0 { 0.0 } else { totals[((0.95 * n as f64).ceil() as usize).clamp(1, n) - 1] };
        let last = records.last();
        Self {
            status: "complete".into(),
            frames: n,
            frames_lost: records.iter().filter(|r| r.status == TrackStatus::Lost).count(),
            ms_per_frame_mean: mean(&mut totals.iter().copied()),
            ms_per_frame_p95: p95,
            ms_per_stage_mean: per_stage,
            surfels: last.map_or(0, |r| r.map.total),
            surfels_active: last.map_or(0, |r| r.map.active),
            loop_closures: records.iter().filter(|r| r.loop_closed).count(),
            counters_mean: counters.0.iter().map(|(k, (s, n))| (k.clone(), s / *n as f64)).collect(),
            counters_sum: counters.0.iter().map(|(k, (s, _))| (k.clone(), *s)).collect(),
            ..Self::default()
        }
    }
}

/// What the run writes of one frame: its pose (`trajectory.txt`), its row of `frames.csv` and
/// its counters (`counters.jsonl`).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRow {
    /// 0-based frame index.
    pub index: usize,
    /// The estimated pose, stamped.
    pub pose: StampedPose,
    /// `tracked` or `lost`.
    pub status: &'static str,
    /// Milliseconds per stage, `(column, value)` in pipeline order.
    pub ms: Vec<(&'static str, f64)>,
    /// Milliseconds for the whole frame.
    pub total_ms: f64,
    /// Surfels after the frame.
    pub surfels_total: usize,
    /// Active surfels after the frame.
    pub surfels_active: usize,
    /// New surfels.
    pub surfels_added: usize,
    /// Surfels merged into.
    pub surfels_merged: usize,
    /// Tracker inliers.
    pub tracker_inliers: usize,
    /// Tracker RMS residual.
    pub tracker_residual: f64,
    /// Whether a loop closure was applied at this frame.
    pub loop_closure: bool,
    /// AbsRel of an estimated depth against the input's depth.
    pub depth_abs_rel: Option<f64>,
    /// Tracker Gauss-Newton iterations.
    pub tracker_iterations: usize,
    /// The tracker's warp of the map: mean and max node displacement, millimetres.
    pub warp_mm: Option<(f64, f64)>,
    /// The tracker's warp solver time, milliseconds (its `ms_warp_solver` counter).
    pub warp_solver_ms: Option<f64>,
    /// Every counter the stages reported, keyed `plugin.counter`.
    pub counters: BTreeMap<String, f64>,
}

/// Every counter of a frame's record, keyed `plugin.counter`.
pub fn counters_of(r: &FrameRecord) -> BTreeMap<String, f64> {
    r.reports.iter().flat_map(|(plugin, rep)| rep.counters.iter().map(move |(k, v)| (format!("{plugin}.{k}"), *v))).collect()
}

/// The row the writer writes of a frame record.
pub fn frame_row(r: &FrameRecord) -> FrameRow {
    FrameRow {
        index: r.index,
        pose: StampedPose { timestamp_s: r.timestamp_s, t_world_cam: r.t_world_cam },
        status: r.status.as_str(),
        ms: r.ms.named().to_vec(),
        total_ms: r.total_ms,
        surfels_total: r.map.total,
        surfels_active: r.map.active,
        surfels_added: r.fuse.added,
        surfels_merged: r.fuse.merged,
        tracker_inliers: r.inliers,
        tracker_residual: r.residual_rms,
        loop_closure: r.loop_closed,
        depth_abs_rel: r.depth_abs_rel,
        tracker_iterations: r.tracker_iterations,
        warp_mm: r.warp_m.map(|(mean, max)| (mean * 1e3, max * 1e3)),
        warp_solver_ms: r.reports.values().find_map(|rep| rep.counters.get(capsule_slam_framework::context::WARP_SOLVER_MS).copied()),
        counters: counters_of(r),
    }
}
