//! An input folder: TUM RGB-D layout (`rgb.txt`, optional `depth.txt` and `groundtruth.txt`)
//! or a plain folder of images sorted by name, with `camera.toml` beside them.
//! Frames are loaded one at a time ([`Dataset::load`]), so a run streams.

use std::path::{Path, PathBuf};

use capsule_slam_framework::camera::{CameraFile, PinholeCamera, Rig};
use capsule_slam_framework::config::{InputConfig, UndistortedView};
use capsule_slam_framework::error::LoadError;
use capsule_slam_framework::files::read_camera_file;
use capsule_slam_framework::frame::{CameraFrame, MASK_OUT_OF_VIEW, Masks, Photometry, Views};
use capsule_slam_framework::geometry::nearest_in_time;
use capsule_slam_framework::geometry::{Iso3, StampedPose};
use capsule_slam_framework::image::Mask;

use crate::undistort::Undistortion;
use crate::{images, tum};

#[derive(Debug, Clone)]
struct Entry {
    timestamp_s: f64,
    rgb: PathBuf,
    /// The right view of a stereo sequence (`rgb_right.txt`).
    rgb_right: Option<PathBuf>,
    depth: Option<PathBuf>,
    gt: Option<Iso3>,
}

/// An opened input folder.
#[derive(Debug, Clone)]
pub struct Dataset {
    dir: PathBuf,
    camera: CameraFile,
    entries: Vec<Entry>,
    ground_truth: Vec<StampedPose>,
    has_depth: bool,
    dropped_without_depth: usize,
    dropped_without_right: usize,
    out_of_view: Option<Mask>,
    /// The map from the lens's images to the pinhole ones, when `camera.toml` names a lens.
    undistortion: Option<Undistortion>,
    /// The same for the right camera of a stereo rig.
    right_undistortion: Option<Undistortion>,
}

/// The undistortion of a lens camera (after checking that `first_rgb` has the camera's size: the
/// map is as large as the camera says) and the out-of-view mask the stages get, if any.
fn view_maps(camera: &CameraFile, first_rgb: &Path, view: UndistortedView) -> Result<(Option<Undistortion>, Option<Mask>), LoadError> {
    let cam = camera.camera();
    if cam.distortion.is_some() {
        images::check_dimensions(first_rgb, (cam.width, cam.height))?;
        let u = Undistortion::with_view(&cam, view);
        let out_of_view = u.out_of_view().data().iter().any(|b| *b).then(|| u.out_of_view().clone());
        return Ok((Some(u), out_of_view));
    }
    let out_of_view = cam.fov_radius_px.map(|_| {
        let mut m = cam.fov_mask();
        m.data_mut().iter_mut().for_each(|v| *v = !*v);
        m
    });
    Ok((None, out_of_view))
}

/// The right views of a stereo sequence (`rgb_right.txt`), checked against the camera: a stereo
/// list needs a stereo rig and a stereo rig needs its list.
fn stereo_list(dir: &Path, camera: &CameraFile) -> Result<Option<Vec<tum::ListEntry>>, LoadError> {
    let list = dir.join("rgb_right.txt");
    let stereo_rig = matches!(camera.rig(), Rig::Stereo { .. });
    match (list.exists(), stereo_rig) {
        (true, true) => Ok(Some(tum::read_list(&list)?)),
        (false, false) => Ok(None),
        (true, false) => Err(LoadError::parse(
            &list,
            0,
            "a stereo sequence, but camera.toml describes one camera: add its [right] table (fx, fy, cx, cy, rotation, translation_m) or baseline_m",
        )),
        (false, true) => Err(LoadError::parse(
            &list,
            0,
            "missing: camera.toml describes a stereo rig ([right] or baseline_m), so the folder needs rgb_right.txt (the right images, as rgb.txt lists the left)",
        )),
    }
}

