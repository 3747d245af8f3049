//! Tests of `nonrigid` against known warps: a curved, textured wall patch in front of the
//! camera, displaced by a smooth field the test knows, rendered to depth and intensity.

use capsule_slam_framework::{DepthMap, GrayF32, Iso3};
use nalgebra::{Point3, Vector3};

use super::fixture::{cam, level, model};
use super::points::ModelPoint;
use super::*;
use crate::common::ed_graph::NodeModel;
use crate::common::maps::GeometryParams;
use crate::track::icp_rgb::frames::pyramid;

fn tracker(camera: CameraMode) -> Nonrigid {
    let params = NonrigidParams {
        camera,
        node_spacing_m: 0.004,
        reach_m: 0.008,
        max_edge_m: 0.012,
        iterations: 8,
        min_points_per_node: 4,
        sigma_step_m: 0.0,
        sigma_step_rot: 0.0,
        factor_common: false,
        // The warp is to be recovered from the depth: the photometric term at the paper's
        // weight, and no prior on sliding (the test's displacement is along z, not the normal).
        w_rgb: 0.1,
        sigma_slide_m: 0.0,
        // The warp recovered is the wall's, not led ahead of it.
        warp_lead: 0.0,
        ..Default::default()
    };
    Nonrigid::new(params).unwrap()
}

/// RMS distance of the warped model points from where the test moved them, metres.
fn warp_error(warp: &Deformation, pts: &[(ModelPoint, Point3<f64>)]) -> f64 {
    let sse: f64 = pts.iter().map(|(p, truth)| (warp.warp_point(&p.x_world_m, 0) - truth).norm_squared()).sum();
    (sse / pts.len() as f64).sqrt()
}

/// The rest wall's model points with where a 0.5 mm wave moved each, the points alone, and the
/// live level of the moved wall.
type MovedWall = (Vec<(ModelPoint, Point3<f64>)>, Vec<ModelPoint>, Level);

fn moved_wall() -> MovedWall {
    let amp = 0.0005;
    let pts = model(amp);
    let points = pts.iter().map(|p| p.0).collect();
    (pts, points, level(amp))
}

#[test]
fn a_known_smooth_warp_is_recovered_from_its_depth() {
    let (pts, points, live) = moved_wall();
    let before = (pts.iter().map(|(p, t)| (p.x_world_m - t).norm_squared()).sum::<f64>() / pts.len() as f64).sqrt();
    for (camera, model) in [CameraMode::Fixed, CameraMode::Joint].into_iter().flat_map(|c| [NodeModel::Affine, NodeModel::Twist].map(|m| (c, m))) {
        let mut t = tracker(camera);
        t.params.node_model = model;
        t.nodes.cover(&points, t.params.node_spacing_m, 4096);
        let Fit::Solved { warp, t_world_cam, .. } = t.fit(&points, &live, &Iso3::identity(), true).unwrap() else { panic!("{camera:?} {model:?}: fell back") };
        let err = warp_error(&warp, &pts);
        assert!(err < 0.1e-3, "{camera:?} {model:?}: warp error {:.4} mm (before {:.4} mm)", err * 1e3, before * 1e3);
        let moved = t_world_cam.translation.vector.norm();
        assert!(moved < 0.05e-3, "{camera:?} {model:?}: the camera moved {:.4} mm", moved * 1e3);
    }
}

#[test]
fn the_chord_iterations_reach_the_gauss_newton_solution() {
    // Factorising once and iterating on the gradient alone converges to the fixed point of
    // Gauss-Newton (the gradient's zero), more slowly: run both to convergence.
    let (pts, points, live) = moved_wall();
    for model in [NodeModel::Affine, NodeModel::Twist] {
        let fit = |reuse_factor: bool| {
            let mut t = tracker(CameraMode::Joint);
            (t.params.node_model, t.params.iterations, t.params.step_tolerance_m, t.params.reuse_factor) = (model, 30, 1e-9, reuse_factor);
            (t.params.min_rms_gain, t.params.min_evidence) = (0.0, 0.0);
            t.nodes.cover(&points, t.params.node_spacing_m, 4096);
            let Fit::Solved { warp, t_world_cam, outcome, .. } = t.fit(&points, &live, &Iso3::identity(), true).unwrap() else {
                panic!("{model:?}, reuse {reuse_factor}: fell back")
            };
            let moved: Vec<Point3<f64>> = pts.iter().map(|(p, _)| warp.warp_point(&p.x_world_m, 0)).collect();
            (moved, t_world_cam, warp_error(&warp, &pts), (outcome.factorisations, outcome.iterations))
        };
        let (exact, t_exact, err_exact, (factorised, iterations)) = fit(false);
        assert_eq!(factorised, iterations, "{model:?}: Gauss-Newton factorises on every iteration");
        let (chord, t_chord, err_chord, (factorised, iterations)) = fit(true);
        // From this far start the first kept matrix swings the steps back and forth: the guard
        // factorises again, and then the kept matrix serves the rest.
        assert!(factorised >= 2 && 2 * factorised < iterations, "{model:?}: the chord method factorised {factorised} times in {iterations} iterations");
        let apart = exact.iter().zip(&chord).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        assert!(apart < 2e-6, "{model:?}: the chord solution is {:.2} µm from Gauss-Newton's", apart * 1e6);
        assert!((t_exact.translation.vector - t_chord.translation.vector).norm() < 1e-6, "{model:?}: the cameras differ");
        assert!(err_chord < 0.1e-3 && err_exact < 0.1e-3, "{model:?}: warp errors {err_exact} / {err_chord} m");
    }
}

