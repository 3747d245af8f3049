//! Frames: what the camera delivers ([`CameraFrame`]) and what the stages after depth
//! estimation see ([`RgbdFrame`]).

use std::any::Any;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use crate::camera::ViewKind;
use crate::geometry::Iso3;
use crate::image::{DepthMap, GrayF32, Mask, Rgb8};

/// Well-known mask name: specular highlights found by a preprocessor.
pub const MASK_SPECULAR: &str = "specular";
/// Well-known mask name: pixels outside the lens' round field of view.
pub const MASK_OUT_OF_VIEW: &str = "out-of-view";
/// Well-known mask name: pixels clipped by the sensor before a preprocessor rescaled them (their
/// value no longer tells the radiance).
pub const MASK_SATURATED: &str = "saturated";

/// Which radial fall-off a preprocessor divided out of the images (Goldman 2010, "Vignette and exposure calibration and compensation", IEEE TPAMI 32(12); Kim & Pollefeys 2008).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Falloff {
    /// The lens vignetting and the LED profile, `V(u) · μ(u)`: what a near-light model keeps
    /// apart from the cos θ / r² cue of the shape.
    LensAndLight,
    /// The whole flat field, `V(u) · μ(u) · cos³α(u)` (a flat target facing the capsule,
    /// α the ray's angle to the optical axis): what a distant-light model (Tsai–Shah) expects.
    FlatField,
}

impl Falloff {
    /// The factor by which a flat-field-divided pixel must be multiplied to be lens-and-light
    /// divided, at a ray with `cos α = cos_alpha` (a flat target at distance D sees the light at
    /// distance D / cos α under incidence α: cos α · cos² α).
    pub fn flat_to_lens_and_light(cos_alpha: f64) -> f64 {
        cos_alpha * cos_alpha * cos_alpha
    }
}

/// A fall-off divided out of every view's linear image: the corrected linear value is
/// `linear_scale · L / F(u)` with L the input's linear value (each 8-bit channel decoded with
/// `gamma`) and F the fall-off of kind `falloff`, 1 at the principal point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DividedFalloff {
    /// What was divided out.
    pub falloff: Falloff,
    /// Global factor applied after the division (keeps the brightest corrected pixel below
    /// clipping).
    pub linear_scale: f64,
    /// The encoding exponent used: pixel = linear^(1/gamma).
    pub gamma: f64,
}

/// What preprocessors did to the photometry of a frame's images, so that a depth estimator with
/// a photometric model sees the image it models.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Photometry {
    /// The fall-off divided out, if any.
    pub divided: Option<DividedFalloff>,
}

/// Named per-pixel masks. A set pixel marks a pixel that later stages must ignore
/// (a specular highlight, a pixel outside the field of view, ...).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Masks(BTreeMap<String, Mask>);

impl Masks {
    /// No masks.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds or replaces a mask.
    pub fn insert(&mut self, name: impl Into<String>, mask: Mask) {
        self.0.insert(name.into(), mask);
    }

    /// A mask by name.
    pub fn get(&self, name: &str) -> Option<&Mask> {
        self.0.get(name)
    }

    /// Masks in name order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &Mask)> {
        self.0.iter().map(|(k, v)| (k.as_str(), v))
    }

    /// Whether any mask marks pixel `(x, y)` (it is to be ignored).
    pub fn ignored(&self, x: usize, y: usize) -> bool {
        self.0.values().any(|m| m.at(x, y))
    }

    /// The union of all masks, or `None` when there are none.
    pub fn union(&self) -> Option<Mask> {
        self.union_except(&[])
    }

    /// The union of the masks not named in `skip`, or `None` when there are none.
    pub fn union_except(&self, skip: &[&str]) -> Option<Mask> {
        let mut it = self.0.iter().filter(|(name, _)| !skip.contains(&name.as_str())).map(|(_, m)| m);
        let mut out = it.next()?.clone();
        for m in it {
            for (o, v) in out.data_mut().iter_mut().zip(m.data()) {
                *o |= *v;
            }
        }
        Some(out)
    }
}

