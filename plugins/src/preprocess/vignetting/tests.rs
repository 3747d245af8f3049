use capsule_slam_calib::fit_flat_field;
use capsule_slam_eval::depth::depth_error;
use capsule_slam_framework::camera::Rig;
use capsule_slam_framework::context::StageReport;
use capsule_slam_framework::frame::{Falloff, MASK_SATURATED};
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::light::vignetting::{cos_alpha, flat_field_linear, light_falloff};
use capsule_slam_framework::{CameraFrame, Context, DepthEstimator, PinholeCamera, Preprocessor, Rgb8};
use capsule_slam_phantom::{Phantom, PhantomSpec};
use rand::{Rng, SeedableRng};

use super::*;
use crate::depth::near_light_sfs::{NearLightSfs, NearLightSfsParams};

fn cam() -> PinholeCamera {
    let mut c = PinholeCamera::new(160, 160, 80.0, 80.0, 79.5, 79.5);
    c.fov_radius_px = Some(75.2);
    c
}

/// The phantom's light without the ambient term (which a flat field does not divide by).
fn light() -> LightModel {
    LightModel { gain: 0.6, spot_exponent: 1.0, ambient: 0.0, ..LightModel::default() }
}

fn flat_image(light: &LightModel, cam: &PinholeCamera) -> Rgb8 {
    Rgb8::from_fn(cam.width, cam.height, |x, y| {
        if !cam.in_fov(x as f64, y as f64) {
            return [0; 3];
        }
        let l = flat_field_linear(light, cam, x as f64, y as f64, 0.025, 0.8);
        [light.encode(l)].map(|e| (e * 255.0).round() as u8)[0..1].repeat(3).try_into().unwrap()
    })
}

fn run(stage: &mut Vignetting, frame: &mut CameraFrame, cam: &PinholeCamera) -> StageReport {
    let mut report = StageReport::default();
    stage.process(frame, &mut Context::new(frame.index, &Rig::Mono(cam.clone()), None, &mut report)).unwrap();
    report
}

/// Worst relative deviation from the centre of `linear(u, v) · factor(u, v)` inside the field
/// of view, over rings of r² (noise averaged per ring).
fn radial_bias(img: &Rgb8, cam: &PinholeCamera, gamma: f64, factor: impl Fn(f64, f64) -> f64) -> f64 {
    let mut rings = [(0.0, 0.0); 10];
    for y in 0..cam.height {
        for x in 0..cam.width {
            let (u, v) = (x as f64, y as f64);
            if !cam.in_fov(u, v) {
                continue;
            }
            let l = (f64::from(img.pixel(x, y)[0]) / 255.0).powf(gamma) * factor(u, v);
            let r = ((capsule_slam_framework::light::vignetting::radius2(cam, u, v) * 10.0) as usize).min(9);
            rings[r].0 += l;
            rings[r].1 += 1.0;
        }
    }
    let means: Vec<f64> = rings.iter().filter(|r| r.1 > 0.0).map(|r| r.0 / r.1).collect();
    means.iter().map(|m| (m / means[0] - 1.0).abs()).fold(0.0, f64::max)
}

#[test]
fn a_rendered_flat_field_comes_out_flat() {
    let (c, l) = (cam(), light());
    let raw = flat_image(&l, &c);
    assert!(radial_bias(&raw, &c, l.gamma, |_, _| 1.0) > 0.4, "the input falls off");
    // Flat field divided: flat.
    let params = VignettingParams { divide: Falloff::FlatField, ..VignettingParams::default() };
    let mut frame = CameraFrame::mono(0, 0.0, raw.clone());
    run(&mut Vignetting::new(params, FalloffSource::Light(l.clone())), &mut frame, &c);
    let b = radial_bias(frame.views.reference(), &c, l.gamma, |_, _| 1.0);
    assert!(b < 0.01, "flat-field correction leaves {:.2} % radial bias", b * 100.0);
    // Lens and light divided: what is left is the cos³α of the flat target's own geometry.
    let mut frame = CameraFrame::mono(0, 0.0, raw);
    run(&mut Vignetting::new(VignettingParams::default(), FalloffSource::Light(l.clone())), &mut frame, &c);
    let d = frame.photometry.divided.unwrap();
    assert_eq!((d.falloff, d.gamma), (Falloff::LensAndLight, l.gamma));
    assert_eq!(d.linear_scale, 1.0, "the centre keeps its value");
    assert_eq!(frame.views.reference().pixel(80, 80), flat_image(&l, &c).pixel(80, 80));
    let b = radial_bias(frame.views.reference(), &c, l.gamma, |u, v| 1.0 / Falloff::flat_to_lens_and_light(cos_alpha(&c, u, v)));
    assert!(b < 0.01, "lens-and-light correction leaves {:.2} % radial bias after cos³α", b * 100.0);
}

