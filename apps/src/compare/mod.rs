//! `capsule-slam compare PLAN.toml --out DIR` (issue 20): variants × inputs (× sweeps), each cell
//! one ordinary `run` into `DIR/<input>/<variant>/`, then `results.csv`, `results.md` and
//! `plots/`. A cell already finished by this build with the same resolved config is reused, so
//! an interrupted comparison resumes; `--emit-jobs` writes the cells as shell commands for
//! `parallel`, `xargs -P` or a Slurm array, and `--collect` builds the tables from cells run
//! anywhere.

pub mod cells;
pub mod plan;
pub mod plots;
pub mod results;

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};

use cells::{Cell, shell_word};
use plan::Plan;

/// Arguments of `compare`.
#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    /// The plan: [[variant]] name / config / set, [[input]] path or synth / name / frames,
    /// optional [[sweep]] key / values (see docs/usage.md).
    plan: PathBuf,
    /// Output folder: `<input>/<variant>/` per cell, `results.csv`, `results.md`, `plots/`.
    #[arg(long)]
    out: PathBuf,
    /// Write one self-contained `run` command per cell to this file (phantom inputs are made
    /// first) and run nothing; then `--collect`.
    #[arg(long, value_name = "FILE", conflicts_with = "collect")]
    emit_jobs: Option<PathBuf>,
    /// Build the tables and plots from the cells' outputs, running nothing.
    #[arg(long)]
    collect: bool,
    /// No plots.
    #[arg(long)]
    no_plots: bool,
}

/// The folder of every input, making the valid phantoms into the cache unless `make` is false.
fn input_dirs(plan: &Plan, base: &Path, make: bool) -> anyhow::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for (k, (i, name)) in plan.input.iter().zip(plan.input_names()).enumerate() {
        let dir = match (&i.path, &i.synth) {
            (Some(p), _) => base.join(p),
            (None, Some(s)) => {
                let spec = s.phantom();
                let dir = cells::absolute(&crate::cmd_run::cache_dir().join(s.name()))?;
                if make && plan.input_ok(k, base) && !capsule_slam_phantom::writer::is_complete(&dir, &spec) {
                    eprintln!("input {name}: making the phantom into {}", dir.display());
                    crate::cmd_synth::synthesize(spec, &dir, true)?;
                }
                dir
            }
            (None, None) => base.join(format!("(input {k} has no path)")),
        };
        out.push(dir);
    }
    Ok(out)
}

/// How a cell ended here.
enum Outcome {
    Reused,
    Ran,
    Failed(String),
}

