//! A uniform grid over the nodes of a deformation with a reach: the nodes that can influence a
//! point lie in the 27 cells around it (cells at least as wide as the reach), so warping a large
//! map costs a few dozen distance tests per surfel near the nodes and one box test elsewhere.

use nalgebra::{Point3, Vector3};

/// Most cells along one axis (wider cells beyond it; any width ≥ the reach is correct).
const MAX_CELLS_PER_AXIS: usize = 32;

/// Node indices by grid cell, dense over the nodes' bounding box.
pub(super) struct NodeGrid {
    cell_m: f64,
    /// Corner of cell (0, 0, 0), one cell below the nodes' lowest corner.
    origin: Point3<f64>,
    dims: [usize; 3],
    /// Per cell, the nodes of the 27 cells around it (ascending).
    hoods: Vec<Vec<usize>>,
}

impl NodeGrid {
    /// Bins the node positions into cells at least `reach_m` (> 0) wide.
    pub(super) fn new(positions: &[Point3<f64>], reach_m: f64) -> Self {
        let (mut lo, mut hi) = (Point3::from([f64::INFINITY; 3]), Point3::from([f64::NEG_INFINITY; 3]));
        for p in positions.iter().filter(|p| p.iter().all(|v| v.is_finite())) {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        if lo.x > hi.x {
            return Self { cell_m: reach_m, origin: Point3::origin(), dims: [0; 3], hoods: Vec::new() };
        }
        let extent = (hi - lo).max();
        let cell_m = reach_m.max(extent / (MAX_CELLS_PER_AXIS - 2) as f64);
        let origin = lo - Vector3::repeat(cell_m);
        let dims = [0, 1, 2].map(|a| ((hi[a] - origin[a]) / cell_m).floor() as usize + 2);
        let mut grid = Self { cell_m, origin, dims, hoods: vec![Vec::new(); dims[0] * dims[1] * dims[2]] };
        for (i, p) in positions.iter().enumerate() {
            let Some(c) = grid.cell(p) else { continue };
            for z in c[2].saturating_sub(1)..=(c[2] + 1).min(dims[2] - 1) {
                for y in c[1].saturating_sub(1)..=(c[1] + 1).min(dims[1] - 1) {
                    for x in c[0].saturating_sub(1)..=(c[0] + 1).min(dims[0] - 1) {
                        let k = grid.index([x, y, z]);
                        grid.hoods[k].push(i);
                    }
                }
            }
        }
        grid
    }

    fn cell(&self, p: &Point3<f64>) -> Option<[usize; 3]> {
        let mut c = [0usize; 3];
        for a in 0..3 {
            let f = ((p[a] - self.origin[a]) / self.cell_m).floor();
            if !(f >= 0.0 && f < self.dims[a] as f64) {
                return None;
            }
            c[a] = f as usize;
        }
        Some(c)
    }

    fn index(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// The nodes in the 27 cells around `p` (a superset of those within the reach); none when
    /// `p` lies outside the grid, which is then farther than the reach from every node.
    pub(super) fn near(&self, p: &Point3<f64>) -> &[usize] {
        match self.cell(p) {
            Some(c) => &self.hoods[self.index(c)],
            None => &[],
        }
    }
}
