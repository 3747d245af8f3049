//! The image pyramids the tracker works on: the live frame and the reference (the model
//! prediction, filled in with the previous live frame where the model has nothing).

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::{MASK_OUT_OF_VIEW, MASK_SPECULAR, ShareMap};
use capsule_slam_framework::image::gray_from_rgb;
use capsule_slam_framework::{DepthMap, GrayF32, ModelView, RgbdFrame};

use crate::common::maps::{GeometryParams, NormalMap, VertexMap, geometry, normal_map, vertex_map};
use crate::common::masks::dilate;
use crate::common::pyramid::{half_depth, half_gray};
use rayon::prelude::*;
use std::sync::Arc;

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
    /// Source pixels behind each pixel where the image was resampled (the frame's
    /// [`RgbdFrame::sample_share`], a level's pixel the mean of its block of level-0 pixels);
    /// `None`: 1 everywhere. The photometric term weighs each residual by it.
    pub share: Option<Arc<GrayF32>>,
    /// Correlation length of the depth error, pixels of this level.
    pub sigma_correlation_px: f64,
}

impl Level {
    /// The share of pixel `(x, y)` ([`Level::share`]).
    #[inline]
    pub fn share_at(&self, x: usize, y: usize) -> f64 {
        self.share.as_ref().map_or(1.0, |s| f64::from(s.at(x, y)))
    }
}

/// Depth preparation parameters (shared with the fuser, so both can reuse the frame's memo).
pub type DepthPrep = GeometryParams;

/// Central differences where both neighbours have depth and an intensity (0 marks none); both
/// images in one pass over the rows.
fn gradients(g: &GrayF32, valid: &DepthMap) -> (GrayF32, GrayF32) {
    let (w, h) = g.size();
    let (mut gx, mut gy) = (GrayF32::new(w, h), GrayF32::new(w, h));
    if w == 0 || h == 0 {
        return (gx, gy);
    }
    let (gd, vd) = (g.data(), valid.data());
    let row = |y: usize| (&gd[y * w..(y + 1) * w], &vd[y * w..(y + 1) * w]);
    let ok = |(g, v): (&[f32], &[f32]), x: usize| v[x] > 0.0 && g[x] > 0.0;
    gx.data_mut().par_chunks_mut(w).zip(gy.data_mut().par_chunks_mut(w)).enumerate().for_each(|(y, (out_x, out_y))| {
        let here = row(y);
        for (x, out) in out_x.iter_mut().enumerate().take(w - 1).skip(1) {
            if ok(here, x - 1) && ok(here, x + 1) {
                *out = 0.5 * (here.0[x + 1] - here.0[x - 1]);
            }
        }
        if y > 0 && y + 1 < h {
            let (up, down) = (row(y - 1), row(y + 1));
            for (x, out) in out_y.iter_mut().enumerate() {
                if ok(up, x) && ok(down, x) {
                    *out = 0.5 * (down.0[x] - up.0[x]);
                }
            }
        }
    });
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
        let next_gray = half_gray(&gray, &depth);
        out.push(Level { cam: c, depth, vertices, normals, gray, gx, gy, sigma: None, share: None, sigma_correlation_px: 0.0 });
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
/// view-dependent amount that brightness constancy cannot explain. It is 0 too wherever the
/// frame sees nothing ([`MASK_OUT_OF_VIEW`]: beyond the round field of view, or beyond what an
/// undistortion map reaches): a real sensor's black there is noise, not 0, and 0 is the mark of
/// "no intensity" that the photometric terms and the model points' references test
/// (`docs/results/camera-models.md`, "The black border").
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
    gray.data_mut().par_iter_mut().for_each(|v| *v /= 255.0);
    if let Some(restore) = restore {
        gray = restore(gray);
    }
    if let Some(highlights) = frame.masks.get(MASK_SPECULAR).filter(|_| rgb_margin_px > 0) {
        let margin = dilate(highlights, rgb_margin_px, None);
        blank(&mut gray, &margin);
    }
    if let Some(unseen) = frame.masks.get(MASK_OUT_OF_VIEW) {
        blank(&mut gray, unseen);
    }
    let mut out = pyramid(g.smooth.clone(), gray, (Some(g.v_smooth.clone()), Some(g.normals.clone())), cam, levels, prep);
    if let Some(sigma) = &frame.depth_sigma_m {
        set_sigma(&mut out, sigma, frame.depth_sigma_correlation_px);
    }
    if let Some(share) = &frame.sample_share {
        set_share(&mut out, share);
    }
    out
}

