//! Fusers: the surfel map.

pub mod measure;
pub mod surfel_cpu;
#[cfg(feature = "gpu")]
pub mod surfel_gpu;
pub mod surfel_params;
pub mod surfel_rules;
pub mod window;
