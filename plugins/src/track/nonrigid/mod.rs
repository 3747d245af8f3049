//! `nonrigid`: the camera pose **and** a deformation of the active model, every frame — the
//! non-rigid half of the paper's title (Sec. 3.4 applies embedded deformation at loop closures;
//! this tracker applies it to the moving wall itself, as SurfelWarp and SuPer do; design digest:
//! `shared/design/nonrigid.md`).
//!
//! Per frame:
//! 1. a rigid start: `icp-rgb` (every option of it, under `[plugins.nonrigid.rigid]`) against the
//!    prediction of the map, which the previous frames' warps keep at the wall's last shape;
//!    its loss detection is this tracker's; while the wall clearly moves (a window of kept
//!    warps), it runs the coarsest level and level 0's first iteration only, on all but every
//!    `moving_probe_every_frames`-th frame (`coarse_start_level`), since the joint solve refines
//!    the camera at level 0 itself; those frames keep their warp unjudged, and one whose solve
//!    does not stand finishes the rigid start and is solved again (counter
//!    `nonrigid_coarse_start_finished`);
//! 2. embedded-deformation nodes cover the predicted surface (`node_spacing_m`, `nodes.rs`); the
//!    prediction's pixels on a grid are bound to their k nearest nodes within `reach_m`;
//! 3. a joint Gauss-Newton solve of the camera and the nodes' affine increments (`solve.rs`):
//!    point to plane + photometric against the live frame, the ED graph's rotation and
//!    smoothness terms (shared with the `deformation` loop closer), a rest-shape prior that
//!    gives motion common to every node to the camera, a per-frame step prior and a camera prior
//!    toward the rigid start; faer's sparse Cholesky, its analysis kept while the pattern holds;
//! 4. model selection: optionally the rigid motion common to the nodes is factored out of the
//!    warp (`factor_common`, OpenCV dynafu's `factorCommon`), and the warp is kept only when the
//!    point-to-plane RMS over the points that are inliers before and after the solve (`verdict.rs`)
//!    falls by `min_rms_gain` on average over the last `gain_window_frames`
//!    solves and its χ² by more than `min_evidence` per unknown (Akaike): a still wall is left
//!    still (counter `nonrigid_still`); while it is clearly still, the warp is solved on every
//!    `still_probe_every_frames`-th frame only (counter `nonrigid_probe_skipped`), the interval
//!    doubling up to `still_probe_max_every_frames` while the probes find it still, and a rigid
//!    residual risen by `still_probe_residual_rise` calls the next probe at once (counter
//!    `nonrigid_probe_called`);
//! 5. when the joint solve would move the camera farther from the rigid start than
//!    `max_camera_step_m`/`_rad`, the nodes are solved again with the camera held there
//!    (`hold_camera_on_step`, counter `nonrigid_camera_held`: the map keeps following the wall);
//! 6. the map leads the moving wall: a kept warp's node translations are scaled by
//!    `1 + warp_lead`, so the next frame's rigid start and warp meet a map nearer where the wall
//!    has gone (a peristaltic wall keeps moving; `params.rs` gives the steady state and the
//!    stability bound);
//! 7. a fallback to the rigid pose, without a warp, when too few model points find the live
//!    wall, the solver fails, a node would jump or (without the hold) the camera would leave
//!    the rigid start (each named in a warning, counter `nonrigid_fallback`).
//!
//! With depth estimated from the image the warp is off (`warp_estimated_depth`): the tracker is
//! then `icp-rgb` exactly. By default the camera is an unknown of the warp solve (`camera =
//! "joint"`, held by a prior toward the rigid start and the nodes' rest-shape prior) and the
//! model selection judges the mean gain of the last `gain_window_frames` solves, so a still
//! wall keeps no warp and tracks as `icp-rgb` (`docs/results/nonrigid.md`, "With the default
//! preprocessors"); `camera = "fixed"` is SurfelWarp's nodes-only solve.
//!
//! The photometric reference (the previous frame's intensity at each model point) is relit to
//! the rigid start's view with the rigid start's light model (`relight`, `points::relight`).
//!
//! The warp goes out in [`TrackResult::warp`]: the pipeline applies it to the map (through the
//! fuser) before fusion, so the frame fuses into the wall as it is now. Surfels beyond
//! `reach_m` of every solved node stay where they are.

