//! Whole-config validation against the registry, before the first frame. Every problem is
//! collected; each names its key and its fix.

use std::collections::BTreeMap;

use super::Config;
use crate::camera::ViewKind;
use crate::error::{ConfigError, ConfigProblem};
use crate::registry::{Registry, StageKind};

/// Checks the config against the registry and the rig kind of the input. On success returns
/// the resolved parameter table of every selected plugin (defaults filled in), which is what
/// the run's `config.toml` records.
pub fn validate(config: &Config, registry: &Registry, rig: ViewKind, source_name: &str) -> Result<BTreeMap<String, toml::Table>, ConfigError> {
    let mut problems = Vec::new();
    let mut resolved = BTreeMap::new();
    let empty = toml::Table::new();

    for (kind, name) in config.pipeline.selected() {
        let key = kind.config_key();
        if let Some(p) = name_problem(registry, kind, name) {
            problems.push(p);
            continue;
        }
        let Some(e) = registry.get(name) else { continue };
        let table = config.plugins.get(name).unwrap_or(&empty);
        let found = e.check(table);
        if found.is_empty() {
            resolved.insert(name.to_owned(), with_defaults(&e.param_docs(), table));
        }
        problems.extend(found);
        if kind == StageKind::DepthEstimator && e.views == ViewKind::Stereo && rig == ViewKind::Mono {
            problems.push(ConfigProblem::new(
                key,
                format!("`{name}` needs a stereo rig, but the input is mono"),
                "choose a mono depth estimator, or give the input a stereo rig (a [right] table or baseline_m in camera.toml, and rgb_right.txt)",
            ));
        }
    }

    let selected: Vec<&str> = config.pipeline.selected().into_iter().map(|(_, n)| n).collect();
    for name in config.plugins.keys() {
        if !selected.contains(&name.as_str()) {
            let msg = if registry.get(name).is_some() {
                format!("`{name}` is not selected by any stage in [pipeline]")
            } else {
                format!("no plugin is named `{name}`")
            };
            problems.push(ConfigProblem::new(
                format!("plugins.{name}"),
                msg,
                format!("remove [plugins.{name}] or select `{name}` in [pipeline] (selected: {})", selected.join(", ")),
            ));
        }
    }

    let input = &config.input;
    if !(input.association_tolerance_s.is_finite() && input.association_tolerance_s > 0.0) {
        problems.push(ConfigProblem::new(
            "input.association_tolerance_s",
            format!("{} is not a positive number of seconds", input.association_tolerance_s),
            "use e.g. 0.02 (TUM's associate.py)",
        ));
    }
    if !(input.frame_rate_hz.is_finite() && input.frame_rate_hz > 0.0) {
        problems.push(ConfigProblem::new(
            "input.frame_rate_hz",
            format!("{} is not a positive frame rate", input.frame_rate_hz),
            "use the camera's frame rate in Hz, e.g. 30",
        ));
    }
    if input.max_frames == Some(0) {
        problems.push(ConfigProblem::new("input.max_frames", "0 frames would do nothing", "remove the key to process every frame, or give a positive count"));
    }
    if let Some(cam) = &config.camera {
        problems.extend(cam.problems("camera."));
    }

    if problems.is_empty() { Ok(resolved) } else { Err(ConfigError { source_name: source_name.to_owned(), problems }) }
}

fn choose(registry: &Registry, kind: StageKind) -> String {
    let names = registry.names(kind);
    if names.is_empty() { format!("no {} plugin is registered in this build", kind.as_str()) } else { format!("use one of: {}", names.join(", ")) }
}

/// The problems of the plugin names `[pipeline]` selects (unknown, or of another stage) alone:
/// what [`Config::load_checked`] adds for a config whose other problems stop it short of
/// [`validate`].
pub fn plugin_name_problems(config: &Config, registry: &Registry) -> Vec<ConfigProblem> {
    config.pipeline.selected().into_iter().filter_map(|(kind, name)| name_problem(registry, kind, name)).collect()
}

/// Why `name` cannot be the plugin of stage `kind`, if it cannot.
fn name_problem(registry: &Registry, kind: StageKind, name: &str) -> Option<ConfigProblem> {
    match registry.get(name) {
        None => Some(unknown_plugin(registry, kind, name)),
        Some(e) if e.kind != kind => {
            Some(ConfigProblem::new(kind.config_key(), format!("`{name}` is a {}, not a {}", e.kind.as_str(), kind.as_str()), choose(registry, kind)))
        }
        Some(_) => None,
    }
}

fn unknown_plugin(registry: &Registry, kind: StageKind, name: &str) -> ConfigProblem {
    let hint = if kind == StageKind::LoopCloser { " (or \"none\")" } else { "" };
    ConfigProblem::new(kind.config_key(), format!("unknown {} `{name}`", kind.as_str()), format!("{}{hint}", choose(registry, kind)))
}

/// The plugin's defaults overlaid with the given table.
fn with_defaults(docs: &[crate::params::ParamDoc], table: &toml::Table) -> toml::Table {
    let mut out = toml::Table::new();
    for d in docs {
        if let Some(v) = &d.default {
            out.insert(d.name.to_owned(), v.clone());
        }
    }
    for (k, v) in table {
        out.insert(k.clone(), v.clone());
    }
    out
}
