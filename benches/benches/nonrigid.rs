//! The `nonrigid` tracker's warp solve against the node count (issue 16): 64 to 4096 nodes on a
//! 22 × 22 mm wall patch seen with a 0.3 mm wave, model points bound, the block-sparse normal
//! equations assembled and solved by faer's sparse Cholesky, 3 Gauss-Newton iterations, the
//! symbolic analysis kept between calls as it is between frames with an unchanged graph; affine
//! nodes (12 unknowns, the default) and twist nodes (6).

use capsule_slam_plugins::common::ed_graph::NodeModel;
use capsule_slam_plugins::track::nonrigid::fixture::SolverCase;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn solve(c: &mut Criterion) {
    let mut group = c.benchmark_group("nonrigid-warp-solve");
    group.sample_size(10);
    for model in [NodeModel::Affine, NodeModel::Twist] {
        for n in [64usize, 256, 1024, 4096] {
            let mut case = SolverCase::new(n, model).unwrap_or_else(|e| panic!("{model:?}, {n} nodes: {e}"));
            assert!(case.solve(), "{model:?}, {n} nodes: the solve fell back");
            group.bench_with_input(BenchmarkId::new(format!("{model:?}").to_lowercase(), case.nodes), &n, |b, _| b.iter(|| case.solve()));
        }
    }
    group.finish();
}

criterion_group!(benches, solve);
criterion_main!(benches);
