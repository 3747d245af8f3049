//! The live depth's error as the model sees it (issue 17): a sequence that declares no depth
//! noise (`camera.toml` without `depth_noise`, a TUM folder, a recording whose sensor nobody
//! measured) gets the `sensor` stage's small uncorrelated default, and a depth 5 % off, correlated
//! over a fifth of the image, then pulls the pose by millimetres that the tracker trusts to
//! 0.1 mm: it lost 247 of 300 frames of preset 1 (`docs/results/depth-noise.md`).
//!
//! After each tracked frame the point-to-plane residuals at the tracked pose (level 1, every
//! correspondence within `icp_gate_m`) are read as the live depth's relative error,
//! `nᵀ(s − d) / nᵀs`: a point whose depth is off by a factor `1 + ε` moves along its ray,
//! `s = (1 + ε) s₀`, and reads `ε / (1 + ε)`, its error relative to the live depth, as
//! `σ = relative · z` is applied to it. Its scale is the median absolute deviation's
//! (`1.4826 · MAD`, robust to the tails a gate cuts); its correlation length is read from the
//! variogram `γ(L) = ½ E[(ε(u + L) − ε(u))²]` (Cressie 1993, Ch. 2) at lags of 1–32 pixels: the
//! correlation `ρ(L) = 1 − γ(L) / var ε` falls to ½ at half the side of an equivalent block of
//! one shared error (for an error constant over blocks of side B, `ρ(L) = 1 − L / B`), the
//! `correlation_px` the depth stages declare. Both are averaged over frames
//! (`depth_error_memory`). The model is an average of many frames and the tracked pose
//! explains what it can, so the residual overstates the depth's error a little (by √2 where the
//! reference is the previous frame, the fill-in): the estimate is a bound, not a measurement.
//!
//! Where it exceeds the frame's own σ by `depth_error_factor` (the median over the frame's
//! pixels), the next frames' σ is raised to it ([`MeasuredNoise::apply`], with a warning that
//! names both figures). Declared models that the data bear out are left as they are: the
//! phantom's declared smooth and structured-light errors, exact depth and stereo depth track
//! to the bit as before.

use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::frame::DepthSource;
use capsule_slam_framework::{Context, Iso3};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::IcpRgb;
use super::frames::Level;
use super::terms::nearest_pixel;
use crate::common::maps::{normal, vertex};

/// Lags of the variogram, pixels of the level measured.
const LAGS_PX: [usize; 6] = [1, 2, 4, 8, 16, 32];
/// Fewest residuals a frame must give to be measured.
const MIN_SAMPLES: usize = 500;
/// Every how many pixels and rows [`MeasuredNoise::compare`] reads the frame.
const COMPARE_STEP: usize = 4;
/// Least obliquity kept, `|nᵀs| / |s|`: at grazing incidence a depth error hardly moves the
/// residual, and ε would divide by almost nothing.
const MIN_COS: f64 = 0.5;

/// One frame's measurement: the relative error's robust σ and its correlation length in pixels
/// of level 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measured {
    pub relative: f64,
    pub correlation_px: f64,
}

/// The running estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeasuredNoise {
    /// Relative σ of the live depth, the frames' variances averaged.
    pub relative: f64,
    /// Correlation length, pixels of level 0.
    pub correlation_px: f64,
    /// Frames measured.
    pub frames: u32,
}

/// The live depth's relative error per pixel of `live` at the pose `t_ref_live`, against the
/// reference (NaN where it has none): residuals within `gate_m` whose normals agree within
/// `cos_gate`.
pub fn residual_image(live: &Level, reference: &Level, t_ref_live: &Iso3, gate_m: f64, cos_gate: f64) -> (usize, usize, Vec<f64>) {
    let (w, h) = live.depth.size();
    let (cam, size) = (&reference.cam, reference.depth.size());
    let mut out = vec![f64::NAN; w * h];
    out.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        for (x, e) in row.iter_mut().enumerate() {
            let (Some(v), Some(nl)) = (vertex(&live.vertices, x, y), normal(&live.normals, x, y)) else { continue };
            let s = (t_ref_live * Point3::from(v.cast::<f64>())).coords;
            if s.z <= 0.0 {
                continue;
            }
            let Some((_, (ui, vi))) = nearest_pixel(cam, &s, size) else { continue };
            let (Some(d), Some(n)) = (vertex(&reference.vertices, ui, vi), normal(&reference.normals, ui, vi)) else { continue };
            let (d, n): (Vector3<f64>, Vector3<f64>) = (d.cast(), n.cast());
            let along = n.dot(&s);
            if (s - d).norm() > gate_m || (t_ref_live.rotation * nl.cast::<f64>()).dot(&n) < cos_gate || along.abs() < MIN_COS * s.norm() {
                continue;
            }
            *e = n.dot(&(s - d)) / along;
        }
    });
    (w, h, out)
}

