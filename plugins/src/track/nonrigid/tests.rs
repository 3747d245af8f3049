//! Tests of `nonrigid` against known warps: a curved, textured wall patch in front of the
//! camera, displaced by a smooth field the test knows, rendered to depth and intensity.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::{DepthMap, GrayF32, Iso3};
use nalgebra::{Point3, Vector3};

use super::points::ModelPoint;
use super::*;
use crate::common::maps::GeometryParams;
use crate::track::icp_rgb::frames::pyramid;

const F: f64 = 100.0;

fn cam() -> PinholeCamera {
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

fn level(amp_m: f64) -> Level {
    let (depth, gray) = render(amp_m);
    let prep = GeometryParams { min_m: 0.001, max_m: 1.0, radius_px: 0, sigma_px: 1.0, sigma_m: 1.0, edge_jump_m: 0.01 };
    pyramid(depth, gray, (None, None), &cam(), 1, &prep).remove(0)
}

/// Model points of the rest wall on a grid, with their true displaced positions.
fn model(amp_m: f64) -> Vec<(ModelPoint, Point3<f64>)> {
    let mut out = Vec::new();
    for i in -14..=14 {
        for j in -14..=14 {
            let (x, y) = (i as f64 * 0.0008, j as f64 * 0.0008);
            let p = Point3::new(x, y, wall(x, y));
            let n = Vector3::new(16.0 * x + 0.1, 8.0 * y, -1.0).normalize();
            let moved = Point3::new(x, y, p.z + displacement(x, y, amp_m));
            out.push((ModelPoint { x_world_m: p, n_world: n, gray_ref: Some(texture(x, y)) }, moved));
        }
    }
    out
}

fn tracker(camera: CameraMode) -> Nonrigid {
    let params = NonrigidParams { camera, node_spacing_m: 0.004, reach_m: 0.008, max_edge_m: 0.012, iterations: 8, min_points_per_node: 4, sigma_step_m: 0.0, sigma_step_rot: 0.0, factor_common: false, ..Default::default() };
    Nonrigid::new(params).unwrap()
}

/// RMS distance of the warped model points from where the test moved them, metres.
fn warp_error(warp: &Deformation, pts: &[(ModelPoint, Point3<f64>)]) -> f64 {
    let sse: f64 = pts.iter().map(|(p, truth)| (warp.warp_point(&p.x_world_m, 0) - truth).norm_squared()).sum();
    (sse / pts.len() as f64).sqrt()
}

#[test]
fn a_known_smooth_warp_is_recovered_from_its_depth() {
    let amp = 0.0005;
    let pts = model(amp);
    let points: Vec<ModelPoint> = pts.iter().map(|p| p.0).collect();
    let before = (pts.iter().map(|(p, t)| (p.x_world_m - t).norm_squared()).sum::<f64>() / pts.len() as f64).sqrt();
    let live = level(amp);
    for camera in [CameraMode::Fixed, CameraMode::Joint] {
        let mut t = tracker(camera);
        t.nodes.cover(&points, t.params.node_spacing_m, 0, 4096);
        let Fit::Solved { warp, t_world_cam, .. } = t.fit(&points, &live, &Iso3::identity(), 1).unwrap() else { panic!("fell back") };
        let err = warp_error(&warp, &pts);
        assert!(err < 0.1e-3, "{camera:?}: warp error {:.4} mm (before {:.4} mm)", err * 1e3, before * 1e3);
        assert!(t_world_cam.translation.vector.norm() < 0.05e-3, "{camera:?}: the camera moved {:.4} mm", t_world_cam.translation.vector.norm() * 1e3);
    }
}
