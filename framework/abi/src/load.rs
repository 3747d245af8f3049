//! The host side of the C ABI: opens a library with `libloading`, checks its ABI version
//! before reading anything else, validates each plugin's declaration, and wraps each one as a
//! registry entry whose stages call through the ABI.
#![allow(unsafe_code)]

use std::ffi::{CStr, CString, c_char, c_void};
use std::path::Path;

use super::{
    ABI_VERSION, ABI_VERSION_MIN, AbiBuffer, AbiCamera, AbiPlugin, AbiPluginList, AbiPluginV1, ENTRY_SYMBOL, EntryFn, KIND_DEPTH_ESTIMATOR, KIND_PREPROCESSOR,
    KIND_STEREO_DEPTH_ESTIMATOR, KIND_TRACKER, OK, PANIC, ParamDocsToml, ProblemsToml,
};
use crate::host_stage::{LibraryStage, Message};
use capsule_slam_framework::camera::{PinholeCamera, ViewKind};
use capsule_slam_framework::error::{ConfigProblem, RegistryError, StageError};
use capsule_slam_framework::lens::LensModel;
use capsule_slam_framework::params::ParamDoc;
use capsule_slam_framework::registry::{BuildEnv, BuildError, ForeignPlugin, PluginEntry, Registry, Stage, StageKind};

/// Largest text (parameter docs, problems) the host accepts from a library, bytes.
const MAX_TEXT_BYTES: usize = 1 << 20;

pub use crate::host_stage::LoadedPlugin;

fn library_error(path: &Path, message: impl Into<String>, fix: impl Into<String>) -> RegistryError {
    RegistryError::Library { path: path.to_path_buf(), message: message.into(), fix: fix.into() }
}

/// Loads the plugins of the shared library at `path` and registers them; returns their names.
/// The library stays loaded for the life of the process.
pub fn load_library(registry: &mut Registry, path: &Path) -> Result<Vec<&'static str>, RegistryError> {
    let mut names = Vec::new();
    for p in load(path)? {
        registry.register(PluginEntry::foreign(p))?;
        names.push(p.name);
    }
    Ok(names)
}

/// Opens the library at `path` and returns its plugins. The library is never unloaded.
pub fn load(path: &Path) -> Result<Vec<&'static LoadedPlugin>, RegistryError> {
    if path.is_dir() {
        return Err(library_error(path, "is a directory", "pass the library file itself (its lib*.so / *.dylib / *.dll)"));
    }
    if !path.is_file() {
        return Err(library_error(
            path,
            "no such file",
            "build the plugin library (e.g. `cargo build --release -p capsule-slam-dylib-example`) and pass the path of its lib*.so / *.dylib / *.dll",
        ));
    }
    // The file itself: a bare name (no directory) would make the dynamic loader search the
    // system's library path instead of opening the file the user named.
    let file = std::fs::canonicalize(path).map_err(|e| library_error(path, format!("cannot be resolved: {e}"), "pass a readable file"))?;
    // SAFETY: loading a library runs its initialisers; the user asked for this library.
    let lib = unsafe { libloading::Library::new(&file) }.map_err(|e| {
        library_error(path, format!("cannot be opened as a shared library: {}", with_reason(&e)), "pass a shared library built for this platform")
    })?;
    // SAFETY: the symbol, if present, is an `EntryFn` by the ABI contract.
    let entry: EntryFn = unsafe { lib.get::<EntryFn>(ENTRY_SYMBOL) }.map(|s| *s).map_err(|_| {
        library_error(
            path,
            "it is not a capsule-slam plugin library: it exports no `capsule_slam_plugins`",
            "export the plugins with `capsule_slam_abi::export_plugins!` in a crate of type cdylib",
        )
    })?;
    // Never unloaded: the entries keep its function pointers (dlclose while one is alive is
    // undefined behaviour).
    std::mem::forget(lib);
    // SAFETY: the entry function takes nothing and returns a pointer to static data.
    let list = unsafe { entry() };
    // SAFETY: a non-null pointer from the entry points to a list that lives as long as the
    // library; its first field is read alone before the version is known to match.
    let list = unsafe { list_of(list, path)? };
    let plugins = unsafe { plugins_of(list, path)? };
    Ok(plugins.into_iter().map(|p| &*Box::leak(Box::new(p))).collect())
}

/// An error with its sources (libloading's "dlopen failed" keeps the loader's reason there).
fn with_reason(e: &dyn std::error::Error) -> String {
    let mut out = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        out.push_str(&format!(": {s}"));
        source = s.source();
    }
    out
}