mod assemble;
mod energy;
#[doc(hidden)]
pub mod fixture;
mod iterate;
mod nodes;
mod params;
pub(crate) mod points;
mod priors;
mod problem;
mod solve;
mod system;
#[cfg(test)]
mod tests;
mod verdict;

pub use params::{CameraMode, NonrigidParams};

use capsule_slam_framework::deformation::{Deformation, DeformationNode};
use capsule_slam_framework::frame::DepthSource;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, Iso3, ModelView, Plugin, RgbdFrame, StageError, TrackResult, TrackStatus, Tracker, register};

use crate::track::icp_rgb::IcpRgb;
use crate::track::icp_rgb::frames::Level;
use crate::track::icp_rgb::register::Stop;

use nodes::Nodes;
use points::ModelPoint;
use problem::{Built, Ready};
use solve::Cache;
#[cfg(test)]
use solve::Problem;
use std::ops::ControlFlow;
pub(crate) use verdict::Fit;
use verdict::{Gains, Moving, Probe, windowed_gain};

/// The non-rigid tracker.
pub struct Nonrigid {
    params: NonrigidParams,
    rigid: IcpRgb,
    nodes: Nodes,
    cache: Cache,
    /// The point-to-plane gains of the last `gain_window_frames` solves.
    recent_gains: std::collections::VecDeque<f64>,
    /// The still wall's probe schedule (`still_probe_every_frames`).
    probe: Probe,
    /// The moving wall's coarse rigid starts (`moving_probe_every_frames`).
    moving: Moving,
}

impl Plugin for Nonrigid {
    const NAME: &'static str = "nonrigid";
    const SUMMARY: &'static str = "camera pose and an embedded deformation of the active model per frame: rigid icp-rgb start, then joint point-to-plane + photometric + ARAP + rest-prior Gauss-Newton (faer sparse Cholesky)";
    type Params = NonrigidParams;

    fn build(params: NonrigidParams, env: &BuildEnv) -> Result<Self, StageError> {
        let mut tracker = Self::new(params)?;
        // The rigid start relights its photometric term with the input's light model.
        tracker.rigid = IcpRgb::with_env(tracker.params.rigid.clone(), env)?;
        Ok(tracker)
    }
}

impl Nonrigid {
    /// A tracker with no history.
    pub fn new(params: NonrigidParams) -> Result<Self, StageError> {
        params.check()?;
        Ok(Self {
            nodes: Nodes::new(params.reach_m),
            rigid: IcpRgb::new(params.rigid.clone()),
            params,
            cache: Cache::default(),
            recent_gains: Default::default(),
            probe: Probe::default(),
            moving: Moving::default(),
        })
    }
}

