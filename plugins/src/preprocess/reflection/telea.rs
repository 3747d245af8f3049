//! Inpainting by fast marching, Telea (2004), "An image inpainting technique based on the fast
//! marching method", J. Graphics Tools 9(1), doi:10.1080/10867651.2004.10487596 (OpenCV's
//! `INPAINT_TELEA`). The masked region is filled from its boundary inward in the order of the
//! distance T to the boundary (the eikonal equation |∇T| = 1, solved by Sethian's fast marching); each pixel p
//! becomes the weighted mean over the already known pixels q within `radius_px` of the first-order
//! extrapolation `I(q) + ∇I(q) · (p − q)` (eq. 3), with weights (eq. 4–5)
//! `dir = |N(p) · (p − q)| / |p − q|` (N = ∇T / |∇T|), `dst = 1 / |p − q|²`,
//! `lev = 1 / (1 + |T(p) − T(q)|)`.
//!
//! [`Order::Zero`] drops the gradient term (a weighted mean); [`Order::First`] keeps it with
//! the gradients of filled pixels propagated rather than differenced (see [`Order`]).
//!
//! Deterministic: ties in T are broken by the pixel index. Pixels outside the mask are never
//! written; only pixels that `source` allows are read (so the black outside of a round field of
//! view does not bleed in); masked pixels that no source reaches keep their value.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use capsule_slam_framework::{Mask, Rgb8, StageError};

#[derive(Clone, Copy, PartialEq, Eq)]
enum Flag {
    /// A value to read (a source, or already filled).
    Known,
    /// On the marching front (value known, T final).
    Band,
    /// Still to fill.
    Inside,
    /// Neither to read nor to fill.
    Excluded,
}

/// Min-heap entry on T, ties by index.
#[derive(PartialEq)]
struct Entry(f32, usize);

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        other.0.total_cmp(&self.0).then_with(|| other.1.cmp(&self.1))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// The extrapolation from each known pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Order {
    /// The known value itself: a weighted mean (what OpenCV's `INPAINT_TELEA` amounts to, its
    /// gradient term being normalised to at most √2 levels). Robust to the bright halo around a
    /// highlight, which a first-order term extrapolates inward.
    Zero,
    /// Telea's eq. 3, `I(q) + ∇I(q) · (p − q)`: exact on linear ramps. ∇I of an input pixel is
    /// its central difference over input pixels; a filled pixel carries the weighted mean of its
    /// sources' gradients (never a difference of filled values, which compounds errors).
    First,
}

/// Fills the pixels of `img` set in `mask` from the pixels set in `source` and not in `mask`.
/// Returns the number of pixels filled. Works on the mask's bounding box grown by the radius.
/// A mask of another size than the image is an error.
pub fn inpaint(img: &mut Rgb8, mask: &Mask, source: &Mask, radius_px: f64, order: Order) -> Result<usize, StageError> {
    let (w, h) = img.size();
    if mask.size() != (w, h) || source.size() != (w, h) {
        return Err(StageError::invalid_input(format!(
            "inpainting: the image is {w}×{h} but the mask {:?} and the source mask {:?}",
            mask.size(),
            source.size()
        )));
    }
    if w == 0 || h == 0 {
        return Ok(0);
    }
    let Some((x0, y0, x1, y1)) = mask.data().iter().enumerate().filter(|(_, m)| **m).fold(None, |b: Option<(usize, usize, usize, usize)>, (k, _)| {
        let (x, y) = (k % w, k / w);
        Some(b.map_or((x, y, x + 1, y + 1), |(a, b, c, d)| (a.min(x), b.min(y), c.max(x + 1), d.max(y + 1))))
    }) else {
        return Ok(0);
    };
    let pad = radius_px.max(1.0).ceil() as usize + 2;
    let (x0, y0, x1, y1) = (x0.saturating_sub(pad), y0.saturating_sub(pad), (x1 + pad).min(w), (y1 + pad).min(h));
    if (x0, y0, x1, y1) == (0, 0, w, h) {
        return Ok(inpaint_full(img, mask, source, radius_px, order));
    }
    let (cw, ch) = (x1 - x0, y1 - y0);
    let mut crop = Rgb8::from_fn(cw, ch, |x, y| img.pixel(x0 + x, y0 + y));
    let crop_mask = Mask::from_fn(cw, ch, |x, y| [mask.at(x0 + x, y0 + y)]);
    let crop_source = Mask::from_fn(cw, ch, |x, y| [source.at(x0 + x, y0 + y)]);
    let filled = inpaint_full(&mut crop, &crop_mask, &crop_source, radius_px, order);
    for y in 0..ch {
        for x in 0..cw {
            if crop_mask.at(x, y) {
                img.set_pixel(x0 + x, y0 + y, crop.pixel(x, y));
            }
        }
    }
    Ok(filled)
}

