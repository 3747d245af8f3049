//! `ground-truth`: the oracle tracker. Returns the frame's ground-truth pose, so that fusion
//! and loop closure can be measured without tracking error. With `initial_pose = "identity"`
//! the ground truth is re-expressed relative to the first frame's pose, so the trajectory
//! starts at the identity like every other tracker's.

use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, Iso3, ModelView, Plugin, RgbdFrame, StageError, TrackResult, Tracker, register};

capsule_slam_framework::plugin_params! {
    /// Parameters of `ground-truth`.
    pub struct GroundTruthParams {
        /// Express poses relative to the first ground-truth pose times the pipeline's initial
        /// pose (true), or in the ground truth's own world frame (false).
        pub relative_to_first: bool = true; unit = "-";
    }
}

/// The oracle tracker.
#[derive(Debug, Clone)]
pub struct GroundTruth {
    params: GroundTruthParams,
    /// `t_world_gtworld`: maps ground-truth world coordinates into the run's world frame.
    offset: Option<Iso3>,
}

impl Plugin for GroundTruth {
    const NAME: &'static str = "ground-truth";
    const SUMMARY: &'static str = "oracle: the frame's ground-truth pose (needs groundtruth.txt)";
    type Params = GroundTruthParams;

    fn build(params: GroundTruthParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self { params, offset: None })
    }
}

impl Tracker for GroundTruth {
    fn track(&mut self, frame: &RgbdFrame, _model: Option<&ModelView>, t_world_prev: &Iso3, _ctx: &mut Context) -> Result<TrackResult, StageError> {
        let Some(gt) = frame.gt_t_world_cam else {
            return Err(StageError::invalid_input(format!(
                "frame {} has no ground-truth pose: `ground-truth` needs groundtruth.txt with a pose within input.association_tolerance_s of every frame",
                frame.index
            )));
        };
        let offset = match (self.params.relative_to_first, self.offset) {
            (false, _) => Iso3::identity(),
            (true, Some(o)) => o,
            (true, None) => {
                // First frame: the pipeline's prior is the initial pose.
                let o = t_world_prev * gt.inverse();
                self.offset = Some(o);
                o
            }
        };
        Ok(TrackResult::tracked(offset * gt))
    }
}

register!(Tracker, GroundTruth);
