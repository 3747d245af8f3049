//! Specular highlight detection: "the gradient map of the input image combined with the peak
//! values detected by an adaptive threshold" (the paper, Sec. 3.1; after
//! Arnold et al. 2010 and Oh et al. 2007):
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

use capsule_slam_framework::image::NTSC_WEIGHTS;
use capsule_slam_framework::{Mask, Rgb8, StageError};

use super::integral::Integral;

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

/// The per-pixel planes of one image the steps read: brightness, saturation, validity, and
/// the window and neighbourhood geometry.
struct Planes<'a> {
    img: &'a Rgb8,
    valid: &'a Mask,
    value: &'a [u8],
    saturation: &'a [f32],
    w: usize,
    h: usize,
    /// Half the window side, pixels.
    half: usize,
}

impl Planes<'_> {
    fn ok(&self, k: usize) -> bool {
        self.valid.data()[k]
    }

    /// The statistics window about pixel `k` (exclusive ends), clipped to the image.
    fn window(&self, k: usize) -> (usize, usize, usize, usize) {
        let (x, y, half) = (k % self.w, k / self.w, self.half);
        (x.saturating_sub(half), y.saturating_sub(half), (x + half + 1).min(self.w), (y + half + 1).min(self.h))
    }

    /// The 8-connected neighbours of pixel `k` inside the image.
    fn neighbours8(&self, k: usize) -> impl Iterator<Item = usize> + use<> {
        let (w, h) = (self.w, self.h);
        let (x, y) = ((k % w) as isize, (k / w) as isize);
        (-1..=1isize).flat_map(move |dy| (-1..=1isize).map(move |dx| (dx, dy))).filter_map(move |(dx, dy)| {
            let (nx, ny) = (x + dx, y + dy);
            ((dx, dy) != (0, 0) && nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h).then(|| ny as usize * w + nx as usize)
        })
    }

    /// Sobel gradient magnitude of V at pixel `k`, levels per pixel (0 on the image border).
    fn sobel(&self, k: usize) -> f64 {
        let (w, h) = (self.w, self.h);
        let (x, y) = (k % w, k / w);
        if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
            return 0.0;
        }
        let v = |dx: isize, dy: isize| f64::from(self.value[(y as isize + dy) as usize * w + (x as isize + dx) as usize]);
        let gx = (v(1, -1) + 2.0 * v(1, 0) + v(1, 1)) - (v(-1, -1) + 2.0 * v(-1, 0) + v(-1, 1));
        let gy = (v(-1, 1) + 2.0 * v(0, 1) + v(1, 1)) - (v(-1, -1) + 2.0 * v(0, -1) + v(1, -1));
        (gx * gx + gy * gy).sqrt() / 8.0
    }
}

/// Detects the highlights of `img` among the pixels set in `valid`; `decode` maps 8-bit values
/// to linear. A `valid` mask of another size than the image is an error.
pub fn detect(img: &Rgb8, valid: &Mask, p: &DetectParams, decode: &[f64; 256], scratch: &mut Scratch) -> Result<Detection, StageError> {
    let (w, h) = img.size();
    if valid.size() != (w, h) {
        return Err(StageError::invalid_input(format!("reflection: the valid-pixel mask is {:?} but the image {w}×{h}", valid.size())));
    }
    let mut out = Detection { mask: Mask::new(w, h), groups: 0, rejected: 0 };
    if w * h == 0 {
        return Ok(out);
    }
    let Scratch { value, saturation, integral, peak, label, steps } = scratch;
    brightness_and_saturation(img, value, saturation);
    let planes = Planes { img, valid, value, saturation, w, h, half: p.window_px / 2 };
    find_peaks(&planes, p, integral, peak);
    if !peak.iter().any(|v| *v) {
        return Ok(out);
    }
    // `label` is all 0 and `steps` all u16::MAX between calls (each step resets what it set),
    // so only a new image size fills them.
    if label.len() != w * h {
        label.clear();
        label.resize(w * h, 0);
        steps.clear();
        steps.resize(w * h, u16::MAX);
    }
    let (seeds, labelled) = keep_by_rim_gradient(&planes, peak, label, p, &mut out);
    if seeds.is_empty() {
        for k in labelled {
            label[k] = 0;
        }
        return Ok(out);
    }
    let lum = Luminance::new(decode);
    let background = Background::around(&planes, &seeds, peak, &lum, p.max_grow_px + planes.half + 1);
    for k in labelled {
        label[k] = 0;
    }
    grow(&planes, &seeds, &background, &lum, p, steps, &mut out.mask);
    Ok(out)
}

/// Brightness V = max channel and saturation 1 − min / max per pixel.
fn brightness_and_saturation(img: &Rgb8, value: &mut Vec<u8>, saturation: &mut Vec<f32>) {
    let n = img.width() * img.height();
    value.resize(n, 0);
    saturation.resize(n, 0.0);
    for ((v, s), c) in value.iter_mut().zip(saturation.iter_mut()).zip(img.data().chunks_exact(3)) {
        let (hi, lo) = (c[0].max(c[1]).max(c[2]), c[0].min(c[1]).min(c[2]));
        *v = hi;
        *s = if hi > 0 { 1.0 - f32::from(lo) / f32::from(hi) } else { 1.0 };
    }
}

