//! Semi-global aggregation of a matching-cost volume (Hirschmüller 2008, IEEE TPAMI 30(2),
//! Eq. 13: `L_r(p, d) = C(p, d) + min(L_r(p−r, d), L_r(p−r, d±1) + P1, min_k L_r(p−r, k) + P2)
//! − min_k L_r(p−r, k)`, summed over 4 or 8 path directions), winner-takes-all with a parabola
//! through the three costs around the minimum, the left–right check against the right image's
//! disparities read from the same aggregated volume (Sec. 3.5), and speckle filtering
//! (connected regions of similar disparity smaller than a size are removed). Disparities are
//! `d = x_left − x_right ≥ 0`; a volume index `k` is the disparity `d_min + k`. The volume is
//! `w × h × n`, row-major then disparity, in the cost units of [`super::zncc`].

use rayon::prelude::*;

/// Marks an invalid disparity.
pub const INVALID: f32 = -1.0;

/// What SGM is asked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SgmSettings {
    /// Smallest disparity searched, pixels.
    pub d_min: usize,
    /// Largest disparity searched, pixels.
    pub d_max: usize,
    /// Penalty of a disparity step of one pixel, cost units.
    pub p1: u16,
    /// Penalty of a larger step, cost units.
    pub p2: u16,
    /// 4 or 8 aggregation paths.
    pub paths: usize,
    /// Largest left–right disagreement kept, pixels.
    pub lr_max_px: f32,
    /// The best aggregated cost must be below every other (more than a pixel away) by this
    /// share (OpenCV's `uniquenessRatio` / 100).
    pub uniqueness: f32,
}

impl SgmSettings {
    /// The number of disparities searched.
    pub fn count(&self) -> usize {
        self.d_max - self.d_min + 1
    }
}

/// One path's step (Eq. 13) from the previous pixel's path costs `prev` into `out`.
#[inline(always)]
fn step(c: &[u16], prev: &[u16], out: &mut [u16], p1: u16, p2: u16) {
    let n = c.len();
    let prev_min = prev.iter().copied().min().unwrap_or(0);
    for k in 0..n {
        let mut best = prev[k];
        if k > 0 {
            best = best.min(prev[k - 1].saturating_add(p1));
        }
        if k + 1 < n {
            best = best.min(prev[k + 1].saturating_add(p1));
        }
        best = best.min(prev_min.saturating_add(p2));
        out[k] = c[k] + best - prev_min;
    }
}

/// [`step`] for `N` disparities known at compile time (the refinements' 5): unrolled.
#[inline(always)]
fn step_fixed<const N: usize>(c: &[u16; N], prev: &[u16; N], out: &mut [u16; N], p1: u16, p2: u16) {
    let prev_min = prev.iter().copied().fold(u16::MAX, u16::min);
    let floor = prev_min.saturating_add(p2);
    for k in 0..N {
        let left = if k > 0 { prev[k - 1].saturating_add(p1) } else { u16::MAX };
        let right = if k + 1 < N { prev[k + 1].saturating_add(p1) } else { u16::MAX };
        out[k] = c[k] + prev[k].min(left).min(right).min(floor) - prev_min;
    }
}

/// One path step for `n` disparities: the unrolled form for 5 (±2 px of residual), else the
/// general one.
#[inline(always)]
fn step_any(c: &[u16], prev: &[u16], out: &mut [u16], p1: u16, p2: u16) {
    match (<&[u16; 5]>::try_from(c), <&[u16; 5]>::try_from(prev), <&mut [u16; 5]>::try_from(&mut *out)) {
        (Ok(c), Ok(prev), Ok(out)) => step_fixed(c, prev, out, p1, p2),
        _ => step(c, prev, out, p1, p2),
    }
}

/// The path directions (dx, dy): 4 or 8 of them.
fn directions(paths: usize) -> Vec<(isize, isize)> {
    let four = [(1, 0), (-1, 0), (0, 1), (0, -1)];
    let diagonals = [(1, 1), (-1, 1), (1, -1), (-1, -1)];
    four.into_iter().chain(diagonals.into_iter().filter(|_| paths >= 8)).collect()
}

/// The sum of the path costs over every direction, `w × h × n` (saturating u16: 8 paths of at
/// most the worst cost plus P2 each; every term is non-negative, so the order of the sum does
/// not change it). Two sweeps, in parallel: down the image for the paths that come from above
/// (and the left-to-right path), up it for the others; each sweep steps all its paths one
/// row at a time and adds them into its running total while the row is in cache.
pub fn aggregate(c: &[u16], w: usize, h: usize, s: &SgmSettings) -> Vec<u16> {
    let n = s.count();
    let (down, up): (Vec<_>, Vec<_>) = directions(s.paths).into_iter().partition(|&(dx, dy)| dy > 0 || (dy == 0 && dx > 0));
    let (mut total, other) = rayon::join(|| sweep(c, (w, h, n), &down, s, true), || sweep(c, (w, h, n), &up, s, false));
    total.iter_mut().zip(&other).for_each(|(t, v)| *t = t.saturating_add(*v));
    total
}

