//! The embedded deformation graph (Sumner, Schmid and Pauly 2007) and its optimisation, as
//! ElasticFusion builds it (Whelan et al. 2016, Sec. 4; Sumner et al. 2007): 12 unknowns per node (the 3×3
//! affine R, column-major, and the translation t; [`NodeModel::Affine`]), or 6 for a rigid node
//! ([`NodeModel::Twist`]: t and a left rotation increment, R ← exp(ω) R, as DynamicFusion's and
//! SurfelWarp's nodes; R stays a rotation, so `E_rot` is zero and has no rows), the energy
//!
//! `E = w_rot E_rot + w_reg E_reg + w_con E_con`
//!
//! - `E_rot = Σ_j (c0·c1)² + (c0·c2)² + (c1·c2)² + (c0·c0 − 1)² + (c1·c1 − 1)² + (c2·c2 − 1)²`
//!   (c_i the columns of R_j: R_j close to a rotation; Sumner Eq. (3));
//! - `E_reg = Σ_j Σ_{n ∈ N(j)} ‖R_j (g_n − g_j) + g_j + t_j − (g_n + t_n)‖²` (neighbouring nodes
//!   agree; Sumner Eq. (4));
//! - `E_con = Σ_c ‖φ(v_c) − q_c‖²` with φ the warp of Eq. (5) (the paper's Eq. (5)–(7)): surface
//!   constraints move a source point onto its target, pins (q = v) hold a point in place.
//!
//! Position residuals are divided by `length_unit_m`, so the weights mean what ElasticFusion's
//! (1, 10, 100, tuned with positions in metres at room scale) mean at the scale of the organ.
//! Gauss-Newton: the normal equations `JᵀJ δ = −Jᵀr` by faer's sparse Cholesky, the symbolic
//! analysis once per graph, a numeric factorisation per iteration.

use faer::sparse::{SparseColMat, Triplet};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

use capsule_slam_framework::StageError;
use capsule_slam_framework::deformation::{Deformation, DeformationNode};

use crate::common::sparse_llt::SparseLlt;

/// Force the simplicial factorisation: no (faer's supernodal choice is 1.3–5× faster here;
/// `cargo bench -p capsule-slam-benches --bench deformation`).
const SIMPLICIAL: bool = false;

/// How a node's transform is parametrised.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NodeModel {
    /// Sumner's affine node: R's 9 entries (column-major), then t; R held near a rotation by
    /// `E_rot` (ElasticFusion's deformation graph).
    #[default]
    Affine,
    /// A rigid node: t, then the rotation increment ω of `R ← exp(ω) R` (DynamicFusion's and
    /// SurfelWarp's warp fields). Half the unknowns: a quarter of the normal-equation entries.
    Twist,
}

impl NodeModel {
    /// Unknowns per node.
    pub const fn unknowns(self) -> usize {
        match self {
            Self::Affine => 12,
            Self::Twist => 6,
        }
    }

    /// Where the translation starts among a node's unknowns.
    pub const fn translation(self) -> usize {
        match self {
            Self::Affine => 9,
            Self::Twist => 0,
        }
    }

    /// Pushes the Jacobian entries of component `axis` of `c · (R_i v + t_i)` with respect to
    /// node i's unknowns (R_i its current rotation part): for the affine node
    /// `∂/∂R[axis][col] = c v[col]`; for the twist `∂/∂ω = −c [R_i v]×` (row `axis`).
    pub fn push_entries(self, row: &mut Vec<(usize, f64)>, i: usize, c: f64, r_i: &Matrix3<f64>, v: &Vector3<f64>, axis: usize) {
        let base = self.unknowns() * i;
        match self {
            Self::Affine => row.extend((0..3).map(|col| (base + 3 * col + axis, c * v[col]))),
            Self::Twist => {
                let u = r_i * v;
                let minus_skew_row = [[0.0, u.z, -u.y], [-u.z, 0.0, u.x], [u.y, -u.x, 0.0]][axis];
                row.extend((0..3).map(|b| (base + 3 + b, c * minus_skew_row[b])));
            }
        }
        row.push((base + self.translation() + axis, c));
    }

    /// Applies `scale ·` a node's step (its unknowns in this model's order) to `node`.
    pub fn shift(self, node: &mut DeformationNode, x: &[f64], scale: f64) {
        match self {
            Self::Affine => {
                node.rotation += Matrix3::from_column_slice(&x[..9]) * scale;
                node.translation_m += Vector3::new(x[9], x[10], x[11]) * scale;
            }
            Self::Twist => {
                node.translation_m += Vector3::new(x[0], x[1], x[2]) * scale;
                node.rotation = Rotation3::new(Vector3::new(x[3], x[4], x[5]) * scale).matrix() * node.rotation;
            }
        }
    }
}

