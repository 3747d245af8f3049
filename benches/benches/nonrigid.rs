//! The `nonrigid` tracker's warp solve against the node count (issue 16): 64 to 4096 nodes on a
//! 22 × 22 mm wall patch seen with a 0.3 mm wave, model points bound, the block-sparse normal
//! equations assembled and solved by faer's sparse Cholesky, 3 Gauss-Newton iterations, the
//! symbolic analysis kept between calls as it is between frames with an unchanged graph; affine
//! nodes (12 unknowns, the default) and twist nodes (6), each by Gauss-Newton (`gn`, a
//! factorisation per iteration) and by the chord method (`chord`, `reuse_factor`: the first
//! iteration's factorisation kept while the steps shrink).
//!
//! `nonrigid-analysis`: the symbolic analysis of the same cases' patterns (affine nodes), by
//! faer's AMD on the scalar matrix (`scalar`) and by AMD on the node graph with each node's
//! unknowns kept together (`block`, the tracker's; `SparseLlt::blocked`). The warp solve
//! analyses anew whenever the model points couple other node pairs, on the phantom every frame.

use capsule_slam_plugins::common::ed_graph::NodeModel;
use capsule_slam_plugins::track::nonrigid::fixture::SolverCase;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn solve(c: &mut Criterion) {
    capsule_slam_benches::link();
    let mut group = c.benchmark_group("nonrigid-warp-solve");
    group.sample_size(10);
    for model in [NodeModel::Affine, NodeModel::Twist] {
        for (mode, reuse) in [("gn", false), ("chord", true)] {
            for n in [64usize, 256, 1024, 4096] {
                let mut case = SolverCase::new(n, model).unwrap_or_else(|e| panic!("{model:?}, {n} nodes: {e}")).reuse_factor(reuse);
                assert!(case.solve(), "{model:?} {mode}, {n} nodes: the solve fell back");
                let id = BenchmarkId::new(format!("{}-{mode}", format!("{model:?}").to_lowercase()), case.nodes);
                group.bench_with_input(id, &n, |b, _| b.iter(|| case.solve()));
            }
        }
    }
    group.finish();
}

fn analysis(c: &mut Criterion) {
    let mut group = c.benchmark_group("nonrigid-analysis");
    group.sample_size(10);
    for n in [64usize, 256, 1024, 4096] {
        let case = SolverCase::new(n, NodeModel::Affine).unwrap_or_else(|e| panic!("{n} nodes: {e}"));
        let pattern = case.pattern().unwrap_or_else(|e| panic!("{n} nodes: {e}"));
        for (name, block) in [("scalar", false), ("block", true)] {
            let fill = pattern.analyse(block).unwrap_or_else(|e| panic!("{name}, {n} nodes: {e}"));
            eprintln!("nonrigid-analysis/{name}/{}: {} unknowns, {fill} values in the factor", case.nodes, pattern.unknowns);
            group.bench_with_input(BenchmarkId::new(name, case.nodes), &n, |b, _| b.iter(|| pattern.analyse(block)));
        }
    }
    group.finish();
}

criterion_group!(benches, solve, analysis);
criterion_main!(benches);
