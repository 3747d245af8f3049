//! The parameters of the `deformation` loop closer: the graph (ElasticFusion's constants, organ
//! scale where they are lengths), the closure checks and how map and trajectory follow.

use capsule_slam_framework::deformation::SurfelTime;

use crate::common::ed_graph::Edges;

/// Which model stays where it is at a closure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Reference {
    /// The older, inactive model (ElasticFusion: drift is in the newer part): the active
    /// surface and the camera move onto it.
    Old,
    /// The recent, active model (a deforming organ: the current view is its current shape):
    /// the inactive surface moves onto it and the camera stays.
    Recent,
}

/// How camera poses follow the deformation (see [`PoseWarp`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PoseWarpKind {
    /// The camera centre as a point (ElasticFusion).
    Position,
    /// The points in front of the camera.
    View,
}

/// Which graph nodes a closure may move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Freeze {
    /// Every node is free (the correction spreads over the whole time line).
    None,
    /// Nodes of inactive surfels (by the fuser's δt) stay: the closure moves the active model
    /// onto the inactive one and leaves the rest of the old map where it is (ElasticFusion
    /// freezes the nodes older than its last local closure).
    Inactive,
}

/// What `window` counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WindowUnit {
    /// Nodes nearest in time (ElasticFusion).
    Nodes,
    /// Frames either side of the point's time.
    Frames,
}

