//! The surfel rules as pure functions, shared by every surfel fuser (a GPU fuser mirrors them
//! line for line). Sources: Keller et al. 2013, "Real-time 3D reconstruction in dynamic scenes
//! using point-based fusion" (3DV), and ElasticFusion's shaders (Whelan et al. 2016, IJRR,
//! doi:10.1177/0278364916669237), Sec. 3.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::{Iso3, Surfel};

use super::surfel_params::SurfelParams;
use nalgebra::{Point3, Vector3};

/// Confidence of a new measurement from its pixel's distance to the principal point:
/// `α = exp(−(ρ / ρ_max)² / (2 · 0.6²))`, ρ_max the image half-diagonal (ElasticFusion
/// hard-codes 400 px, the half-diagonal of 640×480).
pub fn confidence(dist_to_centre_px: f32, half_diagonal_px: f32) -> f32 {
    let r = dist_to_centre_px / half_diagonal_px;
    (-(r * r) / 0.72).exp()
}

/// Surfel radius of a measurement: `r = √2 · z / f`, widened for oblique views to
/// `min(r / |n_z|, 2 r)` (n camera-frame normal).
pub fn radius(depth_m: f32, focal_mean_px: f32, normal_z: f32) -> f32 {
    let r = std::f32::consts::SQRT_2 * depth_m / focal_mean_px;
    (r / normal_z.abs().max(1e-6)).min(2.0 * r)
}

/// The depth gate of association, compared along the ray:
/// `|z_model − z_live| · λ < gate`, `λ = ‖K⁻¹ [u v 1]ᵀ‖`.
pub fn depth_gate(z_model: f32, z_live: f32, lambda: f32, gate_m: f32) -> bool {
    (z_model - z_live).abs() * lambda < gate_m
}

/// The normal gate: the model normal is nearly parallel to the view axis
/// (|n_model.z| < `bypass_nz`) or within `max_angle_rad` of the live normal.
pub fn normal_gate(n_model: &Vector3<f32>, n_live: &Vector3<f32>, max_angle_rad: f32, bypass_nz: f32) -> bool {
    n_model.z.abs() < bypass_nz || n_model.dot(n_live).clamp(-1.0, 1.0).acos() < max_angle_rad
}

/// A measurement in world coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Position, metres.
    pub position_m: Point3<f32>,
    /// Unit normal toward the camera.
    pub normal: Vector3<f32>,
    /// Colour.
    pub colour: [u8; 3],
    /// Confidence α.
    pub confidence: f32,
    /// Radius, metres.
    pub radius_m: f32,
    /// Observed albedo (0 = none).
    pub albedo: f32,
    /// σ of its depth, metres (0 = none given).
    pub sigma_m: f32,
}

impl Measurement {
    /// A new, unstable surfel from this measurement at frame `now`.
    pub fn to_surfel(&self, now: u32) -> Surfel {
        Surfel {
            position_m: self.position_m,
            normal: self.normal,
            colour: self.colour,
            confidence: self.confidence,
            radius_m: self.radius_m,
            t0: now,
            t: now,
            albedo: self.albedo,
            sigma_m: self.sigma_m,
            warp_m: Vector3::zeros(),
        }
    }
}

/// Raises a surfel's σ to `noise`'s σ at its depth along the optical axis of the camera
/// `t_cam_world` (its distance where it lies behind the camera) where that is larger
/// ([`capsule_slam_framework::Fuser::raise_sigma`]): one rule for both fusers.
pub fn raise_sigma(s: &mut Surfel, noise: &DepthNoiseModel, t_cam_world: &Iso3) {
    let p = t_cam_world * s.position_m.cast::<f64>();
    let z = if p.z > 0.0 { p.z } else { p.coords.norm() };
    s.sigma_m = s.sigma_m.max(noise.sigma_m(z) as f32);
}

