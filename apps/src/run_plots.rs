//! `run`'s pictures in `out/plots/` (issue 20), so that a user looks before reading numbers:
//! with ground truth the trajectory over it from the top and the side and the position error
//! over time (`plot.rs`, aligned as the run's headline ATE); always the final map splatted by
//! `surfel-cpu`'s renderer (`predict`, the disc splatting the tracker's prediction uses) from
//! three viewpoints outside it, in colour and by confidence.

use std::path::Path;

use anyhow::{Context as _, Result};
use capsule_slam_eval::{align_trajectory, associate};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::StampedPose;
use capsule_slam_framework::{Iso3, Rgb8, SurfelSet};
use capsule_slam_plugins::fuse::surfel_cpu::{SplatDepths, predict};
use nalgebra::{Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// The confidence shown as the top of the ramp (surfel-cpu's `stable_confidence` default).
const STABLE_CONFIDENCE: f32 = 10.0;

/// Writes the plots; returns how many images it wrote.
pub fn write(dir: &Path, trajectory: &[StampedPose], truth: &[StampedPose], tolerance_s: f64, sim3: bool, map: Option<&SurfelSet>) -> Result<usize> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut written = 0;
    if let Some(align) = align_trajectory(trajectory, truth, tolerance_s, sim3) {
        let pairs: Vec<(StampedPose, StampedPose)> = associate(trajectory, truth, tolerance_s)
            .into_iter()
            .map(|(e, g)| (StampedPose { timestamp_s: e.timestamp_s, t_world_cam: align.apply_pose(&e.t_world_cam) }, *g))
            .collect();
        crate::plot::plot(dir, &pairs)?;
        written += 3;
    }
    if let Some(map) = map.filter(|m| !m.surfels.is_empty()) {
        for (name, forward, down) in VIEWS {
            let (cam, pose, far) = viewpoint(map, Vector3::from(forward), Vector3::from(down));
            let view = predict(&map.surfels, |_| true, &cam, &pose, &SplatDepths { min_m: 1e-4, max_m: far, blend_m: 0.0, stable: STABLE_CONFIDENCE });
            let conf = Rgb8::from_fn(cam.width, cam.height, |x, y| {
                let c = view.confidence.at(x, y);
                crate::cmd_depth::ramp((view.depth_m.at(x, y) > 0.0).then(|| f64::from((c / STABLE_CONFIDENCE).min(1.0))))
            });
            for (kind, img) in [("colour", &view.colour), ("confidence", &conf)] {
                let p = dir.join(format!("map_{name}_{kind}.png"));
                capsule_slam_io::images::write_rgb(&p, img).with_context(|| format!("writing {}", p.display()))?;
                written += 1;
            }
        }
    }
    Ok(written)
}

/// The viewpoints: name, viewing direction and the image's down direction (world frame; the
/// world is the first camera's, z forward, y down).
const VIEWS: [(&str, [f32; 3], [f32; 3]); 3] =
    [("front", [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]), ("top", [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]), ("side", [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])];

/// A camera looking along `forward` at the map's centroid from outside it (2.5 × its 95th
/// percentile radius away), and the far limit of its depth range.
fn viewpoint(map: &SurfelSet, forward: Vector3<f32>, down: Vector3<f32>) -> (PinholeCamera, Iso3, f32) {
    let n = map.surfels.len() as f32;
    let centre = map.surfels.iter().fold(Vector3::zeros(), |a, s| a + s.position_m.coords) / n;
    let mut r: Vec<f32> = map.surfels.iter().map(|s| (s.position_m.coords - centre).norm()).collect();
    r.sort_by(f32::total_cmp);
    let radius = r[((r.len() - 1) as f32 * 0.95) as usize].max(1e-3);
    let eye = Point3::from(centre - forward * 2.5 * radius);
    let y = (down - forward * down.dot(&forward)).normalize();
    let x = y.cross(&forward);
    let rotation = Rotation3::from_basis_unchecked(&[x, y, forward]);
    let pose = Iso3::from_parts(Translation3::from(eye.coords.cast::<f64>()), UnitQuaternion::from_rotation_matrix(&rotation.cast::<f64>()));
    (PinholeCamera::new(640, 480, 500.0, 500.0, 319.5, 239.5), pose, 5.0 * radius)
}
