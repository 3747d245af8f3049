//! One Gauss-Newton system of the joint energy, Eq. (4): `E = E_icp + w_rgb E_rgb`, each term
//! normalised by its noise scale and robustified with Huber weights. Rows are accumulated in
//! parallel and summed in row order, so the result is deterministic.

use capsule_slam_framework::Iso3;
use nalgebra::{Matrix6, Vector3, Vector6};
use rayon::prelude::*;

use super::frames::Level;
use super::relight::Relighter;
use super::terms::{correlated_count, huber, icp_jacobian, icp_residual, nearest_pixel, projected_gradient, residual_sigma, twist_row};
use crate::common::maps::{normal, vertex};
use crate::common::pyramid::Bilinear;
use capsule_slam_framework::GrayF32;

/// Weights and gates of one system.
#[derive(Debug, Clone, Copy)]
pub struct Weights {
    /// Weight of the photometric term (the paper's w_rgb).
    pub w_rgb: f64,
    /// Noise scale of the point-to-plane residual, metres.
    pub sigma_icp_m: f64,
    /// Noise scale of the intensity residual, intensity in [0, 1].
    pub sigma_rgb: f64,
    /// Huber threshold, in noise scales.
    pub huber_k: f64,
    /// ICP correspondence distance gate, metres (the least: see `gate_sigmas`).
    pub icp_gate_m: f64,
    /// The ICP and photometric occlusion gates widen to this many σ of the residual where the
    /// depth is noisier than the fixed gates allow.
    pub gate_sigmas: f64,
    /// Cosine of the ICP normal-angle gate.
    pub icp_cos_gate: f64,
    /// Photometric occlusion gate on depth, metres.
    pub rgb_depth_gate_m: f64,
    /// Smallest reference gradient used by the photometric term, intensity per pixel.
    pub rgb_min_gradient: f64,
    /// Warp the photometric term's live points at the inverse-variance mean of their depth and
    /// the model's ([`blended_point`]) where the frame carries a σ.
    pub rgb_model_depth: bool,
    /// k in the photometric row's variance `σ_rgb² + (k ∇I · ∂u/∂ε · σ_ε)²` (the depth's error
    /// carried through the warp); 0: `σ_rgb²` alone.
    pub rgb_flow_sigma_scale: f64,
}

/// The upper triangle of a symmetric 6×6 matrix, row by row (21 values): rank-one updates cost
/// 21 multiply-adds instead of 36.
#[derive(Debug, Clone, Copy)]
pub struct Upper6([f64; 21]);

impl Upper6 {
    fn zero() -> Self {
        Self([0.0; 21])
    }

    /// `self += w · j jᵀ`.
    #[inline]
    fn add_outer(&mut self, j: &Vector6<f64>, w: f64) {
        let mut k = 0;
        for r in 0..6 {
            let wr = w * j[r];
            for c in r..6 {
                self.0[k] += wr * j[c];
                k += 1;
            }
        }
    }

    fn add(&mut self, o: &Upper6) {
        for (a, b) in self.0.iter_mut().zip(o.0.iter()) {
            *a += b;
        }
    }

    /// The full symmetric matrix.
    pub fn full(&self) -> Matrix6<f64> {
        let mut m = Matrix6::zeros();
        let mut k = 0;
        for r in 0..6 {
            for c in r..6 {
                m[(r, c)] = self.0[k];
                m[(c, r)] = self.0[k];
                k += 1;
            }
        }
        m
    }
}

/// An accumulated normal-equation system and its statistics.
#[derive(Debug, Clone, Copy)]
pub struct System {
    /// JᵀWJ (upper triangle).
    pub a: Upper6,
    /// JᵀWr.
    pub b: Vector6<f64>,
    /// ICP inliers.
    pub icp_n: usize,
    /// Sum of squared ICP residuals, m².
    pub icp_sse: f64,
    /// Sum of squared ICP residuals over their σ² (χ²).
    pub icp_chi2: f64,
    /// Photometric pixels used.
    pub rgb_n: usize,
    /// Sum of squared intensity residuals.
    pub rgb_sse: f64,
    /// Live pixels with a valid vertex and normal.
    pub live_n: usize,
}

impl System {
    fn zero() -> Self {
        Self { a: Upper6::zero(), b: Vector6::zeros(), icp_n: 0, icp_sse: 0.0, icp_chi2: 0.0, rgb_n: 0, rgb_sse: 0.0, live_n: 0 }
    }

