//! `surfel-gpu` against `surfel-cpu`, the reference it mirrors: the same frames give the same
//! map and the same predictions (to f32 rounding), run after run.

use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stage::LoopClosure;
use capsule_slam_framework::{Context, Fuser, Iso3, ModelSet, ModelView, Plugin, Surfel};
use capsule_slam_phantom::Phantom;
use nalgebra::{Point3, Rotation3, Vector3};

use super::SurfelGpu;
use crate::fuse::surfel_cpu::SurfelCpu;
use crate::fuse::surfel_params::SurfelParams;
use crate::testing::{phantom, rgbd, rig};
use capsule_slam_gpu::GpuHandle;

/// Parameters that exercise every rule within a few frames: removal of stale unstable surfels
/// (lifetime 5), stable surfels (confidence 3), inactive surfels (δt 8).
fn params() -> SurfelParams {
    SurfelParams { stable_confidence: 3.0, unstable_lifetime: 5, delta_t: 8, ..SurfelParams::default() }
}

/// Frame `i` with a structured-light-like depth σ (0.2 mm + 0.2 m⁻¹·z²), which varies from
/// pixel to pixel, so that the merges weigh by it.
fn frame(ph: &Phantom, i: usize) -> capsule_slam_framework::frame::RgbdFrame {
    let mut f = rgbd(ph, i);
    let d = &f.depth_m;
    f.depth_sigma_m = Some(capsule_slam_framework::DepthMap::from_fn(d.width(), d.height(), |x, y| [2e-4 + 0.2 * d.at(x, y) * d.at(x, y)]));
    f
}

/// Fuses `frames` at their true poses into both fusers, with a depth σ per pixel if
/// `sigma` (the map then weighs by it; f32 division and square root differ by an ulp between
/// the devices, so the tests of deformation, whose gates are tight, fuse without).
fn fuse_both(ph: &Phantom, g: &mut dyn Fuser, c: &mut dyn Fuser, frames: std::ops::Range<usize>, sigma: bool) {
    let rig = rig(ph);
    let mut r = StageReport::default();
    for i in frames {
        let f = if sigma { frame(ph, i) } else { rgbd(ph, i) };
        let pose = f.gt_t_world_cam.unwrap();
        let a = g.fuse(&f, &pose, &mut Context::new(i, &rig, None, &mut r)).unwrap();
        let b = c.fuse(&f, &pose, &mut Context::new(i, &rig, None, &mut r)).unwrap();
        let (da, db) = (a.added as f64, b.added as f64);
        assert!((da - db).abs() <= 0.01 * db.max(100.0), "frame {i}: gpu {a:?}, cpu {b:?}");
    }
}

/// Surfels of both maps that agree (position within 1 µm, same times, confidence to 1e-4,
/// colour within one level), as a share of the CPU map; the counts must match to 1 %. Each CPU
/// surfel looks for its twin among the GPU surfels of its creation time near its x (a snapshot
/// is sorted by t0, then position), so that one association flipped on a gate (f32 rounding)
/// costs a surfel or two, not the order of everything after it.
fn agreement(g: &[Surfel], c: &[Surfel]) -> f64 {
    assert!((g.len() as f64 - c.len() as f64).abs() <= 0.01 * c.len() as f64, "gpu {} surfels, cpu {}", g.len(), c.len());
    let same = |a: &Surfel, b: &Surfel| {
        (a.position_m - b.position_m).norm() < 1e-6
            && (a.normal - b.normal).norm() < 1e-4
            && a.t0 == b.t0
            && a.t == b.t
            && (a.confidence - b.confidence).abs() < 1e-4
            && (a.radius_m - b.radius_m).abs() < 1e-7
            && (a.sigma_m - b.sigma_m).abs() <= 1e-5 * b.sigma_m
            && (a.warp_m - b.warp_m).norm() < 1e-6
            && a.colour.iter().zip(&b.colour).all(|(x, y)| x.abs_diff(*y) <= 1)
    };
    let key = |s: &Surfel| (s.t0, s.position_m.x);
    let matched = c
        .iter()
        .filter(|b| {
            let (t0, x) = key(b);
            let from = g.partition_point(|a| key(a) < (t0, x - 1e-6));
            g[from..].iter().take_while(|a| key(a) <= (t0, x + 1e-6)).any(|a| same(a, b))
        })
        .count();
    matched as f64 / c.len() as f64
}