/// A point constraint: the warp of `source_m` (a point of time `time`) should land on
/// `target_m`. A pin has `target_m == source_m`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Constraint {
    /// The point before the deformation, metres, world frame.
    pub source_m: Point3<f64>,
    /// Where it should go.
    pub target_m: Point3<f64>,
    /// The point's time (frame index), which picks its influencing nodes.
    pub time: u32,
}

/// Weights and stopping rules of the optimisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GraphWeights {
    /// w_rot (ElasticFusion: 1).
    pub rot: f64,
    /// w_reg (ElasticFusion: 10).
    pub reg: f64,
    /// w_con (ElasticFusion: 100).
    pub con: f64,
    /// Position residuals are divided by this, metres.
    pub length_unit_m: f64,
    /// Most Gauss-Newton iterations (ElasticFusion: 3).
    pub iterations: usize,
}

impl Default for GraphWeights {
    fn default() -> Self {
        Self { rot: 1.0, reg: 10.0, con: 100.0, length_unit_m: 0.01, iterations: 5 }
    }
}

/// A deformation graph ready to optimise: nodes in time order, their time-ordered neighbours,
/// and the constraints with their influencing nodes.
pub struct Graph {
    /// The nodes (positions g and times; R and t are the unknowns).
    pub deformation: Deformation,
    /// Neighbours of each node (directed: j → n).
    pub neighbours: Vec<Vec<usize>>,
    /// Nodes held at the identity (not optimised).
    pub fixed: Vec<bool>,
    /// The nodes' parametrisation ([`NodeModel::Affine`] unless [`Graph::with_model`] says).
    pub model: NodeModel,
    constraints: Vec<(Constraint, Vec<(usize, f64)>)>,
}

/// How graph edges are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Edges {
    /// The `connectivity` nodes nearest in time order (ElasticFusion): on a sweep these run
    /// along one direction of the surface only, so bends across it are not felt by R.
    Time,
    /// The `connectivity` nodes nearest in space among the node's time window (the candidates
    /// of its influence): a surface neighbourhood in every direction, still never linking an
    /// old surface to a new one that crosses it.
    SpaceInWindow,
}

/// The `count` node indices nearest to `i` in time order (ElasticFusion's `connectGraphSeq`:
/// i ± 1, i ± 2 for count 4, shifted inward at the ends).
pub fn time_neighbours(i: usize, n: usize, count: usize) -> Vec<usize> {
    let count = count.min(n.saturating_sub(1));
    let half = count / 2;
    let start = i.saturating_sub(half).min(n.saturating_sub(count + 1));
    (start..(start + count + 1).min(n)).filter(|&j| j != i).collect()
}

impl Graph {
    /// A graph of the nodes of `deformation` (reset to undeformed) with `connectivity`
    /// neighbours each; points find their influencing nodes by the deformation's rules.
    pub fn new(mut deformation: Deformation, connectivity: usize, edges: Edges) -> Self {
        for n in &mut deformation.nodes {
            *n = DeformationNode::identity(n.position_m, n.time);
        }
        let n = deformation.nodes.len();
        let neighbours = (0..n)
            .map(|i| match edges {
                Edges::Time => time_neighbours(i, n, connectivity),
                Edges::SpaceInWindow => {
                    let g = deformation.nodes[i].position_m;
                    let mut c: Vec<(f64, usize)> = deformation
                        .candidates(deformation.nodes[i].time)
                        .filter(|&j| j != i)
                        .map(|j| ((deformation.nodes[j].position_m - g).norm(), j))
                        .collect();
                    c.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                    c.into_iter().take(connectivity).map(|x| x.1).collect()
                }
            })
            .collect();
        Self { deformation, neighbours, fixed: vec![false; n], model: NodeModel::Affine, constraints: Vec::new() }
    }

    /// The graph with its nodes parametrised by `model`.
    pub fn with_model(mut self, model: NodeModel) -> Self {
        self.model = model;
        self
    }

    /// Unknowns in all.
    pub fn unknowns(&self) -> usize {
        self.model.unknowns() * self.deformation.nodes.len()
    }

    /// Holds node `i` at the identity: it moves the points it influences not at all and is no
    /// unknown of the optimisation (ElasticFusion freezes the nodes older than its last local
    /// closure).
    pub fn fix(&mut self, i: usize) {
        if let Some(f) = self.fixed.get_mut(i) {
            *f = true;
            self.deformation.nodes[i] = DeformationNode::identity(self.deformation.nodes[i].position_m, self.deformation.nodes[i].time);
        }
    }

    /// Adds a constraint (its influencing nodes are fixed now, from the undeformed graph).
    pub fn constrain(&mut self, c: Constraint) {
        let infl = self.deformation.influences(&c.source_m, c.time);
        if !infl.is_empty() {
            self.constraints.push((c, infl));
        }
    }

