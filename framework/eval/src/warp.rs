//! The warp error: how well the map's warp followed the wall's own motion (issue 16). A
//! non-rigid tracker moves the surfels it sees with the wall; each surfel adds up the
//! displacement the warps gave it since its creation ([`Surfel::warp_m`]). For the surfels seen
//! at the last frame, this is compared with the true displacement of the wall's material point
//! under the surfel between its creation frame t0 and the last frame.
//!
//! The truth is a wall sampled at several frames on one material grid (vertex i is the same
//! material point in every file, as `synth --surface-every N` writes `gt_surface_NNNNNN.ply`).
//! A surfel is matched to the material point nearest to it at the last frame (after the
//! trajectory alignment, as the live surface error); the point's position at t0 is interpolated
//! linearly between the two truth frames around t0 (at most `max_gap_frames` apart; a 6 s wave
//! sampled every 10 frames at 30 Hz is then linear to ~1 % of its amplitude). A rigid wall's
//! true displacement is zero: its warp error is the warp the tracker made up.
//!
//! Figures: the RMS of |estimated − true| (vector), of its component along the true wall's
//! normal (what depth observes; sliding along the wall is nearly unobservable), the RMS true
//! displacement (the error of a map that does not move) and the RMS estimated one.

use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::Similarity;
use crate::surface::Truth;
use capsule_slam_framework::map::SurfelSet;

/// Warp error statistics, metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WarpError {
    /// RMS of |estimated − true displacement|.
    pub rmse_m: f64,
    /// RMS of the error's component along the true wall normal.
    pub normal_rmse_m: f64,
    /// RMS of |true displacement| (the warp error of a map that stays still).
    pub true_rms_m: f64,
    /// RMS of |estimated displacement|.
    pub estimated_rms_m: f64,
    /// Surfels measured.
    pub points: usize,
    /// Surfels seen at the last frame left out: their creation frame has no truth within
    /// `max_gap_frames` on both sides.
    pub skipped: usize,
}

/// The wall's positions at the frames it was sampled, on one material grid.
#[derive(Debug, Clone, Default)]
pub struct WallMotion {
    /// (frame, vertex positions), sorted by frame; every entry has the same length.
    frames: Vec<(u32, Vec<Point3<f32>>)>,
}

/// Why a surface cannot join a [`WallMotion`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("the true surface at frame {frame} has {got} samples, the one at frame {first_frame} has {expected}: the files do not share one material grid")]
pub struct GridMismatch {
    /// The frame whose sampling differs.
    pub frame: u32,
    /// Its sample count.
    pub got: usize,
    /// The first frame added.
    pub first_frame: u32,
    /// That frame's sample count.
    pub expected: usize,
}

impl WallMotion {
    /// The wall sampled at these (frame, surface) pairs; a single frame is a rigid wall.
    pub fn new<'a>(frames: impl IntoIterator<Item = (u32, &'a SurfelSet)>) -> Result<Self, GridMismatch> {
        let mut wall = Self::default();
        for (frame, s) in frames {
            wall.add(frame, s)?;
        }
        Ok(wall)
    }

    /// Adds the wall at `frame` (replacing one already at that frame).
    pub fn add(&mut self, frame: u32, surface: &SurfelSet) -> Result<(), GridMismatch> {
        if let Some((first_frame, p)) = self.frames.first()
            && p.len() != surface.len()
        {
            return Err(GridMismatch { frame, got: surface.len(), first_frame: *first_frame, expected: p.len() });
        }
        let points = surface.surfels.iter().map(|x| x.position_m).collect();
        match self.frames.binary_search_by_key(&frame, |f| f.0) {
            Ok(k) => self.frames[k].1 = points,
            Err(k) => self.frames.insert(k, (frame, points)),
        }
        Ok(())
    }

    /// Frames sampled.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether no frame is sampled.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Material point `i` at frame `t`, interpolated between the sampled frames around it, or
    /// held beyond the first and last (a rigid wall: one frame, held everywhere). `None` when
    /// the frames around `t` are more than `max_gap` apart.
    fn at(&self, i: usize, t: u32, max_gap: u32) -> Option<Point3<f64>> {
        let k = self.frames.partition_point(|(f, _)| *f <= t);
        if k == 0 {
            return (self.frames.len() == 1).then(|| self.frames[0].1.get(i).map(|p| p.cast()))?;
        }
        let (fa, pa) = &self.frames[k - 1];
        let a: Point3<f64> = pa.get(i)?.cast();
        if *fa == t || self.frames.len() == 1 {
            return Some(a);
        }
        let (fb, pb) = self.frames.get(k)?;
        if fb - fa > max_gap {
            return None;
        }
        let u = f64::from(t - fa) / f64::from(fb - fa);
        Some(a + u * (pb.get(i)?.cast::<f64>() - a))
    }
}

