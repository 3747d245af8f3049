//! Fusers: the surfel map.

pub mod surfel_cpu;
pub mod surfel_rules;