/// The list, once its ABI version is known to match.
///
/// # Safety
/// `list` is null or points to a readable `u32` that, if it equals [`ABI_VERSION`], begins a
/// valid [`AbiPluginList`] that lives for the rest of the process.
pub(crate) unsafe fn list_of(list: *const AbiPluginList, path: &Path) -> Result<&'static AbiPluginList, RegistryError> {
    if list.is_null() {
        return Err(library_error(path, "its `capsule_slam_plugins` returned no plugin list", "return the list made by `export_plugins!`"));
    }
    // SAFETY: the first field is a u32 in every ABI version.
    let version = unsafe { *list.cast::<u32>() };
    if !(ABI_VERSION_MIN..=ABI_VERSION).contains(&version) {
        return Err(library_error(
            path,
            format!(
                "it was built for plugin ABI version {version}; this capsule-slam speaks versions {ABI_VERSION_MIN} to {ABI_VERSION} (framework {})",
                env!("CARGO_PKG_VERSION")
            ),
            "rebuild the plugin against this capsule-slam framework",
        ));
    }
    // SAFETY: the version matches, so the layout is this one.
    Ok(unsafe { &*list })
}

/// A NUL-terminated UTF-8 string from the library, leaked (it is read once per load).
///
/// # Safety
/// `text` is null or NUL-terminated.
unsafe fn lib_str(text: *const c_char, path: &Path, what: &str) -> Result<&'static str, RegistryError> {
    if text.is_null() {
        return Err(library_error(path, format!("a plugin has no {what}"), format!("set the plugin's {what}")));
    }
    // SAFETY: the caller's contract.
    let s = unsafe { CStr::from_ptr(text) }.to_str().map_err(|_| library_error(path, format!("a plugin's {what} is not UTF-8"), "use UTF-8"))?;
    Ok(Box::leak(s.to_owned().into_boxed_str()))
}

/// Validates the plugins of a list and reads their parameter docs.
///
/// # Safety
/// `list.plugins` points to `list.count` valid [`AbiPlugin`]s with valid strings and functions.
pub(crate) unsafe fn plugins_of(list: &AbiPluginList, path: &Path) -> Result<Vec<LoadedPlugin>, RegistryError> {
    if list.count == 0 || list.plugins.is_null() {
        return Err(library_error(path, "it declares no plugins", "list at least one plugin in `export_plugins!`"));
    }
    // SAFETY: the caller's contract; a version-1 list holds the shorter version-1 plugins.
    let raw: Vec<AbiPlugin> = if list.abi_version == 1 {
        unsafe { std::slice::from_raw_parts(list.plugins.cast::<AbiPluginV1>(), list.count) }.iter().map(|p| AbiPlugin::from(*p)).collect()
    } else {
        unsafe { std::slice::from_raw_parts(list.plugins, list.count) }.to_vec()
    };
    let mut out = Vec::with_capacity(raw.len());
    for p in &raw {
        // SAFETY: the caller's contract.
        let name = unsafe { lib_str(p.name, path, "name")? };
        // SAFETY: the caller's contract.
        let summary = unsafe { lib_str(p.summary, path, "summary")? };
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-') {
            return Err(library_error(path, format!("plugin name `{name}` is not kebab-case"), "name it with lower-case letters, digits and '-'"));
        }
        let (kind, views) = kind_of(p, name, path)?;
        // SAFETY: the caller's contract; null input asks for the docs.
        let (rc, text) = unsafe { call_text(p.params, std::ptr::null()) };
        if rc != OK {
            return Err(library_error(path, format!("plugin `{name}` failed to describe its parameters: {text}"), "fix the plugin's parameter docs"));
        }
        let docs: ParamDocsToml = toml::from_str(&text).map_err(|e| {
            library_error(path, format!("plugin `{name}` described its parameters in unreadable TOML: {e}"), "write [[param]] tables (abi::ParamDocsToml)")
        })?;
        let params = docs
            .param
            .into_iter()
            .map(|d| ParamDoc {
                name: Box::leak(d.name.into_boxed_str()),
                unit: Box::leak(d.unit.into_boxed_str()),
                doc: d.doc,
                default: d.default,
                range: d.range.map(|[lo, hi]| (lo, hi)),
            })
            .collect();
        out.push(LoadedPlugin { name, summary, kind, params, views, library: path.to_path_buf(), abi_version: list.abi_version, raw: *p });
    }
    Ok(out)
}