capsule_slam_framework::plugin_params! {
    /// Parameters of `deformation`.
    pub struct DeformationParams {
        /// Influencing nodes per point, k (ElasticFusion: 4).
        pub k: u32 = 4; unit = "-"; range = 1.0..=16.0;
        /// Candidate nodes per point, in `window_unit`s (ElasticFusion: 20 nodes).
        pub window: u32 = 10; unit = "frames or nodes"; range = 1.0..=1.0e7;
        /// `frames` (the nodes within `window` frames of the point's time) or `nodes`
        /// (ElasticFusion: the `window` nodes nearest in time; the first frame alone holds ~150
        /// of 1024 nodes, all of time 0, so 20 of them are picked by position order, a strip).
        pub window_unit: WindowUnit = WindowUnit::Frames; unit = "-";
        /// The time that places nodes and surfels in the window: `last-seen` (t: a surface still
        /// in view moves with the camera that tracks it, whenever it was created) or `created`
        /// (t0, ElasticFusion: the active surface in view mixes old and new t0 and tears).
        pub surfel_time: SurfelTime = SurfelTime::LastSeen; unit = "-";
        /// Graph edges per node (ElasticFusion: 4).
        pub connectivity: u32 = 4; unit = "-"; range = 1.0..=16.0;
        /// `space-in-window` (the nearest nodes in space among the time window) or `time`
        /// (ElasticFusion: the nearest in time order).
        pub edges: Edges = Edges::SpaceInWindow; unit = "-";
        /// Most graph nodes (ElasticFusion: 1024, one per 5000 surfels).
        pub max_nodes: u32 = 1024; unit = "nodes"; range = 5.0..=100000.0;
        /// Fewest surfels per node.
        pub min_surfels_per_node: u32 = 50; unit = "surfels"; range = 1.0..=1.0e7;
        /// w_rot (ElasticFusion: 1).
        pub w_rot: f64 = 1.0; unit = "-"; range = 0.0..=1.0e9;
        /// w_reg (ElasticFusion: 10).
        pub w_reg: f64 = 10.0; unit = "-"; range = 0.0..=1.0e9;
        /// w_con (ElasticFusion: 100).
        pub w_con: f64 = 100.0; unit = "-"; range = 0.0..=1.0e9;
        /// Position residuals are divided by this (ElasticFusion: 1 m implicitly, room scale).
        pub length_unit_m: f64 = 0.01; unit = "m"; range = 1.0e-6..=100.0;
        /// Most Gauss-Newton iterations of the graph (ElasticFusion: 3).
        pub iterations: u32 = 5; unit = "-"; range = 1.0..=100.0;
        /// Surface constraints every this many pixels of the active view in x and y
        /// (ElasticFusion: 20 px at 640×480, 768 samples).
        pub constraint_stride_px: u32 = 10; unit = "px"; range = 1.0..=200.0;
        /// Pin the reference surface at each constraint (ElasticFusion: first closure only,
        /// plus freezing older nodes).
        pub pins: bool = true; unit = "-";
        /// Accept a loop only after this many consecutive frames whose registrations pass every
        /// check and agree on the correction (ElasticFusion: 1, the frame's own registration;
        /// ORB-SLAM asks 3 consecutive keyframes). One frame's registration slides along the
        /// tube or follows the wave; a loop stays put.
        pub consistent_frames: u32 = 3; unit = "frames"; range = 1.0..=100.0;
        /// Consecutive corrections agree when they move the view's surface samples by less than
        /// this on average.
        pub max_correction_change_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// How the trajectory follows the map: `position` (ElasticFusion: the camera centre
        /// warped as a point) or `view` (the rigid motion of points `pose_view_depth_m` in front
        /// of the camera).
        pub pose_warp: PoseWarpKind = PoseWarpKind::View; unit = "-";
        /// Distance of the points a pose follows with `pose_warp = "view"` (a capsule sees the
        /// stomach wall at 10–30 mm).
        pub pose_view_depth_m: f64 = 0.02; unit = "m"; range = 1.0e-4..=10.0;
        /// Nodes held in place: `inactive` (every node of an inactive surfel) or `none`.
        pub freeze: Freeze = Freeze::Inactive; unit = "-";
        /// Which model stays: `old` (ElasticFusion: the active surface and the camera move onto
        /// the inactive one) or `recent` (the inactive surface moves onto the current view).
        pub reference: Reference = Reference::Old; unit = "-";
        /// Reject when the inactive model covers less than this share of the active view.
        pub min_overlap: f64 = 0.2; unit = "-"; range = 0.0..=1.0;
        /// Reject when fewer than this share of the active pixels are ICP inliers
        /// (ElasticFusion: 35 000 of 307 200 pixels).
        pub min_inlier_share: f64 = 0.15; unit = "-"; range = 0.0..=1.0;
        /// Reject when the ICP RMS residual exceeds this (ElasticFusion: 5e-5 mean squared,
        /// about 1 cm RMS at room scale).
        pub max_residual_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when a translation standard deviation of T_est exceeds this (ElasticFusion:
        /// covariance diagonals < 1e-5).
        pub max_std_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when a rotation standard deviation of T_est exceeds this.
        pub max_std_rad: f64 = 0.01; unit = "rad"; range = 0.0..=3.15;
        /// Reject when the correction moves the camera farther than this: a local loop closure
        /// corrects drift, it does not relocalise (larger bends go through few nodes and
        /// extrapolate; measured in `docs/results/loop-closure.md`).
        pub max_correction_m: f64 = 0.003; unit = "m"; range = 0.0..=1.0;
        /// Reject a correction below this: nothing to close, the graph's own interpolation
        /// error is of this order (the best of 0.1, 0.5 and 1 mm on a loopy phantom,
        /// `docs/results/loop-closure.md`).
        pub min_correction_m: f64 = 0.0005; unit = "m"; range = 0.0..=1.0;
        /// Reject when the two models already agree: their ICP RMS residual at the tracked pose,
        /// before any correction, is below this (a closure would bend the map by more than it
        /// disagrees; fused models of one rigid wall agree to 0.02–0.2 mm).
        pub min_disagreement_m: f64 = 0.00025; unit = "m"; range = 0.0..=1.0;
        /// Reject when the ICP residual after the correction is above this share of the one
        /// before it (the correction does not explain the data: the registration slid).
        pub max_residual_ratio: f64 = 0.5; unit = "-"; range = 0.0..=1.0e6;
        /// Noise scale of the registration's point-to-plane residual (model depths are fused,
        /// hence measured-like).
        pub sigma_icp_m: f64 = 0.0003; unit = "m"; range = 1.0e-7..=1.0;
        /// Weight of the registration's photometric term.
        pub w_rgb: f64 = 0.1; unit = "-"; range = 0.0..=1000.0;
        /// Registration ICP correspondence gate.
        pub icp_gate_m: f64 = 0.004; unit = "m"; range = 0.0..=1.0;
        /// When the rigid registration leaves a residual it cannot explain (rejected for
        /// `residual` or `unexplained`), register the two models again through a warp (the
        /// `nonrigid` tracker's joint solve of camera and nodes, `warped.rs`): a moving wall's
        /// old surface was fused at another phase. Accepted by the same checks on the residual
        /// after the warp; the closure then also moves the inactive surface by the warp.
        pub warp: bool = true; unit = "-";
        /// Reject a warp that moves a node farther than this (a few wave amplitudes; a larger
        /// mismatch is another surface, not the same one moved).
        pub max_warp_m: f64 = 0.005; unit = "m"; range = 0.0..=1.0;
    }
}