/// Share of pixels where both predictions agree: both empty, or depths within 1 µm and the
/// same surfel times.
fn view_agreement(a: &ModelView, b: &ModelView) -> (f64, usize) {
    let n = a.depth_m.data().len();
    let mut same = 0;
    let mut filled = 0;
    for k in 0..n {
        let (da, db) = (a.depth_m.data()[k], b.depth_m.data()[k]);
        filled += usize::from(db > 0.0);
        let ok = if da == 0.0 || db == 0.0 { da == db } else { (da - db).abs() < 1e-6 && a.t.data()[k] == b.t.data()[k] && a.t0.data()[k] == b.t0.data()[k] };
        same += usize::from(ok);
    }
    (same as f64 / n as f64, filled)
}

/// [`view_agreement`] of both fusers' predictions of `set` from the true pose of frame
/// `frames.0`, at frame `frames.1`.
fn prediction_agreement(ph: &Phantom, (g, c): (&mut dyn Fuser, &mut dyn Fuser), set: ModelSet, frames: (usize, usize)) -> (f64, usize) {
    let (rig, mut r) = (rig(ph), StageReport::default());
    let pose = rgbd(ph, frames.0).gt_t_world_cam.unwrap();
    let a = g.predict(&pose, set, &mut Context::new(frames.1, &rig, None, &mut r)).unwrap();
    let b = c.predict(&pose, set, &mut Context::new(frames.1, &rig, None, &mut r)).unwrap();
    view_agreement(&a, &b)
}

fn builders(ph: &Phantom, cap: Option<u32>, gpu: &GpuHandle) -> (SurfelGpu, SurfelCpu) {
    builders_with(ph, cap, gpu, params())
}

fn builders_with(ph: &Phantom, cap: Option<u32>, gpu: &GpuHandle, p: SurfelParams) -> (SurfelGpu, SurfelCpu) {
    let env = BuildEnv::new(rig(ph), None).with_gpu(gpu.clone());
    let g = SurfelGpu::with_capacity(p.clone(), &env, cap).unwrap();
    (g, SurfelCpu::build(p, &env).unwrap())
}

#[test]
fn the_gpu_map_and_its_predictions_equal_the_cpu_ones() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("the_gpu_map_and_its_predictions_equal_the_cpu_ones").is_none() {
        return;
    }
    let ph = phantom(2, 24, 0.0);
    // Room for 1 000 surfels at first: the map grows on the device many times.
    let (mut g, mut c) = builders(&ph, Some(1000), &gpu);
    fuse_both(&ph, &mut g, &mut c, 0..24, true);
    let (sg, sc) = (g.snapshot().unwrap().surfels, c.snapshot().unwrap().surfels);
    let share = agreement(&sg, &sc);
    // Measured: every surfel (34 000) agrees.
    assert!(share > 0.999, "only {:.2} % of the surfels agree", 100.0 * share);
    assert_eq!(g.stats(), c.stats(), "counts");
    assert!(c.stats().total > c.stats().active && c.stats().active > 0, "both sets are exercised: {:?}", c.stats());
    assert!(sc.iter().all(|s| s.sigma_m > 2e-4), "every surfel carries its depth σ");
    for (set, pose_frame) in [(ModelSet::Active, 23), (ModelSet::Inactive, 3)] {
        let (share, filled) = prediction_agreement(&ph, (&mut g, &mut c), set, (pose_frame, 23));
        assert!(filled > 500, "{set:?}: the CPU prediction has only {filled} pixels");
        // Measured: 100 % (active and inactive).
        assert!(share > 0.998, "{set:?}: only {:.2} % of the pixels agree", 100.0 * share);
    }
}

