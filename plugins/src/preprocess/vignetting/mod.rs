//! `vignetting`: divides a radial fall-off out of every view (the paper's step 2; frontend
//! Goldman 2010, IEEE TPAMI 32(12)). What is divided must agree with the depth model:
//!
//! - `divide = "lens-and-light"` (default): the lens vignetting V and the LED profile μ only,
//!   keeping the cos θ / r² cue that `near-light-sfs` reads depth from;
//! - `divide = "flat-field"`: the whole flat field V · μ · cos³α, what a distant-light model
//!   such as `tsai-shah` expects.
//!
//! The fall-off comes from `source`: `light` (the calibrated `light.toml`: V and μ exactly per
//! pixel), `file` (a `vignetting.toml` of radial polynomials from `capsule-slam
//! calibrate-vignetting` on flat-field frames) or `sequence` (no calibration: estimated from the
//! first `learn_frames` frames themselves, [`sequence`]).
//!
//! In linear terms the corrected value is `s · L / F(u)`, F floored at `1 / max_gain`, s = 1
//! (`scale = "centre"`: the principal point keeps its value, pixels that the correction clips are
//! masked) or the smallest F in view (`"no-clip"`); as the encoding is a power law this is one
//! gain per pixel on the 8-bit values, `(s / F)^(1/γ)`. The frame records what was divided, the
//! scale and γ (`CameraFrame::photometry`), so that a depth estimator with a light model sees the
//! image it models; pixels clipped by the sensor are masked as `saturated` (their corrected value
//! would no longer look clipped, so nothing later could tell). Applying the stage twice does nothing the
//! second time (the record says the fall-off is already divided).

pub mod sequence;

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::{DividedFalloff, Falloff, MASK_SATURATED};
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::light::vignetting::{VignettingFile, light_falloff, profile_falloff};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{CameraFrame, Context, Mask, Plugin, Preprocessor, Rgb8, StageError, register};
use serde::{Deserialize, Serialize};

use sequence::Learner;

/// How the sequence estimate removes the scene from the fall-off.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SequenceModel {
    /// Mean brightness per ring over cos³α.
    Mean,
    /// Brightness over the predicted near-light shading.
    Shading,
}

/// The brightness reference of the corrected image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OutputScale {
    /// The principal point keeps its value; clipped pixels are masked.
    Centre,
    /// Scaled by the smallest fall-off in view: nothing clips.
    NoClip,
}

/// Where the fall-off comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Source {
    /// `light` if the input has `light_file`, else `file` if it has `vignetting_file`, else
    /// `sequence`.
    Auto,
    /// `light.toml`: V and the LED profile, per pixel.
    Light,
    /// `vignetting.toml` (calibrate-vignetting).
    File,
    /// Estimated from the sequence.
    Sequence,
    /// Nothing divided: the frames pass unchanged.
    None,
}

capsule_slam_framework::plugin_params! {
    /// Parameters of `vignetting`.
    pub struct VignettingParams {
        /// Where the fall-off comes from: `light`, `file`, `sequence`, `none`, or `auto`
        /// (`light` or `file` if the input folder has its file; else, when the depth is
        /// estimated, the assumed light of an uncalibrated capsule, for a stereo rig `none`,
        /// and `sequence` for an RGB-D input).
        pub source: Source = Source::Auto; unit = "-";
        /// What to divide: `lens-and-light` (for near-light shape from shading) or `flat-field`
        /// (for a distant-light model such as tsai-shah).
        pub divide: Falloff = Falloff::LensAndLight; unit = "-";
        /// The light model (source `light`), relative to the input folder.
        pub light_file: String = "light.toml".to_string(); unit = "path";
        /// The profiles (source `file`), relative to the input folder.
        pub vignetting_file: String = "vignetting.toml".to_string(); unit = "path";
        /// Source `sequence`: frames the estimate is learnt from (refitted on each, then frozen).
        pub learn_frames: u32 = 60; unit = "frames"; range = 1.0..=100000.0;
        /// Source `sequence`: terms of the radial polynomial (r², r⁴, r⁶).
        pub degree: u32 = 3; unit = "-"; range = 1.0..=3.0;
        /// Source `sequence`: `mean` (the radial profile of the frames' (trimmed) mean brightness over the
        /// flat target's cos³α: needs scenes without radial structure of their own) or
        /// `shading` (each pixel's brightness over its near-light shading cos θ / r² from the
        /// map's prediction at the last pose: needs measured or stereo depth; frames before the
        /// first prediction are not corrected).
        pub sequence_model: SequenceModel = SequenceModel::Shading; unit = "-";
        /// Source `sequence`: the encoding exponent of the pixels (light and file give theirs).
        pub gamma: f64 = 2.2; unit = "-"; range = 0.1..=10.0;
        /// A pixel with a channel at or above this was clipped by the sensor: it is masked as
        /// `saturated`.
        pub saturation: u8 = 250; unit = "8-bit"; range = 1.0..=255.0;
        /// The largest linear gain of the correction (F is floored at its inverse): a poor
        /// estimate at the rim of the field of view must not turn noise into signal.
        pub max_gain: f64 = 8.0; unit = "-"; range = 1.0..=100.0;
        /// Brightness of the output: `centre` (the principal point keeps its value, the rim is
        /// brightened as in I / F; pixels that clip are masked as `saturated`) or `no-clip` (all
        /// scaled by the smallest F in view so that nothing clips; the image darkens).
        pub scale: OutputScale = OutputScale::Centre; unit = "-";
    }
}

