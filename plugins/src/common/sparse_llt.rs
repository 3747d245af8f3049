//! A sparse Cholesky factorisation that is analysed once and refactorised in place: faer's
//! symbolic analysis (AMD ordering) once per sparsity pattern, then per Gauss-Newton iteration a
//! numeric factorisation into the same buffers (no allocation) and an in-place solve. faer
//! picks the simplicial or the supernodal method by a flop heuristic; `simplicial` forces the
//! former (on the deformation graph, 64–4096 nodes, the heuristic's supernodal choice was 1.3–5×
//! faster, so callers leave it off unless they measured otherwise).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::cholesky::{CholeskySymbolicParams, LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
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
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: if simplicial { SupernodalThreshold::FORCE_SIMPLICIAL } else { SupernodalThreshold::AUTO },
            ..Default::default()
        };
        let symbolic = factorize_symbolic_cholesky(pattern, Side::Lower, SymmetricOrdering::Amd, params).map_err(|e| SparseLltError(format!("{e:?}")))?;
        let factor_req = symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default());
        let solve_req = symbolic.solve_in_place_scratch::<f64>(1, Par::Seq);
        let buffer = |req| MemBuffer::try_new(req).map_err(|e| SparseLltError(format!("workspace: {e:?}")));
        Ok(Self { values: vec![0.0; symbolic.len_val()], factor_buf: buffer(factor_req)?, solve_buf: buffer(solve_req)?, symbolic, factored: false })
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
    fn both_methods_solve_and_refactorise() {
        for simplicial in [true, false] {
            let a = tridiagonal(50);
            let mut llt = SparseLlt::new(a.symbolic(), simplicial).unwrap();
            let mut x = vec![0.0; 50];
            assert!(llt.solve_in_place(&mut x).is_err(), "no factorisation yet");
            llt.factorize(a.as_ref()).unwrap();
            // A x = b with x* = (1, 2, ..., 50).
            let truth: Vec<f64> = (1..=50).map(f64::from).collect();
            let mut b: Vec<f64> = (0..50).map(|i| 3.0 * truth[i] - if i > 0 { truth[i - 1] } else { 0.0 } - if i < 49 { truth[i + 1] } else { 0.0 }).collect();
            llt.solve_in_place(&mut b).unwrap();
            assert!(b.iter().zip(&truth).all(|(x, t)| (x - t).abs() < 1e-10), "{simplicial}: {b:?}");
            // The same pattern with other values.
            let mut scaled = a.clone();
            scaled.val_mut().iter_mut().for_each(|v| *v *= 2.0);
            llt.factorize(scaled.as_ref()).unwrap();
            let mut ones = vec![2.0; 50];
            llt.solve_in_place(&mut ones).unwrap();
            let mut expect = vec![2.0; 50];
            let mut check = SparseLlt::new(a.symbolic(), simplicial).unwrap();
            check.factorize(a.as_ref()).unwrap();
            check.solve_in_place(&mut expect).unwrap();
            assert!(ones.iter().zip(&expect).all(|(x, e)| (2.0 * x - e).abs() < 1e-12));
        }
    }

    #[test]
    fn an_indefinite_matrix_is_an_error_not_a_panic() {
        let t = vec![Triplet::new(0, 0, 1.0), Triplet::new(1, 0, 2.0), Triplet::new(1, 1, 1.0)];
        let a = SparseColMat::<usize, f64>::try_new_from_triplets(2, 2, &t).unwrap();
        let mut llt = SparseLlt::new(a.symbolic(), true).unwrap();
        assert!(llt.factorize(a.as_ref()).is_err());
    }
}