#[test]
fn a_revisit_reactivates_the_same_surfels_on_both() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("a_revisit_reactivates_the_same_surfels_on_both").is_none() {
        return;
    }
    // Forth along frames 0..12, then back from frame 11 to 0 (indices 12..24): with δt 3 the
    // start of the path is inactive when the capsule returns to it.
    let ph = phantom(2, 12, 0.0);
    let p = SurfelParams { delta_t: 3, ..params() };
    let forth_and_back = |p: SurfelParams| {
        let (mut g, mut c) = builders_with(&ph, None, &gpu, p);
        fuse_both(&ph, &mut g, &mut c, 0..12, false);
        let (rig, mut r) = (rig(&ph), StageReport::default());
        for k in 12..24 {
            let mut f = rgbd(&ph, 23 - k);
            f.index = k;
            let pose = f.gt_t_world_cam.unwrap();
            let a = g.fuse(&f, &pose, &mut Context::new(k, &rig, None, &mut r)).unwrap();
            let b = c.fuse(&f, &pose, &mut Context::new(k, &rig, None, &mut r)).unwrap();
            assert!(a.added.abs_diff(b.added) as f64 <= 0.01 * (b.added as f64).max(100.0), "frame {k}: gpu {a:?}, cpu {b:?}");
        }
        (g, c)
    };
    let (g, c) = forth_and_back(p.clone());
    let (sg, sc) = (g.snapshot().unwrap().surfels, c.snapshot().unwrap().surfels);
    // A few associations that sit on a gate flip with the last bits of f32, so the counts
    // may differ by a handful.
    assert!(agreement(&sg, &sc) > 0.999, "only {:.2} % of the surfels agree", 100.0 * agreement(&sg, &sc));
    let (a, b) = (g.stats(), c.stats());
    assert!(a.total.abs_diff(b.total) * 1000 <= b.total && a.active.abs_diff(b.active) * 1000 <= b.active, "gpu {a:?}, cpu {b:?}");
    // Surfels of the way out that the way back saw again, on both maps; with ElasticFusion's
    // rule, those that were inactive by then stay so and the way back lays new ones.
    let revisited = |s: &[Surfel]| s.iter().filter(|s| s.t0 <= 2 && s.t >= 20).count();
    let (_, ef) = forth_and_back(SurfelParams { revisit_reactivation: false, ..p });
    let sef = ef.snapshot().unwrap().surfels;
    // Measured: 517 against 13.
    assert!(revisited(&sc) > 300 && revisited(&sef) < revisited(&sc) / 10, "{} revisited, {} with ElasticFusion's rule", revisited(&sc), revisited(&sef));
    assert!(revisited(&sg).abs_diff(revisited(&sc)) * 100 <= revisited(&sc), "gpu {}, cpu {}", revisited(&sg), revisited(&sc));
    assert!(sc.len() < sef.len(), "{} surfels, {} with ElasticFusion's rule", sc.len(), sef.len());
}