/// A plugin's stage and views from its declared kind and the stage functions it sets (exactly
/// those of its kind).
fn kind_of(p: &AbiPlugin, name: &str, path: &Path) -> Result<(StageKind, ViewKind), RegistryError> {
    let set = [p.preprocess.is_some(), p.estimate_depth.is_some(), p.track.is_some(), p.create_stereo.is_some() && p.estimate_stereo_depth.is_some()];
    let (expected, stage, views, needs) = match p.kind {
        KIND_PREPROCESSOR => (0, StageKind::Preprocessor, ViewKind::Mono, "`preprocess`"),
        KIND_DEPTH_ESTIMATOR => (1, StageKind::DepthEstimator, ViewKind::Mono, "`estimate_depth`"),
        KIND_TRACKER => (2, StageKind::Tracker, ViewKind::Mono, "`track`"),
        KIND_STEREO_DEPTH_ESTIMATOR => (3, StageKind::DepthEstimator, ViewKind::Stereo, "`create_stereo` and `estimate_stereo_depth`"),
        k => {
            return Err(library_error(
                path,
                format!("plugin `{name}` has unknown kind {k}"),
                format!(
                    "use {KIND_PREPROCESSOR} (preprocessor), {KIND_DEPTH_ESTIMATOR} (depth estimator), {KIND_TRACKER} (tracker) or {KIND_STEREO_DEPTH_ESTIMATOR} (stereo depth estimator)"
                ),
            ));
        }
    };
    let others = set.iter().enumerate().any(|(i, s)| *s && i != expected) || p.create_stereo.is_some() != p.estimate_stereo_depth.is_some();
    if !set[expected] || others {
        return Err(library_error(
            path,
            format!("plugin `{name}` declares kind {} but not exactly its stage functions", p.kind),
            format!("set {needs} for this kind, and no other stage function"),
        ));
    }
    Ok((stage, views))
}

/// Calls a text function with a buffer big enough for its answer.
///
/// # Safety
/// `f` is a [`super::TextFn`] of a loaded library; `input` is null or NUL-terminated.
unsafe fn call_text(f: super::TextFn, input: *const c_char) -> (i32, String) {
    let mut capacity = 16 * 1024;
    loop {
        let mut bytes = vec![0u8; capacity];
        let mut buf = AbiBuffer { data: bytes.as_mut_ptr(), capacity, len: 0 };
        // SAFETY: the caller's contract; the buffer is ours and holds `capacity` bytes.
        let rc = unsafe { f(input, &mut buf) };
        if buf.len > capacity && buf.len <= MAX_TEXT_BYTES {
            capacity = buf.len;
            continue;
        }
        bytes.truncate(buf.len.min(capacity));
        return (rc, String::from_utf8_lossy(&bytes).into_owned());
    }
}

impl ForeignPlugin for LoadedPlugin {
    fn name(&self) -> &'static str {
        self.name
    }
    fn summary(&self) -> &'static str {
        self.summary
    }
    fn kind(&self) -> StageKind {
        self.kind
    }
    fn param_docs(&self) -> Vec<ParamDoc> {
        self.params.clone()
    }
    fn check(&self, table: &toml::Table) -> Vec<ConfigProblem> {
        self.check_table(table)
    }
    fn build(&'static self, table: &toml::Table, env: &BuildEnv) -> Result<Stage, BuildError> {
        self.build_stage(table, env)
    }
    fn origin(&self) -> &Path {
        &self.library
    }
    fn views(&self) -> ViewKind {
        self.views
    }
}

impl LoadedPlugin {
    fn params_text(&self, table: &toml::Table) -> Result<CString, ConfigProblem> {
        let text = toml::to_string(table).map_err(|e| ConfigProblem::new(format!("plugins.{}", self.name), e.to_string(), "write plain TOML values"))?;
        CString::new(text).map_err(|_| ConfigProblem::new(format!("plugins.{}", self.name), "a value holds a NUL character", "remove it"))
    }

