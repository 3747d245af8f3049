//! The observed albedo of a stereo frame (issue 19): with the depth triangulated, the near-light
//! model of `light.toml` (`capsule_slam_framework::light`),
//!
//! `L(u) = V(u) · ρ · (gain · cos θ · (ref / r)² · spot + ambient)`,
//!
//! is solved for ρ at every pixel with depth, the surface's normal from the depth itself:
//! `ρ = (L / V) / (direct(p, n) + ambient)`. Unlike shape from shading's (which assumes an
//! albedo to get its depth), this albedo is independent of the geometry's source: what the map
//! keeps per surfel (`Surfel::albedo`) for a monocular estimator to read back.
//!
//! When a preprocessor divided a fall-off out of the image (`Photometry::divided`), its scale
//! replaces V (and the LED profile, which it contains), as in `near-light-sfs`.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::{DividedFalloff, Falloff};
use capsule_slam_framework::image::NTSC_WEIGHTS;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::light::vignetting::cos_alpha;
use capsule_slam_framework::{DepthMap, GrayF32, Mask, Rgb8};
use nalgebra::Point3;

/// What a pixel of the image is read with.
pub struct AlbedoInput<'a> {
    /// The left view, as the preprocessors left it.
    pub image: &'a Rgb8,
    /// The left camera's depth, metres (0: none).
    pub depth_m: &'a DepthMap,
    /// Pixels to leave without albedo (highlights, out of view).
    pub ignore: Option<&'a Mask>,
    /// The fall-off a preprocessor divided out of the image.
    pub divided: Option<DividedFalloff>,
    /// A channel at or above this was clipped: no albedo.
    pub saturation: u16,
    /// Half the span of the central differences the normal is taken from, pixels.
    pub normal_px: usize,
}

/// The calibrated light and its gamma decoding.
pub struct AlbedoModel {
    light: LightModel,
    decode: [f64; 256],
}

impl AlbedoModel {
    /// The model of a capsule's light.
    pub fn new(light: LightModel) -> Self {
        let decode = std::array::from_fn(|v| light.decode(v as f64 / 255.0));
        Self { light, decode }
    }

    /// Per pixel the observed albedo (linear NTSC luminance), 0 where there is no depth, no
    /// normal (a neighbour `normal_px` away without depth), a masked or clipped pixel, or a
    /// surface the light does not reach.
    pub fn observe(&self, input: &AlbedoInput, cam: &PinholeCamera) -> GrayF32 {
        let (w, h) = input.image.size();
        let k = input.normal_px.max(1);
        let mut light = self.light.clone();
        if input.divided.is_some() {
            // The divided fall-off contains the LED profile.
            light.spot_exponent = 0.0;
        }
        let point = |x: usize, y: usize| -> Option<Point3<f64>> {
            let z = f64::from(input.depth_m.at(x, y));
            if z <= 0.0 {
                return None;
            }
            let pin = cam.pinhole_pixel(x as f64, y as f64)?;
            Some(cam.unproject(pin.x, pin.y, z))
        };
        GrayF32::from_fn_par(w, h, |x, y| {
            let rho = (|| -> Option<f64> {
                if input.ignore.is_some_and(|m| m.at(x, y)) || x < k || y < k || x + k >= w || y + k >= h {
                    return None;
                }
                let c = input.image.pixel(x, y);
                if c.iter().any(|v| u16::from(*v) >= input.saturation) {
                    return None;
                }
                let p = point(x, y)?;
                let du = point(x + k, y)? - point(x - k, y)?;
                let dv = point(x, y + k)? - point(x, y - k)?;
                let mut n = du.cross(&dv).try_normalize(1e-18)?;
                if n.dot(&p.coords) > 0.0 {
                    n = -n;
                }
                let (u, v) = (x as f64, y as f64);
                let (scale, ambient) = match input.divided {
                    None => (1.0 / self.light.vignetting_at(cam, u, v).max(1e-6), light.ambient),
                    Some(d) => {
                        let back = match d.falloff {
                            Falloff::LensAndLight => 1.0,
                            Falloff::FlatField => Falloff::flat_to_lens_and_light(cos_alpha(cam, u, v)),
                        };
                        // The ambient light never had the LED profile that was divided out.
                        let ambient = match self.light.spot_exponent {
                            0.0 => self.light.ambient,
                            e => self.light.ambient / cos_alpha(cam, u, v).powf(e),
                        };
                        (back / d.linear_scale, ambient)
                    }
                };
                let lum: f64 = (0..3).map(|i| NTSC_WEIGHTS[i] * self.decode[usize::from(c[i])]).sum();
                let irradiance = light.direct(&p, &n) + ambient;
                (irradiance > 1e-9).then(|| lum * scale / irradiance)
            })();
            [rho.filter(|r| r.is_finite()).unwrap_or(0.0) as f32]
        })
    }
}
