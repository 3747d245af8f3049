//! The synthetic deformable stomach phantom: the ground truth of every stage.
//!
//! A capsule camera inside a closed, bent, bulging cavity ([`shape`]) with procedural tissue
//! texture ([`texture`]), lit by a point light at (or beside) the optical centre with the
//! near-light model of `light.toml` ([`capsule_slam_framework::light`]): Lambertian `albedo · cos θ / r²`, LED
//! spot profile, Blinn–Phong highlights of wet tissue, lens vignetting, gamma, Gaussian read
//! and shot noise, optional motion blur and a peristaltic wall motion. Seven camera paths
//! mirror the paper's Table 3 ([`trajectory`]). Rendering is deterministic for a seed.

pub mod depth_noise;
pub mod render;
pub mod shape;
pub mod texture;
pub mod trajectory;
pub mod writer;

use serde::{Deserialize, Serialize};

use capsule_slam_framework::camera::{CameraFile, PinholeCamera};
use capsule_slam_framework::geometry::Iso3;
use capsule_slam_framework::lens::{DistortionSpec, LensModel};
use capsule_slam_framework::light::LightModel;
use shape::StomachShape;

/// Image size presets: the paper's three cameras, a 320×320 capsule and PAL video.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum SizePreset {
    /// NanEye, 250×250.
    #[serde(rename = "naneye")]
    NanEye,
    /// 320×320 capsule camera (default).
    #[default]
    #[serde(rename = "320")]
    Capsule320,
    /// Voyager, 720×480.
    #[serde(rename = "voyager")]
    Voyager,
    /// Potensic, 1280×720.
    #[serde(rename = "potensic")]
    Potensic,
    /// PAL video, 720×576: what stereo endoscopes record (the Open-CAS ex-vivo pairs, the
    /// Hamlyn sequences at twice their 360×288).
    #[serde(rename = "pal")]
    Pal,
}

impl SizePreset {
    /// Parses `naneye`, `320`, `voyager`, `potensic` or `pal`.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "naneye" | "250" => Self::NanEye,
            "320" | "capsule" => Self::Capsule320,
            "voyager" | "720x480" => Self::Voyager,
            "potensic" | "1280x720" => Self::Potensic,
            "pal" | "720x576" => Self::Pal,
            _ => return None,
        })
    }

    /// (width, height) in pixels.
    pub fn size(&self) -> (u32, u32) {
        match self {
            Self::NanEye => (250, 250),
            Self::Capsule320 => (320, 320),
            Self::Voyager => (720, 480),
            Self::Potensic => (1280, 720),
            Self::Pal => (720, 576),
        }
    }
}

/// Everything that defines a phantom sequence (written as `phantom.toml` beside it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhantomSpec {
    /// Trajectory preset, 1–7 (the paper's Table 3).
    pub preset: u8,
    /// Frames of one walk along the path.
    pub frames: usize,
    /// Walks along the path: forth, back, forth, ... (a capsule revisits); the sequence has
    /// `frames × repeat` frames and the wall moves on throughout.
    #[serde(default = "one_walk", skip_serializing_if = "is_one_walk")]
    pub repeat: usize,
    /// Image size.
    pub size: SizePreset,
    /// Seed of texture and noise.
    pub seed: u64,
    /// Amplitude of the peristaltic wall motion, mm (0 = rigid).
    pub deform_mm: f64,
    /// The frame at which the wall starts to move (it grows to `deform_mm` over
    /// [`shape::WAVE_ONSET_RAMP_S`]); 0: it moves from the first frame.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub deform_onset_frame: usize,
    /// Scale of the specular highlights (0 = none, 1 = wet tissue).
    pub specular: f64,
    /// Scale of the sensor noise (0 = none, 1 = a good capsule sensor).
    pub noise: f64,
    /// Procedural tissue texture; false = uniform albedo (for shape from shading).
    pub texture: bool,
    /// Light offset from the optical centre along camera x, mm.
    pub light_offset_mm: f64,
    /// Sub-frame samples of motion blur (1 = none).
    pub motion_blur: u32,
    /// The lens (none: a pinhole); `camera.toml` names it, and `run` undistorts the frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<LensModel>,
    /// Frame rate, Hz.
    pub frame_rate_hz: f64,
    /// With wall motion, the true surface is also written at every this many frames (0: only
    /// at the first, middle and last frame), for the live surface error.
    #[serde(default)]
    pub surface_every: usize,
    /// The error added to the depth the sensor reads (the exact depth stays the ground truth).
    #[serde(default)]
    pub depth_noise: depth_noise::DepthNoise,
    /// A stereo rig: a second, identical camera this far along +x of the first (the reference),
    /// mm, with the light midway between the two (issue 19); none: one camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stereo_baseline_mm: Option<f64>,
}

