//! The second photometric reference (`keyframe-and-previous`) and the depth's error carried
//! through the photometric warp (`rgb_flow_sigma_scale`).

use capsule_slam_framework::Iso3;
use capsule_slam_framework::geometry::exp_se3;
use nalgebra::{Matrix6, Vector3, Vector6};
use proptest::prelude::*;

use super::gn;
use super::terms::projected_gradient;
use super::tests::{level0, levels, photometric_weights};

proptest! {
    /// A live point `v` at relative depth error ε lands at `p(ε) = R v (1 + ε) + t`; the
    /// intensity there changes with ε by `g · ∂u/∂ε = a · R v = −a · t`, `a` the image gradient
    /// `g` projected on the point (`a · p = 0`): without translation the depth moves nothing.
    #[test]
    fn the_warps_depth_sensitivity_is_the_projected_gradient_along_the_translation(
        v in (-0.02f64..0.02, -0.02f64..0.02, 0.02f64..0.08),
        w in (-0.2f64..0.2, -0.2f64..0.2, -0.2f64..0.2),
        t in (-0.003f64..0.003, -0.003f64..0.003, -0.003f64..0.003),
        g in (-0.05f64..0.05, -0.05f64..0.05),
    ) {
        let (fx, fy) = (160.0, 150.0);
        let t_photo_live = exp_se3(&Vector6::new(t.0, t.1, t.2, w.0, w.1, w.2));
        let v = Vector3::new(v.0, v.1, v.2);
        let p = |eps: f64| (t_photo_live * nalgebra::Point3::from(v * (1.0 + eps))).coords;
        let pixel = |q: Vector3<f64>| (fx * q.x / q.z, fy * q.y / q.z);
        prop_assume!(p(0.0).z > 0.01);
        let h = 1e-6;
        let ((u1, v1), (u0, v0)) = (pixel(p(h)), pixel(p(-h)));
        let numeric = (g.0 * (u1 - u0) + g.1 * (v1 - v0)) / (2.0 * h);
        let a = projected_gradient(&p(0.0), g, fx, fy);
        let analytic = -a.dot(&t_photo_live.translation.vector);
        prop_assert!((numeric - analytic).abs() <= 1e-6 * (1.0 + analytic.abs()), "numeric {numeric}, analytic {analytic}");
    }
}

#[test]
fn without_its_scale_the_photometric_sigma_is_sigma_rgb_bit_for_bit() {
    let w = photometric_weights();
    assert_eq!(gn::photometric_sigma(&w, 0.3), (w.sigma_rgb, w.sigma_rgb * w.sigma_rgb));
    let scaled = gn::Weights { rgb_flow_sigma_scale: 10.0, ..w };
    let (sigma, var) = gn::photometric_sigma(&scaled, 0.003);
    assert!((var - (w.sigma_rgb * w.sigma_rgb + 0.03 * 0.03)).abs() < 1e-15 && (sigma * sigma - var).abs() < 1e-15);
}

/// The full normal matrix and right-hand side of a system.
fn ab(s: &gn::System) -> (Matrix6<f64>, Vector6<f64>) {
    (s.a.full(), s.b)
}

#[test]
fn a_second_reference_equal_to_the_first_counts_each_photometric_row_twice() {
    let (live, reference) = levels(None);
    let t = Iso3::identity();
    let w = photometric_weights();
    let one = gn::accumulate(&level0(&live, &reference, None), &t, &w);
    let two = gn::accumulate(&gn::Inputs { second: Some((&reference[0], None)), ..level0(&live, &reference, None) }, &t, &w);
    let icp = gn::accumulate(&level0(&live, &reference, None), &t, &gn::Weights { w_rgb: 0.0, ..w });
    assert!(one.rgb_n > 1000, "{} photometric rows", one.rgb_n);
    assert_eq!((two.rgb_n, two.icp_n), (2 * one.rgb_n, one.icp_n));
    let ((a1, b1), (a2, b2), (ai, bi)) = (ab(&one), ab(&two), ab(&icp));
    let (expected_a, expected_b) = (ai + (a1 - ai) * 2.0, bi + (b1 - bi) * 2.0);
    assert!((a2 - expected_a).norm() <= 1e-9 * expected_a.norm(), "A off by {:e}", (a2 - expected_a).norm() / expected_a.norm());
    assert!((b2 - expected_b).norm() <= 1e-9 * expected_b.norm(), "b off by {:e}", (b2 - expected_b).norm() / expected_b.norm());
}

#[test]
fn the_depths_error_weighs_a_row_less_the_farther_the_reference_camera_moved() {
    // Frames with a 1 mm depth σ: without translation the warp carries no depth error and the
    // flow scale changes nothing; 2 mm away the photometric information falls.
    let (live, reference) = levels(Some(0.001));
    let w = photometric_weights();
    let scaled = gn::Weights { rgb_flow_sigma_scale: 10.0, ..w };
    let info = |t: &Iso3, w: &gn::Weights| {
        let s = gn::accumulate(&level0(&live, &reference, None), t, w);
        let icp = gn::accumulate(&level0(&live, &reference, None), t, &gn::Weights { w_rgb: 0.0, ..*w });
        (s.a.full() - icp.a.full()).trace()
    };
    let still = Iso3::identity();
    let (plain, flow) = (info(&still, &w), info(&still, &scaled));
    assert!(plain > 0.0 && (flow - plain).abs() <= 1e-9 * plain, "still: {flow} against {plain}");
    let moved = exp_se3(&Vector6::new(0.002, 0.0, 0.0, 0.0, 0.0, 0.0));
    let (plain, flow) = (info(&moved, &w), info(&moved, &scaled));
    assert!(flow < 0.9 * plain, "2 mm away: {flow} against {plain}");
}

#[test]
fn auto_reads_a_keyframe_beside_the_previous_frame_only_where_the_depth_error_is_correlated_and_relit() {
    use super::RgbReference::{Auto, Keyframe, KeyframeAndPrevious, Model, PreviousFrame};
    assert_eq!(Auto.for_frame(0.0, true), PreviousFrame);
    assert_eq!(Auto.for_frame(8.0, true), KeyframeAndPrevious);
    assert_eq!(Auto.for_frame(0.25, true), KeyframeAndPrevious);
    assert_eq!(Auto.for_frame(8.0, false), PreviousFrame, "unlit, a keyframe's brightness is not the live frame's");
    for kind in [PreviousFrame, Keyframe, KeyframeAndPrevious, Model] {
        for relit in [false, true] {
            assert_eq!((kind.for_frame(0.0, relit), kind.for_frame(80.0, relit)), (kind, kind));
        }
    }
    assert!(KeyframeAndPrevious.keeps_keyframe() && Keyframe.keeps_keyframe() && !PreviousFrame.keeps_keyframe() && !Model.keeps_keyframe());
}