/// The robust σ and correlation length (pixels of the image's own grid) of a residual image
/// (NaN: none), or none with fewer than [`MIN_SAMPLES`] residuals or no spread.
pub fn measure((w, h, e): (usize, usize, &[f64])) -> Option<(f64, f64)> {
    let mut valid: Vec<f64> = e.iter().copied().filter(|v| v.is_finite()).collect();
    if valid.len() < MIN_SAMPLES {
        return None;
    }
    let median = median(&mut valid);
    let mut dev: Vec<f64> = valid.iter().map(|v| (v - median).abs()).collect();
    let sigma = 1.4826 * self::median(&mut dev);
    if sigma <= 0.0 || !sigma.is_finite() {
        return None;
    }
    // The variogram on the values clipped to ±4σ about the median: a few gross residuals do
    // not set the correlation.
    let clip = |v: f64| (v - median).clamp(-4.0 * sigma, 4.0 * sigma);
    let variance = valid.iter().map(|v| clip(*v).powi(2)).sum::<f64>() / valid.len() as f64;
    let e: Vec<f64> = e.iter().map(|v| if v.is_finite() { clip(*v) } else { f64::NAN }).collect();
    let mut previous = (0.0, 1.0);
    for &lag in LAGS_PX.iter().filter(|l| **l < w.max(h)) {
        // Rows in parallel, summed in row order: the same sum on any number of threads.
        let rows: Vec<(f64, usize)> = (0..h)
            .into_par_iter()
            .map(|y| {
                let (mut sum, mut n) = (0.0, 0usize);
                for x in 0..w {
                    let a = e[y * w + x];
                    if !a.is_finite() {
                        continue;
                    }
                    for (bx, by) in [(x + lag, y), (x, y + lag)] {
                        if bx < w && by < h && e[by * w + bx].is_finite() {
                            sum += 0.5 * (e[by * w + bx] - a).powi(2);
                            n += 1;
                        }
                    }
                }
                (sum, n)
            })
            .collect();
        let (sum, n) = rows.iter().fold((0.0, 0usize), |(s, c), (rs, rc)| (s + rs, c + rc));
        if n == 0 {
            break;
        }
        let rho = 1.0 - sum / n as f64 / variance;
        if rho <= 0.5 {
            // Linear between the last lag above ½ and this one; a block of side 2 L½.
            let (l0, r0) = previous;
            let half = l0 + (r0 - 0.5) / (r0 - rho) * (lag as f64 - l0);
            return Some((sigma, 2.0 * half));
        }
        previous = (lag as f64, rho);
    }
    Some((sigma, 2.0 * previous.0.max(1.0)))
}

