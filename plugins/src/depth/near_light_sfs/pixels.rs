//! The per-pixel steps of `near-light-sfs`: each usable pixel's irradiance term before the grid
//! solve (step 1), and each pixel's depth, confidence and observed albedo after it (step 3).

use capsule_slam_framework::frame::{DividedFalloff, Falloff};
use capsule_slam_framework::image::NTSC_WEIGHTS;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::{GrayF32, Mask, Rgb8};
use rayon::prelude::*;

use super::params::{Detail, NearLightSfsParams};
use super::solve::{Bilinear, CellData};

/// The finest grid's solution of one frame.
pub(super) struct Solved {
    /// Per cell: mean irradiance data of the finest grid.
    pub data: Vec<CellData>,
    /// Per cell: ln M, the model's irradiance at the solution.
    pub ln_m: Vec<f64>,
    /// Per cell: depth, metres.
    pub z_cell: Vec<f64>,
    /// The coarsest grid's log depths (the next frame's warm start).
    pub coarsest: Vec<f64>,
    /// Sparse factorisations over every level.
    pub factorisations: usize,
}

/// One usable pixel.
#[derive(Debug, Clone, Copy)]
pub(super) struct Pixel {
    /// L / V: the linear luminance with the vignetting divided out.
    pub radiance: f64,
    /// The irradiance term the solve fits: `L / (V ρ) − ambient`.
    pub e: f64,
    /// The ambient term in units of the radiance: `ambient`, or `ambient / μ(u)` when the LED
    /// profile μ was divided out of the image (the ambient light never had it).
    pub ambient: f64,
    /// Confidence of the signal level.
    pub conf: f32,
    /// Whether ρ came from the map.
    pub from_map: bool,
}

/// What step 1 reads of the frame.
pub(super) struct PixelInput<'a> {
    pub image: &'a Rgb8,
    pub ignore: Option<&'a Mask>,
    /// The map's albedo at the last pose (only with `albedo_source = "map"`, of the image's size).
    pub map_albedo: Option<&'a GrayF32>,
    /// The fall-off a preprocessor divided out of the image.
    pub divided: Option<DividedFalloff>,
    /// Gamma decoding of 8-bit values.
    pub decode: &'a [f64; 256],
    /// The light model's LED profile exponent (the `light` passed beside has 0 once the profile
    /// was divided out).
    pub spot_exponent: f64,
}

/// Step 1: per usable pixel (in the field of view, not masked, not saturated, not too dark)
/// `L / V`, `E = L / (V ρ) − ambient`, the confidence of its signal level and whether its
/// albedo came from the map; into `out` (resized to the image, its buffer kept from frame to
/// frame), row by row.
///
/// `cos_alpha` holds each pixel's `[cos α, cos^s α]` (s: `input.spot_exponent`), which the
/// divided fall-offs need.
pub(super) fn irradiance(
    input: &PixelInput,
    light: &LightModel,
    (inv_vignetting, cos_alpha): (&[Option<f64>], &[[f64; 2]]),
    p: &NearLightSfsParams,
    out: &mut Vec<Option<Pixel>>,
) {
    let (w, h) = input.image.size();
    out.clear();
    out.resize(w * h, None);
    if w == 0 {
        return;
    }
    let rho_of = |x: usize, y: usize| -> (f64, bool) {
        match input.map_albedo.map(|a| f64::from(a.at(x, y))) {
            Some(r) if r > 1e-3 && r.is_finite() => (r, true),
            _ => (p.albedo, false),
        }
    };
    let pixel = |x: usize, y: usize| {
        let k = y * w + x;
        let inv_v = match input.divided {
            None => inv_vignetting[k]?,
            Some(d) => {
                inv_vignetting[k]?;
                let back = match d.falloff {
                    Falloff::LensAndLight => 1.0,
                    Falloff::FlatField => Falloff::flat_to_lens_and_light(cos_alpha[k][0]),
                };
                back / d.linear_scale
            }
        };
        if input.ignore.is_some_and(|m| m.at(x, y)) {
            return None;
        }
        let c = input.image.pixel(x, y);
        if c.iter().any(|v| *v >= p.saturation) {
            return None;
        }
        let lum: f64 = (0..3).map(|i| NTSC_WEIGHTS[i] * input.decode[usize::from(c[i])]).sum();
        if lum < p.min_luminance {
            return None;
        }
        let (rho, from_map) = rho_of(x, y);
        let radiance = lum * inv_v;
        let ambient = match input.divided {
            Some(_) if input.spot_exponent != 0.0 => light.ambient / cos_alpha[k][1],
            _ => light.ambient,
        };
        let e = radiance / rho - ambient;
        (e > 1e-9).then(|| Pixel { radiance, e, ambient, conf: ((lum - p.min_luminance) / 0.02).clamp(0.0, 1.0) as f32, from_map })
    };
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| row.iter_mut().enumerate().for_each(|(x, o)| *o = pixel(x, y)));
}

/// Step 3: per pixel the depth (m), the confidence and the observed albedo into `[depth,
/// confidence, albedo]` (each one value per pixel), bilinear over the finest grid's cell centres
/// (plus, with `detail = "shading"`, the pixel's brightness deviation `½ (ln M − ln E)`); zeros
/// where there is none or it falls outside the depth range.
pub(super) fn per_pixel(
    irradiance: &[Option<Pixel>],
    fine_taps: &[Bilinear],
    solved: &Solved,
    p: &NearLightSfsParams,
    [depth, confidence, albedo]: [&mut [f32]; 3],
) {
    let shading = p.detail == Detail::Shading;
    let (lo, hi) = (p.min_depth_m, p.max_depth_m);
    let pixel = |k: usize| {
        let Some(px) = irradiance[k] else { return [0.0; 3] };
        let Some([z, m, dw]) = fine_taps[k].apply(|c| [solved.z_cell[c], solved.ln_m[c], solved.data[c].weight]) else { return [0.0; 3] };
        let mut z_px = z;
        if shading && dw > 0.0 {
            z_px *= (0.5 * (m - px.e.ln())).exp();
        }
        let d = z_px as f32;
        // The albedo that explains the pixel on the smooth solved surface (on the map's
        // surface at the last pose instead it comes out worse: the map lags a frame and
        // carries the tracking drift).
        let rho = (px.radiance / (m.exp() + px.ambient)) as f32;
        if d.is_finite() && d >= lo && d <= hi { [d, px.conf * dw.min(1.0) as f32, if rho.is_finite() { rho.max(0.0) } else { 0.0 }] } else { [0.0; 3] }
    };
    (depth, confidence, albedo).into_par_iter().enumerate().for_each(|(k, (d, c, a))| [*d, *c, *a] = pixel(k));
}
