//! Lens models (issue 18, item 6): how a camera-frame ray lands on the image before the pinhole
//! intrinsics. Normalised coordinates `x = X/Z, y = Y/Z` go to distorted ones `(x_d, y_d)`, and
//! the pixel is `u = f_x x_d + c_x` (OpenCV's conventions, so a `calibrateCamera` result can be
//! copied into `camera.toml`):
//!
//! - `radial-tangential` (Brown–Conrady; OpenCV `calib3d`, with the rational model of
//!   `CALIB_RATIONAL_MODEL` when 8 coefficients are given): with `r² = x² + y²`,
//!   `x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x y + p2 (r² + 2 x²)`,
//!   `y_d = y (…) / (…) + p1 (r² + 2 y²) + 2 p2 x y`;
//! - `equidistant` (Kannala–Brandt as OpenCV's `fisheye` module): `θ = atan r`,
//!   `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`, `(x_d, y_d) = (θ_d / r) (x, y)`.
//!
//! `camera.toml` accepts `distortion = [k1, k2, p1, p2, k3]` (radial-tangential) or
//! `distortion = { model = "radial-tangential" | "equidistant", coefficients = [...] }`.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::error::ConfigProblem;

/// A lens model with its coefficients (see the module documentation for the formulas).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", content = "coefficients", rename_all = "kebab-case")]
pub enum LensModel {
    /// Brown–Conrady with OpenCV's rational extension: `[k1, k2, p1, p2, k3, k4, k5, k6]`.
    RadialTangential([f64; 8]),
    /// OpenCV's fisheye: `[k1, k2, k3, k4]`.
    Equidistant([f64; 4]),
}

/// Newton steps of [`LensModel::undistort`].
const NEWTON_STEPS: usize = 40;
/// Convergence of [`LensModel::undistort`] in normalised coordinates (1e-12 is 1e-10 px at f = 100 px).
const NEWTON_TOLERANCE: f64 = 1e-12;

impl LensModel {
    /// Radial-tangential from OpenCV's five coefficients `[k1, k2, p1, p2, k3]`.
    pub fn brown_conrady(k: [f64; 5]) -> Self {
        Self::RadialTangential([k[0], k[1], k[2], k[3], k[4], 0.0, 0.0, 0.0])
    }

    /// The model's name in `camera.toml`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::RadialTangential(_) => "radial-tangential",
            Self::Equidistant(_) => "equidistant",
        }
    }

    /// The coefficients in `camera.toml`'s order (five for a radial-tangential model without the
    /// rational terms).
    pub fn coefficients(&self) -> Vec<f64> {
        match self {
            Self::RadialTangential(k) if k[5..].iter().all(|v| *v == 0.0) => k[..5].to_vec(),
            Self::RadialTangential(k) => k.to_vec(),
            Self::Equidistant(k) => k.to_vec(),
        }
    }

    /// Whether the model maps every point to itself (a radial-tangential lens with all
    /// coefficients zero; an equidistant lens never does: `θ ≠ tan θ`).
    pub fn is_identity(&self) -> bool {
        matches!(self, Self::RadialTangential(k) if k.iter().all(|v| *v == 0.0))
    }

    /// Distorts normalised coordinates `(x, y)` (the formulas of the module documentation).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        match *self {
            Self::RadialTangential([k1, k2, p1, p2, k3, k4, k5, k6]) => {
                let radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)));
                (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
            }
            Self::Equidistant(k) => {
                let r = r2.sqrt();
                if r < 1e-12 {
                    return (x, y);
                }
                let theta = r.atan();
                let s = (theta / r) * equidistant_factor(&k, theta * theta);
                (x * s, y * s)
            }
        }
    }

    /// Inverts [`LensModel::distort`]: the normalised coordinates whose image is `(xd, yd)`, or
    /// `None` where the model folds over (its Jacobian is not positive) or behind the camera (an
    /// equidistant angle ≥ 90°). Radial-tangential: damped Newton from `(xd, yd)`; equidistant:
    /// Newton on `θ` alone.
    pub fn undistort(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        match self {
            Self::RadialTangential(_) => self.undistort_newton(xd, yd),
            Self::Equidistant(k) => {
                let rd = xd.hypot(yd);
                if rd < 1e-12 {
                    return Some((xd, yd));
                }
                let mut theta = rd.min(1.5);
                for _ in 0..NEWTON_STEPS {
                    let t2 = theta * theta;
                    let f = theta * equidistant_factor(k, t2) - rd;
                    let df = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
                    if df.is_nan() || df <= 0.0 {
                        return None;
                    }
                    theta -= f / df;
                    if f.abs() < NEWTON_TOLERANCE {
                        break;
                    }
                }
                let ok = (0.0..std::f64::consts::FRAC_PI_2).contains(&theta);
                let s = theta.tan() / rd;
                (ok && (theta * equidistant_factor(k, theta * theta) - rd).abs() < 1e-9).then_some((xd * s, yd * s))
            }
        }
    }

    fn undistort_newton(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        let (mut x, mut y) = (xd, yd);
        let residual = |x: f64, y: f64| {
            let (u, v) = self.distort(x, y);
            (u - xd, v - yd)
        };
        let (mut ex, mut ey) = residual(x, y);
        for _ in 0..NEWTON_STEPS {
            if ex.hypot(ey) < NEWTON_TOLERANCE {
                break;
            }
            let [a, b, c, d] = self.jacobian(x, y);
            let det = a * d - b * c;
            if det.is_nan() || det <= 0.0 {
                return None;
            }
            let (mut sx, mut sy) = ((d * ex - b * ey) / det, (a * ey - c * ex) / det);
            // Halve the step until the residual falls (strong distortion far out).
            let mut improved = false;
            for _ in 0..30 {
                let (nx, ny) = residual(x - sx, y - sy);
                if nx.hypot(ny) < ex.hypot(ey) {
                    (x, y, ex, ey, improved) = (x - sx, y - sy, nx, ny, true);
                    break;
                }
                (sx, sy) = (0.5 * sx, 0.5 * sy);
            }
            if !improved {
                break;
            }
        }
        let [a, b, c, d] = self.jacobian(x, y);
        (ex.hypot(ey) < 1e-9 && a * d - b * c > 0.0).then_some((x, y))
    }

    /// `∂(x_d, y_d)/∂(x, y)` as `[∂x_d/∂x, ∂x_d/∂y, ∂y_d/∂x, ∂y_d/∂y]`, by central differences.
    fn jacobian(&self, x: f64, y: f64) -> [f64; 4] {
        let h = 1e-7 * (1.0 + x.abs().max(y.abs()));
        let (xp, yp) = self.distort(x + h, y);
        let (xm, ym) = self.distort(x - h, y);
        let (xq, yq) = self.distort(x, y + h);
        let (xn, yn) = self.distort(x, y - h);
        [(xp - xm) / (2.0 * h), (xq - xn) / (2.0 * h), (yp - ym) / (2.0 * h), (yq - yn) / (2.0 * h)]
    }
}

