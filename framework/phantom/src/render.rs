//! Ray-cast rendering of the phantom, row-parallel with rayon and deterministic: noise comes
//! from a PCG stream seeded by (seed, frame, row).

use nalgebra::{Point2, Point3, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::{Phantom, SHININESS, SPECULAR_ALBEDO, texture, trajectory};
use capsule_slam_framework::geometry::Iso3;
use capsule_slam_framework::image::{DepthMap, GrayF32, Mask, Rgb8};
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::map::{Surfel, SurfelSet};
use capsule_slam_framework::stereo::rectify::Side;

/// Read noise σ (linear units) at noise scale 1.
const READ_NOISE: f64 = 0.003;
/// Shot-noise variance per unit of linear signal at noise scale 1.
const SHOT_NOISE: f64 = 0.0006;
/// Rays stop after this distance, metres (the cavity is smaller).
const MAX_RAY_M: f64 = 0.5;

/// One rendered frame with its per-pixel ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderedFrame {
    /// Frame index.
    pub index: usize,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// Ground-truth pose.
    pub t_world_cam: Iso3,
    /// The camera image.
    pub rgb: Rgb8,
    /// The same without specular highlights (ground truth for inpainting).
    pub diffuse: Rgb8,
    /// Where the highlight term dominates the diffuse term.
    pub specular: Mask,
    /// Ground-truth depth along z, metres (0 outside the field of view).
    pub depth_m: DepthMap,
    /// The depth a sensor reads: `depth_m` with the spec's `depth_noise` (`depth_noise.rs`).
    pub measured_depth_m: DepthMap,
}

impl RenderedFrame {
    /// The frame as tracking and fusion see it: colour, measured depth, ground-truth pose, and the
    /// out-of-view mask of `camera`'s round field of view (if any).
    pub fn to_rgbd(&self, camera: &capsule_slam_framework::camera::PinholeCamera) -> capsule_slam_framework::frame::RgbdFrame {
        let mut masks = capsule_slam_framework::frame::Masks::new();
        if camera.fov_radius_px.is_some() {
            let mut out = camera.fov_mask();
            out.data_mut().iter_mut().for_each(|v| *v = !*v);
            masks.insert(capsule_slam_framework::frame::MASK_OUT_OF_VIEW, out);
        }
        capsule_slam_framework::frame::RgbdFrame {
            depth_source: capsule_slam_framework::frame::DepthSource::Measured,
            index: self.index,
            timestamp_s: self.timestamp_s,
            colour: self.rgb.clone(),
            depth_m: self.measured_depth_m.clone(),
            depth_confidence: None,
            depth_sigma_m: None,
            depth_sigma_correlation_px: 0.0,
            photometry: Default::default(),
            albedo: None,
            gt_t_world_cam: Some(self.t_world_cam),
            masks,
            sample_share: None,
            derived: Default::default(),
        }
    }
}

/// One rendered image row: colour, diffuse-only colour, specular mask, depth.
struct Row {
    rgb: Vec<u8>,
    dif: Vec<u8>,
    spec: Vec<bool>,
    depth: Vec<f32>,
}

/// Linear radiance of one pixel.
#[derive(Debug, Clone, Copy, Default)]
struct Sample {
    depth_m: f64,
    diffuse: [f64; 3],
    specular: f64,
}

/// Where a pixel's ray meets the wall.
struct RayHit {
    /// The pixel's pinhole pixel (itself without a lens).
    pin: Point2<f64>,
    /// The unit ray in the camera frame.
    d_cam: Vector3<f64>,
    /// The distance along the ray, metres.
    s: f64,
    /// The world point.
    p_w: Point3<f64>,
}

impl Phantom {
    /// Where the ray of pixel `(u, v)` meets the wall: the pixel's pinhole pixel, the unit ray
    /// in the camera frame, the distance along it and the world point; `None` outside the field
    /// of view, beyond the lens's fold (no ray lands there) or when the ray meets no wall.
    fn hit(&self, u: f64, v: f64, pose: &Iso3, t_s: f64) -> Option<RayHit> {
        let cam = &self.camera;
        if !cam.in_fov(u, v) {
            return None;
        }
        let pin = cam.pinhole_pixel(u, v)?;
        let (xn, yn) = ((pin.x - cam.cx) / cam.fx, (pin.y - cam.cy) / cam.fy);
        let d_cam = Vector3::new(xn, yn, 1.0).normalize();
        let d_w = pose.rotation * d_cam;
        let o = Point3::from(pose.translation.vector);
        let s = self.shape.raycast(&o, &d_w, t_s, MAX_RAY_M)?;
        Some(RayHit { pin, d_cam, s, p_w: o + d_w * s })
    }

