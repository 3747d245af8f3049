//! Writes a phantom sequence in the input layout (TUM RGB-D + `camera.toml`) with its ground
//! truth: `groundtruth.txt`, `gt_surface.ply` (rest shape; with deformation also
//! `gt_surface_NNNNNN.ply` at the first, middle and last frame; the `confidence` of each truth
//! point counts the frames that saw it, 0 = never observed), `specular/` masks, `diffuse/`
//! images, `vignetting.png` (16-bit, V × 65535), `light.toml` and `phantom.toml` (the spec,
//! written last: its presence marks a complete sequence).

use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicU32, Ordering};

use rayon::prelude::*;

use super::{Phantom, PhantomSpec};
use capsule_slam_framework::error::LoadError;
use capsule_slam_framework::files::{write_camera_file, write_light_file};
use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_framework::image::{Gray8, Rgb8};
use capsule_slam_io::{images, ply, tum};

/// The frames of an `n`-frame sequence that get a deformed ground-truth surface: the first, the
/// middle, the last and (`every` > 0) every `every`-th, in order.
pub fn surface_frames(n: usize, every: usize) -> Vec<usize> {
    let mut v = vec![0, n / 2, n.saturating_sub(1)];
    if every > 0 {
        v.extend((0..n).step_by(every));
    }
    v.sort_unstable();
    v.dedup();
    v
}

/// Sample spacing of the ground-truth surface, metres.
pub const SURFACE_SPACING_M: f64 = 0.0005;

/// Renders and writes every frame of `phantom` into `dir`; calls `on_frame` after each.
pub fn write_sequence(phantom: &Phantom, dir: &Path, on_frame: &(dyn Fn(usize) + Sync)) -> Result<(), LoadError> {
    let clean = (phantom.spec.depth_noise != crate::depth_noise::DepthNoise::None).then_some("depth_clean");
    let stereo = phantom.spec.stereo_baseline_mm.is_some();
    for sub in ["rgb", "depth", "diffuse", "specular"].into_iter().chain(clean).chain(stereo.then_some("rgb_right")) {
        let d = dir.join(sub);
        std::fs::create_dir_all(&d).map_err(|e| LoadError::io(&d, e))?;
    }
    let spec_file = dir.join("phantom.toml");
    if spec_file.exists() {
        std::fs::remove_file(&spec_file).map_err(|e| LoadError::io(&spec_file, e))?;
    }
    let n = phantom.spec.frame_count();
    let mut rest = phantom.clone();
    rest.shape.wave_m = 0.0;
    let mut surface = rest.surface(0.0, SURFACE_SPACING_M);
    let seen: Vec<AtomicU32> = surface.surfels.iter().map(|_| AtomicU32::new(0)).collect();
    (0..n).into_par_iter().try_for_each(|i| -> Result<(), LoadError> {
        let f = phantom.render(i);
        mark_visible(phantom, &f, &surface, &seen);
        images::write_rgb(&dir.join(format!("rgb/{i:06}.png")), &f.rgb)?;
        images::write_rgb(&dir.join(format!("diffuse/{i:06}.png")), &f.diffuse)?;
        images::write_depth(&dir.join(format!("depth/{i:06}.png")), &f.measured_depth_m, 5000.0)?;
        if phantom.spec.depth_noise != crate::depth_noise::DepthNoise::None {
            images::write_depth(&dir.join(format!("depth_clean/{i:06}.png")), &f.depth_m, 5000.0)?;
        }
        let mask = Gray8::from_fn(f.specular.width(), f.specular.height(), |x, y| [if f.specular.at(x, y) { 255 } else { 0 }]);
        images::write_gray(&dir.join(format!("specular/{i:06}.png")), &mask)?;
        if stereo {
            let right = phantom.render_view(i, capsule_slam_framework::stereo::rectify::Side::Right);
            images::write_rgb(&dir.join(format!("rgb_right/{i:06}.png")), &right.rgb)?;
        }
        on_frame(i);
        Ok(())
    })?;

    let text = |name: &str, lines: Vec<String>| -> Result<(), LoadError> {
        let p = dir.join(name);
        std::fs::write(&p, lines.join("\n") + "\n").map_err(|e| LoadError::io(&p, e))
    };
    let stamps: Vec<f64> = (0..n).map(|i| phantom.time_s(i)).collect();
    text(
        "rgb.txt",
        std::iter::once("# timestamp filename".to_owned()).chain(stamps.iter().enumerate().map(|(i, t)| format!("{t:.6} rgb/{i:06}.png"))).collect(),
    )?;
    if stereo {
        text(
            "rgb_right.txt",
            std::iter::once("# timestamp filename".to_owned()).chain(stamps.iter().enumerate().map(|(i, t)| format!("{t:.6} rgb_right/{i:06}.png"))).collect(),
        )?;
    }
    text(
        "depth.txt",
        std::iter::once("# timestamp filename".to_owned()).chain(stamps.iter().enumerate().map(|(i, t)| format!("{t:.6} depth/{i:06}.png"))).collect(),
    )?;
    let gt: Vec<StampedPose> = (0..n).map(|i| StampedPose { timestamp_s: stamps[i], t_world_cam: phantom.pose(i) }).collect();
    tum::write_trajectory(&dir.join("groundtruth.txt"), &gt)?;
    write_camera_file(&dir.join("camera.toml"), &Phantom::camera_file_for(&phantom.spec))?;
    write_light_file(&dir.join("light.toml"), &phantom.light)?;
    let v = phantom.vignetting_field();
    images::write_gray16(&dir.join("vignetting.png"), &v, 65535.0)?;

    for (s, c) in surface.surfels.iter_mut().zip(&seen) {
        s.confidence = c.load(Ordering::Relaxed) as f32;
    }
    ply::write_surfels(&dir.join("gt_surface.ply"), &surface)?;
    if phantom.shape.wave_m > 0.0 {
        for i in surface_frames(n, phantom.spec.surface_every) {
            let mut at = phantom.surface(phantom.time_s(i), SURFACE_SPACING_M);
            for (s, r) in at.surfels.iter_mut().zip(&surface.surfels) {
                s.confidence = r.confidence;
            }
            ply::write_surfels(&dir.join(format!("gt_surface_{i:06}.ply")), &at)?;
        }
    }
    let spec_text = toml::to_string(&phantom.spec).map_err(|e| LoadError::parse(&spec_file, 0, e.to_string()))?;
    let mut f = std::fs::File::create(&spec_file).map_err(|e| LoadError::io(&spec_file, e))?;
    writeln!(f, "# capsule-slam phantom: `capsule-slam synth` with these settings reproduces this folder\n{spec_text}")
        .map_err(|e| LoadError::io(&spec_file, e))
}

