//! `reflection`: specular highlight removal, the paper's first step (Sec. 3.1): detection by
//! the image's gradient map combined with adaptive-threshold peaks ([`detect`]), a dilation
//! margin for the halo, inpainting of the masked pixels by Telea's fast marching ([`telea`]).
//!
//! Every view is cleaned; the reference view's mask is published in the frame as
//! [`MASK_SPECULAR`] (`publish_mask`, on by default), so that the depth estimator, the tracker
//! and the fuser ignore those pixels rather than trusting the inpainted guess. The pixels
//! already masked (out of view) are neither searched nor read by the inpainting.
//!
//! Idempotent: an image without highlights is returned unchanged (the inpainted region has no
//! peak with a sharp rim).

pub mod detect;
mod integral;
pub mod telea;

use capsule_slam_framework::frame::MASK_SPECULAR;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{CameraFrame, Context, Mask, Plugin, Preprocessor, Rgb8, StageError, register};

use crate::common::masks::dilate;
use detect::{DetectParams, detect};
use telea::Order;

capsule_slam_framework::plugin_params! {
    /// Parameters of `reflection`.
    pub struct ReflectionParams {
        /// Side of the local-statistics window of the adaptive threshold (Arnold et al. 2010,
        /// "Automatic segmentation and inpainting of specular highlights for endoscopic
        /// imaging", EURASIP JIVP: 31–51 px at 1350×1080). Larger than the longest highlight,
        /// or the window sees only the highlight (`docs/results/preprocessing.md`).
        pub window_px: u32 = 61; unit = "px"; range = 3.0..=255.0;
        /// A peak lies this many local standard deviations above the local mean brightness
        /// (Arnold et al. 2010: k ≈ 2–3; 1 here, as the colour and rim tests keep the
        /// precision).
        pub peak_sigma: f64 = 1.0; unit = "σ"; range = 0.0..=20.0;
        /// A peak is at least this bright, max(R, G, B) in 8-bit levels (small highlights deep
        /// in the tube are 80–120; 250 keeps only clipped ones, for sensors that clip every
        /// highlight).
        pub min_value: f64 = 60.0; unit = "8-bit"; range = 0.0..=255.0;
        /// A peak is nearly white: saturation 1 − min/max of its channels at most this
        /// (Arnold et al. 2010: S < ~0.3; mucosa has S 0.28–0.43, its highlights 0.08–0.23).
        pub max_saturation: f64 = 0.22; unit = "-"; range = 0.0..=1.0;
        /// A group of peaks is a highlight only if the mean Sobel magnitude of the brightness on
        /// its outer ring reaches this (sharp rims; Arnold et al. 2010, T_g).
        pub min_rim_gradient: f64 = 2.0; unit = "8-bit/px"; range = 0.0..=255.0;
        /// The highlight extends over neighbours at least this many times brighter (linear
        /// luminance) than the local diffuse background: 2 = where the highlight adds as much
        /// light as the tissue reflects (the phantom's ground-truth definition).
        pub grow_ratio: f64 = 2.0; unit = "-"; range = 1.0..=100.0;
        /// The highlight also extends over neighbours whitened to at most this saturation.
        pub grow_saturation: f64 = 0.25; unit = "-"; range = 0.0..=1.0;
        /// Most pixels the highlight grows from its peaks.
        pub max_grow_px: u32 = 20; unit = "px"; range = 0.0..=255.0;
        /// Margin added around each highlight before inpainting (the halo), pixels.
        pub dilate_px: u32 = 2; unit = "px"; range = 0.0..=32.0;
        /// Radius of the inpainting neighbourhood (Telea's ε; OpenCV's examples use 5; 4 is as
        /// good at two thirds of the cost).
        pub inpaint_radius_px: f64 = 4.0; unit = "px"; range = 1.0..=64.0;
        /// Extrapolation of the inpainting from each known pixel: `zero` (a weighted mean) or
        /// `first` (Telea's eq. 3, exact on ramps, but it carries a highlight's bright halo
        /// inward).
        pub inpaint_order: Order = Order::Zero; unit = "-";
        /// Encoding exponent of the pixels (for the linear luminance of the growth test).
        pub gamma: f64 = 2.2; unit = "-"; range = 0.1..=10.0;
        /// Publish the mask in the frame (`specular`), so that later stages ignore the
        /// inpainted pixels; off = later stages use the inpainted values, as the paper does.
        pub publish_mask: bool = true; unit = "-";
    }
}

/// The reflection remover.
pub struct Reflection {
    params: ReflectionParams,
    decode: [f64; 256],
    scratch: detect::Scratch,
}

impl Plugin for Reflection {
    const NAME: &'static str = "reflection";
    const SUMMARY: &'static str = "specular highlights: adaptive-threshold peaks kept by their rim gradient, grown against the diffuse background, dilated, inpainted by Telea's fast marching; publishes the `specular` mask";
    type Params = ReflectionParams;