    /// The linear RGB albedo of the wall at world point `p_w` (its texture at the rest shape).
    fn albedo_at(&self, p_w: &Point3<f64>) -> [f64; 3] {
        let tc = self.shape.coords(p_w);
        texture::albedo(&self.shape.rest_point(tc.phi, tc.theta), self.spec.seed, self.spec.texture)
    }

    /// Ground truth of an observed albedo: the luminance (NTSC, linear) of the wall's albedo at
    /// every pixel of frame `i`'s reference view (0 where no wall is seen).
    pub fn albedo_image(&self, i: usize) -> GrayF32 {
        let (pose, t_s) = (self.pose(i), self.time_s(i));
        GrayF32::from_fn_par(self.camera.width, self.camera.height, |x, y| {
            let a = self.hit(x as f64, y as f64, &pose, t_s).map(|hit| capsule_slam_framework::image::luminance(self.albedo_at(&hit.p_w)));
            [a.unwrap_or(0.0) as f32]
        })
    }

    fn shade(&self, u: f64, v: f64, pose: &Iso3, t_s: f64, light: &LightModel) -> Option<Sample> {
        let cam = &self.camera;
        let RayHit { pin, d_cam, s, p_w } = self.hit(u, v, pose, t_s)?;
        let n_w = self.shape.inward_normal(&p_w, t_s);
        let p_cam = Point3::from(d_cam * s);
        let n_cam = pose.rotation.inverse() * n_w;
        let albedo = self.albedo_at(&p_w);
        // The lens and light fall-off V is a function of the ray (its pinhole pixel): what the
        // stages, which see undistorted frames, divide out with `light.toml`.
        let vig = light.vignetting_at(cam, pin.x, pin.y);
        let cos_inc = light.cos_incidence(&p_cam, &n_cam);
        let fall = light.falloff(&p_cam);
        let mut diffuse = [0.0; 3];
        for c in 0..3 {
            diffuse[c] = vig * albedo[c] * (cos_inc * fall + light.ambient);
        }
        // Blinn–Phong: half vector between the directions to the light and to the camera.
        let specular = if cos_inc > 0.0 && self.spec.specular > 0.0 {
            let h = ((light.position() - p_cam).normalize() - p_cam.coords.normalize()).normalize();
            vig * self.spec.specular * SPECULAR_ALBEDO * fall * n_cam.dot(&h).max(0.0).powf(SHININESS)
        } else {
            0.0
        };
        Some(Sample { depth_m: s * d_cam.z, diffuse, specular })
    }

    /// Renders frame `i` (the reference camera's view).
    pub fn render(&self, i: usize) -> RenderedFrame {
        self.render_view(i, Side::Left)
    }

