//! `capsule-slam`: the command line of the capsule-slam framework.

mod cmd_bench;
mod cmd_calibrate_camera;
mod cmd_calibrate_light;
mod cmd_calibrate_vignetting;
mod cmd_config;
mod cmd_depth;
mod cmd_depth_eval;
mod cmd_eval;
mod cmd_plugins;
mod cmd_preprocess;
mod cmd_preprocess_eval;
mod cmd_run;
mod cmd_synth;
mod compare;
mod plot;
mod run_plots;
mod run_record;
mod stages;

use clap::{Parser, Subcommand};

/// jemalloc, not the system's: a frame's large buffers (cost volumes, pyramids, residuals) are
/// freed and asked for again every frame, and glibc's allocator hands their pages back to the
/// kernel and faults them in again (`docs/results/speed.md`, "The allocator").
#[cfg(not(target_env = "msvc"))]
#[global_allocator]
static ALLOC: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

/// Dense non-rigid RGB-D SLAM for endoscopic capsule robots (after Turan et al. 2017).
#[derive(Parser, Debug)]
#[command(name = "capsule-slam", version, about)]
struct Cli {
    /// Load the plugins of a shared library built against capsule-slam's C ABI (repeatable;
    /// e.g. target/release/libcapsule_slam_dylib_example.so). Its plugins are then named in
    /// the config like linked ones.
    #[arg(long = "plugin-lib", value_name = "PATH", global = true)]
    plugin_libs: Vec<std::path::PathBuf>,
    #[command(subcommand)]
    command: Command,
}

/// The libraries of `--plugin-lib`, set once in `main`.
static PLUGIN_LIBS: std::sync::OnceLock<Vec<std::path::PathBuf>> = std::sync::OnceLock::new();

#[derive(Subcommand, Debug)]
enum Command {
    /// Run a pipeline over a sequence and write the trajectory, the map and the metrics.
    Run(cmd_run::RunArgs),
    /// Run variants × inputs (× sweeps) of a plan, each cell an ordinary run, and tabulate
    /// and plot them (`results.csv`, `results.md`, `plots/`); resumes, emits jobs, collects.
    Compare(compare::CompareArgs),
    /// List every registered plugin with its stage, parameters, defaults and units.
    Plugins,
    /// Print configuration.
    Config(cmd_config::ConfigArgs),
    /// Time the default pipeline per stage on the phantom at several image sizes.
    Bench(cmd_bench::BenchArgs),
    /// Fit camera.toml (intrinsics and lens) to checkerboard images.
    CalibrateCamera(cmd_calibrate_camera::CalibrateCameraArgs),
    /// Fit light.toml to frames of a target of known albedo and geometry (depth).
    CalibrateLight(cmd_calibrate_light::CalibrateLightArgs),
    /// Fit vignetting.toml (lens and LED fall-off) to flat-field frames.
    CalibrateVignetting(cmd_calibrate_vignetting::CalibrateVignettingArgs),
    /// Run the configured preprocessors and depth estimator over a folder and write each
    /// frame's depth (16-bit PNG) and a false-colour strip (with the disparity for a stereo rig).
    Depth(cmd_depth::DepthArgs),
    /// Single-frame error of the configured depth estimator against the input's depth.
    DepthEval(cmd_depth_eval::DepthEvalArgs),
    /// Run the configured preprocessors alone over a folder of images and write their output.
    Preprocess(cmd_preprocess::PreprocessArgs),
    /// Highlight mask precision / recall, inpainting error and vignetting bias of the
    /// configured preprocessors against a phantom sequence's ground truth.
    PreprocessEval(cmd_preprocess_eval::PreprocessEvalArgs),
    /// Trajectory and surface error of an estimate against ground truth.
    Eval(cmd_eval::EvalArgs),
    /// Render a synthetic stomach phantom sequence with its ground truth.
    Synth(cmd_synth::SynthArgs),
}

fn main() -> std::process::ExitCode {
    capsule_slam_plugins::link();
    let cli = Cli::parse();
    let _ = PLUGIN_LIBS.set(cli.plugin_libs.clone());
    // The process's GPU, handed to whatever builds stages; opened only if a stage asks for it.
    let gpu = capsule_slam_gpu::GpuHandle::new();
    let result = match cli.command {
        Command::Run(a) => cmd_run::run(&a, &gpu),
        Command::Compare(a) => compare::run(&a, &gpu),
        Command::Plugins => cmd_plugins::run(),
        Command::Config(a) => cmd_config::run(&a),
        Command::Synth(a) => cmd_synth::run(&a),
        Command::Eval(a) => cmd_eval::run(&a),
        Command::Bench(a) => cmd_bench::run_bench(&a, &gpu),
        Command::Depth(a) => cmd_depth::run(&a, &gpu),
        Command::DepthEval(a) => cmd_depth_eval::run(&a, &gpu),
        Command::CalibrateCamera(a) => cmd_calibrate_camera::run(&a),
        Command::CalibrateLight(a) => cmd_calibrate_light::run(&a),
        Command::PreprocessEval(a) => cmd_preprocess_eval::run(&a, &gpu),
        Command::Preprocess(a) => cmd_preprocess::run(&a, &gpu),
        Command::CalibrateVignetting(a) => cmd_calibrate_vignetting::run(&a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// The registry of every linked plugin and of the `--plugin-lib` libraries.
/// Reads the config; when other problems stop it short of the registry's validation, the
/// plugin names of `[pipeline]` are checked too, so an unknown key does not hide an unknown
/// plugin beside it (issue 18, item 8).
fn load_config(
    path: Option<&std::path::Path>,
    set: &[String],
    registry: &capsule_slam_framework::Registry,
) -> Result<capsule_slam_framework::config::Config, capsule_slam_framework::ConfigError> {
    capsule_slam_framework::config::Config::load_checked(path, set, |c| capsule_slam_framework::config::validate::plugin_name_problems(c, registry))
}

fn registry() -> anyhow::Result<capsule_slam_framework::Registry> {
    use anyhow::Context as _;
    let mut registry = capsule_slam_framework::Registry::from_inventory()?;
    for lib in PLUGIN_LIBS.get().into_iter().flatten() {
        capsule_slam_abi::load::load_library(&mut registry, lib).with_context(|| format!("--plugin-lib {}", lib.display()))?;
    }
    Ok(registry)
}
