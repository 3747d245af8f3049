use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{Context, Fuser, ModelSet, Plugin};

use super::SurfelCpu;
use crate::fuse::surfel_params::SurfelParams;
use crate::testing::{phantom, rgbd, rig};

fn fuser(p: SurfelParams, ph: &capsule_slam_phantom::Phantom) -> SurfelCpu {
    SurfelCpu::build(p, &BuildEnv::new(rig(ph), None)).unwrap()
}

#[test]
fn fusing_the_same_frame_twice_adds_no_surfels() {
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let f = rgbd(&ph, 3);
    let pose = f.gt_t_world_cam.unwrap();
    let mut s = fuser(SurfelParams::default(), &ph);
    let mut r = StageReport::default();
    let first = s.fuse(&f, &pose, &mut Context::new(3, &rig, None, &mut r)).unwrap();
    assert!(first.added > 5000, "{first:?}");
    let second = s.fuse(&f, &pose, &mut Context::new(3, &rig, None, &mut r)).unwrap();
    assert_eq!(second.added, 0, "{second:?}");
    assert_eq!(second.merged, first.added);
}

#[test]
fn predicting_a_fused_frame_from_its_pose_reproduces_its_depth() {
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let f = rgbd(&ph, 4);
    let pose = f.gt_t_world_cam.unwrap();
    let mut s = fuser(SurfelParams { stable_confidence: 0.0, subsample: 1, ..SurfelParams::default() }, &ph);
    let mut r = StageReport::default();
    s.fuse(&f, &pose, &mut Context::new(4, &rig, None, &mut r)).unwrap();
    let view = s.predict(&pose, ModelSet::Active, &mut Context::new(4, &rig, None, &mut r)).unwrap();
    let mut err: Vec<f32> = Vec::new();
    let mut valid = 0;
    for (p, t) in view.depth_m.data().iter().zip(f.depth_m.data()) {
        if *t > 0.0 {
            valid += 1;
            if *p > 0.0 {
                err.push((p - t).abs());
            }
        }
    }
    err.sort_by(f32::total_cmp);
    assert!(err.len() as f64 > 0.95 * valid as f64, "coverage {} of {valid}", err.len());
    let median = err[err.len() / 2];
    assert!(median < 1e-4, "median depth error {median}");
}

#[test]
fn the_active_split_follows_delta_t_and_stale_unstable_surfels_go() {
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let f = rgbd(&ph, 0);
    let pose = f.gt_t_world_cam.unwrap();
    let mut s = fuser(SurfelParams { stable_confidence: 0.0, delta_t: 50, ..SurfelParams::default() }, &ph);
    let mut r = StageReport::default();
    s.fuse(&f, &pose, &mut Context::new(0, &rig, None, &mut r)).unwrap();
    let n = s.stats().total;
    let active_at = |s: &mut SurfelCpu, now: usize, set| {
        let mut r = StageReport::default();
        s.predict(&pose, set, &mut Context::new(now, &rig, None, &mut r)).unwrap().valid_pixels()
    };
    assert!(active_at(&mut s, 50, ModelSet::Active) > 1000);
    assert_eq!(active_at(&mut s, 50, ModelSet::Inactive), 0);
    assert_eq!(active_at(&mut s, 51, ModelSet::Active), 0);
    assert!(active_at(&mut s, 51, ModelSet::Inactive) > 1000);

    // With the default threshold these surfels are unstable; unseen for 21 frames they go.
    let mut u = fuser(SurfelParams::default(), &ph);
    u.fuse(&f, &pose, &mut Context::new(0, &rig, None, &mut r)).unwrap();
    assert_eq!(u.stats().total, n);
    let mut empty = f.clone();
    empty.index = 20;
    empty.depth_m.data_mut().iter_mut().for_each(|d| *d = 0.0);
    u.fuse(&empty, &pose, &mut Context::new(20, &rig, None, &mut r)).unwrap();
    assert_eq!(u.stats().total, n, "20 frames unseen: kept");
    empty.index = 21;
    u.fuse(&empty, &pose, &mut Context::new(21, &rig, None, &mut r)).unwrap();
    assert_eq!(u.stats().total, 0, "21 frames unseen: removed");
}

