//! Pinhole camera with an optional lens model ([`crate::lens`]) and a round field-of-view mask, and
//! the rig (mono or stereo). Pixel centres are at integer coordinates; x right, y down,
//! z forward (the optical axis).

use nalgebra::{Point2, Point3};
use serde::{Deserialize, Serialize};

use crate::error::ConfigProblem;
use crate::geometry::Iso3;
use crate::image::Mask;
use crate::lens::{DistortionSpec, LensModel};
use crate::stereo::RightCameraFile;

/// The intrinsics file of an input folder, `camera.toml`; the `[camera]` config section has the
/// same schema. Other tools write it, so its keys are fixed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraFile {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Depth PNG units per metre (TUM: 5000).
    #[serde(default = "default_depth_scale")]
    pub depth_scale: f64,
    /// The lens model: `[k1, k2, p1, p2, k3]` (radial-tangential, OpenCV's order) or
    /// `{ model = "radial-tangential" | "equidistant", coefficients = [...] }` ([`crate::lens`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<DistortionSpec>,
    /// Radius of the round field of view about (cx, cy), pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fov_radius_px: Option<f64>,
    /// Stereo baseline in metres (right camera at +x); absent for a mono capsule.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baseline_m: Option<f64>,
    /// The depth's noise model, if the sensor's is known (without it `sensor` gives no σ, and
    /// the trackers' own noise floors stand alone).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_noise: Option<crate::depth_noise::DepthNoiseModel>,
    /// The right camera of a calibrated stereo rig (`[right]`, [`crate::stereo`]); this file's
    /// top level is then the left camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub right: Option<RightCameraFile>,
}

fn default_depth_scale() -> f64 {
    5000.0
}

impl CameraFile {
    /// Checks every field and returns every problem, keys prefixed with `prefix`.
    pub fn problems(&self, prefix: &str) -> Vec<ConfigProblem> {
        let mut out = Vec::new();
        let mut check = |key: &str, ok: bool, msg: String, fix: &str| {
            if !ok {
                out.push(ConfigProblem::new(format!("{prefix}{key}"), msg, fix));
            }
        };
        check("width", self.width > 0, "width is 0".into(), "give the image width in pixels");
        check("height", self.height > 0, "height is 0".into(), "give the image height in pixels");
        for (key, v) in [("fx", self.fx), ("fy", self.fy)] {
            check(key, v.is_finite() && v > 0.0, format!("{key} = {v} must be a positive focal length"), "give the focal length in pixels");
        }
        for (key, v) in [("cx", self.cx), ("cy", self.cy)] {
            check(key, v.is_finite(), format!("{key} = {v} is not finite"), "give the principal point in pixels");
        }
        check(
            "depth_scale",
            self.depth_scale.is_finite() && self.depth_scale > 0.0,
            format!("depth_scale = {} must be positive", self.depth_scale),
            "give depth PNG units per metre (TUM: 5000)",
        );
        if let Some(r) = self.fov_radius_px {
            check(
                "fov_radius_px",
                r.is_finite() && r > 0.0,
                format!("fov_radius_px = {r} must be positive"),
                "give the field-of-view radius in pixels, or remove the key",
            );
        }
        if let Some(b) = self.baseline_m {
            check(
                "baseline_m",
                b.is_finite() && b > 0.0,
                format!("baseline_m = {b} must be positive"),
                "give the stereo baseline in metres, or remove the key for a mono rig",
            );
        }
        if let Some(d) = &self.distortion {
            out.extend(d.problems(&format!("{prefix}distortion")));
        }
        if let Some(n) = &self.depth_noise {
            out.extend(n.problems(&format!("{prefix}depth_noise.")));
        }
        if let Some(r) = &self.right {
            out.extend(r.problems(&format!("{prefix}right.")));
            if self.baseline_m.is_some() {
                out.push(ConfigProblem::new(
                    format!("{prefix}baseline_m"),
                    "both baseline_m and a [right] table describe the stereo rig",
                    "keep [right] (a calibrated rig) or baseline_m (two identical rectified cameras), not both",
                ));
            }
        }
        out
    }

    /// The camera described by this file (call [`CameraFile::problems`] first).
    pub fn camera(&self) -> PinholeCamera {
        lens_camera((self.width as usize, self.height as usize), [self.fx, self.fy, self.cx, self.cy], self.distortion.as_ref(), self.fov_radius_px)
    }

    /// The rig: stereo with a `[right]` table (its own intrinsics, lens and extrinsics) or a
    /// `baseline_m` (two identical cameras, the right along +x), mono otherwise. A `[right]`
    /// table with a problem gives a mono rig: call [`CameraFile::problems`] first.
    pub fn rig(&self) -> Rig {
        let camera = self.camera();
        let right = self.right.as_ref().and_then(|r| Some((right_camera(r, camera.width, camera.height)?, r.t_right_left()?)));
        match (right, self.baseline_m) {
            (Some((right, t_right_left)), _) => Rig::Stereo { left: camera, right, t_right_left },
            (None, Some(b)) => Rig::Stereo { right: camera.clone(), left: camera, t_right_left: crate::stereo::rectified_t_right_left(b) },
            (None, None) => Rig::Mono(camera),
        }
    }
}