fn one_walk() -> usize {
    1
}

fn is_one_walk(r: &usize) -> bool {
    *r == 1
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

impl PhantomSpec {
    /// Frames of the sequence: `frames × repeat`.
    pub fn frame_count(&self) -> usize {
        self.frames * self.repeat.max(1)
    }

    /// Where along the path (0 start, 1 end) the capsule is at frame `f` (fractional for motion
    /// blur): one walk takes `frames` frames, and each further walk goes back the way the last
    /// came (a triangle wave of period `2 (frames − 1)`), so the capsule never jumps.
    pub fn path_tau(&self, f: f64) -> f64 {
        if self.frames <= 1 {
            return 0.0;
        }
        let u = (f / (self.frames - 1) as f64).rem_euclid(2.0);
        if u <= 1.0 { u } else { 2.0 - u }
    }

    /// The defaults of a trajectory preset: heavy noise on 6, heavy reflections on 7.
    pub fn preset(preset: u8) -> Self {
        Self {
            preset,
            frames: 300,
            repeat: 1,
            size: SizePreset::default(),
            seed: 1,
            deform_mm: 0.0,
            deform_onset_frame: 0,
            specular: if preset == 7 { 2.5 } else { 1.0 },
            noise: if preset == 6 { 5.0 } else { 1.0 },
            texture: true,
            light_offset_mm: 0.0,
            motion_blur: 1,
            distortion: None,
            frame_rate_hz: 30.0,
            surface_every: 0,
            depth_noise: depth_noise::DepthNoise::None,
            stereo_baseline_mm: None,
        }
    }

    /// Every invalid field as `(field, message)`.
    pub fn problems(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        if !(1..=7).contains(&self.preset) {
            out.push(("preset", format!("{} is not a preset; use 1–7", self.preset)));
        }
        if self.frames == 0 {
            out.push(("frames", "must be at least 1".into()));
        }
        if !(1..=1000).contains(&self.repeat) {
            out.push(("repeat", format!("{} walks: use 1 to 1000", self.repeat)));
        }
        if !(self.deform_mm.is_finite() && (0.0..=8.0).contains(&self.deform_mm)) {
            out.push(("deform_mm", format!("{} must be in [0, 8] mm", self.deform_mm)));
        }
        if self.deform_onset_frame > 0 && self.deform_mm == 0.0 {
            out.push(("deform_onset_frame", format!("{}: an onset needs a wave (deform_mm > 0)", self.deform_onset_frame)));
        }
        for (k, v) in [("specular", self.specular), ("noise", self.noise)] {
            if !(v.is_finite() && (0.0..=20.0).contains(&v)) {
                out.push((k, format!("{v} must be in [0, 20]")));
            }
        }
        if let Some(b) = self.stereo_baseline_mm
            && !(b.is_finite() && (0.5..=50.0).contains(&b))
        {
            out.push(("stereo_baseline_mm", format!("{b} must be within 0.5–50 mm")));
        }
        if !(self.light_offset_mm.is_finite() && self.light_offset_mm.abs() <= 10.0) {
            out.push(("light_offset_mm", format!("{} must be within ±10 mm", self.light_offset_mm)));
        }
        if !(1..=32).contains(&self.motion_blur) {
            out.push(("motion_blur", format!("{} samples: use 1 (off) to 32", self.motion_blur)));
        }
        if let Some(lens) = &self.distortion {
            let spec = DistortionSpec::from_model(lens);
            out.extend(spec.problems("distortion").into_iter().map(|p| ("distortion", format!("{} ({})", p.message, p.fix))));
            // The corner of the image must be reached by a ray (no fold inside the frame).
            let (w, h) = self.size.size();
            let f = 0.5 * f64::from(w.min(h));
            let corner = (f64::from(w.max(h)) / 2.0 / f, f64::from(w.min(h)) / 2.0 / f);
            if lens.undistort(corner.0, corner.1).is_none() {
                out.push((
                    "distortion",
                    format!("{} {:?} folds over inside the image (no ray reaches its corner): weaken it", lens.name(), lens.coefficients()),
                ));
            }
        }
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            out.push(("frame_rate_hz", format!("{} must be positive", self.frame_rate_hz)));
        }
        out
    }
}

/// Specular reflectance of wet mucosa (Blinn–Phong k_s), white.
pub const SPECULAR_ALBEDO: f64 = 1.5;
/// Blinn–Phong exponent of wet mucosa (a sharp, mirror-like film of fluid).
pub const SHININESS: f64 = 250.0;

