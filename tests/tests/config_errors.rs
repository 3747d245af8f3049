//! Every class of configuration error gives its message, with the key and the fix, and all
//! problems are reported at once.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_framework::camera::CameraFile;
use capsule_slam_framework::config::Config;
use capsule_slam_framework::config::validate::validate;
use capsule_slam_framework::{ConfigError, Registry, ViewKind};
use capsule_slam_tests::stages::test_registry;

fn load(text: &str, sets: &[&str]) -> Result<Config, ConfigError> {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.toml");
    std::fs::write(&p, text).unwrap();
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    Config::load(Some(&p), &sets)
}

fn check(text: &str, sets: &[&str], rig: ViewKind) -> Result<(), ConfigError> {
    let c = load(text, sets)?;
    validate(&c, &test_registry(), rig, "c.toml").map(|_| ())
}

const OK: &str = "[pipeline]\ndepth = \"sensor\"\ntracker = \"ground-truth\"\nfuser = \"test-points\"\n";

#[test]
fn a_valid_config_passes() {
    check(OK, &[], ViewKind::Mono).unwrap();
}

#[test]
fn unknown_plugin_lists_the_known_names() {
    let e = check(OK, &["pipeline.tracker=icp-magic"], ViewKind::Mono).unwrap_err();
    assert_eq!(e.problems.len(), 1);
    let p = &e.problems[0];
    assert_eq!(p.key, "pipeline.tracker");
    assert!(p.message.contains("icp-magic"));
    assert!(p.fix.contains("ground-truth"), "{}", p.fix);
}

#[test]
fn a_plugin_of_the_wrong_stage_is_named_as_such() {
    let e = check(OK, &["pipeline.tracker=sensor"], ViewKind::Mono).unwrap_err();
    assert!(e.problems[0].message.contains("is a depth estimator, not a tracker"), "{}", e);
}

#[test]
fn unknown_keys_are_rejected_everywhere() {
    let e = load(&format!("{OK}colour = 1\n"), &[]).unwrap_err();
    assert!(e.problems[0].key == "pipeline" && e.problems[0].message.contains("colour"), "{e}");
    let e = load(&format!("{OK}[input]\npth = \"x\"\n"), &[]).unwrap_err();
    assert!(e.problems[0].message.contains("pth"), "{e}");
    let e = load(&format!("{OK}[outputs]\n"), &[]).unwrap_err();
    assert_eq!(e.problems[0].key, "outputs");
    let e = check(&format!("{OK}[plugins.sensor]\nmax_depth = 1.0\n"), &[], ViewKind::Mono).unwrap_err();
    assert_eq!(e.problems[0].key, "plugins.sensor.max_depth");
    assert!(e.problems[0].fix.contains("max_depth_m"), "{}", e.problems[0].fix);
}

#[test]
fn out_of_range_and_nan_values_are_rejected() {
    let e = check(OK, &["plugins.sensor.max_depth_m=-1", "plugins.test-points.stride=nan"], ViewKind::Mono).unwrap_err();
    let keys: Vec<_> = e.problems.iter().map(|p| p.key.as_str()).collect();
    assert!(keys.contains(&"plugins.sensor.max_depth_m"), "{e}");
    assert!(e.to_string().contains("out of range") || e.to_string().contains("invalid"), "{e}");
    let e = check(OK, &["input.association_tolerance_s=nan"], ViewKind::Mono).unwrap_err();
    assert_eq!(e.problems[0].key, "input.association_tolerance_s");
}

#[test]
fn the_undistorted_view_is_one_of_two_and_a_typo_says_which() {
    check(OK, &["input.undistorted_view=whole"], ViewKind::Mono).unwrap();
    check(OK, &["input.undistorted_view=source"], ViewKind::Mono).unwrap();
    let e = check(OK, &["input.undistorted_view=wide"], ViewKind::Mono).unwrap_err().to_string();
    assert!(e.contains("undistorted_view") && e.contains("whole") && e.contains("source"), "{e}");
}

#[test]
fn an_unused_plugin_table_is_an_error() {
    let e = check(&format!("{OK}[plugins.test-shift]\nat_frame = 3\n[plugins.nonexistent]\n"), &[], ViewKind::Mono).unwrap_err();
    let keys: Vec<_> = e.problems.iter().map(|p| p.key.as_str()).collect();
    assert_eq!(keys, vec!["plugins.nonexistent", "plugins.test-shift"]);
    assert!(e.problems[1].message.contains("not selected"));
    assert!(e.problems[0].message.contains("no plugin is named"));
}

