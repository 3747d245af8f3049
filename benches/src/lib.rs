//! Shared helpers of the criterion benchmarks (`benches/*.rs`): bench ids are registry names.

/// Keeps the plugin registrations linked into every bench binary.
pub fn link() {
    capsule_slam_plugins::link();
}
