//! The `nonrigid` tracker's warp solve against the node count (issue 16): 64 to 4096 nodes on a
//! 22 × 22 mm wall patch seen with a 0.3 mm wave, model points bound, the block-sparse normal
//! equations assembled and solved by faer's sparse Cholesky, 3 Gauss-Newton iterations, the
//! symbolic analysis kept between calls as it is between frames with an unchanged graph; affine
//! nodes (12 unknowns, the default) and twist nodes (6), each by Gauss-Newton (`gn`, a
//! factorisation per iteration) and by the chord method (`chord`, `reuse_factor`: the first
//! iteration's factorisation kept while the steps shrink).

use capsule_slam_plugins::common::ed_graph::NodeModel;
use capsule_slam_plugins::track::nonrigid::fixture::SolverCase;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn solve(c: &mut Criterion) {
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

criterion_group!(benches, solve);
criterion_main!(benches);
