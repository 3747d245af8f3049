//! `eval --plot DIR`: the trajectory against ground truth from the top and the side, and the
//! position error over time (plotters, PNG).

use std::path::Path;

use anyhow::{Context as _, Result};
use capsule_slam_framework::geometry::StampedPose;
use plotters::prelude::*;

fn bounds(v: impl Iterator<Item = (f64, f64)> + Clone) -> ((f64, f64), (f64, f64)) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (x, y) in v {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    let pad = 0.05 * (x1 - x0).max(y1 - y0).max(1e-6);
    ((x0 - pad, x1 + pad), (y0 - pad, y1 + pad))
}

fn view(path: &Path, title: &str, est: &[(f64, f64)], gt: &[(f64, f64)], labels: (&str, &str)) -> Result<()> {
    let root = BitMapBackend::new(path, (800, 700)).into_drawing_area();
    root.fill(&WHITE)?;
    let ((x0, x1), (y0, y1)) = bounds(est.iter().chain(gt).copied());
    let mut chart =
        ChartBuilder::on(&root).caption(title, ("sans-serif", 24)).margin(15).x_label_area_size(40).y_label_area_size(60).build_cartesian_2d(x0..x1, y0..y1)?;
    chart.configure_mesh().x_desc(labels.0).y_desc(labels.1).draw()?;
    chart
        .draw_series(LineSeries::new(gt.iter().copied(), BLACK.stroke_width(1)))?
        .label("ground truth")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    chart
        .draw_series(LineSeries::new(est.iter().copied(), RED.stroke_width(1)))?
        .label("estimate (aligned)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
    root.present()?;
    Ok(())
}

/// A 2-D series of the estimate and of the ground truth.
type Series = Vec<(f64, f64)>;

fn project(pairs: &[(StampedPose, StampedPose)], f: &dyn Fn(&StampedPose) -> (f64, f64)) -> (Series, Series) {
    (pairs.iter().map(|(e, _)| f(e)).collect(), pairs.iter().map(|(_, g)| f(g)).collect())
}

/// Writes `trajectory_top.png`, `trajectory_side.png` and `ate_over_time.png` into `dir`.
/// `pairs` are (aligned estimate, ground truth) matched by timestamp; positions in mm.
pub fn plot(dir: &Path, pairs: &[(StampedPose, StampedPose)]) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mm = |p: &StampedPose| p.t_world_cam.translation.vector * 1e3;
    let (e, g) = project(pairs, &|p| (mm(p).x, mm(p).y));
    view(&dir.join("trajectory_top.png"), "trajectory, top view (x–y)", &e, &g, ("x [mm]", "y [mm]")).context("plotting the top view")?;
    let (e, g) = project(pairs, &|p| (mm(p).x, mm(p).z));
    view(&dir.join("trajectory_side.png"), "trajectory, side view (x–z)", &e, &g, ("x [mm]", "z [mm]")).context("plotting the side view")?;

    let t0 = pairs.first().map_or(0.0, |p| p.1.timestamp_s);
    let err: Vec<(f64, f64)> = pairs.iter().map(|(e, g)| (g.timestamp_s - t0, (mm(e) - mm(g)).norm())).collect();
    let path = dir.join("ate_over_time.png");
    let root = BitMapBackend::new(&path, (900, 400)).into_drawing_area();
    root.fill(&WHITE)?;
    let t1 = err.last().map_or(1.0, |p| p.0.max(1e-6));
    let e1 = err.iter().map(|p| p.1).fold(0.0, f64::max).max(1e-6) * 1.1;
    let mut chart = ChartBuilder::on(&root)
        .caption("position error after alignment", ("sans-serif", 24))
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t1, 0.0..e1)?;
    chart.configure_mesh().x_desc("time [s]").y_desc("error [mm]").draw()?;
    chart.draw_series(LineSeries::new(err, BLUE.stroke_width(1)))?;
    root.present().context("plotting the error over time")?;
    Ok(())
}
