//! Image files: colour (PNG, JPEG, BMP) and 16-bit depth PNGs.

use std::path::Path;

use image::{DynamicImage, ImageBuffer, Luma, Rgb};

use capsule_slam_framework::error::LoadError;
use capsule_slam_framework::image::{DepthMap, Rgb8};

fn open(path: &Path) -> Result<DynamicImage, LoadError> {
    if !path.exists() {
        return Err(LoadError::Image { path: path.to_owned(), message: "file not found".into() });
    }
    image::open(path).map_err(|e| LoadError::Image { path: path.to_owned(), message: format!("cannot decode: {e}") })
}

fn check_size(path: &Path, found: (u32, u32), expected: Option<(usize, usize)>) -> Result<(), LoadError> {
    match expected {
        Some((w, h)) if (found.0 as usize, found.1 as usize) != (w, h) => {
            Err(LoadError::Image { path: path.to_owned(), message: format!("image is {}×{}, but camera.toml says {w}×{h}", found.0, found.1) })
        }
        _ => Ok(()),
    }
}

/// File extensions read as images (any case).
pub const IMAGE_EXTENSIONS: [&str; 4] = ["png", "jpg", "jpeg", "bmp"];

/// The image files (PNG, JPEG, BMP) of a folder, sorted by name.
pub fn list_images(dir: &Path) -> Result<Vec<std::path::PathBuf>, LoadError> {
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| LoadError::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().and_then(|e| e.to_str()).is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str())))
        .collect();
    files.sort();
    Ok(files)
}

/// Checks an image's size from its header alone (without decoding it).
pub fn check_dimensions(path: &Path, expected: (usize, usize)) -> Result<(), LoadError> {
    if !path.exists() {
        return Err(LoadError::Image { path: path.to_owned(), message: "file not found".into() });
    }
    let found = image::image_dimensions(path).map_err(|e| LoadError::Image { path: path.to_owned(), message: format!("cannot read the image header: {e}") })?;
    check_size(path, found, Some(expected))
}

/// Reads a colour image (grey images are expanded to RGB), checking its size if given.
pub fn read_rgb(path: &Path, expected: Option<(usize, usize)>) -> Result<Rgb8, LoadError> {
    let img = open(path)?;
    check_size(path, (img.width(), img.height()), expected)?;
    let rgb = img.to_rgb8();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    Rgb8::from_vec(w, h, rgb.into_raw()).map_err(|e| LoadError::Image { path: path.to_owned(), message: e.to_string() })
}

/// Reads a 16-bit grey depth PNG and converts it to metres (`value / depth_scale`, 0 stays
/// invalid). Anything but 16-bit grey is rejected: an 8-bit depth image has lost its range.
pub fn read_depth(path: &Path, depth_scale: f64, expected: Option<(usize, usize)>) -> Result<DepthMap, LoadError> {
    let img = open(path)?;
    check_size(path, (img.width(), img.height()), expected)?;
    let DynamicImage::ImageLuma16(buf) = img else {
        return Err(LoadError::Image { path: path.to_owned(), message: format!("expected a 16-bit grey PNG depth image, found {:?}", img.color()) });
    };
    let (w, h) = (buf.width() as usize, buf.height() as usize);
    let scale = 1.0 / depth_scale;
    let data = buf.into_raw().into_iter().map(|v| (f64::from(v) * scale) as f32).collect();
    DepthMap::from_vec(w, h, data).map_err(|e| LoadError::Image { path: path.to_owned(), message: e.to_string() })
}

/// Writes a colour PNG.
pub fn write_rgb(path: &Path, img: &Rgb8) -> Result<(), LoadError> {
    let buf: ImageBuffer<Rgb<u8>, Vec<u8>> = ImageBuffer::from_raw(img.width() as u32, img.height() as u32, img.data().to_vec())
        .ok_or_else(|| LoadError::Image { path: path.to_owned(), message: "buffer size mismatch".into() })?;
    buf.save(path).map_err(|e| LoadError::Image { path: path.to_owned(), message: format!("cannot write: {e}") })
}

