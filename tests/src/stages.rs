//! Test-only stages that prove the pipeline runner end to end. They are deliberately simple
//! but real: the point fuser keeps every fused pixel as a surfel and renders them with a
//! z-buffer; the shift closer returns a known rigid deformation at a chosen frame; the probe
//! tells what a preprocessor was given.

use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
use capsule_slam_framework::map::MapStats;
use capsule_slam_framework::registry::{BuildEnv, PluginEntry};
use capsule_slam_framework::stage::{FuseStats, LoopClosure, LoopInput};
use capsule_slam_framework::{
    CameraFrame, Context, DepthEstimate, DepthEstimator, Fuser, Iso3, LoopCloser, ModelSet, ModelView, Plugin, Preprocessor, RgbdFrame, StageError, Surfel,
    SurfelSet, TrackResult, Tracker, ViewKind,
};
use nalgebra::Vector3;

capsule_slam_framework::plugin_params! {
    /// Parameters of the test point fuser.
    pub struct PointFuserParams {
        /// Keep every n-th pixel in x and y.
        pub stride: u32 = 4; unit = "px"; range = 1.0..=64.0;
        /// Active window, frames.
        pub delta_t: u32 = 200; unit = "frames"; range = 1.0..=100000.0;
    }
}

/// Keeps every `stride`-th pixel of every fused frame as a surfel.
pub struct PointFuser {
    params: PointFuserParams,
    surfels: Vec<Surfel>,
    now: u32,
}

impl Plugin for PointFuser {
    const NAME: &'static str = "test-points";
    const SUMMARY: &'static str = "test only: every n-th pixel becomes a surfel";
    type Params = PointFuserParams;
    fn build(params: PointFuserParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self { params, surfels: Vec::new(), now: 0 })
    }
}

impl Fuser for PointFuser {
    fn fuse(&mut self, frame: &RgbdFrame, t_world_cam: &Iso3, ctx: &mut Context) -> Result<FuseStats, StageError> {
        let cam = ctx.rig.camera();
        let s = self.params.stride as usize;
        self.now = frame.index as u32;
        let mut added = 0;
        for y in (0..frame.depth_m.height()).step_by(s) {
            for x in (0..frame.depth_m.width()).step_by(s) {
                if !frame.usable(x, y) {
                    continue;
                }
                let p = t_world_cam * cam.unproject(x as f64, y as f64, f64::from(frame.depth_m.at(x, y)));
                let n = t_world_cam.rotation * Vector3::new(0.0, 0.0, -1.0);
                self.surfels.push(Surfel {
                    position_m: p.cast(),
                    normal: n.cast(),
                    colour: frame.colour.pixel(x, y),
                    confidence: 1.0,
                    radius_m: 1e-3,
                    t0: self.now,
                    t: self.now,
                    albedo: 0.0,
                    sigma_m: 0.0,
                    warp_m: Vector3::zeros(),
                });
                added += 1;
            }
        }
        ctx.count("added", added as f64);
        Ok(FuseStats { merged: 0, added, removed: 0 })
    }

    fn predict(&mut self, t_world_cam: &Iso3, set: ModelSet, ctx: &mut Context) -> Result<ModelView, StageError> {
        let cam = ctx.rig.camera();
        let mut view = ModelView::empty(cam.width, cam.height, *t_world_cam);
        let t_cam_world = t_world_cam.inverse();
        let now = ctx.frame_index as u32;
        for s in &self.surfels {
            if s.is_active(now, self.params.delta_t) != (set == ModelSet::Active) {
                continue;
            }
            let pc = t_cam_world * s.position_m.cast::<f64>();
            let Some(uv) = cam.project(&pc) else { continue };
            let (u, v) = (uv.x.round() as i64, uv.y.round() as i64);
            if !view.depth_m.contains(u, v) {
                continue;
            }
            let (u, v) = (u as usize, v as usize);
            let z = view.depth_m.at(u, v);
            if z == 0.0 || (pc.z as f32) < z {
                *view.depth_m.at_mut(u, v) = pc.z as f32;
                view.colour.set_pixel(u, v, s.colour);
                *view.confidence.at_mut(u, v) = s.confidence;
            }
        }
        Ok(view)
    }

    fn deform(&mut self, closure: &LoopClosure, _ctx: &mut Context) -> Result<(), StageError> {
        for s in &mut self.surfels {
            closure.deformation.warp_surfel(s);
        }
        Ok(())
    }

    fn stats(&self) -> MapStats {
        let active = self.surfels.iter().filter(|s| s.is_active(self.now, self.params.delta_t)).count();
        MapStats { total: self.surfels.len(), active, stable: self.surfels.len() }
    }

    fn snapshot(&self) -> Result<SurfelSet, StageError> {
        Ok(SurfelSet::new(self.surfels.clone()))
    }

    fn active_window(&self) -> Option<u32> {
        Some(self.params.delta_t)
    }
}

