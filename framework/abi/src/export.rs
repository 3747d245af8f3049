//! The plugin side of the C ABI, for plugins written in Rust: implement
//! [`LibraryPreprocessor`], [`LibraryDepthEstimator`], or (ABI version 2, in
//! [`export_v2`](crate::export_v2)) `LibraryStereoDepthEstimator` or `LibraryTracker`, then list
//! the types once in the library's `lib.rs`:
//!
//! ```ignore
//! capsule_slam_abi::export_plugins!(preprocessor MyGamma, depth_estimator MyDepth,
//!     stereo_depth_estimator MyStereo, tracker MyTracker);
//! ```
//!
//! with `crate-type = ["cdylib", "rlib"]` in its Cargo.toml. The generated functions catch
//! panics at the boundary (an unwinding panic may not cross `extern "C"`) and copy images in
//! and out, so the plugin works on ordinary [`Rgb8`], [`Mask`] and [`DepthMap`] values.
//! Parameters are a [`PluginParams`] struct, declared with
//! [`plugin_params!`](capsule_slam_framework::plugin_params) like a linked plugin's, and validated on the
//! plugin's side of the boundary by the same [`parse_params`].
#![allow(unsafe_code)]

use std::ffi::{CStr, c_char, c_void};
use std::panic::{AssertUnwindSafe, catch_unwind};

use super::{AbiBuffer, AbiCamera, AbiImage, AbiPlugin, ERROR, KIND_DEPTH_ESTIMATOR, KIND_PREPROCESSOR, OK, PANIC, ParamDocToml, ParamDocsToml, ProblemsToml};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::image::{DepthMap, Mask, Rgb8};

use capsule_slam_framework::params::{PluginParams, parse_params};

/// A stage built by a library.
pub trait LibraryPlugin: Sized + Send + 'static {
    /// Registry name (kebab-case).
    const NAME: &'static CStr;
    /// One line on what it does, with its source.
    const SUMMARY: &'static CStr;
    /// Its parameters.
    type Params: PluginParams;
    /// Builds the stage; an error is a sentence naming what is wrong and the fix.
    fn build(params: Self::Params, camera: &PinholeCamera) -> Result<Self, String>;
}

/// A preprocessor in a library (step 1–2 of the paper).
pub trait LibraryPreprocessor: LibraryPlugin {
    /// Processes one image in place; sets `mask` (all false on entry) where later stages must
    /// not look.
    fn process(&mut self, image: &mut Rgb8, mask: &mut Mask) -> Result<(), String>;
}

/// A depth estimator in a library (step 3 of the paper).
pub trait LibraryDepthEstimator: LibraryPlugin {
    /// Depth along z in metres of every pixel of the image (0 = invalid), of the image's size.
    fn estimate(&mut self, image: &Rgb8) -> Result<DepthMap, String>;
}

/// The table entry of a preprocessor.
pub const fn preprocessor<T: LibraryPreprocessor>() -> AbiPlugin {
    AbiPlugin {
        name: T::NAME.as_ptr(),
        summary: T::SUMMARY.as_ptr(),
        kind: KIND_PREPROCESSOR,
        params: params::<T>,
        check: check::<T>,
        create: create::<T>,
        destroy: destroy::<T>,
        preprocess: Some(preprocess::<T>),
        estimate_depth: None,
        track: None,
        create_stereo: None,
        estimate_stereo_depth: None,
    }
}

/// The table entry of a depth estimator.
pub const fn depth_estimator<T: LibraryDepthEstimator>() -> AbiPlugin {
    AbiPlugin {
        name: T::NAME.as_ptr(),
        summary: T::SUMMARY.as_ptr(),
        kind: KIND_DEPTH_ESTIMATOR,
        params: params::<T>,
        check: check::<T>,
        create: create::<T>,
        destroy: destroy::<T>,
        preprocess: None,
        estimate_depth: Some(estimate_depth::<T>),
        track: None,
        create_stereo: None,
        estimate_stereo_depth: None,
    }
}

/// The table entry of one plugin of [`export_plugins!`](crate::export_plugins) by its kind.
#[doc(hidden)]
#[macro_export]
macro_rules! plugin_entry {
    (preprocessor $ty:ty) => {
        $crate::export::preprocessor::<$ty>()
    };
    (depth_estimator $ty:ty) => {
        $crate::export::depth_estimator::<$ty>()
    };
    (tracker $ty:ty) => {
        $crate::export_v2::tracker::<$ty>()
    };
    (stereo_depth_estimator $ty:ty) => {
        $crate::export_v2::stereo_depth_estimator::<$ty>()
    };
}

