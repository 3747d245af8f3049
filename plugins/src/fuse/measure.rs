//! One frame's measurements for surfel fusion, in pixel order (rows, then columns): the same
//! for every surfel fuser, so that the CPU and GPU maps see identical input. Positions come
//! from the raw depth, normals from the bilateral-filtered depth (ElasticFusion).

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::RgbdFrame;
use capsule_slam_framework::{Context, Iso3};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::surfel_params::SurfelParams;
use super::surfel_rules::{Measurement, confidence, radius};
use crate::common::maps::{GeometryParams, geometry, normal, vertex};

/// A measurement with what association needs of its pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelMeasurement {
    /// Pixel column.
    pub x: usize,
    /// Pixel row.
    pub y: usize,
    /// The measurement, world frame.
    pub m: Measurement,
    /// Its depth along z, metres (camera frame).
    pub z_live_m: f32,
    /// Its normal, camera frame.
    pub n_cam: Vector3<f32>,
    /// `λ = ‖K⁻¹ [u v 1]ᵀ‖` of the pixel (the depth gate compares along the ray), divided by
    /// how far the pixel's depth σ widens the gate, `max(1, gate_sigmas · σ / depth_gate_m)`:
    /// the one number both fusers' gates read, so the widening needs no change of theirs.
    pub lambda: f32,
    /// Unit ray through the pixel, camera frame.
    pub ray_unit: Vector3<f32>,
}

/// The measurements of one frame at `t_world_cam`: one pixel in `subsample`² (rotating with
/// the frame index) with a valid vertex and normal. Files `ms_maps`.
pub fn measurements(frame: &RgbdFrame, t_world_cam: &Iso3, cam: &PinholeCamera, p: &SurfelParams, ctx: &mut Context) -> Vec<PixelMeasurement> {
    let clock = std::time::Instant::now();
    let g = geometry(
        frame,
        cam,
        &GeometryParams {
            min_m: p.min_depth_m,
            max_m: p.max_depth_m,
            radius_px: p.bilateral_radius_px as usize,
            sigma_px: p.bilateral_sigma_px,
            sigma_m: p.bilateral_sigma_m,
            edge_jump_m: p.edge_jump_m,
        },
    );
    let (v_raw, n_map) = (&g.v_raw, &g.normals);
    let (w, h) = g.raw.size();
    let sigma = frame.depth_sigma_m.as_ref().filter(|s| {
        let fits = s.size() == (w, h);
        if !fits {
            ctx.warn(format!("the depth σ image is {:?} but the depth {w}×{h}: the fixed depth gate is used", s.size()));
        }
        fits
    });
    let step = p.subsample as usize;
    let phase = frame.index % step.max(1);
    let half_diag = cam.half_diagonal_px() as f32;
    let f_mean = (0.5 * (cam.fx + cam.fy)) as f32;
    let t = t_world_cam.cast::<f32>();
    // An albedo image of another size than the depth is left out, with a warning naming it
    // (a depth estimator's bug, not the map's to crash on).
    let albedo = frame.albedo.as_ref().filter(|a| {
        let fits = a.size() == (w, h);
        if !fits {
            ctx.warn(format!("the albedo image is {:?} but the depth {w}×{h}: the frame's albedo is not fused", a.size()));
        }
        fits
    });
    let out = (0..h)
        .into_par_iter()
        .filter(|y| y % step == phase)
        .map(|y| {
            let mut out = Vec::new();
            for x in (phase..w).step_by(step) {
                let (Some(v), Some(n)) = (vertex(v_raw, x, y), normal(n_map, x, y)) else { continue };
                let ray = Vector3::new((x as f32 - cam.cx as f32) / cam.fx as f32, (y as f32 - cam.cy as f32) / cam.fy as f32, 1.0);
                let lambda = ray.norm();
                let widen = sigma.map_or(1.0, |s| (p.gate_sigmas * s.at(x, y) / p.depth_gate_m).max(1.0));
                let rho = ((x as f32 - cam.cx as f32).powi(2) + (y as f32 - cam.cy as f32).powi(2)).sqrt();
                let m = Measurement {
                    position_m: t * Point3::from(v),
                    normal: t.rotation * n,
                    colour: frame.colour.pixel(x, y),
                    confidence: confidence(rho, half_diag),
                    radius_m: radius(v.z, f_mean, n.z),
                    albedo: albedo.map_or(0.0, |a| a.at(x, y)).max(0.0),
                    sigma_m: sigma.map_or(0.0, |s| s.at(x, y)).max(0.0),
                };
                out.push(PixelMeasurement { x, y, m, z_live_m: v.z, n_cam: n, lambda: lambda / widen, ray_unit: ray / lambda });
            }
            out
        })
        .flatten_iter()
        .collect();
    ctx.count("ms_maps", clock.elapsed().as_secs_f64() * 1e3);
    out
}

