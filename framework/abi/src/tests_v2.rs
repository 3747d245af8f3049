//! ABI version 2 in one process: a tracker and a stereo depth estimator exported and read
//! back, and a version-1 library still loading.

#![allow(unsafe_code)]

use std::path::Path;

use super::export::{LibraryPlugin, preprocessor};
use super::export_v2::{LibraryStereoDepthEstimator, LibraryTracker, TrackInput, TrackOutput, stereo_depth_estimator, tracker};
use super::load::{list_of, plugins_of};
use super::*;
use capsule_slam_framework::camera::{PinholeCamera, Rig, ViewKind};
use capsule_slam_framework::frame::{CameraFrame, DepthSource, Masks, Photometry, RgbdFrame, Views};
use capsule_slam_framework::geometry::Iso3;
use capsule_slam_framework::image::{DepthMap, Rgb8};
use capsule_slam_framework::map::ModelView;
use capsule_slam_framework::registry::{BuildEnv, PluginEntry, Stage, StageKind};
use capsule_slam_framework::stage::TrackStatus;

capsule_slam_framework::plugin_params! {
    /// Parameters of the test tracker.
    pub struct ForwardParams {
        /// Scale of the rotation it returns (1: a rotation; else not a rigid motion).
        pub rotation_scale: f64 = 1.0; unit = "-"; range = 0.0..=10.0;
    }
}

/// Moves 1 mm along its axis per frame when it sees a model whose depth it can read; lost on
/// frame 3.
struct Forward {
    rotation_scale: f64,
}

impl LibraryPlugin for Forward {
    const NAME: &'static std::ffi::CStr = c"test-forward";
    const SUMMARY: &'static std::ffi::CStr = c"1 mm forward per frame";
    type Params = ForwardParams;
    fn build(p: ForwardParams, _camera: &PinholeCamera) -> Result<Self, String> {
        Ok(Self { rotation_scale: p.rotation_scale })
    }
}

impl LibraryTracker for Forward {
    fn track(&mut self, input: &TrackInput) -> Result<TrackOutput, String> {
        let model_depth = input.model.as_ref().map_or(0.0, |m| m.depth_m.at(0, 0));
        let mut pose = input.t_world_prev * Iso3::translation(0.0, 0.0, 0.001);
        if self.rotation_scale != 1.0 {
            pose.rotation = nalgebra::UnitQuaternion::new_unchecked(pose.rotation.into_inner() * self.rotation_scale.sqrt());
        }
        Ok(TrackOutput {
            t_world_cam: pose,
            tracked: input.index != 3,
            inliers: (1000.0 * model_depth) as usize,
            residual_rms: 0.5,
            iterations: input.depth_m.data().len(),
        })
    }
}

capsule_slam_framework::plugin_params! {
    /// Parameters of the test stereo estimator.
    pub struct DisparityParams {
        /// The disparity it assumes everywhere, pixels.
        pub disparity_px: f64 = 8.0; unit = "px"; range = 0.1..=1000.0;
    }
}

/// Depth `f b / d` for one assumed disparity, from the rig it was given.
struct Disparity {
    disparity_px: f64,
    fb: f64,
}

impl LibraryPlugin for Disparity {
    const NAME: &'static std::ffi::CStr = c"test-disparity";
    const SUMMARY: &'static std::ffi::CStr = c"one disparity";
    type Params = DisparityParams;
    fn build(p: DisparityParams, _left: &PinholeCamera) -> Result<Self, String> {
        Ok(Self { disparity_px: p.disparity_px, fb: 0.0 })
    }
}

impl LibraryStereoDepthEstimator for Disparity {
    fn rig(&mut self, right: &PinholeCamera, t_right_left: &Iso3) -> Result<(), String> {
        self.fb = right.fx * t_right_left.translation.vector.norm();
        Ok(())
    }
    fn estimate(&mut self, left: &Rgb8, right: &Rgb8) -> Result<DepthMap, String> {
        if left.size() != right.size() {
            return Err("the views differ in size".into());
        }
        Ok(DepthMap::filled(left.width(), left.height(), (self.fb / self.disparity_px) as f32))
    }
}

static TABLE: &[AbiPlugin] = &[tracker::<Forward>(), stereo_depth_estimator::<Disparity>()];
static LIST: AbiPluginList = AbiPluginList::new(TABLE);

fn entries(list: &'static AbiPluginList) -> Vec<PluginEntry> {
    // SAFETY: a valid static list.
    let list = unsafe { list_of(list, Path::new("in-process")) }.unwrap();
    // SAFETY: as above.
    let plugins = unsafe { plugins_of(list, Path::new("in-process")) }.unwrap();
    plugins.into_iter().map(|p| PluginEntry::foreign(&*Box::leak(Box::new(p)))).collect()
}

fn camera() -> PinholeCamera {
    PinholeCamera::new(4, 2, 2.0, 2.0, 1.5, 0.5)
}

fn ctx(rig: Rig) -> capsule_slam_framework::Context<'static> {
    let rig: &'static Rig = Box::leak(Box::new(rig));
    capsule_slam_framework::Context::new(0, rig, None, Box::leak(Box::default()))
}

