//! `icp-rgb`: the paper's "joint photometric and geometric pose estimation from a splatted
//! surfel prediction" (Sec. 3.3, Eqs. (2)–(4)): point-to-plane ICP against the predicted
//! active model plus a photometric term on NTSC intensity, `E = E_icp + w_rgb E_rgb`,
//! Gauss-Newton on a 3-level pyramid (10/5/4 iterations fine→coarse, run coarse to fine),
//! projective data association with distance and normal gates, Huber weights, SE(3)
//! increments by the exponential map, and a constant-velocity motion prior.
//!
//! Weighting. Both residuals are divided by a noise scale (`sigma_icp_m`, `sigma_rgb`) so that
//! `w_rgb` is dimensionless; the paper's `w_rgb = 0.1` is the default. ElasticFusion instead
//! builds `A = A_rgb + icpWeight² A_icp`, `b = b_rgb + icpWeight b_icp` with icpWeight = 10,
//! metres against raw 8-bit intensity differences scaled by 1/8 and weighted by
//! `1 / (√N + |Δ|)`: its effective photometric weight depends on the pixel count and the image
//! content and is not a fixed number; with our normalisation `w_rgb = 0.1` means one
//! photometric residual of one σ weighs a tenth of one geometric residual of one σ.
//!
//! Photometric reference. A capsule's light moves with its camera, so the brightness of a wall
//! point changes with the pose (distance², incidence) and the fused model colour, an average
//! over many poses, disagrees with the live image; consecutive frames share nearly the same
//! illumination. The photometric term therefore compares with the previous live frame by
//! default (`rgb_reference = "previous-frame"`, ElasticFusion's `-ftf` option) while ICP uses
//! the model; `"model"` is the paper's literal choice, and tracks worse than ICP alone
//! (`docs/results/tracking.md`).
//!
//! Where the prediction has no surface (early frames, newly seen walls), the previous live
//! frame fills in (ElasticFusion's fill-in). Tracking is declared lost when too few pixels
//! agree, the residual is too large, or the solution jumps; the pipeline then skips fusion.

pub(crate) mod frames;
mod gn;
mod keyframe;
mod measured_noise;
mod options;
pub(crate) mod register;
mod relight;
mod start;
pub(crate) mod terms;

pub use options::{Mode, MotionModel, RgbReference};
pub use terms::{correlated_count, huber, icp_jacobian, icp_residual, residual_sigma, rgb_jacobian};

use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::frame::DepthSource;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, GrayF32, Iso3, ModelView, Plugin, RgbdFrame, StageError, TrackResult, Tracker, register};

use frames::{DepthPrep, Level};
use gn::Weights;
use relight::{Lighting, Undivide, load_light};

