//! PLY point clouds: the surfel map (`map.ply`) and ground-truth surfaces.
//!
//! Written as binary little-endian with `x y z nx ny nz red green blue` (what Open3D, MeshLab
//! and CloudCompare read) plus `confidence radius t0 t albedo sigma warp_x warp_y warp_z` (`sigma`: the surfel's depth σ in
//! metres, 0 where its depth carried none; `warp_*`: the displacement the trackers' warps gave it
//! since its creation, metres). The reader takes ASCII or binary
//! little-endian files with any scalar properties of the vertex element and fills what it
//! finds (normals, colour and surfel attributes are optional).

use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::Path;

use nalgebra::{Point3, Vector3};

use capsule_slam_framework::error::LoadError;
use capsule_slam_framework::map::{Surfel, SurfelSet};

/// Writes surfels as a binary PLY, atomically (temporary file renamed over the target).
pub fn write_surfels(path: &Path, set: &SurfelSet) -> Result<(), LoadError> {
    let tmp = path.with_extension("ply.tmp");
    let io = |e| LoadError::io(&tmp, e);
    let mut f = BufWriter::new(std::fs::File::create(&tmp).map_err(io)?);
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment capsule-slam surfel map (metres, world frame)\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float confidence\nproperty float radius\n\
         property uint t0\nproperty uint t\nproperty float albedo\nproperty float sigma\n\
         property float warp_x\nproperty float warp_y\nproperty float warp_z\nend_header\n",
        set.len()
    );
    f.write_all(header.as_bytes()).map_err(io)?;
    for s in &set.surfels {
        for v in [s.position_m.x, s.position_m.y, s.position_m.z, s.normal.x, s.normal.y, s.normal.z] {
            f.write_all(&v.to_le_bytes()).map_err(io)?;
        }
        f.write_all(&s.colour).map_err(io)?;
        f.write_all(&s.confidence.to_le_bytes()).map_err(io)?;
        f.write_all(&s.radius_m.to_le_bytes()).map_err(io)?;
        f.write_all(&s.t0.to_le_bytes()).map_err(io)?;
        f.write_all(&s.t.to_le_bytes()).map_err(io)?;
        f.write_all(&s.albedo.to_le_bytes()).map_err(io)?;
        f.write_all(&s.sigma_m.to_le_bytes()).map_err(io)?;
        for v in [s.warp_m.x, s.warp_m.y, s.warp_m.z] {
            f.write_all(&v.to_le_bytes()).map_err(io)?;
        }
    }
    f.flush().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| LoadError::io(path, e))
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    fn read_le(self, b: &[u8]) -> f64 {
        match self {
            Self::I8 => f64::from(b[0] as i8),
            Self::U8 => f64::from(b[0]),
            Self::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Self::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Self::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Self::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Self::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Self::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
        }
    }
}

/// Reads the vertices of a PLY file as surfels (missing attributes: zero normal, grey colour,
/// confidence 1, radius 0, times 0, albedo 0, σ 0, warp 0). The set keeps file order; use [`SurfelSet::new`] to sort.
pub fn read_surfels(path: &Path) -> Result<SurfelSet, LoadError> {
    let file = std::fs::File::open(path).map_err(|e| LoadError::io(path, e))?;
    let mut r = Lines { path, reader: BufReader::new(file), line: String::new(), number: 0 };
    let header = read_header(&mut r)?;
    let props = &header.props;
    let idx = |n: &str| props.iter().position(|p| p.0 == n);
    let (ix, iy, iz) = match (idx("x"), idx("y"), idx("z")) {
        (Some(a), Some(b), Some(c)) => (a, b, c),
        _ => return Err(r.bad(0, "the vertex element has no x, y, z properties")),
    };
    let opt = [
        idx("nx"),
        idx("ny"),
        idx("nz"),
        idx("red"),
        idx("green"),
        idx("blue"),
        idx("confidence"),
        idx("radius"),
        idx("t0"),
        idx("t"),
        idx("albedo"),
        idx("sigma"),
        idx("warp_x"),
        idx("warp_y"),
        idx("warp_z"),
    ];
    let mut vals = vec![0.0f64; props.len()];
    let mut out = Vec::with_capacity(header.n_vertex);
    let stride: usize = props.iter().map(|p| p.1.size()).sum();
    let mut buf = vec![0u8; stride];
    for v in 0..header.n_vertex {
        if header.binary {
            r.reader.read_exact(&mut buf).map_err(|_| r.bad(0, format!("file ends at vertex {v} of {}", header.n_vertex)))?;
            let mut off = 0;
            for (k, p) in props.iter().enumerate() {
                vals[k] = p.1.read_le(&buf[off..off + p.1.size()]);
                off += p.1.size();
            }
        } else {
            read_ascii_vertex(&mut r, props.len(), &mut vals)?;
        }
        let g = |i: Option<usize>, d: f64| i.map_or(d, |i| vals[i]);
        out.push(Surfel {
            position_m: Point3::new(vals[ix] as f32, vals[iy] as f32, vals[iz] as f32),
            normal: Vector3::new(g(opt[0], 0.0) as f32, g(opt[1], 0.0) as f32, g(opt[2], 0.0) as f32),
            colour: [g(opt[3], 128.0) as u8, g(opt[4], 128.0) as u8, g(opt[5], 128.0) as u8],
            confidence: g(opt[6], 1.0) as f32,
            radius_m: g(opt[7], 0.0) as f32,
            t0: g(opt[8], 0.0) as u32,
            t: g(opt[9], 0.0) as u32,
            albedo: g(opt[10], 0.0) as f32,
            sigma_m: g(opt[11], 0.0) as f32,
            warp_m: Vector3::new(g(opt[12], 0.0) as f32, g(opt[13], 0.0) as f32, g(opt[14], 0.0) as f32),
        });
    }
    Ok(SurfelSet { surfels: out })
}

