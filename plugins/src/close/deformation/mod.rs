//! `deformation`: local loop closure between the active and the inactive model and the
//! non-rigid correction of the map by an embedded deformation graph (the paper's "Deformation
//! graph" and "Loop closure"; ElasticFusion, `shared/design/elasticfusion.md` §4–5).
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
//!    `max_nodes`), optimised ([`graph`]) and returned with the corrected pose. The pipeline
//!    deforms the map (positions and normals) and the trajectory; the fuser reactivates the
//!    inactive surfels seen from the corrected pose.
//!
//! Influence and edges follow ElasticFusion's time windows (`window`), so an old surface and
//! the new one that meets it are moved by their own nodes.

pub mod detect;
pub mod graph;

use capsule_slam_framework::deformation::{Deformation, DeformationNode, SurfelTime, Window};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stage::{LoopClosure, LoopInput};
use capsule_slam_framework::{Context, Fuser, Iso3, LoopCloser, Plugin, StageError, register};

pub use detect::Reference;
use detect::{Registration, constraints, median_t0, register_models, samples};
use graph::{Edges, Graph, GraphWeights};

/// The time of an active constraint point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ActiveTime {
    /// The current frame (ElasticFusion).
    Now,
    /// The time of the active surfel the point samples.
    Surfel,
}

/// What `window` counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WindowUnit {
    /// Nodes nearest in time (ElasticFusion).
    Nodes,
    /// Frames either side of the point's time.
    Frames,
}

