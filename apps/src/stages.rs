//! Building single stages outside a pipeline, for the commands that run a part of it
//! (`depth-eval`, `preprocess`, `preprocess-eval`).

use anyhow::{anyhow, bail};
use capsule_slam_framework::Preprocessor;
use capsule_slam_framework::registry::{BuildEnv, Registry, Stage};

/// Builds plugin `name` from its resolved parameter table (`validate`'s output).
pub fn build(registry: &Registry, resolved: &std::collections::BTreeMap<String, toml::Table>, env: &BuildEnv, name: &str) -> anyhow::Result<Stage> {
    let entry = registry.get(name).ok_or_else(|| anyhow!("unknown plugin {name}"))?;
    entry.build(&resolved.get(name).cloned().unwrap_or_default(), env).map_err(|e| anyhow!("building {name}: {e}"))
}

/// Builds the preprocessors named in order, each with its name.
pub fn preprocessors(
    registry: &Registry,
    resolved: &std::collections::BTreeMap<String, toml::Table>,
    env: &BuildEnv,
    names: &[String],
) -> anyhow::Result<Vec<(String, Box<dyn Preprocessor>)>> {
    let mut out = Vec::new();
    for name in names {
        match build(registry, resolved, env, name)? {
            Stage::Preprocessor(p) => out.push((name.clone(), p)),
            _ => bail!("{name} is not a preprocessor"),
        }
    }
    Ok(out)
}

/// What `depth` and `depth-eval` run over a folder: its config, its dataset, the preprocessors and
/// the depth estimator, built as `run` builds them.
pub struct FrontEnd {
    /// The loaded config.
    pub config: capsule_slam_framework::config::Config,
    /// The opened input.
    pub dataset: capsule_slam_io::Dataset,
    /// The configured preprocessors with their names.
    pub preprocessors: Vec<(String, Box<dyn Preprocessor>)>,
    /// The configured depth estimator.
    pub depth: Box<dyn capsule_slam_framework::DepthEstimator>,
}

/// Loads the config (with `set` overrides), opens `input` and builds its front end.
pub fn front_end(config: Option<&std::path::Path>, set: &[String], input: &std::path::Path, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<FrontEnd> {
    use anyhow::Context as _;
    let registry = crate::registry()?;
    let config = crate::load_config(config, set, &registry)?;
    let dataset = capsule_slam_io::Dataset::open(input, &config.input, config.camera.as_ref()).with_context(|| format!("opening {}", input.display()))?;
    for w in dataset.warnings() {
        eprintln!("warning: {w}");
    }
    let resolved = capsule_slam_framework::config::validate::validate(&config, &registry, dataset.rig().kind(), "the config")?;
    let env = BuildEnv::new(dataset.rig(), Some(input.to_path_buf())).with_depth_noise(dataset.camera_file().depth_noise).with_gpu(gpu.clone());
    let preprocessors = preprocessors(&registry, &resolved, &env, &config.pipeline.preprocess)?;
    let Stage::DepthEstimator(depth) = build(&registry, &resolved, &env, &config.pipeline.depth)? else {
        anyhow::bail!("{} is not a depth estimator", config.pipeline.depth)
    };
    Ok(FrontEnd { config, dataset, preprocessors, depth })
}