/// A deformation that moves nothing: a tracker's warp of a wall that moved too little to see.
fn still_warp() -> capsule_slam_framework::deformation::Deformation {
    use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
    Deformation::new(vec![DeformationNode::identity(nalgebra::Point3::new(0.0, 0.0, 0.05), 0)], 4, Window::All)
}

#[test]
fn a_warp_shortens_the_active_window_of_what_the_camera_left_before_it() {
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let f = rgbd(&ph, 0);
    let pose = f.gt_t_world_cam.unwrap();
    let p = SurfelParams { stable_confidence: 0.0, delta_t: 100, delta_t_moving: 30, subsample: 1, ..SurfelParams::default() };
    let mut r = StageReport::default();
    let valid = |s: &mut SurfelCpu, now: usize, set| {
        let mut r = StageReport::default();
        s.predict(&pose, set, &mut Context::new(now, &rig, None, &mut r)).unwrap().valid_pixels()
    };
    // A wall that never moved: the map seen at frame 0 is active up to frame 100.
    let mut still = fuser(p.clone(), &ph);
    let first = still.fuse(&f, &pose, &mut Context::new(0, &rig, None, &mut r)).unwrap();
    assert!(valid(&mut still, 60, ModelSet::Active) > 1000);
    assert_eq!(still.active_window(), Some(100));

    // The wall moved at frame 5 (a warp): the map seen before it is active for 30 frames only.
    let mut moving = fuser(p, &ph);
    moving.fuse(&f, &pose, &mut Context::new(0, &rig, None, &mut r)).unwrap();
    moving.warp(&still_warp(), &mut Context::new(5, &rig, None, &mut r)).unwrap();
    assert!(valid(&mut moving, 30, ModelSet::Active) > 1000);
    assert_eq!(valid(&mut moving, 31, ModelSet::Active), 0);
    assert!(valid(&mut moving, 31, ModelSet::Inactive) > 1000);
    // It does not come back as the window grows back: the window stays below its age.
    assert_eq!(valid(&mut moving, 99, ModelSet::Active), 0);
    // Seen again at frame 60, it is not revived (the wall moved since it was seen): the frame
    // lays new surfels, which keep the whole window from there.
    let mut back = f.clone();
    back.index = 60;
    let again = moving.fuse(&back, &pose, &mut Context::new(60, &rig, None, &mut r)).unwrap();
    assert_eq!((again.added, again.merged), (first.added, 0), "{again:?}");
    assert_eq!(moving.stats().active, first.added);
    assert!(moving.surfels()[..first.added].iter().all(|s| s.t == 0), "the stale surface stays as it was");
    assert!(valid(&mut moving, 155, ModelSet::Active) > 1000);
    assert_eq!(moving.active_window(), Some(55), "60 − 5 frames since the wall last moved");

    // What was seen after the last warp is revived by a revisit: seen at 6, again at 200.
    let mut after = fuser(SurfelParams { stable_confidence: 0.0, delta_t: 100, delta_t_moving: 30, subsample: 1, ..SurfelParams::default() }, &ph);
    let mut seen = |s: &mut SurfelCpu, i: usize| {
        let mut g = f.clone();
        g.index = i;
        s.fuse(&g, &pose, &mut Context::new(i, &rig, None, &mut r)).unwrap()
    };
    seen(&mut after, 0);
    after.warp(&still_warp(), &mut Context::new(5, &rig, None, &mut StageReport::default())).unwrap();
    seen(&mut after, 6);
    assert_eq!(valid(&mut after, 200, ModelSet::Active), 0, "inactive by frame 200");
    let revisit = seen(&mut after, 200);
    assert_eq!((revisit.added, revisit.merged), (0, first.added), "{revisit:?}");
}

