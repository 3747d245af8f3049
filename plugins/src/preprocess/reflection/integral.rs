//! Window statistics of the highlight detector: summed-area tables (Crow 1984) of a valid-pixel
//! count, the brightness and its square, over small square bins, so that the local mean and
//! variance of any window cost four reads.

/// Side of the square bins the window statistics are summed over (the window's edges snap to
/// them: a 61 px window becomes 61–63 px; a quarter of the table to build and read).
const BIN: usize = 2;

/// Summed-area tables, over `BIN`×`BIN` bins, of the valid pixels' count, brightness and squared
/// brightness (exact integer sums).
pub struct Integral {
    /// Bins per row (+1 for the table's zero border).
    bw: usize,
    /// Bins per column.
    bh: usize,
    /// Per entry: (count, Σ V, Σ V²).
    pub sum: Vec<(u32, u32, u64)>,
}

impl Integral {
    /// The tables of an image `w` × `h` whose pixel `k` holds `f(k)` (`None`: not counted),
    /// built in the buffer `sum`.
    pub fn new(w: usize, h: usize, mut sum: Vec<(u32, u32, u64)>, f: impl Fn(usize) -> Option<u8>) -> Self {
        let (bw, bh) = (w.div_ceil(BIN), h.div_ceil(BIN));
        sum.clear();
        sum.resize((bw + 1) * (bh + 1), (0, 0, 0));
        // Bin sums into row by + 1 of the table, then prefix sums in place.
        for y in 0..h {
            let row = (y / BIN + 1) * (bw + 1);
            for x in 0..w {
                if let Some(v) = f(y * w + x) {
                    let e = &mut sum[row + x / BIN + 1];
                    e.0 += 1;
                    e.1 += u32::from(v);
                    e.2 += u64::from(v) * u64::from(v);
                }
            }
        }
        for by in 1..=bh {
            let mut acc = (0u32, 0u32, 0u64);
            for bx in 1..=bw {
                let i = by * (bw + 1) + bx;
                let (b, up) = (sum[i], sum[i - bw - 1]);
                acc = (acc.0 + b.0, acc.1 + b.1, acc.2 + b.2);
                sum[i] = (up.0 + acc.0, up.1 + acc.1, up.2 + acc.2);
            }
        }
        Self { bw: bw + 1, bh, sum }
    }

    /// (count, mean, variance) over the bins holding columns x0..x1 and rows y0..y1 (exclusive
    /// ends, pixels).
    pub fn stats(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> (f64, f64, f64) {
        let (bx0, by0) = (x0 / BIN, y0 / BIN);
        let (bx1, by1) = (x1.div_ceil(BIN).min(self.bw - 1), y1.div_ceil(BIN).min(self.bh));
        let s = |x: usize, y: usize| self.sum[y * self.bw + x];
        let (a, b, c, d) = (s(bx1, by1), s(bx0, by1), s(bx1, by0), s(bx0, by0));
        let n = f64::from(a.0 + d.0 - b.0 - c.0);
        if n <= 0.0 {
            return (0.0, 0.0, 0.0);
        }
        let s1 = f64::from(a.1 + d.1 - b.1 - c.1);
        let s2 = (a.2 + d.2 - b.2 - c.2) as f64;
        let mean = s1 / n;
        (n, mean, (s2 / n - mean * mean).max(0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_statistics_equal_the_brute_force_ones_on_bin_aligned_windows() {
        let (w, h) = (20, 14);
        let value = |k: usize| ((k * 37 + 11) % 251) as u8;
        let valid = |k: usize| k % 7 != 3;
        let t = Integral::new(w, h, Vec::new(), |k| valid(k).then_some(value(k)));
        for (x0, y0, x1, y1) in [(0, 0, w, h), (2, 4, 10, 12), (6, 0, 8, 2)] {
            let px: Vec<f64> = (y0..y1).flat_map(|y| (x0..x1).map(move |x| y * w + x)).filter(|&k| valid(k)).map(|k| f64::from(value(k))).collect();
            let n = px.len() as f64;
            let mean = px.iter().sum::<f64>() / n;
            let var = px.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
            let (cn, cm, cv) = t.stats(x0, y0, x1, y1);
            assert_eq!(cn, n);
            assert!((cm - mean).abs() < 1e-9 && (cv - var).abs() < 1e-6, "({x0},{y0})-({x1},{y1}): {cm} {cv} vs {mean} {var}");
        }
    }
}
