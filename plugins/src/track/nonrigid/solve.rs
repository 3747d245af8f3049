//! One frame's joint Gauss-Newton solve of the camera pose and the node increments:
//!
//! `E = Σ ρ(r_icp/σ_icp)² + w_rgb Σ ρ(r_rgb/σ_rgb)² + E_rot/σ_rot² + w_reg E_reg/σ_reg²
//!    + Σ ‖g_j + t_j − ĝ_j‖²/σ_rest² + Σ (‖t_j‖²/σ_step² + ‖R_j − I‖²/σ_rot_step²)
//!    + Σ ‖(I − n_j n_jᵀ) t_j‖²/σ_slide² + ‖ξ‖²_Σcam`
//!
//! (data terms: `energy.rs`; `E_rot`, `E_reg`: the ED graph of `crate::common::ed_graph`, Sumner
//! et al. 2007 Eqs. (3)–(4); ĝ_j the node's reference position, the rest-shape prior that gives
//! the motion common to all nodes to the camera (nonrigid.md §5); n_j the node's normal averaged
//! with its graph neighbours' (`slide_normal_passes`), the slide prior ours; ξ the camera's
//! departure from the rigid start). Bindings of model points to nodes are fixed for the frame,
//! correspondences are re-projected every iteration (SurfelWarp), full steps (no line search).
//! With `reuse_factor` the first iteration's factorised matrix serves the later ones, which form
//! the gradient alone (the chord method, Ortega & Rheinboldt's simplified Newton), until a step
//! fails to shrink; the data terms are summed in `assemble.rs`.

use capsule_slam_framework::{Iso3, StageError};
use nalgebra::Vector3;

use crate::common::ed_graph::{Graph, NodeModel};
use crate::track::icp_rgb::frames::Level;
use crate::track::icp_rgb::{correlated_count, huber, residual_sigma};

use super::energy::{data_camera_row, data_residual, image_gradient_cam, photo_camera_row, photo_world_gradient};
use super::points::{ModelPoint, look};
use super::system::{Factor, Pattern, Residual};

/// The weights and gates of the energy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Weights {
    /// Point-to-plane noise scale, metres.
    pub sigma_icp_m: f64,
    /// Weight of the photometric term.
    pub w_rgb: f64,
    /// Intensity noise scale.
    pub sigma_rgb: f64,
    /// Huber threshold in noise scales.
    pub huber_k: f64,
    /// Correspondence distance gate, metres.
    pub gate_m: f64,
    /// Cosine of the normal-angle gate.
    pub cos_gate: f64,
    /// Photometric occlusion gate, metres.
    pub rgb_depth_gate_m: f64,
    /// Smallest live gradient for the photometric term, per level pixel.
    pub rgb_min_gradient: f64,
    /// Scale of the E_rot residuals (dimensionless).
    pub sigma_rot: f64,
    /// Weight of E_reg.
    pub w_reg: f64,
    /// Scale of the E_reg residuals, metres.
    pub sigma_reg_m: f64,
    /// Rest-shape prior scale, metres (0: off).
    pub sigma_rest_m: f64,
    /// Per-frame node translation prior, metres (0: off).
    pub sigma_step_m: f64,
    /// Per-frame node R − I prior (0: off).
    pub sigma_step_rot: f64,
    /// Per-frame prior on a node's translation along its surface (0: off).
    pub sigma_slide_m: f64,
    /// Camera prior toward the rigid start: translation, metres (0: off).
    pub sigma_camera_m: f64,
    /// Camera prior: rotation, radians (0: off).
    pub sigma_camera_rad: f64,
    /// Gauss-Newton iterations.
    pub iterations: usize,
    /// Stop once no node's and not the camera's translation moves by more than this in an
    /// iteration, metres (0: never early).
    pub step_tolerance_m: f64,
    /// Iterations after the first keep the last factorised matrix and linearise the gradient
    /// alone (the chord method) while each step is smaller than the one before; one that is
    /// not makes the next iteration factorise anew. false: Gauss-Newton exactly.
    pub reuse_factor: bool,
    /// Model points every this many pixels (a depth error correlated over more pixels counts
    /// once per correlated patch, as in `icp-rgb`).
    pub point_stride_px: f64,
    /// Gates widen to this many σ of the live depth (as `icp-rgb`'s `gate_sigmas`).
    pub gate_sigmas: f64,
}