#[test]
fn a_revisited_wall_merges_into_its_inactive_surfels_and_reactivates_them() {
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let f = rgbd(&ph, 0);
    let pose = f.gt_t_world_cam.unwrap();
    let mut back = f.clone();
    back.index = 60;
    let p = SurfelParams { stable_confidence: 0.0, delta_t: 50, subsample: 1, ..SurfelParams::default() };
    let mut r = StageReport::default();
    let mut fuse = |s: &mut SurfelCpu, f: &capsule_slam_framework::frame::RgbdFrame| s.fuse(f, &pose, &mut Context::new(f.index, &rig, None, &mut r)).unwrap();

    // Frame 60 sees the wall that frame 0 mapped, now inactive: it merges into it, adds
    // nothing, and the whole map is active again.
    let mut s = fuser(p.clone(), &ph);
    let first = fuse(&mut s, &f);
    let alpha: Vec<f32> = s.surfels().iter().map(|x| x.confidence).collect();
    let again = fuse(&mut s, &back);
    assert_eq!((again.added, again.merged), (0, first.added), "{again:?}");
    assert_eq!(s.stats().active, first.added);
    assert!(s.surfels().iter().zip(&alpha).all(|(x, a)| x.t == 60 && x.t0 == 0 && (x.confidence - 2.0 * a).abs() < 1e-5));

    // ElasticFusion's rule (`revisit_reactivation = false`): a second layer of the same size.
    let mut e = fuser(SurfelParams { revisit_reactivation: false, ..p.clone() }, &ph);
    fuse(&mut e, &f);
    let layered = fuse(&mut e, &back);
    assert_eq!((layered.added, layered.merged), (first.added, 0));
    assert_eq!(e.stats().total, 2 * first.added);

    // A wall 5 mm behind the old one (beyond the 2 mm gate) is another surface, not a revisit.
    let mut moved = back.clone();
    moved.depth_m.data_mut().iter_mut().filter(|d| **d > 0.0).for_each(|d| *d += 0.005);
    let mut m = fuser(p, &ph);
    fuse(&mut m, &f);
    let other = fuse(&mut m, &moved);
    assert_eq!(other.merged, 0, "{other:?}");
    assert!(other.added as f64 > 0.95 * first.added as f64, "{other:?} against {first:?}");
}

#[test]
fn fused_surfels_lie_on_the_phantom_wall() {
    let ph = phantom(2, 30, 0.0);
    let rig = rig(&ph);
    let mut s = fuser(SurfelParams::default(), &ph);
    let mut r = StageReport::default();
    for i in 0..6 {
        let f = rgbd(&ph, i);
        s.fuse(&f, &f.gt_t_world_cam.unwrap(), &mut Context::new(i, &rig, None, &mut r)).unwrap();
    }
    let mut d: Vec<f64> = s.surfels().iter().map(|x| ph.shape.implicit(&x.position_m.cast(), 0.0).abs()).collect();
    d.sort_by(f64::total_cmp);
    assert!(d[d.len() / 2] < 1e-4, "median distance to the wall {}", d[d.len() / 2]);
    assert!(d[d.len() * 95 / 100] < 5e-4, "95th percentile {}", d[d.len() * 95 / 100]);
}

/// p99 of |predicted − observed| albedo over the predicted pixels.
fn albedo_error_p99(view: &capsule_slam_framework::ModelView, albedo: &capsule_slam_framework::GrayF32) -> (f32, usize) {
    let mut errors: Vec<f32> =
        view.depth_m.data().iter().zip(view.albedo.data().iter().zip(albedo.data())).filter(|(d, _)| **d > 0.0).map(|(_, (p, o))| (p - o).abs()).collect();
    errors.sort_by(f32::total_cmp);
    (errors.get(errors.len() * 99 / 100).copied().unwrap_or(f32::INFINITY), errors.len())
}

