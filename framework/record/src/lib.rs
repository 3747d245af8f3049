//! A run's recording for the [rerun](https://rerun.io) viewer: an `.rrd` file (file sink only,
//! no viewer and no network) with, per frame, the input image, the image after the
//! preprocessors, the estimated depth, the model's predicted depth and colour, the camera pose,
//! the estimated trajectory so far and a few per-frame figures; every `map_every` frames the
//! surfel map (decimated); the ground-truth trajectory once. Open it with `rerun out.rrd` (the viewer:
//! `pip install rerun-sdk==0.36.3`, which works on this project's machines).
//!
//! Entities (the camera looks along +z, x right, y down, as every camera of this framework):
//!
//! | entity | what | when |
//! |---|---|---|
//! | `world/camera` | `t_world_cam` | every frame |
//! | `world/camera/image` | the reference camera's pinhole | once |
//! | `world/camera/image/{input, preprocessed}` | the image before and after the preprocessors | every frame |
//! | `world/camera/image/depth` | the depth the tracker and the fuser used (16 bits, 0.1 mm steps) | every frame |
//! | `world/camera/image/predicted_{depth, colour}` | the active model rendered at the frame's pose (what the next frame is tracked against) | every frame that was fused |
//! | `world/trajectory/{estimated, ground_truth}` | camera positions, metres | every frame and at the end / once |
//! | `world/map` | surfels (position, colour, radius), at most `max_map_points` | every `map_every` frames and at the end |
//! | `metrics/*` | ms per frame, surfels, tracker residual (mm), warp (mm) | every frame |
//! | `log` | the stages' warnings | when there are some |

mod contents;
mod convert;
mod error;

use std::path::{Path, PathBuf};

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::RgbdFrame;
use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_framework::image::Rgb8;
use capsule_slam_framework::map::{ModelView, SurfelSet};
use capsule_slam_framework::pipeline::FrameRecord;

pub use contents::{Contents, contents};
pub use error::RecordError;

/// How much is recorded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordOptions {
    /// The map every this many frames (and at the end); 0: only at the end.
    pub map_every: usize,
    /// At most this many surfels per map (every k-th surfel of the map's canonical order).
    pub max_map_points: usize,
}

impl Default for RecordOptions {
    fn default() -> Self {
        Self { map_every: 30, max_map_points: 100_000 }
    }
}

/// One processed frame as the pipeline shows it after the frame.
pub struct Step<'a> {
    /// The frame's record (index, pose, status, timings, warnings).
    pub record: &'a FrameRecord,
    /// The reference camera.
    pub camera: &'a PinholeCamera,
    /// The image as it came in, if kept.
    pub input: Option<&'a Rgb8>,
    /// The frame after the preprocessors and the depth stage, if kept.
    pub frame: Option<&'a RgbdFrame>,
    /// The active model predicted at the frame's pose (none before the first fused frame).
    pub prediction: Option<&'a ModelView>,
    /// The trajectory so far.
    pub trajectory: &'a [StampedPose],
}

/// An open recording.
pub struct Recorder {
    stream: rerun::RecordingStream,
    path: PathBuf,
    options: RecordOptions,
    pinhole_logged: bool,
}

/// The timeline every entity is logged on: the frame index.
pub const TIMELINE: &str = "frame";

impl Recorder {
    /// Creates the recording at `path` (replacing a file there).
    pub fn create(path: &Path, options: RecordOptions) -> Result<Self, RecordError> {
        let stream =
            rerun::RecordingStreamBuilder::new("capsule-slam").save(path).map_err(|e| RecordError::Create { path: path.to_owned(), message: e.to_string() })?;
        Ok(Self { stream, path: path.to_owned(), options, pinhole_logged: false })
    }

