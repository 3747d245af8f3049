//! Checkerboard corners in an image, by the `calib-targets` crate (ChESS X-junction corners,
//! Bennett & Lasenby 2014, grown into a labelled grid whose every corner is checked against its
//! neighbours; robust to lens distortion and blur). A corner labelled `(i, j)` lies at
//! `(i, j) × square` on the board; a grid larger than the board is refused (a false grid).

use calib_targets::chessboard::ChessboardParams;
use calib_targets::detect;
use capsule_slam_framework::image::{GrayF32, Rgb8, gray_from_rgb};
use nalgebra::Point2;

use crate::camera_fit::{BoardCorner, BoardView};

/// The board: inner corners along its two sides, and the square's side.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Board {
    /// Inner corners along one side (OpenCV's pattern size).
    pub cols: usize,
    /// Inner corners along the other side.
    pub rows: usize,
    /// Side of a square, metres.
    pub square_m: f64,
}

/// Why an image gave no view.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoardError {
    /// The detector found no grid.
    #[error("no checkerboard found")]
    NotFound,
    /// The grid found is larger than the board.
    #[error("a {found_cols}×{found_rows} grid of corners was found, larger than the {cols}×{rows} board: a false grid, or give --board")]
    TooLarge {
        /// Found along one side.
        found_cols: usize,
        /// Found along the other.
        found_rows: usize,
        /// The board's.
        cols: usize,
        /// The board's.
        rows: usize,
    },
}

/// The board's corners in `img` (named `name` in messages).
pub fn detect_board(img: &Rgb8, board: &Board, name: &str) -> Result<BoardView, BoardError> {
    let gray = gray_from_rgb(img);
    let (w, h) = img.size();
    let bytes: Vec<u8> = gray.data().iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect();
    let image = calib_targets::image::GrayImage::from_raw(w as u32, h as u32, bytes).ok_or(BoardError::NotFound)?;
    let found = detect::detect_chessboard(&image, &detect::default_chess_config(), &ChessboardParams::default()).map_err(|_| BoardError::NotFound)?;
    if found.corners.is_empty() {
        return Err(BoardError::NotFound);
    }
    let span = |f: fn(&calib_targets::chessboard::ChessboardCorner) -> i32| {
        let (lo, hi) = found.corners.iter().map(f).fold((i32::MAX, i32::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
        (hi - lo + 1) as usize
    };
    let (si, sj) = (span(|c| c.grid.u), span(|c| c.grid.v));
    let fits = (si <= board.cols && sj <= board.rows) || (si <= board.rows && sj <= board.cols);
    if !fits {
        return Err(BoardError::TooLarge { found_cols: si, found_rows: sj, cols: board.cols, rows: board.rows });
    }
    // The refinement window: under half a square, so it holds one X-junction.
    let half = (0.3 * f64::from(found.cell_size.unwrap_or(10.0))).clamp(2.0, 6.0) as i64;
    let corners = found
        .corners
        .iter()
        .map(|c| BoardCorner {
            board_m: Point2::new(f64::from(c.grid.u) * board.square_m, f64::from(c.grid.v) * board.square_m),
            pixel: refine_corner(&gray, Point2::new(f64::from(c.position.x), f64::from(c.position.y)), half),
        })
        .collect();
    Ok(BoardView { name: name.to_owned(), corners })
}

/// Sub-pixel refinement of an X-junction (Förstner & Gülch 1987; OpenCV's `cornerSubPix`): at
/// the corner `q`, every image gradient `g` at a point `p` nearby is orthogonal to `p − q`, so
/// `q = (Σ w g gᵀ)⁻¹ Σ w g gᵀ p` over a window of `2 half + 1` pixels (Gaussian weights),
/// iterated until it moves less than 0.005 px. A window the gradients do not pin, or a corner
/// that leaves it, keeps the detector's position.
pub fn refine_corner(gray: &GrayF32, start: Point2<f64>, half: i64) -> Point2<f64> {
    let (w, h) = (gray.width() as i64, gray.height() as i64);
    let at = |x: i64, y: i64| f64::from(gray.at(x.clamp(0, w - 1) as usize, y.clamp(0, h - 1) as usize));
    let sigma2 = (half as f64 * 0.75).powi(2);
    let mut q = start;
    for _ in 0..20 {
        let (cx, cy) = (q.x.round() as i64, q.y.round() as i64);
        let (mut a, mut b) = (nalgebra::Matrix2::<f64>::zeros(), nalgebra::Vector2::<f64>::zeros());
        for y in cy - half..=cy + half {
            for x in cx - half..=cx + half {
                if x < 1 || y < 1 || x >= w - 1 || y >= h - 1 {
                    continue;
                }
                let g = nalgebra::Vector2::new(at(x + 1, y) - at(x - 1, y), at(x, y + 1) - at(x, y - 1)) * 0.5;
                let d2 = (x as f64 - q.x).powi(2) + (y as f64 - q.y).powi(2);
                let ggt = g * g.transpose() * (-d2 / (2.0 * sigma2)).exp();
                a += ggt;
                b += ggt * nalgebra::Vector2::new(x as f64, y as f64);
            }
        }
        let Some(next) = a.try_inverse().map(|inv| inv * b) else { return start };
        let next = Point2::new(next.x, next.y);
        if !(next.x.is_finite() && next.y.is_finite()) || (next - start).norm() > half as f64 {
            return start;
        }
        let moved = (next - q).norm();
        q = next;
        if moved < 0.005 {
            break;
        }
    }
    q
}
