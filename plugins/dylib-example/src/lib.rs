//! An example plugin library for capsule-slam's C ABI ([`capsule_slam_abi`]),
//! built as a `cdylib` and loaded at run time:
//!
//! ```sh
//! cargo build --release -p capsule-slam-dylib-example
//! capsule-slam --plugin-lib target/release/libcapsule_slam_dylib_example.so run \
//!     --set 'pipeline.preprocess=["example-gamma"]' --set pipeline.depth=example-inverse-square
//! ```
//!
//! `example-depth-centroid` is a tracker (ABI version 2): `--set pipeline.tracker=example-depth-centroid`.
//!
//! Copy this crate to start a plugin of your own: one file per plugin, parameters declared
//! with `plugin_params!` (validated by the host like a linked plugin's), and the list of
//! exported types in [`export_plugins!`](capsule_slam_abi::export_plugins) below.

mod depth_centroid;
mod gamma;
mod inverse_square;

pub use depth_centroid::DepthCentroid;
pub use gamma::Gamma;
pub use inverse_square::InverseSquare;

capsule_slam_abi::export_plugins!(preprocessor Gamma, depth_estimator InverseSquare, tracker DepthCentroid);