    /// The recording's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn log(&self, entity: &str, what: &impl rerun::AsComponents) -> Result<(), RecordError> {
        self.stream.log(entity, what).map_err(|e| self.log_error(entity, e))
    }

    fn log_static(&self, entity: &str, what: &impl rerun::AsComponents) -> Result<(), RecordError> {
        self.stream.log_static(entity, what).map_err(|e| self.log_error(entity, e))
    }

    fn log_error(&self, entity: &str, e: impl std::fmt::Display) -> RecordError {
        RecordError::Log { path: self.path.clone(), entity: entity.to_owned(), message: e.to_string() }
    }

    /// The ground-truth trajectory (static: shown at every frame); nothing when it is empty.
    pub fn log_ground_truth(&self, poses: &[StampedPose]) -> Result<(), RecordError> {
        if poses.is_empty() {
            return Ok(());
        }
        self.log_static("world/trajectory/ground_truth", &convert::strip(poses, [90, 200, 90]))
    }

    /// Everything of one frame; the map too on every `map_every`-th frame (`map` is asked for
    /// only then: a snapshot costs a copy of the map).
    pub fn log_step(&mut self, step: &Step<'_>, map: impl FnOnce() -> Option<SurfelSet>) -> Result<(), RecordError> {
        let rec = step.record;
        self.stream.set_time_sequence(TIMELINE, rec.index as i64);
        if !self.pinhole_logged {
            self.log_static("world/camera/image", &convert::pinhole(step.camera))?;
            self.pinhole_logged = true;
        }
        self.log("world/camera", &convert::transform(&rec.t_world_cam))?;
        if let Some(input) = step.input {
            self.log("world/camera/image/input", &convert::rgb(input))?;
        }
        if let Some(frame) = step.frame {
            self.log("world/camera/image/preprocessed", &convert::rgb(&frame.colour))?;
            self.log("world/camera/image/depth", &convert::depth(&frame.depth_m))?;
        }
        if let Some(p) = step.prediction.filter(|p| p.t_world_cam == rec.t_world_cam) {
            self.log("world/camera/image/predicted_depth", &convert::depth(&p.depth_m))?;
            self.log("world/camera/image/predicted_colour", &convert::rgb(&p.colour))?;
        }
        self.log("world/trajectory/estimated", &convert::strip(step.trajectory, [230, 120, 30]))?;
        self.log_figures(rec)?;
        if self.options.map_every > 0
            && rec.index.is_multiple_of(self.options.map_every)
            && let Some(m) = map()
        {
            self.log("world/map", &convert::surfels(&m, self.options.max_map_points))?;
        }
        Ok(())
    }

    fn log_figures(&self, rec: &FrameRecord) -> Result<(), RecordError> {
        self.log("metrics/ms_per_frame", &rerun::Scalars::new([rec.total_ms]))?;
        self.log("metrics/surfels", &rerun::Scalars::new([rec.map.total as f64]))?;
        self.log("metrics/tracker_residual_mm", &rerun::Scalars::new([rec.residual_rms * 1e3]))?;
        if let Some((mean, _)) = rec.warp_m {
            self.log("metrics/warp_mean_mm", &rerun::Scalars::new([mean * 1e3]))?;
        }
        let warnings: Vec<String> = rec.warnings().collect();
        if !warnings.is_empty() {
            let text = warnings.join("\n");
            self.log("log", &rerun::TextLog::new(text).with_level(rerun::TextLogLevel::WARN))?;
        }
        Ok(())
    }

    /// The final trajectory (after any loop closure) and map at the last frame `last_index`,
    /// then the file is completed.
    pub fn finish(self, last_index: usize, trajectory: &[StampedPose], map: Option<&SurfelSet>) -> Result<PathBuf, RecordError> {
        self.stream.set_time_sequence(TIMELINE, last_index as i64);
        self.log("world/trajectory/estimated", &convert::strip(trajectory, [230, 120, 30]))?;
        if let Some(m) = map {
            self.log("world/map", &convert::surfels(m, self.options.max_map_points))?;
        }
        self.stream.flush_blocking().map_err(|e| RecordError::Flush { path: self.path.clone(), message: e.to_string() })?;
        Ok(self.path)
    }
}