/// Exports a library's plugins: `export_plugins!(preprocessor A, depth_estimator B,
/// tracker C, stereo_depth_estimator D, ...)`.
#[macro_export]
macro_rules! export_plugins {
    ($($kind:ident $ty:ty),+ $(,)?) => {
        static CAPSULE_SLAM_PLUGIN_TABLE: &[$crate::AbiPlugin] = &[$($crate::plugin_entry!($kind $ty)),+];
        static CAPSULE_SLAM_PLUGIN_LIST: $crate::AbiPluginList = $crate::AbiPluginList::new(CAPSULE_SLAM_PLUGIN_TABLE);
        /// The entry point of the C ABI ([`capsule_slam_framework::abi::ENTRY_SYMBOL`]).
        #[allow(unsafe_code)]
        #[unsafe(no_mangle)]
        pub extern "C" fn capsule_slam_plugins() -> *const $crate::AbiPluginList {
            &CAPSULE_SLAM_PLUGIN_LIST
        }
    };
}

/// Writes `text` into the host's buffer (cut at its capacity) and records its full length.
///
/// # Safety
/// `out` is null or a valid [`AbiBuffer`] whose `data` holds `capacity` writable bytes.
pub(crate) unsafe fn write_text(out: *mut AbiBuffer, text: &str) {
    // SAFETY: the caller's contract.
    let Some(out) = (unsafe { out.as_mut() }) else { return };
    let n = text.len().min(out.capacity);
    if !out.data.is_null() && n > 0 {
        // SAFETY: `data` holds `capacity ≥ n` bytes and does not overlap `text`.
        unsafe { std::ptr::copy_nonoverlapping(text.as_ptr(), out.data, n) };
    }
    out.len = text.len();
}

/// Runs `f`, turning an error or a panic into its return code and message.
///
/// # Safety
/// As [`write_text`] for `out`.
pub(crate) unsafe fn guarded(out: *mut AbiBuffer, f: impl FnOnce() -> Result<(), String>) -> i32 {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(())) => OK,
        Ok(Err(message)) => {
            // SAFETY: the caller's contract.
            unsafe { write_text(out, &message) };
            ERROR
        }
        Err(panic) => {
            let what = panic.downcast_ref::<&str>().map(|s| (*s).to_owned()).or_else(|| panic.downcast_ref::<String>().cloned()).unwrap_or_default();
            // SAFETY: the caller's contract.
            unsafe { write_text(out, &format!("panicked: {what}")) };
            PANIC
        }
    }
}

/// A NUL-terminated UTF-8 string from the host.
///
/// # Safety
/// `text` is null or NUL-terminated.
pub(crate) unsafe fn host_str<'a>(text: *const c_char, what: &str) -> Result<&'a str, String> {
    if text.is_null() {
        return Err(format!("the host passed no {what}"));
    }
    // SAFETY: the caller's contract.
    unsafe { CStr::from_ptr(text) }.to_str().map_err(|e| format!("the {what} is not UTF-8: {e}"))
}

pub(crate) fn parse_table<T: LibraryPlugin>(toml_text: &str) -> Result<T::Params, Vec<capsule_slam_framework::ConfigProblem>> {
    let name = T::NAME.to_string_lossy();
    let table: toml::Table =
        toml_text.parse().map_err(|e| vec![capsule_slam_framework::ConfigProblem::new(format!("plugins.{name}"), format!("{e}"), "write a TOML table")])?;
    parse_params::<T::Params>(&name, &table)
}

pub(crate) unsafe extern "C" fn params<T: LibraryPlugin>(_input: *const c_char, out: *mut AbiBuffer) -> i32 {
    // SAFETY: the host passes a valid buffer (ABI contract).
    unsafe {
        guarded(out, || {
            let docs = ParamDocsToml {
                param: T::Params::docs()
                    .into_iter()
                    .map(|d| ParamDocToml {
                        name: d.name.to_owned(),
                        unit: d.unit.to_owned(),
                        doc: d.doc,
                        default: d.default,
                        range: d.range.map(|(lo, hi)| [lo, hi]),
                    })
                    .collect(),
            };
            let text = toml::to_string(&docs).map_err(|e| format!("parameter docs: {e}"))?;
            write_text(out, &text);
            Ok(())
        })
    }
}

pub(crate) unsafe extern "C" fn check<T: LibraryPlugin>(input: *const c_char, out: *mut AbiBuffer) -> i32 {
    // SAFETY: the host passes a NUL-terminated string and a valid buffer (ABI contract).
    unsafe {
        guarded(out, || {
            let text = host_str(input, "parameter table")?;
            if let Err(problem) = parse_table::<T>(text) {
                let text = toml::to_string(&ProblemsToml { problem }).map_err(|e| format!("problems: {e}"))?;
                write_text(out, &text);
            }
            Ok(())
        })
    }
}

pub(crate) unsafe extern "C" fn create<T: LibraryPlugin>(
    params_toml: *const c_char,
    camera: *const AbiCamera,
    state_out: *mut *mut c_void,
    message: *mut AbiBuffer,
) -> i32 {
    // SAFETY: the host passes a NUL-terminated string, a valid camera and state slot, and a
    // valid buffer (ABI contract).
    unsafe { guarded(message, || store(state_out, built::<T>(params_toml, camera)?)) }
}