    /// Renders frame `i` as one camera of the rig sees it (the right one of a stereo phantom:
    /// its own pose, and the light where it stands in that camera's frame, so that each camera
    /// sees its own highlights). The measured depth is the left's only.
    pub fn render_view(&self, i: usize, view: Side) -> RenderedFrame {
        let (w, h) = (self.camera.width, self.camera.height);
        let t_left_view = self.t_left_view(view);
        let pose = self.pose(i) * t_left_view;
        let light = self.light.at(&t_left_view.inverse());
        let t_s = self.time_s(i);
        let n_blur = self.spec.motion_blur.max(1) as usize;
        // Motion blur: sub-frame poses over the last half frame interval before the exposure end.
        let blur_poses: Vec<(Iso3, f64)> = (1..n_blur)
            .map(|k| {
                let dt = 0.5 * k as f64 / n_blur as f64;
                let ti = (i as f64 - dt).max(0.0);
                (trajectory::pose(&self.shape, &trajectory::waypoint(self.spec.preset, self.spec.path_tau(ti))) * t_left_view, ti / self.spec.frame_rate_hz)
            })
            .collect();
        let seed = self.spec.seed;
        let noise = self.spec.noise;
        let rows: Vec<Row> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(seed.wrapping_mul(0x9E37_79B9).wrapping_add((i as u64) << 20).wrapping_add(y as u64));
                let (mut rgb, mut dif, mut spec, mut depth) = (vec![0u8; w * 3], vec![0u8; w * 3], vec![false; w], vec![0f32; w]);
                for x in 0..w {
                    let (u, v) = (x as f64, y as f64);
                    let Some(mut px) = self.shade(u, v, &pose, t_s, &light) else { continue };
                    depth[x] = px.depth_m as f32;
                    let lum = 0.2989 * px.diffuse[0] + 0.5870 * px.diffuse[1] + 0.1140 * px.diffuse[2];
                    spec[x] = px.specular > lum;
                    for (bp, bt) in &blur_poses {
                        let b = self.shade(u, v, bp, *bt, &light).unwrap_or_default();
                        for c in 0..3 {
                            px.diffuse[c] += b.diffuse[c];
                        }
                        px.specular += b.specular;
                    }
                    let k = 1.0 / n_blur as f64;
                    for c in 0..3 {
                        let lin = px.diffuse[c] * k;
                        let n: f64 = if noise > 0.0 {
                            let g: f64 = StandardNormal.sample(&mut rng);
                            g * (noise * (READ_NOISE * READ_NOISE + SHOT_NOISE * lin.max(0.0))).sqrt()
                        } else {
                            0.0
                        };
                        rgb[3 * x + c] = to_u8(self.light.encode(lin + px.specular * k + n));
                        dif[3 * x + c] = to_u8(self.light.encode(lin + n));
                    }
                }
                Row { rgb, dif, spec, depth }
            })
            .collect();
        let mut out = RenderedFrame {
            index: i,
            timestamp_s: t_s,
            t_world_cam: pose,
            rgb: Rgb8::new(w, h),
            diffuse: Rgb8::new(w, h),
            specular: Mask::new(w, h),
            depth_m: DepthMap::new(w, h),
            measured_depth_m: DepthMap::new(0, 0),
        };
        for (y, Row { rgb, dif, spec, depth }) in rows.into_iter().enumerate() {
            out.rgb.data_mut()[y * w * 3..(y + 1) * w * 3].copy_from_slice(&rgb);
            out.diffuse.data_mut()[y * w * 3..(y + 1) * w * 3].copy_from_slice(&dif);
            out.specular.data_mut()[y * w..(y + 1) * w].copy_from_slice(&spec);
            out.depth_m.data_mut()[y * w..(y + 1) * w].copy_from_slice(&depth);
        }
        if view == Side::Left {
            out.measured_depth_m = self.spec.depth_noise.apply(&out.depth_m, &self.camera, self.spec.seed, i);
        }
        out
    }

    /// Flat-field calibration frame `k`: a matte white target (albedo 0.8) facing the capsule at
    /// `distance_m`, under the phantom's light and lens with its sensor noise, and no ambient
    /// light (a calibration rig has no organ around it to reflect). What `capsule-slam
    /// calibrate-vignetting` fits.
    pub fn render_flat_field(&self, k: usize, distance_m: f64) -> Rgb8 {
        let cam = &self.camera;
        let light = capsule_slam_framework::light::LightModel { ambient: 0.0, ..self.light.clone() };
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(self.spec.seed ^ 0xF1A7_F1E1D ^ ((k as u64) << 32));
        let noise = self.spec.noise;
        Rgb8::from_fn(cam.width, cam.height, |x, y| {
            let (u, v) = (x as f64, y as f64);
            let Some(pin) = cam.pinhole_pixel(u, v).filter(|_| cam.in_fov(u, v)) else {
                return [0; 3];
            };
            let lin = capsule_slam_framework::light::vignetting::flat_field_linear(&light, cam, pin.x, pin.y, distance_m, 0.8);
            std::array::from_fn(|_| {
                let g: f64 = StandardNormal.sample(&mut rng);
                let n = g * (noise * (READ_NOISE * READ_NOISE + SHOT_NOISE * lin)).sqrt();
                to_u8(light.encode(lin + n))
            })
        })
    }

    /// The lens vignetting V(u) of every pixel.
    pub fn vignetting_field(&self) -> GrayF32 {
        let cam = &self.camera;
        GrayF32::from_fn(cam.width, cam.height, |x, y| [cam.pinhole_pixel(x as f64, y as f64).map_or(0.0, |p| self.light.vignetting_at(cam, p.x, p.y) as f32)])
    }

    /// The wall at time `t_s` sampled about every `spacing_m` (world frame, inward normals,
    /// texture colour): the ground-truth surface.
    pub fn surface(&self, t_s: f64, spacing_m: f64) -> SurfelSet {
        let s = &self.shape;
        let n_phi = (s.length_m() / spacing_m).ceil() as usize;
        let n_theta = (std::f64::consts::TAU * s.radius_m * (1.0 + s.bulge) / spacing_m).ceil() as usize;
        let surfels = (0..n_phi)
            .into_par_iter()
            .flat_map_iter(|i| {
                let phi = -s.half_angle_rad + (i as f64 + 0.5) * 2.0 * s.half_angle_rad / n_phi as f64;
                (0..n_theta).map(move |j| {
                    let theta = -std::f64::consts::PI + (j as f64 + 0.5) * std::f64::consts::TAU / n_theta as f64;
                    let p = s.surface_point(phi, theta, t_s);
                    let n = s.inward_normal(&p, t_s);
                    let a = texture::albedo(&self.shape.rest_point(phi, theta), self.spec.seed, self.spec.texture);
                    Surfel {
                        position_m: p.cast(),
                        normal: n.cast(),
                        colour: [to_u8(a[0]), to_u8(a[1]), to_u8(a[2])],
                        confidence: 1.0,
                        radius_m: (0.5 * spacing_m) as f32,
                        t0: 0,
                        t: 0,
                        albedo: capsule_slam_framework::image::luminance(a) as f32,
                        sigma_m: 0.0,
                        warp_m: Vector3::zeros(),
                    }
                })
            })
            .collect();
        SurfelSet { surfels }
    }

    /// Where along the path (0 start, 1 end) frame `i` is.
    pub fn tau(&self, i: usize) -> f64 {
        self.spec.path_tau(i as f64)
    }
}

