//! A sparse Cholesky factorisation that is analysed once and refactorised in place: faer's
//! symbolic analysis (AMD ordering) once per sparsity pattern, then per Gauss-Newton iteration a
//! numeric factorisation into the same buffers (no allocation) and an in-place solve. faer
//! picks the simplicial or the supernodal method by a flop heuristic; `simplicial` forces the
//! former (on the deformation graph, 64–4096 nodes, the heuristic's supernodal choice was 1.3–5×
//! faster, so callers leave it off unless they measured otherwise), and
//! [`SparseLlt::supernodal`] the latter (the heuristic picks the simplicial method for
//! `near-light-sfs`'s grid of 1 116 log depths, where the supernodal one is 2.3× faster).
//! [`SparseLlt::blocked`] orders a matrix of dense blocks by AMD on its block graph instead of
//! the scalar one.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{CholeskySymbolicParams, LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side};

/// What can go wrong: the analysis, the workspace or a matrix that is not positive definite.
#[derive(Debug, thiserror::Error)]
#[error("sparse Cholesky: {0}")]
pub struct SparseLltError(String);

/// A reusable LLᵀ factorisation of matrices with one sparsity pattern (lower triangle used).
pub struct SparseLlt {
    symbolic: SymbolicCholesky<usize>,
    values: Vec<f64>,
    factor_buf: MemBuffer,
    solve_buf: MemBuffer,
    factored: bool,
}

impl SparseLlt {
    /// Analyses `pattern` (square; its lower triangle is read); `simplicial` forces the
    /// simplicial method, otherwise faer chooses by its flop heuristic.
    pub fn new(pattern: SymbolicSparseColMatRef<'_, usize>, simplicial: bool) -> Result<Self, SparseLltError> {
        let method = if simplicial { SupernodalThreshold::FORCE_SIMPLICIAL } else { SupernodalThreshold::AUTO };
        Self::analysed(pattern, method, SymmetricOrdering::Amd)
    }

    /// [`SparseLlt::new`] with the supernodal method whatever faer's heuristic would choose.
    pub fn supernodal(pattern: SymbolicSparseColMatRef<'_, usize>) -> Result<Self, SparseLltError> {
        Self::analysed(pattern, SupernodalThreshold::FORCE_SUPERNODAL, SymmetricOrdering::Amd)
    }

    /// [`SparseLlt::new`] for a matrix of dense blocks: `blocks` blocks of `block` unknowns
    /// each (block b's are `block·b .. block·(b+1)`), coupled in the lower-triangle `pairs`
    /// `(i ≥ j)`, then `tail` unknowns coupled to everything (a camera's, last). The fill-
    /// reducing ordering is AMD's on the block graph, each block's unknowns kept together and
    /// the tail last, much as scalar AMD orders such a matrix (it finds the blocks as
    /// supervariables and defers the dense tail), for the cost of ordering a graph `block²`
    /// times smaller. The fill is not always the same: on the warp solve's patterns it is
    /// within 0.4 % and on the solver bench's patches identical, but on a grid of blocks
    /// coupled to their four neighbours alone it was 31 % larger. `pattern` must be the scalar
    /// pattern of that block structure.
    pub fn blocked(
        pattern: SymbolicSparseColMatRef<'_, usize>,
        blocks: usize,
        block: usize,
        pairs: &[(usize, usize)],
        tail: usize,
    ) -> Result<Self, SparseLltError> {
        let n = blocks * block + tail;
        if pattern.nrows() != n || pattern.ncols() != n {
            return Err(SparseLltError(format!("a {}×{} pattern for {blocks} blocks of {block} and {tail} more unknowns", pattern.nrows(), pattern.ncols())));
        }
        let order = block_order(blocks, pairs)?;
        let fwd: Vec<usize> = order.iter().flat_map(|&b| block * b..block * (b + 1)).chain(blocks * block..n).collect();
        let mut inv = vec![0; n];
        for (k, &i) in fwd.iter().enumerate() {
            inv[i] = k;
        }
        Self::analysed(pattern, SupernodalThreshold::AUTO, SymmetricOrdering::Custom(PermRef::new_checked(&fwd, &inv, n)))
    }