#[test]
fn a_warp_shortens_the_active_window_alike_on_both() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("a_warp_shortens_the_active_window_alike_on_both").is_none() {
        return;
    }
    // Frames 0..16 at their true poses, the wall said to move at frame 10 (a warp that moves
    // nothing): at frame 15 the window is 5 frames (15 − 10), not δt = 8, on both maps, and
    // neither revives by a revisit what was last seen before frame 10.
    let ph = phantom(2, 16, 0.0);
    let run = |p: SurfelParams| {
        let (mut g, mut c) = builders_with(&ph, None, &gpu, p);
        fuse_both(&ph, &mut g, &mut c, 0..10, false);
        let (rig, mut r) = (rig(&ph), StageReport::default());
        let nodes = vec![DeformationNode::identity(Point3::new(0.0, 0.0, 0.05), 0)];
        let warp = Deformation::new(nodes, 4, Window::All);
        g.warp(&warp, &mut Context::new(10, &rig, None, &mut r)).unwrap();
        c.warp(&warp, &mut Context::new(10, &rig, None, &mut r)).unwrap();
        fuse_both(&ph, &mut g, &mut c, 10..16, false);
        (g, c)
    };
    let (mut g, mut c) = run(SurfelParams { delta_t_moving: 2, ..params() });
    assert_eq!((g.active_window(), c.active_window()), (Some(5), Some(5)));
    let (a, b) = (g.stats(), c.stats());
    assert!(a.active.abs_diff(b.active) * 1000 <= b.active, "gpu {a:?}, cpu {b:?}");
    // Without the rule (δt_moving ≥ δt) the window is δt, and the maps differ.
    let (_, plain) = run(params());
    assert_eq!(plain.active_window(), Some(8));
    assert_ne!(b, plain.stats());
    for (set, pose_frame) in [(ModelSet::Active, 15), (ModelSet::Inactive, 8)] {
        let (share, filled) = prediction_agreement(&ph, (&mut g, &mut c), set, (pose_frame, 15));
        assert!(filled > 500, "{set:?}: the CPU prediction has only {filled} pixels");
        assert!(share > 0.998, "{set:?}: only {:.2} % of the pixels agree", 100.0 * share);
    }
}

#[test]
fn elasticfusions_nearest_wins_splat_is_the_same_on_both() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("elasticfusions_nearest_wins_splat_is_the_same_on_both").is_none() {
        return;
    }
    let ph = phantom(2, 12, 0.0005);
    let (mut g, mut c) = builders_with(&ph, None, &gpu, SurfelParams { splat_blend_depth_m: 0.0, ..params() });
    fuse_both(&ph, &mut g, &mut c, 0..12, false);
    let (share, filled) = prediction_agreement(&ph, (&mut g, &mut c), ModelSet::Active, (11, 11));
    assert!(filled > 500 && share > 0.998, "{filled} pixels, {:.2} % agree", 100.0 * share);
}

#[test]
fn the_same_frames_give_the_same_map_every_time() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("the_same_frames_give_the_same_map_every_time").is_none() {
        return;
    }
    let ph = phantom(1, 12, 0.0005);
    let run = || {
        let (mut g, mut c) = builders(&ph, None, &gpu);
        fuse_both(&ph, &mut g, &mut c, 0..12, true);
        g.snapshot().unwrap().surfels
    };
    let (a, b) = (run(), run());
    assert_eq!(a.len(), b.len());
    assert!(a.iter().zip(&b).all(|(x, y)| x == y), "two runs differ");
}

