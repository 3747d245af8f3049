//! Single-frame depth error of a depth estimator (Eigen et al. 2014 conventions): AbsRel,
//! RMSE, δ < 1.25, over pixels where both maps are valid, optionally after per-frame median
//! scaling (monocular methods have no absolute scale); the coverage of the field of view; and,
//! for a stereo rig, the share of pixels whose disparity `f b / z` is off by more than 1 or 2
//! pixels (Middlebury's bad-τ, Scharstein & Szeliski 2002).

use serde::Serialize;

use crate::image::{DepthMap, Mask};

/// Depth error statistics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DepthError {
    /// Mean |d − d*| / d*.
    pub abs_rel: f64,
    /// RMS of d − d*, metres.
    pub rmse_m: f64,
    /// Share of pixels with max(d/d*, d*/d) < 1.25.
    pub delta_1_25: f64,
    /// Pixels compared.
    pub pixels: usize,
    /// Scale applied to the estimate (1 without median scaling).
    pub scale: f64,
}

/// Compares `est` with `gt`; `None` if the sizes differ or no pixel is valid in both.
pub fn depth_error(est: &DepthMap, gt: &DepthMap, median_scaling: bool) -> Option<DepthError> {
    if est.size() != gt.size() {
        return None;
    }
    let pairs: Vec<(f64, f64)> = est
        .data()
        .iter()
        .zip(gt.data())
        .filter(|(e, g)| e.is_finite() && g.is_finite() && **e > 0.0 && **g > 0.0)
        .map(|(e, g)| (f64::from(*e), f64::from(*g)))
        .collect();
    if pairs.is_empty() {
        return None;
    }
    let scale = if median_scaling {
        let med = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        med(pairs.iter().map(|p| p.1).collect()) / med(pairs.iter().map(|p| p.0).collect())
    } else {
        1.0
    };
    let n = pairs.len() as f64;
    let (mut rel, mut sq, mut good) = (0.0, 0.0, 0usize);
    for (e, g) in &pairs {
        let e = e * scale;
        rel += (e - g).abs() / g;
        sq += (e - g) * (e - g);
        if (e / g).max(g / e) < 1.25 {
            good += 1;
        }
    }
    Some(DepthError { abs_rel: rel / n, rmse_m: (sq / n).sqrt(), delta_1_25: good as f64 / n, pixels: pairs.len(), scale })
}

/// The share of the pixels with a ground truth inside `fov` (every pixel when `None`) that have
/// an estimate; `None` if the sizes differ or no such pixel exists.
pub fn coverage(est: &DepthMap, gt: &DepthMap, fov: Option<&Mask>) -> Option<f64> {
    if est.size() != gt.size() || fov.is_some_and(|m| m.size() != gt.size()) {
        return None;
    }
    let (mut seen, mut covered) = (0usize, 0usize);
    for (i, (e, g)) in est.data().iter().zip(gt.data()).enumerate() {
        if !(g.is_finite() && *g > 0.0) || fov.is_some_and(|m| !m.data()[i]) {
            continue;
        }
        seen += 1;
        covered += usize::from(e.is_finite() && *e > 0.0);
    }
    (seen > 0).then(|| covered as f64 / seen as f64)
}

/// The shares of the pixels valid in both maps whose disparity `fb / z` (`fb`: the rectified
/// focal length times the baseline, pixel·metres) differs from the truth's by more than 1 and
/// by more than 2 pixels; `None` if the sizes differ or no pixel is valid in both.
pub fn bad_disparity(est: &DepthMap, gt: &DepthMap, fb: f64) -> Option<(f64, f64)> {
    if est.size() != gt.size() {
        return None;
    }
    let (mut n, mut bad1, mut bad2) = (0usize, 0usize, 0usize);
    for (e, g) in est.data().iter().zip(gt.data()) {
        if !(e.is_finite() && g.is_finite() && *e > 0.0 && *g > 0.0) {
            continue;
        }
        let err = (fb / f64::from(*e) - fb / f64::from(*g)).abs();
        n += 1;
        bad1 += usize::from(err > 1.0);
        bad2 += usize::from(err > 2.0);
    }
    (n > 0).then(|| (bad1 as f64 / n as f64, bad2 as f64 / n as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_errors() {
        let gt = DepthMap::filled(10, 10, 0.04);
        let est = DepthMap::filled(10, 10, 0.05);
        let e = depth_error(&est, &gt, false).unwrap();
        assert!((e.abs_rel - 0.25).abs() < 1e-6 && (e.rmse_m - 0.01).abs() < 1e-6);
        assert_eq!(e.delta_1_25, 0.0);
        let s = depth_error(&est, &gt, true).unwrap();
        assert!(s.abs_rel < 1e-6 && (s.scale - 0.8).abs() < 1e-6 && s.delta_1_25 == 1.0);
        assert!(depth_error(&DepthMap::new(10, 10), &gt, false).is_none());
    }

    #[test]
    fn coverage_and_bad_disparities() {
        // Truth 50 mm everywhere (disparity 16 px at fb = 0.8); the estimate has 20 of 100 pixels
        // empty, 10 at 1.5 px off, 5 at 3 px off.
        let gt = DepthMap::filled(10, 10, 0.05);
        let est = DepthMap::from_fn(10, 10, |x, y| {
            let i = y * 10 + x;
            [if i < 20 {
                0.0
            } else if i < 30 {
                0.8 / 17.5
            } else if i < 35 {
                0.8 / 13.0
            } else {
                0.05
            }]
        });
        assert!((coverage(&est, &gt, None).unwrap() - 0.8).abs() < 1e-9);
        let mut fov = Mask::filled(10, 10, true);
        (0..20).for_each(|i| *fov.at_mut(i % 10, i / 10) = false);
        assert!((coverage(&est, &gt, Some(&fov)).unwrap() - 1.0).abs() < 1e-9);
        let (b1, b2) = bad_disparity(&est, &gt, 0.8).unwrap();
        assert!((b1 - 15.0 / 80.0).abs() < 1e-9 && (b2 - 5.0 / 80.0).abs() < 1e-9, "{b1} {b2}");
    }
}
