//! The plugin registry. Plugins register an [`PluginEntry`] with `inventory` through
//! [`register!`](crate::register); [`Registry::from_inventory`] collects them into a sorted map
//! and rejects duplicate names; [`Registry::register`] adds entries by hand (tests, and the
//! plugins of shared libraries, which `capsule-slam-abi` wraps as [`ForeignPlugin`]s).
//!
//! Linker note: a plugin crate that the binary never names is not linked, and its
//! registrations vanish. Each plugin crate exports `pub fn link() {}` and every binary and test
//! calls it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::camera::Rig;
use crate::camera::ViewKind;
use crate::error::{ConfigProblem, RegistryError, StageError};
use crate::params::{ParamDoc, PluginParams, parse_params};
use crate::stage::{DepthEstimator, Fuser, LoopCloser, Preprocessor, Tracker};

/// The five stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum StageKind {
    /// [`Preprocessor`].
    Preprocessor,
    /// [`DepthEstimator`].
    DepthEstimator,
    /// [`Tracker`].
    Tracker,
    /// [`Fuser`].
    Fuser,
    /// [`LoopCloser`].
    LoopCloser,
}

impl StageKind {
    /// Human-readable name.
    pub fn as_str(&self) -> &'static str {
        match self {
            StageKind::Preprocessor => "preprocessor",
            StageKind::DepthEstimator => "depth estimator",
            StageKind::Tracker => "tracker",
            StageKind::Fuser => "fuser",
            StageKind::LoopCloser => "loop closer",
        }
    }

    /// The `[pipeline]` key that selects this stage.
    pub fn config_key(&self) -> &'static str {
        match self {
            StageKind::Preprocessor => "pipeline.preprocess",
            StageKind::DepthEstimator => "pipeline.depth",
            StageKind::Tracker => "pipeline.tracker",
            StageKind::Fuser => "pipeline.fuser",
            StageKind::LoopCloser => "pipeline.loop_closer",
        }
    }
}

/// What a plugin may use when it is built.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct BuildEnv {
    /// The cameras of the input.
    pub rig: Rig,
    /// The input folder, for plugins that read calibration files beside the frames.
    pub input_dir: Option<PathBuf>,
    /// The depth noise model `camera.toml` declares, if any (the `sensor` stage's σ).
    pub depth_noise: Option<crate::depth_noise::DepthNoiseModel>,
    /// Whether the pipeline measures or estimates depth, once its depth stage is built
    /// (`Pipeline::build` builds it first): a stage whose calibration is missing may fall back
    /// to what suits the depth it will see (`vignetting`'s `source = "auto"`).
    pub depth_source: Option<crate::frame::DepthSource>,
    /// The application's GPU, for plugins that run on one (opened on their first request).
    #[cfg(feature = "gpu")]
    pub gpu: capsule_slam_gpu::GpuHandle,
}

impl BuildEnv {
    /// An environment for a rig, with a GPU handle of its own (replace it with
    /// [`BuildEnv::with_gpu`] to share the application's).
    pub fn new(rig: Rig, input_dir: Option<PathBuf>) -> Self {
        Self {
            rig,
            input_dir,
            depth_noise: None,
            depth_source: None,
            #[cfg(feature = "gpu")]
            gpu: capsule_slam_gpu::GpuHandle::new(),
        }
    }

    /// A calibration file named in a plugin's parameters: relative to the input folder when
    /// there is one, else as given.
    pub fn input_file(&self, name: &str) -> PathBuf {
        self.input_dir.as_ref().map_or_else(|| PathBuf::from(name), |dir| dir.join(name))
    }

    /// The same environment with the depth noise model of the input's `camera.toml`.
    pub fn with_depth_noise(mut self, model: Option<crate::depth_noise::DepthNoiseModel>) -> Self {
        self.depth_noise = model;
        self
    }

    /// The same environment, for a pipeline whose depth is `source`.
    pub fn with_depth_source(mut self, source: crate::frame::DepthSource) -> Self {
        self.depth_source = Some(source);
        self
    }

    /// The same environment with the application's GPU.
    #[cfg(feature = "gpu")]
    pub fn with_gpu(mut self, gpu: capsule_slam_gpu::GpuHandle) -> Self {
        self.gpu = gpu;
        self
    }
}

/// A built stage.
pub enum Stage {
    /// A preprocessor.
    Preprocessor(Box<dyn Preprocessor>),
    /// A depth estimator.
    DepthEstimator(Box<dyn DepthEstimator>),
    /// A tracker.
    Tracker(Box<dyn Tracker>),
    /// A fuser.
    Fuser(Box<dyn Fuser>),
    /// A loop closer.
    LoopCloser(Box<dyn LoopCloser>),
}

