//! The plugin side of the stages ABI version 2 added: trackers ([`LibraryTracker`]; rigid, a
//! non-rigid warp stays with linked trackers) and stereo depth estimators
//! ([`LibraryStereoDepthEstimator`]). Listed in `export_plugins!` as `tracker T` and
//! `stereo_depth_estimator T`.
#![allow(unsafe_code)]

use std::ffi::{c_char, c_void};

use super::export::{LibraryPlugin, built, camera_in, check, destroy, guarded, image_in, params, store};
use super::{AbiBuffer, AbiCamera, AbiImage, AbiPlugin, AbiStereoRig, AbiTrackInput, AbiTrackOutput, KIND_STEREO_DEPTH_ESTIMATOR, KIND_TRACKER};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::Iso3;
use capsule_slam_framework::image::{DepthMap, Image, Rgb8};

/// The model's prediction a tracker is given (rendered at [`TrackInput::t_world_prev`]).
#[derive(Debug, Clone)]
pub struct ModelImages {
    /// Depth along z, metres (0: no surfel).
    pub depth_m: DepthMap,
    /// Unit normals in the camera frame.
    pub normals_cam: Image<f32, 3>,
    /// Colour.
    pub colour: Rgb8,
}

/// One frame for a library tracker.
#[derive(Debug, Clone)]
pub struct TrackInput {
    /// Frame index.
    pub index: usize,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// The frame's colour.
    pub image: Rgb8,
    /// Its depth, metres (0 = invalid).
    pub depth_m: DepthMap,
    /// The model's prediction (none before the map shows anything).
    pub model: Option<ModelImages>,
    /// The last trusted pose (camera to world).
    pub t_world_prev: Iso3,
}

/// A library tracker's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackOutput {
    /// The estimated pose (camera to world).
    pub t_world_cam: Iso3,
    /// Trusted (the frame is fused) or lost.
    pub tracked: bool,
    /// Inlier correspondences.
    pub inliers: usize,
    /// RMS residual.
    pub residual_rms: f64,
    /// Iterations run.
    pub iterations: usize,
}

/// A tracker in a library (step 4 of the paper).
pub trait LibraryTracker: LibraryPlugin {
    /// The pose of the frame.
    fn track(&mut self, input: &TrackInput) -> Result<TrackOutput, String>;
}

/// A stereo depth estimator in a library: built with the left camera
/// ([`LibraryPlugin::build`]), then given the right one.
pub trait LibraryStereoDepthEstimator: LibraryPlugin {
    /// The rig's right camera and `x_right = t_right_left · x_left`.
    fn rig(&mut self, right: &PinholeCamera, t_right_left: &Iso3) -> Result<(), String>;
    /// The left view's depth along z, metres (0 = invalid), of the left view's size.
    fn estimate(&mut self, left: &Rgb8, right: &Rgb8) -> Result<DepthMap, String>;
}

/// The table entry of a tracker.
pub const fn tracker<T: LibraryTracker>() -> AbiPlugin {
    AbiPlugin {
        name: T::NAME.as_ptr(),
        summary: T::SUMMARY.as_ptr(),
        kind: KIND_TRACKER,
        params: params::<T>,
        check: check::<T>,
        create: super::export::create::<T>,
        destroy: destroy::<T>,
        preprocess: None,
        estimate_depth: None,
        track: Some(track::<T>),
        create_stereo: None,
        estimate_stereo_depth: None,
    }
}

/// The table entry of a stereo depth estimator.
pub const fn stereo_depth_estimator<T: LibraryStereoDepthEstimator>() -> AbiPlugin {
    AbiPlugin {
        name: T::NAME.as_ptr(),
        summary: T::SUMMARY.as_ptr(),
        kind: KIND_STEREO_DEPTH_ESTIMATOR,
        params: params::<T>,
        check: check::<T>,
        create: super::export::create::<T>,
        destroy: destroy::<T>,
        preprocess: None,
        estimate_depth: None,
        track: None,
        create_stereo: Some(create_stereo::<T>),
        estimate_stereo_depth: Some(estimate_stereo_depth::<T>),
    }
}

/// A host buffer of `n` values, copied.
///
/// # Safety
/// `data` is null or points to `n` readable values.
unsafe fn copied<T: Copy>(data: *const T, n: usize, what: &str) -> Result<Vec<T>, String> {
    if data.is_null() {
        return Err(format!("the host passed no {what}"));
    }
    // SAFETY: the caller's contract.
    Ok(unsafe { std::slice::from_raw_parts(data, n) }.to_vec())
}

