//! The rectified views of a rig and the way back: per rectified pixel, where each camera's own
//! image is read (bilinear luminance; its field of view and its masks by the nearest pixel),
//! and per pixel of the left camera's own image, where the rectified left view sees its ray
//! (the depth is returned there). Made once per rig from [`Rectification`].

use capsule_slam_framework::StageError;
use capsule_slam_framework::camera::{PinholeCamera, Rig};
use capsule_slam_framework::image::{DepthMap, Rgb8};
use capsule_slam_framework::stereo::rectify::{Rectification, Side};
use rayon::prelude::*;

use super::sgm::INVALID;

/// The maps of one rig.
pub struct Rectifier {
    /// The rectification.
    pub rect: Rectification,
    /// The rig's own cameras.
    left: PinholeCamera,
    right: PinholeCamera,
    /// Per rectified pixel, the source pixel of each view (`None`: outside its image or view).
    left_src: Vec<Option<(f32, f32)>>,
    right_src: Vec<Option<(f32, f32)>>,
    /// Per pixel of the left camera, its place in the rectified left view.
    back: Vec<Option<(f32, f32)>>,
}

impl Rectifier {
    /// The maps of a stereo rig; an error for a mono rig or one that cannot be rectified.
    pub fn new(rig: &Rig) -> Result<Self, StageError> {
        let Rig::Stereo { left, right, t_right_left } = rig else {
            return Err(StageError::invalid_input(
                "stereo-sgm needs a stereo rig: give camera.toml a [right] table (or baseline_m) and the folder rgb_right.txt",
            ));
        };
        let rect = Rectification::new(left, right, t_right_left)?;
        let (w, h) = (rect.camera.width, rect.camera.height);
        let src = |side: Side, cam: &PinholeCamera| -> Vec<Option<(f32, f32)>> {
            (0..w * h)
                .into_par_iter()
                .map(|k| {
                    let p = rect.source_pixel(side, cam, (k % w) as f64, (k / w) as f64)?;
                    cam.in_fov(p.x, p.y).then_some((p.x as f32, p.y as f32))
                })
                .collect()
        };
        let (left_src, right_src) = (src(Side::Left, left), src(Side::Right, right));
        let back = (0..left.width * left.height)
            .into_par_iter()
            .map(|k| {
                let p = rect.left_to_rectified(left, (k % left.width) as f64, (k / left.width) as f64)?;
                (p.x > -0.5 && p.y > -0.5 && p.x < w as f64 - 0.5 && p.y < h as f64 - 0.5).then_some((p.x as f32, p.y as f32))
            })
            .collect();
        Ok(Self { rect, left: left.clone(), right: right.clone(), left_src, right_src, back })
    }

    /// Whether `cam` is the camera this rectifier was made for (of that side).
    pub fn fits(&self, rig: &Rig) -> bool {
        matches!(rig, Rig::Stereo { left, right, .. } if *left == self.left && *right == self.right)
    }

    /// The rectified luminance of one view (linear in the 8-bit values, 0–255), and where it
    /// has nothing: outside the view, or a source pixel `blocked` says to leave out.
    pub fn view(&self, side: Side, img: &Rgb8, blocked: impl Fn(usize, usize) -> bool + Sync) -> (Vec<f32>, Vec<bool>) {
        let src = match side {
            Side::Left => &self.left_src,
            Side::Right => &self.right_src,
        };
        let (iw, ih) = img.size();
        let w = self.rect.camera.width.max(1);
        let (mut gray, mut invalid) = (vec![0.0f32; src.len()], vec![true; src.len()]);
        // Row by row into the two outputs (a parallel unzip per pixel cost more than the
        // sampling); each pixel the same arithmetic.
        gray.par_chunks_mut(w).zip(invalid.par_chunks_mut(w)).zip(src.par_chunks(w)).for_each(|((g_row, i_row), s_row)| {
            for ((g_out, i_out), s) in g_row.iter_mut().zip(i_row.iter_mut()).zip(s_row) {
                let Some((u, v)) = *s else { continue };
                let (x0, y0) = (u.floor().max(0.0) as usize, v.floor().max(0.0) as usize);
                let (x1, y1) = ((x0 + 1).min(iw - 1), (y0 + 1).min(ih - 1));
                let (fx, fy) = ((u - x0 as f32).clamp(0.0, 1.0), (v - y0 as f32).clamp(0.0, 1.0));
                let lum = |x: usize, y: usize| {
                    let p = img.pixel(x, y);
                    0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2])
                };
                *g_out = (1.0 - fy) * ((1.0 - fx) * lum(x0, y0) + fx * lum(x1, y0)) + fy * ((1.0 - fx) * lum(x0, y1) + fx * lum(x1, y1));
                let (nx, ny) = ((u.round().max(0.0) as usize).min(iw - 1), (v.round().max(0.0) as usize).min(ih - 1));
                *i_out = blocked(nx, ny);
            }
        });
        (gray, invalid)
    }

    /// The left camera's own depth image from the rectified left disparities: each pixel reads
    /// the disparity where its ray lands (bilinear where the four neighbours agree within a
    /// pixel, else the nearest) and gets the depth along its own z.
    pub fn depth_in_left(&self, disparity: &[f32]) -> Result<DepthMap, StageError> {
        let (w, h) = (self.rect.camera.width, self.rect.camera.height);
        let (lw, lh) = (self.left.width, self.left.height);
        let at = |x: usize, y: usize| disparity[y * w + x];
        let data: Vec<f32> = self
            .back
            .par_iter()
            .map(|b| {
                let Some((u, v)) = *b else { return 0.0 };
                let (x0, y0) = (u.floor().max(0.0) as usize, v.floor().max(0.0) as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let four = [at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1)];
                let (lo, hi) = four.iter().fold((f32::MAX, f32::MIN), |(a, b), d| (a.min(*d), b.max(*d)));
                let d = if lo > INVALID && hi - lo <= 1.0 {
                    let (fx, fy) = ((u - x0 as f32).clamp(0.0, 1.0), (v - y0 as f32).clamp(0.0, 1.0));
                    (1.0 - fy) * ((1.0 - fx) * four[0] + fx * four[1]) + fy * ((1.0 - fx) * four[2] + fx * four[3])
                } else {
                    at((u.round().max(0.0) as usize).min(w - 1), (v.round().max(0.0) as usize).min(h - 1))
                };
                self.rect.left_depth_m(f64::from(u), f64::from(v), f64::from(d)).map_or(0.0, |z| z as f32)
            })
            .collect();
        DepthMap::from_vec(lw, lh, data).map_err(|e| StageError::invalid_input(e.to_string()))
    }
}
