//! The map on the device: its buffers (made once, grown by doubling), the dispatch of the
//! kernels of one fuse or one prediction, and the read-back of counts, predictions and the map.

use std::sync::Arc;

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::{Iso3, ModelSet, ModelView, StageError, Surfel};
use capsule_slam_gpu::Gpu;

use super::kernels::{COUNTER_SLOTS, Kernel, Kernels, Slot, WORKGROUP, compile};
use super::layout::{GpuMeasurement, GpuSurfel, Uniforms, ViewPixel, unpack_colour};
use crate::fuse::surfel_params::SurfelParams;
use crate::fuse::window::ActiveWindow;

/// A [`StageError::Gpu`].
pub fn gpu_error(message: impl Into<String>) -> StageError {
    StageError::Gpu { message: message.into() }
}

/// What one call works with: the pose, the time, the model set, the parameters.
pub struct Phase {
    /// Camera from world.
    pub t_cam_world: Iso3,
    /// The current frame.
    pub now: u32,
    /// Active or inactive model (prediction).
    pub set: ModelSet,
    /// The fuser's parameters.
    pub params: SurfelParams,
    /// The map's last warp: the active window at `now` and which surfels a revisit revives.
    pub window: ActiveWindow,
}

/// The counts a fuse reads back.
#[derive(Debug, Clone, Copy, Default)]
pub struct Counts {
    /// Surfels after the frame.
    pub total: u32,
    /// New surfels.
    pub added: u32,
    /// Surfels updated.
    pub merged: u32,
    /// Active surfels after the frame.
    pub active: u32,
    /// Stable surfels after the frame.
    pub stable: u32,
}

const SURFEL_BYTES: u64 = std::mem::size_of::<GpuSurfel>() as u64;
const MEAS_BYTES: u64 = std::mem::size_of::<GpuMeasurement>() as u64;
const VIEW_BYTES: u64 = std::mem::size_of::<ViewPixel>() as u64;

/// Buffers sized by the surfel capacity.
struct Sized {
    cap: u32,
    surf: [wgpu::Buffer; 2],
    winner: wgpu::Buffer,
    /// Scan buffers: bound in `binds`, held here with them.
    _scan: [wgpu::Buffer; 3],
    binds: [wgpu::BindGroup; 2],
}

/// The map on the device.
pub struct DeviceMap {
    gpu: Arc<Gpu>,
    kernels: Arc<Kernels>,
    width: usize,
    height: usize,
    uniforms: wgpu::Buffer,
    meas: wgpu::Buffer,
    zdepth: wgpu::Buffer,
    zid: wgpu::Buffer,
    zconf: wgpu::Buffer,
    counters: wgpu::Buffer,
    view: wgpu::Buffer,
    staging_counters: wgpu::Buffer,
    staging_view: wgpu::Buffer,
    sized: Sized,
    /// Which of the two surfel buffers holds the map.
    cur: usize,
    n: u32,
    n_before: u32,
}

fn buffer(gpu: &Gpu, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
    gpu.device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size: size.max(16), usage, mapped_at_creation: false })
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE.union(wgpu::BufferUsages::COPY_DST).union(wgpu::BufferUsages::COPY_SRC);
const STAGING: wgpu::BufferUsages = wgpu::BufferUsages::MAP_READ.union(wgpu::BufferUsages::COPY_DST);

impl DeviceMap {
    /// An empty map for a `width × height` camera with room for `cap` surfels at first (it
    /// grows by doubling).
    pub fn with_capacity(gpu: Arc<Gpu>, width: usize, height: usize, cap: u32) -> Result<Self, StageError> {
        let kernels = Arc::new(compile(&gpu).map_err(gpu_error)?);
        let px = (width * height) as u64;
        let uniforms = buffer(&gpu, "uniforms", std::mem::size_of::<Uniforms>() as u64, wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST);
        let meas = buffer(&gpu, "measurements", px * MEAS_BYTES, STORAGE);
        let zdepth = buffer(&gpu, "zdepth", px * 4, STORAGE);
        let zid = buffer(&gpu, "zid", px * 4, STORAGE);
        let zconf = buffer(&gpu, "zconf", px * 4, STORAGE);
        let counters = buffer(&gpu, "counters", COUNTER_SLOTS * 4, STORAGE);
        let view = buffer(&gpu, "view", px * VIEW_BYTES, STORAGE);
        let staging_counters = buffer(&gpu, "staging counters", COUNTER_SLOTS * 4, STAGING);
        let staging_view = buffer(&gpu, "staging view", px * VIEW_BYTES, STAGING);
        let cap = cap.max(1);
        Ok(Self {
            sized: Self::sized(&gpu, &kernels, cap, px as u32, [&uniforms, &meas, &zdepth, &zid, &counters, &view, &zconf])?,
            gpu,
            kernels,
            width,
            height,
            uniforms,
            meas,
            zdepth,
            zid,
            zconf,
            counters,
            view,
            staging_counters,
            staging_view,
            cur: 0,
            n: 0,
            n_before: 0,
        })
    }