impl Tracker for Nonrigid {
    fn track(&mut self, frame: &RgbdFrame, model: Option<&ModelView>, t_world_prev: &Iso3, ctx: &mut Context) -> Result<TrackResult, StageError> {
        let warps = frame.depth_source == DepthSource::Measured || self.params.warp_estimated_depth;
        let warps = warps && model.is_some() && !self.probe.skips(self.params.still_probe_every_frames);
        let probe_skipped = self.probe.skipped > 0;
        if probe_skipped {
            ctx.count("nonrigid_probe_skipped", 1.0);
        }
        // The model points read the previous frame's intensity, which registering replaces.
        let clock = std::time::Instant::now();
        let (mut points, mostly_fill_in) = match (model, warps) {
            (Some(m), true) => self.model_points(m, ctx),
            _ => (Vec::new(), false),
        };
        let ms_points = clock.elapsed().as_secs_f64() * 1e3;
        // A clearly moving wall: the joint solve refines the camera at level 0 itself.
        let p = &self.params;
        let coarse = warps && p.camera == CameraMode::Joint && self.moving.shortens(p.gain_window_frames, p.moving_probe_every_frames);
        if coarse {
            ctx.count("nonrigid_coarse_start", 1.0);
        }
        let stop = if coarse { Stop::Coarse { lowest: p.coarse_start_level as usize } } else { Stop::Fine };
        let clock_start = std::time::Instant::now();
        let (rigid, ready) = self.start(frame, model, t_world_prev, stop, warps.then_some(&points[..]), ctx);
        // Wall time of the rigid start and the problem built beside it.
        ctx.count("ms_start", clock_start.elapsed().as_secs_f64() * 1e3);
        if probe_skipped
            && let Ok(r) = &rigid
            && r.status == TrackStatus::Tracked
            && self.probe.observe(r.residual_rms, self.params.still_probe_residual_rise)
        {
            ctx.count("nonrigid_probe_called", 1.0);
        }
        let (rigid, ready) = match (rigid, ready) {
            (Ok(rigid), Some(ready)) if rigid.status != TrackStatus::Lost => (rigid, ready),
            (rigid, ready) => {
                if let Some(ready) = ready {
                    ready.release(&mut self.cache);
                }
                return rigid;
            }
        };
        if self.params.relight
            && let (Some(light), Some(m)) = (self.rigid.light(), model)
        {
            let relit = points::relight(&mut points, light, ctx.rig.camera(), &m.t_world_cam, &rigid.t_world_cam);
            ctx.count("nonrigid_relit_points", relit as f64);
        }
        let Ready { nodes, added, refused, built, ms: ms_ready } = ready;
        self.nodes = nodes;
        if refused > 0 {
            ctx.warn(format!("{refused} model points found no node: the cap max_nodes = {} is reached", self.params.max_nodes));
        }
        ctx.count("nonrigid_nodes_added", added as f64);
        ctx.count("ms_nonrigid_points", ms_points);
        let clock = std::time::Instant::now();
        let outcome = self.solve_on_live(&points, mostly_fill_in, &rigid, !coarse, built, ctx);
        let (rigid, outcome) = match coarse {
            true => match self.finish_coarse(&points, mostly_fill_in, rigid, outcome, ctx) {
                ControlFlow::Continue(solved) => solved,
                ControlFlow::Break(lost) => return Ok(lost),
            },
            false => (rigid, outcome),
        };
        // The solver's time: building its problem (beside the rigid start) and solving it.
        ctx.count("ms_nonrigid_ready", ms_ready);
        ctx.count(capsule_slam_framework::context::WARP_SOLVER_MS, ms_ready + clock.elapsed().as_secs_f64() * 1e3);
        match outcome {
            Ok(Some(result)) => {
                if self.params.camera == CameraMode::Joint {
                    self.rigid.set_last_motion(capsule_slam_framework::geometry::renormalised(t_world_prev.inverse() * result.t_world_cam));
                }
                Ok(result)
            }
            Ok(None) => Ok(rigid.clone()),
            Err(e) => {
                // A failed solve is no evidence of a moving wall.
                self.moving = Moving::default();
                ctx.warn(format!("rigid pose kept, no warp: {e}"));
                ctx.count("nonrigid_fallback", 1.0);
                Ok(rigid)
            }
        }
    }

    /// The rigid start's live pyramid ([`IcpRgb`]'s).
    fn prepare(&mut self, frame: &RgbdFrame, ctx: &mut Context) {
        self.rigid.prepare(frame, ctx);
    }

    /// The rigid start's: its live pyramid, which the joint solve reads, carries the raised σ.
    fn depth_noise_in_use(&self) -> Option<capsule_slam_framework::depth_noise::DepthNoiseModel> {
        self.rigid.depth_noise_in_use()
    }
}

/// A solve's result: the tracking result with the warp, none (the rigid pose stands), or an error.
type Solved = Result<Option<TrackResult>, StageError>;

