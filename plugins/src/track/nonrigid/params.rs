//! Parameters of `nonrigid`, organ-scale defaults with their sources.

use capsule_slam_framework::StageError;
use capsule_slam_framework::params::PluginParams;
use serde::{Deserialize, Serialize};

use crate::common::ed_graph::NodeModel;
use crate::track::icp_rgb::IcpRgbParams;

use super::solve::Weights;

/// Whether the camera moves in the joint solve.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CameraMode {
    /// Camera and nodes together (the camera held near the rigid start by its prior).
    Joint,
    /// The rigid start's camera, nodes only (SurfelWarp).
    Fixed,
}

capsule_slam_framework::plugin_params! {
    /// Parameters of `nonrigid`.
    pub struct NonrigidParams {
        /// The rigid start: every `icp-rgb` parameter, as a table `[plugins.nonrigid.rigid]`.
        pub rigid: IcpRgbParams = IcpRgbParams::default(); unit = "-";
        /// `joint` (camera and nodes, held near the rigid start by the camera prior: the texture
        /// sees motion the geometry hides) or `fixed` (nodes only, SurfelWarp). Joint: 1.4–3× lower
        /// ATE than fixed on the deforming phantoms (`docs/results/nonrigid.md`).
        pub camera: CameraMode = CameraMode::Joint; unit = "-";
        /// Remove from the warp the rigid motion common to its nodes (OpenCV dynafu's
        /// `factorCommon`): the camera explains it, and the map cannot drift with a camera error.
        /// Off by default: the joint solve's camera already takes the common motion.
        pub factor_common: bool = false; unit = "-";
        /// The nodes' transforms: `affine` (Sumner's 12 unknowns, R held near a rotation by
        /// `E_rot`, the `deformation` closer's) or `twist` (a rigid motion, 6 unknowns: DynamicFusion,
        /// SurfelWarp; a quarter of the normal-equation entries).
        pub node_model: NodeModel = NodeModel::Affine; unit = "-";
        /// Node spacing (SurfelWarp: 25 mm at body scale; nonrigid.md §8: λ/6 ≈ 8–10 mm for a 60 mm wave).
        pub node_spacing_m: f64 = 0.008; unit = "m"; range = 1.0e-4..=1.0;
        /// Nodes farther than this do not move a point (and bind no model point); 2 × spacing.
        pub reach_m: f64 = 0.016; unit = "m"; range = 1.0e-4..=1.0;
        /// Influencing nodes per point (SurfelWarp, SuPer: 4).
        pub k: u32 = 4; unit = "-"; range = 1.0..=8.0;
        /// Graph neighbours per node (SurfelWarp: 8).
        pub connectivity: u32 = 8; unit = "-"; range = 1.0..=16.0;
        /// Longest graph edge (nonrigid.md §8: 3 × spacing; no edge across the lumen).
        pub max_edge_m: f64 = 0.024; unit = "m"; range = 1.0e-4..=1.0;
        /// Largest angle between the normals of linked nodes (opposite walls face each other).
        pub max_edge_angle_rad: f64 = 1.2; unit = "rad"; range = 0.0..=3.15;
        /// Pyramid level of the live frame the warp is fitted on (0 finest).
        pub level: u32 = 0; unit = "-"; range = 0.0..=2.0;
        /// Model points every this many prediction pixels (320² → 107² at 3). 3, not 4: the
        /// camera of the joint solve rests on the model points, and at the fastest turns of a
        /// 4 mm wave the sparser set pulled it 0.5–0.9° off a rigid start that was within 0.2°;
        /// with 3 the 4 mm waves' summed ATE falls by 24–34 % per seed (seeds 1–3), the rigid twins are
        /// unchanged (`docs/results/nonrigid.md`, "Denser model points").
        pub point_stride_px: u32 = 3; unit = "px"; range = 1.0..=32.0;
        /// Largest angle between a model point's normal and its view ray (SurfelWarp's append
        /// rule: view·normal > 0.4, 66°); grazing walls are left out of the fit.
        pub max_incidence_rad: f64 = 1.15; unit = "rad"; range = 0.0..=1.571;
        /// Fit the warp also on the previous live frame where the prediction shows nothing
        /// (ElasticFusion's fill-in) while the prediction covers less than this share of the
        /// previous frame's valid depth pixels: a young map (its surfels not yet stable, so not
        /// predicted: the first 10 or so frames) and a fast camera (new wall entering the view)
        /// then warp from the second frame instead of after `stable_confidence` sightings.
        /// 0: never; 1: wherever the prediction has a hole. 0.5 against 0, seed 1, 2 mm: ATE
        /// lower on presets 1, 2, 4, 5, 7 (preset 4 0.375 → 0.237 %); 4 mm: lower on 1, 2, 5
        /// (0.502 → 0.381 %), higher on 4 (+5 %) and 7 (0.353 → 0.504 %); rigid and noisy-depth
        /// rigid runs unchanged (`docs/results/nonrigid.md`).
        pub fill_in_below_share: f64 = 0.5; unit = "-"; range = 0.0..=1.0;
        /// Fewest model points for a node to be solved.
        pub min_points_per_node: u32 = 8; unit = "-"; range = 1.0..=10000.0;
        /// Gauss-Newton iterations (SurfelWarp: 6 after a 3-iteration rigid pre-solve). 8 measured
        /// better than 5 on the slow, fast and loopy deforming phantoms (presets 1, 4, 5 over
        /// seeds), slightly worse on presets 2 and 7, `docs/results/nonrigid.md`; each costs
        /// about 5 ms on a moving wall.
        pub iterations: u32 = 8; unit = "-"; range = 1.0..=50.0;
        /// Stop the Gauss-Newton iterations early once an iteration moves no node's translation
        /// and not the camera's by more than this (0: always run `iterations`). 5 µm, a
        /// twentieth of the phantom's depth noise σ, cut the 8 iterations to 6 on average and
        /// left ATE within −9 … +8 % on the deforming phantoms and the rigid twins unchanged;
        /// 10 µm cost preset 4 half its accuracy (`docs/results/nonrigid.md`).
        pub step_tolerance_m: f64 = 5.0e-6; unit = "m"; range = 0.0..=1.0;
        /// Iterations after the first solve with the last factorised normal matrix and the current
        /// gradient (the chord method: an iteration then costs the residuals, the gradient and two
        /// triangular solves instead of every point's 12 × 12 blocks and a numeric factorisation)
        /// while each step is smaller than the one before; a step that is not makes the next
        /// iteration factorise anew. Gauss-Newton's own steps shrink only linearly here (the
        /// correspondences and image gradients move with the warp), so the kept matrix costs no
        /// iterations: 1.06 factorisations per solve, the warp solve 48 → 27 ms per frame on
        /// preset 2 with a 2 mm wave, and over the 30 deforming phantoms ATE sums −0.1 % (2 mm)
        /// and +3.7 % (4 mm, one chaotic run; within the noise of a null change), the rigid and
        /// noisy-depth twins identical (`docs/results/nonrigid.md`). false: Gauss-Newton exactly
        /// (every iteration factorises).
        pub reuse_factor: bool = true; unit = "-";
        /// Point-to-plane noise scale (as `icp-rgb`'s `sigma_icp_m`).
        pub sigma_icp_m: f64 = 0.0003; unit = "m"; range = 1.0e-7..=1.0;
        /// Weight of the photometric term (paper Eq. 4: 0.1; 3 measured best for the joint solve,
        /// where the texture pins the camera: `docs/results/nonrigid.md`).
        pub w_rgb: f64 = 3.0; unit = "-"; range = 0.0..=1000.0;
        /// Relight the photometric reference to the live view with the rigid start's light model
        /// (`[plugins.nonrigid.rigid] light_file`), as `icp-rgb` does: the light moves with the capsule.
        pub relight: bool = true; unit = "-";
        /// Intensity noise scale.
        pub sigma_rgb: f64 = 0.02; unit = "-"; range = 1.0e-6..=1.0;
        /// Huber threshold in noise scales.
        pub huber_k: f64 = 1.345; unit = "-"; range = 0.01..=1000.0;
        /// Correspondence gate (SurfelWarp: 3 cm at body scale; ≈ 2 × wave + motion).
        pub gate_m: f64 = 0.003; unit = "m"; range = 0.0..=1.0;
        /// Normal-angle gate (SurfelWarp: n·n ≥ 0.7, 45°).
        pub angle_gate_rad: f64 = 0.6; unit = "rad"; range = 0.0..=3.15;
        /// Photometric occlusion gate on depth.
        pub rgb_depth_gate_m: f64 = 0.002; unit = "m"; range = 0.0..=1.0;
        /// Smallest live intensity gradient for the photometric term, per level pixel.
        pub rgb_min_gradient: f64 = 0.002; unit = "1/px"; range = 0.0..=1.0;
        /// Scale of E_rot (R_j near a rotation; Sumner Eq. 3).
        pub sigma_rot: f64 = 0.01; unit = "-"; range = 1.0e-6..=10.0;
        /// Weight of E_reg against one data residual (SuPer: ARAP ×10).
        pub w_reg: f64 = 10.0; unit = "-"; range = 0.0..=1.0e6;
        /// Scale of the E_reg residuals.
        pub sigma_reg_m: f64 = 0.0003; unit = "m"; range = 1.0e-7..=1.0;
        /// Rest-shape prior: a node's pull to where it was created (nonrigid.md §8: ≈ 2 × wave). 0: off.
        pub sigma_rest_m: f64 = 0.005; unit = "m"; range = 0.0..=10.0;
        /// Per-frame node translation prior (the wall moves ≤ 0.21 mm per frame at 30 Hz). 0: off.
        pub sigma_step_m: f64 = 0.0005; unit = "m"; range = 0.0..=10.0;
        /// Per-frame prior on a node's translation along its surface, metres per frame (a wave moves
        /// the wall along its normal; a tube's axis and roll are near-null directions of point to
        /// plane, along which a warp drifts on a still wall). 25 µm: when the capsule rides the
        /// wave (the wave's shape travels with the camera), geometry alone sees no motion, and a
        /// looser prior (100 µm) let the nodes slide with the camera and take 2–5 % of its forward
        /// motion (ATE on the deforming grid −12 to −16 % in sum, `docs/results/nonrigid.md`). A
        /// tissue that slides along itself (breathing) wants a looser one. 0: off.
        pub sigma_slide_m: f64 = 0.000025; unit = "m"; range = 0.0..=10.0;
        /// Passes of averaging each node's normal with its graph neighbours' before the slide
        /// prior takes its tangent plane (0: the node's own normal, which tilts with the wave's
        /// slope; `docs/results/nonrigid.md`).
        pub slide_normal_passes: u32 = 1; unit = "-"; range = 0.0..=16.0;
        /// Per-frame node R − I prior (a twist node's ω counts as its first-order ‖R − I‖_F = √2 ‖ω‖). 0: off.
        pub sigma_step_rot: f64 = 0.02; unit = "-"; range = 0.0..=10.0;
        /// Camera prior toward the rigid start, translation. 0: off.
        pub sigma_camera_m: f64 = 0.001; unit = "m"; range = 0.0..=10.0;
        /// Camera prior toward the rigid start, rotation. 0: off.
        pub sigma_camera_rad: f64 = 0.01; unit = "rad"; range = 0.0..=10.0;
        /// The map leads the moving wall: a kept warp's node translations (not their rotations)
        /// are scaled by `1 + warp_lead` before the map and the nodes move, a predictor of the
        /// wall's next position from its last motion (a peristaltic wave moves each point smoothly
        /// over a period of seconds). The next frame's rigid start then meets a map nearer the
        /// wall and gives less of the wall's motion to the camera. If one solve recovers a share κ
        /// of the wall's motion since the map last moved, a steadily moving wall meets the next
        /// frame's start `1 / ((1 + warp_lead) κ)` of a frame's motion away (instead of `1 / κ`),
        /// and the lead is stable while `(1 + warp_lead) κ < 2`: on a clean wall, where a solve
        /// recovers nearly all of a frame's motion, the map rings about the wall from a lead of 1
        /// (unit test). 0: the map stays where the wall was seen. On the 20 deforming phantoms
        /// ATE falls ×0.88 / ×0.83 / ×0.82 / ×0.78 at 0.5 / 0.75 / 1 / 1.5
        /// (`docs/results/nonrigid.md`, "The map leads the wall"); 0.75 is the largest lead that
        /// does not ring on the clean wall.
        pub warp_lead: f64 = 0.75; unit = "-"; range = 0.0..=2.0;
        /// Fall back to rigid when fewer model points than this share are point-to-plane inliers.
        pub min_point_share: f64 = 0.3; unit = "-"; range = 0.0..=1.0;
        /// Fall back to rigid when a node would move more than this in one frame.
        pub max_step_m: f64 = 0.002; unit = "m"; range = 0.0..=1.0;
        /// Keep the map still unless the warp's drop in χ² (inliers × (RMS before² / RMS after² − 1),
        /// the RMS over the common inliers)
        /// exceeds this many per unknown (2: Akaike's criterion). 0 by default: the windowed
        /// point-to-plane gain decides (`min_rms_gain`, `gain_window_frames`).
        pub min_evidence: f64 = 0.0; unit = "-"; range = 0.0..=1000.0;
        /// Fall back to rigid when the joint solve moves the camera farther than this from the rigid start.
        pub max_camera_step_m: f64 = 0.001; unit = "m"; range = 0.0..=1.0;
        /// The same for the camera's rotation.
        pub max_camera_step_rad: f64 = 0.02; unit = "rad"; range = 0.0..=3.15;
        /// When the joint solve would move the camera beyond `max_camera_step_m`/`_rad`, solve the
        /// nodes again with the camera held at the rigid start (SurfelWarp's solve; the map still
        /// follows the wall) instead of keeping the rigid pose without a warp.
        pub hold_camera_on_step: bool = true; unit = "-";
        /// Keep the map still unless the warp lowers the point-to-plane RMS (over the points that
        /// are inliers both before and after the solve) by at least this share
        /// on average over `gain_window_frames` (the rigid start's residual is then sensor noise
        /// or the map's own error, and a warp would fit it). Measured with the default
        /// preprocessors, seed 1: the rigid presets 1, 4, 5's gains are −0.042 at the median and
        /// below −0.013 in 90 % of the frames; the 2 and 4 mm waves' 0.082 and 0.085 at the median
        /// and above 0.03 in 90 % (`docs/results/nonrigid.md`; 0.06 until the gain was taken over
        /// the common inliers).
        pub min_rms_gain: f64 = 0.03; unit = "-"; range = 0.0..=1.0;
        /// Test `min_rms_gain` on the mean gain of the last this many solves that reached the
        /// model selection (this one included): a moving wall keeps the gain up frame after frame, a still one
        /// gives a gain now and then from the map's own errors (`docs/results/nonrigid.md`).
        /// 1: this frame alone; 20 keeps every warp off the seven rigid phantoms.
        pub gain_window_frames: u32 = 20; unit = "frames"; range = 1.0..=1000.0;
        /// While the wall is clearly still (the last `gain_window_frames` solves all kept no warp
        /// and their mean gain is below a quarter of `min_rms_gain`), solve the warp on every this-many-th
        /// frame only: the frames between are `icp-rgb`'s (what a still verdict gives anyway),
        /// without the warp solve's cost. A probe whose own gain reaches `min_rms_gain`, or any
        /// kept warp or fallback, ends it. 1: solve every frame.
        pub still_probe_every_frames: u32 = 8; unit = "frames"; range = 1.0..=1000.0;
        /// While the wall stays clearly still, each probe that finds it so doubles the interval,
        /// from `still_probe_every_frames` up to this many frames: a still wall's cost falls
        /// toward `icp-rgb`'s (rigid preset 2, 320×320: 30 probes in frames 60–299 at 8, 7 with
        /// the doubling; each about 10 ms of tracking, `docs/results/speed.md`). A wall that
        /// starts moving is caught by `still_probe_residual_rise` before the interval ends.
        /// Equal to `still_probe_every_frames`: a fixed interval.
        pub still_probe_max_every_frames: u32 = 32; unit = "frames"; range = 1.0..=1000.0;
        /// Between probes, a frame whose rigid start's point-to-plane RMS residual exceeds this
        /// factor times its running mean over the still frames skipped before it (after 4 of
        /// them) is probed on the next frame, and the interval returns to
        /// `still_probe_every_frames`: a wall that starts to move raises the rigid residual at
        /// once (preset 2 with a 2 mm wave from frame 150, `synth --deform-onset 150`: 1.05×
        /// two frames in, 1.8× four frames in), a still wall's stays within a few per cent.
        /// 0: off (the interval alone).
        pub still_probe_residual_rise: f64 = 1.5; unit = "-"; range = 0.0..=100.0;
        /// While the wall is clearly moving (`camera = "joint"`; it becomes so once the last
        /// `gain_window_frames` judged solves all kept their warp with a mean gain of at least twice
        /// `min_rms_gain`, and stays so while every judged solve keeps its warp), the
        /// rigid start stops after the coarse levels on all but every this-many-th frame: the joint
        /// solve refines the camera at level 0 itself, and the rigid start's level 0 (about a third
        /// of its time) would be done twice. Those frames keep their warp unjudged (a gain from a
        /// coarse start counts the camera's own refinement too); one whose solve falls back, or
        /// would hold the camera at the coarse pose, finishes the rigid start at level 0 and is
        /// solved again as any other frame (counter `nonrigid_coarse_start_finished`). 1: never.
        /// 16, not 8: over the 30 deforming runs the two are alike within a null change's spread
        /// in two grids (ATE sums 3.401 / 8.550 against 3.392 / 8.372 % at `15cbfc8`, 3.478 / 8.405
        /// against 3.361 / 8.211 % at `fe32e0a`), the rigid twins byte-identical, and `track`
        /// 1 ms shorter per frame on `p2d2` (`docs/results/nonrigid.md`).
        pub moving_probe_every_frames: u32 = 16; unit = "frames"; range = 1.0..=1000.0;
        /// The coarse rigid start runs the pyramid levels from the coarsest down to this one,
        /// then level 0's first iteration: 2, level 2 alone (a sixteenth of the pixels); 1, levels
        /// 2 and 1. Over the 30 deforming phantom runs the two are alike within a null change's
        /// spread, and level 2 alone saves about 4 ms more per coarse frame
        /// (`docs/results/nonrigid.md`, "A coarse rigid start on a clearly moving wall").
        pub coarse_start_level: u32 = 2; unit = "-"; range = 1.0..=2.0;
        /// Most nodes (SurfelWarp: 4096).
        pub max_nodes: u32 = 4096; unit = "-"; range = 1.0..=1.0e6;
        /// Warp also with depth estimated from the image (shape from shading): its view-dependent
        /// biases would be read as wall motion, so off by default (the rigid start alone).
        pub warp_estimated_depth: bool = false; unit = "-";
    }
}

