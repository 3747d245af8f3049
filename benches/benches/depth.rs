//! Depth from one image: `near-light-sfs` and `tsai-shah` on a phantom frame of preset 2 at
//! 250×250 and 320×320 (issue 5's speed goal: ≤ 5 ms for `near-light-sfs` at 320×320).

use capsule_slam_benches::{phantom, rig};
use capsule_slam_framework::context::StageReport;

use capsule_slam_framework::{CameraFrame, Context, DepthEstimator};
use capsule_slam_phantom::SizePreset;
use capsule_slam_plugins::depth::near_light_sfs::{NearLightSfs, NearLightSfsParams};
use capsule_slam_plugins::depth::tsai_shah::{TsaiShah, TsaiShahParams};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn depth(c: &mut Criterion) {
    let mut g = c.benchmark_group("depth");
    g.sample_size(20);
    for (size, label) in [(SizePreset::NanEye, "250x250"), (SizePreset::Capsule320, "320x320")] {
        let p = phantom(size, 300);
        let rig = rig(&p);
        let r = p.render(100);
        let frame = CameraFrame::mono(100, r.timestamp_s, r.rgb.clone());
        let estimators: [(&str, Box<dyn DepthEstimator>); 2] = [
            ("near-light-sfs", Box::new(NearLightSfs::with_light(NearLightSfsParams::default(), p.light.clone()))),
            ("tsai-shah", Box::new(TsaiShah::new(TsaiShahParams::default()))),
        ];
        for (name, mut est) in estimators {
            g.bench_with_input(BenchmarkId::new(name, label), &frame, |b, f| {
                b.iter(|| est.estimate(f, &mut Context::new(100, &rig, None, &mut StageReport::default())).unwrap_or_else(|e| panic!("{e}")))
            });
        }
    }
    g.finish();
}

criterion_group!(benches, depth);
criterion_main!(benches);
