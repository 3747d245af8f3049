//! Depth errors of real depth sources, added to the phantom's exact depth (`synth
//! --depth-noise`). The exact depth stays the ground truth; the noisy one is what the `sensor`
//! stage reads.
//!
//! - `smooth:R`: `z (1 + R F)`, F a unit-variance field from a 5 × 5 grid of standard normal
//!   values upsampled bicubically (Catmull–Rom) and divided pixel by pixel by the interpolation's
//!   own standard deviation, drawn anew each frame: the low-frequency error of stereo matching
//!   or of a learned estimator (issue 17; about 1.5–3 mm at organ distances with R = 0.05).
//! - `structured`: a structured-light or active-stereo sensor at organ scale: disparity
//!   `f b / z` (b = 5 mm) with Gaussian noise such that σ_z = 0.2 m⁻¹ · z² (0.5 mm at 50 mm),
//!   quantised to 1/8 px; holes where the surface is seen at more than 70° from its normal and
//!   at depth edges (Khoshelham & Elberink 2012 for the z² law; Kinect v1's 1/8 px sub-pixel
//!   disparity).

use std::str::FromStr;

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::image::DepthMap;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Baseline of the simulated structured-light sensor, metres.
pub const STRUCTURED_BASELINE_M: f64 = 0.005;
/// σ_z = this × z² for the structured-light sensor, 1/m.
pub const STRUCTURED_SIGMA_PER_M: f64 = 0.2;
/// Disparity quantisation of the structured-light sensor, pixels.
pub const STRUCTURED_DISPARITY_STEP_PX: f64 = 0.125;
/// Largest angle between the view ray and the surface normal with a structured-light return.
pub const STRUCTURED_MAX_INCIDENCE_DEG: f64 = 70.0;
/// A neighbour this much nearer or farther (relative) marks a depth edge: no return.
pub const STRUCTURED_EDGE_RELATIVE: f64 = 0.05;

/// What error the phantom adds to its depth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum DepthNoise {
    /// Exact depth (the 16-bit PNG's 0.2 mm steps aside).
    #[default]
    None,
    /// `z (1 + relative · F)`, F a smooth unit-variance field per frame.
    Smooth {
        /// Standard deviation of the relative error.
        relative: f64,
    },
    /// The structured-light sensor of the module documentation.
    Structured,
}

impl FromStr for DepthNoise {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("--depth-noise {s:?}: expected none, structured or smooth:R with R a relative σ in (0, 1), e.g. smooth:0.05");
        match s {
            "none" => Ok(Self::None),
            "structured" => Ok(Self::Structured),
            _ => {
                let r: f64 = s.strip_prefix("smooth:").ok_or_else(bad)?.parse().map_err(|_| bad())?;
                if r.is_finite() && r > 0.0 && r < 1.0 { Ok(Self::Smooth { relative: r }) } else { Err(bad()) }
            }
        }
    }
}

impl DepthNoise {
    /// The σ(z) model of this error for images `width_px` wide, written into the phantom's
    /// `camera.toml`: the PNG's 0.2 mm steps (σ = 0.2 mm / √12) plus the added error, and the
    /// smooth field's grid spacing as its correlation length.
    pub fn model(&self, width_px: usize) -> DepthNoiseModel {
        let png = 0.2e-3 / 12f64.sqrt();
        match *self {
            Self::None => DepthNoiseModel { absolute_m: png, relative: 0.0, quadratic_per_m: 0.0, correlation_px: 0.0 },
            // The field's grid nodes are (width − 1) / 4 apart.
            Self::Smooth { relative } => {
                DepthNoiseModel { absolute_m: png, relative, quadratic_per_m: 0.0, correlation_px: width_px.saturating_sub(1) as f64 / 4.0 }
            }
            Self::Structured => DepthNoiseModel { absolute_m: png, relative: 0.0, quadratic_per_m: STRUCTURED_SIGMA_PER_M, correlation_px: 0.0 },
        }
    }

