//! The data terms of the joint solve summed into its normal equations: the model points in
//! fixed chunks (the same sums on any thread count), each point's residuals (`solve.rs`,
//! `Problem::point_terms`) entering the blocks of its node pairs once (`system.rs`), or, in an
//! iteration that keeps an earlier factorisation, the gradient alone.

use capsule_slam_framework::{Iso3, StageError};
use nalgebra::{Vector3, Vector6};
use rayon::prelude::*;

use crate::common::ed_graph::{GraphWeights, NodeModel};
use crate::track::icp_rgb::frames::Level;

use super::points::ModelPoint;
use super::solve::{Problem, Stats, Weights};
use super::system::{Accumulator, NodeFactor, Pattern, PointSums};

/// One chunk's part of `accumulate` besides its accumulator: the counts and sums of squares of
/// the point-to-plane and photometric residuals, and its points' squared point-to-plane
/// residuals.
type ChunkSums = ([usize; 2], [f64; 2], Vec<Option<f64>>);

/// The model points are summed in this many fixed chunks, in order: the same sums on any
/// thread count.
const CHUNKS: usize = 4;

/// A problem's pattern and the slots of its terms.
pub(crate) struct Layout {
    /// The normal matrix (lower triangle).
    pub(crate) pattern: Pattern,
    /// Per bound model point, what its residuals need of the layout (fixed for the frame).
    bound: Vec<BoundPoint>,
    reg_slots: Vec<usize>,
    diag: Vec<usize>,
    /// Per node, the slots of its translation block's lower triangle, (a, b) for b ≤ a, row major.
    translation_slots: Vec<[usize; 6]>,
    /// One accumulator per chunk of model points, zeroed and refilled every iteration.
    parts: Vec<Accumulator>,
}

impl Problem {
    /// The normal-equation pattern of this problem and where every term lands in it.
    pub(crate) fn layout(&self, points: &[ModelPoint], w: &Weights) -> Result<Layout, StageError> {
        let model = self.graph.model;
        let pattern = Pattern::new(self.graph.deformation.nodes.len(), &self.pairs(), self.camera, model);
        let bound: Vec<BoundPoint> = self.points.par_iter().map(|(i, b)| self.bound_point(&pattern, &points[*i], b)).collect();
        let mut reg_slots = Vec::new();
        self.graph.visit(&Self::graph_weights(w), |_, row| {
            for &(a, _) in row {
                for &(b, _) in row {
                    if a >= b {
                        reg_slots.push(pattern.slot(a, b).unwrap_or(usize::MAX));
                    }
                }
            }
        });
        let diag: Vec<usize> = (0..pattern.unknowns()).map(|u| pattern.slot(u, u).unwrap_or(usize::MAX)).collect();
        let translation_slots = (0..self.graph.deformation.nodes.len())
            .map(|j| {
                let base = model.unknowns() * j + model.translation();
                let mut s = [usize::MAX; 6];
                let mut k = 0;
                for a in 0..3 {
                    for b in 0..=a {
                        s[k] = pattern.slot(base + a, base + b).unwrap_or(usize::MAX);
                        k += 1;
                    }
                }
                s
            })
            .collect();
        let parts = self.points.chunks(chunk_len(self.points.len())).map(|_| pattern.accumulator()).collect();
        Ok(Layout { pattern, bound, reg_slots, diag, translation_slots, parts })
    }

