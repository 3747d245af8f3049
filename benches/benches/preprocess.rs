//! The preprocessors on frame 100 of phantom preset 7 (heavy reflections) at 320×320: the
//! `reflection` remover (detection, dilation, inpainting) and the `vignetting` correction
//! (issue 6's goal: ≤ 2 ms each). Every iteration works on a fresh copy of the frame.

use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::{CameraFrame, Context, Preprocessor};
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_plugins::preprocess::reflection::{Reflection, ReflectionParams};
use capsule_slam_plugins::preprocess::vignetting::{FalloffSource, Vignetting, VignettingParams};
use criterion::{BatchSize, Criterion, criterion_group, criterion_main};

fn preprocess(c: &mut Criterion) {
    let mut g = c.benchmark_group("preprocess");
    g.sample_size(30);
    let p = Phantom::new(PhantomSpec { size: SizePreset::Capsule320, ..PhantomSpec::preset(7) }).unwrap_or_else(|e| panic!("phantom: {e}"));
    let rig = capsule_slam_benches::rig(&p);
    let r = p.render(100);
    let mut frame = CameraFrame::mono(100, r.timestamp_s, r.rgb.clone());
    let mut oov = p.camera.fov_mask();
    oov.data_mut().iter_mut().for_each(|v| *v = !*v);
    frame.masks.insert(capsule_slam_framework::frame::MASK_OUT_OF_VIEW, oov);
    let stages: [(&str, Box<dyn Preprocessor>); 2] = [
        ("reflection/320x320", Box::new(Reflection::new(ReflectionParams::default()))),
        ("vignetting/320x320", Box::new(Vignetting::new(VignettingParams::default(), FalloffSource::Light(p.light.clone())))),
    ];
    for (name, mut stage) in stages {
        g.bench_function(name, |b| {
            b.iter_batched_ref(
                || frame.clone(),
                |f| stage.process(f, &mut Context::new(100, &rig, None, &mut StageReport::default())).unwrap_or_else(|e| panic!("{e}")),
                BatchSize::SmallInput,
            )
        });
    }
    g.finish();
}

criterion_group!(benches, preprocess);
criterion_main!(benches);
