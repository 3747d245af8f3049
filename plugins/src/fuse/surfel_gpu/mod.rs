//! `surfel-gpu`: the surfel map on the GPU (wgpu compute shaders, `fuse.wgsl`). The same map
//! as `surfel-cpu`, rule for rule (`surfel_rules.rs`), with the map kept on the device:
//! association against an index map, confidence-weighted merging, new surfels appended in
//! pixel order, stale unstable surfels removed by an order-preserving compaction (prefix
//! sums), and the splatted prediction, all as kernels; what leaves the device per frame is a
//! handful of counts and, per prediction, the predicted images. A loop closure's deformation
//! is applied on the host (the graph's influences use a k-d tree): the map is read, warped
//! with the framework's `Deformation::warper` and written back, as a closure is rare.
//!
//! Takes the same parameters as `surfel-cpu` (`[plugins.surfel-gpu]`, same keys, same
//! defaults). Both resolve every z-test by (depth, index), so both are deterministic; they
//! differ only by the last bits of f32 arithmetic (the GPU rotates with a matrix, the CPU
//! with a quaternion), which can flip an association that sits exactly on a gate.

mod device;
mod kernels;
mod layout;

use capsule_slam_framework::deformation::Deformation;
use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::frame::RgbdFrame;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stage::{FuseStats, LoopClosure};
use capsule_slam_framework::{Context, Fuser, Iso3, MapStats, ModelSet, ModelView, Plugin, StageError, Surfel, SurfelSet, register};
use rayon::prelude::*;

use super::measure::measurements;
use super::surfel_params::SurfelParams;
use super::surfel_rules::{raise_sigma, reactivate};
use super::window::ActiveWindow;
use device::{DeviceMap, Phase, gpu_error};
use layout::GpuMeasurement;

/// The GPU surfel map.
pub struct SurfelGpu {
    params: SurfelParams,
    map: DeviceMap,
    now: u32,
    stats: MapStats,
    window: ActiveWindow,
}

impl Plugin for SurfelGpu {
    const NAME: &'static str = "surfel-gpu";
    const SUMMARY: &'static str =
        "surfel map on the GPU (wgpu compute): the rules of surfel-cpu as kernels, the map kept on the device; same parameters as surfel-cpu";
    type Params = SurfelParams;

    fn build(params: SurfelParams, env: &BuildEnv) -> Result<Self, StageError> {
        Self::with_capacity(params, env, None)
    }
}

impl SurfelGpu {
    /// A map that starts with room for `cap` surfels (`None`: 4 a pixel; it grows by doubling).
    fn with_capacity(params: SurfelParams, env: &BuildEnv, cap: Option<u32>) -> Result<Self, StageError> {
        crate::common::ordered("min_depth_m", f64::from(params.min_depth_m), "max_depth_m", f64::from(params.max_depth_m))?;
        let gpu = env.gpu.get().map_err(|e| gpu_error(e.message))?;
        let cam = env.rig.camera();
        let cap = cap.unwrap_or_else(|| (4 * cam.width * cam.height).max(1024) as u32);
        let map = DeviceMap::with_capacity(gpu, cam.width, cam.height, cap)?;
        Ok(Self { params, map, now: 0, stats: MapStats::default(), window: ActiveWindow::default() })
    }

    /// The device's name and backend (e.g. "llvmpipe (LLVM 15.0.6, 256 bits), Vulkan").
    pub fn device_name(&self) -> String {
        self.map.gpu().name()
    }

    /// Warps the map on the host (download, `d`, then `then`, upload) and recounts it: a
    /// deformation's influences need a k-d tree, and a warp is one pass over the map. With
    /// `motion` (a tracker's warp) the displacement is added to each surfel's `warp_m`.
    fn rewrite(&mut self, d: &Deformation, motion: bool, then: impl FnOnce(&mut [Surfel])) -> Result<(), StageError> {
        let mut surfels = self.map.download()?;
        let warper = d.warper();
        if motion {
            surfels.par_iter_mut().for_each(|s| warper.warp_surfel_as_motion(s));
        } else {
            surfels.par_iter_mut().for_each(|s| warper.warp_surfel(s));
        }
        then(&mut surfels);
        self.map.upload(&surfels)?;
        let (stable, dt) = (self.params.stable_confidence, self.window.frames(self.now, &self.params));
        self.stats = MapStats {
            total: surfels.len(),
            active: surfels.iter().filter(|s| s.is_active(self.now, dt)).count(),
            stable: surfels.iter().filter(|s| s.confidence >= stable).count(),
        };
        Ok(())
    }