fn median(v: &mut [f64]) -> f64 {
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

impl MeasuredNoise {
    /// The estimate with one more frame's measurement: each frame weighs `1 / memory` of the
    /// variance and the correlation length (the first frame all of it).
    pub fn update(current: Option<Self>, m: Measured, memory: f64) -> Self {
        match current {
            None => Self { relative: m.relative, correlation_px: m.correlation_px, frames: 1 },
            Some(c) => {
                let a = (1.0 / memory.max(1.0)).max(1.0 / f64::from(c.frames + 1));
                let variance = (1.0 - a) * c.relative * c.relative + a * m.relative * m.relative;
                Self { relative: variance.sqrt(), correlation_px: (1.0 - a) * c.correlation_px + a * m.correlation_px, frames: c.frames + 1 }
            }
        }
    }

    /// The estimate as a depth noise model, σ = `relative · z`, correlated over
    /// `correlation_px` pixels of level 0.
    pub fn model(&self) -> DepthNoiseModel {
        DepthNoiseModel { absolute_m: 0.0, relative: self.relative, quadratic_per_m: 0.0, correlation_px: self.correlation_px }
    }

    /// The frame's own σ, the median of `level`'s (level 0's) σ over its pixels with depth, and
    /// the σ this estimate gives them, the median of `relative · depth` (`relative` times the
    /// median depth: the same pixel's), over every [`COMPARE_STEP`]-th pixel of every
    /// `COMPARE_STEP`-th row (a median needs no more, and this runs twice a frame): none where
    /// the level carries no σ (estimated depth keeps its own scale).
    pub fn compare(&self, level: &Level) -> Option<(f64, f64)> {
        let sigma = level.sigma.as_ref()?;
        let (w, h) = level.depth.size();
        let (mut own, mut depth) = (Vec::new(), Vec::new());
        for y in (0..h).step_by(COMPARE_STEP) {
            for x in (0..w).step_by(COMPARE_STEP) {
                let d = level.depth.at(x, y);
                if d > 0.0 {
                    own.push(f64::from(sigma.at(x, y)));
                    depth.push(f64::from(d));
                }
            }
        }
        if own.is_empty() {
            return None;
        }
        Some((median(&mut own), self.model().sigma_m(median(&mut depth))))
    }

    /// Raises every level's σ to `relative · depth` where that is larger, and its correlation
    /// length to the estimate's (pixels of level 0 halved per level), as the pipeline raises
    /// the frame's ([`DepthNoiseModel::raise`]).
    pub fn apply(&self, levels: &mut [Level]) {
        for (l, level) in levels.iter_mut().enumerate() {
            let model = DepthNoiseModel { correlation_px: self.correlation_px / f64::from(1u32 << l), ..self.model() };
            model.raise(&level.depth, &mut level.sigma, &mut level.sigma_correlation_px);
        }
    }
}

impl IcpRgb {
    /// Raises the live pyramid's σ to the depth error measured against the model (`measured_noise.rs`)
    /// where that exceeds the frame's own by `depth_error_factor`, and says so once.
    pub(super) fn weigh_by_measured_error(&mut self, live: &mut [Level], ctx: &mut Context) {
        let factor = self.params.depth_error_factor;
        let (Some(e), Some(first)) = (self.depth_error, live.first()) else { return };
        let Some((own_m, measured_m)) = e.compare(first) else { return };
        // What the tracker takes a residual's σ to be: the registration floor and the frame's σ.
        let assumed_m = own_m.hypot(self.params.sigma_icp_m);
        let raise = factor > 0.0 && measured_m > factor * assumed_m;
        ctx.count("depth_error_rel_percent", 100.0 * e.relative);
        ctx.count("depth_error_correlation_px", e.correlation_px);
        ctx.count("depth_sigma_raised", f64::from(u8::from(raise)));
        if !raise {
            return;
        }
        e.apply(live);
        self.noise_in_use = Some(e.model());
        if !std::mem::replace(&mut self.depth_error_told, true) {
            ctx.warn(format!(
                "the depth is noisier than its σ says: against the model its error is {:.1} % of the depth (median {:.2} mm), correlated over {:.0} px, where the frame's σ is {:.3} mm ({:.3} mm with the registration floor sigma_icp_m); tracking and fusion weigh it by the measured error from here on (declare the sensor's depth_noise in camera.toml, docs/usage.md; depth_error_factor = 0 under the tracker's table, or [plugins.nonrigid.rigid], turns this off)",
                100.0 * e.relative,
                measured_m * 1e3,
                e.correlation_px,
                own_m * 1e3,
                assumed_m * 1e3
            ));
        }
    }

    /// Measures the depth error of the frame just tracked, `live` at the pose `t_ref_live`
    /// against `reference`, at level 1 (`measured_noise.rs`), into the running estimate.
    fn observe_depth_error(&mut self, live: &[Level], reference: &[Level], t_ref_live: &Iso3) {
        if self.params.depth_error_factor <= 0.0 {
            return;
        }
        let (Some(l), Some(r)) = (live.get(1), reference.get(1)) else { return };
        let (w, h, e) = residual_image(l, r, t_ref_live, self.params.icp_gate_m, self.params.icp_angle_gate_rad.cos());
        if let Some((relative, correlation)) = measure((w, h, &e)) {
            let m = Measured { relative, correlation_px: 2.0 * correlation };
            self.depth_error = Some(MeasuredNoise::update(self.depth_error, m, self.params.depth_error_memory));
        }
    }

    /// Measures the depth error of `live` (measured depth) at the pose `t` against `reference`
    /// into the running estimate ([`IcpRgb::observe_depth_error`]); where the estimate now
    /// outweighs the frame's σ by `depth_error_factor`, raises it
    /// ([`IcpRgb::weigh_by_measured_error`]) and returns true: the frame is registered again.
    pub(super) fn measure_noise(&mut self, live: &mut [Level], reference: &[Level], t: &Iso3, depth_source: DepthSource, ctx: &mut Context) -> bool {
        if depth_source != DepthSource::Measured {
            return false;
        }
        let clock = std::time::Instant::now();
        self.observe_depth_error(live, reference, t);
        ctx.count("ms_depth_error", clock.elapsed().as_secs_f64() * 1e3);
        let before = self.noise_in_use;
        self.weigh_by_measured_error(live, ctx);
        let again = self.noise_in_use.is_some() && self.noise_in_use != before;
        if again {
            ctx.count("depth_error_retried", 1.0);
        }
        again
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random value in (−√3, √3): unit variance.
    fn noise(i: u64) -> f64 {
        let mut z = i.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(0x6A09_E667_F3BC_C909);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 3f64.sqrt()
    }

    #[test]
    fn a_white_error_has_its_sigma_and_no_correlation() {
        let (w, h) = (160, 160);
        let e: Vec<f64> = (0..w * h).map(|i| 0.03 * noise(i as u64)).collect();
        let (sigma, corr) = measure((w, h, &e)).expect("measured");
        // A uniform error's MAD-σ is 1.4826 · (√3 / 2) · 0.03 = 0.0385.
        assert!((sigma - 0.0385).abs() < 0.002, "σ {sigma}");
        assert!(corr < 1.5, "correlation {corr} px");
    }

    #[test]
    fn an_error_shared_by_blocks_is_correlated_over_their_side() {
        let (w, h) = (160, 160);
        for block in [8usize, 16, 40] {
            // Blocks at random offsets per row band would blur the side; a regular grid of
            // blocks has ρ(L) = 1 − L / B along each axis.
            let e: Vec<f64> = (0..w * h).map(|i| 0.05 * noise(((i % w) / block + 1000 * ((i / w) / block)) as u64)).collect();
            let (_, corr) = measure((w, h, &e)).expect("measured");
            assert!((corr / block as f64 - 1.0).abs() < 0.25, "block {block}: correlation {corr} px");
        }
    }

    #[test]
    fn a_depth_off_by_a_factor_reads_as_that_relative_error_at_every_pixel() {
        use super::super::frames::{DepthPrep, pyramid};
        use capsule_slam_framework::{DepthMap, GrayF32, PinholeCamera};
        let cam = PinholeCamera::new(64, 48, 50.0, 50.0, 31.5, 23.5);
        let prep = DepthPrep { min_m: 0.001, max_m: 1.0, radius_px: 0, sigma_px: 1.0, sigma_m: 0.001, edge_jump_m: 0.01 };
        // A tilted plane, z = 0.05 + 0.01 x' along the image's x (x' the ray's slope).
        let plane = |x: usize| 0.05 / (1.0 - 0.2 * (x as f64 - cam.cx) / cam.fx);
        let level = |scale: f64| {
            let depth = DepthMap::from_fn(64, 48, |x, _| [(scale * plane(x)) as f32]);
            pyramid(depth, GrayF32::filled(64, 48, 0.5), (None, None), &cam, 1, &prep).remove(0)
        };
        let (live, reference) = (level(1.03), level(1.0));
        let (w, h, e) = residual_image(&live, &reference, &Iso3::identity(), 0.004, 0.5);
        let read: Vec<f64> = e.iter().copied().filter(|v| v.is_finite()).collect();
        assert_eq!((w, h), (64, 48));
        assert!(read.len() > 2000, "{} residuals", read.len());
        for v in read {
            assert!((v - 0.03 / 1.03).abs() < 1e-5, "ε {v}");
        }
        // Beyond the gate (3 % of 15 cm is 4.5 mm) nothing is read.
        let far = |scale: f64| {
            let depth = DepthMap::from_fn(64, 48, |x, _| [(3.0 * scale * plane(x)) as f32]);
            pyramid(depth, GrayF32::filled(64, 48, 0.5), (None, None), &cam, 1, &prep).remove(0)
        };
        let (_, _, e) = residual_image(&far(1.03), &far(1.0), &Iso3::identity(), 0.004, 0.5);
        assert!(e.iter().all(|v| v.is_nan()));
    }

    #[test]
    fn holes_and_too_few_residuals_are_not_an_estimate() {
        let (w, h) = (20, 20);
        let e: Vec<f64> = (0..w * h).map(|i| 0.01 * noise(i as u64)).collect();
        assert_eq!(measure((w, h, &e)), None, "400 residuals");
        let e = vec![f64::NAN; 160 * 160];
        assert_eq!(measure((160, 160, &e)), None);
        let e = vec![0.02; 160 * 160];
        assert_eq!(measure((160, 160, &e)), None, "no spread");
    }

    #[test]
    fn the_running_estimate_averages_variances_and_forgets_with_its_memory() {
        let m = |relative, correlation_px| Measured { relative, correlation_px };
        let first = MeasuredNoise::update(None, m(0.04, 60.0), 10.0);
        assert_eq!((first.relative, first.correlation_px, first.frames), (0.04, 60.0, 1));
        // The second frame weighs a half (1 / frames beats 1 / memory while young).
        let second = MeasuredNoise::update(Some(first), m(0.02, 20.0), 10.0);
        assert!((second.relative - (0.5f64 * 0.04 * 0.04 + 0.5 * 0.02 * 0.02).sqrt()).abs() < 1e-12);
        assert!((second.correlation_px - 40.0).abs() < 1e-12);
        let mut e = second;
        for _ in 0..200 {
            e = MeasuredNoise::update(Some(e), m(0.01, 2.0), 10.0);
        }
        assert!((e.relative - 0.01).abs() < 1e-6 && (e.correlation_px - 2.0).abs() < 1e-6, "{e:?}");
    }
}