/// The summed path costs of the directions `dirs`, all of which visit the rows downward
/// (`downward`) or all upward: each pixel's predecessor `p − r` comes first.
///
/// The paths that come from the row before (`dy ≠ 0`) work on the row disparity-major (`k`,
/// then `x`: [`step_row`]), where a disparity's neighbours and a pixel's smallest cost are
/// whole-row operations the compiler vectorises; the path along the row works on it as stored.
fn sweep(c: &[u16], (w, h, n): (usize, usize, usize), dirs: &[(isize, isize)], s: &SgmSettings, downward: bool) -> Vec<u16> {
    let mut total = vec![0u16; w * h * n];
    let mut prev: Vec<Vec<u16>> = dirs.iter().map(|_| vec![0u16; w * n]).collect();
    let mut row: Vec<Vec<u16>> = dirs.iter().map(|_| vec![0u16; w * n]).collect();
    let (mut cells_kx, mut sums_kx, mut along) = (vec![0u16; w * n], vec![0u16; w * n], vec![0u16; w * n]);
    let mut smallest = vec![0u16; w];
    let ys: Vec<usize> = if downward { (0..h).collect() } else { (0..h).rev().collect() };
    for (j, &y) in ys.iter().enumerate() {
        let (cells, sums) = (&c[y * w * n..(y + 1) * w * n], &mut total[y * w * n..(y + 1) * w * n]);
        transpose(cells, &mut cells_kx, w, n);
        sums_kx.fill(0);
        for (i, &(dx, dy)) in dirs.iter().enumerate() {
            let out = &mut row[i];
            if dy == 0 {
                step_along_row(cells, &mut along, (w, n, dx), s);
                for (t, v) in sums.iter_mut().zip(&along) {
                    *t = t.saturating_add(*v);
                }
                continue;
            }
            if j == 0 {
                out.copy_from_slice(&cells_kx);
            } else {
                step_row(&cells_kx, &prev[i], out, (w, n, dx), s, &mut smallest);
            }
            for (t, v) in sums_kx.iter_mut().zip(out.iter()) {
                *t = t.saturating_add(*v);
            }
        }
        // Back to pixel-major, added to what the path along the row left there.
        for (k, from) in sums_kx.chunks_exact(w.max(1)).enumerate() {
            for (cell, v) in sums.chunks_exact_mut(n.max(1)).zip(from) {
                cell[k] = cell[k].saturating_add(*v);
            }
        }
        std::mem::swap(&mut prev, &mut row);
    }
    total
}

/// A row of `w` pixels × `n` disparities from pixel-major (`x * n + k`) to disparity-major
/// (`k * w + x`).
fn transpose(src: &[u16], dst: &mut [u16], w: usize, n: usize) {
    for (k, to) in dst.chunks_exact_mut(w.max(1)).take(n).enumerate() {
        for (d, cell) in to.iter_mut().zip(src.chunks_exact(n.max(1))) {
            *d = cell[k];
        }
    }
}

