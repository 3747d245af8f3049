//! # capsule-slam framework
//!
//! The contracts of capsule-slam, a dense non-rigid RGB-D SLAM framework for endoscopic
//! capsule robots after Turan et al. (2017), "A non-rigid map fusion-based direct SLAM method
//! for endoscopic capsule robots", Int. J. Intell. Robot. Appl. 1, 399–409,
//! doi:10.1007/s41315-017-0036-4.
//!
//! This crate holds everything a stage implementation or an application needs and nothing
//! algorithmic beyond the shared maths:
//! - typed images, the camera and rig ([`image`], [`camera`]), frames ([`frame`]), poses
//!   ([`geometry`]), the surfel map types ([`map`]) and non-rigid deformations ([`deformation`]);
//! - the five stage traits ([`stage`]) and the per-stage [`context::Context`];
//! - the plugin registry ([`registry`]) with typed, validated parameters ([`params`]);
//! - the TOML configuration with `--set` overrides and whole-config validation ([`config`]);
//! - dataset input and run output ([`io`]), trajectory evaluation ([`eval`]);
//! - the pipeline that runs the stages frame by frame ([`pipeline`]).
//!
//! Units are SI (metres, seconds, radians) unless a name says otherwise; poses are named for
//! their frames: `t_world_cam` maps camera coordinates to world coordinates.

pub mod abi;
pub mod camera;
pub mod config;
pub mod context;
pub mod deformation;
pub mod error;
pub mod eval;
pub mod frame;
pub mod geometry;
pub mod image;
pub mod io;
pub mod light;
pub mod map;
pub mod params;
pub mod phantom;
pub mod pipeline;
pub mod registry;
pub mod stage;

/// Re-exported so that [`register!`] works from plugin crates without naming inventory.
pub use inventory;
/// Re-exported for the same reason, for [`plugin_params!`].
pub use toml;

pub use camera::{PinholeCamera, Rig};
pub use context::Context;
pub use error::{ConfigError, ConfigProblem, LoadError, PipelineError, RegistryError, StageError};
pub use frame::{CameraFrame, Masks, RgbdFrame, Views};
pub use geometry::Iso3;
pub use image::{DepthMap, GrayF32, Image, Mask, Rgb8};
pub use map::{MapStats, ModelSet, ModelView, Surfel, SurfelSet};
pub use registry::{Plugin, PluginEntry, Registry, StageKind};
pub use stage::{
    DepthEstimate, DepthEstimator, FuseStats, Fuser, LoopCloser, LoopClosure, LoopInput, Preprocessor, TrackResult, TrackStatus, Tracker, ViewKind,
};
