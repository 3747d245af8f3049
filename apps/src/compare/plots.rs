//! `compare`'s pictures (plotters, PNG) in `DIR/plots/`: per headline metric the variants side
//! by side for each input; per input every variant's trajectory over the ground truth (top
//! view, SE(3)-aligned, or Sim(3) for a run without metric scale); per swept key every metric
//! against the swept value.

use std::path::Path;

use anyhow::{Context as _, Result};
use capsule_slam_eval::{align_trajectory, associate};
use capsule_slam_io::tum::read_trajectory;
use plotters::prelude::*;

use super::cells::Cell;
use super::plan::safe_name;
use super::results::{HEADLINE, Row};

/// A colour per series, repeating.
fn colour(k: usize) -> RGBColor {
    const C: [RGBColor; 8] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
    ];
    C[k % C.len()]
}

/// Per headline metric: a panel per input (its own scale), a bar per variant.
pub fn bars(dir: &Path, rows: &[Row], inputs: &[String], variants: &[String]) -> Result<usize> {
    let mut written = 0;
    for (key, name, scale, _) in HEADLINE {
        let value = |i: &str, v: &str| rows.iter().find(|r| r.input == i && r.variant == v).and_then(|r| r.numbers.get(key)).map(|x| x * scale);
        if !inputs.iter().any(|i| variants.iter().any(|v| value(i, v).is_some_and(|x| x > 0.0))) {
            continue;
        }
        let path = dir.join(format!("{}.png", safe_name(key)));
        let panel_w = (60 + 50 * variants.len() as u32).max(260);
        let root = BitMapBackend::new(&path, (panel_w * inputs.len() as u32, 520)).into_drawing_area();
        root.fill(&WHITE)?;
        let root = root.titled(name, ("sans-serif", 22))?;
        let last = inputs.len() - 1;
        for (k, (panel, input)) in root.split_evenly((1, inputs.len())).iter().zip(inputs).enumerate() {
            let top = variants.iter().filter_map(|v| value(input, v)).fold(0.0, f64::max).max(1e-12);
            let mut chart = ChartBuilder::on(panel)
                .caption(input, ("sans-serif", 16))
                .margin(10)
                .x_label_area_size(20)
                .y_label_area_size(55)
                .build_cartesian_2d(0.0..variants.len() as f64, 0.0..top * 1.15)?;
            chart.configure_mesh().disable_x_mesh().x_labels(0).draw()?;
            for (vk, v) in variants.iter().enumerate() {
                let c = colour(vk);
                let bar = value(input, v).map(|y| Rectangle::new([(vk as f64 + 0.1, 0.0), (vk as f64 + 0.9, y)], c.filled()));
                let series = chart.draw_series(bar)?;
                if k == last {
                    series.label(v.as_str()).legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], c.filled()));
                }
            }
            if k == last {
                chart.configure_series_labels().position(SeriesLabelPosition::UpperRight).background_style(WHITE.mix(0.85)).border_style(BLACK).draw()?;
            }
        }
        root.present().with_context(|| format!("plotting {}", path.display()))?;
        written += 1;
    }
    Ok(written)
}

