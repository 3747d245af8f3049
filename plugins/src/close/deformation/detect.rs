//! Local loop detection: registering the active model to the inactive one and checking the
//! result (ElasticFusion, Whelan et al. 2016, Sec. 5, with organ-scale thresholds), and the surface constraints of an
//! accepted closure.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::deformation::{Deformation, SurfelTime};
use capsule_slam_framework::frame::{DepthSource, Masks};
use capsule_slam_framework::{Context, Iso3, ModelView, RgbdFrame, StageError, TrackStatus};

use super::params::{DeformationParams, Reference};
use crate::common::ed_graph::Constraint;
use crate::track::icp_rgb::{IcpRgb, IcpRgbParams, MotionModel, RgbReference};

/// The outcome of registering the active model to the inactive one.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// Share of the active view's pixels that the inactive model covers too.
    pub overlap: f64,
    /// The registered pose, when the registration ran (enough overlap).
    pub t_est: Option<Iso3>,
    /// The corrected pose, when every check passed.
    pub accepted: Option<Iso3>,
    /// The check that failed, as a counter name (`inliers`, `residual`, ...; `None` when
    /// accepted or when there was too little overlap to try).
    pub rejected: Option<&'static str>,
    /// How the inactive surface has moved since it was seen, when the registration that was
    /// accepted went through a warp (`warped.rs`).
    pub warp: Option<Deformation>,
}

/// Share of the active view's pixels that the inactive model covers too (0 for views of
/// different sizes).
pub fn overlap(active: &ModelView, inactive: &ModelView) -> f64 {
    let active_px = active.valid_pixels();
    if active_px == 0 || active.depth_m.size() != inactive.depth_m.size() {
        return 0.0;
    }
    let both = active.depth_m.data().iter().zip(inactive.depth_m.data()).filter(|(a, i)| **a > 0.0 && **i > 0.0).count();
    both as f64 / active_px as f64
}

/// Registers `active` (as the live frame) to `inactive` (as the model), both rendered at
/// `t_world_cam`, and applies the checks of `p`.
pub fn register_models(
    active: &ModelView,
    inactive: &ModelView,
    t_world_cam: &Iso3,
    p: &DeformationParams,
    ctx: &mut Context,
) -> Result<Registration, StageError> {
    let active_px = active.valid_pixels();
    let overlap = overlap(active, inactive);
    if overlap < p.min_overlap || active.depth_m.size() != inactive.depth_m.size() {
        return Ok(Registration { overlap, t_est: None, accepted: None, rejected: None, warp: None });
    }
    let frame = RgbdFrame {
        depth_source: DepthSource::Measured,
        index: ctx.frame_index,
        timestamp_s: 0.0,
        colour: active.colour.clone(),
        depth_m: active.depth_m.clone(),
        depth_confidence: None,
        depth_sigma_m: None,
        depth_sigma_correlation_px: 0.0,
        photometry: Default::default(),
        albedo: None,
        gt_t_world_cam: None,
        masks: Masks::new(),
        sample_share: None,
        derived: Default::default(),
    };
    let mut tracker = IcpRgb::new(IcpRgbParams {
        motion_model: MotionModel::None,
        rgb_reference: RgbReference::Model,
        rgb_reference_estimated: RgbReference::Model,
        w_rgb: p.w_rgb,
        sigma_icp_m: p.sigma_icp_m,
        icp_gate_m: p.icp_gate_m,
        stride_l0: 1,
        min_inlier_fraction: 0.0,
        max_residual_m: f64::MAX,
        max_jump_m: f64::MAX,
        // The closer judges the pose's uncertainty itself (`max_std_m`, `max_std_rad`).
        max_pose_sigma_m: f64::MAX,
        ..IcpRgbParams::default()
    });
    // The tracker's own counters and warnings stay in a scratch report: a rejected closure is
    // not a tracking failure. With the registration comes the residual where the models stand
    // now: a correction must explain the data much better than none, or it is the registration
    // sliding along a weakly constrained direction.
    let mut scratch = capsule_slam_framework::context::StageReport::default();
    let (tr, before) = tracker.register(&frame, Some(inactive), t_world_cam, true, &mut Context::new(ctx.frame_index, ctx.rig, None, &mut scratch))?;
    let inlier_share = tr.inliers as f64 / active_px as f64;
    let (std_t, std_r) = tr.covariance.map_or((f64::INFINITY, f64::INFINITY), |c| {
        let d = c.diagonal();
        (d.rows(0, 3).max().max(0.0).sqrt(), d.rows(3, 3).max().max(0.0).sqrt())
    });
    let figures = |t_est: &Iso3, residual_m: f64| Figures {
        tracked: tr.status == TrackStatus::Tracked,
        inlier_share,
        residual_m,
        std: (std_t, std_r),
        correction_m: (t_world_cam.inverse() * t_est).translation.vector.norm(),
        before_m: before,
    };
    let rigid = figures(&tr.t_world_cam, tr.residual_rms);
    ctx.count("inlier_share", inlier_share);
    ctx.count("residual_mm", tr.residual_rms * 1e3);
    ctx.count("correction_mm", rigid.correction_m * 1e3);
    ctx.count("residual_ratio", rigid.ratio());
    let rejected = rigid.rejection(p);
    let registration = Registration { overlap, t_est: Some(tr.t_world_cam), accepted: rejected.is_none().then_some(tr.t_world_cam), rejected, warp: None };
    if !(p.warp && matches!(rejected, Some("residual" | "unexplained"))) {
        return Ok(registration);
    }
    // The residual the rigid correction leaves may be the wall's motion since the old surface
    // was seen: register through a warp, from the tracked pose (`warped.rs`).
    Ok(match through_warp(active, inactive, t_world_cam, p, ctx, figures)? {
        Some((t_est, warp)) => Registration { accepted: Some(t_est), rejected: None, warp: Some(warp), ..registration },
        None => registration,
    })
}