/// The host's tracking input, copied into owned images.
///
/// # Safety
/// `input` is null or a valid [`AbiTrackInput`] whose buffers have the sizes it states.
unsafe fn track_input(input: *const AbiTrackInput) -> Result<TrackInput, String> {
    // SAFETY: the caller's contract.
    let i = unsafe { input.as_ref() }.ok_or("the host passed no input")?;
    // SAFETY: as above.
    let image = unsafe { image_in(&i.image) }?;
    let (w, h) = image.size();
    let sized = |e: capsule_slam_framework::image::ImageSizeError| e.to_string();
    // SAFETY: as above: w·h depths, and with a model its w·h depths, 3·w·h normals, its colour.
    let depth_m = DepthMap::from_vec(w, h, unsafe { copied(i.depth_m, w * h, "depth") }?).map_err(sized)?;
    let model = if i.has_model == 1 {
        Some(ModelImages {
            depth_m: DepthMap::from_vec(w, h, unsafe { copied(i.model_depth_m, w * h, "model depth") }?).map_err(sized)?,
            normals_cam: Image::from_vec(w, h, unsafe { copied(i.model_normals_cam, 3 * w * h, "model normals") }?).map_err(sized)?,
            colour: unsafe { image_in(&i.model_colour) }?,
        })
    } else {
        None
    };
    let t_world_prev = super::pose_of(&i.t_world_prev).ok_or("the host passed a pose that is not a rigid motion")?;
    Ok(TrackInput { index: i.index as usize, timestamp_s: i.timestamp_s, image, depth_m, model, t_world_prev })
}

unsafe extern "C" fn track<T: LibraryTracker>(state: *mut c_void, input: *const AbiTrackInput, out: *mut AbiTrackOutput, message: *mut AbiBuffer) -> i32 {
    // SAFETY: `state` came from `create::<T>`; the input, output and buffer are the host's
    // valid buffers of the stated sizes (ABI contract).
    unsafe {
        guarded(message, || {
            let stage = state.cast::<T>().as_mut().ok_or("the host passed no state")?;
            let input = track_input(input)?;
            let r = stage.track(&input)?;
            let out = out.as_mut().ok_or("the host passed no output")?;
            *out = AbiTrackOutput {
                t_world_cam: super::matrix_of(&r.t_world_cam),
                tracked: u32::from(r.tracked),
                inliers: r.inliers as u64,
                residual_rms: r.residual_rms,
                iterations: r.iterations as u64,
            };
            Ok(())
        })
    }
}

unsafe extern "C" fn create_stereo<T: LibraryStereoDepthEstimator>(
    params_toml: *const c_char,
    camera: *const AbiCamera,
    rig: *const AbiStereoRig,
    state_out: *mut *mut c_void,
    message: *mut AbiBuffer,
) -> i32 {
    // SAFETY: the host passes a NUL-terminated string, valid cameras and state slot, and a
    // valid buffer (ABI contract).
    unsafe {
        guarded(message, || {
            let rig = rig.as_ref().ok_or("the host passed no stereo rig")?;
            let (r, t) = (&rig.rotation, &rig.translation_m);
            let m = [r[0], r[1], r[2], t[0], r[3], r[4], r[5], t[1], r[6], r[7], r[8], t[2], 0.0, 0.0, 0.0, 1.0];
            let t_right_left = super::pose_of(&m).ok_or("the rig's rotation is not a rotation")?;
            let mut stage = built::<T>(params_toml, camera)?;
            stage.rig(&camera_in(&rig.right), &t_right_left)?;
            store(state_out, stage)
        })
    }
}

unsafe extern "C" fn estimate_stereo_depth<T: LibraryStereoDepthEstimator>(
    state: *mut c_void,
    left: *const AbiImage,
    right: *const AbiImage,
    depth_m: *mut f32,
    message: *mut AbiBuffer,
) -> i32 {
    // SAFETY: as for `track`.
    unsafe {
        guarded(message, || {
            let stage = state.cast::<T>().as_mut().ok_or("the host passed no state")?;
            let (l, r) = (image_in(left)?, image_in(right)?);
            let depth = stage.estimate(&l, &r)?;
            if depth.size() != l.size() {
                return Err(format!("`{}` returned a {:?} depth map for a {:?} left view", T::NAME.to_string_lossy(), depth.size(), l.size()));
            }
            if depth_m.is_null() {
                return Err("the host passed no depth buffer".to_owned());
            }
            std::ptr::copy_nonoverlapping(depth.data().as_ptr(), depth_m, depth.data().len());
            Ok(())
        })
    }
}
