//! The five stage traits. Every stage has one verb of the shape
//! `(&mut self, input, &mut Context) -> Result<Output, StageError>`; outcomes such as tracking
//! loss or "no loop found" are values. Stages never call each other: the
//! [`crate::pipeline::Pipeline`] owns the order and passes each stage what it needs.

use nalgebra::Matrix6;

use crate::camera::ViewKind;
use crate::context::Context;
use crate::deformation::Deformation;
use crate::error::StageError;
use crate::frame::{CameraFrame, RgbdFrame};
use crate::geometry::Iso3;
use crate::image::{DepthMap, GrayF32};
use crate::map::{MapStats, ModelSet, ModelView, SurfelSet};

/// Step 1–2 of the paper: works on the camera images in place (reflection removal, vignetting
/// correction, ...) and may add masks. Mono plugins loop over `frame.views.iter_mut()` and so
/// work on stereo rigs unchanged.
pub trait Preprocessor: Send {
    /// Processes one frame in place.
    fn process(&mut self, frame: &mut CameraFrame, ctx: &mut Context) -> Result<(), StageError>;
    /// Whether processing the next frame reads `ctx.prediction`, the map's prediction that the
    /// pipeline has only once the current frame is fused. A stage that does not may process the
    /// next frame while the current one is fused ([`crate::pipeline::Pipeline::push`]); it then
    /// gets no prediction. `true` (the safe answer) unless the plugin says otherwise.
    fn reads_prediction(&self) -> bool {
        true
    }
}

/// A depth map with an optional per-pixel confidence.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthEstimate {
    /// Depth along z, metres; 0 = invalid.
    pub depth_m: DepthMap,
    /// Confidence in [0, 1] per pixel, if the estimator has one.
    pub confidence: Option<GrayF32>,
    /// σ of the depth per pixel, metres, if the estimator knows its noise
    /// ([`crate::depth_noise`]).
    pub sigma_m: Option<DepthMap>,
    /// Correlation length of the depth error, pixels (0: independent pixels).
    pub sigma_correlation_px: f64,
    /// Albedo per pixel (linear luminance; 0 = none): the observed radiance over the light
    /// model's irradiance on the estimated surface, if the estimator has a light model. The
    /// fuser averages it into the map, and the map's prediction gives it back
    /// ([`ModelView::albedo`]).
    pub albedo: Option<GrayF32>,
}

impl DepthEstimate {
    /// A depth map alone.
    pub fn depth_only(depth_m: DepthMap) -> Self {
        Self { depth_m, confidence: None, albedo: None, sigma_m: None, sigma_correlation_px: 0.0 }
    }
}

/// Step 3: depth of the reference view, from whatever the frame holds (one image by shape
/// from shading, a stereo pair, a sensor). Later stages only see the resulting
/// [`RgbdFrame`], so a stereo estimator changes nothing downstream.
pub trait DepthEstimator: Send {
    /// The views this estimator needs; validation rejects a stereo estimator on a mono rig.
    fn input_kind(&self) -> ViewKind {
        ViewKind::Mono
    }
    /// Whether the depth is measured or estimated (default: estimated).
    fn source(&self) -> crate::frame::DepthSource {
        crate::frame::DepthSource::Estimated
    }
    /// Whether the depth is in metres (default: if it is measured). An estimator whose scale
    /// rests on a calibration says so when it has one (`near-light-sfs` with a `light.toml`);
    /// without, the run's headline figures are Sim(3) and `summary.json` says
    /// `"metric_scale": false`.
    fn metric_scale(&self) -> bool {
        self.source() == crate::frame::DepthSource::Measured
    }
    /// Estimates depth for the frame's reference view. `ctx.prediction` holds the model
    /// prediction at the previous pose, for estimators that use the map (e.g. its albedo).
    fn estimate(&mut self, frame: &CameraFrame, ctx: &mut Context) -> Result<DepthEstimate, StageError>;
    /// Whether estimating the next frame's depth reads `ctx.prediction`
    /// ([`Preprocessor::reads_prediction`]). `true` unless the plugin says otherwise.
    fn reads_prediction(&self) -> bool {
        true
    }
}

