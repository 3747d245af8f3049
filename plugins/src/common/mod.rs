//! Pure helpers shared by several plugins: vertex and normal maps from depth, edge-preserving
//! depth smoothing, intensity images and image pyramids. Stages never call each other; they
//! call these functions.

pub mod ed_graph;
pub mod maps;
pub mod masks;
pub mod pyramid;
pub mod sparse_llt;

use capsule_slam_framework::StageError;

/// Checks that parameter `lo_name` lies below `hi_name` (e.g. a depth range), with a message
/// naming both.
pub fn ordered(lo_name: &str, lo: f64, hi_name: &str, hi: f64) -> Result<(), StageError> {
    if lo < hi { Ok(()) } else { Err(StageError::invalid_input(format!("{lo_name} ({lo}) must be below {hi_name} ({hi})"))) }
}
