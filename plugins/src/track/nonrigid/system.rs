//! The normal equations of the joint solve, `JᵀWJ δ = −JᵀWr`, in faer's sparse column format:
//! 12 unknowns per node (the ED graph's order), then the camera's 6 (an arrowhead: the camera
//! couples to every node). Data terms are gathered per pixel into dense 12 × 12 node-pair blocks
//! and scattered once per iteration; the graph's own rows (`E_rot`, `E_reg`) land through slots
//! found once per pattern. The sparse Cholesky's symbolic analysis is kept while the pattern
//! (nodes, edges and the node pairs the pixels couple) stays the same.

use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use nalgebra::{Matrix3, Vector3, Vector6};

use crate::common::ed_graph::UNKNOWNS;
use crate::common::sparse_llt::{SparseLlt, SparseLltError};

/// Where each block of the normal matrix lives in the sparse values.
pub struct Pattern {
    /// The matrix (lower triangle), values overwritten per iteration.
    pub a: SparseColMat<usize, f64>,
    nodes: usize,
    camera: bool,
    /// The node pairs (i ≥ j), sorted by (j, i): a block's id is its index.
    blocks: Vec<(usize, usize)>,
    /// Where column node j's blocks start in `blocks` (`nodes + 1` entries).
    column_start: Vec<usize>,
    /// Value slot of each entry of each block (`12 a + b`: row a of node i, column b of node
    /// j); `usize::MAX` for the upper half of a diagonal block.
    block_slots: Vec<usize>,
    /// Value slots of the camera rows against each node's columns (`12 c + b`).
    camera_slots: Vec<usize>,
    /// Value slots of the camera block's lower triangle (`6 r + c`, `usize::MAX` above).
    camera_block: [usize; 36],
}

impl Pattern {
    /// The pattern of `nodes` nodes coupled in the given pairs (any order; the diagonal is
    /// always there), with a camera block when `camera`. The compressed columns are laid out
    /// directly from the sorted block list (rows ascending in every column, no triplet sort),
    /// and every block entry's value slot is recorded on the way.
    pub fn new(nodes: usize, pairs: &[(usize, usize)], camera: bool) -> Self {
        let mut blocks: Vec<(usize, usize)> = (0..nodes).map(|i| (i, i)).chain(pairs.iter().map(|&(i, j)| (i.max(j), i.min(j)))).collect();
        blocks.sort_unstable_by_key(|&(i, j)| (j, i));
        blocks.dedup();
        let cam0 = UNKNOWNS * nodes;
        let n = cam0 + if camera { 6 } else { 0 };
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(blocks.len() * 144 + if camera { nodes * 72 + 21 } else { 0 });
        let mut block_slots = vec![usize::MAX; blocks.len() * 144];
        let mut camera_slots = if camera { vec![usize::MAX; nodes * 72] } else { Vec::new() };
        let mut camera_block = [usize::MAX; 36];
        // Blocks sorted by (column node j, row node i ≥ j): each column's diagonal block first.
        let mut start = 0;
        let mut column_start = Vec::with_capacity(nodes + 1);
        for j in 0..nodes {
            column_start.push(start);
            let end = start + blocks[start..].iter().take_while(|b| b.1 == j).count();
            for b in 0..UNKNOWNS {
                col_ptr.push(row_idx.len());
                for (id, &(i, _)) in blocks.iter().enumerate().take(end).skip(start) {
                    for a in (if i == j { b } else { 0 })..UNKNOWNS {
                        block_slots[144 * id + UNKNOWNS * a + b] = row_idx.len();
                        row_idx.push(UNKNOWNS * i + a);
                    }
                }
                if camera {
                    for c in 0..6 {
                        camera_slots[72 * j + UNKNOWNS * c + b] = row_idx.len();
                        row_idx.push(cam0 + c);
                    }
                }
            }
            start = end;
        }
        column_start.push(start);
        if camera {
            for c in 0..6 {
                col_ptr.push(row_idx.len());
                for r in c..6 {
                    camera_block[6 * r + c] = row_idx.len();
                    row_idx.push(cam0 + r);
                }
            }
        }
        col_ptr.push(row_idx.len());
        let values = vec![0.0; row_idx.len()];
        let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        Self { a: SparseColMat::new(symbolic, values), nodes, camera, blocks, column_start, block_slots, camera_slots, camera_block }
    }

