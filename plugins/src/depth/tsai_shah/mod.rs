//! `tsai-shah`: the paper's depth estimator (Sec. 3.2), Tsai & Shah (1994), "Shape from shading
//! using linear approximation", Image and Vision Computing 12(8), doi:10.1016/0262-8856(94)90002-7:
//! a Lambertian surface under a distant light seen orthographically, the reflectance map
//! linearised in depth and solved per pixel by Jacobi sweeps.
//!
//! - Reflectance (Tsai & Shah 1994, eq. 1): `R(p, q) = (1 + p ps + q qs) / (√(1+p²+q²) √(1+ps²+qs²))`, clipped at
//!   0, `ps = cos τ tan σ`, `qs = sin τ tan σ`, backward differences `p = Z(x,y) − Z(x−1,y)`,
//!   `q = Z(x,y) − Z(x,y−1)` (0 where a neighbour is missing), Z depth.
//! - Update (A2): `f = E − R`, `df/dZ = −[(ps+qs)/(N Ns) − (p+q)(1+p ps+q qs)/(N³ Ns)]`; the Kalman
//!   form of the original C code (`K = S df/(Wn + S df²)`, `S ← (1 − K df) S`, `Z ← Z − K f`,
//!   S₀ = 0.01, Wn = 1e-8; never blows up) by default, or the Newton form `Z ← Z − f/(df + ε)`.
//! - Light and albedo (A3): the moment estimator on E normalised by its maximum, computed only
//!   inside the field of view and the masks (γ² clamped at 0, 4μ₁/γ clamped to ≤ 1, tilt by
//!   atan2), or fixed by parameters.
//! - Guards (A6/A8): a capsule's light is beside its lens, slant ≈ 0, where the method
//!   degenerates (df = 0 from a flat start): the slant is floored (`slant_floor_deg`, 1°).
//! - Metric convention (A4): Z has no scale, offset or sign; the output takes the sign that
//!   makes bright pixels near, then maps the 2nd–98th percentiles of Z affinely onto
//!   `[near_m, far_m]`. Confidence falls with the final reflectance residual |E − R|.

use capsule_slam_framework::frame::Falloff;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{CameraFrame, Context, DepthEstimate, DepthEstimator, DepthMap, GrayF32, Mask, Plugin, StageError, register};
use serde::{Deserialize, Serialize};

/// The per-pixel update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Form {
    /// The damped (Kalman) form of the original code.
    Kalman,
    /// Newton's form, as in the paper's equation.
    Newton,
}

/// Where the light direction comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LightSource {
    /// Slant, tilt and albedo from image statistics (Zheng & Chellappa moments).
    Estimate,
    /// `slant_deg` and `tilt_deg` as given.
    Fixed,
}

capsule_slam_framework::plugin_params! {
    /// Parameters of `tsai-shah`.
    pub struct TsaiShahParams {
        /// `kalman` (original code, default) or `newton` (paper's equation).
        pub form: Form = Form::Kalman; unit = "-";
        /// Jacobi sweeps (public code: 5–400; 200 in the Elhabian tutorial).
        pub iterations: u32 = 200; unit = "-"; range = 0.0..=10000.0;
        /// `estimate` the light from the image, or use the `fixed` angles below.
        pub light: LightSource = LightSource::Estimate; unit = "-";
        /// Slant σ when fixed (angle of the light to the optical axis).
        pub slant_deg: f64 = 0.0; unit = "deg"; range = 0.0..=89.0;
        /// Tilt τ when fixed (azimuth in the image, x right, y down).
        pub tilt_deg: f64 = 45.0; unit = "deg"; range = -360.0..=360.0;
        /// Smallest slant used (guard against the degeneracy at slant 0: with the light along the view axis the linearised reflectance has no first-order term in p and q).
        pub slant_floor_deg: f64 = 1.0; unit = "deg"; range = 0.0..=89.0;
        /// Output depth of the nearest (2nd percentile) pixels.
        pub near_m: f64 = 0.01; unit = "m"; range = 0.0..=10.0;
        /// Output depth of the farthest (98th percentile) pixels.
        pub far_m: f64 = 0.06; unit = "m"; range = 0.0..=10.0;
    }
}

/// The Tsai–Shah estimator.
pub struct TsaiShah {
    params: TsaiShahParams,
    /// Whether the warning about a lens-and-light-divided image was given.
    warned_falloff: bool,
}

impl TsaiShah {
    /// An estimator with the given parameters (`near_m < far_m` is checked by `build`).
    pub fn new(params: TsaiShahParams) -> Self {
        Self { params, warned_falloff: false }
    }
}

