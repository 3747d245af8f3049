//! Surface error as in the paper (Sec. 4.2): the reconstruction is aligned to the
//! ground-truth surface by point-to-plane ICP, then the nearest-neighbour distances of the map
//! to the truth give the RMSE. Because RMSE alone rewards a tiny map, accuracy (median map →
//! truth distance) and completeness (share of the observed truth within 1 and 2 mm of the map)
//! are reported too. Nearest neighbours: kiddo. Sums are accumulated in a fixed order, so the
//! result is deterministic.

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;
use serde::Serialize;

use capsule_slam_framework::geometry::{Iso3, exp_se3};
use capsule_slam_framework::map::SurfelSet;

/// Options of [`surface_error`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceOptions {
    /// At most this many map points are used (evenly subsampled).
    pub max_points: usize,
    /// ICP iterations (0 = use the initial alignment as is).
    pub icp_iterations: usize,
    /// Initial ICP correspondence gate, metres.
    pub icp_gate_m: f64,
    /// Truth points observed in at least this many frames form the second completeness figure
    /// (10 = ElasticFusion's stability threshold: what a confidence-gated fuser can keep).
    pub min_views: f32,
    /// Lateral offset within which the distance to the nearest truth sample is measured along
    /// its normal (point-to-plane), metres; beyond it the Euclidean distance is used.
    pub plane_radius_m: f64,
}

impl Default for SurfaceOptions {
    fn default() -> Self {
        Self { max_points: 200_000, icp_iterations: 30, icp_gate_m: 0.005, min_views: 10.0, plane_radius_m: 0.001 }
    }
}

/// Surface error statistics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SurfaceError {
    /// RMS of the map → truth distances, metres.
    pub rmse_m: f64,
    /// Median map → truth distance (accuracy), metres.
    pub accuracy_m: f64,
    /// Share of the observed truth within 1 mm of the map.
    pub completeness_1mm: f64,
    /// Share of the observed truth within 2 mm of the map.
    pub completeness_2mm: f64,
    /// Share of the truth observed in ≥ `min_views` frames within 1 mm of the map.
    pub completeness_1mm_min_views: f64,
    /// Share of the truth observed in ≥ `min_views` frames within 2 mm of the map.
    pub completeness_2mm_min_views: f64,
    /// Map points evaluated.
    pub map_points: usize,
    /// Truth points counted for completeness.
    pub truth_points: usize,
}

/// The ground-truth surface with a k-d tree over its samples.
pub(crate) struct Truth {
    tree: ImmutableKdTree<f32, 3>,
    points: Vec<Point3<f64>>,
    normals: Vec<Vector3<f64>>,
}

impl Truth {
    /// The samples of `truth` in a k-d tree (`None` when it is empty or the tree cannot be built).
    pub(crate) fn new(truth: &SurfelSet) -> Option<Self> {
        if truth.is_empty() {
            return None;
        }
        let pts: Vec<[f32; 3]> = truth.surfels.iter().map(|s| [s.position_m.x, s.position_m.y, s.position_m.z]).collect();
        Some(Self {
            tree: ImmutableKdTree::new_from_slice(&pts).ok()?,
            points: truth.surfels.iter().map(|s| s.position_m.cast()).collect(),
            normals: truth.surfels.iter().map(|s| s.normal.cast::<f64>().try_normalize(1e-9).unwrap_or_else(Vector3::z)).collect(),
        })
    }

    /// Nearest truth sample of `p`: (index, distance to the surface): along the sample's normal
    /// within `plane_radius_m` of it laterally, Euclidean beyond.
    pub(crate) fn distance(&self, p: &Point3<f64>, plane_radius_m: f64) -> (usize, f64) {
        let r = self.tree.query(&[p.x as f32, p.y as f32, p.z as f32]).nearest_one::<SquaredEuclidean<f32>>().execute();
        let i = r.item as usize;
        let d = p - self.points[i];
        let along = d.dot(&self.normals[i]);
        let lateral = (d - along * self.normals[i]).norm();
        (i, if lateral <= plane_radius_m { along.abs() } else { d.norm() })
    }
}