capsule_slam_framework::plugin_params! {
    /// Parameters of the test shift closer.
    pub struct ShiftCloserParams {
        /// The frame at which the closure fires.
        pub at_frame: u32 = 5; unit = "frame"; range = 0.0..=1.0e9;
        /// Translation applied to the whole map and trajectory, metres.
        pub shift_m: Vec<f64> = vec![0.0, 0.0, 0.01]; unit = "m";
    }
}

/// Returns, once, a rigid translation of everything by `shift_m`.
pub struct ShiftCloser {
    params: ShiftCloserParams,
}

impl Plugin for ShiftCloser {
    const NAME: &'static str = "test-shift";
    const SUMMARY: &'static str = "test only: a known rigid shift at one frame";
    type Params = ShiftCloserParams;
    fn build(params: ShiftCloserParams, _env: &BuildEnv) -> Result<Self, StageError> {
        if params.shift_m.len() != 3 {
            return Err(StageError::invalid_input("shift_m needs 3 values"));
        }
        Ok(Self { params })
    }
}

impl LoopCloser for ShiftCloser {
    fn close(&mut self, input: &LoopInput<'_>, map: &dyn Fuser, _ctx: &mut Context) -> Result<Option<LoopClosure>, StageError> {
        if input.frame.index as u32 != self.params.at_frame {
            return Ok(None);
        }
        let shift = Vector3::new(self.params.shift_m[0], self.params.shift_m[1], self.params.shift_m[2]);
        let snap = map.snapshot()?;
        let step = (snap.len() / 16).max(1);
        let nodes = snap
            .surfels
            .iter()
            .step_by(step)
            .map(|s| DeformationNode { translation_m: shift, ..DeformationNode::identity(s.position_m.cast(), s.t0) })
            .collect();
        let t_world_cam = Iso3::from_parts((input.t_world_cam.translation.vector + shift).into(), input.t_world_cam.rotation);
        Ok(Some(LoopClosure { deformation: Deformation::new(nodes, 4, Window::All), t_world_cam }))
    }
}

capsule_slam_framework::plugin_params! {
    /// Parameters of the test warping tracker.
    pub struct WarpTrackerParams {
        /// Translation of the whole map per tracked frame, metres.
        pub shift_m: Vec<f64> = vec![0.0, 0.0, 0.0001]; unit = "m";
        /// Relative depth σ the tracker says it weighed every frame by
        /// (`Tracker::depth_noise_in_use`; 0: none).
        pub noise_relative: f64 = 0.0; unit = "-"; range = 0.0..=1.0;
        /// The first frame it says so.
        pub noise_from_frame: u32 = 0; unit = "frame"; range = 0.0..=1.0e9;
    }
}

/// Tracks by the frame's ground-truth pose and returns, every frame after the first, a warp that
/// translates the whole map by `shift_m`: a known non-rigid tracker's output, for the pipeline.
pub struct WarpTracker {
    params: WarpTrackerParams,
    /// The frame tracked last.
    index: usize,
}

impl Plugin for WarpTracker {
    const NAME: &'static str = "test-warp";
    const SUMMARY: &'static str = "test only: ground-truth pose and a known warp of the map";
    type Params = WarpTrackerParams;
    fn build(params: WarpTrackerParams, _env: &BuildEnv) -> Result<Self, StageError> {
        if params.shift_m.len() != 3 {
            return Err(StageError::invalid_input("shift_m needs 3 values"));
        }
        Ok(Self { params, index: 0 })
    }
}

impl Tracker for WarpTracker {
    fn track(&mut self, frame: &RgbdFrame, model: Option<&ModelView>, _t_world_prev: &Iso3, _ctx: &mut Context) -> Result<TrackResult, StageError> {
        self.index = frame.index;
        let pose = frame.gt_t_world_cam.ok_or_else(|| StageError::invalid_input("test-warp needs ground truth"))?;
        let mut result = TrackResult::tracked(pose);
        if model.is_some() {
            let shift = Vector3::new(self.params.shift_m[0], self.params.shift_m[1], self.params.shift_m[2]);
            let node = DeformationNode { translation_m: shift, ..DeformationNode::identity(pose.translation.vector.into(), 0) };
            result.warp = Some(Deformation::new(vec![node], 1, Window::All));
        }
        Ok(result)
    }

    fn depth_noise_in_use(&self) -> Option<capsule_slam_framework::depth_noise::DepthNoiseModel> {
        let relative = self.params.noise_relative;
        (relative > 0.0 && self.index >= self.params.noise_from_frame as usize).then_some(capsule_slam_framework::depth_noise::DepthNoiseModel {
            absolute_m: 0.0,
            relative,
            quadratic_per_m: 0.0,
            correlation_px: 0.0,
        })
    }
}

capsule_slam_framework::plugin_params! {
    /// Parameters of the test bad-pose tracker.
    pub struct BadPoseParams {
        /// Factor on the ground-truth rotation quaternion (1: a true rotation).
        pub quaternion_scale: f64 = 1.0; unit = "-"; range = 0.0..=10.0;
        /// The frame whose pose is NaN.
        pub nan_at_frame: u32 = 1000000; unit = "frame"; range = 0.0..=1.0e9;
    }
}

