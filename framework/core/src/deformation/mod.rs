//! Embedded deformation (Sumner, Schmid and Pauly 2007, "Embedded deformation for shape
//! manipulation", SIGGRAPH, doi:10.1145/1275808.1276478), as the paper's Eqs. (5)–(7) apply
//! it to the surfel map. A loop closer computes a [`Deformation`]; the pipeline applies it to
//! the map (through the fuser) and to the trajectory, so every consumer warps the same way.
//!
//! Influencing nodes of a point are the `k` nearest nodes in space (Sumner's rule, the paper's
//! text) among a candidate set ([`Window`]): every node; ElasticFusion's `m` nodes nearest in
//! time to the point's own time; or the nodes within a number of frames of it. An old surface
//! and a new one that cross in space (exactly what a loop closure brings together) are thus
//! moved by their own nodes.
//!
//! Whose time ([`SurfelTime`]): ElasticFusion times nodes and surfels by creation (t0). A surface
//! the camera keeps seeing is kept consistent with the camera by frame-to-model tracking, so its
//! error is the camera's error when it was last seen (t), whenever it was created; timed by t,
//! every surfel in the current view moves with the current camera.

use nalgebra::{Matrix3, Point3, UnitQuaternion, Vector3};

use crate::geometry::Iso3;
pub use crate::geometry::orthonormalise;
use crate::map::Surfel;

mod grid;
use grid::NodeGrid;

/// One graph node: position g, affine 3×3 R and translation t, and its time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeformationNode {
    /// Node position g, metres, world frame.
    pub position_m: Point3<f64>,
    /// Affine part R (identity when undeformed).
    pub rotation: Matrix3<f64>,
    /// Translation t, metres (zero when undeformed).
    pub translation_m: Vector3<f64>,
    /// Frame index of the node (the [`SurfelTime`] of the surfel it was sampled from).
    pub time: u32,
}

impl DeformationNode {
    /// An undeformed node at `position_m`.
    pub fn identity(position_m: Point3<f64>, time: u32) -> Self {
        Self { position_m, rotation: Matrix3::identity(), translation_m: Vector3::zeros(), time }
    }

    /// The node's local transform of a point: `R (v − g) + g + t` (one term of Eq. (5)).
    pub fn transform(&self, v: &Point3<f64>) -> Point3<f64> {
        self.position_m + self.rotation * (v - self.position_m) + self.translation_m
    }
}

/// Which nodes may influence a point of a given time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Window {
    /// Every node (Sumner: space alone).
    All,
    /// The m nodes nearest in time (ElasticFusion: 20, the nearest and the m − 1 before it,
    /// completed by the ones after it if fewer exist).
    Nodes(usize),
    /// The nodes within this many frames of the point's time; if fewer than k + 1, the k + 1
    /// nearest in time.
    Frames(u32),
}

/// The time of a surfel that picks its influencing nodes (and the time of the nodes sampled
/// from surfels).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SurfelTime {
    /// t0, the frame that created it (ElasticFusion).
    Created,
    /// t, the frame that last saw it.
    LastSeen,
}

impl SurfelTime {
    /// This time of `s`.
    pub fn of(self, s: &Surfel) -> u32 {
        match self {
            Self::Created => s.t0,
            Self::LastSeen => s.t,
        }
    }
}

/// How a camera pose follows a deformation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PoseWarp {
    /// Its centre warped as a point, its rotation by the orthonormalised blend of the nodes'
    /// R (ElasticFusion). Inside an organ the centre is in the lumen, centimetres from the
    /// nodes on the wall, so their affine transforms are extrapolated over a long lever arm.
    Position,
    /// With what it looks at: a 3 × 3 grid of points at this distance in front of it (rays
    /// through ±26.6° in x and y) is warped and the rigid motion that fits them best (Kabsch)
    /// moves the pose.
    View {
        /// Distance of the points from the camera, metres.
        depth_m: f64,
    },
}

/// A deformation graph with optimised node transforms.
#[derive(Debug, Clone, PartialEq)]
pub struct Deformation {
    /// The nodes, in time order (stable).
    pub nodes: Vec<DeformationNode>,
    /// Number of influencing nodes per point (k; the (k+1)-th nearest gives d_max).
    pub k: usize,
    /// Candidate nodes per point.
    pub window: Window,
    /// Which surfel time the nodes carry and a surfel is warped by ([`Deformation::warp_surfel`]).
    pub surfel_time: SurfelTime,
    /// How camera poses follow ([`Deformation::warp_pose`]).
    pub pose_warp: PoseWarp,
    /// Nodes farther than this from a point do not influence it, and a point with none this
    /// near is not moved (metres; `None`: no limit, Sumner). A tracker's warp of the surface in
    /// view sets it, so the rest of the map stays where it is.
    pub reach_m: Option<f64>,
}

