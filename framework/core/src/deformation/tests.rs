//! Tests of the deformation: identity, weights, rigid motion, time windows, reach.

use super::*;
use nalgebra::Rotation3;
use proptest::prelude::*;

fn grid(k: usize) -> Deformation {
    let mut nodes = Vec::new();
    for i in 0..4 {
        for j in 0..4 {
            nodes.push(DeformationNode::identity(Point3::new(i as f64 * 0.01, j as f64 * 0.01, 0.0), 0));
        }
    }
    Deformation::new(nodes, k, Window::All)
}

proptest! {
    #[test]
    fn identity_deformation_is_a_no_op(x in -0.01f64..0.05, y in -0.01f64..0.05, z in -0.01f64..0.01) {
        let d = grid(4);
        let p = Point3::new(x, y, z);
        prop_assert!((d.warp_point(&p, 0) - p).norm() < 1e-12);
        let n = Vector3::new(0.3, -0.2, 0.9).normalize();
        prop_assert!((d.warp_normal(&p, &n, 0) - n).norm() < 1e-12);
    }

    /// The grid's candidates of any point hold every node within the reach (so the warper
    /// finds what a scan of all nodes finds), whatever the nodes' spread and the reach.
    #[test]
    fn the_grid_holds_every_node_within_the_reach(
        seed in 0u64..1000,
        spread in 0.005f64..0.5,
        reach in 0.001f64..0.05,
        px in -0.2f64..1.2, py in -0.2f64..1.2, pz in -0.2f64..1.2,
    ) {
        // Nodes from a small linear congruential sequence in a cube of side `spread`.
        let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut next = || { state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407); (state >> 11) as f64 / (1u64 << 53) as f64 };
        let nodes: Vec<Point3<f64>> = (0..60).map(|_| Point3::new(next() * spread, next() * spread, next() * spread)).collect();
        let grid = super::grid::NodeGrid::new(&nodes, reach);
        let p = Point3::new(px, py, pz) * spread;
        let near = grid.near(&p);
        for (i, n) in nodes.iter().enumerate() {
            if (n - p).norm_squared() <= reach * reach {
                prop_assert!(near.contains(&i), "node {} at {} m of the point, reach {}", i, (n - p).norm(), reach);
            }
        }
    }

    #[test]
    fn weights_sum_to_one(x in -0.01f64..0.05, y in -0.01f64..0.05) {
        let w = grid(4).influences(&Point3::new(x, y, 0.003), 0);
        prop_assert_eq!(w.len(), 4);
        prop_assert!((w.iter().map(|x| x.1).sum::<f64>() - 1.0).abs() < 1e-12);
    }
}

#[test]
fn rigid_deformation_moves_points_and_poses_rigidly() {
    let rot = Rotation3::from_euler_angles(0.1, -0.05, 0.2);
    let shift = Vector3::new(0.002, -0.001, 0.003);
    let mut d = grid(4);
    // A rigid motion x ↦ R x + s expressed per node: R (v − g) + g + t with t = R g + s − g.
    for n in &mut d.nodes {
        n.rotation = *rot.matrix();
        n.translation_m = rot * n.position_m.coords + shift - n.position_m.coords;
    }
    let p = Point3::new(0.013, 0.021, 0.002);
    assert!((d.warp_point(&p, 0) - (rot * p + shift)).norm() < 1e-12);
    let n = Vector3::new(0.0, 0.6, 0.8);
    assert!((d.warp_normal(&p, &n, 0) - rot * n).norm() < 1e-12);
    let pose = Iso3::translation(0.01, 0.01, -0.02);
    for d in [d.clone(), d.poses_by(PoseWarp::View { depth_m: 0.02 })] {
        let warped = d.warp_pose(&pose, 0);
        assert!((warped.rotation.to_rotation_matrix().matrix() - rot.matrix()).norm() < 1e-9);
        assert!((warped.translation.vector - (rot * pose.translation.vector + shift)).norm() < 1e-12);
    }
}

