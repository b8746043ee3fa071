//! STL decoding. ASCII goes through `stl_io`; binary STL is decoded here after the size
//! check, because `stl_io` picks its ASCII reader for any file whose 80-byte header starts
//! with `solid `, which many binary exporters write.
//!
//! Both produce an unindexed mesh (three fresh vertices per triangle); [`super::repair`]
//! merges coincident vertices.

use super::{Mesh, MeshError, MeshLimits};
use glam::DVec3;
use std::borrow::Cow;

const HEADER: usize = 84;
const RECORD: usize = 50;

/// Does the length equal 84 + 50 × the count in the header?
pub(super) fn binary_size_matches(bytes: &[u8]) -> bool {
    if bytes.len() < HEADER {
        return false;
    }
    let count = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as u64;
    HEADER as u64 + RECORD as u64 * count == bytes.len() as u64
}

/// Plain printable text in the first kilobyte (ASCII STL), as opposed to binary.
pub(super) fn looks_like_text(bytes: &[u8]) -> bool {
    bytes
        .iter()
        .take(1024)
        .all(|&b| b.is_ascii_graphic() || b.is_ascii_whitespace())
}

pub(super) fn load_binary(bytes: &[u8], limits: &MeshLimits) -> Result<Mesh, MeshError> {
    let size = bytes.len() as u64;
    if bytes.len() < HEADER {
        return Err(MeshError::StlTruncatedHeader { size });
    }
    let declared = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as u64;
    let expected = HEADER as u64 + RECORD as u64 * declared;
    if expected != size {
        return Err(MeshError::StlCountMismatch {
            declared,
            expected,
            size,
        });
    }
    if declared == 0 {
        return Err(MeshError::NoTriangles);
    }
    if declared > limits.max_triangles_checked() {
        return Err(MeshError::TooManyTriangles {
            count: declared,
            limit: limits.max_triangles,
        });
    }
    let n = declared as usize;
    let mut mesh = Mesh {
        vertices: Vec::with_capacity(3 * n),
        triangles: Vec::with_capacity(n),
    };
    for (t, rec) in bytes[HEADER..].chunks_exact(RECORD).enumerate() {
        for corner in 0..3 {
            let off = 12 + 12 * corner;
            let f = |k: usize| {
                let o = off + 4 * k;
                f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]]) as f64
            };
            let v = DVec3::new(f(0), f(1), f(2));
            if !v.is_finite() {
                return Err(MeshError::NotFinite {
                    format: "binary STL",
                    triangle: t as u64,
                    corner,
                    at: Some(format!("byte offset {}", HEADER + t * RECORD + off)),
                });
            }
            mesh.vertices.push(v);
        }
        let b = 3 * t as u32;
        mesh.triangles.push([b, b + 1, b + 2]);
    }
    Ok(mesh)
}

pub(super) fn load_ascii(bytes: &[u8], limits: &MeshLimits) -> Result<Mesh, MeshError> {
    // stl_io wants "solid <name>"; accept a bare "solid" line too.
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(0);
    let body = &bytes[start..];
    let first_line_end = body.iter().position(|&b| b == b'\n').unwrap_or(body.len());
    let first = String::from_utf8_lossy(&body[..first_line_end]);
    let text: Cow<[u8]> = if first.trim_end() == "solid" {
        let mut v = b"solid unnamed".to_vec();
        v.extend_from_slice(&body[first_line_end..]);
        Cow::Owned(v)
    } else {
        Cow::Borrowed(body)
    };
    let mut cursor = std::io::Cursor::new(text.as_ref());
    let reader = stl_io::create_stl_reader(&mut cursor).map_err(|e| MeshError::StlAscii {
        message: e.to_string(),
        triangles_read: 0,
    })?;
    let mut mesh = Mesh::default();
    for (t, tri) in reader.enumerate() {
        let tri = tri.map_err(|e| MeshError::StlAscii {
            message: e.to_string(),
            triangles_read: t as u64,
        })?;
        if t as u64 >= limits.max_triangles_checked() {
            return Err(MeshError::TooManyTriangles {
                count: t as u64 + 1,
                limit: limits.max_triangles,
            });
        }
        for (corner, v) in tri.vertices.iter().enumerate() {
            let v = DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64);
            if !v.is_finite() {
                return Err(MeshError::NotFinite {
                    format: "ASCII STL",
                    triangle: t as u64,
                    corner,
                    at: None,
                });
            }
            mesh.vertices.push(v);
        }
        let b = 3 * t as u32;
        mesh.triangles.push([b, b + 1, b + 2]);
    }
    if mesh.triangles.is_empty() {
        return Err(MeshError::NoTriangles);
    }
    Ok(mesh)
}
