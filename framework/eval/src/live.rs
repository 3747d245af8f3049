//! The live surface error: how far the part of the map the camera saw last is from the wall as
//! it is now. Where the paper's surface error ([`crate::surface`]) aligns the whole map to the
//! rest shape by ICP (so a map that drifts or lags a moving wall can still score well), this
//! one takes the surfels seen in the last `window_frames` frames, moves them by the trajectory
//! alignment alone (the Umeyama alignment of the ATE: SE(3), or Sim(3) for monocular runs; no
//! ICP, so pose error counts) and measures their distance to the true surface at the last frame
//! (point-to-plane near a truth sample, Euclidean beyond). A rigid wall's true surface at any
//! frame is its rest shape.

use serde::Serialize;

use crate::Similarity;
use crate::surface::Truth;
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
    let truth = Truth::new(truth_now)?;
    let first = last_frame.saturating_sub(window_frames);
    let mut dist: Vec<f64> = map
        .surfels
        .iter()
        .filter(|s| s.t >= first && s.t <= last_frame)
        .map(|s| truth.distance(&alignment.apply(&s.position_m.cast()), plane_radius_m).1)
        .collect();
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
