//! `icp-rgb`: one frame tracked against the prediction of a map fused from the 20 frames before
//! it, at 250×250 and 320×320; unlit (no light model), relit with the phantom's `light.toml`,
//! and relit on images whose lens-and-LED fall-off was divided out (the default pipeline's
//! `vignetting`), which the tracker multiplies back in first. `bilateral`: the depth filter the
//! trackers and fusers share, at 320×320, radius 1 (the default, each pair's weight taken once)
//! and 2 (per tap).

use capsule_slam_benches::{build_in, fused_map, phantom, rgbd, rig};
use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::frame::{DividedFalloff, Falloff};
use capsule_slam_framework::light::vignetting::light_falloff;
use capsule_slam_framework::registry::Stage;
use capsule_slam_framework::{Context, ModelSet, RgbdFrame};
use capsule_slam_phantom::{Phantom, SizePreset};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

/// The frame with the light's lens-and-LED fall-off divided out, as `vignetting` leaves it.
fn divided(p: &Phantom, mut f: RgbdFrame) -> RgbdFrame {
    let (w, l) = (f.colour.width(), &p.light);
    for (k, px) in f.colour.data_mut().chunks_mut(3).enumerate() {
        let fall = light_falloff(l, &p.camera, (k % w) as f64, (k / w) as f64, Falloff::LensAndLight);
        px.iter_mut().for_each(|c| *c = (255.0 * l.encode(l.decode(f64::from(*c) / 255.0) / fall)).round().clamp(0.0, 255.0) as u8);
    }
    f.photometry.divided = Some(DividedFalloff { falloff: Falloff::LensAndLight, linear_scale: 1.0, gamma: l.gamma });
    f
}

fn track(c: &mut Criterion) {
    let mut g = c.benchmark_group("icp-rgb");
    g.sample_size(20);
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    for (size, label) in [(SizePreset::NanEye, "250x250"), (SizePreset::Capsule320, "320x320")] {
        let p = phantom(size, 300);
        capsule_slam_framework::files::write_light_file(&dir.path().join("light.toml"), &p.light).unwrap_or_else(|e| panic!("{e}"));
        let rig = rig(&p);
        let mut fuser = fused_map(&p, 80..100);
        let mut r = StageReport::default();
        let prev_pose = rgbd(&p, 99).gt_t_world_cam.unwrap_or_default();
        let model = fuser.predict(&prev_pose, ModelSet::Active, &mut Context::new(99, &rig, None, &mut r)).unwrap_or_else(|e| panic!("{e}"));
        for variant in ["unlit", "relit", "relit-divided"] {
            let lit = variant != "unlit";
            let frame = |i| if variant == "relit-divided" { divided(&p, rgbd(&p, i)) } else { rgbd(&p, i) };
            let (prev, cur) = (frame(99), frame(100));
            let id = BenchmarkId::new(variant, label);
            g.bench_with_input(id, &cur, |b, cur| {
                b.iter(|| {
                    let Stage::Tracker(mut t) = build_in("icp-rgb", &p, lit.then(|| dir.path())) else { panic!("icp-rgb is a tracker") };
                    let mut r = StageReport::default();
                    t.track(&prev, Some(&model), &prev_pose, &mut Context::new(99, &rig, Some(&model), &mut r)).unwrap_or_else(|e| panic!("{e}"));
                    t.track(cur, Some(&model), &prev_pose, &mut Context::new(100, &rig, Some(&model), &mut r)).unwrap_or_else(|e| panic!("{e}"))
                })
            });
        }
    }
    g.finish();
}

fn bilateral(c: &mut Criterion) {
    let mut g = c.benchmark_group("bilateral");
    let p = phantom(SizePreset::Capsule320, 300);
    let depth = rgbd(&p, 100).depth_m;
    for radius in [1usize, 2] {
        g.bench_with_input(BenchmarkId::new("320x320", format!("radius {radius}")), &depth, |b, d| {
            b.iter(|| capsule_slam_plugins::common::maps::bilateral_depth(d, radius, 2.0, 0.0008))
        });
    }
    g.finish();
}

criterion_group!(benches, track, bilateral);
criterion_main!(benches);
