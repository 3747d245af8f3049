//! `stereo-sgm`: metric depth from a calibrated stereo pair on the CPU (issue 19). Per frame:
//! 1. both views rectified (Bouguet, `capsule_slam_framework::stereo::rectify`; maps made once
//!    per rig, [`remap`]), their luminance sampled bilinearly; the masks of either view
//!    (`CameraFrame::masks` and `right_masks`: highlights, out of view) and clipped pixels of
//!    either view leave no match;
//! 2. coarse-to-fine matching ([`matcher`]): masked ZNCC costs ([`zncc`]) aggregated by
//!    semi-global matching ([`sgm`], Hirschmüller 2008, 4 or 8 paths) over the whole disparity
//!    range at the top of a pyramid, then refined down every level around the level above
//!    after warping the right view by it; sub-pixel winner-takes-all, both directions matched
//!    and checked against each other, speckle filter; the range is what `min_depth_m`–
//!    `max_depth_m` give at the rig's baseline and focal length;
//! 3. the depth `z = f b / d` returned in the left camera's own image, with its σ
//!    `σ_z = z² σ_d / (f b)` (`disparity_sigma_px`), which the trackers and the fuser weigh by.
//!
//! Stereo needs no light model: its scale is the baseline's. Where the input has one
//! (`light.toml`), the estimate also carries each pixel's observed albedo ([`albedo`]), which
//! the fuser averages into the map.

pub mod albedo;
pub mod matcher;
pub mod pyramid;
pub mod remap;
pub mod sgm;
pub mod zncc;

use capsule_slam_framework::camera::ViewKind;
use capsule_slam_framework::frame::{DepthSource, Views};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stereo::rectify::Side;
use capsule_slam_framework::{CameraFrame, Context, DepthEstimate, DepthEstimator, DepthMap, Plugin, StageError, register};

use albedo::{AlbedoInput, AlbedoModel};
use capsule_slam_framework::GrayF32;
use matcher::MatchSettings;
use remap::Rectifier;
use sgm::SgmSettings;
use zncc::{COST_PER_RHO, Plane};

