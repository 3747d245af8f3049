//! The pipeline runner end to end on a rendered fixture with exact depth and ground truth,
//! with test-only fuser and loop closer.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use capsule_slam_framework::config::{Config, InitialPose};
use capsule_slam_framework::pipeline::Pipeline;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::{Dataset, ply, tum};
use capsule_slam_run::RunWriter;
use capsule_slam_run::{RunOptions, run};
use capsule_slam_tests::{fixtures, stages::test_registry};

fn config(extra: &[&str]) -> Config {
    let mut sets = vec!["pipeline.depth=sensor".to_string(), "pipeline.tracker=ground-truth".into(), "pipeline.fuser=test-points".into()];
    sets.extend(extra.iter().map(|s| s.to_string()));
    Config::load(None, &sets).unwrap()
}

fn run_on(dir: &std::path::Path, out: &std::path::Path, cfg: &Config) -> Result<capsule_slam_run::Summary, capsule_slam_framework::PipelineError> {
    let registry = test_registry();
    let ds = Dataset::open(dir, &cfg.input, None).unwrap();
    let env = BuildEnv::new(ds.rig(), Some(dir.to_owned()));
    let mut p = Pipeline::build(cfg, "test", &registry, &env).unwrap();
    let mut w = RunWriter::create(out, &p.resolved_config().to_toml_string()).unwrap();
    run(&ds, &mut p, &mut w, &RunOptions { max_frames: cfg.input.max_frames, write_map: true, eval_sim3: false, ..RunOptions::default() }, |_| {})
}

#[test]
fn oracle_pipeline_reproduces_ground_truth_and_writes_every_output() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    let gt = fixtures::write_dataset(&data, 12);
    let cfg = config(&[]);
    let summary = run_on(&data, &out, &cfg).unwrap();

    assert_eq!(summary.frames, 12);
    assert_eq!(summary.status, "complete");
    assert!(summary.ate_rmse_m.unwrap() < 1e-6, "{:?}", summary.ate_rmse_m);
    let traj = tum::read_trajectory(&out.join("trajectory.txt")).unwrap();
    assert_eq!(traj.len(), 12);
    // gt_pose(0) is the identity, so the oracle's relative poses equal the ground truth.
    for (e, g) in traj.iter().zip(&gt) {
        assert!((e.t_world_cam.translation.vector - g.t_world_cam.translation.vector).norm() < 1e-8);
    }
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    assert_eq!(csv.lines().count(), 13);
    assert!(csv.starts_with("frame,timestamp_s,status,ms_preprocess"));
    // counters.jsonl: one object a frame with every stage counter, keyed `plugin.counter`.
    let counters: Vec<serde_json::Value> =
        std::fs::read_to_string(out.join("counters.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(counters.len(), 12);
    for (i, c) in counters.iter().enumerate() {
        assert_eq!(c["frame"], i);
        assert!(c["sensor.valid_pixels"].as_f64().unwrap() > 0.0, "{c}");
    }
    // The summary's sums and means are those of the written counters (the run keeps running
    // sums, not every frame's reports).
    for key in ["test-points.added", "sensor.valid_pixels"] {
        let sum = counters.iter().map(|c| c[key].as_f64().unwrap()).sum::<f64>();
        assert_eq!(sum, summary.counters_sum[key], "{key}");
        assert!((sum / 12.0 - summary.counters_mean[key]).abs() <= 1e-9 * sum, "{key}");
    }

    // The map lies on the rendered plane z = 0.05 m and has what the fuser reported.
    let map = ply::read_surfels(&out.join("map.ply")).unwrap();
    assert_eq!(map.len(), summary.surfels);
    assert!(map.len() > 100);
    for s in &map.surfels {
        assert!((s.position_m.z - 0.05).abs() < 2e-4, "{}", s.position_m.z);
    }

    // summary.json has the promised keys; config.toml reloads into the resolved config.
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    for key in ["frames", "ms_per_frame_mean", "ms_per_frame_p95", "surfels", "pipeline", "ate_rmse_m"] {
        assert!(json.get(key).is_some(), "summary.json lacks {key}");
    }
    let again = Config::load(Some(&out.join("config.toml")), &[]).unwrap();
    assert_eq!(again.pipeline, cfg.pipeline);
    assert_eq!(again.plugins["test-points"]["stride"].as_integer(), Some(4), "defaults are recorded");
}

#[test]
fn a_loop_closure_deforms_the_map_and_the_trajectory() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    fixtures::write_dataset(&data, 10);
    let cfg = config(&["pipeline.loop_closer=test-shift", "plugins.test-shift.at_frame=5"]);
    let summary = run_on(&data, &out, &cfg).unwrap();
    assert_eq!(summary.loop_closures, 1);

    let online = tum::read_trajectory(&out.join("trajectory_online.txt")).unwrap();
    let final_ = tum::read_trajectory(&out.join("trajectory.txt")).unwrap();
    assert_eq!(online.len(), 10);
    assert_eq!(final_.len(), 10);
    // Poses before the closure moved by the shift; the closure frame's pose is the corrected one.
    for i in 0..5 {
        let d = final_[i].t_world_cam.translation.vector - online[i].t_world_cam.translation.vector;
        assert!((d - nalgebra::Vector3::new(0.0, 0.0, 0.01)).norm() < 1e-9, "frame {i}: {d}");
    }
    // Surfels fused before frame 5 were lifted by 1 cm, and frame 5 is fused at the corrected
    // pose; later frames come from the (unshifted) oracle again.
    let map = ply::read_surfels(&out.join("map.ply")).unwrap();
    for s in &map.surfels {
        let expected = if s.t0 <= 5 { 0.06 } else { 0.05 };
        assert!((s.position_m.z - expected).abs() < 2e-4, "t0 {} z {}", s.t0, s.position_m.z);
    }
}

