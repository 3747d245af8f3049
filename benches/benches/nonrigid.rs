//! The `nonrigid` tracker's warp solve against the node count (issue 16): 64 to 4096 nodes on a
//! 22 × 22 mm wall patch seen with a 0.3 mm wave, model points bound, the block-sparse normal
//! equations assembled and solved by faer's sparse Cholesky, 3 Gauss-Newton iterations, the
//! symbolic analysis kept between calls as it is between frames with an unchanged graph.

use capsule_slam_plugins::track::nonrigid::fixture::SolverCase;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn solve(c: &mut Criterion) {
    let mut group = c.benchmark_group("nonrigid-warp-solve");
    group.sample_size(10);
    for n in [64usize, 256, 1024, 4096] {
        let mut case = SolverCase::new(n).unwrap_or_else(|e| panic!("{n} nodes: {e}"));
        assert!(case.solve(), "{n} nodes: the solve fell back");
        group.bench_with_input(BenchmarkId::from_parameter(case.nodes), &n, |b, _| b.iter(|| case.solve()));
    }
    group.finish();
}

criterion_group!(benches, solve);
criterion_main!(benches);
