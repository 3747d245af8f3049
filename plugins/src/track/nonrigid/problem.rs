//! A frame's problem for the joint solve, built from the nodes and the model points alone: the
//! nodes with enough points, the points bound to them, the ED graph with its edges, and the
//! normal equations laid out with their pattern analysed (`Problem::prepare`). None of it
//! depends on the rigid start, so `Nonrigid::track` builds it while the rigid start runs
//! (`rayon::join`), on a copy of the nodes that a frame which loses track drops.

use capsule_slam_framework::StageError;
use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
use rayon::prelude::*;

use crate::common::ed_graph::{Edges, Graph};

use super::iterate::Prepared;
use super::nodes::Nodes;
use super::params::{CameraMode, NonrigidParams};
use super::points::ModelPoint;
use super::priors;
use super::solve::{Cache, Problem};

/// A frame's problem ready to solve.
pub(crate) struct Built {
    /// The problem.
    pub problem: Problem,
    /// Each solve node's index among all nodes.
    pub solve_ids: Vec<usize>,
    /// Every node's count of model points.
    pub used: Vec<usize>,
    /// Its normal equations laid out and analysed.
    pub prepared: Prepared,
    /// Time building the problem (before `prepared`), ms.
    pub ms_problem: f64,
}

/// The problem of `points` on `nodes` with its normal equations prepared (the analysis kept in
/// `cache` when the pattern is unchanged); `None` when no node has enough model points.
pub(crate) fn build(nodes: &Nodes, p: &NonrigidParams, cache: &mut Cache, points: &[ModelPoint]) -> Option<Result<Built, StageError>> {
    build_near(nodes, p, cache, points, None)
}

/// [`build`] with each point's nodes within reach when they are known.
fn build_near(nodes: &Nodes, p: &NonrigidParams, cache: &mut Cache, points: &[ModelPoint], near: Option<Vec<Vec<usize>>>) -> Option<Result<Built, StageError>> {
    let clock = std::time::Instant::now();
    let (problem, solve_ids, used) = problem_of(nodes, p, points, near)?;
    let ms_problem = clock.elapsed().as_secs_f64() * 1e3;
    Some(problem.prepare(points, &p.weights(), cache).map(|prepared| Built { problem, solve_ids, used, prepared, ms_problem }))
}

/// The nodes covering a frame's model points and the problem built on them, before the rigid
/// start is known.
pub(crate) struct Ready {
    /// A copy of the tracker's nodes with the new ones that cover the points.
    pub nodes: Nodes,
    /// Nodes added.
    pub added: usize,
    /// Model points left without a node by the `max_nodes` cap.
    pub refused: usize,
    /// The problem (`build`).
    pub built: Option<Result<Built, StageError>>,
    /// Time covering and building, ms (on its own thread, beside the rigid start).
    pub ms: f64,
}

impl Ready {
    /// Covers `points` with nodes on a copy of `nodes` and builds the problem there.
    pub(crate) fn new(nodes: &Nodes, p: &NonrigidParams, cache: &mut Cache, points: &[ModelPoint]) -> Self {
        let clock = std::time::Instant::now();
        let mut nodes = nodes.clone();
        // Each point's nodes within reach serve the cover (reach ≥ spacing) and the problem; a
        // frame that adds nodes finds them again.
        let near = nodes.within_each_point(points, p.reach_m);
        let (added, refused) = nodes.cover_near(points, &near, p.node_spacing_m, p.max_nodes as usize);
        let near = if added == 0 { near } else { nodes.within_each_point(points, p.reach_m) };
        let built = build_near(&nodes, p, cache, points, Some(near));
        Self { nodes, added, refused, built, ms: clock.elapsed().as_secs_f64() * 1e3 }
    }

    /// Drops it unused (a frame that lost track), giving its pattern's analysis back to `cache`.
    pub(crate) fn release(self, cache: &mut Cache) {
        release(self.built, cache);
    }
}