/// A plugin: a stage implementation with a registry name and typed parameters.
pub trait Plugin: Sized + Send + 'static {
    /// Registry name (kebab-case; the file stem in snake case).
    const NAME: &'static str;
    /// One line on what it does, with its source.
    const SUMMARY: &'static str;
    /// Views a depth estimator needs (ignored for other stages).
    const VIEWS: ViewKind = ViewKind::Mono;
    /// Its parameters.
    type Params: PluginParams;
    /// Builds the stage from validated parameters.
    fn build(params: Self::Params, env: &BuildEnv) -> Result<Self, StageError>;
}

/// Builds a stage from its `[plugins.<name>]` table.
pub type BuildFn = fn(&toml::Table, &BuildEnv) -> Result<Stage, BuildError>;

/// Why a plugin could not be built.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// Its parameters are invalid.
    #[error("invalid parameters")]
    Params(Vec<ConfigProblem>),
    /// Its constructor failed (e.g. a calibration file it needs is missing).
    #[error(transparent)]
    Stage(#[from] StageError),
}

/// One registration.
#[derive(Clone, Copy)]
pub struct PluginEntry {
    /// Registry name.
    pub name: &'static str,
    /// Which stage it implements.
    pub kind: StageKind,
    /// One line on what it does.
    pub summary: &'static str,
    /// Views a depth estimator needs.
    pub views: ViewKind,
    source: Source,
}

/// Where a plugin's code lives.
#[derive(Clone, Copy)]
enum Source {
    /// Linked into this binary (inventory or a manual registration).
    Linked { params: fn() -> Vec<ParamDoc>, check: fn(&str, &toml::Table) -> Vec<ConfigProblem>, build: BuildFn },
    /// Loaded from elsewhere (a shared library, through `capsule-slam-abi`).
    Foreign(&'static dyn ForeignPlugin),
}

/// A plugin whose code is not linked into this binary: the registry sees it through this
/// trait, which the loader of shared-library plugins (`capsule-slam-abi`) implements.
pub trait ForeignPlugin: Send + Sync {
    /// Registry name.
    fn name(&self) -> &'static str;
    /// One line on what it does.
    fn summary(&self) -> &'static str;
    /// Which stage it implements.
    fn kind(&self) -> StageKind;
    /// Its parameters' documentation.
    fn param_docs(&self) -> Vec<ParamDoc>;
    /// Every problem of a `[plugins.<name>]` table, without building.
    fn check(&self, table: &toml::Table) -> Vec<ConfigProblem>;
    /// Builds the stage.
    fn build(&'static self, table: &toml::Table, env: &BuildEnv) -> Result<Stage, BuildError>;
    /// Where its code came from (the library file).
    fn origin(&self) -> &Path;
    /// The views it needs (a stereo depth estimator: both).
    fn views(&self) -> ViewKind {
        ViewKind::Mono
    }
}

impl PluginEntry {
    /// An entry for a plugin linked into this binary, from its three functions (the
    /// `preprocessor::<P>()`, ... constructors fill them from a [`Plugin`]).
    pub const fn linked(
        name: &'static str,
        kind: StageKind,
        summary: &'static str,
        views: ViewKind,
        params: fn() -> Vec<ParamDoc>,
        check: fn(&str, &toml::Table) -> Vec<ConfigProblem>,
        build: BuildFn,
    ) -> Self {
        Self { name, kind, summary, views, source: Source::Linked { params, check, build } }
    }

    /// An entry for a plugin whose code lives elsewhere (a shared library).
    pub fn foreign(plugin: &'static dyn ForeignPlugin) -> Self {
        Self { name: plugin.name(), kind: plugin.kind(), summary: plugin.summary(), views: plugin.views(), source: Source::Foreign(plugin) }
    }

    /// Its parameters' documentation (name, unit, default, range, meaning).
    pub fn param_docs(&self) -> Vec<ParamDoc> {
        match self.source {
            Source::Linked { params, .. } => params(),
            Source::Foreign(p) => p.param_docs(),
        }
    }

    /// Parses and validates a `[plugins.<name>]` table without building: every problem.
    pub fn check(&self, table: &toml::Table) -> Vec<ConfigProblem> {
        match self.source {
            Source::Linked { check, .. } => check(self.name, table),
            Source::Foreign(p) => p.check(table),
        }
    }

