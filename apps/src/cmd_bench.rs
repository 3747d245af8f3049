//! `capsule-slam bench`: the default pipeline end to end on the phantom, per image size: mean
//! and p95 ms per stage, and the surfel count over time. With `--rounds N` each size is run N
//! times, each from a freshly built pipeline, and the table gives the median of the N runs'
//! figures beside each run's mean (the protocol of issue 21: this machine's speed drifts, a
//! single run is one sample).

use std::path::PathBuf;

use anyhow::{Context as _, anyhow};
use capsule_slam_framework::pipeline::{FrameRecord, Pipeline};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::Dataset;
use capsule_slam_phantom::writer::is_complete;
use capsule_slam_phantom::{PhantomSpec, SizePreset};
use capsule_slam_run::RunWriter;
use capsule_slam_run::{RunOptions, run};

/// Arguments of `bench`.
#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Image sizes, comma-separated (naneye, 320, voyager, potensic, pal).
    #[arg(long, default_value = "naneye,320")]
    sizes: String,
    /// Phantom preset.
    #[arg(long, default_value_t = 2)]
    preset: u8,
    /// Amplitude of the phantom's peristaltic wave, millimetres (0: a rigid wall; a moving
    /// wall makes the default tracker solve its warp every frame).
    #[arg(long = "deform", value_name = "MM", default_value_t = 0.0)]
    deform_mm: f64,
    /// Frames per run.
    #[arg(long, default_value_t = 300)]
    frames: usize,
    /// Override any config key, as for `run`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Print the surfel count every this many frames (0 = only at the end).
    #[arg(long, default_value_t = 0)]
    surfels_every: usize,
    /// Runs per size: the table gives the median of their means and p95s, and each run's mean.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=99))]
    rounds: u32,
}

/// The median of `v` (the mean of the two middle values for an even count; 0 for none).
fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => 0.0,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// One stage's time per frame, ms.
type StageTime = fn(&FrameRecord) -> f64;

/// The stages of the table, in order.
const STAGES: [(&str, StageTime); 6] = [
    ("depth", |r| r.ms.depth),
    ("track", |r| r.ms.track),
    ("fuse", |r| r.ms.fuse),
    ("predict", |r| r.ms.predict),
    ("track + fuse + predict", |r| r.ms.track + r.ms.fuse + r.ms.predict),
    ("total", |r| r.total_ms),
];

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1]
}

pub fn run_bench(args: &BenchArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let registry = crate::registry()?;
    let cache = std::env::var_os("CAPSULE_SLAM_CACHE").map_or_else(|| PathBuf::from(".cache/capsule-slam"), PathBuf::from);
    let rounds = args.rounds as usize; // at least 1: clap refuses 0
    if rounds == 1 {
        println!("| size | frames | stage | mean ms | p95 ms |");
        println!("|---|---|---|---|---|");
    } else {
        println!("| size | frames | stage | mean ms (median of {rounds} runs) | p95 ms (median) | each run's mean ms |");
        println!("|---|---|---|---|---|---|");
    }
    for name in args.sizes.split(',').map(str::trim) {
        let size = SizePreset::parse(name).ok_or_else(|| anyhow!("--sizes: unknown size `{name}` (naneye, 320, voyager, potensic, pal)"))?;
        let spec = PhantomSpec { frames: args.frames, size, deform_mm: args.deform_mm, ..PhantomSpec::preset(args.preset) };
        let (w, h) = size.size();
        let wave = if spec.deform_mm > 0.0 { format!("-deform{}mm", spec.deform_mm) } else { String::new() };
        let dir = cache.join(format!("phantom-preset{}-{w}x{h}-{}f-seed{}{wave}", spec.preset, spec.frames, spec.seed));
        if !is_complete(&dir, &spec) {
            eprintln!("generating {} into {}", name, dir.display());
            crate::cmd_synth::synthesize(spec, &dir, true)?;
        }
        let runs = (0..rounds).map(|_| bench_once(args, &registry, &dir, gpu)).collect::<anyhow::Result<Vec<_>>>()?;
        let frames = runs[0].0.len();
        for (label, f) in STAGES {
            let (mut means, mut p95s) = (Vec::with_capacity(rounds), Vec::with_capacity(rounds));
            for (records, _) in &runs {
                let mut v: Vec<f64> = records.iter().map(f).collect();
                means.push(v.iter().sum::<f64>() / v.len().max(1) as f64);
                p95s.push(percentile(&mut v, 0.95));
            }
            if rounds == 1 {
                println!("| {w}×{h} | {frames} | {label} | {:.2} | {:.2} |", means[0], p95s[0]);
            } else {
                let each: Vec<String> = means.iter().map(|m| format!("{m:.2}")).collect();
                println!("| {w}×{h} | {frames} | {label} | {:.2} | {:.2} | {} |", median(&means), median(&p95s), each.join(" / "));
            }
        }
        let (records, summary) = &runs[rounds - 1];
        if args.surfels_every > 0 {
            for r in records.iter().filter(|r| (r.index + 1) % args.surfels_every == 0) {
                println!("|   surfels after {} frames: {} ({} active) |", r.index + 1, r.map.total, r.map.active);
            }
        }
        println!("|   {w}×{h}: {} surfels at the end, ATE {:.3} mm |", summary.surfels, summary.ate_rmse_m.unwrap_or(f64::NAN) * 1e3);
        // The same input and config give the same output: every run's trajectory error and map
        // size must agree, or the timing compared different work.
        let differ = runs.iter().any(|(_, s)| s.surfels != summary.surfels || s.ate_rmse_m.map(f64::to_bits) != summary.ate_rmse_m.map(f64::to_bits));
        if differ {
            eprintln!(
                "warning: {w}×{h}: the {rounds} runs ended with different maps or trajectories: the pipeline is not deterministic here, and the runs timed different work"
            );
        } else if rounds > 1 {
            println!("|   {w}×{h}: the {rounds} runs ended with the same map size and ATE to the bit |");
        }
        println!("|   {w}×{h}: a frame's preprocess, depth and track times include its preparation beside the previous frame's fusion; total is wall time |");
    }
    Ok(())
}

/// One run of the configured pipeline over the phantom in `dir`: every frame's record and the
/// run's summary.
fn bench_once(
    args: &BenchArgs,
    registry: &capsule_slam_framework::registry::Registry,
    dir: &std::path::Path,
    gpu: &capsule_slam_gpu::GpuHandle,
) -> anyhow::Result<(Vec<FrameRecord>, capsule_slam_run::Summary)> {
    let config = crate::load_config(None, &args.set, registry)?;
    let dataset = Dataset::open(dir, &config.input, None).with_context(|| format!("opening {}", dir.display()))?;
    let env = BuildEnv::new(dataset.rig(), Some(dir.to_path_buf())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone());
    let mut pipeline = Pipeline::build(&config, "bench", registry, &env)?;
    let out = std::env::temp_dir().join(format!("capsule-slam-bench-{}", std::process::id()));
    let mut writer = RunWriter::create(&out, &pipeline.resolved_config().to_toml_string())?;
    let mut records: Vec<FrameRecord> = Vec::new();
    let options = RunOptions { max_frames: None, write_map: false, eval_sim3: false, ..RunOptions::default() };
    let summary = run(&dataset, &mut pipeline, &mut writer, &options, |r| records.push(r.clone()))?;
    if let Err(e) = std::fs::remove_dir_all(&out) {
        eprintln!("warning: could not remove the bench's scratch folder {}: {e}", out.display());
    }
    Ok((records, summary))
}
