//! The model points the warp is fitted on and what the live frame says about them.
//!
//! Model points are the prediction's pixels on a regular grid (the surfels the tracker sees,
//! already splatted), lifted to the world at the pose the prediction was rendered from; each
//! keeps its normal and the previous live frame's intensity there (the photometric reference,
//! lit like the live frame; `icp-rgb`'s `previous-frame` choice).

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::{GrayF32, Iso3, ModelView};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::common::maps::{normal, vertex};
use crate::common::pyramid::Bilinear;
use crate::track::icp_rgb::frames::Level;
use crate::track::icp_rgb::terms::nearest_pixel;

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
            if !faces_camera(&n_cam, &x_cam.coords, min_cos) {
                continue;
            }
            let gray_ref = previous_gray.map(|g| f64::from(g.at(x, y))).filter(|v| *v > 0.0);
            out.push(ModelPoint { x_world_m: t_wc * x_cam, n_world: r_wc * n_cam, gray_ref, sigma_m: f64::from(model.sigma_m.at(x, y)) });
        }
    }
    out
}

/// Whether a surface at `x_cam` with normal `n_cam` faces the camera within the angle whose
/// cosine is `min_cos` (either side of the wall).
fn faces_camera(n_cam: &Vector3<f64>, x_cam: &Vector3<f64>, min_cos: f64) -> bool {
    n_cam.dot(x_cam).abs() >= min_cos * x_cam.norm()
}

/// The share of the previous live frame's valid depth pixels that the prediction covers (1 when
/// that frame has none).
pub fn predicted_share(model: &ModelView, previous: &Level) -> f64 {
    let seen = previous.depth.data().iter().filter(|d| **d > 0.0).count();
    if seen == 0 {
        return 1.0;
    }
    let both = previous.depth.data().iter().zip(model.depth_m.data()).filter(|(l, m)| **l > 0.0 && **m > 0.0).count();
    both as f64 / seen as f64
}

/// The previous live frame's pixels every `stride` pixels where the prediction has no surface
/// (ElasticFusion's fill-in, `FillIn.cpp`: the tracker's reference takes the live frame where
/// the model shows nothing), facing the camera within `max_incidence_rad`, lifted to the world
/// at the prediction's pose. While the map is young (its surfels below the stable confidence,
/// so not predicted: the first 10 or so frames) and where new surface enters the view, the
/// warp is fitted on them and the map's unstable surfels there follow the wall from the start.
/// `None` when the prediction and the previous frame differ in size.
pub fn sample_fill_in(model: &ModelView, previous: &Level, stride: usize, max_incidence_rad: f64) -> Option<Vec<ModelPoint>> {
    let min_cos = max_incidence_rad.cos();
    let (w, h) = model.depth_m.size();
    if previous.depth.size() != (w, h) {
        return None;
    }
    let t_wc = model.t_world_cam;
    let stride = stride.max(1);
    let mut out = Vec::new();
    for y in (stride / 2..h).step_by(stride) {
        for x in (stride / 2..w).step_by(stride) {
            let z = model.depth_m.at(x, y);
            if z > 0.0 && z.is_finite() {
                continue;
            }
            let (Some(v), Some(n)) = (vertex(&previous.vertices, x, y), normal(&previous.normals, x, y)) else { continue };
            let (x_cam, n_cam) = (v.cast::<f64>(), n.cast::<f64>());
            if !faces_camera(&n_cam, &x_cam, min_cos) {
                continue;
            }
            let gray_ref = Some(f64::from(previous.gray.at(x, y))).filter(|g| *g > 0.0);
            let sigma_m = previous.sigma.as_ref().map_or(0.0, |s| f64::from(s.at(x, y)));
            out.push(ModelPoint { x_world_m: t_wc * Point3::from(x_cam), n_world: t_wc.rotation * n_cam, gray_ref, sigma_m });
        }
    }
    Some(out)
}

/// Relights each point's reference intensity from the view it was read in (`t_world_ref`) to
/// the live view (`t_world_live`, the rigid start): `encode(decode(I_ref) · L_live / L_ref)`, L
/// the light model's response to a unit albedo at the point's pixel, position and normal
/// (`icp-rgb`'s relighting, `relight.rs`, done once per frame here: the light moves with the
/// capsule, and brightness constancy fails by about twice the relative change of distance).
/// A point either view leaves unlit loses its reference. Returns how many were relit.
pub fn relight(points: &mut [ModelPoint], light: &LightModel, cam: &PinholeCamera, t_world_ref: &Iso3, t_world_live: &Iso3) -> usize {
    let response = |t_world_cam: &Iso3, p: &ModelPoint| -> Option<f64> {
        let q = t_world_cam.inverse_transform_point(&p.x_world_m);
        let mut n = t_world_cam.inverse_transform_vector(&p.n_world);
        if n.dot(&q.coords) > 0.0 {
            n = -n;
        }
        let uv = cam.project(&q)?;
        let r = light.linear(cam, uv.x, uv.y, 1.0, &q, &n);
        (r > 1e-9).then_some(r)
    };
    // Each point alone, in parallel (the count is an integer sum: the same on any thread count).
    points
        .par_iter_mut()
        .map(|p| {
            let Some(g) = p.gray_ref else { return 0 };
            p.gray_ref = match (response(t_world_ref, p), response(t_world_live, p)) {
                (Some(r_ref), Some(r_live)) => Some(light.encode(light.decode(g) * r_live / r_ref)),
                _ => None,
            };
            usize::from(p.gray_ref.is_some())
        })
        .sum()
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
    /// The live pixel's share of a source pixel there ([`Level::share`]; 1 where the image was
    /// not resampled).
    pub share: f64,
}

