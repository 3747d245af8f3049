//! The cavity: a bent, bulging, closed tube like a stomach, given implicitly.
//!
//! The centreline is a circular arc of radius `arc_radius_m` in the world x–y plane,
//! `c(φ) = C + A (sin φ, cos φ, 0)`, `C = (0, −A, 0)`, `φ ∈ [−Φ, Φ]`, so `c(0)` is the origin
//! and the tube runs along +x there. A point `x` has tube coordinates: `φ` (its nearest arc
//! point), `ρ` (distance to it) and `θ` (angle about the arc, 0 = away from C, π/2 = +z).
//! The wall is `ρ = r(φ, θ, t)`; inside is `F(x, t) = ρ − r < 0`.
//!
//! `r` = base radius × bulge (larger fundus at φ < 0) × end cap `sqrt(1 − |u|³)`, `u = φ/Φ`
//! (closes the tube), × an elliptic cross-section, minus longitudinal folds (rugae), plus an
//! optional peristaltic wave `D sin(2π (s/λ − t/T))` (s = A φ) that vanishes at the ends.

use nalgebra::{Point3, Vector3};

/// Parameters of the cavity. Lengths in metres, times in seconds.
#[derive(Debug, Clone, PartialEq)]
pub struct StomachShape {
    /// Radius A of the centreline arc.
    pub arc_radius_m: f64,
    /// Half opening angle Φ of the arc; the cavity is 2 A Φ long.
    pub half_angle_rad: f64,
    /// Base tube radius.
    pub radius_m: f64,
    /// Relative radius gain toward the fundus (φ < 0).
    pub bulge: f64,
    /// Relative ellipticity of the cross-section.
    pub ellipticity: f64,
    /// Height of the folds.
    pub fold_m: f64,
    /// Number of folds around the tube.
    pub folds: f64,
    /// Amplitude D of the peristaltic wave (0 = rigid).
    pub wave_m: f64,
    /// Wavelength λ of the wave along the tube.
    pub wave_length_m: f64,
    /// Period T of the wave.
    pub wave_period_s: f64,
    /// When the wave starts, seconds: before it the wall is still, after it the amplitude grows
    /// to D over [`WAVE_ONSET_RAMP_S`] (a smoothstep). 0: the wave runs from the start, at D.
    pub wave_onset_s: f64,
}

/// How long a wave that starts late ([`StomachShape::wave_onset_s`]) takes to grow from 0 to
/// its full amplitude, seconds: a contraction sets in over about a second.
pub const WAVE_ONSET_RAMP_S: f64 = 1.0;

impl Default for StomachShape {
    /// A 14 cm long, 3.2 cm radius stomach with 1.2 mm folds, rigid.
    fn default() -> Self {
        Self {
            arc_radius_m: 0.1,
            half_angle_rad: 0.7,
            radius_m: 0.032,
            bulge: 0.25,
            ellipticity: 0.1,
            fold_m: 0.0012,
            folds: 9.0,
            wave_m: 0.0,
            wave_length_m: 0.05,
            wave_period_s: 6.0,
            wave_onset_s: 0.0,
        }
    }
}

/// Tube coordinates of a point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TubeCoords {
    /// Arc angle of the nearest centreline point.
    pub phi: f64,
    /// Distance to it.
    pub rho: f64,
    /// Angle about the centreline.
    pub theta: f64,
}

impl StomachShape {
    /// Length of the centreline, metres.
    pub fn length_m(&self) -> f64 {
        2.0 * self.arc_radius_m * self.half_angle_rad
    }

    /// Centreline point at arc angle φ.
    pub fn centre(&self, phi: f64) -> Point3<f64> {
        let a = self.arc_radius_m;
        Point3::new(a * phi.sin(), a * phi.cos() - a, 0.0)
    }

    /// Unit tangent of the centreline at φ (direction of increasing φ).
    pub fn tangent(&self, phi: f64) -> Vector3<f64> {
        Vector3::new(phi.cos(), -phi.sin(), 0.0)
    }

    /// In-plane unit normal of the centreline at φ (pointing away from the arc centre).
    pub fn outward(&self, phi: f64) -> Vector3<f64> {
        Vector3::new(phi.sin(), phi.cos(), 0.0)
    }

    /// Tube coordinates of `x`.
    pub fn coords(&self, x: &Point3<f64>) -> TubeCoords {
        let a = self.arc_radius_m;
        let (qx, qy, qz) = (x.x, x.y + a, x.z);
        let phi = qx.atan2(qy);
        let radial = (qx * qx + qy * qy).sqrt() - a;
        TubeCoords { phi, rho: (radial * radial + qz * qz).sqrt(), theta: qz.atan2(radial) }
    }