/// The right camera of a `[right]` table, with the left's image size (`None` while a field is
/// missing or wrong: [`CameraFile::problems`] says which).
fn right_camera(r: &RightCameraFile, width: usize, height: usize) -> Option<PinholeCamera> {
    Some(lens_camera((width, height), [r.fx?, r.fy?, r.cx?, r.cy?], r.distortion.as_ref(), r.fov_radius_px))
}

/// A camera of `camera.toml`: its size, `[fx, fy, cx, cy]`, its lens (none when the model is
/// the identity) and its field of view.
fn lens_camera(size: (usize, usize), k: [f64; 4], distortion: Option<&DistortionSpec>, fov_radius_px: Option<f64>) -> PinholeCamera {
    let mut c = PinholeCamera::new(size.0, size.1, k[0], k[1], k[2], k[3]);
    c.distortion = distortion.and_then(DistortionSpec::model).filter(|d| !d.is_identity());
    c.fov_radius_px = fov_radius_px;
    c
}

/// A pinhole camera, with the lens in front of it. The stages see undistorted images: an input
/// folder whose `camera.toml` names a lens is undistorted as it is read (`capsule-slam-io`), and
/// the rig the stages are built with has no `distortion`; the phantom renderer models it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PinholeCamera {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Lens distortion, if any.
    pub distortion: Option<LensModel>,
    /// Radius of the round field of view about (cx, cy), pixels.
    pub fov_radius_px: Option<f64>,
    /// The radius that vignetting's `r` is a share of, pixels: the half-diagonal of the camera
    /// `light.toml` was calibrated with. `None`: this camera's own
    /// ([`PinholeCamera::half_diagonal_px`]); set where the frames are undistorted onto a larger
    /// canvas than the file's (`input.undistorted_view = "whole"`), so that V stays a function
    /// of the ray.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vignetting_radius_px: Option<f64>,
}

impl PinholeCamera {
    /// An undistorted camera with the full rectangle as field of view.
    pub fn new(width: usize, height: usize, fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { width, height, fx, fy, cx, cy, distortion: None, fov_radius_px: None, vignetting_radius_px: None }
    }

    /// Projects a camera-frame point with the pinhole model (no distortion); `None` behind the
    /// camera.
    pub fn project(&self, p_cam: &Point3<f64>) -> Option<Point2<f64>> {
        (p_cam.z > 0.0).then(|| Point2::new(self.fx * p_cam.x / p_cam.z + self.cx, self.fy * p_cam.y / p_cam.z + self.cy))
    }

    /// Projects a camera-frame point through the lens (with distortion when present).
    pub fn project_distorted(&self, p_cam: &Point3<f64>) -> Option<Point2<f64>> {
        if p_cam.z <= 0.0 {
            return None;
        }
        let (mut x, mut y) = (p_cam.x / p_cam.z, p_cam.y / p_cam.z);
        if let Some(d) = &self.distortion {
            (x, y) = d.distort(x, y);
        }
        Some(Point2::new(self.fx * x + self.cx, self.fy * y + self.cy))
    }

