//! Bouguet's rectification of a calibrated stereo rig (J.-Y. Bouguet, Camera Calibration
//! Toolbox for Matlab; OpenCV's `stereoRectify` without its scaling `alpha`): each camera is
//! turned by half the rig's relative rotation, then both by the rotation that lays the baseline
//! along the rectified x axis, and both share one pinhole camera. A 3D point then projects to
//! the same row in both rectified views, at columns `d = f · b / z` apart.
//!
//! The views are the rig's pinhole cameras (the dataset has undistorted them), so the map
//! between an original and a rectified pixel is a rotation of its ray: `ray_rect = R_i · ray_i`.
//! This module is the geometry; a stereo stage resamples its images with
//! [`Rectification::source_pixel`] and returns its depth in the left camera's own image with
//! [`Rectification::left_to_rectified`].

use nalgebra::{Point2, Point3, Rotation3, Vector3};

use crate::camera::PinholeCamera;
use crate::error::StageError;
use crate::geometry::Iso3;

/// Which view of the pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// The left (reference) camera.
    Left,
    /// The right camera.
    Right,
}

/// The rectification of one rig.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    /// The camera both rectified views share: the left's size, the mean focal length of the
    /// two, the principal point where the left's optical axis lands.
    pub camera: PinholeCamera,
    /// The left camera's frame turned into the rectified left frame (OpenCV's R1).
    pub r_rect_left: Rotation3<f64>,
    /// The right camera's frame turned into the rectified right frame (OpenCV's R2).
    pub r_rect_right: Rotation3<f64>,
    /// How far the right rectified camera sits along +x of the left one, metres.
    pub baseline_m: f64,
}

impl Rectification {
    /// The rectification of `left` and `right` with `x_right = t_right_left · x_left`. An error
    /// for a rig whose right camera is not beside the left (its baseline mostly along the
    /// optical axis or the image's y: this rectifies a horizontal pair only).
    pub fn new(left: &PinholeCamera, right: &PinholeCamera, t_right_left: &Iso3) -> Result<Self, StageError> {
        // Half the relative rotation on each camera (Bouguet): r_half turns the right frame
        // halfway back to the left's, and its inverse turns the left halfway forward.
        let r = t_right_left.rotation.to_rotation_matrix();
        let r_half = Rotation3::from_scaled_axis(-0.5 * r.scaled_axis());
        let t = r_half * t_right_left.translation.vector;
        if t.x.abs() < t.y.abs().max(t.z.abs()) || t.norm() == 0.0 {
            return Err(StageError::invalid_input(format!(
                "the stereo rig's baseline {:?} m (in the half-turned frame) is not mostly along x: only a horizontal pair can be rectified; check [right] translation_m",
                t.as_slice()
            )));
        }
        // The rotation that lays the baseline along ∓x (the right camera at +x of the left, so
        // x_right = x_left − b: t points along −x).
        let target = Vector3::new(t.x.signum(), 0.0, 0.0);
        let axis = t.cross(&target);
        let angle = (t.x.abs() / t.norm()).clamp(-1.0, 1.0).acos();
        let w = if axis.norm() > 0.0 { Rotation3::from_scaled_axis(axis.normalize() * angle) } else { Rotation3::identity() };
        let r_rect_left = w * r_half.inverse();
        let r_rect_right = w * r_half;
        let baseline_m = -(w * t).x;
        let f = 0.25 * (left.fx + left.fy + right.fx + right.fy);
        let mut camera = PinholeCamera::new(left.width, left.height, f, f, 0.0, 0.0);
        // The principal point where the left's optical axis lands in the rectified view.
        let axis_rect = r_rect_left * Vector3::z();
        camera.cx = left.cx - f * axis_rect.x / axis_rect.z;
        camera.cy = left.cy - f * axis_rect.y / axis_rect.z;
        Ok(Self { camera, r_rect_left, r_rect_right, baseline_m })
    }

    /// The rotation from a camera's own frame to its rectified frame.
    pub fn rotation(&self, side: Side) -> &Rotation3<f64> {
        match side {
            Side::Left => &self.r_rect_left,
            Side::Right => &self.r_rect_right,
        }
    }

