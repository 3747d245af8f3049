//! The ABI in one process: a Rust plugin exported through [`super::export`] and read back by
//! [`super::load`], as the host reads a library (without `dlopen`, which the CLI tests cover).

#![allow(unsafe_code)]

use std::path::Path;

use super::export::{LibraryDepthEstimator, LibraryPlugin, LibraryPreprocessor, depth_estimator, preprocessor};
use super::load::{list_of, plugins_of};
use super::*;
use capsule_slam_framework::camera::{PinholeCamera, Rig};
use capsule_slam_framework::frame::CameraFrame;
use capsule_slam_framework::image::{DepthMap, Mask, Rgb8};
use capsule_slam_framework::registry::StageKind;
use capsule_slam_framework::registry::{BuildEnv, BuildError, PluginEntry, Stage};

capsule_slam_framework::plugin_params! {
    /// Parameters of the test preprocessor.
    pub struct InvertParams {
        /// Pixels at or above this value are masked.
        pub mask_above: u32 = 250; unit = "-"; range = 0.0..=255.0;
    }
}

/// Inverts the image and masks its bright pixels.
pub(crate) struct Invert {
    mask_above: u8,
}

impl LibraryPlugin for Invert {
    const NAME: &'static std::ffi::CStr = c"test-invert";
    const SUMMARY: &'static std::ffi::CStr = c"inverts the image";
    type Params = InvertParams;
    fn build(params: InvertParams, _camera: &PinholeCamera) -> Result<Self, String> {
        Ok(Self { mask_above: params.mask_above as u8 })
    }
}

impl LibraryPreprocessor for Invert {
    fn process(&mut self, image: &mut Rgb8, mask: &mut Mask) -> Result<(), String> {
        for (i, px) in image.data_mut().chunks_exact_mut(3).enumerate() {
            if px[0] >= self.mask_above {
                mask.data_mut()[i] = true;
            }
            for c in px {
                *c = 255 - *c;
            }
        }
        Ok(())
    }
}

capsule_slam_framework::plugin_params! {
    /// Parameters of the test depth estimator.
    pub struct PlaneParams {
        /// Depth of the plane.
        pub depth_m: f64 = 0.02; unit = "m"; range = 0.0..=1.0;
    }
}

/// Depth of a fronto-parallel plane; panics on a black image, fails on a 1-pixel one.
struct Plane {
    depth_m: f32,
    width: usize,
}

impl LibraryPlugin for Plane {
    const NAME: &'static std::ffi::CStr = c"test-plane";
    const SUMMARY: &'static std::ffi::CStr = c"a plane";
    type Params = PlaneParams;
    fn build(params: PlaneParams, camera: &PinholeCamera) -> Result<Self, String> {
        if params.depth_m == 0.0 {
            return Err("depth_m = 0 is no plane".to_owned());
        }
        Ok(Self { depth_m: params.depth_m as f32, width: camera.width })
    }
}

impl LibraryDepthEstimator for Plane {
    fn estimate(&mut self, image: &Rgb8) -> Result<DepthMap, String> {
        assert!(image.data().iter().any(|&v| v > 0), "a black image");
        if image.width() != self.width {
            return Err("not the camera's width".to_owned());
        }
        let nan = image.pixel(0, 0)[0] == 1;
        Ok(DepthMap::filled(image.width(), image.height(), if nan { f32::NAN } else { self.depth_m }))
    }
}

static TABLE: &[AbiPlugin] = &[preprocessor::<Invert>(), depth_estimator::<Plane>()];
static LIST: AbiPluginList = AbiPluginList::new(TABLE);

fn entries() -> Vec<PluginEntry> {
    // SAFETY: LIST is a valid static list.
    let list = unsafe { list_of(&LIST, Path::new("in-process")) }.unwrap();
    // SAFETY: as above.
    let plugins = unsafe { plugins_of(list, Path::new("in-process")) }.unwrap();
    plugins.into_iter().map(|p| PluginEntry::foreign(&*Box::leak(Box::new(p)))).collect()
}

