//! Coarse-to-fine stereo matching by warping, with semi-global aggregation at every level.
//!
//! A capsule's wall is smooth, weakly textured, noisy and strongly slanted (a tube seen along its
//! axis). Matched at full resolution over the whole disparity range, wide windows are biased by
//! the slant and narrow ones by the noise (on the phantom pair, 14 % of pixels more than a pixel
//! off whatever the window). So, as in coarse-to-fine optical flow and DIS/BDIS (Kroeger et al.,
//! ECCV 2016; Song et al., MICCAI 2022):
//! 1. both views are halved `levels` times (each coarse pixel the mean of `4^L`, the noise `2^L`
//!    times lower); at the top, masked ZNCC ([`super::zncc`]) + SGM ([`super::sgm`]) over the
//!    whole range, with its left–right check;
//! 2. down every level, the disparity is smoothed into a prior, the right view warped by it
//!    ([`pyramid::warp_right`]), and only the residual `±search_px` searched with ZNCC + SGM: the
//!    warp has taken out the slant, so the window is unbiased and can be wide;
//! 3. at full resolution both directions (the left view against the right, and the mirrored pair
//!    for the right's own disparities) are matched and checked against each other; the
//!    consistent disparities, smoothed over their holes, are the prior of `passes − 1` further
//!    refinements, which recover regions whose coarse prior was off by more than the search.

use rayon::prelude::*;

use super::pyramid::{self, mirror};
use super::sgm::{self, INVALID, SgmSettings};
use super::zncc::{self, Plane};

/// What the matcher is asked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchSettings {
    /// Full-resolution disparity range, SGM penalties and paths, the left–right tolerance and
    /// the top level's uniqueness.
    pub sgm: SgmSettings,
    /// How many times the views are halved before the first match.
    pub levels: usize,
    /// ZNCC window radius at the top level, pixels of that level.
    pub top_radius: usize,
    /// ZNCC window radius of every refinement, pixels of its level.
    pub radius: usize,
    /// σ of the full-resolution intensities, 8-bit levels (halved at every level up).
    pub noise_levels: f32,
    /// Residual disparities searched around the prior: `±search_px`.
    pub search_px: usize,
    /// σ of the Gaussian smoothing a level's disparities into the next level's prior, pixels.
    pub smooth_px: f32,
    /// Refinements at `check_level` with both directions checked (at least 1: the descent).
    pub passes: usize,
    /// The level of the checked passes (0: full resolution; 1: half, then one checked
    /// refinement per level down).
    pub check_level: usize,
    /// σ of the smoothing that fills the holes of a checked pass for the next, pixels.
    pub fill_px: f32,
    /// Connected regions (within 1 px of disparity) smaller than this are removed at the end.
    pub speckle_px: usize,
}

/// The left view's disparities (pixels, [`INVALID`] where none) of a rectified pair.
pub fn match_pair(left: &Plane, right: &Plane, s: &MatchSettings) -> Vec<f32> {
    let w = left.width;
    let mirrored_left = Plane { gray: mirror(&right.gray, w), invalid: mirror(&right.invalid, w), ..right.clone() };
    let mirrored_right = Plane { gray: mirror(&left.gray, w), invalid: mirror(&left.invalid, w), ..left.clone() };
    let (pl, pr) = rayon::join(|| pyramid_of(left, right, s.levels), || pyramid_of(&mirrored_left, &mirrored_right, s.levels));
    let cl = s.check_level.min(s.levels);
    let (mut dl, mut dr) = rayon::join(|| one_way(&pl, cl, s), || one_way(&pr, cl, s));
    // Checked passes at the check level, then down to the full resolution with both directions.
    for pass in 1..s.passes.max(1) + cl {
        let level = if pass < s.passes.max(1) { cl } else { cl - (pass - s.passes.max(1)) - 1 };
        let up = if pass < s.passes.max(1) { 0 } else { 1 };
        let (l_here, l_from) = (&pl[level].0, &pl[level + up].0);
        let (lw, lh, fw, fh) = (l_here.width, l_here.height, l_from.width, l_from.height);
        let fill = s.fill_px / (1usize << (level + up)) as f32;
        // The right direction's disparities in the right view's own frame (unmirrored).
        let dr_right = mirror(&dr, fw);
        let prior = |a: &[f32], b: &[f32], sign: f32| {
            let f = pyramid::smooth(&checked(a, b, fw, s.sgm.lr_max_px, sign), fw, fh, fill);
            if up == 1 { pyramid::smooth(&pyramid::double(&f, fw, fh, lw, lh), lw, lh, 1.0) } else { f }
        };
        let mut prior_l = prior(&dl, &dr_right, 1.0);
        let mut prior_r = mirror(&prior(&dr_right, &dl, -1.0), lw);
        mask(&mut prior_l, &pl[level].0.invalid);
        mask(&mut prior_r, &pr[level].0.invalid);
        let noise = s.noise_levels / (1usize << level) as f32;
        (dl, dr) = rayon::join(|| refine(&pl[level].0, &pl[level].1, &prior_l, s, noise), || refine(&pr[level].0, &pr[level].1, &prior_r, s, noise));
    }
    let mut out = checked(&dl, &mirror(&dr, w), w, s.sgm.lr_max_px, 1.0);
    let (lo, hi) = (s.sgm.d_min as f32, s.sgm.d_max as f32);
    out.iter_mut().filter(|d| **d < lo || **d > hi).for_each(|d| *d = INVALID);
    sgm::remove_speckles(&mut out, w, left.height, s.speckle_px);
    out
}

