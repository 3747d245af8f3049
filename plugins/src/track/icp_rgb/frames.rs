//! The image pyramids the tracker works on: the live frame and the reference (the model
//! prediction, filled in with the previous live frame where the model has nothing).

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::MASK_SPECULAR;
use capsule_slam_framework::image::gray_from_rgb;
use capsule_slam_framework::{DepthMap, GrayF32, ModelView, RgbdFrame};

use crate::common::maps::{GeometryParams, NormalMap, VertexMap, geometry, normal_map, vertex_map};
use crate::common::masks::dilate;
use crate::common::pyramid::{half_depth, half_gray};
use rayon::prelude::*;

/// One pyramid level.
#[derive(Clone)]
pub struct Level {
    /// The level's camera.
    pub cam: PinholeCamera,
    /// Depth, metres (0 = invalid).
    pub depth: DepthMap,
    /// Camera-frame vertices.
    pub vertices: VertexMap,
    /// Camera-frame normals.
    pub normals: NormalMap,
    /// Intensity in [0, 1] (0 = invalid where the depth is invalid, for references).
    pub gray: GrayF32,
    /// Intensity gradient along x, per pixel.
    pub gx: GrayF32,
    /// Intensity gradient along y, per pixel.
    pub gy: GrayF32,
    /// σ of the depth per pixel, metres (live frames whose depth stage gave one; references
    /// whose model or previous frame carries one).
    pub sigma: Option<DepthMap>,
    /// Correlation length of the depth error, pixels of this level.
    pub sigma_correlation_px: f64,
}

/// Depth preparation parameters (shared with the fuser, so both can reuse the frame's memo).
pub type DepthPrep = GeometryParams;

/// Central differences where both neighbours have depth and an intensity (0 marks none).
fn gradients(g: &GrayF32, valid: &DepthMap) -> (GrayF32, GrayF32) {
    let (w, h) = g.size();
    let ok = |x: usize, y: usize| valid.at(x, y) > 0.0 && g.at(x, y) > 0.0;
    let gx =
        GrayF32::from_fn_par(w, h, |x, y| [if x > 0 && x + 1 < w && ok(x - 1, y) && ok(x + 1, y) { 0.5 * (g.at(x + 1, y) - g.at(x - 1, y)) } else { 0.0 }]);
    let gy =
        GrayF32::from_fn_par(w, h, |x, y| [if y > 0 && y + 1 < h && ok(x, y - 1) && ok(x, y + 1) { 0.5 * (g.at(x, y + 1) - g.at(x, y - 1)) } else { 0.0 }]);
    (gx, gy)
}

/// Builds `levels` levels from a level-0 depth (already prepared) and intensity, with the
/// level-0 vertices and normals when they are known already.
pub fn pyramid(
    depth0: DepthMap,
    gray0: GrayF32,
    known0: (Option<VertexMap>, Option<NormalMap>),
    cam: &PinholeCamera,
    levels: usize,
    prep: &DepthPrep,
) -> Vec<Level> {
    let mut out: Vec<Level> = Vec::with_capacity(levels);
    let (mut depth, mut gray) = (depth0, gray0);
    let (mut v0, mut n0) = known0;
    for l in 0..levels {
        let c = cam.pyramid_level(l as u32);
        let vertices = v0.take().unwrap_or_else(|| vertex_map(&depth, &c));
        let normals = n0.take().unwrap_or_else(|| normal_map(&vertices, 1, prep.edge_jump_m * (1 << l) as f32));
        let (gx, gy) = gradients(&gray, &depth);
        let next_depth = half_depth(&depth, prep.edge_jump_m);
        let (d, g) = (&depth, &gray);
        let next_gray = half_gray(&gray, |x, y| d.at(x, y) > 0.0 && g.at(x, y) > 0.0);
        out.push(Level { cam: c, depth, vertices, normals, gray, gx, gy, sigma: None, sigma_correlation_px: 0.0 });
        depth = next_depth;
        gray = next_gray;
    }
    out
}