fn env() -> BuildEnv {
    BuildEnv::new(Rig::Mono(PinholeCamera::new(4, 2, 2.0, 2.0, 1.5, 0.5)), None)
}

/// A context for one call (its report is leaked: a few bytes per test).
fn ctx() -> capsule_slam_framework::Context<'static> {
    let rig: &'static Rig = Box::leak(Box::new(env().rig));
    capsule_slam_framework::Context::new(0, rig, None, Box::leak(Box::default()))
}

fn table(text: &str) -> toml::Table {
    text.parse().unwrap()
}

#[test]
fn plugins_come_through_with_their_names_kinds_and_parameter_docs() {
    let e = entries();
    assert_eq!(
        e.iter().map(|e| (e.name, e.kind)).collect::<Vec<_>>(),
        vec![("test-invert", StageKind::Preprocessor), ("test-plane", StageKind::DepthEstimator)]
    );
    let docs = e[1].param_docs();
    assert_eq!(docs.len(), 1);
    assert_eq!((docs[0].name, docs[0].unit, docs[0].range), ("depth_m", "m", Some((0.0, 1.0))));
    assert_eq!(docs[0].default, Some(toml::Value::Float(0.02)));
    assert_eq!(e[0].library(), Some(Path::new("in-process")));
}

#[test]
fn parameters_are_checked_on_the_plugins_side_like_a_linked_plugins() {
    let e = entries();
    assert!(e[1].check(&table("depth_m = 0.05")).is_empty());
    let p = e[1].check(&table("depth_m = 5.0\n"));
    assert_eq!(p.len(), 1);
    assert_eq!(p[0].key, "plugins.test-plane.depth_m");
    assert!(p[0].fix.contains("[0, 1]"), "{p:?}");
    let p = e[1].check(&table("depht_m = 0.05"));
    assert_eq!(p[0].key, "plugins.test-plane.depht_m");
    assert!(p[0].fix.contains("depth_m"), "{p:?}");
}

#[test]
fn a_preprocessor_changes_the_image_and_adds_its_mask() {
    let e = entries();
    let Ok(Stage::Preprocessor(mut stage)) = e[0].build(&table(""), &env()) else { panic!("not a preprocessor") };
    let img = Rgb8::from_fn(4, 2, |x, y| [(x * 60 + y) as u8, 7, 9]);
    let mut frame = CameraFrame::mono(3, 0.1, img.clone());
    stage.process(&mut frame, &mut ctx()).unwrap();
    let out = frame.views.reference();
    for (a, b) in out.data().iter().zip(img.data()) {
        assert_eq!(*a, 255 - *b);
    }
    // No pixel is ≥ 250: no mask. With mask_above = 100, x = 2 and 3 are (120, 180).
    assert!(frame.masks.union().is_none());
    let Ok(Stage::Preprocessor(mut stage)) = e[0].build(&table("mask_above = 100"), &env()) else { panic!() };
    let mut frame = CameraFrame::mono(3, 0.1, img);
    stage.process(&mut frame, &mut ctx()).unwrap();
    let m = frame.masks.union().unwrap();
    assert_eq!((0..4).map(|x| m.at(x, 0)).collect::<Vec<_>>(), vec![false, false, true, true]);
}

