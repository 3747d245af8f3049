//! The deformation graph (issue 7): the Gauss-Newton solve against the node count (64 to 4096
//! nodes on a curved sheet with one surface constraint and one pin per node, as a closure
//! gives), one factorisation per iteration; and warping a map of 100 000 surfels by a solved
//! 1024-node graph whose older half is frozen (the fuser's share of a closure), and by a
//! tracker's warp of the surface in view (nodes with a reach: the fuser's share of a frame of
//! `nonrigid`).

use capsule_slam_framework::Surfel;
use capsule_slam_framework::deformation::{Deformation, DeformationNode, SurfelTime, Window};
use capsule_slam_plugins::common::ed_graph::{Constraint, Edges, Graph, GraphWeights};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};

/// `n` nodes on a 40 mm square sheet, in sweep (time) order, plus one constraint per node that
/// bends the newer half by up to 1 mm and one pin per node that holds the older half.
fn graph(n: usize) -> Graph {
    let side = (n as f64).sqrt().ceil() as usize;
    let step = 0.04 / side as f64;
    let nodes: Vec<DeformationNode> =
        (0..n).map(|i| DeformationNode::identity(Point3::new((i / side) as f64 * step, (i % side) as f64 * step, 0.03), (i / side) as u32)).collect();
    let mut g = Graph::new(Deformation::new(nodes.clone(), 4, Window::Nodes(20)), 4, Edges::SpaceInWindow);
    let half = (side / 2) as u32;
    for node in &nodes {
        let p = node.position_m + Vector3::new(0.3 * step, 0.4 * step, 0.0);
        if node.time >= half {
            let bend = 0.001 * ((node.time - half) as f64 / half.max(1) as f64).powi(2);
            g.constrain(Constraint { source_m: p, target_m: p + Vector3::new(0.0, 0.0, bend), time: node.time });
        } else {
            g.constrain(Constraint { source_m: p, target_m: p, time: node.time });
        }
    }
    g
}

fn solve(c: &mut Criterion) {
    capsule_slam_benches::link();
    let mut group = c.benchmark_group("deformation-graph-solve");
    group.sample_size(10);
    for n in [64usize, 256, 1024, 4096] {
        group.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, &n| {
            b.iter_batched(|| graph(n), |mut g| g.optimise(&GraphWeights::default()).unwrap_or_else(|e| panic!("{e}")), criterion::BatchSize::LargeInput)
        });
    }
    group.finish();
}

fn warp_map(c: &mut Criterion) {
    let mut g = graph(1024);
    let half = g.deformation.nodes.iter().map(|n| n.time).max().unwrap_or(0) / 2;
    for i in 0..g.deformation.nodes.len() {
        if g.deformation.nodes[i].time < half {
            g.fix(i);
        }
    }
    g.optimise(&GraphWeights::default()).unwrap_or_else(|e| panic!("{e}"));
    let d = Deformation { window: Window::Frames(2), ..g.deformation.clone() }.timed_by(SurfelTime::LastSeen);
    let side = 32u32;
    let map: Vec<Surfel> = (0..100_000u32)
        .map(|i| {
            let (x, y) = ((i % 316) as f32 / 316.0 * 0.04, (i / 316) as f32 / 316.0 * 0.04);
            sheet_surfel(x, y, (x / 0.04 * side as f32) as u32)
        })
        .collect();
    bench_warp(c, "deformation-warp-map/100000", &d, &map, false);
}

/// Times warping a copy of `map` by `d` (as the fuser does: in parallel, through a
/// [`Deformation::warper`]; as a tracker's motion when `motion`).
fn bench_warp(c: &mut Criterion, id: &str, d: &Deformation, map: &[Surfel], motion: bool) {
    use rayon::prelude::*;
    c.bench_function(id, |b| {
        b.iter_batched(
            || map.to_vec(),
            |mut m| {
                let w = d.warper();
                if motion {
                    m.par_iter_mut().for_each(|s| w.warp_surfel_as_motion(s));
                } else {
                    m.par_iter_mut().for_each(|s| w.warp_surfel(s));
                }
                m
            },
            criterion::BatchSize::LargeInput,
        )
    });
}

/// A tracker's warp (`nonrigid`): 81 nodes 8 mm apart on a 64 mm square in the middle of a
/// 100 mm square map of 100 000 surfels, each node moved up to 0.5 mm, reach 16 mm (so almost
/// every surfel has nodes within it), every node a candidate of every surfel.
fn warp_map_reach(c: &mut Criterion) {
    let nodes: Vec<DeformationNode> = (0..81)
        .map(|i| {
            let mut n = DeformationNode::identity(Point3::new(0.018 + (i % 9) as f64 * 0.008, 0.018 + (i / 9) as f64 * 0.008, 0.03), 0);
            n.translation_m = Vector3::new(0.0, 0.0, 0.0005 * ((i % 9) as f64 * 0.7).sin());
            n
        })
        .collect();
    let d = Deformation::new(nodes, 4, Window::All).within(0.016).timed_by(SurfelTime::LastSeen);
    let map: Vec<Surfel> = (0..100_000u32).map(|i| sheet_surfel((i % 316) as f32 / 316.0 * 0.1, (i / 316) as f32 / 316.0 * 0.1, 0)).collect();
    bench_warp(c, "deformation-warp-map-reach/100000", &d, &map, true);
}

/// A surfel at (x, y) on the plane z = 30 mm, facing +z, last seen at frame `t`.
fn sheet_surfel(x: f32, y: f32, t: u32) -> Surfel {
    Surfel {
        position_m: nalgebra::Point3::new(x, y, 0.03),
        normal: Vector3::<f32>::z(),
        colour: [0; 3],
        confidence: 10.0,
        radius_m: 2e-4,
        t0: t,
        t,
        albedo: 0.0,
        sigma_m: 0.0,
        warp_m: Vector3::zeros(),
    }
}

criterion_group!(benches, solve, warp_map, warp_map_reach);
criterion_main!(benches);
