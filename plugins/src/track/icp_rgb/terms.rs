//! The two residuals of the paper's tracking energy and their analytic Jacobians with respect
//! to a left increment `T ← exp(ξ) T`, `ξ = [ρ; ω]` (translation first, as in ElasticFusion).
//! `v` is a live vertex (current camera frame) and `s = T v` its position in the reference
//! (previous camera) frame.

use capsule_slam_framework::PinholeCamera;
use nalgebra::{Vector3, Vector6};

/// Point-to-plane residual, Eq. (2): `r = n · (s − d)`, reference point d with normal n.
pub fn icp_residual(s: &Vector3<f64>, d: &Vector3<f64>, n: &Vector3<f64>) -> f64 {
    n.dot(&(s - d))
}

/// Its Jacobian, `J = [nᵀ, (s × n)ᵀ]`.
pub fn icp_jacobian(s: &Vector3<f64>, n: &Vector3<f64>) -> Vector6<f64> {
    let c = s.cross(n);
    Vector6::new(n.x, n.y, n.z, c.x, c.y, c.z)
}

/// Jacobian of the photometric residual of Eq. (3), `r = I_ref(π(s)) − I_live(u)`: the image
/// gradient `g = ∇I_ref(π(s))` through the projection, `a = g · ∂π/∂s`, `J = [aᵀ, (s × a)ᵀ]`.
pub fn rgb_jacobian(s: &Vector3<f64>, grad: (f64, f64), fx: f64, fy: f64) -> Vector6<f64> {
    twist_row(s, &projected_gradient(s, grad, fx, fy))
}

/// The image gradient `g` at the projection of `p` carried back through the projection,
/// `a = g · ∂π/∂p` (intensity per metre, in `p`'s camera frame).
pub fn projected_gradient(p: &Vector3<f64>, grad: (f64, f64), fx: f64, fy: f64) -> Vector3<f64> {
    let iz = 1.0 / p.z;
    Vector3::new(grad.0 * fx * iz, grad.1 * fy * iz, -(grad.0 * fx * p.x + grad.1 * fy * p.y) * iz * iz)
}

/// The Jacobian row `[aᵀ, (s × a)ᵀ]` of a residual whose derivative with respect to the point
/// `s` (reference frame) is `a`, under the left increment of the module.
pub fn twist_row(s: &Vector3<f64>, a: &Vector3<f64>) -> Vector6<f64> {
    let c = s.cross(a);
    Vector6::new(a.x, a.y, a.z, c.x, c.y, c.z)
}

/// σ of a point-to-plane residual, metres: the registration floor, the live depth's own σ and
/// the reference's (issue 17), `√(floor² + σ_live² + σ_ref²)`; it scales the gates, the Huber
/// threshold and the loss test.
pub fn residual_sigma(floor_m: f64, sigma_live_m: f64, sigma_ref_m: f64) -> f64 {
    (floor_m * floor_m + sigma_live_m * sigma_live_m + sigma_ref_m * sigma_ref_m).sqrt()
}

/// How many residuals, `spacing_px` apart, share one draw of a depth error correlated over
/// `correlation_px` pixels, `max(1, ℓ / spacing)²`: the live σ² enters a residual's weight
/// that many times, so that a correlated patch counts as one measurement.
pub fn correlated_count(correlation_px: f64, spacing_px: f64) -> f64 {
    (correlation_px / spacing_px).max(1.0).powi(2)
}

/// The projection `(u, v)` of the point `p` (camera frame, `z > 0`) by `cam` and its nearest
/// pixel of a `w × h` image, none outside it. Truncation after +0.5 rounds non-negative values
/// without libm.
#[inline]
pub fn nearest_pixel(cam: &PinholeCamera, p: &Vector3<f64>, (w, h): (usize, usize)) -> Option<((f64, f64), (usize, usize))> {
    let (uf, vf) = (cam.fx * p.x / p.z + cam.cx, cam.fy * p.y / p.z + cam.cy);
    let (ui, vi) = ((uf + 0.5) as usize, (vf + 0.5) as usize);
    (uf >= -0.5 && vf >= -0.5 && ui < w && vi < h).then_some(((uf, vf), (ui, vi)))
}

/// Huber weight of a normalised residual `e` (1 inside ±k, k/|e| outside).
pub fn huber(e: f64, k: f64) -> f64 {
    if e.abs() <= k { 1.0 } else { k / e.abs() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use capsule_slam_framework::geometry::exp_se3;
    use nalgebra::Point3;

    #[test]
    fn the_nearest_pixel_rounds_and_stays_inside_the_image() {
        let cam = PinholeCamera::new(4, 3, 10.0, 10.0, 1.5, 1.0);
        let at = |x: f64, y: f64| nearest_pixel(&cam, &Vector3::new(x, y, 1.0), (4, 3)).map(|(_, p)| p);
        assert_eq!(at(0.0, 0.0), Some((2, 1)), "(1.5, 1.0) rounds to (2, 1)");
        assert_eq!(at(-0.19, -0.14), Some((0, 0)), "(−0.4, −0.4) is still pixel 0");
        assert_eq!(at(-0.21, 0.0), None, "u = −0.6");
        assert_eq!(at(0.19, 0.0), Some((3, 1)), "u = 3.4 rounds to the last column");
        assert_eq!(at(0.21, 0.0), None, "u = 3.6 rounds past it");
        assert_eq!(at(f64::NAN, 0.0), None);
        let ((u, v), _) = nearest_pixel(&cam, &Vector3::new(0.02, -0.03, 0.5), (4, 3)).unwrap();
        assert!((u - 1.9).abs() < 1e-12 && (v - 0.4).abs() < 1e-12);
    }

    fn numeric(f: impl Fn(&Vector6<f64>) -> f64) -> Vector6<f64> {
        let h = 1e-7;
        Vector6::from_fn(|i, _| {
            let mut e = Vector6::zeros();
            e[i] = h;
            (f(&e) - f(&-e)) / (2.0 * h)
        })
    }

    #[test]
    fn icp_jacobian_matches_finite_differences() {
        let t = exp_se3(&Vector6::new(0.001, -0.002, 0.0005, 0.02, -0.01, 0.03));
        let v = Point3::new(0.004, -0.006, 0.031);
        let (d, n) = (Vector3::new(0.005, -0.005, 0.032), Vector3::new(0.2, -0.1, -0.97).normalize());
        let s = (t * v).coords;
        let num = numeric(|xi| icp_residual(&(exp_se3(xi) * t * v).coords, &d, &n));
        assert!((icp_jacobian(&s, &n) - num).norm() < 1e-6, "{} vs {}", icp_jacobian(&s, &n), num);
    }

    #[test]
    fn rgb_jacobian_matches_finite_differences() {
        // A linear reference image I(u, v) = 0.3 + 0.002 u − 0.001 v, so its gradient is exact.
        let (fx, fy, cx, cy) = (160.0, 150.0, 159.5, 159.5);
        let image = |p: &Vector3<f64>| {
            let (u, v) = (fx * p.x / p.z + cx, fy * p.y / p.z + cy);
            0.3 + 0.002 * u - 0.001 * v
        };
        let t = exp_se3(&Vector6::new(0.001, 0.002, -0.001, -0.02, 0.01, 0.02));
        let v = Point3::new(0.003, 0.004, 0.028);
        let s = (t * v).coords;
        let num = numeric(|xi| image(&(exp_se3(xi) * t * v).coords) - 0.5);
        let ana = rgb_jacobian(&s, (0.002, -0.001), fx, fy);
        assert!((ana - num).norm() < 1e-6 * num.norm().max(1.0), "{ana} vs {num}");
    }
}
