#![allow(clippy::unwrap_used, reason = "test-support crate: a failed fixture write is a failed test")]
//! Helpers of the integration tests: fixtures written by the tests themselves, and test-only
//! stages (they live here, never in `plugins/`).

pub mod fixtures;
pub mod runs;
pub mod stages;