#[test]
fn a_time_window_keeps_crossing_surfaces_apart() {
    // Two layers of nodes at the same place, an old one (t0 0..16) that stays and a new one
    // (t0 100..116) that moves by 2 mm: with a window of 16, a point of time 3 or 120 follows
    // its own layer only.
    let old = grid(4).nodes;
    let new: Vec<DeformationNode> =
        old.iter().enumerate().map(|(i, n)| DeformationNode { time: 100 + i as u32, translation_m: Vector3::new(0.0, 0.0, 0.002), ..*n }).collect();
    let old: Vec<DeformationNode> = old.iter().enumerate().map(|(i, n)| DeformationNode { time: i as u32, ..*n }).collect();
    let p = Point3::new(0.012, 0.017, 0.0);
    let windowed = Deformation::new([new.clone(), old.clone()].concat(), 4, Window::Nodes(16));
    assert!((windowed.warp_point(&p, 3) - p).norm() < 1e-12, "an old point stays");
    assert!((windowed.warp_point(&p, 120) - (p + Vector3::new(0.0, 0.0, 0.002))).norm() < 1e-12, "a new point moves");
    let spatial = Deformation::new([new.clone(), old.clone()].concat(), 4, Window::All);
    let mixed = spatial.warp_point(&p, 3).z;
    assert!(mixed > 0.0 && mixed < 0.002, "without a window the layers mix: {mixed}");
    // The window is the m nodes up to the nearest in time, completed forward.
    assert_eq!(windowed.candidates(0), 0..16);
    assert_eq!(windowed.candidates(108), 9..25);
    assert_eq!(windowed.candidates(200), 16..32);
    assert_eq!(windowed.candidates(20), 0..16);
    assert_eq!(windowed.candidates(57), 0..16, "node 15 (t0 15) is nearer than node 16 (t0 100)");
    assert_eq!(windowed.candidates(58), 1..17, "node 16 is nearer");
    // A window of frames: the same separation, whatever the node counts.
    let framed = Deformation::new([new, old].concat(), 4, Window::Frames(30));
    assert!((framed.warp_point(&p, 3) - p).norm() < 1e-12, "an old point stays");
    assert!((framed.warp_point(&p, 120) - (p + Vector3::new(0.0, 0.0, 0.002))).norm() < 1e-12, "a new point moves");
    assert_eq!(framed.candidates(10), 0..16);
    assert_eq!(framed.candidates(140), 26..32, "frames 110 to 170 hold the nodes of times 110..115");
    assert_eq!(framed.candidates(60), 12..17, "no node within 30 frames: the k + 1 nearest in time (up to time 100)");
}

#[test]
fn a_surfel_is_warped_by_the_time_the_deformation_names() {
    // Old nodes (time 0..16) stay, new ones (100..116) move by 2 mm; a surfel created at 5
    // and last seen at 110 moves with the new layer when timed by last sighting.
    let old = grid(4).nodes;
    let new: Vec<DeformationNode> =
        old.iter().enumerate().map(|(i, n)| DeformationNode { time: 100 + i as u32, translation_m: Vector3::new(0.0, 0.0, 0.002), ..*n }).collect();
    let old: Vec<DeformationNode> = old.iter().enumerate().map(|(i, n)| DeformationNode { time: i as u32, ..*n }).collect();
    let d = Deformation::new([new, old].concat(), 4, Window::Frames(30));
    let s = Surfel {
        position_m: Point3::new(0.012, 0.017, 0.0),
        normal: Vector3::z(),
        colour: [0; 3],
        confidence: 10.0,
        radius_m: 0.001,
        t0: 5,
        t: 110,
        albedo: 0.0,
        sigma_m: 0.0,
        warp_m: nalgebra::Vector3::zeros(),
    };
    let mut created = s;
    d.clone().warp_surfel(&mut created);
    assert_eq!(created.position_m, s.position_m, "timed by creation it stays");
    let mut skipped = s;
    d.warper().warp_surfel(&mut skipped);
    assert_eq!(skipped, created, "the warper skips the window of undeformed old nodes");
    let mut seen = s;
    let d = d.timed_by(SurfelTime::LastSeen);
    let mut fast = s;
    d.warper().warp_surfel(&mut fast);
    d.warp_surfel(&mut seen);
    assert_eq!(fast, seen);
    assert!((seen.position_m.z - 0.002).abs() < 1e-7, "timed by last sighting it moves: {}", seen.position_m);
    assert!((seen.normal.norm() - 1.0).abs() < 1e-6);
}

#[test]
fn orthonormalise_returns_a_rotation() {
    let m = Matrix3::new(1.1, 0.1, 0.0, -0.05, 0.9, 0.02, 0.0, 0.03, 1.2);
    let r = orthonormalise(&m);
    assert!((r.matrix() * r.matrix().transpose() - Matrix3::identity()).norm() < 1e-12);
    assert!((r.matrix().determinant() - 1.0).abs() < 1e-12);
}

