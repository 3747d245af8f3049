//! Evaluation against ground truth, with evo's definitions (Grupp, "evo: Python package for the
//! evaluation of odometry and SLAM", 2017): trajectory alignment (Umeyama), absolute trajectory
//! error (ATE, SE(3) or Sim(3)), relative pose error ([`rpe`]), surface error ([`surface`]) and
//! single-frame depth error ([`depth`]).

pub mod align;
pub use capsule_slam_framework::depth_error as depth;
pub mod live;
pub mod report;
pub mod rpe;
pub mod surface;
#[cfg(test)]
mod testing;
pub mod warp;

use nalgebra::{Point3, UnitQuaternion};
use serde::Serialize;

use capsule_slam_framework::geometry::{Iso3, StampedPose};

pub use align::{Similarity, umeyama};

/// Pairs of (estimated, ground-truth) poses matched by nearest timestamp within `tolerance_s`
/// (each estimated pose matched to its nearest ground-truth pose).
pub fn associate<'a>(est: &'a [StampedPose], gt: &'a [StampedPose], tolerance_s: f64) -> Vec<(&'a StampedPose, &'a StampedPose)> {
    est.iter()
        .filter_map(|e| capsule_slam_framework::geometry::nearest_in_time(gt, e.timestamp_s, tolerance_s, |p| p.timestamp_s).map(|i| (e, &gt[i])))
        .collect()
}

/// Summary statistics of a list of errors, as evo reports them (`std` is the population
/// standard deviation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// Standard deviation.
    pub std: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
    /// Number of values.
    pub count: usize,
}

impl Stats {
    /// Statistics of `v`; `None` when empty.
    pub fn of(v: &[f64]) -> Option<Self> {
        if v.is_empty() {
            return None;
        }
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let m = s.len();
        let median = if m % 2 == 1 { s[m / 2] } else { 0.5 * (s[m / 2 - 1] + s[m / 2]) };
        Some(Self {
            rmse: (v.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
            mean,
            median,
            std: (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n).sqrt(),
            min: s[0],
            max: s[m - 1],
            count: m,
        })
    }
}

/// Absolute trajectory error (translation part) after alignment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Ate {
    /// Position error statistics, metres.
    pub stats: Stats,
    /// The alignment estimate → ground truth.
    #[serde(skip)]
    pub alignment: Similarity,
}

impl Ate {
    /// RMSE, metres.
    pub fn rmse_m(&self) -> f64 {
        self.stats.rmse
    }
}

/// Below this spread across its main direction (the square root of the positions' second
/// principal variance, metres), a ground-truth path is still or straight: its positions leave
/// the rotation about it free. Every phantom preset spreads 3.5–8 mm.
pub const PATH_SPREAD_MIN_M: f64 = 1e-3;

/// How far along each camera axis the orientations enter the alignment of a still or straight
/// path (metres): organ scale, the distance to the wall.
pub const AXIS_REACH_M: f64 = 0.01;

/// Umeyama alignment of pose positions `src` onto `dst` (TUM's ATE). A ground-truth path that
/// spreads less than [`PATH_SPREAD_MIN_M`] across its main direction (a still camera, a
/// straight push) does not fix the rotation about it, and Umeyama's would be the noise's: such a
/// path is aligned by its poses instead, each as its centre and the points [`AXIS_REACH_M`] along
/// its axes. With scale, the scale is the positions' (`None` for a still path, which has none).
pub fn umeyama_poses(src: &[Iso3], dst: &[Iso3], with_scale: bool) -> Option<Similarity> {
    let s: Vec<Point3<f64>> = src.iter().map(|p| Point3::from(p.translation.vector)).collect();
    let d: Vec<Point3<f64>> = dst.iter().map(|p| Point3::from(p.translation.vector)).collect();
    let spread = principal_spreads_m(&d);
    if spread[1] >= PATH_SPREAD_MIN_M {
        return umeyama(&s, &d, with_scale);
    }
    // A still path (no spread along its main direction either) has no scale to fit.
    if with_scale && spread[0] < PATH_SPREAD_MIN_M {
        return None;
    }
    let scale = if with_scale { umeyama(&s, &d, true).map(|a| a.scale).filter(|s| s.is_finite() && *s > 0.0)? } else { 1.0 };
    let fs: Vec<Point3<f64>> = src.iter().flat_map(|p| pose_points(p, AXIS_REACH_M / scale)).collect();
    let fd: Vec<Point3<f64>> = dst.iter().flat_map(|p| pose_points(p, AXIS_REACH_M)).collect();
    let rigid = umeyama(&fs.iter().map(|p| Point3::from(p.coords * scale)).collect::<Vec<_>>(), &fd, false)?;
    Some(Similarity { scale, rotation: rigid.rotation, translation: rigid.translation })
}

