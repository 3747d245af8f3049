//! Model selection for the `nonrigid` tracker: what a fit did (`Fit`), the residual gains a
//! warp is judged on (`Gains`), their window (`windowed_gain`), the still-wall probe (`Probe`)
//! and the moving wall's coarse rigid start (`Moving`).

use capsule_slam_framework::deformation::Deformation;
use capsule_slam_framework::{Context, Iso3};

use super::solve;

/// While the wall is clearly still, the warp is solved on every n-th frame only, n doubling
/// while the probes keep finding it still; a rise of the rigid residual between probes calls
/// the next one at once.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Probe {
    /// Whether the wall is judged clearly still.
    pub(crate) still: bool,
    /// Consecutive still verdicts.
    pub(crate) streak: u32,
    /// Frames since the last solve while still.
    pub(crate) skipped: u32,
    /// The interval while still, frames (0: the first, `still_probe_every_frames`).
    every: u32,
    /// Running mean of the rigid RMS residual over the skipped frames of this still phase, m,
    /// and how many it has seen.
    mean_rms_m: f64,
    seen: u32,
    /// The next frame probes (the residual rose).
    due: bool,
}

/// Skipped frames the residual's mean needs before a rise is judged against it.
const RISE_AFTER_FRAMES: u32 = 4;
/// Frames the residual's running mean remembers (each new one weighs at least 1 / this): the
/// view changes as the capsule moves on.
const RISE_MEMORY_FRAMES: u32 = 30;

impl Probe {
    /// Whether this frame skips the warp solve (and counts it), the interval being `first`
    /// frames at first (`still_probe_every_frames`).
    pub(crate) fn skips(&mut self, first: u32) -> bool {
        if !self.still || self.due || self.skipped + 1 >= self.every.max(first) {
            self.skipped = 0;
            self.due = false;
            return false;
        }
        self.skipped += 1;
        true
    }

    /// Files a probe's verdict: clearly still or not. A second clearly still verdict in a row
    /// doubles the interval, from `first` up to `max` frames; anything else ends the still phase
    /// (its interval and residual mean with it).
    pub(crate) fn verdict(&mut self, still: bool, (first, max): (u32, u32)) {
        if still && self.still {
            self.every = self.every.max(first).saturating_mul(2).min(max.max(first));
        } else if !still {
            *self = Self { streak: self.streak, ..Self::default() };
        }
        self.still = still;
    }

    /// Files a skipped frame's rigid RMS residual `rms_m`; one above `rise` times the running
    /// mean of those before it (0: never) calls a probe on the next frame and returns the
    /// interval to its first. Returns whether it did.
    pub(crate) fn observe(&mut self, rms_m: f64, rise: f64) -> bool {
        if !rms_m.is_finite() {
            return false;
        }
        if rise > 0.0 && self.seen >= RISE_AFTER_FRAMES && rms_m > rise * self.mean_rms_m {
            self.due = true;
            self.every = 0;
            return true;
        }
        self.seen += 1;
        self.mean_rms_m += (rms_m - self.mean_rms_m) / f64::from(self.seen.min(RISE_MEMORY_FRAMES));
        false
    }
}

/// While the wall is clearly moving, the rigid start stops after the coarse levels on all but
/// every n-th frame (`moving_probe_every_frames`).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Moving {
    /// Consecutive judged solves that kept a warp with a clear gain.
    pub(crate) streak: u32,
    /// Frames since the last full rigid start while clearly moving.
    pub(crate) skipped: u32,
}

impl Moving {
    /// Whether this frame's rigid start stops after the coarse levels (and counts it): the
    /// wall has been clearly moving for `window` judged solves, and this is not an
    /// `every`-th frame.
    pub(crate) fn shortens(&mut self, window: u32, every: u32) -> bool {
        if self.streak < window || self.skipped + 1 >= every {
            self.skipped = 0;
            return false;
        }
        self.skipped += 1;
        true
    }

