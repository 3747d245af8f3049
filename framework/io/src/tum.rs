//! The TUM RGB-D benchmark's text files (Sturm et al. 2012, "A benchmark for the evaluation of
//! RGB-D SLAM systems", IROS): `rgb.txt` / `depth.txt` (`timestamp filename`) and trajectories
//! (`timestamp tx ty tz qx qy qz qw`), with `#` comments.

use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, Translation3, UnitQuaternion};

use capsule_slam_framework::error::LoadError;
use capsule_slam_framework::geometry::{Iso3, StampedPose};

/// One line of `rgb.txt` or `depth.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct ListEntry {
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// File name relative to the dataset folder.
    pub file: PathBuf,
}

fn lines(path: &Path) -> Result<Vec<(usize, String)>, LoadError> {
    let text = std::fs::read_to_string(path).map_err(|e| LoadError::io(path, e))?;
    Ok(text.lines().enumerate().map(|(i, l)| (i + 1, l.trim().to_owned())).filter(|(_, l)| !l.is_empty() && !l.starts_with('#')).collect())
}

fn timestamp(path: &Path, line: usize, word: &str) -> Result<f64, LoadError> {
    word.parse::<f64>().ok().filter(|t| t.is_finite()).ok_or_else(|| LoadError::parse(path, line, format!("expected a timestamp in seconds, found `{word}`")))
}

/// Reads `rgb.txt` or `depth.txt`, sorted by timestamp.
pub fn read_list(path: &Path) -> Result<Vec<ListEntry>, LoadError> {
    let mut out = Vec::new();
    for (n, l) in lines(path)? {
        let mut w = l.split_whitespace();
        let (Some(t), Some(f), None) = (w.next(), w.next(), w.next()) else {
            return Err(LoadError::parse(path, n, format!("expected `timestamp filename`, found `{l}`")));
        };
        out.push(ListEntry { timestamp_s: timestamp(path, n, t)?, file: PathBuf::from(f) });
    }
    out.sort_by(|a, b| a.timestamp_s.total_cmp(&b.timestamp_s));
    Ok(out)
}

/// Reads a TUM trajectory (e.g. `groundtruth.txt`), sorted by timestamp. Quaternions are
/// normalised; a zero quaternion is an error.
pub fn read_trajectory(path: &Path) -> Result<Vec<StampedPose>, LoadError> {
    let mut out = Vec::new();
    for (n, l) in lines(path)? {
        let w: Vec<&str> = l.split_whitespace().collect();
        if w.len() != 8 {
            return Err(LoadError::parse(path, n, format!("expected 8 values `timestamp tx ty tz qx qy qz qw`, found {}", w.len())));
        }
        let mut v = [0.0; 8];
        for (k, s) in w.iter().enumerate() {
            v[k] = s
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| LoadError::parse(path, n, format!("value {} is not a finite number: `{s}`", k + 1)))?;
        }
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if q.norm() < 1e-9 {
            return Err(LoadError::parse(path, n, "the quaternion qx qy qz qw is zero"));
        }
        let t_world_cam = Iso3::from_parts(Translation3::new(v[1], v[2], v[3]), UnitQuaternion::from_quaternion(q));
        out.push(StampedPose { timestamp_s: v[0], t_world_cam });
    }
    out.sort_by(|a, b| a.timestamp_s.total_cmp(&b.timestamp_s));
    Ok(out)
}

/// Formats one trajectory line.
pub fn format_pose(p: &StampedPose) -> String {
    let t = p.t_world_cam.translation.vector;
    let q = p.t_world_cam.rotation;
    format!("{:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}", p.timestamp_s, t.x, t.y, t.z, q.i, q.j, q.k, q.w)
}

/// Writes a whole trajectory atomically (a temporary file renamed over the target), so a
/// reader never sees a half-written file.
pub fn write_trajectory(path: &Path, poses: &[StampedPose]) -> Result<(), LoadError> {
    let tmp = path.with_extension("txt.tmp");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(|e| LoadError::io(&tmp, e))?);
    writeln!(f, "# timestamp tx ty tz qx qy qz qw").map_err(|e| LoadError::io(&tmp, e))?;
    for p in poses {
        writeln!(f, "{}", format_pose(p)).map_err(|e| LoadError::io(&tmp, e))?;
    }
    f.flush().map_err(|e| LoadError::io(&tmp, e))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| LoadError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trajectory_roundtrip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.txt");
        let poses: Vec<StampedPose> = (0..5)
            .map(|i| StampedPose {
                timestamp_s: i as f64 * 0.1,
                t_world_cam: capsule_slam_framework::geometry::exp_se3(&nalgebra::Vector6::new(0.01 * i as f64, 0.002, -0.003, 0.1, 0.2 * i as f64, -0.3)),
            })
            .collect();
        write_trajectory(&p, &poses).unwrap();
        let back = read_trajectory(&p).unwrap();
        assert_eq!(back.len(), 5);
        for (a, b) in poses.iter().zip(&back) {
            assert!((a.timestamp_s - b.timestamp_s).abs() < 1e-6);
            assert!((a.t_world_cam.translation.vector - b.t_world_cam.translation.vector).norm() < 1e-8);
            assert!(a.t_world_cam.rotation.angle_to(&b.t_world_cam.rotation) < 1e-8);
        }
    }
}