impl Deformation {
    /// A deformation of `nodes` (sorted here by time) with `k` influencing nodes per point among
    /// the `window`, surfels timed by creation (ElasticFusion; see [`Deformation::timed_by`]).
    pub fn new(mut nodes: Vec<DeformationNode>, k: usize, window: Window) -> Self {
        nodes.sort_by_key(|n| n.time);
        Self { nodes, k, window, surfel_time: SurfelTime::Created, pose_warp: PoseWarp::Position, reach_m: None }
    }

    /// The same deformation with poses warped by `pose_warp`.
    pub fn poses_by(self, pose_warp: PoseWarp) -> Self {
        Self { pose_warp, ..self }
    }

    /// The same deformation limited to points within `reach_m` of a node.
    pub fn within(self, reach_m: f64) -> Self {
        Self { reach_m: Some(reach_m), ..self }
    }

    /// The same deformation with surfels timed by `surfel_time`.
    pub fn timed_by(self, surfel_time: SurfelTime) -> Self {
        Self { surfel_time, ..self }
    }

    /// Indices of the candidate nodes of a point of time `time` (nodes are sorted by time, so
    /// every window is a contiguous range).
    pub fn candidates(&self, time: u32) -> std::ops::Range<usize> {
        let n = self.nodes.len();
        let nearest_m = |m: usize| {
            let m = m.clamp(1, n);
            // The first node at or after `time`, or the one before it if that is nearer.
            let after = self.nodes.partition_point(|x| x.time < time);
            let nearest = if after == n || (after > 0 && time - self.nodes[after - 1].time <= self.nodes[after].time - time) { after - 1 } else { after };
            let start = (nearest + 1).saturating_sub(m);
            let end = (start + m).min(n);
            end.saturating_sub(m)..end
        };
        match self.window {
            Window::Nodes(m) if m < n => nearest_m(m),
            Window::Frames(w) => {
                let lo = self.nodes.partition_point(|x| x.time < time.saturating_sub(w));
                let hi = self.nodes.partition_point(|x| x.time <= time.saturating_add(w));
                if hi - lo > self.k { lo..hi } else { nearest_m(self.k + 1) }
            }
            _ => 0..n,
        }
    }

    /// The influencing nodes of a point `p` of time `time` (a surfel's t0, a pose's frame
    /// index) with their normalised weights, `w_n = (1 − ‖p − g_n‖ / d_max)²` (Eq. (7)), d_max
    /// the distance to the (k+1)-th nearest candidate. With k or fewer candidates, d_max is
    /// 1.01 × the farthest one's distance.
    pub fn influences(&self, p: &Point3<f64>, time: u32) -> Vec<(usize, f64)> {
        self.influences_among(p, self.candidates(time))
    }

    /// [`Deformation::influences`] among the given candidate nodes (in any order; ties are
    /// broken by index), those beyond [`Deformation::reach_m`] left out. With a reach and fewer
    /// than k + 1 nodes in it, d_max is the reach.
    pub fn influences_among(&self, p: &Point3<f64>, candidates: impl Iterator<Item = usize>) -> Vec<(usize, f64)> {
        self.with_influences(p, candidates, <[(usize, f64)]>::to_vec)
    }

    /// Calls `f` with [`Deformation::influences_among`] held on the stack (k < 16) rather than
    /// in a new vector: the per-surfel path of a map warp.
    pub fn with_influences<R>(&self, p: &Point3<f64>, candidates: impl Iterator<Item = usize>, f: impl FnOnce(&[(usize, f64)]) -> R) -> R {
        const INLINE: usize = 16;
        let k = self.k.max(1);
        if k < INLINE {
            let mut buf = [(0usize, 0.0f64); INLINE];
            let n = self.influences_into(p, candidates, &mut buf[..=k]);
            f(&buf[..n])
        } else {
            let mut buf = vec![(0usize, 0.0f64); k + 1];
            let n = self.influences_into(p, candidates, &mut buf);
            f(&buf[..n])
        }
    }