    fn analysed(
        pattern: SymbolicSparseColMatRef<'_, usize>,
        method: SupernodalThreshold,
        ordering: SymmetricOrdering<'_, usize>,
    ) -> Result<Self, SparseLltError> {
        let params = CholeskySymbolicParams { supernodal_flop_ratio_threshold: method, ..Default::default() };
        let symbolic = factorize_symbolic_cholesky(pattern, Side::Lower, ordering, params).map_err(|e| SparseLltError(format!("{e:?}")))?;
        let factor_req = symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default());
        let solve_req = symbolic.solve_in_place_scratch::<f64>(1, Par::Seq);
        let buffer = |req| MemBuffer::try_new(req).map_err(|e| SparseLltError(format!("workspace: {e:?}")));
        Ok(Self { values: vec![0.0; symbolic.len_val()], factor_buf: buffer(factor_req)?, solve_buf: buffer(solve_req)?, symbolic, factored: false })
    }

    /// Values of the Cholesky factor the analysis laid out (its fill-in included).
    pub fn factor_len(&self) -> usize {
        self.symbolic.len_val()
    }

    /// Factorises `a`, which must have the analysed pattern.
    pub fn factorize(&mut self, a: SparseColMatRef<'_, usize, f64>) -> Result<(), SparseLltError> {
        self.factored = false;
        self.symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.values,
                a,
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut self.factor_buf),
                Default::default(),
            )
            .map_err(|e| SparseLltError(format!("{e:?}")))?;
        self.factored = true;
        Ok(())
    }

    /// Solves `A x = rhs` in place with the last factorisation.
    pub fn solve_in_place(&mut self, rhs: &mut [f64]) -> Result<(), SparseLltError> {
        if !self.factored || rhs.len() != self.symbolic.nrows() {
            return Err(SparseLltError(format!("solve without a factorisation or with {} values for {} unknowns", rhs.len(), self.symbolic.nrows())));
        }
        let n = rhs.len();
        LltRef::new(&self.symbolic, &self.values).solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(rhs, n, 1),
            Par::Seq,
            MemStack::new(&mut self.solve_buf),
        );
        Ok(())
    }
}

