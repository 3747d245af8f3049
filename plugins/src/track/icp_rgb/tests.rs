use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::geometry::exp_se3;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, Iso3, Plugin, TrackStatus, Tracker};
use nalgebra::Vector6;

use super::{IcpRgb, IcpRgbParams};
use crate::testing::{phantom, rgbd, rig};

fn tracker(p: IcpRgbParams, ph: &capsule_slam_phantom::Phantom) -> IcpRgb {
    IcpRgb::build(p, &BuildEnv::new(rig(ph), None)).unwrap()
}

#[test]
fn recovers_a_known_rigid_motion_between_two_rendered_frames() {
    let ph = phantom(1, 300, 0.0);
    let rig = rig(&ph);
    let (a, b) = (rgbd(&ph, 100), rgbd(&ph, 103));
    let (ta, tb) = (a.gt_t_world_cam.unwrap(), b.gt_t_world_cam.unwrap());
    let mut t = tracker(IcpRgbParams { motion_model: super::MotionModel::None, ..IcpRgbParams::default() }, &ph);
    let mut r = StageReport::default();
    let first = t.track(&a, None, &ta, &mut Context::new(100, &rig, None, &mut r)).unwrap();
    assert_eq!(first.t_world_cam, ta);
    let res = t.track(&b, None, &ta, &mut Context::new(103, &rig, None, &mut r)).unwrap();
    assert_eq!(res.status, TrackStatus::Tracked);
    let err = ta.inverse() * tb;
    let est = ta.inverse() * res.t_world_cam;
    let e = est.inverse() * err;
    assert!(err.translation.vector.norm() > 5e-4, "the motion is not trivial");
    assert!(e.translation.vector.norm() < 1e-4, "translation error {} m", e.translation.vector.norm());
    assert!(e.rotation.angle().to_degrees() < 0.05, "rotation error {}°", e.rotation.angle().to_degrees());
}

#[test]
fn a_frame_of_noise_is_lost() {
    let ph = phantom(1, 300, 0.0);
    let rig = rig(&ph);
    let a = rgbd(&ph, 50);
    let ta = a.gt_t_world_cam.unwrap();
    let mut t = tracker(IcpRgbParams::default(), &ph);
    let mut r = StageReport::default();
    t.track(&a, None, &ta, &mut Context::new(50, &rig, None, &mut r)).unwrap();
    let mut noise = rgbd(&ph, 51);
    let mut state = 12345u64;
    for (d, c) in noise.depth_m.data_mut().iter_mut().zip(noise.colour.data_mut().chunks_mut(3)) {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let u = (state >> 33) as f32 / (1u64 << 31) as f32;
        *d = 0.01 + 0.1 * u;
        c.copy_from_slice(&[(u * 255.0) as u8; 3]);
    }
    let res = t.track(&noise, None, &ta, &mut Context::new(51, &rig, None, &mut r)).unwrap();
    assert_eq!(res.status, TrackStatus::Lost);
}

#[test]
fn the_motion_prior_does_not_bias_a_static_camera() {
    let ph = phantom(1, 300, 0.0);
    let rig = rig(&ph);
    let a = rgbd(&ph, 10);
    let ta = a.gt_t_world_cam.unwrap();
    let mut t = tracker(IcpRgbParams::default(), &ph);
    let mut r = StageReport::default();
    t.track(&a, None, &ta, &mut Context::new(10, &rig, None, &mut r)).unwrap();
    // A wrong velocity: the same frame again must still come out at the same pose.
    t.velocity = Some(exp_se3(&Vector6::new(0.001, 0.0, 0.0005, 0.0, 0.01, 0.0)));
    let res = t.track(&a, None, &ta, &mut Context::new(11, &rig, None, &mut r)).unwrap();
    let e = ta.inverse() * res.t_world_cam;
    assert!(e.translation.vector.norm() < 2e-5 && e.rotation.angle() < 1e-3, "{e:?}");
    let _ = Iso3::identity();
}