fn to_u8(v: f64) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

#[cfg(test)]
mod tests {
    use super::super::PhantomSpec;
    use super::*;

    fn phantom(f: impl FnOnce(&mut PhantomSpec)) -> Phantom {
        let mut spec = PhantomSpec::preset(1);
        spec.frames = 10;
        f(&mut spec);
        Phantom::new(spec).unwrap()
    }

    #[test]
    fn a_repeated_walk_goes_back_the_way_it_came_and_the_wall_moves_on() {
        let once = phantom(|s| s.deform_mm = 2.0);
        let thrice = phantom(|s| {
            s.deform_mm = 2.0;
            s.repeat = 3;
        });
        assert_eq!(thrice.poses().len(), 30);
        assert_eq!(&thrice.poses()[..10], once.poses(), "the first walk is the single walk");
        let same = |a: Iso3, b: Iso3| (a.translation.vector - b.translation.vector).norm() < 1e-12 && a.rotation.angle_to(&b.rotation) < 1e-9;
        for k in 0..10 {
            // Frame 9 is the far end; the second walk retraces the first, the third the second.
            assert!(same(thrice.pose(9 + k), once.pose(9 - k)), "back: frame {}", 9 + k);
            assert!(same(thrice.pose(18 + k.min(9)), once.pose(k.min(9))), "forth again: frame {}", 18 + k.min(9));
        }
        // Same place, later time: the wall is elsewhere.
        assert!(thrice.time_s(18) > once.time_s(0));
        assert_ne!(thrice.render(18).depth_m.data(), once.render(0).depth_m.data());
    }