/// The frames of a TUM folder: each `rgb.txt` entry with its depth and its right view (when the
/// input has them) within the tolerance, as TUM's associate.py pairs rgb and depth; the entries
/// without are dropped and counted (depth, right view). Also whether the input has depth.
fn tum_entries(dir: &Path, rgb_txt: &Path, stereo: Option<&[tum::ListEntry]>, tol: f64, gt_at: impl Fn(f64) -> Option<Iso3>) -> Result<Listing, LoadError> {
    let rgb = tum::read_list(rgb_txt)?;
    let depth_txt = dir.join("depth.txt");
    let depth = if depth_txt.exists() { Some(tum::read_list(&depth_txt)?) } else { None };
    let nearest = |list: Option<&[tum::ListEntry]>, t: f64| list.map(|l| nearest_in_time(l, t, tol, |e| e.timestamp_s).map(|i| dir.join(&l[i].file)));
    let mut entries = Vec::with_capacity(rgb.len());
    let mut dropped = (0, 0);
    for r in rgb {
        let (d, right) = (nearest(depth.as_deref(), r.timestamp_s), nearest(stereo, r.timestamp_s));
        if d == Some(None) {
            dropped.0 += 1;
            continue;
        }
        if right == Some(None) {
            dropped.1 += 1;
            continue;
        }
        entries.push(Entry { timestamp_s: r.timestamp_s, rgb: dir.join(&r.file), rgb_right: right.flatten(), depth: d.flatten(), gt: gt_at(r.timestamp_s) });
    }
    Ok(Listing { entries, has_depth: depth.is_some(), dropped })
}

/// The frames of a folder and what their association dropped.
struct Listing {
    entries: Vec<Entry>,
    has_depth: bool,
    /// Frames dropped without depth, without a right view.
    dropped: (usize, usize),
}

