//! The phantom as ground truth, end to end: a written sequence reads back as a dataset, the
//! oracle pipeline reproduces its trajectory, and a map of its exact depth matches its surface.

use capsule_slam_framework::config::Config;
use capsule_slam_framework::files::read_light_file;
use capsule_slam_framework::pipeline::Pipeline;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::{Dataset, ply};
use capsule_slam_phantom::writer::{is_complete, surface_frames, write_sequence};
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_run::RunWriter;
use capsule_slam_run::{RunOptions, run};
use capsule_slam_tests::stages::test_registry;

fn spec(frames: usize, deform_mm: f64) -> PhantomSpec {
    PhantomSpec { frames, size: SizePreset::NanEye, deform_mm, ..PhantomSpec::preset(1) }
}

#[test]
fn a_written_phantom_is_a_complete_dataset_with_its_ground_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let s = spec(24, 0.0);
    let phantom = Phantom::new(s.clone()).unwrap();
    write_sequence(&phantom, tmp.path(), &|_| {}).unwrap();
    assert!(is_complete(tmp.path(), &s));
    assert!(!is_complete(tmp.path(), &PhantomSpec { seed: 9, ..s.clone() }));
    assert_eq!(read_light_file(&tmp.path().join("light.toml")).unwrap(), phantom.light);

    let cfg = Config::load(
        None,
        &["pipeline.depth=sensor".into(), "pipeline.tracker=ground-truth".into(), "pipeline.fuser=test-points".into(), "plugins.test-points.stride=2".into()],
    )
    .unwrap();
    let ds = Dataset::open(tmp.path(), &cfg.input, None).unwrap();
    assert_eq!(ds.len(), 24);
    assert!(ds.has_depth());
    let f = ds.load(3).unwrap();
    assert!(f.masks.get(capsule_slam_framework::frame::MASK_OUT_OF_VIEW).is_some(), "round field of view is masked");

    let registry = test_registry();
    let mut p = Pipeline::build(&cfg, "test", &registry, &BuildEnv::new(ds.rig(), None)).unwrap();
    let out = tmp.path().join("out");
    let mut w = RunWriter::create(&out, "").unwrap();
    let summary = run(&ds, &mut p, &mut w, &RunOptions { max_frames: None, write_map: true, eval_sim3: false, ..RunOptions::default() }, |_| {}).unwrap();
    let m = &summary.metrics;
    assert!(summary.ate_rmse_m.unwrap() < 1e-6, "{summary:?}");
    assert!(m["path_length_m"] > 0.005);
    // Exact depth (16-bit, 0.2 mm steps) fused at the true poses lies on the true surface.
    assert!(m["surface_rmse_m"] < 2e-4, "{m:?}");
    assert!(m["surface_accuracy_m"] < 1e-4, "{m:?}");
    assert!(m["surface_completeness_2mm"] > 0.95, "{m:?}");
}

#[test]
fn a_deforming_phantom_writes_the_surface_at_chosen_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let phantom = Phantom::new(spec(5, 3.0)).unwrap();
    write_sequence(&phantom, tmp.path(), &|_| {}).unwrap();
    let rest = ply::read_surfels(&tmp.path().join("gt_surface.ply")).unwrap();
    for i in surface_frames(5, 0) {
        let at = ply::read_surfels(&tmp.path().join(format!("gt_surface_{i:06}.ply"))).unwrap();
        assert_eq!(at.len(), rest.len());
        let moved = at.surfels.iter().zip(&rest.surfels).map(|(a, b)| (a.position_m - b.position_m).norm()).fold(0.0f32, f32::max);
        assert!(moved > 0.001 && moved < 0.0035, "frame {i}: the wall moves by up to the 3 mm amplitude, moved {moved}");
    }
}
