//! The pipeline: runs the stages of one frame in order and owns the state between frames
//! (last trusted pose, model prediction, trajectory). Stages never call each other.
//!
//! ```text
//! CameraFrame ─► Preprocessor* ─► DepthEstimator ─► RgbdFrame ─► Tracker ─► pose
//!                                                      │           ▲   (prediction of the
//!                                                      │           │    active model)
//!                      LoopCloser (active vs inactive) ◄┤           │
//!                        └─► Deformation ─► Fuser.deform, trajectory warp
//!                                                      ▼           │
//!                                                    Fuser.fuse ─► Fuser.predict(Active)
//! ```

mod front;
pub mod record;

use std::time::Instant;

use crate::camera::Rig;
use crate::config::validate::validate;
use crate::config::{Config, InitialPose};
use crate::context::{Context, StageReport};
use crate::deformation::Deformation;
use crate::error::{ConfigError, ConfigProblem, PipelineError, StageError};
use crate::frame::{CameraFrame, DepthSource, RgbdFrame};
use crate::geometry::{Iso3, StampedPose};
use crate::map::{MapStats, ModelSet, ModelView, SurfelSet};
use crate::registry::{BuildEnv, BuildError, Registry, Stage};
use crate::stage::{DepthEstimator, Fuser, LoopCloser, LoopInput, Preprocessor, TrackResult, TrackStatus, Tracker};

use front::{Ahead, Front, Pending, Prepared};
pub use record::{FrameRecord, StageTimes};
use record::{ms_since, report, stage_err};

/// The built stages, each with its registry name.
pub struct Stages {
    /// Preprocessors in order.
    pub preprocessors: Vec<(String, Box<dyn Preprocessor>)>,
    /// Depth estimator.
    pub depth: (String, Box<dyn DepthEstimator>),
    /// Tracker.
    pub tracker: (String, Box<dyn Tracker>),
    /// Fuser.
    pub fuser: (String, Box<dyn Fuser>),
    /// Loop closer, if any.
    pub loop_closer: Option<(String, Box<dyn LoopCloser>)>,
}

/// A configured pipeline and its state between frames.
pub struct Pipeline {
    stages: Stages,
    rig: Rig,
    initial_pose: InitialPose,
    resolved: Config,
    t_world_last: Option<Iso3>,
    prediction: Option<ModelView>,
    trajectory: Vec<StampedPose>,
    loop_closures: usize,
    keep_last: bool,
    /// The last frame, kept for an observer when asked ([`Pipeline::keep_last_frame`]).
    last: Option<LastFrame>,
    /// The frame pushed last, not processed yet ([`Pipeline::push`]).
    pending: Option<Pending>,
    /// Whether the map's σ was raised to a noise the tracker measured ([`Fuser::raise_sigma`]).
    map_sigma_raised: bool,
}

/// The last processed frame as the stages saw it, kept for an observer (a recording of the
/// run) when [`Pipeline::keep_last_frame`] asked for it.
pub struct LastFrame {
    /// The reference view's image as it came in, before the preprocessors.
    pub input: crate::image::Rgb8,
    /// The frame after the preprocessors and the depth stage (its image, depth and masks).
    pub frame: RgbdFrame,
}

impl Pipeline {
    /// The configuration a pipeline built from `config` for a rig of `kind` records as its
    /// resolved one (every selected plugin's defaults filled in), without building a stage:
    /// what `compare` checks a finished run against.
    pub fn resolve(config: &Config, source_name: &str, registry: &Registry, kind: crate::camera::ViewKind) -> Result<Config, ConfigError> {
        let mut resolved = config.clone();
        resolved.plugins = validate(config, registry, kind, source_name)?;
        Ok(resolved)
    }

