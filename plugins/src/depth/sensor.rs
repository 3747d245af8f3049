//! `sensor`: the oracle depth estimator. Passes the frame's own depth through (an RGB-D
//! camera's, or the phantom's ground truth), so that tracking and fusion can be measured
//! without the error of shape from shading.
//!
//! Every valid pixel also gets its σ, which the trackers and fusers weigh by (issue 17): from
//! `camera.toml`'s `depth_noise` where it declares one, else a small uncorrelated default,
//! `default_sigma_m` (0.1 mm: the 0.2 mm steps of a 1/5000 m depth PNG are σ 0.06 mm, and a
//! sensor adds to them), with a warning that names it.

use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, DepthEstimate, DepthEstimator, Plugin, StageError, register};

capsule_slam_framework::plugin_params! {
    /// Parameters of `sensor`.
    pub struct SensorParams {
        /// Depths below this are set invalid (0). ElasticFusion hard-codes 0.3 m (room scale);
        /// a capsule sees tissue from a few millimetres.
        pub min_depth_m: f64 = 0.001; unit = "m"; range = 0.0..=100.0;
        /// Depths beyond this are set invalid (ElasticFusion's depthCut, 3 m, is room scale;
        /// a stomach is 8–20 cm long).
        pub max_depth_m: f64 = 0.3; unit = "m"; range = 0.0..=100.0;
        /// σ of every depth pixel where `camera.toml` declares no `depth_noise`: an absolute,
        /// uncorrelated error (a 1/5000 m depth PNG's steps alone are 0.06 mm; declare the
        /// sensor's model for anything else, `docs/usage.md`).
        pub default_sigma_m: f64 = 0.0001; unit = "m"; range = 1.0e-9..=1.0;
    }
}

/// The oracle depth estimator.
#[derive(Debug, Clone)]
pub struct Sensor {
    params: SensorParams,
    noise: DepthNoiseModel,
    /// Why σ is the default (told on the first frame), if it is.
    default_noise: Option<String>,
}

impl Plugin for Sensor {
    const NAME: &'static str = "sensor";
    const SUMMARY: &'static str = "oracle: the frame's own depth (RGB-D sensor or phantom ground truth), clipped to [min_depth_m, max_depth_m]";
    type Params = SensorParams;

    fn build(params: SensorParams, env: &BuildEnv) -> Result<Self, StageError> {
        crate::common::ordered("min_depth_m", params.min_depth_m, "max_depth_m", params.max_depth_m)?;
        let noise = env.depth_noise;
        if let Some(p) = noise.and_then(|n| n.problems("camera.depth_noise.").into_iter().next()) {
            return Err(StageError::invalid_input(format!("sensor: {}: {} ({})", p.key, p.message, p.fix)));
        }
        let default_noise = noise.is_none().then(|| {
            format!(
                "camera.toml declares no depth_noise: every depth pixel is taken to have σ = {} mm, uncorrelated (plugins.sensor.default_sigma_m); declare the sensor's model (docs/usage.md) if it is noisier",
                params.default_sigma_m * 1e3
            )
        });
        let noise = noise.unwrap_or(DepthNoiseModel { absolute_m: params.default_sigma_m, relative: 0.0, quadratic_per_m: 0.0, correlation_px: 0.0 });
        Ok(Self { params, noise, default_noise })
    }
}

impl DepthEstimator for Sensor {
    fn reads_prediction(&self) -> bool {
        false
    }

    fn source(&self) -> capsule_slam_framework::frame::DepthSource {
        capsule_slam_framework::frame::DepthSource::Measured
    }

    fn estimate(&mut self, frame: &capsule_slam_framework::CameraFrame, ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        let Some(depth) = &frame.depth_m else {
            return Err(StageError::invalid_input(format!(
                "frame {} has no depth image: `sensor` needs an input with depth.txt (RGB-D), or choose a depth estimator that works from the image",
                frame.index
            )));
        };
        let (lo, hi) = (self.params.min_depth_m as f32, self.params.max_depth_m as f32);
        let mut out = depth.clone();
        let mut valid = 0usize;
        for d in out.data_mut() {
            if !(d.is_finite() && *d >= lo && *d <= hi) {
                *d = 0.0;
            } else {
                valid += 1;
            }
        }
        ctx.count("valid_pixels", valid as f64);
        if valid == 0 {
            ctx.warn(format!("no depth within [{lo}, {hi}] m"));
        }
        if let Some(why) = self.default_noise.take() {
            ctx.warn(why);
        }
        let model = self.noise;
        let sigma = capsule_slam_framework::DepthMap::from_fn(out.width(), out.height(), |x, y| {
            let z = out.at(x, y);
            [if z > 0.0 { model.sigma_m(f64::from(z)) as f32 } else { 0.0 }]
        });
        Ok(DepthEstimate { sigma_m: Some(sigma), sigma_correlation_px: model.correlation_px, ..DepthEstimate::depth_only(out) })
    }
}

register!(DepthEstimator, Sensor);

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::context::StageReport;
    use capsule_slam_framework::{CameraFrame, DepthMap, PinholeCamera, Rgb8, Rig};

    fn estimate(noise: Option<DepthNoiseModel>) -> (DepthEstimate, Vec<String>) {
        let cam = PinholeCamera::new(8, 6, 8.0, 8.0, 3.5, 2.5);
        let rig = Rig::Mono(cam);
        let mut s = Sensor::build(SensorParams::default(), &BuildEnv::new(rig.clone(), None).with_depth_noise(noise)).unwrap();
        let mut frame = CameraFrame::mono(0, 0.0, Rgb8::new(8, 6));
        // 5 cm everywhere but one pixel without a return and one beyond max_depth_m.
        frame.depth_m = Some(DepthMap::from_fn(8, 6, |x, y| {
            [if (x, y) == (1, 1) {
                0.0
            } else if (x, y) == (2, 2) {
                9.0
            } else {
                0.05
            }]
        }));
        let mut r = StageReport::default();
        let out = s.estimate(&frame, &mut Context::new(0, &rig, None, &mut r)).unwrap();
        (out, r.warnings)
    }

    #[test]
    fn every_valid_pixel_carries_the_declared_sigma_or_the_default_with_a_warning() {
        let (out, warnings) = estimate(None);
        let sigma = out.sigma_m.expect("a σ per pixel");
        assert_eq!(sigma.at(0, 0), 1e-4, "the 0.1 mm default");
        assert_eq!((sigma.at(1, 1), sigma.at(2, 2)), (0.0, 0.0), "no σ where there is no depth");
        assert_eq!(out.sigma_correlation_px, 0.0);
        assert!(warnings.iter().any(|w| w.contains("default_sigma_m")), "{warnings:?}");
        let declared = DepthNoiseModel { absolute_m: 2e-4, relative: 0.01, quadratic_per_m: 0.0, correlation_px: 12.0 };
        let (out, warnings) = estimate(Some(declared));
        let sigma = out.sigma_m.expect("a σ per pixel");
        assert!((f64::from(sigma.at(0, 0)) - (2e-4 + 0.01 * 0.05)).abs() < 1e-9, "{}", sigma.at(0, 0));
        assert_eq!(out.sigma_correlation_px, 12.0);
        assert!(warnings.is_empty(), "{warnings:?}");
    }
}
