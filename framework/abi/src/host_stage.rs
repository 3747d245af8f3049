//! The host side of a library's stages: each call goes through the C ABI with host-owned
//! buffers (images, masks, depth, the model's prediction), and what comes back is checked.
#![allow(unsafe_code)]

use std::ffi::c_void;

use super::{AbiBuffer, AbiImage, AbiPlugin, AbiTrackInput, AbiTrackOutput, DepthFn, OK, PreprocessFn, StereoDepthFn, TrackFn};
use std::path::PathBuf;

use capsule_slam_framework::camera::ViewKind;
use capsule_slam_framework::context::Context;
use capsule_slam_framework::error::StageError;
use capsule_slam_framework::frame::{CameraFrame, RgbdFrame, Views};
use capsule_slam_framework::geometry::Iso3;
use capsule_slam_framework::image::{DepthMap, Mask, Rgb8};
use capsule_slam_framework::map::ModelView;
use capsule_slam_framework::params::ParamDoc;
use capsule_slam_framework::registry::StageKind;
use capsule_slam_framework::stage::{DepthEstimate, DepthEstimator, Preprocessor, TrackResult, TrackStatus, Tracker};

/// A plugin loaded from a library. Lives for the whole process, as its library does.
#[derive(Debug)]
pub struct LoadedPlugin {
    /// Registry name.
    pub name: &'static str,
    /// One line on what it does.
    pub summary: &'static str,
    /// Its stage.
    pub kind: StageKind,
    /// Its parameters.
    pub params: Vec<ParamDoc>,
    /// The views it needs (a stereo depth estimator: both).
    pub views: ViewKind,
    /// The library file.
    pub library: PathBuf,
    /// The ABI version of its library.
    pub abi_version: u32,
    pub(crate) raw: AbiPlugin,
}

// SAFETY: `raw` holds pointers to the library's immutable static strings and its functions;
// the library is never unloaded, and the ABI requires its functions to be callable from any
// thread (a stage's state is used by one thread at a time: see `LibraryStage`).
unsafe impl Send for LoadedPlugin {}
// SAFETY: as above; nothing in it is ever written after loading.
unsafe impl Sync for LoadedPlugin {}

/// Size of the buffer for a stage's error message, bytes (a longer message is cut).
const MESSAGE_BYTES: usize = 4096;

/// A message buffer for one call.
pub(crate) struct Message {
    bytes: Vec<u8>,
    buf: AbiBuffer,
}

impl Message {
    pub(crate) fn new() -> Box<Self> {
        let mut m = Box::new(Self { bytes: vec![0; MESSAGE_BYTES], buf: AbiBuffer { data: std::ptr::null_mut(), capacity: MESSAGE_BYTES, len: 0 } });
        m.buf.data = m.bytes.as_mut_ptr();
        m
    }
    pub(crate) fn buffer(&mut self) -> *mut AbiBuffer {
        &mut self.buf
    }
    pub(crate) fn text(&self) -> String {
        let n = self.buf.len.min(self.buf.capacity);
        let cut = if self.buf.len > self.buf.capacity { " [...]" } else { "" };
        format!("{}{cut}", String::from_utf8_lossy(&self.bytes[..n]).trim())
    }
}

/// A stage whose code is in a library.
pub(crate) struct LibraryStage {
    pub(crate) plugin: &'static LoadedPlugin,
    pub(crate) state: *mut c_void,
}

// SAFETY: the ABI requires a state to be usable from any thread, one at a time; the pipeline
// owns the stage and calls it through `&mut self`, so never from two threads at once.
unsafe impl Send for LibraryStage {}

impl Drop for LibraryStage {
    fn drop(&mut self) {
        // SAFETY: the state came from this plugin's create and is freed once.
        unsafe { (self.plugin.raw.destroy)(self.state) };
    }
}

