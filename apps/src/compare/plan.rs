//! `compare`'s plan file (issue 20): variants × inputs (× the cartesian product of the sweeps),
//! read and checked as a whole before anything runs.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use serde::Deserialize;

/// The plan as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plan {
    /// One or more pipelines.
    #[serde(default)]
    pub variant: Vec<Variant>,
    /// One or more sequences.
    #[serde(default)]
    pub input: Vec<InputSpec>,
    /// Parameters swept over every variant.
    #[serde(default)]
    pub sweep: Vec<Sweep>,
}

/// One pipeline: a config (default: the built-in one) with `--set` overrides.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variant {
    /// Short name, used in paths and tables.
    pub name: String,
    /// Config file, relative to the plan.
    pub config: Option<PathBuf>,
    /// Overrides, as `run --set`.
    #[serde(default)]
    pub set: Vec<String>,
}

/// One sequence: a folder, or a phantom made once into the cache.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputSpec {
    /// Sequence folder, relative to the plan.
    pub path: Option<PathBuf>,
    /// A phantom instead.
    pub synth: Option<SynthSpec>,
    /// Name in paths and tables (default: the folder's name, or `phantom-p<preset>...`).
    pub name: Option<String>,
    /// At most this many frames (as `run --frames`).
    pub frames: Option<usize>,
}

/// A phantom input (`capsule-slam synth`'s options).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SynthSpec {
    /// Trajectory preset, 1–7.
    pub preset: u8,
    /// Frames of the walk (default 300).
    pub frames: Option<usize>,
    /// Peristaltic wave amplitude, mm (default 0: rigid).
    pub deform: Option<f64>,
    /// The frame at which the wave starts (default 0: from the start).
    pub deform_onset: Option<usize>,
    /// Seed of texture and noise (default 1).
    pub seed: Option<u64>,
    /// Walks along the path (default 1).
    pub repeat: Option<usize>,
    /// A stereo rig of this baseline, mm.
    pub stereo: Option<f64>,
    /// Image size: naneye, 320 (default), voyager, potensic or pal.
    pub size: Option<String>,
    /// With a wave, the true surface every this many frames too (the live surface error).
    pub surface_every: Option<usize>,
}

/// One swept parameter.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sweep {
    /// A config key, as in `--set` (e.g. `plugins.icp-rgb.w_rgb`).
    pub key: String,
    /// Its values.
    pub values: Vec<toml::Value>,
}

/// A name made safe for a path: anything but letters, digits and `. _ - + =` becomes `_`.
pub fn safe_name(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || ".-_+=".contains(c) { c } else { '_' }).collect()
}

/// A swept value as `--set` takes it, and as a cell's name shows it (strings unquoted).
pub fn value_text(v: &toml::Value) -> (String, String) {
    match v {
        toml::Value::String(s) => (format!("{s:?}"), s.clone()),
        other => (other.to_string(), other.to_string()),
    }
}

impl SynthSpec {
    /// The phantom this describes.
    pub fn phantom(&self) -> capsule_slam_phantom::PhantomSpec {
        let mut spec = capsule_slam_phantom::PhantomSpec::preset(self.preset);
        spec.frames = self.frames.unwrap_or(spec.frames);
        spec.deform_mm = self.deform.unwrap_or(spec.deform_mm);
        spec.deform_onset_frame = self.deform_onset.unwrap_or(spec.deform_onset_frame);
        spec.seed = self.seed.unwrap_or(spec.seed);
        spec.repeat = self.repeat.unwrap_or(spec.repeat);
        spec.stereo_baseline_mm = self.stereo.or(spec.stereo_baseline_mm);
        spec.surface_every = self.surface_every.unwrap_or(spec.surface_every);
        if let Some(size) = self.size.as_deref().and_then(capsule_slam_phantom::SizePreset::parse) {
            spec.size = size;
        }
        spec
    }

    /// Its default name and cache folder name.
    pub fn name(&self) -> String {
        let s = self.phantom();
        let mut name = format!("phantom-p{}-{}f-seed{}", s.preset, s.frames, s.seed);
        if s.deform_mm != 0.0 {
            name += &format!("-deform{}", s.deform_mm);
        }
        if s.deform_onset_frame > 0 {
            name += &format!("-from{}", s.deform_onset_frame);
        }
        if s.repeat > 1 {
            name += &format!("-x{}", s.repeat);
        }
        if let Some(b) = s.stereo_baseline_mm {
            name += &format!("-stereo{b}");
        }
        if let Some(size) = &self.size {
            name += &format!("-{size}");
        }
        if let Some(n) = self.surface_every.filter(|n| *n > 0) {
            name += &format!("-surface{n}");
        }
        safe_name(&name)
    }
}

