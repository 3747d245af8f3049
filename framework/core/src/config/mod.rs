//! The run configuration: one TOML file with `[pipeline]`, `[input]`, `[output]`, an optional
//! `[camera]` and `[plugins.<name>]` tables. Every table denies unknown keys; the whole file is
//! validated before the first frame ([`validate`]) and every problem is reported at once.
//! `--set KEY=VALUE` overrides any key ([`overrides`]).

pub mod default_text;
pub mod overrides;
pub mod validate;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::CameraFile;
use crate::error::{ConfigError, ConfigProblem};

/// The value that switches an optional stage off.
pub const NONE: &str = "none";

/// The whole configuration.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Which plugin runs each stage.
    #[serde(default)]
    pub pipeline: PipelineConfig,
    /// Where the frames come from.
    #[serde(default)]
    pub input: InputConfig,
    /// Where the results go.
    #[serde(default)]
    pub output: OutputConfig,
    /// Intrinsics overriding the input's `camera.toml`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraFile>,
    /// Parameters per plugin, `[plugins.<name>]`.
    #[serde(default)]
    pub plugins: BTreeMap<String, toml::Table>,
}

/// `[pipeline]`: the plugin of each stage, by registry name. A key left out keeps its default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PipelineConfig {
    /// Preprocessors, run in order (`[]` for none).
    pub preprocess: Vec<String>,
    /// Depth estimator.
    pub depth: String,
    /// Tracker.
    pub tracker: String,
    /// Fuser.
    pub fuser: String,
    /// Loop closer, or `"none"`.
    pub loop_closer: String,
}

fn none() -> String {
    NONE.to_owned()
}

impl Default for PipelineConfig {
    /// The default pipeline is the capsule's, monocular, as in the paper: highlights removed
    /// (`reflection`), the lens and LED fall-off divided out (`vignetting`), depth by
    /// `near-light-sfs` from the image and the input's `light.toml`, `nonrigid` tracking (a rigid
    /// `icp-rgb` start, then a warp of the map where the wall moves, which it does only with
    /// measured depth) and the CPU surfel fuser. For an RGB-D input set `depth = "sensor"`. Where a stage has no real
    /// plugin in this build, the app substitutes the oracle and says so.
    fn default() -> Self {
        Self {
            preprocess: vec!["reflection".into(), "vignetting".into()],
            depth: "near-light-sfs".into(),
            tracker: "nonrigid".into(),
            fuser: "surfel-cpu".into(),
            loop_closer: none(),
        }
    }
}

impl PipelineConfig {
    /// The loop closer, or `None` when switched off.
    pub fn loop_closer(&self) -> Option<&str> {
        (self.loop_closer != NONE).then_some(self.loop_closer.as_str())
    }

    /// Every selected plugin name with its stage kind, in pipeline order.
    pub fn selected(&self) -> Vec<(crate::registry::StageKind, &str)> {
        use crate::registry::StageKind as K;
        let mut out: Vec<(K, &str)> = self.preprocess.iter().map(|p| (K::Preprocessor, p.as_str())).collect();
        out.push((K::DepthEstimator, &self.depth));
        out.push((K::Tracker, &self.tracker));
        out.push((K::Fuser, &self.fuser));
        if let Some(l) = self.loop_closer() {
            out.push((K::LoopCloser, l));
        }
        out
    }
}

/// The first pose of the trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InitialPose {
    /// The identity (the map's world frame is the first camera frame).
    #[default]
    Identity,
    /// The first frame's ground-truth pose when the input has one (maps then line up with a
    /// ground-truth surface without alignment).
    GroundTruth,
}

/// The camera the stages see when `camera.toml` names a lens (the frames are undistorted onto
/// it as they load).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum UndistortedView {
    /// The file's intrinsics and image size: a barrel lens's outer field, which a pinhole
    /// camera of that size does not see, is cropped.
    #[default]
    Source,
    /// The file's focal length and every ray the lens's image sees: the canvas grows (the
    /// principal point moves with it) to hold the source's whole field of view, at most
    /// twice the file's width and height (OpenCV's `getOptimalNewCameraMatrix` with alpha 1
    /// and a larger new image size, the focal length kept).
    Whole,
}