#[test]
fn a_depth_estimator_returns_depth_and_its_failures_are_errors_not_crashes() {
    let e = entries();
    let Ok(Stage::DepthEstimator(mut stage)) = e[1].build(&table("depth_m = 0.05"), &env()) else { panic!("not a depth estimator") };
    let frame = CameraFrame::mono(0, 0.0, Rgb8::from_fn(4, 2, |_, _| [9, 9, 9]));
    let d = stage.estimate(&frame, &mut ctx()).unwrap();
    assert!(d.depth_m.data().iter().all(|&z| z == 0.05));
    // A panic inside the plugin comes back as an error naming it.
    let black = CameraFrame::mono(5, 0.0, Rgb8::new(4, 2));
    let err = stage.estimate(&black, &mut ctx()).unwrap_err().to_string();
    assert!(err.contains("test-plane") && err.contains("frame 5") && err.contains("panicked") && err.contains("a black image"), "{err}");
    // The plugin's own error.
    let wide = CameraFrame::mono(6, 0.0, Rgb8::from_fn(5, 2, |_, _| [9, 9, 9]));
    let err = stage.estimate(&wide, &mut ctx()).unwrap_err().to_string();
    assert!(err.contains("not the camera's width"), "{err}");
    // NaN depth is refused by the host.
    let nan = CameraFrame::mono(7, 0.0, Rgb8::from_fn(4, 2, |_, _| [1, 9, 9]));
    let err = stage.estimate(&nan, &mut ctx()).unwrap_err().to_string();
    assert!(err.contains("NaN") && err.contains("(0, 0)"), "{err}");
    // A failing constructor is a build error with the plugin's reason.
    let Err(BuildError::Stage(err)) = e[1].build(&table("depth_m = 0.0"), &env()) else { panic!("built a plane at 0 m") };
    assert!(err.to_string().contains("no plane"), "{err}");
}

#[test]
fn another_abi_version_is_refused_before_anything_else_is_read() {
    // A list whose layout after the version is garbage: only the version may be read.
    #[repr(C)]
    struct Future {
        abi_version: u32,
        garbage: [u8; 4],
    }
    let future = Future { abi_version: ABI_VERSION + 1, garbage: [0xff; 4] };
    let _ = future.garbage;
    // SAFETY: the first field is a u32.
    let err = unsafe { list_of(std::ptr::from_ref(&future).cast(), Path::new("/tmp/libnew.so")) }.unwrap_err().to_string();
    assert!(err.contains("/tmp/libnew.so") && err.contains(&format!("version {}", ABI_VERSION + 1)) && err.contains("rebuild"), "{err}");
    // SAFETY: null is allowed.
    let err = unsafe { list_of(std::ptr::null(), Path::new("x.so")) }.unwrap_err().to_string();
    assert!(err.contains("no plugin list"), "{err}");
}

#[test]
fn bad_declarations_are_refused_with_the_reason() {
    let mut bad = preprocessor::<Invert>();
    bad.kind = 9;
    let table: &'static [AbiPlugin] = Box::leak(Box::new([bad]));
    let list = AbiPluginList::new(table);
    // SAFETY: a valid list.
    let err = unsafe { plugins_of(&list, Path::new("lib.so")) }.unwrap_err().to_string();
    assert!(err.contains("unknown kind 9"), "{err}");
    let mut both = preprocessor::<Invert>();
    both.estimate_depth = depth_estimator::<Plane>().estimate_depth;
    let table: &'static [AbiPlugin] = Box::leak(Box::new([both]));
    let list = AbiPluginList::new(table);
    // SAFETY: a valid list.
    let err = unsafe { plugins_of(&list, Path::new("lib.so")) }.unwrap_err().to_string();
    assert!(err.contains("not exactly its stage functions"), "{err}");
    let mut upper = preprocessor::<Invert>();
    upper.name = c"Test Invert".as_ptr();
    let table: &'static [AbiPlugin] = Box::leak(Box::new([upper]));
    let list = AbiPluginList::new(table);
    // SAFETY: a valid list.
    let err = unsafe { plugins_of(&list, Path::new("lib.so")) }.unwrap_err().to_string();
    assert!(err.contains("kebab-case"), "{err}");
}

#[test]
fn a_missing_or_foreign_file_is_a_clear_error() {
    let err = load::load(Path::new("/nonexistent/libplugin.so")).unwrap_err().to_string();
    assert!(err.contains("/nonexistent/libplugin.so") && err.contains("no such file") && err.contains("cargo build"), "{err}");
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("libjunk.so");
    std::fs::write(&junk, b"not an ELF file").unwrap();
    let err = load::load(&junk).unwrap_err().to_string();
    assert!(err.contains("libjunk.so") && err.contains("cannot be opened as a shared library"), "{err}");
}
