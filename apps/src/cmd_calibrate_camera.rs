//! `capsule-slam calibrate-camera`: intrinsics and lens from checkerboard images
//! (`capsule_slam_calib::board` finds and refines the corners, `camera_fit` fits Zhang's model
//! and refines it by Levenberg-Marquardt); prints the reprojection error of every image and
//! writes `camera.toml`.

use std::path::PathBuf;

use anyhow::{Context as _, anyhow, bail};
use capsule_slam_calib::board::{Board, detect_board};
use capsule_slam_calib::camera_fit::{LensKind, fit_camera};
use capsule_slam_framework::camera::CameraFile;
use capsule_slam_framework::files::write_camera_file;
use capsule_slam_framework::lens::DistortionSpec;
use capsule_slam_io::images;

/// Arguments of `calibrate-camera`.
#[derive(clap::Args, Debug)]
pub struct CalibrateCameraArgs {
    /// Folder of checkerboard images (PNG, JPEG, BMP), all of one size.
    #[arg(long)]
    images: PathBuf,
    /// Inner corners of the board, COLSxROWS (OpenCV's pattern size; a board of 8 × 7 squares
    /// has 7x6). Images whose grid is larger are left out; partial grids are used.
    #[arg(long)]
    board: String,
    /// Side of a square, millimetres (sets the scale of the board poses only: the intrinsics
    /// do not depend on it).
    #[arg(long)]
    square_mm: f64,
    /// Lens model to fit: radial-tangential (k1 k2 p1 p2 k3) or equidistant (fisheye k1..k4).
    #[arg(long, default_value = "radial-tangential")]
    model: String,
    /// Where to write the camera.
    #[arg(long, default_value = "camera.toml")]
    out: PathBuf,
}

pub fn run(args: &CalibrateCameraArgs) -> anyhow::Result<()> {
    let (cols, rows) = args
        .board
        .split_once(['x', 'X', '×'])
        .and_then(|(c, r)| Some((c.trim().parse::<usize>().ok()?, r.trim().parse::<usize>().ok()?)))
        .filter(|(c, r)| *c >= 2 && *r >= 2)
        .ok_or_else(|| anyhow!("--board {}: give the inner corners as COLSxROWS, e.g. 7x6", args.board))?;
    if !(args.square_mm.is_finite() && args.square_mm > 0.0) {
        bail!("--square-mm {}: give the side of a square in millimetres", args.square_mm);
    }
    let lens = match args.model.as_str() {
        "radial-tangential" => LensKind::RadialTangential,
        "equidistant" => LensKind::Equidistant,
        m => bail!("--model {m}: use radial-tangential or equidistant"),
    };
    let board = Board { cols, rows, square_m: args.square_mm * 1e-3 };
    let files = images::list_images(&args.images).with_context(|| format!("reading the image folder {}", args.images.display()))?;
    if files.is_empty() {
        bail!("{} holds no PNG, JPEG or BMP image: give the folder of checkerboard images", args.images.display());
    }
    // The first image sets the size every other must have.
    let mut size = None;
    let mut views = Vec::new();
    for f in &files {
        let name = f.file_name().map_or_else(|| f.display().to_string(), |n| n.to_string_lossy().into_owned());
        let img = images::read_rgb(f, size).with_context(|| format!("checkerboard image {} (all images must have the first one's size)", f.display()))?;
        size = Some(img.size());
        match detect_board(&img, &board, &name) {
            Ok(v) => {
                println!("{name:<44} {} corners", v.corners.len());
                views.push(v);
            }
            Err(e) => eprintln!("warning: {name}: {e}; left out"),
        }
    }
    let size = size.unwrap_or_default();
    let fit = fit_camera(&views, size.0, size.1, lens).map_err(|e| anyhow!("{e} (from {} images in {})", files.len(), args.images.display()))?;
    for (name, why) in &fit.dropped {
        eprintln!("warning: {name}: left out of the fit: {why}");
    }
    println!("\nreprojection RMS per image (px):");
    for (name, rms) in &fit.views {
        println!("  {name:<44} {rms:.3}");
    }
    let [fx, fy, cx, cy] = fit.intrinsics;
    println!("\nreprojection RMS  {:.3} px over {} images", fit.rms_px, fit.views.len());
    println!("fx fy cx cy       {fx:.3} {fy:.3} {cx:.3} {cy:.3} px");
    println!("lens              {} {:?}", fit.lens.name(), fit.lens.coefficients());
    let file = CameraFile {
        width: size.0 as u32,
        height: size.1 as u32,
        fx,
        fy,
        cx,
        cy,
        depth_scale: 5000.0,
        distortion: Some(DistortionSpec::from_model(&fit.lens)),
        fov_radius_px: None,
        baseline_m: None,
        right: None,
        depth_noise: None,
    };
    write_camera_file(&args.out, &file)?;
    println!("written           {} (add fov_radius_px for a round field of view)", args.out.display());
    Ok(())
}
