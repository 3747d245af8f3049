//! Undistortion of an input folder's frames through a map computed once per camera (issue 18,
//! item 6). The stages see a pinhole camera `K'` with no lens: each of its pixels `(u, v)` looks
//! along the ray `K'⁻¹ [u v 1]ᵀ`, which the lens puts at the source pixel
//! `K · distort(K'⁻¹ [u v 1]ᵀ)` (OpenCV's `initUndistortRectifyMap`). `K'` is the file's `K`
//! ([`UndistortedView::Source`]) or the same focal length on a canvas grown to the lens's whole
//! view ([`UndistortedView::Whole`]: a barrel lens sees wider than a pinhole of its size).
//! Colour is sampled bicubically; depth bilinearly where the four source pixels agree (within
//! [`DEPTH_BLEND_SHARE`] of the depth) and from the nearest pixel across a depth edge, so no
//! depth between two surfaces is invented; masks from the nearest pixel. A pixel whose ray
//! lands outside the source image or its round field of view, or beyond the lens's fold (where
//! the model maps two rays to one pixel), is out of view, and so is one whose colour kernel
//! reaches a source pixel beyond the round field of view (black in a capsule's frames: a
//! darkened ring fixed in the image, which raised the lens phantoms' ATE by up to 60 %). Each
//! pixel also gets the source pixels behind it ([`Undistortion::sample_share`]), which the
//! trackers weigh its photometric residual by.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::config::UndistortedView;
use capsule_slam_framework::frame::{SampleShare, ShareMap};
use capsule_slam_framework::image::{DepthMap, GrayF32, Mask, Rgb8};
use rayon::prelude::*;
use std::sync::Arc;

/// Largest spread of the four depths a bilinear depth sample blends, as a share of the nearest:
/// 2.5 mm at 50 mm, a fold of the wall; a wall slanted at 80° to the ray spreads less over a
/// source pixel of a capsule's fisheye corner.
pub const DEPTH_BLEND_SHARE: f32 = 0.05;

/// Where one undistorted pixel reads the source image.
#[derive(Debug, Clone, Copy)]
struct Tap {
    /// Indices of the bilinear 2×2 source pixels: top left, top right, bottom left, bottom right.
    four: [u32; 4],
    /// Bilinear weights along x and y.
    wx: f32,
    wy: f32,
    /// Index of the nearest source pixel.
    nearest: u32,
    /// Index of the bicubic 4×4's first source pixel, `(x0 − 1, y0 − 1)`; `None` where the 4×4
    /// crosses the image border (its rows and columns are then clamped).
    cubic_origin: Option<u32>,
    /// Keys' weights of the 4×4's columns and rows.
    kx: [f32; 4],
    ky: [f32; 4],
}

/// The precomputed undistortion of one camera.
#[derive(Debug, Clone)]
pub struct Undistortion {
    /// The source (distorted) image size.
    width: usize,
    height: usize,
    /// The camera the stages see: no lens, the source's focal length, its size and principal
    /// point or a larger canvas ([`UndistortedView`]), the field of view that the source's
    /// covers.
    camera: PinholeCamera,
    /// One per undistorted pixel, row-major; `None` out of view.
    taps: Vec<Option<Tap>>,
    /// Out of view in the undistorted image.
    out_of_view: Mask,
    /// The whole view asked for did not fit in the largest canvas.
    clipped: bool,
    /// Source pixels per undistorted pixel, at most 1 (0 out of view).
    sample_share: SampleShare,
}

impl Undistortion {
    /// The map of `source` (which must have a lens; without one every tap is the identity) onto
    /// a pinhole camera with the file's intrinsics and size.
    pub fn new(source: &PinholeCamera) -> Self {
        Self::with_view(source, UndistortedView::Source)
    }

