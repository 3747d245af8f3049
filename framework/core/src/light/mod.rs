//! The photometric model of a capsule camera and its light, `light.toml` (written by the
//! phantom, fitted by calibration tools for real capsules, read by shape-from-shading plugins):
//!
//! `linear pixel = V(u) · albedo · (gain · cos(incidence) · (ref_distance_m / distance_m)² · spot + ambient)`,
//! then gamma-encoded: `pixel = linear^(1/gamma)` in [0, 1].
//! `V = 1 + v1 r² + v2 r⁴ (+ v3 r⁶)`, r = pixel distance to (cx, cy) / half-diagonal;
//! `spot = cos(angle to the optical axis)^spot_exponent`. Distance and incidence are measured
//! from the light at `position_m` (camera frame).

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::PinholeCamera;

pub mod vignetting;

/// `light.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightModel {
    /// Light gain: 1 = a white Lambertian wall head-on at `ref_distance_m` gives linear value 1.
    pub gain: f64,
    /// Reference distance of the gain, metres.
    pub ref_distance_m: f64,
    /// Ambient term (inter-reflections), linear units.
    pub ambient: f64,
    /// Encoding exponent of the pixel values.
    pub gamma: f64,
    /// Light position in the camera frame, metres.
    pub position_m: [f64; 3],
    /// LED profile exponent: spot = cos(angle to the optical axis)^spot_exponent.
    pub spot_exponent: f64,
    /// Vignetting coefficients v1, v2 (, v3) of V = 1 + v1 r² + v2 r⁴ (+ v3 r⁶).
    pub vignetting: Vec<f64>,
}

impl Default for LightModel {
    fn default() -> Self {
        Self { gain: 1.0, ref_distance_m: 0.025, ambient: 0.02, gamma: 2.2, position_m: [0.0; 3], spot_exponent: 0.0, vignetting: vec![-0.3, -0.25] }
    }
}

impl LightModel {
    /// The light a monocular run assumes when the input has no `light.toml` (issue 18): the
    /// light at the lens (`position_m` 0), the sRGB-like encoding (γ 2.2), a Lambertian LED
    /// (`spot_exponent` 1), an ambient of 2 % of the light, and the lens vignetting
    /// V = 1 − 0.5 r², the best of V = 1 − v r² for v ∈ {0, 0.25, 0.5, 0.75} measured on the
    /// phantom's presets 1, 2 and 5 with their `light.toml` removed (0.75 did better on some
    /// and lost a sequence; `docs/results/uncalibrated-monocular.md`). The gain is 1 at 25 mm: the albedo and the
    /// gain are not known, so neither is the scale of the depth, and a run with this light
    /// reports `metric_scale: false` and leads with its Sim(3) figures.
    pub fn uncalibrated() -> Self {
        Self { gain: 1.0, ref_distance_m: 0.025, ambient: 0.02, gamma: 2.2, position_m: [0.0; 3], spot_exponent: 1.0, vignetting: vec![-0.5, 0.0] }
    }

    /// The model in a few words, for messages: where the light is, its encoding, LED, ambient
    /// and vignetting (e.g. "at the lens, γ 2.2, spot exponent 1, ambient 0.02, V = 1 − 0.5 r²").
    pub fn describe(&self) -> String {
        let at = if self.position_m.iter().all(|v| *v == 0.0) {
            "at the lens".to_owned()
        } else {
            let [x, y, z] = self.position_m.map(|v| v * 1e3);
            format!("at ({x:.1}, {y:.1}, {z:.1}) mm from the lens")
        };
        let powers = ["r²", "r⁴", "r⁶"];
        let v: String = self
            .vignetting
            .iter()
            .zip(powers)
            .filter(|(c, _)| **c != 0.0)
            .map(|(c, p)| format!(" {} {} {p}", if *c < 0.0 { "−" } else { "+" }, c.abs()))
            .collect();
        format!("{at}, γ {}, spot exponent {}, ambient {}, V = 1{v}", self.gamma, self.spot_exponent, self.ambient)
    }

