//! The Levenberg-Marquardt refinement of a camera fit (Zhang 2000, §3.3; Marquardt 1963):
//! the reprojection error of every board corner over the intrinsics, the lens coefficients and
//! each view's pose (a rotation vector and a translation), with a numeric Jacobian (central
//! differences; a view's pose moves only its own corners).

use capsule_slam_framework::lens::LensModel;
use nalgebra::{DMatrix, DVector, Point3, Rotation3, Vector3};

use super::{BoardView, LensKind};

/// Intrinsics and lens first, then 6 per view.
pub struct Problem<'a> {
    pub views: &'a [BoardView],
    pub lens: LensKind,
}

/// Parameters per view: rotation vector, translation.
const PER_VIEW: usize = 6;
/// Most iterations.
const MAX_ITERATIONS: usize = 200;

impl Problem<'_> {
    /// Unknowns of the camera: fx fy cx cy and the lens's coefficients.
    pub fn camera_len(&self) -> usize {
        4 + self.lens.coefficients()
    }

    /// The lens of a parameter vector.
    pub fn lens_of(&self, p: &[f64]) -> LensModel {
        let k = &p[4..self.camera_len()];
        match self.lens {
            LensKind::RadialTangential => LensModel::RadialTangential([k[0], k[1], k[2], k[3], k[4], 0.0, 0.0, 0.0]),
            LensKind::Equidistant => LensModel::Equidistant([k[0], k[1], k[2], k[3]]),
        }
    }

    /// The reprojection residuals (pixels, u then v) of view `i`; a corner behind the camera
    /// gives a large residual rather than none, so that a step there is refused.
    pub fn view_residuals(&self, p: &[f64], i: usize, out: &mut Vec<f64>) {
        let lens = self.lens_of(p);
        let o = self.camera_len() + PER_VIEW * i;
        let rot = Rotation3::new(Vector3::new(p[o], p[o + 1], p[o + 2]));
        let t = Vector3::new(p[o + 3], p[o + 4], p[o + 5]);
        for c in &self.views[i].corners {
            let q = rot * Point3::new(c.board_m.x, c.board_m.y, 0.0) + t;
            if q.z <= 1e-9 {
                out.extend([1e3, 1e3]);
                continue;
            }
            let (xd, yd) = lens.distort(q.x / q.z, q.y / q.z);
            out.push(p[0] * xd + p[2] - c.pixel.x);
            out.push(p[1] * yd + p[3] - c.pixel.y);
        }
    }

    /// Every residual, view after view.
    pub fn residuals(&self, p: &[f64]) -> Vec<f64> {
        let mut out = Vec::new();
        for i in 0..self.views.len() {
            self.view_residuals(p, i, &mut out);
        }
        out
    }

    fn jacobian(&self, p: &[f64], rows: usize) -> DMatrix<f64> {
        let n = p.len();
        let mut j = DMatrix::zeros(rows, n);
        let offsets: Vec<usize> = self.views.iter().scan(0, |acc, v| Some(std::mem::replace(acc, *acc + 2 * v.corners.len()))).collect();
        let mut q = p.to_vec();
        for col in 0..n {
            let h = 1e-6 * (1.0 + p[col].abs());
            let view = col.checked_sub(self.camera_len()).map(|k| k / PER_VIEW);
            let (mut plus, mut minus) = (Vec::new(), Vec::new());
            for (side, out) in [(h, &mut plus), (-h, &mut minus)] {
                q[col] = p[col] + side;
                match view {
                    Some(i) => self.view_residuals(&q, i, out),
                    None => *out = self.residuals(&q),
                }
            }
            q[col] = p[col];
            let first = view.map_or(0, |i| offsets[i]);
            for (k, (a, b)) in plus.iter().zip(&minus).enumerate() {
                j[(first + k, col)] = (a - b) / (2.0 * h);
            }
        }
        j
    }

    /// Minimises the squared reprojection error from `p`; returns the parameters and the RMS
    /// reprojection error per corner (pixels).
    pub fn solve(&self, mut p: Vec<f64>) -> (Vec<f64>, f64) {
        let mut r = DVector::from_vec(self.residuals(&p));
        let mut cost = r.norm_squared();
        let mut mu = 1e-3;
        for _ in 0..MAX_ITERATIONS {
            let j = self.jacobian(&p, r.len());
            let jtj = j.transpose() * &j;
            let g = j.transpose() * &r;
            let mut improved = false;
            while mu < 1e12 {
                let mut a = jtj.clone();
                for d in 0..a.nrows() {
                    a[(d, d)] += mu * jtj[(d, d)].max(1e-12);
                }
                let Some(step) = a.cholesky().map(|c| c.solve(&(-&g))) else {
                    mu *= 10.0;
                    continue;
                };
                let trial: Vec<f64> = p.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
                let rt = DVector::from_vec(self.residuals(&trial));
                let c = rt.norm_squared();
                if c.is_finite() && c < cost {
                    let gain = (cost - c) / cost.max(1e-300);
                    (p, r, cost, improved) = (trial, rt, c, true);
                    mu = (mu / 10.0).max(1e-12);
                    if gain < 1e-12 {
                        return (p, rms(cost, r.len()));
                    }
                    break;
                }
                mu *= 10.0;
            }
            if !improved {
                break;
            }
        }
        (p, rms(cost, r.len()))
    }
}

/// RMS per corner from the squared sum over `n` residuals (two per corner).
fn rms(cost: f64, n: usize) -> f64 {
    (cost / (n / 2).max(1) as f64).sqrt()
}
