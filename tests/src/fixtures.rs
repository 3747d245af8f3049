//! Small TUM-layout datasets written by the tests: a textured plane seen by a camera moving
//! along a known path, with exact depth and ground truth.

use std::io::Write;
use std::path::Path;

use capsule_slam_framework::files::write_camera_file;
use capsule_slam_framework::geometry::{StampedPose, exp_se3};
use capsule_slam_framework::{DepthMap, Iso3, Rgb8, camera::CameraFile};
use capsule_slam_io::{images, tum};
use nalgebra::{Point3, Vector6};

/// A tiny camera (48×40).
pub fn camera() -> CameraFile {
    CameraFile {
        width: 48,
        height: 40,
        fx: 40.0,
        fy: 40.0,
        cx: 23.5,
        cy: 19.5,
        depth_scale: 5000.0,
        distortion: None,
        fov_radius_px: None,
        baseline_m: None,
        right: None,
        depth_noise: None,
    }
}

/// The ground-truth pose of frame `i`: a slow drift and turn.
pub fn gt_pose(i: usize) -> Iso3 {
    let s = i as f64;
    exp_se3(&Vector6::new(0.0005 * s, 0.0002 * s, 0.0, 0.0, 0.002 * s, 0.001 * s))
}

/// Renders the plane z = 0.05 m (world) with a checker texture from `pose`.
pub fn render(cam: &CameraFile, pose: &Iso3) -> (Rgb8, DepthMap) {
    let c = cam.camera();
    let (w, h) = (c.width, c.height);
    let mut rgb = Rgb8::new(w, h);
    let mut depth = DepthMap::new(w, h);
    let inv = pose.rotation;
    for y in 0..h {
        for x in 0..w {
            let ray_cam = c.unproject(x as f64, y as f64, 1.0).coords;
            let ray_w = inv * ray_cam;
            let o = pose.translation.vector;
            if ray_w.z.abs() < 1e-9 {
                continue;
            }
            let s = (0.05 - o.z) / ray_w.z;
            if s <= 0.0 {
                continue;
            }
            let p_w = Point3::from(o + s * ray_w);
            let p_c = pose.inverse() * p_w;
            *depth.at_mut(x, y) = p_c.z as f32;
            let checker = ((p_w.x / 0.004).floor() as i64 + (p_w.y / 0.004).floor() as i64).rem_euclid(2);
            rgb.set_pixel(x, y, if checker == 0 { [200, 90, 80] } else { [120, 40, 40] });
        }
    }
    (rgb, depth)
}

/// Writes an `n`-frame TUM dataset at 30 Hz into `dir`.
pub fn write_dataset(dir: &Path, n: usize) -> Vec<StampedPose> {
    write_dataset_with(dir, n, gt_pose)
}

/// [`write_dataset`] along the trajectory `pose(i)`.
pub fn write_dataset_with(dir: &Path, n: usize, pose: impl Fn(usize) -> Iso3) -> Vec<StampedPose> {
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    let cam = camera();
    write_camera_file(&dir.join("camera.toml"), &cam).unwrap();
    let mut rgb_txt = std::fs::File::create(dir.join("rgb.txt")).unwrap();
    let mut depth_txt = std::fs::File::create(dir.join("depth.txt")).unwrap();
    writeln!(rgb_txt, "# timestamp filename").unwrap();
    let mut gt = Vec::new();
    for i in 0..n {
        let t = 1.0 + i as f64 / 30.0;
        let pose = pose(i);
        let (rgb, depth) = render(&cam, &pose);
        images::write_rgb(&dir.join(format!("rgb/{i:04}.png")), &rgb).unwrap();
        images::write_depth(&dir.join(format!("depth/{i:04}.png")), &depth, cam.depth_scale).unwrap();
        writeln!(rgb_txt, "{t:.6} rgb/{i:04}.png").unwrap();
        // Depth stamped 5 ms later, as a real sensor pair would be.
        writeln!(depth_txt, "{:.6} depth/{i:04}.png", t + 0.005).unwrap();
        gt.push(StampedPose { timestamp_s: t, t_world_cam: pose });
    }
    tum::write_trajectory(&dir.join("groundtruth.txt"), &gt).unwrap();
    gt
}

/// Copies a folder and everything below it (a fixture to damage, leaving the original).
pub fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for entry in std::fs::read_dir(src).unwrap() {
        let p = entry.unwrap().path();
        let to = dst.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &to);
        } else {
            std::fs::copy(&p, &to).unwrap();
        }
    }
}

/// The right camera of [`write_stereo_dataset`]: the left's intrinsics shifted a little, 5 mm
/// to the right of the left and turned 1° about y (toward the left's axis).
pub fn right_camera() -> capsule_slam_framework::stereo::RightCameraFile {
    let a = 1f64.to_radians();
    capsule_slam_framework::stereo::RightCameraFile {
        fx: Some(41.0),
        fy: Some(40.5),
        cx: Some(24.0),
        cy: Some(19.0),
        // x_right = R x_left + t with the right centre at +5 mm along the left's x: t = −R c.
        rotation: Some(vec![a.cos(), 0.0, -a.sin(), 0.0, 1.0, 0.0, a.sin(), 0.0, a.cos()]),
        translation_m: Some(vec![-0.005 * a.cos(), 0.0, -0.005 * a.sin()]),
        ..Default::default()
    }
}

/// [`write_dataset`] with a right view per frame (`rgb_right/`, `rgb_right.txt`, stamped 2 ms
/// after the left) from [`right_camera`], and the `[right]` table in `camera.toml`.
pub fn write_stereo_dataset(dir: &Path, n: usize) -> Vec<StampedPose> {
    let gt = write_dataset(dir, n);
    let mut cam = camera();
    cam.right = Some(right_camera());
    write_camera_file(&dir.join("camera.toml"), &cam).unwrap();
    let right = right_camera();
    let t_right_left = right.t_right_left().unwrap();
    let right_file = CameraFile { fx: right.fx.unwrap(), fy: right.fy.unwrap(), cx: right.cx.unwrap(), cy: right.cy.unwrap(), ..camera() };
    std::fs::create_dir_all(dir.join("rgb_right")).unwrap();
    let mut list = std::fs::File::create(dir.join("rgb_right.txt")).unwrap();
    for p in &gt {
        let i = gt.iter().position(|q| q.timestamp_s == p.timestamp_s).unwrap();
        let (rgb, _) = render(&right_file, &(p.t_world_cam * t_right_left.inverse()));
        images::write_rgb(&dir.join(format!("rgb_right/{i:04}.png")), &rgb).unwrap();
        writeln!(list, "{:.6} rgb_right/{i:04}.png", p.timestamp_s + 0.002).unwrap();
    }
    gt
}