/// The images of one exposure.
#[derive(Debug, Clone, PartialEq)]
pub enum Views {
    /// One camera.
    Mono(Rgb8),
    /// A stereo pair, each view undistorted to its own pinhole camera (the rig's `left` and
    /// `right`, related by its extrinsics; not rectified: a stereo stage rectifies).
    Stereo {
        /// Reference (left) image.
        left: Rgb8,
        /// Right image.
        right: Rgb8,
    },
}

impl Views {
    /// The reference image (the mono image, or the left one).
    pub fn reference(&self) -> &Rgb8 {
        match self {
            Views::Mono(i) => i,
            Views::Stereo { left, .. } => left,
        }
    }

    /// Every image, mutable, so that a mono preprocessor works on stereo unchanged.
    pub fn iter_mut(&mut self) -> impl Iterator<Item = &mut Rgb8> {
        let v: Vec<&mut Rgb8> = match self {
            Views::Mono(i) => vec![i],
            Views::Stereo { left, right } => vec![left, right],
        };
        v.into_iter()
    }

    /// Mono or stereo.
    pub fn kind(&self) -> ViewKind {
        match self {
            Views::Mono(_) => ViewKind::Mono,
            Views::Stereo { .. } => ViewKind::Stereo,
        }
    }
}

/// A frame as read from the input, before depth estimation.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFrame {
    /// 0-based index in the sequence.
    pub index: usize,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// The camera image(s).
    pub views: Views,
    /// Depth from a sensor or the phantom's ground truth, if the input has it.
    pub depth_m: Option<DepthMap>,
    /// Ground-truth camera pose, if the input has it.
    pub gt_t_world_cam: Option<Iso3>,
    /// Masks of pixels to ignore, in the reference (mono or left) view's pixels: what every
    /// stage after depth estimation reads.
    pub masks: Masks,
    /// Masks of the right view of a stereo pair, in its own pixels (e.g. its highlights, which a
    /// light beside the lenses puts elsewhere than the left's); empty for a mono frame. A stereo
    /// depth estimator ignores these pixels of the right view.
    pub right_masks: Masks,
    /// What the preprocessors did to the images' photometry.
    pub photometry: Photometry,
    /// Where the reference image was resampled from a coarser sampling (an undistortion's
    /// stretched outer ring), the source pixels behind each of its pixels, at most 1
    /// ([`SampleShare`]); `None`: every pixel is a pixel of the sensor.
    pub sample_share: Option<SampleShare>,
}

/// Per pixel, how many source pixels stand behind a pixel of a resampled image, clamped to 1:
/// the determinant of the resampling map's Jacobian, `|∂(u_src, v_src) / ∂(u, v)|`. Where an
/// undistortion stretches the lens's outer ring, one source pixel's noise and interpolation error
/// spread over `1 / share` neighbouring pixels; a tracker that weighs each pixel's photometric
/// residual by its share counts them once (the counterpart of the depth error's correlated
/// blocks, [`RgbdFrame::depth_sigma_correlation_px`]). Shared by every frame of a sequence.
pub type SampleShare = Arc<ShareMap>;

/// A [`SampleShare`]'s per-pixel map (it dereferences to it) and its block means, derived once
/// per sequence rather than once per frame.
#[derive(Debug)]
pub struct ShareMap {
    per_pixel: GrayF32,
    /// `block_means[l]`: each pixel the mean of a 2^l × 2^l block; made on first use.
    block_means: Mutex<Vec<Option<Arc<GrayF32>>>>,
}

impl ShareMap {
    /// The share of every pixel.
    pub fn new(per_pixel: GrayF32) -> Self {
        Self { per_pixel, block_means: Mutex::new(Vec::new()) }
    }

