//! Fitting `light.toml` to images of a target of known geometry and albedo (`capsule-slam
//! calibrate-light`): Levenberg-Marquardt on the encoded pixel values,
//!
//! `value_c = (V(u) · ρ_c · (gain · cos θ · (ref / r)² · spot + ambient))^(1/γ)`,
//!
//! over the unknowns `ln gain`, `ambient`, `γ` and the vignetting `v1, v2, v3`, each pixel a
//! sample with its camera-frame point and normal (from the target's depth), Huber-weighted so
//! that highlights and edge pixels do not pull the fit. The light position and the LED profile
//! exponent are given: with the light at the optical centre the profile `cos^e` of the angle to
//! the axis is a function of the pixel alone, exactly like vignetting, so the two cannot be told
//! apart from images; the fitted `V` absorbs whatever profile the given exponent misses, and the
//! product `V · spot` that shape from shading uses is what the fit recovers.

use nalgebra::{DMatrix, DVector, Point3, Vector3};

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::light::LightModel;

/// One observed pixel of the calibration target.
#[derive(Debug, Clone, Copy)]
pub struct LightSample {
    /// Pixel column.
    pub u: f64,
    /// Pixel row.
    pub v: f64,
    /// The target point in the camera frame, metres.
    pub p_cam: Point3<f64>,
    /// Its unit normal toward the camera.
    pub n_cam: Vector3<f64>,
    /// Encoded pixel value per channel in [0, 1].
    pub value: [f64; 3],
}

/// What the fit is told.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// The target's linear albedo per channel.
    pub albedo: [f64; 3],
    /// Light position in the camera frame, metres.
    pub position_m: [f64; 3],
    /// LED profile exponent.
    pub spot_exponent: f64,
    /// Reference distance of the gain, metres.
    pub ref_distance_m: f64,
    /// Levenberg-Marquardt iterations.
    pub iterations: u32,
    /// Huber threshold on the encoded residual.
    pub huber: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self { albedo: [0.5; 3], position_m: [0.0; 3], spot_exponent: 0.0, ref_distance_m: 0.025, iterations: 50, huber: 0.02 }
    }
}

/// The fitted light and how well it explains the samples.
#[derive(Debug, Clone)]
pub struct LightFit {
    /// The fitted model.
    pub light: LightModel,
    /// RMS of the encoded residuals over the samples (0–1 scale).
    pub rms: f64,
    /// Samples kept for the final fit.
    pub samples: usize,
}

/// Why a fit failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    /// Too few usable samples.
    #[error("only {0} usable calibration pixels (need ≥ 100): give frames where the target fills the view, neither saturated nor black")]
    TooFewSamples(usize),
    /// The normal equations were singular.
    #[error("the fit is degenerate (singular normal equations): use frames at several distances that cover the whole field of view")]
    Degenerate,
}

const N: usize = 6;

fn model(theta: &[f64; N], opts: &FitOptions) -> LightModel {
    LightModel {
        gain: theta[0].exp(),
        ref_distance_m: opts.ref_distance_m,
        ambient: theta[1],
        gamma: theta[2],
        position_m: opts.position_m,
        spot_exponent: opts.spot_exponent,
        vignetting: vec![theta[3], theta[4], theta[5]],
    }
}

fn residuals(theta: &[f64; N], samples: &[LightSample], cam: &PinholeCamera, opts: &FitOptions) -> Vec<f64> {
    let light = model(theta, opts);
    let mut out = Vec::with_capacity(samples.len() * 3);
    for s in samples {
        let v = light.vignetting_at(cam, s.u, s.v);
        let irradiance = light.direct(&s.p_cam, &s.n_cam) + light.ambient;
        for c in 0..3 {
            let lin = (v * opts.albedo[c] * irradiance).max(1e-12);
            out.push(lin.powf(1.0 / light.gamma) - s.value[c]);
        }
    }
    out
}

fn cost(r: &[f64], k: f64) -> f64 {
    r.iter().map(|e| if e.abs() <= k { 0.5 * e * e } else { k * (e.abs() - 0.5 * k) }).sum()
}