    fn sized(gpu: &Gpu, kernels: &Kernels, cap: u32, pixels: u32, fixed: [&wgpu::Buffer; 7]) -> Result<Sized, StageError> {
        let bytes = u64::from(cap) * SURFEL_BYTES;
        if bytes > gpu.limits.max_storage_buffer_binding_size {
            return Err(gpu_error(format!(
                "the map needs {cap} surfels ({} MiB), more than this device binds in one buffer ({} MiB); use surfel-cpu or a shorter sequence",
                bytes >> 20,
                gpu.limits.max_storage_buffer_binding_size >> 20
            )));
        }
        let surf = [buffer(gpu, "surfels 0", bytes, STORAGE), buffer(gpu, "surfels 1", bytes, STORAGE)];
        let winner = buffer(gpu, "winner", u64::from(cap) * 4, STORAGE);
        let flag_len = u64::from(cap) + u64::from(pixels);
        let flags = buffer(gpu, "flags", flag_len * 4, STORAGE);
        let offsets = buffer(gpu, "offsets", flag_len * 4, STORAGE);
        let blocks = buffer(gpu, "blocks", flag_len.div_ceil(u64::from(WORKGROUP)) * 4, STORAGE);
        let [uniforms, meas, zdepth, zid, counters, view, zconf] = fixed;
        let bind = |a: &wgpu::Buffer, b: &wgpu::Buffer| {
            let res = [uniforms, a, b, meas, zdepth, zid, &winner, &flags, &offsets, &blocks, counters, view, zconf];
            let entries: Vec<wgpu::BindGroupEntry> =
                res.iter().enumerate().map(|(i, buf)| wgpu::BindGroupEntry { binding: i as u32, resource: buf.as_entire_binding() }).collect();
            gpu.device.create_bind_group(&wgpu::BindGroupDescriptor { label: Some("surfel-gpu"), layout: &kernels.layout, entries: &entries })
        };
        let binds = [bind(&surf[0], &surf[1]), bind(&surf[1], &surf[0])];
        Ok(Sized { cap, surf, winner, _scan: [flags, offsets, blocks], binds })
    }

    /// The device.
    pub fn gpu(&self) -> &Gpu {
        &self.gpu
    }

    /// The camera size it was made for.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Surfels before the last fuse.
    pub fn len_before(&self) -> u32 {
        self.n_before
    }

