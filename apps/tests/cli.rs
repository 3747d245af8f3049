//! The `capsule-slam` binary: discovery commands, `--set` overrides and clear errors.

use std::process::Command;

use capsule_slam_framework::config::Config;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_capsule-slam"))
}

fn output(args: &[&str]) -> (bool, String, String) {
    let o = bin().args(args).output().expect("run capsule-slam");
    (o.status.success(), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn plugins_lists_every_plugin_with_units() {
    let (ok, out, _) = output(&["plugins"]);
    assert!(ok);
    assert!(out.contains("sensor (depth estimator)"), "{out}");
    assert!(out.contains("ground-truth (tracker)"), "{out}");
    assert!(out.contains("max_depth_m = 0.3  [m in [0, 100]]"), "{out}");
}

#[test]
fn the_default_config_is_complete_and_parses() {
    let (ok, out, _) = output(&["config", "--default"]);
    assert!(ok);
    let c = Config::from_table(out.parse().expect("valid TOML")).expect("valid config");
    assert_eq!(c.pipeline, capsule_slam_framework::config::PipelineConfig::default());
    assert!(out.contains("[plugins.sensor]") && out.contains("# [plugins.ground-truth]"), "{out}");
}

#[test]
fn set_overrides_reach_the_validation() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 2);
    let input = tmp.path().to_str().unwrap();
    let (ok, _, err) = output(&[
        "run",
        "--input",
        input,
        "--set",
        "pipeline.tracker=icp-magic",
        "--set",
        "pipeline.depth=sensor",
        "--set",
        "plugins.sensor.max_depth_m=-1",
        "-q",
    ]);
    assert!(!ok);
    assert!(err.contains("pipeline.tracker") && err.contains("ground-truth"), "{err}");
    assert!(err.contains("plugins.sensor.max_depth_m"), "{err}");
    // The problems are blamed on the --set overrides as well as on the config they amend.
    assert!(err.contains("the built-in default config with --set pipeline.tracker=icp-magic"), "{err}");
}

