//! The bad-input corpus (issue 18): each case a fixture made here from a small valid TUM folder,
//! run through the binary. Each asserts the exit status, that the message names the culprit,
//! that nothing panicked, and what the output folder holds afterwards (kept and valid, or
//! nothing when the run could not start).

#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::path::Path;
use std::process::Command;

/// One case: how to break a copy of the valid folder, the extra arguments, and what must follow.
struct Case {
    name: &'static str,
    damage: fn(&Path),
    args: &'static [&'static str],
    succeeds: bool,
    /// Every one of these must appear in stderr.
    names: &'static [&'static str],
    /// Files the output folder must hold afterwards (empty: it must not exist).
    kept: &'static [&'static str],
}

fn replace(dir: &Path, file: &str, text: &str) {
    std::fs::write(dir.join(file), text).unwrap();
}

const CASES: &[Case] = &[
    Case {
        name: "no usable depth",
        damage: |d| {
            for i in 0..6 {
                let depth = capsule_slam_framework::DepthMap::new(48, 40);
                capsule_slam_io::images::write_depth(&d.join(format!("depth/{i:04}.png")), &depth, 5000.0).unwrap();
            }
        },
        args: &["--set", "pipeline.depth=sensor"],
        succeeds: false,
        names: &["no frame tracked", "depth"],
        kept: &["trajectory.txt", "frames.csv", "summary.json"],
    },
    Case {
        name: "a broken depth image in the middle",
        damage: |d| replace(d, "depth/0003.png", "not a png"),
        args: &["--set", "pipeline.depth=sensor"],
        succeeds: false,
        names: &["0003.png", "frame 3"],
        kept: &["trajectory.txt", "frames.csv", "summary.json"],
    },
    Case {
        name: "a corrupt evaluation surface",
        damage: |d| replace(d, "gt_surface.ply", "ply\nformat nonsense\n"),
        args: &["--set", "pipeline.depth=sensor"],
        succeeds: true,
        names: &["gt_surface.ply"],
        kept: &["trajectory.txt", "frames.csv", "summary.json", "map.ply"],
    },
    Case {
        name: "an unknown lens model",
        damage: |d| {
            let text = std::fs::read_to_string(d.join("camera.toml")).unwrap();
            replace(d, "camera.toml", &format!("{text}\ndistortion = {{ model = \"kannala\", coefficients = [0.1] }}\n"));
        },
        args: &["--set", "pipeline.depth=sensor"],
        succeeds: false,
        names: &["camera.toml", "distortion.model", "kannala"],
        kept: &[],
    },
    Case {
        name: "a frame of the wrong size",
        damage: |d| capsule_slam_io::images::write_rgb(&d.join("rgb/0002.png"), &capsule_slam_framework::Rgb8::new(32, 24)).unwrap(),
        args: &["--set", "pipeline.depth=sensor"],
        succeeds: false,
        names: &["0002.png", "32×24", "48×40"],
        kept: &["trajectory.txt", "summary.json"],
    },
    Case {
        name: "a garbled line of rgb.txt",
        damage: |d| {
            let text = std::fs::read_to_string(d.join("rgb.txt")).unwrap();
            replace(d, "rgb.txt", &text.replacen("1.000000", "zero", 1));
        },
        args: &["--set", "pipeline.depth=sensor"],
        succeeds: false,
        names: &["rgb.txt:2", "zero"],
        kept: &[],
    },
    Case {
        name: "an unknown key beside an unknown plugin",
        damage: |_| {},
        args: &["--set", "pipeline.depthh=sensor", "--set", "pipeline.tracker=nosuch"],
        succeeds: false,
        names: &["depthh", "nosuch"],
        kept: &[],
    },
    Case {
        name: "a light.toml whose vignetting is negative in the image",
        damage: |d| replace(d, "light.toml", "gain = -1.0\nvignetting = [-1.5, 0.3]\n"),
        args: &[],
        succeeds: false,
        names: &["light.toml", "gain", "vignetting"],
        kept: &[],
    },
];

#[test]
fn every_bad_input_is_an_error_or_a_warning_that_names_it_and_costs_no_data() {
    let root = tempfile::tempdir().unwrap();
    let valid = root.path().join("valid");
    capsule_slam_tests::fixtures::write_dataset(&valid, 6);
    let mut failures = Vec::new();
    for (k, case) in CASES.iter().enumerate() {
        let input = root.path().join(format!("case{k}"));
        capsule_slam_tests::fixtures::copy_dir(&valid, &input);
        (case.damage)(&input);
        let out = root.path().join(format!("out{k}"));
        let o = Command::new(env!("CARGO_BIN_EXE_capsule-slam"))
            .args(["run", "--input", input.to_str().unwrap(), "--out", out.to_str().unwrap(), "-q"])
            .args(case.args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        let mut wrong = Vec::new();
        if o.status.success() != case.succeeds {
            wrong.push(format!("exit {:?}", o.status.code()));
        }
        if err.contains("panicked") {
            wrong.push("a panic".to_owned());
        }
        wrong.extend(case.names.iter().filter(|n| !err.contains(*n)).map(|n| format!("`{n}` not named")));
        if case.kept.is_empty() && out.join("summary.json").exists() {
            wrong.push("a summary for a run that never started".to_owned());
        }
        for f in case.kept {
            if !out.join(f).is_file() {
                wrong.push(format!("{f} not kept"));
            }
        }
        if out.join("summary.json").is_file() {
            let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
            let status = s["status"].as_str().unwrap_or("");
            if case.succeeds != (status == "complete") {
                wrong.push(format!("summary status `{status}`"));
            }
        }
        if !wrong.is_empty() {
            failures.push(format!("{}: {} — stderr: {err}", case.name, wrong.join(", ")));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}
