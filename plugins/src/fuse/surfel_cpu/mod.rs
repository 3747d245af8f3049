//! `surfel-cpu`: the surfel map on the CPU (rayon), after Keller et al. 2013 and ElasticFusion
//! (Whelan et al. 2016), as the paper uses it (Sec. 3.3): surfels with position, normal,
//! colour, confidence, radius, t0 and t; projective association of each measurement against
//! an index map of the active model (depth gate along the ray, normal gate, the candidate
//! nearest the pixel ray wins); confidence-weighted averaging; stable surfels at
//! `stable_confidence`; stale unstable surfels removed; active/inactive split by `delta_t`,
//! shortened to `delta_t_moving` for what the camera left while the wall moved ([`super::window`]).
//!
//! Deviations from ElasticFusion, on purpose: every metric gate is an organ-scale parameter;
//! the confidence normaliser is the image half-diagonal, not 400 px; positions come from the
//! raw depth and normals from bilateral-filtered depth, as in ElasticFusion.

mod splat;

use capsule_slam_framework::deformation::Deformation;
use capsule_slam_framework::depth_noise::DepthNoiseModel;
use capsule_slam_framework::frame::RgbdFrame;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::stage::{FuseStats, LoopClosure};
use capsule_slam_framework::{Context, Fuser, Iso3, MapStats, ModelSet, ModelView, Plugin, StageError, Surfel, SurfelSet, register};
use rayon::prelude::*;

use super::measure::measurements;
use super::surfel_params::SurfelParams;
use super::surfel_rules::{Layer, Measurement, depth_gate, merge, normal_gate, raise_sigma, reactivate, revisit_layer};
use super::window::ActiveWindow;
pub use splat::{IndexMap, SplatDepths, predict};

/// The CPU surfel map.
pub struct SurfelCpu {
    params: SurfelParams,
    surfels: Vec<Surfel>,
    now: u32,
    window: ActiveWindow,
}

impl Plugin for SurfelCpu {
    const NAME: &'static str = "surfel-cpu";
    const SUMMARY: &'static str =
        "surfel map on the CPU: projective association, confidence-weighted fusion, active/inactive split (Keller 2013, ElasticFusion)";
    type Params = SurfelParams;

    fn build(params: SurfelParams, _env: &BuildEnv) -> Result<Self, StageError> {
        crate::common::ordered("min_depth_m", f64::from(params.min_depth_m), "max_depth_m", f64::from(params.max_depth_m))?;
        Ok(Self { params, surfels: Vec::new(), now: 0, window: ActiveWindow::default() })
    }
}

/// What one pixel's measurement does.
enum Action {
    Merge(u32, Measurement),
    Add(Measurement),
}

impl SurfelCpu {
    /// The surfels, in creation order.
    pub fn surfels(&self) -> &[Surfel] {
        &self.surfels
    }

    /// Moves every surfel by `d` (Eqs. 5–7 of the deformation graph: positions and normals);
    /// with `motion` (a tracker's warp) the displacement is added to each surfel's `warp_m`.
    fn warp_surfels(&mut self, d: &Deformation, motion: bool) {
        let warper = d.warper();
        if motion {
            self.surfels.par_iter_mut().for_each(|s| warper.warp_surfel_as_motion(s));
        } else {
            self.surfels.par_iter_mut().for_each(|s| warper.warp_surfel(s));
        }
    }

    /// The active window at frame `now`, in frames.
    fn delta_t(&self, now: u32) -> u32 {
        self.window.frames(now, &self.params)
    }

    /// Measurements of one frame and what to do with each.
    fn associate(&self, frame: &RgbdFrame, t_world_cam: &Iso3, ctx: &mut Context) -> Vec<Action> {
        let p = &self.params;
        let cam = ctx.rig.camera();
        let measured = measurements(frame, t_world_cam, cam, p, ctx);
        let clock = std::time::Instant::now();
        let now = self.now;
        let (stable, revisit) = (p.stable_confidence, p.revisit_reactivation);
        let dt = self.delta_t(now);
        let window = self.window;
        let layer = |s: &Surfel| revisit_layer(s.is_active(now, dt), s.confidence >= stable, revisit && window.revisits(s.t));
        let index = IndexMap::render(&self.surfels, layer, cam, t_world_cam, p.max_depth_m);
        ctx.count("ms_index_map", clock.elapsed().as_secs_f64() * 1e3);
        let (w, h) = (cam.width, cam.height);
        measured
            .par_iter()
            .map(|pm| {
                let (x, y, n) = (pm.x, pm.y, pm.n_cam);
                // Candidates: the index map's 3×3 neighbourhood.
                let mut best: Option<((Layer, f32), u32)> = None;
                for yy in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                    for xx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                        let k = yy * index.width + xx;
                        let i = index.index[k];
                        if i == u32::MAX {
                            continue;
                        }
                        let (pc, nm) = (index.p_cam[k], index.n_cam[k]);
                        let layer = if self.surfels[i as usize].is_active(now, dt) { Layer::First } else { Layer::Behind };
                        let gate = if layer == Layer::First { p.depth_gate_m } else { p.revisit_gate_m };
                        if !depth_gate(pc.z, pm.z_live_m, pm.lambda, gate) || !normal_gate(&nm, &n, p.normal_gate_rad, p.normal_bypass_nz) {
                            continue;
                        }
                        // An active candidate comes before any inactive one, then the nearest the ray.
                        let perp = (pc.coords - pm.ray_unit * pc.coords.dot(&pm.ray_unit)).norm();
                        let rank = (layer, perp);
                        if best.is_none_or(|(r, _)| rank < r) {
                            best = Some((rank, i));
                        }
                    }
                }
                match best {
                    Some((_, i)) => Action::Merge(i, pm.m),
                    None => Action::Add(pm.m),
                }
            })
            .collect()
    }
}

