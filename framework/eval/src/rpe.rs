//! Relative pose error (Sturm et al. 2012), computed as evo's `evo_rpe` does: pose pairs
//! (i, j) chosen on the (aligned) estimate by index step or by travelled path, error
//! `E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)` with Q the ground truth and P the estimate; translation
//! error ‖t(E)‖, rotation error = angle of R(E) in degrees.

use serde::Serialize;

use super::{Stats, associate, umeyama_poses};
use capsule_slam_framework::geometry::{Iso3, StampedPose};

/// How pose pairs are spaced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Delta {
    /// Every `n`-th pose (evo's `--delta n --delta_unit f`; consecutive, non-overlapping pairs).
    Frames(usize),
    /// Pairs a travelled path of this many metres apart, starting at the first pose (evo's
    /// `--delta_unit m`, v1.38).
    Metres(f64),
}

/// RPE statistics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Rpe {
    /// Translation error statistics, metres.
    pub trans_m: Stats,
    /// Rotation error statistics, degrees.
    pub rot_deg: Stats,
    /// Sum of translation errors over the ground-truth path between the pairs (m per m).
    pub trans_per_m: f64,
    /// Sum of rotation errors over the ground-truth path between the pairs (degrees per m).
    pub rot_deg_per_m: f64,
}

/// Index pairs on a pose list.
pub fn pairs(poses: &[Iso3], delta: Delta) -> Vec<(usize, usize)> {
    let ids: Vec<usize> = match delta {
        Delta::Frames(n) => (0..poses.len()).step_by(n.max(1)).collect(),
        Delta::Metres(d) => {
            // The first pose always starts a pair (evo ≥ 1.30).
            let mut ids = vec![0];
            let mut path = 0.0;
            for i in 1..poses.len() {
                path += (poses[i].translation.vector - poses[i - 1].translation.vector).norm();
                if path >= d {
                    ids.push(i);
                    path = 0.0;
                }
            }
            ids
        }
    };
    ids.windows(2).map(|w| (w[0], w[1])).collect()
}

/// RPE of `est` against `gt` (matched by timestamp within `tolerance_s`), after aligning the
/// estimate (`Some(with_scale)`) or not (`None`; SE(3) alignment does not change RPE). `None`
/// when no pair exists.
pub fn rpe(est: &[StampedPose], gt: &[StampedPose], tolerance_s: f64, delta: Delta, align: Option<bool>) -> Option<Rpe> {
    let matched = associate(est, gt, tolerance_s);
    let mut p: Vec<Iso3> = matched.iter().map(|(e, _)| e.t_world_cam).collect();
    let q: Vec<Iso3> = matched.iter().map(|(_, g)| g.t_world_cam).collect();
    if let Some(with_scale) = align {
        let sim = umeyama_poses(&p, &q, with_scale)?;
        p = p.iter().map(|x| sim.apply_pose(x)).collect();
    }
    let pairs = pairs(&p, delta);
    if pairs.is_empty() {
        return None;
    }
    let (mut t_err, mut r_err, mut path) = (Vec::new(), Vec::new(), 0.0);
    for &(i, j) in &pairs {
        let e = (q[i].inverse() * q[j]).inverse() * (p[i].inverse() * p[j]);
        t_err.push(e.translation.vector.norm());
        r_err.push(e.rotation.angle().to_degrees());
        path += (i..j).map(|k| (q[k + 1].translation.vector - q[k].translation.vector).norm()).sum::<f64>();
    }
    let per = |v: &[f64]| if path > 0.0 { v.iter().sum::<f64>() / path } else { 0.0 };
    Some(Rpe { trans_m: Stats::of(&t_err)?, rot_deg: Stats::of(&r_err)?, trans_per_m: per(&t_err), rot_deg_per_m: per(&r_err) })
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::geometry::exp_se3;
    use nalgebra::Vector6;

    #[test]
    fn rpe_of_a_constant_drift_is_that_drift() {
        // Ground truth: a smooth path. Estimate: the same steps, each with an extra 0.5 mm along
        // the camera's x and 0.1° about its z.
        let step = |i: usize| exp_se3(&Vector6::new(0.002, 0.001 * (i as f64 * 0.1).sin(), 0.0005, 0.01, 0.02 * (i as f64 * 0.2).cos(), 0.0));
        let drift = exp_se3(&Vector6::new(0.0005, 0.0, 0.0, 0.0, 0.0, 0.1f64.to_radians()));
        let (mut g, mut e) = (Iso3::identity(), Iso3::identity());
        let (mut gt, mut est) = (Vec::new(), Vec::new());
        for i in 0..100 {
            gt.push(StampedPose { timestamp_s: i as f64, t_world_cam: g });
            est.push(StampedPose { timestamp_s: i as f64, t_world_cam: e });
            g *= step(i);
            e = e * step(i) * drift;
        }
        let r = rpe(&est, &gt, 0.01, Delta::Frames(1), None).unwrap();
        assert_eq!(r.trans_m.count, 99);
        // E = step⁻¹ (step · drift) = drift.
        assert!((r.trans_m.rmse - 0.0005).abs() < 1e-9 && (r.trans_m.max - 0.0005).abs() < 1e-9, "{r:?}");
        assert!((r.rot_deg.mean - 0.1).abs() < 1e-9, "{r:?}");
    }

    #[test]
    fn path_pairs_follow_the_travelled_distance() {
        let poses: Vec<Iso3> = (0..11).map(|i| Iso3::translation(0.1 * i as f64, 0.0, 0.0)).collect();
        assert_eq!(pairs(&poses, Delta::Metres(0.25)), vec![(0, 3), (3, 6), (6, 9)]);
        assert_eq!(pairs(&poses, Delta::Frames(5)), vec![(0, 5), (5, 10)]);
    }
}