#[test]
fn a_kept_warp_leads_the_wall_by_its_share_of_the_solved_motion() {
    let (_, points, live) = moved_wall();
    // Frame 1: the wall moved by the test's field; frame 2 by twice it (steady motion).
    let frames = |lead: f64| {
        let mut t = tracker(CameraMode::Joint);
        t.params.warp_lead = lead;
        t.nodes.cover(&points, t.params.node_spacing_m, 4096);
        let before: Vec<Point3<f64>> = t.nodes.nodes.iter().map(|n| n.position_m).collect();
        let Fit::Solved { warp, .. } = t.fit(&points, &live, &Iso3::identity(), true).unwrap() else { panic!("lead {lead}: frame 1 fell back") };
        let moved: Vec<Vector3<f64>> = t.nodes.nodes.iter().zip(&before).map(|(n, b)| n.position_m - b).collect();
        let next: Vec<ModelPoint> = points.iter().map(|p| ModelPoint { x_world_m: warp.warp_point(&p.x_world_m, 0), ..*p }).collect();
        let Fit::Solved { outcome, .. } = t.fit(&next, &level(0.001), &Iso3::identity(), true).unwrap() else { panic!("lead {lead}: frame 2 fell back") };
        (warp, moved, outcome.icp_rms_first_m)
    };
    let (seen, moved_seen, start_seen) = frames(0.0);
    let (led, moved_led, start_led) = frames(0.5);
    // The same solve, its translations scaled by 1.5, its rotations kept; the nodes move alike.
    assert!(seen.nodes.iter().map(|n| n.translation_m.norm()).fold(0.0, f64::max) > 0.2e-3, "the wall moved");
    for (a, b) in seen.nodes.iter().zip(&led.nodes) {
        assert!((b.translation_m - 1.5 * a.translation_m).norm() < 1e-12 && a.rotation == b.rotation);
    }
    assert!(moved_seen.iter().zip(&moved_led).all(|(a, b)| (b - 1.5 * a).norm() < 1e-12));
    // The next frame of a steadily moving wall meets a map nearer it.
    assert!(start_led < 0.8 * start_seen, "point-to-plane RMS at frame 2's start: {:.4} mm led, {:.4} mm not", start_led * 1e3, start_seen * 1e3);
}

/// The point-to-plane RMS at the start of each of 8 frames of a wall moving steadily by the test's
/// field per frame, with the default priors and a lead, mm.
fn steady_starts_mm(lead: f64) -> Vec<f64> {
    let (_, points, _) = moved_wall();
    let params = NonrigidParams {
        node_spacing_m: 0.004,
        reach_m: 0.008,
        max_edge_m: 0.012,
        min_points_per_node: 4,
        // Model selection is not under test.
        min_rms_gain: 0.0,
        gain_window_frames: 1,
        warp_lead: lead,
        // No prior on sliding: the test's displacement is along z, not along the normal.
        sigma_slide_m: 0.0,
        ..Default::default()
    };
    let mut t = Nonrigid::new(params).unwrap();
    t.nodes.cover(&points, t.params.node_spacing_m, 4096);
    let mut pts = points;
    (1..=8)
        .map(|f| {
            let Fit::Solved { warp, outcome, .. } = t.fit(&pts, &level(0.0005 * f as f64), &Iso3::identity(), true).unwrap() else {
                panic!("lead {lead}: frame {f} fell back")
            };
            pts = pts.iter().map(|p| ModelPoint { x_world_m: warp.warp_point(&p.x_world_m, 0), ..*p }).collect();
            outcome.icp_rms_first_m * 1e3
        })
        .collect()
}

#[test]
fn the_default_lead_follows_a_steady_wall_closer_without_ringing() {
    // Without a lead the priors leave a lag that grows to a steady one; the default lead settles
    // nearer; a lead beyond the stability bound rings from frame to frame.
    let (none, default, beyond) = (steady_starts_mm(0.0), steady_starts_mm(NonrigidParams::default().warp_lead), steady_starts_mm(1.5));
    let ringing = |r: &[f64]| r[3..].windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
    assert!(none[7] > none[1], "the lag grows without a lead: {none:?}");
    assert!((2..8).all(|k| default[k] < 0.7 * none[k]), "the default lead starts nearer the wall: {default:?} against {none:?}");
    assert!(ringing(&default) < 0.05 && ringing(&beyond) > 0.15, "ringing {:.3} mm at the default, {:.3} mm at 1.5", ringing(&default), ringing(&beyond));
}

