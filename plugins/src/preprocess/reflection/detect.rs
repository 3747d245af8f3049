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

/// Box sums over a summed-area table.
struct Integral {
    w: usize,
    sum: Vec<f64>,
}

impl Integral {
    fn new(w: usize, h: usize, f: impl Fn(usize) -> f64) -> Self {
        let mut sum = vec![0.0; (w + 1) * (h + 1)];
        for y in 0..h {
            let mut row = 0.0;
            for x in 0..w {
                row += f(y * w + x);
                sum[(y + 1) * (w + 1) + x + 1] = sum[y * (w + 1) + x + 1] + row;
            }
        }
        Self { w, sum }
    }

    /// Sum over columns x0..x1 and rows y0..y1 (exclusive ends).
    fn rect(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> f64 {
        let s = |x: usize, y: usize| self.sum[y * (self.w + 1) + x];
        s(x1, y1) - s(x0, y1) - s(x1, y0) + s(x0, y0)
    }
}

/// Detects the highlights of `img` among the pixels set in `valid`; `decode` maps 8-bit values
/// to linear.
pub fn detect(img: &Rgb8, valid: &Mask, p: &DetectParams, decode: &[f64; 256]) -> Detection {
    let (w, h) = img.size();
    let n = w * h;
    let mut out = Detection { mask: Mask::new(w, h), groups: 0, rejected: 0 };
    if n == 0 || valid.size() != (w, h) {
        return out;
    }
    let px = |k: usize| -> [u8; 3] { [img.data()[3 * k], img.data()[3 * k + 1], img.data()[3 * k + 2]] };
    let value: Vec<f64> = (0..n).map(|k| f64::from(*px(k).iter().max().unwrap_or(&0))).collect();
    let saturation: Vec<f64> = (0..n)
        .map(|k| {
            let lo = f64::from(*px(k).iter().min().unwrap_or(&0));
            if value[k] > 0.0 { 1.0 - lo / value[k] } else { 1.0 }
        })
        .collect();
    let lum: Vec<f64> = (0..n).map(|k| px(k).iter().zip(NTSC_WEIGHTS).map(|(c, wt)| wt * decode[usize::from(*c)]).sum()).collect();
    let ok = |k: usize| valid.data()[k];
    let count = Integral::new(w, h, |k| if ok(k) { 1.0 } else { 0.0 });
    let s1 = Integral::new(w, h, |k| if ok(k) { value[k] } else { 0.0 });
    let s2 = Integral::new(w, h, |k| if ok(k) { value[k] * value[k] } else { 0.0 });
    let half = p.window_px / 2;
    let window = |k: usize| {
        let (x, y) = (k % w, k / w);
        (x.saturating_sub(half), y.saturating_sub(half), (x + half + 1).min(w), (y + half + 1).min(h))
    };
    // 1. Peaks by the adaptive threshold.
    let peak: Vec<bool> = (0..n)
        .map(|k| {
            if !ok(k) || value[k] < p.min_value {
                return false;
            }
            if saturation[k] > p.max_saturation {
                return false;
            }
            let (x0, y0, x1, y1) = window(k);
            let m = count.rect(x0, y0, x1, y1).max(1.0);
            let mean = s1.rect(x0, y0, x1, y1) / m;
            let var = (s2.rect(x0, y0, x1, y1) / m - mean * mean).max(0.0);
            value[k] > mean + p.peak_sigma * var.sqrt()
        })
        .collect();
    // 2. Groups of peaks (8-connected, in index order) kept by their rim gradient.
    let sobel = |k: usize| -> f64 {
        let (x, y) = (k % w, k / w);
        if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
            return 0.0;
        }
        let v = |dx: isize, dy: isize| value[(y as isize + dy) as usize * w + (x as isize + dx) as usize];
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
    let mut label = vec![0u32; n];
    let mut seeds = Vec::new();
    let mut stack = Vec::new();
    for start in 0..n {
        if !peak[start] || label[start] != 0 {
            continue;
        }
        out.groups += 1;
        let id = out.groups as u32;
        let mut members = vec![start];
        label[start] = id;
        stack.push(start);
        while let Some(k) = stack.pop() {
            for q in neighbours8(k) {
                if peak[q] && label[q] == 0 {
                    label[q] = id;
                    members.push(q);
                    stack.push(q);
                }
            }
        }
        let mut rim = (0.0, 0usize);
        for &k in &members {
            for q in neighbours8(k) {
                if label[q] == 0 && ok(q) {
                    label[q] = u32::MAX;
                    rim.0 += sobel(q);
                    rim.1 += 1;
                }
            }
        }
        // Un-mark the ring (u32::MAX was only to count each ring pixel once).
        for &k in &members {
            for q in neighbours8(k) {
                if label[q] == u32::MAX {
                    label[q] = 0;
                }
            }
        }
        if rim.1 > 0 && rim.0 / rim.1 as f64 >= p.min_rim_gradient {
            seeds.extend(members);
        } else {
            out.rejected += 1;
        }
    }
    // 3. Growth against the diffuse background: the window's mean linear luminance without the
    // peaks.
    let bg_count = Integral::new(w, h, |k| if ok(k) && !peak[k] { 1.0 } else { 0.0 });
    let bg_sum = Integral::new(w, h, |k| if ok(k) && !peak[k] { lum[k] } else { 0.0 });
    let background = |k: usize| {
        let (x0, y0, x1, y1) = window(k);
        let m = bg_count.rect(x0, y0, x1, y1);
        if m > 0.0 { bg_sum.rect(x0, y0, x1, y1) / m } else { f64::INFINITY }
    };
    let mut steps = vec![usize::MAX; n];
    let mut queue = std::collections::VecDeque::new();
    for k in seeds {
        out.mask.data_mut()[k] = true;
        steps[k] = 0;
        queue.push_back(k);
    }
    while let Some(k) = queue.pop_front() {
        if steps[k] >= p.max_grow_px {
            continue;
        }
        for q in neighbours8(k) {
            if ok(q) && steps[q] == usize::MAX && (saturation[q] <= p.grow_saturation || lum[q] >= p.grow_ratio * background(q)) {
                steps[q] = steps[k] + 1;
                out.mask.data_mut()[q] = true;
                queue.push_back(q);
            }
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