    /// Fills the layout's matrix with `JᵀWJ` of the model `points` at the current node
    /// transforms, camera `t` and camera departure `xi`; returns `JᵀWr` and the residual
    /// statistics.
    /// With `matrix` false only `JᵀWr` is formed (the values of the matrix are left stale, to be
    /// overwritten by the next full linearisation).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn linearise(
        &self,
        points: &[ModelPoint],
        level: &Level,
        t: &Iso3,
        xi: &Vector6<f64>,
        w: &Weights,
        layout: &mut Layout,
        matrix: bool,
    ) -> (Vec<f64>, Stats) {
        let stats = self.accumulate(points, level, t, w, &mut layout.parts, &layout.bound, matrix);
        let mut g = if matrix { layout.pattern.scatter(&layout.parts) } else { layout.pattern.gradient(&layout.parts) };
        self.add_graph_rows(&Self::graph_weights(w), &mut layout.pattern, &layout.reg_slots, &mut g);
        self.add_priors(w, xi, &mut layout.pattern, &layout.diag, &mut g);
        self.add_slide_prior(w, &mut layout.pattern, &layout.translation_slots, &mut g);
        (g, stats)
    }

    fn pairs(&self) -> Vec<(usize, usize)> {
        let mut pairs: Vec<(usize, usize)> = Vec::new();
        for (j, nb) in self.graph.neighbours.iter().enumerate() {
            pairs.extend(nb.iter().map(|&n| (j, n)));
        }
        for (_, b) in &self.points {
            for (k, &(i, _)) in b.iter().enumerate() {
                pairs.extend(b[..k].iter().map(|&(j, _)| (i, j)));
            }
        }
        pairs
    }

    /// The graph's weights for `E_rot`, `E_reg` (no point constraints).
    fn graph_weights(w: &Weights) -> GraphWeights {
        GraphWeights { rot: 1.0 / (w.sigma_rot * w.sigma_rot), reg: w.w_reg, con: 0.0, length_unit_m: w.sigma_reg_m, iterations: 1 }
    }

    /// Adds the graph's `E_rot` and `E_reg` rows (slots in visiting order).
    fn add_graph_rows(&self, gw: &GraphWeights, pattern: &mut Pattern, slots: &[usize], g: &mut [f64]) {
        let vals = pattern.a.val_mut();
        let mut next = slots.iter();
        self.graph.visit(gw, |r, row| {
            for &(a, ja) in row {
                g[a] += ja * r;
                for &(b, jb) in row {
                    if a >= b
                        && let Some(&s) = next.next()
                        && s != usize::MAX
                    {
                        vals[s] += ja * jb;
                    }
                }
            }
        });
    }

    /// The data terms at pose `t` summed into `parts` (one accumulator per fixed chunk of
    /// points, `CHUNKS`, reset first); returns the residual statistics.
    #[allow(clippy::too_many_arguments)]
    fn accumulate(&self, model: &[ModelPoint], level: &Level, t: &Iso3, w: &Weights, parts: &mut [Accumulator], bound: &[BoundPoint], matrix: bool) -> Stats {
        let chunk = chunk_len(self.points.len());
        let sums: Vec<ChunkSums> = self
            .points
            .par_chunks(chunk)
            .zip(bound.par_chunks(chunk))
            .zip(parts.par_iter_mut())
            .map(|((pts, bound), acc)| {
                if matrix {
                    acc.reset();
                } else {
                    acc.reset_gradient();
                }
                let (mut n, mut sse) = ([0usize; 2], [0.0; 2]);
                let mut icp_r2 = Vec::with_capacity(pts.len());
                let mut factors = Vec::new();
                for ((i, binding), b) in pts.iter().zip(bound) {
                    let p = &model[*i];
                    let mut sums = PointSums::default();
                    let r2 = if matrix {
                        self.point_terms(level, t, w, p, binding, &mut |q| sums.add(q))
                    } else {
                        self.point_terms(level, t, w, p, binding, &mut |q| sums.add_gradient(q))
                    };
                    if sums.count > 0 {
                        self.node_factors(b, &mut factors);
                        if matrix {
                            acc.add_point(&factors, &b.pairs, &sums);
                        } else {
                            acc.add_point_gradient(&factors, &sums);
                        }
                    }
                    icp_r2.push(r2[0]);
                    for (k, v) in r2.into_iter().enumerate() {
                        if let Some(v) = v {
                            n[k] += 1;
                            sse[k] += v;
                        }
                    }
                }
                (n, sse, icp_r2)
            })
            .collect();
        let (mut n, mut sse) = ([0usize; 2], [0.0; 2]);
        let mut icp_r2 = Vec::with_capacity(self.points.len());
        for (pn, ps, r2) in &sums {
            icp_r2.extend_from_slice(r2);
            for k in 0..2 {
                n[k] += pn[k];
                sse[k] += ps[k];
            }
        }
        let rms = |k: usize| if n[k] == 0 { f64::INFINITY } else { (sse[k] / n[k] as f64).sqrt() };
        ((n[0], rms(0), rms(1)), icp_r2)
    }

    fn bound_point(&self, pattern: &Pattern, p: &ModelPoint, binding: &[(usize, f64)]) -> BoundPoint {
        let mut pairs = Vec::with_capacity(binding.len() * (binding.len() + 1) / 2);
        for (k, &(i, _)) in binding.iter().enumerate() {
            for &(j, _) in &binding[..=k] {
                pairs.push(pattern.block(i, j).unwrap_or(0));
            }
        }
        let factors = binding.iter().map(|&(k, wk)| (k, wk, p.x_world_m - self.graph.deformation.nodes[k].position_m)).collect();
        BoundPoint { pairs, factors }
    }

    /// The bound point's node factors at the current node transforms (a twist node's offset
    /// turns with its rotation).
    fn node_factors(&self, b: &BoundPoint, out: &mut Vec<NodeFactor>) {
        let nodes = &self.graph.deformation.nodes;
        out.clear();
        out.extend(b.factors.iter().map(|&(node, w, v)| NodeFactor {
            node,
            w,
            v: match self.graph.model {
                NodeModel::Affine => v,
                NodeModel::Twist => nodes[node].rotation * v,
            },
        }));
    }
}

/// What a bound model point's residuals need of the layout: the block ids of its node pairs,
/// `pairs[k (k + 1) / 2 + l]` for l ≤ k, and its nodes with their weights and offsets
/// `(k, w_k, x − g_k)` (the nodes' positions stay put while the solve moves their transforms).
struct BoundPoint {
    pairs: Vec<usize>,
    factors: Vec<(usize, f64, Vector3<f64>)>,
}

/// Model points per chunk of `accumulate` (`CHUNKS` chunks, at least one point each).
fn chunk_len(points: usize) -> usize {
    points.div_ceil(CHUNKS).max(1)
}