    /// Unknowns in all.
    pub fn unknowns(&self) -> usize {
        self.a.nrows()
    }

    /// The block id of the node pair (either order), if it is in the pattern.
    pub fn block(&self, i: usize, j: usize) -> Option<usize> {
        let (i, j) = (i.max(j), i.min(j));
        let (lo, hi) = (*self.column_start.get(j)?, *self.column_start.get(j + 1)?);
        let column = &self.blocks[lo..hi];
        let at = column.partition_point(|b| b.0 < i);
        (at < column.len() && column[at].0 == i).then_some(lo + at)
    }

    /// The value slot of entry (row, col) of the lower triangle.
    pub fn slot(&self, row: usize, col: usize) -> Option<usize> {
        let (row, col) = (row.max(col), row.min(col));
        let sym = self.a.symbolic();
        let (lo, hi) = (sym.col_ptr()[col], sym.col_ptr()[col + 1]);
        let idx = &sym.row_idx()[lo..hi];
        let at = idx.partition_point(|&x| x < row);
        (at < idx.len() && idx[at] == row).then_some(lo + at)
    }

    /// Whether two patterns have the same structure (so one analysis serves both).
    pub fn same_structure(&self, other: &Pattern) -> bool {
        let (a, b) = (self.a.symbolic(), other.a.symbolic());
        a.nrows() == b.nrows() && a.col_ptr() == b.col_ptr() && a.row_idx() == b.row_idx()
    }

    /// A zeroed accumulator for this pattern.
    pub fn accumulator(&self) -> Accumulator {
        Accumulator {
            blocks: vec![[0.0; 144]; self.blocks.len()],
            camera_node: if self.camera { vec![[0.0; 72]; self.nodes] } else { Vec::new() },
            camera: [0.0; 36],
            g: vec![0.0; self.unknowns()],
            energy: 0.0,
        }
    }

    /// Writes the accumulated data blocks into the matrix values (zeroing the rest) and
    /// returns the gradient.
    pub fn scatter(&mut self, acc: &Accumulator) -> Vec<f64> {
        let vals = self.a.val_mut();
        vals.iter_mut().for_each(|v| *v = 0.0);
        for (id, block) in acc.blocks.iter().enumerate() {
            for (e, v) in block.iter().enumerate() {
                let s = self.block_slots[144 * id + e];
                if s != usize::MAX {
                    vals[s] += v;
                }
            }
        }
        for (j, block) in acc.camera_node.iter().enumerate() {
            for (e, v) in block.iter().enumerate() {
                vals[self.camera_slots[72 * j + e]] += v;
            }
        }
        for (e, v) in acc.camera.iter().enumerate() {
            if self.camera_block[e] != usize::MAX {
                vals[self.camera_block[e]] += v;
            }
        }
        acc.g.clone()
    }
}

/// One residual of a model point whose warped position x̃ it depends on linearly: gradient `a`
/// with respect to x̃ (world frame), camera row, value and weight. Its Jacobian entries for a
/// bound node k are `w_k (e_k ⊗ a)`, `e_k = [x − g_k; 1]` (`energy::node_row`).
#[derive(Debug, Clone, Copy)]
pub struct Residual {
    /// ∂r/∂x̃.
    pub a: Vector3<f64>,
    /// ∂r/∂ξ (ignored without a camera block).
    pub camera: Vector6<f64>,
    /// The residual.
    pub r: f64,
    /// Its weight.
    pub w: f64,
}

/// The weighted sums of one model point's residuals that its normal-equation blocks need: all
/// its residuals share the node factors `w_k e_k`, so a node pair's block is
/// `(w_k e_k)(w_l e_l)ᵀ ⊗ Σ W a aᵀ` and the point's residuals enter the blocks once.
#[derive(Debug, Clone, Copy, Default)]
pub struct PointSums {
    /// Σ W a aᵀ.
    aa: Matrix3<f64>,
    /// Σ W c aᵀ (camera rows × gradient).
    ca: nalgebra::Matrix6x3<f64>,
    /// Σ W c cᵀ.
    cc: nalgebra::Matrix6<f64>,
    /// Σ W r a.
    ra: Vector3<f64>,
    /// Σ W r c.
    rc: Vector6<f64>,
    /// Σ W r².
    energy: f64,
    /// Residuals added.
    pub count: usize,
}

