//! The right camera of a stereo rig: `camera.toml`'s `[right]` table (issue 19). The left
//! camera is the file's top level and the reference of the map; the right one has its own
//! intrinsics and lens and sits where the extrinsics put it, in OpenCV's `stereoCalibrate`
//! convention: `x_right = rotation · x_left + translation_m` (a right camera 5 mm to the right of
//! the left has `translation_m = [-0.005, 0, 0]`). Both images have the left's size.
//!
//! Every field is optional in the parse so that a table with several missing or wrong fields
//! gets one error that lists them all ([`RightCameraFile::problems`]).

pub mod rectify;

use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

use crate::error::ConfigProblem;
use crate::geometry::Iso3;
use crate::lens::DistortionSpec;

/// How far `rotation` may be from orthonormal (largest entry of `R Rᵀ − I`): calibration tools
/// write 6 or more decimals, which keeps a true rotation well within it.
pub const ROTATION_TOLERANCE: f64 = 1e-5;

/// `camera.toml`'s `[right]` table.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RightCameraFile {
    /// Focal length along x, pixels.
    pub fx: Option<f64>,
    /// Focal length along y, pixels.
    pub fy: Option<f64>,
    /// Principal point x, pixels.
    pub cx: Option<f64>,
    /// Principal point y, pixels.
    pub cy: Option<f64>,
    /// The right lens, in the forms of the left's `distortion` ([`crate::lens`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<DistortionSpec>,
    /// Radius of the right view's round field of view about (cx, cy), pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fov_radius_px: Option<f64>,
    /// Rotation from the left camera's frame to the right's, 3×3 row-major.
    pub rotation: Option<Vec<f64>>,
    /// Translation from the left camera's frame to the right's, metres.
    pub translation_m: Option<Vec<f64>>,
}

impl RightCameraFile {
    /// Every problem of the table, keys prefixed with `prefix` (e.g. `right.`).
    pub fn problems(&self, prefix: &str) -> Vec<ConfigProblem> {
        let mut out = Vec::new();
        let mut push = |key: &str, msg: String, fix: &str| out.push(ConfigProblem::new(format!("{prefix}{key}"), msg, fix));
        for (key, v, positive) in [("fx", self.fx, true), ("fy", self.fy, true), ("cx", self.cx, false), ("cy", self.cy, false)] {
            match v {
                None => push(key, format!("{key} is missing"), "give the right camera's intrinsics in pixels (fx, fy, cx, cy)"),
                Some(v) if !v.is_finite() || (positive && v <= 0.0) => {
                    push(key, format!("{key} = {v} must be {}", if positive { "a positive focal length" } else { "finite" }), "give it in pixels")
                }
                Some(_) => {}
            }
        }
        if let Some(r) = self.fov_radius_px
            && !(r.is_finite() && r > 0.0)
        {
            push("fov_radius_px", format!("fov_radius_px = {r} must be positive"), "give the radius in pixels, or remove the key");
        }
        match &self.rotation {
            None => push("rotation", "rotation is missing".into(), "give the 3×3 rotation from the left camera to the right, row-major (stereoCalibrate's R)"),
            Some(r) => {
                if let Some(why) = rotation_problem(r) {
                    push("rotation", why, "give a proper rotation (orthonormal, determinant +1), row-major, with at least 6 decimals");
                }
            }
        }
        match &self.translation_m {
            None => push("translation_m", "translation_m is missing".into(), "give the left-to-right translation in metres (stereoCalibrate's T)"),
            Some(t) if t.len() != 3 || !t.iter().all(|v| v.is_finite()) => {
                push("translation_m", format!("translation_m has {} values, or one is not finite", t.len()), "give three finite numbers in metres")
            }
            Some(t) if t.iter().all(|v| *v == 0.0) => push("translation_m", "translation_m is zero: the cameras coincide".into(), "give the baseline"),
            Some(_) => {}
        }
        if let Some(d) = &self.distortion {
            out.extend(d.problems(&format!("{prefix}distortion")));
        }
        out
    }

    /// The pose of the left camera in the right one's frame, `x_right = T · x_left` (`None` while
    /// a field is missing or wrong).
    pub fn t_right_left(&self) -> Option<Iso3> {
        let (r, t) = (self.rotation.as_ref()?, self.translation_m.as_ref()?);
        if rotation_problem(r).is_some() || t.len() != 3 {
            return None;
        }
        let rot = Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(r));
        Some(Iso3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_rotation_matrix(&rot)))
    }
}

/// Why nine numbers are not a rotation, if they are not.
fn rotation_problem(r: &[f64]) -> Option<String> {
    if r.len() != 9 || !r.iter().all(|v| v.is_finite()) {
        return Some(format!("rotation has {} values, or one is not finite: it needs 9 (3×3, row-major)", r.len()));
    }
    let m = Matrix3::from_row_slice(r);
    let off = (m * m.transpose() - Matrix3::identity()).abs().max();
    if off > ROTATION_TOLERANCE {
        return Some(format!("rotation is not orthonormal (R Rᵀ differs from I by {off:.2e}, more than {ROTATION_TOLERANCE:e})"));
    }
    let det = m.determinant();
    (det < 0.0).then(|| format!("rotation has determinant {det:.3}: a reflection, not a rotation"))
}

/// The extrinsics of a rectified pair of identical cameras `baseline_m` apart, the right one
/// along +x of the left: `x_right = x_left − [b, 0, 0]` (`camera.toml`'s `baseline_m`).
pub fn rectified_t_right_left(baseline_m: f64) -> Iso3 {
    Iso3::translation(-baseline_m, 0.0, 0.0)
}

/// The baseline of a rig's extrinsics: the distance between the two optical centres, metres
/// (the right centre in the left frame is `−Rᵀ t`, as long as `t`).
pub fn baseline_m(t_right_left: &Iso3) -> f64 {
    t_right_left.translation.vector.norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rotation_written_to_six_decimals_passes_and_a_skewed_one_does_not() {
        let r = Rotation3::from_euler_angles(0.01f64, -0.02, 0.3);
        let rounded: Vec<f64> = r.matrix().transpose().iter().map(|v: &f64| (v * 1e6).round() / 1e6).collect();
        assert_eq!(rotation_problem(&rounded), None);
        let mut skewed = rounded.clone();
        skewed[1] += 1e-3;
        assert!(rotation_problem(&skewed).is_some_and(|w| w.contains("orthonormal")));
        assert!(rotation_problem(&rounded[..8]).is_some_and(|w| w.contains("9")));
    }

    #[test]
    fn the_baseline_shorthand_puts_the_right_camera_along_plus_x() {
        let t = rectified_t_right_left(0.0055);
        assert!((baseline_m(&t) - 0.0055).abs() < 1e-15);
        let centre = t.inverse() * nalgebra::Point3::origin();
        assert!((centre.x - 0.0055).abs() < 1e-15 && centre.y == 0.0 && centre.z == 0.0);
        // A table's extrinsics read as x_right = R x_left + t.
        let file = RightCameraFile {
            rotation: Some(vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
            translation_m: Some(vec![-0.004, 0.0, 0.0]),
            ..RightCameraFile::default()
        };
        let p = nalgebra::Point3::new(0.01, 0.0, 0.05);
        assert!((file.t_right_left().unwrap() * p - nalgebra::Point3::new(0.006, 0.0, 0.05)).norm() < 1e-15);
    }
}