#[cfg(test)]
mod tests {
    use capsule_slam_framework::context::StageReport;
    use capsule_slam_framework::{Context, DepthMap};

    use super::*;
    use crate::fuse::surfel_rules::depth_gate;
    use crate::testing::{phantom, rgbd, rig};

    #[test]
    fn the_depth_gate_widens_to_gate_sigmas_of_the_pixels_sigma() {
        let ph = phantom(1, 300, 0.0);
        let (rig, p) = (rig(&ph), SurfelParams::default());
        let mut frame = rgbd(&ph, 20);
        let t = frame.gt_t_world_cam.unwrap();
        let mut r = StageReport::default();
        let exact = measurements(&frame, &t, &ph.camera, &p, &mut Context::new(20, &rig, None, &mut r));
        // σ 2 mm: the 2 mm gate becomes 12 mm (6 σ), so λ (the gate's only reader) shrinks 6 ×;
        // a σ of 0.1 mm leaves the gate alone.
        for (sigma, widen) in [(0.002f32, 6.0f32), (0.0001, 1.0)] {
            frame.depth_sigma_m = Some(DepthMap::from_fn(frame.depth_m.width(), frame.depth_m.height(), |_, _| [sigma]));
            let noisy = measurements(&frame, &t, &ph.camera, &p, &mut Context::new(20, &rig, None, &mut r));
            assert_eq!(noisy.len(), exact.len());
            for (a, b) in exact.iter().zip(&noisy) {
                assert!((a.lambda / b.lambda - widen).abs() < 1e-4, "λ {} against {}", a.lambda, b.lambda);
                assert_eq!(a.m, Measurement { sigma_m: 0.0, ..b.m }, "only σ differs");
                assert_eq!(b.m.sigma_m, sigma, "the measurement carries its pixel's σ");
            }
        }
        // The tail of a correlated error: a measurement 4 σ behind its surfel (a 5 % error of
        // 2 mm, 8 mm off) still merges into it instead of starting a second layer.
        frame.depth_sigma_m = Some(DepthMap::from_fn(frame.depth_m.width(), frame.depth_m.height(), |_, _| [0.002]));
        let noisy = measurements(&frame, &t, &ph.camera, &p, &mut Context::new(20, &rig, None, &mut r));
        let m = &noisy[noisy.len() / 2];
        assert!(depth_gate(m.z_live_m + 0.008, m.z_live_m, m.lambda, p.depth_gate_m));
        assert!(!depth_gate(m.z_live_m + 0.013, m.z_live_m, m.lambda, p.depth_gate_m), "beyond 6 σ it does not");
        // A σ image of another size is left out with a warning.
        frame.depth_sigma_m = Some(DepthMap::new(3, 3));
        let odd = measurements(&frame, &t, &ph.camera, &p, &mut Context::new(20, &rig, None, &mut r));
        assert_eq!(odd, exact);
        assert!(r.warnings.iter().any(|w| w.contains("σ image")), "{:?}", r.warnings);
    }
}
