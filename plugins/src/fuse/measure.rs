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
    /// `λ = ‖K⁻¹ [u v 1]ᵀ‖` of the pixel (the depth gate compares along the ray).
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
            ctx.warn(format!("frame {}: the albedo image is {:?} but the depth {w}×{h}: the frame's albedo is not fused", frame.index, a.size()));
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
                let rho = ((x as f32 - cam.cx as f32).powi(2) + (y as f32 - cam.cy as f32).powi(2)).sqrt();
                let m = Measurement {
                    position_m: t * Point3::from(v),
                    normal: t.rotation * n,
                    colour: frame.colour.pixel(x, y),
                    confidence: confidence(rho, half_diag),
                    radius_m: radius(v.z, f_mean, n.z),
                    albedo: albedo.map_or(0.0, |a| a.at(x, y)).max(0.0),
                };
                out.push(PixelMeasurement { x, y, m, z_live_m: v.z, n_cam: n, lambda, ray_unit: ray / lambda });
            }
            out
        })
        .flatten_iter()
        .collect();
    ctx.count("ms_maps", clock.elapsed().as_secs_f64() * 1e3);
    out
}