capsule_slam_framework::plugin_params! {
    /// Parameters of `stereo-sgm`. Defaults measured on the 5 mm phantom pair
    /// (`docs/results/stereo.md`).
    pub struct StereoSgmParams {
        /// Nearest depth searched (the largest disparity, `f b / min_depth_m`): organ scale.
        pub min_depth_m: f64 = 0.01; unit = "m"; range = 0.001..=10.0;
        /// Farthest depth searched (the smallest disparity).
        pub max_depth_m: f64 = 0.25; unit = "m"; range = 0.001..=100.0;
        /// Pyramid levels above the full resolution (the first match is at 1/2^levels); see
        /// `focal_reference_px`.
        pub levels: u32 = 2; unit = "-"; range = 0.0..=5.0;
        /// ZNCC window radius at the top level, pixels of that level.
        pub top_radius: u32 = 3; unit = "px"; range = 1.0..=15.0;
        /// ZNCC window radius of every refinement, pixels of its level: wide, because the warp
        /// has taken out the slant and the noise needs the support; see `focal_reference_px`.
        pub radius: u32 = 10; unit = "px"; range = 1.0..=30.0;
        /// 0 (the default): `radius` and `levels` as given. Else the focal length they are set
        /// for (160: the 320×320 phantom's, where they were measured): at a longer focal length
        /// f the radius becomes `radius · f / focal_reference_px` (rounded) and the levels
        /// `levels + round(log₂(f / focal_reference_px))`, so that the windows see the same
        /// angle of the wall; a shorter one keeps both (fewer pixels would average less noise).
        /// On 720×576 phantom pairs (f = 288 px) 160 halves the single-frame pixels more than
        /// 1 px off (9.7 → 4.0 %), but a still sequence's map covers less of the rim (CT-style
        /// points within 2 mm 96.2 → 94.5 %, 88.9 → 82.3 % through a strong lens), which the
        /// ex-vivo acceptance scores: off by default (`docs/results/stereo.md`).
        pub focal_reference_px: f64 = 0.0; unit = "px"; range = 0.0..=100000.0;
        /// σ of the sensor noise of the 8-bit intensities: a window whose variance is mostly
        /// noise correlates near 0 (the phantom: 2.4–3.5).
        pub noise_levels: f64 = 2.0; unit = "levels"; range = 0.0..=50.0;
        /// Residual disparities searched around the level above: ±search_px.
        pub search_px: u32 = 2; unit = "px"; range = 1.0..=8.0;
        /// σ of the smoothing of a level's disparities into the prior of the next.
        pub smooth_px: f64 = 2.0; unit = "px"; range = 0.5..=20.0;
        /// Full-resolution refinements with both directions checked; each one after the first
        /// starts from the checked disparities, their holes filled (`fill_px`).
        pub passes: u32 = 2; unit = "-"; range = 1.0..=10.0;
        /// The pyramid level of the checked passes (0: full resolution; 1: half, then one
        /// checked refinement per level down: about half the time).
        pub check_level: u32 = 1; unit = "-"; range = 0.0..=5.0;
        /// σ of the smoothing that fills a checked pass's holes for the next, full-resolution
        /// pixels.
        pub fill_px: f64 = 8.0; unit = "px"; range = 0.5..=30.0;
        /// SGM penalty of a one-pixel disparity step, in units of the cost `1 − ρ`
        /// (Hirschmüller's P1).
        pub p1: f64 = 0.0625; unit = "1-rho"; range = 0.0..=2.0;
        /// SGM penalty of a larger step (P2).
        pub p2: f64 = 0.5; unit = "1-rho"; range = 0.0..=8.0;
        /// Aggregation paths: 4 or 8.
        pub paths: u32 = 8; unit = "-"; range = 4.0..=8.0;
        /// Largest disagreement of the left–right check.
        pub lr_max_px: f64 = 1.0; unit = "px"; range = 0.0..=10.0;
        /// The top level's best aggregated cost must be this share below every other
        /// disparity's (more than a pixel away): OpenCV's `uniquenessRatio` / 100.
        pub uniqueness: f64 = 0.0; unit = "-"; range = 0.0..=0.9;
        /// Connected regions of similar disparity smaller than this are removed (speckles).
        pub speckle_px: u32 = 50; unit = "px"; range = 0.0..=100000.0;
        /// A pixel with a channel at or above this in either view was clipped: no match there.
        pub saturation: u32 = 250; unit = "8-bit"; range = 1.0..=256.0;
        /// Whether the pixels of either view's `specular` mask (the `reflection` stage's
        /// highlights) get no match. false: the windows read the inpainted images there, as
        /// the rest of each window's texture carries the match (clipped pixels never match).
        pub mask_specular: bool = true; unit = "-";
        /// σ of a matched disparity, the depth's σ is `z² σ_d / (f b)`: the RMS of this
        /// matcher's disparity error over every matched pixel, 0.46–0.52 px on the 5 mm phantom
        /// pairs of presets 1, 4, 5 (`docs/results/stereo.md`, "The depth's σ"). The robust σ
        /// (1.48 MAD) is 0.32–0.33 px; the RMS counts the tails the weights must expect.
        pub disparity_sigma_px: f64 = 0.5; unit = "px"; range = 0.01..=10.0;
        /// Correlation length of the depth error handed to the trackers (a block of this size
        /// counts as one measurement; `DepthEstimate::sigma_correlation_px`). The refinement's
        /// window is 21 px, but counting 21×21 blocks leaves tracking to the photometric term,
        /// which fails without a light model when the capsule moves fast: SE(3) ATE on presets
        /// 1 / 5 / preset 1 in 30 frames 0.34 / 0.16 / 14.8 % at 21, 0.40 / 0.14 / 5.7 % at 8,
        /// 0.55 / 0.15 / 2.0 % at 0 (`docs/results/stereo.md`).
        pub correlation_px: f64 = 8.0; unit = "px"; range = 0.0..=200.0;
        /// The capsule's light model, relative to the input folder: where it exists, each
        /// pixel's observed albedo is returned beside the depth; where not, none (stereo needs
        /// no light).
        pub light_file: String = "light.toml".to_string(); unit = "path";
        /// Half the span of the depth differences a pixel's normal is taken from, for its
        /// albedo (cos θ): wider is smoother (the phantom pair's bias in the albedo: +3.1 % at
        /// 1 px, +1.5 % at 4, +0.5 % at 8).
        pub normal_px: u32 = 8; unit = "px"; range = 1.0..=30.0;
    }
}

/// The refinement window's radius and the pyramid's levels at focal length `fx_px`
/// ([`StereoSgmParams::focal_reference_px`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScaledWindow {
    /// ZNCC radius of the refinements, pixels.
    pub radius: usize,
    /// Pyramid levels above the full resolution.
    pub levels: usize,
}

