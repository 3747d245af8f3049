//! `run --record FILE.rrd`: a recording of the run for the rerun viewer (`capsule-slam-record`,
//! cargo feature `record`). A recording that fails mid-run stops with a warning; the run goes on.

use std::path::{Path, PathBuf};

use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_framework::map::SurfelSet;
use capsule_slam_framework::pipeline::{FrameRecord, Pipeline};

/// The recording's command-line options.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct RecordArgs {
    /// Write a recording of the run for the rerun viewer (open it with `rerun FILE.rrd`): per
    /// frame the input image, the preprocessed image, the depth, the model's predicted depth
    /// and colour, the pose, the trajectory and figures; the surfel map every
    /// --record-map-every frames. Needs a build with `--features record`.
    #[arg(long, value_name = "FILE.rrd")]
    pub record: Option<PathBuf>,
    /// The map in the recording every this many frames (0: at the end only).
    #[arg(long, value_name = "N", default_value_t = 30)]
    pub record_map_every: usize,
    /// At most this many surfels per recorded map (every k-th surfel).
    #[arg(long, value_name = "N", default_value_t = 100_000)]
    pub record_max_points: usize,
}

/// An open recording, or the reason it stopped.
pub struct Recording {
    #[cfg(feature = "record")]
    recorder: Option<capsule_slam_record::Recorder>,
    path: PathBuf,
    stopped: Option<String>,
}

impl Recording {
    /// What is wrong with `args` before anything is written: a file name that does not end in
    /// `.rrd`, or a build without the `record` feature.
    pub fn check(args: &RecordArgs) -> anyhow::Result<()> {
        let Some(path) = &args.record else { return Ok(()) };
        if path.extension().is_none_or(|e| e != "rrd") {
            anyhow::bail!("--record {}: a rerun recording's file name ends in `.rrd` (e.g. --record out/run.rrd)", path.display());
        }
        if !cfg!(feature = "record") {
            anyhow::bail!(
                "--record {}: this build has no recording; build with the `record` feature (`cargo run --release -p capsule-slam --features record -- run --record ...`)",
                path.display()
            );
        }
        Ok(())
    }

    /// Opens the recording `args` asks for (none without `--record`), after [`Recording::check`].
    pub fn open(args: &RecordArgs, ground_truth: &[StampedPose]) -> anyhow::Result<Option<Self>> {
        Self::check(args)?;
        let Some(path) = &args.record else { return Ok(None) };
        Self::create(args, path, ground_truth).map(Some)
    }

    #[cfg(feature = "record")]
    fn create(args: &RecordArgs, path: &Path, ground_truth: &[StampedPose]) -> anyhow::Result<Self> {
        let options = capsule_slam_record::RecordOptions { map_every: args.record_map_every, max_map_points: args.record_max_points };
        let recorder = capsule_slam_record::Recorder::create(path, options)?;
        recorder.log_ground_truth(ground_truth)?;
        Ok(Self { recorder: Some(recorder), path: path.to_owned(), stopped: None })
    }

    #[cfg(not(feature = "record"))]
    fn create(_: &RecordArgs, path: &Path, _: &[StampedPose]) -> anyhow::Result<Self> {
        Ok(Self { path: path.to_owned(), stopped: Some("this build has no `record` feature".into()) })
    }

    /// Whether the pipeline must keep each frame's images for the recording.
    pub fn wants_frames(&self) -> bool {
        self.stopped.is_none()
    }

    /// Logs one processed frame; the first failure stops the recording with a warning.
    #[cfg(feature = "record")]
    pub fn observe(&mut self, rec: &FrameRecord, pipeline: &Pipeline) {
        let Some(recorder) = self.recorder.as_mut() else { return };
        let last = pipeline.last_frame();
        let step = capsule_slam_record::Step {
            record: rec,
            camera: pipeline.rig().camera(),
            input: last.map(|l| &l.input),
            frame: last.map(|l| &l.frame),
            prediction: pipeline.prediction(),
            trajectory: pipeline.trajectory(),
        };
        if let Err(e) = recorder.log_step(&step, || pipeline.snapshot().ok()) {
            eprintln!("warning: the recording stopped at frame {}: {e}", rec.index);
            self.stopped = Some(format!("stopped at frame {}: {e}", rec.index));
            self.recorder = None;
        }
    }

    /// Without the `record` feature there is never an open recording.
    #[cfg(not(feature = "record"))]
    pub fn observe(&mut self, _: &FrameRecord, _: &Pipeline) {}

    /// Logs the final trajectory and map (the run's last snapshot) at the last frame and
    /// completes the file.
    #[cfg(feature = "record")]
    pub fn finish(mut self, trajectory: &[StampedPose], map: Option<&SurfelSet>) -> anyhow::Result<PathBuf> {
        if let Some(why) = self.stopped.take() {
            anyhow::bail!("the recording {} is incomplete: {why}", self.path.display());
        }
        let Some(recorder) = self.recorder.take() else { anyhow::bail!("the recording {} was not opened", self.path.display()) };
        Ok(recorder.finish(trajectory.len().saturating_sub(1), trajectory, map)?)
    }

    /// Without the `record` feature there is never an open recording.
    #[cfg(not(feature = "record"))]
    pub fn finish(self, _: &[StampedPose], _: Option<&SurfelSet>) -> anyhow::Result<PathBuf> {
        anyhow::bail!("the recording {} was not opened (this build has no `record` feature)", self.path.display())
    }
}
