//! Vertex and normal maps (camera frame) from a depth map.

use std::sync::Arc;

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::Masks;
use capsule_slam_framework::{DepthMap, Image, RgbdFrame};
use nalgebra::Vector3;
use rayon::prelude::*;

/// Camera-frame points, one per pixel; z = 0 where invalid.
pub type VertexMap = Image<f32, 3>;
/// Camera-frame unit normals pointing toward the camera; zero where invalid.
pub type NormalMap = Image<f32, 3>;

/// Depth with masked pixels (specular, out of view, ...) and values outside
/// `[min_m, max_m]` set invalid (0).
pub fn usable_depth(depth: &DepthMap, masks: &Masks, min_m: f32, max_m: f32) -> DepthMap {
    let union = masks.union();
    let mut out = depth.clone();
    for (k, d) in out.data_mut().iter_mut().enumerate() {
        let masked = union.as_ref().is_some_and(|m| m.data()[k]);
        if masked || !d.is_finite() || *d < min_m || *d > max_m {
            *d = 0.0;
        }
    }
    out
}

/// Edge-preserving smoothing of depth (ElasticFusion's bilateral filter, with organ-scale
/// range σ): a `(2 radius + 1)²` window, spatial σ in pixels, range σ in metres; pixels without
/// depth (≤ 0) stay so and are never averaged in. Each pixel sums its taps' weights
/// `exp(−|o|²/2σ_s² − (d_q − d_p)²/2σ_r²)` in row-major order; radius 1 (the default) takes
/// each pair's exponential once ([`bilateral_3x3`]), with the same sums to the bit.
pub fn bilateral_depth(depth: &DepthMap, radius: usize, sigma_space_px: f32, sigma_range_m: f32) -> DepthMap {
    let (w, h) = depth.size();
    let mut out = DepthMap::new(w, h);
    if w == 0 || h == 0 {
        return out;
    }
    let inv_s = -0.5 / (sigma_space_px * sigma_space_px);
    let inv_r = -0.5 / (sigma_range_m * sigma_range_m);
    let window = Window::new(radius, inv_s, inv_r);
    if radius == 1 {
        bilateral_3x3(depth, &window, &mut out);
        return out;
    }
    out.data_mut().par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            *out = window.filtered(depth, x, y);
        }
    });
    out
}

/// A bilateral window: its radius, the spatial exponent of each offset (row-major, computed
/// once, not per pixel) and the range exponent's factor.
struct Window {
    radius: usize,
    spatial: Vec<f32>,
    inv_r: f32,
}

impl Window {
    fn new(radius: usize, inv_s: f32, inv_r: f32) -> Self {
        let r = radius as i64;
        let spatial = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| ((dx * dx + dy * dy) as f32) * inv_s)).collect();
        Self { radius, spatial, inv_r }
    }

    /// The weight of a tap of depth `d` at window slot `slot` from a centre of depth `c`.
    fn weight(&self, slot: usize, c: f32, d: f32) -> f32 {
        (self.spatial[slot] + (d - c) * (d - c) * self.inv_r).exp()
    }

    /// The filtered depth at (x, y): the window clipped to the image, taps in row-major order.
    fn filtered(&self, depth: &DepthMap, x: usize, y: usize) -> f32 {
        let ((w, h), data, radius) = (depth.size(), depth.data(), self.radius);
        let side = 2 * radius + 1;
        let c = data[y * w + x];
        if c <= 0.0 {
            return 0.0;
        }
        let (y0, y1) = (y.saturating_sub(radius), (y + radius).min(h - 1));
        let (x0, x1) = (x.saturating_sub(radius), (x + radius).min(w - 1));
        let (mut sum, mut wsum) = (0.0f32, 0.0f32);
        for yy in y0..=y1 {
            let first = (yy + radius - y) * side + x0 + radius - x;
            for (k, &d) in data[yy * w + x0..=yy * w + x1].iter().enumerate() {
                if d <= 0.0 {
                    continue;
                }
                // The centre's weight is exp(−0) = 1 exactly.
                let wgt = if yy == y && x0 + k == x { 1.0 } else { self.weight(first + k, c, d) };
                sum += wgt * d;
                wsum += wgt;
            }
        }
        sum / wsum
    }
}

