//! Radial fall-off profiles and `vignetting.toml` (Goldman 2010, "Vignette and exposure calibration and compensation", IEEE TPAMI 32(12); Kim & Pollefeys 2008).
//!
//! A profile is the even polynomial of Goldman & Chen (2005), `F(r) = 1 + c1 r² + c2 r⁴ (+ c3 r⁶)`,
//! about the principal point, r the pixel distance to (cx, cy) over the half-diagonal (the same
//! normaliser as `light.toml`'s V). A capsule's light moves with its lens, so what a flat target
//! facing it shows is lens vignetting V × LED profile μ × the target's own geometry:
//! `I_flat ∝ V · μ · cos³α / D²` (α the ray's angle to the optical axis: cos α from the incidence,
//! cos²α from the 1/r² of a plane at distance D). `vignetting.toml` keeps
//! `lens_and_light` (V · μ, what a near-light depth model divides out and keeps cos θ / r² as its
//! cue); the flat field (V · μ · cos³α, what a distant-light model such as Tsai–Shah divides out)
//! is that times the known cos³α.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::LightModel;
use crate::camera::PinholeCamera;
use crate::frame::Falloff;

/// `r²` of pixel (u, v): squared distance to the principal point over the half-diagonal² (of
/// the calibrated camera: [`PinholeCamera::vignetting_radius`]).
pub fn radius2(cam: &PinholeCamera, u: f64, v: f64) -> f64 {
    let (du, dv) = (u - cam.cx, v - cam.cy);
    let hd = cam.vignetting_radius();
    (du * du + dv * dv) / (hd * hd)
}

/// cos α of the ray through pixel (u, v) (pinhole; the angle to the optical axis).
pub fn cos_alpha(cam: &PinholeCamera, u: f64, v: f64) -> f64 {
    let (x, y) = ((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy);
    1.0 / (1.0 + x * x + y * y).sqrt()
}

/// `F(r) = 1 + Σ c_k r^{2k}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RadialProfile {
    /// c1, c2 (, c3).
    pub coeffs: Vec<f64>,
}

impl RadialProfile {
    /// F at `r2 = r²`.
    pub fn at_r2(&self, r2: f64) -> f64 {
        let mut out = 1.0;
        let mut rk = 1.0;
        for c in &self.coeffs {
            rk *= r2;
            out += c * rk;
        }
        out
    }

    /// F at pixel (u, v) of `cam`.
    pub fn at(&self, cam: &PinholeCamera, u: f64, v: f64) -> f64 {
        self.at_r2(radius2(cam, u, v))
    }

    /// Weighted least-squares fit of `degree` coefficients (2 or 3) to samples `(r², value,
    /// weight)` of a profile normalised to 1 at the centre (`value − 1 = Σ c_k r^{2k}`).
    /// `None` when the samples do not determine the coefficients (too few radii).
    pub fn fit(samples: &[(f64, f64, f64)], degree: usize) -> Option<Self> {
        let mut a = DMatrix::<f64>::zeros(degree, degree);
        let mut b = DVector::<f64>::zeros(degree);
        for &(r2, value, w) in samples {
            if !(r2.is_finite() && value.is_finite() && w.is_finite() && w > 0.0) {
                continue;
            }
            let row: Vec<f64> = (1..=degree).map(|k| r2.powi(k as i32)).collect();
            for i in 0..degree {
                b[i] += w * row[i] * (value - 1.0);
                for j in 0..degree {
                    a[(i, j)] += w * row[i] * row[j];
                }
            }
        }
        let coeffs = a.cholesky()?.solve(&b);
        coeffs.iter().all(|c| c.is_finite()).then(|| Self { coeffs: coeffs.iter().copied().collect() })
    }
}

/// `vignetting.toml`: the lens-and-light profile of a capsule and the encoding exponent to
/// linearise its pixels with (written by `capsule-slam calibrate-vignetting`). The flat field is
/// this profile times the flat target's own cos³α, which is known exactly from the intrinsics
/// (an even polynomial cannot follow a wide capsule lens' cos⁴-like fall-off to 2 %).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VignettingFile {
    /// Encoding exponent: pixel = linear^(1/gamma).
    pub gamma: f64,
    /// V · μ: lens vignetting times LED profile, coefficients c1 (c2 c3) of `1 + c1 r² + …`.
    pub lens_and_light: Vec<f64>,
}

impl VignettingFile {
    /// The fall-off of one kind at pixel (u, v).
    pub fn falloff(&self, cam: &PinholeCamera, u: f64, v: f64, falloff: Falloff) -> f64 {
        profile_falloff(&RadialProfile { coeffs: self.lens_and_light.clone() }, cam, u, v, falloff)
    }

    /// Every invalid field as `(key, message)`.
    pub fn problems(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        if !(self.gamma.is_finite() && self.gamma > 0.0) {
            out.push(("gamma", format!("{} must be positive", self.gamma)));
        }
        if !(1..=3).contains(&self.lens_and_light.len()) || !self.lens_and_light.iter().all(|v| v.is_finite()) {
            out.push(("lens_and_light", "needs 1 to 3 finite coefficients c1 (c2 c3) of F = 1 + c1 r² + c2 r⁴ + c3 r⁶".into()));
        }
        out
    }
}

/// A lens-and-light profile's fall-off of one kind at pixel (u, v) (the flat field multiplies
/// in cos³α).
pub fn profile_falloff(lens_and_light: &RadialProfile, cam: &PinholeCamera, u: f64, v: f64, falloff: Falloff) -> f64 {
    let f = lens_and_light.at(cam, u, v);
    match falloff {
        Falloff::LensAndLight => f,
        Falloff::FlatField => f * Falloff::flat_to_lens_and_light(cos_alpha(cam, u, v)),
    }
}

/// The fall-off of a light model at pixel (u, v), 1 at the principal point: `V · μ` (μ the LED
/// profile along the pixel's ray, exact for a light at the optical centre) or that times cos³α.
pub fn light_falloff(light: &LightModel, cam: &PinholeCamera, u: f64, v: f64, falloff: Falloff) -> f64 {
    let c = cos_alpha(cam, u, v);
    let spot = if light.spot_exponent == 0.0 { 1.0 } else { c.powf(light.spot_exponent) };
    let lens_and_light = light.vignetting_at(cam, u, v) * spot;
    match falloff {
        Falloff::LensAndLight => lens_and_light,
        Falloff::FlatField => lens_and_light * Falloff::flat_to_lens_and_light(c),
    }
}

/// The linear image of a matte target of `albedo` facing the capsule at `distance_m`, under
/// `light` (no noise): the ground truth a flat-field calibration sees.
pub fn flat_field_linear(light: &LightModel, cam: &PinholeCamera, u: f64, v: f64, distance_m: f64, albedo: f64) -> f64 {
    let p = cam.unproject(u, v, distance_m);
    let n = nalgebra::Vector3::new(0.0, 0.0, -1.0);
    light.linear(cam, u, v, albedo, &p, &n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profile_fit_recovers_a_polynomial() {
        let truth = RadialProfile { coeffs: vec![-0.3, -0.25, 0.1] };
        let samples: Vec<_> = (0..50).map(|i| (i as f64 / 100.0, truth.at_r2(i as f64 / 100.0), 1.0)).collect();
        let fit = RadialProfile::fit(&samples, 3).unwrap();
        for (a, b) in fit.coeffs.iter().zip(&truth.coeffs) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        assert!(RadialProfile::fit(&[(0.1, 0.9, 1.0)], 3).is_none(), "one radius cannot fix three coefficients");
    }
}
