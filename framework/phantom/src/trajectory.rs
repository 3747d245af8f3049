//! The seven camera paths, mirroring Table 3 of the paper: 1 slow and smooth; 2 a scan with
//! local revisits; 3 a longer scan with more loops; 4 fast rotations and translations; 5 very
//! loopy; 6 = 5 (rendered with heavy noise); 7 = 5 with fast drift (rendered with heavy
//! reflections). Each is a smooth function of normalised time τ ∈ [0, 1], so motion blur can
//! sample between frames.

use std::f64::consts::TAU;

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use super::shape::StomachShape;
use capsule_slam_framework::geometry::Iso3;

/// Where the camera is in tube terms and where it looks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Waypoint {
    /// Arc angle along the centreline, rad.
    pub phi: f64,
    /// Offset from the centreline along the in-plane normal, as a fraction of the local radius.
    pub a: f64,
    /// Offset along world z, as a fraction of the local radius.
    pub b: f64,
    /// View direction turned from the tangent toward the in-plane normal, rad.
    pub yaw: f64,
    /// View direction raised toward world z, rad.
    pub pitch: f64,
    /// Roll about the view direction, rad.
    pub roll: f64,
}

/// The waypoint of preset `preset` (1–7) at τ.
pub fn waypoint(preset: u8, tau: f64) -> Waypoint {
    let w = TAU;
    let s = |f: f64, p: f64| (w * f * tau + p).sin();
    let c = |f: f64, p: f64| (w * f * tau + p).cos();
    match preset {
        1 => Waypoint {
            phi: -0.4 + 0.8 * tau,
            a: 0.15 * s(1.0, 0.0),
            b: 0.1 * s(1.5, 0.0),
            yaw: 0.35 * s(1.2, 0.0),
            pitch: 0.25 * s(0.8, 0.0),
            roll: 0.2 * s(0.5, 0.0),
        },
        2 => Waypoint {
            phi: -0.4 + 0.8 * tau + 0.08 * s(4.0, 0.0),
            a: 0.3 * c(2.0, 0.0),
            b: 0.3 * s(2.0, 0.0),
            yaw: 0.7 * s(2.0, 0.3),
            pitch: 0.4 * s(1.7, 0.0),
            roll: 0.3 * s(1.0, 0.0),
        },
        3 => Waypoint {
            phi: -0.42 * c(1.5, 0.0) + 0.05 * s(6.0, 0.0),
            a: 0.3 * c(3.0, 0.0),
            b: 0.35 * s(3.0, 0.0),
            yaw: 0.8 * s(2.5, 0.0),
            pitch: 0.5 * s(2.0, 0.0),
            roll: 0.4 * s(1.3, 0.0),
        },
        4 => Waypoint {
            phi: -0.3 + 0.6 * tau + 0.06 * s(7.0, 0.0),
            a: 0.25 * s(5.0, 0.0),
            b: 0.25 * c(4.0, 0.0),
            yaw: 0.9 * s(6.0, 0.0),
            pitch: 0.6 * s(5.0, 1.0),
            roll: 0.8 * s(4.0, 0.0),
        },
        7 => Waypoint {
            phi: 0.3 * s(2.6, 0.0) + 0.12 * (tau - 0.5),
            a: 0.35 * c(6.5, 0.0),
            b: 0.35 * s(6.5, 0.0),
            yaw: 0.7 * s(3.9, 0.0),
            pitch: 0.5 * s(5.2, 0.5),
            roll: 0.5 * s(2.6, 0.0),
        },
        _ => Waypoint {
            phi: 0.3 * s(2.0, 0.0),
            a: 0.35 * c(5.0, 0.0),
            b: 0.35 * s(5.0, 0.0),
            yaw: 0.7 * s(3.0, 0.0),
            pitch: 0.5 * s(4.0, 0.5),
            roll: 0.5 * s(2.0, 0.0),
        },
    }
}

/// The camera pose `t_world_cam` of a waypoint in a cavity (camera x right, y down, z forward).
pub fn pose(shape: &StomachShape, wp: &Waypoint) -> Iso3 {
    let t = shape.tangent(wp.phi);
    let n1 = shape.outward(wp.phi);
    let up = Vector3::z();
    let r_local = shape.radius(wp.phi, wp.b.atan2(wp.a), 0.0);
    let position = shape.centre(wp.phi) + r_local * (wp.a * n1 + wp.b * up);
    let forward = wp.pitch.cos() * (wp.yaw.cos() * t + wp.yaw.sin() * n1) + wp.pitch.sin() * up;
    let z_cam = forward.normalize();
    let y_cam = -(up - up.dot(&z_cam) * z_cam).normalize();
    let x_cam = y_cam.cross(&z_cam);
    let roll = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(z_cam), wp.roll);
    let r = Matrix3::from_columns(&[roll * x_cam, roll * y_cam, z_cam]);
    Iso3::from_parts(position.coords.into(), UnitQuaternion::from_matrix(&r))
}

/// Path length of a sampled trajectory, metres.
pub fn path_length_m(poses: &[Iso3]) -> f64 {
    poses.windows(2).map(|w| (w[1].translation.vector - w[0].translation.vector).norm()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_are_rotations_and_stay_inside_the_cavity() {
        let shape = StomachShape { wave_m: 0.004, ..StomachShape::default() };
        for preset in 1..=7 {
            let poses: Vec<Iso3> = (0..300).map(|i| pose(&shape, &waypoint(preset, i as f64 / 299.0))).collect();
            for (i, p) in poses.iter().enumerate() {
                let r = p.rotation.to_rotation_matrix();
                assert!((r.matrix().determinant() - 1.0).abs() < 1e-9);
                let pos = nalgebra::Point3::from(p.translation.vector);
                // At least 8 mm from the wall at any time of the wave.
                assert!(shape.implicit(&pos, i as f64 / 30.0) < -0.008, "preset {preset} frame {i}: {}", shape.implicit(&pos, 0.0));
            }
            let len = path_length_m(&poses);
            assert!((0.05..1.0).contains(&len), "preset {preset}: {len} m");
        }
    }
}
