//! `capsule-slam synth`: render a phantom sequence with its ground truth.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::{Context as _, anyhow};
use capsule_slam_framework::lens::{DistortionSpec, DistortionTable, LensModel};
use capsule_slam_phantom::writer::{contact_sheet, write_sequence};
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use indicatif::ProgressBar;

/// Arguments of `synth`.
#[derive(clap::Args, Debug, Clone)]
pub struct SynthArgs {
    /// Trajectory preset 1–7 (the paper's Table 3): 1 slow, 2 local revisits, 3 long scan with
    /// loops, 4 fast motion, 5 very loopy, 6 = 5 with heavy noise, 7 = 5 with heavy reflections
    /// and fast drift.
    #[arg(long, default_value_t = 2)]
    pub preset: u8,
    /// Frames of one walk along the preset's path.
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Walk the path this many times, forth and back (a capsule revisits): `frames × repeat`
    /// frames in all.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Image size: naneye (250×250), 320, voyager (720×480), potensic (1280×720), pal (720×576,
    /// a stereo endoscope's video).
    #[arg(long, default_value = "320")]
    pub size: String,
    /// Seed of texture and noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Peristaltic wall motion amplitude, mm (0 = rigid).
    #[arg(long = "deform", value_name = "MM", default_value_t = 0.0)]
    pub deform_mm: f64,
    /// The wall starts to move at this frame (still before it; the wave grows to its amplitude
    /// over a second): a still wall that starts moving, for the non-rigid tracker's detection.
    #[arg(long = "deform-onset", value_name = "FRAME", default_value_t = 0)]
    pub deform_onset_frame: usize,
    /// With wall motion, also write the true surface at every N-th frame
    /// (`gt_surface_NNNNNN.ply`; the first, middle and last frame always get one), for the live
    /// surface error of `run` and `eval`.
    #[arg(long = "surface-every", value_name = "N", default_value_t = 0)]
    pub surface_every: usize,
    /// Scale of the specular highlights (default: 1, preset 7: 2.5; 0 = none).
    #[arg(long)]
    pub specular: Option<f64>,
    /// Scale of the sensor noise (default: 1, preset 6: 5; 0 = none).
    #[arg(long)]
    pub noise: Option<f64>,
    /// Error added to the depth the sensor reads: `none`, `smooth:R` (depth × (1 + R·F), F a
    /// smooth unit-variance field drawn anew each frame; e.g. smooth:0.05) or `structured` (an
    /// organ-scale structured-light sensor: σ = 0.2 m⁻¹·z², 1/8 px disparity steps, holes at
    /// grazing walls and depth edges). The exact depth goes to `depth_clean/`.
    #[arg(long = "depth-noise", value_name = "KIND", default_value = "none")]
    pub depth_noise: capsule_slam_phantom::depth_noise::DepthNoise,
    /// Tissue texture: `tissue` or `none` (uniform albedo, for shape from shading).
    #[arg(long, default_value = "tissue")]
    pub texture: String,
    /// Light offset from the optical centre along camera x, mm.
    #[arg(long, default_value_t = 0.0)]
    pub light_offset_mm: f64,
    /// Motion-blur sub-samples per frame (1 = off).
    #[arg(long, default_value_t = 1)]
    pub motion_blur: u32,
    /// A lens: `radial-tangential:k1,k2,p1,p2,k3` (or 8 numbers with k4,k5,k6) or
    /// `equidistant:k1,k2,k3,k4` (OpenCV's models and order). The frames are rendered through it
    /// (each pixel's own ray), `camera.toml` names it, the ground truth is the same.
    #[arg(long)]
    pub distortion: Option<String>,
    /// A stereo capsule: a second camera this many mm along +x (5 when no value is given), the
    /// light midway; writes `rgb_right/`, `rgb_right.txt` and `camera.toml`'s `[right]` table.
    #[arg(long, num_args = 0..=1, default_missing_value = "5", value_name = "BASELINE_MM")]
    pub stereo: Option<f64>,
    /// Output folder.
    #[arg(long, default_value = "phantom")]
    pub out: PathBuf,
    /// Also write contact_sheet.png with every 30th frame.
    #[arg(long)]
    pub contact_sheet: bool,
    /// Also write this many flat-field calibration frames (a white target facing the capsule at
    /// 25 mm, no ambient light) into `flat_field/`, for `calibrate-vignetting`.
    #[arg(long, default_value_t = 0)]
    pub flat_field: usize,
    /// No progress bar.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Distance of the synthetic flat-field target, metres.
pub const FLAT_FIELD_DISTANCE_M: f64 = 0.025;

impl SynthArgs {
    /// The phantom spec these arguments describe.
    pub fn spec(&self) -> anyhow::Result<PhantomSpec> {
        let mut s = PhantomSpec::preset(self.preset);
        s.frames = self.frames;
        s.repeat = self.repeat;
        s.size = SizePreset::parse(&self.size).ok_or_else(|| anyhow!("--size {}: use naneye, 320, voyager, potensic or pal", self.size))?;
        s.seed = self.seed;
        s.deform_mm = self.deform_mm;
        s.deform_onset_frame = self.deform_onset_frame;
        s.surface_every = self.surface_every;
        s.depth_noise = self.depth_noise;
        if let Some(v) = self.specular {
            s.specular = v;
        }
        if let Some(v) = self.noise {
            s.noise = v;
        }
        s.texture = match self.texture.as_str() {
            "tissue" => true,
            "none" => false,
            t => return Err(anyhow!("--texture {t}: use tissue or none")),
        };
        s.light_offset_mm = self.light_offset_mm;
        s.motion_blur = self.motion_blur;
        s.distortion = self.distortion.as_deref().map(parse_lens).transpose()?;
        s.stereo_baseline_mm = self.stereo;
        Ok(s)
    }
}

/// Parses `--distortion MODEL:k1,k2,...` into a lens, with every problem named.
fn parse_lens(text: &str) -> anyhow::Result<LensModel> {
    let usage = "use radial-tangential:k1,k2,p1,p2,k3 (or 8 numbers) or equidistant:k1,k2,k3,k4";
    let (model, numbers) = text.split_once(':').ok_or_else(|| anyhow!("--distortion {text}: no model name; {usage}"))?;
    let coefficients = numbers
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|e| anyhow!("--distortion {text}: `{v}` is not a number ({e}); {usage}")))
        .collect::<anyhow::Result<Vec<f64>>>()?;
    let spec = DistortionSpec::Table(DistortionTable { model: model.to_owned(), coefficients, unknown: Default::default() });
    if let Some(p) = spec.problems("--distortion").into_iter().next() {
        return Err(anyhow!("--distortion {text}: {} ({})", p.message, p.fix));
    }
    spec.model().ok_or_else(|| anyhow!("--distortion {text}: {usage}"))
}