/// Samples the live level at the projection of `x_world` seen from `t_world_cam`.
pub fn look(level: &Level, t_world_cam: &Iso3, x_world: &Point3<f64>) -> Option<LiveSample> {
    let q = t_world_cam.inverse_transform_point(x_world).coords;
    if q.z <= 0.0 {
        return None;
    }
    let (w, h) = level.depth.size();
    let ((uf, vf), (ui, vi)) = nearest_pixel(&level.cam, &q, (w, h))?;
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
        share: level.share_at(ui, vi),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::geometry::exp_se3;
    use nalgebra::Vector6;

    #[test]
    fn fill_in_points_come_from_the_previous_frame_where_the_prediction_has_no_surface() {
        let previous = crate::track::nonrigid::fixture::level(0.0);
        let cam = crate::track::nonrigid::fixture::cam();
        let t_wc = exp_se3(&Vector6::new(0.003, -0.001, 0.002, 0.02, -0.01, 0.03));
        // The prediction shows the wall on the left half only (its depth from the same frame).
        let mut model = ModelView::empty(cam.width, cam.height, t_wc);
        for y in 0..cam.height {
            for x in 0..cam.width / 2 {
                model.depth_m.data_mut()[y * cam.width + x] = previous.depth.at(x, y);
            }
        }
        let stride = 4;
        let fill = sample_fill_in(&model, &previous, stride, 1.5).expect("same size");
        let grid = (cam.width / stride) * (cam.height / stride);
        assert!(fill.len() > grid / 3 && fill.len() <= grid / 2 + cam.height / stride, "{} of {grid} grid pixels", fill.len());
        for p in &fill {
            // Each is a right-half pixel of the previous frame, lifted at the prediction's pose.
            let q = t_wc.inverse_transform_point(&p.x_world_m);
            let uv = cam.project(&q).expect("in front of the camera");
            let (x, y) = ((uv.x + 0.5) as usize, (uv.y + 0.5) as usize);
            assert!(x >= cam.width / 2, "pixel {x} has a predicted surface");
            assert!((q.z - f64::from(previous.depth.at(x, y))).abs() < 1e-6, "depth {} vs {}", q.z, previous.depth.at(x, y));
            assert!((p.gray_ref.expect("textured") - f64::from(previous.gray.at(x, y))).abs() < 1e-6);
            let n_cam = t_wc.inverse_transform_vector(&p.n_world);
            assert!((n_cam - normal(&previous.normals, x, y).expect("a normal").cast::<f64>()).norm() < 1e-6);
        }
        // A prediction of another size is refused (not misread).
        assert!(sample_fill_in(&ModelView::empty(8, 8, t_wc), &previous, stride, 1.5).is_none());
    }

    #[test]
    fn relighting_gives_the_intensity_the_live_view_sees_of_the_same_albedo() {
        let light = LightModel::default();
        let cam = PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5);
        let t_ref = exp_se3(&Vector6::new(0.001, -0.002, 0.0, 0.01, 0.0, -0.02));
        let t_live = exp_se3(&Vector6::new(0.002, -0.001, 0.006, 0.03, -0.02, 0.0));
        let albedo = 0.6;
        let x = Point3::new(0.004, -0.003, 0.032);
        let n = Vector3::new(0.2, -0.1, -1.0).normalize();
        // What a camera at `t` reads of the point (the phantom's image formation).
        let seen = |t: &Iso3| {
            let q = t.inverse_transform_point(&x);
            let uv = cam.project(&q).unwrap();
            light.encode(light.linear(&cam, uv.x, uv.y, albedo, &q, &t.inverse_transform_vector(&n)))
        };
        let mut pts = [ModelPoint { x_world_m: x, n_world: n, gray_ref: Some(seen(&t_ref)), sigma_m: 0.0 }];
        assert_ne!((seen(&t_ref) * 1e3).round(), (seen(&t_live) * 1e3).round(), "the test needs a brightness change");
        assert_eq!(relight(&mut pts, &light, &cam, &t_ref, &t_live), 1);
        assert!((pts[0].gray_ref.unwrap() - seen(&t_live)).abs() < 1e-12, "{:?} vs {}", pts[0].gray_ref, seen(&t_live));
        // A normal given facing away is the same surface; a point behind the live camera loses its reference.
        let mut flipped = [ModelPoint { n_world: -n, gray_ref: Some(seen(&t_ref)), ..pts[0] }];
        relight(&mut flipped, &light, &cam, &t_ref, &t_live);
        assert!((flipped[0].gray_ref.unwrap() - seen(&t_live)).abs() < 1e-12);
        let behind = Iso3::translation(0.0, 0.0, 0.05);
        let mut lost = [ModelPoint { gray_ref: Some(0.5), ..pts[0] }];
        assert_eq!(relight(&mut lost, &light, &cam, &t_ref, &behind), 0);
        assert_eq!(lost[0].gray_ref, None);
    }
}