#[test]
fn an_interrupted_run_keeps_what_it_wrote() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    fixtures::write_dataset(&data, 10);
    std::fs::write(data.join("rgb/0006.png"), b"not a png").unwrap();
    let err = run_on(&data, &out, &config(&[])).unwrap_err().to_string();
    assert!(err.contains("rgb/0006.png") && err.contains("decode"), "{err}");

    let traj = tum::read_trajectory(&out.join("trajectory.txt")).unwrap();
    assert_eq!(traj.len(), 6, "frames 0..5 survive");
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    assert_eq!(csv.lines().count(), 7);
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert!(json["status"].as_str().unwrap().starts_with("failed at frame 6: "), "{}", json["status"]);
    assert_eq!(json["frames"], 6);
    assert!(!ply::read_surfels(&out.join("map.ply")).unwrap().is_empty());
}

#[test]
fn a_run_with_no_usable_depth_says_it_failed_and_why() {
    // All-zero depth: every frame runs, nothing is fused. The run used to end `complete`.
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    fixtures::write_dataset(&data, 5);
    let cam = fixtures::camera();
    for i in 0..5 {
        let empty = capsule_slam_framework::DepthMap::new(cam.width as usize, cam.height as usize);
        capsule_slam_io::images::write_depth(&data.join(format!("depth/{i:04}.png")), &empty, cam.depth_scale).unwrap();
    }
    let err = run_on(&data, &out, &config(&[])).unwrap_err();
    assert!(matches!(err, capsule_slam_framework::PipelineError::NoResult(_)), "{err}");
    assert!(err.to_string().contains("map is empty after 5 frames"), "{err}");
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let status = json["status"].as_str().unwrap();
    assert!(status.starts_with("failed") && status.contains("usable depth"), "{status}");
    assert_eq!(json["frames"], 5, "every frame ran and is recorded");
    assert_eq!(tum::read_trajectory(&out.join("trajectory.txt")).unwrap().len(), 5);
}

#[test]
fn a_rerun_that_is_cut_off_leaves_no_older_result_beside_its_own() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    fixtures::write_dataset(&data, 4);
    run_on(&data, &out, &config(&[])).unwrap();
    assert!(out.join("map.ply").exists() && out.join("summary.json").exists());
    // A second run into the same folder, killed right after it started: no older result.
    drop(RunWriter::create(&out, "").unwrap());
    assert!(!out.join("map.ply").exists() && !out.join("summary.json").exists(), "the older run's map and summary are gone");
    assert!(tum::read_trajectory(&out.join("trajectory.txt")).unwrap().is_empty());
    // A folder that holds a file a run does not write is refused, naming it; with force the
    // run writes beside it and leaves it alone.
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let err = RunWriter::create(&out, "").err().unwrap().to_string();
    assert!(err.contains("notes.txt") && err.contains("--force"), "{err}");
    drop(RunWriter::create_with(&out, "", true).unwrap());
    assert_eq!(std::fs::read_to_string(out.join("notes.txt")).unwrap(), "mine");
}

