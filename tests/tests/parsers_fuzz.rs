//! Every parser of an input file, fed arbitrary bytes and damaged copies of a valid file
//! (issue 18): an error or a valid value, never a panic. A TOML file that parses must also pass
//! its own validation (no invalid value slips through as `Ok`).
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::path::Path;

use capsule_slam_framework::camera::CameraFile;
use capsule_slam_framework::config::InputConfig;
use capsule_slam_framework::files::{read_camera_file, read_light_file, read_vignetting_file};
use capsule_slam_framework::{DepthMap, Surfel, SurfelSet};
use capsule_slam_io::{Dataset, images, ply, tum};
use nalgebra::{Point3, Vector3};
use proptest::prelude::*;

const CAMERA: &str = "width = 8\nheight = 6\nfx = 5.0\nfy = 5.0\ncx = 3.5\ncy = 2.5\nfov_radius_px = 4.0\n\
                      distortion = { model = \"equidistant\", coefficients = [0.05, -0.01, 0.002, -0.0005] }\n\
                      depth_noise = { relative = 0.01, absolute_m = 0.0002 }\n";
const LIGHT: &str =
    "gain = 0.6\nref_distance_m = 0.025\nambient = 0.02\ngamma = 2.2\nposition_m = [0.0, 0.0, 0.0]\nspot_exponent = 1.0\nvignetting = [-0.3, -0.25]\n";
const VIGNETTING: &str = "gamma = 2.2\nlens_and_light = [-0.3, -0.25]\n";
const TRAJECTORY: &str = "# timestamp tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.033 0.001 0 0 0 0 0.01 1\n";
const LIST: &str = "# timestamp filename\n0.0 rgb/000000.png\n0.033 rgb/000001.png\n";

/// A valid file, damaged: cut at `cut` (a share of its length) and `flips` bytes replaced.
fn damaged(valid: &[u8], cut: f64, flips: &[(f64, u8)]) -> Vec<u8> {
    let mut b = valid[..((valid.len() as f64 * cut) as usize).min(valid.len())].to_vec();
    for (at, byte) in flips {
        if !b.is_empty() {
            let i = ((b.len() as f64 * at) as usize).min(b.len() - 1);
            b[i] = *byte;
        }
    }
    b
}

fn valid_ply(dir: &Path) -> Vec<u8> {
    let s = |i: u32| Surfel {
        position_m: Point3::new(i as f32 * 1e-3, 0.0, 0.05),
        normal: Vector3::z(),
        colour: [200, 80, 80],
        confidence: 12.0,
        radius_m: 3e-4,
        t0: i,
        t: i,
        albedo: 0.4,
        sigma_m: 1e-4,
        warp_m: Vector3::zeros(),
    };
    let p = dir.join("valid.ply");
    ply::write_surfels(&p, &SurfelSet::new((0..3).map(s).collect())).unwrap();
    std::fs::read(p).unwrap()
}

fn valid_depth_png(dir: &Path) -> Vec<u8> {
    let p = dir.join("valid.png");
    images::write_depth(&p, &DepthMap::from_fn(8, 6, |x, y| [0.02 + 0.001 * (x + y) as f32]), 5000.0).unwrap();
    std::fs::read(p).unwrap()
}

/// Feeds `bytes` to every parser; panics (failing the property) only if one panics or lets an
/// invalid value through.
fn every_parser(dir: &Path, bytes: &[u8]) {
    let p = dir.join("input.png"); // the image readers go by the extension; the others ignore it
    std::fs::write(&p, bytes).unwrap();
    if let Ok(cam) = read_camera_file(&p) {
        assert!(cam.problems("").is_empty(), "an invalid camera.toml was accepted: {cam:?}");
        // A lens that parsed gives a map (or none) without a panic, however wild.
        let _ = Dataset::open(dir, &InputConfig::default(), Some(&cam));
    }
    if let Ok(light) = read_light_file(&p) {
        assert!(light.problems().is_empty(), "an invalid light.toml was accepted: {light:?}");
    }
    let _ = read_vignetting_file(&p);
    let _ = tum::read_list(&p);
    let _ = tum::read_trajectory(&p);
    let _ = ply::read_surfels(&p);
    let _ = images::read_depth(&p, 5000.0, None);
    let _ = images::read_rgb(&p, Some((8, 6)));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_are_an_error_or_a_valid_value(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        let tmp = tempfile::tempdir().unwrap();
        every_parser(tmp.path(), &bytes);
    }

    #[test]
    fn damaged_valid_files_are_an_error_or_a_valid_value(
        which in 0usize..7,
        cut in 0.0f64..=1.0,
        flips in proptest::collection::vec((0.0f64..1.0, any::<u8>()), 0..6),
    ) {
        let tmp = tempfile::tempdir().unwrap();
        let valid: Vec<u8> = match which {
            0 => CAMERA.into(),
            1 => LIGHT.into(),
            2 => VIGNETTING.into(),
            3 => TRAJECTORY.into(),
            4 => LIST.into(),
            5 => valid_ply(tmp.path()),
            _ => valid_depth_png(tmp.path()),
        };
        every_parser(tmp.path(), &damaged(&valid, cut, &flips));
    }

    /// Any finite lens coefficients in a camera.toml: the undistortion map is made without a
    /// panic, and every pixel it keeps reads a source pixel inside the image.
    #[test]
    fn any_lens_gives_a_map_without_a_panic(k in proptest::array::uniform8(-5.0f64..5.0), fisheye in any::<bool>()) {
        let lens = if fisheye { format!("{{ model = \"equidistant\", coefficients = {:?} }}", &k[..4]) } else { format!("{:?}", &k[..5]) };
        let text = format!("width = 8\nheight = 6\nfx = 5.0\nfy = 5.0\ncx = 3.5\ncy = 2.5\ndistortion = {lens}\n");
        let cam: CameraFile = toml::from_str(&text).unwrap();
        prop_assert!(cam.problems("").is_empty());
        let u = capsule_slam_io::undistort::Undistortion::new(&cam.camera());
        let img = capsule_slam_framework::Rgb8::from_fn(8, 6, |x, y| [x as u8, y as u8, 7]);
        let out = u.rgb(&img);
        prop_assert_eq!(out.size(), (8, 6));
    }
}

#[test]
fn the_valid_seeds_parse() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("f.png");
    for (text, check) in [(CAMERA, 0), (LIGHT, 1), (VIGNETTING, 2), (TRAJECTORY, 3), (LIST, 4)] {
        std::fs::write(&p, text).unwrap();
        let ok = match check {
            0 => read_camera_file(&p).is_ok(),
            1 => read_light_file(&p).is_ok(),
            2 => read_vignetting_file(&p).is_ok(),
            3 => tum::read_trajectory(&p).is_ok_and(|t| t.len() == 2),
            _ => tum::read_list(&p).is_ok_and(|l| l.len() == 2),
        };
        assert!(ok, "the seed {check} does not parse: the damaged copies would test nothing");
    }
    std::fs::write(&p, valid_ply(tmp.path())).unwrap();
    assert_eq!(ply::read_surfels(&p).unwrap().surfels.len(), 3);
    std::fs::write(&p, valid_depth_png(tmp.path())).unwrap();
    assert_eq!(images::read_depth(&p, 5000.0, None).unwrap().size(), (8, 6));
}
