//! The coarse Gauss-Newton solve of `near-light-sfs`.
//!
//! Unknown: the log depth ζ = ln z on a grid of cells of `cell_px` pixels inside the field of
//! view. A cell's surface point is `P = e^ζ (x, y, 1)` ((x, y) its normalised ray), its normal
//! comes from central differences of the neighbouring cells' points (one-sided at the border),
//! and the near-light image irradiance equation (Prados & Faugeras 2005,
//! "Shape from shading: a well-posed problem?", Eq. 3 with the 1/r² term) becomes one residual
//! per cell,
//!
//! `r_c(ζ) = ln(gain · ref² · spot(P) · cos θ(P, n) / |P − l|²) − ln E_c`,
//!
//! with `ln E_c` the mean log irradiance of the cell's usable pixels (`E = L / (V ρ) − ambient`).
//! A curvature prior `λ (ζ_{i−1} − 2 ζ_i + ζ_{i+1})` along both grid axes removes the
//! checkerboard null space of central differences and fills cells without data. Gauss-Newton
//! with Levenberg damping (with `line_search`, a rejected step is tried at half and a quarter of
//! its length before the damping grows) minimises `Σ w_c r_c² + λ² Σ (Δ²ζ)²` (w_c: the cell's share of
//! usable pixels); the normal equations are solved by faer's sparse Cholesky
//! ([`SparseLlt`], supernodal: 2.3× faster than the simplicial method faer's heuristic picks for
//! this grid), the symbolic analysis once per camera and the numeric factorisation, into the
//! same buffers, once per iteration. Unlike a
//! per-pixel fixed point, which transports errors along the characteristics and drifts, this
//! least-squares form has a unique minimum near the pure fall-off start.

use std::sync::Mutex;

use faer::sparse::{SparseColMat, Triplet};
use nalgebra::Vector3;

use crate::common::sparse_llt::SparseLlt;

use capsule_slam_framework::StageError;
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::light::LightModel;

/// One grid cell: its normalised ray and its stencil `[centre, left, right, up, down]` (indices
/// of unknowns; a missing neighbour is replaced by the centre: a one-sided difference).
#[derive(Debug, Clone, Copy)]
pub(super) struct Cell {
    /// Normalised ray (x, y, 1) through the cell centre.
    pub ray: Vector3<f64>,
    /// Grid column and row.
    pub grid: (usize, usize),
    /// `[c, l, r, u, d]` unknown indices.
    pub stencil: [usize; 5],
}

/// The grid of a camera: cells, the pixel → cell map and the factorisation pattern.
pub(super) struct Grid {
    /// Cell size in pixels.
    pub cell_px: usize,
    /// Grid columns and rows.
    pub cols: usize,
    /// Grid rows.
    pub rows: usize,
    /// The unknowns.
    pub cells: Vec<Cell>,
    /// Grid position → unknown index.
    pub index: Vec<Option<usize>>,
    /// Curvature rows `(a, centre, b)`.
    smooth_rows: Vec<[usize; 3]>,
    /// Where each entry of the normal matrix's lower triangle lives, and its diagonal's slots.
    slots: Slots,
    diag: Vec<usize>,
    /// The normal matrix and its factorisation, analysed once and refilled and refactorised by
    /// every solve on this grid (locked for the solve: its buffers are reused).
    normal: Mutex<Normal>,
}

/// The normal matrix (lower triangle) and its sparse Cholesky factorisation.
struct Normal {
    a: SparseColMat<usize, f64>,
    llt: SparseLlt,
}

fn solver_error(e: impl std::fmt::Display) -> StageError {
    StageError::invalid_input(format!("near-light-sfs: sparse Cholesky failed: {e}"))
}

