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
        right_masks: Masks::new(),
        photometry: Photometry::default(),
        sample_share: None,
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
    // Measured 0.0148, 0.036, 0.785; the geometry leaves about 13 % of the field of view seen by
    // the left camera alone.
    assert!(abs_rel < 0.02 && bad < 0.05 && coverage > 0.7, "AbsRel {abs_rel:.4}, bad {bad:.4}, coverage {coverage:.3}");
    // σ grows with the square of the depth.
    let sd = StereoSgmParams::default().disparity_sigma_px;
    let (x, y) = (160, 160);
    let z = f64::from(depth.at(x, y));
    assert!(z > 0.0 && (f64::from(sigma.at(x, y)) - z * z * sd / (160.0 * 0.005)).abs() < 1e-6);
    // The declared σ_d is the matcher's own error: the RMS of the disparity error over every
    // matched pixel (measured 0.52 px on this frame; 0.46–0.52 px over the 60-frame phantoms
    // of presets 1, 4, 5), within a quarter.
    let (cam, truth) = (rig.camera(), f.depth_m.as_ref().unwrap());
    let fb = cam.fx * rig.baseline_m().unwrap();
    let errors: Vec<f64> = (0..cam.width * cam.height)
        .map(|p| (f64::from(depth.at(p % cam.width, p / cam.width)), f64::from(truth.at(p % cam.width, p / cam.width))))
        .filter(|(e, t)| *e > 0.0 && *t > 0.0)
        .map(|(e, t)| fb / e - fb / t)
        .collect();
    let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    eprintln!("disparity error RMS {rms:.3} px over {} pixels; declared σ_d {sd} px", errors.len());
    assert!((0.75 * rms..=1.25 * rms).contains(&sd), "the matcher's disparity error is {rms:.3} px RMS, the declared σ_d {sd} px");
}

/// The right view's own masks (`CameraFrame::right_masks`, e.g. its highlights) leave no depth
/// where a left pixel's match falls in them; a mask of another size is an error naming it.
#[test]
fn the_right_views_masks_leave_no_depth_where_they_hide_the_match() {
    let (ph, rig) = stereo_phantom(1);
    let sgm = StereoSgm::build(StereoSgmParams::default(), &BuildEnv::new(rig.clone(), None)).unwrap();
    let mut f = frame(&ph, 5);
    let cam = rig.camera();
    let fb = cam.fx * rig.baseline_m().unwrap();
    let truth = f.depth_m.clone().unwrap();
    let (cx, cy, radius) = (150.0, 160.0, 14.0);
    let mut disc = capsule_slam_framework::Mask::new(cam.width, cam.height);
    for y in 0..cam.height {
        for x in 0..cam.width {
            *disc.at_mut(x, y) = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2) < radius * radius;
        }
    }
    // Left pixels whose true match lies 2 px or more inside the disc (the rig is rectified).
    let hidden: Vec<(usize, usize)> = (0..cam.height)
        .flat_map(|y| (0..cam.width).map(move |x| (x, y)))
        .filter(|&(x, y)| {
            let z = f64::from(truth.at(x, y));
            z > 0.0 && ((x as f64 - fb / z - cx).powi(2) + (y as f64 - cy).powi(2)).sqrt() < radius - 2.0
        })
        .collect();
    assert!(hidden.len() > 300, "{} hidden pixels", hidden.len());
    let with_depth = |d: &capsule_slam_framework::DepthMap| hidden.iter().filter(|&&(x, y)| d.at(x, y) > 0.0).count();
    let (open, _) = sgm.depth(&f).unwrap();
    assert!(with_depth(&open) as f64 > 0.8 * hidden.len() as f64, "unmasked, {} of {} have depth", with_depth(&open), hidden.len());
    f.right_masks.insert(capsule_slam_framework::frame::MASK_SPECULAR, disc.clone());
    let (masked, _) = sgm.depth(&f).unwrap();
    assert_eq!(with_depth(&masked), 0, "masked in the right view, none has depth");
    // With `mask_specular = false` a highlight mask leaves the match to the windows; any other
    // mask still hides it.
    let through = StereoSgm::build(StereoSgmParams { mask_specular: false, ..StereoSgmParams::default() }, &BuildEnv::new(rig.clone(), None)).unwrap();
    let (matched, _) = through.depth(&f).unwrap();
    assert!(with_depth(&matched) as f64 > 0.8 * hidden.len() as f64, "highlights matched through, {} of {} have depth", with_depth(&matched), hidden.len());
    let mut g = f.clone();
    g.right_masks.insert("other", disc);
    let (hidden_again, _) = through.depth(&g).unwrap();
    assert_eq!(with_depth(&hidden_again), 0, "a mask other than the highlights still hides the match");
    f.right_masks.insert("other", capsule_slam_framework::Mask::new(7, 5));
    let err = sgm.depth(&f).err().unwrap().to_string();
    assert!(err.contains("right view's masks are 7×5") && err.contains("frame 5"), "{err}");
}

