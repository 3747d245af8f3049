//! Depth estimators.

pub mod near_light_sfs;
pub mod sensor;
pub mod stereo_sgm;
pub mod tsai_shah;
