//! `results.csv` (every scalar of every cell's `summary.json`, nested keys joined with dots) and
//! `results.md` (per input the headline figures, the best of each column in bold, and each
//! variant's mean ± sd over the inputs).

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;

use super::cells::Cell;

/// One cell's scalars, keyed by their flattened names.
#[derive(Debug, Clone, Default)]
pub struct Row {
    /// The input's name.
    pub input: String,
    /// The variant's name.
    pub variant: String,
    /// Numbers.
    pub numbers: BTreeMap<String, f64>,
    /// Strings and booleans (e.g. `status`).
    pub words: BTreeMap<String, String>,
}

/// The headline columns of `results.md`: key, heading, scale to the shown unit, lower is better.
pub const HEADLINE: [(&str, &str, f64, bool); 11] = [
    ("frames_lost", "lost", 1.0, true),
    ("ate_rmse_m", "ATE mm", 1e3, true),
    ("ate_rmse_sim3_m", "ATE Sim3 mm", 1e3, true),
    ("ate_percent_of_path", "ATE % path", 1.0, true),
    ("rpe_trans_rmse_m", "RPE mm", 1e3, true),
    ("surface_rmse_m", "surface mm", 1e3, true),
    ("live_surface_rmse_m", "live surface mm", 1e3, true),
    ("surface_completeness_1mm", "complete 1 mm", 100.0, false),
    ("ms_per_frame_mean", "ms/frame", 1.0, true),
    ("ms_per_frame_p95", "ms p95", 1.0, true),
    ("loop_closures", "closures", 1.0, false),
];

/// Flattens a JSON object's scalars (arrays and the resolved `pipeline` config are left out).
fn flatten(prefix: &str, v: &serde_json::Value, row: &mut Row) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, v) in m {
                if prefix.is_empty() && (k == "pipeline" || k == "warnings") {
                    continue;
                }
                let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                flatten(&key, v, row);
            }
        }
        serde_json::Value::Number(n) => {
            if let Some(x) = n.as_f64() {
                row.numbers.insert(prefix.to_owned(), x);
            }
        }
        serde_json::Value::String(s) => {
            row.words.insert(prefix.to_owned(), s.clone());
        }
        serde_json::Value::Bool(b) => {
            row.words.insert(prefix.to_owned(), b.to_string());
        }
        _ => {}
    }
}

/// The row of a cell: its summary's scalars, or `status = missing` without one.
pub fn row(cell: &Cell) -> Row {
    let mut r = Row { input: cell.input.clone(), variant: cell.variant.clone(), ..Row::default() };
    match cell.summary() {
        Some(s) => flatten("", &s, &mut r),
        None => {
            r.words.insert("status".into(), "missing (no summary.json)".into());
        }
    }
    r
}

/// A CSV field, quoted where it must be.
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) { format!("\"{}\"", s.replace('"', "\"\"")) } else { s.to_owned() }
}

/// `results.csv`: `input`, `variant`, `status`, then every other key in name order.
pub fn csv(rows: &[Row]) -> String {
    let mut keys: BTreeSet<String> = BTreeSet::new();
    for r in rows {
        keys.extend(r.numbers.keys().cloned());
        keys.extend(r.words.keys().cloned());
    }
    keys.remove("status");
    let keys: Vec<String> = std::iter::once("status".to_owned()).chain(keys).collect();
    let mut out = String::from("input,variant");
    for k in &keys {
        out += ",";
        out += &csv_field(k);
    }
    out += "\n";
    for r in rows {
        out += &format!("{},{}", csv_field(&r.input), csv_field(&r.variant));
        for k in &keys {
            let v = r.numbers.get(k).map(|x| format!("{x}")).or_else(|| r.words.get(k).cloned()).unwrap_or_default();
            out += ",";
            out += &csv_field(&v);
        }
        out += "\n";
    }
    out
}

/// Mean and sample standard deviation.
fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n.max(1.0);
    let var = if v.len() > 1 { v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0) } else { 0.0 };
    (m, var.sqrt())
}

/// The headline columns any row has.
fn columns(rows: &[Row]) -> Vec<(&'static str, &'static str, f64, bool)> {
    HEADLINE.iter().copied().filter(|(k, ..)| rows.iter().any(|r| r.numbers.contains_key(*k))).collect()
}