/// Whether tracking succeeded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TrackStatus {
    /// The pose is trusted: the frame is fused.
    Tracked,
    /// Tracking failed: the pose is the tracker's best guess, the frame is not fused and the
    /// next frame is tracked from the last trusted pose.
    Lost,
}

impl TrackStatus {
    /// Lower-case name for files.
    pub fn as_str(&self) -> &'static str {
        match self {
            TrackStatus::Tracked => "tracked",
            TrackStatus::Lost => "lost",
        }
    }
}

/// The outcome of tracking one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackResult {
    /// Estimated camera pose.
    pub t_world_cam: Iso3,
    /// Tracked or lost.
    pub status: TrackStatus,
    /// Number of inlier correspondences at the finest level.
    pub inliers: usize,
    /// RMS residual of the final iteration (metres for geometric trackers).
    pub residual_rms: f64,
    /// Covariance of the pose increment (inverse of the final Gauss-Newton Hessian), ordered
    /// translation then rotation, when the tracker has one.
    pub covariance: Option<Matrix6<f64>>,
    /// Gauss-Newton iterations run in total.
    pub iterations: usize,
    /// A deformation of the map estimated with the pose (a non-rigid tracker: the wall moved
    /// since the map saw it). The pipeline applies it to the map ([`Fuser::warp`]) before the
    /// loop closer and the fusion see the map; `None` for a rigid tracker.
    pub warp: Option<Deformation>,
}

impl TrackResult {
    /// A trusted pose with no statistics (oracle trackers).
    pub fn tracked(t_world_cam: Iso3) -> Self {
        Self { t_world_cam, status: TrackStatus::Tracked, inliers: 0, residual_rms: 0.0, covariance: None, iterations: 0, warp: None }
    }
}

/// Step 4: frame-to-model tracking (Eqs. (2)–(4)).
pub trait Tracker: Send {
    /// Estimates the pose of `frame`. `model` is the active-model prediction rendered at
    /// `t_world_prev` (the last trusted pose) after the previous fusion; it is `None` before
    /// the map has anything to show. A tracker that cannot track returns
    /// [`TrackStatus::Lost`], not an error.
    fn track(&mut self, frame: &RgbdFrame, model: Option<&ModelView>, t_world_prev: &Iso3, ctx: &mut Context) -> Result<TrackResult, StageError>;
    /// Work on `frame` that needs neither the map nor a pose (e.g. the live frame's pyramid),
    /// done ahead: the pipeline calls it, when frames are pushed ([`crate::pipeline::Pipeline::push`]),
    /// while the previous frame is fused, and the next [`Tracker::track`] is of this frame.
    /// Tracking must give the same result with it as without. Nothing by default.
    fn prepare(&mut self, frame: &RgbdFrame, ctx: &mut Context) {
        let _ = (frame, ctx);
    }
    /// The depth noise the last [`Tracker::track`] weighed its frame by, where that was more
    /// than the frame's own σ: a tracker that measures the depth's error against the model
    /// (`icp-rgb`'s `depth_error_factor`) and found the declared σ too small. The pipeline
    /// raises the frame's σ to it ([`crate::depth_noise::DepthNoiseModel::raise`]) before the
    /// fuser weighs the frame, so that map and tracker read the same noise. None by default:
    /// the frame's σ stands.
    fn depth_noise_in_use(&self) -> Option<crate::depth_noise::DepthNoiseModel> {
        None
    }
}

/// Counts from fusing one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FuseStats {
    /// Measurements merged into existing surfels.
    pub merged: usize,
    /// New surfels.
    pub added: usize,
    /// Surfels removed (stale unstable ones, free-space violations).
    pub removed: usize,
}

