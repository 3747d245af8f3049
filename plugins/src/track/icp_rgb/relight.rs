//! Relighting of the photometric term. A capsule's light moves with its camera, so between
//! frames the same tissue changes brightness by about twice the relative change of its distance
//! (11 % for 1.7 mm at 30 mm): brightness constancy fails. With the capsule's light model
//! (`light.toml`) the live intensity is relit to where each point stands in the reference view,
//! `encode(decode(I_live) · L_ref / L_live)`, L the model's linear response to a unit albedo
//! (distance², incidence, the LED's spot and the lens vignetting, the near-light model of
//! `light.toml`, `capsule_slam_framework::light`; the albedo cancels).
//!
//! Where a preprocessor divided a fall-off F(u) out of the images (`vignetting`: the lens and
//! LED profile, or the whole flat field; the default pipeline's images), the image holds
//! `s · L / F` (Goldman 2010): [`Undivide`] multiplies F back in before tracking. Relighting
//! the divided values by `L / F` is the same arithmetic, but the photometric gates and noise
//! scale are fixed intensities, and on the divided images (brighter towards the rim) they
//! tracked worse: on the seven 5 % smooth-noise phantoms 4 of 7 lost frames against 1 of 7
//! (`docs/results/depth-noise.md`).

use capsule_slam_framework::frame::DividedFalloff;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::light::vignetting::light_falloff;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{GrayF32, Iso3, PinholeCamera, StageError};
use nalgebra::{Point3, Vector3};

use super::frames::Level;
use crate::common::maps::{normal, vertex};

/// What multiplies a divided fall-off F back in, per pixel of one camera:
/// `encode(decode_d(I) · F / s) = min(1, I^(γ_d/γ) · (F / s)^(1/γ))` with the light's encoding γ
/// and the preprocessor's γ_d (the same in practice, and then one product per pixel). Built once
/// per camera and fall-off.
#[derive(Debug, Clone)]
pub struct Undivide {
    cam: PinholeCamera,
    divided: DividedFalloff,
    exponent: f32,
    gain: GrayF32,
}

impl Undivide {
    /// The table of `light`'s fall-off `divided` for `cam`.
    pub fn new(light: &LightModel, divided: DividedFalloff, cam: &PinholeCamera) -> Self {
        let gain = GrayF32::from_fn_par(cam.width, cam.height, |x, y| {
            let f = light_falloff(light, cam, x as f64, y as f64, divided.falloff);
            [(f.max(0.0) / divided.linear_scale).powf(1.0 / light.gamma) as f32]
        });
        Self { cam: cam.clone(), divided, exponent: (divided.gamma / light.gamma) as f32, gain }
    }

    /// The table kept in `slot`, rebuilt when the camera or the fall-off changed; none where
    /// there is no light model or nothing was divided out.
    pub fn kept<'s>(slot: &'s mut Option<Self>, light: Option<&LightModel>, divided: Option<DividedFalloff>, cam: &PinholeCamera) -> Option<&'s Self> {
        let (light, divided) = (light?, divided?);
        if slot.as_ref().is_none_or(|u| u.cam != *cam || u.divided != divided) {
            *slot = Some(Self::new(light, divided, cam));
        }
        slot.as_ref()
    }

    /// The intensity image (in [0, 1]) with the fall-off multiplied back in: the image as the
    /// camera took it, up to the 8-bit rounding and the pixels the division clipped (which the
    /// preprocessor masks).
    pub fn apply(&self, mut gray: GrayF32) -> GrayF32 {
        let exact = (self.exponent - 1.0).abs() < 1e-6;
        for (g, k) in gray.data_mut().iter_mut().zip(self.gain.data()) {
            let v = g.clamp(0.0, 1.0);
            *g = (if exact { v } else { v.powf(self.exponent) } * k).min(1.0);
        }
        gray
    }
}

/// `x^e` on [0, 1] by linear interpolation in a table of 2¹⁴ + 1 values: the relighting's gamma
/// decoding (e = γ) and encoding (e = 1/γ), several hundred thousand of each per frame, which
/// libm's `pow` made a tenth of a frame's time. Within 1e-6 of `powf` (the test); for e < 1
/// the curve is too steep near 0 for the table, and below [`PowerTable::EXACT_BELOW`] `powf`
/// itself answers (a linear value below 0.3 % of white, 7 % encoded with γ = 2.2).
#[derive(Debug, Clone)]
pub struct PowerTable {
    exponent: f64,
    values: Vec<f64>,
}

impl PowerTable {
    const STEPS: usize = 1 << 14;
    /// Below this a root (e < 1) is computed, not looked up.
    pub const EXACT_BELOW: f64 = 3e-3;

    /// The table of `x^exponent`.
    pub fn new(exponent: f64) -> Self {
        Self { exponent, values: (0..=Self::STEPS).map(|i| (i as f64 / Self::STEPS as f64).powf(exponent)).collect() }
    }

    /// `x^e` for x clamped to [0, 1].
    pub fn at(&self, x: f64) -> f64 {
        let x = x.clamp(0.0, 1.0);
        if self.exponent < 1.0 && x < Self::EXACT_BELOW {
            return x.powf(self.exponent);
        }
        let f = x * Self::STEPS as f64;
        let i = (f as usize).min(Self::STEPS - 1);
        let t = f - i as f64;
        self.values[i] + t * (self.values[i + 1] - self.values[i])
    }
}