/// `results.md`.
pub fn markdown(rows: &[Row], inputs: &[String], variants: &[String], title: &str) -> String {
    let cols = columns(rows);
    let mut out = format!(
        "# {title}\n\nPer input, variants as rows; the best figure of each column in **bold** (lowest, or highest for completeness and closures). Times are this machine's.\n"
    );
    let header = |first: &str| {
        let mut h = format!("\n| {first} | status |");
        let mut sep = String::from("|---|---|");
        for (_, name, ..) in &cols {
            h += &format!(" {name} |");
            sep += "---|";
        }
        format!("{h}\n{sep}\n")
    };
    for input in inputs {
        let here: Vec<&Row> = rows.iter().filter(|r| &r.input == input).collect();
        let _ = write!(out, "\n## {input}\n{}", header("variant"));
        for r in &here {
            let _ = write!(out, "| {} | {} |", r.variant, r.words.get("status").map_or("?", String::as_str));
            for (key, _, scale, lower) in &cols {
                let best = here.iter().filter(|o| o.words.get("status").is_some_and(|s| s == "complete")).filter_map(|o| o.numbers.get(*key)).copied().reduce(
                    |a, b| {
                        if *lower { a.min(b) } else { a.max(b) }
                    },
                );
                match r.numbers.get(*key) {
                    Some(v) if Some(*v) == best && here.len() > 1 => {
                        let _ = write!(out, " **{}** |", fmt(v * scale));
                    }
                    Some(v) => {
                        let _ = write!(out, " {} |", fmt(v * scale));
                    }
                    None => out += " — |",
                }
            }
            out += "\n";
        }
    }
    let _ = write!(out, "\n## Mean ± sd over the inputs\n{}", header("variant"));
    for v in variants {
        let mine: Vec<&Row> = rows.iter().filter(|r| &r.variant == v).collect();
        let complete = mine.iter().filter(|r| r.words.get("status").is_some_and(|s| s == "complete")).count();
        let _ = write!(out, "| {v} | {complete} of {} complete |", mine.len());
        for (key, _, scale, _) in &cols {
            let vals: Vec<f64> = mine.iter().filter_map(|r| r.numbers.get(*key)).map(|x| x * scale).collect();
            if vals.is_empty() {
                out += " — |";
            } else {
                let (m, sd) = mean_sd(&vals);
                let _ = write!(out, " {} ± {} |", fmt(m), fmt(sd));
            }
        }
        out += "\n";
    }
    out
}

/// Whole numbers as they are (counts); else three significant digits (at least), no exponent
/// for the usual ranges.
fn fmt(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 || a >= 100.0 || (v.fract() == 0.0 && a < 1e9) {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else if a >= 0.01 {
        format!("{v:.3}")
    } else {
        format!("{v:.2e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r(input: &str, variant: &str, ate: f64) -> Row {
        let mut row = Row { input: input.into(), variant: variant.into(), ..Row::default() };
        row.numbers.insert("ate_rmse_m".into(), ate);
        row.numbers.insert("ms_per_stage_mean.track".into(), 3.0);
        row.words.insert("status".into(), "complete".into());
        row
    }

    #[test]
    fn flattening_keeps_every_scalar_under_a_dotted_key() {
        let mut row = Row::default();
        let v: serde_json::Value =
            serde_json::json!({"status": "complete", "frames": 3, "ms_per_stage_mean": {"track": 1.5}, "pipeline": {"x": 1}, "warnings": ["w"]});
        flatten("", &v, &mut row);
        assert_eq!(row.numbers.get("frames"), Some(&3.0));
        assert_eq!(row.numbers.get("ms_per_stage_mean.track"), Some(&1.5));
        assert_eq!(row.words.get("status").map(String::as_str), Some("complete"));
        assert!(!row.numbers.keys().chain(row.words.keys()).any(|k| k.starts_with("pipeline") || k == "warnings"));
    }

    #[test]
    fn the_table_marks_the_best_and_averages_over_inputs() {
        let mut rows = vec![r("a", "x", 0.0015), r("a", "y", 0.0025), r("b", "x", 0.0035), r("b", "y", 0.001)];
        rows[0].numbers.insert("frames_lost".into(), 1.0);
        let md = markdown(&rows, &["a".into(), "b".into()], &["x".into(), "y".into()], "t");
        // A count stays whole; the lowest ATE of an input is bold.
        assert!(md.contains("| x | complete | **1** | **1.50** |") && md.contains("| y | complete | — | 2.50 |"), "{md}");
        // x: mean 2.5 mm, sd √2.
        assert!(md.contains("| x | 2 of 2 complete | 1 ± 0 | 2.50 ± 1.41 |"), "{md}");
        let csv = csv(&rows);
        assert!(csv.starts_with("input,variant,status,ate_rmse_m,frames_lost,ms_per_stage_mean.track\n") && csv.lines().count() == 5, "{csv}");
    }
}