/// [`bilateral_depth`] with radius 1. A pair's weight is the same, to the bit, seen from either
/// pixel (`(d_q − d_p)² = (d_p − d_q)²`, the spatial exponent symmetric), so each pixel's
/// weights to its east, south-west, south and south-east neighbours are taken once, and read
/// by both pixels of the pair; a tap without depth adds a weight of 0 (the same sums as
/// skipping it). The image's border rows and columns take the clipped window.
fn bilateral_3x3(depth: &DepthMap, window: &Window, out: &mut DepthMap) {
    let (w, h) = depth.size();
    let data = depth.data();
    // The east, south-west, south and south-east taps: window slot (row-major, 3 × 3), dy, dx + 1.
    const FORWARD: [(usize, usize, usize); 4] = [(5, 0, 2), (6, 1, 0), (7, 1, 1), (8, 1, 2)];
    let mut pairs = vec![[0.0f32; 4]; w * h];
    pairs.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            let c = data[y * w + x];
            if c <= 0.0 {
                continue;
            }
            for (k, &(slot, dy, dxp1)) in FORWARD.iter().enumerate() {
                let (yy, xx) = (y + dy, (x + dxp1).wrapping_sub(1));
                if yy >= h || xx >= w {
                    continue;
                }
                let d = data[yy * w + xx];
                if d > 0.0 {
                    out[k] = window.weight(slot, c, d);
                }
            }
        }
    });
    let valid = |d: f32| if d <= 0.0 { 0.0 } else { d };
    out.data_mut().par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            if y == 0 || x == 0 || y + 1 == h || x + 1 == w {
                *out = window.filtered(depth, x, y);
                continue;
            }
            let i = y * w + x;
            let c = data[i];
            if c <= 0.0 {
                continue;
            }
            // Row-major taps: the three above read the pair weights stored at them, the west
            // one its east weight, the centre 1, the rest this pixel's own.
            let (up, here) = (i - w, &pairs[i]);
            let weights = [pairs[up - 1][3], pairs[up][2], pairs[up + 1][1], pairs[i - 1][0], 1.0, here[0], here[1], here[2], here[3]];
            let taps = [data[up - 1], data[up], data[up + 1], data[i - 1], c, data[i + 1], data[i + w - 1], data[i + w], data[i + w + 1]];
            let (mut sum, mut wsum) = (0.0f32, 0.0f32);
            for (wgt, d) in weights.into_iter().zip(taps) {
                sum += wgt * valid(d);
                wsum += wgt;
            }
            *out = sum / wsum;
        }
    });
}

/// Back-projects every valid pixel: `v = K⁻¹ [u v 1]ᵀ d` (the paper's p(u, D)), as
/// [`PinholeCamera::unproject`] does, with the ray's `(u − cx) / fx` and `(v − cy) / fy` taken
/// from a table per column and per row (the same values, not recomputed per pixel).
pub fn vertex_map(depth: &DepthMap, cam: &PinholeCamera) -> VertexMap {
    let (w, h) = depth.size();
    let ray_x: Vec<f64> = (0..w).map(|x| (x as f64 - cam.cx) / cam.fx).collect();
    let mut out = VertexMap::new(w, h);
    out.data_mut().par_chunks_mut((3 * w).max(1)).zip(depth.data().par_chunks(w.max(1))).enumerate().for_each(|(y, (row, depths))| {
        let ray_y = (y as f64 - cam.cy) / cam.fy;
        for ((v, &d), &rx) in row.chunks_exact_mut(3).zip(depths).zip(&ray_x) {
            if d <= 0.0 {
                continue;
            }
            let d = f64::from(d);
            v.copy_from_slice(&[(rx * d) as f32, (ray_y * d) as f32, d as f32]);
        }
    });
    out
}

/// The vertex at pixel (x, y), if valid.
pub fn vertex(v: &VertexMap, x: usize, y: usize) -> Option<Vector3<f32>> {
    let p = v.pixel(x, y);
    (p[2] > 0.0).then(|| Vector3::new(p[0], p[1], p[2]))
}

/// Normals by central differences over `step` pixels: `n = −normalize((v₊ₓ − v₋ₓ) × (v₊ᵧ − v₋ᵧ))`,
/// oriented toward the camera; zero where a neighbour is invalid or the neighbours are more
/// than `max_jump_m` apart in depth (a depth edge).
pub fn normal_map(v: &VertexMap, step: usize, max_jump_m: f32) -> NormalMap {
    let (w, h) = v.size();
    let mut out = NormalMap::new(w, h);
    if step == 0 || w <= 2 * step || h <= 2 * step {
        return out;
    }
    let rows = |y: usize| &v.data()[3 * w * y..3 * w * (y + 1)];
    let at = |row: &[f32], x: usize| {
        let p = &row[3 * x..3 * x + 3];
        (p[2] > 0.0).then(|| Vector3::new(p[0], p[1], p[2]))
    };
    out.data_mut().par_chunks_mut(3 * w).enumerate().skip(step).take(h - 2 * step).for_each(|(y, out)| {
        let (here, up, down) = (rows(y), rows(y - step), rows(y + step));
        for x in step..w - step {
            let (Some(c), Some(l), Some(r), Some(u), Some(d)) = (at(here, x), at(here, x - step), at(here, x + step), at(up, x), at(down, x)) else {
                continue;
            };
            if [l, r, u, d].iter().any(|q| (q.z - c.z).abs() > max_jump_m) {
                continue;
            }
            let n = (r - l).cross(&(d - u));
            let len = n.norm();
            if len <= 0.0 {
                continue;
            }
            let mut n = -n / len;
            if n.dot(&c) > 0.0 {
                n = -n;
            }
            out[3 * x..3 * x + 3].copy_from_slice(&[n.x, n.y, n.z]);
        }
    });
    out
}