/// The capsule's light model and its gamma tables: what relights the photometric term.
#[derive(Debug, Clone)]
pub struct Lighting {
    /// The light model (`light.toml`).
    pub model: LightModel,
    decode: PowerTable,
    encode: PowerTable,
}

impl Lighting {
    /// The tables of `model`'s gamma.
    pub fn new(model: LightModel) -> Self {
        Self { decode: PowerTable::new(model.gamma), encode: PowerTable::new(1.0 / model.gamma), model }
    }
}

/// The light model `light_file` names (relative to the input folder), or none with the reason
/// when the file does not exist; a file that exists but does not parse is an error. Without the
/// file, a pipeline that estimates depth from the shading (monocular) relights with the light
/// its depth stage then assumes, [`LightModel::uncalibrated`] (the relighting needs only where
/// the light is and how it spreads, not its unknown gain); one that measures depth (any
/// lighting, a room) compares unlit.
pub fn load_light(light_file: &str, env: &BuildEnv) -> Result<(Option<Lighting>, Option<String>), StageError> {
    if light_file.is_empty() {
        return Ok((None, None));
    }
    let path = env.input_file(light_file);
    if !path.exists() && env.depth_source == Some(capsule_slam_framework::frame::DepthSource::Estimated) {
        let light = LightModel::uncalibrated();
        let why = format!(
            "no {} (light_file): the photometric term is relit by the assumed light of an uncalibrated capsule ({}; `capsule-slam calibrate-light` fits the capsule's light.toml; light_file = \"\" compares unlit)",
            path.display(),
            light.describe()
        );
        return Ok((Some(Lighting::new(light)), Some(why)));
    }
    if !path.exists() {
        let why = format!(
            "no {} (light_file): the photometric term compares intensities unlit; the capsule's light.toml relights them (the phantom writes it, `capsule-slam calibrate-light` fits one; light_file = \"\" turns this off)",
            path.display()
        );
        return Ok((None, Some(why)));
    }
    let light = capsule_slam_framework::files::read_light_file(&path).map_err(|e| {
        StageError::invalid_input(format!("icp-rgb: light_file: {e}; fix the file, or set plugins.icp-rgb.light_file = \"\" to compare intensities unlit"))
    })?;
    Ok((Some(Lighting::new(light)), None))
}

/// The light model that relights the photometric term.
#[derive(Debug, Clone, Copy)]
pub struct Relighter<'a> {
    lighting: &'a Lighting,
}

impl<'a> Relighter<'a> {
    /// Relights images lit by `lighting` as the camera took them.
    pub fn new(lighting: &'a Lighting) -> Self {
        Self { lighting }
    }

    /// The image's linear response at pixel (u, v) to a unit albedo at camera-frame point `p`
    /// with normal `n`.
    fn response(&self, cam: &PinholeCamera, (u, v): (f64, f64), p: &Point3<f64>, n: &Vector3<f64>) -> f64 {
        self.lighting.model.linear(cam, u, v, 1.0, p, n)
    }

    fn decode(&self, encoded: f64) -> f64 {
        self.lighting.decode.at(encoded)
    }

    fn encode(&self, linear: f64) -> f64 {
        self.lighting.encode.at(linear)
    }

    /// The live level's intensity over the light's response at each pixel, `decode(I) /
    /// response` (the albedo up to the light's gain; 0 where the pixel has no surface or no
    /// light): the pose-free half of the relighting, once per frame. Made at every `stride`-th
    /// pixel of every `stride`-th row only, the ones a Gauss-Newton system with that stride
    /// reads (`gn::Inputs::stride`); 0 elsewhere.
    pub fn live_albedo(&self, live: &Level, stride: usize) -> GrayF32 {
        let (w, h) = live.depth.size();
        let stride = stride.max(1);
        GrayF32::from_fn_par(w, h, |x, y| {
            if x % stride != 0 || y % stride != 0 {
                return [0.0];
            }
            let (Some(v), Some(n)) = (vertex(&live.vertices, x, y), normal(&live.normals, x, y)) else { return [0.0] };
            let r = self.response(&live.cam, (x as f64, y as f64), &Point3::from(v.cast::<f64>()), &n.cast::<f64>());
            [if r > 1e-9 { (self.decode(f64::from(live.gray.at(x, y))) / r) as f32 } else { 0.0 }]
        })
    }

    /// A live pixel of albedo `albedo` ([`Relighter::live_albedo`]) and normal `nl` relit to
    /// where its point stands in the reference view (`s`, at `uv_ref`): `encode(albedo ·
    /// response_ref)`. `None` where either side is unlit.
    pub fn relit(&self, cam: &PinholeCamera, albedo: f32, nl: &Vector3<f32>, t_ref_live: &Iso3, uv_ref: (f64, f64), s: &Vector3<f64>) -> Option<f64> {
        let (a, nl) = (f64::from(albedo), nl.cast::<f64>());
        let r_ref = self.response(cam, uv_ref, &Point3::from(*s), &(t_ref_live.rotation * nl));
        (a > 0.0 && r_ref > 0.0).then(|| self.encode(a * r_ref))
    }
}