    /// The `width × height` image whose pixel `(x, y)` is the mean share of the 2^l × 2^l
    /// block at `(x·2^l, y·2^l)` (0 beyond the map); made once per `l`.
    pub fn block_mean(&self, l: usize, (width, height): (usize, usize)) -> Arc<GrayF32> {
        let mut made = self.block_means.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(m) = made.get(l).and_then(Option::as_ref).filter(|m| m.size() == (width, height)) {
            return m.clone();
        }
        let (sw, sh, step) = (self.per_pixel.width(), self.per_pixel.height(), 1usize << l);
        let mean = Arc::new(GrayF32::from_fn(width, height, |x, y| {
            let (mut sum, mut n) = (0.0f32, 0usize);
            for yy in (y * step)..((y + 1) * step).min(sh) {
                for xx in (x * step)..((x + 1) * step).min(sw) {
                    sum += self.per_pixel.at(xx, yy);
                    n += 1;
                }
            }
            [if n > 0 { sum / n as f32 } else { 0.0 }]
        }));
        if made.len() <= l {
            made.resize(l + 1, None);
        }
        made[l] = Some(mean.clone());
        mean
    }
}

impl std::ops::Deref for ShareMap {
    type Target = GrayF32;

    fn deref(&self) -> &GrayF32 {
        &self.per_pixel
    }
}

impl PartialEq for ShareMap {
    /// Two maps are equal when their shares are (the block means derive from them).
    fn eq(&self, other: &Self) -> bool {
        self.per_pixel == other.per_pixel
    }
}

impl CameraFrame {
    /// A mono frame with no depth, pose, masks or photometric corrections.
    pub fn mono(index: usize, timestamp_s: f64, image: Rgb8) -> Self {
        Self {
            index,
            timestamp_s,
            views: Views::Mono(image),
            depth_m: None,
            gt_t_world_cam: None,
            masks: Masks::new(),
            right_masks: Masks::new(),
            photometry: Photometry::default(),
            sample_share: None,
        }
    }
}

/// A memo of data derived from one frame (filtered depth, vertex and normal maps, ...), so that
/// stages needing the same derivation compute it once. Keys name the derivation and every
/// parameter it used. Stages still never call each other: they share results through the frame.
/// A clone starts empty, so a modified copy of a frame never sees stale data.
#[derive(Default)]
pub struct Derived(Mutex<Vec<(String, Arc<dyn Any + Send + Sync>)>>);

impl Derived {
    /// The value under `key`, computed by `f` on first use.
    pub fn get_or_compute<T: Any + Send + Sync>(&self, key: &str, f: impl FnOnce() -> T) -> Arc<T> {
        let mut memo = self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(v) = memo.iter().find(|(k, _)| k == key).and_then(|(_, v)| v.clone().downcast::<T>().ok()) {
            return v;
        }
        let v = Arc::new(f());
        memo.push((key.to_owned(), v.clone()));
        v
    }

    /// Number of memoised values.
    pub fn len(&self) -> usize {
        self.0.lock().map_or(0, |m| m.len())
    }

    /// Whether nothing is memoised.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Clone for Derived {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl PartialEq for Derived {
    /// Derived data never makes two frames differ.
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for Derived {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Derived({} values)", self.len())
    }
}

/// Where a frame's depth came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum DepthSource {
    /// Measured (an RGB-D sensor, or the phantom's exact depth): noise of fractions of a mm.
    #[default]
    Measured,
    /// Estimated from the image (shape from shading): smooth, but biased by millimetres where
    /// the albedo or the light model is off.
    Estimated,
}