    /// Where rectified pixel `(u, v)` of `side` reads that camera's own image (`cam`, the rig's
    /// pinhole camera of that side); `None` for a ray behind it.
    pub fn source_pixel(&self, side: Side, cam: &PinholeCamera, u: f64, v: f64) -> Option<Point2<f64>> {
        let ray_rect = self.camera.unproject(u, v, 1.0).coords;
        let ray = self.rotation(side).inverse() * ray_rect;
        cam.project(&Point3::from(ray))
    }

    /// Where pixel `(u, v)` of the left camera (`left`, the rig's) lands in the rectified left
    /// view; `None` for a ray that turns behind the rectified camera.
    pub fn left_to_rectified(&self, left: &PinholeCamera, u: f64, v: f64) -> Option<Point2<f64>> {
        self.camera.project(&Point3::from(self.r_rect_left * left.unproject(u, v, 1.0).coords))
    }

    /// The depth along the left camera's own z of the point that rectified left pixel
    /// `(u_rect, v_rect)` sees at disparity `d_px` (`z_rect = f b / d`), metres; `None` for a
    /// disparity ≤ 0.
    pub fn left_depth_m(&self, u_rect: f64, v_rect: f64, d_px: f64) -> Option<f64> {
        (d_px > 0.0).then(|| {
            let z_rect = self.camera.fx * self.baseline_m / d_px;
            (self.r_rect_left.inverse() * self.camera.unproject(u_rect, v_rect, z_rect)).z
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A rig like a capsule's: two slightly different cameras 5 mm apart, the right one turned
    /// by 2° and 1° and a little off the left's row.
    fn rig() -> (PinholeCamera, PinholeCamera, Iso3) {
        let left = PinholeCamera::new(320, 320, 160.0, 161.0, 159.5, 158.0);
        let right = PinholeCamera::new(320, 320, 158.0, 158.5, 162.0, 161.0);
        let rot = UnitQuaternion::from_euler_angles(0.01, -0.035, 0.017);
        // The right centre at (5, 0.3, 0.2) mm in the left frame: t = −R c.
        let c = Vector3::new(0.005, 0.0003, 0.0002);
        (left, right, Iso3::from_parts(Translation3::from(-(rot * c)), rot))
    }

    #[test]
    fn a_point_lands_on_the_same_row_of_both_views_at_its_disparity() {
        let (left, right, t) = rig();
        let rect = Rectification::new(&left, &right, &t).unwrap();
        assert!((rect.baseline_m - 0.005_013).abs() < 1e-5, "{}", rect.baseline_m);
        for (x, y, z) in [(0.0, 0.0, 0.05), (0.02, -0.015, 0.04), (-0.03, 0.02, 0.08), (0.01, 0.025, 0.02)] {
            let p_left = Point3::new(x, y, z);
            let p_right = t * p_left;
            // Seen by each real camera, then moved into its rectified view by its rotation.
            let (ul, ur) = (left.project(&p_left).unwrap(), right.project(&p_right).unwrap());
            let a = rect.left_to_rectified(&left, ul.x, ul.y).unwrap();
            let b = rect.camera.project(&Point3::from(rect.r_rect_right * right.unproject(ur.x, ur.y, 1.0).coords)).unwrap();
            assert!((a.y - b.y).abs() < 0.05, "rows {} and {} for {p_left}", a.y, b.y);
            let d = a.x - b.x;
            // And back: the disparity gives the point's depth in the left camera.
            let z_back = rect.left_depth_m(a.x, a.y, d).unwrap();
            assert!((z_back - z).abs() < 1e-9 * z.max(1.0) + 1e-9, "depth {z_back} for {z}");
            // The maps agree with the projections: the rectified pixel reads the real one.
            let src = rect.source_pixel(Side::Right, &right, b.x, b.y).unwrap();
            assert!((src - ur).norm() < 1e-9);
        }
    }

    #[test]
    fn a_rectified_pair_is_left_alone_and_a_forward_baseline_is_refused() {
        let cam = PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5);
        let rect = Rectification::new(&cam, &cam, &Iso3::translation(-0.005, 0.0, 0.0)).unwrap();
        assert!(rect.r_rect_left.angle() < 1e-12 && rect.r_rect_right.angle() < 1e-12);
        assert_eq!((rect.camera.fx, rect.camera.cx, rect.camera.cy, rect.baseline_m), (160.0, 159.5, 159.5, 0.005));
        let err = Rectification::new(&cam, &cam, &Iso3::translation(0.0, 0.0, -0.005)).unwrap_err().to_string();
        assert!(err.contains("horizontal") && err.contains("translation_m"), "{err}");
    }
}