#[test]
fn a_calibrated_file_corrects_like_the_light_model() {
    let (c, l) = (cam(), light());
    let raw = flat_image(&l, &c);
    let linear: Vec<f64> = raw.data().chunks_exact(3).map(|p| if p[0] == 0 { 0.0 } else { l.decode(f64::from(p[0]) / 255.0) }).collect();
    let file = fit_flat_field(&linear, &c, l.gamma, 3).unwrap();
    for divide in [Falloff::FlatField, Falloff::LensAndLight] {
        let params = VignettingParams { divide, ..VignettingParams::default() };
        let mut frame = CameraFrame::mono(0, 0.0, raw.clone());
        run(&mut Vignetting::new(params, FalloffSource::File(file.clone())), &mut frame, &c);
        let back = |u: f64, v: f64| if divide == Falloff::FlatField { 1.0 } else { 1.0 / Falloff::flat_to_lens_and_light(cos_alpha(&c, u, v)) };
        let b = radial_bias(frame.views.reference(), &c, l.gamma, back);
        assert!(b < 0.01, "{divide:?}: {:.2} % radial bias", b * 100.0);
    }
}

#[test]
fn the_sequence_estimate_learns_the_flat_field_from_varied_scenes() {
    // Scenes whose brightness does not depend on the position (random albedo per pixel and
    // frame) under the light: their mean is the flat field.
    let (c, l) = (cam(), light());
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(7);
    let params = VignettingParams {
        source: Source::Sequence,
        sequence_model: SequenceModel::Mean,
        divide: Falloff::FlatField,
        learn_frames: 20,
        ..VignettingParams::default()
    };
    let mut stage = Vignetting::new(params, FalloffSource::Sequence);
    for i in 0..25 {
        let img = Rgb8::from_fn(c.width, c.height, |x, y| {
            let a: f64 = rng.random_range(0.2..0.9);
            let v = if c.in_fov(x as f64, y as f64) { (l.encode(flat_field_linear(&l, &c, x as f64, y as f64, 0.025, a)) * 255.0).round() as u8 } else { 0 };
            [v, v, v]
        });
        let mut frame = CameraFrame::mono(i, 0.0, img);
        let r = run(&mut stage, &mut frame, &c);
        assert_eq!(r.counters.get("learnt_frames").copied(), if i < 20 { Some((i + 1) as f64) } else { None });
    }
    let mut worst = 0.0f64;
    for k in (0..c.width * c.height).step_by(5) {
        let (u, v) = ((k % c.width) as f64, (k / c.width) as f64);
        if c.in_fov(u, v) {
            worst = worst.max((stage.falloff(&c, u, v).unwrap() / light_falloff(&l, &c, u, v, Falloff::FlatField) - 1.0).abs());
        }
    }
    assert!(worst < 0.02, "learnt flat field off by {:.2} %", worst * 100.0);
}

#[test]
fn a_second_pass_changes_nothing_and_saturated_pixels_are_masked() {
    let (c, l) = (cam(), light());
    let mut img = flat_image(&l, &c);
    img.set_pixel(80, 80, [255, 255, 255]);
    let mut frame = CameraFrame::mono(0, 0.0, img);
    let mut stage = Vignetting::new(VignettingParams::default(), FalloffSource::Light(l));
    run(&mut stage, &mut frame, &c);
    let once = frame.clone();
    assert!(frame.masks.get(MASK_SATURATED).unwrap().at(80, 80));
    assert_eq!(frame.masks.get(MASK_SATURATED).unwrap().data().iter().filter(|v| **v).count(), 1);
    let r = run(&mut stage, &mut frame, &c);
    assert_eq!(frame, once);
    assert_eq!(r.warnings.len(), 1, "{:?}", r.warnings);
}

