//! `capsule-slam run`: assemble the pipeline from the config, run it over the input, write the
//! outputs and print the metrics.

use std::path::PathBuf;

use anyhow::Context as _;
use capsule_slam_eval::report::EvalOptions;
use capsule_slam_framework::config::Config;
use capsule_slam_framework::frame::DepthSource;
use capsule_slam_framework::pipeline::Pipeline;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Registry, StageKind};
use capsule_slam_io::Dataset;
use capsule_slam_phantom::PhantomSpec;
use capsule_slam_phantom::writer::is_complete;
use capsule_slam_run::{RunOptions, run_observed};
use capsule_slam_run::{RunWriter, Summary};
use indicatif::{ProgressBar, ProgressStyle};

/// Arguments of `run`.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Configuration file (TOML); absent: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Input folder (TUM RGB-D layout or images, with camera.toml); overrides [input] path.
    #[arg(long)]
    input: Option<PathBuf>,
    /// Output folder; overrides [output] dir.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Override any config key: KEY=VALUE, VALUE a TOML value or a bare word (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Process at most N frames; overrides [input] max_frames.
    #[arg(long)]
    frames: Option<usize>,
    /// No progress bar (the plots are still written).
    #[arg(short, long)]
    quiet: bool,
    /// Do not write `out/plots/` (trajectory over the ground truth, error over time, the map
    /// from three viewpoints in colour and by confidence).
    #[arg(long)]
    no_plots: bool,
    /// Score every loop closure as it is applied (ATE and surface RMSE just before and after,
    /// `closures.csv`); needs an input with ground truth. Slower: a map snapshot per frame.
    #[arg(long)]
    closure_report: bool,
    /// Write into an output folder that holds files a run does not write (they are kept; a
    /// previous run's outputs are always replaced).
    #[arg(long)]
    force: bool,
    /// The recording for the rerun viewer.
    #[command(flatten)]
    record: crate::run_record::RecordArgs,
}

/// The oracle that stands in for a default stage whose real plugin is not in this build.
const ORACLES: [(StageKind, &str); 2] = [(StageKind::DepthEstimator, "sensor"), (StageKind::Tracker, "ground-truth")];

/// Replaces default stage choices that this build lacks by their oracle, saying so.
fn substitute_oracles(config: &mut Config, registry: &Registry) {
    let defaults = capsule_slam_framework::config::PipelineConfig::default();
    let p = &mut config.pipeline;
    for (kind, oracle) in ORACLES {
        let (slot, default) = match kind {
            StageKind::DepthEstimator => (&mut p.depth, &defaults.depth),
            _ => (&mut p.tracker, &defaults.tracker),
        };
        if slot == default && registry.get(slot).is_none() && registry.get(oracle).is_some() {
            eprintln!("note: the default {} `{slot}` is not in this build; using the oracle `{oracle}` instead", kind.as_str());
            *slot = oracle.to_owned();
        }
    }
}

/// Where phantoms are made once and reused: `$CAPSULE_SLAM_CACHE`, default `.cache/capsule-slam`.
pub fn cache_dir() -> PathBuf {
    std::env::var_os("CAPSULE_SLAM_CACHE").map_or_else(|| PathBuf::from(".cache/capsule-slam"), PathBuf::from)
}

/// The built-in default input: phantom preset 2 at 320×320, 300 frames, generated once into a
/// cache folder (`$CAPSULE_SLAM_CACHE`, default `.cache/capsule-slam`) and reused.
fn default_phantom(quiet: bool) -> anyhow::Result<PathBuf> {
    let spec = PhantomSpec::preset(2);
    let dir = cache_dir().join(format!("phantom-preset{}-320-{}f-seed{}", spec.preset, spec.frames, spec.seed));
    if is_complete(&dir, &spec) {
        eprintln!("input: the built-in phantom (preset 2, 320×320, {} frames), cached in {}", spec.frames, dir.display());
    } else {
        eprintln!("input: the built-in phantom (preset 2, 320×320, {} frames): generating it into {}", spec.frames, dir.display());
        crate::cmd_synth::synthesize(spec, &dir, quiet)?;
    }
    Ok(dir)
}

/// The build of this binary, as `summary.json` records it.
pub const BUILD: capsule_slam_run::BuildStamp = capsule_slam_run::BuildStamp { version: env!("CARGO_PKG_VERSION"), commit: env!("CAPSULE_SLAM_COMMIT") };

/// What `run` runs: the config with the command line's overrides and the oracles in, the
/// config's source name and the input folder (the built-in phantom, made if need be, when none
/// is given).
pub struct Prepared {
    /// The config.
    pub config: Config,
    /// Where it came from, for error messages.
    pub source: String,
    /// The input folder.
    pub input: PathBuf,
}