    fn add(&mut self, o: &System) {
        self.a.add(&o.a);
        self.b += o.b;
        self.icp_n += o.icp_n;
        self.icp_sse += o.icp_sse;
        self.icp_chi2 += o.icp_chi2;
        self.rgb_n += o.rgb_n;
        self.rgb_sse += o.rgb_sse;
        self.live_n += o.live_n;
    }

    /// Adds one residual `r` with row `j` and weight `wt`.
    #[inline]
    fn add_row(&mut self, j: &Vector6<f64>, r: f64, wt: f64) {
        self.a.add_outer(j, wt);
        self.b += wt * j * r;
    }

    /// The Gauss-Newton step `δ = −A⁻¹ b`, if A is positive definite.
    pub fn step(&self) -> Option<Vector6<f64>> {
        self.a.full().cholesky().map(|c| -c.solve(&self.b))
    }

    /// The Gauss-Newton step measured in the system's own information, `δᵀAδ = bᵀA⁻¹b`: how
    /// many σ² of evidence the data hold against the pose the system was built at; infinite
    /// where A is not positive definite.
    pub fn step_chi2(&self) -> f64 {
        self.step().map_or(f64::INFINITY, |d| self.chi2_of(&d))
    }

    /// A step `d` measured in the system's own information, `dᵀAd`, σ².
    pub fn chi2_of(&self, d: &Vector6<f64>) -> f64 {
        d.dot(&(self.a.full() * d))
    }

    /// RMS of the ICP residuals, metres.
    pub fn icp_rms(&self) -> f64 {
        if self.icp_n == 0 { f64::INFINITY } else { (self.icp_sse / self.icp_n as f64).sqrt() }
    }

    /// RMS of the ICP residuals in units of their own σ.
    pub fn icp_rms_sigmas(&self) -> f64 {
        if self.icp_n == 0 { f64::INFINITY } else { (self.icp_chi2 / self.icp_n as f64).sqrt() }
    }
}

/// The relighter and the live level's albedo ([`Relighter::live_albedo`]) that relight the
/// photometric term, or none.
pub type Relight<'a> = Option<(&'a Relighter<'a>, &'a GrayF32)>;

/// What one system is accumulated over: the live level, the ICP `reference` (in the reference
/// camera frame) and the photometric reference `photo`, in the reference camera frame or, with
/// `t_photo_ref`, in a keyframe's (`keyframe.rs`), the relighting, and every `stride`-th live
/// pixel.
#[derive(Clone, Copy)]
pub struct Inputs<'a> {
    pub live: &'a Level,
    pub reference: &'a Level,
    pub photo: &'a Level,
    /// The photometric reference's camera ← the reference camera (none: the same camera).
    pub t_photo_ref: Option<Iso3>,
    pub light: Relight<'a>,
    pub stride: usize,
    /// A second photometric reference (the previous frame beside a keyframe,
    /// `RgbReference::KeyframeAndPrevious`): a second row per live pixel against it, in the
    /// reference camera or carried by its transform as `t_photo_ref`.
    pub second: Option<(&'a Level, Option<Iso3>)>,
}

/// Accumulates the system of `t_ref_live`.
///
/// With the capsule's light model (`light`, `relight.rs`) the photometric term compares the
/// reference with the live intensity relit where the point stands in the reference view; the
/// relit value is held fixed in the Jacobian (iteratively reweighted, as the depth of the
/// residual is). A depth error correlated over ℓ pixels is counted once per block: the
/// (ℓ / stride)² residuals of a block carry one residual's information, so the live σ² in the
/// weight's variance is multiplied by that count; the gates and the loss test keep each pixel's
/// own σ.
pub fn accumulate(inp: &Inputs<'_>, t_ref_live: &Iso3, w: &Weights) -> System {
    let (lw, lh) = inp.live.depth.size();
    let stride = inp.stride.max(1);
    let correlated = correlated_count(inp.live.sigma_correlation_px, stride as f64);
    // The photometric references' cameras ← the live camera, once per system.
    let photo_live = |t_photo_ref: Option<Iso3>| t_photo_ref.map_or(*t_ref_live, |t| t * t_ref_live);
    let t_photo_live = [photo_live(inp.t_photo_ref), photo_live(inp.second.and_then(|(_, t)| t))];
    let rows: Vec<System> = (0..lh)
        .into_par_iter()
        .step_by(stride)
        .map(|y| {
            let mut sys = System::zero();
            for x in (0..lw).step_by(stride) {
                pixel(inp, (x, y), (t_ref_live, &t_photo_live), (w, correlated), &mut sys);
            }
            sys
        })
        .collect();
    let mut total = System::zero();
    for r in &rows {
        total.add(r);
    }
    total
}

