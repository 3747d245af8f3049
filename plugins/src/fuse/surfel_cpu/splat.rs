//! Rendering surfels into a camera: the index map (each surfel a point, for association; nearest
//! wins) and the splatted prediction (each surfel a disc, ray–disc intersection per pixel, an
//! ε-z-buffer picks the disc, and the pixel gets its depth's σ). Both resolve their tests with
//! minima and maxima over (key, index), atomic ones for the index map and per band of rows for
//! the splat, so they are parallel and deterministic.

use std::sync::atomic::{AtomicU64, Ordering};

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::{Iso3, ModelView, Surfel};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::fuse::surfel_params::SurfelParams;
use crate::fuse::surfel_rules::Layer;

const EMPTY: u64 = u64::MAX;

fn pack(depth_m: f32, idx: usize) -> u64 {
    (u64::from(depth_m.to_bits()) << 32) | idx as u64
}

fn unpack(v: u64) -> (f32, usize) {
    (f32::from_bits(((v >> 32) & 0x7FFF_FFFF) as u32), (v & 0xFFFF_FFFF) as usize)
}

/// The model as points: per pixel the nearest surfel's index (of the first [`Layer`] that
/// reaches it) and its camera-frame position and normal.
pub struct IndexMap {
    /// Width.
    pub width: usize,
    /// Surfel index per pixel (`u32::MAX` = empty).
    pub index: Vec<u32>,
    /// Camera-frame position per pixel.
    pub p_cam: Vec<Point3<f32>>,
    /// Camera-frame normal per pixel.
    pub n_cam: Vec<Vector3<f32>>,
}

impl IndexMap {
    /// Renders the surfels to which `layer` gives a [`Layer`] as 1-pixel points seen from
    /// `t_world_cam`: per pixel the nearest of the first layer that reaches it.
    pub fn render(surfels: &[Surfel], layer: impl Fn(&Surfel) -> Option<Layer> + Sync, cam: &PinholeCamera, t_world_cam: &Iso3, max_depth_m: f32) -> Self {
        let (w, h) = (cam.width, cam.height);
        let zbuf: Vec<AtomicU64> = (0..w * h).map(|_| AtomicU64::new(EMPTY)).collect();
        let t_cam_world = t_world_cam.inverse().cast::<f32>();
        surfels.par_iter().enumerate().for_each(|(i, s)| {
            let Some(layer) = layer(s) else { return };
            let p = t_cam_world * s.position_m;
            if p.z <= 0.0 || p.z > max_depth_m {
                return;
            }
            let u = (cam.fx as f32 * p.x / p.z + cam.cx as f32).round();
            let v = (cam.fy as f32 * p.y / p.z + cam.cy as f32).round();
            if u < 0.0 || v < 0.0 || u >= w as f32 || v >= h as f32 {
                return;
            }
            // A positive depth's bits stay below 2³¹: the top bit orders the layers.
            let behind = if layer == Layer::Behind { 1u64 << 63 } else { 0 };
            zbuf[v as usize * w + u as usize].fetch_min(behind | pack(p.z, i), Ordering::Relaxed);
        });
        let mut index = vec![u32::MAX; w * h];
        let mut p_cam = vec![Point3::origin(); w * h];
        let mut n_cam = vec![Vector3::zeros(); w * h];
        (index.par_iter_mut(), p_cam.par_iter_mut(), n_cam.par_iter_mut(), zbuf.par_iter()).into_par_iter().for_each(|(index, p, n, z)| {
            let v = z.load(Ordering::Relaxed);
            if v != EMPTY {
                let (_, i) = unpack(v);
                *index = i as u32;
                *p = t_cam_world * surfels[i].position_m;
                *n = t_cam_world.rotation * surfels[i].normal;
            }
        });
        Self { width: w, index, p_cam, n_cam }
    }
}

