//! The surfel map types shared by every fuser, and the model prediction the tracker uses.
//!
//! A surfel (Sec. 3.3 of the paper, after Keller et al. 2013) has a position p, normal n,
//! colour c, weight (confidence) w, radius r, initialisation time t0 and last-update time t.
//! Times are frame indices. A fuser may keep its map anywhere (host or device); it exports it
//! only through [`SurfelSet`] snapshots.

use nalgebra::{Point3, Vector3};

use crate::geometry::Iso3;
use crate::image::{DepthMap, GrayF32, Image, Rgb8};

/// One surfel, in world coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Surfel {
    /// Position, metres, world frame.
    pub position_m: Point3<f32>,
    /// Unit normal, world frame, pointing towards the cameras that saw it.
    pub normal: Vector3<f32>,
    /// RGB colour.
    pub colour: [u8; 3],
    /// Accumulated confidence weight w.
    pub confidence: f32,
    /// Disc radius, metres.
    pub radius_m: f32,
    /// Frame index of creation (t0).
    pub t0: u32,
    /// Frame index of the last update (t).
    pub t: u32,
    /// Linear NTSC-luminance albedo fused from the frames that saw the surfel (observed
    /// radiance over the light model's irradiance, from the depth estimator); 0 = never
    /// observed (an estimator without a light model, such as `sensor`).
    pub albedo: f32,
    /// σ of the depth measurements fused into it, metres: the inverse-variance mean
    /// `√(Σα / Σ(α/σ²))` of their per-pixel σ weighed by confidence α (issue 17); 0 = its depth
    /// carried no σ.
    pub sigma_m: f32,
    /// Displacement the trackers' warps (the wall's motion, [`crate::stage::TrackResult::warp`])
    /// have applied to it since its creation, metres, world frame; a loop closure's correction of
    /// drift is not counted. Zero under a rigid tracker. Evaluation compares it with the true
    /// wall's motion (the warp error).
    pub warp_m: Vector3<f32>,
}

impl Surfel {
    /// Whether the surfel is active at frame `now` with time window `delta_t` frames:
    /// active iff `now − t ≤ δt` (ElasticFusion's test).
    pub fn is_active(&self, now: u32, delta_t: u32) -> bool {
        now.saturating_sub(self.t) <= delta_t
    }
}

/// An exported copy of a map, in a canonical order (by t0, then position) so that two fusers'
/// snapshots can be compared element by element.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SurfelSet {
    /// The surfels, sorted.
    pub surfels: Vec<Surfel>,
}

impl SurfelSet {
    /// Wraps surfels and sorts them canonically.
    pub fn new(mut surfels: Vec<Surfel>) -> Self {
        surfels.sort_by(|a, b| {
            a.t0.cmp(&b.t0).then_with(|| {
                let ka = [a.position_m.x, a.position_m.y, a.position_m.z];
                let kb = [b.position_m.x, b.position_m.y, b.position_m.z];
                ka.iter().zip(kb.iter()).map(|(x, y)| x.total_cmp(y)).find(|o| o.is_ne()).unwrap_or(std::cmp::Ordering::Equal)
            })
        });
        Self { surfels }
    }

    /// Number of surfels.
    pub fn len(&self) -> usize {
        self.surfels.len()
    }

    /// Whether the set is empty.
    pub fn is_empty(&self) -> bool {
        self.surfels.is_empty()
    }
}

/// Which part of the map a prediction renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ModelSet {
    /// Surfels seen within the time window δt: used for tracking and fusion.
    Active,
    /// Surfels not seen for longer than δt: the reference of local loop closure.
    Inactive,
}

/// Surfel counts of a map.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MapStats {
    /// All surfels.
    pub total: usize,
    /// Active surfels.
    pub active: usize,
    /// Stable surfels (confidence at or above the fuser's threshold).
    pub stable: usize,
}

/// A splatted rendering of the model from a pose, in that camera's frame (the paper's
/// "predicted active depth map" D̂ and colour Ĉ of Eqs. (2)–(3)).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelView {
    /// The pose it was rendered from.
    pub t_world_cam: Iso3,
    /// Depth along z, metres; 0 = no surfel.
    pub depth_m: DepthMap,
    /// Unit normals in the camera frame (zero where empty).
    pub normals_cam: Image<f32, 3>,
    /// Colour.
    pub colour: Rgb8,
    /// Confidence of the visible surfel (0 where empty).
    pub confidence: GrayF32,
    /// Creation time t0 of the visible surfel (0 where empty).
    pub t0: Image<u32, 1>,
    /// Last-seen time t of the visible surfel (0 where empty).
    pub t: Image<u32, 1>,
    /// Fused albedo of the visible surfel (0 where empty or never observed).
    pub albedo: GrayF32,
    /// σ of the predicted depth, metres: the visible surfel's σ over the square root of its
    /// confidence (the σ of a mean of that many measurements; issue 17); 0 where empty or where
    /// its depth carried no σ.
    pub sigma_m: DepthMap,
}

impl ModelView {
    /// An empty prediction of the given size.
    pub fn empty(width: usize, height: usize, t_world_cam: Iso3) -> Self {
        Self {
            t_world_cam,
            depth_m: DepthMap::new(width, height),
            normals_cam: Image::new(width, height),
            colour: Rgb8::new(width, height),
            confidence: GrayF32::new(width, height),
            t0: Image::new(width, height),
            t: Image::new(width, height),
            albedo: GrayF32::new(width, height),
            sigma_m: DepthMap::new(width, height),
        }
    }

    /// Number of pixels with a surface.
    pub fn valid_pixels(&self) -> usize {
        self.depth_m.data().iter().filter(|d| **d > 0.0).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(t0: u32, x: f32) -> Surfel {
        Surfel {
            position_m: Point3::new(x, 0.0, 0.0),
            normal: Vector3::z(),
            colour: [0; 3],
            confidence: 1.0,
            radius_m: 0.001,
            t0,
            t: t0,
            albedo: 0.0,
            sigma_m: 0.0,
            warp_m: Vector3::zeros(),
        }
    }

    #[test]
    fn snapshot_order_is_canonical() {
        let a = SurfelSet::new(vec![s(2, 0.0), s(1, 0.5), s(1, 0.1)]);
        let b = SurfelSet::new(vec![s(1, 0.1), s(2, 0.0), s(1, 0.5)]);
        assert_eq!(a, b);
        assert_eq!(a.surfels[0].position_m.x, 0.1);
    }

    #[test]
    fn active_window() {
        let x = s(0, 0.0);
        assert!(x.is_active(200, 200));
        assert!(!x.is_active(201, 200));
    }
}
