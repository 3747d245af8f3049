//! Test fixtures shared by the evaluation's unit tests.

use capsule_slam_framework::map::{Surfel, SurfelSet};
use nalgebra::{Matrix3, Point3, Vector3};

use crate::Similarity;

/// A plane z = `z` m facing −z, `n` × `n` samples 0.5 mm apart centred on the z axis, created
/// at frame `t0` and last seen at `t`.
pub(crate) fn plane(z: f32, n: u32, t0: u32, t: u32) -> SurfelSet {
    let start = -0.00025 * n as f32;
    let surfels = (0..n)
        .flat_map(|i| (0..n).map(move |j| (i, j)))
        .map(|(i, j)| Surfel {
            position_m: Point3::new(start + 0.0005 * i as f32, start + 0.0005 * j as f32, z),
            normal: Vector3::new(0.0, 0.0, -1.0),
            colour: [128; 3],
            confidence: 10.0,
            radius_m: 0.0003,
            t0,
            t,
            albedo: 0.0,
            sigma_m: 0.0,
            warp_m: Vector3::zeros(),
        })
        .collect();
    SurfelSet { surfels }
}

/// The identity alignment.
pub(crate) fn identity() -> Similarity {
    Similarity { rotation: Matrix3::identity(), translation: Vector3::zeros(), scale: 1.0 }
}