/// How a prediction is splatted: its depth limits and ε in metres along the camera's z axis,
/// and the confidence at which the ε-z-buffer stops preferring one disc over another.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatDepths {
    /// Intersections at or nearer than this are ignored.
    pub min_m: f32,
    /// Intersections beyond this are ignored.
    pub max_m: f32,
    /// The ε of the ε-z-buffer: discs within this of the nearest at a pixel are one surface.
    pub blend_m: f32,
    /// The confidence from which a surfel counts as stable (`stable_confidence`).
    pub stable: f32,
}

impl SplatDepths {
    /// The limits a map's parameters give.
    pub fn of(params: &SurfelParams) -> Self {
        Self { min_m: params.min_depth_m, max_m: params.max_depth_m, blend_m: params.splat_blend_depth_m, stable: params.stable_confidence }
    }
}

/// The confidence the ε-z-buffer compares: capped at `depths.stable`, except at ε = 0, which
/// stays ElasticFusion's z-test exactly (ties: the most confident); `fuse.wgsl` the same.
fn capped(confidence: f32, depths: &SplatDepths) -> f32 {
    if depths.blend_m > 0.0 { confidence.min(depths.stable) } else { confidence }
}

/// A confidence as a key whose unsigned order is the float order (negative values flipped),
/// so that an atomic maximum picks the most confident; `fuse.wgsl`'s `conf_key` is the same.
fn conf_key(confidence: f32) -> u32 {
    let b = confidence.to_bits();
    if b >> 31 == 1 { !b } else { b | 0x8000_0000 }
}

/// One disc in the camera: its centre, normal and radius, and the pixel box it can cover.
struct Disc {
    p: Vector3<f32>,
    n: Vector3<f32>,
    np: f32,
    r2: f32,
    x: (i64, i64),
    y: (i64, i64),
}

/// The pixels whose centres the disc (centre `p`, unit normal `n`, radius `r_m`, camera frame)
/// can cover: the projection of its axis-aligned bounding box (half-extent `r·√(1 − n_i²)` per
/// axis; the nearest depth at least `min_m`, where hits start), whose extremes of x/z and y/z
/// lie at its corners; capped at 12 pixels from the rounded centre; clipped to the image.
/// Conservative: every pixel [`Disc::hit`] accepts is inside (a margin of 10⁻³ px for rounding).
fn pixel_box(p: &Vector3<f32>, n: &Vector3<f32>, r_m: f32, cam: &PinholeCamera, min_m: f32) -> ((i64, i64), (i64, i64)) {
    let e = n.map(|c| r_m * (1.0 - c * c).max(0.0).sqrt());
    let (z_lo, z_hi) = ((p.z - e.z).max(min_m.max(1e-6)), (p.z + e.z).max(min_m.max(1e-6)));
    let span = |c: f32, e: f32, f: f64, centre: f64, size: usize| {
        let (f, centre) = (f as f32, centre as f32);
        let ends = [(c - e) / z_lo, (c - e) / z_hi, (c + e) / z_lo, (c + e) / z_hi];
        let lo = ends.iter().fold(f32::INFINITY, |a, b| a.min(*b)) * f + centre;
        let hi = ends.iter().fold(f32::NEG_INFINITY, |a, b| a.max(*b)) * f + centre;
        let mid = (f * c / p.z + centre).round() as i64;
        let first = ((lo - 1e-3).ceil() as i64).max(mid - 12).max(0);
        let last = ((hi + 1e-3).floor() as i64).min(mid + 12).min(size as i64 - 1);
        (first, last)
    };
    (span(p.x, e.x, cam.fx, cam.cx, cam.width), span(p.y, e.y, cam.fy, cam.cy, cam.height))
}