#[test]
fn a_corrupt_file_read_only_to_score_the_run_costs_its_figures_not_the_run() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    fixtures::write_dataset(&data, 4);
    std::fs::write(data.join("gt_surface.ply"), b"ply\nformat nonsense\n").unwrap();
    let summary = run_on(&data, &out, &config(&[])).unwrap();
    assert_eq!(summary.status, "complete");
    assert!(summary.warnings.iter().any(|w| w.contains("surface figures off") && w.contains("gt_surface.ply")), "{:?}", summary.warnings);
    assert!(!summary.metrics.contains_key("surface_rmse_m") && summary.ate_rmse_m.is_some());
}

#[test]
fn a_broken_depth_image_costs_a_monocular_run_its_score_of_that_frame_not_the_run() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    fixtures::write_dataset(&data, 4);
    std::fs::write(data.join("depth/0002.png"), b"not a png").unwrap();
    // Depth from the image: the input's depth only scores it.
    let summary = run_on(&data, &out, &config(&["pipeline.depth=tsai-shah"])).unwrap();
    assert_eq!((summary.status.as_str(), summary.frames), ("complete", 4));
    assert!(summary.warnings.iter().any(|w| w.contains("frame 2: depth not scored") && w.contains("depth/0002.png")), "{:?}", summary.warnings);
    // With sensor depth the same file stops the run at frame 2, naming it.
    let err = run_on(&data, &tmp.path().join("out2"), &config(&[])).unwrap_err().to_string();
    assert!(err.contains("depth/0002.png"), "{err}");
}

#[test]
fn initial_pose_ground_truth_starts_at_the_first_ground_truth_pose() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, out) = (tmp.path().join("data"), tmp.path().join("out"));
    let gt = fixtures::write_dataset(&data, 4);
    // Re-write the ground truth with an offset world frame.
    let off = capsule_slam_framework::Iso3::translation(0.1, 0.2, 0.3);
    let moved: Vec<_> =
        gt.iter().map(|p| capsule_slam_framework::geometry::StampedPose { timestamp_s: p.timestamp_s, t_world_cam: off * p.t_world_cam }).collect();
    tum::write_trajectory(&data.join("groundtruth.txt"), &moved).unwrap();
    let mut cfg = config(&[]);
    cfg.input.initial_pose = InitialPose::GroundTruth;
    run_on(&data, &out, &cfg).unwrap();
    let traj = tum::read_trajectory(&out.join("trajectory.txt")).unwrap();
    assert!((traj[3].t_world_cam.translation.vector - moved[3].t_world_cam.translation.vector).norm() < 1e-8);
}

#[test]
fn same_input_and_config_give_the_same_output() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    fixtures::write_dataset(&data, 6);
    let cfg = config(&[]);
    run_on(&data, &tmp.path().join("a"), &cfg).unwrap();
    run_on(&data, &tmp.path().join("b"), &cfg).unwrap();
    for f in ["trajectory.txt", "map.ply", "config.toml"] {
        assert_eq!(std::fs::read(tmp.path().join("a").join(f)).unwrap(), std::fs::read(tmp.path().join("b").join(f)).unwrap(), "{f} differs");
    }
}

