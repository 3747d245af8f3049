//! Stereo depth: `stereo-sgm` on a 5 mm phantom pair (preset 1, frame 5) at 320×320 (issue
//! 19's speed goal: ≤ 15 ms per frame on 2 cores, moonshot ≤ 8 ms), and the rectification of
//! both views alone. `CAPSULE_SLAM_BENCH_STEREO_PARAMS` (TOML, e.g. `"passes = 1"`) times
//! other parameters than the defaults (`docs/results/stereo.md`, "Speed against coverage").

use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::frame::{CameraFrame, Masks, Photometry, Views};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stereo::rectify::Side;
use capsule_slam_framework::{Context, DepthEstimator, Plugin};
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_plugins::depth::stereo_sgm::remap::Rectifier;
use capsule_slam_plugins::depth::stereo_sgm::{StereoSgm, StereoSgmParams};
use criterion::{Criterion, criterion_group, criterion_main};

fn stereo(c: &mut Criterion) {
    capsule_slam_benches::link();
    let spec = PhantomSpec { frames: 20, size: SizePreset::Capsule320, stereo_baseline_mm: Some(5.0), ..PhantomSpec::preset(1) };
    let p = Phantom::new(spec).unwrap_or_else(|e| panic!("phantom: {e}"));
    let rig = Phantom::camera_file_for(&p.spec).rig();
    let (l, r) = (p.render_view(5, Side::Left), p.render_view(5, Side::Right));
    let frame = CameraFrame {
        index: 5,
        timestamp_s: l.timestamp_s,
        views: Views::Stereo { left: l.rgb, right: r.rgb },
        depth_m: None,
        gt_t_world_cam: None,
        masks: Masks::new(),
        right_masks: Masks::new(),
        photometry: Photometry::default(),
        sample_share: None,
    };
    let params = match std::env::var("CAPSULE_SLAM_BENCH_STEREO_PARAMS") {
        Ok(text) => {
            let p: StereoSgmParams = toml::from_str(&text).unwrap_or_else(|e| panic!("CAPSULE_SLAM_BENCH_STEREO_PARAMS: {e}"));
            eprintln!("stereo-sgm with CAPSULE_SLAM_BENCH_STEREO_PARAMS: {text:?}");
            p
        }
        Err(_) => StereoSgmParams::default(),
    };
    let mut est = StereoSgm::build(params, &BuildEnv::new(rig.clone(), None)).unwrap_or_else(|e| panic!("{e}"));
    let mut g = c.benchmark_group("stereo");
    g.sample_size(10);
    g.bench_function("stereo-sgm/320x320", |b| {
        b.iter(|| est.estimate(&frame, &mut Context::new(5, &rig, None, &mut StageReport::default())).unwrap_or_else(|e| panic!("{e}")))
    });
    let rectifier = Rectifier::new(&rig).unwrap_or_else(|e| panic!("{e}"));
    let Views::Stereo { left, right } = &frame.views else { panic!("a stereo frame") };
    g.bench_function("rectify-both-views/320x320", |b| {
        b.iter(|| (rectifier.view(Side::Left, left, |_, _| false), rectifier.view(Side::Right, right, |_, _| false)))
    });
    g.finish();
}

criterion_group!(benches, stereo);
criterion_main!(benches);
