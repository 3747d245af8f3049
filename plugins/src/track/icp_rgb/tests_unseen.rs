//! Where the frame sees nothing ([`MASK_OUT_OF_VIEW`]) no intensity is read, whatever its pixels
//! hold: a real sensor's black beyond the round field of view is noise, not the 0 that marks "no
//! intensity" (`frames::live`).

use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::frame::MASK_OUT_OF_VIEW;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, Iso3, Plugin, RgbdFrame, Tracker};

use super::{IcpRgb, IcpRgbParams};
use crate::testing::{phantom, rgbd, rig};

/// `f` with every colour value beyond its field of view replaced by a dark noise of 1 to 3
/// levels.
fn dark_noise_outside(f: &RgbdFrame) -> RgbdFrame {
    let mut g = f.clone();
    let unseen = f.masks.get(MASK_OUT_OF_VIEW).expect("the phantom masks its round field of view");
    let w = unseen.width();
    for (k, px) in g.colour.data_mut().chunks_exact_mut(3).enumerate() {
        if unseen.at(k % w, k / w) {
            for (c, v) in px.iter_mut().enumerate() {
                *v = 1 + ((7 * k + 3 * c) % 3) as u8;
            }
        }
    }
    g
}

#[test]
fn dark_noise_beyond_the_field_of_view_changes_neither_the_intensity_levels_nor_the_pose() {
    let ph = phantom(5, 300, 0.0);
    let rig = rig(&ph);
    let (a, b) = (rgbd(&ph, 60), rgbd(&ph, 62));
    let (noisy_a, noisy_b) = (dark_noise_outside(&a), dark_noise_outside(&b));
    assert_ne!(a.colour.data(), noisy_a.colour.data(), "the noise lands somewhere");
    let build = || IcpRgb::build(IcpRgbParams::default(), &BuildEnv::new(rig.clone(), None)).unwrap();
    let prep = build().params.depth_prep();
    let clean = super::frames::live(&b, &ph.camera, 3, &prep, None, 0);
    let noisy = super::frames::live(&noisy_b, &ph.camera, 3, &prep, None, 0);
    for (level, (c, n)) in clean.iter().zip(&noisy).enumerate() {
        let differ = c.gray.data().iter().zip(n.gray.data()).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "level {level}: {differ} intensities differ");
    }
    // Tracked against the previous frame (the photometric reference) the pose is the same.
    let track = |first: &RgbdFrame, second: &RgbdFrame| -> Iso3 {
        let mut t = build();
        let mut r = StageReport::default();
        let start = first.gt_t_world_cam.unwrap();
        t.track(first, None, &start, &mut Context::new(60, &rig, None, &mut r)).unwrap();
        t.track(second, None, &start, &mut Context::new(62, &rig, None, &mut r)).unwrap().t_world_cam
    };
    assert_eq!(track(&a, &b), track(&noisy_a, &noisy_b));
}