#[test]
fn a_mono_rig_is_refused_with_the_fix() {
    let ph = Phantom::new(PhantomSpec { frames: 2, ..PhantomSpec::preset(1) }).unwrap();
    let rig = Phantom::camera_file_for(&ph.spec).rig();
    let err = StereoSgm::build(StereoSgmParams::default(), &BuildEnv::new(rig, None)).err().unwrap().to_string();
    assert!(err.contains("[right]") && err.contains("rgb_right.txt"), "{err}");
}

/// A smooth texture with detail at several scales (analytic, so any sub-pixel shift is exact).
fn texture(x: f64, y: f64) -> f32 {
    let t = 0.5 * (0.31 * x + 0.17 * y).sin() + 0.35 * (0.11 * x - 0.23 * y + 1.0).sin() + 0.25 * (0.53 * x + 0.41 * y + 2.0).sin();
    (120.0 + 40.0 * t) as f32
}

fn plane_of(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> super::zncc::Plane {
    super::zncc::Plane { gray: (0..w * h).map(|p| f(p % w, p / w)).collect(), invalid: vec![false; w * h], width: w, height: h }
}

fn settings() -> super::matcher::MatchSettings {
    let (ph, rig) = stereo_phantom(1);
    drop(ph);
    let sgm = StereoSgm::build(StereoSgmParams::default(), &BuildEnv::new(rig, None)).unwrap();
    sgm.settings()
}

#[test]
fn a_fronto_parallel_plane_gives_its_exact_disparity() {
    let (w, h, d) = (160, 120, 12.3);
    let left = plane_of(w, h, |x, y| texture(x as f64, y as f64));
    let right = plane_of(w, h, |x, y| texture(x as f64 + d, y as f64));
    let disp = super::matcher::match_pair(&left, &right, &settings());
    let mut err: Vec<f64> = Vec::new();
    let (mut seen, mut matched) = (0, 0);
    for y in 12..h - 12 {
        for x in 30..w - 12 {
            seen += 1;
            let e = disp[y * w + x];
            if e > 0.0 {
                matched += 1;
                err.push((f64::from(e) - d).abs());
            }
        }
    }
    err.sort_by(f64::total_cmp);
    let (median, p95) = (err[err.len() / 2], err[err.len() * 95 / 100]);
    assert!(matched as f64 > 0.9 * seen as f64, "{matched} of {seen} matched");
    assert!(median < 0.05 && p95 < 0.2, "median {median:.3} px, p95 {p95:.3} px");
}

#[test]
fn the_left_right_check_removes_an_occluded_band() {
    // A strip (x in [80, 150)) 20 px of disparity in front of a wall at 8 px: the 12 columns
    // left of the strip show wall the right camera cannot see. (The coarse-to-fine matcher
    // loses a strip much narrower than its top level's window: 30 px here.)
    let (w, h, d_wall, d_strip, a, b) = (220, 100, 8.0, 20.0, 80usize, 150usize);
    let strip = |x: f64, y: f64| texture(1.7 * x + 300.0, 1.3 * y + 50.0);
    let left = plane_of(w, h, |x, y| if (a..b).contains(&x) { strip(x as f64, y as f64) } else { texture(x as f64, y as f64) });
    let right = plane_of(w, h, |x, y| {
        let xs = x as f64 + d_strip;
        if xs >= a as f64 && xs < b as f64 { strip(xs, y as f64) } else { texture(x as f64 + d_wall, y as f64) }
    });
    let band = (a - (d_strip - d_wall) as usize)..a;
    let rows = 15..h - 15;
    let in_band = rows.len() * band.len();
    // (band pixels left empty, band pixels given another disparity than the wall's)
    let band_stats = |disp: &[f32]| {
        let px = rows.clone().flat_map(|y| band.clone().map(move |x| disp[y * w + x]));
        px.fold((0, 0), |(e, wr), d| (e + usize::from(d <= 0.0), wr + usize::from(d > 0.0 && (f64::from(d) - d_wall).abs() > 1.0)))
    };
    // SGM over the whole range at full resolution: its left–right check is what empties the band.
    let sgm_only = |lr_max_px: f32| {
        let s = super::sgm::SgmSettings { d_min: 0, d_max: 30, lr_max_px, ..settings().sgm };
        let volume = super::zncc::costs(&left, &right, s.d_min, s.d_max, 5, 2.0);
        super::sgm::disparities(&super::sgm::aggregate(&volume, w, h, &s), &left.invalid, &right.invalid, w, h, &s)
    };
    let (_, wrong_unchecked) = band_stats(&sgm_only(1000.0));
    let (_, wrong_checked) = band_stats(&sgm_only(1.0));
    assert!(wrong_unchecked as f64 > 0.5 * in_band as f64, "without the check {wrong_unchecked} of {in_band} band pixels are wrong");
    assert!(wrong_checked as f64 <= 0.1 * in_band as f64, "with the check {wrong_checked} of {in_band} band pixels are wrong");
    // The whole matcher (its refinements also reject what the other direction cannot confirm).
    let disp = super::matcher::match_pair(&left, &right, &settings());
    let (empty, wrong) = band_stats(&disp);
    assert!(wrong as f64 <= 0.05 * in_band as f64, "{wrong} of {in_band} band pixels matched to something else");
    assert!(empty as f64 > 0.8 * in_band as f64, "{empty} of {in_band} band pixels empty");
    // Away from the edges both surfaces are found.
    let at = |x: usize| rows.clone().map(|y| disp[y * w + x]).filter(|d| *d > 0.0).map(f64::from).sum::<f64>() / rows.len() as f64;
    assert!((at(115) - d_strip).abs() < 0.3 && (at(185) - d_wall).abs() < 0.3, "strip {:.2}, wall {:.2}", at(115), at(185));
}

#[test]
fn masked_pixels_in_either_view_get_no_depth() {
    let (w, h, d) = (160, 120, 10.0);
    let mut left = plane_of(w, h, |x, y| texture(x as f64, y as f64));
    let mut right = plane_of(w, h, |x, y| texture(x as f64 + d, y as f64));
    // A masked disc in the left view, and one in the right view whose left pixels are at +d.
    let disc = |x: usize, y: usize, cx: f64, cy: f64| (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2) < 100.0;
    (0..w * h).for_each(|p| left.invalid[p] = disc(p % w, p / w, 60.0, 60.0));
    (0..w * h).for_each(|p| right.invalid[p] = disc(p % w, p / w, 110.0, 60.0));
    let disp = super::matcher::match_pair(&left, &right, &settings());
    for y in 0..h {
        for x in 0..w {
            if disc(x, y, 60.0, 60.0) || disc(x, y, 110.0 + d, 60.0) {
                assert!(disp[y * w + x] <= 0.0, "({x}, {y}) masked but matched {}", disp[y * w + x]);
            }
        }
    }
    // Next to them, depth is there.
    assert!(disp[60 * w + 85] > 0.0 && (f64::from(disp[60 * w + 85]) - d).abs() < 0.2);
}

/// Signed relative errors of an observed albedo against the truth, sorted, where both exist.
fn albedo_errors(observed: &capsule_slam_framework::GrayF32, truth: &capsule_slam_framework::GrayF32) -> Vec<f64> {
    let mut r: Vec<f64> =
        observed.data().iter().zip(truth.data()).filter(|(o, t)| **o > 0.0 && **t > 0.0).map(|(o, t)| f64::from(*o) / f64::from(*t) - 1.0).collect();
    r.sort_by(f64::total_cmp);
    r
}

/// With the phantom's light model the observed albedo is the wall's (which the monocular
/// estimators can only assume): unbiased, and per pixel as noisy as the image makes it with
/// the exact depth.
#[test]
fn with_a_light_model_the_observed_albedo_is_the_walls() {
    let (ph, rig) = stereo_phantom(1);
    let sgm = StereoSgm::build(StereoSgmParams::default(), &BuildEnv::new(rig.clone(), None)).unwrap();
    let f = frame(&ph, 5);
    let (depth, _) = sgm.depth(&f).unwrap();
    assert!(sgm.albedo(&f, &depth, rig.camera()).is_none(), "no light model, no albedo");
    let sgm = sgm.with_light(ph.light.clone());
    let truth = ph.albedo_image(5);
    let observed = sgm.albedo(&f, &depth, rig.camera()).unwrap();
    let stereo = albedo_errors(&observed, &truth);
    let exact = albedo_errors(&sgm.albedo(&f, f.depth_m.as_ref().unwrap(), rig.camera()).unwrap(), &truth);
    let abs_median = |r: &[f64]| {
        let mut a: Vec<f64> = r.iter().map(|v| v.abs()).collect();
        a.sort_by(f64::total_cmp);
        a[a.len() / 2]
    };
    let with_depth = depth.data().iter().filter(|d| **d > 0.0).count();
    let (bias, spread, floor) = (stereo[stereo.len() / 2], abs_median(&stereo), abs_median(&exact));
    eprintln!(
        "albedo on {} of {with_depth} pixels with depth: signed median {bias:.4}, |error| median {spread:.4} (exact depth: {floor:.4}, bias {:.4})",
        stereo.len(),
        exact[exact.len() / 2]
    );
    // Measured: 83 % of the pixels (a normal needs depth 8 px away), bias 0.005, |error| 0.07 against 0.05 with the exact depth
    // (the image noise of a dark pixel, gamma-decoded).
    assert!(stereo.len() as f64 > 0.8 * with_depth as f64, "{} of {with_depth}", stereo.len());
    assert!(bias.abs() < 0.015 && spread < 1.6 * floor, "bias {bias:.4}, |error| {spread:.4} against {floor:.4}");
    // A light twice as strong explains the same pixels with half the albedo.
    let brighter = capsule_slam_framework::light::LightModel { gain: 2.0 * ph.light.gain, ambient: 2.0 * ph.light.ambient, ..ph.light.clone() };
    let half = sgm.with_light(brighter).albedo(&f, &depth, rig.camera()).unwrap();
    let (a, b) = (observed.at(160, 160), half.at(160, 160));
    assert!(a > 0.0 && (b / a - 0.5).abs() < 1e-4, "{a} {b}");
}

#[test]
fn the_window_scales_up_with_the_focal_length_and_never_down() {
    let given = super::ScaledWindow { radius: 10, levels: 2 };
    // Off by default: the window as given at any focal length.
    assert_eq!(super::scaled_window(&StereoSgmParams::default(), 288.0), given);
    let p = StereoSgmParams { focal_reference_px: 160.0, ..StereoSgmParams::default() };
    let at = |f: f64| super::scaled_window(&p, f);
    // The reference camera (320×320, f = 160) and a shorter lens keep the measured window.
    assert_eq!(at(160.0), given);
    assert_eq!(at(125.0), given);
    // A 720×576 phantom (f = 288) sees the same angle through 18 px and one level more; a
    // camera twice as sharp, 20 px.
    assert_eq!(at(288.0), super::ScaledWindow { radius: 18, levels: 3 });
    assert_eq!(at(320.0), super::ScaledWindow { radius: 20, levels: 3 });
    // Bounded.
    assert_eq!(at(1e6), super::ScaledWindow { radius: 60, levels: 5 });
}