impl Nonrigid {
    /// The model points of the prediction `m` (`point_stride_px`, `max_incidence_rad`) with their
    /// references in the previous live frame, and the previous frame's fill-in while the
    /// prediction covers less of it than `fill_in_below_share`; whether the fill-in outnumbers
    /// the predicted points.
    fn model_points(&self, m: &ModelView, ctx: &mut Context) -> (Vec<ModelPoint>, bool) {
        let previous = self.rigid.previous_level0();
        let (stride, incidence) = (self.params.point_stride_px as usize, self.params.max_incidence_rad);
        let mut points = points::sample(m, ctx.rig.camera(), previous.map(|l| &l.gray), stride, incidence);
        let mut mostly_fill_in = false;
        if let Some(previous) = previous
            && self.params.fill_in_below_share > 0.0
            && points::predicted_share(m, previous) < self.params.fill_in_below_share
        {
            match points::sample_fill_in(m, previous, stride, incidence) {
                Some(fill) => {
                    ctx.count("nonrigid_fill_in_points", fill.len() as f64);
                    mostly_fill_in = fill.len() > points.len();
                    points.extend(fill);
                }
                None => ctx.warn("fill_in skipped: the prediction and the previous frame differ in size"),
            }
        }
        (points, mostly_fill_in)
    }

    /// The rigid start (the live pyramid and its registration, stopped at `stop`) and, when the
    /// frame warps (`points`), alongside it on the other thread the nodes covering the points
    /// and the problem built on them ([`Ready`]): neither needs the other.
    fn start(
        &mut self,
        frame: &RgbdFrame,
        model: Option<&ModelView>,
        t_world_prev: &Iso3,
        stop: Stop,
        points: Option<&[ModelPoint]>,
        ctx: &mut Context,
    ) -> (Result<TrackResult, StageError>, Option<Ready>) {
        let rigid = &mut self.rigid;
        let mut register = |ctx: &mut Context| {
            let live = rigid.live_pyramid(frame, ctx);
            rigid.register_pyramid(live, frame.depth_source, model, t_world_prev, false, stop, ctx).map(|r| r.0)
        };
        match points {
            Some(points) => {
                let (params, nodes, cache) = (&self.params, &self.nodes, &mut self.cache);
                let (rigid, ready) = rayon::join(|| register(ctx), || Ready::new(nodes, params, cache, points));
                (rigid, Some(ready))
            }
            None => (register(ctx), None),
        }
    }

    /// After a coarse rigid start: drops the unfinished registration when the solve stood;
    /// otherwise finishes the rigid start at level 0 and solves again (the model points stay
    /// relit to the coarse pose). Continues with the rigid result and the solve's, or breaks with
    /// the finished rigid start when it lost track.
    fn finish_coarse(
        &mut self,
        points: &[ModelPoint],
        mostly_fill_in: bool,
        rigid: TrackResult,
        outcome: Solved,
        ctx: &mut Context,
    ) -> ControlFlow<TrackResult, (TrackResult, Solved)> {
        if matches!(outcome, Ok(Some(_))) {
            self.rigid.drop_unfinished();
            return ControlFlow::Continue((rigid, outcome));
        }
        if let Err(e) = &outcome {
            ctx.warn(format!("the joint solve from the coarse rigid start failed ({e}): the rigid start is finished and the frame solved again"));
        }
        ctx.count("nonrigid_coarse_start_finished", 1.0);
        self.moving = Moving::default();
        match self.rigid.finish_fine(ctx) {
            Some(fine) if fine.status == TrackStatus::Lost => ControlFlow::Break(fine),
            Some(fine) => {
                let built = self.build(points);
                let outcome = self.solve_on_live(points, mostly_fill_in, &fine, true, built, ctx);
                ControlFlow::Continue((fine, outcome))
            }
            None => {
                ctx.warn("the coarse rigid start could not be finished at level 0: its pose stands");
                ControlFlow::Continue((rigid, outcome))
            }
        }
    }