/// The warp error of the surfels of `map` seen at `last_frame`, moved by `alignment`
/// (estimated world → true world), against `wall`, whose surface at `last_frame` is
/// `truth_now`. `None` when no surfel is measured.
pub fn warp_error(
    map: &SurfelSet,
    alignment: &Similarity,
    wall: &WallMotion,
    truth_now: &SurfelSet,
    last_frame: u32,
    max_gap_frames: u32,
) -> Option<WarpError> {
    let truth = Truth::new(truth_now)?;
    let rotate = alignment.scale * alignment.rotation;
    let (mut err2, mut nrm2, mut true2, mut est2, mut points, mut skipped) = (0.0, 0.0, 0.0, 0.0, 0usize, 0usize);
    for s in map.surfels.iter().filter(|s| s.t == last_frame) {
        let (i, _) = truth.distance(&alignment.apply(&s.position_m.cast()), 0.0);
        let (Some(then), Some(now)) = (wall.at(i, s.t0, max_gap_frames), wall.at(i, last_frame, max_gap_frames)) else {
            skipped += 1;
            continue;
        };
        let true_m: Vector3<f64> = now - then;
        let est_m: Vector3<f64> = rotate * s.warp_m.cast::<f64>();
        let e = est_m - true_m;
        let n = truth_now.surfels[i].normal.cast::<f64>().try_normalize(1e-9).unwrap_or_else(Vector3::zeros);
        err2 += e.norm_squared();
        nrm2 += e.dot(&n).powi(2);
        true2 += true_m.norm_squared();
        est2 += est_m.norm_squared();
        points += 1;
    }
    if points == 0 {
        return None;
    }
    let rms = |x: f64| (x / points as f64).sqrt();
    Some(WarpError { rmse_m: rms(err2), normal_rmse_m: rms(nrm2), true_rms_m: rms(true2), estimated_rms_m: rms(est2), points, skipped })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::identity;
    use capsule_slam_framework::map::Surfel;
    use nalgebra::Matrix3;

    /// The test plane (1 cm × 1 cm), seen from t0 to t.
    fn plane(z: f32, t0: u32, t: u32) -> SurfelSet {
        crate::testing::plane(z, 20, t0, t)
    }

    /// A wall that moves 2 mm along z between frames 0 and 20 (sampled at 0, 10, 20).
    fn moving() -> (SurfelSet, SurfelSet, SurfelSet) {
        (plane(0.05, 0, 0), plane(0.051, 0, 0), plane(0.052, 0, 0))
    }

    #[test]
    fn a_warp_that_followed_the_wall_scores_zero_and_a_still_map_the_true_motion() {
        let (a, b, c) = moving();
        let wall = WallMotion::new(vec![(0, &a), (10, &b), (20, &c)]).unwrap();
        // Surfels created at frame 5 (the wall at 50.5 mm then), seen at 20, warped 1.5 mm.
        let mut map = plane(0.052, 5, 20);
        map.surfels.iter_mut().for_each(|s| s.warp_m = Vector3::new(0.0, 0.0, 0.0015));
        let e = warp_error(&map, &identity(), &wall, &c, 20, 30).unwrap();
        assert!(e.rmse_m < 1e-7 && e.normal_rmse_m < 1e-7, "{e:?}");
        assert!((e.true_rms_m - 0.0015).abs() < 1e-7 && (e.estimated_rms_m - 0.0015).abs() < 1e-7, "{e:?}");
        assert_eq!((e.points, e.skipped), (400, 0));
        map.surfels.iter_mut().for_each(|s| s.warp_m = Vector3::zeros());
        let still = warp_error(&map, &identity(), &wall, &c, 20, 30).unwrap();
        assert!((still.rmse_m - 0.0015).abs() < 1e-7 && (still.normal_rmse_m - 0.0015).abs() < 1e-7, "{still:?}");
    }

    #[test]
    fn sliding_along_the_wall_is_an_error_but_not_along_its_normal() {
        let (a, b, c) = moving();
        let wall = WallMotion::new(vec![(0, &a), (10, &b), (20, &c)]).unwrap();
        let mut map = plane(0.052, 0, 20);
        map.surfels.iter_mut().for_each(|s| s.warp_m = Vector3::new(0.001, 0.0, 0.002));
        let e = warp_error(&map, &identity(), &wall, &c, 20, 30).unwrap();
        assert!((e.rmse_m - 0.001).abs() < 1e-7 && e.normal_rmse_m < 1e-7, "{e:?}");
    }

    #[test]
    fn the_alignment_rotates_the_estimated_displacement_and_only_the_last_frame_counts() {
        let (a, b, c) = moving();
        let wall = WallMotion::new(vec![(0, &a), (10, &b), (20, &c)]).unwrap();
        // The estimate's world is the true one turned 90° about x; the alignment brings the map
        // and its displacements back onto the wall.
        let rx = Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0);
        let align = Similarity { rotation: rx, translation: Vector3::zeros(), scale: 1.0 };
        let mut map = SurfelSet {
            surfels: plane(0.052, 0, 20)
                .surfels
                .into_iter()
                .map(|s| Surfel {
                    position_m: Point3::from(rx.transpose() * s.position_m.coords.cast::<f64>()).cast(),
                    warp_m: (rx.transpose() * Vector3::new(0.0, 0.0, 0.002)).cast(),
                    ..s
                })
                .collect(),
        };
        map.surfels.extend(plane(0.06, 0, 12).surfels);
        let e = warp_error(&map, &align, &wall, &c, 20, 30).unwrap();
        assert!(e.rmse_m < 1e-6, "{e:?}");
        assert_eq!(e.points, 400, "the surfels last seen at frame 12 are not measured");
    }

    #[test]
    fn a_rigid_wall_counts_every_warp_as_error_and_sparse_truth_skips() {
        let a = plane(0.05, 0, 0);
        let rigid = WallMotion::new(vec![(0, &a)]).unwrap();
        let mut map = plane(0.05, 40, 90);
        map.surfels.iter_mut().for_each(|s| s.warp_m = Vector3::new(0.0, 0.0, 0.0003));
        let e = warp_error(&map, &identity(), &rigid, &a, 90, 30).unwrap();
        assert!((e.rmse_m - 0.0003).abs() < 1e-7 && e.true_rms_m == 0.0, "{e:?}");
        let (b, c) = (plane(0.051, 0, 0), plane(0.052, 0, 0));
        let sparse = WallMotion::new(vec![(0, &a), (50, &b), (90, &c)]).unwrap();
        let e = warp_error(&map, &identity(), &sparse, &c, 90, 30);
        assert!(e.is_none(), "truth 50 frames apart around t0 = 40 is too coarse: {e:?}");
        let odd = plane(0.05, 0, 0);
        let short = SurfelSet { surfels: odd.surfels[..10].to_vec() };
        assert!(matches!(WallMotion::new(vec![(0, &a), (10, &short)]), Err(GridMismatch { frame: 10, got: 10, .. })));
    }
}