impl Disc {
    /// The disc of `s` seen from `t_cam_world`, or `None` when its centre is outside the depth
    /// range.
    fn new(s: &Surfel, t_cam_world: &nalgebra::Isometry3<f32>, cam: &PinholeCamera, depths: &SplatDepths) -> Option<Self> {
        let p = t_cam_world * s.position_m;
        if p.z <= depths.min_m || p.z > depths.max_m {
            return None;
        }
        let n = t_cam_world.rotation * s.normal;
        let (x, y) = pixel_box(&p.coords, &n, s.radius_m, cam, depths.min_m);
        Some(Self { p: p.coords, n, np: n.dot(&p.coords), r2: s.radius_m * s.radius_m, x, y })
    }

    /// Depth of the intersection of pixel (x, y)'s ray with the disc, if it hits within range.
    fn hit(&self, x: i64, y: i64, rays: &Rays, depths: &SplatDepths) -> Option<f32> {
        // Ray through the pixel centre, z = 1; plane n·(X − p) = 0.
        let d = Vector3::new(rays.x[x as usize], rays.y[y as usize], 1.0);
        let nd = self.n.dot(&d);
        if nd.abs() < 1e-6 {
            return None;
        }
        let t = self.np / nd;
        (t > depths.min_m && t <= depths.max_m && (d * t - self.p).norm_squared() <= self.r2).then_some(t)
    }
}

/// The rays through the pixel centres at z = 1, `(x − cx) / fx` per column and `(y − cy) / fy`
/// per row (f32), computed once per render instead of per pixel and disc.
struct Rays {
    x: Vec<f32>,
    y: Vec<f32>,
}

impl Rays {
    fn new(cam: &PinholeCamera) -> Self {
        let ray = |i: usize, c: f64, f: f64| (i as f32 - c as f32) / f as f32;
        Self { x: (0..cam.width).map(|x| ray(x, cam.cx, cam.fx)).collect(), y: (0..cam.height).map(|y| ray(y, cam.cy, cam.fy)).collect() }
    }
}

/// Splats the surfels `include` accepts as discs into a prediction seen from `t_world_cam`.
///
/// Each pixel shows one disc, chosen by an ε-z-buffer (Zwicker et al. 2001, "Surface
/// splatting", §5; Pfister et al. 2000): the discs whose ray intersection lies within
/// `depths.blend_m` of the nearest are taken as one surface, and the most confident of them
/// wins, its confidence counted up to `depths.stable` (ElasticFusion's c_stable; ties: the
/// lowest index, the surfel created first); the pixel gets its intersection depth, normal and
/// colour. The cap matters on a moving wall: a surfel fused for hundreds of frames where the
/// wall was is not more the wall than a stable one where it is (uncapped, a rigid tracker lost
/// 66 of 300 frames on a deforming phantom, `docs/results/depth-noise.md`).
/// ElasticFusion's nearest-wins z-test (its `combo_splat.frag`) is `blend_m = 0` (ties: the
/// most confident): with noisy depth it shows the surfels that noise put in front of the wall,
/// a bias toward the camera of about one noise σ that the tracker then follows
/// (`docs/results/depth-noise.md`).
///
/// Parallel passes with atomics (nearest depth; most confident within ε; the winner's
/// intersection), so the result does not depend on the thread schedule.
pub fn predict(surfels: &[Surfel], include: impl Fn(&Surfel) -> bool + Sync, cam: &PinholeCamera, t_world_cam: &Iso3, depths: &SplatDepths) -> ModelView {
    let (w, h) = (cam.width, cam.height);
    let t_cam_world = t_world_cam.inverse().cast::<f32>();
    let disc = |s: &Surfel| if include(s) { Disc::new(s, &t_cam_world, cam, depths) } else { None };
    let winners = most_confident(surfels, disc, cam, depths);
    // The winner's normal and colour beside its intersection depth, row by row in parallel.
    let mut view = ModelView::empty(w, h, *t_world_cam);
    if w == 0 {
        return view;
    }
    let v = &mut view;
    let rows = (v.depth_m.data_mut().par_chunks_mut(w), v.normals_cam.data_mut().par_chunks_mut(3 * w), v.colour.data_mut().par_chunks_mut(3 * w));
    let more = (v.confidence.data_mut().par_chunks_mut(w), v.t0.data_mut().par_chunks_mut(w), v.t.data_mut().par_chunks_mut(w));
    let last = (v.albedo.data_mut().par_chunks_mut(w), v.sigma_m.data_mut().par_chunks_mut(w), winners.par_chunks(w));
    (rows.into_par_iter(), more.into_par_iter(), last.into_par_iter()).into_par_iter().for_each(
        |((depth, normal, colour), (confidence, t0, t), (albedo, sigma, winners))| {
            for (x, &v) in winners.iter().enumerate() {
                if v == EMPTY {
                    continue;
                }
                let (d, i) = unpack(v);
                let s = &surfels[i];
                let n = t_cam_world.rotation * s.normal;
                depth[x] = d;
                normal[3 * x..3 * x + 3].copy_from_slice(&[n.x, n.y, n.z]);
                colour[3 * x..3 * x + 3].copy_from_slice(&s.colour);
                (confidence[x], t0[x], t[x], albedo[x]) = (s.confidence, s.t0, s.t, s.albedo);
                sigma[x] = predicted_sigma(s.sigma_m, s.confidence);
            }
        },
    );
    view
}