    fn phase(&self, t_world_cam: &Iso3, now: u32, set: ModelSet) -> Phase {
        Phase { t_cam_world: t_world_cam.inverse(), now, set, params: self.params.clone(), window: self.window }
    }
}

impl Fuser for SurfelGpu {
    fn fuse(&mut self, frame: &RgbdFrame, t_world_cam: &Iso3, ctx: &mut Context) -> Result<FuseStats, StageError> {
        self.now = frame.index as u32;
        let cam = ctx.rig.camera();
        if (cam.width, cam.height) != self.map.size() {
            return Err(StageError::invalid_input(format!("the camera is {}×{}, the map was made for {:?}", cam.width, cam.height, self.map.size())));
        }
        let measured = measurements(frame, t_world_cam, cam, &self.params, ctx);
        let gm: Vec<GpuMeasurement> = measured.iter().map(|m| GpuMeasurement::new(m, cam.width)).collect();
        let clock = std::time::Instant::now();
        let phase = self.phase(t_world_cam, self.now, ModelSet::Active);
        let c = self.map.fuse(&phase, cam, &gm)?;
        ctx.count("ms_gpu_fuse", clock.elapsed().as_secs_f64() * 1e3);
        self.stats = MapStats { total: c.total as usize, active: c.active as usize, stable: c.stable as usize };
        let removed = (self.map.len_before() as usize + c.added as usize).saturating_sub(c.total as usize);
        ctx.count("surfels_merged", f64::from(c.merged));
        ctx.count("surfels_added", f64::from(c.added));
        ctx.count("surfels_removed", removed as f64);
        Ok(FuseStats { merged: c.merged as usize, added: c.added as usize, removed })
    }

    fn predict(&mut self, t_world_cam: &Iso3, set: ModelSet, ctx: &mut Context) -> Result<ModelView, StageError> {
        let now = (ctx.frame_index as u32).max(self.now);
        let clock = std::time::Instant::now();
        let phase = self.phase(t_world_cam, now, set);
        let view = self.map.predict(&phase, ctx.rig.camera(), t_world_cam)?;
        ctx.count("ms_gpu_predict", clock.elapsed().as_secs_f64() * 1e3);
        Ok(view)
    }

    fn deform(&mut self, closure: &LoopClosure, ctx: &mut Context) -> Result<(), StageError> {
        let clock = std::time::Instant::now();
        let now = (ctx.frame_index as u32).max(self.now);
        let mut reactivated = 0;
        let params = self.window.params_at(now, &self.params);
        self.rewrite(&closure.deformation, false, |surfels| reactivated = reactivate(surfels, &closure.t_world_cam, ctx.rig.camera(), now, &params))?;
        ctx.count("ms_deform", clock.elapsed().as_secs_f64() * 1e3);
        ctx.count("surfels_reactivated", reactivated as f64);
        Ok(())
    }

    fn warp(&mut self, deformation: &Deformation, ctx: &mut Context) -> Result<(), StageError> {
        let clock = std::time::Instant::now();
        self.window.warped(ctx.frame_index as u32);
        self.rewrite(deformation, true, |_| {})?;
        ctx.count("ms_warp", clock.elapsed().as_secs_f64() * 1e3);
        Ok(())
    }

    /// On a copy of the map brought back from the device and uploaded again, as `rewrite`
    /// does: once a run.
    fn raise_sigma(&mut self, noise: &DepthNoiseModel, t_world_cam: &Iso3, ctx: &mut Context) -> Result<(), StageError> {
        let t_cam_world = t_world_cam.inverse();
        let mut surfels = self.map.download()?;
        surfels.par_iter_mut().for_each(|s| raise_sigma(s, noise, &t_cam_world));
        self.map.upload(&surfels)?;
        ctx.count("surfels_sigma_raised", surfels.len() as f64);
        Ok(())
    }

    fn stats(&self) -> MapStats {
        self.stats
    }

    fn snapshot(&self) -> Result<SurfelSet, StageError> {
        Ok(SurfelSet::new(self.map.download()?))
    }

    fn active_window(&self) -> Option<u32> {
        Some(self.window.frames(self.now, &self.params))
    }

    fn stable_confidence(&self) -> Option<f32> {
        Some(self.params.stable_confidence)
    }
}

register!(Fuser, SurfelGpu);

#[cfg(test)]
mod tests;