/// Aligns `map` to `truth` starting from `initial` (map → truth) and measures the error.
/// Truth points with confidence 0 (never observed) are left out of completeness. `None` when
/// either set is empty.
pub fn surface_error(map: &SurfelSet, truth: &SurfelSet, initial: &Iso3, opts: &SurfaceOptions) -> Option<SurfaceError> {
    if map.is_empty() {
        return None;
    }
    let truth_set = Truth::new(truth)?;
    let step = map.len().div_ceil(opts.max_points.max(1)).max(1);
    let src: Vec<Point3<f64>> = map.surfels.iter().step_by(step).map(|s| s.position_m.cast()).collect();
    let t = align_point_to_plane(&src, &truth_set, initial, opts);
    let mut dist: Vec<f64> = src.par_iter().map(|p| truth_set.distance(&(t * p), opts.plane_radius_m).1).collect();
    let rmse_m = (dist.iter().map(|d| d * d).sum::<f64>() / dist.len() as f64).sqrt();
    dist.sort_by(f64::total_cmp);
    let accuracy_m = dist[dist.len() / 2];
    let completeness = Completeness::of(map, truth, &t)?;
    Some(SurfaceError {
        rmse_m,
        accuracy_m,
        completeness_1mm: completeness.share(0.001, 0.0),
        completeness_2mm: completeness.share(0.002, 0.0),
        completeness_1mm_min_views: completeness.share(0.001, opts.min_views),
        completeness_2mm_min_views: completeness.share(0.002, opts.min_views),
        map_points: src.len(),
        truth_points: completeness.near.len(),
    })
}

/// Point-to-plane ICP of the map samples `src` onto the truth from `initial`, with a gate that
/// shrinks to 3 × the RMS residual: r = n·(T p − q), J = [nᵀ, (T p × n)ᵀ] for T ← exp(δ) T.
fn align_point_to_plane(src: &[Point3<f64>], truth: &Truth, initial: &Iso3, opts: &SurfaceOptions) -> Iso3 {
    let mut t = *initial;
    let mut gate = opts.icp_gate_m;
    for _ in 0..opts.icp_iterations {
        let rows: Vec<Option<(Vector6<f64>, f64)>> = src
            .par_iter()
            .map(|p| {
                let tp = t * p;
                let r = truth.tree.query(&[tp.x as f32, tp.y as f32, tp.z as f32]).nearest_one::<SquaredEuclidean<f32>>().execute();
                let i = r.item as usize;
                if f64::from(r.distance).sqrt() > gate {
                    return None;
                }
                let n = truth.normals[i];
                let c = tp.coords.cross(&n);
                Some((Vector6::new(n.x, n.y, n.z, c.x, c.y, c.z), n.dot(&(tp - truth.points[i]))))
            })
            .collect();
        let (mut a, mut b, mut sse, mut n) = (Matrix6::zeros(), Vector6::zeros(), 0.0, 0usize);
        for (j, r) in rows.into_iter().flatten() {
            a += j * j.transpose();
            b += j * r;
            sse += r * r;
            n += 1;
        }
        if n < 6 {
            break;
        }
        let Some(delta) = a.cholesky().map(|c| -c.solve(&b)) else { break };
        t = exp_se3(&delta) * t;
        gate = (3.0 * (sse / n as f64).sqrt()).clamp(0.0005, opts.icp_gate_m);
        if delta.norm() < 1e-9 {
            break;
        }
    }
    t
}

/// For every observed truth point, its distance to the nearest surfel of the aligned map, and
/// how often it was observed.
struct Completeness {
    near: Vec<f32>,
    views: Vec<f32>,
}

