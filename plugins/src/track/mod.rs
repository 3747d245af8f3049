//! Trackers.

pub mod ground_truth;
pub mod icp_rgb;
pub mod nonrigid;
