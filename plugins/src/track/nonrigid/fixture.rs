//! A synthetic wall patch for the tests and the solver benchmark: a curved, textured wall in
//! front of the camera, displaced by a smooth field the caller knows, rendered to depth and
//! intensity.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::{DepthMap, GrayF32, Iso3};
use nalgebra::{Point3, Vector3};

use super::points::ModelPoint;
use super::{Fit, Nonrigid, NonrigidParams};
use crate::common::maps::GeometryParams;
use crate::track::icp_rgb::frames::{Level, pyramid};

const F: f64 = 100.0;

pub(crate) fn cam() -> PinholeCamera {
    PinholeCamera::new(160, 160, F, F, 79.5, 79.5)
}

/// The rest wall: z = 30 mm + a bowl (no symmetry a point-to-plane term cannot see).
fn wall(x: f64, y: f64) -> f64 {
    0.03 + 8.0 * x * x + 4.0 * y * y + 0.1 * x
}

/// A smooth texture of the material point.
fn texture(x: f64, y: f64) -> f64 {
    0.5 + 0.2 * (x * 900.0).sin() * (y * 700.0).cos()
}

/// The test's displacement along z of the material point (x, y): a sine of amplitude `amp_m`.
fn displacement(x: f64, y: f64, amp_m: f64) -> f64 {
    amp_m * (2.0 * std::f64::consts::PI * (x / 0.06 + y / 0.09)).sin()
}

/// Depth and intensity of the displaced wall seen from the origin (a ray cast by fixed point).
fn render(amp_m: f64) -> (DepthMap, GrayF32) {
    let c = cam();
    let depth = DepthMap::from_fn(c.width, c.height, |u, v| {
        let (a, b) = ((u as f64 - c.cx) / F, (v as f64 - c.cy) / F);
        let mut z = 0.03;
        for _ in 0..60 {
            z = wall(z * a, z * b) + displacement(z * a, z * b, amp_m);
        }
        [z as f32]
    });
    let gray = GrayF32::from_fn(c.width, c.height, |u, v| {
        let z = f64::from(depth.at(u, v));
        [texture(z * (u as f64 - c.cx) / F, z * (v as f64 - c.cy) / F) as f32]
    });
    (depth, gray)
}

pub(crate) fn level(amp_m: f64) -> Level {
    let (depth, gray) = render(amp_m);
    let prep = GeometryParams { min_m: 0.001, max_m: 1.0, radius_px: 0, sigma_px: 1.0, sigma_m: 1.0, edge_jump_m: 0.01 };
    pyramid(depth, gray, (None, None), &cam(), 1, &prep).remove(0)
}

/// Model points of the rest wall on a grid, with their true displaced positions.
#[cfg(test)]
pub(crate) fn model(amp_m: f64) -> Vec<(ModelPoint, Point3<f64>)> {
    model_grid(amp_m, 14, 0.0008)
}

/// Model points on a (2 half + 1)² grid `step_m` apart.
fn model_grid(amp_m: f64, half: i32, step_m: f64) -> Vec<(ModelPoint, Point3<f64>)> {
    let mut out = Vec::new();
    for i in -half..=half {
        for j in -half..=half {
            let (x, y) = (i as f64 * step_m, j as f64 * step_m);
            let p = Point3::new(x, y, wall(x, y));
            let n = Vector3::new(16.0 * x + 0.1, 8.0 * y, -1.0).normalize();
            let moved = Point3::new(x, y, p.z + displacement(x, y, amp_m));
            out.push((ModelPoint { x_world_m: p, n_world: n, gray_ref: Some(texture(x, y)), sigma_m: 0.0 }, moved));
        }
    }
    out
}

/// One solve of a given node count on the patch (the `nonrigid_solver` criterion bench).
pub struct SolverCase {
    tracker: Nonrigid,
    points: Vec<ModelPoint>,
    live: Level,
    /// Nodes covering the patch.
    pub nodes: usize,
}

impl SolverCase {
    /// About `nodes` nodes on a 22 × 22 mm patch seen with a 0.3 mm wave (spacing from the
    /// count; ≥ 4 model points per node), parametrised by `model`.
    pub fn new(nodes: usize, model: crate::common::ed_graph::NodeModel) -> Result<Self, capsule_slam_framework::StageError> {
        let side_m = 0.0224;
        let spacing_m = side_m / (nodes.max(1) as f64).sqrt();
        let half = ((side_m / 2.0) / (spacing_m / 2.0)).ceil().max(14.0) as i32;
        let points: Vec<ModelPoint> = model_grid(0.0003, half, side_m / (2 * half) as f64).into_iter().map(|p| p.0).collect();
        let params = NonrigidParams {
            node_spacing_m: spacing_m,
            reach_m: 2.0 * spacing_m,
            max_edge_m: 3.0 * spacing_m,
            min_points_per_node: 1,
            min_rms_gain: 0.0,
            min_evidence: 0.0,
            // The nodes alone (SurfelWarp's solve; the joint camera adds 6 unknowns to thousands):
            // started at the identity, not at a rigid fit, the camera would turn 1.4° on this
            // patch and the solve fall back, and there would be nothing to time.
            camera: super::CameraMode::Fixed,
            // Three iterations, as the solver table of docs/results/nonrigid.md was measured.
            iterations: 3,
            step_tolerance_m: 0.0,
            node_model: model,
            ..Default::default()
        };
        let mut tracker = Nonrigid::new(params)?;
        tracker.nodes.cover(&points, spacing_m, 100_000);
        let nodes = tracker.nodes.nodes.len();
        Ok(Self { tracker, points, live: level(0.0003), nodes })
    }

    /// The same case solved with the chord method (`reuse_factor`) or Gauss-Newton exactly.
    pub fn reuse_factor(mut self, on: bool) -> Self {
        self.tracker.params.reuse_factor = on;
        self
    }

    /// The normal-equation pattern of this case's solve (the nodes with their model points
    /// bound), as the solve lays it out before analysing it.
    pub fn pattern(&self) -> Result<PatternCase, capsule_slam_framework::StageError> {
        let p = &self.tracker.params;
        let (problem, _, _) = super::problem::problem_of(&self.tracker.nodes, p, &self.points, None)
            .ok_or_else(|| capsule_slam_framework::StageError::invalid_input("no node has enough model points"))?;
        let pattern = problem.layout(&self.points, &p.weights())?.pattern;
        Ok(PatternCase { unknowns: pattern.unknowns(), pattern })
    }

    /// Binds, assembles and solves once (the tracker's nodes are reset so every call does the
    /// same work); returns whether it solved.
    pub fn solve(&mut self) -> bool {
        let saved = self.tracker.nodes.clone();
        let solved = matches!(self.tracker.fit(&self.points, &self.live, &Iso3::identity(), true), Ok(Fit::Solved { .. }));
        self.tracker.nodes = saved;
        solved
    }
}

/// A solve's normal-equation pattern, for timing its symbolic analysis (the
/// `nonrigid-analysis` criterion bench).
pub struct PatternCase {
    pattern: super::system::Pattern,
    /// Unknowns of the pattern.
    pub unknowns: usize,
}

impl PatternCase {
    /// Analyses the pattern with scalar AMD (`block = false`) or AMD on the node graph (the
    /// tracker's); returns the number of values of the Cholesky factor (its fill).
    pub fn analyse(&self, block: bool) -> Result<usize, capsule_slam_framework::StageError> {
        self.pattern.analyse(block).map(|llt| llt.factor_len()).map_err(|e| capsule_slam_framework::StageError::invalid_input(e.to_string()))
    }
}
