use capsule_slam_framework::Plugin;
use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::frame::{CameraFrame, Masks, Photometry, Views};
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stereo::rectify::Side;
use capsule_slam_phantom::{Phantom, PhantomSpec, SizePreset};

use super::{StereoSgm, StereoSgmParams};

/// A stereo phantom (5 mm) and its rig as the dataset gives it.
fn stereo_phantom(preset: u8) -> (Phantom, Rig) {
    let spec = PhantomSpec { frames: 20, size: SizePreset::Capsule320, stereo_baseline_mm: Some(5.0), ..PhantomSpec::preset(preset) };
    let ph = Phantom::new(spec).unwrap();
    let rig = Phantom::camera_file_for(&ph.spec).rig();
    (ph, rig)
}

fn frame(ph: &Phantom, i: usize) -> CameraFrame {
    let (l, r) = (ph.render_view(i, Side::Left), ph.render_view(i, Side::Right));
    CameraFrame {
        index: i,
        timestamp_s: 0.0,
        views: Views::Stereo { left: l.rgb, right: r.rgb },
        depth_m: Some(l.depth_m),
        gt_t_world_cam: None,
        masks: Masks::new(),
        photometry: Photometry::default(),
    }
}

/// AbsRel, the share more than a pixel of disparity off, and coverage of the field of view.
fn score(est: &capsule_slam_framework::DepthMap, truth: &capsule_slam_framework::DepthMap, rig: &Rig) -> (f64, f64, f64) {
    let cam = rig.camera();
    let fb = cam.fx * rig.baseline_m().unwrap();
    let (mut sum, mut bad, mut n, mut seen) = (0.0, 0usize, 0usize, 0usize);
    for y in 0..cam.height {
        for x in 0..cam.width {
            let t = f64::from(truth.at(x, y));
            if t <= 0.0 || !cam.in_fov(x as f64, y as f64) {
                continue;
            }
            seen += 1;
            let e = f64::from(est.at(x, y));
            if e > 0.0 {
                sum += (e - t).abs() / t;
                bad += usize::from((fb / e - fb / t).abs() > 1.0);
                n += 1;
            }
        }
    }
    (sum / n.max(1) as f64, bad as f64 / n.max(1) as f64, n as f64 / seen.max(1) as f64)
}

#[test]
fn a_phantom_pair_gives_its_depth() {
    let (ph, rig) = stereo_phantom(1);
    let sgm = StereoSgm::build(StereoSgmParams::default(), &BuildEnv::new(rig.clone(), None)).unwrap();
    let f = frame(&ph, 5);
    let (depth, sigma) = sgm.depth(&f).unwrap();
    let (abs_rel, bad, coverage) = score(&depth, f.depth_m.as_ref().unwrap(), &rig);
    eprintln!("AbsRel {abs_rel:.4}, bad > 1 px {bad:.4}, coverage {coverage:.3}");
    assert!(abs_rel < 0.02 && bad < 0.05 && coverage > 0.75, "AbsRel {abs_rel:.4}, bad {bad:.4}, coverage {coverage:.3}");
    // σ grows with the square of the depth.
    let (x, y) = (160, 160);
    let z = f64::from(depth.at(x, y));
    assert!(z > 0.0 && (f64::from(sigma.at(x, y)) - z * z * 0.3 / (160.0 * 0.005)).abs() < 1e-6);
}

#[test]
fn a_mono_rig_is_refused_with_the_fix() {
    let ph = Phantom::new(PhantomSpec { frames: 2, ..PhantomSpec::preset(1) }).unwrap();
    let rig = Phantom::camera_file_for(&ph.spec).rig();
    let err = StereoSgm::build(StereoSgmParams::default(), &BuildEnv::new(rig, None)).err().unwrap().to_string();
    assert!(err.contains("[right]") && err.contains("rgb_right.txt"), "{err}");
}