/// AMD's elimination order of `blocks` vertices joined by `pairs` (either order; repeats and
/// self-pairs allowed): `order[k]` is the vertex eliminated k-th.
fn block_order(blocks: usize, pairs: &[(usize, usize)]) -> Result<Vec<usize>, SparseLltError> {
    let mut rows_of: Vec<Vec<usize>> = vec![Vec::new(); blocks];
    for &(a, b) in pairs {
        let (i, j) = (a.max(b), a.min(b));
        if i >= blocks {
            return Err(SparseLltError(format!("block pair ({a}, {b}) beyond {blocks} blocks")));
        }
        if i != j {
            rows_of[j].push(i);
        }
    }
    let mut col_ptr = Vec::with_capacity(blocks + 1);
    let mut row_idx = Vec::new();
    for (j, rows) in rows_of.iter_mut().enumerate() {
        rows.push(j);
        rows.sort_unstable();
        rows.dedup();
        col_ptr.push(row_idx.len());
        row_idx.extend_from_slice(rows);
    }
    col_ptr.push(row_idx.len());
    let graph = SymbolicSparseColMat::new_checked(blocks, blocks, col_ptr, None, row_idx);
    let (mut order, mut inverse) = (vec![0usize; blocks], vec![0usize; blocks]);
    let mut scratch =
        MemBuffer::try_new(amd::order_scratch::<usize>(blocks, graph.row_idx().len())).map_err(|e| SparseLltError(format!("workspace: {e:?}")))?;
    amd::order(&mut order, &mut inverse, graph.as_ref(), amd::Control::default(), MemStack::new(&mut scratch)).map_err(|e| SparseLltError(format!("{e:?}")))?;
    Ok(order)
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::sparse::{SparseColMat, Triplet};

    /// The 1-D Laplacian plus the identity, n unknowns, lower triangle.
    fn tridiagonal(n: usize) -> SparseColMat<usize, f64> {
        let mut t = Vec::new();
        for i in 0..n {
            t.push(Triplet::new(i, i, 3.0));
            if i + 1 < n {
                t.push(Triplet::new(i + 1, i, -1.0));
            }
        }
        SparseColMat::try_new_from_triplets(n, n, &t).unwrap()
    }

    #[test]
    fn every_method_solves_and_refactorises() {
        let make = |a: &SparseColMat<usize, f64>, method: &str| match method {
            "simplicial" => SparseLlt::new(a.symbolic(), true),
            "auto" => SparseLlt::new(a.symbolic(), false),
            _ => SparseLlt::supernodal(a.symbolic()),
        };
        for method in ["simplicial", "auto", "supernodal"] {
            let a = tridiagonal(50);
            let mut llt = make(&a, method).unwrap();
            let mut x = vec![0.0; 50];
            assert!(llt.solve_in_place(&mut x).is_err(), "no factorisation yet");
            llt.factorize(a.as_ref()).unwrap();
            // A x = b with x* = (1, 2, ..., 50).
            let truth: Vec<f64> = (1..=50).map(f64::from).collect();
            let mut b: Vec<f64> = (0..50).map(|i| 3.0 * truth[i] - if i > 0 { truth[i - 1] } else { 0.0 } - if i < 49 { truth[i + 1] } else { 0.0 }).collect();
            llt.solve_in_place(&mut b).unwrap();
            assert!(b.iter().zip(&truth).all(|(x, t)| (x - t).abs() < 1e-10), "{method}: {b:?}");
            // The same pattern with other values.
            let mut scaled = a.clone();
            scaled.val_mut().iter_mut().for_each(|v| *v *= 2.0);
            llt.factorize(scaled.as_ref()).unwrap();
            let mut ones = vec![2.0; 50];
            llt.solve_in_place(&mut ones).unwrap();
            let mut expect = vec![2.0; 50];
            let mut check = make(&a, method).unwrap();
            check.factorize(a.as_ref()).unwrap();
            check.solve_in_place(&mut expect).unwrap();
            assert!(ones.iter().zip(&expect).all(|(x, e)| (2.0 * x - e).abs() < 1e-12));
        }
    }

    /// A positive-definite matrix of `side²` 12-unknown blocks on a 2-D grid, each coupled to
    /// about a dozen neighbours, and a 6-unknown tail coupled to every block (a camera): its
    /// lower triangle and the block pairs.
    fn grid_blocks(side: usize) -> (SparseColMat<usize, f64>, Vec<(usize, usize)>) {
        let (n, u) = (side * side, 12);
        let mut pairs = Vec::new();
        for y in 0..side {
            for x in 0..side {
                let b = y * side + x;
                pairs.push((b, b));
                // Within two nodes along x or y, one diagonally (a surface's k-nearest nodes).
                for (dx, dy) in [(1, 0), (2, 0), (0, 1), (0, 2), (1, 1), (-1, 1)] {
                    let (xx, yy) = (x as i64 + dx, y as i64 + dy);
                    if (0..side as i64).contains(&xx) && (0..side as i64).contains(&yy) {
                        pairs.push((yy as usize * side + xx as usize, b));
                    }
                }
            }
        }
        let value = |r: usize, c: usize| 0.05 * (((r * 31 + c * 17) % 13) as f64 - 6.0) / 6.0;
        let mut t = Vec::new();
        let total = n * u + 6;
        for &(i, j) in &pairs {
            for a in 0..u {
                for b in 0..u {
                    let (r, c) = (u * i + a, u * j + b);
                    if r > c {
                        t.push(Triplet::new(r, c, value(r, c)));
                    }
                }
            }
        }
        for r in n * u..total {
            for c in 0..r {
                t.push(Triplet::new(r, c, value(r, c)));
            }
        }
        // Diagonally dominant: off-diagonal entries are at most 0.05, and a row has at most
        // 13 · 12 + 6 of them (a tail row: `total`).
        (0..total).for_each(|i| t.push(Triplet::new(i, i, 8.0 + 0.05 * total as f64)));
        (SparseColMat::try_new_from_triplets(total, total, &t).unwrap(), pairs)
    }

    #[test]
    fn the_block_ordering_solves_as_the_scalar_one_with_no_more_fill() {
        let side = 7;
        let (a, pairs) = grid_blocks(side);
        let n = a.nrows();
        let rhs: Vec<f64> = (0..n).map(|i| ((i * 7) % 11) as f64 - 5.0).collect();
        let mut scalar = SparseLlt::new(a.symbolic(), false).unwrap();
        let mut blocked = SparseLlt::blocked(a.symbolic(), side * side, 12, &pairs, 6).unwrap();
        let (mut x_scalar, mut x_blocked) = (rhs.clone(), rhs.clone());
        scalar.factorize(a.as_ref()).unwrap();
        scalar.solve_in_place(&mut x_scalar).unwrap();
        blocked.factorize(a.as_ref()).unwrap();
        blocked.solve_in_place(&mut x_blocked).unwrap();
        let scale = x_scalar.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.01);
        assert!(x_scalar.iter().zip(&x_blocked).all(|(s, b)| (s - b).abs() < 1e-12 * scale), "the two orderings solve differently");
        // The residual of the blocked solve against A (lower triangle mirrored).
        let mut ax = vec![0.0; n];
        for j in 0..n {
            for (i, v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                ax[i] += v * x_blocked[j];
                if i != j {
                    ax[j] += v * x_blocked[i];
                }
            }
        }
        assert!(ax.iter().zip(&rhs).all(|(l, r)| (l - r).abs() < 1e-9), "A x ≠ b");
        // The block graph's AMD fills no more than 10 % beyond the scalar AMD's (on the
        // phantom's solves, 288.6 against 287.3 thousand values of L).
        let (fill_scalar, fill_blocked) = (scalar.factor_len(), blocked.factor_len());
        assert!(fill_blocked as f64 <= 1.1 * fill_scalar as f64, "fill {fill_blocked} against {fill_scalar}");
        // The block order is a permutation of the blocks (the tail follows them by construction).
        let order = block_order(side * side, &pairs).unwrap();
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..side * side).collect::<Vec<_>>(), "not a permutation");
    }

    #[test]
    fn a_block_structure_that_does_not_fit_the_pattern_is_an_error() {
        let (a, pairs) = grid_blocks(3);
        assert!(SparseLlt::blocked(a.symbolic(), 9, 12, &pairs, 5).is_err(), "wrong tail");
        assert!(SparseLlt::blocked(a.symbolic(), 8, 12, &pairs, 18).is_err(), "a pair beyond the blocks");
    }

    #[test]
    fn an_indefinite_matrix_is_an_error_not_a_panic() {
        let t = vec![Triplet::new(0, 0, 1.0), Triplet::new(1, 0, 2.0), Triplet::new(1, 1, 1.0)];
        let a = SparseColMat::<usize, f64>::try_new_from_triplets(2, 2, &t).unwrap();
        let mut llt = SparseLlt::new(a.symbolic(), true).unwrap();
        assert!(llt.factorize(a.as_ref()).is_err());
    }
}