    /// The map of `source` onto the camera `view` asks for: the file's intrinsics and size, or
    /// the file's focal length on a canvas grown to the lens's whole view.
    pub fn with_view(source: &PinholeCamera, view: UndistortedView) -> Self {
        let (w, h) = (source.width, source.height);
        let (mut camera, clipped) = match view {
            UndistortedView::Source => (source.clone(), false),
            UndistortedView::Whole => whole_view(source),
        };
        camera.distortion = None;
        let (ow, oh) = (camera.width, camera.height);
        let lens = source.distortion;
        let taps: Vec<Option<Tap>> = (0..ow * oh)
            .into_par_iter()
            .map(|k| {
                let ((x, y), (xd, yd), (us, vs)) = through_lens(source, &camera, (k % ow) as f64, (k / ow) as f64);
                // Beyond the fold a far ray lands back inside: only a pixel the inverse maps
                // back to its own ray is seen.
                let unfolded = lens.is_none_or(|l| l.undistort(xd, yd).is_some_and(|(xu, yu)| (xu - x).hypot(yu - y) < 1e-6 * (1.0 + x.hypot(y))));
                // Every source pixel the colour kernel reads must be seen: one beyond the round
                // field of view is black, and a kernel reaching it darkens the rim by a fixed
                // pattern that the photometric term then tracks (docs/results/camera-models.md).
                // On a canvas larger than the source's, its last half pixel would be
                // extrapolated: at a compressed rim that is degrees of ray.
                let sampled = view == UndistortedView::Source || (us >= 0.0 && vs >= 0.0 && us <= (w - 1) as f64 && vs <= (h - 1) as f64);
                (unfolded && sampled && source.in_fov(us, vs))
                    .then(|| tap(us, vs, w, h))
                    .filter(|t| t.support(w, h).all(|(x, y)| source.in_fov(x as f64, y as f64)))
            })
            .collect();
        // The largest circle about the principal point inside which every pixel is seen.
        camera.fov_radius_px = source.fov_radius_px.map(|_| {
            let nearest_unseen = taps
                .iter()
                .enumerate()
                .filter(|(_, t)| t.is_none())
                .map(|(k, _)| ((k % ow) as f64 - camera.cx).hypot((k / ow) as f64 - camera.cy))
                .fold(f64::INFINITY, f64::min);
            (nearest_unseen - 0.5).min(0.5 * (ow as f64).hypot(oh as f64)).max(0.0)
        });
        let out_of_view = Mask::from_fn(ow, oh, |x, y| [taps[y * ow + x].is_none() || !camera.in_fov(x as f64, y as f64)]);
        let sample_share = Arc::new(ShareMap::new(GrayF32::from_fn_par(ow, oh, |x, y| {
            [if out_of_view.at(x, y) { 0.0 } else { source_pixels_per_pixel(source, &camera, x as f64, y as f64).min(1.0) as f32 }]
        })));
        Self { width: w, height: h, camera, taps, out_of_view, sample_share, clipped }
    }

    /// Whether the lens's whole view did not fit on a canvas twice the file's size, so that its
    /// outer field is cropped there ([`UndistortedView::Whole`]).
    pub fn clipped(&self) -> bool {
        self.clipped
    }

    /// Per undistorted pixel, the source pixels behind it, at most 1 (0 out of view): where the
    /// map stretches the lens's outer ring, below 1 ([`SampleShare`]).
    pub fn sample_share(&self) -> &SampleShare {
        &self.sample_share
    }

    /// The camera of the undistorted frames.
    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    /// Where the undistorted image sees nothing (`true`): outside the source's image, its round
    /// field of view, or beyond the lens's fold.
    pub fn out_of_view(&self) -> &Mask {
        &self.out_of_view
    }

    /// Whether an image has the source size.
    pub fn fits(&self, size: (usize, usize)) -> bool {
        size == (self.width, self.height)
    }

    /// The colour image undistorted (bicubic, Keys' kernel with a = −0.5: unlike a bilinear
    /// sample, it does not blur a pixel more the nearer its source lies to a half-pixel, a blur
    /// that would change over the image and move with the texture; black out of view). The
    /// image must have the source size ([`Undistortion::fits`]).
    pub fn rgb(&self, src: &Rgb8) -> Rgb8 {
        let (s, w, h) = (src.data(), self.width, self.height);
        let ow = self.camera.width;
        let mut out = Rgb8::new(ow, self.camera.height);
        out.data_mut().par_chunks_mut(3 * ow).zip(self.taps.par_chunks(ow)).for_each(|(row_out, row_taps)| {
            for (px, tap) in row_out.chunks_exact_mut(3).zip(row_taps) {
                let Some(t) = tap else { continue };
                let mut acc = [0.0f32; 3];
                let mut add = |k: usize, weight: f32| {
                    for (a, v) in acc.iter_mut().zip(&s[3 * k..3 * k + 3]) {
                        *a += weight * f32::from(*v);
                    }
                };
                match t.cubic_origin {
                    Some(origin) => {
                        for (r, ky) in t.ky.iter().enumerate() {
                            let first = origin as usize + r * w;
                            for (c, kx) in t.kx.iter().enumerate() {
                                add(first + c, kx * ky);
                            }
                        }
                    }
                    None => {
                        let weights = t.ky.iter().flat_map(|ky| t.kx.iter().map(move |kx| kx * ky));
                        for ((x, y), k) in t.support(w, h).zip(weights) {
                            add(y * w + x, k);
                        }
                    }
                }
                for (p, a) in px.iter_mut().zip(acc) {
                    *p = a.round().clamp(0.0, 255.0) as u8;
                }
            }
        });
        out
    }