/// [`inpaint`] on the whole image.
fn inpaint_full(img: &mut Rgb8, mask: &Mask, source: &Mask, radius_px: f64, order: Order) -> usize {
    let mut m = March::new(img, mask, source, order);
    let disc = source_disc(radius_px);
    let mut heap = m.initial_front();
    let mut filled = 0;
    while let Some(Entry(_, k)) = heap.pop() {
        if m.flag[k] == Flag::Known {
            continue;
        }
        m.flag[k] = Flag::Known;
        for q in m.neighbours(k).into_iter().flatten() {
            if m.flag[q] != Flag::Inside {
                continue;
            }
            let tq = solve_t(q, m.w, m.h, &m.t, &m.flag);
            m.t[q] = tq;
            filled += usize::from(m.fill(q, &disc));
            m.flag[q] = Flag::Band;
            heap.push(Entry(tq, q));
        }
    }
    m.write_back(img, mask);
    filled
}

/// The disc of sources: offset (dx, dy) from the pixel to the source, 1 / |d|, 1 / |d|².
fn source_disc(radius_px: f64) -> Vec<(isize, isize, f64, f64)> {
    let r = radius_px.max(1.0);
    let ri = r.ceil() as isize;
    (-ri..=ri)
        .flat_map(|dy| (-ri..=ri).map(move |dx| (dx, dy)))
        .filter_map(|(dx, dy)| {
            let d2 = (dx * dx + dy * dy) as f64;
            (d2 > 0.0 && d2 <= r * r).then(|| (dx, dy, 1.0 / d2.sqrt(), 1.0 / d2))
        })
        .collect()
}

/// The state of one fast march: each pixel's flag, distance T, value and (first order)
/// gradient per channel.
struct March {
    w: usize,
    h: usize,
    order: Order,
    flag: Vec<Flag>,
    t: Vec<f32>,
    val: Vec<[f32; 3]>,
    grad: Vec<[[f64; 2]; 3]>,
}

impl March {
    fn new(img: &Rgb8, mask: &Mask, source: &Mask, order: Order) -> Self {
        let (w, h) = img.size();
        let n = w * h;
        let flag: Vec<Flag> = (0..n)
            .map(|k| {
                if mask.data()[k] {
                    Flag::Inside
                } else if source.data()[k] {
                    Flag::Known
                } else {
                    Flag::Excluded
                }
            })
            .collect();
        let val: Vec<[f32; 3]> = img.data().chunks_exact(3).map(|c| [f32::from(c[0]), f32::from(c[1]), f32::from(c[2])]).collect();
        // Gradient of each readable pixel per channel (first order only): input pixels from
        // their input neighbours, filled pixels from their sources.
        let original = |i: usize| !mask.data()[i] && source.data()[i];
        let mut grad: Vec<[[f64; 2]; 3]> = vec![[[0.0; 2]; 3]; if order == Order::First { n } else { 0 }];
        if order == Order::First {
            for (k, g) in grad.iter_mut().enumerate() {
                if original(k) {
                    *g = std::array::from_fn(|c| gradient(k, w, h, |i| original(i).then_some(val[i][c]), original));
                }
            }
        }
        Self { w, h, order, flag, t: vec![f32::INFINITY; n], val, grad }
    }

