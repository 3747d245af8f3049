//! Registering a live pyramid to the reference, coarse to fine (Eqs. 2–4 on ElasticFusion's
//! 3-level pyramid), and the loss verdict on the result.
//!
//! A caller that refines the pose at level 0 itself (the `nonrigid` tracker's joint solve on a
//! clearly moving wall) may stop the registration after the coarsest level (or the two coarse
//! levels) and level 0's first iteration, whose system the loss verdict needs anyway
//! ([`IcpRgb::register_pyramid`] to [`Stop::Coarse`]), and, where its own refinement does not
//! stand, finish the registration later ([`IcpRgb::finish_fine`]). The stopped registration
//! keeps everything the rest needs, so the finished result is the uninterrupted
//! registration's to the bit.

use capsule_slam_framework::frame::DepthSource;
use capsule_slam_framework::{Context, GrayF32, Iso3, ModelView, StageError, TrackResult, TrackStatus};

use super::frames::{self, Level};
use super::gn::{self, Weights, accumulate};
use super::keyframe::Keyframe;
use super::relight::Relighter;
use super::{DepthNoise, IcpRgb, LEVELS, Mode, MotionModel, RgbReference};

/// The photometric reference's pyramid, and its camera ← the reference camera where that is not
/// the reference camera (a keyframe's).
type Photo<'a> = (&'a [Level], Option<Iso3>);

/// What a registration stopped before level 0 keeps to finish there.
pub(crate) struct Unfinished {
    /// The reference pyramid.
    reference: Vec<Level>,
    /// The previous live frame's pyramid, which the photometric term compares with
    /// (`rgb_reference = "previous-frame"`): the current frame is now `IcpRgb::previous`.
    before: Option<Vec<Level>>,
    /// The velocity before the coarse result replaced it.
    velocity: Option<Iso3>,
    /// The photometric keyframe before the coarse result moved it on.
    keyframe: Option<Keyframe>,
    /// The live albedo per level, where the photometric term is relit.
    albedo: Option<Vec<GrayF32>>,
    /// The motion prior the registration started from.
    prior: Iso3,
    /// Where the registration stopped.
    run: Run,
    /// The level `run` continues at: 0 after level 0's first iteration; 1 when the coarse start
    /// skipped level 1 (`run` then holds the pose after level 2, and level 0 starts afresh).
    resume_level: usize,
    /// The previous camera's pose.
    t_world_prev: Iso3,
    /// The frame's depth source.
    depth_source: DepthSource,
}

/// Where a registration stops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Stop {
    /// At level 0, converged.
    Fine,
    /// After the levels from the coarsest down to `lowest` (2 or 1) and level 0's first
    /// iteration, unless the pose there would be declared lost.
    Coarse { lowest: usize },
}

impl Stop {
    /// The stop with its lowest coarse level within the pyramid's coarse levels (1 or 2).
    fn within_levels(self) -> Self {
        match self {
            Self::Coarse { lowest } => Self::Coarse { lowest: lowest.clamp(1, LEVELS - 1) },
            fine => fine,
        }
    }
}

/// The pose reached so far, the iterations run, and on the current level how many ran and
/// whether it has ended (converged, or no step); the last level-0 system.
#[derive(Clone, Copy)]
struct Run {
    t: Iso3,
    iterations: u32,
    on_level: u32,
    level_ended: bool,
    fin: Option<gn::System>,
}