/// `radius` and `levels` scaled from `focal_reference_px` up to a longer `fx_px`: the radius by
/// the ratio (at most 60 px), the levels by its base-2 logarithm (at most 5); a shorter focal
/// length keeps both.
pub fn scaled_window(p: &StereoSgmParams, fx_px: f64) -> ScaledWindow {
    let given = ScaledWindow { radius: p.radius as usize, levels: p.levels as usize };
    if p.focal_reference_px <= 0.0 || fx_px.is_nan() || fx_px <= 0.0 {
        return given;
    }
    // Never below the reference: a smaller window averages fewer pixels of sensor noise (the
    // 250×250 phantom pair at f = 125 px, its window scaled to 8 px: AbsRel 0.028 → 0.030).
    let ratio = (fx_px / p.focal_reference_px).max(1.0);
    ScaledWindow {
        radius: (f64::from(p.radius) * ratio).round().clamp(1.0, 60.0) as usize,
        levels: (f64::from(p.levels) + ratio.log2().round()).clamp(0.0, 5.0) as usize,
    }
}

/// The stereo depth estimator.
pub struct StereoSgm {
    params: StereoSgmParams,
    rectifier: Rectifier,
    /// The light model of `light_file`, if the input has one.
    albedo: Option<AlbedoModel>,
}

impl Plugin for StereoSgm {
    const NAME: &'static str = "stereo-sgm";
    const SUMMARY: &'static str = "metric depth from a calibrated stereo pair: Bouguet rectification, coarse-to-fine masked ZNCC + semi-global matching (Hirschmüller 2008) with warping, both directions checked, speckle filter, σ per pixel";
    const VIEWS: ViewKind = ViewKind::Stereo;
    type Params = StereoSgmParams;

    fn build(params: StereoSgmParams, env: &BuildEnv) -> Result<Self, StageError> {
        crate::common::ordered("min_depth_m", params.min_depth_m, "max_depth_m", params.max_depth_m)?;
        if params.paths != 4 && params.paths != 8 {
            return Err(StageError::invalid_input(format!("stereo-sgm: paths = {} (use 4 or 8)", params.paths)));
        }
        let path = env.input_file(&params.light_file);
        let albedo = match path.exists() {
            false => None,
            true => Some(AlbedoModel::new(capsule_slam_framework::files::read_light_file(&path).map_err(|e| {
                StageError::invalid_input(format!(
                    "{e}; `stereo-sgm` reads the capsule's light model there for the observed albedo: fix the file (`capsule-slam calibrate-light` fits one), or set plugins.stereo-sgm.light_file to a file that does not exist to run without albedo"
                ))
            })?)),
        };
        Ok(Self { rectifier: Rectifier::new(&env.rig)?, params, albedo })
    }
}

impl StereoSgm {
    /// The same estimator with a light model: it returns the observed albedo too.
    pub fn with_light(mut self, light: capsule_slam_framework::light::LightModel) -> Self {
        self.albedo = Some(AlbedoModel::new(light));
        self
    }

    /// Each pixel's observed albedo given the frame's depth, if there is a light model.
    pub fn albedo(&self, frame: &CameraFrame, depth_m: &DepthMap, cam: &capsule_slam_framework::camera::PinholeCamera) -> Option<GrayF32> {
        let model = self.albedo.as_ref()?;
        let Views::Stereo { left, .. } = &frame.views else { return None };
        let ignore = frame.masks.union();
        let input = AlbedoInput {
            image: left,
            depth_m,
            ignore: ignore.as_ref(),
            divided: frame.photometry.divided,
            saturation: self.params.saturation.min(256) as u16,
            normal_px: self.params.normal_px as usize,
        };
        Some(model.observe(&input, cam))
    }