    fn neighbours(&self, k: usize) -> [Option<usize>; 4] {
        let (w, h) = (self.w, self.h);
        let (x, y) = (k % w, k / w);
        [(x > 0).then(|| k - 1), (x + 1 < w).then(|| k + 1), (y > 0).then(|| k - w), (y + 1 < h).then(|| k + w)]
    }

    /// The initial front (known pixels next to the region, T = 0); every known pixel gets
    /// T = 0.
    fn initial_front(&mut self) -> BinaryHeap<Entry> {
        let mut heap = BinaryHeap::new();
        for k in 0..self.w * self.h {
            if self.flag[k] == Flag::Known && self.neighbours(k).iter().flatten().any(|&q| self.flag[q] == Flag::Inside) {
                self.flag[k] = Flag::Band;
                self.t[k] = 0.0;
                heap.push(Entry(0.0, k));
            }
        }
        for k in 0..self.w * self.h {
            if self.flag[k] == Flag::Known {
                self.t[k] = 0.0;
            }
        }
        heap
    }

    /// Fills pixel `q` (its T just solved) by the weighted mean of eqs. 3–5 over the known
    /// pixels of the disc; false when none is in reach (the pixel keeps its value).
    fn fill(&mut self, q: usize, disc: &[(isize, isize, f64, f64)]) -> bool {
        let (w, h, tq) = (self.w, self.h, self.t[q]);
        let (qx, qy) = ((q % w) as isize, (q / w) as isize);
        let grad_t = gradient(q, w, h, |i| (self.flag[i] != Flag::Inside && self.flag[i] != Flag::Excluded).then_some(self.t[i]), |_| true);
        let norm = (grad_t[0] * grad_t[0] + grad_t[1] * grad_t[1]).sqrt();
        let nrm = if norm > 0.0 { [grad_t[0] / norm, grad_t[1] / norm] } else { [0.0, 0.0] };
        let mut sum = [0.0f64; 3];
        let mut gsum = [[0.0f64; 2]; 3];
        let mut wsum = 0.0f64;
        for &(dx, dy, inv_len, inv_d2) in disc {
            let (x, y) = (qx + dx, qy + dy);
            if x < 0 || y < 0 || x >= w as isize || y >= h as isize {
                continue;
            }
            let s = y as usize * w + x as usize;
            if !matches!(self.flag[s], Flag::Known | Flag::Band) {
                continue;
            }
            // Vector from the source s to the pixel q.
            let (vx, vy) = (-dx as f64, -dy as f64);
            let dir = ((vx * nrm[0] + vy * nrm[1]) * inv_len).abs().max(1e-6); // eq. 5, dir
            let lev = 1.0 / (1.0 + (f64::from(tq) - f64::from(self.t[s])).abs()); // eq. 5, lev
            let wt = dir * inv_d2 * lev;
            if self.order == Order::First {
                for c in 0..3 {
                    let g = self.grad[s][c];
                    sum[c] += wt * (f64::from(self.val[s][c]) + g[0] * vx + g[1] * vy); // eq. 3
                    gsum[c][0] += wt * g[0];
                    gsum[c][1] += wt * g[1];
                }
            } else {
                for (acc, v) in sum.iter_mut().zip(self.val[s]) {
                    *acc += wt * f64::from(v);
                }
            }
            wsum += wt;
        }
        if wsum <= 0.0 {
            return false;
        }
        self.val[q] = sum.map(|v| (v / wsum).clamp(0.0, 255.0) as f32);
        if self.order == Order::First {
            self.grad[q] = gsum.map(|g| [g[0] / wsum, g[1] / wsum]);
        }
        true
    }