impl Grid {
    /// The grid of `cam` with cells of `cell_px` pixels; cells whose centre lies outside the
    /// field of view are not unknowns.
    pub fn new(cam: &PinholeCamera, cell_px: usize) -> Result<Self, StageError> {
        let s = cell_px.max(1);
        let (cols, rows) = (cam.width.div_ceil(s), cam.height.div_ceil(s));
        let mut index = vec![None; cols * rows];
        let mut cells = Vec::new();
        for gy in 0..rows {
            for gx in 0..cols {
                let (u, v) = (
                    ((gx * s) as f64 + (s as f64 - 1.0) / 2.0).min(cam.width as f64 - 1.0),
                    ((gy * s) as f64 + (s as f64 - 1.0) / 2.0).min(cam.height as f64 - 1.0),
                );
                if !cam.in_fov(u, v) {
                    continue;
                }
                let p = cam.unproject(u, v, 1.0);
                index[gy * cols + gx] = Some(cells.len());
                cells.push(Cell { ray: Vector3::new(p.x, p.y, 1.0), grid: (gx, gy), stencil: [0; 5] });
            }
        }
        let at = |gx: i64, gy: i64| -> Option<usize> {
            (gx >= 0 && gy >= 0 && (gx as usize) < cols && (gy as usize) < rows).then(|| index[gy as usize * cols + gx as usize]).flatten()
        };
        let mut smooth_rows = Vec::new();
        for gy in 0..rows as i64 {
            for gx in 0..cols as i64 {
                let Some(c) = at(gx, gy) else { continue };
                let (l, r, u, d) = (at(gx - 1, gy), at(gx + 1, gy), at(gx, gy - 1), at(gx, gy + 1));
                cells[c].stencil = [c, l.unwrap_or(c), r.unwrap_or(c), u.unwrap_or(c), d.unwrap_or(c)];
                if let (Some(l), Some(r)) = (l, r) {
                    smooth_rows.push([l, c, r]);
                }
                if let (Some(u), Some(d)) = (u, d) {
                    smooth_rows.push([u, c, d]);
                }
            }
        }
        let n = cells.len();
        let mut trips = Vec::new();
        let mut add_block = |idx: &[usize]| {
            for &a in idx {
                for &b in idx {
                    if a >= b {
                        trips.push(Triplet::new(a, b, 0.0));
                    }
                }
            }
        };
        for c in &cells {
            add_block(&c.stencil);
        }
        for r in &smooth_rows {
            add_block(r);
        }
        for k in 0..n {
            trips.push(Triplet::new(k, k, 0.0));
        }
        let pattern = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &trips).map_err(solver_error)?;
        let llt = SparseLlt::supernodal(pattern.symbolic()).map_err(solver_error)?;
        let slots = Slots { col_ptr: pattern.symbolic().col_ptr().to_vec(), row_idx: pattern.symbolic().row_idx().to_vec() };
        let diag = (0..n).map(|k| slots.at(k, k)).collect();
        Ok(Self { cell_px: s, cols, rows, cells, index, smooth_rows, slots, diag, normal: Mutex::new(Normal { a: pattern, llt }) })
    }

    /// The pixel at a cell's centre.
    pub fn centre_px(&self, cell: &Cell) -> (f64, f64) {
        let half = (self.cell_px as f64 - 1.0) / 2.0;
        ((cell.grid.0 * self.cell_px) as f64 + half, (cell.grid.1 * self.cell_px) as f64 + half)
    }

    /// The cells and weights of a bilinear interpolation at pixel (x, y) over the cell centres
    /// that exist (at the border the weights are renormalised when applied).
    pub fn bilinear(&self, x: f64, y: f64) -> Bilinear {
        let s = self.cell_px as f64;
        let half = (s - 1.0) / 2.0;
        let (gx, gy) = ((x - half) / s, (y - half) / s);
        let (x0, y0) = (gx.floor(), gy.floor());
        let (fx, fy) = (gx - x0, gy - y0);
        let mut out = Bilinear::default();
        for (dx, dy, wt) in [(0.0, 0.0, (1.0 - fx) * (1.0 - fy)), (1.0, 0.0, fx * (1.0 - fy)), (0.0, 1.0, (1.0 - fx) * fy), (1.0, 1.0, fx * fy)] {
            let (cx, cy) = (x0 + dx, y0 + dy);
            if cx < 0.0 || cy < 0.0 || cx >= self.cols as f64 || cy >= self.rows as f64 {
                continue;
            }
            let Some(c) = self.index[cy as usize * self.cols + cx as usize] else { continue };
            out.taps[out.n] = (c as u32, wt + 1e-6);
            out.n += 1;
        }
        out
    }

    /// Bilinear interpolation of per-cell values at pixel (x, y); `None` far outside the grid.
    pub fn interpolate(&self, x: f64, y: f64, f: impl Fn(usize) -> f64) -> Option<f64> {
        self.bilinear(x, y).apply(|c| [f(c)]).map(|[v]| v)
    }
}

