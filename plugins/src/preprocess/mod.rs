//! Preprocessors: the paper's steps 1–2 (reflection removal, vignetting correction).

pub mod reflection;
pub mod vignetting;
