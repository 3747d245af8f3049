//! `deformation`: local loop closure between the active and the inactive model and the
//! non-rigid correction of the map by an embedded deformation graph (the paper's "Deformation
//! graph" and "Loop closure"; ElasticFusion, Whelan et al. 2016, IJRR 35(14), Sec. 4–5).
//!
//! Every tracked frame, with the active and inactive predictions rendered at the tracked pose T:
//! 1. registration: the active prediction plays the live frame and the inactive one the model,
//!    in a fresh `icp-rgb` (no motion prior, photometric reference = the model) started at T;
//!    result T_est ([`detect`]);
//! 2. checks (organ-scale parameters): the inactive model overlaps the active view, enough ICP
//!    inliers, a small residual, a well-determined pose (covariance), a small correction;
//! 3. on acceptance: surface constraints on a grid of the view where both models have a surface,
//!    and pins on the reference model (`reference`: `old`, ElasticFusion's choice, moves the
//!    active surface and the camera onto the inactive one; `recent` moves the inactive surface
//!    onto the current view, the camera stays), each point at the creation time of the surfel it
//!    samples; the graph is sampled from the map (every n-th surfel in time order, at most
//!    `max_nodes`), optimised ([`graph`]) and returned with the corrected pose, unless the
//!    optimisation could not lower the graph's energy (the map would stay and the camera move
//!    alone: rejected, counter `rejected_graph`). The pipeline
//!    deforms the map (positions and normals) and the trajectory; the fuser reactivates the
//!    inactive surfels seen from the corrected pose.
//!
//! Influence and edges follow ElasticFusion's time windows (`window`), so an old surface and
//! the new one that meets it are moved by their own nodes.

pub mod detect;
mod params;
pub mod warped;

use capsule_slam_framework::deformation::{Deformation, DeformationNode, PoseWarp, SurfelTime, Window};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stage::{LoopClosure, LoopInput};
use capsule_slam_framework::{Context, Fuser, Iso3, LoopCloser, Plugin, StageError, Surfel, SurfelSet, register};

use crate::common::ed_graph::{Graph, GraphWeights};
use detect::{Registration, Sample, constraints, median_t0, register_models, samples};
pub use params::{DeformationParams, Freeze, PoseWarpKind, Reference, WindowUnit};

/// The local loop closer.
pub struct DeformationCloser {
    params: DeformationParams,
    /// World corrections of the last consecutive registrations that passed the checks, newest
    /// last (frame index, `T_est T⁻¹`).
    streak: Vec<(usize, Iso3)>,
}

impl Plugin for DeformationCloser {
    const NAME: &'static str = "deformation";
    const SUMMARY: &'static str = "local loop closure (active vs inactive model registered by icp-rgb, organ-scale checks) and embedded deformation graph (E_rot + E_reg + E_con, faer sparse Cholesky)";
    type Params = DeformationParams;

    fn build(params: DeformationParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self::new(params))
    }
}

impl DeformationCloser {
    /// The closer with these parameters.
    pub fn new(params: DeformationParams) -> Self {
        Self { params, streak: Vec::new() }
    }

    fn weights(&self) -> GraphWeights {
        let p = &self.params;
        GraphWeights { rot: p.w_rot, reg: p.w_reg, con: p.w_con, length_unit_m: p.length_unit_m, iterations: p.iterations as usize }
    }
}