    /// The noisy depth of frame `frame` from the exact `depth_m` (0 = no return), deterministic
    /// for (`seed`, `frame`).
    pub fn apply(&self, depth_m: &DepthMap, cam: &PinholeCamera, seed: u64, frame: usize) -> DepthMap {
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(seed ^ 0xD397_0000_0000 ^ ((frame as u64) << 8));
        match *self {
            Self::None => depth_m.clone(),
            Self::Smooth { relative } => {
                let field = smooth_field(depth_m.width(), depth_m.height(), &mut rng);
                DepthMap::from_fn(depth_m.width(), depth_m.height(), |x, y| {
                    let z = depth_m.at(x, y);
                    [if z > 0.0 { (f64::from(z) * (1.0 + relative * f64::from(field.at(x, y)))).max(0.0) as f32 } else { 0.0 }]
                })
            }
            Self::Structured => structured(depth_m, cam, &mut rng),
        }
    }
}

/// Catmull–Rom weights of the four samples around fractional position `t` in [0, 1).
fn catmull_rom(t: f64) -> [f64; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0), 0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2)]
}

/// A unit-variance field: a 5 × 5 grid of N(0, 1) spanning the image corner to corner,
/// bicubically interpolated (indices clamped at the border) and divided by the interpolation
/// weights' norm, so every pixel is N(0, 1).
pub fn smooth_field(w: usize, h: usize, rng: &mut impl rand::Rng) -> DepthMap {
    const N: usize = 5;
    let grid: Vec<f64> = (0..N * N).map(|_| StandardNormal.sample(rng)).collect();
    let taps = |p: f64| -> [(usize, f64); 4] {
        let i = p.floor().min((N - 2) as f64);
        let wts = catmull_rom(p - i);
        std::array::from_fn(|k| (((i as i64) + k as i64 - 1).clamp(0, N as i64 - 1) as usize, wts[k]))
    };
    let scale = |n: usize| if n > 1 { (N - 1) as f64 / (n - 1) as f64 } else { 0.0 };
    let (sx, sy) = (scale(w), scale(h));
    DepthMap::from_fn(w, h, |x, y| {
        let (tx, ty) = (taps(x as f64 * sx), taps(y as f64 * sy));
        // Clamped taps may repeat a grid value: sum the weights per value before the norm.
        let mut per = [0.0; N * N];
        for &(j, wy) in &ty {
            for &(i, wx) in &tx {
                per[j * N + i] += wx * wy;
            }
        }
        let (mut v, mut norm2) = (0.0, 0.0);
        for (k, wk) in per.iter().enumerate() {
            v += wk * grid[k];
            norm2 += wk * wk;
        }
        [(v / norm2.sqrt()) as f32]
    })
}

