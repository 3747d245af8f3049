//! `capsule-slam depth-eval`: single-frame depth error of the configured preprocessors and
//! depth estimator against the input's own depth (the phantom's ground truth): AbsRel, RMSE,
//! δ < 1.25, with and without per-frame median scaling, and ms per frame.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context as _, anyhow, bail};
use capsule_slam_eval::depth::{DepthError, depth_error};
use capsule_slam_framework::config::validate::validate;
use capsule_slam_framework::context::{Context, StageReport};
use capsule_slam_framework::registry::{BuildEnv, Stage};
use capsule_slam_io::Dataset;

/// Arguments of `depth-eval`.
#[derive(clap::Args, Debug)]
pub struct DepthEvalArgs {
    /// Configuration file (TOML); absent: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Input folder with ground-truth depth (e.g. a phantom sequence).
    #[arg(long)]
    input: PathBuf,
    /// Override any config key (e.g. `--set pipeline.depth=near-light-sfs`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Evaluate every N-th frame.
    #[arg(long, default_value_t = 30)]
    every: usize,
}

fn mean(v: &[DepthError], f: impl Fn(&DepthError) -> f64) -> f64 {
    v.iter().map(f).sum::<f64>() / v.len().max(1) as f64
}

pub fn run(args: &DepthEvalArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let registry = crate::registry()?;
    let config = crate::load_config(args.config.as_deref(), &args.set, &registry)?;
    let dataset = Dataset::open(&args.input, &config.input, config.camera.as_ref()).with_context(|| format!("opening {}", args.input.display()))?;
    if !dataset.has_depth() {
        bail!("{} has no depth.txt: depth-eval needs ground-truth depth", args.input.display());
    }
    let resolved = validate(&config, &registry, dataset.rig().kind(), "the config")?;
    let env = BuildEnv::new(dataset.rig(), Some(args.input.clone())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone());
    let mut pre = crate::stages::preprocessors(&registry, &resolved, &env, &config.pipeline.preprocess)?;
    let Stage::DepthEstimator(mut depth) = crate::stages::build(&registry, &resolved, &env, &config.pipeline.depth)? else {
        bail!("{} is not a depth estimator", config.pipeline.depth)
    };
    let rig = dataset.rig();
    let (mut raw, mut scaled, mut ms) = (Vec::new(), Vec::new(), Vec::new());
    for i in (0..dataset.len()).step_by(args.every.max(1)) {
        let mut frame = dataset.load(i)?;
        let truth = frame.depth_m.clone().ok_or_else(|| anyhow!("frame {i} has no depth"))?;
        let mut report = StageReport::default();
        let start = Instant::now();
        for (_, p) in &mut pre {
            p.process(&mut frame, &mut Context::new(i, &rig, None, &mut report))?;
        }
        let est = depth.estimate(&frame, &mut Context::new(i, &rig, None, &mut report))?;
        ms.push(start.elapsed().as_secs_f64() * 1e3);
        if let (Some(a), Some(b)) = (depth_error(&est.depth_m, &truth, false), depth_error(&est.depth_m, &truth, true)) {
            raw.push(a);
            scaled.push(b);
        }
    }
    if raw.is_empty() {
        bail!("no frame had pixels with both an estimate and ground truth");
    }
    println!("{} on {} frames of {}", config.pipeline.depth, raw.len(), args.input.display());
    println!("| scaling | AbsRel | RMSE mm | δ<1.25 | coverage px |");
    println!("|---|---|---|---|---|");
    for (label, v) in [("none", &raw), ("median", &scaled)] {
        println!(
            "| {label} | {:.4} | {:.3} | {:.3} | {:.0} |",
            mean(v, |e| e.abs_rel),
            mean(v, |e| e.rmse_m) * 1e3,
            mean(v, |e| e.delta_1_25),
            mean(v, |e| e.pixels as f64)
        );
    }
    let mut sorted = ms.clone();
    sorted.sort_by(f64::total_cmp);
    println!(
        "ms per frame {:.2} mean, {:.2} median (the first frame also builds the per-camera tables: {:.2})",
        ms.iter().sum::<f64>() / ms.len() as f64,
        sorted[sorted.len() / 2],
        ms[0]
    );
    Ok(())
}
