//! `capsule-slam bench`: the default pipeline end to end on the phantom, per image size: mean
//! and p95 ms per stage, and the surfel count over time.

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
}

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
    println!("| size | frames | stage | mean ms | p95 ms |");
    println!("|---|---|---|---|---|");
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
        let config = crate::load_config(None, &args.set, &registry)?;
        let dataset = Dataset::open(&dir, &config.input, None).with_context(|| format!("opening {}", dir.display()))?;
        let mut pipeline = Pipeline::build(
            &config,
            "bench",
            &registry,
            &BuildEnv::new(dataset.rig(), Some(dir.clone())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone()),
        )?;
        let out = std::env::temp_dir().join(format!("capsule-slam-bench-{}", std::process::id()));
        let mut writer = RunWriter::create(&out, &pipeline.resolved_config().to_toml_string())?;
        let mut records: Vec<FrameRecord> = Vec::new();
        let summary =
            run(&dataset, &mut pipeline, &mut writer, &RunOptions { max_frames: None, write_map: false, eval_sim3: false, ..RunOptions::default() }, |r| {
                records.push(r.clone())
            })?;
        let _ = std::fs::remove_dir_all(&out);
        let stage = |label: &str, f: &dyn Fn(&FrameRecord) -> f64| {
            let mut v: Vec<f64> = records.iter().map(f).collect();
            let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
            println!("| {w}×{h} | {} | {label} | {mean:.2} | {:.2} |", records.len(), percentile(&mut v, 0.95));
        };
        stage("depth", &|r| r.ms.depth);
        stage("track", &|r| r.ms.track);
        stage("fuse", &|r| r.ms.fuse);
        stage("predict", &|r| r.ms.predict);
        stage("track + fuse + predict", &|r| r.ms.track + r.ms.fuse + r.ms.predict);
        stage("total", &|r| r.total_ms);
        if args.surfels_every > 0 {
            for r in records.iter().filter(|r| (r.index + 1) % args.surfels_every == 0) {
                println!("|   surfels after {} frames: {} ({} active) |", r.index + 1, r.map.total, r.map.active);
            }
        }
        println!("|   {w}×{h}: {} surfels at the end, ATE {:.3} mm |", summary.surfels, summary.ate_rmse_m.unwrap_or(f64::NAN) * 1e3);
        println!("|   {w}×{h}: a frame's preprocess, depth and track times include its preparation beside the previous frame's fusion; total is wall time |");
    }
    Ok(())
}
