//! The model points the warp is fitted on and what the live frame says about them.
//!
//! Model points are the prediction's pixels on a regular grid (the surfels the tracker sees,
//! already splatted), lifted to the world at the pose the prediction was rendered from; each
//! keeps its normal and the previous live frame's intensity there (the photometric reference,
//! lit like the live frame; `icp-rgb`'s `previous-frame` choice).

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::{GrayF32, Iso3, ModelView};
use nalgebra::{Point3, Vector3};

use crate::common::maps::{normal, vertex};
use crate::common::pyramid::Bilinear;
use crate::track::icp_rgb::frames::Level;

/// One model point.
#[derive(Debug, Clone, Copy)]
pub struct ModelPoint {
    /// Position, metres, world frame.
    pub x_world_m: Point3<f64>,
    /// Unit normal, world frame.
    pub n_world: Vector3<f64>,
    /// Reference intensity in [0, 1], if the previous frame saw the pixel.
    pub gray_ref: Option<f64>,
    /// σ of its predicted depth, metres (`ModelView::sigma_m`; 0 = none).
    pub sigma_m: f64,
}

/// The prediction's valid pixels every `stride` pixels whose surface faces the camera within
/// `max_incidence_rad` (grazing walls give unstable correspondences), in raster order.
pub fn sample(model: &ModelView, cam: &PinholeCamera, previous_gray: Option<&GrayF32>, stride: usize, max_incidence_rad: f64) -> Vec<ModelPoint> {
    let min_cos = max_incidence_rad.cos();
    let (w, h) = model.depth_m.size();
    let t_wc = model.t_world_cam;
    let r_wc = t_wc.rotation;
    let stride = stride.max(1);
    let mut out = Vec::with_capacity((w / stride + 1) * (h / stride + 1));
    for y in (stride / 2..h).step_by(stride) {
        for x in (stride / 2..w).step_by(stride) {
            let z = f64::from(model.depth_m.at(x, y));
            let n = model.normals_cam.pixel(x, y);
            if z <= 0.0 || !z.is_finite() || n == [0.0; 3] {
                continue;
            }
            let n_cam = Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2]));
            if !n_cam.iter().all(|v| v.is_finite()) {
                continue;
            }
            let x_cam = cam.unproject(x as f64, y as f64, z);
            if n_cam.dot(&x_cam.coords).abs() < min_cos * x_cam.coords.norm() {
                continue;
            }
            let gray_ref = previous_gray.map(|g| f64::from(g.at(x, y))).filter(|v| *v > 0.0);
            out.push(ModelPoint { x_world_m: t_wc * x_cam, n_world: r_wc * n_cam, gray_ref, sigma_m: f64::from(model.sigma_m.at(x, y)) });
        }
    }
    out
}

/// What the live level says at the projection of a world point.
pub struct LiveSample {
    /// The live vertex there, world frame.
    pub p_world_m: Point3<f64>,
    /// The live normal there, world frame.
    pub n_world: Vector3<f64>,
    /// The point in the live camera frame.
    pub q_cam_m: Vector3<f64>,
    /// Intensity and its gradient (per level pixel) by bilinear interpolation, if defined.
    pub gray: Option<(f64, f64, f64)>,
    /// The live depth at the nearest pixel, metres.
    pub depth_m: f64,
    /// The live depth's σ there, metres (0 when the frame carries none).
    pub sigma_m: f64,
}

/// Samples the live level at the projection of `x_world` seen from `t_world_cam`.
pub fn look(level: &Level, t_world_cam: &Iso3, x_world: &Point3<f64>) -> Option<LiveSample> {
    let q = t_world_cam.inverse_transform_point(x_world).coords;
    if q.z <= 0.0 {
        return None;
    }
    let cam = &level.cam;
    let (w, h) = level.depth.size();
    let (uf, vf) = (cam.fx * q.x / q.z + cam.cx, cam.fy * q.y / q.z + cam.cy);
    if !(uf >= -0.5 && vf >= -0.5 && uf.is_finite() && vf.is_finite()) {
        return None;
    }
    let (ui, vi) = ((uf + 0.5) as usize, (vf + 0.5) as usize);
    if ui >= w || vi >= h {
        return None;
    }
    let d = vertex(&level.vertices, ui, vi)?;
    let n = normal(&level.normals, ui, vi)?;
    let gray = Bilinear::at(w, h, uf, vf)
        .filter(|b| !b.corners(&level.gray).contains(&0.0))
        .map(|b| (f64::from(b.sample(&level.gray)), f64::from(b.sample(&level.gx)), f64::from(b.sample(&level.gy))));
    Some(LiveSample {
        p_world_m: t_world_cam * Point3::from(d.cast::<f64>()),
        n_world: t_world_cam.rotation * n.cast::<f64>(),
        q_cam_m: q,
        gray,
        depth_m: f64::from(level.depth.at(ui, vi)),
        sigma_m: level.sigma.as_ref().map_or(0.0, |s| f64::from(s.at(ui, vi))),
    })
}
