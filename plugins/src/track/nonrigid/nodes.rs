//! The tracker's embedded-deformation nodes: sampled on the surface the prediction shows, kept
//! from frame to frame and moved with the wall.
//!
//! A node is added where a model point has no node within the spacing (Poisson-disk-like, in
//! raster order, as SurfelWarp's candidate rule: `WarpFieldUpdater.cpp`); it keeps the position it
//! had when it was created (its reference: the rest-shape prior pulls it back there, after
//! DefSLAM's `EdgesReference`) and its live position, which each frame's warp moves.

use nalgebra::{Point3, Vector3};

use rayon::prelude::*;
use rustc_hash::FxHashMap as HashMap;

use super::points::ModelPoint;

/// One node.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Node {
    /// Where the wall under it is now, metres, world frame.
    pub position_m: Point3<f64>,
    /// Where it was created, metres, world frame.
    pub reference_m: Point3<f64>,
    /// Surface normal there, world frame.
    pub normal: Vector3<f64>,
}

/// The nodes and a grid over their live positions.
#[derive(Debug, Clone, Default)]
pub struct Nodes {
    /// The nodes, in creation order.
    pub nodes: Vec<Node>,
    cells: HashMap<[i64; 3], Vec<usize>>,
    cell_m: f64,
}

impl Nodes {
    /// No nodes; the grid's cells are `cell_m` wide.
    pub fn new(cell_m: f64) -> Self {
        Self { nodes: Vec::new(), cells: HashMap::default(), cell_m }
    }

    fn cell(&self, p: &Point3<f64>) -> [i64; 3] {
        [(p.x / self.cell_m).floor() as i64, (p.y / self.cell_m).floor() as i64, (p.z / self.cell_m).floor() as i64]
    }

    /// Indices of the nodes within `radius_m` (≤ the cell width) of `p`, ascending.
    pub fn within(&self, p: &Point3<f64>, radius_m: f64) -> Vec<usize> {
        self.close(p, &self.hood(self.cell(p)), radius_m)
    }

    /// [`Nodes::within_each`] at the model points' positions.
    pub fn within_each_point(&self, points: &[ModelPoint], radius_m: f64) -> Vec<Vec<usize>> {
        let positions: Vec<Point3<f64>> = points.iter().map(|p| p.x_world_m).collect();
        self.within_each(&positions, radius_m)
    }

    /// [`Nodes::within`] for many points at once: each cell's neighbourhood is gathered once,
    /// then filtered per point in parallel; the same lists.
    ///
    /// The points are grouped by sub-cells a quarter of a cell wide, and each group is given the
    /// nodes of its cell's neighbourhood that can lie within `radius_m` of the sub-cell's box
    /// (a conservative test, 1 nm of slack for rounding): a point then tests about a third as
    /// many nodes as its whole neighbourhood holds.
    pub fn within_each(&self, points: &[Point3<f64>], radius_m: f64) -> Vec<Vec<usize>> {
        let sub_m = self.cell_m / 4.0;
        let sub = |p: &Point3<f64>| [(p.x / sub_m).floor() as i64, (p.y / sub_m).floor() as i64, (p.z / sub_m).floor() as i64];
        let reach2 = (radius_m + 1e-9) * (radius_m + 1e-9);
        let mut hoods: HashMap<[i64; 3], Vec<usize>> = HashMap::default();
        let mut groups: HashMap<([i64; 3], [i64; 3]), Vec<usize>> = HashMap::default();
        for p in points {
            let key = (self.cell(p), sub(p));
            if groups.contains_key(&key) {
                continue;
            }
            let hood = hoods.entry(key.0).or_insert_with(|| self.hood(key.0));
            let lo = key.1.map(|k| k as f64 * sub_m);
            let near_box = |i: &usize| {
                let q = self.nodes[*i].position_m;
                let gap = |x: f64, lo: f64| (lo - x).max(x - lo - sub_m).max(0.0);
                let (gx, gy, gz) = (gap(q.x, lo[0]), gap(q.y, lo[1]), gap(q.z, lo[2]));
                gx * gx + gy * gy + gz * gz <= reach2
            };
            groups.insert(key, hood.iter().copied().filter(near_box).collect());
        }
        points.par_iter().map(|p| self.close(p, groups.get(&(self.cell(p), sub(p))).map_or(&[], |h| &h[..]), radius_m)).collect()
    }