/// A stage built from the host's parameter table and camera.
///
/// # Safety
/// `params_toml` is null or NUL-terminated; `camera` is null or valid.
pub(crate) unsafe fn built<T: LibraryPlugin>(params_toml: *const c_char, camera: *const AbiCamera) -> Result<T, String> {
    // SAFETY: the caller's contract.
    let text = unsafe { host_str(params_toml, "parameter table") }?;
    let params = parse_table::<T>(text).map_err(|p| p.iter().map(ToString::to_string).collect::<Vec<_>>().join("; "))?;
    // SAFETY: the caller's contract.
    let cam = camera_in(unsafe { camera.as_ref() }.ok_or("the host passed no camera")?);
    T::build(params, &cam)
}

/// Hands a stage to the host as its state.
///
/// # Safety
/// `state_out` is null or a valid slot.
pub(crate) unsafe fn store<T>(state_out: *mut *mut c_void, stage: T) -> Result<(), String> {
    // SAFETY: the caller's contract.
    let slot = unsafe { state_out.as_mut() }.ok_or("the host passed no state slot")?;
    *slot = Box::into_raw(Box::new(stage)).cast();
    Ok(())
}

/// The camera the host passed.
pub(crate) fn camera_in(c: &AbiCamera) -> PinholeCamera {
    let mut cam = PinholeCamera::new(c.width as usize, c.height as usize, c.fx, c.fy, c.cx, c.cy);
    if c.fov_radius_px > 0.0 {
        cam.fov_radius_px = Some(c.fov_radius_px);
    }
    if c.distortion.iter().any(|&k| k != 0.0) {
        cam.distortion = Some(capsule_slam_framework::lens::LensModel::brown_conrady(c.distortion));
    }
    cam
}

pub(crate) unsafe extern "C" fn destroy<T: LibraryPlugin>(state: *mut c_void) {
    if !state.is_null() {
        // SAFETY: `state` was made by `create::<T>` and is freed once (ABI contract).
        let stage = unsafe { Box::from_raw(state.cast::<T>()) };
        let _ = catch_unwind(AssertUnwindSafe(move || drop(stage)));
    }
}

/// The host's image, copied.
///
/// # Safety
/// `image` is null or points to an [`AbiImage`] whose data holds `3 · width · height` bytes.
pub(crate) unsafe fn image_in(image: *const AbiImage) -> Result<Rgb8, String> {
    // SAFETY: the caller's contract.
    let img = unsafe { image.as_ref() }.ok_or("the host passed no image")?;
    let n = 3 * img.width as usize * img.height as usize;
    if img.data.is_null() {
        return Err("the host passed an image without pixels".to_owned());
    }
    // SAFETY: the caller's contract.
    let bytes = unsafe { std::slice::from_raw_parts(img.data, n) };
    Rgb8::from_vec(img.width as usize, img.height as usize, bytes.to_vec()).map_err(|e| e.to_string())
}

unsafe extern "C" fn preprocess<T: LibraryPreprocessor>(state: *mut c_void, image: *mut AbiImage, mask: *mut u8, message: *mut AbiBuffer) -> i32 {
    // SAFETY: `state` came from `create::<T>`; the image, mask and buffer are the host's
    // valid, non-overlapping buffers of the stated sizes (ABI contract).
    unsafe {
        guarded(message, || {
            let stage = state.cast::<T>().as_mut().ok_or("the host passed no state")?;
            let mut rgb = image_in(image)?;
            let (w, h) = rgb.size();
            let mut m = Mask::new(w, h);
            stage.process(&mut rgb, &mut m)?;
            if rgb.size() != (w, h) || m.size() != (w, h) {
                return Err(format!("`{}` changed the image size", T::NAME.to_string_lossy()));
            }
            let img = &*image;
            std::ptr::copy_nonoverlapping(rgb.data().as_ptr(), img.data, 3 * w * h);
            if !mask.is_null() {
                let out = std::slice::from_raw_parts_mut(mask, w * h);
                for (o, &v) in out.iter_mut().zip(m.data()) {
                    *o = u8::from(v);
                }
            }
            Ok(())
        })
    }
}

unsafe extern "C" fn estimate_depth<T: LibraryDepthEstimator>(state: *mut c_void, image: *const AbiImage, depth_m: *mut f32, message: *mut AbiBuffer) -> i32 {
    // SAFETY: as for `preprocess`.
    unsafe {
        guarded(message, || {
            let stage = state.cast::<T>().as_mut().ok_or("the host passed no state")?;
            let rgb = image_in(image)?;
            let depth = stage.estimate(&rgb)?;
            if depth.size() != rgb.size() {
                return Err(format!("`{}` returned a {:?} depth map for a {:?} image", T::NAME.to_string_lossy(), depth.size(), rgb.size()));
            }
            if depth_m.is_null() {
                return Err("the host passed no depth buffer".to_owned());
            }
            std::ptr::copy_nonoverlapping(depth.data().as_ptr(), depth_m, depth.data().len());
            Ok(())
        })
    }
}
