//! The output folder of a run: `config.toml` (written first, after a previous run's outputs
//! are removed), `trajectory.txt`, `frames.csv`
//! and `counters.jsonl` (one line per frame, flushed at once, so an interrupted run keeps every
//! finished frame), then `map.ply` and `summary.json` at the end (also after a failure).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use capsule_slam_framework::error::LoadError;
use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_framework::map::SurfelSet;
use capsule_slam_io::{ply, tum};

use crate::summary::{FrameRow, Summary};

/// The immediate effect of each loop closure (with `RunOptions::closure_report`).
pub const CLOSURES_FILE: &str = "closures.csv";

/// Per-frame counters of every stage, one JSON object a line.
pub const COUNTERS_FILE: &str = "counters.jsonl";

/// Every file a run writes into its output folder.
pub const RUN_OUTPUTS: [&str; 8] =
    ["config.toml", "trajectory.txt", "trajectory_online.txt", "frames.csv", COUNTERS_FILE, CLOSURES_FILE, "map.ply", "summary.json"];

/// The folder of a run's pictures (written by the command line, `out/plots/`).
pub const PLOTS_DIR: &str = "plots";

/// Whether `name` is a recording `run --record` writes (a rerun `.rrd` file; the command line
/// may put it into the output folder, and a rerun of the same command replaces it).
pub fn is_run_recording(name: &str) -> bool {
    name.ends_with(".rrd")
}

/// Whether `name` is a picture a run writes into [`PLOTS_DIR`].
fn is_run_plot(name: &str) -> bool {
    name.ends_with(".png") && ["map_", "trajectory_", "ate_over_time"].iter().any(|p| name.starts_with(p))
}

/// The files of a previous run's [`PLOTS_DIR`] in `dir`, or the first file there a run does not
/// write.
fn previous_plots(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let Ok(entries) = std::fs::read_dir(dir.join(PLOTS_DIR)) else { return Ok(Vec::new()) };
    let mut out = Vec::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if !is_run_plot(&name) {
            return Err(format!("{PLOTS_DIR}/{name}"));
        }
        out.push(e.path());
    }
    out.sort();
    Ok(out)
}

/// One line of `counters.jsonl`: `{"frame": N, "plugin.counter": value, ...}` (keys sorted; a
/// non-finite value is written as `null`, as JSON has no NaN).
pub fn counters_line(frame: usize, counters: &BTreeMap<String, f64>) -> String {
    let mut obj = serde_json::Map::new();
    obj.insert("frame".into(), serde_json::Value::from(frame));
    for (k, v) in counters {
        obj.insert(k.clone(), serde_json::Number::from_f64(*v).map_or(serde_json::Value::Null, serde_json::Value::Number));
    }
    serde_json::Value::Object(obj).to_string()
}

/// Writes a run's output folder as the run goes.
pub struct RunWriter {
    dir: PathBuf,
    trajectory: BufWriter<File>,
    frames: BufWriter<File>,
    counters: BufWriter<File>,
    closures: Option<BufWriter<File>>,
}

/// Header of `frames.csv`.
pub const FRAMES_CSV_HEADER: &str = "frame,timestamp_s,status,ms_preprocess,ms_depth,ms_track,ms_loop,ms_fuse,ms_predict,ms_total,surfels_total,surfels_active,surfels_added,surfels_merged,tracker_inliers,tracker_residual,loop_closure,depth_abs_rel,tracker_iterations,warp_mean_mm,warp_max_mm,warp_solver_ms";

impl RunWriter {
    /// Creates the folder and writes `config.toml`; opens the streamed files.
    ///
    /// The folder must hold nothing but a previous run's outputs ([`RUN_OUTPUTS`], its plots
    /// and recordings), which go
    /// first: a run that fails early or is killed never leaves an older run's map and summary
    /// beside its own files (a killed run leaves no `summary.json`). A folder that holds other
    /// files is refused (the error names one), unless `force`, which keeps them.
    pub fn create(dir: &Path, resolved_config: &str) -> Result<Self, LoadError> {
        Self::create_with(dir, resolved_config, false)
    }

    /// [`RunWriter::create`], into a folder that may hold other files when `force`.
    pub fn create_with(dir: &Path, resolved_config: &str, force: bool) -> Result<Self, LoadError> {
        std::fs::create_dir_all(dir).map_err(|e| LoadError::io(dir, e))?;
        let entries = std::fs::read_dir(dir).map_err(|e| LoadError::io(dir, e))?;
        let mut names: Vec<String> = entries.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        let plots = previous_plots(dir);
        let ours = |n: &str| RUN_OUTPUTS.contains(&n) || is_run_recording(n);
        let foreign = names.iter().find(|n| !ours(n) && n.as_str() != PLOTS_DIR).cloned().or(plots.as_ref().err().cloned());
        if let Some(other) = foreign.filter(|_| !force) {
            return Err(LoadError::parse(
                dir,
                0,
                format!("the output folder holds `{other}`, which a run does not write; choose an empty or new --out, or pass --force to write beside it"),
            ));
        }
        for name in names.iter().filter(|n| ours(n)) {
            let p = dir.join(name);
            std::fs::remove_file(&p).map_err(|e| LoadError::io(&p, e))?;
        }
        for p in plots.unwrap_or_default() {
            std::fs::remove_file(&p).map_err(|e| LoadError::io(&p, e))?;
        }
        let cfg = dir.join("config.toml");
        std::fs::write(&cfg, resolved_config).map_err(|e| LoadError::io(&cfg, e))?;
        let open = |name: &str, header: Option<&str>| -> Result<BufWriter<File>, LoadError> {
            let p = dir.join(name);
            let mut f = BufWriter::new(File::create(&p).map_err(|e| LoadError::io(&p, e))?);
            if let Some(header) = header {
                writeln!(f, "{header}").and_then(|()| f.flush()).map_err(|e| LoadError::io(&p, e))?;
            }
            Ok(f)
        };
        Ok(Self {
            dir: dir.to_owned(),
            trajectory: open("trajectory.txt", Some("# timestamp tx ty tz qx qy qz qw"))?,
            frames: open("frames.csv", Some(FRAMES_CSV_HEADER))?,
            counters: open(COUNTERS_FILE, None)?,
            closures: None,
        })
    }