    /// Where a pinhole camera with these intrinsics sees the ray of pixel `(u, v)` of this one
    /// (the pixel itself without a lens); `None` beyond the lens's fold, where no ray lands.
    pub fn pinhole_pixel(&self, u: f64, v: f64) -> Option<Point2<f64>> {
        let Some(d) = &self.distortion else { return Some(Point2::new(u, v)) };
        let (x, y) = d.undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)?;
        Some(Point2::new(self.fx * x + self.cx, self.fy * y + self.cy))
    }

    /// Back-projects pixel `(u, v)` at depth `depth_m` (z, metres): `p = K⁻¹ [u v 1]ᵀ d`
    /// (the paper's back-projection, Sec. 3.3).
    pub fn unproject(&self, u: f64, v: f64, depth_m: f64) -> Point3<f64> {
        Point3::new((u - self.cx) / self.fx * depth_m, (v - self.cy) / self.fy * depth_m, depth_m)
    }

    /// Whether pixel `(u, v)` lies in the image and inside the round field of view.
    pub fn in_fov(&self, u: f64, v: f64) -> bool {
        let inside = u > -0.5 && v > -0.5 && u < self.width as f64 - 0.5 && v < self.height as f64 - 0.5;
        inside
            && self.fov_radius_px.is_none_or(|r| {
                let (du, dv) = (u - self.cx, v - self.cy);
                du * du + dv * dv <= r * r
            })
    }

    /// The field-of-view mask: `true` inside the round field of view.
    pub fn fov_mask(&self) -> Mask {
        Mask::from_fn(self.width, self.height, |x, y| [self.in_fov(x as f64, y as f64)])
    }

    /// Half the image diagonal, pixels: the radius normaliser of vignetting and of
    /// ElasticFusion's confidence (which hard-codes 400 px for 640×480).
    pub fn half_diagonal_px(&self) -> f64 {
        0.5 * ((self.width * self.width + self.height * self.height) as f64).sqrt()
    }

    /// The radius vignetting's `r` is a share of, pixels: [`PinholeCamera::vignetting_radius_px`]
    /// or, without one, the half-diagonal.
    pub fn vignetting_radius(&self) -> f64 {
        self.vignetting_radius_px.unwrap_or_else(|| self.half_diagonal_px())
    }

    /// The camera of a pyramid level downsampled by `2^level` (fx/2^l, cx/2^l as in
    /// ElasticFusion's pyramid; sizes rounded down).
    pub fn pyramid_level(&self, level: u32) -> Self {
        let s = f64::from(1u32 << level);
        Self {
            width: self.width >> level,
            height: self.height >> level,
            fx: self.fx / s,
            fy: self.fy / s,
            cx: self.cx / s,
            cy: self.cy / s,
            distortion: self.distortion,
            fov_radius_px: self.fov_radius_px.map(|r| r / s),
            vignetting_radius_px: self.vignetting_radius_px.map(|r| r / s),
        }
    }
}

/// Which views a depth estimator needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ViewKind {
    /// One image.
    Mono,
    /// A rectified stereo pair.
    Stereo,
}

/// The capsule's cameras.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[expect(clippy::large_enum_variant, reason = "one rig per run, built once: boxing a camera would buy nothing")]
pub enum Rig {
    /// One camera.
    Mono(PinholeCamera),
    /// A stereo pair; `left` is the reference camera of the map.
    Stereo {
        /// Reference camera.
        left: PinholeCamera,
        /// Second camera.
        right: PinholeCamera,
        /// The left camera's frame in the right's: `x_right = t_right_left · x_left`
        /// (OpenCV's `stereoCalibrate` R and T).
        t_right_left: Iso3,
    },
}

impl Rig {
    /// The reference camera (the only one for mono; the left for stereo).
    pub fn camera(&self) -> &PinholeCamera {
        match self {
            Rig::Mono(c) => c,
            Rig::Stereo { left, .. } => left,
        }
    }

    /// The stereo baseline, metres (`None` for mono).
    pub fn baseline_m(&self) -> Option<f64> {
        match self {
            Rig::Mono(_) => None,
            Rig::Stereo { t_right_left, .. } => Some(crate::stereo::baseline_m(t_right_left)),
        }
    }

    /// Mono or stereo.
    pub fn kind(&self) -> ViewKind {
        match self {
            Rig::Mono(_) => ViewKind::Mono,
            Rig::Stereo { .. } => ViewKind::Stereo,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn cam() -> PinholeCamera {
        PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5)
    }

    proptest! {
        #[test]
        fn project_unproject_roundtrip(u in 0.0f64..320.0, v in 0.0f64..320.0, d in 0.005f64..0.2) {
            let c = cam();
            let p = c.unproject(u, v, d);
            let q = c.project(&p).unwrap();
            prop_assert!((q.x - u).abs() < 1e-9 && (q.y - v).abs() < 1e-9);
        }

    }

    #[test]
    fn fov_mask_is_round() {
        let mut c = cam();
        c.fov_radius_px = Some(100.0);
        let m = c.fov_mask();
        assert!(m.at(160, 160));
        assert!(!m.at(0, 0));
        assert!(m.at(159, 60) && !m.at(159, 58));
        let inside = m.data().iter().filter(|b| **b).count() as f64;
        assert!((inside - std::f64::consts::PI * 1e4).abs() / (std::f64::consts::PI * 1e4) < 0.01);
    }

    #[test]
    fn camera_file_problems_name_the_key() {
        let f = CameraFile {
            width: 0,
            height: 10,
            fx: -1.0,
            fy: 1.0,
            cx: 0.0,
            cy: f64::NAN,
            depth_scale: 5000.0,
            distortion: None,
            fov_radius_px: None,
            baseline_m: None,
            right: None,
            depth_noise: Some(crate::depth_noise::DepthNoiseModel { absolute_m: -0.001, relative: 0.01, quadratic_per_m: 0.0, correlation_px: 0.0 }),
        };
        let keys: Vec<_> = f.problems("camera.").into_iter().map(|p| p.key).collect();
        assert_eq!(keys, vec!["camera.width", "camera.fx", "camera.cy", "camera.depth_noise.absolute_m"]);
    }
}
