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

use nalgebra::{Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};

use crate::geometry::Iso3;
use crate::map::Surfel;

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
}

impl Deformation {
    /// A deformation of `nodes` (sorted here by time) with `k` influencing nodes per point among
    /// the `window`, surfels timed by creation (ElasticFusion; see [`Deformation::timed_by`]).
    pub fn new(mut nodes: Vec<DeformationNode>, k: usize, window: Window) -> Self {
        nodes.sort_by_key(|n| n.time);
        Self { nodes, k, window, surfel_time: SurfelTime::Created, pose_warp: PoseWarp::Position }
    }

    /// The same deformation with poses warped by `pose_warp`.
    pub fn poses_by(self, pose_warp: PoseWarp) -> Self {
        Self { pose_warp, ..self }
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
        let k = self.k.max(1);
        // The k + 1 nearest candidates by squared distance (then index), kept sorted in a short
        // list: one pass over the window, no sort of it.
        let mut d: Vec<(usize, f64)> = Vec::with_capacity(k + 2);
        for i in self.candidates(time) {
            let di = (p - self.nodes[i].position_m).norm_squared();
            if d.len() > k && di >= d[k].1 {
                continue;
            }
            let at = d.partition_point(|x| x.1 < di || (x.1 == di && x.0 < i));
            d.insert(at, (i, di));
            d.truncate(k + 1);
        }
        d.iter_mut().for_each(|x| x.1 = x.1.sqrt());
        let d_max = match d.get(k) {
            Some(&(_, dk)) => dk,
            None => d.last().map_or(0.0, |&(_, dl)| 1.01 * dl),
        };
        d.truncate(k);
        let mut w: Vec<(usize, f64)> = d.iter().map(|&(i, di)| (i, if d_max > 0.0 { (1.0 - di / d_max).max(0.0).powi(2) } else { 1.0 })).collect();
        let sum: f64 = w.iter().map(|x| x.1).sum();
        if sum > 0.0 {
            w.iter_mut().for_each(|x| x.1 /= sum);
        } else if let Some(first) = w.first_mut() {
            // Every node is exactly at d_max: fall back to the nearest one alone.
            first.1 = 1.0;
            w.truncate(1);
        }
        w
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
        Warper { deformation: self, moving_before }
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
        let mut out = Vector3::zeros();
        for &(i, w) in influences {
            let r = self.nodes[i].rotation;
            let r_inv_t = r.try_inverse().map_or(r, |m| m.transpose());
            out += w * (r_inv_t * n);
        }
        let len = out.norm();
        if len > 1e-12 { out / len } else { *n }
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

/// [`Deformation::warp_surfel`] for a whole map ([`Deformation::warper`]).
pub struct Warper<'a> {
    deformation: &'a Deformation,
    /// `moving_before[i]`: nodes before node i that are not the identity.
    moving_before: Vec<u32>,
}

impl Warper<'_> {
    /// Warps a surfel's position and normal in place; the same result as
    /// [`Deformation::warp_surfel`].
    pub fn warp_surfel(&self, s: &mut Surfel) {
        let r = self.deformation.candidates(self.deformation.surfel_time.of(s));
        if self.moving_before[r.end] == self.moving_before[r.start] {
            return;
        }
        self.deformation.warp_surfel(s);
    }
}

