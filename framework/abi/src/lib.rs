//! The C ABI of shared-library plugins (loaded with `libloading`): preprocessors and depth
//! estimators built as a separate `cdylib`, in Rust or in any language with a C FFI, and
//! loaded at run time (`capsule-slam --plugin-lib PATH ...`).
//!
//! Only `#[repr(C)]` data and `extern "C"` functions cross the boundary: Rust's layout of
//! `String`, `Vec`, trait objects and enums is not stable between compilers, so a library
//! built by another rustc (or in C++) would otherwise crash the host. Each side allocates and
//! frees its own memory: the host owns every buffer it passes (images, masks, depth, text),
//! the plugin owns its state and frees it in `destroy`. A library stays loaded for the life
//! of the process (unloading while a function pointer is alive is undefined behaviour).
//!
//! The handshake: the library exports [`ENTRY_SYMBOL`], a function returning a
//! [`AbiPluginList`] whose first field is the [`ABI_VERSION`] it was built for; the host reads
//! that field alone, refuses any other version, and only then reads the plugins.
//!
//! Text travels as TOML in NUL-terminated UTF-8 (parameters in, parameter docs and problems
//! out: [`ParamDocsToml`], [`ProblemsToml`]), so validation reports a library plugin's
//! problems exactly like a linked one's. A plugin written in Rust needs none of this by hand:
//! implement [`export::LibraryPreprocessor`] or [`export::LibraryDepthEstimator`] and list the
//! types in [`export_plugins!`](crate::export_plugins) (`plugins/dylib-example/` is a
//! complete one).

use std::ffi::{c_char, c_void};

pub mod export;
pub mod load;

/// The version of this ABI; any change to the structs or signatures below increments it.
pub const ABI_VERSION: u32 = 1;

/// The symbol a plugin library exports: an [`EntryFn`].
pub const ENTRY_SYMBOL: &[u8] = b"capsule_slam_plugins\0";

/// [`AbiPlugin::kind`] of a [`capsule_slam_framework::Preprocessor`].
pub const KIND_PREPROCESSOR: u32 = 1;
/// [`AbiPlugin::kind`] of a [`capsule_slam_framework::DepthEstimator`].
pub const KIND_DEPTH_ESTIMATOR: u32 = 2;

/// Return code: success.
pub const OK: i32 = 0;
/// Return code: failure, the reason in the message buffer.
pub const ERROR: i32 = 1;
/// Return code: the plugin panicked (caught at the boundary), the message in the buffer.
pub const PANIC: i32 = 2;

/// An 8-bit RGB image owned by the host: `3 · width · height` bytes, rows top to bottom,
/// pixels interleaved R, G, B, no padding.
#[repr(C)]
#[derive(Debug)]
pub struct AbiImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// The pixels.
    pub data: *mut u8,
}

/// The reference camera (pinhole, pixels), given at creation.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AbiCamera {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Radius of the round field of view about (cx, cy), pixels; 0 = the whole image.
    pub fov_radius_px: f64,
    /// Brown–Conrady distortion k1 k2 p1 p2 k3 (zeros: none).
    pub distortion: [f64; 5],
}

/// A text buffer owned by the host. The plugin writes at most `capacity` bytes of UTF-8 (no
/// NUL needed) and sets `len` to the full length of its text; a `len` above `capacity` tells
/// the host the text was cut (for parameter docs and problems it asks again, bigger).
#[repr(C)]
#[derive(Debug)]
pub struct AbiBuffer {
    /// The bytes.
    pub data: *mut u8,
    /// Their number.
    pub capacity: usize,
    /// Set by the plugin: the length of its whole text.
    pub len: usize,
}