#[test]
fn a_closure_moves_the_gpu_map_like_the_cpu_map_and_reactivates_it() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("a_closure_moves_the_gpu_map_like_the_cpu_map_and_reactivates_it").is_none() {
        return;
    }
    let ph = phantom(2, 20, 0.0);
    let (mut g, mut c) = builders(&ph, None, &gpu);
    fuse_both(&ph, &mut g, &mut c, 0..20, false);
    // A rigid correction expressed per node: R (v − g) + g + t with t = R g + s − g.
    let rot = Rotation3::from_euler_angles(0.01, -0.02, 0.015);
    let shift = Vector3::new(0.0005, -0.0003, 0.0008);
    let nodes = (0..27)
        .map(|i| {
            let p = Point3::new(f64::from(i % 3) * 0.02 - 0.02, f64::from((i / 3) % 3) * 0.02 - 0.02, f64::from(i / 9) * 0.02);
            let mut n = DeformationNode::identity(p, 0);
            n.rotation = *rot.matrix();
            n.translation_m = rot * p.coords + shift - p.coords;
            n
        })
        .collect();
    let closure = LoopClosure { deformation: Deformation::new(nodes, 4, Window::All), t_world_cam: rgbd(&ph, 2).gt_t_world_cam.unwrap() };
    let rig = rig(&ph);
    let mut r = StageReport::default();
    let before = g.stats();
    let centroid = |s: &[Surfel]| s.iter().map(|s| s.position_m.coords.cast::<f64>()).sum::<Vector3<f64>>() / s.len() as f64;
    let normal_sum = |s: &[Surfel]| s.iter().map(|s| s.normal.cast::<f64>()).sum::<Vector3<f64>>() / s.len() as f64;
    let old = g.snapshot().unwrap().surfels;
    g.deform(&closure, &mut Context::new(20, &rig, None, &mut r)).unwrap();
    let reactivated_gpu = r.counters["surfels_reactivated"];
    c.deform(&closure, &mut Context::new(20, &rig, None, &mut r)).unwrap();
    assert_eq!(reactivated_gpu, r.counters["surfels_reactivated"]);
    assert!(reactivated_gpu > 100.0, "the old surface seen from frame 2's pose is reactivated: {reactivated_gpu}");
    assert!(g.stats().active > before.active);
    let (sg, sc) = (g.snapshot().unwrap().surfels, c.snapshot().unwrap().surfels);
    assert!(agreement(&sg, &sc) > 0.999);
    assert!(sg.iter().all(|s| s.warp_m == Vector3::zeros()), "a closure corrects drift: it is not wall motion");
    // And it moved rigidly (a snapshot is sorted by position, so compare the centroid and the
    // mean normal): R c + s, R n̄.
    let moved = rot * centroid(&old) + shift;
    assert!((centroid(&sg) - moved).norm() < 1e-6, "{:?} vs {moved:?}", centroid(&sg));
    assert!((normal_sum(&sg) - rot * normal_sum(&old)).norm() < 1e-5);
}

#[test]
fn a_camera_of_another_size_is_an_error_not_a_crash() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("a_camera_of_another_size_is_an_error_not_a_crash").is_none() {
        return;
    }
    let ph = phantom(1, 2, 0.0);
    let (mut g, _) = builders(&ph, None, &gpu);
    let big = capsule_slam_framework::camera::Rig::Mono(capsule_slam_framework::PinholeCamera::new(64, 48, 50.0, 50.0, 31.5, 23.5));
    let mut r = StageReport::default();
    let err = g.predict(&Iso3::identity(), ModelSet::Active, &mut Context::new(0, &big, None, &mut r)).unwrap_err().to_string();
    assert!(err.contains("64×48"), "{err}");
}