/// Fractional bits of the fixed-point gains (an exact 8-bit result for gains up to 2^(32−8−12)).
const GAIN_BITS: u32 = 12;

/// Per-camera gains.
struct Table {
    camera: PinholeCamera,
    /// Gain per pixel on the 8-bit values, `(s / F)^(1/γ)` (1 outside the field of view), in
    /// fixed point with `GAIN_BITS` fractional bits.
    gain: Vec<u32>,
    /// s.
    linear_scale: f64,
}

/// The vignetting corrector.
pub struct Vignetting {
    params: VignettingParams,
    source: FalloffSource,
    /// The sequence estimate (source `sequence`).
    learner: Learner,
    table: Option<Table>,
    warned_twice: bool,
    /// A warning of the build, told on the first frame.
    pending_warning: Option<String>,
}

impl Plugin for Vignetting {
    const NAME: &'static str = "vignetting";
    const SUMMARY: &'static str = "divides the lens and LED fall-off (or the whole flat field) out of every view, from light.toml, a calibrated vignetting.toml or the sequence itself; records what it divided for the depth model";
    type Params = VignettingParams;

    fn build(params: VignettingParams, env: &BuildEnv) -> Result<Self, StageError> {
        let path = |name: &str| env.input_file(name);
        let monocular = env.depth_source == Some(capsule_slam_framework::frame::DepthSource::Estimated);
        // A stereo rig's depth does not need the fall-off, and its photometric tracking needs
        // the same brightness in every frame: learning the fall-off from the first frames
        // changes it while tracking starts (stereo preset 1, 24 frames: SE(3) ATE 6.1 % of the
        // path with `sequence`, 3.5 % with the assumed light, 0.8 % uncorrected;
        // `docs/results/stereo.md`).
        let stereo = env.rig.kind() == capsule_slam_framework::camera::ViewKind::Stereo;
        let chosen = match params.source {
            Source::Auto if path(&params.light_file).is_file() => Source::Light,
            Source::Auto if path(&params.vignetting_file).is_file() => Source::File,
            // Without a calibration, a depth estimated from the shading must see the fall-off
            // its own assumed light divides (`near-light-sfs`), not one learnt from that depth;
            // a stereo rig is left uncorrected.
            Source::Auto if stereo => {
                let mut v = Self::new(params, FalloffSource::None);
                v.pending_warning = Some(
                    "no light.toml or vignetting.toml in the input folder: the stereo views are left uncorrected (stereo matching does not need it; a fall-off learnt from the first frames would change the brightness while tracking starts; `capsule-slam calibrate-vignetting` measures the capsule's)"
                        .into(),
                );
                return Ok(v);
            }
            Source::Auto if monocular => {
                let light = LightModel::uncalibrated();
                let why = format!(
                    "no light.toml or vignetting.toml in the input folder: the fall-off of the assumed light is divided ({}; `capsule-slam calibrate-light` or `calibrate-vignetting` measure the capsule's)",
                    light.describe()
                );
                let mut v = Self::new(params, FalloffSource::Light(light));
                v.pending_warning = Some(why);
                return Ok(v);
            }
            Source::Auto => Source::Sequence,
            s => s,
        };
        let source = match chosen {
            Source::Light => FalloffSource::Light(capsule_slam_framework::files::read_light_file(&path(&params.light_file)).map_err(|e| {
                StageError::invalid_input(format!(
                    "{e}; `vignetting` with source = \"light\" needs the capsule's light model: put light.toml in the input folder, or set plugins.vignetting.source = \"file\" (a calibrated vignetting.toml) or \"sequence\""
                ))
            })?),
            Source::File => FalloffSource::File(capsule_slam_framework::files::read_vignetting_file(&path(&params.vignetting_file)).map_err(|e| {
                StageError::invalid_input(format!(
                    "{e}; `vignetting` with source = \"file\" needs a vignetting.toml: `capsule-slam calibrate-vignetting` writes one from flat-field frames, or set plugins.vignetting.source = \"sequence\""
                ))
            })?),
            Source::Sequence | Source::Auto => FalloffSource::Sequence,
            Source::None => FalloffSource::None,
        };
        Ok(Self::new(params, source))
    }
}