#[test]
fn observed_albedo_is_fused_and_predicted_back() {
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let mut f = rgbd(&ph, 4);
    let pose = f.gt_t_world_cam.unwrap();
    // An albedo image that varies across the frame: 0.2 left to 0.6 right.
    let (w, h) = f.depth_m.size();
    let mut albedo = capsule_slam_framework::GrayF32::new(w, h);
    for y in 0..h {
        for x in 0..w {
            *albedo.at_mut(x, y) = 0.2 + 0.4 * x as f32 / w as f32;
        }
    }
    f.albedo = Some(albedo.clone());
    let mut s = fuser(SurfelParams { stable_confidence: 0.0, subsample: 1, ..SurfelParams::default() }, &ph);
    let mut r = StageReport::default();
    s.fuse(&f, &pose, &mut Context::new(4, &rig, None, &mut r)).unwrap();
    s.fuse(&f, &pose, &mut Context::new(4, &rig, None, &mut r)).unwrap();
    let view = s.predict(&pose, ModelSet::Active, &mut Context::new(4, &rig, None, &mut r)).unwrap();
    // A surfel predicted one pixel off carries its neighbour's albedo: 0.4 / 250 per pixel.
    let (p99, n) = albedo_error_p99(&view, &albedo);
    assert!(n > 10_000 && p99 < 0.01, "p99 albedo error {p99} over {n} pixels");
    // A frame without albedo leaves the fused albedo as it is.
    f.albedo = None;
    s.fuse(&f, &pose, &mut Context::new(5, &rig, None, &mut r)).unwrap();
    let again = s.predict(&pose, ModelSet::Active, &mut Context::new(5, &rig, None, &mut r)).unwrap();
    let (p99, n) = albedo_error_p99(&again, &albedo);
    assert!(n > 10_000 && p99 < 0.01, "after a frame without albedo: p99 {p99} over {n} pixels");
}

/// A disc facing the camera on its axis at `z_m`, of radius 2 mm.
fn disc_at(z_m: f32, confidence: f32, colour: u8) -> capsule_slam_framework::Surfel {
    capsule_slam_framework::Surfel {
        position_m: nalgebra::Point3::new(0.0, 0.0, z_m),
        normal: nalgebra::Vector3::new(0.0, 0.0, -1.0),
        colour: [colour; 3],
        confidence,
        radius_m: 0.002,
        t0: 0,
        t: 0,
        albedo: 0.0,
        sigma_m: 0.0,
        warp_m: nalgebra::Vector3::zeros(),
    }
}

#[test]
fn the_splat_shows_the_most_confident_disc_within_blend_depth_of_the_nearest() {
    use super::{SplatDepths, predict};
    let cam = capsule_slam_framework::camera::PinholeCamera::new(64, 64, 60.0, 60.0, 31.5, 31.5);
    let pose = capsule_slam_framework::Iso3::identity();
    // A noisy, weak disc in front; the well-fused wall 0.6 mm behind it; a very confident disc
    // 3 mm further (another surface).
    let mut discs = [disc_at(0.0500, 2.0, 10), disc_at(0.0506, 30.0, 20), disc_at(0.0536, 500.0, 30)];
    discs[1].sigma_m = 6e-4;
    let centre = |d: &SplatDepths| {
        let v = predict(&discs, |_| true, &cam, &pose, d);
        let k = 32 * 64 + 32;
        (v.depth_m.data()[k], v.colour.pixel(32, 32)[0], v.confidence.data()[k])
    };
    let (z, colour, conf) = centre(&SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.001, stable: 1000.0 });
    assert_eq!((colour, conf), (20, 30.0), "the most confident disc within 1 mm is shown");
    assert!((z - 0.0506).abs() < 1e-6, "at its own depth, not the nearest's: {z}");
    let v = predict(&discs, |_| true, &cam, &pose, &SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.001, stable: 1000.0 });
    let sigma = v.sigma_m.at(32, 32);
    assert!((sigma - 6e-4 / 30f32.sqrt()).abs() < 1e-9, "the σ of a mean of 30 measurements: {sigma}");
    let (z, colour, _) = centre(&SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.0, stable: 1000.0 });
    assert_eq!(colour, 10, "ε = 0 is ElasticFusion's nearest-wins z-test");
    assert!((z - 0.05).abs() < 1e-6, "{z}");
    let (_, colour, _) = centre(&SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.01, stable: 1000.0 });
    assert_eq!(colour, 30, "a wider ε reaches the third disc");
    // Confidence counts up to `stable` (ElasticFusion's c_stable): two stable discs tie, and
    // the one created first wins, however much longer the other was fused; the weak disc
    // in front still loses.
    let (_, colour, _) = centre(&SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.01, stable: 10.0 });
    assert_eq!(colour, 20, "the confidence is capped at stable_confidence");
    let (_, colour, _) = centre(&SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.01, stable: 40.0 });
    assert_eq!(colour, 30, "below the cap the more confident disc wins");
    // At ε = 0 the z-test is ElasticFusion's: equal depths go to the most confident, uncapped.
    let tie = [disc_at(0.05, 20.0, 1), disc_at(0.05, 50.0, 2)];
    let v = predict(&tie, |_| true, &cam, &pose, &SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.0, stable: 10.0 });
    assert_eq!(v.colour.pixel(32, 32)[0], 2);
    // Equal confidence: the lowest index wins, whatever the depth order.
    let tie = [disc_at(0.0506, 5.0, 1), disc_at(0.0500, 5.0, 2)];
    let v = predict(&tie, |_| true, &cam, &pose, &SplatDepths { min_m: 0.001, max_m: 0.2, blend_m: 0.001, stable: 1000.0 });
    assert_eq!(v.colour.pixel(32, 32)[0], 1);
}

