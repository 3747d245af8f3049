//! `capsule-slam preprocess`: runs the configured preprocessors alone over a folder of images
//! and writes what they made of each frame: the corrected image, the highlight mask, and a
//! before | after | mask strip for looking at (e.g. the real capsule frames in `docs/`).

use std::path::PathBuf;

use anyhow::Context as _;
use capsule_slam_framework::Rgb8;
use capsule_slam_framework::config::validate::validate;
use capsule_slam_framework::context::{Context, StageReport};
use capsule_slam_framework::files::read_camera_file;
use capsule_slam_framework::frame::MASK_SPECULAR;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::{Dataset, images};

/// Arguments of `preprocess`.
#[derive(clap::Args, Debug)]
pub struct PreprocessArgs {
    /// Configuration file (TOML); absent: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Input folder (TUM layout or a plain folder of images).
    #[arg(long)]
    input: PathBuf,
    /// camera.toml to use instead of the input folder's own (for folders without one).
    #[arg(long)]
    camera: Option<PathBuf>,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// Override any config key; `pipeline.preprocess` defaults to `["reflection", "vignetting"]`
    /// here.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
}

pub fn run(args: &PreprocessArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let registry = crate::registry()?;
    let mut set = vec!["pipeline.preprocess=[\"reflection\", \"vignetting\"]".to_owned()];
    set.extend(args.set.iter().cloned());
    let config = crate::load_config(args.config.as_deref(), &set, &registry)?;
    let camera = match &args.camera {
        Some(p) => Some(read_camera_file(p)?),
        None => config.camera.clone(),
    };
    let dataset = Dataset::open(&args.input, &config.input, camera.as_ref()).with_context(|| format!("opening {}", args.input.display()))?;
    let resolved = validate(&config, &registry, dataset.rig().kind(), "the config")?;
    let env = BuildEnv::new(dataset.rig(), Some(args.input.clone())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone());
    let mut stages = crate::stages::preprocessors(&registry, &resolved, &env, &config.pipeline.preprocess)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let rig = dataset.rig();
    for i in 0..dataset.len() {
        let mut frame = dataset.load(i)?;
        let before = frame.views.reference().clone();
        let mut report = StageReport::default();
        for (name, stage) in &mut stages {
            stage.process(&mut frame, &mut Context::new(i, &rig, None, &mut report)).with_context(|| format!("{name} on frame {i}"))?;
        }
        for w in &report.warnings {
            eprintln!("frame {i}: {w}");
        }
        let after = frame.views.reference();
        let (w, h) = after.size();
        let mask = frame.masks.get(MASK_SPECULAR);
        let strip = Rgb8::from_fn(3 * w, h, |x, y| match x / w {
            0 => before.pixel(x, y),
            1 => after.pixel(x - w, y),
            _ => {
                let p = before.pixel(x - 2 * w, y);
                if mask.is_some_and(|m| m.at(x - 2 * w, y)) { [255, 0, 255] } else { p.map(|v| v / 2) }
            }
        });
        let stem = format!("{i:04}");
        images::write_rgb(&args.out.join(format!("{stem}.png")), after)?;
        images::write_rgb(&args.out.join(format!("{stem}_strip.png")), &strip)?;
        let share = mask.map_or(0.0, |m| m.data().iter().filter(|v| **v).count() as f64 / (w * h) as f64);
        println!(
            "frame {i}: highlights {:.2} % of the image; {}",
            share * 100.0,
            report.counters.iter().map(|(k, v)| format!("{k} {v:.3}")).collect::<Vec<_>>().join(", ")
        );
    }
    println!("written to {}", args.out.display());
    Ok(())
}