    /// Validates the whole config against the registry and the rig, then builds every stage.
    /// Every problem (config or plugin constructor) is reported at once.
    pub fn build(config: &Config, source_name: &str, registry: &Registry, env: &BuildEnv) -> Result<Self, ConfigError> {
        let resolved = Self::resolve(config, source_name, registry, env.rig.kind())?;
        let resolved_tables = &resolved.plugins;
        let mut problems = Vec::new();
        let mut build = |name: &str, env: &BuildEnv| -> Option<Stage> {
            let entry = registry.get(name)?;
            let table = resolved_tables.get(name).cloned().unwrap_or_default();
            match entry.build(&table, env) {
                Ok(s) => Some(s),
                Err(BuildError::Params(mut p)) => {
                    problems.append(&mut p);
                    None
                }
                Err(BuildError::Stage(e)) => {
                    problems.push(ConfigProblem::new(format!("plugins.{name}"), format!("cannot build `{name}`: {e}"), "fix the cause named above"));
                    None
                }
            }
        };
        let p = &config.pipeline;
        // The depth stage first: the others may fall back to what suits its depth.
        let depth = build(&p.depth, env);
        let env = match &depth {
            Some(Stage::DepthEstimator(d)) => &env.clone().with_depth_source(d.source()),
            _ => env,
        };
        let pre: Vec<_> = p.preprocess.iter().map(|n| (n.clone(), build(n, env))).collect();
        let tracker = build(&p.tracker, env);
        let fuser = build(&p.fuser, env);
        let closer = p.loop_closer().map(|n| (n.to_owned(), build(n, env)));
        let fail = |problems: Vec<ConfigProblem>| ConfigError { source_name: source_name.to_owned(), problems };
        if !problems.is_empty() {
            return Err(fail(problems));
        }
        let mismatch = |key: &str| fail(vec![ConfigProblem::new(key, "registry returned the wrong stage kind", "report this bug")]);
        let mut preprocessors = Vec::new();
        for (n, s) in pre {
            match s {
                Some(Stage::Preprocessor(b)) => preprocessors.push((n, b)),
                _ => return Err(mismatch("pipeline.preprocess")),
            }
        }
        let Some(Stage::DepthEstimator(depth)) = depth else { return Err(mismatch("pipeline.depth")) };
        let Some(Stage::Tracker(tracker)) = tracker else { return Err(mismatch("pipeline.tracker")) };
        let Some(Stage::Fuser(fuser)) = fuser else { return Err(mismatch("pipeline.fuser")) };
        let loop_closer = match closer {
            None => None,
            Some((n, Some(Stage::LoopCloser(b)))) => Some((n, b)),
            Some(_) => return Err(mismatch("pipeline.loop_closer")),
        };
        let stages =
            Stages { preprocessors, depth: (p.depth.clone(), depth), tracker: (p.tracker.clone(), tracker), fuser: (p.fuser.clone(), fuser), loop_closer };
        Ok(Self::from_stages(stages, env.rig.clone(), resolved))
    }

    /// A pipeline from already-built stages (tests, custom assemblies). `config` is recorded
    /// as the resolved configuration; its `[input] initial_pose` is used.
    pub fn from_stages(stages: Stages, rig: Rig, config: Config) -> Self {
        Self {
            stages,
            rig,
            initial_pose: config.input.initial_pose,
            resolved: config,
            t_world_last: None,
            prediction: None,
            trajectory: Vec::new(),
            loop_closures: 0,
            keep_last: false,
            last: None,
            pending: None,
            map_sigma_raised: false,
        }
    }

    /// Keeps the last processed frame (its input image, and the frame after the preprocessors
    /// and the depth stage) for [`Pipeline::last_frame`]: one image copy per frame. Off by
    /// default.
    pub fn keep_last_frame(&mut self, keep: bool) {
        if !keep {
            self.last = None;
        }
        self.keep_last = keep;
    }

    /// The last processed frame, when [`Pipeline::keep_last_frame`] is on.
    pub fn last_frame(&self) -> Option<&LastFrame> {
        self.last.as_ref()
    }

    /// The active model predicted at the last trusted pose (what the next frame is tracked
    /// against), once a frame was fused.
    pub fn prediction(&self) -> Option<&ModelView> {
        self.prediction.as_ref()
    }

    /// The camera rig.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The resolved configuration (defaults of every selected plugin filled in).
    pub fn resolved_config(&self) -> &Config {
        &self.resolved
    }

    /// The trajectory so far, including loop-closure corrections.
    pub fn trajectory(&self) -> &[StampedPose] {
        &self.trajectory
    }

    /// Loop closures applied so far.
    pub fn loop_closures(&self) -> usize {
        self.loop_closures
    }

    /// Whether the depth estimator measures depth or estimates it from the image (a monocular
    /// pipeline's scale is only estimated: it is evaluated with Sim(3) alignment).
    pub fn depth_source(&self) -> DepthSource {
        self.stages.depth.1.source()
    }

    /// Whether the depth, and so the map and the trajectory, are in metres
    /// ([`crate::DepthEstimator::metric_scale`]).
    pub fn metric_scale(&self) -> bool {
        self.stages.depth.1.metric_scale()
    }

    /// Map counts.
    pub fn map_stats(&self) -> MapStats {
        self.stages.fuser.1.stats()
    }

