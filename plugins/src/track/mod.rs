//! Trackers.

pub mod ground_truth;