impl LoopCloser for DeformationCloser {
    fn close(&mut self, input: &LoopInput<'_>, map: &dyn Fuser, ctx: &mut Context) -> Result<Option<LoopClosure>, StageError> {
        let p = &self.params;
        let now = input.frame.index;
        let cam = ctx.rig.camera();
        let clock = std::time::Instant::now();
        let reg: Registration = register_models(input.active, input.inactive, input.t_world_cam, p, ctx)?;
        ctx.count("ms_registration", clock.elapsed().as_secs_f64() * 1e3);
        ctx.count("overlap", reg.overlap);
        let samples = samples(input.active, input.inactive, input.t_world_cam, p.constraint_stride_px as usize, p.surfel_time, cam);
        let Some((t_est, c)) = self.confirm(&reg, &samples, now, input.t_world_cam, ctx) else { return Ok(None) };
        let p = &self.params;
        let clock = std::time::Instant::now();
        let Some(then) = median_t0(&samples) else { return Ok(None) };
        ctx.count("loop_age_frames", now.saturating_sub(then as usize) as f64);
        let cons = constraints(&samples, |_| c, now as u32, p.pins, p.reference, reg.warp.as_ref());
        if reg.warp.is_some() {
            ctx.count("through_warp", 1.0);
        }
        let snap_clock = std::time::Instant::now();
        let snap = map.snapshot()?;
        ctx.count("ms_snapshot", snap_clock.elapsed().as_secs_f64() * 1e3);
        let graph = if cons.is_empty() { None } else { self.graph(&snap, map.active_window(), now, ctx) };
        let Some(mut graph) = graph else {
            ctx.count("rejected", 1.0);
            return Ok(None);
        };
        for c in cons {
            graph.constrain(c);
        }
        let solution = graph.optimise(&self.weights())?;
        ctx.count("ms_graph", clock.elapsed().as_secs_f64() * 1e3);
        // A graph that cannot lower its energy (or gives no number) leaves the map where it is: applying the
        // closure would move the camera alone, off the map it is looking at.
        if solution.energy_after.partial_cmp(&solution.energy_before) != Some(std::cmp::Ordering::Less) {
            ctx.warn(format!(
                "a loop was found but the deformation graph could not bend the map toward it (energy {:.4} before, {:.4} after): not closed",
                solution.energy_before, solution.energy_after
            ));
            ctx.count("rejected", 1.0);
            ctx.count("rejected_graph", 1.0);
            return Ok(None);
        }
        let clock = std::time::Instant::now();
        let (moved, held) = fit_in_view(&graph.deformation, &snap, input, &c, cam);
        ctx.count("ms_fit_in_view", clock.elapsed().as_secs_f64() * 1e3);
        ctx.count("active_misfit_mm", moved * 1e3);
        ctx.count("inactive_shift_mm", held * 1e3);
        ctx.count("nodes", graph.deformation.nodes.len() as f64);
        ctx.count("constraints", graph.constraints() as f64);
        ctx.count("energy_before", solution.energy_before);
        ctx.count("energy_after", solution.energy_after);
        ctx.count("accepted", 1.0);
        let t_world_cam = match p.reference {
            Reference::Old => t_est,
            Reference::Recent => *input.t_world_cam,
        };
        Ok(Some(LoopClosure { deformation: graph.deformation, t_world_cam }))
    }
}

impl DeformationCloser {
    /// A streak of consecutive frames whose registrations pass the checks and agree on the
    /// world correction (one frame's registration can slide, a loop stays put): the estimated
    /// pose and the world correction `C` once the streak is `consistent_frames` long.
    fn confirm(&mut self, reg: &Registration, samples: &[Sample], now: usize, t_world_cam: &Iso3, ctx: &mut Context) -> Option<(Iso3, Iso3)> {
        let p = &self.params;
        if self.streak.last().is_some_and(|(f, _)| *f + 1 != now) {
            self.streak.clear();
        }
        let Some(t_est) = reg.accepted else {
            self.streak.clear();
            if let Some(check) = reg.rejected {
                ctx.count("rejected", 1.0);
                ctx.count(&format!("rejected_{check}"), 1.0);
            }
            return None;
        };
        let c = t_est * t_world_cam.inverse();
        let change = self.streak.last().map(|(_, prev)| mean_displacement_m(prev, &c, samples));
        if let Some(d) = change {
            ctx.count("correction_change_mm", d * 1e3);
        }
        if change.is_some_and(|d| d > p.max_correction_change_m) {
            self.streak.clear();
        }
        self.streak.push((now, c));
        if self.streak.len() < p.consistent_frames as usize {
            ctx.count("rejected", 1.0);
            ctx.count("rejected_unconfirmed", 1.0);
            return None;
        }
        self.streak.clear();
        Some((t_est, c))
    }

