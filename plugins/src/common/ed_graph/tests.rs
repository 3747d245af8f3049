use capsule_slam_framework::Iso3;
use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
use nalgebra::{Matrix3, Point3, UnitQuaternion, Vector3};

use super::{Constraint, Edges, Graph, GraphWeights, NodeModel, time_neighbours};

/// A 40 × 40 mm sheet of points at z = 30 mm sampled every `step_m`, with times increasing
/// along x (as a capsule sweeping it would see them).
fn sheet(step_m: f64) -> Vec<(Point3<f64>, u32)> {
    let n = (0.04 / step_m).round() as usize;
    let mut out = Vec::new();
    for i in 0..=n {
        for j in 0..=n {
            out.push((Point3::new(i as f64 * step_m, j as f64 * step_m, 0.03), i as u32));
        }
    }
    out
}

/// A smooth bend: up to 2 mm out of the plane, quadratic in x.
fn bend(p: &Point3<f64>) -> Point3<f64> {
    p + Vector3::new(0.0, 0.0, 0.002 * (p.x / 0.04).powi(2))
}

fn graph_on_sheet(node_step_m: f64, edges: Edges) -> Graph {
    let nodes = sheet(node_step_m).into_iter().map(|(p, t)| DeformationNode::identity(p, t)).collect();
    Graph::new(Deformation::new(nodes, 4, Window::Nodes(20)), 4, edges)
}

#[test]
fn time_neighbours_follow_elastic_fusion() {
    assert_eq!(time_neighbours(5, 10, 4), vec![3, 4, 6, 7]);
    assert_eq!(time_neighbours(0, 10, 4), vec![1, 2, 3, 4]);
    assert_eq!(time_neighbours(9, 10, 4), vec![5, 6, 7, 8]);
    assert_eq!(time_neighbours(1, 3, 4), vec![0, 2]);
}

/// A node transform off the identity for node `j` (`f` a phase): an affine R near a rotation
/// for the affine model, a rotation for the twist.
fn perturbed(model: NodeModel, f: f64) -> Matrix3<f64> {
    match model {
        NodeModel::Affine => Matrix3::identity() + Matrix3::new(f.sin(), 0.1, -0.05, 0.02, f.cos() * 0.1, 0.03, -0.04, 0.01, 0.05) * 0.1,
        NodeModel::Twist => *nalgebra::Rotation3::new(Vector3::new(f.sin(), 0.3, f.cos()) * 0.05).matrix(),
    }
}

#[test]
fn the_jacobian_matches_finite_differences() {
    for model in [NodeModel::Affine, NodeModel::Twist] {
        jacobian_matches_finite_differences(model);
    }
}

fn jacobian_matches_finite_differences(model: NodeModel) {
    let mut g = graph_on_sheet(0.01, Edges::Time).with_model(model);
    // A non-trivial state: perturb every node.
    for (j, n) in g.deformation.nodes.iter_mut().enumerate() {
        let f = j as f64 * 0.37;
        n.rotation = perturbed(model, f);
        n.translation_m = Vector3::new(f.cos(), f.sin(), 0.5) * 1e-3;
    }
    for (i, (p, t)) in sheet(0.007).into_iter().enumerate().step_by(3) {
        g.constrain(Constraint { source_m: p, target_m: bend(&p) + Vector3::new(0.0, 1e-4 * i as f64, 0.0), time: t });
    }
    let w = GraphWeights::default();
    let r0 = g.residuals(&w);
    let n_unknowns = g.unknowns();
    let mut jac = vec![std::collections::BTreeMap::new(); r0.len()];
    let mut k = 0;
    g.visit(&w, |_, row| {
        for &(u, v) in row {
            *jac[k].entry(u).or_insert(0.0) += v;
        }
        k += 1;
    });
    let h = 1e-7;
    let mut checked = 0;
    for u in (0..n_unknowns).step_by(5) {
        let mut step = vec![0.0; n_unknowns];
        step[u] = h;
        g.shift(&step, 1.0);
        let rp = g.residuals(&w);
        g.shift(&step, -2.0);
        let rm = g.residuals(&w);
        g.shift(&step, 1.0);
        for (row, (a, b)) in rp.iter().zip(&rm).enumerate() {
            let numeric = (a - b) / (2.0 * h);
            let analytic = jac[row].get(&u).copied().unwrap_or(0.0);
            assert!((numeric - analytic).abs() < 1e-5 * (1.0 + numeric.abs()), "{model:?}: residual {row}, unknown {u}: {analytic} vs {numeric}");
            checked += usize::from(numeric != 0.0);
        }
    }
    assert!(checked > 100, "{model:?}: {checked} non-zero derivatives checked");
}