capsule_slam_framework::plugin_params! {
    /// Parameters of `icp-rgb`.
    pub struct IcpRgbParams {
        /// `frame-to-model` (the paper) or `frame-to-frame`.
        pub mode: Mode = Mode::FrameToModel; unit = "-";
        /// `constant-velocity` or `none`.
        pub motion_model: MotionModel = MotionModel::ConstantVelocity; unit = "-";
        /// Photometric reference for measured depth: `auto` (`keyframe-and-previous` where the
        /// depth's error is correlated across pixels and a light model relights the term, else
        /// `previous-frame`; `RgbReference::Auto`), `previous-frame`
        /// (robust to the moving light), `keyframe` (the last keyframe, `keyframe.rs`),
        /// `keyframe-and-previous` or `model`. With the 5 % smooth depth error
        /// `keyframe-and-previous` tracked presets 1, 4, 5 to 0.147 / 0.137 / 0.091 % against
        /// 0.244 / 0.148 / 0.157 % with the previous frame, and the stereo phantoms 11–18 %
        /// better (`docs/results/depth-noise.md`).
        pub rgb_reference: RgbReference = RgbReference::Auto; unit = "-";
        /// The same for depth estimated from the image, where the photometric term carries the
        /// tracking. A keyframe lowered the monocular ATE on 4 of the 7 rigid presets (mean
        /// −13 %), and on walls moving by 2–4 mm was better on 4 of 10 and worse on 4
        /// (`docs/results/depth.md`, "A keyframe as the photometric reference").
        pub rgb_reference_estimated: RgbReference = RgbReference::PreviousFrame; unit = "-";
        /// `keyframe`: frames registered to one keyframe, at most.
        pub keyframe_max_frames: u32 = 10; unit = "-"; range = 1.0..=10000.0;
        /// `keyframe`: the camera's translation from the keyframe that replaces it.
        pub keyframe_max_translation_m: f64 = 0.003; unit = "m"; range = 0.0..=100.0;
        /// `keyframe`: the camera's rotation from the keyframe that replaces it.
        pub keyframe_max_rotation_rad: f64 = 0.1; unit = "rad"; range = 0.0..=3.15;
        /// `keyframe`: replaced when the photometric term finds fewer than this share of the
        /// pixels it found on the keyframe's first frame.
        pub keyframe_min_overlap: f64 = 0.7; unit = "-"; range = 0.0..=1.0;
        /// `keyframe`: the frame is finished against the previous frame, and the keyframe
        /// replaced, when the previous frame's term at the keyframe's solution would step by more
        /// than this, `δᵀAδ` in its own information (a moving wall; `register.rs`).
        pub keyframe_max_disagreement: f64 = 3.0; unit = "-"; range = 0.0..=1.0e12;
        /// Weight of the photometric term, Eq. (4) (paper: 0.1).
        pub w_rgb: f64 = 0.1; unit = "-"; range = 0.0..=1000.0;
        /// Noise scale of the point-to-plane residual for measured depth.
        pub sigma_icp_m: f64 = 0.0003; unit = "m"; range = 1.0e-7..=1.0;
        /// Noise scale of the point-to-plane residual for depth estimated from the image
        /// (`near-light-sfs`, `tsai-shah`): its millimetre biases move with the view, so the
        /// photometric term must carry the tracking (30 mm ≡ `w_rgb` × 10⁴ against the measured
        /// scale: the best of 0.3, 10 and 30 mm, `docs/results/tracking.md`).
        pub sigma_icp_estimated_m: f64 = 0.03; unit = "m"; range = 1.0e-7..=1.0;
        /// Noise scale of the intensity residual (intensity in [0, 1]).
        pub sigma_rgb: f64 = 0.02; unit = "-"; range = 1.0e-6..=1.0;
        /// Huber threshold in noise scales.
        pub huber_k: f64 = 1.345; unit = "-"; range = 0.01..=1000.0;
        /// Gauss-Newton iterations at level 0 (finest).
        pub iterations_l0: u32 = 10; unit = "-"; range = 0.0..=100.0;
        /// Gauss-Newton iterations at level 1.
        pub iterations_l1: u32 = 5; unit = "-"; range = 0.0..=100.0;
        /// Gauss-Newton iterations at level 2 (coarsest).
        pub iterations_l2: u32 = 4; unit = "-"; range = 0.0..=100.0;
        /// Stop a level when the step is below this (‖ξ‖, metres and radians mixed as in the twist).
        pub convergence: f64 = 1.0e-5; unit = "-"; range = 0.0..=1.0;
        /// Stop level 0 also when the step is this small in the system's own information: δᵀAδ,
        /// the decrease of the χ² the step predicts, in units of σ² (1e-3: a thirtieth of the
        /// pose's standard deviation). The test in metres and radians above cannot tell a
        /// converged monocular pose, whose steps wander by 1–2 µm at the wall from iteration 5
        /// on (the photometric weights and relighting move with the pose), from one still
        /// converging; a quarter of those frames ran to the cap of 10. 0: the step norm alone
        /// (`register.rs`; `docs/results/speed.md`, "Convergence in the system's information").
        pub convergence_chi2: f64 = 1.0e-3; unit = "σ²"; range = 0.0..=1.0e6;
        /// The same for the coarse levels 1 and 2, whose pose the next level refines: their
        /// first step there is 0.8–3 σ² (the median, sensor depth), so iterating a coarse level
        /// below a tenth of a σ buys nothing.
        pub convergence_chi2_coarse: f64 = 1.0e-2; unit = "σ²"; range = 0.0..=1.0e6;
        /// Use every n-th pixel of level 0 in x and y (ElasticFusion: 1, all; 2 tracks as well,
        /// 1.6× faster, `docs/results/tracking.md`).
        pub stride_l0: u32 = 2; unit = "px"; range = 1.0..=8.0;
        /// ICP correspondence distance gate (ElasticFusion: 0.10 m, room scale).
        pub icp_gate_m: f64 = 0.004; unit = "m"; range = 0.0..=10.0;
        /// Where the frame's depth carries a σ per pixel (`sensor` with a noise model), the ICP and
        /// photometric occlusion gates widen to this many σ of the residual (issue 17: a gate
        /// tuned for exact depth would cut noisy depth's inliers, not its outliers). 6 as the
        /// fuser's `gate_sigmas`: a correlated error shifts whole patches by 2–3 σ (5 % smooth
        /// error, presets 1–7: ATE −8 … +0.4 % against 3 σ, `docs/results/depth-noise.md`).
        pub gate_sigmas: f64 = 6.0; unit = "-"; range = 0.0..=100.0;
        /// ICP normal-angle gate (ElasticFusion: 20°).
        pub icp_angle_gate_rad: f64 = 0.35; unit = "rad"; range = 0.0..=3.15;
        /// Photometric occlusion gate on depth (ElasticFusion: 0.07 m, room scale).
        pub rgb_depth_gate_m: f64 = 0.002; unit = "m"; range = 0.0..=10.0;
        /// The capsule's light model (relative to the input folder), which relights the live
        /// intensity to where each point stands in the reference view (`gn.rs`: the light moves
        /// with the camera; `docs/results/depth-noise.md`: ATE −18 to −42 % on exact depth). A
        /// missing file is a warning, and intensities are compared as they are (measured depth)
        /// or relit by the assumed light of an uncalibrated capsule (estimated depth,
        /// `LightModel::uncalibrated`); "": always compared as they are.
        pub light_file: String = "light.toml".to_string(); unit = "path";
        /// The photometric term ignores the pixels within this distance of a detected highlight
        /// (the `specular` mask of the `reflection` stage; pixels of the full image): the
        /// highlight's tail beyond its detected core adds view-dependent light that brightness
        /// constancy cannot explain. ICP and fusion keep the depth there. 0: only the mask
        /// itself (`docs/results/depth-noise.md`, "A margin around highlights").
        pub rgb_specular_margin_px: u32 = 10; unit = "px"; range = 0.0..=64.0;
        /// Where the frame carries a depth σ, the photometric term warps each live pixel at the
        /// inverse-variance mean, along its ray, of its own depth and the model's (the tangent
        /// plane of its ICP match, σ of a fused mean): the model averages many frames' noise
        /// (`gn::blended_point`; `docs/results/depth-noise.md`).
        pub rgb_model_depth: bool = true; unit = "-";
        /// The depth's error moves a warped pixel: a relative error ε of the live point's depth
        /// moves its image in the photometric reference by `∂u/∂ε = −J_π t` (t: the translation
        /// from the live camera to the reference's), so its intensity by `∇I · ∂u/∂ε · σ_ε`
        /// (Engel et al., LSD-SLAM, ECCV 2014, its photometric variance; σ_ε the
        /// blended depth's relative σ). Each photometric row's variance is `σ_rgb² + (k ∇I ·
        /// ∂u/∂ε · σ_ε)²` with this k, with the references that keep a keyframe (`keyframe`, and
        /// both rows of `keyframe-and-previous`; with `previous-frame` or `model` the rows keep
        /// σ_rgb); 0 leaves σ_rgb alone. A keyframe's rows weigh less as its baseline grows.
        /// k = 1 counts each pixel's depth error as independent; the smooth 5 % error is
        /// correlated over 80 px, and 10 tracked best with `keyframe-and-previous` (k at the
        /// square root of the correlated count, about 40, lost the pose on fast preset 4;
        /// `docs/results/depth-noise.md`).
        pub rgb_flow_sigma_scale: f64 = 10.0; unit = "-"; range = 0.0..=1000.0;
        /// Smallest reference gradient for the photometric term, intensity per pixel.
        pub rgb_min_gradient: f64 = 0.002; unit = "1/px"; range = 0.0..=1.0;
        /// Valid depth range: nearest (ElasticFusion: 0.3 m, room scale).
        pub min_depth_m: f32 = 0.002; unit = "m"; range = 0.0..=100.0;
        /// Valid depth range: farthest.
        pub max_depth_m: f32 = 0.25; unit = "m"; range = 0.0..=100.0;
        /// Bilateral window radius for the live depth (ElasticFusion: 6, a 13×13 window).
        pub bilateral_radius_px: u32 = 1; unit = "px"; range = 0.0..=10.0;
        /// Bilateral spatial σ for the live depth.
        pub bilateral_sigma_px: f32 = 2.0; unit = "px"; range = 0.1..=20.0;
        /// Bilateral range σ for the live depth (ElasticFusion: 0.03 m, room scale).
        pub bilateral_sigma_m: f32 = 0.0008; unit = "m"; range = 1.0e-6..=10.0;
        /// Depth step that breaks a normal.
        pub edge_jump_m: f32 = 0.003; unit = "m"; range = 0.0..=10.0;
        /// Lost if fewer than this share of the live pixels are ICP inliers (measured depth).
        pub min_inlier_fraction: f64 = 0.2; unit = "-"; range = 0.0..=1.0;
        /// The same for estimated depth. Its ICP inliers measure how well shape from shading
        /// agrees with the map, not the pose: 0 (off) keeps tracking through the frames where
        /// they disagree (`docs/results/tracking.md`).
        pub min_inlier_fraction_estimated: f64 = 0.0; unit = "-"; range = 0.0..=1.0;
        /// Lost if the ICP RMS residual exceeds this (measured depth) at the noise floor
        /// `sigma_icp_m`; with the frame's per-pixel σ the test is on the RMS in units of each
        /// residual's σ, against `max_residual_m / sigma_icp_m` (5 σ): a frame is lost when its
        /// residual is far above what its noise explains, not because its depth is noisy.
        pub max_residual_m: f64 = 0.0015; unit = "m"; range = 0.0..=10.0;
        /// Lost if the ICP RMS residual exceeds this (estimated depth).
        pub max_residual_estimated_m: f64 = 0.004; unit = "m"; range = 0.0..=10.0;
        /// Lost if the solution moves this far from the prior (ElasticFusion: 0.3 m, room scale).
        pub max_jump_m: f64 = 0.01; unit = "m"; range = 0.0..=100.0;
        /// Lost if the pose is not constrained: the standard deviation of the camera's
        /// translation along its worst direction (from the Gauss-Newton information) exceeds this.
        pub max_pose_sigma_m: f64 = 0.002; unit = "m"; range = 0.0..=100.0;
        /// Measured depth whose error against the model (`measured_noise.rs`: the residuals'
        /// robust σ relative to depth and their correlation length, over the frames) exceeds
        /// by this factor the σ the tracker takes its residuals to have, `√(sigma_icp_m² + σ²)`
        /// with the frame's σ (medians over its pixels), is weighed by the measured error
        /// instead, in tracking and fusion, with a warning; the first frame that shows it is
        /// registered again. A sequence that declares no `depth_noise` gets 0.1 mm, and 5 %
        /// smooth depth then lost 247 of 300 frames of preset 1 (`docs/results/depth-noise.md`).
        /// 0 turns the check off.
        pub depth_error_factor: f64 = 2.0; unit = "-"; range = 0.0..=1000.0;
        /// Frames the measured depth error averages over (each new frame weighs 1 / this).
        pub depth_error_memory: f64 = 10.0; unit = "frames"; range = 1.0..=100000.0;
    }
}