impl NonrigidParams {
    /// Checks what the ranges cannot: the rigid table's own ranges and reach ≥ spacing.
    pub fn check(&self) -> Result<(), StageError> {
        if let Some((field, problem)) = self.rigid.range_problems().into_iter().next() {
            return Err(StageError::invalid_input(format!("nonrigid: rigid.{field}: {problem}")));
        }
        crate::common::ordered("min_depth_m", f64::from(self.rigid.min_depth_m), "max_depth_m", f64::from(self.rigid.max_depth_m))?;
        if self.still_probe_max_every_frames < self.still_probe_every_frames {
            return Err(StageError::invalid_input(format!(
                "nonrigid: still_probe_max_every_frames ({}) must be at least still_probe_every_frames ({}); equal gives a fixed interval",
                self.still_probe_max_every_frames, self.still_probe_every_frames
            )));
        }
        if self.reach_m < self.node_spacing_m {
            return Err(StageError::invalid_input(format!(
                "nonrigid: reach_m ({}) must be at least node_spacing_m ({}), or points between nodes bind none",
                self.reach_m, self.node_spacing_m
            )));
        }
        Ok(())
    }

    /// The solver's weights.
    pub(super) fn weights(&self) -> Weights {
        Weights {
            sigma_icp_m: self.sigma_icp_m,
            w_rgb: self.w_rgb,
            sigma_rgb: self.sigma_rgb,
            huber_k: self.huber_k,
            gate_m: self.gate_m,
            cos_gate: self.angle_gate_rad.cos(),
            rgb_depth_gate_m: self.rgb_depth_gate_m,
            rgb_min_gradient: self.rgb_min_gradient,
            sigma_rot: self.sigma_rot,
            w_reg: self.w_reg,
            sigma_reg_m: self.sigma_reg_m,
            sigma_rest_m: self.sigma_rest_m,
            sigma_step_m: self.sigma_step_m,
            sigma_step_rot: self.sigma_step_rot,
            sigma_slide_m: self.sigma_slide_m,
            sigma_camera_m: self.sigma_camera_m,
            sigma_camera_rad: self.sigma_camera_rad,
            iterations: self.iterations as usize,
            step_tolerance_m: self.step_tolerance_m,
            reuse_factor: self.reuse_factor,
            point_stride_px: f64::from(self.point_stride_px),
            gate_sigmas: self.rigid.gate_sigmas,
        }
    }
}