impl Plan {
    /// Reads `path` (a file that does not parse is an error naming its line); the plan's own
    /// problems are [`Plan::problems`].
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading the plan {}", path.display()))?;
        toml::from_str(&text).map_err(|e| {
            let line = e.span().map_or(0, |s| text[..s.start.min(text.len())].matches('\n').count() + 1);
            anyhow::anyhow!(
                "{} line {line}: {} (a plan has [[variant]] name/config/set, [[input]] path or synth/name/frames, [[sweep]] key/values)",
                path.display(),
                e.message()
            )
        })
    }

    /// Whether input `k` can be read (its folder exists, or its phantom spec is valid).
    pub fn input_ok(&self, k: usize, base: &Path) -> bool {
        match (&self.input[k].path, &self.input[k].synth) {
            (Some(p), None) => base.join(p).is_dir(),
            (None, Some(s)) => {
                (1..=7).contains(&s.preset)
                    && s.size.as_deref().is_none_or(|z| capsule_slam_phantom::SizePreset::parse(z).is_some())
                    && s.phantom().problems().is_empty()
            }
            _ => false,
        }
    }

    /// The names of the inputs, in order.
    pub fn input_names(&self) -> Vec<String> {
        self.input
            .iter()
            .map(|i| match (&i.name, &i.path, &i.synth) {
                (Some(n), ..) => safe_name(n),
                (None, Some(p), _) => safe_name(&p.file_name().map_or_else(|| p.display().to_string(), |f| f.to_string_lossy().into_owned())),
                (None, None, Some(s)) => s.name(),
                (None, None, None) => String::new(),
            })
            .collect()
    }

    /// Every problem of the plan itself (names, files, phantom specs, empty sweeps).
    pub fn problems(&self, base: &Path) -> Vec<String> {
        let mut out = Vec::new();
        if self.variant.is_empty() {
            out.push("no [[variant]]: add one (name = \"...\", optionally config and set)".to_owned());
        }
        if self.input.is_empty() {
            out.push("no [[input]]: add one (path = \"a sequence folder\" or synth = { preset = 5, frames = 120 })".to_owned());
        }
        let mut names = BTreeSet::new();
        for (k, v) in self.variant.iter().enumerate() {
            if v.name.is_empty() || safe_name(&v.name) != v.name {
                out.push(format!("variant[{k}].name = {:?}: use letters, digits and . _ - + = only", v.name));
            }
            if !names.insert(v.name.clone()) {
                out.push(format!("variant[{k}].name = {:?} is used twice: names must differ", v.name));
            }
            if let Some(c) = &v.config
                && !base.join(c).is_file()
            {
                out.push(format!("variant[{k}].config: {} does not exist (paths are relative to the plan)", base.join(c).display()));
            }
        }
        let mut inputs = BTreeSet::new();
        for (k, (i, name)) in self.input.iter().zip(self.input_names()).enumerate() {
            match (&i.path, &i.synth) {
                (Some(p), None) if !base.join(p).is_dir() => {
                    out.push(format!("input[{k}].path: {} is not a folder (paths are relative to the plan)", base.join(p).display()))
                }
                (Some(_), None) => {}
                (None, Some(s)) => {
                    if let Some(size) = s.size.as_deref().filter(|z| capsule_slam_phantom::SizePreset::parse(z).is_none()) {
                        out.push(format!("input[{k}].synth.size = {size:?}: use naneye, 320, voyager, potensic or pal"));
                    }
                    if !(1..=7).contains(&s.preset) {
                        out.push(format!("input[{k}].synth.preset = {}: presets are 1–7", s.preset));
                    } else {
                        out.extend(s.phantom().problems().into_iter().map(|(f, m)| format!("input[{k}].synth ({f}): {m}")));
                    }
                }
                _ => out.push(format!("input[{k}]: give either path or synth, not {}", if i.path.is_some() { "both" } else { "neither" })),
            }
            if !inputs.insert(name.clone()) {
                out.push(format!("input[{k}]: the name {name:?} is used twice: give each input its own name"));
            }
        }
        for (k, s) in self.sweep.iter().enumerate() {
            if s.values.is_empty() {
                out.push(format!("sweep[{k}] ({}): no values", s.key));
            }
        }
        out
    }
}
