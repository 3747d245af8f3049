//! The camera from views of a planar checkerboard (issue 18, item 11): Zhang's closed-form start
//! ([`zhang`]) and a Levenberg-Marquardt refinement of the intrinsics, the lens and every view's
//! pose ([`refine`]), for OpenCV's radial-tangential (k1 k2 p1 p2 k3) or equidistant (fisheye)
//! lens. Corner detection is [`crate::board`]'s.

mod refine;
mod zhang;

use capsule_slam_framework::lens::LensModel;
use nalgebra::Point2;

/// One detected corner: where it is on the board (metres, plane z = 0) and in the image (pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardCorner {
    /// Position on the board, metres.
    pub board_m: Point2<f64>,
    /// Position in the image, pixels.
    pub pixel: Point2<f64>,
}

/// The corners of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardView {
    /// A name for messages (the file's).
    pub name: String,
    /// The corners found.
    pub corners: Vec<BoardCorner>,
}

/// The lens model to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LensKind {
    /// OpenCV's k1 k2 p1 p2 k3.
    RadialTangential,
    /// OpenCV's fisheye k1 k2 k3 k4.
    Equidistant,
}

impl LensKind {
    /// Coefficients fitted.
    pub fn coefficients(self) -> usize {
        match self {
            Self::RadialTangential => 5,
            Self::Equidistant => 4,
        }
    }
}

/// A fitted camera.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFit {
    /// fx, fy, cx, cy in pixels.
    pub intrinsics: [f64; 4],
    /// The lens.
    pub lens: LensModel,
    /// RMS reprojection error per corner over the views kept, pixels.
    pub rms_px: f64,
    /// Each kept view's name and RMS, pixels.
    pub views: Vec<(String, f64)>,
    /// Views left out, each with the reason.
    pub dropped: Vec<(String, String)>,
}

/// Why no camera could be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraFitError {
    /// Zhang's method needs at least two views of the board from different angles.
    #[error("{0} usable board views; at least 2 from different angles are needed (a view needs 6 corners)")]
    TooFewViews(usize),
}

/// Fewest corners a view needs (a homography has 8 unknowns).
pub const MIN_CORNERS: usize = 6;
/// A view is dropped and the fit repeated when its RMS exceeds this many times the median.
const OUTLIER_FACTOR: f64 = 5.0;
/// ... and this many pixels.
const OUTLIER_FLOOR_PX: f64 = 1.0;

/// Fits the camera of an image of `width × height` pixels to its board views.
pub fn fit_camera(views: &[BoardView], width: usize, height: usize, lens: LensKind) -> Result<CameraFit, CameraFitError> {
    let mut dropped = Vec::new();
    let mut kept: Vec<(BoardView, nalgebra::Matrix3<f64>)> = Vec::new();
    for v in views {
        match (v.corners.len() >= MIN_CORNERS).then(|| zhang::homography(v)).flatten() {
            Some(h) => kept.push((v.clone(), h)),
            None => dropped.push((v.name.clone(), format!("{} corners, no homography", v.corners.len()))),
        }
    }
    loop {
        if kept.len() < 2 {
            return Err(CameraFitError::TooFewViews(kept.len()));
        }
        let fit = fit_views(&kept, width as f64, height as f64, lens);
        let mut rms: Vec<f64> = fit.views.iter().map(|v| v.1).collect();
        rms.sort_by(f64::total_cmp);
        let limit = (OUTLIER_FACTOR * rms[rms.len() / 2]).max(OUTLIER_FLOOR_PX);
        let worst = fit.views.iter().enumerate().max_by(|a, b| a.1.1.total_cmp(&b.1.1)).map(|(i, v)| (i, v.1));
        match worst {
            Some((i, r)) if r > limit && kept.len() > 2 => {
                let (v, _) = kept.remove(i);
                dropped.push((v.name, format!("reprojection RMS {r:.2} px, above {limit:.2} px (5 × the median): a wrong grid or a blurred frame")));
            }
            _ => return Ok(CameraFit { dropped, ..fit }),
        }
    }
}

/// One fit over the given views: Zhang's start (or a centred one when the conic is not a
/// camera's) refined from zero lens coefficients.
fn fit_views(kept: &[(BoardView, nalgebra::Matrix3<f64>)], w: f64, h: f64, lens: LensKind) -> CameraFit {
    let homographies: Vec<_> = kept.iter().map(|(_, h)| *h).collect();
    let views: Vec<BoardView> = kept.iter().map(|(v, _)| v.clone()).collect();
    let problem = refine::Problem { views: &views, lens };
    let start = |k: zhang::Intrinsics| {
        let mut p: Vec<f64> = k.to_vec();
        p.extend(std::iter::repeat_n(0.0, lens.coefficients()));
        for hm in &homographies {
            let (r, t) = zhang::pose(hm, &k).unwrap_or((nalgebra::Rotation3::identity(), nalgebra::Vector3::new(0.0, 0.0, 1.0)));
            p.extend(r.scaled_axis().iter().chain(t.iter()));
        }
        problem.solve(p)
    };
    // Both starts are refined and the better kept: Zhang's conic is poor under strong
    // distortion, the centred start when the principal point is far off-centre.
    let centred = start(zhang::centred_intrinsics(&homographies, w, h));
    let (p, rms_px) = match zhang::intrinsics(&homographies, w, h).map(start) {
        Some(z) if z.1 < centred.1 => z,
        _ => centred,
    };
    let per_view = (0..views.len())
        .map(|i| {
            let mut r = Vec::new();
            problem.view_residuals(&p, i, &mut r);
            let n = (r.len() / 2).max(1) as f64;
            (views[i].name.clone(), (r.iter().map(|x| x * x).sum::<f64>() / n).sqrt())
        })
        .collect();
    CameraFit { intrinsics: [p[0], p[1], p[2], p[3]], lens: problem.lens_of(&p), rms_px, views: per_view, dropped: Vec::new() }
}

#[cfg(test)]
mod tests;