/// The normal at pixel (x, y), if valid.
pub fn normal(n: &NormalMap, x: usize, y: usize) -> Option<Vector3<f32>> {
    let p = n.pixel(x, y);
    (p != [0.0; 3]).then(|| Vector3::new(p[0], p[1], p[2]))
}

/// How a frame's geometry is prepared.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeometryParams {
    /// Valid depth range, metres.
    pub min_m: f32,
    /// Valid depth range, metres.
    pub max_m: f32,
    /// Bilateral window radius, pixels.
    pub radius_px: usize,
    /// Bilateral spatial σ, pixels.
    pub sigma_px: f32,
    /// Bilateral range σ, metres.
    pub sigma_m: f32,
    /// Depth step that breaks a normal, metres.
    pub edge_jump_m: f32,
}

/// A frame's geometry: masked depth (raw and bilateral-filtered), their vertex maps, and
/// normals of the filtered depth (ElasticFusion: positions from raw, normals from filtered).
pub struct Geometry {
    /// Masked, range-limited depth.
    pub raw: DepthMap,
    /// Its bilateral-filtered version.
    pub smooth: DepthMap,
    /// Vertices of the raw depth.
    pub v_raw: VertexMap,
    /// Vertices of the filtered depth.
    pub v_smooth: VertexMap,
    /// Normals of the filtered depth.
    pub normals: NormalMap,
}

