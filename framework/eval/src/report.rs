//! Everything `capsule-slam eval` and `capsule-slam run` report against ground truth, as a
//! flat map of named figures (the keys of `summary.json`).

use std::collections::BTreeMap;

use super::live::{LastView, live_surface_error, live_surface_split};
use super::rpe::{Delta, rpe};
use super::surface::{SurfaceOptions, surface_error};
use super::warp::{WallMotion, warp_error};
use super::{align_recent, align_trajectory, associate, ate, path_length_m};
use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::{Iso3, StampedPose, nearest_in_time};
use capsule_slam_framework::map::SurfelSet;

/// What to evaluate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvalOptions {
    /// Timestamp association tolerance, seconds.
    pub tolerance_s: f64,
    /// Align with scale (Sim(3)) for the headline figures; SE(3) otherwise.
    pub sim3: bool,
    /// RPE pair spacing.
    pub rpe_delta: Delta,
    /// Surface error options.
    pub surface: SurfaceOptions,
    /// The live surface error counts the surfels seen in the last this many frames.
    pub live_window_frames: u32,
    /// The warp error interpolates the true wall between samples at most this many frames
    /// apart ([`crate::warp`]).
    pub warp_max_gap_frames: u32,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            tolerance_s: 0.02,
            sim3: false,
            rpe_delta: Delta::Frames(1),
            surface: SurfaceOptions::default(),
            live_window_frames: 30,
            warp_max_gap_frames: 30,
        }
    }
}

/// Trajectory (and optionally surface) figures. Keys: `path_length_m` (the true path the estimate
/// covers, [`covered_path_length_m`]; `ate_percent_of_path` divides by it), `gt_path_length_m`
/// (the whole ground truth's), `ate_rmse_m` (SE(3)),
/// `ate_rmse_sim3_m`, `sim3_scale`, `ate_mean_m`, `ate_median_m`, `ate_max_m` (of the chosen
/// alignment), `ate_percent_of_path`, `rpe_trans_rmse_m`, `rpe_rot_rmse_deg`,
/// `rpe_trans_per_m`, `rpe_rot_deg_per_m`, and with a map `surface_rmse_m`,
/// `surface_accuracy_m`, `surface_completeness_1mm`, `surface_completeness_2mm` (over the truth
/// observed at least once) and `surface_completeness_1mm_seen10`, `..._2mm_seen10` (over the
/// truth observed in at least 10 frames).
pub fn evaluate(est: &[StampedPose], gt: &[StampedPose], map: Option<(&SurfelSet, &SurfelSet)>, opts: &EvalOptions) -> BTreeMap<String, f64> {
    let mut m = BTreeMap::new();
    let path = covered_path_length_m(est, gt, opts.tolerance_s);
    m.insert("path_length_m".to_owned(), path);
    m.insert("gt_path_length_m".to_owned(), path_length_m(gt));
    let se3 = ate(est, gt, opts.tolerance_s, false);
    let sim3 = ate(est, gt, opts.tolerance_s, true);
    if let Some(a) = &se3 {
        m.insert("ate_rmse_m".into(), a.rmse_m());
    }
    if let Some(a) = &sim3 {
        m.insert("ate_rmse_sim3_m".into(), a.rmse_m());
        m.insert("sim3_scale".into(), a.alignment.scale);
    }
    if let Some(a) = if opts.sim3 { &sim3 } else { &se3 } {
        m.insert("ate_mean_m".into(), a.stats.mean);
        m.insert("ate_median_m".into(), a.stats.median);
        m.insert("ate_max_m".into(), a.stats.max);
        if path > 0.0 {
            m.insert("ate_percent_of_path".into(), 100.0 * a.rmse_m() / path);
        }
    }
    if let Some(r) = rpe(est, gt, opts.tolerance_s, opts.rpe_delta, Some(opts.sim3)) {
        m.insert("rpe_trans_rmse_m".into(), r.trans_m.rmse);
        m.insert("rpe_rot_rmse_deg".into(), r.rot_deg.rmse);
        m.insert("rpe_trans_per_m".into(), r.trans_per_m);
        m.insert("rpe_rot_deg_per_m".into(), r.rot_deg_per_m);
    }
    if let (Some((map, truth)), Some(align)) = (map, align_trajectory(est, gt, opts.tolerance_s, opts.sim3)) {
        let mut moved = map.clone();
        for s in &mut moved.surfels {
            s.position_m = align.apply(&s.position_m.cast()).cast();
            s.normal = (align.rotation * s.normal.cast::<f64>()).cast();
        }
        if let Some(e) = surface_error(&moved, truth, &Iso3::identity(), &opts.surface) {
            m.insert("surface_rmse_m".into(), e.rmse_m);
            m.insert("surface_accuracy_m".into(), e.accuracy_m);
            m.insert("surface_completeness_1mm".into(), e.completeness_1mm);
            m.insert("surface_completeness_2mm".into(), e.completeness_2mm);
            m.insert("surface_completeness_1mm_seen10".into(), e.completeness_1mm_min_views);
            m.insert("surface_completeness_2mm_seen10".into(), e.completeness_2mm_min_views);
        }
    }
    m
}

