//! Specular highlight detection: "the gradient map of the input image combined with the peak
//! values detected by an adaptive threshold" (the paper, Sec. 3.1; the recipe of frontend digest
//! §C, after Arnold et al. 2010 and Oh et al. 2007):
//!
//! 1. peaks: on the brightness `V = max(R, G, B)`, a pixel above the local mean plus
//!    `peak_sigma` local standard deviations (a `window_px` box, field of view only), above
//!    `min_value`, and nearly white (saturation `1 − min/max` at most `max_saturation`: the
//!    highlight of a wet film is the light's colour, tissue is red);
//! 2. gradient: a connected group of peaks is kept only when the mean Sobel magnitude of V on
//!    its one-pixel outer ring reaches `min_rim_gradient` (highlights have sharp rims, bright
//!    flat mucosa has none);
//! 3. extent: from the kept peaks the region grows over neighbours that are whitened (saturation
//!    at most `grow_saturation`) or whose linear luminance is at least `grow_ratio` times the
//!    local diffuse background (the window's mean without the peaks), at most `max_grow_px`
//!    steps: with `grow_ratio = 2` this is where the highlight adds at least as much light as
//!    the tissue reflects diffusely, the phantom's ground-truth definition.

use capsule_slam_framework::{Mask, Rgb8};

use capsule_slam_framework::image::NTSC_WEIGHTS;

/// The detector's thresholds.
#[derive(Debug, Clone, Copy)]
pub struct DetectParams {
    /// Side of the local-statistics window, pixels.
    pub window_px: usize,
    /// Peaks lie this many local standard deviations above the local mean.
    pub peak_sigma: f64,
    /// Peaks are at least this bright (8-bit V).
    pub min_value: f64,
    /// Peaks are at most this saturated (1 − min/max).
    pub max_saturation: f64,
    /// Mean Sobel magnitude of V on a peak group's outer ring, 8-bit levels per pixel.
    pub min_rim_gradient: f64,
    /// Growth: linear luminance over the local diffuse background.
    pub grow_ratio: f64,
    /// Growth: saturation at most this (whitened by the highlight).
    pub grow_saturation: f64,
    /// Growth: most steps from a peak, pixels.
    pub max_grow_px: usize,
}

/// What was found.
#[derive(Debug, Clone)]
pub struct Detection {
    /// The highlights (peaks kept by the gradient test, grown to their extent).
    pub mask: Mask,
    /// Peak groups found.
    pub groups: usize,
    /// Peak groups rejected by the gradient test.
    pub rejected: usize,
}

/// Side of the square bins the window statistics are summed over (the window's edges snap to
/// them: a 61 px window becomes 61–63 px; a quarter of the table to build and read).
const BIN: usize = 2;

/// Summed-area tables, over `BIN`×`BIN` bins, of the valid pixels' count, brightness and squared
/// brightness (exact integer sums).
struct Integral {
    /// Bins per row (+1 for the table's zero border).
    bw: usize,
    /// Bins per column.
    bh: usize,
    /// Per entry: (count, Σ V, Σ V²).
    sum: Vec<(u32, u32, u64)>,
}