impl IcpRgbParams {
    /// How depth is prepared for the levels (`frames::live`, `frames::reference`).
    pub fn depth_prep(&self) -> DepthPrep {
        DepthPrep {
            min_m: self.min_depth_m,
            max_m: self.max_depth_m,
            radius_px: self.bilateral_radius_px as usize,
            sigma_px: self.bilateral_sigma_px,
            sigma_m: self.bilateral_sigma_m,
            edge_jump_m: self.edge_jump_m,
        }
    }

    /// When the photometric keyframe is replaced (`keyframe.rs`).
    pub fn keyframe_policy(&self) -> keyframe::Policy {
        keyframe::Policy {
            max_frames: self.keyframe_max_frames,
            max_translation_m: self.keyframe_max_translation_m,
            max_rotation_rad: self.keyframe_max_rotation_rad,
            min_overlap: self.keyframe_min_overlap,
        }
    }
}

/// The joint ICP + photometric tracker.
pub struct IcpRgb {
    params: IcpRgbParams,
    /// The last tracked live frame's pyramid (the fill-in, the photometric and the
    /// frame-to-frame reference).
    previous: Option<Vec<Level>>,
    /// The last relative motion (previous camera → current camera frame).
    velocity: Option<Iso3>,
    /// The capsule's light model, which relights the photometric term (`light_file`).
    light: Option<Lighting>,
    /// Why the light model is not the one `light_file` names (told on the first frame).
    missing: Option<String>,
    /// The table that multiplies a divided fall-off back in (`relight::Undivide`).
    undivide: Option<Undivide>,
    /// The photometric term's keyframe (`rgb_reference = "keyframe"`).
    keyframe: Option<keyframe::Keyframe>,
    /// A registration stopped after the coarse levels (`register.rs`).
    unfinished: Option<Box<register::Unfinished>>,
    /// The next frame's live pyramid, built ahead ([`Tracker::prepare`]), with its frame index.
    ahead: Option<(usize, Vec<Level>)>,
    /// The live depth's error as measured against the model (`measured_noise.rs`), and whether the
    /// warning that it outweighs the frames' own σ was given.
    depth_error: Option<measured_noise::MeasuredNoise>,
    depth_error_told: bool,
    /// The measured noise the current frame is weighed by, where it raised the frame's σ.
    noise_in_use: Option<DepthNoiseModel>,
}