/// Fuses a measurement into a surfel (Keller et al. Eq. (4); ElasticFusion `update.vert`): if
/// the measurement's radius is below `radius_ratio` × the surfel's, position, colour, normal
/// and radius become confidence-weighted means; in any case the confidence grows by α and the
/// surfel is marked seen at `now`. Albedo (an addition to the surfel of the paper) is averaged
/// like colour over the measurements that observed one, and taken as it is by a surfel that
/// had none.
///
/// Where both carry a depth σ (issue 17), position and normal, which the depth makes, are
/// inverse-variance means instead, weights `α/σ²` (the measurement's `a·r` against the surfel's
/// `c`, `r = (σ_s/σ_m)²`), so that a noisy frame moves the map less than a sharp one; with one σ
/// throughout (r = 1) this is the rule above, bit for bit. The surfel's σ becomes that of its
/// measurements, `σ_s·√((c + a)/(c + a·r))`; a surfel without σ takes the measurement's.
pub fn merge(s: &mut Surfel, m: &Measurement, now: u32, radius_ratio: f32) {
    let (c, a) = (s.confidence, m.confidence);
    if m.radius_m < radius_ratio * s.radius_m {
        let k = 1.0 / (c + a);
        let q = if s.sigma_m > 0.0 && m.sigma_m > 0.0 { s.sigma_m / m.sigma_m } else { 1.0 };
        let r = q * q;
        let (ar, kr) = (a * r, 1.0 / (c + a * r));
        s.position_m = Point3::from((s.position_m.coords * c + m.position_m.coords * ar) * kr);
        if s.sigma_m > 0.0 {
            s.sigma_m *= ((c + a) * kr).sqrt();
        } else {
            s.sigma_m = m.sigma_m;
        }
        let n = s.normal * c + m.normal * ar;
        if n.norm() > 1e-12 {
            s.normal = n.normalize();
        }
        for ch in 0..3 {
            s.colour[ch] = ((f32::from(s.colour[ch]) * c + f32::from(m.colour[ch]) * a) * k).round().clamp(0.0, 255.0) as u8;
        }
        s.radius_m = (s.radius_m * c + m.radius_m * a) * k;
        if m.albedo > 0.0 {
            s.albedo = if s.albedo > 0.0 { (s.albedo * c + m.albedo * a) * k } else { m.albedo };
        }
    }
    s.confidence = c + a;
    s.t = now;
}

/// Which surfels an index map holds, and which of them come first at a pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Layer {
    /// Shown wherever it projects (the nearest of its layer wins).
    First,
    /// Shown only at pixels that no surfel of [`Layer::First`] reaches.
    Behind,
}

/// The layer of the association's index map a surfel is drawn in: the active model first and,
/// with `revisit` (`revisit_reactivation`), the stable inactive model where no active surfel
/// projects, so that a measurement of a revisited wall merges into the surfel that mapped it
/// (and [`merge`] makes that surfel active) instead of starting a second layer.
pub fn revisit_layer(active: bool, stable: bool, revisit: bool) -> Option<Layer> {
    if active {
        Some(Layer::First)
    } else if revisit && stable {
        Some(Layer::Behind)
    } else {
        None
    }
}

