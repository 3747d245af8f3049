//! `icp-rgb`: one frame tracked against the prediction of a map fused from the 20 frames before
//! it, at 250×250 and 320×320.

use capsule_slam_benches::{build, fused_map, phantom, rgbd, rig};
use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::registry::Stage;
use capsule_slam_framework::{Context, ModelSet};
use capsule_slam_phantom::SizePreset;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn track(c: &mut Criterion) {
    let mut g = c.benchmark_group("icp-rgb");
    g.sample_size(20);
    for (size, label) in [(SizePreset::NanEye, "250x250"), (SizePreset::Capsule320, "320x320")] {
        let p = phantom(size, 300);
        let rig = rig(&p);
        let mut fuser = fused_map(&p, 80..100);
        let mut r = StageReport::default();
        let prev = rgbd(&p, 99);
        let prev_pose = prev.gt_t_world_cam.unwrap_or_default();
        let model = fuser.predict(&prev_pose, ModelSet::Active, &mut Context::new(99, &rig, None, &mut r)).unwrap_or_else(|e| panic!("{e}"));
        let cur = rgbd(&p, 100);
        g.bench_with_input(BenchmarkId::from_parameter(label), &cur, |b, cur| {
            b.iter(|| {
                let Stage::Tracker(mut t) = build("icp-rgb", &p) else { panic!("icp-rgb is a tracker") };
                let mut r = StageReport::default();
                t.track(&prev, Some(&model), &prev_pose, &mut Context::new(99, &rig, Some(&model), &mut r)).unwrap_or_else(|e| panic!("{e}"));
                t.track(cur, Some(&model), &prev_pose, &mut Context::new(100, &rig, Some(&model), &mut r)).unwrap_or_else(|e| panic!("{e}"))
            })
        });
    }
    g.finish();
}

criterion_group!(benches, track);
criterion_main!(benches);