#[test]
fn satisfied_constraints_give_the_identity() {
    let mut g = graph_on_sheet(0.008, Edges::SpaceInWindow);
    for (p, t) in sheet(0.005) {
        g.constrain(Constraint { source_m: p, target_m: p, time: t });
    }
    let s = g.optimise(&GraphWeights::default()).unwrap();
    assert!(s.energy_before < 1e-20 && s.energy_after <= s.energy_before, "{s:?}");
    for n in &g.deformation.nodes {
        assert!((n.rotation - Matrix3::identity()).norm() < 1e-12 && n.translation_m.norm() < 1e-15, "{n:?}");
    }
}

#[test]
fn a_smooth_bend_is_recovered_from_sparse_constraints() {
    for model in [NodeModel::Affine, NodeModel::Twist] {
        smooth_bend_is_recovered(model);
    }
}

fn smooth_bend_is_recovered(model: NodeModel) {
    // Nodes every 5 mm, constraints on a 10 mm grid (25 points of 1681), the bend 2 mm deep.
    let mut g = graph_on_sheet(0.005, Edges::SpaceInWindow).with_model(model);
    for (p, t) in sheet(0.01) {
        g.constrain(Constraint { source_m: p, target_m: bend(&p), time: t });
    }
    let s = g.optimise(&GraphWeights::default()).unwrap();
    assert!(s.energy_after < 0.01 * s.energy_before, "{s:?}");
    let d = &g.deformation;
    let (mut worst, mut sum_angle, mut sum_unwarped, mut count): (f64, f64, f64, usize) = (0.0, 0.0, 0.0, 0);
    for (p, t) in sheet(0.001) {
        worst = worst.max((d.warp_point(&p, t) - bend(&p)).norm());
        // Normals of the bent sheet: the warped normal stays unit length and turns with the slope.
        let n = d.warp_normal(&p, &Vector3::z(), t);
        assert!((n.norm() - 1.0).abs() < 1e-12);
        let slope = 2.0 * 0.002 * p.x / (0.04 * 0.04);
        let truth = Vector3::new(-slope, 0.0, 1.0).normalize();
        sum_angle += n.angle(&truth);
        sum_unwarped += Vector3::z().angle(&truth);
        count += 1;
    }
    assert!(worst < 0.5e-3, "{model:?}: worst point error {worst} m");
    // The nodes turn the normals part of the way (measured, affine: mean error 0.022 rad
    // against 0.05 unwarped); the regulariser trades the rest for smoothness.
    assert!(sum_angle < 0.5 * sum_unwarped, "{model:?}: mean normal error {} rad, unwarped {}", sum_angle / count as f64, sum_unwarped / count as f64);
    if model == NodeModel::Twist {
        assert!(d.nodes.iter().all(|n| (n.rotation.transpose() * n.rotation - Matrix3::identity()).norm() < 1e-12), "twist nodes stay rotations");
    }
    // A camera looking at the sheet moves with it.
    let pose = Iso3::from_parts(Vector3::new(0.03, 0.02, 0.03).into(), UnitQuaternion::identity());
    let warped = d.warp_pose(&pose, 30);
    let expected = bend(&Point3::from(pose.translation.vector));
    assert!((warped.translation.vector - expected.coords).norm() < 0.5e-3, "{warped:?}");
}