/// Step 5: the surfel map. A fuser owns its map wherever it likes (host memory, a GPU buffer);
/// the rest of the system sees it only through predictions, statistics and explicit
/// [`Fuser::snapshot`]s, so a GPU fuser never copies its map back per frame.
pub trait Fuser: Send {
    /// Fuses a tracked frame at pose `t_world_cam`.
    fn fuse(&mut self, frame: &RgbdFrame, t_world_cam: &Iso3, ctx: &mut Context) -> Result<FuseStats, StageError>;
    /// Renders the active or inactive stable model from `t_world_cam` with the rig's
    /// reference camera (`ctx.rig`).
    fn predict(&mut self, t_world_cam: &Iso3, set: ModelSet, ctx: &mut Context) -> Result<ModelView, StageError>;
    /// Applies a loop closure: deforms every surfel (positions and normals) and reactivates
    /// the matched inactive surfels seen from `closure.t_world_cam`.
    fn deform(&mut self, closure: &LoopClosure, ctx: &mut Context) -> Result<(), StageError>;
    /// Moves every surfel (positions and normals) by a tracker's deformation of the map
    /// ([`TrackResult::warp`]), so that the map follows a moving wall. A fuser that cannot
    /// returns the default error, which stops a run whose tracker deforms.
    fn warp(&mut self, deformation: &Deformation, ctx: &mut Context) -> Result<(), StageError> {
        let _ = (deformation, ctx);
        Err(StageError::invalid_input(
            "this fuser cannot deform its map: choose a fuser that follows a deforming wall (surfel-cpu, surfel-gpu) or a rigid tracker",
        ))
    }
    /// Raises every surfel's σ to `noise`'s σ at its depth in the camera `t_world_cam` where
    /// that is larger: the map fused before a tracker measured the depth to be noisier than its
    /// σ said ([`Tracker::depth_noise_in_use`]; the pipeline calls this once, at the first
    /// frame that reports it, before fusing that frame), so that those surfels do not outweigh
    /// every later measurement. By default the map keeps its σ, with a warning.
    fn raise_sigma(&mut self, noise: &crate::depth_noise::DepthNoiseModel, t_world_cam: &Iso3, ctx: &mut Context) -> Result<(), StageError> {
        let _ = t_world_cam;
        ctx.warn(format!(
            "the depth is noisier than its σ said (a relative σ of {:.1} % measured), but this fuser keeps the σ its surfels were fused with: they outweigh later frames",
            100.0 * noise.relative
        ));
        Ok(())
    }
    /// Surfel counts (cheap: called every frame).
    fn stats(&self) -> MapStats;
    /// An exported copy of the whole map in canonical order (for output and tests; may be
    /// expensive).
    fn snapshot(&self) -> Result<SurfelSet, StageError>;
    /// The time window δt at the map's current frame, in frames: a surfel last seen more than
    /// δt frames ago is inactive (`None`: this fuser keeps every surfel active). It may change
    /// from frame to frame (the surfel fusers shorten it while a tracker's warp says the wall
    /// moves). A loop closer uses it to tell the two models apart in a snapshot.
    fn active_window(&self) -> Option<u32> {
        None
    }
    /// The confidence from which a surfel is stable: seen often enough to be predicted and
    /// written (ElasticFusion's `confThreshold`; its PLY export keeps only such surfels).
    /// `None`: this fuser counts every surfel as stable.
    fn stable_confidence(&self) -> Option<f32> {
        None
    }
}

/// What a loop closer gets each frame.
#[derive(Debug, Clone, Copy)]
pub struct LoopInput<'a> {
    /// The current frame.
    pub frame: &'a RgbdFrame,
    /// The tracked pose of the frame.
    pub t_world_cam: &'a Iso3,
    /// The active model rendered at that pose.
    pub active: &'a ModelView,
    /// The inactive model rendered at that pose.
    pub inactive: &'a ModelView,
}

/// An accepted loop closure.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopClosure {
    /// The non-rigid correction of the map and of the trajectory.
    pub deformation: Deformation,
    /// The corrected pose of the current frame.
    pub t_world_cam: Iso3,
}

/// Step 6: local loop closure between the active and the inactive model. It reads the map
/// (`map` is shared, not mutable) and returns a deformation for the pipeline to apply, or
/// `None` when no loop is found.
pub trait LoopCloser: Send {
    /// Looks for a loop at this frame.
    fn close(&mut self, input: &LoopInput<'_>, map: &dyn Fuser, ctx: &mut Context) -> Result<Option<LoopClosure>, StageError>;
}
