//! The normal equations of the joint solve, `JᵀWJ δ = −JᵀWr`, in faer's sparse column format:
//! the unknowns of every node (12 for an affine node, 6 for a twist; the ED graph's order,
//! `crate::common::ed_graph::NodeModel`), then the camera's 6 (an arrowhead: the camera couples
//! to every node). Data terms are gathered per pixel into dense node-pair blocks and scattered
//! once per iteration; the graph's own rows (`E_rot`, `E_reg`) land through slots found once per
//! pattern. The sparse Cholesky's symbolic analysis is kept while the pattern (nodes, edges and
//! the node pairs the pixels couple) stays the same; its fill-reducing ordering is AMD's on the
//! node graph, each node's unknowns together and the camera's last.

use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use nalgebra::{Matrix3, Vector3, Vector6};

use crate::common::ed_graph::NodeModel;
use crate::common::sparse_llt::{SparseLlt, SparseLltError};

/// Where each block of the normal matrix lives in the sparse values.
pub struct Pattern {
    /// The matrix (lower triangle), values overwritten per iteration.
    pub a: SparseColMat<usize, f64>,
    nodes: usize,
    camera: bool,
    model: NodeModel,
    /// The node pairs (i ≥ j), sorted by (j, i): a block's id is its index.
    blocks: Vec<(usize, usize)>,
    /// Where column node j's blocks start in `blocks` (`nodes + 1` entries).
    column_start: Vec<usize>,
    /// Value slot of each entry of each block (`u² id + u a + b`, u the unknowns per node: row
    /// a of node i, column b of node j); `usize::MAX` for the upper half of a diagonal block.
    block_slots: Vec<usize>,
    /// Value slots of the camera rows against each node's columns (`6 u j + u c + b`).
    camera_slots: Vec<usize>,
    /// Value slots of the camera block's lower triangle (`6 r + c`, `usize::MAX` above).
    camera_block: [usize; 36],
}