    #[test]
    fn depth_equals_the_analytic_ray_surface_distance() {
        let p = phantom(|_| {});
        let f = p.render(4);
        let cam = &p.camera;
        let mut checked = 0;
        for y in (0..cam.height).step_by(7) {
            for x in (0..cam.width).step_by(7) {
                let d = f64::from(f.depth_m.at(x, y));
                if d <= 0.0 {
                    assert!(!cam.in_fov(x as f64, y as f64), "no depth inside the field of view at {x},{y}");
                    continue;
                }
                // The back-projected point lies on the wall, and nothing is in between.
                let p_w = f.t_world_cam * cam.unproject(x as f64, y as f64, d);
                assert!(p.shape.implicit(&p_w, f.timestamp_s).abs() < 1e-6, "{x},{y}: {}", p.shape.implicit(&p_w, f.timestamp_s));
                let o = nalgebra::Point3::from(f.t_world_cam.translation.vector);
                for k in 1..50 {
                    let q = o + (p_w - o) * (k as f64 / 50.0);
                    assert!(p.shape.implicit(&q, f.timestamp_s) < 0.0);
                }
                checked += 1;
            }
        }
        assert!(checked > 1000, "{checked}");
    }

    #[test]
    fn noise_free_pixels_follow_the_light_model() {
        // Independent of the renderer's internals: depth from the image, normal from the
        // implicit surface, albedo from the texture, then V·ρ·(gain cos θ (ref/r)² spot + ambient).
        let p = phantom(|s| {
            s.noise = 0.0;
            s.specular = 0.0;
            s.texture = false;
        });
        let f = p.render(5);
        let mut n = 0;
        for y in (5..p.camera.height).step_by(23) {
            for x in (5..p.camera.width).step_by(23) {
                let d = f64::from(f.depth_m.at(x, y));
                if d <= 0.0 {
                    continue;
                }
                let p_cam = p.camera.unproject(x as f64, y as f64, d);
                let n_cam = f.t_world_cam.rotation.inverse() * p.shape.inward_normal(&(f.t_world_cam * p_cam), f.timestamp_s);
                let cos_t = (-p_cam.coords.normalize()).dot(&n_cam).max(0.0);
                let r = p_cam.coords.norm();
                let spot = (p_cam.z / r).powf(p.light.spot_exponent);
                let lin = p.light.vignetting_at(&p.camera, x as f64, y as f64)
                    * texture::BASE_ALBEDO[1]
                    * (p.light.gain * cos_t * (p.light.ref_distance_m / r).powi(2) * spot + p.light.ambient);
                let expected = p.light.encode(lin) * 255.0;
                let got = f64::from(f.rgb.pixel(x, y)[1]);
                assert!((got - expected).abs() <= 0.5 + 0.02 * expected * f64::from(u8::from(expected > 254.0)), "{x},{y}: {got} vs {expected}");
                n += 1;
            }
        }
        assert!(n > 50);
    }

    #[test]
    fn rendering_is_deterministic_for_a_seed() {
        let a = phantom(|_| {}).render(3);
        assert_eq!(a, phantom(|_| {}).render(3));
        assert_ne!(a.rgb, phantom(|s| s.seed = 2).render(3).rgb);
    }

    #[test]
    fn specular_mask_is_where_the_highlight_dominates_and_absent_without_it() {
        let ph = phantom(|s| {
            s.preset = 2;
            s.frames = 300;
        });
        let lit = (0..300).step_by(10).map(|i| ph.render(i)).find(|f| f.specular.data().iter().any(|m| *m)).expect("some frame has a highlight");
        // Highlighted pixels are brighter than their diffuse-only version.
        for (k, m) in lit.specular.data().iter().enumerate() {
            if *m {
                let (a, b) = (&lit.rgb.data()[3 * k..3 * k + 3], &lit.diffuse.data()[3 * k..3 * k + 3]);
                assert!(a.iter().zip(b).all(|(x, y)| x >= y));
                assert!(a[1] > b[1] || a[1] == 255);
            }
        }
        let dry = phantom(|s| s.specular = 0.0).render(2);
        assert!(dry.specular.data().iter().all(|m| !m));
        assert_eq!(dry.rgb, dry.diffuse);
    }

    #[test]
    fn surface_samples_lie_on_the_wall() {
        let p = phantom(|s| s.deform_mm = 3.0);
        let surf = p.surface(0.7, 0.003);
        assert!(surf.len() > 1000);
        for s in surf.surfels.iter().step_by(17) {
            assert!(p.shape.implicit(&s.position_m.cast(), 0.7).abs() < 1e-6);
            assert!((s.normal.norm() - 1.0).abs() < 1e-5);
        }
    }
}
