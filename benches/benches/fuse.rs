//! `surfel-cpu` and `surfel-gpu`: fusing one frame into a map of the 30 frames before it, and
//! predicting the active model, at 250×250 and 320×320; `surfel-cpu`'s splat also on a map of
//! the whole path, most of it out of the view (`predict-whole-path`). Without a GPU adapter the
//! `surfel-gpu` group is skipped with a message (`CAPSULE_SLAM_REQUIRE_GPU=1`: a failure).

use capsule_slam_benches::{fused_map_of, phantom, rgbd, rig};
use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::{Context, ModelSet};
use capsule_slam_phantom::SizePreset;
use capsule_slam_plugins::fuse::surfel_cpu::{SplatDepths, predict};
use capsule_slam_plugins::fuse::surfel_params::SurfelParams;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn fuse(c: &mut Criterion) {
    // One device for every GPU map of the bench, opened when `surfel-gpu` first asks.
    let gpu = capsule_slam_gpu::GpuHandle::new();
    for name in ["surfel-cpu", "surfel-gpu"] {
        fuse_with(c, name, &gpu);
    }
}

fn fuse_with(c: &mut Criterion, name: &str, gpu: &capsule_slam_gpu::GpuHandle) {
    let mut g = c.benchmark_group(name);
    g.sample_size(20);
    for (size, label) in [(SizePreset::NanEye, "250x250"), (SizePreset::Capsule320, "320x320")] {
        let p = phantom(size, 300);
        let rig = rig(&p);
        let mut fuser = match fused_map_of(name, &p, 70..100, gpu) {
            Ok(f) => f,
            Err(e) => {
                assert!(std::env::var("CAPSULE_SLAM_REQUIRE_GPU").as_deref() != Ok("1"), "CAPSULE_SLAM_REQUIRE_GPU=1 and {name}: {e}");
                eprintln!("\n!!! SKIPPED bench {name}: {e}\n");
                return;
            }
        };
        let next = rgbd(&p, 100);
        let pose = next.gt_t_world_cam.unwrap_or_default();
        g.bench_with_input(BenchmarkId::new("fuse", label), &next, |b, f| {
            b.iter(|| fuser.fuse(f, &pose, &mut Context::new(100, &rig, None, &mut StageReport::default())).unwrap_or_else(|e| panic!("{e}")))
        });
        g.bench_with_input(BenchmarkId::new("predict", label), &pose, |b, pose| {
            b.iter(|| fuser.predict(pose, ModelSet::Active, &mut Context::new(100, &rig, None, &mut StageReport::default())).unwrap_or_else(|e| panic!("{e}")))
        });
        if name == "surfel-cpu" {
            // The splat on the same surfels with ElasticFusion's nearest-wins rule (ε = 0) and
            // the default ε-z-buffer (1 mm): the same passes, other winners.
            let surfels = fuser.snapshot().unwrap_or_else(|e| panic!("{e}")).surfels;
            let params = SurfelParams::default();
            for (variant, blend_m) in [("predict-eps-0", 0.0), ("predict-blend-1mm", 0.001)] {
                let depths = SplatDepths { blend_m, ..SplatDepths::of(&params) };
                g.bench_with_input(BenchmarkId::new(variant, label), &pose, |b, pose| {
                    b.iter(|| predict(&surfels, |s| s.confidence >= params.stable_confidence, &p.camera, pose, &depths))
                });
            }
            // A map of the whole path (every 10th of 300 frames) seen from frame 100: as on a
            // revisit, most of the surfels lie out of the view (`docs/results/speed.md`).
            let whole =
                fused_map_of(name, &p, (0..300).step_by(10), gpu).and_then(|f| f.snapshot().map_err(|e| e.to_string())).unwrap_or_else(|e| panic!("{e}"));
            let depths = SplatDepths::of(&params);
            g.bench_with_input(BenchmarkId::new("predict-whole-path", label), &pose, |b, pose| {
                b.iter(|| predict(&whole.surfels, |_| true, &p.camera, pose, &depths))
            });
        }
    }
    g.finish();
}

criterion_group!(benches, fuse);
criterion_main!(benches);