/// The rotation nearest to `m` in the Frobenius norm (U Vᵀ of its SVD, with the sign fixed so
/// that the determinant is +1).
pub fn orthonormalise(m: &Matrix3<f64>) -> Rotation3<f64> {
    let svd = m.svd(true, true);
    match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => {
            let mut r = u * v_t;
            if r.determinant() < 0.0 {
                let mut u2 = u;
                u2.column_mut(2).neg_mut();
                r = u2 * v_t;
            }
            Rotation3::from_matrix_unchecked(r)
        }
        _ => Rotation3::identity(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn grid(k: usize) -> Deformation {
        let mut nodes = Vec::new();
        for i in 0..4 {
            for j in 0..4 {
                nodes.push(DeformationNode::identity(Point3::new(i as f64 * 0.01, j as f64 * 0.01, 0.0), 0));
            }
        }
        Deformation::new(nodes, k, Window::All)
    }

    proptest! {
        #[test]
        fn identity_deformation_is_a_no_op(x in -0.01f64..0.05, y in -0.01f64..0.05, z in -0.01f64..0.01) {
            let d = grid(4);
            let p = Point3::new(x, y, z);
            prop_assert!((d.warp_point(&p, 0) - p).norm() < 1e-12);
            let n = Vector3::new(0.3, -0.2, 0.9).normalize();
            prop_assert!((d.warp_normal(&p, &n, 0) - n).norm() < 1e-12);
        }

        #[test]
        fn weights_sum_to_one(x in -0.01f64..0.05, y in -0.01f64..0.05) {
            let w = grid(4).influences(&Point3::new(x, y, 0.003), 0);
            prop_assert_eq!(w.len(), 4);
            prop_assert!((w.iter().map(|x| x.1).sum::<f64>() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn rigid_deformation_moves_points_and_poses_rigidly() {
        let rot = Rotation3::from_euler_angles(0.1, -0.05, 0.2);
        let shift = Vector3::new(0.002, -0.001, 0.003);
        let mut d = grid(4);
        // A rigid motion x ↦ R x + s expressed per node: R (v − g) + g + t with t = R g + s − g.
        for n in &mut d.nodes {
            n.rotation = *rot.matrix();
            n.translation_m = rot * n.position_m.coords + shift - n.position_m.coords;
        }
        let p = Point3::new(0.013, 0.021, 0.002);
        assert!((d.warp_point(&p, 0) - (rot * p + shift)).norm() < 1e-12);
        let n = Vector3::new(0.0, 0.6, 0.8);
        assert!((d.warp_normal(&p, &n, 0) - rot * n).norm() < 1e-12);
        let pose = Iso3::translation(0.01, 0.01, -0.02);
        for d in [d.clone(), d.poses_by(PoseWarp::View { depth_m: 0.02 })] {
            let warped = d.warp_pose(&pose, 0);
            assert!((warped.rotation.to_rotation_matrix().matrix() - rot.matrix()).norm() < 1e-9);
            assert!((warped.translation.vector - (rot * pose.translation.vector + shift)).norm() < 1e-12);
        }
    }

    #[test]
    fn a_time_window_keeps_crossing_surfaces_apart() {
        // Two layers of nodes at the same place, an old one (t0 0..16) that stays and a new one
        // (t0 100..116) that moves by 2 mm: with a window of 16, a point of time 3 or 120 follows
        // its own layer only.
        let old = grid(4).nodes;
        let new: Vec<DeformationNode> =
            old.iter().enumerate().map(|(i, n)| DeformationNode { time: 100 + i as u32, translation_m: Vector3::new(0.0, 0.0, 0.002), ..*n }).collect();
        let old: Vec<DeformationNode> = old.iter().enumerate().map(|(i, n)| DeformationNode { time: i as u32, ..*n }).collect();
        let p = Point3::new(0.012, 0.017, 0.0);
        let windowed = Deformation::new([new.clone(), old.clone()].concat(), 4, Window::Nodes(16));
        assert!((windowed.warp_point(&p, 3) - p).norm() < 1e-12, "an old point stays");
        assert!((windowed.warp_point(&p, 120) - (p + Vector3::new(0.0, 0.0, 0.002))).norm() < 1e-12, "a new point moves");
        let spatial = Deformation::new([new.clone(), old.clone()].concat(), 4, Window::All);
        let mixed = spatial.warp_point(&p, 3).z;
        assert!(mixed > 0.0 && mixed < 0.002, "without a window the layers mix: {mixed}");
        // The window is the m nodes up to the nearest in time, completed forward.
        assert_eq!(windowed.candidates(0), 0..16);
        assert_eq!(windowed.candidates(108), 9..25);
        assert_eq!(windowed.candidates(200), 16..32);
        assert_eq!(windowed.candidates(20), 0..16);
        assert_eq!(windowed.candidates(57), 0..16, "node 15 (t0 15) is nearer than node 16 (t0 100)");
        assert_eq!(windowed.candidates(58), 1..17, "node 16 is nearer");
        // A window of frames: the same separation, whatever the node counts.
        let framed = Deformation::new([new, old].concat(), 4, Window::Frames(30));
        assert!((framed.warp_point(&p, 3) - p).norm() < 1e-12, "an old point stays");
        assert!((framed.warp_point(&p, 120) - (p + Vector3::new(0.0, 0.0, 0.002))).norm() < 1e-12, "a new point moves");
        assert_eq!(framed.candidates(10), 0..16);
        assert_eq!(framed.candidates(140), 26..32, "frames 110 to 170 hold the nodes of times 110..115");
        assert_eq!(framed.candidates(60), 12..17, "no node within 30 frames: the k + 1 nearest in time (up to time 100)");
    }

    #[test]
    fn a_surfel_is_warped_by_the_time_the_deformation_names() {
        // Old nodes (time 0..16) stay, new ones (100..116) move by 2 mm; a surfel created at 5
        // and last seen at 110 moves with the new layer when timed by last sighting.
        let old = grid(4).nodes;
        let new: Vec<DeformationNode> =
            old.iter().enumerate().map(|(i, n)| DeformationNode { time: 100 + i as u32, translation_m: Vector3::new(0.0, 0.0, 0.002), ..*n }).collect();
        let old: Vec<DeformationNode> = old.iter().enumerate().map(|(i, n)| DeformationNode { time: i as u32, ..*n }).collect();
        let d = Deformation::new([new, old].concat(), 4, Window::Frames(30));
        let s = Surfel {
            position_m: Point3::new(0.012, 0.017, 0.0),
            normal: Vector3::z(),
            colour: [0; 3],
            confidence: 10.0,
            radius_m: 0.001,
            t0: 5,
            t: 110,
            albedo: 0.0,
        };
        let mut created = s;
        d.clone().warp_surfel(&mut created);
        assert_eq!(created.position_m, s.position_m, "timed by creation it stays");
        let mut skipped = s;
        d.warper().warp_surfel(&mut skipped);
        assert_eq!(skipped, created, "the warper skips the window of undeformed old nodes");
        let mut seen = s;
        let d = d.timed_by(SurfelTime::LastSeen);
        let mut fast = s;
        d.warper().warp_surfel(&mut fast);
        d.warp_surfel(&mut seen);
        assert_eq!(fast, seen);
        assert!((seen.position_m.z - 0.002).abs() < 1e-7, "timed by last sighting it moves: {}", seen.position_m);
        assert!((seen.normal.norm() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn orthonormalise_returns_a_rotation() {
        let m = Matrix3::new(1.1, 0.1, 0.0, -0.05, 0.9, 0.02, 0.0, 0.03, 1.2);
        let r = orthonormalise(&m);
        assert!((r.matrix() * r.matrix().transpose() - Matrix3::identity()).norm() < 1e-12);
        assert!((r.matrix().determinant() - 1.0).abs() < 1e-12);
    }
}