capsule_slam_framework::plugin_params! {
    /// Parameters of `deformation`.
    pub struct DeformationParams {
        /// Influencing nodes per point, k (ElasticFusion: 4).
        pub k: u32 = 4; unit = "-"; range = 1.0..=16.0;
        /// Candidate nodes per point, nearest in time (ElasticFusion: 20 nodes), in
        /// `window_unit`s.
        pub window: u32 = 20; unit = "nodes or frames"; range = 1.0..=1.0e7;
        /// `nodes` (ElasticFusion: the `window` nodes nearest in time) or `frames` (the nodes
        /// within `window` frames of the point's time).
        pub window_unit: WindowUnit = WindowUnit::Nodes; unit = "-";
        /// The time that places nodes and surfels in the window: `created` (t0, ElasticFusion) or
        /// `last-seen` (t: a surface still in view moves with the camera that tracks it).
        pub surfel_time: SurfelTime = SurfelTime::Created; unit = "-";
        /// Graph edges per node (ElasticFusion: 4).
        pub connectivity: u32 = 4; unit = "-"; range = 1.0..=16.0;
        /// `space-in-window` (the nearest nodes in space among the time window) or `time`
        /// (ElasticFusion: the nearest in time order).
        pub edges: Edges = Edges::SpaceInWindow; unit = "-";
        /// Most graph nodes (ElasticFusion: 1024, one per 5000 surfels).
        pub max_nodes: u32 = 1024; unit = "nodes"; range = 5.0..=100000.0;
        /// Fewest surfels per node.
        pub min_surfels_per_node: u32 = 50; unit = "surfels"; range = 1.0..=1.0e7;
        /// w_rot (ElasticFusion: 1).
        pub w_rot: f64 = 1.0; unit = "-"; range = 0.0..=1.0e9;
        /// w_reg (ElasticFusion: 10).
        pub w_reg: f64 = 10.0; unit = "-"; range = 0.0..=1.0e9;
        /// w_con (ElasticFusion: 100).
        pub w_con: f64 = 100.0; unit = "-"; range = 0.0..=1.0e9;
        /// Position residuals are divided by this (ElasticFusion: 1 m implicitly, room scale).
        pub length_unit_m: f64 = 0.01; unit = "m"; range = 1.0e-6..=100.0;
        /// Most Gauss-Newton iterations of the graph (ElasticFusion: 3).
        pub iterations: u32 = 5; unit = "-"; range = 1.0..=100.0;
        /// Surface constraints every this many pixels of the active view in x and y
        /// (ElasticFusion: 20 px at 640×480, 768 samples).
        pub constraint_stride_px: u32 = 10; unit = "px"; range = 1.0..=200.0;
        /// Pin the reference surface at each constraint (ElasticFusion: first closure only,
        /// plus freezing older nodes).
        pub pins: bool = true; unit = "-";
        /// Accept a loop only after this many consecutive frames whose registrations pass every
        /// check and agree on the correction (1: the frame's own registration, ElasticFusion).
        pub consistent_frames: u32 = 1; unit = "frames"; range = 1.0..=100.0;
        /// Consecutive corrections agree when they move the view's surface samples by less than
        /// this on average.
        pub max_correction_change_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// The time of an active constraint point: `now` (ElasticFusion: the current frame) or
        /// `surfel` (the time of the active surfel it samples).
        pub active_time: ActiveTime = ActiveTime::Now; unit = "-";
        /// Hold the nodes of surfels unseen for more than this many frames at the identity (0:
        /// none; δt: every inactive node, the closure moves only the active model).
        pub freeze_unseen_frames: u32 = 0; unit = "frames"; range = 0.0..=1.0e7;
        /// Which model stays: `old` (ElasticFusion: the active surface and the camera move onto
        /// the inactive one) or `recent` (the inactive surface moves onto the current view).
        pub reference: Reference = Reference::Old; unit = "-";
        /// Reject when the inactive model covers less than this share of the active view.
        pub min_overlap: f64 = 0.2; unit = "-"; range = 0.0..=1.0;
        /// Reject when fewer than this share of the active pixels are ICP inliers
        /// (ElasticFusion: 35 000 of 307 200 pixels).
        pub min_inlier_share: f64 = 0.15; unit = "-"; range = 0.0..=1.0;
        /// Reject when the ICP RMS residual exceeds this (ElasticFusion: 5e-5 mean squared,
        /// about 1 cm RMS at room scale).
        pub max_residual_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when a translation standard deviation of T_est exceeds this (ElasticFusion:
        /// covariance diagonals < 1e-5).
        pub max_std_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when a rotation standard deviation of T_est exceeds this.
        pub max_std_rad: f64 = 0.01; unit = "rad"; range = 0.0..=3.15;
        /// Reject when the correction moves the camera farther than this (a local loop
        /// closure corrects drift, not relocalises).
        pub max_correction_m: f64 = 0.005; unit = "m"; range = 0.0..=1.0;
        /// Reject a correction below this (nothing to close: the graph's own interpolation error
        /// is of this order). Phantom preset 5, sensor depth, `delta_t = 60`, rigid / 2 mm wall
        /// motion, ATE and surface RMSE mm: 0.1 mm: 0.53, 0.17 / 2.92, 1.14; 0.5 mm: 0.34, 0.10 /
        /// 2.92, 1.14; 1 mm: 0.52, 0.16 / 3.82, 1.06 (no closer: 0.41, 0.08 / 3.37, 1.18).
        pub min_correction_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when the two models already agree: their ICP RMS residual at the tracked pose,
        /// before any correction, is below this (a closure would bend the map by more than it
        /// disagrees).
        pub min_disagreement_m: f64 = 0.0; unit = "m"; range = 0.0..=1.0;
        /// Reject when the ICP residual after the correction is above this share of the one
        /// before it (the correction does not explain the data: the registration slid).
        pub max_residual_ratio: f64 = 0.5; unit = "-"; range = 0.0..=1.0e6;
        /// Noise scale of the registration's point-to-plane residual (model depths are fused,
        /// hence measured-like).
        pub sigma_icp_m: f64 = 0.0003; unit = "m"; range = 1.0e-7..=1.0;
        /// Weight of the registration's photometric term.
        pub w_rgb: f64 = 0.1; unit = "-"; range = 0.0..=1000.0;
        /// Registration ICP correspondence gate.
        pub icp_gate_m: f64 = 0.004; unit = "m"; range = 0.0..=1.0;
    }
}

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
        // A streak of consecutive frames whose registrations pass the checks and agree on the
        // world correction: one frame's registration can slide, a loop stays put.
        if self.streak.last().is_some_and(|(f, _)| *f + 1 != now) {
            self.streak.clear();
        }
        let Some(t_est) = reg.accepted else {
            self.streak.clear();
            if let Some(check) = reg.rejected {
                ctx.count("rejected", 1.0);
                ctx.count(&format!("rejected_{check}"), 1.0);
            }
            return Ok(None);
        };
        let c = t_est * input.t_world_cam.inverse();
        let change = self.streak.last().map(|(_, prev)| mean_displacement_m(prev, &c, &samples));
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
            return Ok(None);
        }
        self.streak.clear();
        let clock = std::time::Instant::now();
        let Some(then) = median_t0(&samples) else { return Ok(None) };
        ctx.count("loop_age_frames", now.saturating_sub(then as usize) as f64);
        let cons = constraints(&samples, |_| c, (p.active_time == ActiveTime::Now).then_some(now as u32), p.pins, p.reference);
        let snap = map.snapshot()?;
        let step = snap.len().div_ceil(p.max_nodes as usize).max(p.min_surfels_per_node as usize).max(1);
        let mut surfels: Vec<&capsule_slam_framework::Surfel> = snap.surfels.iter().collect();
        if p.surfel_time == SurfelTime::LastSeen {
            // Sampled evenly over last sightings, as ElasticFusion samples over creation.
            surfels.sort_by_key(|s| s.t);
        }
        let sampled: Vec<&capsule_slam_framework::Surfel> = surfels.into_iter().step_by(step).collect();
        if sampled.len() <= p.k as usize || cons.is_empty() {
            ctx.count("rejected", 1.0);
            return Ok(None);
        }
        let nodes: Vec<DeformationNode> = sampled.iter().map(|s| DeformationNode::identity(s.position_m.cast(), p.surfel_time.of(s))).collect();
        let window = match p.window_unit {
            WindowUnit::Nodes => Window::Nodes(p.window as usize),
            WindowUnit::Frames => Window::Frames(p.window),
        };
        let deformation = Deformation::new(nodes, p.k as usize, window).timed_by(p.surfel_time);
        let mut graph = Graph::new(deformation, p.connectivity as usize, p.edges);
        if p.freeze_unseen_frames > 0 {
            // Sampling order is time order already, so node i is sampled[i].
            let mut frozen = 0;
            for (i, s) in sampled.iter().enumerate() {
                if (now as u32).saturating_sub(s.t) > p.freeze_unseen_frames {
                    graph.fix(i);
                    frozen += 1;
                }
            }
            ctx.count("nodes_frozen", f64::from(frozen));
        }
        for c in cons {
            graph.constrain(c);
        }
        let solution = graph.optimise(&self.weights())?;
        ctx.count("ms_graph", clock.elapsed().as_secs_f64() * 1e3);
        let (moved, held) = fit_in_view(&graph.deformation, &snap, input, &c, cam);
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
    let t_cam_world = input.t_world_cam.inverse();
    let (mut a, mut na, mut i, mut ni) = (0.0, 0usize, 0.0, 0usize);
    for s in &snap.surfels {
        let p = s.position_m.cast::<f64>();
        let q = t_cam_world * p;
        let Some(uv) = cam.project(&q) else { continue };
        let (x, y) = (uv.x.round(), uv.y.round());
        if q.z <= 0.0 || x < 0.0 || y < 0.0 || x as usize >= input.active.depth_m.width() || y as usize >= input.active.depth_m.height() {
            continue;
        }
        let (x, y) = (x as usize, y as usize);
        let warped = {
            let mut w = *s;
            d.warp_surfel(&mut w);
            w.position_m.cast::<f64>()
        };
        if (f64::from(input.active.depth_m.at(x, y)) - q.z).abs() < 2e-4 {
            a += (warped - c * p).norm();
            na += 1;
        } else if (f64::from(input.inactive.depth_m.at(x, y)) - q.z).abs() < 2e-4 {
            i += (warped - p).norm();
            ni += 1;
        }
    }
    (a / na.max(1) as f64, i / ni.max(1) as f64)
}

/// Mean distance between where two world corrections put the active samples.
fn mean_displacement_m(a: &Iso3, b: &Iso3, samples: &[detect::Sample]) -> f64 {
    if samples.is_empty() {
        return (a.translation.vector - b.translation.vector).norm();
    }
    samples.iter().map(|s| (a * s.active_m - b * s.active_m).norm()).sum::<f64>() / samples.len() as f64
}

register!(LoopCloser, DeformationCloser);

#[cfg(test)]
mod graph_tests;
#[cfg(test)]
mod tests;