    /// The wall radius at (φ, θ) and time t.
    pub fn radius(&self, phi: f64, theta: f64, t_s: f64) -> f64 {
        (self.rest_radius(phi, theta) + self.wave(phi, t_s)).max(0.0)
    }

    /// The wall radius without the peristaltic wave.
    pub fn rest_radius(&self, phi: f64, theta: f64) -> f64 {
        let u = (phi / self.half_angle_rad).clamp(-1.0, 1.0);
        let cap = (1.0 - u.abs().powi(3)).max(0.0).sqrt();
        // Folds and ellipticity fade out toward the closed ends, where θ degenerates.
        let taper = (1.0 - u * u).powi(2);
        let body = self.radius_m * (1.0 - self.bulge * u) * (1.0 + taper * self.ellipticity * (2.0 * theta).cos());
        let s = self.arc_radius_m * phi;
        let ridge = 0.5 + 0.5 * (self.folds * theta + 0.9 * (s / 0.021).sin()).cos();
        body * cap - self.fold_m * ridge.powi(4) * taper
    }

    /// The radial displacement of the peristaltic wave, `D sin(2π (s/λ − t/T))`, fading at the
    /// ends; a late wave's amplitude grows from its onset ([`StomachShape::wave_onset_s`]).
    pub fn wave(&self, phi: f64, t_s: f64) -> f64 {
        if self.wave_m == 0.0 {
            return 0.0;
        }
        let u = (phi / self.half_angle_rad).clamp(-1.0, 1.0);
        let s = self.arc_radius_m * phi;
        let wave = self.wave_m * (std::f64::consts::TAU * (s / self.wave_length_m - t_s / self.wave_period_s)).sin() * (1.0 - u * u).powi(2);
        if self.wave_onset_s > 0.0 { wave * self.onset_gain(t_s) } else { wave }
    }

    /// The share of the wave's amplitude at time `t_s`: 0 before the onset, a smoothstep to 1
    /// over [`WAVE_ONSET_RAMP_S`] after it.
    pub fn onset_gain(&self, t_s: f64) -> f64 {
        let x = ((t_s - self.wave_onset_s) / WAVE_ONSET_RAMP_S).clamp(0.0, 1.0);
        x * x * (3.0 - 2.0 * x)
    }

    /// The rest-shape wall point at (φ, θ) (no wave): where a wall point's texture lives.
    pub fn rest_point(&self, phi: f64, theta: f64) -> Point3<f64> {
        self.centre(phi) + self.rest_radius(phi, theta).max(0.0) * (theta.cos() * self.outward(phi) + theta.sin() * Vector3::z())
    }

    /// The implicit function: negative inside the cavity, zero on the wall, positive outside.
    pub fn implicit(&self, x: &Point3<f64>, t_s: f64) -> f64 {
        let c = self.coords(x);
        if c.phi.abs() >= self.half_angle_rad {
            let end = self.centre(self.half_angle_rad.copysign(c.phi));
            return (x - end).norm();
        }
        c.rho - self.radius(c.phi, c.theta, t_s)
    }

    /// The wall point at surface parameters (φ, θ) and time t.
    pub fn surface_point(&self, phi: f64, theta: f64, t_s: f64) -> Point3<f64> {
        let r = self.radius(phi, theta, t_s);
        self.centre(phi) + r * (theta.cos() * self.outward(phi) + theta.sin() * Vector3::z())
    }

    /// Unit wall normal at `x`, pointing into the cavity (−∇F, central differences).
    pub fn inward_normal(&self, x: &Point3<f64>, t_s: f64) -> Vector3<f64> {
        let h = 1e-6;
        let g = Vector3::new(
            self.implicit(&(x + Vector3::x() * h), t_s) - self.implicit(&(x - Vector3::x() * h), t_s),
            self.implicit(&(x + Vector3::y() * h), t_s) - self.implicit(&(x - Vector3::y() * h), t_s),
            self.implicit(&(x + Vector3::z() * h), t_s) - self.implicit(&(x - Vector3::z() * h), t_s),
        );
        let n = g.norm();
        if n > 0.0 { -g / n } else { Vector3::z() }
    }

    /// The first wall hit along the ray `origin + s·dir` (`dir` unit, origin inside), as the
    /// distance `s` in metres, or `None` within `max_m`. Sphere tracing with a conservative step
    /// (half the implicit value; |∇F| ≤ 2 away from the end caps), then regula falsi (Illinois)
    /// to 1e-9 m.
    pub fn raycast(&self, origin: &Point3<f64>, dir: &Vector3<f64>, t_s: f64, max_m: f64) -> Option<f64> {
        let f = |s: f64| self.implicit(&(origin + dir * s), t_s);
        let (mut s0, mut f0) = (0.0, f(0.0));
        if f0 >= 0.0 {
            return None;
        }
        loop {
            let s1 = s0 + (-0.5 * f0).max(5e-5);
            if s1 > max_m {
                return None;
            }
            let f1 = f(s1);
            if f1 >= 0.0 {
                return Some(refine(&f, s0, f0, s1, f1));
            }
            (s0, f0) = (s1, f1);
        }
    }
}