/// A pose as points: its centre and the points `reach_m` along its three axes, so that an
/// alignment of them fits the orientation too.
fn pose_points(p: &Iso3, reach_m: f64) -> [Point3<f64>; 4] {
    let c = Point3::from(p.translation.vector);
    [c, c + p.rotation * nalgebra::Vector3::x() * reach_m, c + p.rotation * nalgebra::Vector3::y() * reach_m, c + p.rotation * nalgebra::Vector3::z() * reach_m]
}

/// The square roots of the two largest principal variances of `points`, metres: how far they
/// spread along their main direction and across it.
fn principal_spreads_m(points: &[Point3<f64>]) -> [f64; 2] {
    if points.is_empty() {
        return [0.0; 2];
    }
    let n = points.len() as f64;
    let mu = points.iter().map(|p| p.coords).sum::<nalgebra::Vector3<f64>>() / n;
    let cov = points.iter().map(|p| (p.coords - mu) * (p.coords - mu).transpose()).sum::<nalgebra::Matrix3<f64>>() / n;
    let mut ev: Vec<f64> = cov.symmetric_eigenvalues().iter().copied().collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    [0, 1].map(|k| ev.get(k).copied().unwrap_or(0.0).max(0.0).sqrt())
}

/// The alignment of `est` onto `gt` (positions matched by timestamp), with scale (Sim(3)) or
/// without (SE(3)).
pub fn align_trajectory(est: &[StampedPose], gt: &[StampedPose], tolerance_s: f64, with_scale: bool) -> Option<Similarity> {
    let pairs = associate(est, gt, tolerance_s);
    let (e, g): (Vec<Iso3>, Vec<Iso3>) = pairs.iter().map(|(e, g)| (e.t_world_cam, g.t_world_cam)).unzip();
    umeyama_poses(&e, &g, with_scale)
}

/// The alignment of `est` onto `gt` fitted to the last `last_n` matched poses alone (a local
/// alignment, where [`align_trajectory`] is global): each pose enters as its centre and the
/// points `reach_m` along its three axes, so its orientation counts and a short, straight stretch
/// is still determined. With `global_scale` = Some(s), the scale of the global Sim(3) alignment
/// (a monocular estimate's metre is not the truth's), the fit has a scale too and the estimate's
/// axis points are `reach_m / s` along. A map fused along a drifting trajectory is judged by it
/// without the drift before the window: the live surface error under this alignment is how well
/// the map follows the wall near the camera.
pub fn align_recent(est: &[StampedPose], gt: &[StampedPose], tolerance_s: f64, global_scale: Option<f64>, last_n: usize, reach_m: f64) -> Option<Similarity> {
    let pairs = associate(est, gt, tolerance_s);
    let recent = &pairs[pairs.len().saturating_sub(last_n)..];
    if recent.is_empty() {
        return None;
    }
    let est_reach_m = global_scale.map_or(reach_m, |s| reach_m / s);
    let src: Vec<Point3<f64>> = recent.iter().flat_map(|(e, _)| pose_points(&e.t_world_cam, est_reach_m)).collect();
    let dst: Vec<Point3<f64>> = recent.iter().flat_map(|(_, g)| pose_points(&g.t_world_cam, reach_m)).collect();
    umeyama(&src, &dst, global_scale.is_some())
}