    /// A snapshot of the map.
    pub fn snapshot(&self) -> Result<SurfelSet, StageError> {
        self.stages.fuser.1.snapshot()
    }

    /// The fuser's stable threshold ([`Fuser::stable_confidence`]).
    pub fn stable_confidence(&self) -> Option<f32> {
        self.stages.fuser.1.stable_confidence()
    }

    /// Processes one frame through every stage. Frames handed in with [`Pipeline::push`] and
    /// not yet processed come first: finish them ([`Pipeline::finish`]) before.
    pub fn process(&mut self, frame: CameraFrame) -> Result<FrameRecord, PipelineError> {
        if let Some(p) = &self.pending {
            return Err(PipelineError::Order(format!(
                "frame {} was pushed and is not processed yet, so frame {} cannot go before it: call `finish` before `process`",
                p.index(),
                frame.index
            )));
        }
        self.run_frame(Pending::Raw(Box::new(frame)), None)
    }

    /// Hands in the next frame of a stream; returns the record of the frame pushed before it,
    /// now processed (`None` for the first frame). The pushed frame is prepared beside that
    /// frame's fusion and prediction, on the other cores, as far as no stage needs the
    /// prediction, which does not exist yet: its preprocessing when no preprocessor reads it
    /// ([`crate::Preprocessor::reads_prediction`]), then its depth and the tracker's
    /// [`crate::Tracker::prepare`] when the depth estimator does not either; the rest waits
    /// for its turn. Records, poses and map are those of [`Pipeline::process`] frame by frame.
    /// A frame's `total_ms` is the wall time of the call that processed it, preparing the next
    /// frame included; its own preparation is timed in its preprocess, depth and track times.
    /// On an error the frame pushed with it is dropped too. Call [`Pipeline::finish`] after the
    /// last frame.
    pub fn push(&mut self, frame: CameraFrame) -> Option<Result<FrameRecord, PipelineError>> {
        match self.pending.take() {
            None => {
                self.pending = Some(Pending::Raw(Box::new(frame)));
                None
            }
            Some(current) => Some(self.run_frame(current, Some(frame))),
        }
    }

    /// Processes the last frame handed in with [`Pipeline::push`], if any.
    pub fn finish(&mut self) -> Option<Result<FrameRecord, PipelineError>> {
        self.pending.take().map(|current| self.run_frame(current, None))
    }

    /// Processes `current` (its preparation done unless it is raw), and prepares `next` beside
    /// its fusion when the stages allow it; `next` is then pending.
    fn run_frame(&mut self, current: Pending, next: Option<CameraFrame>) -> Result<FrameRecord, PipelineError> {
        let start = Instant::now();
        let mut front = Front { preprocessors: &mut self.stages.preprocessors, depth: &mut self.stages.depth, rig: &self.rig, keep_last: self.keep_last };
        let prediction = self.prediction.as_ref();
        let Prepared { frame, mut rec, input } = match current {
            Pending::Raw(frame) => front.preprocess_kept(*frame, prediction),
            Pending::Prepared(p) => *p,
        };
        let mut rgbd = match frame? {
            Ahead::Preprocessed(frame) => front.estimate_depth(frame, &mut rec, prediction)?,
            Ahead::Rgbd(rgbd) => rgbd,
        };
        let tr = self.track(&rgbd, &mut rec)?;
        // The noise the tracker found in this depth, where it outweighs the frame's own σ: the
        // map weighs the frame as the tracker did (`Tracker::depth_noise_in_use`).
        let noise = self.stages.tracker.1.depth_noise_in_use();
        if let Some(noise) = &noise {
            noise.raise(&rgbd.depth_m, &mut rgbd.depth_sigma_m, &mut rgbd.depth_sigma_correlation_px);
        }
        let mut pose = tr.t_world_cam;
        let mut next = next.map(|f| Pending::Raw(Box::new(f)));
        if tr.status == TrackStatus::Tracked {
            if let Some(warp) = &tr.warp {
                self.warp_map(rgbd.index, warp, &mut rec)?;
            }
            pose = self.close_loop(&rgbd, pose, &mut rec)?;
            if let Some(noise) = noise.filter(|_| !self.map_sigma_raised) {
                self.raise_map_sigma(&noise, rgbd.index, &pose, &mut rec)?;
            }
            next = self.fuse_and_predict(&rgbd, &pose, &mut rec, next)?;
        }
        self.pending = next;
        rec.t_world_cam = pose;
        rec.map = self.stages.fuser.1.stats();
        self.trajectory.push(StampedPose { timestamp_s: rgbd.timestamp_s, t_world_cam: pose });
        rec.total_ms = ms_since(start);
        self.last = input.map(|input| LastFrame { input, frame: rgbd });
        Ok(rec)
    }

