//! The framework's images, poses and surfels as rerun archetypes.

use capsule_slam_framework::DepthMap;
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::{Iso3, StampedPose};
use capsule_slam_framework::image::Rgb8;
use capsule_slam_framework::map::SurfelSet;

/// The camera's intrinsics, `K` column by column (rerun's layout), and its image size.
pub fn pinhole(cam: &PinholeCamera) -> rerun::Pinhole {
    let (fx, fy, cx, cy) = (cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32);
    rerun::Pinhole::new([[fx, 0.0, 0.0], [0.0, fy, 0.0], [cx, cy, 1.0]]).with_resolution([cam.width as f32, cam.height as f32])
}

/// `t_world_cam` as the transform from the camera entity to its parent, the world.
pub fn transform(t_world_cam: &Iso3) -> rerun::Transform3D {
    let t = t_world_cam.translation.vector.cast::<f32>();
    let q = t_world_cam.rotation.coords.cast::<f32>(); // (i, j, k, w)
    rerun::Transform3D::from_translation_rotation([t.x, t.y, t.z], rerun::Quaternion::from_xyzw([q.x, q.y, q.z, q.w]))
}

/// An 8-bit RGB image.
pub fn rgb(img: &Rgb8) -> rerun::Image {
    rerun::Image::from_rgb24(img.data().to_vec(), [img.width() as u32, img.height() as u32])
}

/// Depth units per metre in the recording: 0.1 mm steps in 16 bits (to 6.5 m), half the size
/// of 32-bit floats and finer than any depth this framework sees.
pub const DEPTH_UNITS_PER_M: f32 = 10_000.0;

/// A depth map in metres (0: none) as 16-bit depth in [`DEPTH_UNITS_PER_M`] (beyond 6.5 m: the
/// largest value).
pub fn depth(d: &DepthMap) -> rerun::DepthImage {
    let bytes: Vec<u8> = d.data().iter().flat_map(|v| depth_units(*v).to_le_bytes()).collect();
    rerun::DepthImage::from_data_type_and_bytes(bytes, [d.width() as u32, d.height() as u32], rerun::ChannelDatatype::U16).with_meter(DEPTH_UNITS_PER_M)
}

/// One depth in recording units (0 for none, NaN or negative).
fn depth_units(depth_m: f32) -> u16 {
    if depth_m.is_finite() && depth_m > 0.0 { (depth_m * DEPTH_UNITS_PER_M).round().min(f32::from(u16::MAX)) as u16 } else { 0 }
}

/// The camera positions of `poses` as one line strip.
pub fn strip(poses: &[StampedPose], colour: [u8; 3]) -> rerun::LineStrips3D {
    let points: Vec<[f32; 3]> = poses.iter().map(|p| p.t_world_cam.translation.vector.cast::<f32>().into()).collect();
    rerun::LineStrips3D::new([points]).with_colors([rerun::Color::from_rgb(colour[0], colour[1], colour[2])]).with_radii([rerun::Radius::new_ui_points(1.5)])
}

/// Every k-th surfel (k = [`decimation`]) with its colour and radius.
pub fn surfels(map: &SurfelSet, max_points: usize) -> rerun::Points3D {
    let step = decimation(map.len(), max_points);
    let kept = || map.surfels.iter().step_by(step);
    rerun::Points3D::new(kept().map(|s| [s.position_m.x, s.position_m.y, s.position_m.z]))
        .with_colors(kept().map(|s| rerun::Color::from_rgb(s.colour[0], s.colour[1], s.colour[2])))
        .with_radii(kept().map(|s| s.radius_m))
}

/// The step k = ⌈n / max_points⌉ (at least 1) that keeps at most `max_points` of `n` surfels.
fn decimation(n: usize, max_points: usize) -> usize {
    n.div_ceil(max_points.max(1)).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_is_kept_to_a_tenth_of_a_millimetre_and_none_stays_none() {
        assert_eq!(depth_units(0.05), 500);
        assert_eq!(depth_units(0.123_45), 1235);
        assert_eq!(depth_units(0.0), 0);
        assert_eq!(depth_units(f32::NAN), 0);
        assert_eq!(depth_units(-1.0), 0);
        assert_eq!(depth_units(100.0), u16::MAX);
    }

    #[test]
    fn the_decimated_map_holds_at_most_the_asked_count_and_every_surfel_below_it() {
        let kept = |n: usize, max: usize| (0..n).step_by(decimation(n, max)).count();
        assert_eq!(kept(10, 100), 10);
        assert_eq!(kept(100, 100), 100);
        assert_eq!(kept(101, 100), 51);
        assert_eq!(kept(250_000, 100_000), 83_334);
        assert_eq!(kept(0, 100), 0);
        assert_eq!(kept(5, 0), 1, "0 is read as 1");
        for n in [1, 7, 99_999, 100_001, 1_234_567] {
            assert!(kept(n, 100_000) <= 100_000 && kept(n, 100_000) * 2 > n.min(100_000), "{n}");
        }
    }
}
