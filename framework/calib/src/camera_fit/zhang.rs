//! The closed-form start of a camera fit (Zhang 2000, "A flexible new technique for camera
//! calibration", IEEE TPAMI 22(11)): a homography per view of the planar board (normalised DLT,
//! Hartley 1997), the intrinsics from the image of the absolute conic `B = K⁻ᵀ K⁻¹` (Zhang's
//! Eqs. 8–9 and Appendix B, zero skew imposed), and each view's pose from its homography
//! (Eq. 12), the rotation made orthonormal by SVD.

use nalgebra::{DMatrix, Matrix3, Point2, Rotation3, SymmetricEigen, Vector3};

use super::BoardView;

/// The pinhole intrinsics `(fx, fy, cx, cy)`.
pub type Intrinsics = [f64; 4];

/// A homography from board coordinates (metres on the plane z = 0) to pixels; `None` for fewer
/// than 4 points or a degenerate set.
pub fn homography(view: &BoardView) -> Option<Matrix3<f64>> {
    let n = view.corners.len();
    if n < 4 {
        return None;
    }
    let (t_board, board) = normalise(view.corners.iter().map(|c| c.board_m));
    let (t_image, image) = normalise(view.corners.iter().map(|c| c.pixel));
    let mut a = DMatrix::<f64>::zeros(2 * n, 9);
    for (k, (p, q)) in board.iter().zip(&image).enumerate() {
        let (x, y, u, v) = (p.x, p.y, q.x, q.y);
        a.row_mut(2 * k).copy_from_slice(&[-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u]);
        a.row_mut(2 * k + 1).copy_from_slice(&[0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v]);
    }
    let h = smallest_eigenvector(&(a.transpose() * &a))?;
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let out = t_image.try_inverse()? * hn * t_board;
    (out[(2, 2)].abs() > 1e-12).then(|| out / out[(2, 2)])
}

/// Hartley's normalisation: the points moved to their centroid and scaled to a mean distance √2.
fn normalise(points: impl Iterator<Item = Point2<f64>>) -> (Matrix3<f64>, Vec<Point2<f64>>) {
    let pts: Vec<Point2<f64>> = points.collect();
    let n = pts.len().max(1) as f64;
    let c = pts.iter().fold(Vector3::zeros(), |s, p| s + Vector3::new(p.x, p.y, 0.0)) / n;
    let mean_dist = pts.iter().map(|p| (p.x - c.x).hypot(p.y - c.y)).sum::<f64>() / n;
    let s = if mean_dist > 0.0 { std::f64::consts::SQRT_2 / mean_dist } else { 1.0 };
    let t = Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0);
    (t, pts.iter().map(|p| Point2::new(s * (p.x - c.x), s * (p.y - c.y))).collect())
}

/// The unit eigenvector of the smallest eigenvalue of a symmetric matrix.
fn smallest_eigenvector(m: &DMatrix<f64>) -> Option<Vec<f64>> {
    let e = SymmetricEigen::new(m.clone());
    let k = e.eigenvalues.iter().enumerate().filter(|(_, v)| v.is_finite()).min_by(|a, b| a.1.total_cmp(b.1))?.0;
    Some(e.eigenvectors.column(k).iter().copied().collect())
}

/// Zhang's intrinsics from at least two homographies (zero skew imposed), in an image of size
/// `(w, h)`; `None` when the conic is not that of a real camera (too few or too similar views).
pub fn intrinsics(homographies: &[Matrix3<f64>], w: f64, h: f64) -> Option<Intrinsics> {
    // Pixels scaled to about ±1 for conditioning: K = N⁻¹ K'.
    let s = 2.0 / w.max(h);
    let norm = Matrix3::new(s, 0.0, -1.0, 0.0, s, -1.0, 0.0, 0.0, 1.0);
    let v = |hm: &Matrix3<f64>, i: usize, j: usize| {
        let (a, b) = (hm.column(i), hm.column(j));
        [a[0] * b[0], a[0] * b[1] + a[1] * b[0], a[1] * b[1], a[2] * b[0] + a[0] * b[2], a[2] * b[1] + a[1] * b[2], a[2] * b[2]]
    };
    let mut rows: Vec<[f64; 6]> = Vec::new();
    for hm in homographies {
        let hn = norm * hm;
        rows.push(v(&hn, 0, 1));
        let (v11, v22) = (v(&hn, 0, 0), v(&hn, 1, 1));
        rows.push(std::array::from_fn(|k| v11[k] - v22[k]));
    }
    rows.push([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]); // B12 = 0: no skew
    let vm = DMatrix::from_fn(rows.len(), 6, |r, c| rows[r][c]);
    let b = smallest_eigenvector(&(vm.transpose() * &vm))?;
    let [b11, b12, b22, b13, b23, b33] = [b[0], b[1], b[2], b[3], b[4], b[5]];
    let den = b11 * b22 - b12 * b12;
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha = (lambda / b11).sqrt();
    let beta = (lambda * b11 / den).sqrt();
    let u0 = -b13 * alpha * alpha / lambda;
    let k = [alpha / s, beta / s, (u0 + 1.0) / s, (v0 + 1.0) / s];
    k.iter().all(|x| x.is_finite() && *x > 0.0).then_some(k)
}

/// A start that needs no conic: the principal point at the image centre and one focal length,
/// the median of what each homography's two constraints give (Zhang's Eqs. 3–4 with `K` known
/// but for `f`); half the larger side when none is positive.
pub fn centred_intrinsics(homographies: &[Matrix3<f64>], w: f64, h: f64) -> Intrinsics {
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let shift = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let mut f2: Vec<f64> = Vec::new();
    for hm in homographies {
        let m = shift * hm;
        let (h1, h2) = (m.column(0), m.column(1));
        let candidates = [
            -(h1[0] * h2[0] + h1[1] * h2[1]) / (h1[2] * h2[2]),
            -(h1[0] * h1[0] + h1[1] * h1[1] - h2[0] * h2[0] - h2[1] * h2[1]) / (h1[2] * h1[2] - h2[2] * h2[2]),
        ];
        f2.extend(candidates.into_iter().filter(|v| v.is_finite() && *v > 0.0));
    }
    f2.sort_by(f64::total_cmp);
    let f = f2.get(f2.len() / 2).map_or(0.5 * w.max(h), |v| v.sqrt());
    [f, f, cx, cy]
}

/// A view's pose (board to camera) from its homography and the intrinsics (Zhang's Eq. 12), the
/// board in front of the camera; the rotation is the nearest orthonormal one.
pub fn pose(hm: &Matrix3<f64>, k: &Intrinsics) -> Option<(Rotation3<f64>, Vector3<f64>)> {
    let kinv = Matrix3::new(k[0], 0.0, k[2], 0.0, k[1], k[3], 0.0, 0.0, 1.0).try_inverse()?;
    let m = kinv * hm;
    let mut scale = 1.0 / m.column(0).norm();
    if m[(2, 2)] * scale < 0.0 {
        scale = -scale;
    }
    let (r1, r2, t) = (m.column(0) * scale, m.column(1) * scale, m.column(2) * scale);
    let r = Matrix3::from_columns(&[r1, r2, r1.cross(&r2)]);
    let svd = r.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut rot = u * vt;
    if rot.determinant() < 0.0 {
        rot = -rot;
    }
    let out = Rotation3::from_matrix_unchecked(rot);
    out.matrix().iter().all(|v| v.is_finite()).then_some((out, t))
}