/// A PLY file read line by line, counting lines for messages.
struct Lines<'a> {
    path: &'a Path,
    reader: BufReader<std::fs::File>,
    line: String,
    number: usize,
}

impl Lines<'_> {
    fn next(&mut self) -> Result<&str, LoadError> {
        self.line.clear();
        self.number += 1;
        self.reader.read_line(&mut self.line).map_err(|e| LoadError::io(self.path, e))?;
        Ok(&self.line)
    }

    fn bad(&self, line: usize, message: impl Into<String>) -> LoadError {
        LoadError::parse(self.path, line, message)
    }
}

/// What the header says of the vertices.
struct Header {
    binary: bool,
    n_vertex: usize,
    props: Vec<(String, Scalar)>,
}

/// Reads the header up to `end_header`: the format and the vertex element's properties (other
/// elements after `vertex` are ignored).
fn read_header(r: &mut Lines) -> Result<Header, LoadError> {
    if r.next()?.trim() != "ply" {
        return Err(r.bad(1, "not a PLY file (first line is not `ply`)"));
    }
    let mut h = Header { binary: false, n_vertex: 0, props: Vec::new() };
    let (mut in_vertex, mut seen_vertex) = (false, false);
    loop {
        let line = r.next()?.to_owned();
        let n = r.number;
        if line.is_empty() {
            return Err(r.bad(n, "end of file inside the header (no `end_header`)"));
        }
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.as_slice() {
            ["end_header"] => return Ok(h),
            ["format", "ascii", _] => h.binary = false,
            ["format", "binary_little_endian", _] => h.binary = true,
            ["format", f, _] => return Err(r.bad(n, format!("unsupported PLY format `{f}` (ascii or binary_little_endian)"))),
            ["element", name, count] => {
                if seen_vertex {
                    in_vertex = false;
                    continue;
                }
                if *name != "vertex" {
                    return Err(r.bad(n, format!("element `{name}` before `vertex` is not supported")));
                }
                h.n_vertex = count.parse().map_err(|_| r.bad(n, format!("bad vertex count `{count}`")))?;
                in_vertex = true;
                seen_vertex = true;
            }
            ["property", "list", ..] if in_vertex => return Err(r.bad(n, "list properties on vertices are not supported")),
            ["property", ty, name] if in_vertex => {
                let s = Scalar::parse(ty).ok_or_else(|| r.bad(n, format!("unknown property type `{ty}`")))?;
                h.props.push(((*name).to_owned(), s));
            }
            _ => {}
        }
    }
}

/// One ASCII vertex line into `vals`.
fn read_ascii_vertex(r: &mut Lines, n_props: usize, vals: &mut [f64]) -> Result<(), LoadError> {
    let line = r.next()?.to_owned();
    let n = r.number;
    let w: Vec<&str> = line.split_whitespace().collect();
    if w.len() < n_props {
        return Err(r.bad(n, format!("expected {n_props} values, found {}", w.len())));
    }
    for k in 0..n_props {
        vals[k] = w[k].parse().map_err(|_| r.bad(n, format!("`{}` is not a number", w[k])))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_points_only() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.ply");
        std::fs::write(&p, "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n1 2 3\n4 5 6\n").unwrap();
        let s = read_surfels(&p).unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(s.surfels[1].position_m, Point3::new(4.0, 5.0, 6.0));
    }

    #[test]
    fn truncated_binary_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.ply");
        std::fs::write(
            &p,
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0",
        )
        .unwrap();
        let e = read_surfels(&p).unwrap_err().to_string();
        assert!(e.contains("vertex 0 of 3"), "{e}");
    }
}
