//! A prepared problem solved: the normal equations laid out and their pattern analysed
//! (`Problem::prepare`, which `problem.rs` runs beside the rigid start), then the Gauss-Newton
//! iterations from the rigid start (`Problem::solve_prepared`; the energy and the chord method
//! are described in `solve.rs`).

use capsule_slam_framework::geometry::{exp_se3, renormalised};
use capsule_slam_framework::{Iso3, StageError};
use nalgebra::Vector6;

use crate::track::icp_rgb::frames::Level;

use super::assemble::Layout;
use super::points::ModelPoint;
use super::solve::{Cache, Outcome, Problem, Weights, common_rms, largest_translation_m, ms, solver_error};
use super::system::Factor;

/// A problem's normal-equation layout with its analysed factorisation: all a solve needs
/// before its first linearisation, none of it depending on the pose or the references.
pub(crate) struct Prepared {
    layout: Layout,
    factor: Factor,
    /// Symbolic analyses run (0: the cache's was reused).
    analyses: usize,
    /// Time laying out the pattern and analysing it, ms.
    ms_setup: f64,
    /// Of it, the analysis, ms.
    ms_analyse: f64,
}

impl Prepared {
    /// Gives the pattern and its analysis back to `cache` unused (a frame that lost track).
    pub(crate) fn keep(self, cache: &mut Cache) {
        cache.kept = Some((self.layout.pattern, self.factor));
    }
}

impl Problem {
    /// The layout of the normal equations and the analysis of their pattern (the cache's
    /// analysis when the pattern is unchanged; taken from the cache either way).
    pub(crate) fn prepare(&self, model: &[ModelPoint], w: &Weights, cache: &mut Cache) -> Result<Prepared, StageError> {
        let clock = std::time::Instant::now();
        let layout = self.layout(model, w)?;
        let ms_layout = ms(clock);
        let (factor, analyses) = match cache.kept.take() {
            Some((old, f)) if old.same_structure(&layout.pattern) => (f, 0),
            _ => (Factor::new(&layout.pattern).map_err(solver_error)?, 1),
        };
        Ok(Prepared { layout, factor, analyses, ms_setup: ms(clock), ms_analyse: ms(clock) - ms_layout })
    }

    /// [`Problem::solve`] with the layout and analysis `prepare` made for these points.
    pub(crate) fn solve_prepared(
        &mut self,
        model: &[ModelPoint],
        prepared: Prepared,
        level: &Level,
        t_start: &Iso3,
        w: &Weights,
        cache: &mut Cache,
    ) -> Result<Outcome, StageError> {
        let nodes = self.graph.deformation.nodes.len();
        let u = self.graph.model.unknowns();
        let Prepared { mut layout, mut factor, analyses, ms_setup, ms_analyse } = prepared;
        let mut t = *t_start;
        let mut xi = Vector6::<f64>::zeros();
        let (mut first_r2, mut last_r2) = (Vec::new(), Vec::new());
        let mut out = Outcome {
            t_world_cam: t,
            iterations: 0,
            factorisations: 0,
            inliers: 0,
            icp_rms_m: f64::INFINITY,
            icp_rms_first_m: f64::INFINITY,
            rgb_rms: f64::INFINITY,
            rgb_rms_first: f64::INFINITY,
            inliers_first: 0,
            icp_common_rms_m: (f64::INFINITY, f64::INFINITY),
            analyses,
            ms_analyse,
            ms_setup,
            ms_assemble: 0.0,
            ms_factor: 0.0,
            ms_problem: 0.0,
        };
        // The chord method's state: the largest translation of the last step, and whether the
        // next iteration factorises.
        let (mut last_step_m, mut refactor) = (f64::INFINITY, true);
        for _ in 0..w.iterations {
            let clock = std::time::Instant::now();
            let matrix = refactor || !w.reuse_factor;
            let (g, (stats, r2)) = self.linearise(model, level, &t, &xi, w, &mut layout, matrix);
            (out.inliers, out.icp_rms_m, out.rgb_rms) = stats;
            if out.iterations == 0 {
                (out.inliers_first, out.icp_rms_first_m, out.rgb_rms_first) = stats;
                first_r2 = r2.clone();
            }
            last_r2 = r2;
            out.ms_assemble += ms(clock);
            let clock = std::time::Instant::now();
            let step = if matrix { factor.solve(&layout.pattern, &g) } else { factor.solve_kept(&g) }.map_err(solver_error)?;
            out.ms_factor += ms(clock);
            if !step.iter().all(|v| v.is_finite()) {
                return Err(StageError::invalid_input("nonrigid: the Gauss-Newton step is not finite"));
            }
            self.graph.shift(&step[..u * nodes], 1.0);
            if self.camera {
                let d = Vector6::from_column_slice(&step[u * nodes..]);
                t = renormalised(exp_se3(&d) * t);
                xi += d;
            }
            out.iterations += 1;
            out.factorisations += usize::from(matrix);
            let norm = step.iter().map(|v| v * v).sum::<f64>().sqrt();
            let step_m = largest_translation_m(&step, nodes, self.camera, self.graph.model);
            if norm < 1e-9 || step_m < w.step_tolerance_m {
                break;
            }
            // A kept matrix far from the current one (robust weights, correspondences and image
            // gradients moved since) gives steps that overshoot and swing back instead of
            // shrinking: factorise again.
            refactor = !matrix && step_m >= last_step_m;
            last_step_m = step_m;
        }
        out.t_world_cam = t;
        out.icp_common_rms_m = common_rms(&first_r2, &last_r2);
        cache.kept = Some((layout.pattern, factor));
        Ok(out)
    }
}
