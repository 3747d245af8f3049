//! The cells of a comparison: one ordinary `run` each, `DIR/<input>/<variant>/`, with the
//! arguments the emitted job line carries too (so a cell run here and one run elsewhere are the
//! same run).

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use capsule_slam_framework::Registry;
use clap::Parser;

use super::plan::{Plan, safe_name, value_text};
use crate::cmd_run::{BUILD, RunArgs};

/// One cell of the grid.
#[derive(Debug, Clone)]
pub struct Cell {
    /// The input's name.
    pub input: String,
    /// The variant's name, `<variant>+<key>=<value>...` for a swept one.
    pub variant: String,
    /// The variant before the sweep.
    pub base_variant: String,
    /// The swept keys and their values as names show them.
    pub swept: Vec<(String, String)>,
    /// `run`'s arguments (after `run`).
    pub args: Vec<String>,
    /// The cell's output folder.
    pub out: PathBuf,
}

/// `run`'s arguments parsed as the command line parses them.
#[derive(Parser, Debug)]
#[command(name = "run")]
struct RunLine {
    #[command(flatten)]
    run: RunArgs,
}

impl Cell {
    /// The parsed `run` arguments.
    pub fn run_args(&self) -> anyhow::Result<RunArgs> {
        RunLine::try_parse_from(std::iter::once("run".to_owned()).chain(self.args.iter().cloned()))
            .map(|l| l.run)
            .with_context(|| format!("cell {}/{}: the run arguments {:?}", self.input, self.variant, self.args))
    }

    /// The `summary.json` of this cell, if there is one that parses.
    pub fn summary(&self) -> Option<serde_json::Value> {
        std::fs::read_to_string(self.out.join("summary.json")).ok().and_then(|t| serde_json::from_str(&t).ok())
    }

    /// Whether a finished run of this cell is there: `complete`, by this build, with the
    /// resolved config this cell would run now (`config.toml`, byte for byte).
    pub fn is_done(&self, registry: &Registry) -> anyhow::Result<bool> {
        let Some(s) = self.summary() else { return Ok(false) };
        let same_build = s["build"]["version"] == BUILD.version && s["build"]["commit"] == BUILD.commit;
        if s["status"] != "complete" || !same_build {
            return Ok(false);
        }
        let written = std::fs::read_to_string(self.out.join("config.toml")).unwrap_or_default();
        Ok(written == crate::cmd_run::resolved_config_text(&self.run_args()?, registry)?)
    }
}

/// The absolute form of `p` (relative to the current folder).
pub fn absolute(p: &Path) -> anyhow::Result<PathBuf> {
    std::path::absolute(p).with_context(|| format!("resolving {}", p.display()))
}

/// Every cell of `plan` (its folder `base`), inputs as `inputs` (their folders, in the plan's
/// order), outputs under `out`.
pub fn cells(plan: &Plan, base: &Path, inputs: &[PathBuf], out: &Path) -> anyhow::Result<Vec<Cell>> {
    // The cartesian product of the sweeps: one list of (key, set text, name text) per combination.
    let mut combos: Vec<Vec<(String, String, String)>> = vec![Vec::new()];
    for s in &plan.sweep {
        combos = combos
            .iter()
            .flat_map(|c| {
                s.values.iter().map(move |v| {
                    let (set, shown) = value_text(v);
                    let mut c = c.clone();
                    c.push((s.key.clone(), set, shown));
                    c
                })
            })
            .collect();
    }
    let mut out_cells = Vec::new();
    for ((spec, name), dir) in plan.input.iter().zip(plan.input_names()).zip(inputs) {
        for v in &plan.variant {
            for combo in &combos {
                let variant =
                    std::iter::once(v.name.clone()).chain(combo.iter().map(|(k, _, shown)| safe_name(&format!("{k}={shown}")))).collect::<Vec<_>>().join("+");
                let cell_out = absolute(&out.join(&name).join(&variant))?;
                let mut args =
                    vec!["--input".to_owned(), absolute(dir)?.display().to_string(), "--out".to_owned(), cell_out.display().to_string(), "-q".to_owned()];
                if let Some(c) = &v.config {
                    args.extend(["--config".to_owned(), absolute(&base.join(c))?.display().to_string()]);
                }
                if let Some(n) = spec.frames {
                    args.extend(["--frames".to_owned(), n.to_string()]);
                }
                for s in v.set.iter().cloned().chain(combo.iter().map(|(k, set, _)| format!("{k}={set}"))) {
                    args.extend(["--set".to_owned(), s]);
                }
                out_cells.push(Cell {
                    input: name.clone(),
                    variant,
                    base_variant: v.name.clone(),
                    swept: combo.iter().map(|(k, _, shown)| (k.clone(), shown.clone())).collect(),
                    args,
                    out: cell_out,
                });
            }
        }
    }
    Ok(out_cells)
}

/// Every cell's problems against the registry and its input (unknown plugins, keys, swept
/// parameters, an input that cannot be opened).
pub fn problems(cells: &[Cell], registry: &Registry) -> Vec<String> {
    cells
        .iter()
        .filter_map(|c| {
            c.run_args().and_then(|a| crate::cmd_run::resolved_config_text(&a, registry)).err().map(|e| format!("{}/{}: {e:#}", c.input, c.variant))
        })
        .collect()
}

/// A word as a POSIX shell reads it back (single-quoted where it needs to be).
pub fn shell_word(s: &str) -> String {
    if !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || "/._-+=:,".contains(c)) {
        s.to_owned()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}