/// A phantom ready to render.
#[derive(Debug, Clone)]
pub struct Phantom {
    /// The spec it was built from.
    pub spec: PhantomSpec,
    /// The cavity.
    pub shape: StomachShape,
    /// The camera.
    pub camera: PinholeCamera,
    /// The light.
    pub light: LightModel,
    poses: Vec<Iso3>,
}

impl Phantom {
    /// Builds the phantom; `Err` lists every invalid field of the spec.
    pub fn new(spec: PhantomSpec) -> Result<Self, String> {
        let problems = spec.problems();
        if !problems.is_empty() {
            return Err(problems.into_iter().map(|(k, m)| format!("{k}: {m}")).collect::<Vec<_>>().join("; "));
        }
        let wave_onset_s = spec.deform_onset_frame as f64 / spec.frame_rate_hz;
        let shape = StomachShape { wave_m: spec.deform_mm * 1e-3, wave_onset_s, ..StomachShape::default() };
        let camera = Self::camera_file_for(&spec).camera();
        let light = LightModel {
            gain: 0.6,
            ref_distance_m: 0.025,
            ambient: 0.02,
            gamma: 2.2,
            // A stereo capsule's light sits midway between its cameras.
            position_m: [spec.light_offset_mm * 1e-3 + 0.5e-3 * spec.stereo_baseline_mm.unwrap_or(0.0), 0.0, 0.0],
            spot_exponent: 1.0,
            vignetting: vec![-0.3, -0.25],
        };
        let poses = (0..spec.frame_count()).map(|i| trajectory::pose(&shape, &trajectory::waypoint(spec.preset, spec.path_tau(i as f64)))).collect();
        Ok(Self { spec, shape, camera, light, poses })
    }

    /// The `camera.toml` of a spec's size: focal length half the shorter side; square sensors
    /// get a round field of view of radius 0.47 × the side (capsule lenses are round).
    pub fn camera_file_for(spec: &PhantomSpec) -> CameraFile {
        let (w, h) = spec.size.size();
        let f = 0.5 * f64::from(w.min(h));
        let mut file = CameraFile {
            width: w,
            height: h,
            fx: f,
            fy: f,
            cx: (f64::from(w) - 1.0) / 2.0,
            cy: (f64::from(h) - 1.0) / 2.0,
            depth_scale: 5000.0,
            distortion: spec.distortion.as_ref().map(DistortionSpec::from_model),
            fov_radius_px: (w == h).then_some(0.47 * f64::from(w)),
            baseline_m: None,
            right: None,
            depth_noise: (spec.depth_noise != depth_noise::DepthNoise::None).then(|| spec.depth_noise.model(w as usize)),
        };
        // The right camera: the left's intrinsics and lens, turned alike, b along +x.
        file.right = spec.stereo_baseline_mm.map(|b| {
            let t = capsule_slam_framework::stereo::rectified_t_right_left(b * 1e-3).translation.vector;
            capsule_slam_framework::stereo::RightCameraFile {
                fx: Some(file.fx),
                fy: Some(file.fy),
                cx: Some(file.cx),
                cy: Some(file.cy),
                distortion: file.distortion.clone(),
                fov_radius_px: file.fov_radius_px,
                rotation: Some(vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
                translation_m: Some(t.iter().copied().collect()),
            }
        });
        file
    }

    /// Where a view's camera sits in the reference (left) camera's frame: the identity for the
    /// left, `stereo_baseline_mm` along +x for the right.
    pub fn t_left_view(&self, view: capsule_slam_framework::stereo::rectify::Side) -> Iso3 {
        match (view, self.spec.stereo_baseline_mm) {
            (capsule_slam_framework::stereo::rectify::Side::Right, Some(b)) => capsule_slam_framework::stereo::rectified_t_right_left(b * 1e-3).inverse(),
            _ => Iso3::identity(),
        }
    }

    /// Ground-truth pose of frame `i`.
    pub fn pose(&self, i: usize) -> Iso3 {
        self.poses[i.min(self.poses.len() - 1)]
    }

    /// Every ground-truth pose.
    pub fn poses(&self) -> &[Iso3] {
        &self.poses
    }

    /// Timestamp of frame `i`, seconds.
    pub fn time_s(&self, i: usize) -> f64 {
        i as f64 / self.spec.frame_rate_hz
    }

    /// Path length of the trajectory, metres.
    pub fn path_length_m(&self) -> f64 {
        trajectory::path_length_m(&self.poses)
    }
}