impl Plugin for TsaiShah {
    const NAME: &'static str = "tsai-shah";
    const SUMMARY: &'static str =
        "the paper's shape from shading (Tsai & Shah 1994): linearised Lambertian reflectance, distant light, Jacobi sweeps; depth by a bright-near convention";
    type Params = TsaiShahParams;

    fn build(params: TsaiShahParams, _env: &BuildEnv) -> Result<Self, StageError> {
        crate::common::ordered("near_m", params.near_m, "far_m", params.far_m)?;
        Ok(Self::new(params))
    }
}

/// Light direction as (ps, qs) from slant and tilt (radians).
pub fn light_pq(slant: f64, tilt: f64) -> (f64, f64) {
    (tilt.cos() * slant.tan(), tilt.sin() * slant.tan())
}

/// The reflectance map R(p, q), clipped at 0.
pub fn reflectance(p: f64, q: f64, ps: f64, qs: f64) -> f64 {
    ((1.0 + p * ps + q * qs) / ((1.0 + p * p + q * q).sqrt() * (1.0 + ps * ps + qs * qs).sqrt())).max(0.0)
}

/// `df/dZ` of `f = E − R(p, q)` with `dp/dZ = dq/dZ = 1` (Tsai & Shah 1994, eq. 5).
pub fn dfdz(p: f64, q: f64, ps: f64, qs: f64) -> f64 {
    let n = (1.0 + p * p + q * q).sqrt();
    let ns = (1.0 + ps * ps + qs * qs).sqrt();
    -((ps + qs) / (n * ns) - (p + q) * (1.0 + p * ps + q * qs) / (n * n * n * ns))
}

/// Slant, tilt (radians) and albedo from the moments of `e` (already normalised by its maximum)
/// over the pixels `valid` accepts (Zheng & Chellappa 1991, "Estimation of illuminant direction, albedo, and shape from shading", IEEE TPAMI 13(7), with guards against empty and flat images).
pub fn estimate_light(e: &GrayF32, valid: &Mask) -> (f64, f64, f64) {
    let (w, h) = e.size();
    let (mut s1, mut s2, mut ex, mut ey, mut n) = (0.0, 0.0, 0.0, 0.0, 0usize);
    for y in 0..h {
        for x in 0..w {
            if !valid.at(x, y) {
                continue;
            }
            let v = f64::from(e.at(x, y));
            s1 += v;
            s2 += v * v;
            n += 1;
            if x + 1 < w && y + 1 < h && x > 0 && y > 0 && valid.at(x + 1, y) && valid.at(x - 1, y) && valid.at(x, y + 1) && valid.at(x, y - 1) {
                let gx = 0.5 * f64::from(e.at(x + 1, y) - e.at(x - 1, y));
                let gy = 0.5 * f64::from(e.at(x, y + 1) - e.at(x, y - 1));
                let m = (gx * gx + gy * gy).sqrt();
                if m > 1e-9 {
                    ex += gx / m;
                    ey += gy / m;
                }
            }
        }
    }
    if n == 0 {
        return (0.0, 0.0, 1.0);
    }
    let (m1, m2) = (s1 / n as f64, s2 / n as f64);
    let pi = std::f64::consts::PI;
    let gamma = (6.0 * pi * pi * m2 - 48.0 * m1 * m1).max(0.0).sqrt();
    let albedo = gamma / pi;
    let slant = if gamma > 0.0 { (4.0 * m1 / gamma).clamp(-1.0, 1.0).acos() } else { 0.0 };
    (slant, ey.atan2(ex), albedo)
}

/// Runs the sweeps from Z = 0 over the pixels `valid` accepts; returns Z and the final residual
/// |E − R| per pixel.
pub fn solve(e: &GrayF32, valid: &Mask, ps: f64, qs: f64, iterations: u32, form: Form) -> (Vec<f64>, Vec<f64>) {
    let (w, h) = e.size();
    let mut z = vec![0.0f64; w * h];
    let mut s = vec![0.01f64; w * h];
    let mut res = vec![0.0f64; w * h];
    let wn = 1e-8;
    for _ in 0..iterations {
        let prev = z.clone();
        for y in 0..h {
            for x in 0..w {
                let k = y * w + x;
                if !valid.at(x, y) {
                    continue;
                }
                let p = if x > 0 && valid.at(x - 1, y) { prev[k] - prev[k - 1] } else { 0.0 };
                let q = if y > 0 && valid.at(x, y - 1) { prev[k] - prev[k - w] } else { 0.0 };
                let f = f64::from(e.at(x, y)) - reflectance(p, q, ps, qs);
                let df = dfdz(p, q, ps, qs);
                res[k] = f.abs();
                match form {
                    Form::Kalman => {
                        let kg = s[k] * df / (wn + s[k] * df * df);
                        s[k] *= 1.0 - kg * df;
                        z[k] = prev[k] - kg * f;
                    }
                    Form::Newton => z[k] = prev[k] - f / (df + f64::EPSILON),
                }
            }
        }
    }
    (z, res)
}