#[test]
fn the_real_rgbd_pipelines_give_the_same_output_twice() {
    // The linked tracker and fuser (parallel Gauss-Newton sums, atomics in the splat), not the
    // oracles: two runs byte-identical.
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    fixtures::write_dataset(&data, 8);
    for tracker in ["icp-rgb", "nonrigid"] {
        let cfg = config(&[&format!("pipeline.tracker={tracker}"), "pipeline.fuser=surfel-cpu"]);
        let (a, b) = (tmp.path().join(format!("{tracker}-a")), tmp.path().join(format!("{tracker}-b")));
        let summary = run_on(&data, &a, &cfg).unwrap();
        assert!(summary.frames == 8 && summary.frames_lost < 8, "{tracker}: {summary:?}");
        run_on(&data, &b, &cfg).unwrap();
        for f in ["trajectory.txt", "map.ply", "frames.csv"] {
            let (x, y) = (std::fs::read(a.join(f)).unwrap(), std::fs::read(b.join(f)).unwrap());
            if f == "frames.csv" {
                // Its timings differ; the rest of each row must not.
                let rows = |t: &[u8]| String::from_utf8_lossy(t).lines().map(|l| l.split(',').take(3).collect::<Vec<_>>().join(",")).collect::<Vec<_>>();
                assert_eq!(rows(&x), rows(&y), "{tracker}: {f}");
            } else {
                assert!(x == y, "{tracker}: {f} differs");
            }
        }
    }
}

