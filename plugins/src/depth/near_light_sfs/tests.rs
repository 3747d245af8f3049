use capsule_slam_eval::depth::depth_error;
use capsule_slam_framework::camera::{PinholeCamera, Rig};
use capsule_slam_framework::context::StageReport;

use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::{CameraFrame, Context, DepthEstimator, DepthMap, Rgb8};
use nalgebra::Vector3;

use super::{AlbedoSource, NearLightSfs, NearLightSfsParams};

fn cam() -> PinholeCamera {
    let mut c = PinholeCamera::new(128, 128, 64.0, 64.0, 63.5, 63.5);
    c.fov_radius_px = Some(62.0);
    c
}

fn light() -> LightModel {
    LightModel { gain: 0.6, spot_exponent: 1.0, ..LightModel::default() }
}

/// Renders a scene given per-ray (distance, unit normal toward the camera) with the light model,
/// uniform albedo `rho` in every channel, 8-bit.
fn render(scene: impl Fn(&Vector3<f64>) -> Option<(f64, Vector3<f64>)>, rho: f64, l: &LightModel) -> (Rgb8, DepthMap) {
    let c = cam();
    let mut img = Rgb8::new(c.width, c.height);
    let mut depth = DepthMap::new(c.width, c.height);
    for y in 0..c.height {
        for x in 0..c.width {
            if !c.in_fov(x as f64, y as f64) {
                continue;
            }
            let d = Vector3::new((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy, 1.0).normalize();
            let Some((t, n)) = scene(&d) else { continue };
            let p = nalgebra::Point3::from(d * t);
            let lin = l.linear(&c, x as f64, y as f64, rho, &p, &n);
            let v = (l.encode(lin) * 255.0).round() as u8;
            img.set_pixel(x, y, [v, v, v]);
            *depth.at_mut(x, y) = p.z as f32;
        }
    }
    (img, depth)
}

fn estimate(img: &Rgb8, rho: f64, l: &LightModel, params: NearLightSfsParams) -> (DepthMap, Vec<String>) {
    let mut est = NearLightSfs::with_light(NearLightSfsParams { albedo: rho * 0.9999, ..params }, l.clone());
    let rig = Rig::Mono(cam());
    let frame = CameraFrame::mono(0, 0.0, img.clone());
    let mut r = StageReport::default();
    let out = est.estimate(&frame, &mut Context::new(0, &rig, None, &mut r)).unwrap();
    (out.depth_m, r.warnings)
}

fn plane(n: Vector3<f64>, q: Vector3<f64>) -> impl Fn(&Vector3<f64>) -> Option<(f64, Vector3<f64>)> {
    let n = n.normalize();
    move |d| {
        let t = n.dot(&q) / n.dot(d);
        (t > 0.0).then_some((t, n))
    }
}

#[test]
fn a_plane_head_on_is_recovered_within_two_percent() {
    let l = light();
    let (img, truth) = render(plane(Vector3::new(0.0, 0.0, -1.0), Vector3::new(0.0, 0.0, 0.03)), 0.5, &l);
    let (d, _) = estimate(&img, 0.5, &l, NearLightSfsParams::default());
    let e = depth_error(&d, &truth, false).unwrap();
    assert!(e.abs_rel < 0.02, "{e:?}");
    assert!(e.pixels > 10_000);
}

#[test]
fn a_tilted_plane_needs_the_incidence_refinement() {
    let l = light();
    let (img, truth) = render(plane(Vector3::new(0.5, 0.2, -1.0), Vector3::new(0.0, 0.0, 0.03)), 0.4, &l);
    let refined = depth_error(&estimate(&img, 0.4, &l, NearLightSfsParams::default()).0, &truth, false).unwrap();
    let falloff = depth_error(&estimate(&img, 0.4, &l, NearLightSfsParams { iterations: 0, ..NearLightSfsParams::default() }).0, &truth, false).unwrap();
    assert!(refined.abs_rel < 0.02, "refined {refined:?}");
    assert!(falloff.abs_rel > 2.0 * refined.abs_rel, "fall-off alone {falloff:?} vs refined {refined:?}");
}

/// A 128×128 image has only 16 cells of the default 8 px across; 4 px cells resolve the
/// sphere's curvature.
#[test]
fn the_inside_of_a_sphere_is_recovered_within_two_percent() {
    // A capsule inside a 4 cm sphere, 1.5 cm off its centre: every wall faces inward.
    let l = LightModel { position_m: [0.002, 0.0, 0.0], ..light() };
    let c = Vector3::new(0.012, -0.004, 0.02);
    let radius: f64 = 0.04;
    let scene = move |d: &Vector3<f64>| {
        // |t d − c| = R, the far root (we are inside).
        let b = d.dot(&c);
        let t = b + (b * b - c.norm_squared() + radius * radius).sqrt();
        Some((t, (c - d * t).normalize()))
    };
    let (img, truth) = render(scene, 0.45, &l);
    let (d, _) = estimate(&img, 0.45, &l, NearLightSfsParams { cell_px: 4, ..NearLightSfsParams::default() });
    let e = depth_error(&d, &truth, false).unwrap();
    assert!(e.abs_rel < 0.02, "{e:?}");
    let falloff = depth_error(&estimate(&img, 0.45, &l, NearLightSfsParams { iterations: 0, ..NearLightSfsParams::default() }).0, &truth, false).unwrap();
    assert!(e.abs_rel < falloff.abs_rel, "the refinement must improve on the pure fall-off: {e:?} vs {falloff:?}");
}

#[test]
fn a_black_frame_gives_an_empty_depth_and_a_warning_not_nan() {
    let l = light();
    let (d, warnings) = estimate(&Rgb8::new(128, 128), 0.45, &l, NearLightSfsParams::default());
    assert!(d.data().iter().all(|v| *v == 0.0));
    assert!(warnings.iter().any(|w| w.contains("no pixel usable")), "{warnings:?}");
    let (d, _) = estimate(&Rgb8::filled(128, 128, 255), 0.45, &l, NearLightSfsParams::default());
    assert!(d.data().iter().all(|v| v.is_finite() && *v == 0.0), "saturated frames have no depth");
}

#[test]
fn a_warm_start_from_the_previous_frame_gives_the_same_depth_within_the_tolerance() {
    let l = light();
    let (a, _) = render(plane(Vector3::new(0.3, 0.1, -1.0), Vector3::new(0.0, 0.0, 0.03)), 0.4, &l);
    let (b, truth) = render(plane(Vector3::new(0.35, 0.1, -1.0), Vector3::new(0.0, 0.0, 0.031)), 0.4, &l);
    let params = NearLightSfsParams { albedo: 0.4 * 0.9999, warm_start: true, ..NearLightSfsParams::default() };
    let mut est = NearLightSfs::with_light(params, l.clone());
    let c = cam();
    est.depth(&a, None, &c, None, None).unwrap();
    let warm = est.depth(&b, None, &c, None, None).unwrap();
    let e = depth_error(&warm.depth_m, &truth, false).unwrap();
    assert!(e.abs_rel < 0.02, "{e:?}");
}

#[test]
fn the_observed_albedo_of_a_plane_is_the_rendered_one() {
    let l = light();
    let (img, _) = render(plane(Vector3::new(0.3, -0.2, -1.0), Vector3::new(0.0, 0.0, 0.03)), 0.5, &l);
    let mut est = NearLightSfs::with_light(NearLightSfsParams { albedo: 0.5, ..NearLightSfsParams::default() }, l.clone());
    let out = est.depth(&img, None, &cam(), None, None).unwrap();
    let obs: Vec<f32> = out.albedo.data().iter().zip(out.depth_m.data()).filter(|(_, d)| **d > 0.0).map(|(a, _)| *a).collect();
    assert!(obs.len() > 10_000);
    let mean = obs.iter().sum::<f32>() / obs.len() as f32;
    assert!((mean - 0.5).abs() < 0.01, "mean observed albedo {mean}");
    assert_eq!(out.map_albedo_pixels, 0);
}

/// The map's albedo replaces the constant: a textured phantom frame (preset 4, frame 90), with
/// the true albedo splatted from the ground-truth surface at the true pose as the "map", comes
/// out as near the truth as the same frame rendered without texture, and far nearer than with
/// the constant (AbsRel 0.008 against 0.054 and 0.009 when written).
#[test]
fn a_map_with_the_true_albedo_removes_the_texture_error() {
    use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
    let spec = PhantomSpec { frames: 300, size: SizePreset::NanEye, noise: 0.0, specular: 0.0, ..PhantomSpec::preset(4) };
    let ph = Phantom::new(spec.clone()).unwrap();
    let untextured = Phantom::new(PhantomSpec { texture: false, ..spec }).unwrap();
    let i = 90;
    let (frame, plain) = (ph.render(i), untextured.render(i));
    let pose = ph.pose(i);
    let mut surface = ph.surface(ph.time_s(i), 2.0e-4);
    for s in &mut surface.surfels {
        s.radius_m = 3.0e-4;
    }
    let map = crate::fuse::surfel_cpu::predict(
        &surface.surfels,
        |_| true,
        &ph.camera,
        &pose,
        &crate::fuse::surfel_cpu::SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.001, stable: 10.0 },
    );
    let run = |source: AlbedoSource, img: &Rgb8| {
        let mut est = NearLightSfs::with_light(NearLightSfsParams { albedo_source: source, ..NearLightSfsParams::default() }, ph.light.clone());
        let out = est.depth(img, None, &ph.camera, Some(&map.albedo), None).unwrap();
        (depth_error(&out.depth_m, &frame.depth_m, false).unwrap().abs_rel, out.map_albedo_pixels)
    };
    let (constant, none) = run(AlbedoSource::Constant, &frame.rgb);
    let (from_map, used) = run(AlbedoSource::Map, &frame.rgb);
    let (uniform, _) = run(AlbedoSource::Constant, &plain.rgb);
    assert_eq!(none, 0);
    assert!(used > 30_000, "map albedo on {used} pixels");
    assert!(from_map < uniform + 0.002, "map {from_map} vs untextured {uniform}");
    assert!(from_map < 0.5 * constant, "map {from_map} vs constant {constant}");
}