impl IcpRgb {
    /// [`IcpRgb::register`] on a prepared live pyramid ([`IcpRgb::live_pyramid`]), run to
    /// `stop`. Stopped after the coarse levels ([`Stop::Coarse`]), the result is the pose there,
    /// judged on level 0's first iteration's system as a finished registration is on its last.
    /// A pose that would be lost there is finished at once (a lost frame is judged at its
    /// converged pose, as always). Otherwise the frame is this tracker's previous frame already,
    /// and [`IcpRgb::finish_fine`] can run the rest until the next registration.
    #[allow(clippy::too_many_arguments, reason = "the registration's inputs and where it stops")]
    pub(crate) fn register_pyramid(
        &mut self,
        mut live: Vec<Level>,
        depth_source: DepthSource,
        model: Option<&ModelView>,
        t_world_prev: &Iso3,
        initial: bool,
        stop: Stop,
        ctx: &mut Context,
    ) -> Result<(TrackResult, Option<f64>), StageError> {
        let stop = stop.within_levels();
        self.unfinished = None;
        let prior = match self.params.motion_model {
            MotionModel::ConstantVelocity => self.velocity.unwrap_or_else(Iso3::identity),
            MotionModel::None => Iso3::identity(),
        };
        let reference = self.reference_pyramid(model, ctx);
        let clock = std::time::Instant::now();
        let Some(reference) = reference else {
            let keyframe = self.depth_noise(depth_source, live.first().map_or(0.0, |l| l.sigma_correlation_px)).rgb_reference.keeps_keyframe();
            return Ok((self.without_reference(live, t_world_prev * prior, keyframe, ctx), None));
        };
        // Registered once more, weighed by the measured depth error, where the frame's own
        // residuals show its σ too small (`measured_noise.rs`).
        let mut retried = false;
        loop {
            let noise = self.depth_noise(depth_source, live.first().map_or(0.0, |l| l.sigma_correlation_px));
            let photo = self.photometric_reference(noise.rgb_reference, self.previous.as_ref(), self.keyframe.as_ref(), &reference);
            let w = self.weights(&noise);
            // The pose-free half of the relighting, per level (`Relighter::live_albedo`).
            let relighter = self.light.as_ref().map(Relighter::new);
            let albedo: Option<Vec<GrayF32>> =
                relighter.as_ref().map(|r| live.iter().enumerate().map(|(level, lv)| r.live_albedo(lv, self.stride(level))).collect());
            let second = Self::second_reference(noise.rgb_reference, photo, self.previous.as_deref());
            let inputs = |level: usize| self.level_inputs([&live, &reference], photo, relighter.as_ref(), albedo.as_deref(), level, second);
            let initial = initial.then(|| accumulate(&inputs(0), &prior, &w).icp_rms());
            // Gauss-Newton from the coarsest level, starting at the prior (Eqs. 2–4).
            let mut run = Run { t: prior, iterations: 0, on_level: 0, level_ended: false, fin: None };
            if let Stop::Coarse { lowest } = stop {
                self.descend(&inputs, (LEVELS - 1, lowest), false, &w, &mut run);
                // Level 0's first iteration from here; the levels skipped resume from `coarse`.
                let coarse = run;
                (run.on_level, run.level_ended) = (0, false);
                self.iterate(&inputs(0), 0, &w, &mut run, self.params.iterations_l0.min(1));
                let fin = run.fin.unwrap_or_else(|| accumulate(&inputs(0), &run.t, &w));
                let (resume, resume_level) = if lowest > 1 { (coarse, lowest - 1) } else { (run, 0) };
                if self.lost_why(&fin, &noise, &prior, &run.t).is_none() {
                    if !std::mem::replace(&mut retried, true) && self.measure_noise(&mut live, &reference, &run.t, depth_source, ctx) {
                        continue;
                    }
                    ctx.count("ms_gauss_newton", clock.elapsed().as_secs_f64() * 1e3);
                    let (velocity, keyframe) = (self.velocity, self.keyframe.clone());
                    let (result, before) = self.conclude(live, (run.t, run.iterations, fin), &prior, &noise, t_world_prev, ctx);
                    let (run, t_world_prev) = (resume, *t_world_prev);
                    let u = Unfinished { reference, before, velocity, keyframe, albedo, prior, run, resume_level, t_world_prev, depth_source };
                    self.unfinished = Some(Box::new(u));
                    return Ok((result, initial));
                }
                // Lost there: finished now, as the uninterrupted registration.
                run = resume;
                self.descend(&inputs, (resume_level, 0), resume_level == 0, &w, &mut run);
            } else {
                self.descend(&inputs, (LEVELS - 1, 0), false, &w, &mut run);
            }
            let previous = self.previous.as_deref();
            let stale = self.keyframe_disagrees([&live, &reference], (photo, previous), (relighter.as_ref(), albedo.as_deref()), &w, &mut run, ctx);
            let fin = run.fin.unwrap_or_else(|| accumulate(&inputs(0), &run.t, &w));
            if stale {
                self.keyframe = None;
            }
            // A lost frame's error is read at the prior, the better guess of its pose.
            let at = if self.lost_why(&fin, &noise, &prior, &run.t).is_some() { prior } else { run.t };
            if !std::mem::replace(&mut retried, true) && self.measure_noise(&mut live, &reference, &at, depth_source, ctx) {
                continue;
            }
            ctx.count("ms_gauss_newton", clock.elapsed().as_secs_f64() * 1e3);
            return Ok((self.conclude(live, (run.t, run.iterations, fin), &prior, &noise, t_world_prev, ctx).0, initial));
        }
    }