pub fn run(args: &CompareArgs, gpu: &capsule_slam_gpu::GpuHandle) -> anyhow::Result<()> {
    let plan = Plan::load(&args.plan)?;
    let base = args.plan.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf();
    let mut problems = plan.problems(&base);
    let dirs = input_dirs(&plan, &base, !args.collect && problems.is_empty())?;
    let cells = cells::cells(&plan, &base, &dirs, &args.out)?;
    let registry = crate::registry()?;
    if !args.collect {
        // Every cell's config, on the inputs that can be read: all problems before any run.
        let names = plan.input_names();
        let readable: Vec<Cell> =
            cells.iter().filter(|c| names.iter().position(|n| *n == c.input).is_some_and(|k| plan.input_ok(k, &base) && dirs[k].is_dir())).cloned().collect();
        problems.extend(cells::problems(&readable, &registry));
    }
    if !problems.is_empty() {
        bail!("{}: {} problem(s), nothing was run:\n  {}", args.plan.display(), problems.len(), problems.join("\n  "));
    }
    if let Some(jobs) = &args.emit_jobs {
        return emit_jobs(jobs, &cells);
    }
    let mut outcomes = Vec::new();
    if !args.collect {
        for (k, c) in cells.iter().enumerate() {
            let tag = format!("[{}/{}] {} / {}", k + 1, cells.len(), c.input, c.variant);
            if c.is_done(&registry)? {
                eprintln!("{tag}: finished by this build with the same config: reused");
                outcomes.push(Outcome::Reused);
                continue;
            }
            eprintln!("{tag}: running");
            outcomes.push(match crate::cmd_run::run(&c.run_args()?, gpu) {
                Ok(()) => Outcome::Ran,
                Err(e) => {
                    eprintln!("{tag}: failed: {e:#}");
                    Outcome::Failed(format!("{e:#}"))
                }
            });
        }
    }
    let mut rows: Vec<results::Row> = cells.iter().map(results::row).collect();
    for (r, o) in rows.iter_mut().zip(&outcomes) {
        // A run that failed before writing its summary (e.g. its input could not be read).
        if let (Outcome::Failed(why), Some(status)) = (o, r.words.get_mut("status"))
            && status.starts_with("missing")
        {
            *status = format!("failed: {why}");
        }
    }
    write_results(args, &plan, &cells, &dirs, &rows)?;
    let incomplete: Vec<String> = rows
        .iter()
        .filter(|r| r.words.get("status").is_none_or(|s| s != "complete"))
        .map(|r| format!("{} / {}: {}", r.input, r.variant, r.words.get("status").map_or("?", String::as_str)))
        .collect();
    let count = |f: fn(&Outcome) -> bool| outcomes.iter().filter(|o| f(o)).count();
    if !args.collect {
        println!(
            "cells             {} ({} run, {} reused, {} failed)",
            cells.len(),
            count(|o| matches!(o, Outcome::Ran)),
            count(|o| matches!(o, Outcome::Reused)),
            count(|o| matches!(o, Outcome::Failed(_)))
        );
    }
    println!("results           {} and results.md", args.out.join("results.csv").display());
    if !incomplete.is_empty() {
        bail!("{} of {} cells are not complete:\n  {}", incomplete.len(), cells.len(), incomplete.join("\n  "));
    }
    Ok(())
}

/// Writes `results.csv`, `results.md` and (unless `--no-plots`) `plots/`.
fn write_results(args: &CompareArgs, plan: &Plan, cells: &[Cell], dirs: &[PathBuf], rows: &[results::Row]) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let inputs = plan.input_names();
    let mut variants: Vec<String> = Vec::new();
    for c in cells {
        if !variants.contains(&c.variant) {
            variants.push(c.variant.clone());
        }
    }
    let write = |name: &str, text: String| {
        let p = args.out.join(name);
        std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))
    };
    write("results.csv", results::csv(rows))?;
    write("results.md", results::markdown(rows, &inputs, &variants, &format!("compare {}", args.plan.display())))?;
    if !args.no_plots {
        let dir = args.out.join("plots");
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let named: Vec<(String, PathBuf)> = inputs.iter().cloned().zip(dirs.iter().cloned()).collect();
        let tolerance = capsule_slam_framework::config::InputConfig::default().association_tolerance_s;
        let n = plots::bars(&dir, rows, &inputs, &variants)?
            + plots::trajectories(&dir, cells, &named, tolerance)?
            + plots::sweeps(&dir, cells, rows, &plan.sweep.iter().map(|s| s.key.clone()).collect::<Vec<_>>())?;
        println!("plots             {} in {}", n, dir.display());
    }
    Ok(())
}

/// Writes one shell command per cell: the binary's absolute path, the `--plugin-lib`s, `run`
/// and the cell's arguments.
fn emit_jobs(path: &Path, cells: &[Cell]) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("finding this binary's path for the job lines")?;
    let mut prefix = vec![shell_word(&exe.display().to_string())];
    for lib in crate::PLUGIN_LIBS.get().into_iter().flatten() {
        prefix.push("--plugin-lib".into());
        prefix.push(shell_word(&cells::absolute(lib)?.display().to_string()));
    }
    prefix.push("run".into());
    let lines: Vec<String> = cells.iter().map(|c| prefix.iter().cloned().chain(c.args.iter().map(|a| shell_word(a))).collect::<Vec<_>>().join(" ")).collect();
    std::fs::write(path, lines.join("\n") + "\n").with_context(|| format!("writing {}", path.display()))?;
    println!("jobs              {} commands in {}", lines.len(), path.display());
    println!("run them with     parallel -j N < {0}   or   xargs -d '\\n' -n 1 -P N sh -c < {0}", path.display());
    println!("then              capsule-slam compare PLAN --collect --out DIR");
    Ok(())
}
