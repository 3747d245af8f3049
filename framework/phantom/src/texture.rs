//! Procedural tissue texture: a solid texture evaluated at a wall point's rest position (so it
//! moves with the wall when it deforms): smooth colour noise and vessel-like lines from ridged
//! noise, in a pink-red palette. Folds come from shading.

use nalgebra::Point3;

/// Linear RGB albedo of the mucosa without texture.
pub const BASE_ALBEDO: [f64; 3] = [0.80, 0.30, 0.25];

fn hash(ix: i64, iy: i64, iz: i64, seed: u64) -> f64 {
    let mut h = (ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (iy as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (iz as u64).wrapping_mul(0x1656_67B1_9E37_79F9)
        ^ seed.wrapping_mul(0x27D4_EB2F_1656_67C5);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 31;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// 3-D value noise in [0, 1] with smoothstep interpolation.
fn value_noise(p: [f64; 3], seed: u64) -> f64 {
    let f = p.map(f64::floor);
    let t = [p[0] - f[0], p[1] - f[1], p[2] - f[2]].map(|v| v * v * (3.0 - 2.0 * v));
    let i = f.map(|v| v as i64);
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let h = |dx: i64, dy: i64, dz: i64| hash(i[0] + dx, i[1] + dy, i[2] + dz, seed);
    let x00 = lerp(h(0, 0, 0), h(1, 0, 0), t[0]);
    let x10 = lerp(h(0, 1, 0), h(1, 1, 0), t[0]);
    let x01 = lerp(h(0, 0, 1), h(1, 0, 1), t[0]);
    let x11 = lerp(h(0, 1, 1), h(1, 1, 1), t[0]);
    lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
}

/// Fractal sum of `octaves` value-noise octaves, in about [−1, 1].
fn fbm(p: [f64; 3], octaves: u32, seed: u64) -> f64 {
    let (mut sum, mut amp, mut freq, mut norm) = (0.0, 1.0, 1.0, 0.0);
    for o in 0..octaves {
        sum += amp * (2.0 * value_noise(p.map(|v| v * freq), seed.wrapping_add(u64::from(o) * 7919)) - 1.0);
        norm += amp;
        amp *= 0.5;
        freq *= 2.0;
    }
    sum / norm
}

/// Linear RGB albedo at a rest-shape wall point (metres); `textured = false` gives the uniform
/// base albedo.
pub fn albedo(rest: &Point3<f64>, seed: u64, textured: bool) -> [f64; 3] {
    if !textured {
        return BASE_ALBEDO;
    }
    let p = [rest.x / 0.012, rest.y / 0.012, rest.z / 0.012];
    let at = |s: f64, o: f64| p.map(|v| v * s + o);
    // Smooth blotches (about ±35 % brightness) with a slight hue shift.
    let n = fbm(p, 4, seed);
    let hue = fbm(at(0.7, 13.1), 3, seed ^ 0xA5A5);
    let bright = 1.0 + 0.45 * n;
    // Vessels: thin where ridged noise is near zero, two scales.
    let v1 = (fbm(at(1.6, 3.3), 3, seed ^ 0x5151) * 2.0).abs();
    let v2 = (fbm(at(4.0, -7.7), 2, seed ^ 0x7373) * 2.0).abs();
    let vessel = (1.0 - v1 / 0.08).max(0.0).powi(2) * 0.55 + (1.0 - v2 / 0.06).max(0.0).powi(2) * 0.3;
    let vessel_tint = [0.45, 0.06, 0.08];
    let mut out = [0.0; 3];
    for c in 0..3 {
        let base = BASE_ALBEDO[c] * bright * (1.0 + 0.12 * hue * if c == 0 { -0.5 } else { 1.0 });
        out[c] = (base * (1.0 - vessel) + vessel_tint[c] * bright * vessel).clamp(0.02, 1.0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_is_deterministic_and_reddish() {
        let p = Point3::new(0.01, 0.02, -0.003);
        let a = albedo(&p, 7, true);
        assert_eq!(a, albedo(&p, 7, true));
        assert_ne!(a, albedo(&p, 8, true));
        let mut red = 0;
        for i in 0..400 {
            let a = albedo(&Point3::new(i as f64 * 0.0013, i as f64 * 0.0007, 0.01), 3, true);
            if a[0] > a[1] && a[0] > a[2] {
                red += 1;
            }
            assert!(a.iter().all(|v| (0.0..=1.0).contains(v)));
        }
        assert!(red > 380, "{red}");
        assert_eq!(albedo(&p, 1, false), BASE_ALBEDO);
    }
}