/// The geometry of `frame`, computed once per frame and parameter set (memoised on the frame,
/// so a tracker and a fuser with the same settings share it).
pub fn geometry(frame: &RgbdFrame, cam: &PinholeCamera, p: &GeometryParams) -> Arc<Geometry> {
    let key = format!("geometry {p:?} {} {} {} {} {} {}", cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy);
    frame.derived.get_or_compute(&key, || {
        let raw = usable_depth(&frame.depth_m, &frame.masks, p.min_m, p.max_m);
        let smooth = bilateral_depth(&raw, p.radius_px, p.sigma_px, p.sigma_m);
        let v_raw = vertex_map(&raw, cam);
        let v_smooth = vertex_map(&smooth, cam);
        let normals = normal_map(&v_smooth, 1, p.edge_jump_m);
        Geometry { raw, smooth, v_raw, v_smooth, normals }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> PinholeCamera {
        PinholeCamera::new(64, 48, 50.0, 50.0, 31.5, 23.5)
    }

    #[test]
    fn a_tilted_plane_gives_its_normal_and_faces_the_camera() {
        // Plane through (0, 0, 0.04) with normal (0.3, 0, −1)/|.|, toward the camera.
        let n_true = Vector3::new(0.3f64, 0.0, -1.0).normalize();
        let c = cam();
        let depth = DepthMap::from_fn(64, 48, |x, y| {
            let ray = Vector3::new((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy, 1.0);
            let t = n_true.dot(&Vector3::new(0.0, 0.0, 0.04)) / n_true.dot(&ray);
            [t as f32]
        });
        let v = vertex_map(&depth, &c);
        let n = normal_map(&v, 1, 0.01);
        let got = normal(&n, 30, 20).unwrap().cast::<f64>();
        assert!((got - n_true).norm() < 1e-4, "{got}");
        assert!(normal(&n, 0, 0).is_none());
    }

    /// A depth map with a slope, a depth edge, holes and a NaN: every branch of the maps.
    fn rough_depth(w: usize, h: usize) -> DepthMap {
        DepthMap::from_fn(w, h, |x, y| {
            let d = 0.03 + 0.0001 * x as f32 + 0.00007 * y as f32 + if x > w / 2 { 0.01 } else { 0.0 };
            [match (x * 7 + y * 13) % 23 {
                0 => 0.0,
                1 => f32::NAN,
                _ => d,
            }]
        })
    }

    #[test]
    fn the_vertex_map_is_the_unprojection_of_every_pixel_with_depth() {
        let c = cam();
        let depth = rough_depth(64, 48);
        let v = vertex_map(&depth, &c);
        for y in 0..48 {
            for x in 0..64 {
                let d = depth.at(x, y);
                let want = if d <= 0.0 {
                    [0.0; 3]
                } else {
                    let p = c.unproject(x as f64, y as f64, f64::from(d));
                    [p.x as f32, p.y as f32, p.z as f32]
                };
                assert_eq!(v.pixel(x, y).map(f32::to_bits), want.map(f32::to_bits), "pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn the_normal_map_is_the_cross_product_of_the_central_differences() {
        let c = cam();
        let v = vertex_map(&rough_depth(64, 48), &c);
        for (step, jump) in [(1, 0.002), (2, 0.02)] {
            let n = normal_map(&v, step, jump);
            let mut seen = 0;
            for y in 0..48 {
                for x in 0..64 {
                    // The definition, pixel by pixel.
                    let want = (|| {
                        if x < step || y < step || x + step >= 64 || y + step >= 48 {
                            return [0.0; 3];
                        }
                        let q = |x: usize, y: usize| vertex(&v, x, y);
                        let (Some(c), Some(l), Some(r), Some(u), Some(d)) = (q(x, y), q(x - step, y), q(x + step, y), q(x, y - step), q(x, y + step)) else {
                            return [0.0; 3];
                        };
                        if [l, r, u, d].iter().any(|p| (p.z - c.z).abs() > jump) {
                            return [0.0; 3];
                        }
                        let m = -(r - l).cross(&(d - u)).normalize();
                        let m = if m.dot(&c) > 0.0 { -m } else { m };
                        [m.x, m.y, m.z]
                    })();
                    seen += usize::from(want != [0.0; 3]);
                    assert_eq!(n.pixel(x, y).map(f32::to_bits), want.map(f32::to_bits), "pixel ({x}, {y}), step {step}");
                }
            }
            assert!(seen > 1000, "{seen} normals");
        }
    }

    #[test]
    fn the_bilateral_filter_is_its_weighted_mean() {
        // Images smaller than the window too.
        for (w, h) in [(40usize, 30usize), (1, 1), (3, 1), (1, 4), (2, 2)] {
            let mut depth = rough_depth(w, h);
            depth.data_mut().iter_mut().filter(|d| d.is_nan()).for_each(|d| *d = 0.0);
            let (wi, hi) = (w as i64, h as i64);
            for (radius, sigma_px, sigma_m) in [(0, 2.0f32, 0.0008f32), (1, 2.0, 0.0008), (2, 1.5, 0.003), (3, 1.5, 0.003)] {
                let f = bilateral_depth(&depth, radius, sigma_px, sigma_m);
                let (inv_s, inv_r, r) = (-0.5 / (sigma_px * sigma_px), -0.5 / (sigma_m * sigma_m), radius as i64);
                for y in 0..hi {
                    for x in 0..wi {
                        let c = depth.at(x as usize, y as usize);
                        let (mut sum, mut wsum) = (0.0f32, 0.0f32);
                        for dy in -r..=r {
                            for dx in -r..=r {
                                let (xx, yy) = (x + dx, y + dy);
                                if c <= 0.0 || !(0..wi).contains(&xx) || !(0..hi).contains(&yy) || depth.at(xx as usize, yy as usize) <= 0.0 {
                                    continue;
                                }
                                let d = depth.at(xx as usize, yy as usize);
                                let wgt = (((dx * dx + dy * dy) as f32) * inv_s + (d - c) * (d - c) * inv_r).exp();
                                sum += wgt * d;
                                wsum += wgt;
                            }
                        }
                        let want = if c <= 0.0 { 0.0 } else { sum / wsum };
                        assert_eq!(f.at(x as usize, y as usize).to_bits(), want.to_bits(), "pixel ({x}, {y}) of {w} × {h}, radius {radius}");
                    }
                }
            }
        }
    }

    #[test]
    fn bilateral_keeps_edges_and_smooths_noise() {
        let depth = DepthMap::from_fn(32, 32, |x, y| [if x < 16 { 0.03 + if (x + y) % 2 == 0 { 0.0002 } else { -0.0002 } } else { 0.05 }]);
        let f = bilateral_depth(&depth, 2, 2.0, 0.001);
        assert!((f.at(8, 8) - 0.03).abs() < 0.00005, "{}", f.at(8, 8));
        assert!((f.at(15, 8) - 0.03).abs() < 0.0003 && (f.at(16, 8) - 0.05).abs() < 1e-6, "edge kept");
        let mut holes = depth.clone();
        *holes.at_mut(5, 5) = 0.0;
        assert_eq!(bilateral_depth(&holes, 2, 2.0, 0.001).at(5, 5), 0.0);
    }
}