/// One step (Eq. 13) of a path that comes from the row before (`dy ≠ 0`, direction `dx`) for
/// a whole row, disparity-major (`k * w + x`): pixel `x` steps from pixel `x − dx` of `prev`;
/// a pixel without a predecessor (outside the image) starts from its own costs. The same
/// arithmetic as [`step`], pixel by pixel.
fn step_row(c: &[u16], prev: &[u16], out: &mut [u16], (w, n, dx): (usize, usize, isize), s: &SgmSettings, smallest: &mut [u16]) {
    // Each predecessor's smallest cost, min over its disparities.
    smallest.fill(u16::MAX);
    for k in 0..n {
        for (m, v) in smallest.iter_mut().zip(&prev[k * w..(k + 1) * w]) {
            *m = (*m).min(*v);
        }
    }
    // Pixels x in [lo, hi) read x − dx in [lo − dx, hi − dx).
    let shift = dx.unsigned_abs().min(w);
    let (lo, hi) = if dx > 0 { (shift, w) } else { (0, w - shift) };
    let src = |x: usize| if dx > 0 { x - shift } else { x + shift };
    for k in 0..n {
        let (c_k, out_k) = (&c[k * w..(k + 1) * w], &mut out[k * w..(k + 1) * w]);
        // Outside [lo, hi) there is no predecessor.
        out_k[..lo].copy_from_slice(&c_k[..lo]);
        out_k[hi..].copy_from_slice(&c_k[hi..]);
        if lo >= hi {
            continue;
        }
        let at = |kk: usize| &prev[kk * w + src(lo)..kk * w + src(lo) + (hi - lo)];
        let here = at(k);
        let m = &smallest[src(lo)..src(lo) + (hi - lo)];
        // Disparities k − 1 and k + 1 where they exist (none below the first, above the last).
        let below = if k > 0 { Some(at(k - 1)) } else { None };
        let above = if k + 1 < n { Some(at(k + 1)) } else { None };
        let (c_in, o) = (&c_k[lo..hi], &mut out_k[lo..hi]);
        let (p1, p2) = (s.p1, s.p2);
        match (below, above) {
            (Some(b), Some(a)) => {
                for (((((o, c), h), b), a), m) in o.iter_mut().zip(c_in).zip(here).zip(b).zip(a).zip(m) {
                    *o = c + (*h).min(b.saturating_add(p1)).min(a.saturating_add(p1)).min(m.saturating_add(p2)) - m;
                }
            }
            (Some(b), None) => {
                for ((((o, c), h), b), m) in o.iter_mut().zip(c_in).zip(here).zip(b).zip(m) {
                    *o = c + (*h).min(b.saturating_add(p1)).min(m.saturating_add(p2)) - m;
                }
            }
            (None, Some(a)) => {
                for ((((o, c), h), a), m) in o.iter_mut().zip(c_in).zip(here).zip(a).zip(m) {
                    *o = c + (*h).min(a.saturating_add(p1)).min(m.saturating_add(p2)) - m;
                }
            }
            (None, None) => {
                for (((o, c), h), m) in o.iter_mut().zip(c_in).zip(here).zip(m) {
                    *o = c + (*h).min(m.saturating_add(p2)) - m;
                }
            }
        }
    }
}

/// A path along the row (`dy = 0`, direction `dx`): each pixel steps from the one visited just
/// before; the first starts from its own costs.
fn step_along_row(cells: &[u16], out: &mut [u16], (w, n, dx): (usize, usize, isize), s: &SgmSettings) {
    for i in 0..w {
        // The i-th pixel visited: from the left for dx ≥ 0, from the right otherwise.
        let x = if dx >= 0 { i } else { w - 1 - i };
        let cell = &cells[x * n..(x + 1) * n];
        if i == 0 {
            out[x * n..(x + 1) * n].copy_from_slice(cell);
            continue;
        }
        // The predecessor and this pixel are neighbours in `out`.
        let p = (x as isize - dx) as usize;
        let (prev, here) = if p < x {
            let (a, b) = out.split_at_mut(x * n);
            (&a[p * n..(p + 1) * n], &mut b[..n])
        } else {
            let (a, b) = out.split_at_mut(p * n);
            (&b[..n], &mut a[x * n..(x + 1) * n])
        };
        step_any(cell, prev, here, s.p1, s.p2);
    }
}

/// The index of the smallest of `v` and its parabola offset in [−0.5, 0.5]; `None` when another
/// minimum, more than one index away, is within `uniqueness` of it.
pub fn argmin_subpixel(v: &[u16], uniqueness: f32) -> Option<(usize, f32)> {
    let (k, best) = v.iter().enumerate().min_by_key(|(_, c)| **c).map(|(k, c)| (k, *c))?;
    let rival = v.iter().enumerate().filter(|(j, _)| j.abs_diff(k) > 1).map(|(_, c)| *c).min();
    if rival.is_some_and(|r| f32::from(r) * (1.0 - uniqueness) <= f32::from(best)) {
        return None;
    }
    if k == 0 || k + 1 >= v.len() {
        return Some((k, 0.0));
    }
    let (a, b, c) = (f32::from(v[k - 1]), f32::from(v[k]), f32::from(v[k + 1]));
    let den = a - 2.0 * b + c;
    Some((k, if den > 0.0 { (0.5 * (a - c) / den).clamp(-0.5, 0.5) } else { 0.0 }))
}

