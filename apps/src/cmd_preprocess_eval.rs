//! `capsule-slam preprocess-eval`: the configured preprocessors against a phantom sequence's
//! ground truth (`specular/` masks, `diffuse/` images, `light.toml`): highlight mask precision
//! and recall, inpainting error against the diffuse-only image inside the mask, the radial bias
//! of the vignetting correction, and ms per frame of each stage.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context as _, bail};
use capsule_slam_framework::config::validate::validate;
use capsule_slam_framework::context::{Context, StageReport};
use capsule_slam_framework::frame::MASK_SPECULAR;
use capsule_slam_framework::image::Gray8;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::light::vignetting::{light_falloff, radius2};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{CameraFrame, Iso3, Mask, ModelView, PinholeCamera, Rgb8};
use capsule_slam_io::{Dataset, images};
use capsule_slam_plugins::common::maps::{normal_map, vertex_map};

/// Arguments of `preprocess-eval`.
#[derive(clap::Args, Debug)]
pub struct PreprocessEvalArgs {
    /// Configuration file (TOML); absent: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// A phantom sequence (`capsule-slam synth`): rgb/, specular/, diffuse/, light.toml.
    #[arg(long)]
    input: PathBuf,
    /// Override any config key; `pipeline.preprocess` defaults to `["reflection", "vignetting"]`
    /// here (e.g. `--set 'pipeline.preprocess=["vignetting"]'`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Evaluate every N-th frame.
    #[arg(long, default_value_t = 10)]
    every: usize,
    /// Give the preprocessors the frame's ground-truth geometry as the map's prediction (what a
    /// pipeline with measured depth would predict; for `plugins.vignetting.sequence_model =
    /// "shading"`).
    #[arg(long)]
    oracle_prediction: bool,
    /// Write, per evaluated frame, the input, the output and the masks (white: found and true;
    /// red: found only; green: true only) as PNG into this folder.
    #[arg(long)]
    dump: Option<PathBuf>,
}

/// Rings of r² for the radial bias.
const RINGS: usize = 12;

#[derive(Default)]
struct Totals {
    tp: f64,
    fp: f64,
    fn_: f64,
    inpaint_sse: f64,
    raw_sse: f64,
    inpaint_n: f64,
    ring_sum: [f64; RINGS],
    ring_n: [f64; RINGS],
}

pub fn run(args: &PreprocessEvalArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let registry = crate::registry()?;
    let mut set = vec!["pipeline.preprocess=[\"reflection\", \"vignetting\"]".to_owned()];
    set.extend(args.set.iter().cloned());
    let config = crate::load_config(args.config.as_deref(), &set, &registry)?;
    let dataset = Dataset::open(&args.input, &config.input, config.camera.as_ref()).with_context(|| format!("opening {}", args.input.display()))?;
    let light_path = args.input.join("light.toml");
    let light = capsule_slam_framework::files::read_light_file(&light_path)
        .with_context(|| format!("preprocess-eval needs the phantom's light model {}: run it on a `capsule-slam synth` folder", light_path.display()))?;
    let resolved = validate(&config, &registry, dataset.rig().kind(), "the config")?;
    let env = BuildEnv::new(dataset.rig(), Some(args.input.clone())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone());
    let mut stages = crate::stages::preprocessors(&registry, &resolved, &env, &config.pipeline.preprocess)?;
    if stages.is_empty() {
        bail!("pipeline.preprocess is empty: nothing to evaluate");
    }
    let rig = dataset.rig();
    let cam = rig.camera().clone();
    let size = Some((cam.width, cam.height));
    let mut t = Totals::default();
    let mut ms = vec![Vec::new(); stages.len()];
    let mut frames = 0;
    for i in (0..dataset.len()).step_by(args.every.max(1)) {
        let mut frame = dataset.load(i)?;
        let spec_path = args.input.join(format!("specular/{i:06}.png"));
        let dif_path = args.input.join(format!("diffuse/{i:06}.png"));
        let truth = images::read_gray(&spec_path, size).with_context(|| format!("ground-truth highlight mask {}", spec_path.display()))?;
        let diffuse = images::read_rgb(&dif_path, size).with_context(|| format!("ground-truth diffuse image {}", dif_path.display()))?;
        let input = frame.views.reference().clone();
        let mut report = StageReport::default();
        let prediction = if args.oracle_prediction { Some(oracle_prediction(&frame, &cam)?) } else { None };
        for (k, (name, stage)) in stages.iter_mut().enumerate() {
            let before = frame.views.reference().clone();
            let start = Instant::now();
            stage.process(&mut frame, &mut Context::new(i, &rig, prediction.as_ref(), &mut report)).with_context(|| format!("{name} on frame {i}"))?;
            ms[k].push(start.elapsed().as_secs_f64() * 1e3);
            if name == "reflection" {
                score_mask(&mut t, frame.masks.get(MASK_SPECULAR), &truth, &cam, frame.views.reference(), &before, &diffuse);
            }
        }
        if let Some(dir) = &args.dump {
            dump_frame(dir, i, &input, &frame, &truth, &cam)?;
        }
        score_vignetting(&mut t, &frame, &input, &cam, &light);
        frames += 1;
    }
    println!("preprocessors {:?} on {frames} frames of {}", stages.iter().map(|s| &s.0).collect::<Vec<_>>(), args.input.display());
    print_scores(&t);
    for (k, (name, _)) in stages.iter().enumerate() {
        let mut s = ms[k].clone();
        s.sort_by(f64::total_cmp);
        println!("{name}: {:.2} ms per frame mean, {:.2} median", s.iter().sum::<f64>() / s.len().max(1) as f64, s[s.len() / 2]);
    }
    Ok(())
}