impl Integral {
    fn new(w: usize, h: usize, mut sum: Vec<(u32, u32, u64)>, f: impl Fn(usize) -> Option<u8>) -> Self {
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
    fn stats(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> (f64, f64, f64) {
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

/// Buffers of one image size, reused from frame to frame (the tables are megabytes: fresh
/// allocations would cost page faults every frame).
#[derive(Default)]
pub struct Scratch {
    value: Vec<u8>,
    saturation: Vec<f32>,
    integral: Vec<(u32, u32, u64)>,
    peak: Vec<bool>,
    label: Vec<u32>,
    steps: Vec<u16>,
}

/// Detects the highlights of `img` among the pixels set in `valid`; `decode` maps 8-bit values
/// to linear.
pub fn detect(img: &Rgb8, valid: &Mask, p: &DetectParams, decode: &[f64; 256], scratch: &mut Scratch) -> Detection {
    let (w, h) = img.size();
    let n = w * h;
    let mut out = Detection { mask: Mask::new(w, h), groups: 0, rejected: 0 };
    if n == 0 || valid.size() != (w, h) {
        return out;
    }
    // Brightness V = max channel and saturation 1 − min / max per pixel.
    let Scratch { value, saturation, integral, peak, label, steps } = scratch;
    value.resize(n, 0);
    saturation.resize(n, 0.0);
    for ((v, s), c) in value.iter_mut().zip(saturation.iter_mut()).zip(img.data().chunks_exact(3)) {
        let (hi, lo) = (c[0].max(c[1]).max(c[2]), c[0].min(c[1]).min(c[2]));
        *v = hi;
        *s = if hi > 0 { 1.0 - f32::from(lo) / f32::from(hi) } else { 1.0 };
    }
    let (value, saturation) = (&*value, &*saturation);
    let ok = |k: usize| valid.data()[k];
    let stats = Integral::new(w, h, std::mem::take(integral), |k| ok(k).then_some(value[k]));
    let half = p.window_px / 2;
    let window = |k: usize| {
        let (x, y) = (k % w, k / w);
        (x.saturating_sub(half), y.saturating_sub(half), (x + half + 1).min(w), (y + half + 1).min(h))
    };
    // 1. Peaks by the adaptive threshold (the window statistics only for the white, bright
    // pixels that could be peaks).
    peak.resize(n, false);
    let is_peak = |k: usize| {
        if !ok(k) || f64::from(value[k]) < p.min_value || f64::from(saturation[k]) > p.max_saturation {
            return false;
        }
        let (x0, y0, x1, y1) = window(k);
        let (_, mean, var) = stats.stats(x0, y0, x1, y1);
        f64::from(value[k]) > mean + p.peak_sigma * var.sqrt()
    };
    for (k, o) in peak.iter_mut().enumerate() {
        *o = is_peak(k);
    }
    *integral = stats.sum;
    let peak = &*peak;
    if !peak.iter().any(|v| *v) {
        return out;
    }
    // 2. Groups of peaks (8-connected, in index order) kept by their rim gradient.
    let sobel = |k: usize| -> f64 {
        let (x, y) = (k % w, k / w);
        if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
            return 0.0;
        }
        let v = |dx: isize, dy: isize| f64::from(value[(y as isize + dy) as usize * w + (x as isize + dx) as usize]);
        let gx = (v(1, -1) + 2.0 * v(1, 0) + v(1, 1)) - (v(-1, -1) + 2.0 * v(-1, 0) + v(-1, 1));
        let gy = (v(-1, 1) + 2.0 * v(0, 1) + v(1, 1)) - (v(-1, -1) + 2.0 * v(0, -1) + v(1, -1));
        (gx * gx + gy * gy).sqrt() / 8.0
    };
    let neighbours8 = |k: usize| {
        let (x, y) = ((k % w) as isize, (k / w) as isize);
        (-1..=1isize).flat_map(move |dy| (-1..=1isize).map(move |dx| (dx, dy))).filter_map(move |(dx, dy)| {
            let (nx, ny) = (x + dx, y + dy);
            ((dx, dy) != (0, 0) && nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h).then(|| ny as usize * w + nx as usize)
        })
    };
    // `label` is all 0 and `steps` all u16::MAX between calls (each resets what it set), so
    // only a new image size fills them.
    if label.len() != n {
        label.clear();
        label.resize(n, 0);
        steps.clear();
        steps.resize(n, u16::MAX);
    }
    let mut labelled = Vec::new();
    let mut seeds = Vec::new();
    let mut stack = Vec::new();
    for start in 0..n {
        if !peak[start] || label[start] != 0 {
            continue;
        }
        out.groups += 1;
        let id = out.groups as u32;
        let first = labelled.len();
        labelled.push(start);
        label[start] = id;
        stack.push(start);
        while let Some(k) = stack.pop() {
            for q in neighbours8(k) {
                if peak[q] && label[q] == 0 {
                    label[q] = id;
                    labelled.push(q);
                    stack.push(q);
                }
            }
        }
        // The one-pixel outer ring, each ring pixel counted once (marked u32::MAX meanwhile).
        let mut rim = (0.0, 0usize);
        let mut ring = Vec::new();
        let members = &labelled[first..];
        for &k in members {
            for q in neighbours8(k) {
                if label[q] == 0 && ok(q) {
                    label[q] = u32::MAX;
                    ring.push(q);
                    rim.0 += sobel(q);
                    rim.1 += 1;
                }
            }
        }
        for q in ring {
            label[q] = 0;
        }
        if rim.1 > 0 && rim.0 / rim.1 as f64 >= p.min_rim_gradient {
            seeds.extend_from_slice(members);
        } else {
            out.rejected += 1;
        }
    }
    // 3. Growth against the diffuse background: the window's mean linear luminance without the
    // peaks (computed where the growth asks).
    let lum_lut: [[f64; 256]; 3] = std::array::from_fn(|c| std::array::from_fn(|v| NTSC_WEIGHTS[c] * decode[v]));
    let lum = |k: usize| -> f64 {
        let c = &img.data()[3 * k..3 * k + 3];
        lum_lut[0][usize::from(c[0])] + lum_lut[1][usize::from(c[1])] + lum_lut[2][usize::from(c[2])]
    };
    // The background table covers the seeds' bounding box grown by the reach of the growth and
    // of the window (a highlight is local; the rest of the image is never asked).
    let reach = p.max_grow_px + half + 1;
    let (bx0, by0, bx1, by1) = seeds.iter().fold((w, h, 0, 0), |(x0, y0, x1, y1), &k| (x0.min(k % w), y0.min(k / w), x1.max(k % w + 1), y1.max(k / w + 1)));
    let (bx0, by0, bx1, by1) = (bx0.saturating_sub(reach), by0.saturating_sub(reach), (bx1 + reach).min(w), (by1 + reach).min(h));
    let bw = bx1 - bx0;
    let mut bg = vec![(0.0f64, 0.0f64); (bw + 1) * (by1 - by0 + 1)];
    for y in by0..by1 {
        let mut row = (0.0, 0.0);
        for x in bx0..bx1 {
            let k = y * w + x;
            if ok(k) && !peak[k] {
                row.0 += 1.0;
                row.1 += lum(k);
            }
            let (ty, tx) = (y - by0, x - bx0);
            let up = bg[ty * (bw + 1) + tx + 1];
            bg[(ty + 1) * (bw + 1) + tx + 1] = (up.0 + row.0, up.1 + row.1);
        }
    }
    let background = |k: usize| {
        let (x0, y0, x1, y1) = window(k);
        let (x0, y0, x1, y1) = (x0.clamp(bx0, bx1) - bx0, y0.clamp(by0, by1) - by0, x1.clamp(bx0, bx1) - bx0, y1.clamp(by0, by1) - by0);
        let s = |x: usize, y: usize| bg[y * (bw + 1) + x];
        let (a, b, c, d) = (s(x1, y1), s(x0, y1), s(x1, y0), s(x0, y0));
        let m = a.0 + d.0 - b.0 - c.0;
        if m > 0.0 { (a.1 + d.1 - b.1 - c.1) / m } else { f64::INFINITY }
    };
    for k in labelled {
        label[k] = 0;
    }
    let mut queue = std::collections::VecDeque::new();
    for k in seeds {
        out.mask.data_mut()[k] = true;
        steps[k] = 0;
        queue.push_back(k);
    }
    while let Some(k) = queue.pop_front() {
        if usize::from(steps[k]) >= p.max_grow_px {
            continue;
        }
        for q in neighbours8(k) {
            if ok(q) && steps[q] == u16::MAX && (f64::from(saturation[q]) <= p.grow_saturation || lum(q) >= p.grow_ratio * background(q)) {
                steps[q] = steps[k] + 1;
                out.mask.data_mut()[q] = true;
                queue.push_back(q);
            }
        }
    }
    for (k, m) in out.mask.data().iter().enumerate() {
        if *m {
            steps[k] = u16::MAX;
        }
    }
    out
}

/// `mask` dilated by a disc of `radius_px` (0 = unchanged), limited to `within`.
pub fn dilate(mask: &Mask, radius_px: usize, within: &Mask) -> Mask {
    if radius_px == 0 {
        return mask.clone();
    }
    let (w, h) = mask.size();
    let r = radius_px as isize;
    let offsets: Vec<(isize, isize)> = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))).filter(|(dx, dy)| dx * dx + dy * dy <= r * r).collect();
    let mut out = mask.clone();
    for k in 0..w * h {
        if !mask.data()[k] {
            continue;
        }
        let (x, y) = ((k % w) as isize, (k / w) as isize);
        for (dx, dy) in &offsets {
            let (nx, ny) = (x + dx, y + dy);
            if nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h {
                let q = ny as usize * w + nx as usize;
                if within.data()[q] {
                    out.data_mut()[q] = true;
                }
            }
        }
    }
    out
}