    /// Every invalid field as `(key, message)`.
    pub fn problems(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if !pos(self.gain) {
            out.push(("gain", format!("{} must be positive", self.gain)));
        }
        if !pos(self.ref_distance_m) {
            out.push(("ref_distance_m", format!("{} must be a positive distance in metres", self.ref_distance_m)));
        }
        if !(self.ambient.is_finite() && self.ambient >= 0.0) {
            out.push(("ambient", format!("{} must be ≥ 0", self.ambient)));
        }
        if !pos(self.gamma) {
            out.push(("gamma", format!("{} must be positive", self.gamma)));
        }
        if !self.position_m.iter().all(|v| v.is_finite()) {
            out.push(("position_m", "must be three finite numbers".into()));
        }
        if !(self.spot_exponent.is_finite() && self.spot_exponent >= 0.0) {
            out.push(("spot_exponent", format!("{} must be ≥ 0", self.spot_exponent)));
        }
        if !(self.vignetting.len() == 2 || self.vignetting.len() == 3) || !self.vignetting.iter().all(|v| v.is_finite()) {
            out.push(("vignetting", "needs 2 or 3 finite coefficients v1 v2 (v3)".into()));
        } else if let Some(r) = self.vignetting_nonpositive_at() {
            out.push((
                "vignetting",
                format!(
                    "{:?} makes V = 1 + v1 r² + v2 r⁴ (+ v3 r⁶) ≤ 0 at r = {r:.2} of the half-diagonal, inside the image: the lens would pass no light there; fit it again (`capsule-slam calibrate-light`)",
                    self.vignetting
                ),
            ));
        }
        out
    }

    /// The smallest r in [0, 1] (pixel distance to the principal point over the half-diagonal,
    /// every pixel of the image) where V(r) ≤ 0, if any (sampled every 1/1000).
    fn vignetting_nonpositive_at(&self) -> Option<f64> {
        (0..=1000).map(|i| f64::from(i) / 1000.0).find(|r| self.vignetting_of_r2(r * r) <= 0.0)
    }

    /// V(u) at pixel (u, v).
    pub fn vignetting_at(&self, cam: &PinholeCamera, u: f64, v: f64) -> f64 {
        let (du, dv) = (u - cam.cx, v - cam.cy);
        self.vignetting_of_r2((du * du + dv * dv) / (cam.vignetting_radius() * cam.vignetting_radius()))
    }

    /// V at r² (r: distance to the principal point over the half-diagonal).
    fn vignetting_of_r2(&self, r2: f64) -> f64 {
        let mut out = 1.0;
        let mut rk = 1.0;
        for c in &self.vignetting {
            rk *= r2;
            out += c * rk;
        }
        out
    }

    /// The same light in the frame of another camera of the rig, `x_view = t_view_ref · x_ref`:
    /// its position moves; the LED's axis stays along the optical axis, as for a stereo
    /// capsule's cameras, which look the same way.
    pub fn at(&self, t_view_ref: &crate::geometry::Iso3) -> Self {
        let p = t_view_ref * self.position();
        Self { position_m: [p.x, p.y, p.z], ..self.clone() }
    }

    /// The light position in the camera frame.
    pub fn position(&self) -> Point3<f64> {
        Point3::new(self.position_m[0], self.position_m[1], self.position_m[2])
    }

    /// The light's fall-off at a camera-frame point, `gain · (ref/d)² · spot`, without the
    /// incidence term.
    pub fn falloff(&self, p_cam: &Point3<f64>) -> f64 {
        let to_point = p_cam - self.position();
        let d = to_point.norm();
        if d <= 0.0 {
            return 0.0;
        }
        self.falloff_at(to_point.z, d)
    }