#[test]
fn a_trackers_warp_adds_up_in_each_surfel_and_a_closure_does_not() {
    use capsule_slam_framework::deformation::{Deformation, DeformationNode, Window};
    use capsule_slam_framework::stage::LoopClosure;
    use nalgebra::{Point3, Vector3};
    let ph = phantom(1, 10, 0.0);
    let rig = rig(&ph);
    let f = rgbd(&ph, 3);
    let pose = f.gt_t_world_cam.unwrap();
    let mut s = fuser(SurfelParams::default(), &ph);
    let mut r = StageReport::default();
    s.fuse(&f, &pose, &mut Context::new(3, &rig, None, &mut r)).unwrap();
    assert!(s.surfels().iter().all(|x| x.warp_m == Vector3::zeros()), "a new surfel has not been warped");
    // Two warps that push every node 0.3 mm and then 0.2 mm along z: each surfel has moved 0.5 mm.
    let push = |dz: f64| {
        let nodes = (0..27)
            .map(|i| {
                let p = Point3::new(f64::from(i % 3) * 0.03 - 0.03, f64::from((i / 3) % 3) * 0.03 - 0.03, f64::from(i / 9) * 0.03);
                let mut n = DeformationNode::identity(p, 0);
                n.translation_m = Vector3::new(0.0, 0.0, dz);
                n
            })
            .collect();
        Deformation::new(nodes, 4, Window::All)
    };
    let before: Vec<_> = s.surfels().iter().map(|x| x.position_m).collect();
    s.warp(&push(3e-4), &mut Context::new(4, &rig, None, &mut r)).unwrap();
    s.warp(&push(2e-4), &mut Context::new(5, &rig, None, &mut r)).unwrap();
    for (x, p0) in s.surfels().iter().zip(&before) {
        assert!((x.warp_m - Vector3::new(0.0, 0.0, 5e-4)).norm() < 1e-7, "{:?}", x.warp_m);
        assert!((x.warp_m - (x.position_m - p0)).norm() < 1e-7);
    }
    // A loop closure moves the map too, but that corrects drift: not wall motion.
    s.deform(&LoopClosure { deformation: push(1e-3), t_world_cam: pose }, &mut Context::new(6, &rig, None, &mut r)).unwrap();
    assert!(s.surfels().iter().all(|x| (x.warp_m - Vector3::new(0.0, 0.0, 5e-4)).norm() < 1e-7));
}