    /// Makes room for `needed` surfels, keeping the map.
    fn reserve(&mut self, needed: u32) -> Result<(), StageError> {
        if needed <= self.sized.cap {
            return Ok(());
        }
        let cap = needed.max(self.sized.cap.saturating_mul(2));
        let fixed = [&self.uniforms, &self.meas, &self.zdepth, &self.zid, &self.counters, &self.view, &self.zconf];
        let sized = Self::sized(&self.gpu, &self.kernels, cap, (self.width * self.height) as u32, fixed)?;
        let mut enc = self.gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("grow") });
        enc.copy_buffer_to_buffer(&self.sized.surf[self.cur], 0, &sized.surf[0], 0, u64::from(self.n) * SURFEL_BYTES);
        self.gpu.queue.submit([enc.finish()]);
        self.sized = sized;
        self.cur = 0;
        Ok(())
    }

    fn uniforms(&self, phase: &Phase, cam: &PinholeCamera) -> Uniforms {
        let p = &phase.params;
        let m = phase.t_cam_world.cast::<f32>().to_homogeneous();
        let mut t_cw = [[0f32; 4]; 4];
        for (c, col) in t_cw.iter_mut().enumerate() {
            for (r, v) in col.iter_mut().enumerate() {
                *v = m[(r, c)];
            }
        }
        Uniforms {
            t_cw,
            fx: cam.fx as f32,
            fy: cam.fy as f32,
            cx: cam.cx as f32,
            cy: cam.cy as f32,
            width: cam.width as u32,
            height: cam.height as u32,
            n_surfels: self.n,
            n_meas: 0,
            now: phase.now,
            delta_t: phase.window.frames(phase.now, p),
            life: p.unstable_lifetime,
            set: u32::from(phase.set != ModelSet::Active),
            stable: p.stable_confidence,
            min_depth: p.min_depth_m,
            max_depth: p.max_depth_m,
            depth_gate: p.depth_gate_m,
            normal_gate: p.normal_gate_rad,
            bypass_nz: p.normal_bypass_nz,
            radius_ratio: p.radius_ratio,
            scan_base: 0,
            scan_n: 0,
            scan_slot: 0,
            add_base: self.sized.cap,
            blend: p.splat_blend_depth_m,
            revisit: u32::from(p.revisit_reactivation),
            revisit_gate: p.revisit_gate_m,
            revisit_after: phase.window.revisit_after(),
            pad: 0,
        }
    }

    fn dispatch(&self, pass: &mut wgpu::ComputePass<'_>, kernel: Kernel, threads: u64) -> Result<(), StageError> {
        let groups = threads.div_ceil(u64::from(WORKGROUP));
        if groups == 0 {
            return Ok(());
        }
        let limit = self.gpu.limits.max_compute_workgroups_per_dimension;
        let groups = u32::try_from(groups).ok().filter(|g| *g <= limit).ok_or_else(|| {
            gpu_error(format!(
                "{kernel:?} needs {groups} workgroups of {WORKGROUP}, more than this device dispatches at once ({limit}); use surfel-cpu or a smaller map"
            ))
        })?;
        pass.set_pipeline(self.kernels.get(kernel));
        pass.set_bind_group(0, &self.sized.binds[self.cur], &[]);
        pass.dispatch_workgroups(groups, 1, 1);
        Ok(())
    }

    fn scan(&self, pass: &mut wgpu::ComputePass<'_>, n: u64) -> Result<(), StageError> {
        self.dispatch(pass, Kernel::ScanBlocks, n)?;
        self.dispatch(pass, Kernel::ScanSums, 1)?;
        self.dispatch(pass, Kernel::ScanAdd, n)
    }

    /// Fuses one frame's measurements (in pixel order) at `phase`.
    pub fn fuse(&mut self, phase: &Phase, cam: &PinholeCamera, meas: &[GpuMeasurement]) -> Result<Counts, StageError> {
        let n_meas = meas.len() as u32;
        if meas.len() > self.width * self.height {
            return Err(gpu_error("more measurements than pixels"));
        }
        self.reserve(self.n.saturating_add(n_meas))?;
        self.n_before = self.n;
        let q = &self.gpu.queue;
        q.write_buffer(&self.meas, 0, bytemuck::cast_slice(meas));
        let px = (self.width * self.height) as u64;
        let n = u64::from(self.n);
        // 1: index map, association, merge, keep flags and the order-preserving compaction.
        let mut u = self.uniforms(phase, cam);
        u.n_meas = n_meas;
        u.scan_base = 0;
        u.scan_n = self.n;
        u.scan_slot = 0;
        q.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        let mut enc = self.gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("fuse 1") });
        enc.clear_buffer(&self.counters, 0, None);
        enc.clear_buffer(&self.sized.winner, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("fuse 1"), timestamp_writes: None });
            self.dispatch(&mut pass, Kernel::ClearZ, px)?;
            self.dispatch(&mut pass, Kernel::IndexDepth, n)?;
            self.dispatch(&mut pass, Kernel::IndexId, n)?;
            self.dispatch(&mut pass, Kernel::Associate, u64::from(n_meas))?;
            self.dispatch(&mut pass, Kernel::Merge, n)?;
            self.dispatch(&mut pass, Kernel::Keep, n)?;
            self.scan(&mut pass, n)?;
            self.dispatch(&mut pass, Kernel::Compact, n)?;
        }
        q.submit([enc.finish()]);
        // 2: the new surfels after the kept ones, and the counts.
        u.scan_base = self.sized.cap;
        u.scan_n = n_meas;
        u.scan_slot = 1;
        q.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        let mut enc = self.gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("fuse 2") });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("fuse 2"), timestamp_writes: None });
            self.scan(&mut pass, u64::from(n_meas))?;
            self.dispatch(&mut pass, Kernel::Append, u64::from(n_meas))?;
            self.dispatch(&mut pass, Kernel::Count, n + u64::from(n_meas))?;
        }
        q.submit([enc.finish()]);
        let raw = self.gpu.read(&self.counters, &self.staging_counters, COUNTER_SLOTS * 4).map_err(|e| gpu_error(e.message))?;
        let c: Vec<u32> = bytemuck::pod_collect_to_vec(&raw);
        let at = |slot: Slot| c[slot as usize];
        let counts = Counts {
            total: at(Slot::Kept) + at(Slot::Added),
            added: at(Slot::Added),
            merged: at(Slot::Merged),
            active: at(Slot::Active),
            stable: at(Slot::Stable),
        };
        self.n = counts.total;
        self.cur = 1 - self.cur;
        Ok(counts)
    }

    /// The splatted prediction of the active or inactive stable model.
    pub fn predict(&mut self, phase: &Phase, cam: &PinholeCamera, t_world_cam: &Iso3) -> Result<ModelView, StageError> {
        let (w, h) = (cam.width, cam.height);
        if (w, h) != (self.width, self.height) {
            return Err(StageError::invalid_input(format!("the camera is {w}×{h}, the map was made for {}×{}", self.width, self.height)));
        }
        let u = self.uniforms(phase, cam);
        self.gpu.queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        let px = (w * h) as u64;
        let mut enc = self.gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("predict") });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("predict"), timestamp_writes: None });
            self.dispatch(&mut pass, Kernel::ClearZ, px)?;
            self.dispatch(&mut pass, Kernel::SplatDepth, u64::from(self.n))?;
            self.dispatch(&mut pass, Kernel::SplatConf, u64::from(self.n))?;
            self.dispatch(&mut pass, Kernel::SplatId, u64::from(self.n))?;
            self.dispatch(&mut pass, Kernel::Resolve, px)?;
        }
        self.gpu.queue.submit([enc.finish()]);
        let raw = self.gpu.read(&self.view, &self.staging_view, px * VIEW_BYTES).map_err(|e| gpu_error(e.message))?;
        let pixels: Vec<ViewPixel> = bytemuck::pod_collect_to_vec(&raw);
        let mut view = ModelView::empty(w, h, *t_world_cam);
        for (k, p) in pixels.iter().enumerate() {
            if p.depth <= 0.0 {
                continue;
            }
            let (x, y) = (k % w, k / w);
            *view.depth_m.at_mut(x, y) = p.depth;
            view.normals_cam.set_pixel(x, y, [p.nx, p.ny, p.nz]);
            view.colour.set_pixel(x, y, unpack_colour(p.colour));
            *view.confidence.at_mut(x, y) = p.conf;
            *view.t0.at_mut(x, y) = p.t0;
            *view.t.at_mut(x, y) = p.t;
            *view.albedo.at_mut(x, y) = p.albedo;
            *view.sigma_m.at_mut(x, y) = p.sigma;
        }
        Ok(view)
    }

    /// The whole map, in order.
    pub fn download(&self) -> Result<Vec<Surfel>, StageError> {
        // A download is rare (a snapshot, a closure): its staging buffer is made for it rather
        // than held at the map's capacity.
        let bytes = u64::from(self.n) * SURFEL_BYTES;
        let staging = buffer(&self.gpu, "staging surfels", bytes, STAGING);
        let raw = self.gpu.read(&self.sized.surf[self.cur], &staging, bytes).map_err(|e| gpu_error(e.message))?;
        let g: Vec<GpuSurfel> = bytemuck::pod_collect_to_vec(&raw);
        Ok(g.iter().map(Surfel::from).collect())
    }

    /// Replaces the map.
    pub fn upload(&mut self, surfels: &[Surfel]) -> Result<(), StageError> {
        let n = u32::try_from(surfels.len()).map_err(|_| gpu_error("too many surfels"))?;
        self.reserve(n)?;
        let g: Vec<GpuSurfel> = surfels.iter().map(GpuSurfel::from).collect();
        self.gpu.queue.write_buffer(&self.sized.surf[self.cur], 0, bytemuck::cast_slice(&g));
        self.n = n;
        Ok(())
    }
}