    /// The matcher's settings at this rig: the disparity range of the depth range.
    pub fn settings(&self) -> MatchSettings {
        let (p, r) = (&self.params, &self.rectifier.rect);
        let fb = r.camera.fx * r.baseline_m;
        let d_max = ((fb / p.min_depth_m).ceil() as usize).min(r.camera.width.saturating_sub(1)).max(1);
        let d_min = ((fb / p.max_depth_m).floor() as usize).min(d_max - 1);
        let penalty = |v: f64| (v * f64::from(COST_PER_RHO)).round() as u16;
        let scaled = scaled_window(p, r.camera.fx);
        MatchSettings {
            sgm: SgmSettings {
                d_min,
                d_max,
                p1: penalty(p.p1),
                p2: penalty(p.p2.max(p.p1)),
                paths: p.paths as usize,
                lr_max_px: p.lr_max_px as f32,
                uniqueness: p.uniqueness as f32,
            },
            levels: scaled.levels,
            top_radius: p.top_radius as usize,
            radius: scaled.radius,
            noise_levels: p.noise_levels as f32,
            search_px: p.search_px as usize,
            smooth_px: p.smooth_px as f32,
            passes: p.passes as usize,
            check_level: p.check_level as usize,
            fill_px: p.fill_px as f32,
            speckle_px: p.speckle_px as usize,
        }
    }

    /// The left camera's depth and its σ from a stereo frame.
    pub fn depth(&self, frame: &CameraFrame) -> Result<(DepthMap, DepthMap), StageError> {
        let Views::Stereo { left, right } = &frame.views else {
            return Err(StageError::invalid_input(format!(
                "stereo-sgm: frame {} has one view; a stereo input lists its right images in rgb_right.txt",
                frame.index
            )));
        };
        let sat = self.params.saturation.min(256) as u16;
        let clipped = |img: &capsule_slam_framework::Rgb8, x: usize, y: usize| img.pixel(x, y).iter().any(|c| u16::from(*c) >= sat);
        let skip: &[&str] = if self.params.mask_specular { &[] } else { &[capsule_slam_framework::frame::MASK_SPECULAR] };
        let (masks, right_masks) = (frame.masks.union_except(skip), frame.right_masks.union_except(skip));
        if let Some(m) = right_masks.as_ref().filter(|m| m.size() != right.size()) {
            let ((mw, mh), (w, h)) = (m.size(), right.size());
            return Err(StageError::invalid_input(format!(
                "stereo-sgm: frame {}: the right view's masks are {mw}×{mh} but its image is {w}×{h}; a preprocessor published a mask of another view",
                frame.index
            )));
        }
        let cam = &self.rectifier.rect.camera;
        let plane = |(gray, invalid): (Vec<f32>, Vec<bool>)| Plane { gray, invalid, width: cam.width, height: cam.height };
        let l = plane(self.rectifier.view(Side::Left, left, |x, y| clipped(left, x, y) || masks.as_ref().is_some_and(|m| m.at(x, y))));
        let r = plane(self.rectifier.view(Side::Right, right, |x, y| clipped(right, x, y) || right_masks.as_ref().is_some_and(|m| m.at(x, y))));
        let disparity = matcher::match_pair(&l, &r, &self.settings());
        let depth = self.rectifier.depth_in_left(&disparity)?;
        let fb = cam.fx * self.rectifier.rect.baseline_m;
        let sd = self.params.disparity_sigma_px;
        let sigma = DepthMap::from_fn(depth.width(), depth.height(), |x, y| {
            let z = f64::from(depth.at(x, y));
            [if z > 0.0 { (z * z * sd / fb) as f32 } else { 0.0 }]
        });
        Ok((depth, sigma))
    }
}

impl DepthEstimator for StereoSgm {
    fn reads_prediction(&self) -> bool {
        false
    }

    fn input_kind(&self) -> ViewKind {
        ViewKind::Stereo
    }

    /// Measured by triangulation, in metres (the baseline gives the scale), with a σ per pixel:
    /// the trackers and the fuser treat it as a noisy sensor's depth (issue 17's weights).
    fn source(&self) -> DepthSource {
        DepthSource::Measured
    }

    fn estimate(&mut self, frame: &CameraFrame, ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        if !self.rectifier.fits(ctx.rig) {
            self.rectifier = Rectifier::new(ctx.rig)?;
        }
        let (depth_m, sigma_m) = self.depth(frame)?;
        let valid = depth_m.data().iter().filter(|d| **d > 0.0).count();
        ctx.count("valid_pixels", valid as f64);
        if valid == 0 {
            ctx.warn("stereo matching found no depth (textureless, masked or out of range views?)");
        }
        let albedo = self.albedo(frame, &depth_m, ctx.rig.camera());
        Ok(DepthEstimate { depth_m, confidence: None, albedo, sigma_m: Some(sigma_m), sigma_correlation_px: self.params.correlation_px })
    }
}

register!(DepthEstimator, StereoSgm);

#[cfg(test)]
mod tests;
