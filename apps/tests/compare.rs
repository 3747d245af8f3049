//! `capsule-slam compare` (issue 20): plan errors before any run, a grid equal to its runs,
//! resume, emitted jobs run elsewhere and collected.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

fn bin(cache: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_capsule-slam"));
    c.env("CAPSULE_SLAM_CACHE", cache);
    c
}

fn output(cache: &Path, args: &[&str]) -> (bool, String, String) {
    let o = bin(cache).args(args).output().expect("run capsule-slam");
    (o.status.success(), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

/// A 2 × 2 plan on two tiny phantoms: the frame-to-model and frame-to-frame `icp-rgb` on
/// sensor depth; `w_rgb` of the first variant as given.
fn plan(dir: &Path, w_rgb: f64) -> std::path::PathBuf {
    let text = format!(
        r#"
[[variant]]
name = "f2m"
set = ["pipeline.depth=sensor", "pipeline.tracker=icp-rgb", "plugins.icp-rgb.w_rgb={w_rgb}"]

[[variant]]
name = "f2f"
set = ["pipeline.depth=sensor", "pipeline.tracker=icp-rgb", "plugins.icp-rgb.mode=frame-to-frame"]

[[input]]
synth = {{ preset = 1, frames = 60, size = "naneye" }}
frames = 8
name = "slow"

[[input]]
synth = {{ preset = 2, frames = 60, size = "naneye" }}
frames = 8
"#
    );
    let p = dir.join("plan.toml");
    std::fs::write(&p, text).expect("write the plan");
    p
}

/// `results.csv` as rows of column → value, keyed by (input, variant).
fn table(path: &Path) -> BTreeMap<(String, String), BTreeMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("results.csv");
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().expect("a header").split(',').collect();
    lines
        .map(|l| {
            let cols: BTreeMap<String, String> = head.iter().zip(l.split(',')).map(|(k, v)| (k.to_string(), v.to_string())).collect();
            ((cols["input"].clone(), cols["variant"].clone()), cols)
        })
        .collect()
}

/// The figures a run computes deterministically (not its timings).
const EXACT: [&str; 6] = ["status", "frames", "frames_lost", "ate_rmse_m", "surface_rmse_m", "surfels"];

#[test]
fn plan_errors_are_reported_at_once_before_any_run() {
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("cache");
    // An unknown key of a variant: the parse names it and its line.
    std::fs::write(tmp.path().join("a.toml"), "[[variant]]\nname = \"x\"\nsett = []\n[[input]]\npath = \".\"\n").unwrap();
    let (ok, _, err) = output(&cache, &["compare", tmp.path().join("a.toml").to_str().unwrap(), "--out", tmp.path().join("o").to_str().unwrap()]);
    assert!(!ok && err.contains("sett") && err.contains("line 3"), "{err}");
    // A missing input and a sweep of an unknown parameter, both reported, nothing run.
    capsule_slam_tests::fixtures::write_dataset(&tmp.path().join("seq"), 3);
    std::fs::write(
        tmp.path().join("b.toml"),
        "[[variant]]\nname = \"x\"\nset = [\"pipeline.depth=sensor\", \"pipeline.tracker=icp-rgb\"]\n\
         [[input]]\npath = \"seq\"\n[[input]]\npath = \"nowhere\"\n\
         [[sweep]]\nkey = \"plugins.icp-rgb.no_such_knob\"\nvalues = [1, 2]\n",
    )
    .unwrap();
    let out = tmp.path().join("o");
    let (ok, _, err) = output(&cache, &["compare", tmp.path().join("b.toml").to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(!ok, "{err}");
    assert!(err.contains("nowhere") && err.contains("no_such_knob") && err.contains("nothing was run"), "{err}");
    assert!(!out.exists(), "nothing may be written before the plan is right");
}

#[test]
fn a_grid_equals_its_runs_resumes_and_collects_jobs_run_elsewhere() {
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("cache");
    let p = plan(tmp.path(), 0.1);
    let out = tmp.path().join("out");
    let (ok, stdout, err) = output(&cache, &["compare", p.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(ok, "{stdout}\n{err}");
    assert!(stdout.contains("cells             4 (4 run, 0 reused, 0 failed)"), "{stdout}");
    let grid = table(&out.join("results.csv"));
    assert_eq!(grid.len(), 4);
    assert!(out.join("results.md").is_file() && out.join("plots/ate_rmse_m.png").is_file() && out.join("plots/trajectories_slow.png").is_file());

    // Each cell is the run it stands for: the same figures from a bare `run`.
    let slow = cache.join("phantom-p1-60f-seed1-naneye");
    let bare = tmp.path().join("bare");
    let (ok, _, err) = output(
        &cache,
        &[
            "run",
            "--input",
            slow.to_str().unwrap(),
            "--out",
            bare.to_str().unwrap(),
            "-q",
            "--frames",
            "8",
            "--set",
            "pipeline.depth=sensor",
            "--set",
            "pipeline.tracker=icp-rgb",
            "--set",
            "plugins.icp-rgb.mode=frame-to-frame",
        ],
    );
    assert!(ok, "{err}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(bare.join("summary.json")).unwrap()).unwrap();
    let cell = &grid[&("slow".to_string(), "f2f".to_string())];
    for col in ["ate_rmse_m", "surface_rmse_m", "surfels", "frames"] {
        assert_eq!(cell[col].parse::<f64>().ok(), summary[col].as_f64(), "{col}");
    }
    assert_eq!(cell["status"], "complete");
    assert_eq!(cell["frames_lost"], "0", "a tiny phantom that tracks");

    // Resume: nothing runs again; an interrupted cell (no summary) and a changed config do.
    let (ok, stdout, _) = output(&cache, &["compare", p.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-plots"]);
    assert!(ok && stdout.contains("(0 run, 4 reused, 0 failed)"), "{stdout}");
    std::fs::remove_file(out.join("slow/f2f/summary.json")).unwrap();
    let p = plan(tmp.path(), 0.2);
    let (ok, stdout, _) = output(&cache, &["compare", p.to_str().unwrap(), "--out", out.to_str().unwrap(), "--no-plots"]);
    assert!(ok && stdout.contains("(3 run, 1 reused, 0 failed)"), "{stdout}");
    let grid = table(&out.join("results.csv"));

    // Emitted jobs, run by xargs from another folder, collect to the same table.
    let jobs = tmp.path().join("jobs.txt");
    let elsewhere = tmp.path().join("elsewhere");
    let (ok, stdout, err) = output(&cache, &["compare", p.to_str().unwrap(), "--out", elsewhere.to_str().unwrap(), "--emit-jobs", jobs.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(stdout.contains("4 commands"), "{stdout}");
    let cwd = tempfile::tempdir().unwrap();
    let status = Command::new("sh")
        .arg("-c")
        .arg(format!("xargs -d '\\n' -n 1 -P 2 sh -c < {}", jobs.display()))
        .current_dir(cwd.path())
        .env("CAPSULE_SLAM_CACHE", &cache)
        .status()
        .unwrap();
    assert!(status.success());
    let (ok, stdout, err) = output(&cache, &["compare", p.to_str().unwrap(), "--out", elsewhere.to_str().unwrap(), "--collect"]);
    assert!(ok, "{stdout}\n{err}");
    let collected = table(&elsewhere.join("results.csv"));
    assert_eq!(collected.keys().collect::<Vec<_>>(), grid.keys().collect::<Vec<_>>());
    for (k, row) in &grid {
        for col in EXACT {
            assert_eq!(row[col], collected[k][col], "{k:?} {col}");
        }
    }
}

/// The plans shipped in `docs/results/compare/`.
fn shipped_plans() -> Vec<std::path::PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/results/compare");
    let mut plans: Vec<_> = std::fs::read_dir(&dir)
        .expect("docs/results/compare")
        .map(|e| e.expect("an entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    plans.sort();
    plans
}

#[test]
fn every_shipped_plan_parses_and_its_variants_resolve() {
    let plans = shipped_plans();
    assert!(plans.len() >= 2, "{plans:?}");
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("cache");
    capsule_slam_tests::fixtures::write_dataset(&tmp.path().join("seq"), 3);
    for (k, plan) in plans.iter().enumerate() {
        // The plan as shipped: it parses and checks clean; `--collect` makes no phantom, runs
        // nothing, and its one complaint is that no cell has run here.
        let out = tmp.path().join(format!("collect{k}"));
        let (_, _, err) = output(&cache, &["compare", plan.to_str().unwrap(), "--out", out.to_str().unwrap(), "--collect", "--no-plots"]);
        assert!(err.contains("cells are not complete") && !err.contains("problem(s)"), "{}: {err}", plan.display());
        // Its variants on a tiny sequence: every config key and plugin they name exists (each
        // cell's config is resolved before a job is emitted).
        let text = std::fs::read_to_string(plan).unwrap();
        let parsed: toml::Table = text.parse().unwrap();
        let variants = parsed["variant"].as_array().expect("[[variant]]").clone();
        let mut tiny = toml::Table::new();
        tiny.insert("variant".into(), toml::Value::Array(variants.clone()));
        let mut input = toml::Table::new();
        input.insert("path".into(), toml::Value::String("seq".into()));
        tiny.insert("input".into(), toml::Value::Array(vec![toml::Value::Table(input)]));
        let p = tmp.path().join(format!("tiny{k}.toml"));
        std::fs::write(&p, toml::to_string(&tiny).unwrap()).unwrap();
        let jobs = tmp.path().join(format!("jobs{k}.txt"));
        let out = tmp.path().join(format!("tiny{k}"));
        let (ok, _, err) = output(&cache, &["compare", p.to_str().unwrap(), "--out", out.to_str().unwrap(), "--emit-jobs", jobs.to_str().unwrap()]);
        assert!(ok, "{}: {err}", plan.display());
        let emitted = std::fs::read_to_string(&jobs).unwrap();
        assert_eq!(emitted.lines().filter(|l| l.contains(" run ")).count(), variants.len(), "{}: {emitted}", plan.display());
    }
}