/// The structured-light depth of the module documentation.
fn structured(depth_m: &DepthMap, cam: &PinholeCamera, rng: &mut impl rand::Rng) -> DepthMap {
    let (w, h) = depth_m.size();
    let fb = cam.fx * STRUCTURED_BASELINE_M;
    // σ_z = z² σ_d / (f b) = k z²  ⇒  σ_d = k f b, the same at every depth.
    let sigma_d = STRUCTURED_SIGMA_PER_M * fb;
    let min_cos = STRUCTURED_MAX_INCIDENCE_DEG.to_radians().cos();
    let z = |x: usize, y: usize| f64::from(depth_m.at(x, y));
    let point = |x: usize, y: usize| cam.unproject(x as f64, y as f64, z(x, y)).coords;
    let mut out = DepthMap::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let noise: f64 = StandardNormal.sample(rng);
            let zc = z(x, y);
            if zc <= 0.0 || x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
                continue;
            }
            let near = [z(x - 1, y), z(x + 1, y), z(x, y - 1), z(x, y + 1)];
            if near.iter().any(|&n| n <= 0.0 || (n - zc).abs() > STRUCTURED_EDGE_RELATIVE * zc) {
                continue;
            }
            let n = (point(x + 1, y) - point(x - 1, y)).cross(&(point(x, y + 1) - point(x, y - 1)));
            let ray = point(x, y);
            if n.norm() == 0.0 || n.dot(&ray).abs() < min_cos * n.norm() * ray.norm() {
                continue;
            }
            let d = fb / zc + sigma_d * noise;
            let dq = (d / STRUCTURED_DISPARITY_STEP_PX).round() * STRUCTURED_DISPARITY_STEP_PX;
            if dq > 0.0 {
                out.set_pixel(x, y, [(fb / dq) as f32]);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> PinholeCamera {
        PinholeCamera::new(160, 120, 80.0, 80.0, 79.5, 59.5)
    }

    #[test]
    fn the_smooth_field_has_zero_mean_and_unit_variance_at_every_pixel() {
        // Over many draws, at a grid node, between nodes and in a corner.
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(7);
        let probes = [(0, 0), (40, 30), (17, 83), (159, 119), (93, 61)];
        let mut sums = vec![(0.0, 0.0); probes.len()];
        let n = 4000;
        for _ in 0..n {
            let f = smooth_field(160, 120, &mut rng);
            for (s, &(x, y)) in sums.iter_mut().zip(&probes) {
                let v = f64::from(f.at(x, y));
                s.0 += v;
                s.1 += v * v;
            }
        }
        for ((s, ss), p) in sums.iter().zip(&probes) {
            let mean = s / n as f64;
            let var = ss / n as f64 - mean * mean;
            assert!(mean.abs() < 0.06, "{p:?}: mean {mean}");
            assert!((var - 1.0).abs() < 0.08, "{p:?}: variance {var}");
        }
    }

    #[test]
    fn the_smooth_field_is_smooth_and_differs_between_frames() {
        let d = DepthMap::from_fn(160, 120, |_, _| [0.05]);
        let a = DepthNoise::Smooth { relative: 0.05 }.apply(&d, &cam(), 1, 0);
        let b = DepthNoise::Smooth { relative: 0.05 }.apply(&d, &cam(), 1, 1);
        let again = DepthNoise::Smooth { relative: 0.05 }.apply(&d, &cam(), 1, 0);
        assert_eq!(a, again, "deterministic for (seed, frame)");
        assert_ne!(a, b, "drawn anew each frame");
        // Neighbouring pixels differ by a small part of σ (40 px between grid nodes).
        let sigma = 0.05 * 0.05;
        let step = (1..160).map(|x| (a.at(x, 60) - a.at(x - 1, 60)).abs()).fold(0.0f32, f32::max);
        assert!(f64::from(step) < 0.15 * sigma, "largest step {step} m against σ {sigma} m");
    }

    #[test]
    fn structured_noise_follows_the_square_law_and_leaves_holes_at_edges_and_grazing_walls() {
        let c = cam();
        // A plane at 50 mm facing the camera, with a 20 mm step on its right third.
        let d = DepthMap::from_fn(160, 120, |x, _| [if x < 100 { 0.05 } else { 0.07 }]);
        let mut errs = Vec::new();
        for frame in 0..20 {
            let n = DepthNoise::Structured.apply(&d, &c, 3, frame);
            for y in 1..119 {
                assert_eq!(n.at(99, y), 0.0, "a hole at the depth edge");
                assert_eq!(n.at(100, y), 0.0, "a hole at the depth edge");
                for x in 1..98 {
                    errs.push(f64::from(n.at(x, y)) - 0.05);
                }
            }
        }
        let sd = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
        let expected = STRUCTURED_SIGMA_PER_M * 0.05 * 0.05;
        assert!((sd / expected - 1.0).abs() < 0.1, "σ {sd} m against {expected} m");
        // A plane seen at 75° from its normal has no return, at 60° it has (both without a
        // depth edge: the relative depth step per pixel stays below 5 %).
        let plane = |deg: f64| {
            let tilt = deg.to_radians().tan();
            DepthMap::from_fn(160, 120, |x, _| {
                let u = (x as f64 - c.cx) / c.fx;
                [(0.05 / (1.0 - tilt * u)).clamp(0.0, 1.0) as f32]
            })
        };
        assert_eq!(DepthNoise::Structured.apply(&plane(75.0), &c, 3, 0).at(80, 60), 0.0, "grazing incidence gives no return");
        assert!(DepthNoise::Structured.apply(&plane(60.0), &c, 3, 0).at(80, 60) > 0.0, "60° gives a return");
    }

    #[test]
    fn bad_specs_are_refused_with_the_expected_form() {
        assert_eq!("smooth:0.05".parse::<DepthNoise>(), Ok(DepthNoise::Smooth { relative: 0.05 }));
        assert_eq!("structured".parse::<DepthNoise>(), Ok(DepthNoise::Structured));
        for bad in ["smooth", "smooth:-0.1", "smooth:NaN", "smooth:2", "gauss"] {
            let e = bad.parse::<DepthNoise>().unwrap_err();
            assert!(e.contains("smooth:0.05"), "{bad}: {e}");
        }
    }
}