    /// [`Deformation::influences_among`] into `buf` (k + 1 entries): returns how many of its
    /// first entries hold the influences.
    fn influences_into(&self, p: &Point3<f64>, candidates: impl Iterator<Item = usize>, buf: &mut [(usize, f64)]) -> usize {
        let cap = buf.len();
        let k = cap - 1;
        let reach2 = self.reach_m.map_or(f64::INFINITY, |r| r * r);
        // The k + 1 nearest candidates by squared distance (then index), kept sorted: one pass
        // over the window, an insertion from the back, no sort of it.
        let mut len = 0;
        for i in candidates {
            let di = (p - self.nodes[i].position_m).norm_squared();
            if di > reach2 || (len == cap && di >= buf[k].1) {
                continue;
            }
            let before = |x: &(usize, f64)| x.1 < di || (x.1 == di && x.0 < i);
            let mut at = len.min(k);
            while at > 0 && !before(&buf[at - 1]) {
                buf[at] = buf[at - 1];
                at -= 1;
            }
            buf[at] = (i, di);
            len = (len + 1).min(cap);
        }
        let d = &mut buf[..len];
        d.iter_mut().for_each(|x| x.1 = x.1.sqrt());
        let d_max = match (len > k, self.reach_m) {
            (true, _) => d[k].1,
            (false, Some(reach)) => reach,
            (false, None) => d.last().map_or(0.0, |&(_, dl)| 1.01 * dl),
        };
        let n = len.min(k);
        let w = &mut buf[..n];
        w.iter_mut().for_each(|x| x.1 = if d_max > 0.0 { (1.0 - x.1 / d_max).max(0.0).powi(2) } else { 1.0 });
        let sum: f64 = w.iter().map(|x| x.1).sum();
        if sum > 0.0 {
            w.iter_mut().for_each(|x| x.1 /= sum);
            n
        } else if n > 0 {
            // Every node is exactly at d_max: fall back to the nearest one alone.
            w[0].1 = 1.0;
            1
        } else {
            0
        }
    }

    /// Warps a point of time `time`, Eq. (5): `φ(v) = Σ w_n [R_n (v − g_n) + g_n + t_n]`.
    pub fn warp_point(&self, p: &Point3<f64>, time: u32) -> Point3<f64> {
        self.warp_with(p, &self.influences(p, time))
    }

    /// Warps a normal at point `p`, Eq. (6): `n' = normalize(Σ w_n R_n⁻ᵀ n)`.
    pub fn warp_normal(&self, p: &Point3<f64>, n: &Vector3<f64>, time: u32) -> Vector3<f64> {
        let infl = self.influences(p, time);
        self.warp_normal_with(n, &infl)
    }

    /// How far the nodes move (a node's own position moves by its translation): mean and max,
    /// metres; zeros without nodes.
    pub fn node_displacement_m(&self) -> (f64, f64) {
        let d: Vec<f64> = self.nodes.iter().map(|n| n.translation_m.norm()).collect();
        if d.is_empty() {
            return (0.0, 0.0);
        }
        (d.iter().sum::<f64>() / d.len() as f64, d.iter().fold(0.0, |m: f64, v| m.max(*v)))
    }

    /// A warper for many surfels: it knows which windows hold only undeformed nodes (the
    /// frozen old map) and leaves their surfels as they are without searching the nodes.
    pub fn warper(&self) -> Warper<'_> {
        let mut moving_before = Vec::with_capacity(self.nodes.len() + 1);
        let mut count = 0u32;
        moving_before.push(0);
        for n in &self.nodes {
            count += u32::from(n.rotation != Matrix3::identity() || n.translation_m != Vector3::zeros());
            moving_before.push(count);
        }
        let grid = self.reach_m.filter(|r| *r > 0.0 && r.is_finite()).map(|r| {
            let positions: Vec<Point3<f64>> = self.nodes.iter().map(|n| n.position_m).collect();
            NodeGrid::new(&positions, r)
        });
        Warper { deformation: self, normal_maps: self.nodes.iter().map(|n| normal_map(&n.rotation)).collect(), moving_before, grid }
    }

    /// Warps a surfel's position and normal in place (timed by [`Deformation::surfel_time`]).
    pub fn warp_surfel(&self, s: &mut Surfel) {
        let p = s.position_m.cast::<f64>();
        let infl = self.influences(&p, self.surfel_time.of(s));
        s.normal = self.warp_normal_with(&s.normal.cast(), &infl).cast();
        s.position_m = self.warp_with(&p, &infl).cast();
    }

    /// [`Deformation::warp_point`] with precomputed influences.
    pub fn warp_with(&self, p: &Point3<f64>, influences: &[(usize, f64)]) -> Point3<f64> {
        if influences.is_empty() {
            return *p;
        }
        let mut out = Vector3::zeros();
        for &(i, w) in influences {
            out += w * self.nodes[i].transform(p).coords;
        }
        Point3::from(out)
    }

    /// [`Deformation::warp_normal`] with precomputed influences.
    pub fn warp_normal_with(&self, n: &Vector3<f64>, influences: &[(usize, f64)]) -> Vector3<f64> {
        blend_normal(n, influences, |i| normal_map(&self.nodes[i].rotation))
    }

    /// Warps a camera pose of frame `time` by [`Deformation::pose_warp`].
    pub fn warp_pose(&self, t_world_cam: &Iso3, time: u32) -> Iso3 {
        let PoseWarp::View { depth_m } = self.pose_warp else { return self.warp_pose_position(t_world_cam, time) };
        let grid = [-0.5, 0.0, 0.5];
        let seen: Vec<Point3<f64>> =
            grid.iter().flat_map(|&y| grid.iter().map(move |&x| t_world_cam * Point3::new(x * depth_m, y * depth_m, depth_m))).collect();
        let warped: Vec<Point3<f64>> = seen.iter().map(|p| self.warp_point(p, time)).collect();
        let n = seen.len() as f64;
        let (ps, qs) = (seen.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n, warped.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n);
        let cross: Matrix3<f64> = seen.iter().zip(&warped).map(|(p, q)| (q.coords - qs) * (p.coords - ps).transpose()).sum();
        let r = orthonormalise(&cross);
        let centre = r * (t_world_cam.translation.vector - ps) + qs;
        Iso3::from_parts(centre.into(), UnitQuaternion::from_rotation_matrix(&(r * t_world_cam.rotation.to_rotation_matrix())))
    }

    /// ElasticFusion's pose update: the centre warped as a point, the rotation by the
    /// SVD-orthonormalised blend `Σ w_n R_n`.
    fn warp_pose_position(&self, t_world_cam: &Iso3, time: u32) -> Iso3 {
        let p = Point3::from(t_world_cam.translation.vector);
        let infl = self.influences(&p, time);
        if infl.is_empty() {
            return *t_world_cam;
        }
        let blend: Matrix3<f64> = infl.iter().map(|&(i, w)| w * self.nodes[i].rotation).sum();
        let r = orthonormalise(&blend) * t_world_cam.rotation.to_rotation_matrix();
        Iso3::from_parts(self.warp_with(&p, &infl).coords.into(), UnitQuaternion::from_rotation_matrix(&r))
    }
}

