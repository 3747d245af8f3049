//! The C ABI of shared-library plugins (loaded with `libloading`): preprocessors, depth
//! estimators (mono and, from version 2, stereo) and trackers (version 2) built as a separate
//! `cdylib`, in Rust or in any language with a C FFI, and
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
//! that field alone, refuses a version it does not know (a newer one), and only then reads the
//! plugins. Version 1 libraries (preprocessors and mono depth estimators, the shorter
//! [`AbiPluginV1`]) still load.
//!
//! Text travels as TOML in NUL-terminated UTF-8 (parameters in, parameter docs and problems
//! out: [`ParamDocsToml`], [`ProblemsToml`]), so validation reports a library plugin's
//! problems exactly like a linked one's. A plugin written in Rust needs none of this by hand:
//! implement [`export::LibraryPreprocessor`], [`export::LibraryDepthEstimator`],
//! [`export_v2::LibraryStereoDepthEstimator`] or [`export_v2::LibraryTracker`] and list the types in [`export_plugins!`](crate::export_plugins) (`plugins/dylib-example/` is a
//! complete one).

use std::ffi::{c_char, c_void};

pub mod export;
pub mod export_v2;
mod host_stage;
pub mod load;

/// The version of this ABI; any change to the structs or signatures below increments it.
/// Version 2 added trackers and stereo depth estimators ([`AbiPlugin::track`],
/// [`AbiPlugin::create_stereo`], [`AbiPlugin::estimate_stereo_depth`]).
pub const ABI_VERSION: u32 = 2;

/// The oldest version the host still loads: version 1's plugins are [`AbiPluginV1`]s.
pub const ABI_VERSION_MIN: u32 = 1;

/// The symbol a plugin library exports: an [`EntryFn`].
pub const ENTRY_SYMBOL: &[u8] = b"capsule_slam_plugins\0";

/// [`AbiPlugin::kind`] of a [`capsule_slam_framework::Preprocessor`].
pub const KIND_PREPROCESSOR: u32 = 1;
/// [`AbiPlugin::kind`] of a [`capsule_slam_framework::DepthEstimator`].
pub const KIND_DEPTH_ESTIMATOR: u32 = 2;
/// [`AbiPlugin::kind`] of a [`capsule_slam_framework::Tracker`] (version 2; rigid: a
/// non-rigid warp stays with linked trackers).
pub const KIND_TRACKER: u32 = 3;
/// [`AbiPlugin::kind`] of a stereo [`capsule_slam_framework::DepthEstimator`] (version 2).
pub const KIND_STEREO_DEPTH_ESTIMATOR: u32 = 4;

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

/// The second camera of a stereo rig, given at the creation of a stereo depth estimator:
/// `x_right = rotation · x_left + translation_m` (OpenCV's `stereoCalibrate` R and T).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AbiStereoRig {
    /// The right camera.
    pub right: AbiCamera,
    /// R, row-major.
    pub rotation: [f64; 9],
    /// T, metres.
    pub translation_m: [f64; 3],
}

/// What a tracker gets each frame (all buffers owned by the host, read-only). Poses are 4×4
/// row-major matrices `t_world_cam` (camera to world, metres).
#[repr(C)]
#[derive(Debug)]
pub struct AbiTrackInput {
    /// Frame index.
    pub index: u64,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// The frame's colour (after the preprocessors).
    pub image: AbiImage,
    /// The frame's depth along z, metres (`width · height`; 0 = invalid).
    pub depth_m: *const f32,
    /// 1 when the model's prediction below is there (0 before the map shows anything).
    pub has_model: u32,
    /// The model's predicted depth at `t_world_prev` (`width · height`; null without model).
    pub model_depth_m: *const f32,
    /// Its unit normals in the camera frame (`3 · width · height`, x y z per pixel).
    pub model_normals_cam: *const f32,
    /// Its colour (`data` null without model).
    pub model_colour: AbiImage,
    /// The last trusted pose, where the model was rendered.
    pub t_world_prev: [f64; 16],
}

/// What a tracker returns.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AbiTrackOutput {
    /// The estimated pose, 4×4 row-major.
    pub t_world_cam: [f64; 16],
    /// 1: tracked (the frame is fused); 0: lost.
    pub tracked: u32,
    /// Inlier correspondences.
    pub inliers: u64,
    /// RMS residual (metres for a geometric tracker).
    pub residual_rms: f64,
    /// Iterations run.
    pub iterations: u64,
}

