//! Depth estimators.

pub mod near_light_sfs;
pub mod sensor;
pub mod tsai_shah;