/// Illinois regula falsi on a bracket with `fa < 0 ≤ fb`.
fn refine(f: &impl Fn(f64) -> f64, mut a: f64, mut fa: f64, mut b: f64, mut fb: f64) -> f64 {
    let mut side = 0;
    for _ in 0..40 {
        if b - a < 1e-9 {
            break;
        }
        let c = (a * fb - b * fa) / (fb - fa);
        let fc = f(c);
        if fc < 0.0 {
            (a, fa) = (c, fc);
            if side == -1 {
                fb *= 0.5;
            }
            side = -1;
        } else {
            (b, fb) = (c, fc);
            if side == 1 {
                fa *= 0.5;
            }
            side = 1;
        }
    }
    // The crossing lies in [a, b]; return the side on the wall.
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surface_points_lie_on_the_implicit_surface() {
        let s = StomachShape { wave_m: 0.003, ..StomachShape::default() };
        for i in 0..40 {
            for j in 0..24 {
                let phi = -0.65 + 1.3 * i as f64 / 39.0;
                let theta = -3.1 + 6.2 * j as f64 / 23.0;
                let p = s.surface_point(phi, theta, 1.3);
                assert!(s.implicit(&p, 1.3).abs() < 1e-9, "φ {phi} θ {theta}: {}", s.implicit(&p, 1.3));
            }
        }
    }

    #[test]
    fn a_late_wave_is_still_before_its_onset_and_whole_a_ramp_after_it() {
        let from_start = StomachShape { wave_m: 0.002, ..StomachShape::default() };
        let late = StomachShape { wave_onset_s: 5.0, ..from_start.clone() };
        let (phi, theta) = (0.1, 0.4);
        let rest = late.rest_radius(phi, theta);
        for k in 0..50 {
            let t = 5.0 * k as f64 / 50.0;
            assert_eq!(late.radius(phi, theta, t), rest, "still at {t} s");
        }
        // Growing through the ramp, whole after it: the wave that ran from the start.
        let share = |t: f64| late.wave(phi, t) / from_start.wave(phi, t);
        assert!((share(5.0 + 0.5 * WAVE_ONSET_RAMP_S) - 0.5).abs() < 1e-12, "half-way up the smoothstep");
        assert!(share(5.0 + 0.1 * WAVE_ONSET_RAMP_S) < 0.05);
        for k in 0..50 {
            let t = 5.0 + WAVE_ONSET_RAMP_S + 0.13 * k as f64;
            assert_eq!(late.wave(phi, t), from_start.wave(phi, t), "at {t} s");
        }
        // The surface stays on the implicit function through the onset.
        let p = late.surface_point(phi, theta, 5.3);
        assert!(late.implicit(&p, 5.3).abs() < 1e-9);
    }

    #[test]
    fn the_centreline_is_inside_and_far_points_outside() {
        let s = StomachShape::default();
        assert!(s.implicit(&Point3::origin(), 0.0) < -0.02);
        assert!(s.implicit(&Point3::new(0.0, 0.0, 0.2), 0.0) > 0.0);
        assert!(s.implicit(&Point3::new(0.5, 0.0, 0.0), 0.0) > 0.0);
        assert!((s.length_m() - 0.14).abs() < 1e-12);
    }

    #[test]
    fn raycast_hits_the_first_crossing() {
        let s = StomachShape::default();
        let o = Point3::new(0.01, -0.003, 0.004);
        for k in 0..200 {
            let a = k as f64 * 0.37;
            let d = Vector3::new(a.cos() * 0.7, a.sin() * 0.5, (a * 0.3).sin()).normalize();
            let hit = s.raycast(&o, &d, 0.0, 0.5).expect("a closed cavity is always hit");
            assert!(s.implicit(&(o + d * hit), 0.0).abs() < 1e-8);
            // No earlier crossing: dense samples before the hit are inside.
            for i in 1..400 {
                let t = hit * i as f64 / 400.0;
                assert!(s.implicit(&(o + d * t), 0.0) < 0.0, "earlier crossing at {t} < {hit}");
            }
        }
    }

    #[test]
    fn the_inward_normal_points_inside() {
        let s = StomachShape::default();
        let p = s.surface_point(0.2, 0.5, 0.0);
        let n = s.inward_normal(&p, 0.0);
        assert!((n.norm() - 1.0).abs() < 1e-9);
        assert!(s.implicit(&(p + n * 1e-4), 0.0) < 0.0);
        assert!(s.implicit(&(p - n * 1e-4), 0.0) > 0.0);
    }
}