    /// [`Nonrigid::solve`] of the `built` problem on the live frame's level, which the rigid
    /// start has made its previous frame (borrowed for the solve).
    fn solve_on_live(
        &mut self,
        points: &[ModelPoint],
        mostly_fill_in: bool,
        rigid: &TrackResult,
        judge: bool,
        built: Option<Result<Built, StageError>>,
        ctx: &mut Context,
    ) -> Solved {
        let Some(pyramid) = self.rigid.take_previous() else {
            problem::release(built, &mut self.cache);
            return Ok(None);
        };
        let level = &pyramid[(self.params.level as usize).min(pyramid.len() - 1)];
        let outcome = self.solve(points, mostly_fill_in, level, rigid, judge, built, ctx);
        self.rigid.restore_previous(pyramid);
        outcome
    }

    /// The joint solve from the rigid result, with the counters and fallback warnings. When the
    /// model points are `mostly_fill_in` (the previous frame's, `fill_in_below_share`), the warp
    /// can explain one frame's motion only, so a still verdict says nothing of the wall and does
    /// not lengthen the still-probe streak. Unless `judge`, the warp is kept without the model
    /// selection (from a coarse rigid start, `moving_probe_every_frames`), and a fallback is
    /// the caller's to tell.
    #[allow(clippy::too_many_arguments)]
    fn solve(
        &mut self,
        points: &[ModelPoint],
        mostly_fill_in: bool,
        level: &Level,
        rigid: &TrackResult,
        judge: bool,
        built: Option<Result<Built, StageError>>,
        ctx: &mut Context,
    ) -> Solved {
        let fit = self.fit_built(points, built, level, &rigid.t_world_cam, judge)?;
        if judge {
            let kept = match &fit {
                Fit::Solved { judged, .. } => judged.unwrap_or(f64::NAN),
                _ => f64::NAN,
            };
            self.moving.judged(kept.is_finite(), kept, 2.0 * self.params.min_rms_gain, self.params.gain_window_frames);
        }
        match fit {
            Fit::Fallback(why) if !judge => {
                ctx.warn(format!("the joint solve from the coarse rigid start fell back ({why}): the rigid start is finished and the frame solved again"));
                Ok(None)
            }
            Fit::Fallback(why) => {
                self.probe = Probe::default();
                ctx.warn(format!("rigid pose kept, no warp: {why}"));
                ctx.count("nonrigid_fallback", 1.0);
                Ok(None)
            }
            Fit::Still(gains, judged) => {
                let p = &self.params;
                if !mostly_fill_in {
                    self.probe.streak += 1;
                }
                // Clearly still: a window of still verdicts, their mean gain and this one's below
                // a quarter of the threshold (a probe that is not clearly still ends the probing).
                let clear = 0.25 * p.min_rms_gain;
                let still = self.probe.streak >= p.gain_window_frames && judged < clear && gains.icp < clear;
                self.probe.verdict(still, (p.still_probe_every_frames, p.still_probe_max_every_frames));
                ctx.count("nonrigid_still", 1.0);
                gains.count(ctx);
                Ok(None)
            }
            Fit::Solved { t_world_cam, warp, outcome, nodes, points, held, .. } => {
                self.probe = Probe::default();
                if held {
                    ctx.count("nonrigid_camera_held", 1.0);
                }
                ctx.count("nonrigid_nodes", nodes as f64);
                let moved = rigid.t_world_cam.inverse() * t_world_cam;
                ctx.count("nonrigid_camera_step_mm", moved.translation.vector.norm() * 1e3);
                ctx.count("nonrigid_camera_step_deg", moved.rotation.angle().to_degrees());
                Gains::of(&outcome).count(ctx);
                ctx.count("nonrigid_points", points as f64);
                ctx.count("nonrigid_iterations", outcome.iterations as f64);
                ctx.count("nonrigid_factorisations", outcome.factorisations as f64);
                ctx.count("nonrigid_analyses", outcome.analyses as f64);
                ctx.count("ms_nonrigid_setup", outcome.ms_setup);
                ctx.count("ms_nonrigid_analyse", outcome.ms_analyse);
                ctx.count("ms_nonrigid_assemble", outcome.ms_assemble);
                ctx.count("ms_nonrigid_factor", outcome.ms_factor);
                ctx.count("ms_nonrigid_problem", outcome.ms_problem);
                Ok(Some(TrackResult {
                    t_world_cam,
                    status: TrackStatus::Tracked,
                    inliers: outcome.inliers,
                    residual_rms: outcome.icp_rms_m,
                    covariance: rigid.covariance,
                    iterations: rigid.iterations + outcome.iterations,
                    warp: Some(warp),
                }))
            }
        }
    }