    /// The reference pyramid (`frames::reference`): the model's prediction in frame-to-model
    /// mode, filled in by the previous frame; none where neither shows anything.
    fn reference_pyramid(&self, model: Option<&ModelView>, ctx: &mut Context) -> Option<Vec<Level>> {
        let clock = std::time::Instant::now();
        let model = if self.params.mode == Mode::FrameToModel { model } else { None };
        let previous = self.previous.as_ref().and_then(|p| p.first());
        let reference = frames::reference(model, previous, ctx.rig.camera(), LEVELS, &self.params.depth_prep());
        ctx.count("ms_reference_pyramid", clock.elapsed().as_secs_f64() * 1e3);
        reference
    }

    /// Runs the rest of the registration [`IcpRgb::register_pyramid`] stopped short of
    /// (a skipped level 1, level 0): the result it would have given run to [`Stop::Fine`],
    /// to the bit. `None` when there is none to finish (the last registration was not stopped,
    /// or was lost).
    pub(crate) fn finish_fine(&mut self, ctx: &mut Context) -> Option<TrackResult> {
        let u = self.unfinished.take()?;
        let live = self.previous.take()?;
        let clock = std::time::Instant::now();
        let noise = self.depth_noise(u.depth_source, live.first().map_or(0.0, |l| l.sigma_correlation_px));
        let w = self.weights(&noise);
        // The keyframe as the registration found it (the coarse result moved it on).
        self.keyframe = u.keyframe.clone();
        let photo = self.photometric_reference(noise.rgb_reference, u.before.as_ref(), self.keyframe.as_ref(), &u.reference);
        let relighter = self.light.as_ref().map(Relighter::new);
        let second = Self::second_reference(noise.rgb_reference, photo, u.before.as_deref());
        let inputs = |level: usize| self.level_inputs([&live, &u.reference], photo, relighter.as_ref(), u.albedo.as_deref(), level, second);
        let mut run = u.run;
        self.descend(&inputs, (u.resume_level, 0), u.resume_level == 0, &w, &mut run);
        let stale = self.keyframe_disagrees([&live, &u.reference], (photo, u.before.as_deref()), (relighter.as_ref(), u.albedo.as_deref()), &w, &mut run, ctx);
        let fin = run.fin.unwrap_or_else(|| accumulate(&inputs(0), &run.t, &w));
        if stale {
            self.keyframe = None;
        }
        ctx.count("ms_gauss_newton_fine", clock.elapsed().as_secs_f64() * 1e3);
        let Unfinished { before, velocity, prior, t_world_prev, .. } = *u;
        let result = self.conclude(live, (run.t, run.iterations, fin), &prior, &noise, &t_world_prev, ctx).0;
        if result.status == TrackStatus::Lost {
            // As if the registration had run uninterrupted: a lost frame leaves the previous
            // frame and the velocity as they were.
            self.previous = before;
            self.velocity = velocity;
        }
        Some(result)
    }

    /// Whether the registration to a keyframe (`photo` with a transform; `keyframe.rs`)
    /// disagrees with the `previous` frame's pyramid: the Gauss-Newton step of the term against
    /// the previous frame at the keyframe's solution, `δᵀAδ` in its own information, above
    /// `keyframe_max_disagreement`. The frame is then finished against the previous frame (level
    /// 0, from the keyframe's solution) and the keyframe is stale: on a moving wall a keyframe
    /// some frames old reads the wall's motion since as the camera's.
    fn keyframe_disagrees(
        &self,
        [live, reference]: [&[Level]; 2],
        (photo, previous): (Photo<'_>, Option<&[Level]>),
        (relighter, albedo): (Option<&Relighter<'_>>, Option<&[GrayF32]>),
        w: &Weights,
        run: &mut Run,
        ctx: &mut Context,
    ) -> bool {
        let (Some(_), Some(previous)) = (photo.1, previous) else { return false };
        let f2f = self.level_inputs([live, reference], (previous, None), relighter, albedo, 0, None);
        let disagreement = accumulate(&f2f, &run.t, w).step_chi2();
        ctx.count("keyframe_disagreement", disagreement);
        if disagreement <= self.params.keyframe_max_disagreement {
            return false;
        }
        (run.on_level, run.level_ended) = (0, false);
        self.iterate(&f2f, 0, w, run, self.params.iterations_l0);
        true
    }

    /// Drops a registration stopped after the coarse levels: the caller's own level-0 pose
    /// stands.
    pub(crate) fn drop_unfinished(&mut self) {
        self.unfinished = None;
    }

    /// What the photometric term compares with, and its camera ← the reference camera where
    /// that is not the reference camera: the keyframe (`rgb_reference = "keyframe"`, where there
    /// is one), the previous live frame's pyramid (`"previous-frame"`, and `"keyframe"` before the
    /// first), else the reference.
    fn photometric_reference<'a>(
        &self,
        kind: RgbReference,
        previous: Option<&'a Vec<Level>>,
        keyframe: Option<&'a Keyframe>,
        reference: &'a [Level],
    ) -> Photo<'a> {
        match (kind, previous, keyframe) {
            // Just taken, the keyframe is the previous frame.
            (RgbReference::Keyframe | RgbReference::KeyframeAndPrevious, _, Some(kf)) if kf.t_kf_prev == Iso3::identity() => (&kf.pyramid, None),
            (RgbReference::Keyframe | RgbReference::KeyframeAndPrevious, _, Some(kf)) => (&kf.pyramid, Some(kf.t_kf_prev)),
            (RgbReference::PreviousFrame | RgbReference::Keyframe | RgbReference::KeyframeAndPrevious, Some(p), _) => (p, None),
            _ => (reference, None),
        }
    }