/// Image rows per band of the splat: each band is resolved by one thread in its own buffers
/// (16 rows of 320 pixels: 20 KB of nearest depths and 40 KB of keys, within a core's L2).
const BAND_ROWS: usize = 16;

/// A band's buffers, reused by the thread that resolves it: the nearest depth and the best key
/// per pixel, and the hits (pixel in the band, position in the discs, depth).
type BandBuffers = (Vec<f32>, Vec<u64>, Vec<(u32, u32, f32)>);

/// The ε-z-buffer: the nearest intersection per pixel, then the most confident disc within ε
/// of it, the maximum of (capped confidence key << 32 | !index); then the winner's own
/// intersection. Returns (depth bits << 32 | index) per pixel (`EMPTY`: none).
/// `disc` gives a surfel's disc in the camera, if the prediction includes it and it is in range;
/// the discs are made once, in surfel order.
///
/// A sort-middle rasteriser: the discs are binned by the bands of [`BAND_ROWS`] rows their pixel
/// boxes reach (in disc order), and each band is resolved by one thread with plain minima and
/// maxima in its own buffers, its hits kept for the second test in a buffer the thread reuses.
/// Minima and maxima do not depend on the order of the hits, so the result is the same for any
/// schedule, and the same as resolving every pixel over every disc (the oracle test).
fn most_confident(surfels: &[Surfel], disc: impl Fn(&Surfel) -> Option<Disc> + Sync, cam: &PinholeCamera, depths: &SplatDepths) -> Vec<u64> {
    let (w, h) = (cam.width, cam.height);
    let mut out = vec![EMPTY; w * h];
    if w == 0 || h == 0 {
        return out;
    }
    let rays = Rays::new(cam);
    let discs: Vec<(u32, Disc)> = surfels.par_iter().enumerate().filter_map(|(i, s)| disc(s).map(|d| (i as u32, d))).collect();
    // The key's low half is !(position in `discs`): discs are in surfel order, so ties still go
    // to the lowest surfel index.
    let keys: Vec<u64> = discs
        .par_iter()
        .enumerate()
        .map(|(j, (i, _))| (u64::from(conf_key(capped(surfels[*i as usize].confidence, depths))) << 32) | u64::from(!(j as u32)))
        .collect();
    let bands = h.div_ceil(BAND_ROWS);
    let chunk = discs.len().div_ceil(4 * rayon::current_num_threads()).max(1024);
    // Per chunk of discs, per band, the positions in `discs` of the discs whose box reaches it.
    let binned: Vec<Vec<Vec<u32>>> = discs
        .par_chunks(chunk)
        .enumerate()
        .map(|(c, ds)| {
            let mut by_band = vec![Vec::new(); bands];
            for (k, (_, d)) in ds.iter().enumerate() {
                if d.x.0 > d.x.1 || d.y.0 > d.y.1 {
                    continue;
                }
                for band in by_band.iter_mut().take(d.y.1 as usize / BAND_ROWS + 1).skip(d.y.0 as usize / BAND_ROWS) {
                    band.push((c * chunk + k) as u32);
                }
            }
            by_band
        })
        .collect();
    out.par_chunks_mut(w * BAND_ROWS).enumerate().for_each_init(
        || (Vec::new(), Vec::new(), Vec::new()),
        |(front, best, hits): &mut BandBuffers, (band, out)| {
            let (y0, rows) = (band * BAND_ROWS, out.len() / w);
            front.clear();
            front.resize(out.len(), f32::INFINITY);
            best.clear();
            best.resize(out.len(), 0);
            hits.clear();
            for &j in binned.iter().flat_map(|c| &c[band]) {
                let d = &discs[j as usize].1;
                let (ya, yb) = (d.y.0.max(y0 as i64), d.y.1.min((y0 + rows) as i64 - 1));
                for y in ya..=yb {
                    let row = (y as usize - y0) * w;
                    for x in d.x.0..=d.x.1 {
                        if let Some(t) = d.hit(x, y, &rays, depths) {
                            let k = row + x as usize;
                            front[k] = front[k].min(t);
                            hits.push((k as u32, j, t));
                        }
                    }
                }
            }
            for &(k, j, t) in hits.iter() {
                let (k, key) = (k as usize, keys[j as usize]);
                if t <= front[k] + depths.blend_m && key > best[k] {
                    best[k] = key;
                }
            }
            for (k, (o, &key)) in out.iter_mut().zip(best.iter()).enumerate() {
                if key != 0 {
                    let (i, d) = &discs[!(key as u32) as usize];
                    *o = d.hit((k % w) as i64, (y0 + k / w) as i64, &rays, depths).map_or(EMPTY, |t| pack(t, *i as usize));
                }
            }
        },
    );
    out
}