/// How far the frame's depth is trusted, by its source (measured or estimated), and what the
/// photometric term compares with then.
struct DepthNoise {
    sigma_icp_m: f64,
    max_residual_m: f64,
    min_inlier_fraction: f64,
    rgb_reference: RgbReference,
}

impl Plugin for IcpRgb {
    const NAME: &'static str = "icp-rgb";
    const SUMMARY: &'static str = "joint point-to-plane ICP + photometric Gauss-Newton on a 3-level pyramid against the predicted model (paper Eqs. 2-4)";
    type Params = IcpRgbParams;

    fn build(params: IcpRgbParams, env: &BuildEnv) -> Result<Self, StageError> {
        crate::common::ordered("min_depth_m", f64::from(params.min_depth_m), "max_depth_m", f64::from(params.max_depth_m))?;
        Self::with_env(params, env)
    }
}

impl IcpRgb {
    /// A tracker with no history (no previous frame, no velocity).
    pub fn new(params: IcpRgbParams) -> Self {
        Self {
            params,
            previous: None,
            velocity: None,
            light: None,
            missing: None,
            undivide: None,
            keyframe: None,
            unfinished: None,
            ahead: None,
            depth_error: None,
            depth_error_told: false,
            noise_in_use: None,
        }
    }

    /// [`IcpRgb::new`] with the light model of `env`'s input folder (`light_file`), as
    /// [`Plugin::build`] loads it.
    pub fn with_env(params: IcpRgbParams, env: &BuildEnv) -> Result<Self, StageError> {
        let (light, missing) = load_light(&params.light_file, env)?;
        Ok(Self { light, missing, ..Self::new(params) })
    }

