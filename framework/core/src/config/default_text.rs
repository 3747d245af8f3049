//! `capsule-slam config --default`: a complete, commented default config generated from the
//! registry, so it always lists the plugins and parameters of this build.

use std::fmt::Write;

use super::{Config, InputConfig, OutputConfig};
use crate::registry::{PluginEntry, Registry, StageKind};

/// The default config as commented TOML. Tables of plugins the default pipeline does not
/// select are commented out (an unused `[plugins.x]` table is a config error).
pub fn default_config_text(registry: &Registry) -> String {
    let c = Config::default();
    let p = &c.pipeline;
    let i = InputConfig::default();
    let o = OutputConfig::default();
    let mut s = String::new();
    let names = |k: StageKind| {
        let n = registry.names(k);
        if n.is_empty() { "(none registered in this build)".to_owned() } else { n.join(", ") }
    };
    let _ = writeln!(s, "# capsule-slam configuration. Every key is optional; the values shown are the defaults.");
    let _ = writeln!(s, "# Override any key on the command line: --set pipeline.depth=sensor --set plugins.<name>.<key>=<value>");
    let _ = writeln!(s, "\n[pipeline]");
    let _ = writeln!(s, "# preprocessors, in order: {}", names(StageKind::Preprocessor));
    let _ = writeln!(s, "preprocess = {}", toml::Value::try_from(&p.preprocess).map(|v| v.to_string()).unwrap_or_else(|_| "[]".into()));
    let _ = writeln!(s, "# depth estimators: {}", names(StageKind::DepthEstimator));
    let _ = writeln!(s, "depth = {:?}", p.depth);
    let _ = writeln!(s, "# trackers: {}", names(StageKind::Tracker));
    let _ = writeln!(s, "tracker = {:?}", p.tracker);
    let _ = writeln!(s, "# fusers: {}", names(StageKind::Fuser));
    let _ = writeln!(s, "fuser = {:?}", p.fuser);
    let _ = writeln!(s, "# loop closers: {} (\"none\" switches loop closure off)", names(StageKind::LoopCloser));
    let _ = writeln!(s, "loop_closer = {:?}", p.loop_closer);
    let _ = writeln!(s, "\n[input]");
    let _ = writeln!(s, "# path = \"data/sequence\"   # TUM RGB-D folder or image folder with camera.toml; absent: the built-in phantom");
    let _ = writeln!(s, "# max_frames = 300          # absent: every frame");
    let _ = writeln!(s, "association_tolerance_s = {:?}   # s, rgb/depth/ground-truth timestamp matching (TUM associate.py)", i.association_tolerance_s);
    let _ = writeln!(s, "frame_rate_hz = {:?}   # Hz, for a plain image folder", i.frame_rate_hz);
    let _ = writeln!(s, "initial_pose = \"identity\"   # or \"ground-truth\": start at the first ground-truth pose");
    let _ = writeln!(s, "undistorted_view = \"source\"   # a lens's frames undistorted at camera.toml's size; \"whole\": grown to the lens's whole view");
    let _ = writeln!(s, "\n[output]");
    let _ = writeln!(s, "dir = {:?}", o.dir.display().to_string());
    let _ = writeln!(s, "map = {}   # write map.ply", o.map);
    let _ = writeln!(s, "\n# [camera]   # overrides the input's camera.toml (same keys)");
    let _ = writeln!(
        s,
        "# width = 320\n# height = 320\n# fx = 160.0\n# fy = 160.0\n# cx = 159.5\n# cy = 159.5\n# depth_scale = 5000.0\n# distortion = [0.0, 0.0, 0.0, 0.0, 0.0]   # k1 k2 p1 p2 k3, or {{ model = \"equidistant\", coefficients = [k1, k2, k3, k4] }}\n# fov_radius_px = 150.0"
    );
    let selected: Vec<&str> = p.selected().into_iter().map(|(_, n)| n).collect();
    for e in registry.iter() {
        plugin_table(&mut s, e, selected.contains(&e.name));
    }
    s
}

fn plugin_table(s: &mut String, e: &PluginEntry, selected: bool) {
    let c = if selected { "" } else { "# " };
    let _ = writeln!(s, "\n# {} ({}): {}", e.name, e.kind.as_str(), e.summary);
    let _ = writeln!(s, "{c}[plugins.{}]", e.name);
    for d in e.param_docs() {
        let range = d.range.map(|(lo, hi)| format!(", range [{lo}, {hi}]")).unwrap_or_default();
        let _ = writeln!(s, "# {} ({}{range})", d.doc, d.unit);
        if let Some(v) = d.default {
            let _ = writeln!(s, "{c}{} = {}", d.name, v);
        }
    }
}