/// Length of the ground-truth path the estimate covers: through the true poses from the first
/// to the last one matched to an estimated pose (a run of part of a sequence, or one that stopped
/// early, is scored against the path it travelled, not the whole sequence's). 0 without a match.
pub fn covered_path_length_m(est: &[StampedPose], gt: &[StampedPose], tolerance_s: f64) -> f64 {
    let stamps: Vec<f64> = associate(est, gt, tolerance_s).iter().map(|(_, g)| g.timestamp_s).collect();
    let (Some(first), Some(last)) = (stamps.iter().copied().reduce(f64::min), stamps.iter().copied().reduce(f64::max)) else { return 0.0 };
    let covered: Vec<StampedPose> = gt.iter().filter(|g| g.timestamp_s >= first && g.timestamp_s <= last).copied().collect();
    path_length_m(&covered)
}

/// A readable table of the figures (millimetres and degrees).
pub fn table(m: &BTreeMap<String, f64>) -> String {
    let rows: [(&str, &str, f64, &str); 28] = [
        ("path_length_m", "path length (covered)", 1e3, "mm"),
        ("gt_path_length_m", "path length (whole truth)", 1e3, "mm"),
        ("ate_rmse_m", "ATE RMSE, SE(3)", 1e3, "mm"),
        ("ate_rmse_sim3_m", "ATE RMSE, Sim(3)", 1e3, "mm"),
        ("sim3_scale", "Sim(3) scale", 1.0, ""),
        ("ate_percent_of_path", "ATE RMSE / path", 1.0, "%"),
        ("ate_median_m", "ATE median", 1e3, "mm"),
        ("ate_max_m", "ATE max", 1e3, "mm"),
        ("rpe_trans_rmse_m", "RPE translation RMSE", 1e3, "mm"),
        ("rpe_rot_rmse_deg", "RPE rotation RMSE", 1.0, "deg"),
        ("rpe_trans_per_m", "RPE translation per path", 100.0, "%"),
        ("rpe_rot_deg_per_m", "RPE rotation per path", 1.0, "deg/m"),
        ("surface_rmse_m", "surface RMSE", 1e3, "mm"),
        ("surface_accuracy_m", "surface accuracy (median)", 1e3, "mm"),
        ("surface_completeness_1mm", "completeness ≤ 1 mm", 100.0, "%"),
        ("surface_completeness_2mm", "completeness ≤ 2 mm", 100.0, "%"),
        ("surface_completeness_1mm_seen10", "  of truth seen ≥ 10×, ≤ 1 mm", 100.0, "%"),
        ("surface_completeness_2mm_seen10", "  of truth seen ≥ 10×, ≤ 2 mm", 100.0, "%"),
        ("live_surface_rmse_m", "live surface RMSE", 1e3, "mm"),
        ("live_surface_median_m", "live surface median", 1e3, "mm"),
        ("live_surface_p95_m", "live surface p95", 1e3, "mm"),
        ("live_surface_in_view_rmse_m", "  in the last frame's view", 1e3, "mm"),
        ("live_surface_left_rmse_m", "  left by the camera", 1e3, "mm"),
        ("live_surface_local_rmse_m", "  window-aligned RMSE", 1e3, "mm"),
        ("live_surface_local_median_m", "  window-aligned median", 1e3, "mm"),
        ("warp_error_rmse_m", "warp error RMSE", 1e3, "mm"),
        ("warp_error_normal_rmse_m", "  along the wall normal", 1e3, "mm"),
        ("warp_true_rms_m", "  true wall motion RMS", 1e3, "mm"),
    ];
    let mut out = String::new();
    for (key, label, scale, unit) in rows {
        if let Some(v) = m.get(key) {
            out.push_str(&format!("{label:<28} {:>10.4} {unit}\n", v * scale));
        }
    }
    out
}