    /// The ICP noise scale, loss residual, loss inlier share and photometric reference for depth
    /// from `source` whose error is correlated over `correlation_px` pixels (the live frame's).
    fn depth_noise(&self, source: DepthSource, correlation_px: f64) -> DepthNoise {
        let p = &self.params;
        let noise = match source {
            DepthSource::Measured => DepthNoise {
                sigma_icp_m: p.sigma_icp_m,
                max_residual_m: p.max_residual_m,
                min_inlier_fraction: p.min_inlier_fraction,
                rgb_reference: p.rgb_reference,
            },
            DepthSource::Estimated => DepthNoise {
                sigma_icp_m: p.sigma_icp_estimated_m,
                max_residual_m: p.max_residual_estimated_m,
                min_inlier_fraction: p.min_inlier_fraction_estimated,
                rgb_reference: p.rgb_reference_estimated,
            },
        };
        DepthNoise { rgb_reference: noise.rgb_reference.for_frame(correlation_px, self.light.is_some()), ..noise }
    }

    fn weights(&self, noise: &DepthNoise) -> Weights {
        let p = &self.params;
        Weights {
            w_rgb: p.w_rgb,
            sigma_icp_m: noise.sigma_icp_m,
            sigma_rgb: p.sigma_rgb,
            huber_k: p.huber_k,
            icp_gate_m: p.icp_gate_m,
            gate_sigmas: p.gate_sigmas,
            icp_cos_gate: p.icp_angle_gate_rad.cos(),
            rgb_depth_gate_m: p.rgb_depth_gate_m,
            rgb_min_gradient: p.rgb_min_gradient,
            rgb_model_depth: p.rgb_model_depth,
            rgb_flow_sigma_scale: if noise.rgb_reference.keeps_keyframe() { p.rgb_flow_sigma_scale } else { 0.0 },
        }
    }
}

const LEVELS: usize = 3;