    /// Covers `points` with nodes (none kept from before need cover them) and fits: one
    /// registration of a model to a view, as the `deformation` closer's through the warp.
    pub(crate) fn fit_fresh(&mut self, points: &[ModelPoint], level: &Level, t_start: &Iso3) -> Result<Fit, StageError> {
        self.nodes.cover(points, self.params.node_spacing_m, self.params.max_nodes as usize);
        self.fit(points, level, t_start, true)
    }

    /// Fits the warp and the pose from `t_start` to the live `level`, the model `points` bound to
    /// the nodes near them; moves the nodes when it succeeds. Unless `judge`, the warp is kept
    /// without the model selection, and the camera is never held at `t_start` (a coarse start,
    /// `moving_probe_every_frames`: a step too large falls back instead).
    pub(crate) fn fit(&mut self, points: &[ModelPoint], level: &Level, t_start: &Iso3, judge: bool) -> Result<Fit, StageError> {
        let built = self.build(points);
        self.fit_built(points, built, level, t_start, judge)
    }

    /// The problem of `points` on the nodes, prepared ([`problem::build`]).
    fn build(&mut self, points: &[ModelPoint]) -> Option<Result<Built, StageError>> {
        problem::build(&self.nodes, &self.params, &mut self.cache, points)
    }

    /// The frame's problem: the nodes with at least `min_points_per_node` model points (their
    /// indices), the points bound to them, the graph with its edges; and every node's point
    /// count. `None` when no node has enough points.
    #[cfg(test)]
    pub(crate) fn problem(&self, points: &[ModelPoint]) -> Option<(Problem, Vec<usize>, Vec<usize>)> {
        problem::problem_of(&self.nodes, &self.params, points, None)
    }

