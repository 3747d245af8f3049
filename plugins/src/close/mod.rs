//! Loop closers.

pub mod deformation;
