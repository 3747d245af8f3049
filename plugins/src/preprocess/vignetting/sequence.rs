//! The fall-off estimated from the sequence itself, when there is no calibration (frontend
//! Goldman 2010: the vignetting of a video from its own frames, lens and light mixed): the trimmed mean linear
//! luminance of the usable pixels over cos³α (the flat field's own geometry, known from the
//! intrinsics) in each of `BINS` rings of r² over the frames seen, fitted by weighted least
//! squares with `G(r²) = a0 + a1 r² + a2 r⁴ + a3 r⁶` and normalised, `F = G / a0`: the
//! lens-and-light profile V · μ, as in `vignetting.toml`.
//!
//! As the scene moves while the fall-off stays, the average over many frames tends to the flat
//! field times the scene's average radial brightness: exact when the capsule looks at the wall
//! from every side equally, biased where the scene has a radial structure of its own (a tube seen
//! along its axis is dark in the middle). The bias is measured in the README.
//!
//! With geometry ([`Learner::add_shaded`], the map's prediction at the last pose) each pixel's
//! luminance is first divided by its near-light shading `cos θ / r²` (light at the optical
//! centre): what is left is V · μ times the albedo and the gain, and the scene's radial structure
//! is gone. This needs geometry that does not itself come from the same fall-off (measured or
//! stereo depth).

use capsule_slam_framework::Rgb8;
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::Falloff;
use capsule_slam_framework::image::NTSC_WEIGHTS;
use capsule_slam_framework::light::vignetting::{RadialProfile, cos_alpha, radius2};
use nalgebra::{DMatrix, DVector};

/// Rings of r² in [0, 1].
const BINS: usize = 64;
/// Histogram bins of a ring's log samples (for the trimmed mean).
const HIST: usize = 2048;
/// Share of each ring's samples dropped at either end before averaging.
const TRIM: f64 = 0.1;
/// Range of the log samples (luminance, or luminance · r² / cos θ in m²).
const LN_LO: f64 = -24.0;
const LN_HI: f64 = 8.0;

/// Accumulated radial statistics.
pub struct Learner {
    degree: usize,
    /// 8-bit value → linear.
    decode: [f64; 256],
    /// Per ring, a histogram of the samples' logarithms (`HIST` bins over [`LN_LO`, `LN_HI`]).
    hist: Vec<Vec<u32>>,
    count: Vec<f64>,
    frames: usize,
    profile: Option<RadialProfile>,
}

impl Learner {
    /// An empty estimate with `degree` polynomial terms, for pixels encoded with `gamma`.
    pub fn new(degree: usize, gamma: f64) -> Self {
        Self {
            degree,
            decode: std::array::from_fn(|v| (v as f64 / 255.0).powf(gamma)),
            hist: vec![vec![0; HIST]; BINS],
            count: vec![0.0; BINS],
            frames: 0,
            profile: None,
        }
    }

    /// Frames added.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The current estimate of the lens-and-light profile, once one could be fitted.
    pub fn profile(&self) -> Option<&RadialProfile> {
        self.profile.as_ref()
    }

    /// Adds the pixels of `img` inside the field of view that `usable` allows, and refits.
    pub fn add(&mut self, img: &Rgb8, cam: &PinholeCamera, usable: impl Fn(usize, usize) -> bool) {
        let decode = self.decode;
        let (w, h) = img.size();
        for y in 0..h {
            for x in 0..w {
                let (u, v) = (x as f64, y as f64);
                if !cam.in_fov(u, v) || !usable(x, y) {
                    continue;
                }
                let lum: f64 = img.pixel(x, y).iter().zip(NTSC_WEIGHTS).map(|(c, wt)| wt * decode[usize::from(*c)]).sum::<f64>()
                    / Falloff::flat_to_lens_and_light(cos_alpha(cam, u, v));
                if lum <= 0.0 {
                    continue;
                }
                let bin = ((radius2(cam, u, v) * BINS as f64) as usize).min(BINS - 1);
                self.push(bin, lum);
            }
        }
        self.frames += 1;
        self.profile = self.fit();
    }