#[test]
fn the_iterations_stop_once_a_step_moves_nothing_by_more_than_the_tolerance() {
    let (pts, points, live) = moved_wall();
    let fit = |tolerance_m: f64| {
        let mut t = tracker(CameraMode::Joint);
        t.params.iterations = 20;
        t.params.step_tolerance_m = tolerance_m;
        // Model selection is not under test: a single step's gain is kept too.
        (t.params.min_rms_gain, t.params.min_evidence) = (0.0, 0.0);
        t.nodes.cover(&points, t.params.node_spacing_m, 4096);
        let Fit::Solved { warp, outcome, .. } = t.fit(&points, &live, &Iso3::identity(), true).unwrap() else { panic!("tolerance {tolerance_m}: fell back") };
        (outcome.iterations, warp_error(&warp, &pts))
    };
    let (all, exact) = fit(0.0);
    let (early, close) = fit(5e-6);
    assert_eq!(all, 20, "without a tolerance every iteration runs");
    assert!((2..all).contains(&early), "5 µm stops after {early} iterations");
    // What the skipped iterations would still have moved is below the tolerance's order.
    assert!((close - exact).abs() < 5e-6 && close < 0.1e-3, "warp error {close} m with the tolerance, {exact} m without");
    assert_eq!(fit(1.0).0, 1, "a tolerance of a metre stops after the first step");
}

/// The dense symmetric matrix of a pattern's lower triangle.
fn dense(pattern: &super::system::Pattern) -> nalgebra::DMatrix<f64> {
    let n = pattern.unknowns();
    let (sym, vals) = (pattern.a.symbolic(), pattern.a.val());
    let mut a = nalgebra::DMatrix::zeros(n, n);
    for c in 0..n {
        let range = sym.col_ptr()[c]..sym.col_ptr()[c + 1];
        for (&r, &v) in sym.row_idx()[range.clone()].iter().zip(&vals[range]) {
            a[(r, c)] = v;
            a[(c, r)] = v;
        }
    }
    a
}

/// A tracker covering the rest wall, its problem's points, and the live level of the wall
/// moved by `amp_m`.
fn setup(camera: CameraMode, amp_m: f64) -> (Nonrigid, Vec<ModelPoint>, Level) {
    let points: Vec<ModelPoint> = model(amp_m).iter().map(|p| p.0).collect();
    let mut t = tracker(camera);
    t.nodes.cover(&points, t.params.node_spacing_m, 4096);
    (t, points, level(amp_m))
}

#[test]
fn the_assembled_normal_equations_equal_the_dense_jacobian_products() {
    for model in [NodeModel::Affine, NodeModel::Twist] {
        assembled_normal_equations_equal_the_dense_products(model);
    }
}

