//! The host side of the kernels' data layouts (`fuse.wgsl` declares the same structs, field for
//! field): surfels, measurements, predicted pixels and the uniforms. Colours travel packed in
//! one `u32`.

use bytemuck::{Pod, Zeroable};
use capsule_slam_framework::Surfel;
use nalgebra::{Point3, Vector3};

use crate::fuse::measure::PixelMeasurement;

/// A surfel as the kernels see it (64 bytes: WGSL rounds a struct with a `vec3` up to 16;
/// `Surfel` in `fuse.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuSurfel {
    pos: [f32; 3],
    conf: f32,
    nrm: [f32; 3],
    radius: f32,
    colour: u32,
    t0: u32,
    t: u32,
    albedo: f32,
    sigma: f32,
    warp: [f32; 3],
}

pub fn pack_colour(c: [u8; 3]) -> u32 {
    u32::from(c[0]) | (u32::from(c[1]) << 8) | (u32::from(c[2]) << 16)
}

pub fn unpack_colour(c: u32) -> [u8; 3] {
    [(c & 0xff) as u8, ((c >> 8) & 0xff) as u8, ((c >> 16) & 0xff) as u8]
}

impl From<&Surfel> for GpuSurfel {
    fn from(s: &Surfel) -> Self {
        Self {
            pos: s.position_m.coords.into(),
            conf: s.confidence,
            nrm: s.normal.into(),
            radius: s.radius_m,
            colour: pack_colour(s.colour),
            t0: s.t0,
            t: s.t,
            albedo: s.albedo,
            sigma: s.sigma_m,
            warp: s.warp_m.into(),
        }
    }
}

impl From<&GpuSurfel> for Surfel {
    fn from(s: &GpuSurfel) -> Self {
        Surfel {
            position_m: Point3::from(s.pos),
            normal: Vector3::from(s.nrm),
            colour: unpack_colour(s.colour),
            confidence: s.conf,
            radius_m: s.radius,
            t0: s.t0,
            t: s.t,
            albedo: s.albedo,
            sigma_m: s.sigma,
            warp_m: Vector3::from(s.warp),
        }
    }
}

/// A measurement as the kernels see it (80 bytes; `Measurement` in `fuse.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuMeasurement {
    pos: [f32; 3],
    conf: f32,
    nrm: [f32; 3],
    radius: f32,
    colour: u32,
    albedo: f32,
    pixel: u32,
    z_live: f32,
    n_cam: [f32; 3],
    lambda: f32,
    ray: [f32; 3],
    sigma: f32,
}

impl GpuMeasurement {
    /// From a measurement of an image `width` pixels wide.
    pub fn new(p: &PixelMeasurement, width: usize) -> Self {
        let m = &p.m;
        Self {
            pos: m.position_m.coords.into(),
            conf: m.confidence,
            nrm: m.normal.into(),
            radius: m.radius_m,
            colour: pack_colour(m.colour),
            albedo: m.albedo,
            pixel: (p.y * width + p.x) as u32,
            z_live: p.z_live_m,
            n_cam: p.n_cam.into(),
            lambda: p.lambda,
            ray: p.ray_unit.into(),
            sigma: m.sigma_m,
        }
    }
}

/// One predicted pixel (40 bytes; `ViewPixel` in `fuse.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct ViewPixel {
    pub depth: f32,
    pub nx: f32,
    pub ny: f32,
    pub nz: f32,
    pub colour: u32,
    pub conf: f32,
    pub t0: u32,
    pub t: u32,
    pub albedo: f32,
    pub sigma: f32,
}

/// The uniforms (176 bytes; `Params` in `fuse.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub t_cw: [[f32; 4]; 4],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    pub n_surfels: u32,
    pub n_meas: u32,
    pub now: u32,
    pub delta_t: u32,
    pub life: u32,
    pub set: u32,
    pub stable: f32,
    pub min_depth: f32,
    pub max_depth: f32,
    pub depth_gate: f32,
    pub normal_gate: f32,
    pub bypass_nz: f32,
    pub radius_ratio: f32,
    pub scan_base: u32,
    pub scan_n: u32,
    pub scan_slot: u32,
    pub add_base: u32,
    pub blend: f32,
    /// `revisit_reactivation` (0 or 1).
    pub revisit: u32,
    pub revisit_gate: f32,
    /// A revisit reactivates only surfels last seen at or after this frame.
    pub revisit_after: u32,
    pub pad: u32,
}