    /// [`LightModel::falloff`] from the light-to-point vector's z and length `d > 0`.
    #[inline]
    fn falloff_at(&self, to_point_z: f64, d: f64) -> f64 {
        let cos_axis = (to_point_z / d).max(0.0);
        // pow(x, 1) is x exactly; skipping it is the same figure without libm's pow, which is
        // the photometric trackers' hottest call (they relight every pixel every iteration).
        let spot = match self.spot_exponent {
            0.0 => 1.0,
            1.0 => cos_axis,
            e => cos_axis.powf(e),
        };
        let r = self.ref_distance_m / d;
        self.gain * r * r * spot
    }

    /// Cosine of the incidence angle at a camera-frame point with unit normal `n_cam` (0 when
    /// the light is behind the surface).
    pub fn cos_incidence(&self, p_cam: &Point3<f64>, n_cam: &Vector3<f64>) -> f64 {
        let to_light = self.position() - p_cam;
        let d = to_light.norm();
        if d <= 0.0 { 0.0 } else { (n_cam.dot(&to_light) / d).max(0.0) }
    }

    /// The direct-light term `gain · cos(incidence) · (ref/d)² · spot`.
    pub fn direct(&self, p_cam: &Point3<f64>, n_cam: &Vector3<f64>) -> f64 {
        // One distance for both factors: the light-to-point vector is the point-to-light one
        // negated, so this is `cos_incidence · falloff` to the bit.
        let to_point = p_cam - self.position();
        let d = to_point.norm();
        if d <= 0.0 {
            return 0.0;
        }
        (-n_cam.dot(&to_point) / d).max(0.0) * self.falloff_at(to_point.z, d)
    }

    /// Linear pixel value of a Lambertian point of the given albedo at pixel (u, v).
    pub fn linear(&self, cam: &PinholeCamera, u: f64, v: f64, albedo: f64, p_cam: &Point3<f64>, n_cam: &Vector3<f64>) -> f64 {
        self.vignetting_at(cam, u, v) * albedo * (self.direct(p_cam, n_cam) + self.ambient)
    }

    /// Gamma-encodes a linear value to [0, 1].
    pub fn encode(&self, linear: f64) -> f64 {
        linear.clamp(0.0, 1.0).powf(1.0 / self.gamma)
    }

    /// Decodes an encoded value in [0, 1] to linear.
    pub fn decode(&self, encoded: f64) -> f64 {
        encoded.clamp(0.0, 1.0).powf(self.gamma)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::{Just, prop_oneof};

    #[test]
    fn a_model_describes_itself_from_its_own_values() {
        assert_eq!(LightModel::uncalibrated().describe(), "at the lens, γ 2.2, spot exponent 1, ambient 0.02, V = 1 − 0.5 r²");
        let beside = LightModel { position_m: [0.0025, 0.0, 0.0], vignetting: vec![-0.3, -0.25], ..LightModel::default() };
        assert_eq!(beside.describe(), "at (2.5, 0.0, 0.0) mm from the lens, γ 2.2, spot exponent 0, ambient 0.02, V = 1 − 0.3 r² − 0.25 r⁴");
    }

    #[test]
    fn vignetting_that_passes_no_light_inside_the_image_is_a_problem() {
        let with = |v: Vec<f64>| LightModel { vignetting: v, ..LightModel::default() };
        // V(1) = 1 − 1.5 + 0.3 < 0: the corners would get no light.
        let bad = with(vec![-1.5, 0.3]).problems();
        assert!(bad.iter().any(|(k, m)| *k == "vignetting" && m.contains("≤ 0 at r = 0.89") && m.contains("calibrate-light")), "{bad:?}");
        assert!(with(vec![-0.4, 0.05]).problems().is_empty());
        assert!(with(vec![-0.5, -0.5]).problems().iter().any(|(k, m)| *k == "vignetting" && m.contains("r = 1.00")));
        // Every problem at once, and no line 0 in the message.
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let path = dir.path().join("light.toml");
        let text =
            "gain = -1.0\nref_distance_m = 0.025\nambient = 0.0\ngamma = 2.2\nposition_m = [0.0, 0.0, 0.0]\nspot_exponent = 1.0\nvignetting = [-1.5, 0.3]\n";
        std::fs::write(&path, text).unwrap_or_else(|e| panic!("{e}"));
        let err = crate::files::read_light_file(&path).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err.contains("gain") && err.contains("vignetting") && !err.contains(":0"), "{err}");
    }

