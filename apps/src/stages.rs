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
