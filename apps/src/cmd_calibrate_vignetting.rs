//! `capsule-slam calibrate-vignetting`: fit `vignetting.toml` to flat-field frames, images of a
//! matte uniform target facing the capsule under its own light (Goldman 2010, "Vignette and exposure calibration and compensation", IEEE TPAMI 32(12); Kim & Pollefeys 2008): the frames
//! are linearised and averaged, the target's own cos³α is divided out and the lens-and-light
//! profile V · μ is fitted as an even polynomial about the principal point
//! (`capsule_slam_calib::fit_flat_field`).

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use capsule_slam_calib::centre_value;
use capsule_slam_framework::files::{read_camera_file, write_vignetting_file};
use capsule_slam_framework::frame::Falloff;
use capsule_slam_framework::light::vignetting::{RadialProfile, profile_falloff, radius2};
use capsule_slam_io::images;
use capsule_slam_io::undistort::Undistortion;

/// Arguments of `calibrate-vignetting`.
#[derive(clap::Args, Debug)]
pub struct CalibrateVignettingArgs {
    /// Folder of flat-field frames (PNG, JPEG or BMP; all of one size), e.g. the `flat_field/`
    /// of `capsule-slam synth --flat-field 8`.
    #[arg(long)]
    images: PathBuf,
    /// The capsule's camera.toml (principal point, focal length, field of view).
    #[arg(long)]
    camera: PathBuf,
    /// Encoding exponent of the pixels (pixel = linear^(1/gamma)); `calibrate-light` fits it.
    #[arg(long, default_value_t = 2.2)]
    gamma: f64,
    /// Polynomial terms (r², r⁴, r⁶): 1 to 3.
    #[arg(long, default_value_t = 3)]
    degree: usize,
    /// Where to write the profile.
    #[arg(long, default_value = "vignetting.toml")]
    out: PathBuf,
}

pub fn run(args: &CalibrateVignettingArgs) -> anyhow::Result<()> {
    if !(1..=3).contains(&args.degree) {
        bail!("--degree {}: use 1, 2 or 3", args.degree);
    }
    if !(args.gamma.is_finite() && args.gamma > 0.0) {
        bail!("--gamma {}: must be positive", args.gamma);
    }
    // With a lens, the frames are undistorted as `run` undistorts them: the fit is then in the
    // pixels the stages see.
    let lens_cam = read_camera_file(&args.camera)?.camera();
    let undistortion = lens_cam.distortion.is_some().then(|| Undistortion::new(&lens_cam));
    let cam = undistortion.as_ref().map_or(lens_cam.clone(), |u| u.camera().clone());
    let files = images::list_images(&args.images).with_context(|| format!("reading the flat-field folder {}", args.images.display()))?;
    if files.is_empty() {
        bail!("{} holds no PNG, JPEG or BMP image: give the folder of flat-field frames", args.images.display());
    }
    let (w, h) = (cam.width, cam.height);
    let mut sum = vec![0.0f64; w * h];
    let mut clipped = 0usize;
    for f in &files {
        let img = images::read_rgb(f, Some((w, h))).with_context(|| format!("flat-field frame {} (fix camera.toml or the frame)", f.display()))?;
        let img = match &undistortion {
            Some(u) => u.rgb(&img),
            None => img,
        };
        for (k, px) in img.data().chunks_exact(3).enumerate() {
            if px.iter().any(|c| *c >= 250) {
                clipped += 1;
            }
            let lum: f64 = px.iter().zip(capsule_slam_framework::image::NTSC_WEIGHTS).map(|(c, wt)| wt * (f64::from(*c) / 255.0).powf(args.gamma)).sum();
            sum[k] += lum;
        }
    }
    let mean: Vec<f64> = sum.iter().map(|s| s / files.len() as f64).collect();
    let Some(file) = capsule_slam_calib::fit_flat_field(&mean, &cam, args.gamma, args.degree) else {
        bail!("the flat field could not be fitted: the frames are black at the principal point or cover too few radii");
    };
    write_vignetting_file(&args.out, &file)?;
    // Residual of the fit per ring of r².
    let profile = RadialProfile { coeffs: file.lens_and_light.clone() };
    let centre = centre_value(&mean, &cam).unwrap_or(1.0);
    let mut rings = [(0.0, 0.0); 8];
    for (k, m) in mean.iter().enumerate() {
        let (u, v) = ((k % w) as f64, (k / w) as f64);
        if !cam.in_fov(u, v) || *m <= 0.0 {
            continue;
        }
        let r = ((radius2(&cam, u, v) * 8.0) as usize).min(7);
        rings[r].0 += m / centre / profile_falloff(&profile, &cam, u, v, Falloff::FlatField);
        rings[r].1 += 1.0;
    }
    println!("{} flat-field frames, {}×{}; {} clipped pixel values", files.len(), w, h, clipped);
    println!("lens_and_light = {:?} (F = 1 + c1 r² + c2 r⁴ + c3 r⁶; the flat field adds cos³α)", file.lens_and_light);
    println!("flat field / fit per ring of r²: {}", rings.iter().filter(|r| r.1 > 0.0).map(|r| format!("{:.3}", r.0 / r.1)).collect::<Vec<_>>().join(" "));
    println!("written to {}", args.out.display());
    Ok(())
}