impl LibraryStage {
    fn preprocess_fn(&self) -> Result<PreprocessFn, StageError> {
        self.plugin.raw.preprocess.ok_or_else(|| StageError::invalid_input(format!("`{}` is not a preprocessor", self.plugin.name)))
    }
    fn depth_fn(&self) -> Result<DepthFn, StageError> {
        self.plugin.raw.estimate_depth.ok_or_else(|| StageError::invalid_input(format!("`{}` is not a depth estimator", self.plugin.name)))
    }
    fn stereo_fn(&self) -> Result<StereoDepthFn, StageError> {
        self.plugin.raw.estimate_stereo_depth.ok_or_else(|| StageError::invalid_input(format!("`{}` is not a stereo depth estimator", self.plugin.name)))
    }
    fn track_fn(&self) -> Result<TrackFn, StageError> {
        self.plugin.raw.track.ok_or_else(|| StageError::invalid_input(format!("`{}` is not a tracker", self.plugin.name)))
    }

    /// The plugin's error for `frame`.
    fn failed(&self, frame: usize, what: String) -> StageError {
        StageError::Plugin { name: self.plugin.name.to_owned(), source: format!("frame {frame}: {what}").into() }
    }

    /// The depth a library wrote, checked: finite and ≥ 0 everywhere.
    fn checked_depth(&self, frame: usize, depth: DepthMap) -> Result<DepthEstimate, StageError> {
        let w = depth.width();
        if let Some(i) = depth.data().iter().position(|d| !d.is_finite() || *d < 0.0) {
            let v = depth.data()[i];
            return Err(self.failed(frame, format!("depth {v} m at pixel ({}, {}); depth must be finite and ≥ 0 (0 = invalid)", i % w, i / w)));
        }
        Ok(DepthEstimate::depth_only(depth))
    }
}

impl Preprocessor for LibraryStage {
    fn process(&mut self, frame: &mut CameraFrame, _ctx: &mut Context) -> Result<(), StageError> {
        let f = self.preprocess_fn()?;
        let mut union: Option<Mask> = None;
        for view in frame.views.iter_mut() {
            let (w, h) = view.size();
            let mut mask = vec![0u8; w * h];
            let mut image = AbiImage { width: w as u32, height: h as u32, data: view.data_mut().as_mut_ptr() };
            let mut message = Message::new();
            // SAFETY: the library's preprocess with its own state, the view's pixels
            // (3·w·h bytes), a w·h mask and a message buffer, all alive during the call.
            let rc = unsafe { f(self.state, &mut image, mask.as_mut_ptr(), message.buffer()) };
            if rc != OK {
                return Err(self.plugin.error(rc, &message, &format!("frame {}", frame.index)));
            }
            if mask.iter().any(|&m| m != 0) {
                let m = union.get_or_insert_with(|| Mask::new(w, h));
                if m.size() == (w, h) {
                    for (o, &v) in m.data_mut().iter_mut().zip(&mask) {
                        *o |= v != 0;
                    }
                }
            }
        }
        if let Some(m) = union {
            frame.masks.insert(self.plugin.name, m);
        }
        Ok(())
    }
}

impl DepthEstimator for LibraryStage {
    /// The ABI's depth is in metres (`estimate_depth`'s contract).
    fn metric_scale(&self) -> bool {
        true
    }

    /// A stereo library plugin needs both views.
    fn input_kind(&self) -> ViewKind {
        self.plugin.views
    }

    fn estimate(&mut self, frame: &CameraFrame, _ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        if self.plugin.views == ViewKind::Stereo {
            return self.estimate_stereo(frame);
        }
        let f = self.depth_fn()?;
        let reference = frame.views.reference();
        let (w, h) = reference.size();
        // The ABI's image is mutable for preprocessors; a depth estimator gets a copy.
        let mut pixels = reference.data().to_vec();
        let image = AbiImage { width: w as u32, height: h as u32, data: pixels.as_mut_ptr() };
        let mut depth = DepthMap::new(w, h);
        let mut message = Message::new();
        // SAFETY: the library's estimate_depth with its own state, a copy of the pixels, a
        // w·h depth buffer and a message buffer, all alive during the call.
        let rc = unsafe { f(self.state, &image, depth.data_mut().as_mut_ptr(), message.buffer()) };
        if rc != OK {
            return Err(self.plugin.error(rc, &message, &format!("frame {}", frame.index)));
        }
        self.checked_depth(frame.index, depth)
    }
}