impl Pattern {
    /// The pattern of `nodes` nodes coupled in the given pairs (any order; the diagonal is
    /// always there), with a camera block when `camera`. The compressed columns are laid out
    /// directly from the sorted block list (rows ascending in every column, no triplet sort),
    /// and every block entry's value slot is recorded on the way.
    pub fn new(nodes: usize, pairs: &[(usize, usize)], camera: bool, model: NodeModel) -> Self {
        // Tens of thousands of pairs (each model point's), most of them repeated: the distinct
        // row nodes of each column node (a stamp per row node), then each column's few sorted.
        let mut rows_of: Vec<Vec<usize>> = (0..nodes).map(|j| vec![j]).collect();
        for &(a, b) in pairs {
            rows_of[a.min(b)].push(a.max(b));
        }
        let mut stamp = vec![usize::MAX; nodes];
        for (j, rows) in rows_of.iter_mut().enumerate() {
            rows.retain(|&i| std::mem::replace(&mut stamp[i], j) != j);
            rows.sort_unstable();
        }
        let blocks: Vec<(usize, usize)> = rows_of.iter().enumerate().flat_map(|(j, rows)| rows.iter().map(move |&i| (i, j))).collect();
        let u = model.unknowns();
        let cam0 = u * nodes;
        let n = cam0 + if camera { 6 } else { 0 };
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(blocks.len() * u * u + if camera { nodes * 6 * u + 21 } else { 0 });
        let mut block_slots = vec![usize::MAX; blocks.len() * u * u];
        let mut camera_slots = if camera { vec![usize::MAX; nodes * 6 * u] } else { Vec::new() };
        let mut camera_block = [usize::MAX; 36];
        // Blocks sorted by (column node j, row node i ≥ j): each column's diagonal block first.
        let mut start = 0;
        let mut column_start = Vec::with_capacity(nodes + 1);
        for j in 0..nodes {
            column_start.push(start);
            let end = start + blocks[start..].iter().take_while(|b| b.1 == j).count();
            for b in 0..u {
                col_ptr.push(row_idx.len());
                for (id, &(i, _)) in blocks.iter().enumerate().take(end).skip(start) {
                    for a in (if i == j { b } else { 0 })..u {
                        block_slots[u * u * id + u * a + b] = row_idx.len();
                        row_idx.push(u * i + a);
                    }
                }
                if camera {
                    for c in 0..6 {
                        camera_slots[6 * u * j + u * c + b] = row_idx.len();
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
        Self { a: SparseColMat::new(symbolic, values), nodes, camera, model, blocks, column_start, block_slots, camera_slots, camera_block }
    }

    /// Analyses the pattern with scalar AMD (`block = false`, faer's own ordering) or AMD on the
    /// node graph ([`SparseLlt::blocked`], what [`Factor::new`] does): the two orderings that the
    /// `nonrigid-analysis` criterion bench times.
    pub fn analyse(&self, block: bool) -> Result<SparseLlt, SparseLltError> {
        let tail = if self.camera { 6 } else { 0 };
        match block {
            true => SparseLlt::blocked(self.a.symbolic(), self.nodes, self.model.unknowns(), &self.blocks, tail),
            false => SparseLlt::new(self.a.symbolic(), false),
        }
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
        let u = self.model.unknowns();
        Accumulator {
            model: self.model,
            blocks: vec![0.0; self.blocks.len() * u * u],
            camera_node: if self.camera { vec![0.0; self.nodes * 6 * u] } else { Vec::new() },
            camera: [0.0; 36],
            g: vec![0.0; self.unknowns()],
        }
    }

    /// Writes the data blocks of the chunk accumulators `parts`, summed in order, into the
    /// matrix values (zeroing the rest) and returns the gradient: per entry `((p₀ + p₁) + p₂) +
    /// …`, the sums of merging the parts into a zeroed accumulator and scattering it, in one
    /// pass and without that accumulator.
    pub fn scatter(&mut self, parts: &[Accumulator]) -> Vec<f64> {
        self.scatter_blocks(parts);
        self.gradient(parts)
    }

    /// The gradient of the chunk accumulators `parts`, summed in order (as `scatter`).
    pub fn gradient(&self, parts: &[Accumulator]) -> Vec<f64> {
        (0..self.unknowns()).map(|u| parts.iter().fold(0.0, |acc, p| acc + p.g[u])).collect()
    }

    fn scatter_blocks(&mut self, parts: &[Accumulator]) {
        let vals = self.a.val_mut();
        vals.iter_mut().for_each(|v| *v = 0.0);
        let sum = |at: usize, of: fn(&Accumulator) -> &[f64]| parts.iter().fold(0.0, |acc, p| acc + of(p)[at]);
        for (e, &s) in self.block_slots.iter().enumerate() {
            if s != usize::MAX {
                vals[s] = sum(e, |p| &p.blocks);
            }
        }
        for (e, &s) in self.camera_slots.iter().enumerate() {
            vals[s] = sum(e, |p| &p.camera_node);
        }
        for e in 0..36 {
            if self.camera_block[e] != usize::MAX {
                vals[self.camera_block[e]] = sum(e, |p| &p.camera);
            }
        }
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
        self.count += 1;
    }

    /// Adds one residual to the gradient's sums alone (`ra`, `rc`: all
    /// [`Accumulator::add_point_gradient`] reads), as [`PointSums::add`] does.
    pub fn add_gradient(&mut self, q: &Residual) {
        let wa = q.w * q.a;
        self.ra += q.r * wa;
        self.rc += q.w * q.r * q.camera;
        self.count += 1;
    }
}

/// The most nodes a model point is bound to (the `k` parameter's range).
pub const MAX_BINDINGS: usize = 8;

/// A model point's tie to one of its nodes: the node's solve index, its weight `w_k` and the
/// point's offset from it, `v = x − g_k` for an affine node and `R_k (x − g_k)` for a twist (the
/// node's current rotation applied).
#[derive(Debug, Clone, Copy)]
pub struct NodeFactor {
    /// Solve index of the node.
    pub node: usize,
    /// The point's weight on it.
    pub w: f64,
    /// The offset (see above).
    pub v: Vector3<f64>,
}

impl NodeFactor {
    /// The twist node's `∂x̃/∂(t, ω)` transposed, `B = w [I; [v]×]` (6 × 3): a residual of world
    /// gradient a has the node entries `B a = w [a; v × a]`.
    fn twist_rows(&self) -> [[f64; 3]; 6] {
        let (w, v) = (self.w, self.v);
        [[w, 0.0, 0.0], [0.0, w, 0.0], [0.0, 0.0, w], [0.0, -w * v.z, w * v.y], [w * v.z, 0.0, -w * v.x], [-w * v.y, w * v.x, 0.0]]
    }
}

/// JᵀWJ in dense blocks and JᵀWr, summed over residuals.
#[derive(Clone)]
pub struct Accumulator {
    model: NodeModel,
    /// Node-pair blocks, u² values each (row-major, u the unknowns per node).
    blocks: Vec<f64>,
    /// Camera rows against each node's columns, 6 u values per node.
    camera_node: Vec<f64>,
    camera: [f64; 36],
    /// JᵀWr.
    pub g: Vec<f64>,
}

impl Accumulator {
    /// Adds one model point's residuals (`sums`), bound to `nodes`, whose pair blocks are
    /// `pairs[k (k + 1) / 2 + l]` for l ≤ k in binding order.
    pub fn add_point(&mut self, nodes: &[NodeFactor], pairs: &[usize], sums: &PointSums) {
        self.add_point_gradient(nodes, sums);
        match self.model {
            NodeModel::Affine => self.add_affine(nodes, pairs, sums),
            NodeModel::Twist => self.add_twist(nodes, pairs, sums),
        }
        if !self.camera_node.is_empty() {
            for c in 0..6 {
                for d in 0..=c {
                    self.camera[6 * c + d] += sums.cc[(c, d)];
                }
            }
        }
    }

    /// The affine nodes' blocks in Kronecker form: node k's entries are `u_k ⊗ a`, `u_k = w_k
    /// [v; 1]`, so a pair's block is `u_k u_lᵀ ⊗ Σ W a aᵀ`.
    fn add_affine(&mut self, nodes: &[NodeFactor], pairs: &[usize], sums: &PointSums) {
        const U: usize = 12;
        let has_camera = !self.camera_node.is_empty();
        let m = &sums.aa;
        let factor = |f: &NodeFactor| [f.w * f.v.x, f.w * f.v.y, f.w * f.v.z, f.w];
        for (k, fk) in nodes.iter().enumerate() {
            let (i, uk) = (fk.node, factor(fk));
            for (l, fl) in nodes.iter().enumerate().take(k + 1) {
                let (j, ul) = (fl.node, factor(fl));
                let block = &mut self.blocks[U * U * pairs[k * (k + 1) / 2 + l]..][..U * U];
                // Row entries belong to the larger node index of the block; a diagonal block's
                // upper half is never scattered (`Pattern::scatter`).
                let (ur, uc) = if i >= j { (uk, ul) } else { (ul, uk) };
                let diagonal = k == l;
                for ca in 0..4 {
                    for cb in 0..(if diagonal { ca + 1 } else { 4 }) {
                        let f = ur[ca] * uc[cb];
                        for aa in 0..3 {
                            let row = &mut block[U * (3 * ca + aa) + 3 * cb..U * (3 * ca + aa) + 3 * cb + 3];
                            for (ab, e) in row.iter_mut().enumerate() {
                                *e += f * m[(aa, ab)];
                            }
                        }
                    }
                }
            }
            if has_camera {
                let block = &mut self.camera_node[6 * U * i..][..6 * U];
                for c in 0..6 {
                    for col in 0..4 {
                        for axis in 0..3 {
                            block[U * c + 3 * col + axis] += uk[col] * sums.ca[(c, axis)];
                        }
                    }
                }
            }
        }
    }

    /// The twist nodes' blocks: node k's entries are `B_k a` ([`NodeFactor::twist_rows`]), so a
    /// pair's block is `B_k (Σ W a aᵀ) B_lᵀ`.
    fn add_twist(&mut self, nodes: &[NodeFactor], pairs: &[usize], sums: &PointSums) {
        const U: usize = 6;
        let has_camera = !self.camera_node.is_empty();
        // B_k and P_k = B_k M (6 × 3) on the stack: a point has at most `MAX_BINDINGS` nodes.
        let mut rows = [[[0.0; 3]; 6]; MAX_BINDINGS];
        let mut products = [[[0.0; 3]; 6]; MAX_BINDINGS];
        let nodes = &nodes[..nodes.len().min(MAX_BINDINGS)];
        for (k, f) in nodes.iter().enumerate() {
            rows[k] = f.twist_rows();
            for (p, b) in products[k].iter_mut().zip(&rows[k]) {
                *p = std::array::from_fn(|c| b[0] * sums.aa[(0, c)] + b[1] * sums.aa[(1, c)] + b[2] * sums.aa[(2, c)]);
            }
        }
        for (k, fk) in nodes.iter().enumerate() {
            let i = fk.node;
            for (l, fl) in nodes.iter().enumerate().take(k + 1) {
                let block = &mut self.blocks[U * U * pairs[k * (k + 1) / 2 + l]..][..U * U];
                // Rows belong to the larger node index of the block.
                let (p, b) = if i >= fl.node { (&products[k], &rows[l]) } else { (&products[l], &rows[k]) };
                for r in 0..U {
                    for c in 0..U {
                        block[U * r + c] += p[r][0] * b[c][0] + p[r][1] * b[c][1] + p[r][2] * b[c][2];
                    }
                }
            }
            if has_camera {
                let block = &mut self.camera_node[6 * U * i..][..6 * U];
                for c in 0..6 {
                    for col in 0..U {
                        block[U * c + col] += (0..3).map(|x| sums.ca[(c, x)] * rows[k][col][x]).sum::<f64>();
                    }
                }
            }
        }
    }

    /// Adds one model point's residuals to the gradient `JᵀWr` alone (all an iteration that
    /// keeps an earlier factorised matrix needs; `add_point` adds the blocks besides).
    pub fn add_point_gradient(&mut self, nodes: &[NodeFactor], sums: &PointSums) {
        match self.model {
            NodeModel::Affine => {
                for f in nodes {
                    let u = [f.w * f.v.x, f.w * f.v.y, f.w * f.v.z, f.w];
                    let g = &mut self.g[12 * f.node..12 * (f.node + 1)];
                    for col in 0..4 {
                        for axis in 0..3 {
                            g[3 * col + axis] += u[col] * sums.ra[axis];
                        }
                    }
                }
            }
            NodeModel::Twist => {
                for f in nodes {
                    for (g, b) in self.g[6 * f.node..6 * (f.node + 1)].iter_mut().zip(&f.twist_rows()) {
                        *g += b[0] * sums.ra[0] + b[1] * sums.ra[1] + b[2] * sums.ra[2];
                    }
                }
            }
        }
        if !self.camera_node.is_empty() {
            let base = self.g.len() - 6;
            for c in 0..6 {
                self.g[base + c] += sums.rc[c];
            }
        }
    }

    /// Zeroes the gradient alone (for `add_point_gradient`).
    pub fn reset_gradient(&mut self) {
        self.g.fill(0.0);
    }

    /// Zeroes every sum, keeping the buffers (one accumulator per chunk serves every iteration).
    pub fn reset(&mut self) {
        self.blocks.fill(0.0);
        self.camera_node.fill(0.0);
        self.camera = [0.0; 36];
        self.g.fill(0.0);
    }
}

/// The factorisation, kept across frames while the pattern's structure is unchanged.
pub struct Factor {
    llt: SparseLlt,
}

impl Factor {
    /// Analyses `pattern`, ordered by AMD on its node graph with the camera last
    /// ([`SparseLlt::blocked`]: the scalar AMD's analysis took 2.3 ms a frame on the phantom's
    /// 90-odd affine nodes, this one 1.3 ms, with the same factorisation time).
    pub fn new(pattern: &Pattern) -> Result<Self, SparseLltError> {
        Ok(Self { llt: pattern.analyse(true)? })
    }

    /// Solves `A δ = −g` for the pattern's current values.
    pub fn solve(&mut self, pattern: &Pattern, g: &[f64]) -> Result<Vec<f64>, SparseLltError> {
        self.llt.factorize(pattern.a.as_ref())?;
        self.solve_kept(g)
    }

    /// Solves `Ã δ = −g` with the last factorised matrix Ã (the chord method's step: Ã from an
    /// earlier linearisation, `g` from the current one).
    pub fn solve_kept(&mut self, g: &[f64]) -> Result<Vec<f64>, SparseLltError> {
        let mut step: Vec<f64> = g.iter().map(|v| -v).collect();
        self.llt.solve_in_place(&mut step)?;
        Ok(step)
    }
}