    /// Step 4: the pose, from the last trusted pose (the initial pose before the first).
    fn track(&mut self, rgbd: &RgbdFrame, rec: &mut FrameRecord) -> Result<TrackResult, PipelineError> {
        let t = Instant::now();
        let idx = rgbd.index;
        let prior = match self.t_world_last {
            Some(p) => p,
            None => match (self.initial_pose, rgbd.gt_t_world_cam) {
                (InitialPose::GroundTruth, Some(gt)) => gt,
                _ => Iso3::identity(),
            },
        };
        let prediction = self.prediction.as_ref();
        let (tname, tracker) = &mut self.stages.tracker;
        let mut tr =
            tracker.track(rgbd, prediction, &prior, &mut Context::new(idx, &self.rig, prediction, report(rec, tname))).map_err(|e| stage_err(idx, tname, e))?;
        checked_pose(&mut tr, &prior, report(rec, tname));
        rec.ms.track = ms_since(t);
        rec.status = tr.status;
        rec.inliers = tr.inliers;
        rec.residual_rms = tr.residual_rms;
        rec.tracker_iterations = tr.iterations;
        rec.warp_m = tr.warp.as_ref().map(|w| w.node_displacement_m());
        Ok(tr)
    }

    /// The map fused before the tracker first measured the depth noisier than its σ, raised to
    /// that noise once ([`Fuser::raise_sigma`], timed with the fusion).
    fn raise_map_sigma(&mut self, noise: &crate::depth_noise::DepthNoiseModel, idx: usize, pose: &Iso3, rec: &mut FrameRecord) -> Result<(), PipelineError> {
        let t = Instant::now();
        let (fname, fuser) = &mut self.stages.fuser;
        fuser
            .raise_sigma(noise, pose, &mut Context::new(idx, &self.rig, self.prediction.as_ref(), report(rec, fname)))
            .map_err(|e| stage_err(idx, fname, e))?;
        self.map_sigma_raised = true;
        rec.ms.fuse += ms_since(t);
        Ok(())
    }

    /// Step 4 of a non-rigid tracker: its deformation of the map, applied before anything
    /// else reads the map (timed with the fusion).
    fn warp_map(&mut self, idx: usize, warp: &Deformation, rec: &mut FrameRecord) -> Result<(), PipelineError> {
        let t = Instant::now();
        let (fname, fuser) = &mut self.stages.fuser;
        fuser.warp(warp, &mut Context::new(idx, &self.rig, self.prediction.as_ref(), report(rec, fname))).map_err(|e| stage_err(idx, fname, e))?;
        rec.ms.fuse += ms_since(t);
        Ok(())
    }

    /// Step 6: with a loop closer, the active and inactive models rendered at the tracked pose;
    /// an accepted closure deforms the map and the trajectory. Returns the (corrected) pose.
    fn close_loop(&mut self, rgbd: &RgbdFrame, pose: Iso3, rec: &mut FrameRecord) -> Result<Iso3, PipelineError> {
        let Some((lname, closer)) = &mut self.stages.loop_closer else { return Ok(pose) };
        let t = Instant::now();
        let (idx, rig, prediction) = (rgbd.index, &self.rig, self.prediction.as_ref());
        let (fname, fuser) = &mut self.stages.fuser;
        let mut fctx = StageReport::default();
        let active = fuser.predict(&pose, ModelSet::Active, &mut Context::new(idx, rig, prediction, &mut fctx)).map_err(|e| stage_err(idx, fname, e))?;
        let inactive = fuser.predict(&pose, ModelSet::Inactive, &mut Context::new(idx, rig, prediction, &mut fctx)).map_err(|e| stage_err(idx, fname, e))?;
        let input = LoopInput { frame: rgbd, t_world_cam: &pose, active: &active, inactive: &inactive };
        let closure =
            closer.close(&input, fuser.as_ref(), &mut Context::new(idx, rig, prediction, report(rec, lname))).map_err(|e| stage_err(idx, lname, e))?;
        let mut pose = pose;
        let closure = closure.filter(|c| {
            let finite = is_finite(&c.t_world_cam);
            if !finite {
                report(rec, lname).warnings.push("closure rejected: its corrected pose is not finite".into());
            }
            finite
        });
        if let Some(mut c) = closure {
            c.t_world_cam = crate::geometry::renormalised(c.t_world_cam);
            fuser.deform(&c, &mut Context::new(idx, rig, prediction, &mut fctx)).map_err(|e| stage_err(idx, fname, e))?;
            for (i, p) in self.trajectory.iter_mut().enumerate() {
                p.t_world_cam = c.deformation.warp_pose(&p.t_world_cam, i as u32);
            }
            pose = c.t_world_cam;
            self.loop_closures += 1;
            rec.loop_closed = true;
        }
        merge(report(rec, fname), fctx);
        rec.ms.loop_close = ms_since(t);
        Ok(pose)
    }

