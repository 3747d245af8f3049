//! `capsule-slam depth`: runs the configured preprocessors and depth estimator over a folder and
//! writes what the estimator made of each frame: the depth as a 16-bit PNG at the camera's
//! `depth_scale` (TUM's convention, readable as a `depth/` folder), and, for looking at, the
//! (preprocessed) left view beside the inverse depth in false colour, which for a stereo rig is
//! the disparity `f b / z`.
//! No ground truth is needed (e.g. the Hamlyn pair in `docs/`).

use std::path::PathBuf;

use anyhow::Context as _;
use capsule_slam_framework::Rgb8;
use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::context::{Context, StageReport};
use capsule_slam_framework::stereo::rectify::Rectification;
use capsule_slam_io::images;

/// Arguments of `depth`.
#[derive(clap::Args, Debug)]
pub struct DepthArgs {
    /// Configuration file (TOML); absent: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Input folder (TUM layout, with rgb_right.txt for a stereo rig).
    #[arg(long)]
    input: PathBuf,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// Override any config key (e.g. `--set pipeline.depth=stereo-sgm`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
}

/// For a stereo rig, the rectified focal length times the baseline (pixel·metres): the
/// disparity of depth z is `fb / z`. `None` for a mono rig.
pub fn rectified_fb(rig: &Rig) -> anyhow::Result<Option<f64>> {
    Ok(match rig {
        Rig::Stereo { left, right, t_right_left } => {
            let r = Rectification::new(left, right, t_right_left)?;
            Some(r.camera.fx * r.baseline_m)
        }
        Rig::Mono(_) => None,
    })
}

/// A perceptual blue → green → yellow → red ramp of `t` in [0, 1] (black where `None`).
pub fn ramp(t: Option<f64>) -> [u8; 3] {
    let Some(t) = t else { return [0, 0, 0] };
    let stops = [[48.0, 18.0, 59.0], [40.0, 145.0, 235.0], [100.0, 240.0, 90.0], [250.0, 190.0, 40.0], [122.0, 4.0, 3.0]];
    let x = t.clamp(0.0, 1.0) * (stops.len() - 1) as f64;
    let (i, f) = ((x.floor() as usize).min(stops.len() - 2), x - x.floor().min((stops.len() - 2) as f64));
    [0, 1, 2].map(|c| (stops[i][c] + f * (stops[i + 1][c] - stops[i][c])).round() as u8)
}

/// The 2nd and 98th percentiles of the positive values.
fn range(v: &[f64]) -> (f64, f64) {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| *x > 0.0 && x.is_finite()).collect();
    s.sort_by(f64::total_cmp);
    if s.is_empty() {
        return (0.0, 1.0);
    }
    let q = |f: f64| s[((s.len() - 1) as f64 * f) as usize];
    (q(0.02), q(0.98).max(q(0.02) + 1e-9))
}

pub fn run(args: &DepthArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let crate::stages::FrontEnd { config, dataset, preprocessors: mut pre, mut depth } =
        crate::stages::front_end(args.config.as_deref(), &args.set, &args.input, gpu)?;
    let rig = dataset.rig();
    let fb = rectified_fb(&rig).with_context(|| format!("rectifying the rig of {}", args.input.display()))?;
    let depth_scale = dataset.camera_file().depth_scale;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    for i in 0..config.input.max_frames.map_or(dataset.len(), |m| m.min(dataset.len())) {
        let mut frame = dataset.load(i)?;
        let mut report = StageReport::default();
        for (name, p) in &mut pre {
            p.process(&mut frame, &mut Context::new(i, &rig, None, &mut report)).with_context(|| format!("{name} on frame {i}"))?;
        }
        let est = depth.estimate(&frame, &mut Context::new(i, &rig, None, &mut report)).with_context(|| format!("{} on frame {i}", config.pipeline.depth))?;
        for w in &report.warnings {
            eprintln!("warning: frame {i}: {w}");
        }
        let stem = format!("{i:04}");
        images::write_depth(&args.out.join(format!("{stem}_depth.png")), &est.depth_m, depth_scale)?;
        let (w, h) = est.depth_m.size();
        let z: Vec<f64> = est.depth_m.data().iter().map(|d| f64::from(*d)).collect();
        let view = frame.views.reference();
        // Inverse depth (near is warm), which for a stereo rig is the disparity `f b / z`.
        let scale = fb.unwrap_or(1.0);
        let panels: Vec<Vec<f64>> = vec![z.iter().map(|z| if *z > 0.0 { scale / z } else { 0.0 }).collect()];
        let ranges: Vec<(f64, f64)> = panels.iter().map(|p| range(p)).collect();
        let strip = Rgb8::from_fn((1 + panels.len()) * w, h, |x, y| match x / w {
            0 => view.pixel(x, y),
            k => {
                let v = panels[k - 1][y * w + x - k * w];
                let (lo, hi) = ranges[k - 1];
                ramp((v > 0.0).then(|| (v - lo) / (hi - lo)))
            }
        });
        images::write_rgb(&args.out.join(format!("{stem}_strip.png")), &strip)?;
        let valid: Vec<f64> = z.iter().copied().filter(|z| *z > 0.0).collect();
        let mut sorted = valid.clone();
        sorted.sort_by(f64::total_cmp);
        let fov = rig.camera().fov_mask();
        let in_fov = fov.data().iter().filter(|v| **v).count().max(1);
        let covered = est.depth_m.data().iter().zip(fov.data()).filter(|(d, f)| **f && **d > 0.0).count();
        let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
        let disparity = fb.map_or(String::new(), |fb| if median > 0.0 { format!(", median disparity {:.1} px", fb / median) } else { String::new() });
        println!("frame {i}: depth at {:.1} % of the field of view, median {:.1} mm{disparity}", 100.0 * covered as f64 / in_fov as f64, 1e3 * median);
    }
    println!("written to {}", args.out.display());
    Ok(())
}