/// Step 1: peaks by the adaptive threshold, V above the window's mean + `peak_sigma` σ (the
/// window statistics only for the white, bright pixels that could be peaks).
fn find_peaks(px: &Planes, p: &DetectParams, integral: &mut Vec<(u32, u32, u64)>, peak: &mut Vec<bool>) {
    let stats = Integral::new(px.w, px.h, std::mem::take(integral), |k| px.ok(k).then_some(px.value[k]));
    peak.resize(px.w * px.h, false);
    for (k, o) in peak.iter_mut().enumerate() {
        *o = px.ok(k) && f64::from(px.value[k]) >= p.min_value && f64::from(px.saturation[k]) <= p.max_saturation && {
            let (x0, y0, x1, y1) = px.window(k);
            let (_, mean, var) = stats.stats(x0, y0, x1, y1);
            f64::from(px.value[k]) > mean + p.peak_sigma * var.sqrt()
        };
    }
    *integral = stats.sum;
}

/// Step 2: groups of peaks (8-connected, in index order) kept by the mean Sobel magnitude on
/// their one-pixel outer ring. Returns the kept groups' pixels (the seeds) and every labelled
/// pixel (to be reset by the caller); counts groups and rejections into `out`.
fn keep_by_rim_gradient(px: &Planes, peak: &[bool], label: &mut [u32], p: &DetectParams, out: &mut Detection) -> (Vec<usize>, Vec<usize>) {
    let mut labelled = Vec::new();
    let mut seeds = Vec::new();
    let mut stack = Vec::new();
    for start in 0..px.w * px.h {
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
            for q in px.neighbours8(k) {
                if peak[q] && label[q] == 0 {
                    label[q] = id;
                    labelled.push(q);
                    stack.push(q);
                }
            }
        }
        let members = &labelled[first..];
        if rim_gradient(px, members, label).is_some_and(|g| g >= p.min_rim_gradient) {
            seeds.extend_from_slice(members);
        } else {
            out.rejected += 1;
        }
    }
    (seeds, labelled)
}

/// The mean Sobel magnitude on a group's one-pixel outer ring (valid pixels, each counted once:
/// marked `u32::MAX` in `label` meanwhile); `None` for a group without a ring.
fn rim_gradient(px: &Planes, members: &[usize], label: &mut [u32]) -> Option<f64> {
    let mut rim = (0.0, 0usize);
    let mut ring = Vec::new();
    for &k in members {
        for q in px.neighbours8(k) {
            if label[q] == 0 && px.ok(q) {
                label[q] = u32::MAX;
                ring.push(q);
                rim.0 += px.sobel(q);
                rim.1 += 1;
            }
        }
    }
    for q in ring {
        label[q] = 0;
    }
    (rim.1 > 0).then(|| rim.0 / rim.1 as f64)
}

/// Linear luminance of an 8-bit colour through a decoding table.
struct Luminance([[f64; 256]; 3]);

impl Luminance {
    fn new(decode: &[f64; 256]) -> Self {
        Self(std::array::from_fn(|c| std::array::from_fn(|v| NTSC_WEIGHTS[c] * decode[v])))
    }

    fn of(&self, img: &Rgb8, k: usize) -> f64 {
        let c = &img.data()[3 * k..3 * k + 3];
        self.0[0][usize::from(c[0])] + self.0[1][usize::from(c[1])] + self.0[2][usize::from(c[2])]
    }
}

/// The local diffuse background of step 3: a summed-area table of the linear luminance of the
/// valid non-peak pixels over the seeds' bounding box grown by `reach` (a highlight is local;
/// the rest of the image is never asked).
struct Background {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
    /// (count, Σ luminance) per entry, `(x1 − x0 + 1)` entries a row.
    table: Vec<(f64, f64)>,
}

impl Background {
    fn around(px: &Planes, seeds: &[usize], peak: &[bool], lum: &Luminance, reach: usize) -> Self {
        let (w, h) = (px.w, px.h);
        let (bx0, by0, bx1, by1) = seeds.iter().fold((w, h, 0, 0), |(x0, y0, x1, y1), &k| (x0.min(k % w), y0.min(k / w), x1.max(k % w + 1), y1.max(k / w + 1)));
        let (x0, y0, x1, y1) = (bx0.saturating_sub(reach), by0.saturating_sub(reach), (bx1 + reach).min(w), (by1 + reach).min(h));
        let bw = x1 - x0;
        let mut table = vec![(0.0f64, 0.0f64); (bw + 1) * (y1 - y0 + 1)];
        for y in y0..y1 {
            let mut row = (0.0, 0.0);
            for x in x0..x1 {
                let k = y * w + x;
                if px.ok(k) && !peak[k] {
                    row.0 += 1.0;
                    row.1 += lum.of(px.img, k);
                }
                let (ty, tx) = (y - y0, x - x0);
                let up = table[ty * (bw + 1) + tx + 1];
                table[(ty + 1) * (bw + 1) + tx + 1] = (up.0 + row.0, up.1 + row.1);
            }
        }
        Self { x0, y0, x1, y1, table }
    }

