//! Evaluation against ground truth: trajectory alignment (Umeyama) and the absolute
//! trajectory error (ATE) of Sturm et al. (2012), as evo's `evo_ape` computes it.

pub mod align;

use nalgebra::Point3;
use serde::Serialize;

use crate::geometry::StampedPose;

pub use align::{Similarity, umeyama};

/// Pairs of (estimated, ground-truth) poses matched by nearest timestamp within `tolerance_s`
/// (each estimated pose matched to its nearest ground-truth pose).
pub fn associate<'a>(est: &'a [StampedPose], gt: &'a [StampedPose], tolerance_s: f64) -> Vec<(&'a StampedPose, &'a StampedPose)> {
    est.iter().filter_map(|e| crate::io::tum::nearest(gt, e.timestamp_s, tolerance_s, |p| p.timestamp_s).map(|i| (e, &gt[i]))).collect()
}

/// Absolute trajectory error statistics (translation part), metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Ate {
    /// RMS of the position errors after alignment.
    pub rmse_m: f64,
    /// Mean error.
    pub mean_m: f64,
    /// Median error.
    pub median_m: f64,
    /// Largest error.
    pub max_m: f64,
    /// Matched pose pairs.
    pub pairs: usize,
    /// Scale of the alignment (1 for SE(3)).
    pub scale: f64,
}

/// ATE after aligning the estimated positions to the ground truth with Umeyama's method,
/// with scale (Sim(3), for monocular runs) or without (SE(3)). `None` with fewer than three
/// matched pairs.
pub fn ate(est: &[StampedPose], gt: &[StampedPose], tolerance_s: f64, with_scale: bool) -> Option<Ate> {
    let pairs = associate(est, gt, tolerance_s);
    if pairs.len() < 3 {
        return None;
    }
    let src: Vec<Point3<f64>> = pairs.iter().map(|(e, _)| Point3::from(e.t_world_cam.translation.vector)).collect();
    let dst: Vec<Point3<f64>> = pairs.iter().map(|(_, g)| Point3::from(g.t_world_cam.translation.vector)).collect();
    let sim = umeyama(&src, &dst, with_scale)?;
    let mut err: Vec<f64> = src.iter().zip(&dst).map(|(s, d)| (sim.apply(s) - d).norm()).collect();
    let n = err.len() as f64;
    let rmse_m = (err.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
    let mean_m = err.iter().sum::<f64>() / n;
    err.sort_by(f64::total_cmp);
    let m = err.len();
    let median_m = if m % 2 == 1 { err[m / 2] } else { 0.5 * (err[m / 2 - 1] + err[m / 2]) };
    Some(Ate { rmse_m, mean_m, median_m, max_m: err[m - 1], pairs: m, scale: sim.scale })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Iso3, exp_se3};
    use nalgebra::Vector6;

    fn traj(n: usize) -> Vec<StampedPose> {
        (0..n)
            .map(|i| {
                let s = i as f64 * 0.1;
                StampedPose { timestamp_s: s, t_world_cam: exp_se3(&Vector6::new(0.05 * s.sin(), 0.03 * s, 0.02 * (2.0 * s).cos(), 0.1 * s, 0.2, -0.1 * s)) }
            })
            .collect()
    }

    #[test]
    fn ate_of_a_transformed_copy_is_zero_after_alignment() {
        let gt = traj(50);
        let t = exp_se3(&Vector6::new(0.3, -0.2, 0.1, 0.5, -0.4, 0.3));
        let est: Vec<_> = gt.iter().map(|p| StampedPose { timestamp_s: p.timestamp_s, t_world_cam: t * p.t_world_cam }).collect();
        let a = ate(&est, &gt, 0.01, false).unwrap();
        assert!(a.rmse_m < 1e-12, "{a:?}");
        assert_eq!(a.pairs, 50);
    }

    #[test]
    fn a_constant_offset_along_one_axis_is_removed_but_noise_is_not() {
        let gt = traj(40);
        // Alternate ±1 mm along x: alignment cannot remove it; the RMSE is 1 mm.
        let est: Vec<_> = gt
            .iter()
            .enumerate()
            .map(|(i, p)| StampedPose {
                timestamp_s: p.timestamp_s,
                t_world_cam: Iso3::translation(if i % 2 == 0 { 0.001 } else { -0.001 }, 0.0, 0.0) * p.t_world_cam,
            })
            .collect();
        let a = ate(&est, &gt, 0.01, false).unwrap();
        assert!((a.rmse_m - 0.001).abs() < 5e-5, "{a:?}");
    }
}
