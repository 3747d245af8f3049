//! The behaviour Tsai & Shah (1994) describe, on an orthographic Lambertian sphere in their
//! convention (128², radius 51.2 px, black background, 8-bit).

use capsule_slam_framework::{GrayF32, Mask};

use super::{Form, TsaiShah, TsaiShahParams, dfdz, estimate_light, light_pq, reflectance, solve};
use capsule_slam_framework::camera::{PinholeCamera, Rig};
use capsule_slam_framework::context::StageReport;

use capsule_slam_framework::{CameraFrame, Context, DepthEstimator, Rgb8};

/// The sphere's image under a light of (slant, tilt), its mask and its true depth (−height).
fn sphere(slant_deg: f64, tilt_deg: f64) -> (GrayF32, Mask, Vec<f64>) {
    let (ps, qs) = light_pq(slant_deg.to_radians(), tilt_deg.to_radians());
    let (n, r) = (128usize, 51.2f64);
    let c = 63.5;
    let mut depth = vec![0.0; n * n];
    let mask = Mask::from_fn(n, n, |x, y| [((x as f64 - c).powi(2) + (y as f64 - c).powi(2)) < r * r]);
    let img = GrayF32::from_fn(n, n, |x, y| {
        let (dx, dy) = (x as f64 - c, y as f64 - c);
        let h2 = r * r - dx * dx - dy * dy;
        if h2 <= 0.0 {
            return [0.0];
        }
        let h = h2.sqrt();
        depth[y * n + x] = -h;
        // Z = −h: p = ∂Z/∂x = dx/h, q = dy/h.
        [((reflectance(dx / h, dy / h, ps, qs) * 255.0).round() / 255.0) as f32]
    });
    (img, mask, depth)
}

fn corr(a: &[f64], b: &[f64], m: &Mask) -> f64 {
    let idx: Vec<usize> = (0..a.len()).filter(|&k| m.data()[k]).collect();
    let n = idx.len() as f64;
    let (ma, mb) = (idx.iter().map(|&k| a[k]).sum::<f64>() / n, idx.iter().map(|&k| b[k]).sum::<f64>() / n);
    let cov: f64 = idx.iter().map(|&k| (a[k] - ma) * (b[k] - mb)).sum();
    let va: f64 = idx.iter().map(|&k| (a[k] - ma).powi(2)).sum();
    let vb: f64 = idx.iter().map(|&k| (b[k] - mb).powi(2)).sum();
    cov / (va * vb).sqrt()
}

#[test]
fn the_derivative_matches_finite_differences() {
    let (ps, qs) = light_pq(0.4, 0.9);
    for (p, q) in [(0.1, -0.2), (0.5, 0.3), (-0.7, 0.05)] {
        let h = 1e-7;
        // f = E − R(p + dz, q + dz): df/dZ = −(∂R/∂p + ∂R/∂q).
        let num = -(reflectance(p + h, q + h, ps, qs) - reflectance(p - h, q - h, ps, qs)) / (2.0 * h);
        assert!((dfdz(p, q, ps, qs) - num).abs() < 1e-6, "{p} {q}: {} vs {num}", dfdz(p, q, ps, qs));
    }
}

#[test]
fn slant_zero_from_a_flat_start_never_moves_the_kalman_form() {
    let (img, mask, _) = sphere(0.0, 45.0);
    let (ps, qs) = light_pq(0.0, 45f64.to_radians());
    let (z, _) = solve(&img, &mask, ps, qs, 50, Form::Kalman);
    assert!(z.iter().all(|v| *v == 0.0), "df = 0 everywhere at slant 0 with Z = 0");
}

#[test]
fn a_one_degree_slant_floor_recovers_the_sphere_as_height() {
    let (img, mask, depth) = sphere(0.0, 45.0);
    let (ps, qs) = light_pq(1f64.to_radians(), 45f64.to_radians());
    // As in A8, the sweeps run over the whole image, black background included.
    let all = Mask::filled(128, 128, true);
    let (z, _) = solve(&img, &all, ps, qs, 200, Form::Kalman);
    let c = corr(&z, &depth, &mask);
    assert!(c <= -0.98, "corr {c} (A8: −0.990; Z comes out as height)");
}

#[test]
fn the_masked_estimator_overshoots_a_30_degree_slant_to_about_39() {
    let (img, mask, _) = sphere(30.0, 45.0);
    let max = img.data().iter().copied().fold(0.0f32, f32::max);
    let e = GrayF32::from_vec(128, 128, img.data().iter().map(|v| v / max).collect()).unwrap();
    let (slant, tilt, albedo) = estimate_light(&e, &mask);
    assert!((35.0..44.0).contains(&slant.to_degrees()), "slant {}° (A8: 39.3°)", slant.to_degrees());
    assert!((tilt.to_degrees() - 45.0).abs() < 3.0, "tilt {}°", tilt.to_degrees());
    assert!((0.8..1.1).contains(&albedo), "albedo {albedo}");
}

fn run(img: Rgb8) -> (capsule_slam_framework::DepthMap, Vec<String>) {
    let mut t = TsaiShah::new(TsaiShahParams::default());
    let rig = Rig::Mono(PinholeCamera::new(img.width(), img.height(), 64.0, 64.0, 63.5, 63.5));
    let frame = CameraFrame::mono(0, 0.0, img);
    let mut r = StageReport::default();
    let out = t.estimate(&frame, &mut Context::new(0, &rig, None, &mut r)).unwrap();
    (out.depth_m, r.warnings)
}

#[test]
fn the_plugin_maps_bright_to_near_within_the_configured_range() {
    let (img, mask, depth) = sphere(20.0, 45.0);
    let rgb = Rgb8::from_fn(128, 128, |x, y| [(img.at(x, y) * 255.0) as u8; 3]);
    let (d, warnings) = run(rgb);
    assert!(warnings.is_empty(), "{warnings:?}");
    let vals: Vec<f64> = d.data().iter().map(|v| f64::from(*v)).collect();
    for (k, v) in vals.iter().enumerate() {
        if mask.data()[k] {
            assert!((0.01 - 1e-6..=0.06 + 1e-6).contains(v), "depth {v} outside [near_m, far_m]");
        }
    }
    // The sphere's top (bright, near) must come out nearer than its rim.
    assert!(corr(&vals, &depth, &mask) > 0.5, "corr with the true depth {}", corr(&vals, &depth, &mask));
}

#[test]
fn a_black_frame_gives_an_empty_depth_and_a_warning() {
    let (d, warnings) = run(Rgb8::new(128, 128));
    assert!(d.data().iter().all(|v| *v == 0.0));
    assert!(warnings.iter().any(|w| w.contains("no lit pixel")), "{warnings:?}");
}
