//! Shared helpers of the criterion benchmarks (`benches/*.rs`): bench ids are registry names,
//! inputs are phantom frames rendered in memory.

use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::frame::RgbdFrame;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};

/// The app's allocator (`apps/src/main.rs`), so that a bench times what a run does. Every bench
/// binary uses this crate (the three that need nothing else from it call [`link`]), which
/// links the allocator.
#[cfg(not(target_env = "msvc"))]
#[global_allocator]
static ALLOC: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

/// Keeps the plugin registrations (and the allocator) linked into every bench binary.
pub fn link() {
    capsule_slam_plugins::link();
}

/// A noise-free phantom of preset 2 at the given size.
pub fn phantom(size: SizePreset, frames: usize) -> Phantom {
    let spec = PhantomSpec { frames, size, ..PhantomSpec::preset(2) };
    Phantom::new(spec).unwrap_or_else(|e| panic!("phantom: {e}"))
}

/// Frame `i` with exact depth, as tracking and fusion see it.
pub fn rgbd(p: &Phantom, i: usize) -> RgbdFrame {
    p.render(i).to_rgbd(&p.camera)
}

/// The phantom's rig.
pub fn rig(p: &Phantom) -> Rig {
    Rig::Mono(p.camera.clone())
}

/// Builds a registered plugin with default parameters.
pub fn build(name: &str, p: &Phantom) -> capsule_slam_framework::registry::Stage {
    build_in(name, p, None)
}

/// Builds a registered plugin with default parameters for an input folder `dir` (where it
/// finds its calibration files, e.g. the phantom's `light.toml`).
pub fn build_in(name: &str, p: &Phantom, dir: Option<&std::path::Path>) -> capsule_slam_framework::registry::Stage {
    link();
    let registry = capsule_slam_framework::Registry::from_inventory().unwrap_or_else(|e| panic!("registry: {e}"));
    let entry = registry.get(name).unwrap_or_else(|| panic!("{name} is not registered"));
    let env = capsule_slam_framework::registry::BuildEnv::new(rig(p), dir.map(std::path::Path::to_path_buf));
    entry.build(&toml::Table::new(), &env).unwrap_or_else(|e| panic!("building {name}: {e}"))
}

/// A `surfel-cpu` map fused from `frames` of `p` at their ground-truth poses.
pub fn fused_map(p: &Phantom, frames: std::ops::Range<usize>) -> Box<dyn capsule_slam_framework::Fuser> {
    fused_map_of("surfel-cpu", p, frames, &capsule_slam_gpu::GpuHandle::new()).unwrap_or_else(|e| panic!("{e}"))
}

/// A map of the fuser `name` fused from `frames` of `p` at their ground-truth poses, or why it
/// could not be built (e.g. `surfel-gpu` without a GPU adapter); a GPU fuser runs on `gpu`.
pub fn fused_map_of(
    name: &str,
    p: &Phantom,
    frames: impl IntoIterator<Item = usize>,
    gpu: &capsule_slam_gpu::GpuHandle,
) -> Result<Box<dyn capsule_slam_framework::Fuser>, String> {
    link();
    let rig = rig(p);
    let registry = capsule_slam_framework::Registry::from_inventory().map_err(|e| e.to_string())?;
    let entry = registry.get(name).ok_or_else(|| format!("{name} is not registered"))?;
    let env = capsule_slam_framework::registry::BuildEnv::new(rig.clone(), None).with_gpu(gpu.clone());
    let capsule_slam_framework::registry::Stage::Fuser(mut fuser) = entry.build(&toml::Table::new(), &env).map_err(|e| format!("building {name}: {e}"))? else {
        return Err(format!("{name} is not a fuser"));
    };
    let mut r = capsule_slam_framework::context::StageReport::default();
    for i in frames {
        let f = rgbd(p, i);
        let pose = f.gt_t_world_cam.unwrap_or_default();
        fuser.fuse(&f, &pose, &mut capsule_slam_framework::Context::new(i, &rig, None, &mut r)).map_err(|e| e.to_string())?;
    }
    Ok(fuser)
}