/// `[input]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InputConfig {
    /// A TUM RGB-D folder or a folder of images (with `camera.toml`). Absent: the app's
    /// built-in input.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub path: Option<PathBuf>,
    /// Process at most this many frames.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_frames: Option<usize>,
    /// Largest timestamp difference for associating rgb, depth and ground truth, seconds
    /// (TUM's associate.py uses 0.02 s).
    pub association_tolerance_s: f64,
    /// Frame rate assumed for a plain folder of images, Hz.
    pub frame_rate_hz: f64,
    /// The first pose of the trajectory.
    pub initial_pose: InitialPose,
    /// The undistorted camera of a lens input: its own size or the lens's whole view.
    pub undistorted_view: UndistortedView,
}

impl Default for InputConfig {
    fn default() -> Self {
        Self {
            path: None,
            max_frames: None,
            association_tolerance_s: 0.02,
            frame_rate_hz: 30.0,
            initial_pose: InitialPose::Identity,
            undistorted_view: UndistortedView::Source,
        }
    }
}

/// `[output]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputConfig {
    /// Output folder.
    pub dir: PathBuf,
    /// Whether to write `map.ply` at the end.
    pub map: bool,
    /// Which surfels `map.ply` holds and the map's figures score.
    pub map_surfels: MapSurfels,
}

impl Default for OutputConfig {
    fn default() -> Self {
        Self { dir: PathBuf::from("out"), map: true, map_surfels: MapSurfels::default() }
    }
}

/// Which surfels of the fuser's map are written (`output.map_surfels`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MapSurfels {
    /// Those seen in at least two frames (last seen after the frame that created them) or
    /// stable: a surfel one frame made and no other confirmed (a stereo mismatch at the rim of
    /// the last frames' view) is left out, while a still camera's ten frames keep their whole view.
    #[default]
    Confirmed,
    /// Those at or above the fuser's stable confidence (ElasticFusion's export: about ten views
    /// for a surfel near the image centre, more towards the rim).
    Stable,
    /// Every surfel.
    All,
}

impl Config {
    /// Reads a config file (or the defaults when `path` is `None`), applies `--set` overrides
    /// in order and checks the structure. Plugin-level validation needs the registry: see
    /// [`validate::validate`].
    pub fn load(path: Option<&Path>, overrides: &[String]) -> Result<Self, ConfigError> {
        Self::load_checked(path, overrides, |_| Vec::new())
    }

