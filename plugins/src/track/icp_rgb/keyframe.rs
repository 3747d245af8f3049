//! A keyframe as the photometric reference (`rgb_reference = "keyframe"`), as dense visual
//! odometry keeps one (DVO-SLAM, Kerl, Sturm and Cremers, IROS 2013, Sec. IV; LSD-SLAM, Engel
//! et al., ECCV 2014, Sec. 3.3): the live image is compared with the last keyframe's, not with
//! the previous frame's, until the two views drift apart.
//!
//! Compared frame to frame, every frame's relative pose carries its own error from the two
//! images' sensor noise, and the errors add up along the path: a random walk. Compared with a
//! keyframe, the frames between two keyframes share one reference, their errors do not add,
//! and the walk takes one step per keyframe instead of one per frame. The capsule's light moves
//! with its camera, which is why the photometric term does not compare with the fused model
//! (`mod.rs`); the relighting (`relight.rs`) carries the keyframe's brightness to each live
//! pose as it carries the previous frame's.
//!
//! A keyframe is replaced by the current frame when it has served `max_frames` frames, when the
//! camera has moved more than `max_translation_m` or turned more than `max_rotation_rad` from
//! it, or when the photometric term finds fewer than `min_overlap` of the pixels it found on
//! the keyframe's first frame ([`Keyframe::advance`]); after a lost frame; and where the
//! previous frame disagrees with the keyframe's solution, the frame then finished against the
//! previous frame (`register.rs`, `keyframe_max_disagreement`: on a moving wall a keyframe some
//! frames old reads the wall's motion since as the camera's). The pose between the keyframe and
//! the previous camera is kept as the chain of the tracked relative motions (not from world
//! poses, which loop closure and the non-rigid tracker may move).

use std::sync::Arc;

use capsule_slam_framework::Iso3;

use super::frames::Level;

/// When a keyframe is replaced.
#[derive(Debug, Clone, Copy)]
pub struct Policy {
    /// Frames registered to one keyframe, at most.
    pub max_frames: u32,
    /// Camera translation from the keyframe, metres.
    pub max_translation_m: f64,
    /// Camera rotation from the keyframe, radians.
    pub max_rotation_rad: f64,
    /// Share of the keyframe's first photometric pixel count below which it is replaced.
    pub min_overlap: f64,
}

/// The photometric reference of the frames since it was taken.
#[derive(Clone)]
pub struct Keyframe {
    /// Its pyramid (shared: the frame it was is also the previous frame for a while).
    pub pyramid: Arc<Vec<Level>>,
    /// Keyframe camera ← previous tracked camera.
    pub t_kf_prev: Iso3,
    /// `t_kf_prev` before the last frame moved it on (none when the last frame became the
    /// keyframe): [`Keyframe::recompose`] moves it on again by a refined motion.
    t_kf_before: Option<Iso3>,
    /// Frames registered to it so far.
    frames: u32,
    /// Photometric pixels on the first frame registered to it.
    first_rgb_n: Option<usize>,
}

impl Keyframe {
    /// A keyframe of the frame whose pyramid is `pyramid`, the previous frame from now on.
    pub fn new(pyramid: &[Level]) -> Self {
        Self { pyramid: Arc::new(pyramid.to_vec()), t_kf_prev: Iso3::identity(), t_kf_before: None, frames: 0, first_rgb_n: None }
    }

    /// After a tracked frame (pyramid `live`, relative motion `t_prev_live`, `rgb_n`
    /// photometric pixels against this keyframe): the keyframe moved on to the live camera, or
    /// the live frame as the new keyframe where `policy` says so. Returns whether it was replaced.
    pub fn advance(slot: &mut Option<Self>, live: &[Level], t_prev_live: &Iso3, rgb_n: usize, policy: &Policy) -> bool {
        let Some(kf) = slot.as_mut() else {
            *slot = Some(Self::new(live));
            return true;
        };
        let t_kf_live = kf.t_kf_prev * t_prev_live;
        kf.frames += 1;
        let first = *kf.first_rgb_n.get_or_insert(rgb_n);
        let apart = t_kf_live.translation.vector.norm() > policy.max_translation_m || t_kf_live.rotation.angle() > policy.max_rotation_rad;
        let thin = (rgb_n as f64) < policy.min_overlap * first as f64;
        if kf.frames >= policy.max_frames || apart || thin {
            *slot = Some(Self::new(live));
            return true;
        }
        kf.t_kf_before = Some(kf.t_kf_prev);
        kf.t_kf_prev = t_kf_live;
        false
    }