/// Up to four cells and their bilinear weights (a per-pixel table, built once per camera).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Bilinear {
    taps: [(u32, f64); 4],
    n: usize,
}

impl Bilinear {
    /// The weighted mean of per-cell values, `None` without any cell.
    pub fn apply<const K: usize>(&self, f: impl Fn(usize) -> [f64; K]) -> Option<[f64; K]> {
        let mut acc = [0.0; K];
        let mut wsum = 0.0;
        for &(c, wt) in &self.taps[..self.n] {
            let v = f(c as usize);
            for k in 0..K {
                acc[k] += wt * v[k];
            }
            wsum += wt;
        }
        (wsum > 0.0).then(|| acc.map(|a| a / wsum))
    }
}

/// The photometric model of one cell's residual.
pub(super) struct Photometry<'a> {
    /// The light.
    light: &'a LightModel,
    /// Smallest cos θ before the soft clamp takes over.
    min_cos: f64,
    /// `ln(gain · ref²)`, the same for every cell.
    ln_gain: f64,
}

impl<'a> Photometry<'a> {
    /// The model of `light` with the soft clamp below `min_cos`.
    pub fn new(light: &'a LightModel, min_cos: f64) -> Self {
        Self { light, min_cos, ln_gain: (light.gain * light.ref_distance_m * light.ref_distance_m).ln() }
    }

    /// `ln(gain ref² spot cos θ / d²)` at the centre cell given the five stencil points.
    pub fn log_irradiance(&self, p: &[Vector3<f64>; 5]) -> f64 {
        let tx = p[2] - p[1];
        let ty = p[4] - p[3];
        let n = ty.cross(&tx);
        let len = n.norm();
        let l = Vector3::from(self.light.position_m);
        let to_light = l - p[0];
        let d = to_light.norm();
        let cos = if len > 0.0 && d > 0.0 { n.dot(&to_light) / (len * d) } else { 1.0 };
        // C¹ soft clamp: below min_cos the cosine decays exponentially instead of reaching 0.
        let c0 = self.min_cos;
        let ln_cos = if cos >= c0 { cos.ln() } else { c0.ln() + (cos - c0) / c0 };
        let spot = if self.light.spot_exponent == 0.0 || d <= 0.0 { 0.0 } else { self.light.spot_exponent * (-to_light.z / d).max(1e-6).ln() };
        self.ln_gain + spot + ln_cos - 2.0 * d.max(1e-9).ln()
    }

    /// The residual of cell `c`, its cells' surface points `points` ([`points`] at the log depths).
    fn residual(&self, cells: &[Cell], points: &[Vector3<f64>], c: usize, ln_e: f64) -> f64 {
        let st = cells[c].stencil;
        self.log_irradiance(&std::array::from_fn(|k| points[st[k]])) - ln_e
    }

    /// The residual of cell `c` and its derivatives with respect to the stencil's unknowns
    /// (forward differences of [`FORWARD_STEP`]): `points` at the log depths and `moved` at the
    /// log depths plus the step ([`points`]; each cell's exponential taken once per iteration,
    /// not once per stencil it belongs to).
    fn linearise(&self, cells: &[Cell], (points, moved): (&[Vector3<f64>], &[Vector3<f64>]), c: usize, ln_e: f64) -> (f64, [f64; 5]) {
        let st = cells[c].stencil;
        let base: [Vector3<f64>; 5] = std::array::from_fn(|k| points[st[k]]);
        let r0 = self.log_irradiance(&base) - ln_e;
        let mut jac = [0.0; 5];
        for (k, j) in jac.iter_mut().enumerate() {
            if st[..k].contains(&st[k]) {
                continue; // the same unknown as an earlier slot: perturbed together there
            }
            let pert: [Vector3<f64>; 5] = std::array::from_fn(|m| if st[m] == st[k] { moved[st[m]] } else { base[m] });
            *j = (self.log_irradiance(&pert) - ln_e - r0) / FORWARD_STEP;
        }
        (r0, jac)
    }
}