    /// Builds the stage from its `[plugins.<name>]` table.
    pub fn build(&self, table: &toml::Table, env: &BuildEnv) -> Result<Stage, BuildError> {
        match self.source {
            Source::Linked { build, .. } => build(table, env),
            Source::Foreign(p) => p.build(table, env),
        }
    }

    /// The shared library it came from, if it was loaded from one.
    pub fn library(&self) -> Option<&'static Path> {
        match self.source {
            Source::Linked { .. } => None,
            Source::Foreign(p) => Some(p.origin()),
        }
    }
}

impl std::fmt::Debug for PluginEntry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PluginEntry").field("name", &self.name).field("kind", &self.kind).finish_non_exhaustive()
    }
}

inventory::collect!(PluginEntry);

fn check<P: Plugin>(name: &str, table: &toml::Table) -> Vec<ConfigProblem> {
    parse_params::<P::Params>(name, table).err().unwrap_or_default()
}

macro_rules! entry_ctor {
    ($fn_name:ident, $trait:ident, $kind:ident) => {
        /// The registry entry of a plugin of this stage kind.
        pub const fn $fn_name<P: Plugin + $trait>() -> Self {
            fn build<P: Plugin + $trait>(table: &toml::Table, env: &BuildEnv) -> Result<Stage, BuildError> {
                let params = parse_params::<P::Params>(P::NAME, table).map_err(BuildError::Params)?;
                Ok(Stage::$kind(Box::new(P::build(params, env)?)))
            }
            Self::linked(P::NAME, StageKind::$kind, P::SUMMARY, P::VIEWS, <P::Params as PluginParams>::docs, check::<P>, build::<P>)
        }
    };
}

impl PluginEntry {
    entry_ctor!(preprocessor, Preprocessor, Preprocessor);
    entry_ctor!(depth_estimator, DepthEstimator, DepthEstimator);
    entry_ctor!(tracker, Tracker, Tracker);
    entry_ctor!(fuser, Fuser, Fuser);
    entry_ctor!(loop_closer, LoopCloser, LoopCloser);
}

/// Registers a plugin with inventory: `register!(DepthEstimator, Sensor);` as the last line of
/// the plugin's file.
#[macro_export]
macro_rules! register {
    (Preprocessor, $ty:ty) => {
        $crate::inventory::submit! { $crate::registry::PluginEntry::preprocessor::<$ty>() }
    };
    (DepthEstimator, $ty:ty) => {
        $crate::inventory::submit! { $crate::registry::PluginEntry::depth_estimator::<$ty>() }
    };
    (Tracker, $ty:ty) => {
        $crate::inventory::submit! { $crate::registry::PluginEntry::tracker::<$ty>() }
    };
    (Fuser, $ty:ty) => {
        $crate::inventory::submit! { $crate::registry::PluginEntry::fuser::<$ty>() }
    };
    (LoopCloser, $ty:ty) => {
        $crate::inventory::submit! { $crate::registry::PluginEntry::loop_closer::<$ty>() }
    };
}

/// Every known plugin, by name.
#[derive(Debug, Clone, Default)]
pub struct Registry {
    entries: BTreeMap<&'static str, PluginEntry>,
}

impl Registry {
    /// An empty registry.
    pub fn empty() -> Self {
        Self::default()
    }

    /// Every plugin registered with inventory in the linked crates.
    pub fn from_inventory() -> Result<Self, RegistryError> {
        let mut r = Self::empty();
        for e in inventory::iter::<PluginEntry> {
            r.register(*e)?;
        }
        Ok(r)
    }

    /// Adds a plugin; a name already taken is an error.
    pub fn register(&mut self, entry: PluginEntry) -> Result<(), RegistryError> {
        if let Some(old) = self.entries.get(entry.name) {
            return Err(RegistryError::Duplicate { name: entry.name.to_owned(), first: old.kind.as_str().to_owned(), second: entry.kind.as_str().to_owned() });
        }
        self.entries.insert(entry.name, entry);
        Ok(())
    }

    /// A plugin by name.
    pub fn get(&self, name: &str) -> Option<&PluginEntry> {
        self.entries.get(name)
    }

    /// All plugins in name order.
    pub fn iter(&self) -> impl Iterator<Item = &PluginEntry> {
        self.entries.values()
    }

    /// Names of the plugins of one stage kind, sorted.
    pub fn names(&self, kind: StageKind) -> Vec<&'static str> {
        self.entries.values().filter(|e| e.kind == kind).map(|e| e.name).collect()
    }
}