#[test]
fn a_trackers_warp_moves_both_maps_alike_and_nothing_else() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("a_trackers_warp_moves_both_maps_alike_and_nothing_else").is_none() {
        return;
    }
    let ph = phantom(2, 20, 0.0);
    let (mut g, mut c) = builders(&ph, None, &gpu);
    fuse_both(&ph, &mut g, &mut c, 0..20, false);
    // A smooth, non-rigid warp: nodes on a 3 × 3 × 3 grid, each pushed along z by up to 1 mm
    // with x, as a wave would push the wall.
    let nodes = (0..27)
        .map(|i| {
            let p = Point3::new(f64::from(i % 3) * 0.02 - 0.02, f64::from((i / 3) % 3) * 0.02 - 0.02, f64::from(i / 9) * 0.02);
            let mut n = DeformationNode::identity(p, 0);
            n.translation_m = Vector3::new(0.0, 0.0, 0.0005 * (1.0 + p.x / 0.02));
            n
        })
        .collect();
    let warp = Deformation::new(nodes, 4, Window::All);
    let rig = rig(&ph);
    let mut r = StageReport::default();
    let (before, old) = (c.stats(), c.snapshot().unwrap().surfels);
    // The same frames as the closure test: both maps agree surfel for surfel before the warp
    // (a different frame count can flip one association that sits on a gate).
    assert!(agreement(&g.snapshot().unwrap().surfels, &old) > 0.999);
    g.warp(&warp, &mut Context::new(20, &rig, None, &mut r)).unwrap();
    c.warp(&warp, &mut Context::new(20, &rig, None, &mut r)).unwrap();
    let (sg, sc) = (g.snapshot().unwrap().surfels, c.snapshot().unwrap().surfels);
    assert!(agreement(&sg, &sc) > 0.999, "the GPU and the CPU map moved alike: {}", agreement(&sg, &sc));
    assert_eq!(c.stats(), before, "a warp adds, removes and reactivates nothing");
    assert_eq!(g.stats(), before);
    // Every surfel moved where the deformation puts it, and counts the move as wall motion
    // (the snapshot is sorted by position, so compare the sorted warped old map).
    let mut expected = old.clone();
    let warper = warp.warper();
    expected.iter_mut().for_each(|s| warper.warp_surfel_as_motion(s));
    let expected = capsule_slam_framework::SurfelSet::new(expected).surfels;
    let moved = sc.iter().zip(&expected).filter(|(a, b)| (a.position_m - b.position_m).norm() < 1e-7 && (a.warp_m - b.warp_m).norm() < 1e-7).count();
    assert_eq!(moved, sc.len());
    assert!(sg.iter().filter(|s| s.warp_m.z > 1e-4).count() > sg.len() / 2, "the GPU map carries the displacement too");
    let mean_dz = sc.iter().map(|s| f64::from(s.position_m.z)).sum::<f64>() / sc.len() as f64
        - old.iter().map(|s| f64::from(s.position_m.z)).sum::<f64>() / old.len() as f64;
    assert!(mean_dz > 1e-4, "the map moved along z: {mean_dz}");
}

#[test]
fn raising_the_maps_sigma_gives_the_same_sigma_on_both() {
    let gpu = GpuHandle::new();
    if gpu.get_or_skip("raising_the_maps_sigma_gives_the_same_sigma_on_both").is_none() {
        return;
    }
    let ph = phantom(2, 6, 0.0);
    let (mut g, mut c) = builders(&ph, None, &gpu);
    fuse_both(&ph, &mut g, &mut c, 0..6, true);
    let noise = capsule_slam_framework::depth_noise::DepthNoiseModel { absolute_m: 0.0, relative: 0.05, quadratic_per_m: 0.0, correlation_px: 80.0 };
    let (rig, mut r) = (rig(&ph), StageReport::default());
    let pose = ph.pose(5);
    for f in [&mut g as &mut dyn Fuser, &mut c] {
        f.raise_sigma(&noise, &pose, &mut Context::new(5, &rig, None, &mut r)).unwrap();
    }
    let (sg, sc) = (g.snapshot().unwrap().surfels, c.snapshot().unwrap().surfels);
    assert!(agreement(&sg, &sc) > 0.999);
    // Every surfel now has at least 5 % of its depth in the camera of frame 5 (its distance
    // where it lies behind it).
    let t_cam_world = pose.inverse();
    for s in &sc {
        let p = t_cam_world * s.position_m.cast::<f64>();
        let z = if p.z > 0.0 { p.z } else { p.coords.norm() };
        assert!(f64::from(s.sigma_m) >= 0.05 * z - 1e-7, "σ {} at {z} m", s.sigma_m);
    }
    assert!(sc.iter().filter(|s| s.sigma_m > 1e-3).count() > sc.len() / 2, "most surfels lie centimetres away");
    let sigma_sum = |m: &[Surfel]| m.iter().map(|s| s.sigma_m).sum::<f32>();
    let (a, b) = (sigma_sum(&sg), sigma_sum(&sc));
    assert!((a - b).abs() <= 1e-4 * b, "σ summed: gpu {a}, cpu {b}");
}
