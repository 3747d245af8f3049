//! The noise of a depth source: `σ(z) = absolute_m + relative · z + quadratic_per_m · z²`,
//! metres, z the depth along the optical axis (issue 17; per-source figures in
//! `docs/depth-noise.md`). A camera declares it in `camera.toml`
//! (`depth_noise = { relative = 0.01, absolute_m = 0.0002 }`); the `sensor` stage turns it into a
//! per-pixel σ that travels with the frame ([`crate::RgbdFrame::depth_sigma_m`]), and the
//! trackers weigh every residual by it.

use serde::{Deserialize, Serialize};

use crate::error::ConfigProblem;
use crate::image::DepthMap;

/// A depth noise model: `σ(z) = absolute_m + relative · z + quadratic_per_m · z²`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthNoiseModel {
    /// Constant part, metres (quantisation, read noise).
    #[serde(default)]
    pub absolute_m: f64,
    /// Part proportional to the depth (a time-of-flight sensor's, a smooth stereo error's).
    #[serde(default)]
    pub relative: f64,
    /// Part growing with the square of the depth, 1/m (triangulation: structured light and
    /// stereo, σ_z = z² σ_d / (f b)).
    #[serde(default)]
    pub quadratic_per_m: f64,
    /// Correlation length of the error, pixels of the full image (0: independent pixels). A
    /// smooth error (stereo matching over windows, a learned estimator, a per-frame scale) moves
    /// a whole neighbourhood alike: a tracker counts a block of this size as one measurement.
    #[serde(default)]
    pub correlation_px: f64,
}

impl DepthNoiseModel {
    /// σ at depth `z_m`, metres.
    pub fn sigma_m(&self, z_m: f64) -> f64 {
        self.absolute_m + self.relative * z_m + self.quadratic_per_m * z_m * z_m
    }

    /// Raises a per-pixel σ image (`sigma_m`, made where there is none) to this model's σ of
    /// each pixel with depth in `depth_m` wherever the model's is larger, and its correlation
    /// length to this model's: the floor a tracker that measured the depth's error puts under
    /// the frame's own σ ([`crate::Tracker::depth_noise_in_use`]). A σ image of another size
    /// than the depth is replaced.
    pub fn raise(&self, depth_m: &DepthMap, sigma_m: &mut Option<DepthMap>, correlation_px: &mut f64) {
        let (w, h) = depth_m.size();
        let sigma = match sigma_m {
            Some(s) if s.size() == (w, h) => s,
            other => other.insert(DepthMap::new(w, h)),
        };
        for (s, z) in sigma.data_mut().iter_mut().zip(depth_m.data()) {
            if *z > 0.0 {
                *s = s.max(self.sigma_m(f64::from(*z)) as f32);
            }
        }
        *correlation_px = correlation_px.max(self.correlation_px);
    }

    /// Every problem of the model, keys prefixed with `prefix` (e.g. `depth_noise.`).
    pub fn problems(&self, prefix: &str) -> Vec<ConfigProblem> {
        let mut out = Vec::new();
        for (key, v, unit) in [
            ("absolute_m", self.absolute_m, "metres"),
            ("relative", self.relative, "a share of the depth"),
            ("quadratic_per_m", self.quadratic_per_m, "1/m"),
            ("correlation_px", self.correlation_px, "pixels"),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                out.push(ConfigProblem::new(
                    format!("{prefix}{key}"),
                    format!("{key} = {v} must be a finite number ≥ 0"),
                    format!("give {key} in {unit}, or remove the key (0)"),
                ));
            }
        }
        if out.is_empty() && self.absolute_m + self.relative + self.quadratic_per_m == 0.0 {
            out.push(ConfigProblem::new(
                prefix.trim_end_matches('.').to_owned(),
                "every term is 0: no depth is exact, and a zero σ would weigh a residual infinitely",
                "give at least absolute_m (e.g. the depth PNG's step / √12)",
            ));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raising_keeps_the_larger_sigma_per_pixel_and_the_longer_correlation() {
        let depth = DepthMap::from_fn(3, 1, |x, _| [[0.05f32, 0.0, 0.1][x]]);
        let m = DepthNoiseModel { absolute_m: 0.0, relative: 0.04, quadratic_per_m: 0.0, correlation_px: 60.0 };
        let mut sigma = Some(DepthMap::from_fn(3, 1, |x, _| [[0.001f32, 0.001, 0.009][x]]));
        let mut corr = 8.0;
        m.raise(&depth, &mut sigma, &mut corr);
        let s = sigma.expect("σ");
        assert_eq!((s.at(0, 0), s.at(1, 0), s.at(2, 0)), (0.002, 0.001, 0.009), "raised, no depth, already larger");
        assert_eq!(corr, 60.0);
        // No σ image, or one of the wrong size: made from the model alone.
        for mut none in [None, Some(DepthMap::new(2, 2))] {
            let mut corr = 100.0;
            m.raise(&depth, &mut none, &mut corr);
            let s = none.expect("σ made");
            assert_eq!((s.size(), s.at(0, 0), s.at(1, 0), corr), ((3, 1), 0.002, 0.0, 100.0));
        }
    }

    #[test]
    fn sigma_adds_the_three_terms() {
        let m = DepthNoiseModel { absolute_m: 0.0002, relative: 0.01, quadratic_per_m: 0.2, correlation_px: 0.0 };
        assert!((m.sigma_m(0.05) - (0.0002 + 0.0005 + 0.0005)).abs() < 1e-15);
    }

    #[test]
    fn negative_nan_and_all_zero_models_name_their_key() {
        let bad = DepthNoiseModel { absolute_m: -1.0, relative: f64::NAN, quadratic_per_m: 0.0, correlation_px: -2.0 };
        let keys: Vec<String> = bad.problems("depth_noise.").into_iter().map(|p| p.key).collect();
        assert_eq!(keys, ["depth_noise.absolute_m", "depth_noise.relative", "depth_noise.correlation_px"]);
        let zero = DepthNoiseModel { absolute_m: 0.0, relative: 0.0, quadratic_per_m: 0.0, correlation_px: 0.0 };
        assert_eq!(zero.problems("depth_noise.")[0].key, "depth_noise");
    }

    #[test]
    fn an_unknown_key_is_refused() {
        let e = toml::from_str::<DepthNoiseModel>("relative = 0.01\nabsolut_m = 0.1").unwrap_err();
        assert!(e.to_string().contains("absolut_m"), "{e}");
    }
}
