//! `near-light-sfs`: shape from shading for a capsule's near light (frontend digest §A7, after
//! Okatani & Deguchi 1997, CVIU 66(2), and Prados & Faugeras 2005): a perspective camera, a
//! point light at (or beside) the optical centre, and the calibrated photometric model of
//! `light.toml`,
//!
//! `L(u) = V(u) · ρ · (gain · cos θ · (ref / r)² · spot + ambient)`,
//!
//! with L the linear NTSC luminance of the pixel (each channel gamma-decoded), ρ the tissue's
//! luminance albedo, r the distance from the light. Solving for r gives
//! `r = ref · sqrt(gain · cos θ · spot / E)`, `E = L / (V ρ) − ambient`.
//! It starts from the pure fall-off estimate (cos θ = 1: well-posed, bright = near) and refines
//! cos θ by damped fixed-point iterations with normals from the smoothed current depth. Specular
//! and out-of-view pixels (the frame's masks), saturated and too-dark pixels get no depth.
//! The output is metric: its scale comes from the light model and the assumed albedo.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{CameraFrame, Context, DepthEstimate, DepthEstimator, DepthMap, GrayF32, Plugin, StageError, register};
use nalgebra::Vector3;
use rayon::prelude::*;

use crate::common::maps::{VertexMap, vertex, vertex_map};

capsule_slam_framework::plugin_params! {
    /// Parameters of `near-light-sfs`.
    pub struct NearLightSfsParams {
        /// Luminance albedo ρ of the tissue (NTSC-weighted linear reflectance; the phantom's
        /// mucosa: 0.444).
        pub albedo: f64 = 0.444; unit = "-"; range = 0.001..=1.0;
        /// The light model, relative to the input folder (written by the phantom or by
        /// `capsule-slam calibrate-light`).
        pub light_file: String = "light.toml".to_string(); unit = "path";
        /// Fixed-point refinements of the incidence term (0 = pure fall-off).
        pub iterations: u32 = 6; unit = "-"; range = 0.0..=100.0;
        /// Damping of each refinement (1 = take the new estimate).
        pub damping: f64 = 0.5; unit = "-"; range = 0.0..=1.0;
        /// Smallest cos θ trusted in a refinement (grazing incidence is ill-conditioned).
        pub min_cos: f64 = 0.2; unit = "-"; range = 0.0..=1.0;
        /// Pixels with any 8-bit channel at or above this are saturated (highlights): no depth.
        pub saturation: u8 = 250; unit = "8-bit"; range = 1.0..=255.0;
        /// Pixels darker than this linear luminance get no depth (noise dominates).
        pub min_luminance: f64 = 0.003; unit = "-"; range = 0.0..=1.0;
        /// Valid depth range: nearest.
        pub min_depth_m: f32 = 0.002; unit = "m"; range = 0.0..=100.0;
        /// Valid depth range: farthest.
        pub max_depth_m: f32 = 0.25; unit = "m"; range = 0.0..=100.0;
        /// Half-width of the box filter (applied three times, ≈ Gaussian) that smooths the depth
        /// the incidence term is computed from. The refinement amplifies depth errors of short
        /// wavelength; the incidence of organ walls varies slowly, fine shape comes from the
        /// per-pixel brightness.
        pub smooth_px: u32 = 4; unit = "px"; range = 0.0..=64.0;
    }
}

/// The near-light perspective shape-from-shading estimator.
pub struct NearLightSfs {
    params: NearLightSfsParams,
    light: LightModel,
}

impl Plugin for NearLightSfs {
    const NAME: &'static str = "near-light-sfs";
    const SUMMARY: &'static str =
        "metric depth from one image under the capsule's near light (albedo cos θ / r², calibrated light.toml), fall-off start + fixed-point refinement";
    type Params = NearLightSfsParams;

    fn build(params: NearLightSfsParams, env: &BuildEnv) -> Result<Self, StageError> {
        let path = match &env.input_dir {
            Some(dir) => dir.join(&params.light_file),
            None => std::path::PathBuf::from(&params.light_file),
        };
        let light = capsule_slam_framework::io::read_light_file(&path).map_err(|e| {
            StageError::invalid_input(format!("{e}; `near-light-sfs` needs the capsule's light model: put light.toml in the input folder (the phantom writes it) or set plugins.near-light-sfs.light_file"))
        })?;
        Ok(Self::with_light(params, light))
    }
}

