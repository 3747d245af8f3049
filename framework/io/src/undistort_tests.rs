use super::*;
use capsule_slam_framework::lens::LensModel;

const BARREL: LensModel = LensModel::RadialTangential([-0.3, 0.1, 0.001, -0.002, 0.0, 0.0, 0.0, 0.0]);
const FISHEYE: LensModel = LensModel::Equidistant([0.05, -0.01, 0.002, -0.0005]);

fn camera(lens: Option<LensModel>, fov_radius_px: Option<f64>) -> PinholeCamera {
    let mut c = PinholeCamera::new(160, 120, 80.0, 80.0, 79.5, 59.5);
    c.distortion = lens;
    c.fov_radius_px = fov_radius_px;
    c
}

/// The ray (normalised coordinates) each source pixel sees, through the lens.
fn ray_of_source_pixel(c: &PinholeCamera, x: usize, y: usize) -> Option<(f64, f64)> {
    let (xd, yd) = ((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy);
    c.distortion.map_or(Some((xd, yd)), |l| l.undistort(xd, yd))
}

/// A smooth colour pattern over rays (about 6 px per period at the centre).
fn pattern(x: f64, y: f64) -> [f64; 3] {
    [128.0 + 90.0 * (9.0 * x).sin(), 128.0 + 90.0 * (7.0 * y).cos(), 128.0 + 60.0 * (5.0 * (x + y)).sin()]
}

/// The depth of a slanted plane `0.3 x + 0.2 y + z = 0.05` along a ray.
fn plane_depth(x: f64, y: f64) -> f64 {
    0.05 / (0.3 * x + 0.2 * y + 1.0)
}

fn source_images(c: &PinholeCamera) -> (Rgb8, DepthMap) {
    let rgb = Rgb8::from_fn(c.width, c.height, |x, y| ray_of_source_pixel(c, x, y).map_or([0; 3], |(rx, ry)| pattern(rx, ry).map(|v| v.round() as u8)));
    let depth = DepthMap::from_fn(c.width, c.height, |x, y| [ray_of_source_pixel(c, x, y).map_or(0.0, |(rx, ry)| plane_depth(rx, ry) as f32)]);
    (rgb, depth)
}

#[test]
fn without_a_lens_the_images_come_back_unchanged() {
    let c = camera(None, None);
    let (rgb, depth) = source_images(&c);
    let u = Undistortion::new(&c);
    assert_eq!(u.rgb(&rgb).data(), rgb.data());
    assert_eq!(u.depth(&depth).data(), depth.data());
    assert!(!u.out_of_view().data().iter().any(|b| *b));
}

#[test]
fn undistorted_pixels_see_their_pinhole_rays() {
    for (lens, view) in [BARREL, FISHEYE].into_iter().flat_map(|l| [(l, UndistortedView::Source), (l, UndistortedView::Whole)]) {
        let c = camera(Some(lens), None);
        let (rgb, depth) = source_images(&c);
        let u = Undistortion::with_view(&c, view);
        let (out_rgb, out_depth) = (u.rgb(&rgb), u.depth(&depth));
        let pin = u.camera();
        assert!(pin.distortion.is_none());
        let (mut worst_rgb, mut worst_depth, mut seen) = (0.0f64, 0.0f64, 0);
        for y in 2..pin.height - 2 {
            for x in 2..pin.width - 2 {
                if u.out_of_view().at(x, y) {
                    continue;
                }
                seen += 1;
                // Where a source pixel spreads over more than four of the whole view's (a
                // fisheye's rim), a slanted wall's depth is its nearest source pixel's.
                if view == UndistortedView::Whole && u.sample_share().at(x, y) < 0.25 {
                    continue;
                }
                let (rx, ry) = ((x as f64 - pin.cx) / pin.fx, (y as f64 - pin.cy) / pin.fy);
                let want = pattern(rx, ry);
                for (ch, w) in want.iter().enumerate() {
                    worst_rgb = worst_rgb.max((f64::from(out_rgb.pixel(x, y)[ch]) - w).abs());
                }
                let e = (f64::from(out_depth.at(x, y)) - plane_depth(rx, ry)).abs() / plane_depth(rx, ry);
                worst_depth = worst_depth.max(e);
            }
        }
        // Barrel and fisheye lenses see wider than their pinhole image: every pixel of one the
        // source's size is seen (the whole view's canvas has unseen corners).
        if view == UndistortedView::Source {
            assert_eq!(seen, (c.width - 4) * (c.height - 4), "{lens:?}");
        }
        // A pattern with a 6-px period: 1.0–1.05 grey levels measured on the source's canvas
        // (the rounding of the source and of the output to whole levels), 1.25–1.9 on the
        // whole view's.
        assert!(worst_rgb < 3.0, "{lens:?}: colour off by {worst_rgb}");
        // 0.5e-4 (barrel) and 1.4e-4 (fisheye, its compressed corners) measured; 2.8e-4 on the
        // fisheye's whole view.
        assert!(worst_depth < 4e-4, "{lens:?}: depth off by a share {worst_depth}");
    }
}

#[test]
fn the_whole_view_holds_every_ray_the_lens_image_sees() {
    for lens in [BARREL, FISHEYE] {
        let c = camera(Some(lens), None);
        let crop = Undistortion::new(&c);
        let whole = Undistortion::with_view(&c, UndistortedView::Whole);
        let pin = whole.camera();
        assert!(!whole.clipped(), "{lens:?}");
        assert_eq!((pin.fx, pin.fy), (c.fx, c.fy), "the focal length is kept");
        assert!(pin.width > c.width && pin.height > c.height, "{lens:?}: {}×{}", pin.width, pin.height);
        // Where each source pixel's ray lands on the pinhole camera of the source's intrinsics
        // (cropped) and on the whole view's: the crop loses the lens image's outer field, the
        // whole view none of it, and sees it (not out of view) away from the rim.
        let (mut lost_by_crop, mut lost_by_whole, mut unseen) = (0, 0, 0);
        for y in 0..c.height {
            for x in 0..c.width {
                let (rx, ry) = ray_of_source_pixel(&c, x, y).expect("no fold in these lenses");
                let inside = |p: &PinholeCamera| {
                    let (u, v) = (p.fx * rx + p.cx, p.fy * ry + p.cy);
                    (u > -0.5 && v > -0.5 && u < p.width as f64 - 0.5 && v < p.height as f64 - 0.5).then_some((u, v))
                };
                lost_by_crop += usize::from(inside(crop.camera()).is_none());
                match inside(pin) {
                    None => lost_by_whole += 1,
                    Some((u, v)) => {
                        let (ui, vi) = (u.round() as usize, v.round() as usize);
                        let rim = x < 3 || y < 3 || x + 3 >= c.width || y + 3 >= c.height;
                        unseen += usize::from(!rim && whole.out_of_view().at(ui, vi));
                    }
                }
            }
        }
        assert!(lost_by_crop > c.width * c.height / 20, "{lens:?}: the crop loses only {lost_by_crop} source pixels");
        assert_eq!(lost_by_whole, 0, "{lens:?}");
        assert_eq!(unseen, 0, "{lens:?}: source pixels inside the whole view marked out of view");
        // V is the same function of the ray on either canvas.
        let light = capsule_slam_framework::light::LightModel { vignetting: vec![-0.3, -0.25], ..Default::default() };
        let (dx, dy) = (pin.cx - c.cx, pin.cy - c.cy);
        let (a, b) = (light.vignetting_at(crop.camera(), 20.0, 30.0), light.vignetting_at(pin, 20.0 + dx, 30.0 + dy));
        assert!((a - b).abs() < 1e-12, "V {a} on the file's canvas, {b} on the whole view's");
    }
}

#[test]
fn a_lens_wider_than_the_largest_canvas_is_cut_and_says_so() {
    // An equidistant lens at f = 40 px: the 160-px image's corners see rays 63° off the axis,
    // which a pinhole canvas of f = 40 puts 80 px out: more than half the width again.
    let mut c = camera(Some(LensModel::Equidistant([0.0; 4])), None);
    (c.fx, c.fy) = (40.0, 40.0);
    let whole = Undistortion::with_view(&c, UndistortedView::Whole);
    assert!(whole.clipped());
    assert_eq!((whole.camera().width, whole.camera().height), (2 * c.width, 2 * c.height));
}

#[test]
fn a_depth_edge_is_not_blended() {
    let c = camera(Some(BARREL), None);
    // Near 30 mm left of x = 0.1, far 60 mm right of it.
    let depth = DepthMap::from_fn(c.width, c.height, |x, y| [ray_of_source_pixel(&c, x, y).map_or(0.0, |(rx, _)| if rx < 0.1 { 0.03 } else { 0.06 })]);
    let out = Undistortion::new(&c).depth(&depth);
    assert!(out.data().iter().all(|z| (z - 0.03).abs() < 1e-7 || (z - 0.06).abs() < 1e-7), "a depth between the two surfaces was invented");
}

#[test]
fn a_round_field_of_view_becomes_the_inscribed_circle_of_what_is_seen() {
    // Pincushion: the pinhole image's corners look outside the source image.
    let pincushion = LensModel::brown_conrady([0.2, 0.0, 0.0, 0.0, 0.0]);
    let c = camera(Some(pincushion), Some(55.0));
    let u = Undistortion::new(&c);
    let r = u.camera().fov_radius_px.expect("a round field of view stays round");
    // A ray at radius r lands at r (1 + 0.2 (r/f)²) in the source, and the colour kernel reads
    // up to 2 px further along x and y: 2√2 px beyond it on a diagonal, where it must still be
    // inside the 55 px.
    let f = 80.0;
    let reach = 55.0 - 2.0 * 2f64.sqrt();
    let expected = (0..2000).map(|i| f64::from(i) * 0.05).filter(|r| r * (1.0 + 0.2 * (r / f).powi(2)) <= reach).fold(0.0, f64::max);
    assert!((r - expected).abs() < 1.5, "inscribed radius {r}, expected about {expected}");
    let mask = u.out_of_view();
    for y in 0..c.height {
        for x in 0..c.width {
            if u.camera().in_fov(x as f64, y as f64) {
                assert!(!mask.at(x, y), "({x}, {y}) is inside the new field of view but unseen");
            }
        }
    }
    let m = u.mask(&Mask::filled(c.width, c.height, true));
    assert!(m.data().iter().zip(mask.data()).all(|(a, out)| !(*a && *out)), "a mask pixel out of view stays set");
}

#[test]
fn beyond_a_lens_fold_nothing_is_seen() {
    // r (1 − 0.9 r²) folds at r = 0.61 (60 px at f = 80): the pinhole corners (r ≈ 1.25) would
    // land back inside the image.
    let c = camera(Some(LensModel::brown_conrady([-0.9, 0.0, 0.0, 0.0, 0.0])), None);
    let u = Undistortion::new(&c);
    assert!(u.out_of_view().at(0, 0) && u.out_of_view().at(159, 119));
    assert!(!u.out_of_view().at(80, 60));
}

#[test]
fn fine_texture_keeps_its_contrast_better_than_a_bilinear_sample() {
    // A 3.5-px period: a bilinear sample halfway between pixels keeps cos(π/3.5) ≈ 62 % of it.
    let c = camera(Some(BARREL), None);
    let fine = |x: f64, _y: f64| 128.0 + 100.0 * (2.0 * std::f64::consts::PI * x * c.fx / 3.5).sin();
    let rgb = Rgb8::from_fn(c.width, c.height, |x, y| {
        let v = ray_of_source_pixel(&c, x, y).map_or(0.0, |(rx, ry)| fine(rx, ry)).round() as u8;
        [v, v, v]
    });
    let out = Undistortion::new(&c).rgb(&rgb);
    let (mut cubic, mut linear, mut n) = (0.0, 0.0, 0.0);
    for y in 30..90 {
        for x in 40..120 {
            let (rx, ry) = ((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy);
            let (xd, yd) = BARREL.distort(rx, ry);
            let (us, vs) = (c.fx * xd + c.cx, c.fy * yd + c.cy);
            let (x0, y0) = (us.floor() as usize, vs.floor() as usize);
            let (fx, fy) = (us - x0 as f64, vs - y0 as f64);
            let at = |x: usize, y: usize| f64::from(rgb.pixel(x, y)[0]);
            let bilinear = (at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx) * (1.0 - fy) + (at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx) * fy;
            let truth = fine(rx, ry);
            cubic += (f64::from(out.pixel(x, y)[0]) - truth).powi(2);
            linear += (bilinear - truth).powi(2);
            n += 1.0;
        }
    }
    let (cubic, linear) = ((cubic / n).sqrt(), (linear / n).sqrt());
    // Measured: 13.1 against 22.0 grey levels RMS.
    assert!(cubic < 0.7 * linear, "bicubic {cubic}, bilinear {linear} grey levels RMS");
}

#[test]
fn no_colour_kernel_reads_beyond_the_round_field_of_view() {
    // A uniform wall inside the source's round field of view, black beyond it (as a capsule
    // camera's frames are): every pixel the undistorted image sees is the wall's grey. A kernel
    // reaching the black would darken a fixed ring at the rim, which a moving camera's
    // photometric term reads as texture that does not move.
    for lens in [BARREL, FISHEYE, LensModel::brown_conrady([-0.01, 0.0, 0.0, 0.0, 0.0])] {
        let c = camera(Some(lens), Some(50.0));
        let rgb = Rgb8::from_fn(c.width, c.height, |x, y| if c.in_fov(x as f64, y as f64) { [200; 3] } else { [0; 3] });
        let u = Undistortion::new(&c);
        let out = u.rgb(&rgb);
        let mut seen = 0;
        for y in 0..c.height {
            for x in 0..c.width {
                if !u.out_of_view().at(x, y) {
                    seen += 1;
                    assert_eq!(out.pixel(x, y), [200; 3], "{lens:?}: ({x}, {y})");
                }
            }
        }
        assert!(seen > 5000, "{lens:?}: {seen} pixels seen");
    }
}

#[test]
fn the_sample_share_is_the_lens_area_ratio_clamped_to_one() {
    // Without a lens every pixel is a source pixel.
    let plain = Undistortion::new(&camera(None, None));
    assert!(plain.sample_share().data().iter().all(|s| (*s - 1.0).abs() < 1e-6));
    // A radial lens r_d = r (1 + k₁ r²) maps a ring of radius r and width dr to one of radius
    // r_d and width r_d' dr: the area ratio is (r_d / r) · r_d' = (1 + k₁ r²)(1 + 3 k₁ r²).
    let k1 = -0.2;
    let c = camera(Some(LensModel::RadialTangential([k1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])), None);
    let u = Undistortion::new(&c);
    let share = u.sample_share();
    let (mut checked, mut below_one) = (0, 0);
    for y in 0..c.height {
        for x in 0..c.width {
            if u.out_of_view().at(x, y) {
                assert_eq!(share.at(x, y), 0.0, "({x}, {y}) is out of view");
                continue;
            }
            let r2 = ((x as f64 - c.cx) / c.fx).powi(2) + ((y as f64 - c.cy) / c.fy).powi(2);
            let expected = ((1.0 + k1 * r2) * (1.0 + 3.0 * k1 * r2)).min(1.0);
            assert!((f64::from(share.at(x, y)) - expected).abs() < 1e-3, "({x}, {y}): {} against {expected}", share.at(x, y));
            checked += 1;
            below_one += usize::from(expected < 0.9);
        }
    }
    assert!(checked > c.width * c.height / 2 && below_one > 1000, "{checked} pixels, {below_one} stretched by more than 10 %");
    // A pincushion lens squeezes the outer ring (more than one source pixel per pixel): 1.
    let pincushion = Undistortion::new(&camera(Some(LensModel::RadialTangential([0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])), None));
    let seen: Vec<f32> = pincushion.sample_share().data().iter().zip(pincushion.out_of_view().data()).filter(|(_, o)| !**o).map(|(s, _)| *s).collect();
    assert!(!seen.is_empty() && seen.iter().all(|s| (*s - 1.0).abs() < 1e-6));
}