/// The frame's ground-truth geometry as the map's prediction (what a pipeline with measured
/// depth would predict).
fn oracle_prediction(frame: &CameraFrame, cam: &PinholeCamera) -> anyhow::Result<ModelView> {
    let Some(d) = &frame.depth_m else { bail!("--oracle-prediction needs the input's depth") };
    let mut view = ModelView::empty(cam.width, cam.height, frame.gt_t_world_cam.unwrap_or_else(Iso3::identity));
    view.normals_cam = normal_map(&vertex_map(d, cam), 4, 0.004);
    view.depth_m = d.clone();
    Ok(view)
}

/// Writes the input, the output and the found / true masks of frame `i` (white: both; red:
/// found only; green: true only).
fn dump_frame(dir: &std::path::Path, i: usize, input: &Rgb8, frame: &CameraFrame, truth: &Gray8, cam: &PinholeCamera) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    images::write_rgb(&dir.join(format!("{i:06}_input.png")), input)?;
    images::write_rgb(&dir.join(format!("{i:06}_output.png")), frame.views.reference())?;
    let found = frame.masks.get(MASK_SPECULAR);
    let overlay = Rgb8::from_fn(cam.width, cam.height, |x, y| {
        let (f, g) = (found.is_some_and(|m| m.at(x, y)), truth.at(x, y) > 127);
        [if f { 255 } else { 0 }, if g { 255 } else { 0 }, if f && g { 255 } else { 0 }]
    });
    images::write_rgb(&dir.join(format!("{i:06}_masks.png")), &overlay)?;
    Ok(())
}

/// The fall-off the vignetting stage applied per pixel, `F = s · L_in / L_out`, over the true
/// one, summed per ring of r².
fn score_vignetting(t: &mut Totals, frame: &CameraFrame, input: &Rgb8, cam: &PinholeCamera, light: &LightModel) {
    let Some(d) = frame.photometry.divided else { return };
    let dec = |v: u8| (f64::from(v) / 255.0).powf(d.gamma);
    let out = frame.views.reference();
    for y in 0..cam.height {
        for x in 0..cam.width {
            let (u, v) = (x as f64, y as f64);
            let (a, b) = (input.pixel(x, y)[0], out.pixel(x, y)[0]);
            if !cam.in_fov(u, v) || frame.masks.ignored(x, y) || !(60..250).contains(&a) || b < 30 {
                continue;
            }
            let applied = d.linear_scale * dec(a) / dec(b);
            let ring = ((radius2(cam, u, v) * RINGS as f64) as usize).min(RINGS - 1);
            t.ring_sum[ring] += applied / light_falloff(light, cam, u, v, d.falloff);
            t.ring_n[ring] += 1.0;
        }
    }
}

/// Prints the mask, inpainting and vignetting scores.
fn print_scores(t: &Totals) {
    if t.tp + t.fn_ > 0.0 || t.fp > 0.0 {
        let precision = t.tp / (t.tp + t.fp).max(1.0);
        let recall = t.tp / (t.tp + t.fn_).max(1.0);
        println!(
            "highlight mask: precision {precision:.3}, recall {recall:.3} ({:.0} true, {:.0} found, {:.0} correct pixels)",
            t.tp + t.fn_,
            t.tp + t.fp,
            t.tp
        );
        if t.inpaint_n > 0.0 {
            println!(
                "inpainting inside the mask, RMS against the diffuse-only image: {:.2} levels (input: {:.2})",
                (t.inpaint_sse / t.inpaint_n).sqrt(),
                (t.raw_sse / t.inpaint_n).sqrt()
            );
        }
    }
    if let Some(centre) = (0..RINGS).find(|&r| t.ring_n[r] > 0.0).map(|r| t.ring_sum[r] / t.ring_n[r]) {
        let bias: Vec<f64> = (0..RINGS).filter(|&r| t.ring_n[r] > 0.0).map(|r| t.ring_sum[r] / t.ring_n[r] / centre - 1.0).collect();
        let worst = bias.iter().fold(0.0f64, |m, b| m.max(b.abs()));
        println!(
            "vignetting: applied / true fall-off per ring of r² (centre = 1): worst radial bias {:.2} % [{}]",
            worst * 100.0,
            bias.iter().map(|b| format!("{:+.1}", b * 100.0)).collect::<Vec<_>>().join(" ")
        );
    }
}

/// Mask precision / recall inside the field of view, and the inpainting error inside the
/// published mask.
fn score_mask(t: &mut Totals, found: Option<&Mask>, truth: &Gray8, cam: &PinholeCamera, out: &Rgb8, input: &Rgb8, diffuse: &Rgb8) {
    for y in 0..cam.height {
        for x in 0..cam.width {
            if !cam.in_fov(x as f64, y as f64) {
                continue;
            }
            let (f, g) = (found.is_some_and(|m| m.at(x, y)), truth.at(x, y) > 127);
            match (f, g) {
                (true, true) => t.tp += 1.0,
                (true, false) => t.fp += 1.0,
                (false, true) => t.fn_ += 1.0,
                (false, false) => {}
            }
            if f {
                for c in 0..3 {
                    let d = f64::from(diffuse.pixel(x, y)[c]);
                    t.inpaint_sse += (f64::from(out.pixel(x, y)[c]) - d).powi(2);
                    t.raw_sse += (f64::from(input.pixel(x, y)[c]) - d).powi(2);
                }
                t.inpaint_n += 3.0;
            }
        }
    }
}
