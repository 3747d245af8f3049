//! Single-frame depth error of a depth estimator (Eigen et al. 2014 conventions): AbsRel,
//! RMSE, δ < 1.25, over pixels where both maps are valid, optionally after per-frame median
//! scaling (monocular methods have no absolute scale).

use serde::Serialize;

use crate::image::DepthMap;

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
}
