//! The active window of a surfel map whose wall moves.
//!
//! ElasticFusion splits the map by time alone: a surfel is active iff it was seen within the
//! last δt frames (`delta_t`, 200). On a rigid wall an old surfel is still where the wall is,
//! and a long window keeps the map's memory. On a wall that moves, a surfel the camera left
//! stays where it was seen while the wall goes on moving (a 4 mm wave moves a point by up to
//! 0.14 mm per frame); kept active it is predicted, tracked against and fused into at a stale
//! phase of the wall (issue 16, `docs/results/nonrigid.md`, "A shorter active window").
//!
//! The rule here: a tracker's warp (`Fuser::warp`) says the wall moved at that frame. A surfel
//! last seen before the map's last warp has missed that motion and stays active for
//! `delta_t_moving` frames only; one seen after it keeps the whole `delta_t`. Since the last
//! warp only moves forward, the active set at frame `now` is again a window, of
//! `clamp(now − last_warp, delta_t_moving, delta_t)` frames: it is `delta_t` on a wall that
//! never moved (every rigid input is unchanged), `delta_t_moving` while it moves, and it grows
//! back by one frame per frame once the wall is still, so no stale surface returns at once.
//!
//! For the same reason a revisit (`revisit_reactivation`) brings back only what was last seen
//! since the map's last warp: a measurement merged into a surfel the wall has moved away from
//! would be held at the stale phase by that surfel's confidence, and the stale surface would
//! be active again.

use super::surfel_params::SurfelParams;

/// The frame of the map's last warp, and the active window it implies.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ActiveWindow {
    last_warp: Option<u32>,
}

impl ActiveWindow {
    /// A tracker's warp moved the map at frame `now`.
    pub fn warped(&mut self, now: u32) {
        self.last_warp = Some(self.last_warp.map_or(now, |t| t.max(now)));
    }

    /// The active window at frame `now`, in frames: a surfel is active iff now − t ≤ this.
    pub fn frames(&self, now: u32, p: &SurfelParams) -> u32 {
        match self.last_warp {
            None => p.delta_t,
            Some(t) => now.saturating_sub(t).clamp(p.delta_t_moving.min(p.delta_t), p.delta_t),
        }
    }

    /// Whether a surfel last seen at frame `t` may be reactivated by a revisit: the wall has
    /// not moved since (no warp after `t`; a warp at `t` came before that frame's fusion).
    pub fn revisits(&self, t: u32) -> bool {
        t >= self.revisit_after()
    }

    /// The first frame of a last sighting that [`Self::revisits`] accepts (0 before any warp).
    pub fn revisit_after(&self) -> u32 {
        self.last_warp.unwrap_or(0)
    }

    /// `p` with `delta_t` replaced by the window at frame `now` (for a closure's reactivation).
    pub fn params_at(&self, now: u32, p: &SurfelParams) -> SurfelParams {
        SurfelParams { delta_t: self.frames(now, p), ..p.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(delta_t: u32, delta_t_moving: u32) -> SurfelParams {
        SurfelParams { delta_t, delta_t_moving, ..SurfelParams::default() }
    }

    #[test]
    fn a_wall_that_never_moved_keeps_the_whole_window() {
        let w = ActiveWindow::default();
        for now in [0, 10, 500, 10_000] {
            assert_eq!(w.frames(now, &params(200, 60)), 200);
        }
    }

    #[test]
    fn a_moving_wall_shortens_the_window_which_grows_back_one_frame_per_frame() {
        let p = params(200, 60);
        let mut w = ActiveWindow::default();
        w.warped(100);
        assert_eq!(w.frames(100, &p), 60);
        assert_eq!(w.frames(160, &p), 60);
        assert_eq!(w.frames(161, &p), 61);
        assert_eq!(w.frames(250, &p), 150);
        assert_eq!(w.frames(300, &p), 200);
        assert_eq!(w.frames(5_000, &p), 200);
        // A surfel seen at 120 (after the warp) stays active at 250 (130 frames later); one
        // seen at 95 (before it) left the window at 156.
        let active = |seen: u32, now: u32| now - seen <= w.frames(now, &p);
        assert!(active(120, 250));
        assert!(!active(95, 156));
        // Whatever is inactive stays so until seen again: the window never outgrows the age
        // of a surfel seen before the warp.
        for now in 156..400 {
            assert!(!active(95, now), "frame {now}");
        }
    }

    #[test]
    fn the_last_warp_only_moves_forward_and_the_window_never_exceeds_delta_t() {
        let mut w = ActiveWindow::default();
        w.warped(50);
        w.warped(40);
        assert_eq!(w.frames(110, &params(200, 60)), 60);
        assert_eq!(w.frames(111, &params(200, 60)), 61);
        // A moving window longer than delta_t is delta_t: the setting turns the rule off.
        assert_eq!(w.frames(60, &params(200, 200)), 200);
        assert_eq!(w.frames(60, &params(30, 60)), 30);
        assert_eq!(w.params_at(60, &params(200, 60)).delta_t, 60);
    }

    #[test]
    fn a_revisit_brings_back_only_what_was_seen_since_the_wall_last_moved() {
        let mut w = ActiveWindow::default();
        assert!(w.revisits(0) && w.revisits(7), "a wall that never moved: every surfel");
        w.warped(40);
        assert!(!w.revisits(39));
        assert!(w.revisits(40) && w.revisits(41), "the warp of frame 40 came before its fusion");
        w.warped(90);
        assert!(!w.revisits(60));
        assert_eq!(w.revisit_after(), 90);
    }
}
