//! Test helpers shared by the plugins' unit tests: phantom frames in memory.

use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::frame::{MASK_OUT_OF_VIEW, Masks, RgbdFrame};
use capsule_slam_framework::phantom::{Phantom, PhantomSpec, SizePreset};

/// A small phantom (NanEye size) of `frames` frames of a preset, noise-free unless asked.
pub fn phantom(preset: u8, frames: usize, noise: f64) -> Phantom {
    let spec = PhantomSpec { frames, size: SizePreset::NanEye, noise, specular: 0.0, ..PhantomSpec::preset(preset) };
    Phantom::new(spec).expect("valid phantom")
}

/// Frame `i` as the stages after depth estimation see it, with the exact depth.
pub fn rgbd(p: &Phantom, i: usize) -> RgbdFrame {
    let f = p.render(i);
    let mut masks = Masks::new();
    let mut out = p.camera.fov_mask();
    out.data_mut().iter_mut().for_each(|v| *v = !*v);
    masks.insert(MASK_OUT_OF_VIEW, out);
    RgbdFrame {
        index: i,
        timestamp_s: f.timestamp_s,
        colour: f.rgb,
        depth_m: f.depth_m,
        depth_confidence: None,
        gt_t_world_cam: Some(f.t_world_cam),
        masks,
        derived: Default::default(),
    }
}

/// The phantom's rig.
pub fn rig(p: &Phantom) -> Rig {
    Rig::Mono(p.camera.clone())
}