#[test]
fn run_on_a_tum_folder_writes_every_output_and_prints_the_metrics() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 8);
    let out = tmp.path().join("out");
    let (ok, stdout, err) = output(&["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "--set", "pipeline.depth=sensor", "-q"]);
    assert!(ok, "{err}");
    assert!(stdout.contains("ATE RMSE (SE3)") && stdout.contains("ms per frame"), "{stdout}");
    for f in ["config.toml", "trajectory.txt", "frames.csv", "map.ply", "summary.json"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["frames"], 8);
    assert_eq!(summary["pipeline"]["pipeline"]["tracker"], "nonrigid");
    assert_eq!(summary["build"]["version"], env!("CARGO_PKG_VERSION"));
    assert!(summary["build"]["commit"].as_str().is_some_and(|c| !c.is_empty()));
    // The pictures: trajectory and error with ground truth, the map from three sides.
    let plot = |name: &str| image::open(out.join("plots").join(name)).map(|i| i.to_rgb8());
    for name in ["trajectory_top.png", "trajectory_side.png", "ate_over_time.png", "map_top_confidence.png"] {
        assert!(plot(name).is_ok(), "plots/{name}");
    }
    for view in ["front", "top", "side"] {
        // The map is in the picture: the fixture's wall faces the first camera, a good share
        // of the front view; the others see it edge-on.
        let img = plot(&format!("map_{view}_colour.png")).unwrap();
        let lit = img.pixels().filter(|p| p.0 != [0, 0, 0]).count();
        let least = if view == "front" { img.pixels().len() / 50 } else { 1 };
        assert!(lit >= least, "map_{view}_colour.png: {lit} pixels");
    }
    // A second run replaces them (the folder is its own); --no-plots writes none.
    let again = |extra: &[&str]| {
        let mut a = vec!["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "--set", "pipeline.depth=sensor", "-q"];
        a.extend_from_slice(extra);
        output(&a)
    };
    let (ok, _, err) = again(&["--frames", "4"]);
    assert!(ok && out.join("plots/map_front_colour.png").is_file(), "{err}");
    let (ok, _, err) = again(&["--frames", "4", "--no-plots"]);
    assert!(ok && !out.join("plots/map_front_colour.png").exists(), "{err}");
    // A file of the user's in plots/ makes the folder foreign.
    std::fs::write(out.join("plots/mine.txt"), "keep").unwrap();
    let (ok, _, err) = again(&["--frames", "4"]);
    assert!(!ok && err.contains("plots/mine.txt"), "{err}");
}

#[test]
fn the_monocular_default_without_a_light_model_assumes_one_and_says_the_scale_is_unknown() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 8);
    let out = tmp.path().join("out");
    let (ok, stdout, err) = output(&["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "-q"]);
    assert!(ok, "{err}");
    // The warnings name the missing file and what it costs; the figures lead with Sim(3).
    assert!(err.contains("light.toml") && err.contains("unknown scale") && err.contains("calibrate-light"), "{err}");
    let (sim3, se3) = (stdout.find("ATE RMSE (Sim3)"), stdout.find("ATE RMSE (SE3)"));
    assert!(sim3.is_some() && se3.is_some() && sim3 < se3 && stdout.contains("metric scale      unknown"), "{stdout}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["metric_scale"], false);
    assert_eq!(summary["status"], "complete");
    // A light.toml that is there but broken is still an error naming it.
    std::fs::write(tmp.path().join("light.toml"), "gain = \"bright\"\n").unwrap();
    let (ok, _, err) = output(&["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "--force", "-q"]);
    assert!(!ok && err.contains("light.toml") && err.contains("gain"), "{err}");
}

#[test]
fn a_missing_input_or_config_names_the_path() {
    let (ok, _, err) = output(&["run", "--input", "/nonexistent/seq", "-q"]);
    assert!(!ok && err.contains("/nonexistent/seq"), "{err}");
    let (ok, _, err) = output(&["run", "--config", "/nonexistent/c.toml", "-q"]);
    assert!(!ok && err.contains("/nonexistent/c.toml"), "{err}");
}

#[test]
fn the_shipped_configs_validate() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    capsule_slam_plugins::link();
    let registry = capsule_slam_framework::Registry::from_inventory().unwrap();
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let c = Config::load(Some(&path), &[]).unwrap_or_else(|e| panic!("{e}"));
        // Validated for the rig its depth estimator takes (stereo-capsule.toml: a stereo one).
        let views = registry.get(&c.pipeline.depth).map_or(capsule_slam_framework::ViewKind::Mono, |e| e.views);
        capsule_slam_framework::config::validate::validate(&c, &registry, views, &path.display().to_string()).unwrap_or_else(|e| panic!("{e}"));
        n += 1;
    }
    assert!(n >= 2);
}

#[test]
fn depth_eval_scores_the_sensor_oracle_as_exact() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 4);
    let (ok, stdout, err) = output(&["depth-eval", "--input", tmp.path().to_str().unwrap(), "--every", "1", "--set", "pipeline.depth=sensor"]);
    assert!(ok, "{err}");
    assert!(stdout.contains("| none | 0.0000 | 0.000 | 1.000"), "{stdout}");
}

#[test]
fn calibrate_light_recovers_the_phantoms_light() {
    // A matte target of uniform albedo, as a calibration target is (with the default highlights
    // the gain and γ still come out within these bounds, the profile at the edge within 3 %).
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("phantom");
    let args = ["synth", "--preset", "1", "--frames", "31", "--size", "naneye", "--texture", "none", "--specular", "0", "--out", input.to_str().unwrap(), "-q"];
    let (ok, _, err) = output(&args);
    assert!(ok, "{err}");
    let out = tmp.path().join("fitted.toml");
    let (ok, stdout, err) = output(&["calibrate-light", "--input", input.to_str().unwrap(), "--every", "15", "--out", out.to_str().unwrap()]);
    assert!(ok, "{err}");
    let truth = capsule_slam_framework::files::read_light_file(&input.join("light.toml")).unwrap();
    let fit = capsule_slam_framework::files::read_light_file(&out).unwrap();
    assert!((fit.gain / truth.gain - 1.0).abs() < 0.03, "{stdout}");
    assert!((fit.gamma - truth.gamma).abs() < 0.05, "{stdout}");
    assert!((fit.ambient - truth.ambient).abs() < 0.005, "{stdout}");
    let cam = capsule_slam_framework::files::read_camera_file(&input.join("camera.toml")).unwrap().camera();
    for (u, v) in [(cam.cx, cam.cy), (cam.cx + 60.0, cam.cy), (cam.cx, cam.cy + 90.0)] {
        let ray = nalgebra::Point3::new((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
        let profile = |l: &capsule_slam_framework::light::LightModel| l.vignetting_at(&cam, u, v) * l.falloff(&ray);
        assert!((profile(&fit) / profile(&truth) - 1.0).abs() < 0.03, "V·gain·spot at ({u}, {v}): {stdout}");
    }
}

#[test]
fn calibrate_vignetting_recovers_the_phantoms_fall_off_and_preprocess_eval_scores_it() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("phantom");
    let args = ["synth", "--preset", "7", "--frames", "21", "--size", "naneye", "--flat-field", "6", "--out", input.to_str().unwrap(), "-q"];
    let (ok, _, err) = output(&args);
    assert!(ok, "{err}");
    let out = input.join("vignetting.toml");
    let camera = input.join("camera.toml");
    let (ok, stdout, err) = output(&[
        "calibrate-vignetting",
        "--images",
        input.join("flat_field").to_str().unwrap(),
        "--camera",
        camera.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    // Truth: the light model's V · μ.
    let truth = capsule_slam_framework::files::read_light_file(&input.join("light.toml")).unwrap();
    let fit = capsule_slam_framework::files::read_vignetting_file(&out).unwrap();
    let cam = capsule_slam_framework::files::read_camera_file(&camera).unwrap().camera();
    use capsule_slam_framework::frame::Falloff;
    for (u, v) in [(cam.cx + 40.0, cam.cy), (cam.cx, cam.cy + 80.0), (cam.cx + 80.0, cam.cy + 60.0)] {
        let (f, t) = (
            fit.falloff(&cam, u, v, Falloff::LensAndLight),
            capsule_slam_framework::light::vignetting::light_falloff(&truth, &cam, u, v, Falloff::LensAndLight),
        );
        assert!((f / t - 1.0).abs() < 0.02, "V·μ at ({u}, {v}): {f} against {t}; {stdout}");
    }
    // The eval scores the file source and the reflection remover against the phantom's truth.
    let (ok, stdout, err) = output(&[
        "preprocess-eval",
        "--input",
        input.to_str().unwrap(),
        "--every",
        "5",
        "--set",
        "plugins.vignetting.source=file",
        "--set",
        "plugins.reflection.dilate_px=0",
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("highlight mask: precision") && stdout.contains("worst radial bias"), "{stdout}");
    let bias: f64 = stdout.split("worst radial bias ").nth(1).and_then(|s| s.split(' ').next()).and_then(|s| s.parse().ok()).unwrap();
    assert!(bias < 2.0, "{stdout}");
    // Missing flat-field folder: the error names it.
    let (ok, _, err) = output(&["calibrate-vignetting", "--images", "/nonexistent/flats", "--camera", camera.to_str().unwrap()]);
    assert!(!ok && err.contains("/nonexistent/flats"), "{err}");
}

#[test]
fn preprocess_writes_the_corrected_frames_of_a_plain_image_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("phantom");
    let (ok, _, err) = output(&["synth", "--preset", "7", "--frames", "3", "--size", "naneye", "--out", input.to_str().unwrap(), "-q"]);
    assert!(ok, "{err}");
    let out = tmp.path().join("pre");
    let (rgb, camera) = (input.join("rgb"), input.join("camera.toml"));
    let preprocess = |extra: &[&str]| {
        let mut args = vec!["preprocess", "--input", rgb.to_str().unwrap(), "--camera", camera.to_str().unwrap(), "--out", out.to_str().unwrap()];
        args.extend_from_slice(extra);
        output(&args)
    };
    let (ok, stdout, err) = preprocess(&["--set", "plugins.vignetting.source=sequence", "--set", "plugins.vignetting.sequence_model=mean"]);
    assert!(ok, "{err}");
    assert_eq!(stdout.matches("highlights").count(), 3, "{stdout}");
    for i in 0..3 {
        assert!(out.join(format!("{i:04}.png")).exists() && out.join(format!("{i:04}_strip.png")).exists());
    }
    // Without a light model beside the images, `auto` falls back to the sequence estimate (the
    // shading model has no prediction outside a pipeline: frames left alone, with a warning);
    // `light` asked for explicitly says where to put it.
    let (ok, _, err) = preprocess(&[]);
    assert!(ok && err.contains("no fall-off estimate yet"), "{err}");
    let (ok, _, err) = preprocess(&["--set", "plugins.vignetting.source=light"]);
    assert!(!ok && err.contains("light.toml") && err.contains("source"), "{err}");
}

/// The example plugin library, built by cargo as a dependency of these tests (cdylib): in
/// `target/<profile>/deps/` under `cargo test`, in `target/<profile>/` under `cargo build`.
fn example_library() -> std::path::PathBuf {
    let exe = std::path::PathBuf::from(env!("CARGO_BIN_EXE_capsule-slam"));
    let profile_dir = exe.parent().expect("the binary is in a folder").to_path_buf();
    let file = format!("{}capsule_slam_dylib_example{}", std::env::consts::DLL_PREFIX, std::env::consts::DLL_SUFFIX);
    [profile_dir.join("deps").join(&file), profile_dir.join(&file)]
        .into_iter()
        .find(|p| p.is_file())
        .unwrap_or_else(|| panic!("{file} not found beside {}: is capsule-slam-dylib-example a cdylib dev-dependency of apps?", exe.display()))
}

#[test]
fn a_plugin_library_loads_lists_its_plugins_and_runs_in_a_pipeline() {
    let lib = example_library();
    let lib = lib.to_str().unwrap();
    let (ok, out, err) = output(&["--plugin-lib", lib, "plugins"]);
    assert!(ok, "{err}");
    assert!(out.contains("example-gamma (preprocessor)") && out.contains("example-inverse-square (depth estimator)"), "{out}");
    assert!(out.contains("gamma = 2.2  [- in [0.1, 10]]") && out.contains("from the library"), "{out}");

    // Its parameters are validated by the host's config validation like a linked plugin's.
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 4);
    let input = tmp.path().to_str().unwrap();
    let (ok, _, err) = output(&[
        "run",
        "--plugin-lib",
        lib,
        "--input",
        input,
        "-q",
        "--set",
        "pipeline.depth=example-inverse-square",
        "--set",
        "plugins.example-inverse-square.z_ref_m=5",
    ]);
    assert!(!ok);
    assert!(err.contains("plugins.example-inverse-square.z_ref_m") && err.contains("[0.0001, 1]"), "{err}");

    // In a pipeline: the library's preprocessor and depth estimator, the linked tracker.
    let out_dir = tmp.path().join("out");
    let (ok, stdout, err) = output(&[
        "run",
        "--plugin-lib",
        lib,
        "--input",
        input,
        "--out",
        out_dir.to_str().unwrap(),
        "-q",
        "--set",
        "pipeline.preprocess=[\"example-gamma\"]",
        "--set",
        "pipeline.depth=example-inverse-square",
        "--set",
        "pipeline.tracker=ground-truth",
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("frames            4"), "{stdout}");
    let config = std::fs::read_to_string(out_dir.join("config.toml")).unwrap();
    assert!(config.contains("[plugins.example-inverse-square]") && config.contains("z_ref_m = 0.02"), "{config}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out_dir.join("summary.json")).unwrap()).unwrap();
    assert!(summary["surfels"].as_u64().unwrap() > 0, "{summary}");
}

#[test]
fn a_tracker_from_a_plugin_library_tracks_in_a_pipeline() {
    // The camera approaches the fixture's wall 0.5 mm a frame: what `example-depth-centroid`
    // (ABI version 2) can see.
    let tmp = tempfile::tempdir().unwrap();
    let approach = |i: usize| capsule_slam_framework::geometry::Iso3::translation(0.0, 0.0, 0.0005 * i as f64);
    capsule_slam_tests::fixtures::write_dataset_with(tmp.path(), 10, approach);
    let lib = example_library();
    let out = tmp.path().join("out");
    let run = |tracker: &str| {
        output(&[
            "--plugin-lib",
            lib.to_str().unwrap(),
            "run",
            "--input",
            tmp.path().to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "-q",
            "--no-plots",
            "--force",
            "--set",
            "pipeline.depth=sensor",
            "--set",
            &format!("pipeline.tracker={tracker}"),
        ])
    };
    let (ok, stdout, err) = run("example-depth-centroid");
    assert!(ok, "{err}");
    assert!(stdout.contains("frames lost       0"), "{stdout}\n{}", std::fs::read_to_string(out.join("frames.csv")).unwrap_or_default());
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    // 4.5 mm of path; the fused map is rendered from the last pose, so the mean depth step
    // is the advance to within the fusion's averaging.
    let ate = summary["ate_rmse_m"].as_f64().unwrap();
    assert!(ate < 0.0002, "ATE {ate} m over 4.5 mm");
    // The library tracker shows in `plugins` with its kind.
    let (ok, listing, _) = output(&["--plugin-lib", lib.to_str().unwrap(), "plugins"]);
    assert!(ok && listing.contains("example-depth-centroid (tracker)"), "{listing}");
}

#[test]
fn a_plugin_library_named_without_a_directory_is_the_file_named_and_a_directory_is_not_one() {
    // A bare file name: the file in the working directory, not a search of the system's
    // library path by the dynamic loader (which does not look in the working directory).
    let tmp = tempfile::tempdir().unwrap();
    let lib = example_library();
    let name = lib.file_name().unwrap();
    std::fs::copy(&lib, tmp.path().join(name)).unwrap();
    // (cargo's LD_LIBRARY_PATH holds the example's own folder: without it, a search finds nothing.)
    let o = bin().current_dir(tmp.path()).env_remove("LD_LIBRARY_PATH").args(["--plugin-lib", name.to_str().unwrap(), "plugins"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("example-gamma (preprocessor)"));
    let (ok, _, err) = output(&["--plugin-lib", tmp.path().to_str().unwrap(), "plugins"]);
    assert!(!ok);
    assert!(err.contains("is a directory") && err.contains("library file itself"), "{err}");
    // A file that is no library: the loader's own reason is kept.
    let bad = tmp.path().join("libbad.so");
    std::fs::write(&bad, "not a library").unwrap();
    let (ok, _, err) = output(&["--plugin-lib", bad.to_str().unwrap(), "plugins"]);
    assert!(!ok);
    assert!(err.contains("dlopen failed: ") && err.contains("libbad.so: "), "{err}");
}

#[test]
fn an_os_error_is_told_once() {
    let (ok, _, err) = output(&["eval", "--gt", "/nonexistent/gt.txt", "--est", "/nonexistent/est.txt"]);
    assert!(!ok);
    assert!(err.contains("/nonexistent/gt.txt") && err.matches("os error").count() == 1, "{err}");
    let (ok, _, err) = output(&["run", "--input", "/nonexistent/seq", "-q"]);
    assert!(!ok);
    assert_eq!(err.matches("not found").count(), 1, "{err}");
}

#[test]
fn a_missing_plugin_library_names_the_path_and_the_fix() {
    let (ok, _, err) = output(&["--plugin-lib", "/nonexistent/libmine.so", "plugins"]);
    assert!(!ok);
    assert!(err.contains("/nonexistent/libmine.so") && err.contains("no such file") && err.contains("cargo build"), "{err}");
    // Without the library its plugins are unknown names, and the error lists the known ones.
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 2);
    let (ok, _, err) = output(&["run", "--set", "pipeline.depth=example-inverse-square", "--input", tmp.path().to_str().unwrap(), "-q"]);
    assert!(!ok);
    assert!(err.contains("pipeline.depth") && err.contains("example-inverse-square") && err.contains("sensor"), "{err}");
}

#[test]
fn calibrate_camera_names_a_bad_board_and_a_folder_without_boards() {
    let tmp = tempfile::tempdir().unwrap();
    let (ok, _, err) = output(&["calibrate-camera", "--images", tmp.path().to_str().unwrap(), "--board", "7", "--square-mm", "2"]);
    assert!(!ok && err.contains("--board 7") && err.contains("COLSxROWS"), "{err}");
    for k in 0..3 {
        let img = capsule_slam_framework::Rgb8::from_fn(64, 48, |x, y| [(x * 3) as u8, (y * 5) as u8, 90]);
        capsule_slam_io::images::write_rgb(&tmp.path().join(format!("{k}.png")), &img).unwrap();
    }
    let (ok, _, err) = output(&["calibrate-camera", "--images", tmp.path().to_str().unwrap(), "--board", "7x6", "--square-mm", "2"]);
    assert!(!ok, "a folder without a board gave a camera: {err}");
    assert!(err.contains("0.png: no checkerboard found") && err.contains("0 usable board views") && err.contains(tmp.path().to_str().unwrap()), "{err}");
    assert!(!tmp.path().join("camera.toml").exists());
}

#[test]
fn an_unknown_key_does_not_hide_the_unknown_plugin_beside_it() {
    let (ok, _, err) = output(&["run", "--set", "pipeline.depthh=sensor", "--set", "pipeline.tracker=nosuch", "--out", "/nonexistent/never-written"]);
    assert!(!ok);
    assert!(err.contains("2 configuration problems"), "{err}");
    assert!(err.contains("unknown field `depthh`") && err.contains("unknown tracker `nosuch`"), "{err}");
    assert!(err.contains("with --set pipeline.depthh=sensor --set pipeline.tracker=nosuch"), "the source names the --set: {err}");
}

#[test]
fn synth_stereo_writes_the_right_views_and_the_rig() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("st");
    let (ok, _, err) = output(&["synth", "--preset", "2", "--frames", "2", "--size", "naneye", "--stereo", "4", "--out", out.to_str().unwrap(), "-q"]);
    assert!(ok, "{err}");
    let cam = capsule_slam_framework::files::read_camera_file(&out.join("camera.toml")).unwrap();
    assert_eq!(cam.right.and_then(|r| r.translation_m), Some(vec![-0.004, 0.0, 0.0]));
    assert_eq!(std::fs::read_to_string(out.join("rgb_right.txt")).unwrap().lines().filter(|l| l.contains("rgb_right/")).count(), 2);
    // Without a value, 5 mm; a baseline out of range is refused, naming it.
    let (ok, _, err) = output(&["synth", "--frames", "1", "--size", "naneye", "--stereo", "--out", out.to_str().unwrap(), "-q"]);
    assert!(ok, "{err}");
    let cam = capsule_slam_framework::files::read_camera_file(&out.join("camera.toml")).unwrap();
    assert_eq!(cam.right.and_then(|r| r.translation_m), Some(vec![-0.005, 0.0, 0.0]));
    let (ok, _, err) = output(&["synth", "--frames", "1", "--stereo", "90", "--out", out.to_str().unwrap(), "-q"]);
    assert!(!ok && err.contains("stereo_baseline_mm"), "{err}");
}

#[test]
fn the_stereo_config_runs_a_stereo_phantom_at_metric_scale_without_a_light_model() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("st");
    let (ok, _, err) = output(&["synth", "--preset", "1", "--frames", "60", "--size", "naneye", "--stereo", "--out", data.to_str().unwrap(), "-q"]);
    assert!(ok, "{err}");
    std::fs::remove_file(data.join("light.toml")).unwrap();
    let config = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/stereo-capsule.toml");
    let (config, data_s) = (config.to_str().unwrap(), data.to_str().unwrap());
    let out = tmp.path().join("out");
    let (ok, stdout, err) = output(&["run", "--config", config, "--input", data_s, "--out", out.to_str().unwrap(), "-q"]);
    assert!(ok, "{err}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(
        (summary["status"].as_str(), summary["metric_scale"].as_bool(), summary["frames_lost"].as_u64()),
        (Some("complete"), Some(true), Some(0)),
        "{stdout}"
    );
    // Metric without any scale alignment: the best Sim(3) scale is 1 within 4 % and the SE(3) ATE
    // small for 60 frames over the whole 86 mm path (measured 0.61 % and 1.014; 0.235 % over the
    // 300 frames of `synth --preset 1 --stereo` at 320×320, docs/results/stereo.md).
    let (ate, scale) = (summary["ate_percent_of_path"].as_f64().unwrap(), summary["sim3_scale"].as_f64().unwrap());
    assert!(ate < 1.2 && (scale - 1.0).abs() < 0.04, "ATE {ate} % of the path, Sim(3) scale {scale}\n{stdout}");
    // depth-eval scores the stereo depth with its disparity errors and what both cameras see.
    let (ok, stdout, err) = output(&["depth-eval", "--config", config, "--input", data_s, "--every", "30"]);
    assert!(ok, "{err}");
    let line = stdout.lines().find(|l| l.starts_with("| none |")).unwrap();
    let abs_rel: f64 = line.split('|').nth(2).unwrap().trim().parse().unwrap();
    assert!(abs_rel < 0.03, "{stdout}");
    assert!(stdout.contains("% of pixels off by > 1 px") && stdout.contains("of the pixels both cameras see"), "{stdout}");
    // depth writes each frame's depth and its strip.
    let dout = tmp.path().join("depth");
    let (ok, stdout, err) = output(&["depth", "--config", config, "--input", data_s, "--out", dout.to_str().unwrap(), "--set", "input.max_frames=2"]);
    assert!(ok, "{err}");
    assert!(stdout.contains("median disparity"), "{stdout}");
    let d = capsule_slam_io::images::read_depth(&dout.join("0001_depth.png"), 5000.0, None).unwrap();
    let truth = capsule_slam_io::images::read_depth(&data.join("depth/000001.png"), 5000.0, None).unwrap();
    let e = capsule_slam_eval::depth::depth_error(&d, &truth, false).unwrap();
    assert!(e.abs_rel < 0.03 && e.pixels > 20_000, "{e:?}");
}

#[test]
fn depth_noisier_than_its_declared_sigma_is_measured_against_the_model_and_tracked() {
    // A sequence whose depth has the 5 % smooth error but whose camera.toml declares no
    // depth_noise (a recording nobody measured): the sensor stage's 0.1 mm σ is far too small.
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("noisy");
    let synth = ["synth", "--preset", "1", "--frames", "40", "--size", "naneye", "--depth-noise", "smooth:0.05", "-q", "--out"];
    let (ok, _, err) = output(&[&synth[..], &[data.to_str().unwrap()]].concat());
    assert!(ok, "{err}");
    let camera = std::fs::read_to_string(data.join("camera.toml")).unwrap();
    let start = camera.find("[depth_noise]").expect("synth declares the noise");
    let end = camera[start + 1..].find("\n[").map_or(camera.len(), |e| start + 1 + e + 1);
    std::fs::write(data.join("camera.toml"), format!("{}{}", &camera[..start], &camera[end..])).unwrap();
    let run = |factor: &str| {
        let out = tmp.path().join(format!("out{factor}"));
        let key = format!("plugins.nonrigid.rigid.depth_error_factor={factor}");
        let args = ["run", "--input", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-plots", "--set", "pipeline.depth=sensor", "--set", &key];
        let (ok, stdout, err) = output(&args);
        assert!(ok, "{err}");
        let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
        (s["frames_lost"].as_u64().unwrap(), s["ate_percent_of_path"].as_f64().unwrap(), format!("{stdout}{err}"))
    };
    // Measured against the model, the error (2–9 % on these frames) replaces the 0.1 mm σ from
    // the first tracked frame, which is registered again: measured 0 lost, 0.30 % of the path.
    let (lost, ate, log) = run("2");
    assert!(log.contains("the depth is noisier than its σ says"), "{log}");
    assert!(lost == 0 && ate < 1.0, "{lost} frames lost, ATE {ate} % of the path\n{log}");
    // Without the measurement the tracker trusts the noise to 0.1 mm: measured 16 of 40 lost.
    let (lost_off, ate_off, log) = run("0");
    assert!(lost_off >= 5 && ate_off > 3.0 * ate, "{lost_off} frames lost, ATE {ate_off} %\n{log}");
}

#[test]
fn eval_splits_the_live_surface_by_the_last_view_with_the_sequences_camera_and_names_a_bad_one() {
    let tmp = tempfile::tempdir().unwrap();
    let (seq, out) = (tmp.path().join("seq"), tmp.path().join("out"));
    let s = |p: &std::path::Path| p.to_str().unwrap().to_owned();
    let synth = ["synth", "--preset", "2", "--frames", "30", "--size", "naneye", "--deform", "4", "--surface-every", "10", "--noise", "0", "--specular", "0"];
    let (ok, _, err) = output(&[&synth[..], &["--out", &s(&seq)]].concat());
    assert!(ok, "{err}");
    let oracle = [
        "--set",
        "pipeline.depth=sensor",
        "--set",
        "pipeline.preprocess=[]",
        "--set",
        "pipeline.tracker=ground-truth",
        "--set",
        "input.initial_pose=ground-truth",
    ];
    let (ok, stdout, err) = output(&[&["run", "--input", &s(&seq), "--out", &s(&out), "--no-plots", "-q"][..], &oracle[..]].concat());
    assert!(ok, "{err}");
    assert!(stdout.contains("in the last frame's view") && stdout.contains("the camera left"), "{stdout}");
    let eval = |live: &std::path::Path| {
        output(&[
            "eval",
            "--gt",
            &s(&seq.join("groundtruth.txt")),
            "--est",
            &s(&out.join("trajectory.txt")),
            "--map",
            &s(&out.join("map.ply")),
            "--surface-gt",
            &s(&seq.join("gt_surface.ply")),
            "--live-surface-gt",
            &s(live),
        ])
    };
    let last = "gt_surface_000029.ply";
    let (ok, stdout, err) = eval(&seq.join(last));
    assert!(ok && stdout.contains("in the last frame's view") && stdout.contains("left by the camera"), "{stdout}{err}");
    // Without a camera.toml beside the true surface the split is left out, and said so.
    let bare = tmp.path().join("bare");
    std::fs::create_dir(&bare).unwrap();
    std::fs::copy(seq.join(last), bare.join(last)).unwrap();
    let (ok, stdout, err) = eval(&bare.join(last));
    assert!(ok && stdout.contains("live surface RMSE") && !stdout.contains("in the last frame's view"), "{stdout}");
    assert!(err.contains("camera.toml") && err.contains("not split"), "{err}");
    // A broken one is an error that names it.
    std::fs::write(bare.join("camera.toml"), "width = 'wide'\n").unwrap();
    let (ok, _, err) = eval(&bare.join(last));
    assert!(!ok && err.contains(&s(&bare.join("camera.toml"))), "{err}");
}

/// `bench --rounds N`: each stage's figure is the median of the N runs' means it lists, and the
/// runs, from freshly built pipelines, end with the same map and ATE (the same work timed).
#[test]
fn bench_rounds_report_the_median_of_identical_runs() {
    let cache = tempfile::tempdir().unwrap();
    let run = |rounds: &str| {
        let o = bin()
            .env("CAPSULE_SLAM_CACHE", cache.path())
            .args(["bench", "--sizes", "naneye", "--frames", "6", "--rounds", rounds, "--set", "pipeline.depth=sensor"])
            .output()
            .expect("run capsule-slam");
        (o.status.success(), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (ok, out, err) = run("3");
    assert!(ok, "{err}");
    assert!(out.contains("mean ms (median of 3 runs)"), "{out}");
    let rows: Vec<Vec<&str>> = out.lines().filter(|l| l.starts_with("| 250×250 | 6 |")).map(|l| l.split('|').map(str::trim).collect()).collect();
    assert_eq!(rows.len(), 6, "one row per stage: {out}");
    for r in &rows {
        // "", size, frames, stage, median, p95, each run's mean, ""
        let median: f64 = r[4].parse().unwrap();
        let mut each: Vec<f64> = r[6].split(" / ").map(|v| v.parse().unwrap()).collect();
        assert_eq!(each.len(), 3, "{r:?}");
        each.sort_by(f64::total_cmp);
        assert_eq!(format!("{median:.2}"), format!("{:.2}", each[1]), "the median of {r:?}");
    }
    assert!(rows.iter().any(|r| r[3] == "total") && rows.iter().all(|r| r[4].parse::<f64>().unwrap() >= 0.0), "{out}");
    assert!(out.contains("the 3 runs ended with the same map size and ATE to the bit"), "{out}\n{err}");
    // One round keeps the plain table; zero rounds is refused, naming the flag.
    let (ok, out, _) = run("1");
    assert!(ok && out.contains("| size | frames | stage | mean ms | p95 ms |") && !out.contains("median"), "{out}");
    let (ok, _, err) = run("0");
    assert!(!ok && err.contains("--rounds"), "{err}");
}
