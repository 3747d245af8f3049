//! Test helpers shared by the plugins' unit tests: phantom frames in memory.

use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::frame::RgbdFrame;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};

/// A small phantom (NanEye size) of `frames` frames of a preset, noise-free unless asked.
pub fn phantom(preset: u8, frames: usize, noise: f64) -> Phantom {
    let spec = PhantomSpec { frames, size: SizePreset::NanEye, noise, specular: 0.0, ..PhantomSpec::preset(preset) };
    Phantom::new(spec).expect("valid phantom")
}

/// Frame `i` as the stages after depth estimation see it, with the exact depth.
pub fn rgbd(p: &Phantom, i: usize) -> RgbdFrame {
    p.render(i).to_rgbd(&p.camera)
}

/// The phantom's rig.
pub fn rig(p: &Phantom) -> Rig {
    Rig::Mono(p.camera.clone())
}
