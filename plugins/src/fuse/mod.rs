//! Fusers: the surfel map.

pub mod measure;
pub mod surfel_cpu;
pub mod surfel_gpu;
pub mod surfel_rules;
