//! The loop closer on phantom surfaces: an old (inactive) copy of the wall and a drifted new
//! (active) copy of it, both splatted at the current pose.

use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::frame::Masks;
use capsule_slam_framework::map::{MapStats, ModelSet, ModelView, Surfel, SurfelSet};
use capsule_slam_framework::phantom::{Phantom, PhantomSpec, SizePreset};
use capsule_slam_framework::stage::{FuseStats, LoopClosure, LoopInput};
use capsule_slam_framework::{Context, Fuser, Iso3, LoopCloser, RgbdFrame, StageError};
use nalgebra::{Translation3, UnitQuaternion, Vector3};

use super::{DeformationCloser, DeformationParams};
use crate::fuse::surfel_cpu::predict;

/// Time of the new surfels (the old ones have t0 = 0).
const NEW: u32 = 1000;

/// A map that is only a surfel set (the closer reads it through `snapshot`).
struct Fixed(SurfelSet);

impl Fuser for Fixed {
    fn fuse(&mut self, _: &RgbdFrame, _: &Iso3, _: &mut Context) -> Result<FuseStats, StageError> {
        Err(StageError::invalid_input("fixed map"))
    }
    fn predict(&mut self, _: &Iso3, _: ModelSet, _: &mut Context) -> Result<ModelView, StageError> {
        Err(StageError::invalid_input("fixed map"))
    }
    fn deform(&mut self, _: &LoopClosure, _: &mut Context) -> Result<(), StageError> {
        Err(StageError::invalid_input("fixed map"))
    }
    fn stats(&self) -> MapStats {
        MapStats::default()
    }
    fn snapshot(&self) -> Result<SurfelSet, StageError> {
        Ok(self.0.clone())
    }
}

struct Scene {
    phantom: Phantom,
    pose: Iso3,
    old: Vec<Surfel>,
}

fn scene() -> Scene {
    let phantom = Phantom::new(PhantomSpec { frames: 300, size: SizePreset::NanEye, ..PhantomSpec::preset(2) }).unwrap();
    let pose = phantom.pose(150);
    let mut old = phantom.surface(phantom.time_s(150), 3.0e-4).surfels;
    for s in &mut old {
        s.radius_m = 4.5e-4;
        s.confidence = 20.0;
    }
    Scene { phantom, pose, old }
}

/// `surfels` moved by `motion` (world frame) and stamped new.
fn moved(surfels: &[Surfel], motion: &Iso3) -> Vec<Surfel> {
    let m = motion.cast::<f32>();
    surfels.iter().map(|s| Surfel { position_m: m * s.position_m, normal: m.rotation * s.normal, t0: NEW, t: NEW, ..*s }).collect()
}

fn close(sc: &Scene, new: &[Surfel], params: DeformationParams) -> (Option<LoopClosure>, StageReport) {
    let cam = &sc.phantom.camera;
    let active = predict(new, |_| true, cam, &sc.pose, 0.001, 0.2);
    let inactive = predict(&sc.old, |_| true, cam, &sc.pose, 0.001, 0.2);
    let map = Fixed(SurfelSet::new([sc.old.clone(), new.to_vec()].concat()));
    let rig = Rig::Mono(cam.clone());
    let frame = sc.phantom.render(150).to_rgbd(cam);
    let frame = RgbdFrame { index: (NEW + 5) as usize, masks: Masks::new(), ..frame };
    let mut report = StageReport::default();
    let input = LoopInput { frame: &frame, t_world_cam: &sc.pose, active: &active, inactive: &inactive };
    let out = DeformationCloser::new(params).close(&input, &map, &mut Context::new(frame.index, &rig, None, &mut report)).unwrap();
    (out, report)
}