    /// The nodes of the 27 cells around cell `c`, ascending.
    fn hood(&self, c: [i64; 3]) -> Vec<usize> {
        let mut hood = Vec::new();
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(v) = self.cells.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        hood.extend_from_slice(v);
                    }
                }
            }
        }
        hood.sort_unstable();
        hood
    }

    /// The nodes of an ascending `hood` within `radius_m` of `p`, in order.
    fn close(&self, p: &Point3<f64>, hood: &[usize], radius_m: f64) -> Vec<usize> {
        hood.iter().copied().filter(|&i| (self.nodes[i].position_m - p).norm() <= radius_m).collect()
    }

    /// Adds a node at every model point with no node within `spacing_m` (the point's normal
    /// facing the same way), up to `max_nodes` in all; returns how many were added and how many
    /// were refused by the cap.
    pub fn cover(&mut self, points: &[ModelPoint], spacing_m: f64, max_nodes: usize) -> (usize, usize) {
        let near = self.within_each_point(points, spacing_m);
        self.cover_near(points, &near, spacing_m, max_nodes)
    }

    /// [`Nodes::cover`] given, per point, the nodes near it: any list that holds every node
    /// within `spacing_m` of the point (the nodes within the reach, which the frame's problem
    /// needs too, [`Nodes::within_each`]).
    pub fn cover_near(&mut self, points: &[ModelPoint], near: &[Vec<usize>], spacing_m: f64, max_nodes: usize) -> (usize, usize) {
        let (mut added, mut refused) = (0, 0);
        // A point the nodes from before cover stays covered (nodes are only added here): those
        // are found in parallel, and the raster-order pass visits the others only.
        let covered: Vec<bool> = points.par_iter().zip(near).map(|(p, near)| self.faces(p, near, spacing_m)).collect();
        for p in points.iter().zip(&covered).filter(|(_, c)| !**c).map(|(p, _)| p) {
            if self.faces(p, &self.within(&p.x_world_m, spacing_m), spacing_m) {
                continue;
            }
            if self.nodes.len() >= max_nodes {
                refused += 1;
                continue;
            }
            let c = self.cell(&p.x_world_m);
            self.cells.entry(c).or_default().push(self.nodes.len());
            self.nodes.push(Node { position_m: p.x_world_m, reference_m: p.x_world_m, normal: p.n_world });
            added += 1;
        }
        (added, refused)
    }

    /// Whether one of the `near` nodes within `spacing_m` of the point faces the point's way.
    fn faces(&self, p: &ModelPoint, near: &[usize], spacing_m: f64) -> bool {
        near.iter().any(|&i| (self.nodes[i].position_m - p.x_world_m).norm() <= spacing_m && self.nodes[i].normal.dot(&p.n_world) > 0.0)
    }

    /// Re-bins every node after positions changed.
    pub fn rebin(&mut self) {
        let mut cells: HashMap<[i64; 3], Vec<usize>> = HashMap::default();
        for (i, n) in self.nodes.iter().enumerate() {
            cells.entry(self.cell(&n.position_m)).or_default().push(i);
        }
        self.cells = cells;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(x: f64, y: f64) -> ModelPoint {
        ModelPoint { x_world_m: Point3::new(x, y, 0.03), n_world: -Vector3::z(), gray_ref: None, sigma_m: 0.0 }
    }

    #[test]
    fn nodes_cover_a_sheet_at_the_spacing_and_not_twice() {
        let pts: Vec<ModelPoint> = (0..41).flat_map(|i| (0..41).map(move |j| point(i as f64 * 0.001, j as f64 * 0.001))).collect();
        let mut n = Nodes::new(0.016);
        let (added, _) = n.cover(&pts, 0.008, 4096);
        assert!((16..=60).contains(&added), "{added} nodes on a 40 mm sheet at 8 mm");
        // Every point has a node within the spacing; no two nodes are closer than it.
        assert!(pts.iter().all(|p| !n.within(&p.x_world_m, 0.008).is_empty()));
        for (i, a) in n.nodes.iter().enumerate() {
            assert!(n.nodes[i + 1..].iter().all(|b| (a.position_m - b.position_m).norm() > 0.008));
        }
        assert_eq!(n.cover(&pts, 0.008, 4096), (0, 0), "a covered surface gets no new nodes");
        // The opposite wall (normal the other way) at the same place gets its own nodes.
        let back: Vec<ModelPoint> = pts.iter().map(|p| ModelPoint { n_world: -p.n_world, ..*p }).collect();
        assert_eq!(n.cover(&back, 0.008, 4096).0, added);
        // The cap refuses, and says so.
        let mut capped = Nodes::new(0.016);
        let (a, r) = capped.cover(&pts, 0.008, 5);
        assert_eq!((a, capped.nodes.len()), (5, 5));
        assert!(r > 0);
    }

    #[test]
    fn the_batched_search_finds_what_the_single_one_does() {
        let pts: Vec<ModelPoint> = (0..41).flat_map(|i| (0..41).map(move |j| point(i as f64 * 0.001, j as f64 * 0.001))).collect();
        let mut n = Nodes::new(0.016);
        n.cover(&pts, 0.004, 4096);
        // Points on the sheet, off it and beyond its edges, at two radii.
        let probes: Vec<Point3<f64>> = (0..60).map(|i| Point3::new(-0.03 + 0.0017 * i as f64, 0.0007 * i as f64, 0.03 + 0.0002 * (i % 7) as f64)).collect();
        for radius in [0.006, 0.016] {
            let batched = n.within_each(&probes, radius);
            let single: Vec<Vec<usize>> = probes.iter().map(|p| n.within(p, radius)).collect();
            assert_eq!(batched, single);
            assert!(single.iter().any(|v| v.len() > 1) && single.iter().any(|v| v.is_empty()), "the probes see some nodes and miss others");
        }
        // Many points scattered over the sheet and around it (sub-cell edges included), at the
        // radii the tracker uses (spacing, reach) and one just above a sub-cell's width.
        let mut state = 99u64;
        let mut unit = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut scattered: Vec<Point3<f64>> = (0..3000).map(|_| Point3::new(-0.01 + 0.06 * unit(), -0.01 + 0.06 * unit(), 0.02 + 0.02 * unit())).collect();
        scattered.extend((0..40).map(|i| Point3::new(0.004 * f64::from(i % 10), 0.004 * f64::from(i / 10), 0.03)));
        for radius in [0.004, 0.0041, 0.008, 0.016] {
            let single: Vec<Vec<usize>> = scattered.iter().map(|p| n.within(p, radius)).collect();
            assert_eq!(n.within_each(&scattered, radius), single, "radius {radius}");
        }
    }
}