#[test]
fn a_reach_leaves_far_points_alone_and_the_grid_agrees_with_the_scan() {
    // The 4 × 4 grid of nodes 10 mm apart, all moved 1 mm along z, reach 12 mm.
    let mut d = grid(4).within(0.012).timed_by(SurfelTime::LastSeen);
    for n in &mut d.nodes {
        n.translation_m = Vector3::new(0.0, 0.0, 0.001);
    }
    let surfel = |x: f32, y: f32| Surfel {
        position_m: Point3::new(x, y, 0.0),
        normal: Vector3::z(),
        colour: [0; 3],
        confidence: 1.0,
        radius_m: 0.001,
        t0: 0,
        t: 0,
        albedo: 0.0,
        sigma_m: 0.0,
        warp_m: nalgebra::Vector3::zeros(),
    };
    let warper = d.warper();
    for (x, y, moves) in [(0.012, 0.017, true), (0.031, -0.005, true), (0.06, 0.06, false), (-0.03, 0.01, false)] {
        let (mut a, mut b) = (surfel(x, y), surfel(x, y));
        d.warp_surfel(&mut a);
        warper.warp_surfel(&mut b);
        assert_eq!(a, b, "the grid finds the same nodes as the scan at ({x}, {y})");
        let dz = f64::from(a.position_m.z);
        assert!(if moves { (dz - 0.001).abs() < 1e-9 } else { dz == 0.0 }, "({x}, {y}) moved {dz}");
    }
    // Without a reach, the far point follows the nearest nodes (Sumner).
    let mut far = surfel(0.06, 0.06);
    Deformation { reach_m: None, ..d.clone() }.warp_surfel(&mut far);
    assert!((f64::from(far.position_m.z) - 0.001).abs() < 1e-9);
}

/// Eq. (7) by its definition: every candidate within the reach sorted by distance (then index),
/// the (k+1)-th nearest (or the reach, or 1.01 × the farthest) as d_max, the k nearest weighted
/// `(1 − d / d_max)²` and normalised.
fn influences_by_definition(d: &Deformation, p: &Point3<f64>) -> Vec<(usize, f64)> {
    let k = d.k.max(1);
    let mut all: Vec<(usize, f64)> =
        (0..d.nodes.len()).map(|i| (i, (p - d.nodes[i].position_m).norm_squared())).filter(|x| d.reach_m.is_none_or(|r| x.1 <= r * r)).collect();
    all.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    let dist: Vec<(usize, f64)> = all.iter().map(|&(i, d2)| (i, d2.sqrt())).collect();
    let d_max = match (dist.get(k), d.reach_m) {
        (Some(x), _) => x.1,
        (None, Some(r)) => r,
        (None, None) => dist.last().map_or(0.0, |x| 1.01 * x.1),
    };
    let w: Vec<(usize, f64)> = dist.iter().take(k).map(|&(i, di)| (i, if d_max > 0.0 { (1.0 - di / d_max).max(0.0).powi(2) } else { 1.0 })).collect();
    let sum: f64 = w.iter().map(|x| x.1).sum();
    if sum > 0.0 { w.iter().map(|&(i, x)| (i, x / sum)).collect() } else { w.first().map(|&(i, _)| vec![(i, 1.0)]).unwrap_or_default() }
}

/// The stack path (k < 16) and the heap path (k ≥ 16) of the influences match the definition,
/// to the bit, with and without a reach, on nodes with tied distances (a lattice) and on points
/// with fewer than k + 1 nodes in reach.
#[test]
fn influences_match_their_definition_on_both_paths() {
    let nodes: Vec<DeformationNode> = (0..64).map(|i| DeformationNode::identity(Point3::new((i % 8) as f64 * 0.004, (i / 8) as f64 * 0.004, 0.0), 0)).collect();
    for k in [1, 4, 8, 15, 16, 24] {
        for reach in [None, Some(0.006), Some(0.02)] {
            let d = Deformation { reach_m: reach, ..Deformation::new(nodes.clone(), k, Window::All) };
            for p in [Point3::new(0.014, 0.014, 0.0), Point3::new(0.0131, 0.0077, 0.002), Point3::new(-0.003, 0.029, 0.001), Point3::new(0.2, 0.2, 0.0)] {
                let got = d.influences(&p, 0);
                assert_eq!(got, influences_by_definition(&d, &p), "k {k}, reach {reach:?}, point {p}");
                assert_eq!(d.with_influences(&p, 0..nodes.len(), <[(usize, f64)]>::to_vec), got);
            }
        }
    }
}