/// Fits the light model to the samples (saturated or black channels should be left out by the
/// caller). Starts from gain 1, ambient 0.01, γ 2.2 and no vignetting; then drops the samples
/// the first fit explains worst (residual above 3 robust standard deviations: unsaturated
/// highlights, depth edges) and fits again from there.
pub fn fit_light(samples: &[LightSample], cam: &PinholeCamera, opts: &FitOptions) -> Result<LightFit, FitError> {
    if samples.len() < 100 {
        return Err(FitError::TooFewSamples(samples.len()));
    }
    let first = fit_from([0.0, 0.01, 2.2, 0.0, 0.0, 0.0], samples, cam, opts)?;
    let r = residuals(&first.0, samples, cam, opts);
    let per_sample: Vec<f64> = r.chunks(3).map(|c| c.iter().fold(0.0, |m: f64, e| m.max(e.abs()))).collect();
    let mut sorted = per_sample.clone();
    sorted.sort_by(f64::total_cmp);
    let sigma = 1.4826 * sorted[sorted.len() / 2];
    let kept: Vec<LightSample> = samples.iter().zip(&per_sample).filter(|(_, e)| **e <= 3.0 * sigma.max(1e-4)).map(|(s, _)| *s).collect();
    if kept.len() < 100 {
        return Ok(LightFit { light: model(&first.0, opts), rms: first.1, samples: samples.len() });
    }
    let (theta, rms) = fit_from(first.0, &kept, cam, opts)?;
    Ok(LightFit { light: model(&theta, opts), rms, samples: kept.len() })
}