/// Tracks by the ground-truth pose but returns it with a rotation quaternion scaled off unit
/// norm, and a NaN pose at one frame: what a buggy plugin may hand the pipeline.
pub struct BadPoseTracker {
    params: BadPoseParams,
}

impl Plugin for BadPoseTracker {
    const NAME: &'static str = "test-bad-pose";
    const SUMMARY: &'static str = "test only: ground-truth pose with a non-unit quaternion, and a NaN pose at one frame";
    type Params = BadPoseParams;
    fn build(params: BadPoseParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self { params })
    }
}

impl Tracker for BadPoseTracker {
    fn track(&mut self, frame: &RgbdFrame, _model: Option<&ModelView>, _t_world_prev: &Iso3, _ctx: &mut Context) -> Result<TrackResult, StageError> {
        let pose = frame.gt_t_world_cam.ok_or_else(|| StageError::invalid_input("test-bad-pose needs ground truth"))?;
        if frame.index as u32 == self.params.nan_at_frame {
            return Ok(TrackResult::tracked(Iso3::translation(f64::NAN, 0.0, 0.0)));
        }
        let q = nalgebra::Unit::new_unchecked(pose.rotation.into_inner() * self.params.quaternion_scale);
        Ok(TrackResult::tracked(Iso3::from_parts(pose.translation, q)))
    }
}

capsule_slam_framework::plugin_params! {
    /// Parameters of the test prediction probe.
    pub struct ProbeParams {
        /// What it answers to `reads_prediction`.
        pub reads_prediction: bool = false; unit = "-";
        /// The frame it fails on.
        pub fail_at_frame: u32 = 1000000; unit = "frame"; range = 0.0..=1.0e9;
    }
}

/// A preprocessor that leaves the frame alone and counts, per frame, whether it was given the
/// map's prediction (`saw_prediction`) and the index of the frame it processed last before
/// this one (`previous_frame`, −1 for none); it fails at `fail_at_frame`.
pub struct PredictionProbe {
    params: ProbeParams,
    previous: Option<usize>,
}

impl Plugin for PredictionProbe {
    const NAME: &'static str = "test-probe";
    const SUMMARY: &'static str = "test only: tells whether a preprocessor was given the prediction";
    type Params = ProbeParams;
    fn build(params: ProbeParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self { params, previous: None })
    }
}

impl Preprocessor for PredictionProbe {
    fn process(&mut self, frame: &mut CameraFrame, ctx: &mut Context) -> Result<(), StageError> {
        if frame.index as u32 == self.params.fail_at_frame {
            return Err(StageError::invalid_input(format!("test-probe fails at frame {}", frame.index)));
        }
        ctx.count("saw_prediction", if ctx.prediction.is_some() { 1.0 } else { 0.0 });
        ctx.count("previous_frame", self.previous.map_or(-1.0, |p| p as f64));
        self.previous = Some(frame.index);
        Ok(())
    }

    fn reads_prediction(&self) -> bool {
        self.params.reads_prediction
    }
}

/// A stereo-only depth estimator, to test rig validation.
pub struct StereoOnly;

capsule_slam_framework::plugin_params! {
    /// No parameters.
    pub struct NoParams {}
}

impl Plugin for StereoOnly {
    const NAME: &'static str = "test-stereo";
    const SUMMARY: &'static str = "test only: claims to need a stereo pair";
    const VIEWS: ViewKind = ViewKind::Stereo;
    type Params = NoParams;
    fn build(_p: NoParams, _env: &BuildEnv) -> Result<Self, StageError> {
        Ok(Self)
    }
}

impl DepthEstimator for StereoOnly {
    fn input_kind(&self) -> ViewKind {
        ViewKind::Stereo
    }
    fn estimate(&mut self, frame: &CameraFrame, _ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        frame.depth_m.clone().map(DepthEstimate::depth_only).ok_or_else(|| StageError::invalid_input("no depth"))
    }
}

/// The registry of every linked plugin plus the test-only stages.
pub fn test_registry() -> capsule_slam_framework::Registry {
    capsule_slam_plugins::link();
    let mut r = capsule_slam_framework::Registry::from_inventory().expect("inventory registry");
    r.register(PluginEntry::fuser::<PointFuser>()).expect("register test-points");
    r.register(PluginEntry::loop_closer::<ShiftCloser>()).expect("register test-shift");
    r.register(PluginEntry::depth_estimator::<StereoOnly>()).expect("register test-stereo");
    r.register(PluginEntry::tracker::<WarpTracker>()).expect("register test-warp");
    r.register(PluginEntry::tracker::<BadPoseTracker>()).expect("register test-bad-pose");
    r.register(PluginEntry::preprocessor::<PredictionProbe>()).expect("register test-probe");
    r
}