    /// Number of constraints.
    pub fn constraints(&self) -> usize {
        self.constraints.len()
    }

    /// Every residual, weighted (`√w · r`), in a fixed order: per node E_rot (6; affine nodes
    /// only), per directed edge E_reg (3), per constraint E_con (3).
    pub fn residuals(&self, w: &GraphWeights) -> Vec<f64> {
        let mut out = Vec::new();
        self.visit(w, |r, _| out.push(r));
        out
    }

    /// The energy `E = Σ r²` of the weighted residuals.
    pub fn energy(&self, w: &GraphWeights) -> f64 {
        let mut e = 0.0;
        self.visit(w, |r, _| e += r * r);
        e
    }

    /// Calls `f(r, jacobian row)` for every weighted residual; the row lists (unknown index,
    /// ∂r/∂x) with unknown `u j + m`, u the model's unknowns per node: for the affine node m < 9
    /// the entries of R_j column-major, m ≥ 9 t_j; for the twist m < 3 t_j, m ≥ 3 ω_j. Fixed
    /// nodes have no E_rot rows and no entries.
    pub fn visit(&self, w: &GraphWeights, mut f: impl FnMut(f64, &[(usize, f64)])) {
        let nodes = &self.deformation.nodes;
        let (fixed, model) = (&self.fixed, self.model);
        let (s_rot, s_reg, s_con) = (w.rot.sqrt(), w.reg.sqrt() / w.length_unit_m, w.con.sqrt() / w.length_unit_m);
        let mut row: Vec<(usize, f64)> = Vec::with_capacity(64);
        for (j, node) in nodes.iter().enumerate() {
            if fixed[j] || model == NodeModel::Twist {
                continue;
            }
            let c = [node.rotation.column(0).into_owned(), node.rotation.column(1).into_owned(), node.rotation.column(2).into_owned()];
            let base = model.unknowns() * j;
            for (a, b) in [(0, 1), (0, 2), (1, 2)] {
                row.clear();
                for (d, (cb, ca)) in c[b].iter().zip(c[a].iter()).enumerate() {
                    row.push((base + 3 * a + d, s_rot * cb));
                    row.push((base + 3 * b + d, s_rot * ca));
                }
                f(s_rot * c[a].dot(&c[b]), &row);
            }
            for (a, col) in c.iter().enumerate() {
                row.clear();
                for d in 0..3 {
                    row.push((base + 3 * a + d, s_rot * 2.0 * col[d]));
                }
                f(s_rot * (col.norm_squared() - 1.0), &row);
            }
        }
        for (j, node) in nodes.iter().enumerate() {
            for &n in &self.neighbours[j] {
                if fixed[j] && fixed[n] {
                    continue;
                }
                let other = &nodes[n];
                let d = other.position_m - node.position_m;
                let e = node.rotation * d + node.position_m.coords + node.translation_m - (other.position_m.coords + other.translation_m);
                for axis in 0..3 {
                    row.clear();
                    if !fixed[j] {
                        model.push_entries(&mut row, j, s_reg, &node.rotation, &d, axis);
                    }
                    if !fixed[n] {
                        row.push((model.unknowns() * n + model.translation() + axis, -s_reg));
                    }
                    f(s_reg * e[axis], &row);
                }
            }
        }
        for (c, infl) in &self.constraints {
            let e = self.deformation.warp_with(&c.source_m, infl) - c.target_m;
            for axis in 0..3 {
                row.clear();
                for &(i, wi) in infl.iter().filter(|(i, _)| !fixed[*i]) {
                    model.push_entries(&mut row, i, s_con * wi, &nodes[i].rotation, &(c.source_m - nodes[i].position_m), axis);
                }
                f(s_con * e[axis], &row);
            }
        }
    }

    /// Adds `scale · step` to the unknowns (ordered as in [`Graph::visit`]).
    pub fn shift(&mut self, step: &[f64], scale: f64) {
        let u = self.model.unknowns();
        for (j, node) in self.deformation.nodes.iter_mut().enumerate() {
            self.model.shift(node, &step[u * j..u * (j + 1)], scale);
        }
    }