#[test]
fn black_saturated_and_wrongly_sized_frames_are_handled() {
    let (c, l) = (cam(), light());
    let mut stage = Vignetting::new(VignettingParams::default(), FalloffSource::Light(l.clone()));
    let mut black = CameraFrame::mono(0, 0.0, Rgb8::new(c.width, c.height));
    run(&mut stage, &mut black, &c);
    assert_eq!(black.views.reference(), &Rgb8::new(c.width, c.height));
    let mut white = CameraFrame::mono(1, 0.0, Rgb8::filled(c.width, c.height, 255));
    run(&mut stage, &mut white, &c);
    assert!(white.masks.get(MASK_SATURATED).unwrap().data().iter().all(|v| *v));
    // No-clip scaling darkens instead, and the record says by how much.
    let params = VignettingParams { scale: OutputScale::NoClip, ..VignettingParams::default() };
    let mut dark = CameraFrame::mono(1, 0.0, Rgb8::filled(c.width, c.height, 200));
    run(&mut Vignetting::new(params, FalloffSource::Light(l.clone())), &mut dark, &c);
    let d = dark.photometry.divided.unwrap();
    assert!(d.linear_scale < 0.7 && dark.masks.get(MASK_SATURATED).is_none());
    assert_eq!(dark.views.reference().pixel(80, 80), [(200.0 * d.linear_scale.powf(1.0 / l.gamma)).round() as u8; 3]);
    // A bright rim that the correction clips is masked.
    let mut bright = CameraFrame::mono(1, 0.0, Rgb8::filled(c.width, c.height, 240));
    run(&mut stage, &mut bright, &c);
    let m = bright.masks.get(MASK_SATURATED).unwrap();
    assert!(!m.at(80, 80) && m.at(80, 8), "centre kept, rim clipped");
    let mut odd = CameraFrame::mono(2, 0.0, Rgb8::new(37, 23));
    let mut report = StageReport::default();
    let e = stage.process(&mut odd, &mut Context::new(2, &Rig::Mono(c.clone()), None, &mut report)).unwrap_err().to_string();
    assert!(e.contains("37×23") && e.contains("camera.toml"), "{e}");
    let odd_cam = PinholeCamera::new(37, 23, 20.0, 20.0, 18.0, 11.0);
    let mut odd = CameraFrame::mono(3, 0.0, Rgb8::filled(37, 23, 100));
    run(&mut stage, &mut odd, &odd_cam);
    // No round field of view: every pixel is corrected, the centre keeps its value, a corner is
    // brightened by F^(−1/γ).
    let g = light_falloff(&l, &odd_cam, 0.0, 0.0, Falloff::LensAndLight).powf(-1.0 / l.gamma);
    assert_eq!(odd.views.reference().pixel(18, 11), [100; 3]);
    assert_eq!(odd.views.reference().pixel(0, 0), [(100.0 * g).round() as u8; 3]);
    // A sequence estimate with nothing usable leaves the frame alone and says so.
    let mut seq = Vignetting::new(VignettingParams { source: Source::Sequence, ..VignettingParams::default() }, FalloffSource::Sequence);
    let mut black = CameraFrame::mono(0, 0.0, Rgb8::new(c.width, c.height));
    let r = run(&mut seq, &mut black, &c);
    assert!(black.photometry.divided.is_none() && r.warnings.len() == 1, "{:?}", r.warnings);
}

#[test]
fn near_light_sfs_reads_the_same_depth_from_a_corrected_frame() {
    // The depth model accounts for what was divided: raw, lens-and-light and flat-field
    // corrected frames give the same depth (to the 8-bit rounding of the correction).
    let spec = PhantomSpec { size: capsule_slam_phantom::SizePreset::NanEye, noise: 0.0, specular: 0.0, ..PhantomSpec::preset(1) };
    let ph = Phantom::new(spec).unwrap();
    let f = ph.render(60);
    let rig = Rig::Mono(ph.camera.clone());
    let depth_of = |frame: &CameraFrame| {
        let mut est = NearLightSfs::with_light(NearLightSfsParams::default(), ph.light.clone());
        let mut report = StageReport::default();
        est.estimate(frame, &mut Context::new(0, &rig, None, &mut report)).unwrap().depth_m
    };
    let raw = CameraFrame::mono(60, 0.0, f.rgb.clone());
    let base = depth_error(&depth_of(&raw), &f.depth_m, false).unwrap().abs_rel;
    for divide in [Falloff::LensAndLight, Falloff::FlatField] {
        let mut frame = raw.clone();
        run(&mut Vignetting::new(VignettingParams { divide, ..VignettingParams::default() }, FalloffSource::Light(ph.light.clone())), &mut frame, &ph.camera);
        let e = depth_error(&depth_of(&frame), &f.depth_m, false).unwrap().abs_rel;
        assert!((e - base).abs() < 0.004, "{divide:?}: AbsRel {e:.4} against {base:.4} uncorrected");
    }
}