/// The ICP and photometric rows of live pixel `(x, y)`; `t_photo_live` the photometric
/// references' cameras ← the live camera (the second's for `inp.second`).
fn pixel(inp: &Inputs<'_>, (x, y): (usize, usize), (t_ref_live, t_photo_live): (&Iso3, &[Iso3; 2]), (w, correlated): (&Weights, f64), sys: &mut System) {
    let (live, reference, cam) = (inp.live, inp.reference, &inp.reference.cam);
    let Some(v) = vertex(&live.vertices, x, y) else { return };
    let s = (t_ref_live * nalgebra::Point3::from(v.cast::<f64>())).coords;
    if s.z <= 0.0 {
        return;
    }
    let near = nearest_pixel(cam, &s, reference.depth.size());
    let (inside, (ui, vi)) = (near.is_some(), near.map_or((0, 0), |(_, p)| p));
    // The residual's σ: the registration floor, the live depth's own σ and the reference's (the
    // model's, fused per surfel); its weight counts a correlated block of live residuals as one
    // (`correlated`).
    let sigma_live = live.sigma.as_ref().map_or(0.0, |m| f64::from(m.at(x, y)));
    let sigma_ref = if inside { reference.sigma.as_ref().map_or(0.0, |m| f64::from(m.at(ui, vi))) } else { 0.0 };
    let sigma = residual_sigma(w.sigma_icp_m, sigma_live, sigma_ref);
    let sigma_w = (w.sigma_icp_m * w.sigma_icp_m + sigma_live * sigma_live * correlated + sigma_ref * sigma_ref).sqrt();
    let live_normal = normal(&live.normals, x, y);
    // The live point the photometric term warps, moved along its ray (`rgb_model_depth`).
    let mut blended: Option<(Vector3<f64>, f64)> = None;
    if let Some(nl) = live_normal {
        sys.live_n += 1;
        if inside && let (Some(d), Some(n)) = (vertex(&reference.vertices, ui, vi), normal(&reference.normals, ui, vi)) {
            let (d, n): (Vector3<f64>, Vector3<f64>) = (d.cast(), n.cast());
            let nl_ref = t_ref_live.rotation * nl.cast::<f64>();
            if (s - d).norm() <= w.icp_gate_m.max(w.gate_sigmas * sigma) && nl_ref.dot(&n) >= w.icp_cos_gate {
                let r = icp_residual(&s, &d, &n);
                let j = icp_jacobian(&s, &n);
                let wt = huber(r / sigma, w.huber_k) / (sigma_w * sigma_w);
                sys.add_row(&j, r, wt);
                sys.icp_n += 1;
                sys.icp_sse += r * r;
                sys.icp_chi2 += (r / sigma) * (r / sigma);
                if w.rgb_model_depth && live.sigma.is_some() {
                    blended = blended_point(&v.cast::<f64>(), t_ref_live, (&d, &n), (sigma_live, sigma_ref));
                }
            }
        }
    }
    // An intensity of 0 marks a pixel without one (`frames::live`: near a highlight).
    if w.w_rgb <= 0.0 || live.gray.at(x, y) <= 0.0 {
        return;
    }
    if inp.t_photo_ref.is_none() && !inside {
        return;
    }
    // A point moved by λ along the ray: the light's fall-off (∝ 1/distance², the light beside the
    // lens) makes its albedo λ² the live one's. Projected again; the Jacobian holds λ fixed.
    // The warped depth's relative σ: the live depth's, or that of its blend with the model's.
    // (Read only by the flow term, `rgb_flow_sigma_scale` > 0.)
    let sigma_rel = if w.rgb_flow_sigma_scale > 0.0 {
        let sigma_warp = match blended {
            Some(_) if sigma_live > 0.0 && sigma_ref > 0.0 => sigma_live * sigma_ref / (sigma_live * sigma_live + sigma_ref * sigma_ref).sqrt(),
            _ => sigma_live,
        };
        sigma_warp / f64::from(v.z)
    } else {
        0.0
    };
    let point = blended.unwrap_or((s, 1.0));
    photometric_row(inp, (x, y), point, &t_photo_live[0], (w, sigma_live, sigma_rel), sys);
    if let Some((photo, t_photo_ref)) = inp.second {
        photometric_row(&Inputs { photo, t_photo_ref, second: None, ..*inp }, (x, y), point, &t_photo_live[1], (w, sigma_live, sigma_rel), sys);
    }
}