/// The left disparity per pixel (winner-takes-all, sub-pixel, unique), checked against the
/// right image's (Sec. 3.5); [`INVALID`] where none, where the left pixel is invalid, and where
/// the match lands on an invalid right pixel (outside the right view: an occluded band).
pub fn disparities(total: &[u16], left_invalid: &[bool], right_invalid: &[bool], w: usize, h: usize, s: &SgmSettings) -> Vec<f32> {
    let n = s.count();
    let left: Vec<f32> = (0..w * h)
        .into_par_iter()
        .map(|p| {
            if left_invalid[p] {
                return INVALID;
            }
            let Some((k, off)) = argmin_subpixel(&total[p * n..(p + 1) * n], s.uniqueness) else { return INVALID };
            let d = s.d_min + k;
            if d > p % w || right_invalid[p - d] {
                return INVALID;
            }
            d as f32 + off
        })
        .collect();
    // The right image's disparity at (x, y): the d minimising S(x + d, y, d).
    let right: Vec<f32> = (0..w * h)
        .into_par_iter()
        .map(|p| {
            let (x, y) = (p % w, p / w);
            let best = (0..n).filter(|k| x + s.d_min + k < w).min_by_key(|k| total[(y * w + x + s.d_min + k) * n + k]);
            best.map_or(INVALID, |k| (s.d_min + k) as f32)
        })
        .collect();
    (0..w * h)
        .map(|p| {
            let d = left[p];
            let xr = (p % w) as f32 - d;
            if d < 0.0 || xr < 0.0 {
                return INVALID;
            }
            let q = p - (p % w) + xr.round() as usize;
            if right[q] >= 0.0 && (right[q] - d).abs() <= s.lr_max_px { d } else { INVALID }
        })
        .collect()
}

/// Removes connected regions (4-neighbours within 1 px of disparity) of fewer than `min_px`.
pub fn remove_speckles(d: &mut [f32], w: usize, h: usize, min_px: usize) {
    let mut label = vec![usize::MAX; w * h];
    let mut stack = Vec::new();
    let mut region = Vec::new();
    for start in 0..w * h {
        if d[start] < 0.0 || label[start] != usize::MAX {
            continue;
        }
        region.clear();
        stack.push(start);
        label[start] = start;
        while let Some(p) = stack.pop() {
            region.push(p);
            let (x, y) = (p % w, p / w);
            let near = [(x > 0).then(|| p - 1), (x + 1 < w).then(|| p + 1), (y > 0).then(|| p - w), (y + 1 < h).then(|| p + w)];
            for q in near.into_iter().flatten() {
                if d[q] >= 0.0 && label[q] == usize::MAX && (d[q] - d[p]).abs() <= 1.0 {
                    label[q] = start;
                    stack.push(q);
                }
            }
        }
        if region.len() < min_px {
            for &p in &region {
                d[p] = INVALID;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eq. 13 as written: every direction on its own, pixel by pixel in path order, each from
    /// its predecessor's costs (none outside the image), summed with saturation.
    fn aggregate_by_definition(c: &[u16], w: usize, h: usize, s: &SgmSettings) -> Vec<u16> {
        let n = s.count();
        let mut total = vec![0u16; w * h * n];
        for (dx, dy) in directions(s.paths) {
            let mut l = vec![0u16; w * h * n];
            let xs: Vec<usize> = if dx >= 0 { (0..w).collect() } else { (0..w).rev().collect() };
            let ys: Vec<usize> = if dy >= 0 { (0..h).collect() } else { (0..h).rev().collect() };
            for &y in &ys {
                for &x in &xs {
                    let (px, py) = (x as isize - dx, y as isize - dy);
                    let p = y * w + x;
                    if px < 0 || py < 0 || px >= w as isize || py >= h as isize {
                        l[p * n..(p + 1) * n].copy_from_slice(&c[p * n..(p + 1) * n]);
                        continue;
                    }
                    let q = py as usize * w + px as usize;
                    let prev = l[q * n..(q + 1) * n].to_vec();
                    step(&c[p * n..(p + 1) * n], &prev, &mut l[p * n..(p + 1) * n], s.p1, s.p2);
                }
            }
            total.iter_mut().zip(&l).for_each(|(t, v)| *t = t.saturating_add(*v));
        }
        total
    }

    #[test]
    fn the_row_sweeps_give_eq_13_path_by_path() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for (w, h, n, paths) in [(13, 9, 5, 8), (13, 9, 5, 4), (7, 11, 21, 8), (6, 5, 1, 8), (9, 4, 2, 4), (1, 6, 5, 8), (8, 1, 3, 8)] {
            let c: Vec<u16> = (0..w * h * n).map(|_| (next() % 1025) as u16).collect();
            let s = SgmSettings { d_min: 0, d_max: n - 1, p1: 37, p2: 211, paths, lr_max_px: 1.0, uniqueness: 0.0 };
            assert_eq!(aggregate(&c, w, h, &s), aggregate_by_definition(&c, w, h, &s), "{w}×{h}, {n} disparities, {paths} paths");
        }
    }
}