/// One frame's problem. It names its model points by their index in the slice every solve is
/// given, so it can be built before the points' photometric references are relit to the rigid
/// start (`Nonrigid::prepare`, alongside the rigid start).
pub struct Problem {
    /// The model points' indices with their bindings (solve-node index, weight).
    pub points: Vec<(usize, Vec<(usize, f64)>)>,
    /// The graph of the solve nodes (live positions, identity transforms) and its edges.
    pub graph: Graph,
    /// Reference position of each solve node.
    pub references: Vec<Vector3<f64>>,
    /// Unit normal at each solve node averaged with its neighbours' (`priors::smoothed_normals`):
    /// the slide prior's tangent plane.
    pub normals: Vec<Vector3<f64>>,
    /// Whether the camera is an unknown.
    pub camera: bool,
}

/// Residual statistics of one linearisation: (point-to-plane inliers, their RMS residual in
/// metres, the photometric RMS), and every bound point's squared point-to-plane residual where
/// it is an inlier, in order.
pub(crate) type Stats = ((usize, f64, f64), Vec<Option<f64>>);

/// What a solve did.
pub struct Outcome {
    /// The pose.
    pub t_world_cam: Iso3,
    /// Iterations run.
    pub iterations: usize,
    /// Of those, the ones that factorised the normal matrix (the rest reused it).
    pub factorisations: usize,
    /// Point-to-plane inliers at the last linearisation.
    pub inliers: usize,
    /// RMS point-to-plane residual there, metres.
    pub icp_rms_m: f64,
    /// RMS point-to-plane residual at the first linearisation (the rigid start), metres.
    pub icp_rms_first_m: f64,
    /// RMS photometric residual (intensity) at the last linearisation.
    pub rgb_rms: f64,
    /// The same at the first linearisation.
    pub rgb_rms_first: f64,
    /// Point-to-plane inliers at the first linearisation.
    pub inliers_first: usize,
    /// RMS point-to-plane residual over the points that are inliers at both the first and the
    /// last linearisation, there and at the first, metres: unlike `icp_rms_m` against
    /// `icp_rms_first_m` it does not rise when the alignment brings more points into the gate.
    pub icp_common_rms_m: (f64, f64),
    /// Symbolic analyses run (0: the previous one was reused).
    pub analyses: usize,
    /// Time building the pattern and the bindings' slots, and analysing it, ms.
    pub ms_setup: f64,
    /// Of `ms_setup`, the symbolic analysis (0 when the previous one was reused), ms.
    pub ms_analyse: f64,
    /// Time assembling the normal equations, ms (all iterations).
    pub ms_assemble: f64,
    /// Time factorising and solving, ms (all iterations).
    pub ms_factor: f64,
    /// Time building the problem before the solve (the nodes with enough points, the
    /// bindings, the graph), ms: set by the caller that built it.
    pub ms_problem: f64,
}

/// The pattern and factorisation kept between frames.
#[derive(Default)]
pub struct Cache {
    pub(super) kept: Option<(Pattern, Factor)>,
}

impl Problem {
    /// Solves from `t_start` (the rigid estimate) with the model points `model`; the graph's node
    /// transforms hold the warp.
    pub fn solve(&mut self, model: &[ModelPoint], level: &Level, t_start: &Iso3, w: &Weights, cache: &mut Cache) -> Result<Outcome, StageError> {
        let prepared = self.prepare(model, w, cache)?;
        self.solve_prepared(model, prepared, level, t_start, w, cache)
    }