    /// The output folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Appends one frame to `trajectory.txt`, `frames.csv` and `counters.jsonl` and flushes them.
    pub fn write_frame(&mut self, r: &FrameRow) -> Result<(), LoadError> {
        let tp = self.dir.join("trajectory.txt");
        writeln!(self.trajectory, "{}", tum::format_pose(&r.pose)).and_then(|()| self.trajectory.flush()).map_err(|e| LoadError::io(&tp, e))?;
        let ms: Vec<String> = r.ms.iter().map(|(_, v)| format!("{v:.3}")).collect();
        let line = format!(
            "{},{:.6},{},{},{:.3},{},{},{},{},{},{:.6e},{},{},{},{},{}",
            r.index,
            r.pose.timestamp_s,
            r.status,
            ms.join(","),
            r.total_ms,
            r.surfels_total,
            r.surfels_active,
            r.surfels_added,
            r.surfels_merged,
            r.tracker_inliers,
            r.tracker_residual,
            u8::from(r.loop_closure),
            r.depth_abs_rel.map(|a| format!("{a:.5}")).unwrap_or_default(),
            r.tracker_iterations,
            r.warp_mm.map(|(mean, max)| format!("{mean:.4},{max:.4}")).unwrap_or_else(|| ",".to_owned()),
            r.warp_solver_ms.map(|v| format!("{v:.3}")).unwrap_or_default()
        );
        let fp = self.dir.join("frames.csv");
        writeln!(self.frames, "{line}").and_then(|()| self.frames.flush()).map_err(|e| LoadError::io(&fp, e))?;
        let cp = self.dir.join(COUNTERS_FILE);
        writeln!(self.counters, "{}", counters_line(r.index, &r.counters)).and_then(|()| self.counters.flush()).map_err(|e| LoadError::io(&cp, e))
    }

    /// Appends one loop closure's scores just before and just after it to `closures.csv`
    /// (created with its header on the first closure): ATE of the trajectory up to the closure
    /// and the map's surface RMSE, millimetres.
    pub fn write_closure(&mut self, frame: usize, before: &BTreeMap<String, f64>, after: &BTreeMap<String, f64>) -> Result<(), LoadError> {
        let p = self.dir.join(CLOSURES_FILE);
        let f = match &mut self.closures {
            Some(f) => f,
            None => {
                let mut f = BufWriter::new(File::create(&p).map_err(|e| LoadError::io(&p, e))?);
                writeln!(f, "frame,ate_before_mm,ate_after_mm,surface_rmse_before_mm,surface_rmse_after_mm").map_err(|e| LoadError::io(&p, e))?;
                self.closures.insert(f)
            }
        };
        let mm = |m: &BTreeMap<String, f64>, k: &str| m.get(k).map(|v| format!("{:.4}", v * 1e3)).unwrap_or_default();
        let line = format!("{frame},{},{},{},{}", mm(before, "ate_rmse_m"), mm(after, "ate_rmse_m"), mm(before, "surface_rmse_m"), mm(after, "surface_rmse_m"));
        writeln!(f, "{line}").and_then(|()| f.flush()).map_err(|e| LoadError::io(&p, e))
    }

    /// Replaces `trajectory.txt` with a corrected trajectory (after loop closures), keeping the
    /// streamed online estimate as `trajectory_online.txt`.
    pub fn rewrite_trajectory(&mut self, poses: &[StampedPose]) -> Result<(), LoadError> {
        let cur = self.dir.join("trajectory.txt");
        let online = self.dir.join("trajectory_online.txt");
        self.trajectory.flush().map_err(|e| LoadError::io(&cur, e))?;
        std::fs::copy(&cur, &online).map_err(|e| LoadError::io(&online, e))?;
        tum::write_trajectory(&cur, poses)
    }

    /// Writes `map.ply`.
    pub fn write_map(&self, set: &SurfelSet) -> Result<(), LoadError> {
        ply::write_surfels(&self.dir.join("map.ply"), set)
    }

    /// Writes `summary.json`.
    pub fn write_summary(&self, s: &Summary) -> Result<(), LoadError> {
        let p = self.dir.join("summary.json");
        let text = serde_json::to_string_pretty(s).map_err(|e| LoadError::parse(&p, 0, e.to_string()))?;
        std::fs::write(&p, text + "\n").map_err(|e| LoadError::io(&p, e))
    }
}