/// Counts, for every truth point, whether frame `f` saw it: inside the field of view and within
/// 1 mm (plus the wave amplitude, as the truth is the rest shape) of the rendered depth.
fn mark_visible(phantom: &Phantom, f: &super::render::RenderedFrame, surface: &capsule_slam_framework::map::SurfelSet, seen: &[AtomicU32]) {
    let t_cam_world = f.t_world_cam.inverse();
    let tol = 0.001 + 1.5 * phantom.shape.wave_m;
    surface.surfels.par_iter().zip(seen).for_each(|(s, c)| {
        let p = t_cam_world * s.position_m.cast::<f64>();
        let Some(uv) = phantom.camera.project_distorted(&p) else { return };
        let (u, v) = (uv.x.round(), uv.y.round());
        if !phantom.camera.in_fov(u, v) {
            return;
        }
        let d = f64::from(f.depth_m.at(u as usize, v as usize));
        if d > 0.0 && (d - p.z).abs() < tol {
            c.fetch_add(1, Ordering::Relaxed);
        }
    });
}

/// Whether `dir` holds a complete sequence of exactly this spec (for caching).
pub fn is_complete(dir: &Path, spec: &PhantomSpec) -> bool {
    std::fs::read_to_string(dir.join("phantom.toml")).ok().and_then(|t| toml::from_str::<PhantomSpec>(&t).ok()).is_some_and(|s| &s == spec)
}

/// One PNG with every `step`-th frame's image, tiled 5 wide, so a person can see a sequence at
/// a glance.
pub fn contact_sheet(dir: &Path, n: usize, step: usize, out: &Path) -> Result<(), LoadError> {
    let picks: Vec<usize> = (0..n).step_by(step.max(1)).collect();
    let first = images::read_rgb(&dir.join("rgb/000000.png"), None)?;
    let (w, h) = first.size();
    let cols = picks.len().clamp(1, 5);
    let rows = picks.len().div_ceil(cols);
    let mut sheet = Rgb8::filled(cols * (w + 4), rows * (h + 4), 255);
    for (k, i) in picks.iter().enumerate() {
        let img = images::read_rgb(&dir.join(format!("rgb/{i:06}.png")), Some((w, h)))?;
        let (ox, oy) = ((k % cols) * (w + 4) + 2, (k / cols) * (h + 4) + 2);
        for y in 0..h {
            for x in 0..w {
                sheet.set_pixel(ox + x, oy + y, img.pixel(x, y));
            }
        }
    }
    images::write_rgb(out, &sheet)
}
