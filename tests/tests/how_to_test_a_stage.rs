//! How to test one stage on its own (documentation as a test): build the plugin from the
//! registry with parameters, feed it a frame from a fixture with known ground truth, and check
//! a real property of its output.

use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::config::InputConfig;
use capsule_slam_framework::context::{Context, StageReport};
use capsule_slam_framework::registry::{BuildEnv, Stage};
use capsule_slam_io::Dataset;
use capsule_slam_tests::{fixtures, stages::test_registry};

#[test]
fn the_sensor_depth_estimator_clips_to_its_range() {
    // 1. A fixture with exact depth: a plane 5 cm in front of the camera.
    let tmp = tempfile::tempdir().unwrap();
    fixtures::write_dataset(tmp.path(), 1);
    let ds = Dataset::open(tmp.path(), &InputConfig::default(), None).unwrap();
    let frame = ds.load(0).unwrap();

    // 2. The stage, built through the registry with a parameter table, as a config would.
    let registry = test_registry();
    let entry = registry.get("sensor").unwrap();
    let params: toml::Table = toml::from_str("max_depth_m = 0.0505").unwrap();
    let env = BuildEnv::new(ds.rig(), None);
    let Ok(Stage::DepthEstimator(mut sensor)) = entry.build(&params, &env) else { panic!("not a depth estimator") };

    // 3. Run it with a context and check the output against the ground truth.
    let rig: Rig = ds.rig();
    let mut report = StageReport::default();
    let est = sensor.estimate(&frame, &mut Context::new(0, &rig, None, &mut report)).unwrap();
    let input = frame.depth_m.unwrap();
    for (d_in, d_out) in input.data().iter().zip(est.depth_m.data()) {
        let expected = if *d_in <= 0.0505 { *d_in } else { 0.0 };
        assert_eq!(*d_out, expected);
    }
    assert!(report.counters["valid_pixels"] > 0.0);
}