    fn build(params: ReflectionParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self::new(params))
    }
}

/// One view's result.
#[derive(Debug, Clone)]
pub struct Cleaned {
    /// The detected highlights before the dilation.
    pub detected: Mask,
    /// The inpainted pixels (detected, dilated).
    pub inpainted: Mask,
    /// Peak groups found, and rejected by the gradient test.
    pub groups: (usize, usize),
}

impl Reflection {
    /// A remover with the given parameters.
    pub fn new(params: ReflectionParams) -> Self {
        let g = params.gamma;
        Self { params, decode: std::array::from_fn(|v| (v as f64 / 255.0).powf(g)), scratch: detect::Scratch::default() }
    }

    fn detect_params(&self) -> DetectParams {
        let p = &self.params;
        DetectParams {
            window_px: p.window_px as usize,
            peak_sigma: p.peak_sigma,
            min_value: p.min_value,
            max_saturation: p.max_saturation,
            min_rim_gradient: p.min_rim_gradient,
            grow_ratio: p.grow_ratio,
            grow_saturation: p.grow_saturation,
            max_grow_px: p.max_grow_px as usize,
        }
    }

    /// Detects and inpaints the highlights of one image in place, among the pixels set in
    /// `valid`.
    /// `valid` of another size than `img` is an error.
    pub fn clean(&mut self, img: &mut Rgb8, valid: &Mask) -> Result<Cleaned, StageError> {
        let params = self.detect_params();
        let d = detect(img, valid, &params, &self.decode, &mut self.scratch)?;
        let inpainted = dilate(&d.mask, self.params.dilate_px as usize, Some(valid));
        telea::inpaint(img, &inpainted, valid, self.params.inpaint_radius_px, self.params.inpaint_order)?;
        Ok(Cleaned { detected: d.mask, inpainted, groups: (d.groups, d.rejected) })
    }
}

impl Preprocessor for Reflection {
    fn reads_prediction(&self) -> bool {
        false
    }

    fn process(&mut self, frame: &mut CameraFrame, ctx: &mut Context) -> Result<(), StageError> {
        let ignored = frame.masks.union();
        let (mut published, mut published_right) = (None, None);
        let (mut groups, mut rejected, mut share) = (0, 0, 0.0);
        for (i, img) in frame.views.iter_mut().enumerate() {
            let (w, h) = img.size();
            let valid = match &ignored {
                Some(m) if i == 0 && m.size() == (w, h) => {
                    let mut v = m.clone();
                    v.data_mut().iter_mut().for_each(|b| *b = !*b);
                    v
                }
                _ => match ctx.rig.camera() {
                    c if (c.width, c.height) == (w, h) => c.fov_mask(),
                    c => {
                        ctx.warn(format!(
                            "frame {}: view {i} is {w}×{h} but the camera {}×{}: its field of view is unknown, every pixel is searched",
                            frame.index, c.width, c.height
                        ));
                        Mask::filled(w, h, true)
                    }
                },
            };
            let out = self.clean(img, &valid)?;
            groups += out.groups.0;
            rejected += out.groups.1;
            if i == 0 {
                let n_valid = valid.data().iter().filter(|v| **v).count().max(1);
                share = out.inpainted.data().iter().filter(|v| **v).count() as f64 / n_valid as f64;
                published = Some(out.inpainted);
            } else {
                published_right = Some(out.inpainted);
            }
        }
        ctx.count("highlight_share", share);
        ctx.count("peak_groups", groups as f64);
        ctx.count("rejected_groups", rejected as f64);
        if self.params.publish_mask {
            for (view, masks, found) in [("left", &mut frame.masks, published), ("right", &mut frame.right_masks, published_right)] {
                if let Some(m) = found
                    && let Some((old_w, old_h)) = add_mask(masks, m)
                {
                    ctx.warn(format!(
                        "frame {}: the {view} view's highlight mask of an earlier stage is {old_w}×{old_h}, not the view's size: it was replaced by this stage's, not joined",
                        frame.index
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Publishes `m` as the view's [`MASK_SPECULAR`], joined with one an earlier stage published.
/// An earlier mask of another size cannot be joined: it is replaced, and its size returned so
/// that the caller can say so.
fn add_mask(masks: &mut capsule_slam_framework::frame::Masks, mut m: Mask) -> Option<(usize, usize)> {
    let mut dropped = None;
    match masks.get(MASK_SPECULAR) {
        Some(old) if old.size() == m.size() => m.data_mut().iter_mut().zip(old.data()).for_each(|(a, b)| *a |= *b),
        Some(old) => dropped = Some(old.size()),
        None => {}
    }
    masks.insert(MASK_SPECULAR, m);
    dropped
}

register!(Preprocessor, Reflection);

#[cfg(test)]
mod tests;