/// ATE after aligning the estimated positions to the ground truth with Umeyama's method, with
/// scale (Sim(3), for monocular runs) or without (SE(3)). `None` with fewer than three matched
/// pairs.
pub fn ate(est: &[StampedPose], gt: &[StampedPose], tolerance_s: f64, with_scale: bool) -> Option<Ate> {
    let pairs = associate(est, gt, tolerance_s);
    if pairs.len() < 3 {
        return None;
    }
    let (e, g): (Vec<Iso3>, Vec<Iso3>) = pairs.iter().map(|(e, g)| (e.t_world_cam, g.t_world_cam)).unzip();
    let sim = umeyama_poses(&e, &g, with_scale)?;
    let err: Vec<f64> = e.iter().zip(&g).map(|(a, b)| (sim.apply(&Point3::from(a.translation.vector)) - Point3::from(b.translation.vector)).norm()).collect();
    Some(Ate { stats: Stats::of(&err)?, alignment: sim })
}

/// Length of the path through the poses' positions, metres.
pub fn path_length_m(poses: &[StampedPose]) -> f64 {
    poses.windows(2).map(|w| (w[1].t_world_cam.translation.vector - w[0].t_world_cam.translation.vector).norm()).sum()
}

impl Similarity {
    /// The rotation as a quaternion: nalgebra's iterative fit with the iterations bounded
    /// (unbounded, `from_matrix` never returned on the slightly non-orthonormal rotation of a
    /// straight-line trajectory's alignment; a converging fit gives the same bits).
    pub fn quaternion(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_matrix_eps(&self.rotation, f64::EPSILON, 1000, UnitQuaternion::identity())
    }

    /// Applies the similarity to a pose: position `s R t + t₀`, rotation `R R_pose` (evo's
    /// `scale` then `transform`).
    pub fn apply_pose(&self, p: &Iso3) -> Iso3 {
        let r = self.quaternion();
        Iso3::from_parts((self.scale * (self.rotation * p.translation.vector) + self.translation).into(), r * p.rotation)
    }

