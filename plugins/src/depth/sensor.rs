//! `sensor`: the oracle depth estimator. Passes the frame's own depth through (an RGB-D
//! camera's, or the phantom's ground truth), so that tracking and fusion can be measured
//! without the error of shape from shading.
//!
//! With a depth noise model (`camera.toml`'s `depth_noise`; issue 17) every valid pixel also
//! gets its σ, which the trackers and fusers weigh by. Without one the frame carries no σ: the
//! trackers' own noise floors stand alone, as before the model existed.

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
    }
}

/// The oracle depth estimator.
#[derive(Debug, Clone)]
pub struct Sensor {
    params: SensorParams,
    noise: Option<DepthNoiseModel>,
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
        Ok(Self { params, noise })
    }
}

impl DepthEstimator for Sensor {
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
            ctx.warn(format!("frame {}: no depth within [{lo}, {hi}] m", frame.index));
        }
        let sigma = self.noise.map(|model| {
            capsule_slam_framework::DepthMap::from_fn(out.width(), out.height(), |x, y| {
                let z = out.at(x, y);
                [if z > 0.0 { model.sigma_m(f64::from(z)) as f32 } else { 0.0 }]
            })
        });
        let sigma_correlation_px = self.noise.map_or(0.0, |m| m.correlation_px);
        Ok(DepthEstimate { sigma_m: sigma, sigma_correlation_px, ..DepthEstimate::depth_only(out) })
    }
}

register!(DepthEstimator, Sensor);