#[test]
fn a_stereo_depth_estimator_on_a_mono_rig_is_rejected() {
    let e = check(OK, &["pipeline.depth=test-stereo"], ViewKind::Mono).unwrap_err();
    assert!(e.problems[0].message.contains("needs a stereo rig"), "{e}");
    check(OK, &["pipeline.depth=test-stereo"], ViewKind::Stereo).unwrap();
}

#[test]
fn every_problem_is_reported_at_once() {
    let text = format!(
        "{OK}[plugins.sensor]\nmax_depth_m = -3.0\nfoo = 1\n[plugins.unused]\n[camera]\nwidth = 0\nheight = 10\nfx = 1.0\nfy = 1.0\ncx = 0.0\ncy = 0.0\n"
    );
    let e = check(&text, &["pipeline.fuser=tsdf", "pipeline.loop_closer=magic"], ViewKind::Mono).unwrap_err();
    let keys: Vec<_> = e.problems.iter().map(|p| p.key.as_str()).collect();
    for k in ["pipeline.fuser", "pipeline.loop_closer", "plugins.sensor.foo", "plugins.unused", "camera.width"] {
        assert!(keys.contains(&k), "{k} missing from {keys:?}");
    }
    let text = e.to_string();
    assert!(text.starts_with(&format!("{} configuration problems in c.toml", e.problems.len())), "{text}");
    assert!(text.contains("fix:"));
}

#[test]
fn every_unknown_key_of_a_section_is_reported_not_just_the_first() {
    let e = load("[pipeline]\ntracker = \"icp-rgb\"\nbogus = 1\nalso_bogus = 2\n[input]\nwhat = 3\n", &[]).unwrap_err();
    let text = e.to_string();
    for k in ["`bogus`", "`also_bogus`", "`what`"] {
        assert!(text.contains(k), "{k} missing from {text}");
    }
    assert_eq!(e.problems.len(), 3, "{text}");
}

#[test]
fn set_overrides_any_key_and_none_switches_stages_off() {
    let c = load(OK, &["plugins.test-points.stride=8", "pipeline.loop_closer=test-shift", r#"pipeline.preprocess=[]"#, "output.dir=elsewhere"]).unwrap();
    assert_eq!(c.plugins["test-points"]["stride"].as_integer(), Some(8));
    assert_eq!(c.pipeline.loop_closer(), Some("test-shift"));
    assert_eq!(c.output.dir, std::path::PathBuf::from("elsewhere"));
    let c = load(&format!("{OK}loop_closer = \"test-shift\"\n"), &["pipeline.loop_closer=none"]).unwrap();
    assert_eq!(c.pipeline.loop_closer(), None);
    let e = load(OK, &["pipeline.depth"]).unwrap_err();
    assert!(e.problems[0].message.contains("KEY=VALUE"));
}

#[test]
fn a_syntax_error_names_the_file_and_a_missing_file_says_so() {
    let e = load("[pipeline\n", &[]).unwrap_err();
    assert!(e.to_string().contains("c.toml") && e.problems[0].key == "(syntax)", "{e}");
    let e = Config::load(Some(std::path::Path::new("/nonexistent/c.toml")), &[]).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/c.toml") && e.problems[0].message.contains("cannot read"), "{e}");
}

#[test]
fn a_camera_override_is_validated() {
    let c = Config {
        camera: Some(CameraFile {
            width: 4,
            height: 4,
            fx: f64::NAN,
            fy: 1.0,
            cx: 0.0,
            cy: 0.0,
            depth_scale: 5000.0,
            distortion: None,
            fov_radius_px: Some(-2.0),
            baseline_m: None,
            right: None,
            depth_noise: None,
        }),
        ..load(OK, &[]).unwrap()
    };
    let e = validate(&c, &test_registry(), ViewKind::Mono, "x").unwrap_err();
    let keys: Vec<_> = e.problems.iter().map(|p| p.key.as_str()).collect();
    assert_eq!(keys, vec!["camera.fx", "camera.fov_radius_px"]);
}

#[test]
fn an_empty_registry_says_nothing_is_registered() {
    let c = load(OK, &[]).unwrap();
    let e = validate(&c, &Registry::empty(), ViewKind::Mono, "x").unwrap_err();
    assert!(e.problems.iter().any(|p| p.fix.contains("no depth estimator plugin is registered")), "{e}");
    assert!(e.problems.iter().any(|p| p.fix.contains("no preprocessor plugin is registered")), "{e}");
}