    /// The mean luminance of the window about pixel `k` without the peaks (∞ when it has none).
    fn at(&self, px: &Planes, k: usize) -> f64 {
        let (bx0, by0, bx1, by1) = (self.x0, self.y0, self.x1, self.y1);
        let bw = bx1 - bx0;
        let (x0, y0, x1, y1) = px.window(k);
        let (x0, y0, x1, y1) = (x0.clamp(bx0, bx1) - bx0, y0.clamp(by0, by1) - by0, x1.clamp(bx0, bx1) - bx0, y1.clamp(by0, by1) - by0);
        let s = |x: usize, y: usize| self.table[y * (bw + 1) + x];
        let (a, b, c, d) = (s(x1, y1), s(x0, y1), s(x1, y0), s(x0, y0));
        let m = a.0 + d.0 - b.0 - c.0;
        if m > 0.0 { (a.1 + d.1 - b.1 - c.1) / m } else { f64::INFINITY }
    }
}

/// Step 3: growth from the seeds, breadth first, over valid neighbours that are whitened or at
/// least `grow_ratio` × the local background, at most `max_grow_px` steps. `steps` is all
/// `u16::MAX` on entry and on return.
fn grow(px: &Planes, seeds: &[usize], background: &Background, lum: &Luminance, p: &DetectParams, steps: &mut [u16], mask: &mut Mask) {
    let mut queue = std::collections::VecDeque::new();
    for &k in seeds {
        mask.data_mut()[k] = true;
        steps[k] = 0;
        queue.push_back(k);
    }
    while let Some(k) = queue.pop_front() {
        if usize::from(steps[k]) >= p.max_grow_px {
            continue;
        }
        for q in px.neighbours8(k) {
            if px.ok(q)
                && steps[q] == u16::MAX
                && (f64::from(px.saturation[q]) <= p.grow_saturation || lum.of(px.img, q) >= p.grow_ratio * background.at(px, q))
            {
                steps[q] = steps[k] + 1;
                mask.data_mut()[q] = true;
                queue.push_back(q);
            }
        }
    }
    for (k, m) in mask.data().iter().enumerate() {
        if *m {
            steps[k] = u16::MAX;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn planes<'a>(img: &'a Rgb8, valid: &'a Mask, value: &'a [u8], saturation: &'a [f32]) -> Planes<'a> {
        let (w, h) = img.size();
        Planes { img, valid, value, saturation, w, h, half: 2 }
    }

    #[test]
    fn a_sharp_bright_square_has_a_steep_rim_and_a_flat_one_none() {
        let (w, h) = (12, 12);
        let img = Rgb8::from_fn(w, h, |x, y| if (4..8).contains(&x) && (4..8).contains(&y) { [250; 3] } else { [40; 3] });
        let (mut value, mut saturation) = (Vec::new(), Vec::new());
        brightness_and_saturation(&img, &mut value, &mut saturation);
        let valid = Mask::filled(w, h, true);
        let px = planes(&img, &valid, &value, &saturation);
        let members: Vec<usize> = (4..8).flat_map(|y| (4..8).map(move |x| y * w + x)).collect();
        let mut label = vec![0u32; w * h];
        for &k in &members {
            label[k] = 1;
        }
        // The ring's Sobel magnitude: a 210-level step seen by the 3×3 kernel, ≥ 210 · 3 / 8 / √2.
        let g = rim_gradient(&px, &members, &mut label).unwrap();
        assert!(g > 50.0, "{g}");
        assert!(label.iter().enumerate().all(|(k, l)| *l == u32::from(members.contains(&k))), "the ring marks are reset");
        let flat = Rgb8::filled(w, h, 40);
        brightness_and_saturation(&flat, &mut value, &mut saturation);
        let px = planes(&flat, &valid, &value, &saturation);
        assert_eq!(rim_gradient(&px, &members, &mut label), Some(0.0));
        let everything: Vec<usize> = (0..w * h).collect();
        let mut all = vec![1u32; w * h];
        assert_eq!(rim_gradient(&px, &everything, &mut all), None, "a group without a ring");
    }

    #[test]
    fn a_valid_mask_of_another_size_is_an_error() {
        let p = DetectParams {
            window_px: 5,
            peak_sigma: 1.0,
            min_value: 60.0,
            max_saturation: 0.2,
            min_rim_gradient: 2.0,
            grow_ratio: 2.0,
            grow_saturation: 0.25,
            max_grow_px: 3,
        };
        let decode = std::array::from_fn(|v| v as f64 / 255.0);
        let err = detect(&Rgb8::new(8, 8), &Mask::new(4, 4), &p, &decode, &mut Scratch::default()).unwrap_err().to_string();
        assert!(err.contains("8×8"), "{err}");
    }
}