/// The model, as passed to [`Vignetting::new`].
pub enum FalloffSource {
    /// A light model.
    Light(LightModel),
    /// Calibrated profiles.
    File(VignettingFile),
    /// Learn from the sequence.
    Sequence,
    /// Divide nothing.
    None,
}

impl Vignetting {
    /// A corrector from its parameters and fall-off source (`params.source` is ignored).
    pub fn new(params: VignettingParams, source: FalloffSource) -> Self {
        let learner = Learner::new(params.degree as usize, params.gamma);
        Self { params, source, learner, table: None, warned_twice: false, pending_warning: None }
    }

    /// The encoding exponent the correction assumes.
    pub fn gamma(&self) -> f64 {
        match &self.source {
            FalloffSource::Light(l) => l.gamma,
            FalloffSource::File(f) => f.gamma,
            FalloffSource::Sequence | FalloffSource::None => self.params.gamma,
        }
    }

    /// The fall-off F at pixel (u, v) (1 at the principal point), `None` while a sequence
    /// estimate has no fit yet.
    pub fn falloff(&self, cam: &PinholeCamera, u: f64, v: f64) -> Option<f64> {
        let divide = self.params.divide;
        Some(match &self.source {
            FalloffSource::Light(l) => light_falloff(l, cam, u, v, divide),
            FalloffSource::File(f) => f.falloff(cam, u, v, divide),
            FalloffSource::Sequence => profile_falloff(self.learner.profile()?, cam, u, v, divide),
            FalloffSource::None => return None,
        })
    }

    fn build_table(&self, cam: &PinholeCamera) -> Option<Table> {
        let (w, h) = (cam.width, cam.height);
        let mut f = vec![1.0f64; w * h];
        let mut min_f = 1.0f64;
        let floor = 1.0 / self.params.max_gain;
        for (k, fk) in f.iter_mut().enumerate() {
            let (u, v) = ((k % w) as f64, (k / w) as f64);
            if cam.in_fov(u, v) {
                let raw = self.falloff(cam, u, v)?;
                *fk = if raw.is_finite() { raw.max(floor) } else { 1.0 };
                min_f = min_f.min(*fk);
            }
        }
        let scale = match self.params.scale {
            OutputScale::Centre => 1.0,
            OutputScale::NoClip => min_f,
        };
        let inv_gamma = 1.0 / self.gamma();
        let one = f64::from(1u32 << GAIN_BITS);
        let gain = (0..w * h)
            .map(|k| if cam.in_fov((k % w) as f64, (k / w) as f64) { ((scale / f[k]).powf(inv_gamma) * one).round() as u32 } else { 1 << GAIN_BITS })
            .collect();
        Some(Table { camera: cam.clone(), gain, linear_scale: scale })
    }