    /// Writes the filled pixels of the mask back into the image.
    fn write_back(&self, img: &mut Rgb8, mask: &Mask) {
        for (k, (px, v)) in img.data_mut().chunks_exact_mut(3).zip(&self.val).enumerate() {
            if mask.data()[k] && self.flag[k] == Flag::Known {
                for (o, c) in px.iter_mut().zip(v) {
                    *o = c.round() as u8;
                }
            }
        }
    }
}

/// The fast-marching update of T at pixel k from its 4-neighbours (Sethian; Telea's `solve`).
fn solve_t(k: usize, w: usize, h: usize, t: &[f32], flag: &[Flag]) -> f32 {
    let (x, y) = (k % w, k / w);
    let known = |i: usize| matches!(flag[i], Flag::Known | Flag::Band);
    let tx = [(x > 0).then(|| k - 1), (x + 1 < w).then(|| k + 1)];
    let ty = [(y > 0).then(|| k - w), (y + 1 < h).then(|| k + w)];
    let mut best = f32::INFINITY;
    for a in tx.into_iter().flatten() {
        for b in ty.into_iter().flatten() {
            best = best.min(solve_pair(known(a).then_some(t[a]), known(b).then_some(t[b])));
        }
    }
    for a in tx.into_iter().chain(ty).flatten() {
        if known(a) {
            best = best.min(t[a] + 1.0);
        }
    }
    best
}

fn solve_pair(a: Option<f32>, b: Option<f32>) -> f32 {
    match (a, b) {
        (Some(t1), Some(t2)) => {
            let d = t1 - t2;
            let r2 = 2.0 - d * d;
            if r2 < 0.0 {
                return t1.min(t2) + 1.0;
            }
            let s = 0.5 * (t1 + t2 + r2.sqrt());
            if s >= t1 && s >= t2 { s } else { t1.min(t2) + 1.0 }
        }
        (Some(t1), None) => t1 + 1.0,
        (None, Some(t2)) => t2 + 1.0,
        (None, None) => f32::INFINITY,
    }
}