fn rgbd(index: usize) -> RgbdFrame {
    RgbdFrame {
        depth_source: DepthSource::Measured,
        index,
        timestamp_s: 0.1 * index as f64,
        colour: Rgb8::new(4, 2),
        depth_m: DepthMap::filled(4, 2, 0.03),
        depth_confidence: None,
        depth_sigma_m: None,
        depth_sigma_correlation_px: 0.0,
        photometry: Photometry::default(),
        albedo: None,
        gt_t_world_cam: None,
        masks: Masks::new(),
        sample_share: None,
        derived: Default::default(),
    }
}

#[test]
fn a_library_tracker_gets_the_frame_and_the_model_and_returns_a_checked_pose() {
    let e = entries(&LIST);
    assert_eq!((e[0].name, e[0].kind, e[0].views), ("test-forward", StageKind::Tracker, ViewKind::Mono));
    let rig = Rig::Mono(camera());
    let env = BuildEnv::new(rig.clone(), None);
    let Ok(Stage::Tracker(mut t)) = e[0].build(&toml::Table::new(), &env) else { panic!("not a tracker") };
    let prev = Iso3::translation(0.01, 0.0, 0.0);
    let mut model = ModelView::empty(4, 2, prev);
    model.depth_m = DepthMap::filled(4, 2, 0.031);
    let r = t.track(&rgbd(1), Some(&model), &prev, &mut ctx(rig.clone())).unwrap();
    assert_eq!(r.status, TrackStatus::Tracked);
    assert!((r.t_world_cam.translation.vector - nalgebra::Vector3::new(0.01, 0.0, 0.001)).norm() < 1e-12);
    // The model's depth and the frame's size came through.
    assert_eq!((r.inliers, r.iterations, r.residual_rms), (31, 8, 0.5));
    let r = t.track(&rgbd(3), None, &prev, &mut ctx(rig.clone())).unwrap();
    assert_eq!((r.status, r.inliers), (TrackStatus::Lost, 0));
    // A pose that is not a rigid motion is an error naming the plugin, not a pose.
    let Ok(Stage::Tracker(mut bad)) = e[0].build(&"rotation_scale = 2.0".parse().unwrap(), &env) else { panic!() };
    let err = bad.track(&rgbd(1), None, &prev, &mut ctx(rig)).unwrap_err().to_string();
    assert!(err.contains("test-forward") && err.contains("not a rigid motion"), "{err}");
}

#[test]
fn a_library_stereo_estimator_needs_a_stereo_rig_and_gets_both_views() {
    let e = entries(&LIST);
    assert_eq!((e[1].name, e[1].kind, e[1].views), ("test-disparity", StageKind::DepthEstimator, ViewKind::Stereo));
    let Err(err) = e[1].build(&toml::Table::new(), &BuildEnv::new(Rig::Mono(camera()), None)) else { panic!("built on a mono rig") };
    assert!(format!("{err:?}").contains("stereo input"), "{err:?}");
    let rig = Rig::Stereo { left: camera(), right: camera(), t_right_left: Iso3::translation(-0.005, 0.0, 0.0) };
    let Ok(Stage::DepthEstimator(mut d)) = e[1].build(&toml::Table::new(), &BuildEnv::new(rig.clone(), None)) else { panic!("not a depth estimator") };
    assert_eq!(d.input_kind(), ViewKind::Stereo);
    let pair = CameraFrame { views: Views::Stereo { left: Rgb8::new(4, 2), right: Rgb8::new(4, 2) }, ..CameraFrame::mono(2, 0.0, Rgb8::new(4, 2)) };
    let depth = d.estimate(&pair, &mut ctx(rig.clone())).unwrap();
    // f b / d = 2 px · 5 mm / 8 px: the right camera and the baseline came through.
    assert!(depth.depth_m.data().iter().all(|z| (f64::from(*z) - 0.00125).abs() < 1e-9), "{:?}", depth.depth_m.data());
    let err = d.estimate(&CameraFrame::mono(4, 0.0, Rgb8::new(4, 2)), &mut ctx(rig)).unwrap_err().to_string();
    assert!(err.contains("frame 4") && err.contains("rgb_right.txt"), "{err}");
}

#[test]
fn a_version_1_library_still_loads_and_runs() {
    let p = preprocessor::<super::tests::Invert>();
    let v1 = AbiPluginV1 {
        name: p.name,
        summary: p.summary,
        kind: p.kind,
        params: p.params,
        check: p.check,
        create: p.create,
        destroy: p.destroy,
        preprocess: p.preprocess,
        estimate_depth: None,
    };
    let table: &'static [AbiPluginV1] = Box::leak(Box::new([v1]));
    let list: &'static AbiPluginList = Box::leak(Box::new(AbiPluginList::v1(table)));
    let e = entries(list);
    assert_eq!((e[0].name, e[0].kind), ("test-invert", StageKind::Preprocessor));
    let Ok(Stage::Preprocessor(mut stage)) = e[0].build(&toml::Table::new(), &BuildEnv::new(Rig::Mono(camera()), None)) else { panic!() };
    let mut frame = CameraFrame::mono(0, 0.0, Rgb8::from_fn(4, 2, |_, _| [10, 20, 30]));
    stage.process(&mut frame, &mut ctx(Rig::Mono(camera()))).unwrap();
    assert_eq!(frame.views.reference().pixel(0, 0), [245, 235, 225]);
}