    /// The previous frame as a second photometric reference: with `keyframe-and-previous`,
    /// while the keyframe (`photo`, carried by its transform) is an older frame.
    fn second_reference<'a>(kind: RgbReference, (_, t_photo_ref): Photo<'a>, previous: Option<&'a [Level]>) -> Option<&'a [Level]> {
        (kind == RgbReference::KeyframeAndPrevious && t_photo_ref.is_some()).then_some(previous).flatten()
    }

    /// One level's Gauss-Newton inputs from the live, reference and photometric pyramids and
    /// the relighting with the live albedo per level (every `stride_l0`-th pixel at level 0).
    fn level_inputs<'a>(
        &self,
        [live, reference]: [&'a [Level]; 2],
        (photo, t_photo_ref): Photo<'a>,
        relighter: Option<&'a Relighter<'a>>,
        albedo: Option<&'a [GrayF32]>,
        level: usize,
        second: Option<&'a [Level]>,
    ) -> gn::Inputs<'a> {
        gn::Inputs {
            live: &live[level],
            reference: &reference[level],
            photo: &photo[level],
            t_photo_ref,
            light: relighter.zip(albedo).map(|(r, a)| (r, &a[level])),
            stride: self.stride(level),
            second: second.map(|p| (&p[level], None)),
        }
    }

    /// Every how many pixels a level's systems read the live image (`stride_l0` at level 0).
    fn stride(&self, level: usize) -> usize {
        if level == 0 { self.params.stride_l0 as usize } else { 1 }
    }

    /// Runs the levels from `from` down to `to`, each from its first iteration, except that with
    /// `resume` the first continues where `run` stopped on it.
    fn descend<'a>(&self, inputs: &dyn Fn(usize) -> gn::Inputs<'a>, (from, to): (usize, usize), resume: bool, w: &Weights, run: &mut Run) {
        let limits = [self.params.iterations_l0, self.params.iterations_l1, self.params.iterations_l2];
        for level in (to..=from).rev() {
            if !(resume && level == from) {
                (run.on_level, run.level_ended) = (0, false);
            }
            self.iterate(&inputs(level), level, w, run, limits[level]);
        }
    }

    /// Gauss-Newton iterations on one level from `run.t` until `upto` have run on it
    /// (`iterations_l0/1/2` at most) or the level ends: the step falls below `convergence`, or
    /// its δᵀAδ below `convergence_chi2` (level 0) or `convergence_chi2_coarse`, or the system
    /// has none. A level-0 system is kept in `run.fin` (the last one accumulated).
    fn iterate(&self, inputs: &gn::Inputs<'_>, level: usize, w: &Weights, run: &mut Run, upto: u32) {
        while !run.level_ended && run.on_level < upto {
            run.on_level += 1;
            let sys = accumulate(inputs, &run.t, w);
            if level == 0 {
                run.fin = Some(sys);
            }
            let Some(delta) = sys.step().filter(|d| d.iter().all(|v| v.is_finite())) else {
                run.level_ended = true;
                break;
            };
            run.t = capsule_slam_framework::geometry::renormalised(capsule_slam_framework::geometry::exp_se3(&delta) * run.t);
            run.iterations += 1;
            // The step's length in the system's own information, δᵀAδ = bᵀA⁻¹b: the χ² decrease
            // it predicts, in σ².
            let chi2_tol = if level == 0 { self.params.convergence_chi2 } else { self.params.convergence_chi2_coarse };
            run.level_ended = delta.norm() < self.params.convergence || sys.chi2_of(&delta) < chi2_tol;
        }
    }

    /// The verdict on the pose `t` (previous camera → live) whose level-0 system is `fin`: the
    /// counters, and on success the velocity and the previous frame set (the previous frame
    /// before it returned). The result is the frame's.
    fn conclude(
        &mut self,
        live: Vec<Level>,
        (t, total_iters, fin): (Iso3, u32, gn::System),
        prior: &Iso3,
        noise: &DepthNoise,
        t_world_prev: &Iso3,
        ctx: &mut Context,
    ) -> (TrackResult, Option<Vec<Level>>) {
        let covariance = fin.a.full().try_inverse();
        let inlier_share = if fin.live_n == 0 { 0.0 } else { fin.icp_n as f64 / fin.live_n as f64 };
        let why = self.lost_why(&fin, noise, prior, &t);
        ctx.count("pose_sigma_mm", pose_sigma_m(covariance.as_ref()) * 1e3);
        ctx.count("icp_rms_sigmas", fin.icp_rms_sigmas());
        ctx.count("icp_inliers", fin.icp_n as f64);
        ctx.count("rgb_pixels", fin.rgb_n as f64);
        ctx.count("inlier_share", inlier_share);
        ctx.count("iterations", f64::from(total_iters));
        let (status, before) = match why {
            Some(why) => {
                ctx.warn(format!("tracking lost: {why}"));
                // The wall may keep moving while the camera is lost: the frame that tracks
                // again starts a keyframe rather than reaching back to one older still.
                self.keyframe = None;
                (TrackStatus::Lost, None)
            }
            None => {
                self.velocity = Some(t);
                if noise.rgb_reference.keeps_keyframe() {
                    let policy = self.params.keyframe_policy();
                    ctx.count("keyframe_new", f64::from(u8::from(Keyframe::advance(&mut self.keyframe, &live, &t, fin.rgb_n, &policy))));
                }
                (TrackStatus::Tracked, self.previous.replace(live))
            }
        };
        let result = TrackResult {
            t_world_cam: t_world_prev * t,
            status,
            inliers: fin.icp_n,
            residual_rms: fin.icp_rms(),
            covariance,
            iterations: total_iters as usize,
            warp: None,
        };
        (result, before)
    }

    /// Why the pose `t` reached from `prior`, whose level-0 system is `fin`, is lost, if it is:
    /// too few inliers, a residual far above what the noise explains (in units of each
    /// residual's σ, times the floor: exactly the RMS in metres when the frame carries no σ), a
    /// jump from the prior, or a pose the data do not constrain.
    fn lost_why(&self, fin: &gn::System, noise: &DepthNoise, prior: &Iso3, t: &Iso3) -> Option<String> {
        let inlier_share = if fin.live_n == 0 { 0.0 } else { fin.icp_n as f64 / fin.live_n as f64 };
        let jump = (prior.inverse() * t).translation.vector.norm();
        let pose_sigma_m = pose_sigma_m(fin.a.full().try_inverse().as_ref());
        let residual_m = fin.icp_rms_sigmas() * noise.sigma_icp_m;
        if inlier_share < noise.min_inlier_fraction {
            Some(format!("{:.0} % of the live pixels are ICP inliers (min_inlier_fraction {:.0} %)", 100.0 * inlier_share, 100.0 * noise.min_inlier_fraction))
        } else if residual_m.is_nan() || residual_m > noise.max_residual_m {
            Some(format!(
                "ICP residual {:.2} σ (max_residual_m / sigma_icp_m = {:.2} σ; RMS {:.3} mm)",
                fin.icp_rms_sigmas(),
                noise.max_residual_m / noise.sigma_icp_m,
                fin.icp_rms() * 1e3
            ))
        } else if jump > self.params.max_jump_m {
            Some(format!("the pose jumps {:.2} mm from the prior (max_jump_m {:.2} mm)", jump * 1e3, self.params.max_jump_m * 1e3))
        } else if pose_sigma_m.is_nan() || pose_sigma_m > self.params.max_pose_sigma_m {
            Some(format!(
                "the pose is not constrained: σ {:.2} mm along its worst direction (max_pose_sigma_m {:.2} mm)",
                pose_sigma_m * 1e3,
                self.params.max_pose_sigma_m * 1e3
            ))
        } else {
            None
        }
    }
}

/// The standard deviation of the camera's translation along its worst direction, from the
/// pose covariance (the inverse Gauss-Newton information; infinite where it is singular).
fn pose_sigma_m(covariance: Option<&nalgebra::Matrix6<f64>>) -> f64 {
    covariance.map_or(f64::INFINITY, |c| c.fixed_view::<3, 3>(0, 0).symmetric_eigenvalues().max().max(0.0).sqrt())
}