    /// The depth map undistorted: bilinear where the four source depths are valid and within
    /// [`DEPTH_BLEND_SHARE`] of each other, the nearest source pixel otherwise; 0 (invalid) out
    /// of view.
    pub fn depth(&self, src: &DepthMap) -> DepthMap {
        let s = src.data();
        let mut out = DepthMap::new(self.camera.width, self.camera.height);
        for (px, tap) in out.data_mut().iter_mut().zip(&self.taps) {
            let Some(t) = tap else { continue };
            let four = t.four.map(|i| s[i as usize]);
            let (lo, hi) = four.iter().fold((f32::INFINITY, 0.0f32), |(lo, hi), &z| (lo.min(z), hi.max(z)));
            *px = if lo > 0.0 && lo.is_finite() && hi.is_finite() && hi - lo <= DEPTH_BLEND_SHARE * lo {
                let top = four[0] * (1.0 - t.wx) + four[1] * t.wx;
                let bottom = four[2] * (1.0 - t.wx) + four[3] * t.wx;
                top * (1.0 - t.wy) + bottom * t.wy
            } else {
                s[t.nearest as usize]
            };
        }
        out
    }

    /// A mask undistorted (nearest; `false` out of view, [`Undistortion::out_of_view`]).
    pub fn mask(&self, src: &Mask) -> Mask {
        let s = src.data();
        let mut out = Mask::new(self.camera.width, self.camera.height);
        for ((px, tap), out_of_view) in out.data_mut().iter_mut().zip(&self.taps).zip(self.out_of_view.data()) {
            *px = !out_of_view && tap.is_some_and(|t| s[t.nearest as usize]);
        }
        out
    }
}

impl Tap {
    /// The source pixels the colour kernel reads (the bicubic 4×4, clamped to the image).
    fn support(&self, w: usize, h: usize) -> impl Iterator<Item = (usize, usize)> {
        let (x0, y0) = (self.four[0] as usize % w, self.four[0] as usize / w);
        let clamp = |v: usize, d: usize, n: usize| (v + d).saturating_sub(1).min(n - 1);
        (0..4).flat_map(move |r| (0..4).map(move |c| (clamp(x0, c, w), clamp(y0, r, h))))
    }
}

/// Pixel `(u, v)` of the undistorted camera `out` through `source`'s lens: its ray
/// (normalised coordinates), where the lens bends it, and the source pixel it lands on.
fn through_lens(source: &PinholeCamera, out: &PinholeCamera, u: f64, v: f64) -> ((f64, f64), (f64, f64), (f64, f64)) {
    let (x, y) = ((u - out.cx) / out.fx, (v - out.cy) / out.fy);
    let (xd, yd) = source.distortion.map_or((x, y), |l| l.distort(x, y));
    ((x, y), (xd, yd), (source.fx * xd + source.cx, source.fy * yd + source.cy))
}

/// The area of the source image that pixel `(u, v)` of the undistorted camera `out` covers, in source pixels: `|det ∂(u_src, v_src) / ∂(u, v)|` by central differences half a
/// pixel either side (1 without a lens; for a radial lens `r_d = r (1 + k₁ r²)`,
/// `(1 + k₁ r²)(1 + 3 k₁ r²)`).
fn source_pixels_per_pixel(source: &PinholeCamera, out: &PinholeCamera, u: f64, v: f64) -> f64 {
    let at = |u: f64, v: f64| through_lens(source, out, u, v).2;
    let (left, right, up, down) = (at(u - 0.5, v), at(u + 0.5, v), at(u, v - 0.5), at(u, v + 0.5));
    ((right.0 - left.0) * (down.1 - up.1) - (right.1 - left.1) * (down.0 - up.0)).abs()
}

/// The largest growth of the whole view's canvas, per side, as a share of the file's width or
/// height: twice the file's size in all (a fisheye's view near 90° off the axis needs an
/// unbounded pinhole canvas).
pub const WHOLE_VIEW_MAX_GROWTH: f64 = 0.5;