impl Fuser for SurfelCpu {
    fn fuse(&mut self, frame: &RgbdFrame, t_world_cam: &Iso3, ctx: &mut Context) -> Result<FuseStats, StageError> {
        self.now = frame.index as u32;
        let now = self.now;
        let actions = self.associate(frame, t_world_cam, ctx);
        let clock = std::time::Instant::now();
        // One update per surfel per frame: the last in pixel order wins (ElasticFusion).
        let mut update: Vec<Option<usize>> = vec![None; self.surfels.len()];
        let mut added = Vec::new();
        for (k, a) in actions.iter().enumerate() {
            match a {
                Action::Merge(i, _) => update[*i as usize] = Some(k),
                Action::Add(m) => added.push(m.to_surfel(now)),
            }
        }
        let ratio = self.params.radius_ratio;
        let merged = update.iter().filter(|u| u.is_some()).count();
        self.surfels.par_iter_mut().zip(update.par_iter()).for_each(|(s, u)| {
            if let Some(Action::Merge(_, m)) = u.map(|k| &actions[k]) {
                merge(s, m, now, ratio);
            }
        });
        let n_added = added.len();
        self.surfels.extend(added);
        // Stale unstable surfels go (ElasticFusion's clean pass, removal rule 3).
        let before = self.surfels.len();
        let (stable, life) = (self.params.stable_confidence, self.params.unstable_lifetime);
        self.surfels.retain(|s| s.confidence >= stable || now.saturating_sub(s.t) <= life);
        let removed = before - self.surfels.len();
        ctx.count("ms_update", clock.elapsed().as_secs_f64() * 1e3);
        ctx.count("surfels_merged", merged as f64);
        ctx.count("surfels_added", n_added as f64);
        ctx.count("surfels_removed", removed as f64);
        Ok(FuseStats { merged, added: n_added, removed })
    }

    fn predict(&mut self, t_world_cam: &Iso3, set: ModelSet, ctx: &mut Context) -> Result<ModelView, StageError> {
        let now = (ctx.frame_index as u32).max(self.now);
        let (stable, dt) = (self.params.stable_confidence, self.delta_t(now));
        let include = |s: &Surfel| s.confidence >= stable && (s.is_active(now, dt) == (set == ModelSet::Active));
        Ok(predict(&self.surfels, include, ctx.rig.camera(), t_world_cam, &SplatDepths::of(&self.params)))
    }

    fn deform(&mut self, closure: &LoopClosure, ctx: &mut Context) -> Result<(), StageError> {
        let clock = std::time::Instant::now();
        self.warp_surfels(&closure.deformation, false);
        ctx.count("ms_deform", clock.elapsed().as_secs_f64() * 1e3);
        // Reactivate the stable inactive surfels seen from the corrected pose.
        let now = (ctx.frame_index as u32).max(self.now);
        let params = self.window.params_at(now, &self.params);
        let reactivated = reactivate(&mut self.surfels, &closure.t_world_cam, ctx.rig.camera(), now, &params);
        ctx.count("surfels_reactivated", reactivated as f64);
        Ok(())
    }

    fn warp(&mut self, deformation: &Deformation, ctx: &mut Context) -> Result<(), StageError> {
        let clock = std::time::Instant::now();
        self.warp_surfels(deformation, true);
        self.window.warped(ctx.frame_index as u32);
        ctx.count("ms_warp", clock.elapsed().as_secs_f64() * 1e3);
        Ok(())
    }

    fn raise_sigma(&mut self, noise: &DepthNoiseModel, t_world_cam: &Iso3, ctx: &mut Context) -> Result<(), StageError> {
        let t_cam_world = t_world_cam.inverse();
        self.surfels.par_iter_mut().for_each(|s| raise_sigma(s, noise, &t_cam_world));
        ctx.count("surfels_sigma_raised", self.surfels.len() as f64);
        Ok(())
    }

    fn stats(&self) -> MapStats {
        let (stable, dt) = (self.params.stable_confidence, self.delta_t(self.now));
        MapStats {
            total: self.surfels.len(),
            active: self.surfels.iter().filter(|s| s.is_active(self.now, dt)).count(),
            stable: self.surfels.iter().filter(|s| s.confidence >= stable).count(),
        }
    }

    fn snapshot(&self) -> Result<SurfelSet, StageError> {
        Ok(SurfelSet::new(self.surfels.clone()))
    }

    fn active_window(&self) -> Option<u32> {
        Some(self.delta_t(self.now))
    }

    fn stable_confidence(&self) -> Option<f32> {
        Some(self.params.stable_confidence)
    }
}

register!(Fuser, SurfelCpu);

#[cfg(test)]
mod tests;
