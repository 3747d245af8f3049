//! `run --record`: the rerun recording of a run (cargo feature `record`).

use std::process::Command;

fn run(args: &[&str]) -> (bool, String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_capsule-slam")).args(args).output().expect("run capsule-slam");
    (o.status.success(), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn a_record_file_must_be_an_rrd_and_is_refused_before_anything_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 3);
    let out = tmp.path().join("out");
    let (ok, _, err) = run(&["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "-q", "--record", "run.txt"]);
    assert!(!ok && err.contains("run.txt") && err.contains(".rrd"), "{err}");
    assert!(!out.exists(), "nothing is written before the run");
}

#[cfg(not(feature = "record"))]
#[test]
fn without_the_feature_record_says_how_to_build_it_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 3);
    let out = tmp.path().join("out");
    let rrd = out.join("run.rrd");
    let (ok, _, err) = run(&["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "-q", "--record", rrd.to_str().unwrap()]);
    assert!(!ok && err.contains("--features record"), "{err}");
    assert!(!out.exists(), "nothing is written before the run");
}

#[cfg(feature = "record")]
#[test]
fn record_writes_every_frame_the_maps_and_the_trajectories_and_a_rerun_replaces_it() {
    let tmp = tempfile::tempdir().unwrap();
    capsule_slam_tests::fixtures::write_dataset(tmp.path(), 8);
    let out = tmp.path().join("out");
    let rrd = out.join("run.rrd");
    let args = ["run", "--input", tmp.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "--set", "pipeline.depth=sensor", "-q", "--no-plots"];
    let record = [&args[..], &["--record", rrd.to_str().unwrap(), "--record-map-every", "3"]].concat();
    let (ok, stdout, err) = run(&record);
    assert!(ok, "{err}");
    assert!(stdout.contains("recording") && stdout.contains("run.rrd"), "{stdout}");
    let c = capsule_slam_record::contents(&rrd).unwrap();
    let rows = |e: &str| c.rows_of(e);
    for e in ["world/camera", "world/camera/image/input", "world/camera/image/preprocessed", "world/camera/image/depth", "metrics/ms_per_frame"] {
        assert_eq!(rows(e), 8, "{e}: {c:?}");
    }
    // Every tracked frame is fused and has the model predicted at its pose; a lost one not.
    let frames = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let tracked = frames.lines().filter(|l| l.split(',').nth(2) == Some("tracked")).count() as u64;
    assert!(tracked >= 4, "{frames}");
    assert_eq!(rows("world/camera/image/predicted_depth"), tracked, "{c:?}");
    assert_eq!(rows("world/camera/image/predicted_colour"), tracked, "{c:?}");
    assert_eq!(rows("world/camera/image"), 1, "the pinhole, once");
    assert_eq!(rows("world/map"), 4, "frames 0, 3, 6 and the end");
    assert_eq!(rows("world/trajectory/estimated"), 9, "every frame and the end");
    assert_eq!(rows("world/trajectory/ground_truth"), 1);
    // The recording does not change the run: the same trajectory without it.
    let with = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    let (ok, _, err) = run(&args);
    assert!(ok, "{err}");
    assert_eq!(std::fs::read_to_string(out.join("trajectory.txt")).unwrap(), with);
    assert!(!rrd.exists(), "the run's folder is its own: the earlier recording went with its other outputs");
    let (ok, _, err) = run(&record);
    assert!(ok && rrd.is_file(), "{err}");
    rerun_verifies(&rrd);
}

/// rerun's own CLI (`pip install rerun-sdk==0.36.3`) loads the file: `python3 -m rerun rrd
/// verify`. Without it the check says so loudly and passes, unless
/// `CAPSULE_SLAM_REQUIRE_RERUN=1` (CI sets it).
#[cfg(feature = "record")]
fn rerun_verifies(rrd: &std::path::Path) {
    let installed = Command::new("python3").args(["-c", "import rerun"]).output().is_ok_and(|o| o.status.success());
    if !installed {
        assert!(
            std::env::var("CAPSULE_SLAM_REQUIRE_RERUN").as_deref() != Ok("1"),
            "rerun-sdk is required (CAPSULE_SLAM_REQUIRE_RERUN=1) but `python3 -c 'import rerun'` fails"
        );
        eprintln!("\n*** SKIPPED: verifying the recording with rerun's own CLI needs `pip install rerun-sdk==0.36.3` ***\n");
        return;
    }
    let o = Command::new("python3").args(["-m", "rerun", "rrd", "verify"]).arg(rrd).output().expect("python3 runs");
    let said = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    // It exits 0 on a file it cannot read too ("0 files verified"): the count is the verdict.
    assert!(o.status.success() && said.contains("1 file verified without error"), "rerun rrd verify: {said}");
}