    /// Minimises E by Gauss-Newton from the current node transforms (a step that raises E is
    /// halved, up to four times; ElasticFusion keeps it). Returns the energy before and after
    /// and the factorisations run.
    pub fn optimise(&mut self, w: &GraphWeights) -> Result<Solution, StageError> {
        let n = self.unknowns();
        let before = self.energy(w);
        if n == 0 {
            return Ok(Solution { energy_before: before, energy_after: before, factorisations: 0 });
        }
        let mut normal = self.normal_pattern(w, n)?;
        let mut llt = SparseLlt::new(normal.a.symbolic(), SIMPLICIAL).map_err(solver_error)?;
        let mut current = before;
        let mut factorisations = 0;
        for _ in 0..w.iterations {
            let g = self.assemble(w, &mut normal);
            llt.factorize(normal.a.as_ref()).map_err(solver_error)?;
            factorisations += 1;
            let mut step: Vec<f64> = g.iter().map(|v| -v).collect();
            llt.solve_in_place(&mut step).map_err(solver_error)?;
            let improved = self.line_search(w, &step, &mut current);
            if !improved || current < 1e-18 {
                break;
            }
        }
        Ok(Solution { energy_before: before, energy_after: current, factorisations })
    }

    /// The sparsity pattern of JᵀJ (every pair of unknowns that share a residual, plus the
    /// diagonal) and where each product of a row's Jacobian entries lands in it, in visiting
    /// order: the rows' structure never changes, so the searches are done once per graph.
    pub(crate) fn normal_pattern(&self, w: &GraphWeights, n: usize) -> Result<NormalPattern, StageError> {
        let mut pairs: Vec<(usize, usize)> = (0..n).map(|k| (k, k)).collect();
        self.visit(w, |_, row| {
            for &(a, _) in row {
                for &(b, _) in row {
                    if a >= b {
                        pairs.push((a, b));
                    }
                }
            }
        });
        pairs.sort_unstable_by_key(|&(r, c)| (c, r));
        pairs.dedup();
        let trips: Vec<Triplet<usize, usize, f64>> = pairs.iter().map(|&(r, c)| Triplet::new(r, c, 0.0)).collect();
        let a = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &trips).map_err(solver_error)?;
        let col_ptr: Vec<usize> = a.symbolic().col_ptr().to_vec();
        let row_idx: Vec<usize> = a.symbolic().row_idx().to_vec();
        let slot = |r: usize, c: usize| -> usize {
            let (lo, hi) = (col_ptr[c], col_ptr[c + 1]);
            lo + row_idx[lo..hi].partition_point(|&x| x < r)
        };
        let mut slots = Vec::new();
        self.visit(w, |_, row| {
            for &(i, _) in row {
                for &(k, _) in row {
                    if i >= k {
                        slots.push(slot(i, k));
                    }
                }
            }
        });
        let diag: Vec<usize> = (0..n).map(|k| slot(k, k)).collect();
        Ok(NormalPattern { a, slots, diag })
    }

    /// Fills JᵀJ (lower triangle) into the pattern's values and returns the gradient Jᵀr.
    pub(crate) fn assemble(&self, w: &GraphWeights, normal: &mut NormalPattern) -> Vec<f64> {
        let n = normal.diag.len();
        let vals = normal.a.val_mut();
        vals.iter_mut().for_each(|v| *v = 0.0);
        let mut g = vec![0.0; n];
        let mut next = normal.slots.iter();
        self.visit(w, |r, row| {
            for &(i, ji) in row {
                g[i] += ji * r;
                for &(k, jk) in row {
                    if i >= k
                        && let Some(&s) = next.next()
                    {
                        vals[s] += ji * jk;
                    }
                }
            }
        });
        // A tiny Levenberg term keeps nodes without constraints or edges solvable.
        for &s in &normal.diag {
            vals[s] += 1e-9;
        }
        g
    }

    /// Takes `step`, halved up to four times until E falls below `current` (updated); false
    /// when no step lowered E by more than a relative 1e-9.
    fn line_search(&mut self, w: &GraphWeights, step: &[f64], current: &mut f64) -> bool {
        let mut scale = 1.0;
        for _ in 0..5 {
            self.shift(step, scale);
            let e = self.energy(w);
            if e.is_finite() && e < *current {
                let small = *current - e < 1e-9 * current.max(1e-300);
                *current = e;
                return !small;
            }
            self.shift(step, -scale);
            scale *= 0.5;
        }
        false
    }
}

/// The normal equations' sparsity pattern and where each Jacobian product lands in it.
pub(crate) struct NormalPattern {
    pub(crate) a: SparseColMat<usize, f64>,
    /// Value slot of each lower-triangle product, in [`Graph::visit`] order.
    slots: Vec<usize>,
    /// Value slot of each diagonal entry.
    diag: Vec<usize>,
}

/// What an optimisation did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Solution {
    /// E before.
    pub energy_before: f64,
    /// E after.
    pub energy_after: f64,
    /// Sparse factorisations run.
    pub factorisations: usize,
}

fn solver_error(e: impl std::fmt::Display) -> StageError {
    StageError::invalid_input(format!("deformation: sparse Cholesky failed: {e}"))
}

#[cfg(test)]
mod tests;
