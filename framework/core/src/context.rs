//! The per-stage context: explicit fields, no type map.

use std::collections::BTreeMap;

use crate::camera::Rig;
use crate::map::ModelView;

/// What a stage reports about one call: counters and warnings. The pipeline times the call
/// itself and files the report into the frame's record.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StageReport {
    /// Named counters (e.g. `inliers`, `surfels_added`).
    pub counters: BTreeMap<String, f64>,
    /// Warnings for the user (e.g. "no valid pixels").
    pub warnings: Vec<String>,
}

/// The counter a non-rigid tracker files its warp solver's time under (milliseconds); the
/// runner writes it to `frames.csv` as `warp_solver_ms`. It is the solver's own work: a part
/// a tracker runs beside other work (as `nonrigid` builds its problem beside the rigid start)
/// counts in full, so it can exceed what the warp adds to the frame's time.
pub const WARP_SOLVER_MS: &str = "ms_warp_solver";

/// Passed to every stage call.
#[derive(Debug)]
pub struct Context<'a> {
    /// 0-based index of the frame being processed.
    pub frame_index: usize,
    /// The cameras.
    pub rig: &'a Rig,
    /// The active-model prediction at the last trusted pose, when the map has one.
    pub prediction: Option<&'a crate::map::ModelView>,
    report: &'a mut StageReport,
}

impl<'a> Context<'a> {
    /// A context that files into `report`.
    pub fn new(frame_index: usize, rig: &'a Rig, prediction: Option<&'a ModelView>, report: &'a mut StageReport) -> Self {
        Self { frame_index, rig, prediction, report }
    }

    /// Sets a counter.
    pub fn count(&mut self, name: &str, value: f64) {
        self.report.counters.insert(name.to_owned(), value);
    }

    /// Records a warning.
    pub fn warn(&mut self, message: impl Into<String>) {
        self.report.warnings.push(message.into());
    }
}
