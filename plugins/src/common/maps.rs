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
/// range σ): a `(2 radius + 1)²` window, spatial σ in pixels, range σ in metres; invalid
/// pixels stay invalid and are never averaged in.
pub fn bilateral_depth(depth: &DepthMap, radius: usize, sigma_space_px: f32, sigma_range_m: f32) -> DepthMap {
    let (w, h) = depth.size();
    let r = radius as i64;
    let inv_s = -0.5 / (sigma_space_px * sigma_space_px);
    let inv_r = -0.5 / (sigma_range_m * sigma_range_m);
    // The spatial exponent of each window offset, row-major: computed once, not per pixel.
    let spatial: Vec<f32> = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| ((dx * dx + dy * dy) as f32) * inv_s)).collect();
    let side = 2 * r + 1;
    let mut out = DepthMap::new(w, h);
    out.data_mut().par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            let c = depth.at(x, y);
            if c <= 0.0 {
                continue;
            }
            let (mut sum, mut wsum) = (0.0f32, 0.0f32);
            for dy in -r..=r {
                let yy = y as i64 + dy;
                if yy < 0 || yy >= h as i64 {
                    continue;
                }
                let source = &depth.data()[yy as usize * w..(yy as usize + 1) * w];
                for dx in -r..=r {
                    let xx = x as i64 + dx;
                    if xx < 0 || xx >= w as i64 {
                        continue;
                    }
                    let d = source[xx as usize];
                    if d <= 0.0 {
                        continue;
                    }
                    // The centre's weight is exp(−0) = 1 exactly.
                    let wgt = if dx == 0 && dy == 0 { 1.0 } else { (spatial[((dy + r) * side + dx + r) as usize] + (d - c) * (d - c) * inv_r).exp() };
                    sum += wgt * d;
                    wsum += wgt;
                }
            }
            *out = sum / wsum;
        }
    });
    out
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
        let mut depth = rough_depth(40, 30);
        depth.data_mut().iter_mut().filter(|d| d.is_nan()).for_each(|d| *d = 0.0);
        for (radius, sigma_px, sigma_m) in [(1, 2.0f32, 0.0008f32), (2, 1.5, 0.003)] {
            let f = bilateral_depth(&depth, radius, sigma_px, sigma_m);
            let (inv_s, inv_r, r) = (-0.5 / (sigma_px * sigma_px), -0.5 / (sigma_m * sigma_m), radius as i64);
            for y in 0..30i64 {
                for x in 0..40i64 {
                    let c = depth.at(x as usize, y as usize);
                    let (mut sum, mut wsum) = (0.0f32, 0.0f32);
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let (xx, yy) = (x + dx, y + dy);
                            if c <= 0.0 || !(0..40).contains(&xx) || !(0..30).contains(&yy) || depth.at(xx as usize, yy as usize) <= 0.0 {
                                continue;
                            }
                            let d = depth.at(xx as usize, yy as usize);
                            let wgt = (((dx * dx + dy * dy) as f32) * inv_s + (d - c) * (d - c) * inv_r).exp();
                            sum += wgt * d;
                            wsum += wgt;
                        }
                    }
                    let want = if c <= 0.0 { 0.0 } else { sum / wsum };
                    assert_eq!(f.at(x as usize, y as usize).to_bits(), want.to_bits(), "pixel ({x}, {y}), radius {radius}");
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