/// Central (or one-sided where a neighbour is missing) differences of `value` at pixel k, over
/// the neighbours `ok` allows; 0 along an axis with no usable neighbour.
fn gradient(k: usize, w: usize, h: usize, value: impl Fn(usize) -> Option<f32>, ok: impl Fn(usize) -> bool) -> [f64; 2] {
    let (x, y) = (k % w, k / w);
    let Some(c) = value(k) else { return [0.0, 0.0] };
    let axis = |lo: Option<usize>, hi: Option<usize>| -> f64 {
        let lo = lo.filter(|&i| ok(i)).and_then(&value);
        let hi = hi.filter(|&i| ok(i)).and_then(&value);
        match (lo, hi) {
            (Some(a), Some(b)) => 0.5 * f64::from(b - a),
            (Some(a), None) => f64::from(c - a),
            (None, Some(b)) => f64::from(b - c),
            (None, None) => 0.0,
        }
    };
    [axis((x > 0).then(|| k - 1), (x + 1 < w).then(|| k + 1)), axis((y > 0).then(|| k - w), (y + 1 < h).then(|| k + w))]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_source_disc_holds_the_lattice_points_of_the_radius_but_the_centre() {
        // Lattice points with 0 < |d|² ≤ r²: 4 at r = 1, 8 at r = 1.5, 12 at r = 2, 28 at r = 3.
        for (r, n) in [(0.5, 4), (1.0, 4), (1.5, 8), (2.0, 12), (3.0, 28)] {
            let disc = source_disc(r);
            assert_eq!(disc.len(), n, "radius {r}");
            for (dx, dy, inv_len, inv_d2) in disc {
                let d2 = (dx * dx + dy * dy) as f64;
                assert!((inv_d2 - 1.0 / d2).abs() < 1e-12 && (inv_len - 1.0 / d2.sqrt()).abs() < 1e-12);
            }
        }
    }

    fn disc(w: usize, h: usize, cx: f64, cy: f64, r: f64) -> Mask {
        Mask::from_fn(w, h, |x, y| [(x as f64 - cx).powi(2) + (y as f64 - cy).powi(2) <= r * r])
    }

    #[test]
    fn a_linear_ramp_is_reproduced_inside_the_mask() {
        let (w, h) = (64, 48);
        let ramp = |x: usize, y: usize| [(2 * x + y) as u8, (x + 3 * y) as u8, 100];
        let truth = Rgb8::from_fn(w, h, ramp);
        let mut img = truth.clone();
        let mask = disc(w, h, 30.0, 22.0, 7.5);
        for k in 0..w * h {
            if mask.data()[k] {
                img.data_mut()[3 * k..3 * k + 3].copy_from_slice(&[255, 255, 255]);
            }
        }
        let holed = img.clone();
        let filled = inpaint(&mut img, &mask, &Mask::filled(w, h, true), 5.0, Order::First).unwrap();
        assert_eq!(filled, mask.data().iter().filter(|m| **m).count());
        let worst = img.data().iter().zip(truth.data()).map(|(a, b)| (i16::from(*a) - i16::from(*b)).abs()).max().unwrap();
        assert!(worst <= 1, "first order: ramp error {worst} levels");
        // The weighted mean bends a ramp (it sees only one side near the rim) but stays within
        // the ramp's range over the inpainting radius: slope 3 levels/px × 5 px.
        let mut zero = holed;
        inpaint(&mut zero, &mask, &Mask::filled(w, h, true), 5.0, Order::Zero).unwrap();
        let worst = zero.data().iter().zip(truth.data()).map(|(a, b)| (i16::from(*a) - i16::from(*b)).abs()).max().unwrap();
        assert!((2..=15).contains(&worst), "zero order: ramp error {worst} levels");
    }

    #[test]
    fn pixels_outside_the_mask_are_untouched_and_excluded_pixels_not_read() {
        let (w, h) = (40, 40);
        let mut img = Rgb8::from_fn(w, h, |x, y| [(x * 3) as u8, (y * 5) as u8, ((x + y) % 200) as u8]);
        // A black outside (x < 8) that must not bleed in.
        for y in 0..h {
            for x in 0..8 {
                img.set_pixel(x, y, [0, 0, 0]);
            }
        }
        let before = img.clone();
        let mask = disc(w, h, 12.0, 20.0, 4.0);
        let source = Mask::from_fn(w, h, |x, _| [x >= 8]);
        inpaint(&mut img, &mask, &source, 5.0, Order::First).unwrap();
        for k in 0..w * h {
            if !mask.data()[k] {
                assert_eq!(&img.data()[3 * k..3 * k + 3], &before.data()[3 * k..3 * k + 3]);
            } else {
                // Red ramps 3 per column from x = 8 on; a black bleed would pull it to ~0.
                let x = k % w;
                assert!((i32::from(img.data()[3 * k]) - 3 * x as i32).abs() <= 2, "pixel {k}: {}", img.data()[3 * k]);
            }
        }
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        let mut img = Rgb8::filled(3, 5, 7);
        assert_eq!(inpaint(&mut img, &Mask::filled(3, 5, true), &Mask::filled(3, 5, true), 5.0, Order::First).unwrap(), 0, "nothing to read from");
        assert_eq!(img, Rgb8::filled(3, 5, 7));
        let mut empty = Rgb8::new(0, 0);
        assert_eq!(inpaint(&mut empty, &Mask::new(0, 0), &Mask::new(0, 0), 5.0, Order::Zero).unwrap(), 0);
        assert!(inpaint(&mut img, &Mask::new(2, 2), &Mask::new(3, 5), 5.0, Order::Zero).is_err(), "size mismatch");
    }
}
