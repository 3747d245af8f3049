//! Pure helpers shared by several plugins: vertex and normal maps from depth, edge-preserving
//! depth smoothing, intensity images and image pyramids. Stages never call each other; they
//! call these functions.

pub mod maps;
pub mod pyramid;
