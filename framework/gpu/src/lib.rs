//! The GPU of a capsule-slam process (wgpu): one adapter, device and queue, created by the
//! application and handed to the plugins that ask for it when they are built
//! (`BuildEnv::gpu`), never a global. A [`GpuHandle`] is cheap to clone; the device behind it
//! is made on the first request, so a run whose stages are all CPU stages never opens one.
//!
//! No GPU is an error the caller can report ([`GpuError`], with the fix); on a machine without
//! one, Mesa's software Vulkan (lavapipe, Debian package `mesa-vulkan-drivers`) runs every
//! kernel on the CPU.

use std::sync::{Arc, OnceLock};

/// Why there is no GPU, or what a GPU call reported.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct GpuError {
    /// The device's or the adapter's message, with the fix where there is one.
    pub message: String,
}

impl GpuError {
    /// An error with a message.
    pub fn new(message: impl Into<String>) -> Self {
        Self { message: message.into() }
    }
}

/// A device and its queue.
pub struct Gpu {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// What it is (name, backend, device type).
    pub info: wgpu::AdapterInfo,
    /// The limits it was created with (the adapter's own).
    pub limits: wgpu::Limits,
}

impl std::fmt::Debug for Gpu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Gpu({}, {:?})", self.info.name, self.info.backend)
    }
}

impl Gpu {
    /// Opens the best adapter wgpu finds (the `WGPU_BACKEND` variable restricts the backends)
    /// and a device with the adapter's own limits.
    pub fn open() -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle().with_env());
        let options = wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        };
        let adapter = pollster::block_on(instance.request_adapter(&options)).map_err(|e| {
            GpuError::new(format!(
                "no GPU adapter ({e}); install a Vulkan driver (without a GPU: Mesa's lavapipe, Debian package mesa-vulkan-drivers) or use `pipeline.fuser = \"surfel-cpu\"`"
            ))
        })?;
        let limits = adapter.limits();
        let desc = wgpu::DeviceDescriptor { label: Some("capsule-slam"), required_limits: limits.clone(), ..Default::default() };
        let (device, queue) = pollster::block_on(adapter.request_device(&desc))
            .map_err(|e| GpuError::new(format!("the GPU adapter {} refused a device: {e}", adapter.get_info().name)))?;
        Ok(Self { device, queue, info: adapter.get_info(), limits })
    }

    /// The device's name and backend (e.g. "llvmpipe (LLVM 15.0.6, 256 bits), Vulkan").
    pub fn name(&self) -> String {
        format!("{}, {:?}", self.info.name, self.info.backend)
    }

    /// Waits for the queue and reads `bytes` bytes of `src` (which has `COPY_SRC`) through the
    /// mappable buffer `staging` (`MAP_READ | COPY_DST`, at least `bytes` long).
    pub fn read(&self, src: &wgpu::Buffer, staging: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>, GpuError> {
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read") });
        enc.copy_buffer_to_buffer(src, 0, staging, 0, bytes);
        self.queue.submit([enc.finish()]);
        let slice = staging.slice(..bytes);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            // The receiver waits below; a send can only fail if it is gone, which ends the call.
            let _ = tx.send(r);
        });
        self.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| GpuError::new(format!("waiting for the device: {e}")))?;
        rx.recv().map_err(|e| GpuError::new(format!("mapping a buffer: {e}")))?.map_err(|e| GpuError::new(format!("mapping a buffer: {e}")))?;
        let data = slice.get_mapped_range().map_err(|e| GpuError::new(format!("reading a mapped buffer: {e}")))?.to_vec();
        staging.unmap();
        Ok(data)
    }
}

/// The application's GPU: made on the first [`GpuHandle::get`], then shared by every clone of
/// the handle (an application creates one handle and gives clones to whatever builds stages).
#[derive(Clone, Default)]
pub struct GpuHandle(Arc<OnceLock<Result<Arc<Gpu>, GpuError>>>);

impl std::fmt::Debug for GpuHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0.get() {
            None => write!(f, "GpuHandle(not opened)"),
            Some(Ok(g)) => write!(f, "GpuHandle({g:?})"),
            Some(Err(e)) => write!(f, "GpuHandle(none: {e})"),
        }
    }
}

impl GpuHandle {
    /// A handle whose device is opened on first use.
    pub fn new() -> Self {
        Self::default()
    }

    /// The device (opened now if this is the first request), or why there is none; a failure
    /// is remembered, so it is reported the same way to every stage that asks.
    pub fn get(&self) -> Result<Arc<Gpu>, GpuError> {
        self.0.get_or_init(|| Gpu::open().map(Arc::new)).clone()
    }

    /// For GPU tests and benches: the device, or `None` after a loud message when there is none,
    /// unless `CAPSULE_SLAM_REQUIRE_GPU=1`, when a missing GPU is a failure (a panic naming
    /// `what`).
    pub fn get_or_skip(&self, what: &str) -> Option<Arc<Gpu>> {
        match self.get() {
            Ok(g) => Some(g),
            Err(e) => {
                assert!(std::env::var("CAPSULE_SLAM_REQUIRE_GPU").as_deref() != Ok("1"), "CAPSULE_SLAM_REQUIRE_GPU=1 and {what} found no GPU: {e}");
                eprintln!(
                    "\n!!! SKIPPED {what}: no GPU adapter ({e}).\n!!! Install mesa-vulkan-drivers (lavapipe); CAPSULE_SLAM_REQUIRE_GPU=1 makes this a failure.\n"
                );
                None
            }
        }
    }
}