/// Sets the intensity to 0 ("no intensity") wherever `mask` is set.
fn blank(gray: &mut GrayF32, mask: &capsule_slam_framework::Mask) {
    gray.data_mut().par_iter_mut().zip(mask.data().par_iter()).filter(|(_, m)| **m).for_each(|(g, _)| *g = 0.0);
}

/// Gives every level its pixels' share ([`Level::share`]): level l's pixel the mean of its
/// 2^l × 2^l block of level-0 shares ([`ShareMap::block_mean`], made once per sequence). A
/// coarse pixel averages the sensor noise of the source pixels behind its block, `4^l · share`
/// of them against a sensor pixel's `4^l`, so its noise variance relative to an unresampled
/// pixel of its level is again `1 / share`.
fn set_share(levels: &mut [Level], share: &ShareMap) {
    for (l, level) in levels.iter_mut().enumerate() {
        level.share = Some(share.block_mean(l, level.depth.size()));
    }
}

/// Gives every level the σ of its pixels from the level-0 σ image. Level l samples every
/// 2^l-th pixel's σ: the mean of a 2 × 2 block of a spatially correlated error (a stereo or
/// smooth error) is hardly better than one pixel.
fn set_sigma(levels: &mut [Level], sigma: &DepthMap, correlation_px: f64) {
    let (sw, sh) = sigma.size();
    for (l, level) in levels.iter_mut().enumerate() {
        let (w, h) = level.depth.size();
        let step = 1usize << l;
        let mut out = DepthMap::new(w, h);
        if sw > 0 && sh > 0 && w > 0 {
            out.data_mut().par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                let src = &sigma.data()[(y * step).min(sh - 1) * sw..][..sw];
                for (x, v) in row.iter_mut().enumerate() {
                    *v = src[(x * step).min(sw - 1)];
                }
            });
        }
        level.sigma = Some(out);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradients_are_central_differences_where_both_neighbours_are_valid() {
        let (w, h) = (37, 23);
        let g = GrayF32::from_fn(w, h, |x, y| [if (x + 3 * y) % 11 == 0 { 0.0 } else { 0.2 + 0.01 * x as f32 + 0.003 * (y * y) as f32 }]);
        let valid = DepthMap::from_fn(w, h, |x, y| [if (2 * x + y) % 13 == 0 { 0.0 } else { 0.04 }]);
        let (gx, gy) = gradients(&g, &valid);
        let ok = |x: usize, y: usize| valid.at(x, y) > 0.0 && g.at(x, y) > 0.0;
        let mut seen = 0;
        for y in 0..h {
            for x in 0..w {
                let want_x = if x > 0 && x + 1 < w && ok(x - 1, y) && ok(x + 1, y) { 0.5 * (g.at(x + 1, y) - g.at(x - 1, y)) } else { 0.0 };
                let want_y = if y > 0 && y + 1 < h && ok(x, y - 1) && ok(x, y + 1) { 0.5 * (g.at(x, y + 1) - g.at(x, y - 1)) } else { 0.0 };
                assert_eq!((gx.at(x, y).to_bits(), gy.at(x, y).to_bits()), (want_x.to_bits(), want_y.to_bits()), "pixel ({x}, {y})");
                seen += usize::from(want_x != 0.0 && want_y != 0.0);
            }
        }
        assert!(seen > 200, "{seen} pixels with both gradients");
    }

    #[test]
    fn every_level_samples_the_sigma_of_its_pixels_corner() {
        let cam = PinholeCamera::new(21, 14, 20.0, 20.0, 10.0, 7.0);
        let depth = DepthMap::from_fn(21, 14, |x, _| [0.03 + 0.001 * x as f32]);
        let gray = GrayF32::filled(21, 14, 0.5);
        let prep = DepthPrep { min_m: 0.001, max_m: 1.0, radius_px: 1, sigma_px: 2.0, sigma_m: 0.001, edge_jump_m: 0.01 };
        let mut levels = pyramid(depth, gray, (None, None), &cam, 3, &prep);
        let sigma = DepthMap::from_fn(21, 14, |x, y| [1e-4 * (x + 100 * y) as f32]);
        set_sigma(&mut levels, &sigma, 6.0);
        for (l, level) in levels.iter().enumerate() {
            let s = level.sigma.as_ref().expect("σ set");
            assert_eq!(s.size(), level.depth.size());
            for y in 0..s.height() {
                for x in 0..s.width() {
                    assert_eq!(s.at(x, y), sigma.at(x << l, y << l), "level {l} pixel ({x}, {y})");
                }
            }
            assert_eq!(level.sigma_correlation_px, 6.0 / f64::from(1u32 << l));
        }
    }
}