/// The live surface error of `map` against `truth_now`, the true surface at `last_frame`
/// (surfels seen in the last `live_window_frames` frames, moved by the trajectory alignment of
/// the headline ATE: SE(3), or Sim(3) with `sim3`). Keys `live_surface_rmse_m`,
/// `live_surface_median_m`, `live_surface_p95_m`, `live_surface_points`; with the `camera`, the
/// same surfels split ([`live_surface_split`]) into `live_surface_in_view_rmse_m` / `_points`
/// (inside the true last camera's image) and `live_surface_left_rmse_m` / `_points` (beside or
/// behind it); and `live_surface_local_rmse_m`, `live_surface_local_median_m` with the alignment fitted to the
/// window's poses alone ([`align_recent`]). Empty when nothing is live or the trajectory cannot
/// be aligned.
pub fn evaluate_live(
    est: &[StampedPose],
    gt: &[StampedPose],
    map: &SurfelSet,
    truth_now: &SurfelSet,
    last_frame: u32,
    camera: Option<&PinholeCamera>,
    opts: &EvalOptions,
) -> BTreeMap<String, f64> {
    let mut m = BTreeMap::new();
    let Some(align) = align_trajectory(est, gt, opts.tolerance_s, opts.sim3) else { return m };
    if let Some(e) = live_surface_error(map, &align, truth_now, last_frame, opts.live_window_frames, opts.surface.plane_radius_m) {
        m.insert("live_surface_rmse_m".into(), e.rmse_m);
        m.insert("live_surface_median_m".into(), e.median_m);
        m.insert("live_surface_p95_m".into(), e.p95_m);
        m.insert("live_surface_points".into(), e.points as f64);
    }
    // The same surfels split into the wall in the last frame's view and the wall the camera has
    // left (no measurement constrains where it went since).
    if let Some(camera) = camera
        && let Some(last) = est.last()
        && let Some(at) = nearest_in_time(gt, last.timestamp_s, opts.tolerance_s, |p| p.timestamp_s)
    {
        let view = LastView { camera, t_world_cam: gt[at].t_world_cam };
        let (in_view, left) = live_surface_split(map, &align, truth_now, last_frame, opts.live_window_frames, opts.surface.plane_radius_m, &view);
        for (key, e) in [("live_surface_in_view", in_view), ("live_surface_left", left)] {
            if let Some(e) = e {
                m.insert(format!("{key}_rmse_m"), e.rmse_m);
                m.insert(format!("{key}_points"), e.points as f64);
            }
        }
    }
    // The same surfels under an alignment fitted to the window's poses alone: what is left is the
    // map's own lag behind the wall, without the drift accumulated before the window.
    let Some(local) = align_recent(est, gt, opts.tolerance_s, opts.sim3.then_some(align.scale), opts.live_window_frames as usize, LOCAL_REACH_M) else {
        return m;
    };
    if let Some(e) = live_surface_error(map, &local, truth_now, last_frame, opts.live_window_frames, opts.surface.plane_radius_m) {
        m.insert("live_surface_local_rmse_m".into(), e.rmse_m);
        m.insert("live_surface_local_median_m".into(), e.median_m);
    }
    m
}

/// How far along each camera axis the local alignment's pose points lie, metres (the distance
/// at which a capsule sees the wall).
const LOCAL_REACH_M: f64 = 0.02;

/// The warp error of `map` ([`crate::warp`]): its surfels seen at `last_frame`, moved by the
/// same trajectory alignment as [`evaluate_live`], against the true wall's motion `wall`, whose
/// surface at `last_frame` is `truth_now`. Keys `warp_error_rmse_m`,
/// `warp_error_normal_rmse_m`, `warp_true_rms_m`, `warp_estimated_rms_m`, `warp_error_points`,
/// `warp_error_skipped`; empty when nothing is measured or the trajectory cannot be aligned.
pub fn evaluate_warp(
    est: &[StampedPose],
    gt: &[StampedPose],
    map: &SurfelSet,
    wall: &WallMotion,
    truth_now: &SurfelSet,
    last_frame: u32,
    opts: &EvalOptions,
) -> BTreeMap<String, f64> {
    let mut m = BTreeMap::new();
    let Some(align) = align_trajectory(est, gt, opts.tolerance_s, opts.sim3) else { return m };
    if let Some(e) = warp_error(map, &align, wall, truth_now, last_frame, opts.warp_max_gap_frames) {
        m.insert("warp_error_rmse_m".into(), e.rmse_m);
        m.insert("warp_error_normal_rmse_m".into(), e.normal_rmse_m);
        m.insert("warp_true_rms_m".into(), e.true_rms_m);
        m.insert("warp_estimated_rms_m".into(), e.estimated_rms_m);
        m.insert("warp_error_points".into(), e.points as f64);
        m.insert("warp_error_skipped".into(), e.skipped as f64);
    }
    m
}
