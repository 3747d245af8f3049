//! `example-gamma`: undoes a display gamma, `I_linear = 255 · (I / 255)^γ`, so that later
//! stages see intensities proportional to radiance (shape from shading assumes a linear
//! camera: capsule videos are gamma-encoded, as any sRGB video), and masks saturated pixels, whose
//! radiance is unknown.

use capsule_slam_abi::export::{LibraryPlugin, LibraryPreprocessor};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::image::{Mask, Rgb8};

capsule_slam_framework::plugin_params! {
    /// Parameters of `example-gamma`.
    pub struct GammaParams {
        /// Display gamma to undo (sRGB ≈ 2.2; 1 = leave the intensities).
        pub gamma: f64 = 2.2; unit = "-"; range = 0.1..=10.0;
        /// Pixels with any channel at or above this value are saturated and masked.
        pub saturated_min: u32 = 255; unit = "8-bit level"; range = 1.0..=256.0;
    }
}

/// The preprocessor: a 256-entry table, made once.
pub struct Gamma {
    table: [u8; 256],
    saturated_min: u32,
}

impl LibraryPlugin for Gamma {
    const NAME: &'static std::ffi::CStr = c"example-gamma";
    const SUMMARY: &'static std::ffi::CStr = c"example library plugin: undoes a display gamma (I/255)^gamma and masks saturated pixels";
    type Params = GammaParams;

    fn build(params: GammaParams, _camera: &PinholeCamera) -> Result<Self, String> {
        let mut table = [0u8; 256];
        for (i, t) in table.iter_mut().enumerate() {
            *t = (255.0 * (i as f64 / 255.0).powf(params.gamma)).round().clamp(0.0, 255.0) as u8;
        }
        Ok(Self { table, saturated_min: params.saturated_min })
    }
}

impl LibraryPreprocessor for Gamma {
    fn process(&mut self, image: &mut Rgb8, mask: &mut Mask) -> Result<(), String> {
        for (px, m) in image.data_mut().chunks_exact_mut(3).zip(mask.data_mut()) {
            *m = px.iter().any(|&v| u32::from(v) >= self.saturated_min);
            for v in px {
                *v = self.table[usize::from(*v)];
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::params::PluginParams;

    #[test]
    fn levels_follow_the_power_law_and_saturated_pixels_are_masked() {
        let mut g = Gamma::build(GammaParams::default(), &PinholeCamera::new(3, 1, 1.0, 1.0, 1.0, 0.0)).unwrap();
        let mut img = Rgb8::from_vec(3, 1, vec![0, 0, 0, 128, 128, 128, 255, 10, 10]).unwrap();
        let mut mask = Mask::new(3, 1);
        g.process(&mut img, &mut mask).unwrap();
        // 255 · (128/255)^2.2 = 56.0
        assert_eq!(img.data(), &[0, 0, 0, 56, 56, 56, 255, 0, 0]);
        assert_eq!(mask.data(), &[false, false, true]);
        assert_eq!(GammaParams::docs().len(), 2);
    }

    #[test]
    fn gamma_one_is_the_identity() {
        let p = GammaParams { gamma: 1.0, ..GammaParams::default() };
        let g = Gamma::build(p, &PinholeCamera::new(1, 1, 1.0, 1.0, 0.0, 0.0)).unwrap();
        assert!(g.table.iter().enumerate().all(|(i, &v)| usize::from(v) == i));
    }
}