/// The photometric row of live pixel `(x, y)` whose point `s` (reference frame; moved by `λ`
/// along its ray where blended) is sampled and relit in the photometric reference: in the
/// reference camera, or carried into a keyframe's by `inp.t_photo_ref` (`t_photo_live`: the
/// photometric reference's camera ← the live camera). Against a keyframe the
/// row is its projected gradient brought back to the reference frame, `a_ref = R_photo_refᵀ
/// a_photo`, so that the increment stays the one on `t_ref_live` (a fixed transform composed on
/// the left).
fn photometric_row(
    inp: &Inputs<'_>,
    (x, y): (usize, usize),
    (s, lambda): (Vector3<f64>, f64),
    t_photo_live: &Iso3,
    (w, sigma_live, sigma_rel): (&Weights, f64, f64),
    sys: &mut System,
) {
    let (live, photo) = (inp.live, inp.photo);
    let cam = &photo.cam;
    let p = inp.t_photo_ref.map_or(s, |t| (t * nalgebra::Point3::from(s)).coords);
    if p.z <= 0.0 {
        return;
    }
    let Some(((uf, vf), (ui, vi))) = nearest_pixel(cam, &p, photo.depth.size()) else { return };
    let gate_m = w.rgb_depth_gate_m.max(w.gate_sigmas * sigma_live);
    let Some((ir, gx, gy)) = reference_sample(photo, (ui, vi), (uf, vf), p.z, gate_m, w.rgb_min_gradient) else { return };
    let predicted = match inp.light {
        None => f64::from(live.gray.at(x, y)),
        Some((l, albedo)) => {
            let lit =
                normal(&live.normals, x, y).and_then(|nl| l.relit(&live.cam, albedo.at(x, y) * (lambda * lambda) as f32, &nl, t_photo_live, (uf, vf), &p));
            match lit {
                Some(i) => i,
                None => return,
            }
        }
    };
    let r = f64::from(ir) - predicted;
    let a = projected_gradient(&p, (gx, gy), cam.fx, cam.fy);
    let j = twist_row(&s, &inp.t_photo_ref.map_or(a, |t| t.rotation.inverse() * a));
    // A pixel resampled from fewer source pixels (an undistortion's stretched ring) shares its
    // noise and interpolation error with its neighbours: counted once (`Level::share`).
    let flow = if w.rgb_flow_sigma_scale > 0.0 { a.dot(&t_photo_live.translation.vector) * sigma_rel } else { 0.0 };
    let (sigma, var) = photometric_sigma(w, flow);
    let wt = live.share_at(x, y) * w.w_rgb * huber(r / sigma, w.huber_k) / var;
    sys.add_row(&j, r, wt);
    sys.rgb_n += 1;
    sys.rgb_sse += r * r;
}

/// σ and σ² of a photometric residual whose depth-carried intensity error is `flow_sigma`
/// (`∇I · ∂u/∂ε · σ_ε`, before the scale k): `σ² = σ_rgb² + (k · flow_sigma)²`; with k = 0,
/// `σ_rgb` and `σ_rgb · σ_rgb` as they were.
pub fn photometric_sigma(w: &Weights, flow_sigma: f64) -> (f64, f64) {
    if w.rgb_flow_sigma_scale <= 0.0 {
        return (w.sigma_rgb, w.sigma_rgb * w.sigma_rgb);
    }
    let flow = w.rgb_flow_sigma_scale * flow_sigma;
    let var = w.sigma_rgb * w.sigma_rgb + flow * flow;
    (var.sqrt(), var)
}

