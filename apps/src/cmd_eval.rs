//! `capsule-slam eval`: trajectory (and surface) error of an estimate against ground truth.

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use capsule_slam_eval::report::{EvalOptions, evaluate, evaluate_live, evaluate_warp, table};
use capsule_slam_eval::rpe::Delta;
use capsule_slam_eval::{align_trajectory, associate};
use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_io::{ply, tum};

/// Arguments of `eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Ground-truth trajectory (TUM format).
    #[arg(long)]
    gt: PathBuf,
    /// Estimated trajectory (TUM format).
    #[arg(long)]
    est: PathBuf,
    /// Alignment of the headline figures: se3 (RGB-D) or sim3 (monocular, up to scale).
    #[arg(long, default_value = "se3")]
    align: String,
    /// RPE pair spacing in frames.
    #[arg(long, default_value_t = 1)]
    rpe_delta: usize,
    /// RPE pair spacing as travelled path in metres (instead of frames).
    #[arg(long)]
    rpe_delta_m: Option<f64>,
    /// Timestamp association tolerance, seconds.
    #[arg(long, default_value_t = 0.02)]
    tolerance: f64,
    /// Ground-truth surface (PLY) for the surface error; needs --map.
    #[arg(long)]
    surface_gt: Option<PathBuf>,
    /// Reconstructed map (PLY).
    #[arg(long)]
    map: Option<PathBuf>,
    /// The true surface at the last frame (PLY, e.g. a phantom's `gt_surface_NNNNNN.ply`) for
    /// the live surface error: the map's surfels seen in the last 30 frames, moved by the
    /// trajectory alignment, against it; needs --map. With --surface-gt, also the warp error
    /// against the wall's motion in the `gt_surface_NNNNNN.ply` files beside it.
    #[arg(long)]
    live_surface_gt: Option<PathBuf>,
    /// The frame the live surface error is measured at (default: the map's newest surfel).
    #[arg(long)]
    last_frame: Option<u32>,
    /// Write the figures as JSON (same keys as summary.json).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write plots (PNG) into this folder.
    #[arg(long)]
    plot: Option<PathBuf>,
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    let sim3 = match args.align.as_str() {
        "se3" => false,
        "sim3" => true,
        a => bail!("--align {a}: use se3 or sim3"),
    };
    let gt = tum::read_trajectory(&args.gt).with_context(|| "reading the ground truth")?;
    let est = tum::read_trajectory(&args.est).with_context(|| "reading the estimate")?;
    let surfaces = match (&args.surface_gt, &args.map) {
        (Some(g), Some(m)) => Some((ply::read_surfels(m).context("reading the map")?, ply::read_surfels(g).context("reading the ground-truth surface")?)),
        (None, None) => None,
        _ => bail!("--surface-gt and --map go together"),
    };
    let rpe_delta = match args.rpe_delta_m {
        Some(m) => Delta::Metres(m),
        None => Delta::Frames(args.rpe_delta),
    };
    let opts = EvalOptions { tolerance_s: args.tolerance, sim3, rpe_delta, ..EvalOptions::default() };
    let mut figures = evaluate(&est, &gt, surfaces.as_ref().map(|(m, g)| (m, g)), &opts);
    if let Some(live) = &args.live_surface_gt {
        let Some(map) = &args.map else { bail!("--live-surface-gt needs --map") };
        let map = ply::read_surfels(map).context("reading the map")?;
        let now = ply::read_surfels(live).with_context(|| format!("reading the true surface {}", live.display()))?;
        let last = args.last_frame.or_else(|| map.surfels.iter().map(|s| s.t).max()).unwrap_or(0);
        // The sequence's camera (beside the true surfaces) splits the live surfels by the last
        // frame's view; without one the split is left out.
        let dir = live.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
        let camera_toml = dir.join("camera.toml");
        let camera = if camera_toml.exists() {
            Some(capsule_slam_framework::files::read_camera_file(&camera_toml).with_context(|| format!("reading {}", camera_toml.display()))?.camera())
        } else {
            eprintln!("warning: no {}: the live surface is not split by the last frame's view", camera_toml.display());
            None
        };
        let live_figures = evaluate_live(&est, &gt, &map, &now, last, camera.as_ref(), &opts);
        if live_figures.is_empty() {
            bail!("no surfel of the map was seen in the 30 frames up to frame {last}; give --last-frame");
        }
        figures.extend(live_figures);
        if let Some((_, rest)) = &surfaces {
            let dir = live.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
            match capsule_slam_run::truth::wall_motion(dir, rest, last as usize) {
                Ok((wall, now)) => figures.extend(evaluate_warp(&est, &gt, &map, &wall, &now, last, &opts)),
                Err(why) => eprintln!("warning: warp error off: {why}"),
            }
        }
    }
    if !figures.contains_key("ate_rmse_m") {
        bail!("fewer than 3 poses of {} match {} within {} s", args.est.display(), args.gt.display(), args.tolerance);
    }
    print!("{}", table(&figures));
    if let Some(j) = &args.json {
        std::fs::write(j, serde_json::to_string_pretty(&figures)? + "\n").with_context(|| format!("writing {}", j.display()))?;
    }
    if let Some(dir) = &args.plot {
        let align = align_trajectory(&est, &gt, args.tolerance, sim3).context("aligning for the plots")?;
        let pairs: Vec<(StampedPose, StampedPose)> = associate(&est, &gt, args.tolerance)
            .into_iter()
            .map(|(e, g)| (StampedPose { timestamp_s: e.timestamp_s, t_world_cam: align.apply_pose(&e.t_world_cam) }, *g))
            .collect();
        crate::plot::plot(dir, &pairs)?;
        println!("plots in {}", dir.display());
    }
    Ok(())
}
