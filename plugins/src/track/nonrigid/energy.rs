//! The residuals of the non-rigid tracking energy and their Jacobians.
//!
//! A model point x (world frame, from the prediction) is warped by its embedded-deformation
//! nodes, `x̃ = Σ_k w_k [R_k (x − g_k) + g_k + t_k]` (Sumner et al. 2007, Eq. 5; the paper's
//! Eq. (5)), and compared with the live frame seen from the camera pose `T_wc`, which moves by a
//! left increment `T_wc ← exp(ξ) T_wc`, `ξ = [ρ; ω]` (translation first, as in `icp-rgb`).
//!
//! - point to plane (the paper's Eq. (2) with the roles of model and live swapped, as
//!   SurfelWarp's `DenseDepthJacobianResidual`): `r = nᵀ (x̃ − T_wc d)`, n the model normal,
//!   d the live vertex the warped point projects to;
//! - photometric (Eq. (3)): `r = I_live(π(T_cw x̃)) − I_ref`, I_ref the previous live frame's
//!   intensity where the model point was predicted (lit like the live frame).
//!
//! A residual linear in x̃ with gradient a has, for node k, the entries of the ED graph's unknown
//! order (`crate::common::ed_graph::NodeModel`): for an affine node
//! `∂r/∂R_k[axis][col] = w_k a[axis] (x − g_k)[col]` at `3 col + axis`, `∂r/∂t_k[axis] = w_k a[axis]`
//! at `9 + axis`; for a twist node (`R_k ← exp(ω) R_k`) `∂r/∂t_k = w_k a` at 0–2 and
//! `∂r/∂ω_k = w_k (R_k (x − g_k)) × a` at 3–5.

use nalgebra::{Matrix3, Point3, Vector3, Vector6};

#[cfg(test)]
use crate::common::ed_graph::NodeModel;

/// Node k's Jacobian entries (the model's count) for a residual with world gradient `a`: `v =
/// x − g_k`, `r` the node's rotation part, `w` its weight. The assembly never forms it:
/// `system::Accumulator::add_point` adds its products in block form; the tests check both
/// against finite differences and dense products.
#[cfg(test)]
pub fn node_row(model: NodeModel, a: &Vector3<f64>, v: &Vector3<f64>, r: &Matrix3<f64>, w: f64) -> Vec<f64> {
    let mut out = vec![0.0; model.unknowns()];
    match model {
        NodeModel::Affine => {
            for col in 0..3 {
                for axis in 0..3 {
                    out[3 * col + axis] = w * a[axis] * v[col];
                }
            }
        }
        NodeModel::Twist => {
            let turn = (r * v).cross(a);
            for axis in 0..3 {
                out[3 + axis] = w * turn[axis];
            }
        }
    }
    for axis in 0..3 {
        out[model.translation() + axis] = w * a[axis];
    }
    out
}

/// Point-to-plane residual `nᵀ (x̃ − p)`, `p = T_wc d` the live point in the world.
pub fn data_residual(n: &Vector3<f64>, warped: &Point3<f64>, p: &Point3<f64>) -> f64 {
    n.dot(&(warped - p))
}

/// Its camera Jacobian: `[−n; −(p × n)]`.
pub fn data_camera_row(n: &Vector3<f64>, p: &Point3<f64>) -> Vector6<f64> {
    let c = p.coords.cross(n);
    Vector6::new(-n.x, -n.y, -n.z, -c.x, -c.y, -c.z)
}

/// The gradient of the image through the projection at the camera-frame point `q`, in the
/// camera frame: `a = g · ∂π/∂q` with `g = (gx, gy)` per pixel (the `icp-rgb` form).
pub fn image_gradient_cam(q: &Vector3<f64>, grad: (f64, f64), fx: f64, fy: f64) -> Vector3<f64> {
    let iz = 1.0 / q.z;
    Vector3::new(grad.0 * fx * iz, grad.1 * fy * iz, -(grad.0 * fx * q.x + grad.1 * fy * q.y) * iz * iz)
}

/// The photometric residual's world gradient with respect to x̃: `m = R_wc a`.
pub fn photo_world_gradient(r_world_cam: &Matrix3<f64>, a_cam: &Vector3<f64>) -> Vector3<f64> {
    r_world_cam * a_cam
}

