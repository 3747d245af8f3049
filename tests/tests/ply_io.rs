//! `map.ply` written and read back equal.

use capsule_slam_framework::{Surfel, SurfelSet};
use capsule_slam_io::ply;
use nalgebra::{Point3, Vector3};
use proptest::prelude::*;

fn surfel() -> impl Strategy<Value = Surfel> {
    (
        prop::array::uniform3(-1.0f32..1.0),
        prop::array::uniform3(-1.0f32..1.0),
        prop::array::uniform3(any::<u8>()),
        0.0f32..100.0,
        0.0f32..0.01,
        0u32..5000,
        0u32..5000,
        (0.0f32..1.0, 0.0f32..0.01, prop::array::uniform3(-0.005f32..0.005)),
    )
        .prop_map(|(p, n, c, conf, r, t0, t, (albedo, sigma_m, w))| Surfel {
            position_m: Point3::new(p[0], p[1], p[2]),
            normal: Vector3::new(n[0], n[1], n[2]),
            colour: c,
            confidence: conf,
            radius_m: r,
            t0,
            t,
            albedo,
            sigma_m,
            warp_m: Vector3::new(w[0], w[1], w[2]),
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]
    #[test]
    fn write_then_read_is_identity(surfels in prop::collection::vec(surfel(), 0..200)) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("map.ply");
        let set = SurfelSet::new(surfels);
        ply::write_surfels(&p, &set).unwrap();
        let back = ply::read_surfels(&p).unwrap();
        prop_assert_eq!(back, set);
    }
}

#[test]
fn the_header_is_what_point_cloud_tools_expect() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("map.ply");
    ply::write_surfels(&p, &SurfelSet::default()).unwrap();
    let text = String::from_utf8(std::fs::read(&p).unwrap()).unwrap();
    assert!(text.starts_with("ply\nformat binary_little_endian 1.0\n"));
    for prop in ["float x", "float nx", "uchar red", "uchar blue", "float confidence", "float radius", "uint t0", "uint t\n", "float sigma"] {
        assert!(text.contains(&format!("property {prop}")), "{prop}");
    }
}