/// The forward-difference step of [`Photometry::linearise`], in log depth.
const FORWARD_STEP: f64 = 1e-6;

/// Each cell's surface point `ray · e^(ζ + dζ)`.
pub(super) fn points(cells: &[Cell], zeta: &[f64], dz: f64) -> Vec<Vector3<f64>> {
    cells.iter().zip(zeta).map(|(cell, z)| cell.ray * (z + dz).exp()).collect()
}

/// Per-cell data: mean log irradiance and the share of usable pixels.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct CellData {
    /// Mean `ln E` over the usable pixels.
    pub ln_e: f64,
    /// Share of the cell's pixels that are usable, in [0, 1].
    pub weight: f64,
}

/// Settings of the solve.
pub(super) struct SolveSettings {
    /// Gauss-Newton iterations.
    pub iterations: u32,
    /// Curvature prior weight λ.
    pub smoothness: f64,
    /// Stop when an iteration lowers the cost by less than this fraction.
    pub tolerance: f64,
    /// Try the step's half and quarter before damping it more.
    pub line_search: bool,
}

/// The cost `Σ w_c r_c² + λ² Σ (Δ²ζ)²` of a log-depth field.
pub(super) fn cost(grid: &Grid, photometry: &Photometry, data: &[CellData], zeta: &[f64], smoothness: f64) -> f64 {
    let at = points(&grid.cells, zeta, 0.0);
    let data_cost: f64 =
        (0..grid.cells.len()).filter(|&c| data[c].weight > 0.0).map(|c| data[c].weight * photometry.residual(&grid.cells, &at, c, data[c].ln_e).powi(2)).sum();
    let smooth: f64 = grid.smooth_rows.iter().map(|[p, c, q]| (zeta[*p] - 2.0 * zeta[*c] + zeta[*q]).powi(2)).sum();
    data_cost + smoothness * smoothness * smooth
}

/// Minimises the cell residuals from `zeta` (the pure fall-off start); returns the final
/// residuals `ln M − ln E` per cell and the number of sparse factorisations.
pub(super) fn solve(
    grid: &Grid,
    photometry: &Photometry,
    data: &[CellData],
    zeta: &mut [f64],
    settings: &SolveSettings,
) -> Result<(Vec<f64>, usize), StageError> {
    let mut factorisations = 0;
    let n = grid.cells.len();
    let (slots, diag) = (&grid.slots, &grid.diag);
    let mut normal = grid.normal.lock().map_err(|_| solver_error("a solve on this grid panicked"))?;
    let Normal { a, llt } = &mut *normal;
    let mut mu = 1e-4;
    let mut current = cost(grid, photometry, data, zeta, settings.smoothness);
    for _ in 0..settings.iterations {
        let g = assemble(grid, photometry, data, zeta, settings.smoothness, slots, a.val_mut());
        let base: Vec<f64> = diag.iter().map(|&s| a.val_mut()[s]).collect();
        // Levenberg-Marquardt: grow the damping until the step lowers the cost.
        let mut accepted = false;
        let mut converged = false;
        for _ in 0..4 {
            let vals = a.val_mut();
            for (k, &s) in diag.iter().enumerate() {
                vals[s] = base[k] * (1.0 + mu) + 1e-9;
            }
            llt.factorize(a.as_ref()).map_err(solver_error)?;
            factorisations += 1;
            let mut step: Vec<f64> = g.iter().map(|v| -v).collect();
            llt.solve_in_place(&mut step).map_err(solver_error)?;
            // The step, then (before damping more, which needs a new factorisation) its half and
            // quarter along the same direction.
            let shortened = [1.0, 0.5, 0.25].into_iter().take(if settings.line_search { 3 } else { 1 });
            for (i, scale) in shortened.enumerate() {
                let trial: Vec<f64> = (0..n).map(|k| zeta[k] + scale * step[k]).collect();
                let c = cost(grid, photometry, data, &trial, settings.smoothness);
                if c.is_finite() && c < current {
                    zeta.copy_from_slice(&trial);
                    converged = c > current * (1.0 - settings.tolerance);
                    current = c;
                    if i == 0 {
                        mu = (mu * 0.3).max(1e-6);
                    }
                    accepted = true;
                    break;
                }
            }
            if accepted {
                break;
            }
            mu *= 10.0;
        }
        if !accepted || converged {
            break;
        }
    }
    let at = points(&grid.cells, zeta, 0.0);
    Ok(((0..n).map(|c| if data[c].weight > 0.0 { photometry.residual(&grid.cells, &at, c, data[c].ln_e) } else { 0.0 }).collect(), factorisations))
}