    /// Files a judged solve: a warp kept with a windowed gain `judged` of at least
    /// `clear_gain` lengthens the streak, and so does any kept warp once the streak has reached
    /// `window` (a wall clearly moving stays moving while its warp is kept: hysteresis between
    /// entering at `clear_gain` and leaving below the keeping gain); anything else ends it.
    pub(crate) fn judged(&mut self, kept: bool, judged: f64, clear_gain: f64, window: u32) {
        if kept && (judged >= clear_gain || self.streak >= window) {
            self.streak += 1;
        } else {
            *self = Self::default();
        }
    }
}

/// What a fit did.
#[allow(clippy::large_enum_variant, reason = "one per frame, matched once; boxing the warp buys nothing")]
pub(crate) enum Fit {
    /// The warp and the pose.
    Solved {
        /// The pose.
        t_world_cam: Iso3,
        /// The warp of the surface near the solved nodes.
        warp: Deformation,
        /// Solver figures.
        outcome: solve::Outcome,
        /// Nodes solved.
        nodes: usize,
        /// Model points bound to them.
        points: usize,
        /// Whether the camera was held at the rigid start (`hold_camera_on_step`).
        held: bool,
        /// The windowed gain the warp was kept on (`None`: kept unjudged).
        judged: Option<f64>,
    },
    /// Why the rigid pose stands.
    Fallback(String),
    /// The warp explained too little of the residual (the wall did not move measurably): the
    /// rigid pose stands, no warp, and this is no failure. The gains, and the mean
    /// point-to-plane gain of the window they were judged on.
    Still(Gains, f64),
}

/// The shares by which a solve lowered the RMS residuals from the rigid start (not finite
/// where a term had no residual).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Gains {
    /// Point to plane over the points that are inliers both at the rigid start and after the
    /// solve: the gain the warp is judged on. Over all inliers (`icp_all`) an alignment that
    /// brings points into the gate raises the RMS (preset 5 with a 4 mm wave, frames 148–150:
    /// −0.11, −0.12, −0.05 with 3–6 % more inliers, judged still while the wall moved; over the
    /// common inliers 0.19, 0.23, 0.25; on the rigid twin both −0.03 to −0.06).
    pub icp: f64,
    /// Point to plane over each linearisation's own inliers.
    pub icp_all: f64,
    /// Photometric.
    pub rgb: f64,
    /// Point-to-plane inliers after the solve over those at the rigid start, minus one.
    pub inliers: f64,
}

impl Gains {
    pub(crate) fn of(outcome: &solve::Outcome) -> Self {
        let (common_last, common_first) = outcome.icp_common_rms_m;
        Self {
            icp: 1.0 - common_last / common_first,
            icp_all: 1.0 - outcome.icp_rms_m / outcome.icp_rms_first_m,
            rgb: 1.0 - outcome.rgb_rms / outcome.rgb_rms_first,
            inliers: outcome.inliers as f64 / outcome.inliers_first.max(1) as f64 - 1.0,
        }
    }

    /// Files the finite gains as counters.
    pub(crate) fn count(&self, ctx: &mut Context) {
        let named =
            [("nonrigid_icp_gain", self.icp), ("nonrigid_icp_all_gain", self.icp_all), ("nonrigid_rgb_gain", self.rgb), ("nonrigid_inlier_gain", self.inliers)];
        for (name, v) in named {
            if v.is_finite() {
                ctx.count(name, v);
            }
        }
    }
}

/// The gain `min_rms_gain` is tested on: the mean of the last `window` finite gains, `gain`
/// included (`gain` itself when it is not finite or the window is one frame).
pub(crate) fn windowed_gain(recent: &mut std::collections::VecDeque<f64>, gain: f64, window: u32) -> f64 {
    if !gain.is_finite() {
        return gain;
    }
    recent.push_back(gain);
    while recent.len() > window.max(1) as usize {
        recent.pop_front();
    }
    recent.iter().sum::<f64>() / recent.len() as f64
}
