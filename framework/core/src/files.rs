//! The calibration files beside a sequence, read and written with their TOML schemas:
//! `camera.toml` ([`CameraFile`]), `light.toml` ([`LightModel`]) and `vignetting.toml`
//! ([`VignettingFile`]). They are contracts: a plugin reads the calibration it needs when it is
//! built. Unknown keys and invalid values are errors naming the file, the line and the fix.

use std::path::Path;

use crate::camera::CameraFile;
use crate::error::LoadError;
use crate::light::LightModel;
use crate::light::vignetting::VignettingFile;

/// Reads a `camera.toml`, rejecting unknown keys and invalid values with the file's name.
pub fn read_camera_file(path: &Path) -> Result<CameraFile, LoadError> {
    let text = std::fs::read_to_string(path).map_err(|e| LoadError::io(path, e))?;
    let cam: CameraFile = toml::from_str(&text).map_err(|e| {
        let line = e.span().map_or(0, |s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        LoadError::parse(
            path,
            line,
            format!("{} (expected keys: width, height, fx, fy, cx, cy, and optionally depth_scale, distortion = [k1, k2, p1, p2, k3] or {{ model = \"radial-tangential\" | \"equidistant\", coefficients = [...] }}, fov_radius_px, baseline_m, depth_noise, and a [right] table: fx, fy, cx, cy, rotation, translation_m, optionally distortion, fov_radius_px)", e.message()),
        )
    })?;
    let problems = cam.problems("");
    every_problem(path, problems.iter().map(|p| format!("{}: {} (fix: {})", p.key, p.message, p.fix)))?;
    Ok(cam)
}

/// One error naming the file with every problem of its content, or none.
fn every_problem(path: &Path, problems: impl Iterator<Item = String>) -> Result<(), LoadError> {
    let all: Vec<String> = problems.collect();
    if all.is_empty() { Ok(()) } else { Err(LoadError::parse(path, 0, all.join("; "))) }
}

/// Writes a `camera.toml`.
pub fn write_camera_file(path: &Path, cam: &CameraFile) -> Result<(), LoadError> {
    let text = toml::to_string(cam).map_err(|e| LoadError::parse(path, 0, e.to_string()))?;
    std::fs::write(path, text).map_err(|e| LoadError::io(path, e))
}

/// Reads a `light.toml`, rejecting unknown keys and invalid values with the file's name.
pub fn read_light_file(path: &Path) -> Result<LightModel, LoadError> {
    let text = std::fs::read_to_string(path).map_err(|e| LoadError::io(path, e))?;
    let light: LightModel = toml::from_str(&text).map_err(|e| {
        let line = e.span().map_or(0, |s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        LoadError::parse(path, line, format!("{} (expected keys: gain, ref_distance_m, ambient, gamma, position_m, spot_exponent, vignetting)", e.message()))
    })?;
    every_problem(path, light.problems().iter().map(|(k, m)| format!("{k}: {m}")))?;
    Ok(light)
}

/// Writes a `light.toml` with the model's formula as a header comment.
pub fn write_light_file(path: &Path, light: &LightModel) -> Result<(), LoadError> {
    let body = toml::to_string(light).map_err(|e| LoadError::parse(path, 0, e.to_string()))?;
    let header = "# linear pixel = V(u) * albedo * (gain * cos(incidence) * (ref_distance_m / distance_m)^2 * spot + ambient), then gamma-encoded\n\
                  # V = 1 + v1 r^2 + v2 r^4 (+ v3 r^6), r = pixel distance to (cx, cy) / half-diagonal; spot = cos(angle to the optical axis)^spot_exponent\n";
    std::fs::write(path, format!("{header}{body}")).map_err(|e| LoadError::io(path, e))
}

/// Reads and validates a `vignetting.toml`; errors name the file, the line and the fix.
pub fn read_vignetting_file(path: &Path) -> Result<VignettingFile, LoadError> {
    let text = std::fs::read_to_string(path).map_err(|e| LoadError::io(path, e))?;
    let file: VignettingFile = toml::from_str(&text).map_err(|e| {
        let line = e.span().map_or(0, |s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        LoadError::parse(path, line, format!("{} (expected keys: gamma, lens_and_light; `capsule-slam calibrate-vignetting` writes this file)", e.message()))
    })?;
    every_problem(path, file.problems().iter().map(|(k, m)| format!("{k}: {m}")))?;
    Ok(file)
}

/// Writes a `vignetting.toml` with the profiles' formula as a header comment.
pub fn write_vignetting_file(path: &Path, file: &VignettingFile) -> Result<(), LoadError> {
    let body = toml::to_string(file).map_err(|e| LoadError::parse(path, 0, e.to_string()))?;
    let header = "# F = 1 + c1 r^2 + c2 r^4 + c3 r^6, r = pixel distance to (cx, cy) / half-diagonal; pixel = linear^(1/gamma)\n\
                  # lens_and_light: lens vignetting x LED profile (divide for near-light shape from shading);\n\
                  # the flat field (divide for Tsai-Shah) is lens_and_light x cos^3(ray angle), what a flat target facing the capsule shows\n";
    std::fs::write(path, format!("{header}{body}")).map_err(|e| LoadError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_file_roundtrip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("camera.toml");
        std::fs::write(&p, "width = 320\nheight = 320\nfx = 160.0\nfy = 160.0\ncx = 159.5\ncy = 159.5\nfov_radius_px = 150.0\n").unwrap();
        let c = read_camera_file(&p).unwrap();
        assert_eq!(c.depth_scale, 5000.0);
        assert_eq!(c.fov_radius_px, Some(150.0));
        write_camera_file(&p, &c).unwrap();
        assert_eq!(read_camera_file(&p).unwrap(), c);

        std::fs::write(&p, "width = 320\nheight = 320\nfx = 160.0\nfy = 160.0\ncx = 159.5\ncy = 159.5\nfocal = 3\n").unwrap();
        let e = read_camera_file(&p).unwrap_err().to_string();
        assert!(e.contains("camera.toml:7") && e.contains("focal"), "{e}");

        std::fs::write(&p, "width = 320\nheight = 320\nfx = 0.0\nfy = 160.0\ncx = 159.5\ncy = 159.5\n").unwrap();
        let e = read_camera_file(&p).unwrap_err().to_string();
        assert!(e.contains("fx"), "{e}");

        // Every problem at once, and a whole-file problem shows no line 0.
        std::fs::write(&p, "width = 0\nheight = 320\nfx = 0.0\nfy = 160.0\ncx = 159.5\ncy = 159.5\ndepth_scale = -1.0\n").unwrap();
        let e = read_camera_file(&p).unwrap_err().to_string();
        assert!(e.contains("width") && e.contains("fx") && e.contains("depth_scale") && !e.contains(":0"), "{e}");
    }
}
