//! Image pyramids for coarse-to-fine tracking: each level halves the size (ElasticFusion uses
//! 3 levels with fx/2^l, cx/2^l).

use capsule_slam_framework::{DepthMap, GrayF32};

/// Halves a depth map: the mean of the valid pixels of each 2×2 block whose values lie within
/// `max_spread_m` of the block's first valid value (so depth edges are not blended); 0 if none.
pub fn half_depth(d: &DepthMap, max_spread_m: f32) -> DepthMap {
    let (w, h) = (d.width() / 2, d.height() / 2);
    DepthMap::from_fn_par(w, h, |x, y| {
        let vals = [d.at(2 * x, 2 * y), d.at(2 * x + 1, 2 * y), d.at(2 * x, 2 * y + 1), d.at(2 * x + 1, 2 * y + 1)];
        let Some(first) = vals.iter().copied().find(|v| *v > 0.0) else { return [0.0] };
        let (s, n) = vals.iter().filter(|v| **v > 0.0 && (**v - first).abs() <= max_spread_m).fold((0.0, 0), |(s, n), v| (s + v, n + 1));
        [s / n as f32]
    })
}

/// Halves an intensity image by 2×2 means over the pixels `valid` accepts (0 where none is).
pub fn half_gray(g: &GrayF32, valid: impl Fn(usize, usize) -> bool + Sync) -> GrayF32 {
    let (w, h) = (g.width() / 2, g.height() / 2);
    GrayF32::from_fn_par(w, h, |x, y| {
        let (mut s, mut n) = (0.0, 0);
        for (xx, yy) in [(2 * x, 2 * y), (2 * x + 1, 2 * y), (2 * x, 2 * y + 1), (2 * x + 1, 2 * y + 1)] {
            if valid(xx, yy) {
                s += g.at(xx, yy);
                n += 1;
            }
        }
        [if n > 0 { s / n as f32 } else { 0.0 }]
    })
}

/// Bilinear interpolation weights at (u, v): the top-left pixel's offset and the fractions.
#[derive(Debug, Clone, Copy)]
pub struct Bilinear {
    k: usize,
    w: usize,
    fx: f32,
    fy: f32,
}

impl Bilinear {
    /// Weights for sampling a `width × height` image at (u, v); `None` unless the 2×2
    /// neighbourhood lies inside.
    #[inline]
    pub fn at(width: usize, height: usize, u: f64, v: f64) -> Option<Self> {
        if !(u >= 0.0 && v >= 0.0) {
            return None;
        }
        // Truncation is floor for non-negative values (and avoids a libm call).
        let (x0, y0) = (u as usize, v as usize);
        if x0 + 1 >= width || y0 + 1 >= height {
            return None;
        }
        Some(Self { k: y0 * width + x0, w: width, fx: (u - x0 as f64) as f32, fy: (v - y0 as f64) as f32 })
    }

    /// The four neighbours of an image sampled with these weights.
    #[inline]
    pub fn corners(&self, g: &GrayF32) -> [f32; 4] {
        let d = g.data();
        [d[self.k], d[self.k + 1], d[self.k + self.w], d[self.k + self.w + 1]]
    }

    /// The interpolated value.
    #[inline]
    pub fn sample(&self, g: &GrayF32) -> f32 {
        let [a, b, c, d] = self.corners(g);
        (a * (1.0 - self.fx) + b * self.fx) * (1.0 - self.fy) + (c * (1.0 - self.fx) + d * self.fx) * self.fy
    }
}

/// Bilinear sample of `g` at (u, v); `None` outside or next to an invalid (zero) pixel, when
/// `zero_invalid` is set.
pub fn bilinear(g: &GrayF32, u: f64, v: f64, zero_invalid: bool) -> Option<f32> {
    let b = Bilinear::at(g.width(), g.height(), u, v)?;
    if zero_invalid && b.corners(g).contains(&0.0) {
        return None;
    }
    Some(b.sample(g))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn halving_keeps_edges_and_skips_holes() {
        let d = DepthMap::from_vec(2, 2, vec![0.03, 0.031, 0.0, 0.08]).unwrap();
        assert!((half_depth(&d, 0.005).at(0, 0) - 0.0305).abs() < 1e-7);
        let g = GrayF32::from_vec(4, 2, vec![1.0, 3.0, 5.0, 5.0, 1.0, 3.0, 5.0, 0.0]).unwrap();
        let h = half_gray(&g, |x, y| g.at(x, y) > 0.0);
        assert_eq!(h.data(), &[2.0, 5.0]);
        assert_eq!(bilinear(&g, 0.5, 0.5, true), Some(2.0));
        assert_eq!(bilinear(&g, 2.5, 0.5, true), None);
    }
}