#[test]
fn the_shading_model_learns_the_fall_off_inside_a_tube_where_the_mean_cannot() {
    // Phantom preset 2 (the capsule looks along the tube: dark in the middle), with its exact
    // geometry as the map's prediction. Truth: the light model's V · μ.
    let spec = PhantomSpec { size: capsule_slam_phantom::SizePreset::NanEye, frames: 300, ..PhantomSpec::preset(2) };
    let ph = Phantom::new(spec).unwrap();
    let c = ph.camera.clone();
    let rig = Rig::Mono(c.clone());
    let mut learners = [SequenceModel::Shading, SequenceModel::Mean].map(|m| {
        let params = VignettingParams { source: Source::Sequence, sequence_model: m, learn_frames: 30, ..VignettingParams::default() };
        Vignetting::new(params, FalloffSource::Sequence)
    });
    // Only the shading model reads the prediction, and only while it learns: a pipeline may
    // preprocess the next frame before the prediction exists otherwise.
    assert_eq!(learners.each_ref().map(|s| s.reads_prediction()), [true, false]);
    for i in (0..300).step_by(10) {
        let f = ph.render(i);
        let normals = crate::common::maps::normal_map(&crate::common::maps::vertex_map(&f.depth_m, &c), 1, 0.002);
        let mut view = capsule_slam_framework::ModelView::empty(c.width, c.height, f.t_world_cam);
        view.depth_m = f.depth_m.clone();
        view.normals_cam = normals;
        for stage in &mut learners {
            let mut frame = CameraFrame::mono(i, 0.0, f.rgb.clone());
            let mut report = StageReport::default();
            stage.process(&mut frame, &mut Context::new(i, &rig, Some(&view), &mut report)).unwrap();
        }
    }
    let worst = |stage: &Vignetting| {
        let mut rings = [(0.0, 0.0); 8];
        for k in 0..c.width * c.height {
            let (u, v) = ((k % c.width) as f64, (k / c.width) as f64);
            if c.in_fov(u, v) {
                let r = ((capsule_slam_framework::light::vignetting::radius2(&c, u, v) * 8.0) as usize).min(7);
                rings[r].0 += stage.falloff(&c, u, v).unwrap() / light_falloff(&ph.light, &c, u, v, Falloff::LensAndLight);
                rings[r].1 += 1.0;
            }
        }
        rings.iter().filter(|r| r.1 > 0.0).map(|r| (r.0 / r.1 - 1.0).abs()).fold(0.0, f64::max)
    };
    assert!(!learners[0].reads_prediction(), "learnt from {} frames, still reads the prediction", learners[0].learner.frames());
    let (shading, mean) = (worst(&learners[0]), worst(&learners[1]));
    assert!(shading < 0.03, "shading model: {:.1} % radial bias", shading * 100.0);
    assert!(mean > 0.2, "the mean model should be fooled by the tube ({:.1} %)", mean * 100.0);
}

#[test]
fn auto_leaves_an_uncalibrated_stereo_rig_uncorrected_and_says_so_once() {
    use capsule_slam_framework::frame::Views;
    use capsule_slam_framework::registry::BuildEnv;
    let c = cam();
    let rig = Rig::Stereo { left: c.clone(), right: c.clone(), t_right_left: capsule_slam_framework::stereo::rectified_t_right_left(0.005) };
    let dir = tempfile::tempdir().unwrap();
    let mut stage = Vignetting::build(VignettingParams::default(), &BuildEnv::new(rig.clone(), Some(dir.path().to_owned()))).unwrap();
    let img = flat_image(&light(), &c);
    let mut frame = CameraFrame { views: Views::Stereo { left: img.clone(), right: img.clone() }, ..CameraFrame::mono(0, 0.0, img.clone()) };
    for i in 0..2 {
        let mut report = StageReport::default();
        stage.process(&mut frame, &mut Context::new(i, &rig, None, &mut report)).unwrap();
        assert_eq!(report.warnings.len(), usize::from(i == 0), "{:?}", report.warnings);
        assert!(i > 0 || report.warnings[0].contains("left uncorrected"));
    }
    let Views::Stereo { left, right } = &frame.views else { panic!("one view") };
    assert!(left.data() == img.data() && right.data() == img.data() && frame.photometry.divided.is_none());
    // With the light model in the folder, the same rig is corrected.
    capsule_slam_framework::files::write_light_file(&dir.path().join("light.toml"), &light()).unwrap();
    let mut stage = Vignetting::build(VignettingParams::default(), &BuildEnv::new(rig.clone(), Some(dir.path().to_owned()))).unwrap();
    stage.process(&mut frame, &mut Context::new(2, &rig, None, &mut StageReport::default())).unwrap();
    assert!(frame.photometry.divided.is_some());
}