    /// The problems of a parameter table, as the plugin reports them.
    fn check_table(&self, table: &toml::Table) -> Vec<ConfigProblem> {
        let text = match self.params_text(table) {
            Ok(t) => t,
            Err(p) => return vec![p],
        };
        // SAFETY: a text function of a loaded library, with a NUL-terminated input.
        let (rc, answer) = unsafe { call_text(self.raw.check, text.as_ptr()) };
        let key = format!("plugins.{}", self.name);
        if rc != OK {
            return vec![ConfigProblem::new(
                key,
                format!("the plugin failed to check its parameters: {answer}"),
                format!("see the plugin library {}", self.library.display()),
            )];
        }
        if answer.trim().is_empty() {
            return Vec::new();
        }
        match toml::from_str::<ProblemsToml>(&answer) {
            Ok(p) => p.problem,
            Err(e) => vec![ConfigProblem::new(key, format!("the plugin answered its check in unreadable TOML: {e}"), "fix the plugin (abi::ProblemsToml)")],
        }
    }

    /// Builds a stage through the library's `create`.
    fn build_stage(&'static self, table: &toml::Table, env: &BuildEnv) -> Result<Stage, BuildError> {
        let problems = self.check_table(table);
        if !problems.is_empty() {
            return Err(BuildError::Params(problems));
        }
        let text = self.params_text(table).map_err(|p| BuildError::Params(vec![p]))?;
        let camera = abi_camera(env.rig.camera())?;
        let mut state: *mut c_void = std::ptr::null_mut();
        let mut message = Message::new();
        let rc = match (self.raw.create_stereo, &env.rig) {
            (Some(create), capsule_slam_framework::camera::Rig::Stereo { right, t_right_left, .. }) => {
                let r = t_right_left.rotation.to_rotation_matrix();
                let rig = super::AbiStereoRig {
                    right: abi_camera(right)?,
                    rotation: std::array::from_fn(|k| r[(k / 3, k % 3)]),
                    translation_m: [t_right_left.translation.x, t_right_left.translation.y, t_right_left.translation.z],
                };
                // SAFETY: the library's create_stereo, with a NUL-terminated table, both
                // cameras, a state slot and a message buffer that all outlive the call.
                unsafe { create(text.as_ptr(), &camera, &rig, &mut state, message.buffer()) }
            }
            (Some(_), _) => {
                return Err(StageError::invalid_input(format!(
                    "`{}` is a stereo depth estimator: give it a stereo input (rgb_right.txt and camera.toml's [right])",
                    self.name
                ))
                .into());
            }
            // SAFETY: the library's create, with a NUL-terminated table, a camera, a state slot
            // and a message buffer that all outlive the call.
            (None, _) => unsafe { (self.raw.create)(text.as_ptr(), &camera, &mut state, message.buffer()) },
        };
        if rc != OK || state.is_null() {
            return Err(BuildError::Stage(self.error(rc, &message, "creating the stage")));
        }
        let stage = LibraryStage { plugin: self, state };
        Ok(match self.kind {
            StageKind::Preprocessor => Stage::Preprocessor(Box::new(stage)),
            StageKind::Tracker => Stage::Tracker(Box::new(stage)),
            _ => Stage::DepthEstimator(Box::new(stage)),
        })
    }

    pub(crate) fn error(&self, rc: i32, message: &Message, doing: &str) -> StageError {
        let what = if rc == PANIC { "panicked" } else { "failed" };
        let text = message.text();
        let text = if text.is_empty() { format!("{doing} {what} (code {rc}, no message)") } else { format!("{doing} {what}: {text}") };
        StageError::Plugin { name: self.name.to_owned(), source: text.into() }
    }
}

/// A camera as the ABI carries it: a pinhole with at most a five-coefficient lens.
fn abi_camera(cam: &PinholeCamera) -> Result<AbiCamera, StageError> {
    let k = match cam.distortion {
        None => [0.0; 5],
        Some(LensModel::RadialTangential(k)) if k[5..].iter().all(|v| *v == 0.0) => [k[0], k[1], k[2], k[3], k[4]],
        Some(lens) => {
            return Err(StageError::invalid_input(format!(
                "the plugin ABI carries a five-coefficient radial-tangential lens, not this {} one: build the stage with the undistorted rig (input folders are undistorted as they are read)",
                lens.name()
            )));
        }
    };
    let to_u32 = |v: usize| u32::try_from(v).map_err(|_| StageError::invalid_input(format!("the image is too large for the plugin ABI ({v} pixels)")));
    Ok(AbiCamera {
        width: to_u32(cam.width)?,
        height: to_u32(cam.height)?,
        fx: cam.fx,
        fy: cam.fy,
        cx: cam.cx,
        cy: cam.cy,
        fov_radius_px: cam.fov_radius_px.unwrap_or(0.0),
        distortion: k,
    })
}
