//! Rendering surfels into a camera: the index map (each surfel a point, for association) and
//! the splatted prediction (each surfel a disc, ray–disc intersection per pixel, nearest wins).
//! Both resolve the z-test with an atomic minimum over (depth bits, index), so they are parallel
//! and deterministic.

use std::sync::atomic::{AtomicU64, Ordering};

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::{Iso3, ModelView, Surfel};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

const EMPTY: u64 = u64::MAX;

fn pack(depth_m: f32, idx: usize) -> u64 {
    (u64::from(depth_m.to_bits()) << 32) | idx as u64
}

fn unpack(v: u64) -> (f32, usize) {
    (f32::from_bits((v >> 32) as u32), (v & 0xFFFF_FFFF) as usize)
}

/// The active model as points: per pixel the nearest surfel's index and its camera-frame
/// position and normal.
pub struct IndexMap {
    /// Width.
    pub width: usize,
    /// Surfel index per pixel (`u32::MAX` = empty).
    pub index: Vec<u32>,
    /// Camera-frame position per pixel.
    pub p_cam: Vec<Point3<f32>>,
    /// Camera-frame normal per pixel.
    pub n_cam: Vec<Vector3<f32>>,
}

impl IndexMap {
    /// Renders the surfels `include` accepts as 1-pixel points seen from `t_world_cam`.
    pub fn render(surfels: &[Surfel], include: impl Fn(&Surfel) -> bool + Sync, cam: &PinholeCamera, t_world_cam: &Iso3, max_depth_m: f32) -> Self {
        let (w, h) = (cam.width, cam.height);
        let zbuf: Vec<AtomicU64> = (0..w * h).map(|_| AtomicU64::new(EMPTY)).collect();
        let t_cam_world = t_world_cam.inverse().cast::<f32>();
        surfels.par_iter().enumerate().for_each(|(i, s)| {
            if !include(s) {
                return;
            }
            let p = t_cam_world * s.position_m;
            if p.z <= 0.0 || p.z > max_depth_m {
                return;
            }
            let u = (cam.fx as f32 * p.x / p.z + cam.cx as f32).round();
            let v = (cam.fy as f32 * p.y / p.z + cam.cy as f32).round();
            if u < 0.0 || v < 0.0 || u >= w as f32 || v >= h as f32 {
                return;
            }
            zbuf[v as usize * w + u as usize].fetch_min(pack(p.z, i), Ordering::Relaxed);
        });
        let mut index = vec![u32::MAX; w * h];
        let mut p_cam = vec![Point3::origin(); w * h];
        let mut n_cam = vec![Vector3::zeros(); w * h];
        for (k, z) in zbuf.iter().enumerate() {
            let v = z.load(Ordering::Relaxed);
            if v != EMPTY {
                let (_, i) = unpack(v);
                index[k] = i as u32;
                p_cam[k] = t_cam_world * surfels[i].position_m;
                n_cam[k] = t_cam_world.rotation * surfels[i].normal;
            }
        }
        Self { width: w, index, p_cam, n_cam }
    }
}

/// Splats the surfels `include` accepts as discs into a prediction seen from `t_world_cam`.
pub fn predict(
    surfels: &[Surfel],
    include: impl Fn(&Surfel) -> bool + Sync,
    cam: &PinholeCamera,
    t_world_cam: &Iso3,
    min_depth_m: f32,
    max_depth_m: f32,
) -> ModelView {
    let (w, h) = (cam.width, cam.height);
    let zbuf: Vec<AtomicU64> = (0..w * h).map(|_| AtomicU64::new(EMPTY)).collect();
    let t_cam_world = t_world_cam.inverse().cast::<f32>();
    let (fx, fy, cx, cy) = (cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32);
    surfels.par_iter().enumerate().for_each(|(i, s)| {
        if !include(s) {
            return;
        }
        let p = t_cam_world * s.position_m;
        if p.z <= min_depth_m || p.z > max_depth_m {
            return;
        }
        let n = t_cam_world.rotation * s.normal;
        let (u, v) = (fx * p.x / p.z + cx, fy * p.y / p.z + cy);
        // Bounding box of the disc: a disc of radius r at depth z projects inside a circle of
        // r·f/z pixels (tilting only shrinks it), widened by a quarter for perspective (capped).
        let r_px = s.radius_m * fx.max(fy) / p.z;
        let half = (1.25 * r_px).ceil().min(12.0) as i64;
        let (u0, v0) = (u.round() as i64, v.round() as i64);
        let np = n.dot(&p.coords);
        let r2 = s.radius_m * s.radius_m;
        for y in (v0 - half).max(0)..=(v0 + half).min(h as i64 - 1) {
            for x in (u0 - half).max(0)..=(u0 + half).min(w as i64 - 1) {
                // Ray through the pixel centre, z = 1; plane n·(X − p) = 0.
                let d = Vector3::new((x as f32 - cx) / fx, (y as f32 - cy) / fy, 1.0);
                let nd = n.dot(&d);
                if nd.abs() < 1e-6 {
                    continue;
                }
                let t = np / nd;
                if t <= min_depth_m || t > max_depth_m || (d * t - p.coords).norm_squared() > r2 {
                    continue;
                }
                // Read first: most candidates lose the z-test, and a plain load is far cheaper
                // than an atomic read-modify-write.
                let (cell, v) = (&zbuf[y as usize * w + x as usize], pack(t, i));
                if v < cell.load(Ordering::Relaxed) {
                    cell.fetch_min(v, Ordering::Relaxed);
                }
            }
        }
    });
    let mut view = ModelView::empty(w, h, *t_world_cam);
    for (k, z) in zbuf.iter().enumerate() {
        let v = z.load(Ordering::Relaxed);
        if v == EMPTY {
            continue;
        }
        let (depth, i) = unpack(v);
        let (x, y) = (k % w, k / w);
        let s = &surfels[i];
        let n = t_cam_world.rotation * s.normal;
        *view.depth_m.at_mut(x, y) = depth;
        view.normals_cam.set_pixel(x, y, [n.x, n.y, n.z]);
        view.colour.set_pixel(x, y, s.colour);
        *view.confidence.at_mut(x, y) = s.confidence;
        *view.t0.at_mut(x, y) = s.t0;
        *view.t.at_mut(x, y) = s.t;
        *view.albedo.at_mut(x, y) = s.albedo;
    }
    view
}