/// Reactivates, after a loop closure, the stable inactive surfels seen from the corrected
/// pose `t_world_cam` (inside the depth range and the field of view): their last sighting
/// becomes `now` (ElasticFusion marks the matched inactive surfels active). Returns how many.
pub fn reactivate(surfels: &mut [Surfel], t_world_cam: &capsule_slam_framework::Iso3, cam: &PinholeCamera, now: u32, p: &SurfelParams) -> usize {
    let t_cam_world = t_world_cam.inverse().cast::<f32>();
    let (stable, dt, lo, hi) = (p.stable_confidence, p.delta_t, p.min_depth_m, p.max_depth_m);
    let mut reactivated = 0usize;
    for s in surfels {
        if s.confidence < stable || s.is_active(now, dt) {
            continue;
        }
        let q = t_cam_world * s.position_m;
        if q.z > lo && q.z < hi && cam.project(&q.cast()).is_some_and(|uv| cam.in_fov(uv.x, uv.y)) {
            s.t = now;
            reactivated += 1;
        }
    }
    reactivated
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raising_a_surfels_sigma_reads_its_depth_in_the_camera_and_keeps_a_larger_one() {
        let noise = DepthNoiseModel { absolute_m: 0.0, relative: 0.04, quadratic_per_m: 0.0, correlation_px: 0.0 };
        // A camera 1 cm behind the world origin, looking along +z: a surfel at z = 4 cm is 5 cm deep.
        let t_cam_world = Iso3::translation(0.0, 0.0, 0.01);
        let at = |position_m: Point3<f32>, sigma_m: f32| Surfel {
            position_m,
            normal: Vector3::z(),
            colour: [0; 3],
            confidence: 1.0,
            radius_m: 1e-4,
            t0: 0,
            t: 0,
            albedo: 0.0,
            sigma_m,
            warp_m: Vector3::zeros(),
        };
        let mut s = at(Point3::new(0.003, 0.0, 0.04), 1e-4);
        raise_sigma(&mut s, &noise, &t_cam_world);
        assert!((s.sigma_m - 0.002).abs() < 1e-9, "{}", s.sigma_m);
        s.sigma_m = 0.005;
        raise_sigma(&mut s, &noise, &t_cam_world);
        assert_eq!(s.sigma_m, 0.005, "a larger σ stays");
        // Behind the camera: its distance.
        let mut behind = at(Point3::new(0.0, 0.03, -0.05), 0.0);
        raise_sigma(&mut behind, &noise, &t_cam_world);
        assert!((behind.sigma_m - 0.04 * 0.05).abs() < 1e-9, "{}", behind.sigma_m);
    }

    #[test]
    fn confidence_is_one_at_the_centre_and_falls_off() {
        assert_eq!(confidence(0.0, 200.0), 1.0);
        assert!((confidence(200.0, 200.0) - (-1.0f32 / 0.72).exp()).abs() < 1e-6);
    }

    #[test]
    fn radius_widens_for_oblique_views_up_to_twice() {
        let r = radius(0.03, 160.0, 1.0);
        assert!((r - std::f32::consts::SQRT_2 * 0.03 / 160.0).abs() < 1e-9);
        assert!((radius(0.03, 160.0, 0.8) - r / 0.8).abs() < 1e-9);
        assert_eq!(radius(0.03, 160.0, 0.1), 2.0 * r);
    }

    #[test]
    fn merging_averages_by_confidence() {
        let m = Measurement {
            position_m: Point3::new(0.0, 0.0, 0.034),
            normal: -Vector3::z(),
            colour: [200, 0, 0],
            confidence: 1.0,
            radius_m: 1e-4,
            albedo: 0.5,
            sigma_m: 0.0,
        };
        let mut s = Measurement { position_m: Point3::new(0.0, 0.0, 0.03), colour: [100, 0, 0], confidence: 3.0, albedo: 0.0, ..m }.to_surfel(0);
        merge(&mut s, &m, 7, 1.5);
        assert!((s.position_m.z - 0.031).abs() < 1e-7);
        assert_eq!(s.colour[0], 125);
        assert_eq!((s.confidence, s.t, s.t0), (4.0, 7, 0));
        // A much coarser measurement only adds confidence.
        let coarse = Measurement { radius_m: 1e-3, ..m };
        merge(&mut s, &coarse, 8, 1.5);
        assert!((s.position_m.z - 0.031).abs() < 1e-7);
        assert_eq!(s.confidence, 5.0);
    }

    #[test]
    fn a_noisy_measurement_moves_the_surfel_less_than_a_sharp_one() {
        let at = |z: f32, sigma_m: f32| Measurement {
            position_m: Point3::new(0.0, 0.0, z),
            normal: -Vector3::z(),
            colour: [0; 3],
            confidence: 1.0,
            radius_m: 1e-4,
            albedo: 0.0,
            sigma_m,
        };
        let fused = |sigma_new: f32| {
            let mut s = at(0.030, 5e-4).to_surfel(0);
            merge(&mut s, &at(0.032, sigma_new), 1, 1.5);
            s
        };
        // Inverse-variance mean of 30 mm (σ 0.5 mm) and 32 mm: weights 1/σ².
        for sigma_new in [1e-3f32, 5e-4, 2.5e-4] {
            let (w0, w1) = (1.0 / (5e-4f64 * 5e-4), 1.0 / (f64::from(sigma_new) * f64::from(sigma_new)));
            let z = (0.030 * w0 + 0.032 * w1) / (w0 + w1);
            let s = fused(sigma_new);
            assert!((f64::from(s.position_m.z) - z).abs() < 1e-7, "σ {sigma_new}: {} against {z}", s.position_m.z);
            // The surfel's σ is its measurements' inverse-variance mean: √(Σα / Σ α/σ²).
            let sigma = (2.0 / (w0 + w1)).sqrt();
            assert!((f64::from(s.sigma_m) - sigma).abs() < 1e-9, "σ {} against {sigma}", s.sigma_m);
        }
        assert!(fused(1e-3).position_m.z < fused(5e-4).position_m.z && fused(5e-4).position_m.z < fused(2.5e-4).position_m.z);
        // One σ throughout is the confidence-weighted rule bit for bit; without σ, the same.
        let (mut a, mut b) = (at(0.030, 5e-4).to_surfel(0), at(0.030, 0.0).to_surfel(0));
        merge(&mut a, &at(0.032, 5e-4), 1, 1.5);
        merge(&mut b, &at(0.032, 0.0), 1, 1.5);
        assert_eq!(a.position_m, b.position_m);
        assert_eq!(b.sigma_m, 0.0);
        // A surfel without σ takes the measurement's.
        merge(&mut b, &at(0.031, 7e-4), 2, 1.5);
        assert_eq!(b.sigma_m, 7e-4);
    }

    #[test]
    fn albedo_is_taken_then_averaged_and_kept_without_observation() {
        let m = Measurement {
            position_m: Point3::new(0.0, 0.0, 0.03),
            normal: -Vector3::z(),
            colour: [0; 3],
            confidence: 1.0,
            radius_m: 1e-4,
            albedo: 0.0,
            sigma_m: 0.0,
        };
        let mut s = Measurement { confidence: 3.0, ..m }.to_surfel(0);
        merge(&mut s, &Measurement { albedo: 0.5, ..m }, 1, 1.5);
        assert_eq!(s.albedo, 0.5, "a surfel without albedo takes the first observation");
        merge(&mut s, &Measurement { albedo: 0.3, ..m }, 2, 1.5);
        assert!((s.albedo - (0.5 * 4.0 + 0.3) / 5.0).abs() < 1e-6, "then the confidence-weighted mean");
        merge(&mut s, &m, 3, 1.5);
        assert!((s.albedo - (0.5 * 4.0 + 0.3) / 5.0).abs() < 1e-6, "a measurement without albedo leaves it");
    }

    #[test]
    fn gates() {
        assert!(depth_gate(0.030, 0.031, 1.1, 0.002));
        assert!(!depth_gate(0.030, 0.033, 1.1, 0.002));
        let n = -Vector3::z();
        assert!(normal_gate(&n, &Vector3::new(0.3, 0.0, -1.0).normalize(), 0.5, 0.75));
        assert!(!normal_gate(&n, &Vector3::new(1.0, 0.0, -0.5).normalize(), 0.5, 0.75));
        assert!(normal_gate(&Vector3::new(1.0, 0.0, -0.5).normalize(), &n, 0.5, 0.75), "bypass for grazing model normals");
    }
}