/// Per-pixel inputs that do not change between refinements.
#[derive(Clone, Copy)]
struct Pixel {
    /// Unit ray direction.
    dir: Vector3<f64>,
    /// Irradiance term E = L / (V ρ) − ambient.
    e: f64,
    /// Confidence from the signal level.
    conf: f32,
}

impl NearLightSfs {
    /// An estimator with a given light model.
    pub fn with_light(params: NearLightSfsParams, light: LightModel) -> Self {
        Self { params, light }
    }

    /// Distance along `dir` at which the light is `r_light` away (light at `l`).
    fn along_ray(dir: &Vector3<f64>, l: &Vector3<f64>, r_light: f64) -> f64 {
        let dl = dir.dot(l);
        let disc = dl * dl - l.norm_squared() + r_light * r_light;
        if disc <= 0.0 { r_light } else { dl + disc.sqrt() }
    }

    fn spot(&self, p: &Vector3<f64>, l: &Vector3<f64>) -> f64 {
        if self.light.spot_exponent == 0.0 {
            return 1.0;
        }
        let d = p - l;
        (d.z / d.norm()).max(0.0).powf(self.light.spot_exponent)
    }

    /// Depth from the image alone.
    pub fn depth(&self, image: &capsule_slam_framework::Rgb8, ignore: Option<&capsule_slam_framework::Mask>, cam: &PinholeCamera) -> (DepthMap, GrayF32) {
        let p = &self.params;
        let (w, h) = image.size();
        let l = self.light.position().coords;
        let ws = [0.2989, 0.5870, 0.1140];
        let pixels: Vec<Option<Pixel>> = (0..w * h)
            .into_par_iter()
            .map(|k| {
                let (x, y) = (k % w, k / w);
                if ignore.is_some_and(|m| m.at(x, y)) || !cam.in_fov(x as f64, y as f64) {
                    return None;
                }
                let c = image.pixel(x, y);
                if c.iter().any(|v| *v >= p.saturation) {
                    return None;
                }
                let lum: f64 = (0..3).map(|i| ws[i] * self.light.decode(f64::from(c[i]) / 255.0)).sum();
                if lum < p.min_luminance {
                    return None;
                }
                let v = self.light.vignetting_at(cam, x as f64, y as f64);
                let e = lum / (v * p.albedo) - self.light.ambient;
                if e <= 1e-9 {
                    return None;
                }
                let dir = Vector3::new((x as f64 - cam.cx) / cam.fx, (y as f64 - cam.cy) / cam.fy, 1.0).normalize();
                let conf = ((lum - p.min_luminance) / 0.02).clamp(0.0, 1.0) as f32;
                Some(Pixel { dir, e, conf })
            })
            .collect();
        let r_of = |px: &Pixel, cos: f64, spot: f64| self.light.ref_distance_m * (self.light.gain * cos * spot / px.e).sqrt();
        // Pure fall-off start: cos θ = 1, spot along the ray from the light.
        let mut depth = DepthMap::from_fn_par(w, h, |x, y| {
            let Some(px) = &pixels[y * w + x] else { return [0.0] };
            let mut t = Self::along_ray(&px.dir, &l, r_of(px, 1.0, 1.0));
            t = Self::along_ray(&px.dir, &l, r_of(px, 1.0, self.spot(&(px.dir * t), &l)));
            [(t * px.dir.z) as f32]
        });
        for _ in 0..p.iterations {
            let smooth = smooth_depth(&depth, p.smooth_px as usize);
            let vertices = vertex_map(&smooth, cam);
            let prev = depth.clone();
            depth = DepthMap::from_fn_par(w, h, |x, y| {
                let (Some(px), z) = (&pixels[y * w + x], prev.at(x, y)) else { return [0.0] };
                if z <= 0.0 {
                    return [0.0];
                }
                let Some(n) = border_normal(&vertices, x, y, 2) else { return [z] };
                let pt = px.dir * (f64::from(z) / px.dir.z);
                let to_light = l - pt;
                let cos = (n.cast::<f64>().dot(&to_light) / to_light.norm()).max(p.min_cos);
                let t = Self::along_ray(&px.dir, &l, r_of(px, cos, self.spot(&pt, &l)));
                let z_new = t * px.dir.z;
                [((1.0 - p.damping) * f64::from(z) + p.damping * z_new) as f32]
            });
        }
        let (lo, hi) = (p.min_depth_m, p.max_depth_m);
        depth.data_mut().iter_mut().for_each(|d| {
            if !(d.is_finite() && *d >= lo && *d <= hi) {
                *d = 0.0;
            }
        });
        let conf = GrayF32::from_fn(w, h, |x, y| [if depth.at(x, y) > 0.0 { pixels[y * w + x].map_or(0.0, |px| px.conf) } else { 0.0 }]);
        (depth, conf)
    }
}