/// Loads and completes the config of `args`.
pub fn prepare(args: &RunArgs, registry: &Registry) -> anyhow::Result<Prepared> {
    let mut config = crate::load_config(args.config.as_deref(), &args.set, registry)?;
    let source = capsule_slam_framework::config::Config::source_name(args.config.as_deref(), &args.set);
    if let Some(i) = &args.input {
        config.input.path = Some(i.clone());
    }
    if let Some(o) = &args.out {
        config.output.dir = o.clone();
    }
    if let Some(n) = args.frames {
        config.input.max_frames = Some(n);
    }
    substitute_oracles(&mut config, registry);
    let input = match config.input.path.clone() {
        Some(p) => p,
        None => default_phantom(args.quiet)?,
    };
    Ok(Prepared { config, source, input })
}

/// The resolved configuration (`config.toml`) a run of `args` writes, without running it.
pub fn resolved_config_text(args: &RunArgs, registry: &Registry) -> anyhow::Result<String> {
    let Prepared { config, source, input } = prepare(args, registry)?;
    let dataset = Dataset::open(&input, &config.input, config.camera.as_ref()).with_context(|| format!("opening the input {}", input.display()))?;
    Ok(Pipeline::resolve(&config, &source, registry, dataset.rig().kind())?.to_toml_string())
}

pub fn run(args: &RunArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let registry = crate::registry()?;
    let Prepared { config, source, input } = prepare(args, &registry)?;
    let dataset = Dataset::open(&input, &config.input, config.camera.as_ref()).with_context(|| format!("opening the input {}", input.display()))?;
    for w in dataset.warnings() {
        eprintln!("warning: {w}");
    }
    if dataset.dropped_without_depth() > 0 {
        eprintln!("note: {} rgb frames have no depth image within {} s and are skipped", dataset.dropped_without_depth(), config.input.association_tolerance_s);
    }
    let env = BuildEnv::new(dataset.rig(), Some(input.clone())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone());
    let mut pipeline = Pipeline::build(&config, &source, &registry, &env)?;
    crate::run_record::Recording::check(&args.record)?;
    let out = config.output.dir.clone();
    let mut writer = RunWriter::create_with(&out, &pipeline.resolved_config().to_toml_string(), args.force)
        .with_context(|| format!("creating the output folder {}", out.display()))?;

    let n = config.input.max_frames.map_or(dataset.len(), |m| m.min(dataset.len()));
    let bar = if args.quiet { ProgressBar::hidden() } else { ProgressBar::new(n as u64) };
    bar.set_style(ProgressStyle::with_template("{bar:40} {pos}/{len} frames  {per_sec}  eta {eta}").unwrap_or_else(|_| ProgressStyle::default_bar()));
    let opts =
        RunOptions { max_frames: config.input.max_frames, write_map: config.output.map, eval_sim3: false, closure_report: args.closure_report, build: BUILD };
    let mut recording = crate::run_record::Recording::open(&args.record, dataset.ground_truth())?;
    pipeline.keep_last_frame(recording.as_ref().is_some_and(|r| r.wants_frames()));
    let result = run_observed(&dataset, &mut pipeline, &mut writer, &opts, |rec, pipeline| {
        for w in rec.warnings() {
            bar.suspend(|| eprintln!("warning: frame {}: {w}", rec.index));
        }
        if let Some(r) = recording.as_mut() {
            r.observe(rec, pipeline);
        }
        bar.inc(1);
    });
    bar.finish_and_clear();
    // One snapshot of the final map for the plots and the recording, the surfels map.ply holds
    // (the runner's own snapshot went into map.ply and the evaluation). The recording is
    // completed whether or not the run was (it shows where a run failed).
    let map = (!args.no_plots || recording.is_some()).then(|| pipeline.snapshot().ok().map(|w| capsule_slam_run::written_map(&pipeline, &w))).flatten();
    let recorded = recording.map(|r| r.finish(pipeline.trajectory(), map.as_ref())).transpose().unwrap_or_else(|e| {
        eprintln!("warning: {e:#}");
        None
    });
    let ended = if matches!(result, Err(capsule_slam_framework::PipelineError::NoResult(_))) {
        "run failed; what it wrote is"
    } else {
        "run stopped; the output so far is"
    };
    let summary = result.with_context(|| format!("{ended} in {}", out.display()))?;

    print_summary(&summary, pipeline.depth_source());
    if !args.no_plots {
        let dir = out.join(capsule_slam_run::writer::PLOTS_DIR);
        let tolerance = config.input.association_tolerance_s;
        match crate::run_plots::write(&dir, pipeline.trajectory(), dataset.ground_truth(), tolerance, !summary.metric_scale, map.as_ref()) {
            Ok(n) => println!("plots             {n} in {}", dir.display()),
            Err(e) => eprintln!("warning: the plots were not written: {e:#}"),
        }
    }
    if let Some(path) = recorded {
        println!("recording         {} (open it with `rerun {}`)", path.display(), path.display());
    }
    println!("outputs           {}", out.display());
    Ok(())
}

