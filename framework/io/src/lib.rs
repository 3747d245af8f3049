//! Dataset input: the TUM RGB-D layout or a plain image folder with its `camera.toml`
//! ([`dataset`]), images and 16-bit depth ([`images`]), PLY surfel maps ([`ply`]), TUM
//! trajectories ([`tum`]) and the undistortion of a lens's frames ([`undistort`]). Every error
//! names its file, and its line where there is one.

pub mod dataset;
pub mod images;
pub mod ply;
pub mod tum;
pub mod undistort;

pub use dataset::Dataset;
