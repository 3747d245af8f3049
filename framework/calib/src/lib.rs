//! Calibration fits of capsule-slam, used by the `calibrate-light` and `calibrate-vignetting`
//! commands: the near-light model from frames of a matte target ([`light_fit`], Levenberg-
//! Marquardt) and the lens-and-light fall-off from flat-field frames ([`flat_field`]).

pub mod flat_field;
pub mod light_fit;

pub use flat_field::{centre_value, fit_flat_field};
pub use light_fit::{FitError, FitOptions, LightFit, LightSample, fit_light};