/// Levenberg-Marquardt from `theta`; returns the parameters and the RMS residual.
fn fit_from(mut theta: [f64; N], samples: &[LightSample], cam: &PinholeCamera, opts: &FitOptions) -> Result<([f64; N], f64), FitError> {
    let mut r = residuals(&theta, samples, cam, opts);
    let mut current = cost(&r, opts.huber);
    let mut mu = 1e-3;
    for _ in 0..opts.iterations {
        // Numeric Jacobian (central differences), Huber weights (IRLS).
        let m = r.len();
        let mut jac = DMatrix::<f64>::zeros(m, N);
        for k in 0..N {
            let h = 1e-6 * (1.0 + theta[k].abs());
            let (mut tp, mut tm) = (theta, theta);
            tp[k] += h;
            tm[k] -= h;
            let (rp, rm) = (residuals(&tp, samples, cam, opts), residuals(&tm, samples, cam, opts));
            for i in 0..m {
                jac[(i, k)] = (rp[i] - rm[i]) / (2.0 * h);
            }
        }
        let w: Vec<f64> = r.iter().map(|e| if e.abs() <= opts.huber { 1.0 } else { opts.huber / e.abs() }).collect();
        let mut jtj = DMatrix::<f64>::zeros(N, N);
        let mut jtr = DVector::<f64>::zeros(N);
        for i in 0..m {
            let row = jac.row(i);
            jtj += w[i] * row.transpose() * row;
            jtr += w[i] * r[i] * row.transpose();
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut a = jtj.clone();
            for k in 0..N {
                a[(k, k)] *= 1.0 + mu;
                a[(k, k)] += 1e-12;
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-&jtr))) else { return Err(FitError::Degenerate) };
            let mut trial = theta;
            for k in 0..N {
                trial[k] += step[k];
            }
            trial[1] = trial[1].max(0.0);
            trial[2] = trial[2].clamp(0.5, 5.0);
            let rt = residuals(&trial, samples, cam, opts);
            let c = cost(&rt, opts.huber);
            if c.is_finite() && c < current {
                let rel = (current - c) / current.max(1e-300);
                theta = trial;
                r = rt;
                current = c;
                mu = (mu * 0.3).max(1e-9);
                improved = rel > 1e-10;
                break;
            }
            mu *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let rms = (r.iter().map(|e| e * e).sum::<f64>() / r.len() as f64).sqrt();
    Ok((theta, rms))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane at distance `d` tilted by `n`, seen by `cam` under `light`: encoded, noise-free
    /// samples on a grid.
    fn plane_samples(cam: &PinholeCamera, light: &LightModel, albedo: [f64; 3], d: f64, n: Vector3<f64>) -> Vec<LightSample> {
        let n = n.normalize();
        let q = Vector3::new(0.0, 0.0, d);
        let mut out = Vec::new();
        for y in (0..cam.height).step_by(4) {
            for x in (0..cam.width).step_by(4) {
                if !cam.in_fov(x as f64, y as f64) {
                    continue;
                }
                let ray = cam.unproject(x as f64, y as f64, 1.0).coords;
                let t = n.dot(&q) / n.dot(&ray);
                let p = Point3::from(ray * t);
                let value = albedo.map(|a| light.encode(light.linear(cam, x as f64, y as f64, a, &p, &n)));
                if value.iter().all(|v| *v > 0.02 && *v < 0.98) {
                    out.push(LightSample { u: x as f64, v: y as f64, p_cam: p, n_cam: n, value });
                }
            }
        }
        out
    }

    #[test]
    fn planes_at_known_distances_give_back_the_light() {
        let mut cam = PinholeCamera::new(160, 160, 80.0, 80.0, 79.5, 79.5);
        cam.fov_radius_px = Some(76.0);
        let truth = LightModel { gain: 0.6, ambient: 0.02, gamma: 2.2, spot_exponent: 1.0, vignetting: vec![-0.3, -0.25], ..LightModel::default() };
        let albedo = [0.8, 0.3, 0.25];
        let mut samples = Vec::new();
        for (d, n) in [(0.015, Vector3::new(0.0, 0.0, -1.0)), (0.025, Vector3::new(0.2, 0.0, -1.0)), (0.04, Vector3::new(0.0, -0.3, -1.0))] {
            samples.extend(plane_samples(&cam, &truth, albedo, d, n));
        }
        let fit = fit_light(&samples, &cam, &FitOptions { albedo, spot_exponent: 1.0, ..FitOptions::default() }).unwrap();
        let l = &fit.light;
        assert!((l.gain / truth.gain - 1.0).abs() < 0.01, "{l:?}");
        assert!((l.gamma - truth.gamma).abs() < 0.02, "{l:?}");
        assert!((l.ambient - truth.ambient).abs() < 0.002, "{l:?}");
        for (u, v) in [(79.5, 79.5), (120.0, 79.5), (140.0, 120.0)] {
            let (a, b) = (l.vignetting_at(&cam, u, v), truth.vignetting_at(&cam, u, v));
            assert!((a / b - 1.0).abs() < 0.01, "V at ({u}, {v}): {a} vs {b}");
        }
        assert!(fit.rms < 1e-3, "noise-free samples are explained: rms {}", fit.rms);
    }

    #[test]
    fn a_profile_exponent_set_wrong_is_absorbed_by_the_vignetting() {
        // Light at the optical centre: V · spot is what matters; with spot_exponent = 0 the fit
        // puts the LED profile into V.
        let mut cam = PinholeCamera::new(120, 120, 60.0, 60.0, 59.5, 59.5);
        cam.fov_radius_px = Some(57.0);
        let truth = LightModel { gain: 0.8, ambient: 0.01, spot_exponent: 1.0, vignetting: vec![-0.2, -0.1], ..LightModel::default() };
        let albedo = [0.6, 0.6, 0.6];
        let mut samples = plane_samples(&cam, &truth, albedo, 0.02, Vector3::new(0.0, 0.0, -1.0));
        samples.extend(plane_samples(&cam, &truth, albedo, 0.035, Vector3::new(0.1, 0.1, -1.0)));
        let fit = fit_light(&samples, &cam, &FitOptions { albedo, spot_exponent: 0.0, ..FitOptions::default() }).unwrap();
        for s in samples.iter().step_by(37) {
            let product = |l: &LightModel| l.vignetting_at(&cam, s.u, s.v) * l.falloff(&s.p_cam);
            assert!((product(&fit.light) / product(&truth) - 1.0).abs() < 0.02, "at ({}, {})", s.u, s.v);
        }
    }

    #[test]
    fn too_few_samples_is_a_clear_error() {
        let cam = PinholeCamera::new(10, 10, 5.0, 5.0, 4.5, 4.5);
        assert_eq!(fit_light(&[], &cam, &FitOptions::default()).unwrap_err(), FitError::TooFewSamples(0));
    }
}
