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

use capsule_slam_framework::deformation::{Deformation, DeformationNode, PoseWarp, SurfelTime, Window};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stage::{LoopClosure, LoopInput};
use capsule_slam_framework::{Context, Fuser, Iso3, LoopCloser, Plugin, StageError, register};

pub use detect::Reference;
use detect::{Registration, constraints, median_t0, register_models, samples};
use graph::{Edges, Graph, GraphWeights};

/// How camera poses follow the deformation (see [`PoseWarp`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PoseWarpKind {
    /// The camera centre as a point (ElasticFusion).
    Position,
    /// The points in front of the camera.
    View,
}

/// Which graph nodes a closure may move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Freeze {
    /// Every node is free (the correction spreads over the whole time line).
    None,
    /// Nodes of inactive surfels (by the fuser's δt) stay: the closure moves the active model
    /// onto the inactive one and leaves the rest of the old map where it is (ElasticFusion
    /// freezes the nodes older than its last local closure).
    Inactive,
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
        /// Candidate nodes per point, in `window_unit`s (ElasticFusion: 20 nodes).
        pub window: u32 = 10; unit = "frames or nodes"; range = 1.0..=1.0e7;
        /// `frames` (the nodes within `window` frames of the point's time) or `nodes`
        /// (ElasticFusion: the `window` nodes nearest in time; the first frame alone holds ~150
        /// of 1024 nodes, all of time 0, so 20 of them are picked by position order, a strip).
        pub window_unit: WindowUnit = WindowUnit::Frames; unit = "-";
        /// The time that places nodes and surfels in the window: `last-seen` (t: a surface still
        /// in view moves with the camera that tracks it, whenever it was created) or `created`
        /// (t0, ElasticFusion: the active surface in view mixes old and new t0 and tears).
        pub surfel_time: SurfelTime = SurfelTime::LastSeen; unit = "-";
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
        /// check and agree on the correction (ElasticFusion: 1, the frame's own registration;
        /// ORB-SLAM asks 3 consecutive keyframes). One frame's registration slides along the
        /// tube or follows the wave; a loop stays put.
        pub consistent_frames: u32 = 3; unit = "frames"; range = 1.0..=100.0;
        /// Consecutive corrections agree when they move the view's surface samples by less than
        /// this on average.
        pub max_correction_change_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// How the trajectory follows the map: `position` (ElasticFusion: the camera centre
        /// warped as a point) or `view` (the rigid motion of points `pose_view_depth_m` in front
        /// of the camera).
        pub pose_warp: PoseWarpKind = PoseWarpKind::View; unit = "-";
        /// Distance of the points a pose follows with `pose_warp = "view"` (the phantom's wall
        /// is 10–30 mm from the capsule).
        pub pose_view_depth_m: f64 = 0.02; unit = "m"; range = 1.0e-4..=10.0;
        /// Nodes held in place: `inactive` (every node of an inactive surfel) or `none`.
        pub freeze: Freeze = Freeze::Inactive; unit = "-";
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
        /// closure corrects drift, not relocalises; larger bends go through few nodes and
        /// extrapolate: 5 mm let through 3.7–4 mm closures that cost preset 2 with 4 mm wall
        /// motion 10–29 % surface RMSE).
        pub max_correction_m: f64 = 0.003; unit = "m"; range = 0.0..=1.0;
        /// Reject a correction below this (nothing to close: the graph's own interpolation error
        /// is of this order). Phantom preset 5, sensor depth, `delta_t = 60`, rigid / 2 mm wall
        /// motion, ATE and surface RMSE mm: 0.1 mm: 0.53, 0.17 / 2.92, 1.14; 0.5 mm: 0.34, 0.10 /
        /// 2.92, 1.14; 1 mm: 0.52, 0.16 / 3.82, 1.06 (no closer: 0.41, 0.08 / 3.37, 1.18).
        pub min_correction_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when the two models already agree: their ICP RMS residual at the tracked pose,
        /// before any correction, is below this (a closure would bend the map by more than it
        /// disagrees). Fused models of the same wall agree to 0.02–0.2 mm; rigid phantom preset 5
        /// closed at 0.13 mm and lost 29 % surface RMSE, preset 3 closed at 0.3 mm and gained 26 %.
        pub min_disagreement_m: f64 = 0.00025; unit = "m"; range = 0.0..=1.0;
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
        let cons = constraints(&samples, |_| c, now as u32, p.pins, p.reference);
        let snap_clock = std::time::Instant::now();
        let snap = map.snapshot()?;
        ctx.count("ms_snapshot", snap_clock.elapsed().as_secs_f64() * 1e3);
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
        let pose_warp = match p.pose_warp {
            PoseWarpKind::Position => PoseWarp::Position,
            PoseWarpKind::View => PoseWarp::View { depth_m: p.pose_view_depth_m },
        };
        let deformation = Deformation::new(nodes, p.k as usize, window).timed_by(p.surfel_time).poses_by(pose_warp);
        let mut graph = Graph::new(deformation, p.connectivity as usize, p.edges);
        if let (Freeze::Inactive, Some(delta_t)) = (p.freeze, map.active_window()) {
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
        for c in cons {
            graph.constrain(c);
        }
        let solution = graph.optimise(&self.weights())?;
        ctx.count("ms_graph", clock.elapsed().as_secs_f64() * 1e3);
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
