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
/// most the worst cost plus P2 each). The directions run in parallel, each one sequentially
/// into its own volume.
pub fn aggregate(c: &[u16], w: usize, h: usize, s: &SgmSettings) -> Vec<u16> {
    let n = s.count();
    directions(s.paths)
        .into_par_iter()
        .map(|dir| path_costs(c, w, h, n, dir, s))
        .reduce_with(|mut a, b| {
            a.iter_mut().zip(&b).for_each(|(t, v)| *t = t.saturating_add(*v));
            a
        })
        .unwrap_or_else(|| vec![0; w * h * n])
}

/// The path costs along one direction: the pixels are visited so that each one's predecessor
/// `p − r` comes first (rows in the path's vertical order, each row in its horizontal order).
fn path_costs(c: &[u16], w: usize, h: usize, n: usize, (dx, dy): (isize, isize), s: &SgmSettings) -> Vec<u16> {
    let mut l = vec![0u16; w * h * n];
    let xs: Vec<usize> = if dx >= 0 { (0..w).collect() } else { (0..w).rev().collect() };
    let ys: Vec<usize> = if dy >= 0 { (0..h).collect() } else { (0..h).rev().collect() };
    let mut prev_row = vec![0u16; w * n];
    let mut row = vec![0u16; w * n];
    let mut last = vec![0u16; n];
    for (j, &y) in ys.iter().enumerate() {
        for (i, &x) in xs.iter().enumerate() {
            let cell = &c[(y * w + x) * n..(y * w + x + 1) * n];
            let out = &mut row[x * n..(x + 1) * n];
            // The predecessor (x − dx, y − dy): the pixel visited just before (dy = 0) or one
            // in the row before.
            let px = x as isize - dx;
            let prev: Option<&[u16]> = if dy == 0 {
                (i > 0).then_some(&last[..])
            } else {
                (j > 0 && px >= 0 && (px as usize) < w).then(|| &prev_row[px as usize * n..(px as usize + 1) * n])
            };
            match prev {
                Some(prev) => step_any(cell, prev, out, s.p1, s.p2),
                None => out.copy_from_slice(cell),
            }
            last.copy_from_slice(out);
        }
        l[y * w * n..(y + 1) * w * n].copy_from_slice(&row);
        std::mem::swap(&mut prev_row, &mut row);
    }
    l
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