/// Per input: every variant's trajectory over the ground truth, top view (x–y, mm).
pub fn trajectories(dir: &Path, cells: &[Cell], inputs: &[(String, std::path::PathBuf)], tolerance_s: f64) -> Result<usize> {
    let mut written = 0;
    for (input, input_dir) in inputs {
        let Ok(gt) = read_trajectory(&input_dir.join("groundtruth.txt")) else { continue };
        let mm = |p: &nalgebra::Vector3<f64>| (p.x * 1e3, p.y * 1e3);
        let mut series = Vec::new();
        // The truth over the time the runs cover (a run of part of a sequence).
        let (mut t0, mut t1) = (f64::MAX, f64::MIN);
        for c in cells.iter().filter(|c| &c.input == input) {
            let Ok(est) = read_trajectory(&c.out.join("trajectory.txt")) else { continue };
            if let (Some(a), Some(b)) = (est.first(), est.last()) {
                (t0, t1) = (t0.min(a.timestamp_s), t1.max(b.timestamp_s));
            }
            let metric = c.summary().is_none_or(|s| s["metric_scale"] != false);
            let Some(align) = align_trajectory(&est, &gt, tolerance_s, !metric) else { continue };
            let xy: Vec<(f64, f64)> = associate(&est, &gt, tolerance_s).iter().map(|(e, _)| mm(&align.apply_pose(&e.t_world_cam).translation.vector)).collect();
            series.push((c.variant.clone(), xy));
        }
        let gt_xy: Vec<(f64, f64)> = gt
            .iter()
            .filter(|p| p.timestamp_s >= t0 - tolerance_s && p.timestamp_s <= t1 + tolerance_s)
            .map(|p| mm(&p.t_world_cam.translation.vector))
            .collect();
        if series.is_empty() || gt_xy.is_empty() {
            continue;
        }
        let all = gt_xy.iter().chain(series.iter().flat_map(|(_, s)| s.iter()));
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for (x, y) in all {
            (x0, x1, y0, y1) = (x0.min(*x), x1.max(*x), y0.min(*y), y1.max(*y));
        }
        let pad = 0.05 * (x1 - x0).max(y1 - y0).max(1e-3);
        let path = dir.join(format!("trajectories_{}.png", safe_name(input)));
        let root = BitMapBackend::new(&path, (800, 700)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(format!("{input}: trajectories, top view (aligned)"), ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0 - pad..x1 + pad, y0 - pad..y1 + pad)?;
        chart.configure_mesh().x_desc("x [mm]").y_desc("y [mm]").draw()?;
        chart
            .draw_series(LineSeries::new(gt_xy, BLACK.stroke_width(2)))?
            .label("ground truth")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        for (k, (name, xy)) in series.into_iter().enumerate() {
            let c = colour(k);
            chart.draw_series(LineSeries::new(xy, c.stroke_width(1)))?.label(name).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw()?;
        root.present().with_context(|| format!("plotting {}", path.display()))?;
        written += 1;
    }
    Ok(written)
}

/// Per swept key and headline metric: the metric against the key's (numeric) value, a line per
/// input and variant (and the other keys' values).
pub fn sweeps(dir: &Path, cells: &[Cell], rows: &[Row], keys: &[String]) -> Result<usize> {
    let mut written = 0;
    for key in keys {
        for (metric, name, scale, _) in HEADLINE {
            // Series: everything but this key's value.
            let mut series: std::collections::BTreeMap<String, Vec<(f64, f64)>> = Default::default();
            for (c, r) in cells.iter().zip(rows) {
                let Some(x) = c.swept.iter().find(|(k, _)| k == key).and_then(|(_, v)| v.parse::<f64>().ok()) else { continue };
                let Some(y) = r.numbers.get(metric) else { continue };
                let rest: Vec<String> = c.swept.iter().filter(|(k, _)| k != key).map(|(k, v)| format!("{k}={v}")).collect();
                let label = std::iter::once(format!("{} / {}", c.input, c.base_variant)).chain(rest).collect::<Vec<_>>().join(" ");
                series.entry(label).or_default().push((x, y * scale));
            }
            if series.is_empty() {
                continue;
            }
            let pts = series.values().flatten();
            let (mut x0, mut x1, mut y1) = (f64::MAX, f64::MIN, 0.0f64);
            for (x, y) in pts {
                (x0, x1, y1) = (x0.min(*x), x1.max(*x), y1.max(*y));
            }
            let xpad = 0.05 * (x1 - x0).max(1e-9);
            let path = dir.join(format!("sweep_{}_{}.png", safe_name(key), safe_name(metric)));
            let root = BitMapBackend::new(&path, (800, 500)).into_drawing_area();
            root.fill(&WHITE)?;
            let mut chart = ChartBuilder::on(&root)
                .caption(format!("{name} against {key}"), ("sans-serif", 20))
                .margin(15)
                .x_label_area_size(40)
                .y_label_area_size(60)
                .build_cartesian_2d(x0 - xpad..x1 + xpad, 0.0..(y1 * 1.15).max(1e-9))?;
            chart.configure_mesh().x_desc(key.as_str()).y_desc(name).draw()?;
            for (k, (label, mut pts)) in series.into_iter().enumerate() {
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                let c = colour(k);
                chart.draw_series(pts.iter().map(|p| Circle::new(*p, 4, c.filled())))?;
                chart.draw_series(LineSeries::new(pts, c.stroke_width(2)))?.label(label).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
            }
            chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw()?;
            root.present().with_context(|| format!("plotting {}", path.display()))?;
            written += 1;
        }
    }
    Ok(written)
}
