//! Registration through the warp: a return to an old surface of a moving wall. The inactive
//! model was fused at an earlier phase of the wall's motion, so no rigid correction explains
//! its difference from the active model (the rigid registration is rejected for its residual).
//! Here the `nonrigid` tracker's joint solve registers the two models: the inactive
//! prediction's points are the model, bound to embedded-deformation nodes sampled on them, the
//! active prediction plays the live frame, and the camera and the warp are solved together from
//! the rigid registration's pose, the rest-shape prior giving the motion common to every node
//! to the camera (`track::nonrigid`, `shared/design/nonrigid.md` §5). The camera part is the
//! drift the closure corrects; the warp is how the old surface has moved since it was seen,
//! which the closure's constraints carry the inactive surface along.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::deformation::Deformation;
use capsule_slam_framework::image::gray_from_rgb;
use capsule_slam_framework::{Iso3, ModelView, StageError};

use super::params::DeformationParams;
use crate::track::icp_rgb::IcpRgbParams;
use crate::track::icp_rgb::frames::reference;
use crate::track::nonrigid::points::sample;
use crate::track::nonrigid::{CameraMode, Fit, Nonrigid, NonrigidParams};

/// A registration through the warp.
#[derive(Debug, Clone)]
pub struct Warped {
    /// The active view's pose on the inactive model (as the rigid registration's `T_est`).
    pub t_world_cam: Iso3,
    /// How the inactive surface has moved since it was seen, world frame.
    pub warp: Deformation,
    /// RMS point-to-plane residual of the inactive points against the active view after the
    /// solve, metres.
    pub rms_m: f64,
    /// Largest node displacement of the warp, metres.
    pub max_node_m: f64,
}

/// The joint solve's parameters for a closure: the tracker's defaults (its camera prior too:
/// with a weaker one the solve ran off on 41 of 107 tries on the loopy phantoms, with it on 26
/// of 88), except that every warp is kept (the closer judges it), the nodes may move up to
/// `max_warp_m` (and correspondences reach as far) without a per-frame step prior (the old
/// surface was seen many frames ago), the camera as far as a correction may
/// (`max_correction_m`), in twice the tracker's iterations. The photometric weight stays the
/// tracker's: with the closer's own (0.1) the unit test's solve runs off.
fn params(p: &DeformationParams) -> NonrigidParams {
    let tracker = NonrigidParams::default();
    NonrigidParams {
        gain_window_frames: 1,
        min_rms_gain: 0.0,
        min_evidence: 0.0,
        max_step_m: p.max_warp_m,
        gate_m: p.max_warp_m,
        sigma_step_m: 0.0,
        max_camera_step_m: p.max_correction_m,
        max_camera_step_rad: 5.0 * tracker.sigma_camera_rad,
        // A correction beyond the limit is rejected, not replaced by a warp of everything.
        hold_camera_on_step: false,
        // A registration of two models, not a wall's motion from frame to frame.
        warp_lead: 0.0,
        iterations: 2 * tracker.iterations,
        camera: CameraMode::Joint,
        ..tracker
    }
}

/// Registers the `inactive` model (as the model) to the `active` one (as the live frame), both
/// rendered at `t_start`, through a warp (from `t_start`: the rigid registration that failed
/// has often slid along the tube, millimetres from it).
/// `Ok(Err(why))` when the solve fell back or found no gain.
pub fn register_through_warp(
    active: &ModelView,
    inactive: &ModelView,
    t_start: &Iso3,
    p: &DeformationParams,
    cam: &PinholeCamera,
) -> Result<Result<Warped, String>, StageError> {
    let prep = IcpRgbParams::default().depth_prep();
    let Some(mut levels) = reference(Some(active), None, cam, 1, &prep) else { return Ok(Err("the active view is empty".into())) };
    let live = levels.remove(0);
    let mut gray = gray_from_rgb(&inactive.colour);
    gray.data_mut().iter_mut().for_each(|v| *v /= 255.0);
    let np = params(p);
    let points = sample(inactive, cam, Some(&gray), np.point_stride_px as usize, np.max_incidence_rad);
    let mut tracker = Nonrigid::new(np)?;
    match tracker.fit_fresh(&points, &live, t_start)? {
        Fit::Solved { t_world_cam, warp, outcome, .. } => {
            let max_node_m = warp.node_displacement_m().1;
            Ok(Ok(Warped { t_world_cam, warp, rms_m: outcome.icp_rms_m, max_node_m }))
        }
        Fit::Fallback(why) => Ok(Err(why)),
        Fit::Still(gains, _) => Ok(Err(format!("the warp lowered the residual by {:.0} % only", 100.0 * gains.icp))),
    }
}