    /// Divides the fall-off out of one image (8-bit gains of the table); marks in `clipped` the
    /// pixels whose corrected value clips.
    fn apply(gain: &[u32], img: &mut Rgb8, clipped: &mut Mask) {
        for ((px, g), clip) in img.data_mut().chunks_exact_mut(3).zip(gain).zip(clipped.data_mut()) {
            for c in px {
                let v = (u32::from(*c) * g + (1 << (GAIN_BITS - 1))) >> GAIN_BITS;
                *clip |= v > 255;
                *c = v.min(255) as u8;
            }
        }
    }
}

impl Preprocessor for Vignetting {
    /// Only while it learns the fall-off from the sequence with the map's shading
    /// (`sequence_model = "shading"`, the first `learn_frames` frames).
    fn reads_prediction(&self) -> bool {
        matches!(self.source, FalloffSource::Sequence)
            && self.params.sequence_model == SequenceModel::Shading
            && self.learner.frames() < self.params.learn_frames as usize
    }

    fn process(&mut self, frame: &mut CameraFrame, ctx: &mut Context) -> Result<(), StageError> {
        if let Some(w) = self.pending_warning.take() {
            ctx.warn(w);
        }
        if matches!(self.source, FalloffSource::None) {
            return Ok(());
        }
        if frame.photometry.divided.is_some() {
            if !self.warned_twice {
                self.warned_twice = true;
                ctx.warn("the frame's fall-off is already divided (a second vignetting stage?): left unchanged");
            }
            return Ok(());
        }
        let cam = ctx.rig.camera().clone();
        let img = frame.views.reference();
        if img.size() != (cam.width, cam.height) {
            return Err(StageError::invalid_input(format!(
                "vignetting: frame {} is {}×{} but the camera is {}×{}: fix camera.toml or the images",
                frame.index,
                img.width(),
                img.height(),
                cam.width,
                cam.height
            )));
        }
        let sat = self.params.saturation;
        let flags = img.data().chunks_exact(3).map(|c| c[0].max(c[1]).max(c[2]) >= sat).collect();
        let mut saturated = Mask::from_vec(cam.width, cam.height, flags).map_err(|e| StageError::invalid_input(e.to_string()))?;
        if matches!(self.source, FalloffSource::Sequence) && self.learner.frames() < self.params.learn_frames as usize {
            // Only while learning: the pixels the frame's masks leave.
            let ignored = frame.masks.union();
            let learner = &mut self.learner;
            let usable = |x: usize, y: usize| !saturated.at(x, y) && !ignored.as_ref().is_some_and(|m| m.at(x, y));
            match (self.params.sequence_model, ctx.prediction) {
                (SequenceModel::Mean, _) => learner.add(img, &cam, usable),
                (SequenceModel::Shading, Some(pred)) => learner.add_shaded(img, &cam, usable, &pred.depth_m, &pred.normals_cam),
                (SequenceModel::Shading, None) => {}
            }
            self.table = None;
            ctx.count("learnt_frames", learner.frames() as f64);
        }
        if self.table.as_ref().is_none_or(|t| t.camera != cam) {
            self.table = self.build_table(&cam);
        }
        let Some(table) = &self.table else {
            ctx.warn("no fall-off estimate yet (too few usable pixels); the frame is left uncorrected");
            return Ok(());
        };
        for (i, img) in frame.views.iter_mut().enumerate() {
            if img.size() == (cam.width, cam.height) {
                let mut other = Mask::new(cam.width, cam.height);
                Self::apply(&table.gain, img, if i == 0 { &mut saturated } else { &mut other });
            }
        }
        let n_sat = saturated.data().iter().filter(|v| **v).count();
        ctx.count("saturated_pixels", n_sat as f64);
        ctx.count("linear_scale", table.linear_scale);
        if n_sat > 0 {
            let mut m = saturated;
            if let Some(old) = frame.masks.get(MASK_SATURATED) {
                m.data_mut().iter_mut().zip(old.data()).for_each(|(a, b)| *a |= *b);
            }
            frame.masks.insert(MASK_SATURATED, m);
        }
        frame.photometry.divided = Some(DividedFalloff { falloff: self.params.divide, linear_scale: table.linear_scale, gamma: self.gamma() });
        Ok(())
    }
}

register!(Preprocessor, Vignetting);

#[cfg(test)]
mod tests;