/// The registration through the warp and its checks (`figures` of a pose and a residual):
/// the accepted pose and warp, or `None` (counted and, for a fallback, warned).
fn through_warp(
    active: &ModelView,
    inactive: &ModelView,
    t_world_cam: &Iso3,
    p: &DeformationParams,
    ctx: &mut Context,
    figures: impl Fn(&Iso3, f64) -> Figures,
) -> Result<Option<(Iso3, Deformation)>, StageError> {
    ctx.count("warp_tried", 1.0);
    let clock = std::time::Instant::now();
    let warped = super::warped::register_through_warp(active, inactive, t_world_cam, p, ctx.rig.camera())?;
    ctx.count("ms_warp_registration", clock.elapsed().as_secs_f64() * 1e3);
    let w = match warped {
        Ok(w) => w,
        Err(why) => {
            ctx.count("rejected_warp_fallback", 1.0);
            ctx.warn(format!("loop closure through the warp: {why}"));
            return Ok(None);
        }
    };
    ctx.count("warp_residual_mm", w.rms_m * 1e3);
    ctx.count("warp_max_node_mm", w.max_node_m * 1e3);
    let check = if w.max_node_m > p.max_warp_m { Some("large_warp") } else { figures(&w.t_world_cam, w.rms_m).rejection(p) };
    if let Some(check) = check {
        ctx.count(&format!("rejected_warp_{check}"), 1.0);
        return Ok(None);
    }
    ctx.count("warp_passed", 1.0);
    Ok(Some((w.t_world_cam, w.warp)))
}

/// What the checks of a registration read.
struct Figures {
    tracked: bool,
    inlier_share: f64,
    /// RMS residual after the correction, metres.
    residual_m: f64,
    /// Largest translation and rotation standard deviations of the pose.
    std: (f64, f64),
    /// How far the correction moves the camera, metres.
    correction_m: f64,
    /// RMS residual before any correction, metres.
    before_m: Option<f64>,
}

impl Figures {
    fn ratio(&self) -> f64 {
        self.residual_m / self.before_m.unwrap_or(f64::NAN)
    }

    /// The first check that fails, as a counter name.
    fn rejection(&self, p: &DeformationParams) -> Option<&'static str> {
        let (std_t, std_r) = self.std;
        let ratio = self.ratio();
        if !self.tracked {
            Some("lost")
        } else if self.inlier_share < p.min_inlier_share {
            Some("inliers")
        } else if self.residual_m.is_nan() || self.residual_m > p.max_residual_m {
            Some("residual")
        } else if std_t.is_nan() || std_r.is_nan() || std_t > p.max_std_m || std_r > p.max_std_rad {
            Some("uncertain")
        } else if self.correction_m > p.max_correction_m {
            Some("large_correction")
        } else if ratio.is_nan() || ratio > p.max_residual_ratio {
            Some("unexplained")
        } else if self.correction_m < p.min_correction_m {
            Some("small_correction")
        } else if self.before_m.is_none_or(|b| b < p.min_disagreement_m) {
            Some("agreement")
        } else {
            None
        }
    }
}