    /// [`Nonrigid::fit`] of the problem `build` made of `points` on the nodes (`None`: no node has
    /// enough points).
    fn fit_built(
        &mut self,
        points: &[ModelPoint],
        built: Option<Result<Built, StageError>>,
        level: &Level,
        t_start: &Iso3,
        judge: bool,
    ) -> Result<Fit, StageError> {
        let Some(built) = built else {
            return Ok(Fit::Fallback("no node has enough model points".into()));
        };
        let Built { mut problem, solve_ids, used, prepared, ms_problem } = built?;
        let p = &self.params;
        let mut outcome = problem.solve_prepared(points, prepared, level, t_start, &p.weights(), &mut self.cache)?;
        let mut held = false;
        if judge && problem.camera && p.hold_camera_on_step && self.camera_step_too_large(t_start, &outcome.t_world_cam) {
            // The warp again from the identity, the camera held at the rigid start.
            for n in &mut problem.graph.deformation.nodes {
                *n = DeformationNode::identity(n.position_m, n.time);
            }
            problem.camera = false;
            outcome = problem.solve(points, level, t_start, &p.weights(), &mut self.cache)?;
            held = true;
        }
        outcome.ms_problem = ms_problem;
        let share = outcome.inliers as f64 / points.len().max(1) as f64;
        let mut d = problem.graph.deformation;
        if p.factor_common {
            let weights: Vec<f64> = solve_ids.iter().map(|&i| used[i] as f64).collect();
            factor_common(&mut d, &weights);
        }
        let (_, max_step) = d.node_displacement_m();
        if share < p.min_point_share || !outcome.icp_rms_m.is_finite() {
            return Ok(Fit::Fallback(format!(
                "{:.0} % of the model points found the live wall (min_point_share {:.0} %)",
                100.0 * share,
                100.0 * p.min_point_share
            )));
        }
        if max_step > p.max_step_m {
            return Ok(Fit::Fallback(format!("a node would move {:.2} mm in one frame (max_step_m {:.2} mm)", max_step * 1e3, p.max_step_m * 1e3)));
        }
        if self.camera_step_too_large(t_start, &outcome.t_world_cam) {
            let moved = t_start.inverse() * outcome.t_world_cam;
            let (shift, turn) = (moved.translation.vector.norm(), moved.rotation.angle());
            return Ok(Fit::Fallback(format!(
                "the joint solve would move the camera {:.2} mm / {:.2}° from the rigid start (max_camera_step_m {:.2} mm, max_camera_step_rad {:.3})",
                shift * 1e3,
                turn.to_degrees(),
                p.max_camera_step_m * 1e3,
                p.max_camera_step_rad
            )));
        }
        // Model selection: the warp must lower the point-to-plane residual by a share, and by
        // more than its unknowns (12 or 6 per node) would by fitting noise (the gain in χ² measured
        // against the fitted residual, an AIC-like test with `min_evidence` per unknown). The
        // photometric gain is reported, not tested: it is alike on still and moving walls
        // (`docs/results/nonrigid.md`).
        let (r1, r0) = outcome.icp_common_rms_m;
        let gain_chi2 = outcome.inliers as f64 * ((r0 * r0) / (r1 * r1).max(1e-30) - 1.0);
        let gains = Gains::of(&outcome);
        let judged = if judge { Some(windowed_gain(&mut self.recent_gains, gains.icp, p.gain_window_frames)) } else { None };
        if let Some(judged) = judged
            && (judged < p.min_rms_gain || gain_chi2 < p.min_evidence * (p.node_model.unknowns() * solve_ids.len()) as f64)
        {
            return Ok(Fit::Still(gains, judged));
        }
        // The map leads the moving wall by a share of this frame's solved motion (`warp_lead`).
        if p.warp_lead > 0.0 {
            for n in &mut d.nodes {
                n.translation_m *= 1.0 + p.warp_lead;
            }
        }
        for (s, &i) in solve_ids.iter().enumerate() {
            let (node, dn) = (&mut self.nodes.nodes[i], &d.nodes[s]);
            node.position_m += dn.translation_m;
            node.normal = d.warp_normal_with(&node.normal, &[(s, 1.0)]);
        }
        self.nodes.rebin();
        Ok(Fit::Solved { t_world_cam: outcome.t_world_cam, warp: d, nodes: solve_ids.len(), points: problem.points.len(), outcome, held, judged })
    }

    /// Whether the solve moved the camera from the rigid start `t_start` farther than
    /// `max_camera_step_m` or `max_camera_step_rad` (or to a pose that is not finite).
    fn camera_step_too_large(&self, t_start: &Iso3, t_world_cam: &Iso3) -> bool {
        let moved = t_start.inverse() * t_world_cam;
        let (shift, turn) = (moved.translation.vector.norm(), moved.rotation.angle());
        !(shift.is_finite() && turn.is_finite()) || shift > self.params.max_camera_step_m || turn > self.params.max_camera_step_rad
    }
}

/// Removes from every node the rigid motion that best explains the nodes' displacements
/// (weighted Kabsch; OpenCV dynafu's `factorCommon`): what moves every node alike is the
/// camera's to explain, so the warp never carries the map along with a camera error.
fn factor_common(d: &mut Deformation, weights: &[f64]) {
    let from: Vec<nalgebra::Point3<f64>> = d.nodes.iter().map(|n| n.position_m).collect();
    let to: Vec<nalgebra::Point3<f64>> = d.nodes.iter().map(|n| n.position_m + n.translation_m).collect();
    let Some(g) = capsule_slam_framework::geometry::kabsch_weighted(&from, &to, weights) else { return };
    let g_inv = g.inverse();
    let r_inv = *g_inv.rotation.to_rotation_matrix().matrix();
    for n in &mut d.nodes {
        let moved = g_inv * (n.position_m + n.translation_m);
        n.rotation = r_inv * n.rotation;
        n.translation_m = moved - n.position_m;
    }
}

register!(Tracker, Nonrigid);