/// Writes TOML text into `out`: the parameter docs (`input` is null) or the problems of the
/// parameter table `input` (TOML; [`OK`] and nothing written when it is valid).
pub type TextFn = unsafe extern "C" fn(input: *const c_char, out: *mut AbiBuffer) -> i32;
/// Creates a stage from its validated parameter table (TOML) and the camera; on [`OK`] the
/// state is in `state_out`, otherwise the reason is in `message`.
pub type CreateFn = unsafe extern "C" fn(params_toml: *const c_char, camera: *const AbiCamera, state_out: *mut *mut c_void, message: *mut AbiBuffer) -> i32;
/// Frees a state made by [`CreateFn`].
pub type DestroyFn = unsafe extern "C" fn(state: *mut c_void);
/// Processes one image in place; may set bytes of `mask` (`width · height`, zero on entry)
/// to 1 for pixels that later stages must ignore.
pub type PreprocessFn = unsafe extern "C" fn(state: *mut c_void, image: *mut AbiImage, mask: *mut u8, message: *mut AbiBuffer) -> i32;
/// Writes depth along z in metres for every pixel of `image` into `depth_m`
/// (`width · height` floats, 0 = invalid).
pub type DepthFn = unsafe extern "C" fn(state: *mut c_void, image: *const AbiImage, depth_m: *mut f32, message: *mut AbiBuffer) -> i32;

/// One plugin of a library.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct AbiPlugin {
    /// Registry name, NUL-terminated UTF-8 (kebab-case).
    pub name: *const c_char,
    /// One line on what it does, NUL-terminated UTF-8.
    pub summary: *const c_char,
    /// [`KIND_PREPROCESSOR`] or [`KIND_DEPTH_ESTIMATOR`].
    pub kind: u32,
    /// Parameter docs as [`ParamDocsToml`].
    pub params: TextFn,
    /// Problems of a parameter table as [`ProblemsToml`].
    pub check: TextFn,
    /// Makes a stage.
    pub create: CreateFn,
    /// Frees a stage.
    pub destroy: DestroyFn,
    /// Set for a preprocessor.
    pub preprocess: Option<PreprocessFn>,
    /// Set for a depth estimator.
    pub estimate_depth: Option<DepthFn>,
}

/// What the entry function returns. `abi_version` comes first so that the host can read it
/// whatever the rest looks like.
#[repr(C)]
#[derive(Debug)]
pub struct AbiPluginList {
    /// [`ABI_VERSION`] of the library.
    pub abi_version: u32,
    /// The capsule-slam framework version it was built with, NUL-terminated (informative).
    pub framework_version: *const c_char,
    /// Number of plugins.
    pub count: usize,
    /// The plugins.
    pub plugins: *const AbiPlugin,
}

/// The entry function, exported as [`ENTRY_SYMBOL`].
pub type EntryFn = unsafe extern "C" fn() -> *const AbiPluginList;

// SAFETY: both hold only pointers to immutable static data (strings, function pointers, the
// plugin array) that no one writes after initialisation.
#[allow(unsafe_code)]
unsafe impl Sync for AbiPlugin {}
#[allow(unsafe_code)]
unsafe impl Sync for AbiPluginList {}

/// The framework version, NUL-terminated, for [`AbiPluginList::framework_version`].
pub const FRAMEWORK_VERSION: &std::ffi::CStr = match std::ffi::CStr::from_bytes_with_nul(concat!(env!("CARGO_PKG_VERSION"), "\0").as_bytes()) {
    Ok(v) => v,
    Err(_) => panic!("the crate version holds a NUL"),
};

impl AbiPluginList {
    /// The list of a library's plugins, for this ABI version.
    pub const fn new(plugins: &'static [AbiPlugin]) -> Self {
        Self { abi_version: ABI_VERSION, framework_version: FRAMEWORK_VERSION.as_ptr(), count: plugins.len(), plugins: plugins.as_ptr() }
    }
}

/// Parameter docs as TOML: `[[param]]` tables with `name`, `unit`, `doc`, `default` (any TOML
/// value) and `range = [lo, hi]` (optional).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamDocsToml {
    /// The parameters.
    #[serde(default)]
    pub param: Vec<ParamDocToml>,
}

/// One parameter of [`ParamDocsToml`].
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamDocToml {
    /// Key in `[plugins.<name>]`.
    pub name: String,
    /// Unit.
    pub unit: String,
    /// Meaning and source.
    pub doc: String,
    /// Default value.
    pub default: Option<toml::Value>,
    /// Valid closed range.
    pub range: Option<[f64; 2]>,
}

/// Problems as TOML: `[[problem]]` tables with `key`, `message`, `fix`.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProblemsToml {
    /// The problems.
    #[serde(default)]
    pub problem: Vec<capsule_slam_framework::ConfigProblem>,
}

#[cfg(test)]
mod tests;