/// The normal at (x, y) toward the camera from central differences, or one-sided ones where a
/// neighbour is missing (the field-of-view border), over `step` pixels.
fn border_normal(v: &VertexMap, x: usize, y: usize, step: usize) -> Option<Vector3<f32>> {
    let c = vertex(v, x, y)?;
    let at = |dx: i64, dy: i64| {
        let (xx, yy) = (x as i64 + dx, y as i64 + dy);
        (xx >= 0 && yy >= 0 && (xx as usize) < v.width() && (yy as usize) < v.height()).then(|| vertex(v, xx as usize, yy as usize)).flatten()
    };
    let s = step as i64;
    let diff = |a: Option<Vector3<f32>>, b: Option<Vector3<f32>>| match (a, b) {
        (Some(a), Some(b)) => Some(a - b),
        (Some(a), None) => Some(a - c),
        (None, Some(b)) => Some(c - b),
        (None, None) => None,
    };
    let dx = diff(at(s, 0), at(-s, 0))?;
    let dy = diff(at(0, s), at(0, -s))?;
    let n = dx.cross(&dy);
    let len = n.norm();
    if len <= 0.0 {
        return None;
    }
    let n = -n / len;
    Some(if n.dot(&c) > 0.0 { -n } else { n })
}

/// Three passes of a normalised box filter of half-width `r` over the valid (non-zero) pixels;
/// invalid pixels stay invalid.
fn smooth_depth(d: &DepthMap, r: usize) -> DepthMap {
    if r == 0 {
        return d.clone();
    }
    let (w, h) = d.size();
    let mut val: Vec<f32> = d.data().to_vec();
    let mut wt: Vec<f32> = d.data().iter().map(|v| f32::from(u8::from(*v > 0.0))).collect();
    let blur = |src: &[f32], horizontal: bool| -> Vec<f32> {
        let mut out = vec![0.0; w * h];
        out.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let mut s = 0.0;
                if horizontal {
                    for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                        s += src[y * w + xx];
                    }
                } else {
                    for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                        s += src[yy * w + x];
                    }
                }
                *o = s;
            }
        });
        out
    };
    for _ in 0..3 {
        for horizontal in [true, false] {
            val = blur(&val, horizontal);
            wt = blur(&wt, horizontal);
        }
    }
    DepthMap::from_fn(w, h, |x, y| {
        let k = y * w + x;
        [if d.at(x, y) > 0.0 && wt[k] > 0.0 { val[k] / wt[k] } else { 0.0 }]
    })
}

impl DepthEstimator for NearLightSfs {
    fn estimate(&mut self, frame: &CameraFrame, ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        let ignore = frame.masks.union();
        let (depth_m, confidence) = self.depth(frame.views.reference(), ignore.as_ref(), ctx.rig.camera());
        let valid = depth_m.data().iter().filter(|d| **d > 0.0).count();
        ctx.count("valid_pixels", valid as f64);
        if valid == 0 {
            ctx.warn(format!("frame {}: no pixel usable for shape from shading (all masked, saturated or too dark); the depth is empty", frame.index));
        }
        Ok(DepthEstimate { depth_m, confidence: Some(confidence) })
    }
}

register!(DepthEstimator, NearLightSfs);

#[cfg(test)]
mod tests;