impl Tracker for IcpRgb {
    fn track(&mut self, frame: &RgbdFrame, model: Option<&ModelView>, t_world_prev: &Iso3, ctx: &mut Context) -> Result<TrackResult, StageError> {
        Ok(self.register(frame, model, t_world_prev, false, ctx)?.0)
    }

    /// The live frame's pyramid, which needs neither the map nor a pose.
    fn prepare(&mut self, frame: &RgbdFrame, ctx: &mut Context) {
        let live = self.build_live_pyramid(frame, ctx);
        self.ahead = Some((frame.index, live));
    }

    fn depth_noise_in_use(&self) -> Option<DepthNoiseModel> {
        self.noise_in_use
    }
}

impl IcpRgb {
    /// [`Tracker::track`], and with `initial` also the level-0 ICP RMS residual at the prior
    /// (before any iteration), from the same pyramids: how much the solution explains.
    pub fn register(
        &mut self,
        frame: &RgbdFrame,
        model: Option<&ModelView>,
        t_world_prev: &Iso3,
        initial: bool,
        ctx: &mut Context,
    ) -> Result<(TrackResult, Option<f64>), StageError> {
        let live = self.live_pyramid(frame, ctx);
        self.register_pyramid(live, frame.depth_source, model, t_world_prev, initial, register::Stop::Fine, ctx)
    }

    /// The live frame's pyramid as this tracker prepares it (3 levels, finest first): the one
    /// built ahead for this frame ([`Tracker::prepare`]) if there is one.
    /// Its σ is raised where the depth's error measured against the model outweighs it
    /// ([`IcpRgb::weigh_by_measured_error`]).
    pub(crate) fn live_pyramid(&mut self, frame: &RgbdFrame, ctx: &mut Context) -> Vec<Level> {
        let mut live = match self.ahead.take() {
            Some((index, live)) if index == frame.index => live,
            _ => self.build_live_pyramid(frame, ctx),
        };
        self.noise_in_use = None;
        if frame.depth_source == DepthSource::Measured {
            self.weigh_by_measured_error(&mut live, ctx);
        }
        live
    }

    fn build_live_pyramid(&mut self, frame: &RgbdFrame, ctx: &mut Context) -> Vec<Level> {
        let clock = std::time::Instant::now();
        let cam = ctx.rig.camera();
        // The photometric term relights images as the camera took them: a fall-off a
        // preprocessor divided out goes back in (`relight.rs`), by a table kept per camera.
        let prep = self.params.depth_prep();
        let undivide = Undivide::kept(&mut self.undivide, self.light.as_ref().map(|l| &l.model), frame.photometry.divided, cam);
        let restore = undivide.map(|u| move |g: GrayF32| u.apply(g));
        let margin = self.params.rgb_specular_margin_px as usize;
        let live = frames::live(frame, cam, LEVELS, &prep, restore.as_ref().map(|f| f as &dyn Fn(GrayF32) -> GrayF32), margin);
        if let Some(why) = self.missing.take() {
            ctx.warn(why);
        }
        ctx.count("ms_live_pyramid", clock.elapsed().as_secs_f64() * 1e3);
        live
    }

    /// Replaces the last relative motion (previous camera → current camera), the
    /// constant-velocity prior of the next frame, when a caller refined the pose.
    pub(crate) fn set_last_motion(&mut self, motion: Iso3) {
        if self.velocity.is_some() {
            self.velocity = Some(motion);
        }
        if let Some(kf) = self.keyframe.as_mut() {
            kf.recompose(&motion);
        }
    }

    /// Lends out the previous tracked live frame's pyramid (give it back with
    /// [`IcpRgb::restore_previous`] before the next frame).
    pub(crate) fn take_previous(&mut self) -> Option<Vec<Level>> {
        self.previous.take()
    }

    /// Returns the pyramid [`IcpRgb::take_previous`] lent out.
    pub(crate) fn restore_previous(&mut self, pyramid: Vec<Level>) {
        self.previous = Some(pyramid);
    }

    /// The light model that relights the photometric term, if one was loaded.
    pub(crate) fn light(&self) -> Option<&LightModel> {
        self.light.as_ref().map(|l| &l.model)
    }

    /// The previous tracked live frame's finest level (the photometric reference).
    pub(crate) fn previous_level0(&self) -> Option<&Level> {
        self.previous.as_ref().and_then(|p| p.first())
    }
}

register!(Tracker, IcpRgb);

#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_references;
#[cfg(test)]
mod tests_unseen;