/// The live vertex `v` moved along its ray to the inverse-variance mean of its own depth (σ
/// `sigma_live_m`) and the model's tangent plane at its ICP match (`d`, `n`, σ `sigma_ref_m`),
/// in the reference frame, with the ray's scale `λ` (1: the live depth). `None` where the ray
/// runs along the plane or the frame and model carry no σ.
pub fn blended_point(
    v: &Vector3<f64>,
    t_ref_live: &Iso3,
    (d, n): (&Vector3<f64>, &Vector3<f64>),
    (sigma_live_m, sigma_ref_m): (f64, f64),
) -> Option<(Vector3<f64>, f64)> {
    let rv = t_ref_live.rotation * v;
    let den = n.dot(&rv);
    let (vl, vm) = (sigma_live_m * sigma_live_m, sigma_ref_m * sigma_ref_m);
    if den.abs() < 1e-9 || vl + vm <= 0.0 {
        return None;
    }
    let on_plane = n.dot(&(d - t_ref_live.translation.vector)) / den;
    let lambda = 1.0 + vl / (vl + vm) * (on_plane - 1.0);
    (lambda > 0.0).then(|| (lambda * rv + t_ref_live.translation.vector, lambda))
}

/// The photometric reference at `(uf, vf)` (nearest pixel `(ui, vi)`): intensity and gradient,
/// if the reference sees the same surface there (depth within `gate_m` of `z`), all four
/// bilinear corners are valid, and the gradient reaches `min_gradient`.
fn reference_sample(photo: &Level, (ui, vi): (usize, usize), (uf, vf): (f64, f64), z: f64, gate_m: f64, min_gradient: f64) -> Option<(f32, f64, f64)> {
    let zr = photo.depth.at(ui, vi);
    if zr <= 0.0 || (f64::from(zr) - z).abs() > gate_m {
        return None;
    }
    let (rw, rh) = photo.depth.size();
    let bl = Bilinear::at(rw, rh, uf, vf)?;
    if bl.corners(&photo.gray).contains(&0.0) {
        return None;
    }
    let (ir, gx, gy) = (bl.sample(&photo.gray), f64::from(bl.sample(&photo.gx)), f64::from(bl.sample(&photo.gy)));
    (gx * gx + gy * gy >= min_gradient * min_gradient).then_some((ir, gx, gy))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_blended_point_weighs_live_and_model_depth_by_their_variances() {
        // The model's plane z = 0.05 in the reference frame, a live point at 0.052 on the optical
        // axis of a camera 1 mm to the side.
        let t = Iso3::translation(0.001, 0.0, 0.0);
        let v = Vector3::new(0.0, 0.0, 0.052);
        let (d, n) = (Vector3::new(0.0, 0.0, 0.05), Vector3::new(0.0, 0.0, -1.0));
        let z = |s: (f64, f64)| blended_point(&v, &t, (&d, &n), s).map(|(p, _)| p);
        let on_ray = |p: Vector3<f64>| (p.x - 0.001).abs() < 1e-15 && p.y.abs() < 1e-15;
        let (half, model, live) = (z((1e-3, 1e-3)).unwrap(), z((1e-3, 0.0)).unwrap(), z((0.0, 1e-3)).unwrap());
        assert!(on_ray(half) && on_ray(model) && on_ray(live));
        assert!((half.z - 0.051).abs() < 1e-12 && (model.z - 0.05).abs() < 1e-12 && (live.z - 0.052).abs() < 1e-12);
        let (_, lambda) = blended_point(&v, &t, (&d, &n), (2e-3, 1e-3)).unwrap();
        assert!((lambda * 0.052 - (0.8 * 0.05 + 0.2 * 0.052)).abs() < 1e-12, "σ 2 mm against 1 mm: 4:1 for the model");
        assert_eq!(z((0.0, 0.0)), None);
        let along = Vector3::new(1.0, 0.0, 0.0);
        assert_eq!(blended_point(&v, &t, (&d, &along), (1e-3, 1e-3)), None, "a ray in the plane");
    }

    #[test]
    fn upper_triangle_accumulation_equals_the_full_outer_product() {
        let (j1, j2) = (Vector6::new(1.0, -2.0, 0.5, 3.0, 0.1, -0.7), Vector6::new(0.3, 0.2, -1.0, 0.0, 2.0, 1.5));
        let mut u = Upper6::zero();
        u.add_outer(&j1, 2.0);
        u.add_outer(&j2, 0.5);
        let full = 2.0 * j1 * j1.transpose() + 0.5 * j2 * j2.transpose();
        assert!((u.full() - full).norm() < 1e-12);
    }
}