/// The live frame's pyramid: masked, range-limited, bilateral-filtered depth (as ElasticFusion
/// tracks on filtered depth) and NTSC intensity in [0, 1].
///
/// `restore` maps the level-0 intensity image before the pyramid is built (the fall-off a
/// preprocessor divided out multiplied back in, `relight::Undivide`). The intensity is 0
/// (no photometric residual) within `rgb_margin_px` of a detected highlight (the frame's
/// [`MASK_SPECULAR`]): the highlight's tail beyond its detected core brightens the wall by a
/// view-dependent amount that brightness constancy cannot explain.
pub fn live(
    frame: &RgbdFrame,
    cam: &PinholeCamera,
    levels: usize,
    prep: &DepthPrep,
    restore: Option<&dyn Fn(GrayF32) -> GrayF32>,
    rgb_margin_px: usize,
) -> Vec<Level> {
    let params = GeometryParams {
        min_m: prep.min_m,
        max_m: prep.max_m,
        radius_px: prep.radius_px,
        sigma_px: prep.sigma_px,
        sigma_m: prep.sigma_m,
        edge_jump_m: prep.edge_jump_m,
    };
    let g = geometry(frame, cam, &params);
    let mut gray = gray_from_rgb(&frame.colour);
    gray.data_mut().iter_mut().for_each(|v| *v /= 255.0);
    if let Some(restore) = restore {
        gray = restore(gray);
    }
    if let Some(highlights) = frame.masks.get(MASK_SPECULAR).filter(|_| rgb_margin_px > 0) {
        let margin = dilate(highlights, rgb_margin_px, None);
        gray.data_mut().iter_mut().zip(margin.data()).filter(|(_, m)| **m).for_each(|(g, _)| *g = 0.0);
    }
    let mut out = pyramid(g.smooth.clone(), gray, (Some(g.v_smooth.clone()), Some(g.normals.clone())), cam, levels, prep);
    if let Some(sigma) = &frame.depth_sigma_m {
        set_sigma(&mut out, sigma, frame.depth_sigma_correlation_px);
    }
    out
}

/// Gives every level the σ of its pixels from the level-0 σ image. Level l samples every
/// 2^l-th pixel's σ: the mean of a 2 × 2 block of a spatially correlated error (a stereo or
/// smooth error) is hardly better than one pixel.
fn set_sigma(levels: &mut [Level], sigma: &DepthMap, correlation_px: f64) {
    for (l, level) in levels.iter_mut().enumerate() {
        let (w, h) = level.depth.size();
        let step = 1usize << l;
        level.sigma = Some(DepthMap::from_fn_par(w, h, |x, y| [sigma.at((x * step).min(sigma.width() - 1), (y * step).min(sigma.height() - 1))]));
        level.sigma_correlation_px = correlation_px / step as f64;
    }
}

/// The reference pyramid: the model prediction where it has a surface, the previous live
/// frame (same camera pose) elsewhere — ElasticFusion's "fill-in". Its σ per pixel is the
/// prediction's (`ModelView::sigma_m`) or the previous frame's, where they carry one.
pub fn reference(model: Option<&ModelView>, previous: Option<&Level>, cam: &PinholeCamera, levels: usize, prep: &DepthPrep) -> Option<Vec<Level>> {
    let (w, h) = (cam.width, cam.height);
    let model_gray = model.map(|m| gray_from_rgb(&m.colour));
    // Per pixel: (depth, intensity, normal, σ) from the model, else from the previous frame.
    let pick = |x: usize, y: usize| -> (f32, f32, [f32; 3], f32) {
        if let (Some(m), Some(g)) = (model, &model_gray) {
            let (d, n) = (m.depth_m.at(x, y), m.normals_cam.pixel(x, y));
            if d > 0.0 && n != [0.0; 3] {
                return (d, g.at(x, y) / 255.0, n, m.sigma_m.at(x, y));
            }
        }
        if let Some(p) = previous {
            let (d, n) = (p.depth.at(x, y), p.normals.pixel(x, y));
            if d > 0.0 && n != [0.0; 3] {
                return (d, p.gray.at(x, y), n, p.sigma.as_ref().map_or(0.0, |s| s.at(x, y)));
            }
        }
        (0.0, 0.0, [0.0; 3], 0.0)
    };
    // One parallel pass over the rows writes the four images.
    let (mut depth, mut gray, mut normals, mut sigma) = (DepthMap::new(w, h), GrayF32::new(w, h), NormalMap::new(w, h), DepthMap::new(w, h));
    let rows = depth.data_mut().par_chunks_mut(w.max(1)).zip(gray.data_mut().par_chunks_mut(w.max(1)));
    let rows = rows.zip(normals.data_mut().par_chunks_mut(3 * w.max(1))).zip(sigma.data_mut().par_chunks_mut(w.max(1)));
    rows.enumerate().for_each(|(y, (((d_row, g_row), n_row), s_row))| {
        for x in 0..w {
            let (d, g, n, s) = pick(x, y);
            (d_row[x], g_row[x], s_row[x]) = (d, g, s);
            n_row[3 * x..3 * x + 3].copy_from_slice(&n);
        }
    });
    if depth.data().iter().all(|d| *d <= 0.0) {
        return None;
    }
    let mut out = pyramid(depth, gray, (None, Some(normals)), cam, levels, prep);
    if sigma.data().iter().any(|s| *s > 0.0) {
        set_sigma(&mut out, &sigma, 0.0);
    }
    Some(out)
}
