//! Calibration fits of capsule-slam, used by the `calibrate-camera`, `calibrate-light` and
//! `calibrate-vignetting` commands: the camera and its lens from checkerboard views
//! ([`board`] finds the corners, [`camera_fit`] fits Zhang's model and refines it by
//! Levenberg-Marquardt), the near-light model from frames of a matte target ([`light_fit`],
//! Levenberg-Marquardt) and the lens-and-light fall-off from flat-field frames ([`flat_field`]).

pub mod board;
pub mod camera_fit;
pub mod flat_field;
pub mod light_fit;

pub use flat_field::{centre_value, fit_flat_field};
pub use light_fit::{FitError, FitOptions, LightFit, LightSample, fit_light};
