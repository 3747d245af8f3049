//! A whole run as the integration tests make one: the default config with `--set`-style
//! overrides, the test registry, a dataset folder, and the figures of its summary.

use std::path::Path;

use capsule_slam_framework::config::Config;
use capsule_slam_framework::pipeline::Pipeline;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_io::Dataset;
use capsule_slam_run::{RunOptions, RunWriter, Summary, run};

use crate::stages::test_registry;

/// Runs the default pipeline with `sets` over the folder `data`, writing into `out`.
pub fn run_with(data: &Path, out: &Path, sets: &[&str], opts: &RunOptions) -> Summary {
    let cfg = Config::load(None, &sets.iter().map(|s| (*s).to_owned()).collect::<Vec<_>>()).unwrap();
    let ds = Dataset::open(data, &cfg.input, None).unwrap();
    let mut p = Pipeline::build(&cfg, "test", &test_registry(), &BuildEnv::new(ds.rig(), Some(data.to_owned()))).unwrap();
    let mut w = RunWriter::create(out, &p.resolved_config().to_toml_string()).unwrap();
    run(&ds, &mut p, &mut w, opts, |_| {}).unwrap()
}

/// A figure of a summary (`ate_rmse_m` included); a missing one fails the test, naming those there are.
pub fn metric(s: &Summary, k: &str) -> f64 {
    if k == "ate_rmse_m" {
        return s.ate_rmse_m.unwrap();
    }
    *s.metrics.get(k).unwrap_or_else(|| panic!("no {k} in {:?}", s.metrics.keys().collect::<Vec<_>>()))
}