/// Its camera Jacobian: `[−m; m × x̃]` (moving the camera by ξ moves x̃ by the inverse in its
/// frame).
pub fn photo_camera_row(m: &Vector3<f64>, warped: &Point3<f64>) -> Vector6<f64> {
    let c = m.cross(&warped.coords);
    Vector6::new(-m.x, -m.y, -m.z, c.x, c.y, c.z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::Iso3;
    use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
    use capsule_slam_framework::geometry::exp_se3;

    fn numeric<const N: usize>(f: impl Fn(usize, f64) -> f64) -> [f64; N] {
        let h = 1e-7;
        std::array::from_fn(|i| (f(i, h) - f(i, -h)) / (2.0 * h))
    }

    fn nodes() -> Deformation {
        let mut d = Deformation::new(
            vec![
                DeformationNode::identity(Point3::new(0.0, 0.0, 0.03), 0),
                DeformationNode::identity(Point3::new(0.008, 0.001, 0.031), 0),
                DeformationNode::identity(Point3::new(0.001, 0.009, 0.029), 0),
            ],
            2,
            Window::All,
        );
        d.nodes[1].rotation += Matrix3::new(0.01, -0.02, 0.0, 0.02, 0.005, 0.01, 0.0, -0.01, -0.003);
        d.nodes[1].translation_m = Vector3::new(0.0002, -0.0001, 0.0003);
        d
    }

    /// Perturbs unknown `i` of node `k` (the model's order) by `h`.
    fn bumped(model: NodeModel, d: &Deformation, k: usize, i: usize, h: f64) -> Deformation {
        let mut d = d.clone();
        let mut step = vec![0.0; model.unknowns()];
        step[i] = h;
        model.shift(&mut d.nodes[k], &step, 1.0);
        d
    }

    const MODELS: [NodeModel; 2] = [NodeModel::Affine, NodeModel::Twist];

    #[test]
    fn point_to_plane_jacobians_match_finite_differences() {
        let d = nodes();
        let x = Point3::new(0.003, 0.002, 0.0302);
        let infl = d.influences(&x, 0);
        let (n, cam_d) = (Vector3::new(0.1, -0.2, -0.97).normalize(), Point3::new(0.001, 0.0015, 0.012));
        let t_wc = exp_se3(&Vector6::new(0.001, 0.002, 0.017, 0.02, -0.01, 0.03));
        let r = |d: &Deformation, t: &Iso3| data_residual(&n, &d.warp_with(&x, &infl), &(t * cam_d));
        for (model, &(k, w)) in MODELS.iter().flat_map(|m| infl.iter().map(move |i| (*m, i))) {
            let ana = node_row(model, &n, &(x - d.nodes[k].position_m), &d.nodes[k].rotation, w);
            let num: [f64; 12] = numeric(|i, h| if i < model.unknowns() { r(&bumped(model, &d, k, i, h), &t_wc) } else { 0.0 });
            assert!(ana.iter().zip(&num).all(|(a, b)| (a - b).abs() < 1e-7), "{model:?} node {k}: {ana:?} vs {num:?}");
        }
        let ana = data_camera_row(&n, &(t_wc * cam_d));
        let num: [f64; 6] = numeric(|i, h| {
            let mut xi = Vector6::zeros();
            xi[i] = h;
            r(&d, &(exp_se3(&xi) * t_wc))
        });
        assert!(ana.iter().zip(&num).all(|(a, b)| (a - b).abs() < 1e-7), "camera: {ana} vs {num:?}");
    }

    #[test]
    fn photometric_jacobians_match_finite_differences() {
        // A linear image I(u, v) = 0.3 + 0.002 u − 0.001 v (exact gradient).
        let (fx, fy, cx, cy) = (160.0, 150.0, 79.5, 79.5);
        let image = |q: &Point3<f64>| 0.3 + 0.002 * (fx * q.x / q.z + cx) - 0.001 * (fy * q.y / q.z + cy);
        let d = nodes();
        let x = Point3::new(0.003, 0.002, 0.0302);
        let infl = d.influences(&x, 0);
        let t_wc = exp_se3(&Vector6::new(0.001, 0.002, 0.005, 0.02, -0.01, 0.03));
        let r = |d: &Deformation, t: &Iso3| image(&(t.inverse() * d.warp_with(&x, &infl))) - 0.4;
        let warped = d.warp_with(&x, &infl);
        let q = t_wc.inverse() * warped;
        let m = photo_world_gradient(t_wc.rotation.to_rotation_matrix().matrix(), &image_gradient_cam(&q.coords, (0.002, -0.001), fx, fy));
        for (model, &(k, w)) in MODELS.iter().flat_map(|m| infl.iter().map(move |i| (*m, i))) {
            let ana = node_row(model, &m, &(x - d.nodes[k].position_m), &d.nodes[k].rotation, w);
            let num: [f64; 12] = numeric(|i, h| if i < model.unknowns() { r(&bumped(model, &d, k, i, h), &t_wc) } else { 0.0 });
            assert!(ana.iter().zip(&num).all(|(a, b)| (a - b).abs() < 1e-6 * (1.0 + b.abs())), "{model:?} node {k}: {ana:?} vs {num:?}");
        }
        let ana = photo_camera_row(&m, &warped);
        let num: [f64; 6] = numeric(|i, h| {
            let mut xi = Vector6::zeros();
            xi[i] = h;
            r(&d, &(exp_se3(&xi) * t_wc))
        });
        assert!(ana.iter().zip(&num).all(|(a, b)| (a - b).abs() < 1e-6 * (1.0 + b.abs())), "camera: {ana} vs {num:?}");
    }
}