fn assembled_normal_equations_equal_the_dense_products(model: NodeModel) {
    let (mut t, points, live) = setup(CameraMode::Joint, 0.0003);
    t.params.huber_k = 1e6; // constant weights
    t.params.sigma_slide_m = 2e-4;
    t.params.node_model = model;
    let w = t.params.weights();
    let (mut problem, _, _) = t.problem(&points).unwrap();
    let (u, tr) = (model.unknowns(), model.translation());
    // Move the nodes off the identity so every Jacobian entry is exercised.
    for (j, n) in problem.graph.deformation.nodes.iter_mut().enumerate() {
        n.translation_m = Vector3::new(1e-5 * j as f64, -2e-5, 3e-5);
        match model {
            NodeModel::Affine => n.rotation[(0, 1)] += 1e-3 * (j % 3) as f64,
            NodeModel::Twist => n.rotation = *nalgebra::Rotation3::new(Vector3::new(1e-3 * (j % 3) as f64, -2e-3, 5e-4)).matrix(),
        }
    }
    let t_wc = capsule_slam_framework::geometry::exp_se3(&nalgebra::Vector6::new(1e-4, -2e-4, 5e-5, 1e-3, 0.0, -2e-3));
    let xi = nalgebra::Vector6::new(1e-4, 0.0, -1e-4, 1e-3, 2e-3, 0.0);
    let mut layout = problem.layout(&points, &w).unwrap();
    let (g, _) = problem.linearise(&points, &live, &t_wc, &xi, &w, &mut layout, true);
    let a = dense(&layout.pattern);
    // The chord method's iterations form the same gradient without the matrix.
    let mut gradient_layout = problem.layout(&points, &w).unwrap();
    let (g_alone, _) = problem.linearise(&points, &live, &t_wc, &xi, &w, &mut gradient_layout, false);
    assert_eq!(g_alone, g, "{model:?}: the gradient alone differs from the full linearisation's");
    // The same terms as dense rows: data rows recorded from the same residual code, the graph's
    // rows from its visitor, the priors written out here.
    let n = a.nrows();
    let nodes = problem.graph.deformation.nodes.len();
    let mut rows: Vec<(nalgebra::DVector<f64>, f64, f64)> = Vec::new();
    for (i, binding) in &problem.points {
        let p = &points[*i];
        problem.point_terms(&live, &t_wc, &w, p, binding, &mut |q: &super::system::Residual| {
            let mut j = nalgebra::DVector::zeros(n);
            for &(k, wk) in binding {
                let node = &problem.graph.deformation.nodes[k];
                let v = p.x_world_m - node.position_m;
                for (m, e) in super::energy::node_row(model, &q.a, &v, &node.rotation, wk).iter().enumerate() {
                    j[u * k + m] += e;
                }
            }
            for c in 0..6 {
                j[u * nodes + c] = q.camera[c];
            }
            rows.push((j, q.r, q.w));
        });
    }
    let gw =
        crate::common::ed_graph::GraphWeights { rot: 1.0 / (w.sigma_rot * w.sigma_rot), reg: w.w_reg, con: 0.0, length_unit_m: w.sigma_reg_m, iterations: 1 };
    problem.graph.visit(&gw, |r, entries| {
        let mut j = nalgebra::DVector::zeros(n);
        for &(u, v) in entries {
            j[u] += v;
        }
        rows.push((j, r, 1.0));
    });
    let inv2 = |s: f64| if s > 0.0 { 1.0 / (s * s) } else { 0.0 };
    for (k, node) in problem.graph.deformation.nodes.iter().enumerate() {
        let off = node.position_m.coords + node.translation_m - problem.references[k];
        match model {
            NodeModel::Affine => {
                for m in 0..9 {
                    let mut j = nalgebra::DVector::zeros(n);
                    j[u * k + m] = 1.0;
                    let id = if m % 4 == 0 { 1.0 } else { 0.0 };
                    rows.push((j, node.rotation[(m % 3, m / 3)] - id, inv2(w.sigma_step_rot)));
                }
            }
            NodeModel::Twist => {
                // ‖R − I‖²_F ≈ 2 ‖ω‖²: the rotation vector's components, twice the weight.
                let omega = nalgebra::Rotation3::from_matrix_unchecked(node.rotation).scaled_axis();
                for m in 0..3 {
                    let mut j = nalgebra::DVector::zeros(n);
                    j[u * k + 3 + m] = 1.0;
                    rows.push((j, omega[m], 2.0 * inv2(w.sigma_step_rot)));
                }
            }
        }
        for axis in 0..3 {
            let mut j = nalgebra::DVector::zeros(n);
            j[u * k + tr + axis] = 1.0;
            rows.push((j.clone(), off[axis], inv2(w.sigma_rest_m)));
            rows.push((j, node.translation_m[axis], inv2(w.sigma_step_m)));
        }
        // The slide prior: the translation's components along two tangents of the node normal.
        let normal = problem.normals[k];
        let t1 = normal.cross(&if normal.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
        for tangent in [t1, normal.cross(&t1)] {
            let mut j = nalgebra::DVector::zeros(n);
            for axis in 0..3 {
                j[u * k + tr + axis] = tangent[axis];
            }
            rows.push((j, tangent.dot(&node.translation_m), inv2(w.sigma_slide_m)));
        }
    }
    for c in 0..6 {
        let mut j = nalgebra::DVector::zeros(n);
        j[u * nodes + c] = 1.0;
        rows.push((j, xi[c], if c < 3 { inv2(w.sigma_camera_m) } else { inv2(w.sigma_camera_rad) }));
    }
    let mut a_dense = nalgebra::DMatrix::<f64>::zeros(n, n);
    let mut g_dense = nalgebra::DVector::<f64>::zeros(n);
    for (j, r, wt) in &rows {
        a_dense += *wt * j * j.transpose();
        g_dense += *wt * *r * j;
    }
    // The assembly adds a 1e-9 Levenberg term per prior row on the diagonal.
    let scale = a_dense.amax();
    assert!((&a - &a_dense).amax() < 1e-9 * scale + 1e-7, "{model:?}: JᵀWJ differs by {:e} (scale {scale:e})", (&a - &a_dense).amax());
    let g = nalgebra::DVector::from_vec(g);
    assert!((&g - &g_dense).amax() < 1e-9 * g_dense.amax().max(1.0), "{model:?}: JᵀWr differs by {:e}", (&g - &g_dense).amax());
}

/// The eigenvalues of the problem's normal matrix at the rest wall seen as it is.
fn eigenvalues(priors: bool, model: NodeModel) -> Vec<f64> {
    let (mut t, points, live) = setup(CameraMode::Joint, 0.0);
    t.params.w_rgb = 0.0;
    t.params.node_model = model;
    if !priors {
        (t.params.sigma_rest_m, t.params.sigma_step_m, t.params.sigma_step_rot, t.params.sigma_slide_m, t.params.sigma_camera_m, t.params.sigma_camera_rad) =
            (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    }
    let w = t.params.weights();
    let (problem, _, _) = t.problem(&points).unwrap();
    let mut layout = problem.layout(&points, &w).unwrap();
    problem.linearise(&points, &live, &Iso3::identity(), &nalgebra::Vector6::zeros(), &w, &mut layout, true);
    let mut e: Vec<f64> = dense(&layout.pattern).symmetric_eigenvalues().iter().copied().collect();
    e.sort_by(f64::total_cmp);
    e
}

#[test]
fn without_priors_camera_and_warp_share_a_six_dimensional_null_space_and_the_priors_remove_it() {
    for model in [NodeModel::Affine, NodeModel::Twist] {
        let free = eigenvalues(false, model);
        let largest = free[free.len() - 1];
        // Six directions (one rigid motion of camera and nodes alike) cost next to nothing (the
        // rotations not exactly nothing: live points sit up to half a pixel from the model
        // points); the seventh is a real deformation, two orders of magnitude up.
        assert!(free[5] < 1e-9 * largest, "{model:?}: 6th eigenvalue {:e} of {largest:e}", free[5]);
        assert!(free[6] > 100.0 * free[5], "{model:?}: 7th eigenvalue {:e} against the 6th {:e}: more than 6 free directions", free[6], free[5]);
        let anchored = eigenvalues(true, model);
        assert!(anchored[0] > 10.0 * free[5] && anchored[0] > 1e6 * free[0], "{model:?}: with the priors the smallest is {:e}", anchored[0]);
    }
}

#[test]
fn bad_input_falls_back_without_a_panic() {
    // No valid live pixel.
    let (mut t, points, _) = setup(CameraMode::Joint, 0.0);
    let empty = {
        let prep = GeometryParams { min_m: 0.001, max_m: 1.0, radius_px: 0, sigma_px: 1.0, sigma_m: 1.0, edge_jump_m: 0.01 };
        pyramid(DepthMap::new(160, 160), GrayF32::new(160, 160), (None, None), &cam(), 1, &prep).remove(0)
    };
    assert!(matches!(t.fit(&points, &empty, &Iso3::identity(), true).unwrap(), Fit::Fallback(_)));
    // NaN depth everywhere.
    let nan = {
        let prep = GeometryParams { min_m: 0.001, max_m: 1.0, radius_px: 0, sigma_px: 1.0, sigma_m: 1.0, edge_jump_m: 0.01 };
        pyramid(DepthMap::from_fn(160, 160, |_, _| [f32::NAN]), GrayF32::new(160, 160), (None, None), &cam(), 1, &prep).remove(0)
    };
    assert!(matches!(t.fit(&points, &nan, &Iso3::identity(), true).unwrap(), Fit::Fallback(_)));
    // A degenerate graph: one node, no edges.
    let (mut one, points, live) = setup(CameraMode::Joint, 0.0002);
    one.nodes = nodes::Nodes::new(one.params.reach_m);
    one.nodes.cover(&points[..1], one.params.node_spacing_m, 1);
    match one.fit(&points, &live, &Iso3::identity(), true) {
        Ok(Fit::Solved { warp, .. }) => assert!(warp.nodes.iter().all(|n| n.translation_m.iter().all(|v| v.is_finite()))),
        Ok(Fit::Fallback(_) | Fit::Still(..)) | Err(_) => {}
    }
    // Model points with NaN positions bind no node.
    let bad = vec![ModelPoint { x_world_m: Point3::new(f64::NAN, 0.0, 0.03), n_world: -Vector3::z(), gray_ref: None, sigma_m: 0.0 }; 10];
    assert!(matches!(t.fit(&bad, &live, &Iso3::identity(), true).unwrap(), Fit::Fallback(_)));
}

#[test]
fn a_points_weight_follows_the_live_depths_sigma_and_its_correlation() {
    let (t, points, mut live) = setup(CameraMode::Fixed, 0.0003);
    let mut w = t.params.weights();
    w.w_rgb = 0.0; // point-to-plane rows only
    w.point_stride_px = 4.0;
    let (problem, _, _) = t.problem(&points).unwrap();
    let t_wc = Iso3::identity();
    let sigma_live = 1e-3;
    let (width, height) = live.depth.size();
    live.sigma = Some(DepthMap::from_fn(width, height, |_, _| [sigma_live as f32]));
    // Independent pixels (correlation 0), then an error alike over 8 px with points 4 px apart:
    // four points per patch, so each weighs as if its σ² were four times the live one.
    for (correlation_px, count) in [(0.0, 1.0), (8.0, 4.0)] {
        live.sigma_correlation_px = correlation_px;
        let mut rows = 0;
        for (i, binding) in &problem.points {
            let p = &points[*i];
            problem.point_terms(&live, &t_wc, &w, p, binding, &mut |q: &super::system::Residual| {
                let (r, wt) = (q.r, q.w);
                let sigma = (w.sigma_icp_m * w.sigma_icp_m + sigma_live * sigma_live).sqrt();
                let expected = crate::track::icp_rgb::huber(r / sigma, w.huber_k) / (w.sigma_icp_m * w.sigma_icp_m + count * sigma_live * sigma_live);
                assert!((wt / expected - 1.0).abs() < 1e-5, "weight {wt} against {expected}");
                rows += 1;
            });
        }
        assert!(rows > 100, "{rows} point-to-plane rows");
    }
}

#[test]
fn the_gain_is_judged_over_a_window_of_solves() {
    let mut recent = std::collections::VecDeque::new();
    // One frame: the gain itself, to the bit (the default keeps the per-frame test).
    assert_eq!(windowed_gain(&mut recent, 0.123_456_789, 1), 0.123_456_789);
    recent.clear();
    // A still wall's occasional gain is averaged down by its neighbours ...
    for g in [0.0, -0.02, 0.01] {
        windowed_gain(&mut recent, g, 4);
    }
    let judged = windowed_gain(&mut recent, 0.15, 4);
    assert!((judged - 0.035).abs() < 1e-12, "{judged}");
    // ... a moving wall's sustained gain is not, and the oldest gains leave the window.
    for _ in 0..3 {
        windowed_gain(&mut recent, 0.12, 4);
    }
    let judged = windowed_gain(&mut recent, 0.12, 4);
    assert!((judged - 0.12).abs() < 1e-12, "{judged}");
    assert_eq!(recent.len(), 4);
    // A gain that is not finite (a term without residuals) is passed on and not remembered.
    assert!(windowed_gain(&mut recent, f64::NAN, 4).is_nan());
    assert_eq!(recent.len(), 4);
}

#[test]
fn a_clearly_still_wall_is_solved_on_every_nth_frame_only() {
    let mut probe = super::Probe::default();
    // Not judged still: every frame solves.
    assert!((0..10).all(|_| !probe.skips(8)));
    // Still: seven frames skip, the eighth probes, and so on.
    probe.still = true;
    let skips: Vec<bool> = (0..16).map(|_| probe.skips(8)).collect();
    let probes: Vec<usize> = (0..16).filter(|&i| !skips[i]).collect();
    assert_eq!(probes, vec![7, 15]);
    // Every frame when `still_probe_every_frames` = 1.
    assert!((0..10).all(|_| !probe.skips(1)));
}

/// The frames of the next `n` that probe (do not skip).
fn probes_within(probe: &mut super::Probe, first: u32, n: usize) -> Vec<usize> {
    (0..n).filter(|_| !probe.skips(first)).collect()
}

#[test]
fn the_still_probe_interval_doubles_while_the_wall_stays_still_and_resets_when_it_moves() {
    let (first, max) = (8, 32);
    let mut probe = super::Probe::default();
    // The first still verdict: every 8th frame.
    probe.verdict(true, (first, max));
    assert_eq!(probes_within(&mut probe, first, 8), vec![7]);
    // Each further still probe doubles it, up to 32.
    probe.verdict(true, (first, max));
    assert_eq!(probes_within(&mut probe, first, 16), vec![15]);
    probe.verdict(true, (first, max));
    assert_eq!(probes_within(&mut probe, first, 32), vec![31]);
    probe.verdict(true, (first, max));
    assert_eq!(probes_within(&mut probe, first, 64), vec![31, 63], "capped at 32");
    // A probe that is not clearly still ends the phase: every frame solves until it is again,
    // and the interval starts from 8 once more.
    probe.verdict(false, (first, max));
    assert!(probes_within(&mut probe, first, 5).len() == 5);
    probe.verdict(true, (first, max));
    assert_eq!(probes_within(&mut probe, first, 8), vec![7]);
    // A maximum equal to the first interval: the fixed interval of before.
    let mut fixed = super::Probe::default();
    for _ in 0..4 {
        fixed.verdict(true, (first, first));
    }
    assert_eq!(probes_within(&mut fixed, first, 24), vec![7, 15, 23]);
}

#[test]
fn a_rigid_residual_risen_between_probes_calls_the_next_probe_at_once() {
    let (first, max) = (8, 32);
    let mut probe = super::Probe::default();
    for _ in 0..3 {
        probe.verdict(true, (first, max));
    }
    assert_eq!(probes_within(&mut probe, first, 32), vec![31], "every 32nd frame");
    // Still frames between probes: 20 µm ± 1 µm. Not judged before four of them.
    assert!(!probe.observe(80e-6, 1.5), "the first frames only build the mean");
    let mut probe = super::Probe::default();
    for _ in 0..3 {
        probe.verdict(true, (first, max));
    }
    for k in 0..10 {
        assert!(probe.skips(first));
        assert!(!probe.observe(20e-6 + if k % 2 == 0 { 1e-6 } else { -1e-6 }, 1.5));
    }
    // 1.4× is within the factor, 1.6× beyond it: the next frame probes, then every 8th.
    assert!(probe.skips(first));
    assert!(!probe.observe(28e-6, 1.5));
    assert!(probe.skips(first));
    assert!(probe.observe(32e-6, 1.5));
    assert!(!probe.skips(first), "the frame after the rise probes");
    probe.verdict(true, (first, max));
    assert_eq!(probes_within(&mut probe, first, 16), vec![15], "the interval starts again from 8, doubled by the still probe");
    // Off with a factor of 0; a residual that is not finite is ignored.
    assert!(!probe.observe(1.0, 0.0));
    assert!(!probe.observe(f64::NAN, 1.5));
}

#[test]
fn a_clearly_moving_wall_starts_from_the_coarse_levels_on_all_but_every_nth_frame() {
    let mut moving = super::Moving::default();
    // Not yet clearly moving: every frame runs the full rigid start.
    assert!((0..10).all(|_| !moving.shortens(3, 8)));
    // Three judged solves that kept a warp with a clear gain, one without: the streak ends.
    moving.judged(true, 0.07, 0.06, 3);
    moving.judged(true, 0.07, 0.06, 3);
    moving.judged(true, 0.05, 0.06, 3);
    assert!(!moving.shortens(3, 8));
    moving.judged(false, f64::NAN, 0.06, 3);
    assert_eq!(moving.streak, 0);
    for _ in 0..3 {
        moving.judged(true, 0.08, 0.06, 3);
    }
    // Clearly moving: seven frames start coarse, the eighth runs the full start, and so on.
    let coarse: Vec<bool> = (0..16).map(|_| moving.shortens(3, 8)).collect();
    let full: Vec<usize> = (0..16).filter(|&i| !coarse[i]).collect();
    assert_eq!(full, vec![7, 15]);
    // Once clearly moving, a kept warp whose gain is below the clear gain keeps it moving
    // (hysteresis); before the streak was full, the same gain ended it (above).
    moving.judged(true, 0.04, 0.06, 3);
    assert_eq!(moving.streak, 4);
    assert!(moving.shortens(3, 8));
    // Never when `moving_probe_every_frames` = 1; a warp not kept on a full frame ends it.
    assert!((0..10).all(|_| !moving.shortens(3, 1)));
    moving.judged(false, 0.01, 0.06, 3);
    assert_eq!(moving.streak, 0);
    assert!((0..10).all(|_| !moving.shortens(3, 8)));
}

#[test]
fn a_camera_step_beyond_the_limit_holds_the_camera_and_still_warps() {
    let (pts, points, live) = moved_wall();
    // A rigid start 1 mm off along the view: the joint solve takes the camera back by about
    // 0.6 mm (the priors give the rest to the nodes), more than a `max_camera_step_m` of 0.3 mm.
    let offset = Vector3::new(0.0, 0.0, 0.001);
    let t_start = Iso3::translation(offset.x, offset.y, offset.z);
    for hold in [false, true] {
        let mut t = tracker(CameraMode::Joint);
        (t.params.hold_camera_on_step, t.params.max_camera_step_m) = (hold, 0.0003);
        (t.params.min_rms_gain, t.params.min_evidence) = (0.0, 0.0);
        t.nodes.cover(&points, t.params.node_spacing_m, 4096);
        match (hold, t.fit(&points, &live, &t_start, true).unwrap()) {
            (false, Fit::Fallback(why)) => assert!(why.contains("max_camera_step_m"), "{why}"),
            (true, Fit::Solved { t_world_cam, held, warp, .. }) => {
                assert!(held && t_world_cam == t_start, "the camera stays at the rigid start");
                // Seen from there, the wall is where the warp puts the model: the truth moved
                // with the camera's offset.
                let shifted: Vec<(ModelPoint, Point3<f64>)> = pts.iter().map(|(p, truth)| (*p, truth + offset)).collect();
                let err = warp_error(&warp, &shifted);
                assert!(err < 0.1e-3, "warp error {:.4} mm against the offset wall (0.047 measured)", err * 1e3);
            }
            (hold, Fit::Solved { t_world_cam, .. }) => panic!("hold_camera_on_step = {hold}: solved, camera at {:?}", t_world_cam.translation.vector),
            (hold, Fit::Fallback(why)) => panic!("hold_camera_on_step = {hold}: fell back: {why}"),
            (hold, Fit::Still(..)) => panic!("hold_camera_on_step = {hold}: judged still"),
        }
    }
}

#[test]
fn the_slide_prior_holds_nodes_nearer_the_direction_a_wave_moves_the_wall() {
    // Nodes 8 mm apart on a wall z = A sin(2π x / λ) (a 4 mm wave of 50 mm wavelength), which
    // moves along z; each node's neighbours are the 8 around it on the grid.
    let (amp_m, wavelength_m, spacing_m, side) = (0.004, 0.05, 0.008, 9usize);
    let tau = std::f64::consts::TAU;
    let mut normals = Vec::new();
    let mut neighbours = Vec::new();
    for i in 0..side {
        for j in 0..side {
            let x = i as f64 * spacing_m;
            let slope = amp_m * tau / wavelength_m * (tau * x / wavelength_m).cos();
            normals.push(Vector3::new(-slope, 0.0, 1.0).normalize());
            let mut nb = Vec::new();
            for (di, dj) in [(-1i64, -1i64), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)] {
                let (a, b) = (i as i64 + di, j as i64 + dj);
                if (0..side as i64).contains(&a) && (0..side as i64).contains(&b) {
                    nb.push(a as usize * side + b as usize);
                }
            }
            neighbours.push(nb);
        }
    }
    // The largest angle between a node's slide direction and the wall's motion, degrees.
    let tilt = |n: &[Vector3<f64>]| n.iter().map(|v| v.z.abs().min(1.0).acos().to_degrees()).fold(0.0, f64::max);
    let own = super::priors::smoothed_normals(&normals, &neighbours, 0);
    assert_eq!(own, normals, "no passes: the nodes' own normals");
    let (raw, one, two) =
        (tilt(&own), tilt(&super::priors::smoothed_normals(&normals, &neighbours, 1)), tilt(&super::priors::smoothed_normals(&normals, &neighbours, 2)));
    assert!((raw - 26.7).abs() < 0.2, "the wave's largest slope: {raw:.2}°");
    assert!(one < 0.8 * raw && two < 0.8 * one, "tilts {raw:.1}°, {one:.1}° after one pass, {two:.1}° after two");
    // A node without neighbours keeps its normal.
    assert_eq!(super::priors::smoothed_normals(&normals[..1], &[Vec::new()], 3), normals[..1].to_vec());
}

#[test]
fn a_problem_built_beside_the_rigid_start_solves_as_one_built_after_it() {
    // `track` covers the model points with nodes and builds the problem on a copy of the nodes
    // while the rigid start runs (`Ready`), relights the points, then solves. The fit must be the
    // one of covering and building after the rigid start, on the relit points (the problem
    // names its points by index: the references read at solve time are the relit ones).
    let (_, points, live) = moved_wall();
    let relit: Vec<ModelPoint> = points.iter().map(|p| ModelPoint { gray_ref: p.gray_ref.map(|g| 0.9 * g), ..*p }).collect();
    let mut after = tracker(CameraMode::Joint);
    after.nodes.cover(&points, after.params.node_spacing_m, 4096);
    let covered = after.nodes.nodes.clone();
    let expected = after.fit(&relit, &live, &Iso3::identity(), true).unwrap();

    let mut beside = tracker(CameraMode::Joint);
    let ready = Ready::new(&beside.nodes, &beside.params, &mut beside.cache, &points);
    assert!(beside.nodes.nodes.is_empty(), "the tracker's nodes change only once the frame goes on");
    assert_eq!(ready.nodes.nodes, covered);
    assert_eq!(ready.added, covered.len());
    beside.nodes = ready.nodes;
    let got = beside.fit_built(&relit, ready.built, &live, &Iso3::identity(), true).unwrap();
    let (Fit::Solved { t_world_cam: a, warp: wa, .. }, Fit::Solved { t_world_cam: b, warp: wb, .. }) = (expected, got) else { panic!("a fit fell back") };
    assert_eq!(a, b, "the pose");
    assert_eq!(wa, wb, "the warp");
    assert_eq!(beside.nodes.nodes, after.nodes.nodes, "the nodes moved alike");
    // With the old references the same problem fits otherwise: the relit ones were used.
    let mut old = tracker(CameraMode::Joint);
    old.nodes.cover(&points, old.params.node_spacing_m, 4096);
    let Fit::Solved { warp: w_old, .. } = old.fit(&points, &live, &Iso3::identity(), true).unwrap() else { panic!("fell back") };
    assert_ne!(w_old, wb);

    // On nodes that already cover the points (none added), `Ready` binds them with the lists of
    // nodes within reach it found for the cover: the same problem as one built afresh.
    let mut fresh = tracker(CameraMode::Joint);
    fresh.nodes.cover(&points, fresh.params.node_spacing_m, 4096);
    let expected = fresh.fit(&relit, &live, &Iso3::identity(), true).unwrap();
    let mut reused = tracker(CameraMode::Joint);
    reused.nodes.cover(&points, reused.params.node_spacing_m, 4096);
    let ready = Ready::new(&reused.nodes, &reused.params, &mut reused.cache, &points);
    assert_eq!(ready.added, 0);
    reused.nodes = ready.nodes;
    let got = reused.fit_built(&relit, ready.built, &live, &Iso3::identity(), true).unwrap();
    let (Fit::Solved { t_world_cam: a, warp: wa, .. }, Fit::Solved { t_world_cam: b, warp: wb, .. }) = (expected, got) else { panic!("a fit fell back") };
    assert_eq!((a, wa), (b, wb), "the pose and the warp");

    // A frame that lost track drops its problem and gives the analysis back: the next solve of
    // the same pattern reuses it, as it would have without the frame.
    for release in [false, true] {
        let mut t = tracker(CameraMode::Joint);
        t.nodes.cover(&points, t.params.node_spacing_m, 4096);
        let ready = Ready::new(&t.nodes, &t.params, &mut t.cache, &points);
        assert_eq!(ready.added, 0);
        if release {
            ready.release(&mut t.cache);
        }
        let Fit::Solved { outcome, .. } = t.fit(&points, &live, &Iso3::identity(), true).unwrap() else { panic!("fell back") };
        assert_eq!(outcome.analyses, usize::from(!release), "release {release}");
    }
}

#[test]
fn a_resampled_live_pixel_weighs_the_photometric_row_by_its_share_only() {
    let (t, points, live) = setup(CameraMode::Joint, 0.0003);
    let w = t.params.weights();
    let (problem, _, _) = t.problem(&points).unwrap();
    let t_wc = Iso3::identity();
    // The live level as an undistortion would give it: a third of a source pixel per pixel.
    let mut stretched = live.clone();
    let (lw, lh) = live.depth.size();
    stretched.share = Some(std::sync::Arc::new(capsule_slam_framework::GrayF32::from_fn(lw, lh, |_, _| [1.0 / 3.0])));
    let rows = |level: &Level| {
        let mut out: Vec<(f64, f64)> = Vec::new();
        for (i, binding) in &problem.points {
            problem.point_terms(level, &t_wc, &w, &points[*i], binding, &mut |q: &super::system::Residual| out.push((q.r, q.w)));
        }
        out
    };
    let (plain, shared) = (rows(&live), rows(&stretched));
    assert_eq!(plain.len(), shared.len());
    // Point-to-plane rows carry a residual in metres (below a millimetre here), photometric ones
    // an intensity difference; each point gives its point-to-plane row first.
    let (mut photometric, mut geometric) = (0, 0);
    for ((r, wp), (r2, ws)) in plain.iter().zip(&shared) {
        assert_eq!(r, r2);
        if (ws - wp).abs() < 1e-15 * wp.abs() {
            geometric += 1;
        } else {
            assert!((ws - wp / 3.0).abs() < 1e-7 * wp.abs(), "a row weighs {ws} against {wp} (the share is an f32)");
            photometric += 1;
        }
    }
    assert!(photometric > 100 && geometric > 100, "{photometric} photometric and {geometric} point-to-plane rows");
    assert!(live.share.is_none() && (0..lw).all(|x| live.share_at(x, lh / 2) == 1.0));
}