/// A drift of 1.2 mm and 0.6° about a point in front of the camera.
fn drift(sc: &Scene) -> Iso3 {
    let centre = sc.pose * nalgebra::Point3::new(0.0, 0.0, 0.03);
    let rot = UnitQuaternion::from_euler_angles(0.006, -0.004, 0.003);
    let to = Iso3::from_parts(Translation3::from(centre.coords), UnitQuaternion::identity());
    Iso3::from_parts(Translation3::new(0.0008, -0.0006, 0.0007), UnitQuaternion::identity())
        * to
        * Iso3::from_parts(Translation3::identity(), rot)
        * to.inverse()
}

#[test]
fn a_drifted_revisit_is_closed_and_bends_the_new_surface_onto_the_old() {
    let sc = scene();
    let d = drift(&sc);
    let new = moved(&sc.old, &d);
    let (closure, report) = close(&sc, &new, DeformationParams::default());
    let closure = closure.unwrap_or_else(|| panic!("rejected: {report:?}"));
    // The corrected pose undoes the drift: T_est = D⁻¹ T.
    let expected = d.inverse() * sc.pose;
    let pose_err = (closure.t_world_cam.translation.vector - expected.translation.vector).norm();
    assert!(pose_err < 2e-4, "pose error {pose_err} m; {report:?}");
    let def = &closure.deformation;
    // In view of the camera, new surfels land on the old ones and the old ones stay.
    let cam = &sc.phantom.camera;
    let t_cam_world = sc.pose.inverse();
    let seen = |s: &Surfel| {
        let p = t_cam_world * s.position_m.cast::<f64>();
        p.z > 0.005 && cam.project(&p).is_some_and(|uv| cam.in_fov(uv.x, uv.y))
    };
    let (mut new_err, mut old_err, mut before, mut n) = (0.0, 0.0, 0.0, 0);
    for (o, m) in sc.old.iter().zip(&new).filter(|(o, _)| seen(o)).step_by(7) {
        let (po, pm) = (o.position_m.cast::<f64>(), m.position_m.cast::<f64>());
        new_err += (def.warp_point(&pm, NEW) - po).norm();
        old_err += (def.warp_point(&po, 0) - po).norm();
        before += (pm - po).norm();
        let nn = def.warp_normal(&pm, &m.normal.cast(), NEW);
        assert!((nn.norm() - 1.0).abs() < 1e-9);
        n += 1;
    }
    let (new_err, old_err, before) = (new_err / n as f64, old_err / n as f64, before / n as f64);
    assert!(n > 1000, "{n} surfels in view");
    assert!(new_err < 0.25 * before, "new surface: {new_err} m from the old after, {before} m before");
    assert!(old_err < 1e-4, "the old surface moved by {old_err} m");
    // The camera moves with the new surface.
    let warped = def.warp_pose(&sc.pose, NEW + 5);
    assert!((warped.translation.vector - expected.translation.vector).norm() < 0.5 * (sc.pose.translation.vector - expected.translation.vector).norm());
}

#[test]
fn a_false_closure_between_two_places_that_look_alike_is_rejected() {
    // The "new" surface is the wall seen 8 mm further along and turned by 25°: tissue of the
    // same kind, placed in front of the camera where the old wall is.
    let sc = scene();
    let elsewhere = sc.phantom.pose(190);
    let swap = sc.pose * elsewhere.inverse();
    let rot = Iso3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.45));
    let new = moved(&sc.old, &(sc.pose * rot * sc.pose.inverse() * swap));
    let (closure, report) = close(&sc, &new, DeformationParams::default());
    assert!(closure.is_none(), "a false closure was accepted: {report:?}");
    let r = &report.counters;
    assert!(r.get("overlap").is_some_and(|o| *o > 0.2), "the views overlap, so the checks ran: {r:?}");
    assert_eq!(r.get("rejected"), Some(&1.0), "{r:?}");
}

#[test]
fn an_aligned_revisit_needs_no_closure() {
    let sc = scene();
    let new = moved(&sc.old, &Iso3::identity());
    let (closure, report) = close(&sc, &new, DeformationParams::default());
    assert!(closure.is_none(), "{report:?}");
}
