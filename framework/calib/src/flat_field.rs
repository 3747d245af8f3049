//! The flat field of a capsule: the lens-and-light fall-off of a `vignetting.toml` fitted to
//! images of a white target facing the capsule (`capsule-slam calibrate-vignetting`).

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::Falloff;
use capsule_slam_framework::light::vignetting::{RadialProfile, VignettingFile, cos_alpha, radius2};

/// The value at the principal point of an image of `cam`'s size: the mean of its positive pixels
/// within 2 % of the half-diagonal of the centre (`None` if there are none).
pub fn centre_value(image: &[f64], cam: &PinholeCamera) -> Option<f64> {
    let w = cam.width;
    let near: Vec<f64> = (0..image.len()).filter(|k| radius2(cam, (k % w) as f64, (k / w) as f64) < 4e-4 && image[*k] > 0.0).map(|k| image[k]).collect();
    (!near.is_empty()).then(|| near.iter().sum::<f64>() / near.len() as f64)
}

/// Fits the lens-and-light profile of a `vignetting.toml` to a linear flat-field image of a
/// target facing the capsule (cos³α divided out first; pixels with value ≤ 0 or outside the
/// field of view are skipped). `degree` 1 to 3.
pub fn fit_flat_field(linear: &[f64], cam: &PinholeCamera, gamma: f64, degree: usize) -> Option<VignettingFile> {
    let (w, h) = (cam.width, cam.height);
    if linear.len() != w * h {
        return None;
    }
    let centre = centre_value(linear, cam)?;
    let samples: Vec<(f64, f64, f64)> = (0..w * h)
        .filter_map(|k| {
            let (u, v) = ((k % w) as f64, (k / w) as f64);
            (linear[k] > 0.0 && cam.in_fov(u, v)).then(|| (radius2(cam, u, v), linear[k] / centre / Falloff::flat_to_lens_and_light(cos_alpha(cam, u, v)), 1.0))
        })
        .collect();
    let lens = RadialProfile::fit(&samples, degree)?;
    Some(VignettingFile { gamma, lens_and_light: lens.coeffs })
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::light::LightModel;
    use capsule_slam_framework::light::vignetting::{flat_field_linear, light_falloff};

    fn cam() -> PinholeCamera {
        let mut c = PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5);
        c.fov_radius_px = Some(150.4);
        c
    }

    #[test]
    fn flat_field_fit_recovers_the_light_models_falloff() {
        let c = cam();
        // No ambient: a flat field's ambient light has no cos³α, so it would show as a misfit of
        // ambient / direct (3 % with the phantom's 0.02).
        let light = LightModel { spot_exponent: 1.0, ambient: 0.0, ..LightModel::default() };
        let img: Vec<f64> = (0..c.width * c.height).map(|k| flat_field_linear(&light, &c, (k % c.width) as f64, (k / c.width) as f64, 0.02, 0.5)).collect();
        let file = fit_flat_field(&img, &c, 2.2, 3).unwrap();
        let mut worst = [0.0f64; 2];
        for k in (0..c.width * c.height).step_by(7) {
            let (u, v) = ((k % c.width) as f64, (k / c.width) as f64);
            if !c.in_fov(u, v) {
                continue;
            }
            for (i, f) in [Falloff::LensAndLight, Falloff::FlatField].into_iter().enumerate() {
                let truth = light_falloff(&light, &c, u, v, f);
                worst[i] = worst[i].max((file.falloff(&c, u, v, f) / truth - 1.0).abs());
            }
        }
        // cos α^1 (the LED profile) against an even polynomial leaves a small misfit.
        assert!(worst[0] < 0.005 && worst[1] < 0.005, "relative misfit lens-and-light {} flat {}", worst[0], worst[1]);
    }
}
