//! # capsule-slam plugins
//!
//! The stage implementations, each in its own file and registered with inventory by a
//! `register!` line at its end. Binaries and tests call [`link`] so that the linker keeps this
//! crate (and its registrations).

pub mod close;
pub mod common;
pub mod depth;
pub mod fuse;
pub mod preprocess;
pub mod track;

#[cfg(test)]
pub(crate) mod testing;

/// Forces the linker to keep this crate's inventory registrations. Call it once from every
/// binary or test that builds a registry.
pub fn link() {}