#[test]
fn fixed_nodes_stay_and_the_free_ones_take_the_bend() {
    // The sheet's first columns (times 0..=2) are held; a 1 mm lift is asked of the last column.
    let mut g = graph_on_sheet(0.005, Edges::SpaceInWindow);
    let held: Vec<usize> = (0..g.deformation.nodes.len()).filter(|&i| g.deformation.nodes[i].time <= 2).collect();
    for &i in &held {
        g.fix(i);
    }
    for (p, t) in sheet(0.005).into_iter().filter(|(p, _)| p.x > 0.035) {
        g.constrain(Constraint { source_m: p, target_m: p + Vector3::new(0.0, 0.0, 0.001), time: t });
    }
    let s = g.optimise(&GraphWeights::default()).unwrap();
    assert!(s.energy_after < 0.05 * s.energy_before, "{s:?}");
    for &i in &held {
        let n = &g.deformation.nodes[i];
        assert_eq!((n.rotation, n.translation_m), (Matrix3::identity(), Vector3::zeros()), "node {i} moved");
    }
    let lifted = g.deformation.warp_point(&Point3::new(0.04, 0.02, 0.03), 8);
    assert!((lifted.z - 0.031).abs() < 2e-4, "the constrained edge rises by 1 mm: {lifted}");
}

#[test]
fn the_assembled_normal_equations_equal_the_dense_jacobian_products() {
    for model in [NodeModel::Affine, NodeModel::Twist] {
        assembled_normal_equations_equal_the_dense_products(model);
    }
}

fn assembled_normal_equations_equal_the_dense_products(model: NodeModel) {
    let mut g = graph_on_sheet(0.01, Edges::SpaceInWindow).with_model(model);
    for (j, n) in g.deformation.nodes.iter_mut().enumerate() {
        let f = j as f64 * 0.53;
        n.rotation = perturbed(model, f);
        n.translation_m = Vector3::new(f.sin(), 0.2, f.cos()) * 1e-3;
    }
    for (p, t) in sheet(0.008) {
        g.constrain(Constraint { source_m: p, target_m: bend(&p), time: t });
    }
    let w = GraphWeights::default();
    let n = g.unknowns();
    // Dense J and r from the rows the solver visits.
    let mut rows: Vec<(f64, Vec<(usize, f64)>)> = Vec::new();
    g.visit(&w, |r, row| rows.push((r, row.to_vec())));
    let mut jtj = nalgebra::DMatrix::<f64>::zeros(n, n);
    let mut jtr = nalgebra::DVector::<f64>::zeros(n);
    for (r, row) in &rows {
        for &(i, ji) in row {
            jtr[i] += ji * r;
            for &(k, jk) in row {
                jtj[(i, k)] += ji * jk;
            }
        }
    }
    let mut normal = g.normal_pattern(&w, n).unwrap();
    let grad = g.assemble(&w, &mut normal);
    for i in 0..n {
        assert!((grad[i] - jtr[i]).abs() <= 1e-9 * (1.0 + jtr[i].abs()), "gradient {i}: {} vs {}", grad[i], jtr[i]);
    }
    // Every stored entry of the lower triangle equals the dense product (the diagonal carries
    // the 1e-9 Levenberg term); every dense entry outside the pattern is zero.
    let (col_ptr, row_idx) = (normal.a.symbolic().col_ptr().to_vec(), normal.a.symbolic().row_idx().to_vec());
    let vals = normal.a.val_mut().to_vec();
    let mut covered = nalgebra::DMatrix::<bool>::from_element(n, n, false);
    for c in 0..n {
        for s in col_ptr[c]..col_ptr[c + 1] {
            let r = row_idx[s];
            let expected = jtj[(r, c)] + if r == c { 1e-9 } else { 0.0 };
            assert!((vals[s] - expected).abs() <= 1e-9 * (1.0 + expected.abs()), "({r}, {c}): {} vs {expected}", vals[s]);
            covered[(r, c)] = true;
        }
    }
    for c in 0..n {
        for r in c..n {
            assert!(covered[(r, c)] || jtj[(r, c)] == 0.0, "({r}, {c}) = {} is outside the pattern", jtj[(r, c)]);
        }
    }
}