/// Drops a built problem unused, giving its pattern's analysis back to `cache` (the next solve
/// of the same pattern reuses it).
pub(crate) fn release(built: Option<Result<Built, StageError>>, cache: &mut Cache) {
    if let Some(Ok(built)) = built {
        built.prepared.keep(cache);
    }
}

/// The frame's problem: the nodes with at least `min_points_per_node` model points (their
/// indices), the points bound to them, the graph with its edges; and every node's point
/// count. `None` when no node has enough points. `near`: each point's nodes within reach
/// ([`Nodes::within_each`]) when the caller has them.
pub(crate) fn problem_of(nodes: &Nodes, p: &NonrigidParams, points: &[ModelPoint], near: Option<Vec<Vec<usize>>>) -> Option<(Problem, Vec<usize>, Vec<usize>)> {
    let reach = p.reach_m;
    // Every node as a deformation (times 0, so the order is kept) to bind points.
    let all = Deformation::new(nodes.nodes.iter().map(|n| DeformationNode::identity(n.position_m, 0)).collect(), p.k as usize, Window::All).within(reach);
    // Each point's nodes within reach, found once for both bindings below.
    let near = near.unwrap_or_else(|| nodes.within_each_point(points, reach));
    let first: Vec<Vec<(usize, f64)>> = points.par_iter().zip(&near).map(|(q, near)| all.influences_among(&q.x_world_m, near.iter().copied())).collect();
    let mut used = vec![0usize; all.nodes.len()];
    for (i, _) in first.iter().flatten() {
        used[*i] += 1;
    }
    let solve_ids: Vec<usize> = (0..used.len()).filter(|&i| used[i] >= p.min_points_per_node as usize).collect();
    if solve_ids.is_empty() {
        return None;
    }
    let mut index = vec![usize::MAX; all.nodes.len()];
    for (s, &i) in solve_ids.iter().enumerate() {
        index[i] = s;
    }
    let solve_nodes: Vec<DeformationNode> = solve_ids.iter().map(|&i| all.nodes[i]).collect();
    let mut graph = Graph::new(Deformation::new(solve_nodes, p.k as usize, Window::All).within(reach), p.connectivity as usize, Edges::SpaceInWindow)
        .with_model(p.node_model);
    let normals: Vec<_> = solve_ids.iter().map(|&i| nodes.nodes[i].normal).collect();
    let cos_edge = p.max_edge_angle_rad.cos();
    for (j, nb) in graph.neighbours.iter_mut().enumerate() {
        let g = graph.deformation.nodes[j].position_m;
        let nodes = &graph.deformation.nodes;
        nb.retain(|&n| (nodes[n].position_m - g).norm() <= p.max_edge_m && normals[j].dot(&normals[n]) >= cos_edge);
    }
    let normals = priors::smoothed_normals(&normals, &graph.neighbours, p.slide_normal_passes);
    // A point whose nodes within reach are all solved keeps its first binding (the same
    // candidates, renumbered in the same order: the same k nearest and weights).
    let bound: Vec<(usize, Vec<(usize, f64)>)> = points
        .par_iter()
        .zip(&near)
        .zip(first)
        .enumerate()
        .filter_map(|(at, ((q, near), mut first))| {
            let b = if near.iter().all(|&i| index[i] != usize::MAX) {
                first.iter_mut().for_each(|(i, _)| *i = index[*i]);
                first
            } else {
                let near = near.iter().filter_map(|&i| (index[i] != usize::MAX).then_some(index[i]));
                graph.deformation.influences_among(&q.x_world_m, near)
            };
            (!b.is_empty()).then_some((at, b))
        })
        .collect();
    let references = solve_ids.iter().map(|&i| nodes.nodes[i].reference_m.coords).collect();
    Some((Problem { points: bound, graph, references, normals, camera: p.camera == CameraMode::Joint }, solve_ids, used))
}