/// Renders the sequence; returns the phantom and the wall-clock ms per frame.
pub fn synthesize(spec: PhantomSpec, out: &std::path::Path, quiet: bool) -> anyhow::Result<(Phantom, f64)> {
    let phantom = Phantom::new(spec).map_err(|e| anyhow!("invalid phantom settings: {e}"))?;
    let n = phantom.spec.frame_count();
    let bar = if quiet { ProgressBar::hidden() } else { ProgressBar::new(n as u64) };
    let done = AtomicUsize::new(0);
    let start = Instant::now();
    write_sequence(&phantom, out, &|_| {
        done.fetch_add(1, Ordering::Relaxed);
        bar.inc(1);
    })
    .with_context(|| format!("writing the phantom to {}", out.display()))?;
    bar.finish_and_clear();
    let ms = start.elapsed().as_secs_f64() * 1e3 / n as f64;
    Ok((phantom, ms))
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let spec = args.spec()?;
    let (phantom, ms) = synthesize(spec, &args.out, args.quiet)?;
    let n = phantom.spec.frame_count();
    if args.contact_sheet {
        let p = args.out.join("contact_sheet.png");
        contact_sheet(&args.out, n, 30, &p).with_context(|| format!("writing {}", p.display()))?;
    }
    if args.flat_field > 0 {
        let dir = args.out.join("flat_field");
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        for k in 0..args.flat_field {
            let p = dir.join(format!("{k:06}.png"));
            capsule_slam_io::images::write_rgb(&p, &phantom.render_flat_field(k, FLAT_FIELD_DISTANCE_M)).with_context(|| format!("writing {}", p.display()))?;
        }
        println!("{} flat-field frames in {}", args.flat_field, dir.display());
    }
    let (w, h) = phantom.spec.size.size();
    println!("preset {}  {} frames  {w}×{h}  path {:.1} mm  {:.1} ms per frame (incl. writing)", phantom.spec.preset, n, phantom.path_length_m() * 1e3, ms);
    println!("written to {}", args.out.display());
    Ok(())
}