/// Creates a stereo depth estimator: as [`CreateFn`] with the left camera in `camera` and the
/// right one in `rig`.
pub type CreateStereoFn = unsafe extern "C" fn(
    params_toml: *const c_char,
    camera: *const AbiCamera,
    rig: *const AbiStereoRig,
    state_out: *mut *mut c_void,
    message: *mut AbiBuffer,
) -> i32;
/// Estimates the pose of a frame ([`AbiTrackInput`]) into `out`.
pub type TrackFn = unsafe extern "C" fn(state: *mut c_void, input: *const AbiTrackInput, out: *mut AbiTrackOutput, message: *mut AbiBuffer) -> i32;
/// Writes the left view's depth along z in metres (`width · height` floats, 0 = invalid)
/// from a stereo pair (the views as loaded, after the preprocessors; not rectified).
pub type StereoDepthFn =
    unsafe extern "C" fn(state: *mut c_void, left: *const AbiImage, right: *const AbiImage, depth_m: *mut f32, message: *mut AbiBuffer) -> i32;

/// One plugin of a version-1 library: [`AbiPlugin`] without the version-2 fields.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct AbiPluginV1 {
    /// As [`AbiPlugin::name`].
    pub name: *const c_char,
    /// As [`AbiPlugin::summary`].
    pub summary: *const c_char,
    /// As [`AbiPlugin::kind`] (1 or 2).
    pub kind: u32,
    /// As [`AbiPlugin::params`].
    pub params: TextFn,
    /// As [`AbiPlugin::check`].
    pub check: TextFn,
    /// As [`AbiPlugin::create`].
    pub create: CreateFn,
    /// As [`AbiPlugin::destroy`].
    pub destroy: DestroyFn,
    /// As [`AbiPlugin::preprocess`].
    pub preprocess: Option<PreprocessFn>,
    /// As [`AbiPlugin::estimate_depth`].
    pub estimate_depth: Option<DepthFn>,
}

impl From<AbiPluginV1> for AbiPlugin {
    fn from(p: AbiPluginV1) -> Self {
        let AbiPluginV1 { name, summary, kind, params, check, create, destroy, preprocess, estimate_depth } = p;
        Self { name, summary, kind, params, check, create, destroy, preprocess, estimate_depth, track: None, create_stereo: None, estimate_stereo_depth: None }
    }
}

/// One plugin of a library.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct AbiPlugin {
    /// Registry name, NUL-terminated UTF-8 (kebab-case).
    pub name: *const c_char,
    /// One line on what it does, NUL-terminated UTF-8.
    pub summary: *const c_char,
    /// [`KIND_PREPROCESSOR`], [`KIND_DEPTH_ESTIMATOR`], [`KIND_TRACKER`] or
    /// [`KIND_STEREO_DEPTH_ESTIMATOR`].
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
    /// Set for a tracker (version 2).
    pub track: Option<TrackFn>,
    /// Set for a stereo depth estimator, which is created by it, not by `create` (version 2).
    pub create_stereo: Option<CreateStereoFn>,
    /// Set for a stereo depth estimator (version 2).
    pub estimate_stereo_depth: Option<StereoDepthFn>,
}

/// What the entry function returns. `abi_version` comes first so that the host can read it
/// whatever the rest looks like.
#[repr(C)]
#[derive(Debug)]
pub struct AbiPluginList {
    /// [`ABI_VERSION`] of the library (1: `plugins` points to [`AbiPluginV1`]s).
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
// SAFETY: as for `AbiPlugin`.
#[allow(unsafe_code)]
unsafe impl Sync for AbiPluginV1 {}
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

    /// The list of a version-1 library (as one built before version 2 exports it).
    pub const fn v1(plugins: &'static [AbiPluginV1]) -> Self {
        Self { abi_version: 1, framework_version: FRAMEWORK_VERSION.as_ptr(), count: plugins.len(), plugins: plugins.as_ptr().cast() }
    }
}

/// A pose as the ABI carries it: 4×4, row-major.
pub fn matrix_of(pose: &capsule_slam_framework::geometry::Iso3) -> [f64; 16] {
    let m = pose.to_homogeneous();
    std::array::from_fn(|k| m[(k / 4, k % 4)])
}

/// A pose from the ABI: the rotation is the nearest one to the upper 3×3 (a library's rounding
/// is tolerated, anything but a rigid motion is not).
pub fn pose_of(m: &[f64; 16]) -> Option<capsule_slam_framework::geometry::Iso3> {
    if m.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let r = nalgebra::Matrix3::from_fn(|i, j| m[4 * i + j]);
    if (r.transpose() * r - nalgebra::Matrix3::identity()).norm() > 1e-6 || r.determinant() <= 0.0 {
        return None;
    }
    let q = nalgebra::UnitQuaternion::from_matrix_eps(&r, f64::EPSILON, 1000, nalgebra::UnitQuaternion::identity());
    Some(capsule_slam_framework::geometry::Iso3::from_parts(nalgebra::Translation3::new(m[3], m[7], m[11]), q))
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
#[cfg(test)]
mod tests_v2;