impl Dataset {
    /// Opens a folder. The camera comes from `camera_override` or `<dir>/camera.toml`.
    /// RGB frames without a depth image within the tolerance are dropped (as TUM's
    /// associate.py does) and counted in [`Dataset::dropped_without_depth`].
    pub fn open(dir: &Path, input: &InputConfig, camera_override: Option<&CameraFile>) -> Result<Self, LoadError> {
        if !dir.is_dir() {
            return Err(LoadError::io(dir, std::io::Error::new(std::io::ErrorKind::NotFound, "input folder not found")));
        }
        let camera = match camera_override {
            Some(c) => c.clone(),
            None => {
                let p = dir.join("camera.toml");
                if !p.exists() {
                    return Err(LoadError::parse(
                        &p,
                        0,
                        "missing: every input folder needs camera.toml (width, height, fx, fy, cx, cy), or give [camera] in the config",
                    ));
                }
                read_camera_file(&p)?
            }
        };
        let tol = input.association_tolerance_s;
        let rgb_txt = dir.join("rgb.txt");
        let gt_txt = dir.join("groundtruth.txt");
        let ground_truth = if gt_txt.exists() { tum::read_trajectory(&gt_txt)? } else { Vec::new() };
        let gt_at = |t: f64| nearest_in_time(&ground_truth, t, tol, |p| p.timestamp_s).map(|i| ground_truth[i].t_world_cam);

        let stereo = stereo_list(dir, &camera)?;
        let Listing { entries, has_depth, dropped } = if rgb_txt.exists() {
            tum_entries(dir, &rgb_txt, stereo.as_deref(), tol, gt_at)?
        } else if stereo.is_some() {
            return Err(LoadError::parse(&rgb_txt, 0, "missing: a stereo sequence lists its left images in rgb.txt, as rgb_right.txt lists the right ones"));
        } else {
            let entries = images::list_images(dir)?
                .into_iter()
                .enumerate()
                .map(|(i, rgb)| {
                    let t = i as f64 / input.frame_rate_hz;
                    Entry { timestamp_s: t, rgb, rgb_right: None, depth: None, gt: gt_at(t) }
                })
                .collect();
            Listing { entries, has_depth: false, dropped: (0, 0) }
        };
        if entries.is_empty() {
            return Err(LoadError::parse(
                if rgb_txt.exists() { rgb_txt } else { dir.to_owned() },
                0,
                "no frames: expected rgb.txt (TUM layout) or image files (png, jpg, bmp)",
            ));
        }
        let (undistortion, out_of_view) = view_maps(&camera, &entries[0].rgb, input.undistorted_view)?;
        let right_undistortion = match camera.rig() {
            Rig::Stereo { right, .. } if right.distortion.is_some() => Some(Undistortion::with_view(&right, input.undistorted_view)),
            _ => None,
        };
        Ok(Self {
            dir: dir.to_owned(),
            camera,
            entries,
            ground_truth,
            has_depth,
            dropped_without_depth: dropped.0,
            dropped_without_right: dropped.1,
            out_of_view,
            undistortion,
            right_undistortion,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether there are no frames (never true for an opened dataset).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The input folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The camera file in force.
    pub fn camera_file(&self) -> &CameraFile {
        &self.camera
    }

    /// The rig the stages see: the file's, with the lens undistorted away (the frames are
    /// undistorted as they load).
    pub fn rig(&self) -> Rig {
        let seen = |c: PinholeCamera, u: &Option<Undistortion>| u.as_ref().map_or(c, |u| u.camera().clone());
        match self.camera.rig() {
            Rig::Mono(c) => Rig::Mono(seen(c, &self.undistortion)),
            Rig::Stereo { left, right, t_right_left } => {
                Rig::Stereo { left: seen(left, &self.undistortion), right: seen(right, &self.right_undistortion), t_right_left }
            }
        }
    }

    /// What the loader changed that a run should say: a lens's whole view cut to the largest
    /// canvas (`input.undistorted_view = "whole"`).
    pub fn warnings(&self) -> Vec<String> {
        [("left", &self.undistortion), ("right", &self.right_undistortion)]
            .into_iter()
            .filter(|(_, u)| u.as_ref().is_some_and(Undistortion::clipped))
            .map(|(side, _)| {
                format!(
                    "the {side} camera's lens sees wider than twice camera.toml's image on a pinhole canvas: its undistorted view (input.undistorted_view = \"whole\") is cut there"
                )
            })
            .collect()
    }

    /// The undistortion applied to every frame, if `camera.toml` names a lens.
    pub fn undistortion(&self) -> Option<&Undistortion> {
        self.undistortion.as_ref()
    }

    /// Whether frames carry depth.
    pub fn has_depth(&self) -> bool {
        self.has_depth
    }

    /// The whole ground-truth trajectory (empty without `groundtruth.txt`).
    pub fn ground_truth(&self) -> &[StampedPose] {
        &self.ground_truth
    }

    /// RGB frames dropped for lack of a depth image within the tolerance.
    pub fn dropped_without_depth(&self) -> usize {
        self.dropped_without_depth
    }

    /// Left frames of a stereo sequence dropped for lack of a right image within the tolerance.
    pub fn dropped_without_right(&self) -> usize {
        self.dropped_without_right
    }

    /// Loads frame `index`.
    pub fn load(&self, index: usize) -> Result<CameraFrame, LoadError> {
        self.load_frame(index, true).map(|(frame, _)| frame)
    }

    /// Loads frame `index` for a pipeline that estimates depth and reads the input's only to
    /// score it: a depth image that cannot be read leaves the frame without depth, and the
    /// returned warning says so (an RGB image that cannot be read is still an error).
    pub fn load_scoring_depth(&self, index: usize) -> Result<(CameraFrame, Option<String>), LoadError> {
        self.load_frame(index, false)
    }

    fn load_frame(&self, index: usize, depth_required: bool) -> Result<(CameraFrame, Option<String>), LoadError> {
        let e =
            self.entries.get(index).ok_or_else(|| LoadError::parse(&self.dir, 0, format!("frame {index} does not exist ({} frames)", self.entries.len())))?;
        let size = Some((self.camera.width as usize, self.camera.height as usize));
        let rgb = images::read_rgb(&e.rgb, size)?;
        let (depth_m, warning) = match (&e.depth, depth_required) {
            (Some(p), true) => (Some(images::read_depth(p, self.camera.depth_scale, size)?), None),
            (Some(p), false) => match images::read_depth(p, self.camera.depth_scale, size) {
                Ok(d) => (Some(d), None),
                Err(err) => (None, Some(format!("frame {index}: depth not scored: {err} (the depth is estimated; the file is read only to score it)"))),
            },
            (None, _) => (None, None),
        };
        let (rgb, depth_m) = match &self.undistortion {
            Some(u) => (u.rgb(&rgb), depth_m.map(|d| u.depth(&d))),
            None => (rgb, depth_m),
        };
        let views = match &e.rgb_right {
            None => Views::Mono(rgb),
            Some(p) => {
                let right = images::read_rgb(p, size)?;
                let right = match &self.right_undistortion {
                    Some(u) => u.rgb(&right),
                    None => right,
                };
                Views::Stereo { left: rgb, right }
            }
        };
        let mut masks = Masks::new();
        if let Some(m) = &self.out_of_view {
            masks.insert(MASK_OUT_OF_VIEW, m.clone());
        }
        let frame = CameraFrame {
            index,
            timestamp_s: e.timestamp_s,
            views,
            depth_m,
            gt_t_world_cam: e.gt,
            masks,
            right_masks: Masks::new(),
            photometry: Photometry::default(),
            sample_share: self.undistortion.as_ref().map(|u| u.sample_share().clone()),
        };
        Ok((frame, warning))
    }
}