    /// Adds the pixels of `img` that `usable` allows and that have geometry: `depth_m` and
    /// unit `normals_cam` (toward the camera) of the same view, each luminance divided by its
    /// shading `cos θ / r²`; and refits.
    pub fn add_shaded(
        &mut self,
        img: &Rgb8,
        cam: &PinholeCamera,
        usable: impl Fn(usize, usize) -> bool,
        depth_m: &capsule_slam_framework::DepthMap,
        normals_cam: &capsule_slam_framework::Image<f32, 3>,
    ) {
        let decode = self.decode;
        let (w, h) = img.size();
        if depth_m.size() != (w, h) || normals_cam.size() != (w, h) {
            return;
        }
        let mut added = false;
        for y in 0..h {
            for x in 0..w {
                let (u, v) = (x as f64, y as f64);
                let d = f64::from(depth_m.at(x, y));
                if !(cam.in_fov(u, v) && usable(x, y) && d.is_finite() && d > 0.0) {
                    continue;
                }
                let p = cam.unproject(u, v, d);
                let r = p.coords.norm();
                let n = normals_cam.pixel(x, y);
                let cos_theta = -(f64::from(n[0]) * p.x + f64::from(n[1]) * p.y + f64::from(n[2]) * p.z) / r;
                if cos_theta < 0.3 {
                    continue;
                }
                let lum: f64 = img.pixel(x, y).iter().zip(NTSC_WEIGHTS).map(|(c, wt)| wt * decode[usize::from(*c)]).sum();
                if lum <= 0.0 {
                    continue;
                }
                let bin = ((radius2(cam, u, v) * BINS as f64) as usize).min(BINS - 1);
                self.push(bin, lum * r * r / cos_theta);
                added = true;
            }
        }
        if added {
            self.frames += 1;
            self.profile = self.fit();
        }
    }

    fn push(&mut self, ring: usize, value: f64) {
        let t = (value.ln() - LN_LO) / (LN_HI - LN_LO) * HIST as f64;
        if t.is_finite() {
            self.hist[ring][(t.max(0.0) as usize).min(HIST - 1)] += 1;
            self.count[ring] += 1.0;
        }
    }

    /// The mean of a ring's samples between their `TRIM` and `1 − TRIM` quantiles (from the
    /// histogram, bin centres): robust to the highlights and shadows a plain mean takes in.
    fn trimmed_mean(&self, ring: usize) -> f64 {
        let (lo, hi) = (TRIM * self.count[ring], (1.0 - TRIM) * self.count[ring]);
        let (mut below, mut sum, mut weight) = (0.0, 0.0, 0.0);
        for (i, c) in self.hist[ring].iter().enumerate() {
            let c = f64::from(*c);
            // The part of this bin's samples that lies between the two quantiles.
            let take = (below + c).min(hi) - below.max(lo);
            if take > 0.0 {
                let v = (LN_LO + (i as f64 + 0.5) / HIST as f64 * (LN_HI - LN_LO)).exp();
                sum += take * v;
                weight += take;
            }
            below += c;
        }
        if weight > 0.0 { sum / weight } else { 0.0 }
    }

    fn fit(&self) -> Option<RadialProfile> {
        let n = self.degree + 1;
        let mut a = DMatrix::<f64>::zeros(n, n);
        let mut b = DVector::<f64>::zeros(n);
        for i in 0..BINS {
            if self.count[i] <= 0.0 {
                continue;
            }
            let r2 = (i as f64 + 0.5) / BINS as f64;
            let value = self.trimmed_mean(i);
            let row: Vec<f64> = (0..n).map(|k| r2.powi(k as i32)).collect();
            for p in 0..n {
                b[p] += self.count[i] * row[p] * value;
                for q in 0..n {
                    a[(p, q)] += self.count[i] * row[p] * row[q];
                }
            }
        }
        let g = a.cholesky()?.solve(&b);
        let a0 = g[0];
        (a0 > 0.0 && g.iter().all(|v| v.is_finite())).then(|| RadialProfile { coeffs: g.iter().skip(1).map(|v| v / a0).collect() })
    }
}