/// σ of a predicted depth: a surfel's σ over √confidence, the σ of the mean of that many
/// measurements (confidence below 1 counts as 1); `fuse.wgsl`'s `resolve` computes the same.
pub fn predicted_sigma(sigma_m: f32, confidence: f32) -> f32 {
    sigma_m / confidence.max(1.0).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// [`most_confident`]'s definition, pixel by pixel over every disc: the nearest hit, the
    /// largest key among the hits within ε of it, that disc's intersection.
    fn most_confident_per_pixel(surfels: &[Surfel], cam: &PinholeCamera, depths: &SplatDepths) -> Vec<u64> {
        let rays = Rays::new(cam);
        let t_cam_world = nalgebra::Isometry3::identity();
        let discs: Vec<(usize, Disc)> = surfels.iter().enumerate().filter_map(|(i, s)| Disc::new(s, &t_cam_world, cam, depths).map(|d| (i, d))).collect();
        let mut out = vec![EMPTY; cam.width * cam.height];
        for (k, o) in out.iter_mut().enumerate() {
            let (x, y) = ((k % cam.width) as i64, (k / cam.width) as i64);
            let inside = |d: &Disc| d.x.0 <= x && x <= d.x.1 && d.y.0 <= y && y <= d.y.1;
            let hits: Vec<(usize, f32)> =
                discs.iter().enumerate().filter(|(_, (_, d))| inside(d)).filter_map(|(j, (_, d))| d.hit(x, y, &rays, depths).map(|t| (j, t))).collect();
            let front = hits.iter().map(|h| h.1).fold(f32::INFINITY, f32::min);
            let key = |j: usize| (u64::from(conf_key(capped(surfels[discs[j].0].confidence, depths))) << 32) | u64::from(!(j as u32));
            if let Some(&(j, t)) = hits.iter().filter(|h| h.1 <= front + depths.blend_m).max_by_key(|h| key(h.0)) {
                *o = pack(t, discs[j].0);
            }
        }
        out
    }

    proptest! {
        /// The banded splat resolves every pixel as its definition does: crowded layers of
        /// discs of every size and confidence, on an image whose height is not a multiple of
        /// the band, with ε = 0 (ElasticFusion's test) and 1 mm.
        #[test]
        fn the_banded_splat_equals_the_splat_resolved_pixel_by_pixel(
            discs in prop::collection::vec((-0.02f32..0.02, -0.02f32..0.02, 0.01f32..0.03, 0.0f32..1.2, 0.0f32..6.3, 0.1f32..1.5, 0.0f32..20.0), 1..400),
            blend_mm in prop_oneof![Just(0.0f32), Just(1.0f32)],
        ) {
            let cam = PinholeCamera::new(45, 37, 30.0, 30.0, 22.0, 18.0);
            let depths = SplatDepths { min_m: 0.002, max_m: 0.25, blend_m: blend_mm * 1e-3, stable: 10.0 };
            let surfels: Vec<Surfel> = discs.iter().map(|&(x, y, z, theta, phi, r_mm, confidence)| Surfel {
                position_m: Point3::new(x, y, z),
                normal: Vector3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos()),
                radius_m: r_mm * 1e-3,
                colour: [0; 3],
                // Whole confidences tie often, so that the lowest index must win.
                confidence: confidence.floor(),
                t0: 0,
                t: 0,
                albedo: 0.0,
                sigma_m: 0.0,
                warp_m: Vector3::zeros(),
            }).collect();
            let banded = most_confident(&surfels, |s| Disc::new(s, &nalgebra::Isometry3::identity(), &cam, &depths), &cam, &depths);
            let oracle = most_confident_per_pixel(&surfels, &cam, &depths);
            let differ = banded.iter().zip(&oracle).filter(|(a, b)| a != b).count();
            let hit = oracle.iter().filter(|&&v| v != EMPTY).count();
            prop_assert!(differ == 0, "{differ} of {} pixels differ ({hit} hit)", oracle.len());
        }

        /// Every pixel a disc's ray test accepts lies in its box, wide-angle corners and tilted
        /// discs included.
        #[test]
        fn the_pixel_box_holds_every_pixel_the_disc_covers(
            x in -0.04f32..0.04, y in -0.04f32..0.04, z in 0.004f32..0.06,
            theta in 0.0f32..1.5, phi in 0.0f32..6.3, r_mm in 0.05f32..1.5,
        ) {
            let cam = PinholeCamera::new(320, 320, 160.0, 160.0, 159.5, 159.5);
            let depths = SplatDepths { min_m: 0.002, max_m: 0.25, blend_m: 0.001, stable: 10.0 };
            let surfel = Surfel {
                position_m: Point3::new(x, y, z),
                normal: Vector3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos()),
                radius_m: r_mm * 1e-3,
                colour: [0; 3],
                confidence: 1.0,
                t0: 0,
                t: 0,
                albedo: 0.0,
                sigma_m: 0.0,
                warp_m: Vector3::zeros(),
            };
            let Some(d) = Disc::new(&surfel, &nalgebra::Isometry3::identity(), &cam, &depths) else { return Ok(()) };
            let (u0, v0) = ((160.0 * x / z + 159.5).round() as i64, (160.0 * y / z + 159.5).round() as i64);
            let rays = Rays::new(&cam);
            for py in (v0 - 12).max(0)..=(v0 + 12).min(319) {
                for px in (u0 - 12).max(0)..=(u0 + 12).min(319) {
                    if d.hit(px, py, &rays, &depths).is_some() {
                        prop_assert!(d.x.0 <= px && px <= d.x.1 && d.y.0 <= py && py <= d.y.1, "pixel ({px}, {py}) outside {:?} {:?}", d.x, d.y);
                    }
                }
            }
        }
    }
}
