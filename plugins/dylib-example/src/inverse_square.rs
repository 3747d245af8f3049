//! `example-inverse-square`: depth from brightness alone. A point light at the camera lights
//! a Lambertian wall of uniform albedo that faces it with irradiance falling as 1/z², so
//! `I = I_ref · (z_ref / z)²` and `z = z_ref · √(I_ref / I)` (the inverse-square term of
//! near-light shape from shading (Okatani & Deguchi 1997) without its shading term: every pixel is taken
//! to face the light). A baseline for real shape from shading, and an example of a
//! depth-estimator library plugin.

use capsule_slam_abi::export::{LibraryDepthEstimator, LibraryPlugin};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::image::{DepthMap, Rgb8, intensity_ntsc};

capsule_slam_framework::plugin_params! {
    /// Parameters of `example-inverse-square`.
    pub struct InverseSquareParams {
        /// Depth at which a facing wall has intensity `intensity_ref`.
        pub z_ref_m: f64 = 0.02; unit = "m"; range = 0.0001..=1.0;
        /// Intensity (NTSC luminance, 0–1) of a facing wall at `z_ref_m`.
        pub intensity_ref: f64 = 0.5; unit = "-"; range = 0.001..=1.0;
        /// Darker pixels get no depth (too noisy, or no light).
        pub min_intensity: f64 = 0.02; unit = "-"; range = 0.0..=1.0;
        /// Depths beyond this are dropped.
        pub max_depth_m: f64 = 0.2; unit = "m"; range = 0.0001..=10.0;
    }
}

/// The estimator.
pub struct InverseSquare {
    params: InverseSquareParams,
    camera: PinholeCamera,
}

impl LibraryPlugin for InverseSquare {
    const NAME: &'static std::ffi::CStr = c"example-inverse-square";
    const SUMMARY: &'static std::ffi::CStr =
        c"example library plugin: depth from brightness, z = z_ref sqrt(I_ref / I) (a light at the camera, every pixel facing it)";
    type Params = InverseSquareParams;

    fn build(params: InverseSquareParams, camera: &PinholeCamera) -> Result<Self, String> {
        if params.min_intensity <= 0.0 {
            return Err(
                "min_intensity = 0 would give infinite depth on black pixels: use a positive value (fix: plugins.example-inverse-square.min_intensity)"
                    .to_owned(),
            );
        }
        Ok(Self { params, camera: camera.clone() })
    }
}

impl LibraryDepthEstimator for InverseSquare {
    fn estimate(&mut self, image: &Rgb8) -> Result<DepthMap, String> {
        let p = &self.params;
        Ok(DepthMap::from_fn(image.width(), image.height(), |x, y| {
            let i = f64::from(intensity_ntsc(image.pixel(x, y))) / 255.0;
            if i < p.min_intensity || !self.camera.in_fov(x as f64, y as f64) {
                return [0.0];
            }
            let z = p.z_ref_m * (p.intensity_ref / i).sqrt();
            [if z <= p.max_depth_m { z as f32 } else { 0.0 }]
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn estimator() -> InverseSquare {
        InverseSquare::build(InverseSquareParams::default(), &PinholeCamera::new(2, 1, 1.0, 1.0, 0.5, 0.0)).unwrap()
    }

    #[test]
    fn a_quarter_of_the_reference_intensity_is_twice_the_reference_depth() {
        // I_ref = 0.5 → level 127.5; a quarter of it, level 31.875 ≈ 32 (grey: luminance = level).
        let img = Rgb8::from_vec(2, 1, vec![32, 32, 32, 255, 255, 255]).unwrap();
        let d = estimator().estimate(&img).unwrap();
        let quarter = 32.0 / 255.0;
        let expect = 0.02 * (0.5f64 / quarter).sqrt();
        assert!((f64::from(d.at(0, 0)) - expect).abs() < 1e-5, "{} vs {expect}", d.at(0, 0)); // f32 luminance
        assert!((expect - 0.04).abs() < 2e-4);
        assert!((f64::from(d.at(1, 0)) - 0.02 * 0.5f64.sqrt()).abs() < 1e-5);
    }

    #[test]
    fn dark_pixels_have_no_depth() {
        let img = Rgb8::from_vec(2, 1, vec![0, 0, 0, 2, 2, 2]).unwrap();
        let d = estimator().estimate(&img).unwrap();
        assert_eq!(d.data(), &[0.0, 0.0]);
    }
}