    /// The last frame's relative motion replaced by `t_prev_live` (a caller refined the pose).
    pub fn recompose(&mut self, t_prev_live: &Iso3) {
        if let Some(before) = self.t_kf_before {
            self.t_kf_prev = before * t_prev_live;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::PinholeCamera;
    use capsule_slam_framework::{DepthMap, GrayF32};

    use crate::track::icp_rgb::frames::{DepthPrep, pyramid};

    fn levels(value: f32) -> Vec<Level> {
        let cam = PinholeCamera::new(8, 8, 10.0, 10.0, 3.5, 3.5);
        let prep = DepthPrep { min_m: 0.001, max_m: 1.0, radius_px: 1, sigma_px: 2.0, sigma_m: 0.001, edge_jump_m: 0.01 };
        pyramid(DepthMap::filled(8, 8, 0.05), GrayF32::filled(8, 8, value), (None, None), &cam, 2, &prep)
    }

    fn step() -> Iso3 {
        Iso3::translation(0.0005, 0.0, 0.0) * Iso3::rotation(nalgebra::Vector3::new(0.0, 0.01, 0.0))
    }

    const POLICY: Policy = Policy { max_frames: 3, max_translation_m: 0.0018, max_rotation_rad: 1.0, min_overlap: 0.5 };

    #[test]
    fn the_pose_from_the_keyframe_is_the_chain_of_motions_until_a_limit_replaces_it() {
        let mut slot = None;
        assert!(Keyframe::advance(&mut slot, &levels(0.1), &Iso3::identity(), 0, &POLICY), "the first frame is a keyframe");
        let mut chain = Iso3::identity();
        for k in 1..=3 {
            let replaced = Keyframe::advance(&mut slot, &levels(0.1 * f32::from(k as u8 + 1)), &step(), 1000, &POLICY);
            chain *= step();
            let kf = slot.as_ref().expect("a keyframe");
            if k < 3 {
                assert!(!replaced, "frame {k}");
                assert!((kf.t_kf_prev.to_homogeneous() - chain.to_homogeneous()).norm() < 1e-15, "frame {k}");
                assert_eq!(kf.pyramid[0].gray.at(0, 0), 0.1, "the keyframe's own image");
            } else {
                // 1.5 mm after three steps is within 1.8 mm, but the third frame is the limit.
                assert!(replaced, "max_frames");
                assert_eq!(kf.t_kf_prev, Iso3::identity());
                assert_eq!(kf.pyramid[0].gray.at(0, 0), 0.4, "the live frame became the keyframe");
            }
        }
        let far = Iso3::translation(0.002, 0.0, 0.0);
        assert!(Keyframe::advance(&mut slot, &levels(0.5), &far, 1000, &POLICY), "2 mm > 1.8 mm");
        assert!(!Keyframe::advance(&mut slot, &levels(0.6), &step(), 1000, &POLICY));
        assert!(Keyframe::advance(&mut slot, &levels(0.7), &step(), 499, &POLICY), "fewer than half the first frame's pixels");
    }

    #[test]
    fn a_refined_motion_replaces_the_last_link_of_the_chain() {
        let mut slot = None;
        Keyframe::advance(&mut slot, &levels(0.1), &Iso3::identity(), 0, &POLICY);
        Keyframe::advance(&mut slot, &levels(0.2), &step(), 1000, &POLICY);
        Keyframe::advance(&mut slot, &levels(0.3), &step(), 1000, &POLICY);
        let refined = Iso3::translation(0.0004, 0.0001, 0.0);
        let kf = slot.as_mut().expect("a keyframe");
        kf.recompose(&refined);
        assert!((kf.t_kf_prev.to_homogeneous() - (step() * refined).to_homogeneous()).norm() < 1e-15);
        // A keyframe that the last frame started stays at the identity.
        let mut fresh = Keyframe::new(&levels(0.1));
        fresh.recompose(&refined);
        assert_eq!(fresh.t_kf_prev, Iso3::identity());
    }

    /// The adjoint of `t` on twists `[ρ; ω]`: `t exp(ξ) = exp(Ad ξ) t`.
    fn adjoint(t: &Iso3) -> nalgebra::Matrix6<f64> {
        let r = t.rotation.to_rotation_matrix().into_inner();
        let mut ad = nalgebra::Matrix6::zeros();
        ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        ad.fixed_view_mut::<3, 3>(0, 3).copy_from(&(t.translation.vector.cross_matrix() * r));
        ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
        ad
    }

    #[test]
    fn the_term_against_a_keyframe_is_the_direct_one_seen_through_the_chain() {
        // Keyframe k, previous frame p, live frame l of the phantom (relit, photometric term
        // alone): registered through p with the fixed transform k ← p, the residuals are those
        // of registering l to k directly, and the Gauss-Newton step is the direct one carried
        // by the adjoint of k ← p (an error in the row's chain rule breaks both).
        use crate::testing::{phantom, rgbd};
        use crate::track::icp_rgb::gn::{self, Inputs, Weights};
        use crate::track::icp_rgb::relight::{Lighting, Relighter};
        use crate::track::icp_rgb::{IcpRgbParams, frames};
        let ph = phantom(1, 300, 0.01);
        let [k, p, l] = [100, 106, 109].map(|i| rgbd(&ph, i));
        let pose = |f: &capsule_slam_framework::RgbdFrame| f.gt_t_world_cam.expect("ground truth");
        let (t_kf_prev, t_prev_live) = (pose(&k).inverse() * pose(&p), pose(&p).inverse() * pose(&l));
        // Off the true pose, so that the step is not zero.
        let t_prev_live = capsule_slam_framework::geometry::exp_se3(&nalgebra::Vector6::new(2e-4, -1e-4, 1e-4, 2e-3, 1e-3, -1e-3)) * t_prev_live;
        let prep = IcpRgbParams::default().depth_prep();
        let [kp, pp, lp] = [&k, &p, &l].map(|f| frames::live(f, &ph.camera, 1, &prep, None, 0));
        let lighting = Lighting::new(ph.light.clone());
        let relighter = Relighter::new(&lighting);
        let albedo = relighter.live_albedo(&lp[0], 1);
        let w = Weights {
            w_rgb: 1.0,
            sigma_icp_m: 3e-4,
            sigma_rgb: 0.02,
            huber_k: 1.345,
            icp_gate_m: 0.0,
            gate_sigmas: 0.0,
            icp_cos_gate: 1.0,
            rgb_depth_gate_m: 0.002,
            rgb_min_gradient: 0.002,
            rgb_model_depth: false,
            rgb_flow_sigma_scale: 0.0,
        };
        let inputs = |reference, t_photo_ref| Inputs {
            live: &lp[0],
            reference,
            photo: &kp[0],
            t_photo_ref,
            light: Some((&relighter, &albedo)),
            stride: 1,
            second: None,
        };
        let through = gn::accumulate(&inputs(&pp[0], Some(t_kf_prev)), &t_prev_live, &w);
        let direct = gn::accumulate(&inputs(&kp[0], None), &(t_kf_prev * t_prev_live), &w);
        assert_eq!((through.icp_n, direct.icp_n), (0, 0), "the photometric term alone");
        assert!(direct.rgb_n > 20_000, "{} pixels", direct.rgb_n);
        assert!(through.rgb_n.abs_diff(direct.rgb_n) <= direct.rgb_n / 1000, "{} against {} pixels", through.rgb_n, direct.rgb_n);
        assert!((through.rgb_sse / direct.rgb_sse - 1.0).abs() < 1e-3, "{} against {}", through.rgb_sse, direct.rgb_sse);
        let (step_through, step_direct) = (through.step().expect("a step"), direct.step().expect("a step"));
        let carried = adjoint(&t_kf_prev) * step_through;
        assert!((carried - step_direct).norm() < 1e-3 * step_direct.norm(), "{carried} against {step_direct}");
        assert!(t_kf_prev.translation.vector.norm() > 1e-3, "a keyframe {} mm back", t_kf_prev.translation.vector.norm() * 1e3);
    }
}
