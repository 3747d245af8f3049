//! The priors of the joint solve, all on the diagonal or a node's translation block: the
//! rest-shape prior (a node's pull to its reference position: the motion common to all nodes
//! goes to the camera, nonrigid.md §5), the per-frame step priors, the slide prior and the
//! camera prior toward the rigid start (`solve.rs` has the energy).

use nalgebra::{Matrix3, Vector3, Vector6};

use crate::common::ed_graph::NodeModel;

use super::solve::{Problem, Weights};
use super::system::Pattern;

impl Problem {
    /// Adds the rest-shape, step and camera priors (all on the diagonal) and a tiny
    /// Levenberg term.
    pub(super) fn add_priors(&self, w: &Weights, xi: &Vector6<f64>, pattern: &mut Pattern, diag: &[usize], g: &mut [f64]) {
        let vals = pattern.a.val_mut();
        let inv2 = |s: f64| if s > 0.0 { 1.0 / (s * s) } else { 0.0 };
        let mut add = |u: usize, h: f64, grad: f64| {
            if diag[u] != usize::MAX {
                vals[diag[u]] += h + 1e-9;
            }
            g[u] += grad;
        };
        let (rest, step, rot) = (inv2(w.sigma_rest_m), inv2(w.sigma_step_m), inv2(w.sigma_step_rot));
        let model = self.graph.model;
        let (u, tr) = (model.unknowns(), model.translation());
        for (j, node) in self.graph.deformation.nodes.iter().enumerate() {
            let off = node.position_m.coords + node.translation_m - self.references[j];
            match model {
                NodeModel::Affine => {
                    let dr = node.rotation - Matrix3::identity();
                    for m in 0..9 {
                        add(u * j + m, rot, rot * dr[(m % 3, m / 3)]);
                    }
                }
                NodeModel::Twist => {
                    // ‖R − I‖²_F = 2 ‖ω‖² to first order; the gradient of ‖log R‖² under the left
                    // increment is log R to first order.
                    let omega = nalgebra::Rotation3::from_matrix_unchecked(node.rotation).scaled_axis();
                    for m in 0..3 {
                        add(u * j + 3 + m, 2.0 * rot, 2.0 * rot * omega[m]);
                    }
                }
            }
            for axis in 0..3 {
                add(u * j + tr + axis, rest + step, rest * off[axis] + step * node.translation_m[axis]);
            }
        }
        if self.camera {
            let base = u * self.graph.deformation.nodes.len();
            for c in 0..6 {
                let h = if c < 3 { inv2(w.sigma_camera_m) } else { inv2(w.sigma_camera_rad) };
                add(base + c, h, h * xi[c]);
            }
        }
    }

    /// Adds the slide prior: `‖(I − n nᵀ) t_j‖² / σ_slide²` per node, a per-frame step along the
    /// surface. A wall moves mostly along its normal (a peristaltic wave is radial), while a
    /// tube's axis and roll are near-null directions of point to plane: without this prior the
    /// nodes slide along the tube and take the camera's motion with them.
    pub(super) fn add_slide_prior(&self, w: &Weights, pattern: &mut Pattern, slots: &[[usize; 6]], g: &mut [f64]) {
        if w.sigma_slide_m <= 0.0 {
            return;
        }
        let h = 1.0 / (w.sigma_slide_m * w.sigma_slide_m);
        let base = |j: usize| self.graph.model.unknowns() * j + self.graph.model.translation();
        let vals = pattern.a.val_mut();
        for (j, node) in self.graph.deformation.nodes.iter().enumerate() {
            let n = self.normals[j];
            let p = (Matrix3::identity() - n * n.transpose()) * h;
            let grad = p * node.translation_m;
            let mut k = 0;
            for a in 0..3 {
                g[base(j) + a] += grad[a];
                for b in 0..=a {
                    if slots[j][k] != usize::MAX {
                        vals[slots[j][k]] += p[(a, b)];
                    }
                    k += 1;
                }
            }
        }
    }
}

/// The directions the slide prior holds a node to: each node's normal averaged with its graph
/// neighbours' (`passes` times; 0: the nodes' own normals). A node's own normal follows the
/// wave's slope (up to 0.5 rad for a 4 mm wave of 50 mm wavelength), so motion "along the normal"
/// would slide the wall along the tube by up to half the wall's own motion; averaged over the
/// node's neighbourhood (± 1–2 node spacings, a good part of a wavelength) it points nearer the
/// direction the wall moves in.
pub(super) fn smoothed_normals(normals: &[Vector3<f64>], neighbours: &[Vec<usize>], passes: u32) -> Vec<Vector3<f64>> {
    let mut out = normals.to_vec();
    for _ in 0..passes {
        out = neighbours
            .iter()
            .enumerate()
            .map(|(j, nb)| {
                let sum = nb.iter().fold(out[j], |acc, &n| acc + out[n]);
                let len = sum.norm();
                if len > 1e-9 { sum / len } else { out[j] }
            })
            .collect();
    }
    out
}
