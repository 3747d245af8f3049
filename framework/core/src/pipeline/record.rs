//! What the pipeline records about each frame.

use std::collections::BTreeMap;
use std::time::Instant;

use crate::context::StageReport;
use crate::error::{PipelineError, StageError};
use crate::geometry::Iso3;
use crate::map::MapStats;
use crate::stage::{FuseStats, TrackStatus};

/// Wall-clock milliseconds per stage for one frame (0 for a stage that did not run).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// All preprocessors together.
    pub preprocess: f64,
    /// Depth estimation.
    pub depth: f64,
    /// Tracking.
    pub track: f64,
    /// Loop closure, including the two predictions it needs.
    pub loop_close: f64,
    /// Fusion.
    pub fuse: f64,
    /// The active-model prediction for the next frame.
    pub predict: f64,
}

impl StageTimes {
    /// `(column name, value)` pairs, in pipeline order.
    pub fn named(&self) -> [(&'static str, f64); 6] {
        [
            ("preprocess", self.preprocess),
            ("depth", self.depth),
            ("track", self.track),
            ("loop", self.loop_close),
            ("fuse", self.fuse),
            ("predict", self.predict),
        ]
    }
}

/// The record of one processed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    /// 0-based frame index.
    pub index: usize,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// Estimated pose (after any loop closure at this frame).
    pub t_world_cam: Iso3,
    /// Tracked or lost.
    pub status: TrackStatus,
    /// Milliseconds per stage.
    pub ms: StageTimes,
    /// Milliseconds for the whole frame: the wall time of the call that processed it. With frames
    /// pushed ([`super::Pipeline::push`]) that includes preparing the next frame beside this one's
    /// fusion, and this frame's own preparation is in its preprocess, depth and track times.
    pub total_ms: f64,
    /// Map counts after the frame.
    pub map: crate::map::MapStats,
    /// Fusion counts (zero when not fused).
    pub fuse: FuseStats,
    /// Tracker inliers.
    pub inliers: usize,
    /// Tracker RMS residual.
    pub residual_rms: f64,
    /// Tracker Gauss-Newton iterations.
    pub tracker_iterations: usize,
    /// The tracker's warp of the map, when it returned one: mean and max node displacement,
    /// metres.
    pub warp_m: Option<(f64, f64)>,
    /// Whether a loop closure was applied at this frame.
    pub loop_closed: bool,
    /// AbsRel of an estimated depth against the input's own depth (the phantom's ground
    /// truth), when the input has depth and the depth was estimated.
    pub depth_abs_rel: Option<f64>,
    /// Counters and warnings per plugin name.
    pub reports: BTreeMap<String, StageReport>,
}

impl FrameRecord {
    /// The record of frame `index` before any stage ran (tracked, at the identity, no figures).
    pub fn new(index: usize, timestamp_s: f64) -> Self {
        Self {
            index,
            timestamp_s,
            t_world_cam: Iso3::identity(),
            status: TrackStatus::Tracked,
            ms: StageTimes::default(),
            total_ms: 0.0,
            map: MapStats::default(),
            fuse: FuseStats::default(),
            inliers: 0,
            residual_rms: 0.0,
            tracker_iterations: 0,
            warp_m: None,
            loop_closed: false,
            depth_abs_rel: None,
            reports: BTreeMap::new(),
        }
    }

    /// Every warning of the frame, prefixed by its plugin's name (once: a plugin that already
    /// names itself, as a library's plugin may, is not named twice).
    pub fn warnings(&self) -> impl Iterator<Item = String> + '_ {
        self.reports.iter().flat_map(|(name, r)| {
            r.warnings.iter().map(move |w| match w.strip_prefix(name.as_str()).and_then(|rest| rest.strip_prefix(": ")) {
                Some(_) => w.clone(),
                None => format!("{name}: {w}"),
            })
        })
    }
}

/// Milliseconds since `t`.
pub(super) fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The report of stage `name` in `rec`.
pub(super) fn report<'r>(rec: &'r mut FrameRecord, name: &str) -> &'r mut StageReport {
    rec.reports.entry(name.to_owned()).or_default()
}

/// A stage's error at `frame`.
pub(super) fn stage_err(frame: usize, stage: &str, source: StageError) -> PipelineError {
    PipelineError::Stage { frame, stage: stage.to_owned(), source }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_warning_names_its_plugin_once() {
        let mut rec = FrameRecord::new(0, 0.0);
        report(&mut rec, "sensor").warnings.extend(["no depth within [0.001, 0.3] m".to_string(), "sensor: already named".to_string()]);
        report(&mut rec, "vignetting").warnings.push("sensor: a name that is not its own".to_string());
        let all: Vec<String> = rec.warnings().collect();
        assert_eq!(all, ["sensor: no depth within [0.001, 0.3] m", "sensor: already named", "vignetting: sensor: a name that is not its own"]);
    }
}
