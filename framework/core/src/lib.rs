//! # capsule-slam framework
//!
//! The contracts of capsule-slam, a dense non-rigid RGB-D SLAM framework for endoscopic
//! capsule robots after Turan et al. (2017), "A non-rigid map fusion-based direct SLAM method
//! for endoscopic capsule robots", Int. J. Intell. Robot. Appl. 1, 399–409,
//! doi:10.1007/s41315-017-0036-4.
//!
//! This crate is what a plugin author compiles against, and nothing else: the contracts and
//! the shared maths they need.
//! - typed images, the camera and rig with the views a stage needs ([`image`], [`camera`]),
//!   frames ([`frame`]), poses ([`geometry`]), the surfel map types ([`map`]) and non-rigid
//!   deformations ([`deformation`]);
//! - the capsule's light model and fall-off profiles ([`light`]) and the TOML calibration files
//!   that hold them and the camera ([`files`]);
//! - the five stage traits ([`stage`]) and the per-stage [`context::Context`];
//! - the plugin registry ([`registry`]) with typed, validated parameters ([`params`]);
//! - the TOML configuration with `--set` overrides and whole-config validation ([`config`]);
//! - the pipeline that runs the stages of one frame ([`pipeline`]), and the in-run depth
//!   score it records ([`depth_error`]).
//!
//! Dataset I/O (`capsule-slam-io`), evaluation (`capsule-slam-eval`), the runner and its output
//! folder (`capsule-slam-run`), the phantom (`capsule-slam-phantom`), shared-library plugins
//! (`capsule-slam-abi`) and the GPU handle (`capsule-slam-gpu`) are crates of their own.
//!
//! Units are SI (metres, seconds, radians) unless a name says otherwise; poses are named for
//! their frames: `t_world_cam` maps camera coordinates to world coordinates.

pub mod camera;
pub mod config;
pub mod context;
pub mod deformation;
pub mod depth_error;
pub mod depth_noise;
pub mod error;
pub mod files;
pub mod frame;
pub mod geometry;
pub mod image;
pub mod lens;
pub mod light;
pub mod map;
pub mod params;
pub mod pipeline;
pub mod registry;
pub mod stage;
pub mod stereo;

/// Re-exported so that [`register!`] works from plugin crates without naming inventory.
pub use inventory;
/// Re-exported for the same reason, for [`plugin_params!`].
pub use toml;

pub use camera::{PinholeCamera, Rig, ViewKind};
pub use context::Context;
pub use error::{ConfigError, ConfigProblem, LoadError, PipelineError, RegistryError, StageError};
pub use frame::{CameraFrame, Masks, RgbdFrame, Views};
pub use geometry::Iso3;
pub use image::{DepthMap, GrayF32, Image, Mask, Rgb8};
pub use map::{MapStats, ModelSet, ModelView, Surfel, SurfelSet};
pub use registry::{Plugin, PluginEntry, Registry, StageKind};
pub use stage::{DepthEstimate, DepthEstimator, FuseStats, Fuser, LoopCloser, LoopClosure, LoopInput, Preprocessor, TrackResult, TrackStatus, Tracker};
