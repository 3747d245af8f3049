use super::*;
use proptest::prelude::*;

/// A strong capsule-like barrel lens (about 20 % at the image corner of a 90° camera).
const BARREL: LensModel = LensModel::RadialTangential([-0.3, 0.1, 0.001, -0.002, -0.01, 0.0, 0.0, 0.0]);
/// A rational model as `CALIB_RATIONAL_MODEL` fits it.
const RATIONAL: LensModel = LensModel::RadialTangential([0.4, -0.05, 0.0005, 0.0003, 0.01, 0.7, 0.02, 0.001]);
/// A fisheye lens.
const FISHEYE: LensModel = LensModel::Equidistant([0.05, -0.01, 0.002, -0.0005]);

fn parse(text: &str) -> DistortionSpec {
    #[derive(Deserialize)]
    struct File {
        distortion: DistortionSpec,
    }
    toml::from_str::<File>(text).expect("parses").distortion
}

proptest! {
    #[test]
    fn undistort_inverts_distort_for_every_model(x in -1.0f64..1.0, y in -1.0f64..1.0) {
        for lens in [BARREL, RATIONAL, FISHEYE] {
            let (xd, yd) = lens.distort(x, y);
            let (xu, yu) = lens.undistort(xd, yd).expect("invertible inside the field of view");
            prop_assert!((xu - x).abs() < 1e-9 && (yu - y).abs() < 1e-9, "{lens:?}: ({x}, {y}) -> ({xu}, {yu})");
        }
    }
}

#[test]
fn equidistant_maps_the_angle_linearly_without_coefficients() {
    // θ_d = θ: a ray at 60° lands at normalised radius π/3 whatever its azimuth.
    let lens = LensModel::Equidistant([0.0; 4]);
    let t = 60f64.to_radians().tan();
    let (xd, yd) = lens.distort(t * 0.6, t * 0.8);
    assert!((xd.hypot(yd) - std::f64::consts::FRAC_PI_3).abs() < 1e-12);
    assert!((yd / xd - 0.8 / 0.6).abs() < 1e-12);
    assert!(!lens.is_identity());
}

#[test]
fn radial_tangential_matches_opencv_formula_at_a_point() {
    // x = 0.3, y = -0.2 by hand: r² = 0.13.
    let (x, y, r2) = (0.3, -0.2, 0.13);
    let [k1, k2, p1, p2, k3, k4, k5, k6] = [0.4, -0.05, 0.0005, 0.0003, 0.01, 0.7, 0.02, 0.001];
    let radial = (1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2) / (1.0 + k4 * r2 + k5 * r2 * r2 + k6 * r2 * r2 * r2);
    let want = (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y);
    let got = RATIONAL.distort(x, y);
    assert!((got.0 - want.0).abs() < 1e-15 && (got.1 - want.1).abs() < 1e-15);
}

#[test]
fn a_lens_that_folds_over_has_no_inverse_beyond_the_fold() {
    // 1 − 0.5 r²: r (1 − 0.5 r²) peaks at r = 0.816 (r_d = 0.544); beyond, no ray lands.
    let lens = LensModel::brown_conrady([-0.5, 0.0, 0.0, 0.0, 0.0]);
    assert!(lens.undistort(0.5, 0.0).is_some());
    assert!(lens.undistort(0.6, 0.0).is_none());
    // An equidistant ray at or beyond 90° is behind the pinhole plane.
    assert!(LensModel::Equidistant([0.0; 4]).undistort(1.6, 0.0).is_none());
}

#[test]
fn the_three_forms_parse_to_their_models() {
    assert_eq!(parse("distortion = [-0.3, 0.1, 0.001, -0.002, -0.01]").model(), Some(LensModel::brown_conrady([-0.3, 0.1, 0.001, -0.002, -0.01])));
    let rational = parse("distortion = { model = \"radial-tangential\", coefficients = [0.4, -0.05, 0.0005, 0.0003, 0.01, 0.7, 0.02, 0.001] }");
    assert_eq!(rational.model(), Some(RATIONAL));
    let fisheye = parse("distortion = { model = \"equidistant\", coefficients = [0.05, -0.01, 0.002, -0.0005] }");
    assert_eq!(fisheye.model(), Some(FISHEYE));
    // What synth writes reads back as the same model.
    for lens in [BARREL, RATIONAL, FISHEYE] {
        let spec = DistortionSpec::from_model(&lens);
        #[derive(Serialize)]
        struct File {
            distortion: DistortionSpec,
        }
        let text = toml::to_string(&File { distortion: spec }).unwrap();
        assert_eq!(parse(&text).model(), Some(lens), "{text}");
    }
}

#[test]
fn an_unknown_model_a_wrong_count_or_a_stray_key_names_the_key() {
    let keys = |text: &str| parse(text).problems("camera.distortion").into_iter().map(|p| p.key).collect::<Vec<_>>();
    assert_eq!(keys("distortion = { model = \"kannala\", coefficients = [1.0] }"), ["camera.distortion.model"]);
    assert_eq!(keys("distortion = { model = \"equidistant\", coefficients = [0.1, 0.0, 0.0, 0.0, 0.0] }"), ["camera.distortion.coefficients"]);
    assert_eq!(keys("distortion = { model = \"radial-tangential\", coefficients = [0.1, 0.0, 0.0, 0.0, 0.0, 0.0] }"), ["camera.distortion.coefficients"]);
    assert_eq!(keys("distortion = [0.1, 0.0, 0.0]"), ["camera.distortion"]);
    assert_eq!(keys("distortion = { model = \"equidistant\", coefficients = [0.1, 0.0, 0.0, 0.0], k5 = 2.0 }"), ["camera.distortion.k5"]);
    assert_eq!(keys("distortion = [0.1, 0.0, 0.0, 0.0, nan]"), ["camera.distortion"]);
    assert_eq!(parse("distortion = [0.1, 0.0, 0.0]").model(), None);
}