/// The matrix that carries a normal through a node's affine part R: `R⁻ᵀ` (R itself when it is
/// singular).
fn normal_map(r: &Matrix3<f64>) -> Matrix3<f64> {
    r.try_inverse().map_or(*r, |m| m.transpose())
}

/// `normalise(Σ w_i M_i n)` over the influences, with `M_i = map(i)`; `n` when the sum vanishes
/// (Sumner et al. 2007, Eq. 2).
fn blend_normal(n: &Vector3<f64>, influences: &[(usize, f64)], map: impl Fn(usize) -> Matrix3<f64>) -> Vector3<f64> {
    let mut out = Vector3::zeros();
    for &(i, w) in influences {
        out += w * (map(i) * n);
    }
    let len = out.norm();
    if len > 1e-12 { out / len } else { *n }
}

/// [`Deformation::warp_surfel`] for a whole map ([`Deformation::warper`]).
pub struct Warper<'a> {
    deformation: &'a Deformation,
    /// Each node's normal map `R⁻ᵀ`, inverted once rather than per surfel.
    normal_maps: Vec<Matrix3<f64>>,
    /// `moving_before[i]`: nodes before node i that are not the identity.
    moving_before: Vec<u32>,
    /// The nodes by cell, with a reach.
    grid: Option<NodeGrid>,
}

impl Warper<'_> {
    /// Warps a surfel's position and normal in place; the same result as
    /// [`Deformation::warp_surfel`].
    pub fn warp_surfel(&self, s: &mut Surfel) {
        let d = self.deformation;
        let r = d.candidates(d.surfel_time.of(s));
        if self.moving_before[r.end] == self.moving_before[r.start] {
            return;
        }
        let Some(grid) = &self.grid else { return d.warp_surfel(s) };
        let p = s.position_m.cast::<f64>();
        let near = grid.near(&p);
        if near.is_empty() {
            return;
        }
        d.with_influences(&p, near.iter().copied().filter(|i| r.contains(i)), |infl| {
            if !infl.is_empty() {
                s.normal = blend_normal(&s.normal.cast(), infl, |i| self.normal_maps[i]).cast();
                s.position_m = d.warp_with(&p, infl).cast();
            }
        });
    }

    /// Warps a surfel as [`Self::warp_surfel`] and adds its displacement to
    /// [`Surfel::warp_m`]: for a tracker's warp (the wall's own motion), not for a loop
    /// closure's correction of drift.
    pub fn warp_surfel_as_motion(&self, s: &mut Surfel) {
        let before = s.position_m;
        self.warp_surfel(s);
        s.warp_m += s.position_m - before;
    }
}

#[cfg(test)]
mod tests;
