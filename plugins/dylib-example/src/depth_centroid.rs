//! `example-depth-centroid`: a one-degree-of-freedom tracker, an example of a tracker library
//! plugin (ABI version 2). The camera is taken to move along its optical axis only: between
//! the model's prediction (rendered at the last pose) and the frame, the mean depth of the
//! pixels valid in both drops by the distance it advanced, `Δz = mean(z_model − z_frame)`
//! (exact for a wall facing the camera), and `t_world_cam = t_world_prev · T(0, 0, Δz)`.
//! Where the model shows too little (a new map shows only its stable surfels), the reference
//! is the last frame it tracked (its own state: a library stage keeps what it likes).
//! Rotation and sideways motion are not seen: a baseline to beat, not a tracker to use.

use capsule_slam_abi::export::LibraryPlugin;
use capsule_slam_abi::export_v2::{LibraryTracker, TrackInput, TrackOutput};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::Iso3;

capsule_slam_framework::plugin_params! {
    /// Parameters of `example-depth-centroid`.
    pub struct DepthCentroidParams {
        /// Fewer pixels with depth in both the frame and the model: the frame is lost.
        pub min_pixels: u32 = 100; unit = "px"; range = 1.0..=1.0e7;
        /// Larger steps along the axis are taken as a failure (lost).
        pub max_step_m: f64 = 0.01; unit = "m"; range = 0.0..=1.0;
    }
}

/// The tracker.
pub struct DepthCentroid {
    params: DepthCentroidParams,
    /// The depth of the last frame it tracked.
    last_depth: Option<capsule_slam_framework::image::DepthMap>,
}

impl LibraryPlugin for DepthCentroid {
    const NAME: &'static std::ffi::CStr = c"example-depth-centroid";
    const SUMMARY: &'static std::ffi::CStr =
        c"example library tracker: motion along the optical axis from the mean depth difference between the model's prediction and the frame";
    type Params = DepthCentroidParams;

    fn build(params: DepthCentroidParams, _camera: &PinholeCamera) -> Result<Self, String> {
        Ok(Self { params, last_depth: None })
    }
}

impl LibraryTracker for DepthCentroid {
    fn track(&mut self, input: &TrackInput) -> Result<TrackOutput, String> {
        let hold = TrackOutput { t_world_cam: input.t_world_prev, tracked: false, inliers: 0, residual_rms: 0.0, iterations: 1 };
        let diffs = |reference: &capsule_slam_framework::image::DepthMap| -> Vec<f64> {
            reference.data().iter().zip(input.depth_m.data()).filter(|(m, f)| **m > 0.0 && **f > 0.0).map(|(m, f)| f64::from(*m) - f64::from(*f)).collect()
        };
        let min = self.params.min_pixels as usize;
        let from_model = input.model.as_ref().map(|m| diffs(&m.depth_m)).filter(|d| d.len() >= min);
        let Some(d) = from_model.or_else(|| self.last_depth.as_ref().map(diffs)) else {
            // The first frame: nothing to compare with, the pose is the start.
            self.last_depth = Some(input.depth_m.clone());
            return Ok(TrackOutput { tracked: true, ..hold });
        };
        if d.len() < min {
            return Ok(hold);
        }
        let dz = d.iter().sum::<f64>() / d.len() as f64;
        let rms = (d.iter().map(|v| (v - dz) * (v - dz)).sum::<f64>() / d.len() as f64).sqrt();
        if dz.abs() > self.params.max_step_m {
            return Ok(hold);
        }
        self.last_depth = Some(input.depth_m.clone());
        Ok(TrackOutput { t_world_cam: input.t_world_prev * Iso3::translation(0.0, 0.0, dz), tracked: true, inliers: d.len(), residual_rms: rms, iterations: 1 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_abi::export_v2::ModelImages;
    use capsule_slam_framework::image::{DepthMap, Image, Rgb8};

    fn input(model_z: f32, frame_z: f32) -> TrackInput {
        let flat = |z: f32| DepthMap::filled(20, 10, z);
        TrackInput {
            index: 1,
            timestamp_s: 0.0,
            image: Rgb8::new(20, 10),
            depth_m: flat(frame_z),
            model: Some(ModelImages { depth_m: flat(model_z), normals_cam: Image::new(20, 10), colour: Rgb8::new(20, 10) }),
            t_world_prev: Iso3::translation(0.01, 0.0, 0.0),
        }
    }

    #[test]
    fn a_wall_one_millimetre_nearer_is_one_millimetre_of_advance() {
        let mut t = DepthCentroid::build(DepthCentroidParams::default(), &PinholeCamera::new(20, 10, 10.0, 10.0, 9.5, 4.5)).unwrap();
        let out = t.track(&input(0.030, 0.029)).unwrap();
        assert!(out.tracked && out.inliers == 200);
        let p = out.t_world_cam.translation.vector;
        assert!((p.x - 0.01).abs() < 1e-12 && (p.z - 0.001).abs() < 1e-6, "{p:?}");
        // Too few pixels: lost, the pose held.
        let mut sparse = input(0.030, 0.029);
        sparse.depth_m = DepthMap::new(20, 10);
        let out = t.track(&sparse).unwrap();
        assert!(!out.tracked && out.t_world_cam == sparse.t_world_prev);
        // Without a model, against its last tracked frame (0.029 m): 0.5 mm nearer.
        let mut no_model = input(0.0, 0.0285);
        no_model.model = None;
        let out = t.track(&no_model).unwrap();
        assert!(out.tracked && (out.t_world_cam.translation.vector.z - 0.0005).abs() < 1e-6, "{out:?}");
    }
}