    /// Step 5: the frame fused at its pose, then the active model predicted there for the next
    /// frame, which becomes the last trusted pose. Beside it, a raw `next` frame is prepared as far
    /// as no stage reads the prediction: preprocessed when no preprocessor does, its depth
    /// estimated and the tracker's preparation done when the depth estimator does not either.
    /// Returns what is then pending.
    fn fuse_and_predict(&mut self, rgbd: &RgbdFrame, pose: &Iso3, rec: &mut FrameRecord, next: Option<Pending>) -> Result<Option<Pending>, PipelineError> {
        let preprocess_ahead = self.stages.preprocessors.iter().all(|(_, p)| !p.reads_prediction());
        let depth_ahead = preprocess_ahead && !self.stages.depth.1.reads_prediction();
        let Self { stages, rig, prediction, keep_last, .. } = self;
        let Stages { preprocessors, depth, tracker, fuser, .. } = stages;
        let mut fuse = |rec: &mut FrameRecord| fuse_then_predict(fuser, rig, prediction.as_ref(), rgbd, pose, rec);
        let (predicted, next) = match next {
            Some(Pending::Raw(frame)) if preprocess_ahead => {
                let mut front = Front { preprocessors, depth, rig, keep_last: *keep_last };
                let tracker = depth_ahead.then_some(tracker);
                let (predicted, prepared) = rayon::join(|| fuse(rec), || front.prepare_ahead(*frame, tracker));
                (predicted, Some(Pending::Prepared(Box::new(prepared))))
            }
            next => (fuse(rec), next),
        };
        self.prediction = Some(predicted?);
        self.t_world_last = Some(*pose);
        Ok(next)
    }
}

/// Step 5 on the fuser alone: fuses `rgbd` at `pose` and predicts the active model there.
fn fuse_then_predict(
    fuser: &mut (String, Box<dyn Fuser>),
    rig: &Rig,
    prediction: Option<&ModelView>,
    rgbd: &RgbdFrame,
    pose: &Iso3,
    rec: &mut FrameRecord,
) -> Result<ModelView, PipelineError> {
    let idx = rgbd.index;
    let (fname, fuser) = fuser;
    let t = Instant::now();
    rec.fuse = fuser.fuse(rgbd, pose, &mut Context::new(idx, rig, prediction, report(rec, fname))).map_err(|e| stage_err(idx, fname, e))?;
    rec.ms.fuse += ms_since(t);
    let t = Instant::now();
    let next = fuser.predict(pose, ModelSet::Active, &mut Context::new(idx, rig, prediction, report(rec, fname))).map_err(|e| stage_err(idx, fname, e))?;
    rec.ms.predict = ms_since(t);
    Ok(next)
}

/// What the pipeline accepts of a tracker's pose: a non-finite pose is a lost frame at the
/// prior, and a rotation quaternion off unit norm (which would scale the map it is fused into)
/// is renormalised, with a warning beyond rounding.
fn checked_pose(tr: &mut TrackResult, prior: &Iso3, report: &mut StageReport) {
    if !is_finite(&tr.t_world_cam) {
        report.warnings.push("the tracker returned a pose that is not finite: frame marked lost at the previous pose".into());
        tr.t_world_cam = *prior;
        tr.status = TrackStatus::Lost;
        tr.warp = None;
        return;
    }
    let norm = tr.t_world_cam.rotation.quaternion().norm();
    if (norm - 1.0).abs() > 1e-6 {
        report.warnings.push(format!("the tracker's rotation quaternion has norm 1 {:+.2e}: renormalised", norm - 1.0));
    }
    tr.t_world_cam = crate::geometry::renormalised(tr.t_world_cam);
}

fn is_finite(t: &Iso3) -> bool {
    t.translation.vector.iter().chain(t.rotation.coords.iter()).all(|v| v.is_finite())
}

fn merge(into: &mut StageReport, from: StageReport) {
    into.counters.extend(from.counters);
    into.warnings.extend(from.warnings);
}