    /// [`Config::load`], and when the config has problems but could still be read with its bad
    /// keys left out, `more` is asked for that partial config's problems too (the registry's
    /// plugin names, [`validate::plugin_name_problems`]): an unknown key does not hide the
    /// unknown plugin beside it.
    pub fn load_checked(path: Option<&Path>, overrides: &[String], more: impl Fn(&Config) -> Vec<ConfigProblem>) -> Result<Self, ConfigError> {
        let source_name = Self::source_name(path, overrides);
        let fail = |problems| ConfigError { source_name: source_name.clone(), problems };
        let mut table = match path {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .map_err(|e| fail(vec![ConfigProblem::new("(file)", format!("cannot read: {e}"), "check the path given to --config")]))?;
                text.parse::<toml::Table>()
                    .map_err(|e| fail(vec![ConfigProblem::new("(syntax)", e.to_string().trim().replace('\n', " "), "fix the TOML syntax at the line shown")]))?
            }
            None => toml::Table::new(),
        };
        let mut problems = Vec::new();
        for o in overrides {
            if let Err(p) = overrides::apply(&mut table, o) {
                problems.push(p);
            }
        }
        let (config, mut found) = Self::from_table_partial(table);
        problems.append(&mut found);
        match config {
            Some(c) if problems.is_empty() => Ok(c),
            Some(partial) => {
                problems.extend(more(&partial));
                Err(fail(problems))
            }
            None => Err(fail(problems)),
        }
    }

    /// How config problems name where they came from: the file (or the built-in default) and,
    /// since a problem may come from a `--set` as well as from the file, the `--set`s.
    pub fn source_name(path: Option<&Path>, overrides: &[String]) -> String {
        let base = path.map_or_else(|| "the built-in default config".to_owned(), |p| p.display().to_string());
        if overrides.is_empty() { base } else { format!("{base} with --set {}", overrides.join(" --set ")) }
    }

    /// Deserialises a table section by section, so that every section's problem is reported.
    pub fn from_table(table: toml::Table) -> Result<Self, Vec<ConfigProblem>> {
        match Self::from_table_partial(table) {
            (Some(c), problems) if problems.is_empty() => Ok(c),
            (_, problems) => Err(problems),
        }
    }

    /// [`Config::from_table`]'s problems, and the config as read with every unknown key left
    /// out (`None` when a section could not be read at all).
    fn from_table_partial(mut table: toml::Table) -> (Option<Self>, Vec<ConfigProblem>) {
        let mut problems = Vec::new();
        for key in table.keys() {
            if !["pipeline", "input", "output", "camera", "plugins"].contains(&key.as_str()) {
                problems.push(ConfigProblem::new(key.clone(), "unknown section", "use [pipeline], [input], [output], [camera] or [plugins.<name>]"));
            }
        }
        /// A section; an unknown key is reported and left out, and the rest read again, so that
        /// it does not hide the section's other problems (an unknown plugin next to it).
        fn section<T: serde::de::DeserializeOwned + Default>(table: &mut toml::Table, key: &str, problems: &mut Vec<ConfigProblem>) -> Option<T> {
            let Some(mut v) = table.remove(key) else { return Some(T::default()) };
            let fix = format!("see `capsule-slam config --default` for the keys of [{key}]");
            loop {
                match v.clone().try_into::<T>() {
                    Ok(t) => return Some(t),
                    Err(e) => {
                        let message = e.to_string().trim().replace('\n', " ");
                        let unknown = message.split("unknown field `").nth(1).and_then(|r| r.split('`').next()).map(str::to_owned);
                        problems.push(ConfigProblem::new(key, message, fix.clone()));
                        let removed = match (unknown, v.as_table_mut()) {
                            (Some(field), Some(t)) => t.remove(&field).is_some(),
                            _ => false,
                        };
                        if !removed {
                            return None;
                        }
                    }
                }
            }
        }
        let pipeline = section::<PipelineConfig>(&mut table, "pipeline", &mut problems);
        let input = section::<InputConfig>(&mut table, "input", &mut problems);
        let output = section::<OutputConfig>(&mut table, "output", &mut problems);
        let camera = section::<Option<CameraFile>>(&mut table, "camera", &mut problems);
        let plugins = section::<BTreeMap<String, toml::Table>>(&mut table, "plugins", &mut problems);
        match (pipeline, input, output, camera, plugins) {
            (Some(pipeline), Some(input), Some(output), Some(camera), Some(plugins)) => (Some(Self { pipeline, input, output, camera, plugins }), problems),
            _ => (None, problems),
        }
    }

    /// The config as TOML text (what `config.toml` in the output holds).
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# could not serialise the config: {e}\n"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_gives_defaults() {
        let c = Config::from_table(toml::Table::new()).unwrap();
        assert_eq!(c, Config::default());
        assert_eq!(c.pipeline.loop_closer(), None);
    }

    #[test]
    fn roundtrip_through_toml() {
        let mut c = Config::default();
        c.pipeline.preprocess = vec!["a".into()];
        c.plugins.insert("a".into(), toml::from_str("x = 1.5").unwrap());
        let back = Config::from_table(c.to_toml_string().parse().unwrap()).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn problems_of_several_sections_are_all_reported() {
        let t: toml::Table = toml::from_str("[pipeline]\ndepthh = 'x'\n[output]\ndirr = 'o'\n[extra]\n").unwrap();
        let p = Config::from_table(t).unwrap_err();
        let keys: Vec<_> = p.iter().map(|p| p.key.as_str()).collect();
        assert_eq!(keys, vec!["extra", "pipeline", "output"]);
        assert!(p[1].message.contains("depthh"), "{}", p[1].message);
    }
}