/// What tracking, fusion and loop closure see: one colour image with its depth, whatever
/// produced the depth (a sensor, shape from shading, a stereo matcher).
#[derive(Debug, Clone, PartialEq)]
pub struct RgbdFrame {
    /// Where the depth came from: a tracker weighs measured and estimated depth differently.
    pub depth_source: DepthSource,
    /// 0-based index in the sequence.
    pub index: usize,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// Reference colour image.
    pub colour: Rgb8,
    /// Depth along z, metres; 0 = invalid.
    pub depth_m: DepthMap,
    /// Per-pixel depth confidence in [0, 1], when the estimator gives one.
    pub depth_confidence: Option<GrayF32>,
    /// Per-pixel σ of the depth, metres (0 where the depth is invalid), when the depth stage
    /// knows its noise ([`crate::depth_noise`]): trackers weigh residuals and fusers measurements
    /// by it. `None`: the trackers' own noise scales alone.
    pub depth_sigma_m: Option<DepthMap>,
    /// Correlation length of the depth error, pixels (0: independent pixels;
    /// [`crate::depth_noise::DepthNoiseModel::correlation_px`]).
    pub depth_sigma_correlation_px: f64,
    /// What the preprocessors did to the colour image's photometry (a tracker that models the
    /// light must not divide a fall-off out twice).
    pub photometry: Photometry,
    /// Per-pixel albedo observed by the depth estimator (linear luminance; 0 = none), when it
    /// has a light model: what the fuser averages into each surfel's albedo.
    pub albedo: Option<GrayF32>,
    /// Ground-truth pose, if known (for oracle stages and evaluation only).
    pub gt_t_world_cam: Option<Iso3>,
    /// Masks of pixels to ignore.
    pub masks: Masks,
    /// The colour image's source pixels per pixel where it was resampled
    /// ([`CameraFrame::sample_share`]); `None`: 1 everywhere.
    pub sample_share: Option<SampleShare>,
    /// Data derived from this frame, shared between stages.
    pub derived: Derived,
}

impl RgbdFrame {
    /// Whether pixel `(x, y)` has valid depth and no mask marks it.
    pub fn usable(&self, x: usize, y: usize) -> bool {
        let d = self.depth_m.at(x, y);
        d > 0.0 && d.is_finite() && !self.masks.ignored(x, y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn union_and_ignored() {
        let mut m = Masks::new();
        assert!(m.union().is_none());
        let mut a = Mask::new(2, 2);
        *a.at_mut(0, 0) = true;
        let mut b = Mask::new(2, 2);
        *b.at_mut(1, 1) = true;
        m.insert(MASK_SPECULAR, a);
        m.insert(MASK_OUT_OF_VIEW, b);
        let u = m.union().unwrap();
        assert_eq!(u.data(), &[true, false, false, true]);
        assert!(m.ignored(1, 1) && !m.ignored(1, 0));
    }

    #[test]
    fn a_share_maps_block_means_are_made_once() {
        let share = ShareMap::new(GrayF32::from_fn(5, 4, |x, y| [(x + 10 * y) as f32]));
        let half = share.block_mean(1, (3, 2));
        // (0, 0) averages 0, 1, 10, 11; (2, 1) the last column's two pixels 24 and 34.
        assert_eq!((half.at(0, 0), half.at(2, 1)), (5.5, 29.0));
        assert!(Arc::ptr_eq(&half, &share.block_mean(1, (3, 2))), "made once");
        assert_eq!(share.block_mean(0, (5, 4)).data(), share.data());
    }

    #[test]
    fn derived_values_are_computed_once_and_not_cloned() {
        let d = Derived::default();
        let mut calls = 0;
        let a = d.get_or_compute("x", || {
            calls += 1;
            41
        });
        let b = d.get_or_compute("x", || 0);
        assert_eq!((*a, *b, calls), (41, 41, 1));
        assert_eq!(*d.get_or_compute("y", || 2.5f32), 2.5);
        assert_eq!(d.len(), 2);
        assert!(d.clone().is_empty());
    }

    #[test]
    fn stereo_iter_mut_visits_both() {
        let mut v = Views::Stereo { left: Rgb8::new(1, 1), right: Rgb8::new(1, 1) };
        for img in v.iter_mut() {
            img.set_pixel(0, 0, [9, 9, 9]);
        }
        match v {
            Views::Stereo { left, right } => assert_eq!(left.pixel(0, 0), right.pixel(0, 0)),
            Views::Mono(_) => unreachable!(),
        }
    }
}