/// One surface sample of a closure: a pixel where both models have a surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// The active surface point, world frame, metres.
    pub active_m: nalgebra::Point3<f64>,
    /// The inactive surface point on the same pixel ray, world frame, metres.
    pub inactive_m: nalgebra::Point3<f64>,
    /// Time of the inactive surfel there (its creation or its last sighting, by the closer's
    /// [`SurfelTime`]).
    pub inactive_time: u32,
}

/// The samples of a closure on a grid of `stride_px` over the pixels where both models, rendered
/// at `t_world_cam`, have a surface.
pub fn samples(active: &ModelView, inactive: &ModelView, t_world_cam: &Iso3, stride_px: usize, time: SurfelTime, cam: &PinholeCamera) -> Vec<Sample> {
    let times = match time {
        SurfelTime::Created => &inactive.t0,
        SurfelTime::LastSeen => &inactive.t,
    };
    let (w, h) = active.depth_m.size();
    let s = stride_px.max(1);
    let mut out = Vec::new();
    for y in (s / 2..h).step_by(s) {
        for x in (s / 2..w).step_by(s) {
            let (d, di) = (active.depth_m.at(x, y), inactive.depth_m.at(x, y));
            if d > 0.0 && di > 0.0 {
                out.push(Sample {
                    active_m: t_world_cam * cam.unproject(x as f64, y as f64, f64::from(d)),
                    inactive_m: t_world_cam * cam.unproject(x as f64, y as f64, f64::from(di)),
                    inactive_time: times.at(x, y),
                });
            }
        }
    }
    out
}

/// The median time of the inactive surface the samples see (the loop's "then").
pub fn median_t0(samples: &[Sample]) -> Option<u32> {
    let mut t: Vec<u32> = samples.iter().map(|s| s.inactive_time).collect();
    t.sort_unstable();
    t.get(t.len() / 2).copied()
}

/// Surface constraints of an accepted closure from its samples. `correction(t)` is the world
/// correction that carries the active model onto inactive surface of time t (for a
/// registration, one `T_est T⁻¹` whatever t). `Reference::Old` moves each active
/// point `p` to `C p` and (with `pins`) holds `C p` at the inactive surfel's time;
/// `Reference::Recent` moves each inactive point `q` to `C⁻¹ q` and holds the active point `p`.
/// Active points carry the current time `now` (ElasticFusion), inactive ones the time of the
/// surfel they sample (not their surfels' creation times, which may be old for a surface still
/// in view: `docs/results/loop-closure.md`).
///
/// With a `warp` (a registration through the warp, `warped.rs`) the old surface has moved
/// since it was seen: each inactive point `q` goes to `W(q)` (`Old`; `C⁻¹ W(q)` with `Recent`)
/// instead of being held where it was.
pub fn constraints(
    samples: &[Sample],
    correction: impl Fn(u32) -> Iso3,
    now: u32,
    pins: bool,
    reference: Reference,
    warp: Option<&Deformation>,
) -> Vec<Constraint> {
    let mut out = Vec::new();
    for s in samples {
        let c = correction(s.inactive_time);
        let moved = warp.map(|w| w.warp_point(&s.inactive_m, s.inactive_time));
        match reference {
            Reference::Old => {
                let target = c * s.active_m;
                out.push(Constraint { source_m: s.active_m, target_m: target, time: now });
                if let Some(m) = moved {
                    out.push(Constraint { source_m: s.inactive_m, target_m: m, time: s.inactive_time });
                } else if pins {
                    out.push(Constraint { source_m: target, target_m: target, time: s.inactive_time });
                }
            }
            Reference::Recent => {
                let q = moved.unwrap_or(s.inactive_m);
                out.push(Constraint { source_m: s.inactive_m, target_m: c.inverse() * q, time: s.inactive_time });
                if pins {
                    out.push(Constraint { source_m: s.active_m, target_m: s.active_m, time: now });
                }
            }
        }
    }
    out
}
