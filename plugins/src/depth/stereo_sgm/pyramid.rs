//! The image operations of the coarse-to-fine matcher ([`super::matcher`]): halving a view,
//! bringing a coarse disparity map up a level, smoothing it into a prior, and warping the right
//! view by that prior.

use rayon::prelude::*;

use super::sgm::INVALID;
use super::zncc::Plane;

/// A view halved: 2×2 means; a coarse pixel is invalid when any of its four is.
pub fn halve(v: &Plane) -> Plane {
    let (w, cw, ch) = (v.width, v.width / 2, v.height / 2);
    let (gray, invalid) = (0..cw * ch)
        .into_par_iter()
        .map(|k| {
            let (x, y) = (2 * (k % cw), 2 * (k / cw));
            let four = [y * w + x, y * w + x + 1, (y + 1) * w + x, (y + 1) * w + x + 1];
            (four.iter().map(|p| v.gray[*p]).sum::<f32>() / 4.0, four.iter().any(|p| v.invalid[*p]))
        })
        .unzip();
    Plane { gray, invalid, width: cw, height: ch }
}

/// A disparity map of `cw × ch` brought to `w × h` (twice the size, or one more for an odd
/// size): each pixel takes its coarse pixel's disparity, doubled.
pub fn double(coarse: &[f32], cw: usize, ch: usize, w: usize, h: usize) -> Vec<f32> {
    (0..w * h)
        .into_par_iter()
        .map(|k| {
            let (cx, cy) = (((k % w) / 2).min(cw - 1), ((k / w) / 2).min(ch - 1));
            let d = coarse[cy * cw + cx];
            if d > INVALID { 2.0 * d } else { INVALID }
        })
        .collect()
}

/// A Gaussian of `sigma_px` over the valid disparities, normalised by the valid weight
/// (normalised convolution, Knutsson & Westin 1993): smooths a level's steps and noise and fills
/// holes narrower than about `2 sigma_px`; [`INVALID`] where no valid disparity is near.
///
/// Each pass runs row by row in parallel and, within a row, tap by tap over the whole row, so
/// that the inner loop is a contiguous multiply-add the compiler vectorises; every pixel still
/// sums its taps in the same order.
pub fn smooth(d: &[f32], w: usize, h: usize, sigma_px: f32) -> Vec<f32> {
    let r = (2.5 * sigma_px).ceil() as isize;
    let k: Vec<f32> = (-r..=r).map(|i| (-(i * i) as f32 / (2.0 * sigma_px * sigma_px)).exp()).collect();
    if w == 0 || h == 0 {
        return Vec::new();
    }
    let wts: Vec<f32> = d.iter().map(|v| f32::from(u8::from(*v > INVALID))).collect();
    let vals: Vec<f32> = d.iter().zip(&wts).map(|(v, w)| v * w).collect();
    // Along the rows: out[x] += k_i · in[x + i] for the taps that stay inside the row.
    let horizontal = |src: &[f32]| -> Vec<f32> {
        let mut out = vec![0f32; w * h];
        out.par_chunks_mut(w).zip(src.par_chunks(w)).for_each(|(o, row)| {
            for (i, kw) in (-r..=r).zip(&k) {
                let (lo, hi) = ((-i).max(0) as usize, (w as isize - i.max(0)).max(0) as usize);
                if lo >= hi {
                    continue;
                }
                let shifted = &row[(lo as isize + i) as usize..(hi as isize + i) as usize];
                for (a, b) in o[lo..hi].iter_mut().zip(shifted) {
                    *a += kw * b;
                }
            }
        });
        out
    };
    // Down the columns: row y of the output sums the rows y + i inside the image.
    let vertical = |src: &[f32]| -> Vec<f32> {
        let mut out = vec![0f32; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, o)| {
            for (i, kw) in (-r..=r).zip(&k) {
                let yy = y as isize + i;
                if yy < 0 || yy >= h as isize {
                    continue;
                }
                for (a, b) in o.iter_mut().zip(&src[yy as usize * w..(yy as usize + 1) * w]) {
                    *a += kw * b;
                }
            }
        });
        out
    };
    let (v1, w1) = rayon::join(|| horizontal(&vals), || horizontal(&wts));
    let (v2, w2) = rayon::join(|| vertical(&v1), || vertical(&w1));
    v2.iter().zip(&w2).map(|(v, w)| if *w > 0.05 { v / w } else { INVALID }).collect()
}

