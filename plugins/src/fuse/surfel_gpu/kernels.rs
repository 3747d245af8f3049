//! The kernels of `fuse.wgsl`: their names, the slots of the counters buffer (named on both
//! sides: the shader gets them as constants from [`shader_source`]) and their compilation,
//! once per map on the device the application gave.

use capsule_slam_gpu::Gpu;

/// Invocations per workgroup (`@workgroup_size` of every kernel in `fuse.wgsl`).
pub const WORKGROUP: u32 = 256;

/// A slot of the counters buffer, as the host reads it and `fuse.wgsl` writes it.
#[derive(Debug, Clone, Copy)]
pub enum Slot {
    /// Surfels kept by the compaction (`SLOT_KEPT`).
    Kept = 0,
    /// New surfels appended (`SLOT_ADDED`).
    Added = 1,
    /// Surfels a measurement merged into (`SLOT_MERGED`).
    Merged = 2,
    /// Active surfels after the frame (`SLOT_ACTIVE`).
    Active = 3,
    /// Stable surfels after the frame (`SLOT_STABLE`).
    Stable = 4,
}

/// Slots in the counters buffer (a few to spare).
pub const COUNTER_SLOTS: u64 = 8;

/// `fuse.wgsl` with the counter slots and the workgroup size declared from the Rust side.
pub fn shader_source() -> String {
    let slots =
        [(Slot::Kept, "SLOT_KEPT"), (Slot::Added, "SLOT_ADDED"), (Slot::Merged, "SLOT_MERGED"), (Slot::Active, "SLOT_ACTIVE"), (Slot::Stable, "SLOT_STABLE")];
    let mut src = String::from("// Declared by kernels.rs (the host's names for the counters buffer).\n");
    for (slot, name) in slots {
        src.push_str(&format!("const {name}: u32 = {}u;\n", slot as u32));
    }
    src.push_str(&format!("const WORKGROUP: u32 = {WORKGROUP}u;\n"));
    src.push_str(include_str!("fuse.wgsl"));
    src
}

/// The kernels of `fuse.wgsl`, in the order of [`KERNELS`].
#[derive(Debug, Clone, Copy)]
pub enum Kernel {
    /// `clear_z`.
    ClearZ,
    /// `index_depth`.
    IndexDepth,
    /// `index_id`.
    IndexId,
    /// `associate`.
    Associate,
    /// `merge`.
    Merge,
    /// `keep`.
    Keep,
    /// `scan_blocks`.
    ScanBlocks,
    /// `scan_sums`.
    ScanSums,
    /// `scan_add`.
    ScanAdd,
    /// `compact`.
    Compact,
    /// `append`.
    Append,
    /// `count`.
    Count,
    /// `splat_depth`.
    SplatDepth,
    /// `splat_conf`.
    SplatConf,
    /// `splat_id`.
    SplatId,
    /// `resolve`.
    Resolve,
}

/// The entry points, indexed by [`Kernel`].
const KERNELS: [&str; 16] = [
    "clear_z",
    "index_depth",
    "index_id",
    "associate",
    "merge",
    "keep",
    "scan_blocks",
    "scan_sums",
    "scan_add",
    "compact",
    "append",
    "count",
    "splat_depth",
    "splat_conf",
    "splat_id",
    "resolve",
];

/// The compiled kernels of one map.
pub struct Kernels {
    /// The bind group layout every kernel shares.
    pub layout: wgpu::BindGroupLayout,
    pipelines: Vec<wgpu::ComputePipeline>,
}

impl Kernels {
    /// The pipeline of a kernel.
    pub fn get(&self, kernel: Kernel) -> &wgpu::ComputePipeline {
        &self.pipelines[kernel as usize]
    }
}

/// Compiles every kernel of `fuse.wgsl` on `gpu`.
pub fn compile(gpu: &Gpu) -> Result<Kernels, String> {
    let d = &gpu.device;
    let scope = d.push_error_scope(wgpu::ErrorFilter::Validation);
    let module = d.create_shader_module(wgpu::ShaderModuleDescriptor { label: Some("fuse.wgsl"), source: wgpu::ShaderSource::Wgsl(shader_source().into()) });
    let storage = |binding: u32, read_only: bool| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer { ty: wgpu::BufferBindingType::Storage { read_only }, has_dynamic_offset: false, min_binding_size: None },
        count: None,
    };
    let mut entries = vec![wgpu::BindGroupLayoutEntry {
        binding: 0,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer { ty: wgpu::BufferBindingType::Uniform, has_dynamic_offset: false, min_binding_size: None },
        count: None,
    }];
    entries.extend((1..=12).map(|b| storage(b, b == 3)));
    let layout = d.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some("surfel-gpu"), entries: &entries });
    let pipeline_layout =
        d.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor { label: Some("surfel-gpu"), bind_group_layouts: &[Some(&layout)], immediate_size: 0 });
    let pipelines = KERNELS
        .iter()
        .map(|name| {
            d.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(name),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(name),
                compilation_options: Default::default(),
                cache: None,
            })
        })
        .collect();
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(format!("compiling fuse.wgsl: {e}"));
    }
    Ok(Kernels { layout, pipelines })
}
