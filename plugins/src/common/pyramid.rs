//! Image pyramids for coarse-to-fine tracking: each level halves the size (ElasticFusion uses
//! 3 levels with fx/2^l, cx/2^l).

use capsule_slam_framework::{DepthMap, GrayF32};
use rayon::prelude::*;

/// Halves a depth map: the mean of the valid pixels of each 2×2 block whose values lie within
/// `max_spread_m` of the block's first valid value (so depth edges are not blended); 0 if none.
pub fn half_depth(d: &DepthMap, max_spread_m: f32) -> DepthMap {
    halved(d, |[top, bottom], x, _| {
        let vals = [top[2 * x], top[2 * x + 1], bottom[2 * x], bottom[2 * x + 1]];
        let Some(first) = vals.iter().copied().find(|v| *v > 0.0) else { return 0.0 };
        let (s, n) = vals.iter().filter(|v| **v > 0.0 && (**v - first).abs() <= max_spread_m).fold((0.0, 0), |(s, n), v| (s + v, n + 1));
        s / n as f32
    })
}

/// Halves an intensity image by 2×2 means over the pixels with depth (> 0 in `depth`, the same
/// size) and an intensity (> 0); 0 where none has both.
pub fn half_gray(g: &GrayF32, depth: &DepthMap) -> GrayF32 {
    let (sw, d) = (g.width(), depth.data());
    halved(g, |[top, bottom], x, y| {
        let (d_top, d_bottom) = (&d[2 * y * sw..][..sw], &d[(2 * y + 1) * sw..][..sw]);
        let (mut s, mut n) = (0.0, 0);
        for (g, d, k) in [(top, d_top, 2 * x), (top, d_top, 2 * x + 1), (bottom, d_bottom, 2 * x), (bottom, d_bottom, 2 * x + 1)] {
            if d[k] > 0.0 && g[k] > 0.0 {
                s += g[k];
                n += 1;
            }
        }
        if n > 0 { s / n as f32 } else { 0.0 }
    })
}

/// An image half the size of `src` (rounded down): pixel (x, y) is `f` of the source rows 2y
/// and 2y + 1, x and y.
fn halved(src: &GrayF32, f: impl Fn([&[f32]; 2], usize, usize) -> f32 + Sync) -> GrayF32 {
    let (sw, w, h) = (src.width(), src.width() / 2, src.height() / 2);
    let mut out = GrayF32::new(w, h);
    if w == 0 {
        return out;
    }
    out.data_mut().par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let rows = [&src.data()[2 * y * sw..][..sw], &src.data()[(2 * y + 1) * sw..][..sw]];
        for (x, out) in row.iter_mut().enumerate() {
            *out = f(rows, x, y);
        }
    });
    out
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
        let h = half_gray(&g, &GrayF32::from_vec(4, 2, vec![1.0; 8]).unwrap());
        assert_eq!(h.data(), &[2.0, 5.0]);
        // A pixel without depth is left out, a block with none is 0.
        let h = half_gray(&g, &GrayF32::from_vec(4, 2, vec![1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]).unwrap());
        assert_eq!(h.data(), &[5.0 / 3.0, 0.0]);
        assert_eq!(bilinear(&g, 0.5, 0.5, true), Some(2.0));
        assert_eq!(bilinear(&g, 2.5, 0.5, true), None);
    }
}