    /// One point's residuals given to `sink` (their Jacobians for node k are
    /// `node_row(a, x − g_k, w_k)`); the squared point-to-plane residual when the point is an ICP
    /// inlier, and the squared photometric residual when it has one.
    pub(crate) fn point_terms(
        &self,
        level: &Level,
        t: &Iso3,
        w: &Weights,
        p: &ModelPoint,
        binding: &[(usize, f64)],
        sink: &mut impl FnMut(&Residual),
    ) -> [Option<f64>; 2] {
        let warped = self.graph.deformation.warp_with(&p.x_world_m, binding);
        let Some(live) = look(level, t, &warped) else { return [None; 2] };
        let mut icp_r2 = None;
        // σ of the residual (floor, live depth and model) for the gate and the Huber threshold;
        // the weight counts a correlated patch of live points once (`icp-rgb`'s `gn.rs`).
        let sigma = residual_sigma(w.sigma_icp_m, live.sigma_m, p.sigma_m);
        let correlated = correlated_count(level.sigma_correlation_px, w.point_stride_px);
        let sigma_w2 = w.sigma_icp_m * w.sigma_icp_m + live.sigma_m * live.sigma_m * correlated + p.sigma_m * p.sigma_m;
        let close = (warped - live.p_world_m).norm() <= w.gate_m.max(w.gate_sigmas * sigma) && p.n_world.dot(&live.n_world) >= w.cos_gate;
        if close {
            let r = data_residual(&p.n_world, &warped, &live.p_world_m);
            let camera = data_camera_row(&p.n_world, &live.p_world_m);
            sink(&Residual { a: p.n_world, camera, r, w: huber(r / sigma, w.huber_k) / sigma_w2 });
            icp_r2 = Some(r * r);
        }
        if w.w_rgb > 0.0
            && let (Some(reference), Some((i, gx, gy))) = (p.gray_ref, live.gray)
            && (live.depth_m - live.q_cam_m.z).abs() <= w.rgb_depth_gate_m.max(w.gate_sigmas * live.sigma_m)
            && gx * gx + gy * gy >= w.rgb_min_gradient * w.rgb_min_gradient
        {
            let a = image_gradient_cam(&live.q_cam_m, (gx, gy), level.cam.fx, level.cam.fy);
            let m = photo_world_gradient(t.rotation.to_rotation_matrix().matrix(), &a);
            let r = i - reference;
            let weight = live.share * w.w_rgb * huber(r / w.sigma_rgb, w.huber_k) / (w.sigma_rgb * w.sigma_rgb);
            sink(&Residual { a: m, camera: photo_camera_row(&m, &warped), r, w: weight });
            return [icp_r2, Some(r * r)];
        }
        [icp_r2, None]
    }
}

/// The RMS of the squared residuals `last` and `first` over the points that have both (inliers
/// at both linearisations): (last, first), infinite when there are none.
pub(super) fn common_rms(first: &[Option<f64>], last: &[Option<f64>]) -> (f64, f64) {
    let (mut n, mut sum_last, mut sum_first) = (0usize, 0.0, 0.0);
    for (a, b) in first.iter().zip(last) {
        if let (Some(a), Some(b)) = (a, b) {
            (n, sum_first, sum_last) = (n + 1, sum_first + a, sum_last + b);
        }
    }
    if n == 0 {
        return (f64::INFINITY, f64::INFINITY);
    }
    ((sum_last / n as f64).sqrt(), (sum_first / n as f64).sqrt())
}

/// The largest translation a Gauss-Newton step gives a node or the camera, metres.
pub(super) fn largest_translation_m(step: &[f64], nodes: usize, camera: bool, model: NodeModel) -> f64 {
    let at = |i: usize| Vector3::new(step[i], step[i + 1], step[i + 2]).norm();
    let u = model.unknowns();
    let node = (0..nodes).map(|j| at(u * j + model.translation())).fold(0.0, f64::max);
    if camera { node.max(at(u * nodes)) } else { node }
}

pub(super) fn ms(since: std::time::Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

pub(super) fn solver_error(e: impl std::fmt::Display) -> StageError {
    StageError::invalid_input(format!("nonrigid: sparse Cholesky failed: {e}"))
}

#[cfg(test)]
mod tests {
    use super::common_rms;

    #[test]
    fn the_common_rms_counts_the_points_that_are_inliers_at_both_linearisations_only() {
        let sq = |mm: f64| Some((mm * 1e-3) * (mm * 1e-3));
        // Two points fitted better (0.4 → 0.2 mm), one brought into the gate (2.5 mm), one
        // that left it, one never seen.
        let first = [sq(0.4), sq(0.4), None, sq(1.0), None];
        let last = [sq(0.2), sq(0.2), sq(2.5), None, None];
        let (rms_last, rms_first) = common_rms(&first, &last);
        assert!((rms_last - 0.2e-3).abs() < 1e-12 && (rms_first - 0.4e-3).abs() < 1e-12, "{rms_last} {rms_first}");
        // Over each linearisation's own inliers the same fit reads as a rise (0.62 → 1.46 mm).
        let own = |r2: &[Option<f64>]| (r2.iter().flatten().sum::<f64>() / r2.iter().flatten().count() as f64).sqrt();
        assert!(own(&last) > 2.0 * own(&first));
        // No point in common: no figure.
        assert_eq!(common_rms(&[None, sq(1.0)], &[sq(1.0), None]), (f64::INFINITY, f64::INFINITY));
    }
}