    /// The rigid part (rotation and translation) as an isometry; exact when the scale is 1.
    pub fn rigid(&self) -> Iso3 {
        Iso3::from_parts(self.translation.into(), self.quaternion())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::geometry::exp_se3;
    use nalgebra::{Rotation3, Vector3, Vector6};
    use proptest::prelude::*;

    #[test]
    fn a_straight_line_aligns_and_its_poses_map_onto_the_truth() {
        // Collinear positions leave the rotation about the line free: the alignment must still
        // return (an unbounded quaternion fit never did) and map the poses onto the truth.
        let line = |k: f64| -> Vec<StampedPose> {
            (0..10).map(|i| StampedPose { timestamp_s: i as f64, t_world_cam: Iso3::translation(0.0, 0.0, k * 0.0005 * i as f64) }).collect()
        };
        let (est, gt) = (line(1.0), line(1.0));
        let sim = align_trajectory(&est, &gt, 0.01, false).unwrap();
        for (e, g) in est.iter().zip(&gt) {
            let p = sim.apply_pose(&e.t_world_cam);
            assert!((p.translation.vector - g.t_world_cam.translation.vector).norm() < 1e-9);
            assert!(p.rotation.angle().is_finite());
        }
    }

    #[test]
    fn a_still_or_straight_path_is_aligned_by_its_orientations() {
        // The estimate is the truth seen from another world frame (a 0.5 rad turn about the
        // path and an offset), with micrometre jitter: positions alone leave the turn to the
        // jitter, the orientations fix it.
        let t = Iso3::from_parts(Vector3::new(0.01, -0.02, 0.005).into(), nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, 0.5)));
        let look = nalgebra::UnitQuaternion::from_euler_angles(0.2, -0.4, 0.1);
        for step_m in [0.0, 0.001] {
            let gt: Vec<StampedPose> = (0..10)
                .map(|i| StampedPose { timestamp_s: i as f64, t_world_cam: Iso3::from_parts(Vector3::new(0.0, 0.0, step_m * i as f64).into(), look) })
                .collect();
            let est: Vec<StampedPose> = gt
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let jitter = Iso3::translation(1e-6 * (i as f64 * 1.3).sin(), 1e-6 * (i as f64 * 2.1).cos(), 1e-6 * (i as f64 * 0.7).sin());
                    StampedPose { timestamp_s: p.timestamp_s, t_world_cam: jitter * t.inverse() * p.t_world_cam }
                })
                .collect();
            let sim = align_trajectory(&est, &gt, 0.01, false).unwrap();
            let turn = (Rotation3::from_matrix_unchecked(sim.rotation) * t.rotation.to_rotation_matrix().inverse()).angle();
            assert!(turn < 1e-3, "path step {step_m} m: the alignment is {turn} rad off the true turn");
            // With scale: a still path has none; a straight one has the positions'.
            let scaled = align_trajectory(&est, &gt, 0.01, true);
            assert_eq!(scaled.is_none(), step_m == 0.0, "path step {step_m} m");
        }
    }

    fn traj(n: usize) -> Vec<StampedPose> {
        (0..n)
            .map(|i| {
                let s = i as f64 * 0.1;
                StampedPose { timestamp_s: s, t_world_cam: exp_se3(&Vector6::new(0.05 * s.sin(), 0.03 * s, 0.02 * (2.0 * s).cos(), 0.1 * s, 0.2, -0.1 * s)) }
            })
            .collect()
    }

    /// The estimate: the truth moved by `early` up to frame `split`, by `late` after it.
    fn two_offsets(gt: &[StampedPose], split: usize, early: &Iso3, late: &Iso3) -> Vec<StampedPose> {
        gt.iter()
            .enumerate()
            .map(|(i, p)| StampedPose { timestamp_s: p.timestamp_s, t_world_cam: if i < split { early } else { late } * p.t_world_cam })
            .collect()
    }

    #[test]
    fn the_recent_alignment_fits_the_last_poses_alone() {
        let gt = traj(60);
        let early = exp_se3(&Vector6::new(0.004, -0.002, 0.003, 0.05, 0.0, -0.03));
        let late = exp_se3(&Vector6::new(-0.001, 0.002, 0.0, 0.0, 0.02, 0.01));
        let est = two_offsets(&gt, 40, &early, &late);
        // Fitted on the last 20 poses (all moved by `late`): exactly late⁻¹.
        let a = align_recent(&est, &gt, 0.01, None, 20, 0.01).unwrap();
        let want = late.inverse();
        assert!((a.rotation - want.rotation.to_rotation_matrix().matrix()).norm() < 1e-9, "{a:?}");
        assert!((a.translation - want.translation.vector).norm() < 1e-9, "{a:?}");
        // Over 30 poses the early offset enters and the fit is no longer exact.
        let b = align_recent(&est, &gt, 0.01, None, 30, 0.01).unwrap();
        assert!((b.translation - want.translation.vector).norm() > 1e-5, "{b:?}");
        // One pose is enough (its centre and axes), and nothing matched is none.
        assert!(align_recent(&est, &gt, 0.01, None, 1, 0.01).is_some());
        assert!(align_recent(&est, &[], 0.01, None, 20, 0.01).is_none());
    }

    #[test]
    fn the_recent_alignment_with_scale_undoes_a_monocular_scale() {
        let gt = traj(60);
        let est: Vec<StampedPose> = gt
            .iter()
            .map(|p| StampedPose {
                timestamp_s: p.timestamp_s,
                t_world_cam: Iso3::from_parts((2.5 * p.t_world_cam.translation.vector).into(), p.t_world_cam.rotation),
            })
            .collect();
        let global = align_trajectory(&est, &gt, 0.01, true).unwrap();
        let a = align_recent(&est, &gt, 0.01, Some(global.scale), 10, 0.01).unwrap();
        assert!((a.scale - 0.4).abs() < 1e-9 && a.translation.norm() < 1e-9, "{a:?}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        #[test]
        fn ate_of_a_similarity_transformed_copy_is_zero_with_sim3(
            angles in prop::array::uniform3(-3.0f64..3.0), shift in prop::array::uniform3(-1.0f64..1.0), scale in 0.2f64..5.0
        ) {
            let gt = traj(50);
            let r = Rotation3::from_euler_angles(angles[0], angles[1], angles[2]);
            let t = Vector3::new(shift[0], shift[1], shift[2]);
            let est: Vec<_> = gt.iter().map(|p| StampedPose {
                timestamp_s: p.timestamp_s,
                t_world_cam: Iso3::from_parts((scale * (r * p.t_world_cam.translation.vector) + t).into(), UnitQuaternion::from_rotation_matrix(&r) * p.t_world_cam.rotation),
            }).collect();
            let a = ate(&est, &gt, 0.01, true).unwrap();
            prop_assert!(a.rmse_m() < 1e-9, "{:?}", a.stats);
            prop_assert!((a.alignment.scale - 1.0 / scale).abs() < 1e-9);
            if (scale - 1.0).abs() > 0.05 {
                prop_assert!(ate(&est, &gt, 0.01, false).unwrap().rmse_m() > 1e-4);
            }
        }
    }

    #[test]
    fn known_noise_gives_the_expected_rmse() {
        // Alternate ±1 mm along x: alignment cannot remove it; the RMSE is 1 mm.
        let gt = traj(40);
        let est: Vec<_> = gt
            .iter()
            .enumerate()
            .map(|(i, p)| StampedPose {
                timestamp_s: p.timestamp_s,
                t_world_cam: Iso3::translation(if i % 2 == 0 { 0.001 } else { -0.001 }, 0.0, 0.0) * p.t_world_cam,
            })
            .collect();
        let a = ate(&est, &gt, 0.01, false).unwrap();
        assert!((a.rmse_m() - 0.001).abs() < 5e-5, "{a:?}");
    }

    #[test]
    fn the_percent_of_path_divides_by_the_path_the_estimate_covers() {
        let gt = traj(60);
        // The first 15 poses only, with alternating ±1 mm: the ATE is 1 mm.
        let est: Vec<_> = gt[..15]
            .iter()
            .enumerate()
            .map(|(i, p)| StampedPose {
                timestamp_s: p.timestamp_s,
                t_world_cam: Iso3::translation(0.0, if i % 2 == 0 { 0.001 } else { -0.001 }, 0.0) * p.t_world_cam,
            })
            .collect();
        let m = report::evaluate(&est, &gt, None, &report::EvalOptions::default());
        let (covered, whole) = (path_length_m(&gt[..15]), path_length_m(&gt));
        assert!(covered < 0.5 * whole, "{covered} {whole}");
        assert!((m["path_length_m"] - covered).abs() < 1e-12 && (m["gt_path_length_m"] - whole).abs() < 1e-12, "{m:?}");
        assert!((m["ate_percent_of_path"] - 100.0 * m["ate_rmse_m"] / covered).abs() < 1e-9, "{m:?}");
        // A whole run covers the whole path.
        let full = report::evaluate(&gt, &gt, None, &report::EvalOptions::default());
        assert!((full["path_length_m"] - whole).abs() < 1e-12);
        // No pose matched: no path, no percentage.
        let late: Vec<_> = est.iter().map(|p| StampedPose { timestamp_s: p.timestamp_s + 100.0, ..*p }).collect();
        let none = report::evaluate(&late, &gt, None, &report::EvalOptions::default());
        assert_eq!(none["path_length_m"], 0.0);
        assert!(!none.contains_key("ate_percent_of_path"));
    }

    #[test]
    fn stats_match_hand_computation() {
        let s = Stats::of(&[3.0, 1.0, 2.0, 4.0]).unwrap();
        assert_eq!((s.mean, s.median, s.min, s.max, s.count), (2.5, 2.5, 1.0, 4.0, 4));
        assert!((s.rmse - (30.0f64 / 4.0).sqrt()).abs() < 1e-12);
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-12);
        assert!(Stats::of(&[]).is_none());
    }
}
