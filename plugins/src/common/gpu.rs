//! The process's GPU (wgpu): one adapter and device, made on first use and shared by every
//! GPU stage. No GPU is an error the caller can report (`StageError::Gpu`, with the fix);
//! on a machine without one, Mesa's software Vulkan (lavapipe, Debian package
//! `mesa-vulkan-drivers`) runs every kernel on the CPU.

use std::sync::{Arc, OnceLock};

use capsule_slam_framework::StageError;

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

static GPU: OnceLock<Result<Arc<Gpu>, String>> = OnceLock::new();

/// The shared GPU, or why there is none.
pub fn gpu() -> Result<Arc<Gpu>, StageError> {
    GPU.get_or_init(|| create().map(Arc::new)).clone().map_err(|message| StageError::Gpu { message })
}

fn create() -> Result<Gpu, String> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle().with_env());
    let options = wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        force_fallback_adapter: false,
        compatible_surface: None,
        ..Default::default()
    };
    let adapter = pollster::block_on(instance.request_adapter(&options)).map_err(|e| {
        format!("no GPU adapter ({e}); install a Vulkan driver (without a GPU: Mesa's lavapipe, Debian package mesa-vulkan-drivers) or use `pipeline.fuser = \"surfel-cpu\"`")
    })?;
    let limits = adapter.limits();
    let desc = wgpu::DeviceDescriptor { label: Some("capsule-slam"), required_limits: limits.clone(), ..Default::default() };
    let (device, queue) =
        pollster::block_on(adapter.request_device(&desc)).map_err(|e| format!("the GPU adapter {} refused a device: {e}", adapter.get_info().name))?;
    Ok(Gpu { device, queue, info: adapter.get_info(), limits })
}

impl Gpu {
    /// Waits for the queue and reads `bytes` bytes of `src` (which has `COPY_SRC`) through the
    /// mappable buffer `staging` (`MAP_READ | COPY_DST`, at least `bytes` long).
    pub fn read(&self, src: &wgpu::Buffer, staging: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>, StageError> {
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read") });
        enc.copy_buffer_to_buffer(src, 0, staging, 0, bytes);
        self.queue.submit([enc.finish()]);
        let slice = staging.slice(..bytes);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| gpu_error(format!("waiting for the device: {e}")))?;
        rx.recv().map_err(|e| gpu_error(format!("mapping a buffer: {e}")))?.map_err(|e| gpu_error(format!("mapping a buffer: {e}")))?;
        let data = slice.get_mapped_range().map_err(|e| gpu_error(format!("reading a mapped buffer: {e}")))?.to_vec();
        staging.unmap();
        Ok(data)
    }
}

/// A [`StageError::Gpu`].
pub fn gpu_error(message: impl Into<String>) -> StageError {
    StageError::Gpu { message: message.into() }
}

/// For GPU tests: the GPU, or `None` after a loud message when there is none — unless
/// `CAPSULE_SLAM_REQUIRE_GPU=1`, when a missing GPU fails the test.
#[cfg(test)]
pub fn gpu_or_skip(test: &str) -> Option<Arc<Gpu>> {
    match gpu() {
        Ok(g) => Some(g),
        Err(e) => {
            assert!(std::env::var("CAPSULE_SLAM_REQUIRE_GPU").as_deref() != Ok("1"), "CAPSULE_SLAM_REQUIRE_GPU=1 and {test} found no GPU: {e}");
            eprintln!(
                "\n!!! SKIPPED {test}: no GPU adapter ({e}).\n!!! Install mesa-vulkan-drivers (lavapipe); CAPSULE_SLAM_REQUIRE_GPU=1 makes this a failure.\n"
            );
            None
        }
    }
}