impl LibraryStage {
    /// The left view's depth from both views.
    fn estimate_stereo(&mut self, frame: &CameraFrame) -> Result<DepthEstimate, StageError> {
        let f = self.stereo_fn()?;
        let Views::Stereo { left, right } = &frame.views else {
            return Err(self.failed(frame.index, "one view: a stereo depth estimator needs rgb_right.txt and camera.toml's [right]".into()));
        };
        let copy = |img: &Rgb8| img.data().to_vec();
        let (mut l, mut r) = (copy(left), copy(right));
        let image = |img: &Rgb8, data: &mut Vec<u8>| AbiImage { width: img.width() as u32, height: img.height() as u32, data: data.as_mut_ptr() };
        let (li, ri) = (image(left, &mut l), image(right, &mut r));
        let mut depth = DepthMap::new(left.width(), left.height());
        let mut message = Message::new();
        // SAFETY: the library's estimate_stereo_depth with its own state, copies of both views,
        // a depth buffer of the left's size and a message buffer, all alive during the call.
        let rc = unsafe { f(self.state, &li, &ri, depth.data_mut().as_mut_ptr(), message.buffer()) };
        if rc != OK {
            return Err(self.plugin.error(rc, &message, &format!("frame {}", frame.index)));
        }
        self.checked_depth(frame.index, depth)
    }
}

impl Tracker for LibraryStage {
    fn track(&mut self, frame: &RgbdFrame, model: Option<&ModelView>, t_world_prev: &Iso3, _ctx: &mut Context) -> Result<TrackResult, StageError> {
        let f = self.track_fn()?;
        let (w, h) = frame.colour.size();
        let mut colour = frame.colour.data().to_vec();
        let mut model_colour = model.map(|m| m.colour.data().to_vec()).unwrap_or_default();
        let model = model.filter(|m| m.depth_m.size() == (w, h));
        let input = AbiTrackInput {
            index: frame.index as u64,
            timestamp_s: frame.timestamp_s,
            image: AbiImage { width: w as u32, height: h as u32, data: colour.as_mut_ptr() },
            depth_m: frame.depth_m.data().as_ptr(),
            has_model: u32::from(model.is_some()),
            model_depth_m: model.map_or(std::ptr::null(), |m| m.depth_m.data().as_ptr()),
            model_normals_cam: model.map_or(std::ptr::null(), |m| m.normals_cam.data().as_ptr()),
            model_colour: AbiImage { width: w as u32, height: h as u32, data: if model.is_some() { model_colour.as_mut_ptr() } else { std::ptr::null_mut() } },
            t_world_prev: super::matrix_of(t_world_prev),
        };
        let mut out = AbiTrackOutput { t_world_cam: super::matrix_of(t_world_prev), tracked: 0, inliers: 0, residual_rms: 0.0, iterations: 0 };
        let mut message = Message::new();
        // SAFETY: the library's track with its own state, an input whose buffers (the frame's
        // colour copy, its depth, the model's images) are alive and of the stated sizes during
        // the call, an output and a message buffer.
        let rc = unsafe { f(self.state, &input, &mut out, message.buffer()) };
        if rc != OK {
            return Err(self.plugin.error(rc, &message, &format!("frame {}", frame.index)));
        }
        let t_world_cam = super::pose_of(&out.t_world_cam).ok_or_else(|| {
            self.failed(frame.index, format!("the pose {:?} is not a rigid motion (finite, rotation orthonormal with determinant 1)", out.t_world_cam))
        })?;
        Ok(TrackResult {
            t_world_cam,
            status: if out.tracked == 1 { TrackStatus::Tracked } else { TrackStatus::Lost },
            inliers: out.inliers as usize,
            residual_rms: out.residual_rms,
            covariance: None,
            iterations: out.iterations as usize,
            warp: None,
        })
    }
}