/// The views halved `levels` times: index 0 is the full resolution.
fn pyramid_of(left: &Plane, right: &Plane, levels: usize) -> Vec<(Plane, Plane)> {
    let mut pyr = vec![(left.clone(), right.clone())];
    for _ in 0..levels {
        let (l, r) = &pyr[pyr.len() - 1];
        let next = (pyramid::halve(l), pyramid::halve(r));
        pyr.push(next);
    }
    pyr
}

/// The disparities of `a` that the other direction's `b` confirms within `tol` pixels: `a` is
/// the left's (`sign` 1: its match is at `x − d` in `b`) or the right's (`sign` −1: at `x + d`).
fn checked(a: &[f32], b: &[f32], w: usize, tol: f32, sign: f32) -> Vec<f32> {
    a.par_iter()
        .enumerate()
        .map(|(p, d)| {
            let x = (p % w) as f32 - sign * d;
            if *d <= INVALID || x < 0.0 || x > (w - 1) as f32 {
                return INVALID;
            }
            let q = p - p % w + x.round() as usize;
            if b[q] > INVALID && (b[q] - d).abs() <= tol { *d } else { INVALID }
        })
        .collect()
}

fn mask(d: &mut [f32], invalid: &[bool]) {
    d.iter_mut().zip(invalid).filter(|(_, i)| **i).for_each(|(d, _)| *d = INVALID);
}

/// One direction down the pyramid `pyr` to level `stop`: the top level over the whole range,
/// then every level refined around the one above.
fn one_way(pyr: &[(Plane, Plane)], stop: usize, s: &MatchSettings) -> Vec<f32> {
    let levels = pyr.len() - 1;
    let scale = 1usize << levels;
    let (tl, tr) = &pyr[levels];
    let top = SgmSettings { d_min: s.sgm.d_min / scale, d_max: s.sgm.d_max.div_ceil(scale), ..s.sgm };
    let volume = zncc::costs(tl, tr, top.d_min, top.d_max, s.top_radius, s.noise_levels / scale as f32);
    let total = sgm::aggregate(&volume, tl.width, tl.height, &top);
    let mut d = sgm::disparities(&total, &tl.invalid, &tr.invalid, tl.width, tl.height, &top);
    for level in (stop..levels).rev() {
        let (up, (l, r)) = (&pyr[level + 1].0, &pyr[level]);
        let coarse = pyramid::smooth(&d, up.width, up.height, s.smooth_px);
        let mut prior = pyramid::smooth(&pyramid::double(&coarse, up.width, up.height, l.width, l.height), l.width, l.height, 1.0);
        mask(&mut prior, &l.invalid);
        d = refine(l, r, &prior, s, s.noise_levels / (1usize << level) as f32);
    }
    d
}

/// The disparities within `±search_px` of `prior`: the right view warped by the prior, ZNCC
/// over the residual planes, SGM, winner-takes-all with a parabola. [`INVALID`] where the
/// prior is, where the best residual is at the edge of the search (the prior was too far off)
/// or where the window cannot be matched.
fn refine(left: &Plane, right: &Plane, prior: &[f32], s: &MatchSettings, noise_levels: f32) -> Vec<f32> {
    let (w, h) = (left.width, left.height);
    let shift = s.search_px as f32;
    let warped = pyramid::warp_right(right, prior, shift);
    let rs = SgmSettings { d_min: 0, d_max: 2 * s.search_px, ..s.sgm };
    let n = rs.count();
    let volume = zncc::costs(left, &warped, 0, rs.d_max, s.radius, noise_levels);
    let total = sgm::aggregate(&volume, w, h, &rs);
    (0..w * h)
        .into_par_iter()
        .map(|p| {
            if prior[p] <= INVALID || left.invalid[p] {
                return INVALID;
            }
            match sgm::argmin_subpixel(&total[p * n..(p + 1) * n], 0.0) {
                Some((k, off)) if k > 0 && k + 1 < n && volume[p * n + k] < zncc::WORST => prior[p] - shift + k as f32 + off,
                _ => INVALID,
            }
        })
        .collect()
}