/// The right view warped by `prior − shift_px`: `out(x, y) = right(x − prior(x, y) + shift_px, y)`
/// (linear along the row), so that the disparity `prior − shift_px + k` is searched over
/// `k ∈ [0, 2 shift_px]` with fronto-parallel windows: the warp has taken out the wall's slant.
/// Invalid where the prior is, or where the sample leaves the right view.
pub fn warp_right(right: &Plane, prior: &[f32], shift_px: f32) -> Plane {
    let w = right.width;
    let (gray, invalid) = (0..right.gray.len())
        .into_par_iter()
        .map(|p| {
            let (x, y) = (p % w, p / w);
            let u = x as f32 - prior[p] + shift_px;
            if prior[p] <= INVALID || u < 0.0 || u > (w - 1) as f32 || w < 2 {
                return (0.0, true);
            }
            let x0 = (u.floor() as usize).min(w - 2);
            let f = u - x0 as f32;
            let (a, b) = (y * w + x0, y * w + x0 + 1);
            ((1.0 - f) * right.gray[a] + f * right.gray[b], right.invalid[a] || right.invalid[b])
        })
        .unzip();
    Plane { gray, invalid, width: w, height: right.height }
}

/// The same plane mirrored left to right.
pub fn mirror<T: Copy>(v: &[T], w: usize) -> Vec<T> {
    v.chunks(w).flat_map(|row| row.iter().rev().copied()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The normalised convolution pixel by pixel, each pass summing its taps in order.
    fn smooth_by_definition(d: &[f32], w: usize, h: usize, sigma_px: f32) -> Vec<f32> {
        let r = (2.5 * sigma_px).ceil() as isize;
        let k: Vec<f32> = (-r..=r).map(|i| (-(i * i) as f32 / (2.0 * sigma_px * sigma_px)).exp()).collect();
        let pass = |vals: &[f32], wts: &[f32], horizontal: bool| -> (Vec<f32>, Vec<f32>) {
            (0..w * h)
                .map(|p| {
                    let (x, y) = ((p % w) as isize, (p / w) as isize);
                    let (mut s, mut ws) = (0.0, 0.0);
                    for (i, kw) in (-r..=r).zip(&k) {
                        let (xx, yy) = if horizontal { (x + i, y) } else { (x, y + i) };
                        if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
                            continue;
                        }
                        let q = (yy * w as isize + xx) as usize;
                        s += kw * vals[q];
                        ws += kw * wts[q];
                    }
                    (s, ws)
                })
                .unzip()
        };
        let wts: Vec<f32> = d.iter().map(|v| f32::from(u8::from(*v > INVALID))).collect();
        let vals: Vec<f32> = d.iter().zip(&wts).map(|(v, w)| v * w).collect();
        let (v1, w1) = pass(&vals, &wts, true);
        let (v2, w2) = pass(&v1, &w1, false);
        v2.iter().zip(&w2).map(|(v, w)| if *w > 0.05 { v / w } else { INVALID }).collect()
    }

    #[test]
    fn the_row_wise_smoothing_is_the_normalised_convolution_to_the_bit() {
        for (w, h, sigma) in [(37, 23, 2.0f32), (16, 40, 4.0), (5, 3, 8.0), (1, 9, 1.0)] {
            // A slanted disparity with holes (a third of the pixels, in runs).
            let d: Vec<f32> = (0..w * h).map(|p| if (p * 7 / 5) % 3 == 0 { INVALID } else { 10.0 + 0.3 * (p % w) as f32 - 0.1 * (p / w) as f32 }).collect();
            let (got, want) = (smooth(&d, w, h, sigma), smooth_by_definition(&d, w, h, sigma));
            assert_eq!(got.len(), want.len());
            for (p, (a, b)) in got.iter().zip(&want).enumerate() {
                assert_eq!(a.to_bits(), b.to_bits(), "{w}×{h}, σ {sigma}, pixel {p}: {a} against {b}");
            }
        }
    }
}