    /// The deformation graph of the whole map: nodes sampled evenly from the snapshot (over last
    /// sightings with `surfel_time = "last-seen"`, as ElasticFusion samples over creation), the
    /// inactive model's nodes held with `freeze = "inactive"`; `None` when the map is too small
    /// for `k` neighbours.
    fn graph(&self, snap: &SurfelSet, active_window: Option<u32>, now: usize, ctx: &mut Context) -> Option<Graph> {
        let p = &self.params;
        let step = snap.len().div_ceil(p.max_nodes as usize).max(p.min_surfels_per_node as usize).max(1);
        let mut surfels: Vec<&Surfel> = snap.surfels.iter().collect();
        if p.surfel_time == SurfelTime::LastSeen {
            surfels.sort_by_key(|s| s.t);
        }
        let sampled: Vec<&Surfel> = surfels.into_iter().step_by(step).collect();
        if sampled.len() <= p.k as usize {
            return None;
        }
        let nodes: Vec<DeformationNode> = sampled.iter().map(|s| DeformationNode::identity(s.position_m.cast(), p.surfel_time.of(s))).collect();
        let window = match p.window_unit {
            WindowUnit::Nodes => Window::Nodes(p.window as usize),
            WindowUnit::Frames => Window::Frames(p.window),
        };
        let pose_warp = match p.pose_warp {
            PoseWarpKind::Position => PoseWarp::Position,
            PoseWarpKind::View => PoseWarp::View { depth_m: p.pose_view_depth_m },
        };
        let deformation = Deformation::new(nodes, p.k as usize, window).timed_by(p.surfel_time).poses_by(pose_warp);
        let mut graph = Graph::new(deformation, p.connectivity as usize, p.edges);
        if let (Freeze::Inactive, Some(delta_t)) = (p.freeze, active_window) {
            // Sampling order is time order already, so node i is sampled[i].
            let mut frozen = 0;
            for (i, s) in sampled.iter().enumerate() {
                if !s.is_active(now as u32, delta_t) {
                    graph.fix(i);
                    frozen += 1;
                }
            }
            ctx.count("nodes_frozen", f64::from(frozen));
        }
        Some(graph)
    }
}

/// How well the deformation does what the closure asked, on the surfels that make up the two
/// predictions: the mean distance of the visible active surfels from `C p` and of the visible
/// inactive surfels from where they were.
fn fit_in_view(
    d: &Deformation,
    snap: &capsule_slam_framework::SurfelSet,
    input: &LoopInput<'_>,
    c: &Iso3,
    cam: &capsule_slam_framework::camera::PinholeCamera,
) -> (f64, f64) {
    use rayon::prelude::*;
    let t_cam_world = input.t_world_cam.inverse();
    let (w, h) = input.active.depth_m.size();
    let warper = d.warper();
    // Every 4th surfel is plenty for a mean.
    let (a, na, i, ni) = snap
        .surfels
        .par_iter()
        .step_by(4)
        .filter_map(|s| {
            let p = s.position_m.cast::<f64>();
            let q = t_cam_world * p;
            let uv = cam.project(&q)?;
            let (x, y) = (uv.x.round(), uv.y.round());
            if q.z <= 0.0 || x < 0.0 || y < 0.0 || x as usize >= w || y as usize >= h {
                return None;
            }
            let (x, y) = (x as usize, y as usize);
            let mut moved = *s;
            warper.warp_surfel(&mut moved);
            let warped = moved.position_m.cast::<f64>();
            if (f64::from(input.active.depth_m.at(x, y)) - q.z).abs() < 2e-4 {
                Some(((warped - c * p).norm(), 1usize, 0.0, 0usize))
            } else if (f64::from(input.inactive.depth_m.at(x, y)) - q.z).abs() < 2e-4 {
                Some((0.0, 0, (warped - p).norm(), 1))
            } else {
                None
            }
        })
        .reduce(|| (0.0, 0, 0.0, 0), |x, y| (x.0 + y.0, x.1 + y.1, x.2 + y.2, x.3 + y.3));
    (a / na.max(1) as f64, i / ni.max(1) as f64)
}

/// Mean distance between where two world corrections put the active samples.
fn mean_displacement_m(a: &Iso3, b: &Iso3, samples: &[Sample]) -> f64 {
    if samples.is_empty() {
        return (a.translation.vector - b.translation.vector).norm();
    }
    samples.iter().map(|s| (a * s.active_m - b * s.active_m).norm()).sum::<f64>() / samples.len() as f64
}

register!(LoopCloser, DeformationCloser);

#[cfg(test)]
mod tests;
