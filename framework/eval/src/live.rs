//! The live surface error: how far the part of the map the camera saw last is from the wall as
//! it is now. Where the paper's surface error ([`crate::surface`]) aligns the whole map to the
//! rest shape by ICP (so a map that drifts or lags a moving wall can still score well), this
//! one takes the surfels seen in the last `window_frames` frames, moves them by the trajectory
//! alignment alone (the Umeyama alignment of the ATE: SE(3), or Sim(3) for monocular runs; no
//! ICP, so pose error counts) and measures their distance to the true surface at the last frame
//! (point-to-plane near a truth sample, Euclidean beyond). A rigid wall's true surface at any
//! frame is its rest shape.

use serde::Serialize;

use nalgebra::Point3;

use crate::Similarity;
use crate::surface::Truth;
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::Iso3;
use capsule_slam_framework::map::SurfelSet;

/// Live surface error statistics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LiveSurfaceError {
    /// RMS distance of the live surfels to the true surface, metres.
    pub rmse_m: f64,
    /// Median distance, metres.
    pub median_m: f64,
    /// 95th percentile of the distance, metres.
    pub p95_m: f64,
    /// Live surfels measured.
    pub points: usize,
}

/// The surfels of `map` last seen at most `window_frames` frames before `last_frame`, moved by
/// `alignment` (estimated world → true world), against `truth_now`, the true surface at
/// `last_frame`. `None` when no surfel is live or the truth is empty.
pub fn live_surface_error(
    map: &SurfelSet,
    alignment: &Similarity,
    truth_now: &SurfelSet,
    last_frame: u32,
    window_frames: u32,
    plane_radius_m: f64,
) -> Option<LiveSurfaceError> {
    let live = live_distances(map, alignment, truth_now, last_frame, window_frames, plane_radius_m)?;
    stats(live.into_iter().map(|(_, d)| d).collect())
}

/// The true camera at the last frame: its intrinsics (with its lens and round field of view)
/// and its pose in the true world.
#[derive(Debug, Clone, Copy)]
pub struct LastView<'a> {
    /// The camera.
    pub camera: &'a PinholeCamera,
    /// Its true pose at the last frame (camera → true world).
    pub t_world_cam: Iso3,
}

impl LastView<'_> {
    /// Whether a true-world point projects into the image (inside its round field of view if
    /// it has one), in front of the camera. Occlusion is not tested.
    fn sees(&self, p_world: &Point3<f64>) -> bool {
        let c = self.camera;
        let Some(px) = c.project_distorted(&self.t_world_cam.inverse_transform_point(p_world)) else { return false };
        let inside = px.x >= 0.0 && px.y >= 0.0 && px.x < c.width as f64 && px.y < c.height as f64;
        inside && c.fov_radius_px.is_none_or(|r| (px.x - c.cx).hypot(px.y - c.cy) <= r)
    }
}

/// [`live_surface_error`] split by where the live surfels are at the last frame: `(in_view,
/// left)`, those that project into the true last camera's image (the wall that frame measured)
/// and those beside or behind it (surface the camera has left since it saw it, whose motion
/// since then no measurement constrains: a map can carry it along only by the warp's reach or a
/// motion model). Each is measured after the alignment, at its aligned position; `None` when
/// it holds no surfel.
pub fn live_surface_split(
    map: &SurfelSet,
    alignment: &Similarity,
    truth_now: &SurfelSet,
    last_frame: u32,
    window_frames: u32,
    plane_radius_m: f64,
    view: &LastView,
) -> (Option<LiveSurfaceError>, Option<LiveSurfaceError>) {
    let Some(live) = live_distances(map, alignment, truth_now, last_frame, window_frames, plane_radius_m) else { return (None, None) };
    let (in_view, left): (Vec<_>, Vec<_>) = live.into_iter().partition(|(p, _)| view.sees(p));
    let part = |v: Vec<(Point3<f64>, f64)>| stats(v.into_iter().map(|(_, d)| d).collect());
    (part(in_view), part(left))
}

/// Each live surfel's aligned position and its distance to `truth_now`; `None` when the truth
/// is empty.
fn live_distances(
    map: &SurfelSet,
    alignment: &Similarity,
    truth_now: &SurfelSet,
    last_frame: u32,
    window_frames: u32,
    plane_radius_m: f64,
) -> Option<Vec<(Point3<f64>, f64)>> {
    let truth = Truth::new(truth_now)?;
    let first = last_frame.saturating_sub(window_frames);
    let live = map.surfels.iter().filter(|s| s.t >= first && s.t <= last_frame);
    Some(live.map(|s| alignment.apply(&s.position_m.cast())).map(|p| (p, truth.distance(&p, plane_radius_m).1)).collect())
}

