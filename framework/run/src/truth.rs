//! The true surfaces of a moving wall, for the live surface error and the warp error: a
//! deforming phantom writes `gt_surface_NNNNNN.ply` at some frames (all on the rest shape's
//! material grid); a rigid one has its rest shape `gt_surface.ply` alone.

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use capsule_slam_eval::warp::WallMotion;
use capsule_slam_framework::error::PipelineError;
use capsule_slam_framework::map::SurfelSet;
use capsule_slam_io::{Dataset, ply};

/// The true surface at a frame, for the live surface error.
pub(crate) enum LiveTruth<'a> {
    /// The surface at that frame (a rigid input's rest shape, borrowed).
    At(Cow<'a, SurfelSet>),
    /// The input has no ground-truth surface.
    None,
    /// A deforming input without the surface at that frame: why the metric is off.
    Missing(String),
}

/// The true surface at frame `last`: `gt_surface_<last>.ply` of a deforming phantom (one with
/// per-frame surfaces), the rest shape of a rigid one.
pub(crate) fn live_truth<'a>(dataset: &Dataset, rest: Option<&'a SurfelSet>, last: usize) -> Result<LiveTruth<'a>, PipelineError> {
    let Some(rest) = rest else { return Ok(LiveTruth::None) };
    let dir = dataset.dir();
    let at = dir.join(format!("gt_surface_{last:06}.ply"));
    if at.exists() {
        return Ok(LiveTruth::At(Cow::Owned(ply::read_surfels(&at)?)));
    }
    let deforming = std::fs::read_dir(dir)
        .map_err(|e| capsule_slam_framework::LoadError::io(dir, e))?
        .flatten()
        .any(|e| e.file_name().to_string_lossy().starts_with("gt_surface_"));
    Ok(if deforming {
        LiveTruth::Missing(format!(
            "live surface error off: the wall moves but {} has no true surface at the last frame {last} ({}); make the sequence with `capsule-slam synth --surface-every N` or run to a frame that has one",
            dir.display(),
            at.display()
        ))
    } else {
        LiveTruth::At(Cow::Borrowed(rest))
    })
}

/// The true surface files of a deforming input, (frame, path), sorted by frame.
fn surface_files(dir: &Path) -> Result<Vec<(u32, PathBuf)>, String> {
    let entries = std::fs::read_dir(dir).map_err(|e| format!("cannot list {}: {e}", dir.display()))?;
    let mut files: Vec<(u32, PathBuf)> = entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let frame = name.strip_prefix("gt_surface_")?.strip_suffix(".ply")?.parse().ok()?;
            Some((frame, e.path()))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// The wall's true motion up to frame `last` and its surface at `last`: the
/// `gt_surface_NNNNNN.ply` files in `dir` (a deforming phantom), or the rigid rest shape `rest`
/// held still when there are none. An error (a message for a warning: these files serve
/// evaluation only) when a file cannot be read or does not share one grid.
pub fn wall_motion(dir: &Path, rest: &SurfelSet, last: usize) -> Result<(WallMotion, SurfelSet), String> {
    let files = surface_files(dir)?;
    if files.is_empty() {
        return WallMotion::new([(0, rest)]).map(|w| (w, rest.clone())).map_err(|e| e.to_string());
    }
    let mut wall = WallMotion::default();
    let mut now = None;
    for (frame, path) in files.into_iter().filter(|(f, _)| *f as usize <= last) {
        let s = ply::read_surfels(&path).map_err(|e| format!("{e}; rewrite the sequence with `capsule-slam synth`"))?;
        wall.add(frame, &s).map_err(|e| format!("{}: {e}", path.display()))?;
        if frame as usize == last {
            now = Some(s);
        }
    }
    let now = now.ok_or_else(|| format!("{} has no true surface at the last frame {last}", dir.display()))?;
    Ok((wall, now))
}