impl DepthEstimator for TsaiShah {
    fn reads_prediction(&self) -> bool {
        false
    }

    fn estimate(&mut self, frame: &CameraFrame, ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        let p = &self.params;
        let img = frame.views.reference();
        let (w, h) = img.size();
        let cam = ctx.rig.camera();
        if !self.warned_falloff && frame.photometry.divided.is_some_and(|d| d.falloff == Falloff::LensAndLight) {
            self.warned_falloff = true;
            ctx.warn(
                "tsai-shah assumes a distant light but the vignetting stage divided only the lens and LED fall-off: set plugins.vignetting.divide = \"flat-field\" (divide the whole flat field, cos³α included)",
            );
        }
        let ignore = frame.masks.union();
        let valid = Mask::from_fn(w, h, |x, y| [cam.in_fov(x as f64, y as f64) && !ignore.as_ref().is_some_and(|m| m.at(x, y))]);
        let mut e = capsule_slam_framework::image::gray_from_rgb(img);
        let max = e.data().iter().zip(valid.data()).filter(|(_, v)| **v).map(|(g, _)| *g).fold(0.0f32, f32::max);
        let empty = |ctx: &mut Context, why: &str| {
            ctx.warn(format!("{why}; the depth is empty"));
            Ok(DepthEstimate { depth_m: DepthMap::new(w, h), confidence: Some(GrayF32::new(w, h)), albedo: None, sigma_m: None, sigma_correlation_px: 0.0 })
        };
        if max <= 0.0 {
            return empty(ctx, "no lit pixel for shape from shading");
        }
        e.data_mut().iter_mut().for_each(|v| *v /= max);
        let (slant, tilt) = match p.light {
            LightSource::Estimate => {
                let (s, t, albedo) = estimate_light(&e, &valid);
                ctx.count("albedo", albedo);
                (s, t)
            }
            LightSource::Fixed => (p.slant_deg.to_radians(), p.tilt_deg.to_radians()),
        };
        let slant = slant.max(p.slant_floor_deg.to_radians());
        ctx.count("slant_deg", slant.to_degrees());
        ctx.count("tilt_deg", tilt.to_degrees());
        let (ps, qs) = light_pq(slant, tilt);
        // The sweeps run over the whole image, as the original code (black pixels included):
        // restricted to the mask, the zero-gradient border weakens the sphere test
        // from corr −0.99 to −0.74. The statistics above and the output below use the mask.
        let (z, res) = solve(&e, &Mask::filled(w, h, true), ps, qs, p.iterations, p.form);
        let idx: Vec<usize> = (0..w * h).filter(|&k| valid.data()[k] && z[k].is_finite()).collect();
        if idx.is_empty() {
            return empty(ctx, "no valid pixel");
        }
        // Bright = near: flip Z if it grows with brightness.
        let n = idx.len() as f64;
        let (mz, me) = (idx.iter().map(|&k| z[k]).sum::<f64>() / n, idx.iter().map(|&k| f64::from(e.data()[k])).sum::<f64>() / n);
        let cov: f64 = idx.iter().map(|&k| (z[k] - mz) * (f64::from(e.data()[k]) - me)).sum();
        let sign = if cov > 0.0 { -1.0 } else { 1.0 };
        let mut sorted: Vec<f64> = idx.iter().map(|&k| sign * z[k]).collect();
        sorted.sort_by(f64::total_cmp);
        let (lo, hi) = (sorted[(0.02 * (n - 1.0)) as usize], sorted[(0.98 * (n - 1.0)) as usize]);
        if hi - lo <= 1e-12 || hi.is_nan() || lo.is_nan() {
            return empty(ctx, "shape from shading stayed flat (degenerate light: raise slant_floor_deg)");
        }
        let mut depth = DepthMap::new(w, h);
        let mut conf = GrayF32::new(w, h);
        for &k in &idx {
            let t = ((sign * z[k] - lo) / (hi - lo)).clamp(0.0, 1.0);
            depth.data_mut()[k] = (p.near_m + t * (p.far_m - p.near_m)) as f32;
            conf.data_mut()[k] = (1.0 - res[k] / 0.2).clamp(0.0, 1.0) as f32;
        }
        ctx.count("valid_pixels", n);
        Ok(DepthEstimate { depth_m: depth, confidence: Some(conf), albedo: None, sigma_m: None, sigma_correlation_px: 0.0 })
    }
}

register!(DepthEstimator, TsaiShah);

#[cfg(test)]
mod tests;