/// RMSE, median and p95 of `dist`; `None` when it is empty.
fn stats(mut dist: Vec<f64>) -> Option<LiveSurfaceError> {
    if dist.is_empty() {
        return None;
    }
    dist.sort_by(f64::total_cmp);
    let n = dist.len();
    let rmse_m = (dist.iter().map(|d| d * d).sum::<f64>() / n as f64).sqrt();
    let at = |q: f64| dist[((q * n as f64).ceil() as usize).clamp(1, n) - 1];
    Some(LiveSurfaceError { rmse_m, median_m: dist[n / 2], p95_m: at(0.95), points: n })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::identity;
    use nalgebra::Vector3;

    /// The test plane (2 cm × 2 cm, created at frame 0) last seen at frame `t`.
    fn plane(z: f32, t: u32) -> SurfelSet {
        crate::testing::plane(z, 40, 0, t)
    }

    #[test]
    fn a_map_on_the_wall_scores_zero_and_one_a_millimetre_off_scores_a_millimetre() {
        let truth = plane(0.05, 0);
        let on = live_surface_error(&plane(0.05, 100), &identity(), &truth, 100, 30, 0.001).unwrap();
        assert!(on.rmse_m < 1e-7 && on.p95_m < 1e-7, "{on:?}");
        let off = live_surface_error(&plane(0.051, 100), &identity(), &truth, 100, 30, 0.001).unwrap();
        assert!((off.rmse_m - 0.001).abs() < 1e-6 && (off.median_m - 0.001).abs() < 1e-6, "{off:?}");
        assert_eq!(off.points, 1600);
    }

    #[test]
    fn only_the_surfels_seen_in_the_window_count() {
        let truth = plane(0.05, 0);
        let mut map = plane(0.05, 100);
        map.surfels.extend(plane(0.06, 50).surfels);
        let e = live_surface_error(&map, &identity(), &truth, 100, 30, 0.001).unwrap();
        assert_eq!(e.points, 1600, "the surfels last seen at frame 50 are not live at frame 100");
        assert!(e.rmse_m < 1e-7);
        assert!(live_surface_error(&plane(0.05, 10), &identity(), &truth, 100, 30, 0.001).is_none(), "nothing live");
    }

    #[test]
    fn the_split_separates_the_wall_in_view_from_the_wall_the_camera_left() {
        // The test plane's surfels lie every 0.5 mm in x, y ∈ [−1, 1) cm at z = 5 cm. A 100×100 px
        // camera with fx = 1250 px, 5 cm in front of it looking along +z and shifted by a quarter
        // of the spacing, sees 4 mm of it across: 8 × 8 surfels.
        let truth = plane(0.05, 0);
        let cam = PinholeCamera::new(100, 100, 1250.0, 1250.0, 50.0, 50.0);
        let view = LastView { camera: &cam, t_world_cam: Iso3::translation(0.000125, 0.000125, 0.0) };
        let mut map = plane(0.05, 100);
        // The map lies 3 mm off the wall outside the view and on it inside.
        for s in &mut map.surfels {
            let p = s.position_m;
            if !view.sees(&p.cast()) {
                s.position_m.z += 0.003;
            }
        }
        let (in_view, left) = live_surface_split(&map, &identity(), &truth, 100, 30, 0.001, &view);
        let (in_view, left) = (in_view.unwrap(), left.unwrap());
        assert_eq!((in_view.points, left.points), (64, 1600 - 64));
        assert!(in_view.rmse_m < 1e-7, "{in_view:?}");
        assert!((left.rmse_m - 0.003).abs() < 1e-6, "{left:?}");
        let all = live_surface_error(&map, &identity(), &truth, 100, 30, 0.001).unwrap();
        let parts = (in_view.points as f64 * in_view.rmse_m.powi(2) + left.points as f64 * left.rmse_m.powi(2)) / all.points as f64;
        assert!((all.rmse_m - parts.sqrt()).abs() < 1e-9, "the parts make the whole");
        // A camera turned away sees nothing of it; a round field of view sees less.
        let away = LastView { camera: &cam, t_world_cam: Iso3::translation(0.0, 0.0, 0.1) };
        assert!(live_surface_split(&map, &identity(), &truth, 100, 30, 0.001, &away).0.is_none());
        let round = PinholeCamera { fov_radius_px: Some(20.0), ..cam.clone() };
        let (r, _) = live_surface_split(&map, &identity(), &truth, 100, 30, 0.001, &LastView { camera: &round, ..view });
        assert!(r.unwrap().points < 64);
    }

    #[test]
    fn the_trajectory_alignment_moves_the_map_and_no_icp_hides_an_offset() {
        let truth = plane(0.05, 0);
        // The estimate lives 2 mm off in z; the alignment from the trajectory brings it back.
        let map = plane(0.052, 100);
        let back = Similarity { translation: Vector3::new(0.0, 0.0, -0.002), ..identity() };
        let e = live_surface_error(&map, &back, &truth, 100, 30, 0.001).unwrap();
        assert!(e.rmse_m < 1e-6, "{e:?}");
        let e = live_surface_error(&map, &identity(), &truth, 100, 30, 0.001).unwrap();
        assert!((e.rmse_m - 0.002).abs() < 1e-6, "without the alignment the offset counts: {e:?}");
    }
}