/// The undistorted camera that holds every ray `source`'s image sees (the file's focal length,
/// the canvas grown on each side as far as the farthest ray, at most
/// [`WHOLE_VIEW_MAX_GROWTH`] of the file's size), and whether the canvas had to be cut there.
/// The vignetting radius stays the file's, so that `light.toml`'s V is the same function of
/// the ray.
fn whole_view(source: &PinholeCamera) -> (PinholeCamera, bool) {
    let (w, h) = (source.width, source.height);
    let Some(lens) = source.distortion else { return (source.clone(), false) };
    // Where each seen source pixel's ray lands on the file's pinhole camera, relative to its
    // principal point: the extent the canvas must hold (beyond the fold no ray is seen).
    let extent = (0..w * h)
        .into_par_iter()
        .filter_map(|k| {
            let (us, vs) = ((k % w) as f64, (k / w) as f64);
            if !source.in_fov(us, vs) {
                return None;
            }
            let (xd, yd) = ((us - source.cx) / source.fx, (vs - source.cy) / source.fy);
            let (x, y) = lens.undistort(xd, yd)?;
            let (xr, yr) = lens.distort(x, y);
            ((xr - xd).hypot(yr - yd) < 1e-6 * (1.0 + xd.hypot(yd))).then_some([source.fx * x, source.fx * x, source.fy * y, source.fy * y])
        })
        .reduce(|| [0.0; 4], |a, b| [a[0].min(b[0]), a[1].max(b[1]), a[2].min(b[2]), a[3].max(b[3])]);
    // Pixels to add on each side (never fewer than none: the canvas holds the file's).
    let grow = |need: f64, has: f64, limit: f64| -> (usize, bool) {
        let add = (need - has).ceil().max(0.0);
        if add > limit { (limit as usize, true) } else { (add as usize, false) }
    };
    let (lw, lh) = ((WHOLE_VIEW_MAX_GROWTH * w as f64).floor(), (WHOLE_VIEW_MAX_GROWTH * h as f64).floor());
    let (left, c1) = grow(-extent[0] - 0.5, source.cx, lw);
    let (right, c2) = grow(extent[1] + 0.5, w as f64 - 1.0 - source.cx, lw);
    let (top, c3) = grow(-extent[2] - 0.5, source.cy, lh);
    let (bottom, c4) = grow(extent[3] + 0.5, h as f64 - 1.0 - source.cy, lh);
    let mut camera = source.clone();
    camera.width = w + left + right;
    camera.height = h + top + bottom;
    camera.cx = source.cx + left as f64;
    camera.cy = source.cy + top as f64;
    camera.vignetting_radius_px = Some(source.vignetting_radius());
    (camera, c1 || c2 || c3 || c4)
}

/// The bilinear and nearest taps of source position `(us, vs)` (inside the image) in a `w × h`
/// image; an image one pixel wide or high reads its one column or row.
fn tap(us: f64, vs: f64, w: usize, h: usize) -> Tap {
    let x0 = (us.floor().max(0.0) as usize).min(w - 1);
    let y0 = (vs.floor().max(0.0) as usize).min(h - 1);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let nx = (us.round().max(0.0) as usize).min(w - 1);
    let ny = (vs.round().max(0.0) as usize).min(h - 1);
    let index = |x: usize, y: usize| (y * w + x) as u32;
    let (fx, fy) = ((us - x0 as f64).clamp(0.0, 1.0), (vs - y0 as f64).clamp(0.0, 1.0));
    Tap {
        four: [index(x0, y0), index(x1, y0), index(x0, y1), index(x1, y1)],
        wx: fx as f32,
        wy: fy as f32,
        nearest: index(nx, ny),
        cubic_origin: (x0 >= 1 && y0 >= 1 && x0 + 2 < w && y0 + 2 < h).then(|| index(x0 - 1, y0 - 1)),
        kx: keys_weights(fx),
        ky: keys_weights(fy),
    }
}

/// Keys' cubic convolution weights (a = −0.5) of the samples at −1, 0, 1, 2 for a position
/// `f ∈ [0, 1]` between samples 0 and 1; they sum to 1.
fn keys_weights(f: f64) -> [f32; 4] {
    let k = |t: f64| {
        let t = t.abs();
        if t <= 1.0 {
            (1.5 * t - 2.5) * t * t + 1.0
        } else if t < 2.0 {
            ((-0.5 * t + 2.5) * t - 4.0) * t + 2.0
        } else {
            0.0
        }
    };
    [k(1.0 + f), k(f), k(1.0 - f), k(2.0 - f)].map(|v| v as f32)
}

#[cfg(test)]
#[path = "undistort_tests.rs"]
mod tests;