/// `1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸`.
fn equidistant_factor(k: &[f64; 4], t2: f64) -> f64 {
    1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
}

/// `camera.toml`'s `distortion` as written: OpenCV's five numbers, or a table naming the model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum DistortionSpec {
    /// `distortion = [k1, k2, p1, p2, k3]`: radial-tangential.
    Coefficients(Vec<f64>),
    /// `distortion = { model = "...", coefficients = [...] }`.
    Table(DistortionTable),
}

/// The table form of [`DistortionSpec`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DistortionTable {
    /// `radial-tangential` or `equidistant`.
    pub model: String,
    /// 5 or 8 numbers for radial-tangential, 4 for equidistant.
    pub coefficients: Vec<f64>,
    /// Keys other than these two (each one a problem).
    #[serde(flatten, skip_serializing)]
    pub unknown: BTreeMap<String, toml::Value>,
}

impl DistortionSpec {
    /// The table form of a model (what `synth` writes).
    pub fn from_model(model: &LensModel) -> Self {
        Self::Table(DistortionTable { model: model.name().to_owned(), coefficients: model.coefficients(), unknown: BTreeMap::new() })
    }

    /// Every problem, keys prefixed with `prefix` (e.g. `camera.distortion`).
    pub fn problems(&self, prefix: &str) -> Vec<ConfigProblem> {
        let mut out = Vec::new();
        let (model, k, key) = match self {
            Self::Coefficients(k) => ("radial-tangential", k, prefix.to_owned()),
            Self::Table(t) => {
                for extra in t.unknown.keys() {
                    out.push(ConfigProblem::new(
                        format!("{prefix}.{extra}"),
                        format!("unknown key `{extra}`"),
                        "the distortion table has `model` and `coefficients` only",
                    ));
                }
                (t.model.as_str(), &t.coefficients, format!("{prefix}.coefficients"))
            }
        };
        let counts: &[usize] = match model {
            "radial-tangential" => &[5, 8],
            "equidistant" => &[4],
            other => {
                out.push(ConfigProblem::new(
                    format!("{prefix}.model"),
                    format!("unknown lens model `{other}`"),
                    "use `radial-tangential` ([k1, k2, p1, p2, k3], or 8 with k4 k5 k6) or `equidistant` ([k1, k2, k3, k4])",
                ));
                return out;
            }
        };
        if !counts.contains(&k.len()) {
            let want = counts.iter().map(ToString::to_string).collect::<Vec<_>>().join(" or ");
            let order = if model == "equidistant" { "k1, k2, k3, k4" } else { "k1, k2, p1, p2, k3 [, k4, k5, k6]" };
            out.push(ConfigProblem::new(
                key.clone(),
                format!("{} coefficients for `{model}`, which takes {want}", k.len()),
                format!("give [{order}] (OpenCV's order)"),
            ));
        } else if !k.iter().all(|v| v.is_finite()) {
            out.push(ConfigProblem::new(key, "a coefficient is not finite", "give finite numbers"));
        }
        out
    }

    /// The model (call [`DistortionSpec::problems`] first: `None` for an invalid spec).
    pub fn model(&self) -> Option<LensModel> {
        if !self.problems("distortion").is_empty() {
            return None;
        }
        let (model, k) = match self {
            Self::Coefficients(k) => ("radial-tangential", k),
            Self::Table(t) => (t.model.as_str(), &t.coefficients),
        };
        Some(match model {
            "equidistant" => LensModel::Equidistant([k[0], k[1], k[2], k[3]]),
            _ => {
                let mut all = [0.0; 8];
                all[..k.len()].copy_from_slice(k);
                LensModel::RadialTangential(all)
            }
        })
    }
}

#[cfg(test)]
#[path = "lens_tests.rs"]
mod tests;