    #[test]
    fn gain_is_one_head_on_at_the_reference_distance() {
        let l = LightModel { ambient: 0.0, ..LightModel::default() };
        let p = Point3::new(0.0, 0.0, 0.025);
        assert!((l.direct(&p, &-Vector3::z()) - 1.0).abs() < 1e-12);
        assert!((l.direct(&Point3::new(0.0, 0.0, 0.05), &-Vector3::z()) - 0.25).abs() < 1e-12);
    }

    #[test]
    fn shading_of_a_plane_follows_cos_cubed_over_distance_squared() {
        // Light at the optical centre, plane z = D: r = D / cos α and cos θ = cos α, so the
        // direct term is gain (ref/D)² cos³α.
        let l = LightModel { gain: 0.7, spot_exponent: 0.0, ..LightModel::default() };
        let d = 0.03;
        for k in 0..20 {
            let alpha = k as f64 * 0.06;
            let p = Point3::new(d * alpha.tan(), 0.0, d);
            let expected = 0.7 * (0.025 / d).powi(2) * alpha.cos().powi(3);
            assert!((l.direct(&p, &-Vector3::z()) - expected).abs() < 1e-12, "α {alpha}");
        }
        // A spot exponent k multiplies by cos^k α.
        let spot = LightModel { spot_exponent: 2.0, ..l.clone() };
        let p = Point3::new(d * 0.5f64.tan(), 0.0, d);
        assert!((spot.direct(&p, &-Vector3::z()) / l.direct(&p, &-Vector3::z()) - 0.5f64.cos().powi(2)).abs() < 1e-12);
    }

    proptest::proptest! {
        /// `direct` shares one distance between its factors; it must stay
        /// `cos_incidence · falloff` to the bit (the phantom renders with the two factors, the
        /// trackers relight with `direct`), whatever the light's offset and spot.
        #[test]
        fn direct_is_cos_incidence_times_falloff_to_the_bit(
            x in -0.03f64..0.03, y in -0.03f64..0.03, z in -0.01f64..0.08,
            nx in -1.0f64..1.0, ny in -1.0f64..1.0, nz in -1.0f64..1.0,
            lx in -0.005f64..0.005, spot in prop_oneof![Just(0.0), Just(1.0), 0.0f64..4.0],
        ) {
            let l = LightModel { position_m: [lx, 0.002, 0.0], spot_exponent: spot, ..LightModel::default() };
            let (p, n) = (Point3::new(x, y, z), Vector3::new(nx, ny, nz));
            let two = l.cos_incidence(&p, &n) * l.falloff(&p);
            proptest::prop_assert_eq!(l.direct(&p, &n).to_bits() == two.to_bits() || (two == 0.0 && l.direct(&p, &n) == 0.0), true);
        }
    }

    #[test]
    fn vignetting_is_one_at_the_centre_and_falls_off() {
        let l = LightModel::default();
        let cam = PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5);
        assert_eq!(l.vignetting_at(&cam, 159.5, 159.5), 1.0);
        let corner = l.vignetting_at(&cam, 319.5, 319.5);
        assert!((corner - (1.0 - 0.3 - 0.25)).abs() < 0.01, "{corner}");
    }

    #[test]
    fn encode_inverts_decode() {
        let l = LightModel::default();
        for v in [0.0, 0.1, 0.5, 1.0] {
            assert!((l.decode(l.encode(v)) - v).abs() < 1e-12);
        }
        assert!(l.problems().is_empty());
        assert_eq!(LightModel { vignetting: vec![1.0], gamma: 0.0, ..l }.problems().len(), 2);
    }
}
