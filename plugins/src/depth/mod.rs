//! Depth estimators.

pub mod sensor;