#[test]
fn a_trackers_warp_moves_the_map_before_fusion_and_a_fuser_without_warp_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    fixtures::write_dataset(&data, 6);
    // surfel-cpu follows the warp: 5 warps of 0.1 mm along z, each before the frame is fused.
    let run = |tracker: &str, out: &str| {
        // Every surfel, those of the last frame too.
        let sets = [
            "pipeline.depth=sensor".to_string(),
            "pipeline.preprocess=[]".into(),
            format!("pipeline.tracker={tracker}"),
            "pipeline.fuser=surfel-cpu".into(),
            "output.map_surfels=all".into(),
        ];
        let summary = run_on(&data, &tmp.path().join(out), &Config::load(None, &sets).unwrap()).unwrap();
        (summary, ply::read_surfels(&tmp.path().join(out).join("map.ply")).unwrap())
    };
    let (summary, warped) = run("test-warp", "warped");
    let (_, plain) = run("ground-truth", "plain");
    assert_eq!(summary.frames_lost, 0);
    let counters: Vec<serde_json::Value> =
        std::fs::read_to_string(tmp.path().join("warped/counters.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(counters.iter().filter(|c| c.get("surfel-cpu.ms_warp").is_some()).count(), 5, "a warp on every frame after the first");
    // frames.csv gives each frame's warp: mean and max node displacement, mm.
    let csv = std::fs::read_to_string(tmp.path().join("warped/frames.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (mean, max) = (col("warp_mean_mm"), col("warp_max_mm"));
    for (i, line) in csv.lines().skip(1).enumerate() {
        let f: Vec<&str> = line.split(',').collect();
        assert_eq!(f.len(), header.len(), "{line}");
        let expect = if i == 0 { "" } else { "0.1000" };
        assert_eq!((f[mean], f[max]), (expect, expect), "frame {i}");
    }
    let mean_z = |map: &capsule_slam_framework::SurfelSet, t0: u32| {
        let z: Vec<f64> = map.surfels.iter().filter(|s| s.t0 == t0).map(|s| f64::from(s.position_m.z)).collect();
        assert!(!z.is_empty(), "no surfel created at frame {t0}");
        z.iter().sum::<f64>() / z.len() as f64
    };
    // The first frame's surface was warped by up to 0.5 mm (less where later frames merged into
    // it, measured where the wall is).
    let first = mean_z(&warped, 0) - mean_z(&plain, 0);
    assert!(first > 5e-5 && first <= 5e-4 + 1e-6, "frame 0's surface moved {first} m");

    // A fuser that cannot deform stops the run with an error naming it.
    let cfg = Config::load(None, &["pipeline.depth=sensor", "pipeline.tracker=test-warp", "pipeline.fuser=test-points"].map(String::from)).unwrap();
    let err = run_on(&data, &tmp.path().join("points"), &cfg).unwrap_err().to_string();
    assert!(err.contains("test-points") && err.contains("cannot deform"), "{err}");
}

#[test]
fn the_noise_a_tracker_weighed_the_depth_by_is_the_noise_the_map_fuses_it_with() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    fixtures::write_dataset(&data, 4);
    let run = |relative: &str, out: &str| {
        let sets = [
            "pipeline.depth=sensor".to_string(),
            "pipeline.preprocess=[]".into(),
            "pipeline.tracker=test-warp".into(),
            "plugins.test-warp.shift_m=[0.0, 0.0, 0.0]".into(),
            format!("plugins.test-warp.noise_relative={relative}"),
            "plugins.test-warp.noise_from_frame=2".into(),
            "pipeline.fuser=surfel-cpu".into(),
            "output.map_surfels=all".into(),
        ];
        run_on(&data, &tmp.path().join(out), &Config::load(None, &sets).unwrap()).unwrap();
        let counters: Vec<serde_json::Value> =
            std::fs::read_to_string(tmp.path().join(out).join("counters.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        let raised_at: Vec<usize> = counters.iter().enumerate().filter(|(_, c)| c.get("surfel-cpu.surfels_sigma_raised").is_some()).map(|(i, _)| i).collect();
        (ply::read_surfels(&tmp.path().join(out).join("map.ply")).unwrap(), raised_at)
    };
    // The fixture's plane lies 5 cm in front of every camera: a 4 % error is 2 mm, where the
    // sensor's undeclared default is 0.1 mm. The tracker says so from frame 2: the map of
    // frames 0 and 1 is raised to it once, then frames 2 and 3 are fused with it, so no surfel
    // is sharper than 2 mm / √4 (without raising the map, frame 0's 0.1 mm surfels would stay
    // about that sharp); without the tracker's noise every surfel keeps 0.1 mm or less.
    let ((raised, at), (plain, none)) = (run("0.04", "raised"), run("0", "plain"));
    assert_eq!((at, none), (vec![2], vec![]), "the map is raised once, at the first frame that reports the noise");
    assert!(raised.len() > 100 && plain.len() > 100);
    let min_sigma = |m: &capsule_slam_framework::SurfelSet| m.surfels.iter().map(|s| s.sigma_m).fold(f32::INFINITY, f32::min);
    let max_sigma = |m: &capsule_slam_framework::SurfelSet| m.surfels.iter().map(|s| s.sigma_m).fold(0.0f32, f32::max);
    assert!(min_sigma(&raised) >= 0.5 * 0.002 - 1e-6, "σ {} m", min_sigma(&raised));
    assert!(max_sigma(&plain) <= 1e-4 + 1e-9, "σ {} m", max_sigma(&plain));
}

#[test]
fn a_trackers_pose_off_unit_rotation_is_renormalised_and_a_nan_pose_is_a_lost_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let gt = fixtures::write_dataset(&data, 8);
    let cfg = config(&["pipeline.tracker=test-bad-pose", "plugins.test-bad-pose.quaternion_scale=1.01", "plugins.test-bad-pose.nan_at_frame=4"]);
    let registry = test_registry();
    let ds = Dataset::open(&data, &cfg.input, None).unwrap();
    let mut p = Pipeline::build(&cfg, "test", &registry, &BuildEnv::new(ds.rig(), Some(data.clone()))).unwrap();
    let mut w = RunWriter::create(&tmp.path().join("out"), &p.resolved_config().to_toml_string()).unwrap();
    let mut warnings: Vec<(usize, String)> = Vec::new();
    let summary = run(&ds, &mut p, &mut w, &RunOptions::default(), |r| warnings.extend(r.warnings().map(|m| (r.index, m)))).unwrap();
    // The NaN pose is a lost frame at the previous pose, and says so.
    assert_eq!(summary.frames_lost, 1);
    assert!(warnings.iter().any(|(i, m)| *i == 4 && m.contains("not finite")), "{warnings:?}");
    // Every other pose is the ground truth with its rotation back at unit norm (a 1 % scaled
    // quaternion would scale the map by 2 %), each renormalisation named.
    let traj = p.trajectory();
    for (i, (e, g)) in traj.iter().zip(&gt).enumerate() {
        assert!((e.t_world_cam.rotation.quaternion().norm() - 1.0).abs() < 1e-12, "frame {i}: norm {}", e.t_world_cam.rotation.quaternion().norm());
        let truth = if i == 4 { &gt[3] } else { g };
        assert!((e.t_world_cam.rotation.coords - truth.t_world_cam.rotation.coords).norm() < 1e-8, "frame {i}");
        assert!((e.t_world_cam.translation.vector - truth.t_world_cam.translation.vector).norm() < 1e-8, "frame {i}");
    }
    assert_eq!(warnings.iter().filter(|(_, m)| m.contains("renormalised")).count(), 7, "{warnings:?}");
}