impl Completeness {
    fn of(map: &SurfelSet, truth: &SurfelSet, t: &Iso3) -> Option<Self> {
        let aligned: Vec<[f32; 3]> = map
            .surfels
            .iter()
            .map(|s| {
                let p = t * s.position_m.cast::<f64>();
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect();
        let map_tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&aligned).ok()?;
        let observed: Vec<usize> = (0..truth.len()).filter(|&i| truth.surfels[i].confidence > 0.0).collect();
        let near: Vec<f32> = observed
            .par_iter()
            .map(|&i| {
                let q = truth.surfels[i].position_m;
                map_tree.query(&[q.x, q.y, q.z]).nearest_one::<SquaredEuclidean<f32>>().execute().distance.sqrt()
            })
            .collect();
        let views: Vec<f32> = observed.iter().map(|&i| truth.surfels[i].confidence).collect();
        Some(Self { near, views })
    }

    /// The share of the truth points seen at least `min_views` times that lie within `r_m`.
    fn share(&self, r_m: f32, min_views: f32) -> f64 {
        let sel: Vec<f32> = self.near.iter().zip(&self.views).filter(|(_, v)| **v >= min_views).map(|(d, _)| *d).collect();
        if sel.is_empty() { 0.0 } else { sel.iter().filter(|d| **d <= r_m).count() as f64 / sel.len() as f64 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::map::Surfel;

    fn plane(n: usize, spacing: f32, z: f32) -> SurfelSet {
        let mut v = Vec::new();
        for i in 0..n {
            for j in 0..n {
                v.push(Surfel {
                    position_m: Point3::new(i as f32 * spacing, j as f32 * spacing, z + 0.002 * ((i as f32) * 0.3).sin()),
                    normal: Vector3::z(),
                    colour: [0; 3],
                    confidence: 1.0,
                    radius_m: 0.0,
                    t0: 0,
                    t: 0,
                    albedo: 0.0,
                    sigma_m: 0.0,
                    warp_m: Vector3::zeros(),
                });
            }
        }
        // Normals of the corrugated surface.
        for s in &mut v {
            let i = s.position_m.x / spacing;
            let slope = 0.002 * 0.3 * (i * 0.3).cos() / spacing;
            s.normal = Vector3::new(-slope, 0.0, 1.0).normalize();
        }
        SurfelSet { surfels: v }
    }

    #[test]
    fn a_copy_with_a_known_offset_is_realigned_and_noise_is_measured() {
        let truth = plane(120, 0.0005, 0.05);
        // The map: a subset of the truth, displaced rigidly by 1 mm and 1°.
        let motion = exp_se3(&Vector6::new(0.001, -0.0005, 0.0007, 0.0, 0.017, 0.0));
        let mut map = SurfelSet { surfels: truth.surfels.iter().step_by(3).cloned().collect() };
        for s in &mut map.surfels {
            s.position_m = (motion * s.position_m.cast::<f64>()).cast();
        }
        let e = surface_error(&map, &truth, &motion.inverse(), &SurfaceOptions::default()).unwrap();
        assert!(e.rmse_m < 2e-5, "{e:?}");
        assert!(e.completeness_1mm > 0.99);
        // Now lift every map point by 0.3 mm along the normal: RMSE 0.3 mm, alignment must not
        // absorb it since the corrugation pins the plane... only its mean; use alternating signs.
        let mut noisy = SurfelSet { surfels: truth.surfels.iter().step_by(3).cloned().collect() };
        for (k, s) in noisy.surfels.iter_mut().enumerate() {
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            s.position_m += s.normal * (sign * 0.0003);
        }
        let e = surface_error(&noisy, &truth, &Iso3::identity(), &SurfaceOptions::default()).unwrap();
        assert!((e.rmse_m - 0.0003).abs() < 2e-5, "{e:?}");
        assert!((e.accuracy_m - 0.0003).abs() < 2e-5, "{e:?}");
    }

    #[test]
    fn completeness_counts_only_observed_truth() {
        let mut truth = plane(40, 0.0005, 0.05);
        let map = SurfelSet { surfels: truth.surfels[..800].to_vec() };
        let all = surface_error(&map, &truth, &Iso3::identity(), &SurfaceOptions { icp_iterations: 0, ..SurfaceOptions::default() }).unwrap();
        assert!((all.completeness_1mm - 0.5).abs() < 0.05, "{all:?}");
        for s in &mut truth.surfels[800..] {
            s.confidence = 0.0;
        }
        let seen = surface_error(&map, &truth, &Iso3::identity(), &SurfaceOptions { icp_iterations: 0, ..SurfaceOptions::default() }).unwrap();
        assert_eq!(seen.truth_points, 800);
        assert!(seen.completeness_1mm > 0.999);
        // The second figure counts only truth observed in ≥ min_views frames.
        for s in &mut truth.surfels[..400] {
            s.confidence = 3.0;
        }
        for s in &mut truth.surfels[400..800] {
            s.confidence = 12.0;
        }
        let mut half = map.clone();
        half.surfels.truncate(400);
        let e = surface_error(&half, &truth, &Iso3::identity(), &SurfaceOptions { icp_iterations: 0, ..SurfaceOptions::default() }).unwrap();
        // Only the two rows next to the covered half lie within 1 mm of the map.
        assert!((e.completeness_1mm - 0.55).abs() < 0.03 && (e.completeness_1mm_min_views - 0.1).abs() < 0.03, "{e:?}");
    }
}