/// Where entry (r, c) of the lower triangle lives in a column-major sparse pattern.
struct Slots {
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
}

impl Slots {
    fn at(&self, r: usize, c: usize) -> usize {
        let (lo, hi) = (self.col_ptr[c], self.col_ptr[c + 1]);
        lo + self.row_idx[lo..hi].partition_point(|&x| x < r)
    }
}

/// Fills the normal equations JᵀWJ (lower triangle, into `vals`) of the weighted cell
/// residuals and the curvature prior `λ² Σ (Δ²ζ)²` at `zeta`; returns the gradient JᵀWr.
fn assemble(grid: &Grid, photometry: &Photometry, data: &[CellData], zeta: &[f64], smoothness: f64, slots: &Slots, vals: &mut [f64]) -> Vec<f64> {
    vals.iter_mut().for_each(|v| *v = 0.0);
    let mut g = vec![0.0; grid.cells.len()];
    let (at, moved) = (points(&grid.cells, zeta, 0.0), points(&grid.cells, zeta, FORWARD_STEP));
    for (c, &d) in data.iter().enumerate() {
        if d.weight <= 0.0 {
            continue;
        }
        let (r, jac) = photometry.linearise(&grid.cells, (&at, &moved), c, d.ln_e);
        let st = grid.cells[c].stencil;
        for i in 0..5 {
            if jac[i] == 0.0 {
                continue;
            }
            g[st[i]] += d.weight * jac[i] * r;
            for k in 0..5 {
                if st[i] >= st[k] && jac[k] != 0.0 {
                    vals[slots.at(st[i], st[k])] += d.weight * jac[i] * jac[k];
                }
            }
        }
    }
    let lambda2 = smoothness * smoothness;
    for row in &grid.smooth_rows {
        let coef = [1.0, -2.0, 1.0];
        let r = zeta[row[0]] - 2.0 * zeta[row[1]] + zeta[row[2]];
        for i in 0..3 {
            g[row[i]] += lambda2 * coef[i] * r;
            for k in 0..3 {
                if row[i] >= row[k] {
                    vals[slots.at(row[i], row[k])] += lambda2 * coef[i] * coef[k];
                }
            }
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    fn cam() -> PinholeCamera {
        let mut c = PinholeCamera::new(64, 48, 40.0, 40.0, 31.5, 23.5);
        c.fov_radius_px = Some(30.0);
        c
    }

    fn light() -> LightModel {
        LightModel { gain: 0.6, spot_exponent: 1.0, position_m: [0.001, -0.0005, 0.0], ..LightModel::default() }
    }

    /// A smooth, non-planar log-depth field.
    fn field(grid: &Grid) -> Vec<f64> {
        grid.cells.iter().map(|c| (0.03 + 0.01 * c.ray.x + 0.004 * (3.0 * c.ray.y).sin() + 0.006 * c.ray.x * c.ray.x).ln()).collect()
    }

    #[test]
    fn the_jacobian_matches_central_differences_at_every_cell_including_the_border() {
        let grid = Grid::new(&cam(), 4).unwrap();
        let l = light();
        let ph = Photometry::new(&l, 0.1);
        let zeta = field(&grid);
        let mut checked = 0;
        for c in 0..grid.cells.len() {
            let (_, jac) = ph.linearise(&grid.cells, (&points(&grid.cells, &zeta, 0.0), &points(&grid.cells, &zeta, FORWARD_STEP)), c, 0.0);
            let st = grid.cells[c].stencil;
            for (k, &u) in st.iter().enumerate() {
                if st[..k].contains(&u) {
                    continue;
                }
                let h = 1e-5;
                let mut zp = zeta.clone();
                zp[u] += h;
                let mut zm = zeta.clone();
                zm[u] -= h;
                let residual = |z: &[f64]| ph.residual(&grid.cells, &points(&grid.cells, z, 0.0), c, 0.0);
                let numeric = (residual(&zp) - residual(&zm)) / (2.0 * h);
                assert!((jac[k] - numeric).abs() < 1e-4 * (1.0 + numeric.abs()), "cell {c} slot {k}: {} vs {numeric}", jac[k]);
                checked += 1;
            }
        }
        assert!(checked > 4 * grid.cells.len());
    }

    #[test]
    fn the_residual_model_is_the_light_model_of_the_renderer() {
        // On a plane the finite-difference normal is exact, so ln M must equal the light
        // model's own direct term at the cell's point.
        let grid = Grid::new(&cam(), 4).unwrap();
        let l = light();
        let ph = Photometry::new(&l, 0.01);
        let n = Vector3::new(0.3, -0.2, -1.0).normalize();
        let q = Vector3::new(0.0, 0.0, 0.03);
        let zeta: Vec<f64> = grid.cells.iter().map(|c| (n.dot(&q) / n.dot(&c.ray)).ln()).collect();
        for (c, cell) in grid.cells.iter().enumerate() {
            let p = cell.ray * zeta[c].exp();
            let truth = l.direct(&Point3::from(p), &n).ln();
            let model = ph.residual(&grid.cells, &points(&grid.cells, &zeta, 0.0), c, 0.0);
            assert!((model - truth).abs() < 1e-9, "cell {c}: {model} vs {truth}");
        }
    }

    /// The worst log-depth error of a solve with `settings` on the noiseless data of the
    /// field [`field`], from `start(cell, true ζ)`.
    fn worst_after_solve(start: impl Fn(&Cell, f64) -> f64, settings: &SolveSettings) -> f64 {
        let grid = Grid::new(&cam(), 4).unwrap();
        let l = light();
        let ph = Photometry::new(&l, 0.01);
        let truth = field(&grid);
        let at = points(&grid.cells, &truth, 0.0);
        let data: Vec<CellData> = (0..grid.cells.len()).map(|c| CellData { ln_e: ph.residual(&grid.cells, &at, c, 0.0), weight: 1.0 }).collect();
        let mut zeta: Vec<f64> = grid.cells.iter().zip(&truth).map(|(c, z)| start(c, *z)).collect();
        solve(&grid, &ph, &data, &mut zeta, settings).unwrap();
        zeta.iter().zip(&truth).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max)
    }

    #[test]
    fn a_solve_from_the_truth_stays_at_the_truth() {
        let worst = worst_after_solve(|_, z| z + 0.05, &SolveSettings { iterations: 20, smoothness: 0.0, tolerance: 0.0, line_search: false });
        assert!(worst < 1e-3, "a 5 % offset must be undone: worst log error {worst}");
    }

    #[test]
    fn the_line_search_reaches_the_truth_from_far_off_starts() {
        // Starts a tenth to half of the depth off, some tilted: full Gauss-Newton steps overshoot
        // there, and the shortened steps must still end at the truth.
        for (offset, tilt) in [(0.1, 0.0), (0.3, 0.0), (0.6, 0.0), (-0.3, 0.0), (-0.6, 0.0), (0.3, 1.0)] {
            let settings = SolveSettings { iterations: 30, smoothness: 0.0, tolerance: 0.0, line_search: true };
            let worst = worst_after_solve(|c, z| z + offset + tilt * c.ray.x * c.ray.x, &settings);
            assert!(worst < 1e-6, "from {offset} + {tilt} x²: worst log error {worst}");
        }
    }
}
