//! A frame with nothing to track against: neither the model nor a previous frame has depth.

use capsule_slam_framework::stage::{TrackResult, TrackStatus};
use capsule_slam_framework::{Context, Iso3};

use super::IcpRgb;
use super::frames::Level;

impl IcpRgb {
    /// The first frame with usable depth is the origin (`t_world_cam`, the prior) and the next
    /// frame's reference; a frame without usable depth is lost (its pose is not measured) and
    /// does not become the reference. With `keyframe` the frame is also the photometric term's
    /// first keyframe.
    pub(super) fn without_reference(&mut self, live: Vec<Level>, t_world_cam: Iso3, keyframe: bool, ctx: &mut Context) -> TrackResult {
        let usable = live.first().is_some_and(|l| l.depth.data().iter().any(|d| *d > 0.0));
        if usable {
            if keyframe {
                self.keyframe = Some(super::keyframe::Keyframe::new(&live));
            }
            self.previous = Some(live);
            return TrackResult::tracked(t_world_cam);
        }
        ctx.warn("tracking lost: the frame has no usable depth and nothing to track against");
        TrackResult { status: TrackStatus::Lost, ..TrackResult::tracked(t_world_cam) }
    }
}
