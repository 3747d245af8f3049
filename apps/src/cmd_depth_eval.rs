//! `capsule-slam depth-eval`: single-frame depth error of the configured preprocessors and
//! depth estimator against the input's own depth (the phantom's ground truth): AbsRel, RMSE,
//! δ < 1.25, with and without per-frame median scaling, the coverage of the field of view, for
//! a stereo rig the bad-pixel shares over 1 and 2 px of disparity, and ms per frame.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context as _, anyhow, bail};
use capsule_slam_eval::depth::{DepthError, bad_disparity, coverage, depth_error};
use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::context::{Context, StageReport};
use capsule_slam_framework::image::{DepthMap, Mask};

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
    let crate::stages::FrontEnd { config, dataset, preprocessors: mut pre, mut depth } =
        crate::stages::front_end(args.config.as_deref(), &args.set, &args.input, gpu)?;
    if !dataset.has_depth() {
        bail!("{} has no depth.txt: depth-eval needs ground-truth depth", args.input.display());
    }
    let rig = dataset.rig();
    let fov = rig.camera().fov_mask();
    // The rectified focal length times the baseline: disparity = fb / z.
    let fb = crate::cmd_depth::rectified_fb(&rig).with_context(|| format!("rectifying the rig of {}", args.input.display()))?;
    let (mut raw, mut scaled, mut ms, mut cov, mut bad) = (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut cov_both, mut both_share) = (Vec::new(), Vec::new());
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
        cov.extend(coverage(&est.depth_m, &truth, Some(&fov)));
        bad.extend(fb.and_then(|fb| bad_disparity(&est.depth_m, &truth, fb)));
        if let Some(both) = seen_by_both(&rig, &truth) {
            cov_both.extend(coverage(&est.depth_m, &truth, Some(&both)));
            both_share.extend(coverage(&DepthMap::from_fn(both.width(), both.height(), |x, y| [f32::from(u8::from(both.at(x, y)))]), &truth, Some(&fov)));
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
    let avg = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!("coverage {:.1} % of the field of view's pixels with ground truth", 100.0 * avg(&cov));
    if let Some(fb) = fb {
        let (b1, b2): (Vec<f64>, Vec<f64>) = bad.iter().copied().unzip();
        println!("disparity (f b = {fb:.3} px·m): {:.2} % of pixels off by > 1 px, {:.2} % by > 2 px", 100.0 * avg(&b1), 100.0 * avg(&b2));
        println!(
            "coverage {:.1} % of the pixels both cameras see (the right camera sees {:.1} % of the left's field of view)",
            100.0 * avg(&cov_both),
            100.0 * avg(&both_share)
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

/// For a stereo rig, the left pixels whose true surface point (`truth`) lies in the right
/// camera's field of view too (occlusion by other surfaces not counted): the most a stereo
/// estimate can cover. `None` for a mono rig.
fn seen_by_both(rig: &Rig, truth: &DepthMap) -> Option<Mask> {
    let Rig::Stereo { left, right, t_right_left } = rig else { return None };
    let (w, h) = truth.size();
    let mut m = Mask::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let z = f64::from(truth.at(x, y));
            if z > 0.0 && left.in_fov(x as f64, y as f64) {
                let p = t_right_left * left.unproject(x as f64, y as f64, z);
                *m.at_mut(x, y) = right.project(&p).is_some_and(|q| right.in_fov(q.x, q.y));
            }
        }
    }
    Some(m)
}
