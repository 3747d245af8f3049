//! Input/output costs that every run pays: decoding one 320×320 frame (colour PNG + 16-bit
//! depth PNG), undistorting it when `camera.toml` names a lens (the map built once per camera,
//! then colour and depth remapped per frame), and writing a 100k-surfel map.

use capsule_slam_framework::lens::LensModel;
use capsule_slam_framework::{DepthMap, PinholeCamera, Rgb8, Surfel, SurfelSet};
use capsule_slam_io::undistort::Undistortion;
use capsule_slam_io::{images, ply};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};

fn io(c: &mut Criterion) {
    capsule_slam_benches::link();
    let dir = std::env::temp_dir().join(format!("capsule-slam-bench-io-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let rgb = Rgb8::from_fn(320, 320, |x, y| [(x % 256) as u8, (y % 256) as u8, ((x * y) % 256) as u8]);
    let depth = DepthMap::from_fn(320, 320, |x, y| [0.02 + 0.0001 * (x + y) as f32]);
    let (rp, dp) = (dir.join("rgb.png"), dir.join("depth.png"));
    images::write_rgb(&rp, &rgb).expect("write rgb");
    images::write_depth(&dp, &depth, 5000.0).expect("write depth");
    c.bench_function("read-frame-320", |b| {
        b.iter(|| {
            let r = images::read_rgb(&rp, Some((320, 320))).expect("rgb");
            let d = images::read_depth(&dp, 5000.0, Some((320, 320))).expect("depth");
            (r, d)
        })
    });
    // A capsule-like barrel lens (the image corner 22 % nearer the centre) and a fisheye.
    for (name, lens) in [
        ("radial-tangential", LensModel::RadialTangential([-0.3, 0.1, 0.001, -0.002, 0.0, 0.0, 0.0, 0.0])),
        ("equidistant", LensModel::Equidistant([0.05, -0.01, 0.002, -0.0005])),
    ] {
        let mut cam = PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5);
        cam.distortion = Some(lens);
        cam.fov_radius_px = Some(150.4);
        c.bench_function(&format!("undistort-map-320/{name}"), |b| b.iter(|| Undistortion::new(&cam)));
        let u = Undistortion::new(&cam);
        c.bench_function(&format!("undistort-rgb-320/{name}"), |b| b.iter(|| u.rgb(&rgb)));
        c.bench_function(&format!("undistort-depth-320/{name}"), |b| b.iter(|| u.depth(&depth)));
    }
    let surfels = SurfelSet::new(
        (0..100_000u32)
            .map(|i| Surfel {
                position_m: Point3::new(i as f32 * 1e-6, 0.0, 0.05),
                normal: Vector3::z(),
                colour: [200, 80, 80],
                confidence: 12.0,
                radius_m: 3e-4,
                t0: i / 1000,
                t: i / 1000,
                albedo: 0.4,
                sigma_m: 0.0,
                warp_m: Vector3::zeros(),
            })
            .collect(),
    );
    let mp = dir.join("map.ply");
    c.bench_function("write-map-100k", |b| b.iter(|| ply::write_surfels(&mp, &surfels).expect("ply")));
    let _ = std::fs::remove_dir_all(&dir);
}

criterion_group!(benches, io);
criterion_main!(benches);