/// Writes a 16-bit depth PNG (`round(depth_m × depth_scale)`, clamped to 65535; invalid = 0).
pub fn write_depth(path: &Path, depth: &DepthMap, depth_scale: f64) -> Result<(), LoadError> {
    let data: Vec<u16> =
        depth.data().iter().map(|d| if d.is_finite() && *d > 0.0 { (f64::from(*d) * depth_scale).round().clamp(0.0, 65535.0) as u16 } else { 0 }).collect();
    let buf: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_raw(depth.width() as u32, depth.height() as u32, data)
        .ok_or_else(|| LoadError::Image { path: path.to_owned(), message: "buffer size mismatch".into() })?;
    buf.save(path).map_err(|e| LoadError::Image { path: path.to_owned(), message: format!("cannot write: {e}") })
}

/// Writes an 8-bit grey PNG.
pub fn write_gray(path: &Path, img: &capsule_slam_framework::image::Gray8) -> Result<(), LoadError> {
    let buf: ImageBuffer<Luma<u8>, Vec<u8>> = ImageBuffer::from_raw(img.width() as u32, img.height() as u32, img.data().to_vec())
        .ok_or_else(|| LoadError::Image { path: path.to_owned(), message: "buffer size mismatch".into() })?;
    buf.save(path).map_err(|e| LoadError::Image { path: path.to_owned(), message: format!("cannot write: {e}") })
}

/// Reads an 8-bit grey PNG (any image is converted to grey).
pub fn read_gray(path: &Path, expected: Option<(usize, usize)>) -> Result<capsule_slam_framework::image::Gray8, LoadError> {
    let img = open(path)?;
    check_size(path, (img.width(), img.height()), expected)?;
    let g = img.to_luma8();
    let (w, h) = (g.width() as usize, g.height() as usize);
    capsule_slam_framework::image::Gray8::from_vec(w, h, g.into_raw()).map_err(|e| LoadError::Image { path: path.to_owned(), message: e.to_string() })
}

/// Writes a float image as a 16-bit grey PNG (`round(value × scale)`, clamped).
pub fn write_gray16(path: &Path, img: &capsule_slam_framework::image::GrayF32, scale: f64) -> Result<(), LoadError> {
    let data: Vec<u16> = img.data().iter().map(|v| (f64::from(*v) * scale).round().clamp(0.0, 65535.0) as u16).collect();
    let buf: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_raw(img.width() as u32, img.height() as u32, data)
        .ok_or_else(|| LoadError::Image { path: path.to_owned(), message: "buffer size mismatch".into() })?;
    buf.save(path).map_err(|e| LoadError::Image { path: path.to_owned(), message: format!("cannot write: {e}") })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_roundtrip_and_type_check() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.png");
        let d = DepthMap::from_fn(4, 3, |x, y| [0.01 * (x + y) as f32]);
        write_depth(&p, &d, 5000.0).unwrap();
        let back = read_depth(&p, 5000.0, Some((4, 3))).unwrap();
        for (a, b) in d.data().iter().zip(back.data()) {
            assert!((a - b).abs() <= 0.5 / 5000.0 + 1e-7);
        }
        let e = read_depth(&p, 5000.0, Some((5, 3))).unwrap_err().to_string();
        assert!(e.contains("4×3") && e.contains("5×3"), "{e}");
        let c = dir.path().join("c.png");
        write_rgb(&c, &Rgb8::new(4, 3)).unwrap();
        let e = read_depth(&c, 5000.0, None).unwrap_err().to_string();
        assert!(e.contains("16-bit"), "{e}");
        assert!(read_rgb(&dir.path().join("missing.png"), None).unwrap_err().to_string().contains("not found"));
    }
}
