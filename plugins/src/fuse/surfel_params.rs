//! The parameters of the surfel map (Keller et al. 2013; ElasticFusion, Whelan et al. 2016),
//! one type for both fusers: the CPU and the GPU map follow the same rules
//! ([`super::surfel_rules`]) with the same constants. Every metric constant is organ scale; the
//! doc of each gives ElasticFusion's room-scale value.

capsule_slam_framework::plugin_params! {
    /// Parameters of the surfel map, shared by `surfel-cpu` and `surfel-gpu` (same keys, same
    /// defaults: `[plugins.surfel-cpu]` and `[plugins.surfel-gpu]` mean the same).
    pub struct SurfelParams {
        /// Active time window δt: a surfel is active iff now − t ≤ δt (ElasticFusion: 200).
        pub delta_t: u32 = 200; unit = "frames"; range = 1.0..=1.0e7;
        /// The active window for a surfel last seen before the map's last warp: a tracker's
        /// warp says the wall moved, and a surfel the camera left then stays where it was seen
        /// (`plugins/src/fuse/window.rs`). A wall that never moved keeps `delta_t`; `delta_t_moving ≥
        /// delta_t` turns the rule off. 60 frames (2 s at 30 Hz): the 30-run deforming grid,
        /// `docs/results/nonrigid.md`, "The active window follows the wall". No ElasticFusion
        /// counterpart (its map is rigid).
        pub delta_t_moving: u32 = 60; unit = "frames"; range = 1.0..=1.0e7;
        /// Confidence at which a surfel becomes stable and is predicted (ElasticFusion: 10).
        pub stable_confidence: f32 = 10.0; unit = "-"; range = 0.0..=1.0e6;
        /// Unstable surfels not seen for this long are removed (ElasticFusion: 20).
        pub unstable_lifetime: u32 = 20; unit = "frames"; range = 1.0..=1.0e7;
        /// Association depth gate along the ray (ElasticFusion: 0.05 m, room scale).
        pub depth_gate_m: f32 = 0.002; unit = "m"; range = 0.0..=10.0;
        /// Where the frame's depth carries a σ per pixel, the depth gate widens to this many σ
        /// (issue 17: a 2 mm gate would turn every noisy measurement into a new surfel). 6, not
        /// 3: a spatially correlated error shifts whole patches of a frame by 2–3 σ against
        /// surfels made of few measurements, and each one a 3 σ gate turns away starts a second
        /// layer (5 % smooth error, presets 1/4/5: surface RMSE 1.09/1.21/1.57 mm at 3 σ,
        /// 0.45/0.63/0.51 mm at 6 σ, 0.45 mm at 9 σ on preset 1; `docs/results/depth-noise.md`).
        pub gate_sigmas: f32 = 6.0; unit = "-"; range = 0.0..=100.0;
        /// A revisit reactivates: a measurement that no active surfel takes may merge into a
        /// stable inactive surfel that passes the same gates, which becomes active again.
        /// ElasticFusion reactivates only after a loop closure, so a capsule that returns to a
        /// wall it left more than `delta_t` frames ago lays a second map over the first, and
        /// the map grows on every pass (issue 18, `docs/results/long-runs.md`); `false` is
        /// ElasticFusion's rule. Only surfels last seen since the map's last warp are revived:
        /// what the wall moved away from is a stale phase (`plugins/src/fuse/window.rs`).
        pub revisit_reactivation: bool = true; unit = "-";
        /// The depth gate of a revisit (an inactive surfel's), along the ray, widened by the
        /// pixel's σ as `depth_gate_m` is: tighter than `depth_gate_m`, because an inactive
        /// surfel of a moving wall was not moved with the active map, and one that sits a
        /// millimetre off the wall would hold its merges there (its confidence outweighs a
        /// frame's). Organ scale; no ElasticFusion counterpart.
        pub revisit_gate_m: f32 = 0.001; unit = "m"; range = 0.0..=10.0;
        /// Association normal gate (ElasticFusion: 0.5 rad).
        pub normal_gate_rad: f32 = 0.5; unit = "rad"; range = 0.0..=3.15;
        /// Model normals with |n_z| below this skip the normal gate (ElasticFusion: 0.75).
        pub normal_bypass_nz: f32 = 0.75; unit = "-"; range = 0.0..=1.0;
        /// A measurement updates position and normal only if its radius is below this × the
        /// surfel's (ElasticFusion: 1.5).
        pub radius_ratio: f32 = 1.5; unit = "-"; range = 0.0..=100.0;
        /// Depths nearer than this are ignored (ElasticFusion: 0.3 m, room scale).
        pub min_depth_m: f32 = 0.002; unit = "m"; range = 0.0..=100.0;
        /// Depths beyond this are ignored (ElasticFusion: depthCut 3 m, room scale).
        pub max_depth_m: f32 = 0.25; unit = "m"; range = 0.0..=100.0;
        /// Fuse one pixel in `subsample`² per frame, rotating with the frame index
        /// (ElasticFusion: 2; 1 fuses every pixel).
        pub subsample: u32 = 2; unit = "px"; range = 1.0..=8.0;
        /// Bilateral filter for normals: window radius (ElasticFusion: 6, a 13×13 window).
        pub bilateral_radius_px: u32 = 1; unit = "px"; range = 0.0..=10.0;
        /// Bilateral filter for normals: spatial σ (ElasticFusion: 4.5 px).
        pub bilateral_sigma_px: f32 = 2.0; unit = "px"; range = 0.1..=20.0;
        /// Bilateral filter for normals: range σ (ElasticFusion: 0.03 m, room scale).
        pub bilateral_sigma_m: f32 = 0.0008; unit = "m"; range = 1.0e-6..=10.0;
        /// The ε of the splatted prediction's ε-z-buffer (Zwicker et al. 2001): discs within
        /// this of the nearest at a pixel are one surface and the most confident of them is
        /// shown (confidence counted up to `stable_confidence`). 0 is ElasticFusion's nearest-wins z-test, which shows the surfels noise put in
        /// front of the wall (issue 17: 0.37 mm of bias under structured-light noise). About
        /// 2–3 σ of the depth noise at working distance; room scale: 0.01–0.03 m.
        pub splat_blend_depth_m: f32 = 0.001; unit = "m"; range = 0.0..=1.0;
        /// Depth step between neighbours above which no normal is computed (a depth edge).
        pub edge_jump_m: f32 = 0.003; unit = "m"; range = 0.0..=10.0;
    }
}