/// Prints the run's figures (and what it could not measure).
fn print_summary(summary: &Summary, depth_source: DepthSource) {
    println!("frames            {}", summary.frames);
    println!("frames lost       {}", summary.frames_lost);
    println!("ms per frame      {:.2} mean, {:.2} p95", summary.ms_per_frame_mean, summary.ms_per_frame_p95);
    println!("surfels           {} ({} active; {} written and scored)", summary.surfels, summary.surfels_active, summary.surfels_written);
    println!("loop closures     {}", summary.loop_closures);
    let path_m = summary.metrics.get("path_length_m").copied().unwrap_or(0.0);
    let pct = |a: f64| if path_m > 0.0 { format!(" ({:.3} % of the {:.1} mm path)", a / path_m * 100.0, path_m * 1e3) } else { String::new() };
    let se3 = summary.ate_rmse_m.map(|a| format!("ATE RMSE (SE3)    {:.3} mm{}", a * 1e3, pct(a)));
    let sim3 = match (summary.metrics.get("ate_rmse_sim3_m"), summary.metrics.get("sim3_scale")) {
        (Some(a), Some(scale)) => Some(format!("ATE RMSE (Sim3)   {:.3} mm{}, scale {scale:.3}", a * 1e3, pct(*a))),
        _ => None,
    };
    // Without a metric scale the similarity alignment leads and the rigid one is marked.
    let lines = if summary.metric_scale { [se3, sim3] } else { [sim3, se3.map(|l| format!("{l} (the scale is unknown: not meaningful)"))] };
    for l in lines.into_iter().flatten() {
        println!("{l}");
    }
    if !summary.metric_scale {
        println!("metric scale      unknown (no calibration for it): figures are Sim(3)-aligned");
    }
    if let Some(r) = summary.metrics.get("surface_rmse_m") {
        let c = summary.metrics.get("surface_completeness_1mm").copied().unwrap_or(0.0);
        let c10 = summary.metrics.get("surface_completeness_1mm_seen10").copied().unwrap_or(0.0);
        match summary.metrics.get("surface_rmse_all_surfels_m") {
            Some(all) => println!("surface RMSE      {:.3} mm (the written surfels; {:.3} mm with every surfel)", r * 1e3, all * 1e3),
            None => println!("surface RMSE      {:.3} mm", r * 1e3),
        }
        println!("completeness      {:.1} % of the observed truth within 1 mm ({:.1} % of the truth observed in ≥ 10 frames)", c * 100.0, c10 * 100.0);
    }
    if let (Some(r), Some(med), Some(p95)) =
        (summary.metrics.get("live_surface_rmse_m"), summary.metrics.get("live_surface_median_m"), summary.metrics.get("live_surface_p95_m"))
    {
        let align = if depth_source == DepthSource::Estimated { "Sim(3)" } else { "SE(3)" };
        println!(
            "live surface      {:.3} mm RMSE, {:.3} median, {:.3} p95 (surfels seen in the last {} frames, {align}-aligned, against the wall at the last frame)",
            r * 1e3,
            med * 1e3,
            p95 * 1e3,
            EvalOptions::default().live_window_frames
        );
        if let (Some(seen), Some(left), Some(n_left)) = (
            summary.metrics.get("live_surface_in_view_rmse_m"),
            summary.metrics.get("live_surface_left_rmse_m"),
            summary.metrics.get("live_surface_left_points"),
        ) {
            println!(
                "                  {:.3} mm RMSE on those in the last frame's view, {:.3} on the {:.0} the camera left beside or behind it",
                seen * 1e3,
                left * 1e3,
                n_left
            );
        }
        if let Some(local) = summary.metrics.get("live_surface_local_rmse_m") {
            println!("                  {:.3} mm RMSE aligned on the poses of those frames alone (without the drift before them)", local * 1e3);
        }
    }
    if let (Some(e), Some(n), Some(t)) =
        (summary.metrics.get("warp_error_rmse_m"), summary.metrics.get("warp_error_normal_rmse_m"), summary.metrics.get("warp_true_rms_m"))
    {
        println!(
            "warp error        {:.3} mm RMSE, {:.3} along the wall normal (surfels seen at the last frame, since their creation; the wall moved {:.3} mm RMS)",
            e * 1e3,
            n * 1e3,
            t * 1e3
        );
    }
    if let Some(a) = summary.metrics.get("depth_abs_rel") {
        println!("depth AbsRel      {a:.4} (estimated against the input's depth, mean over frames)");
    }
    for w in &summary.warnings {
        eprintln!("warning: {w}");
    }
}