impl PointSums {
    /// Adds one residual.
    pub fn add(&mut self, q: &Residual) {
        let wa = q.w * q.a;
        self.aa += wa * q.a.transpose();
        self.ca += q.camera * wa.transpose();
        self.cc += q.w * q.camera * q.camera.transpose();
        self.ra += q.r * wa;
        self.rc += q.w * q.r * q.camera;
        self.energy += q.w * q.r * q.r;
        self.count += 1;
    }
}

/// JᵀWJ in dense blocks and JᵀWr, summed over residuals.
#[derive(Clone)]
pub struct Accumulator {
    blocks: Vec<[f64; 144]>,
    camera_node: Vec<[f64; 72]>,
    camera: [f64; 36],
    /// JᵀWr.
    pub g: Vec<f64>,
    /// Σ w r².
    pub energy: f64,
}

impl Accumulator {
    /// Adds one model point's residuals (`sums`), bound to `nodes` (solve index, `w_k [x − g_k;
    /// 1]`) whose pair blocks are `pairs[k (k + 1) / 2 + l]` for l ≤ k in binding order.
    pub fn add_point(&mut self, nodes: &[(usize, [f64; 4])], pairs: &[usize], sums: &PointSums) {
        self.energy += sums.energy;
        let has_camera = !self.camera_node.is_empty();
        let m = &sums.aa;
        for (k, &(i, uk)) in nodes.iter().enumerate() {
            let g = &mut self.g[UNKNOWNS * i..UNKNOWNS * (i + 1)];
            for col in 0..4 {
                for axis in 0..3 {
                    g[3 * col + axis] += uk[col] * sums.ra[axis];
                }
            }
            for (l, &(j, ul)) in nodes.iter().enumerate().take(k + 1) {
                let block = &mut self.blocks[pairs[k * (k + 1) / 2 + l]];
                // Row entries belong to the larger node index of the block; a diagonal block's
                // upper half is never scattered (`Pattern::scatter`).
                let (ur, uc) = if i >= j { (uk, ul) } else { (ul, uk) };
                let diagonal = k == l;
                for ca in 0..4 {
                    for cb in 0..(if diagonal { ca + 1 } else { 4 }) {
                        let f = ur[ca] * uc[cb];
                        for aa in 0..3 {
                            let row = &mut block[UNKNOWNS * (3 * ca + aa) + 3 * cb..UNKNOWNS * (3 * ca + aa) + 3 * cb + 3];
                            for (ab, e) in row.iter_mut().enumerate() {
                                *e += f * m[(aa, ab)];
                            }
                        }
                    }
                }
            }
            if has_camera {
                let block = &mut self.camera_node[i];
                for c in 0..6 {
                    for col in 0..4 {
                        for axis in 0..3 {
                            block[UNKNOWNS * c + 3 * col + axis] += uk[col] * sums.ca[(c, axis)];
                        }
                    }
                }
            }
        }
        if has_camera {
            let base = self.g.len() - 6;
            for c in 0..6 {
                self.g[base + c] += sums.rc[c];
                for d in 0..=c {
                    self.camera[6 * c + d] += sums.cc[(c, d)];
                }
            }
        }
    }

    /// Adds another accumulator of the same pattern.
    pub fn merge(&mut self, o: &Accumulator) {
        for (a, b) in self.blocks.iter_mut().zip(&o.blocks) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
        for (a, b) in self.camera_node.iter_mut().zip(&o.camera_node) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
        self.camera.iter_mut().zip(&o.camera).for_each(|(x, y)| *x += y);
        self.g.iter_mut().zip(&o.g).for_each(|(x, y)| *x += y);
        self.energy += o.energy;
    }
}

/// The factorisation, kept across frames while the pattern's structure is unchanged.
pub struct Factor {
    llt: SparseLlt,
}

impl Factor {
    /// Analyses `pattern`.
    pub fn new(pattern: &Pattern) -> Result<Self, SparseLltError> {
        Ok(Self { llt: SparseLlt::new(pattern.a.symbolic(), false)? })
    }

    /// Solves `A δ = −g` for the pattern's current values.
    pub fn solve(&mut self, pattern: &Pattern, g: &[f64]) -> Result<Vec<f64>, SparseLltError> {
        self.llt.factorize(pattern.a.as_ref())?;
        let mut step: Vec<f64> = g.iter().map(|v| -v).collect();
        self.llt.solve_in_place(&mut step)?;
        Ok(step)
    }
}
