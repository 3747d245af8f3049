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

pub mod record;

use std::time::Instant;

use crate::camera::Rig;
use crate::config::validate::validate;
use crate::config::{Config, InitialPose};
use crate::context::{Context, StageReport};
use crate::deformation::Deformation;
use crate::depth_error::depth_error;
use crate::error::{ConfigError, ConfigProblem, PipelineError, StageError};
use crate::frame::{CameraFrame, DepthSource, RgbdFrame, Views};
use crate::geometry::{Iso3, StampedPose};
use crate::map::{MapStats, ModelSet, ModelView, SurfelSet};
use crate::registry::{BuildEnv, BuildError, Registry, Stage};
use crate::stage::{DepthEstimator, Fuser, LoopCloser, LoopInput, Preprocessor, TrackResult, TrackStatus, Tracker};

pub use record::{FrameRecord, StageTimes};

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
}

/// The last processed frame as the stages saw it, kept for an observer (a recording of the
/// run) when [`Pipeline::keep_last_frame`] asked for it.
pub struct LastFrame {
    /// The reference view's image as it came in, before the preprocessors.
    pub input: crate::image::Rgb8,
    /// The frame after the preprocessors and the depth stage (its image, depth and masks).
    pub frame: RgbdFrame,
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
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

    /// Processes one frame through every stage.
    pub fn process(&mut self, mut frame: CameraFrame) -> Result<FrameRecord, PipelineError> {
        let start = Instant::now();
        let mut rec = FrameRecord::new(frame.index, frame.timestamp_s);
        if matches!((&self.rig, &frame.views), (Rig::Stereo { .. }, Views::Mono(_))) {
            return Err(stage_err(frame.index, "input", StageError::invalid_input("the rig is stereo but the frame has one view")));
        }
        let input = self.keep_last.then(|| frame.views.reference().clone());
        self.preprocess(&mut frame, &mut rec)?;
        let rgbd = self.estimate_depth(frame, &mut rec)?;
        let tr = self.track(&rgbd, &mut rec)?;
        let mut pose = tr.t_world_cam;
        if tr.status == TrackStatus::Tracked {
            if let Some(warp) = &tr.warp {
                self.warp_map(rgbd.index, warp, &mut rec)?;
            }
            pose = self.close_loop(&rgbd, pose, &mut rec)?;
            self.fuse_and_predict(&rgbd, &pose, &mut rec)?;
        }
        rec.t_world_cam = pose;
        rec.map = self.stages.fuser.1.stats();
        self.trajectory.push(StampedPose { timestamp_s: rgbd.timestamp_s, t_world_cam: pose });
        rec.total_ms = ms_since(start);
        self.last = input.map(|input| LastFrame { input, frame: rgbd });
        Ok(rec)
    }

    /// Steps 1–2: the preprocessors, in order, on the frame in place.
    fn preprocess(&mut self, frame: &mut CameraFrame, rec: &mut FrameRecord) -> Result<(), PipelineError> {
        let t = Instant::now();
        let idx = frame.index;
        for (name, p) in &mut self.stages.preprocessors {
            p.process(frame, &mut Context::new(idx, &self.rig, self.prediction.as_ref(), report(rec, name))).map_err(|e| stage_err(idx, name, e))?;
        }
        rec.ms.preprocess = ms_since(t);
        Ok(())
    }

    /// Step 3: depth of the reference view, scored against the input's depth when it was
    /// estimated; the frame becomes what the later stages see.
    fn estimate_depth(&mut self, frame: CameraFrame, rec: &mut FrameRecord) -> Result<RgbdFrame, PipelineError> {
        let t = Instant::now();
        let idx = frame.index;
        let (dname, depth) = &mut self.stages.depth;
        let est =
            depth.estimate(&frame, &mut Context::new(idx, &self.rig, self.prediction.as_ref(), report(rec, dname))).map_err(|e| stage_err(idx, dname, e))?;
        rec.ms.depth = ms_since(t);
        if depth.source() == DepthSource::Estimated {
            rec.depth_abs_rel = frame.depth_m.as_ref().and_then(|truth| depth_error(&est.depth_m, truth, false)).map(|e| e.abs_rel);
        }
        let colour = match frame.views {
            Views::Mono(c) => c,
            Views::Stereo { left, .. } => left,
        };
        Ok(RgbdFrame {
            depth_source: depth.source(),
            index: idx,
            timestamp_s: frame.timestamp_s,
            colour,
            depth_m: est.depth_m,
            depth_confidence: est.confidence,
            depth_sigma_m: est.sigma_m,
            depth_sigma_correlation_px: est.sigma_correlation_px,
            photometry: frame.photometry,
            albedo: est.albedo,
            gt_t_world_cam: frame.gt_t_world_cam,
            masks: frame.masks,
            derived: Default::default(),
        })
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
    /// frame, which becomes the last trusted pose.
    fn fuse_and_predict(&mut self, rgbd: &RgbdFrame, pose: &Iso3, rec: &mut FrameRecord) -> Result<(), PipelineError> {
        let (idx, rig, prediction) = (rgbd.index, &self.rig, self.prediction.as_ref());
        let (fname, fuser) = &mut self.stages.fuser;
        let t = Instant::now();
        rec.fuse = fuser.fuse(rgbd, pose, &mut Context::new(idx, rig, prediction, report(rec, fname))).map_err(|e| stage_err(idx, fname, e))?;
        rec.ms.fuse += ms_since(t);
        let t = Instant::now();
        let next = fuser.predict(pose, ModelSet::Active, &mut Context::new(idx, rig, prediction, report(rec, fname))).map_err(|e| stage_err(idx, fname, e))?;
        rec.ms.predict = ms_since(t);
        self.prediction = Some(next);
        self.t_world_last = Some(*pose);
        Ok(())
    }
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

fn report<'r>(rec: &'r mut FrameRecord, name: &str) -> &'r mut StageReport {
    rec.reports.entry(name.to_owned()).or_default()
}

fn merge(into: &mut StageReport, from: StageReport) {
    into.counters.extend(from.counters);
    into.warnings.extend(from.warnings);
}

fn stage_err(frame: usize, stage: &str, source: StageError) -> PipelineError {
    PipelineError::Stage { frame, stage: stage.to_owned(), source }
}
