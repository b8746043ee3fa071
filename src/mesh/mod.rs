//! Triangle meshes in: load a part from STL (binary or ASCII) or 3MF bytes, check that it
//! can be sliced soundly, repair what is safe to repair, and say what was found and done.
//!
//! Pipeline (ARCHITECTURE.md, stage `mesh`):
//!
//! 1. [`load_bytes`] sniffs the format and decodes it into an indexed [`Mesh`] (millimetres,
//!    Z the build direction). Sizes are checked against [`MeshLimits`] *before* anything
//!    proportional to the input is allocated; every malformed input is a [`MeshError`] that
//!    names what is wrong and where (byte offset, line, 3MF element), never a panic.
//! 2. [`repair`] merges coincident vertices, drops degenerate and duplicate triangles, makes
//!    face orientation consistent across shared edges, and returns the repaired mesh with a
//!    [`MeshReport`] (counts before repair and what was done). Open edges are not patched
//!    here: the slicer closes small gaps per layer (see `docs/mesh-and-slicing.md`) and
//!    refuses the rest naming the layer and the xy of the open loop.
//!
//! File access is kept out of the core: [`path::load_path`] is the one thin helper the
//! binaries call.

pub mod orient;
pub mod path;
pub mod primitives;
mod repair;
pub(crate) use repair::edge_uses;
mod stl;
mod threemf;

pub use repair::{repair, MeshReport, RepairOptions};

use glam::DVec3;
use serde::Serialize;

/// An indexed triangle mesh, millimetres, Z up (the build direction).
///
/// Triangles index `vertices`; with consistent orientation the vertex order is
/// counter-clockwise seen from outside (right-hand rule gives the outward normal).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// Axis-aligned bounding box `(min, max)` of the vertices used by triangles;
    /// `None` for a mesh without triangles (out-of-range indices are skipped).
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        let mut it = self
            .triangles
            .iter()
            .flatten()
            .filter_map(|&i| self.vertices.get(i as usize).copied());
        let first = it.next()?;
        let (mut lo, mut hi) = (first, first);
        for v in it {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        Some((lo, hi))
    }

    /// The first problem that would make the mesh unusable: an index out of range or a
    /// coordinate that is not finite (what [`repair`] refuses).
    pub fn check_indices_and_coordinates(&self) -> Result<(), MeshError> {
        let nv = self.vertices.len();
        for (t, tri) in self.triangles.iter().enumerate() {
            for (corner, &i) in tri.iter().enumerate() {
                let Some(v) = self.vertices.get(i as usize) else {
                    return Err(MeshError::BadIndex {
                        triangle: t as u64,
                        index: i,
                        vertex_count: nv as u64,
                    });
                };
                if !v.is_finite() {
                    return Err(MeshError::NotFinite {
                        format: "mesh",
                        triangle: t as u64,
                        corner,
                        at: None,
                    });
                }
            }
        }
        Ok(())
    }

    /// The three corners of triangle `t` (indices must be in range: see
    /// [`Mesh::check_indices_and_coordinates`]).
    pub fn corners(&self, t: usize) -> [DVec3; 3] {
        let [a, b, c] = self.triangles[t];
        [
            self.vertices[a as usize],
            self.vertices[b as usize],
            self.vertices[c as usize],
        ]
    }

    /// The mesh as binary STL (normals left zero: readers take them from the winding),
    /// single precision as the format has it. A vertex index out of range is an error.
    pub fn to_binary_stl(&self) -> std::io::Result<Vec<u8>> {
        self.check_indices_and_coordinates()
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e.to_string()))?;
        let tris: Vec<stl_io::Triangle> = (0..self.triangles.len())
            .map(|t| {
                let v = |p: DVec3| {
                    let p = p.as_vec3();
                    stl_io::Vertex::new([p.x, p.y, p.z])
                };
                let [a, b, c] = self.corners(t);
                stl_io::Triangle {
                    normal: stl_io::Normal::new([0.0, 0.0, 0.0]),
                    vertices: [v(a), v(b), v(c)],
                }
            })
            .collect();
        let mut out = Vec::with_capacity(84 + 50 * tris.len());
        stl_io::write_stl(&mut out, tris.iter())?;
        Ok(out)
    }

    /// Signed enclosed volume, mm³ (positive for a closed mesh with outward normals).
    pub fn signed_volume(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| {
                let [a, b, c] = self.corners(t);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }
}

/// Size limits checked before decoding allocates anything proportional to the input.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct MeshLimits {
    /// Largest accepted file, and largest accepted decompressed 3MF model part, bytes.
    /// Default 512 MiB.
    pub max_bytes: u64,
    /// Largest accepted triangle count (after 3MF build items and components are
    /// expanded). Default 10 million.
    pub max_triangles: u64,
}

impl Default for MeshLimits {
    fn default() -> Self {
        MeshLimits {
            max_bytes: 512 * 1024 * 1024,
            max_triangles: 10_000_000,
        }
    }
}

impl MeshLimits {
    /// `max_triangles`, capped so that vertex indices fit `u32` (three per triangle
    /// before merging).
    pub fn max_triangles_checked(&self) -> u64 {
        self.max_triangles.min(u32::MAX as u64 / 3)
    }
}

/// The file formats [`load_bytes`] understands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MeshFormat {
    StlBinary,
    StlAscii,
    ThreeMf,
}

/// Why a mesh could not be loaded or used. Each variant names what and where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    #[error("the file is empty")]
    Empty,
    #[error("the file is {size} bytes, over the limit of {limit} bytes (MeshLimits::max_bytes)")]
    TooLarge { size: u64, limit: u64 },
    #[error(
        "the mesh has {count} triangles, over the limit of {limit} (MeshLimits::max_triangles)"
    )]
    TooManyTriangles { count: u64, limit: u64 },
    #[error("not a mesh file this program reads: it is neither a binary STL (84-byte header + 50 bytes per triangle), an ASCII STL (starting with \"solid\") nor a 3MF (a zip archive)")]
    UnknownFormat,
    #[error("binary STL is truncated: {size} bytes, shorter than the 84-byte header")]
    StlTruncatedHeader { size: u64 },
    #[error("binary STL header says {declared} triangles ({expected} bytes) but the file is {size} bytes; the file is truncated or the count is wrong")]
    StlCountMismatch {
        declared: u64,
        expected: u64,
        size: u64,
    },
    #[error("ASCII STL: {message} (after {triangles_read} triangles)")]
    StlAscii {
        message: String,
        triangles_read: u64,
    },
    #[error("{format} triangle {triangle} vertex {corner} has a coordinate that is not a finite number{}", at.as_ref().map(|a| format!(" ({a})")).unwrap_or_default())]
    NotFinite {
        format: &'static str,
        triangle: u64,
        corner: usize,
        at: Option<String>,
    },
    #[error("3MF is not a readable zip archive: {0}")]
    ThreeMfZip(String),
    #[error("3MF has no 3D model part (looked for {0})")]
    ThreeMfNoModel(String),
    #[error("3MF {part}: {message} (byte {offset})")]
    ThreeMfXml {
        part: String,
        message: String,
        offset: u64,
    },
    #[error("3MF {part}: {message}")]
    ThreeMf { part: String, message: String },
    #[error("the mesh has no triangles")]
    NoTriangles,
    #[error(
        "triangle {triangle} refers to vertex {index}, but there are only {vertex_count} vertices"
    )]
    BadIndex {
        triangle: u64,
        index: u32,
        vertex_count: u64,
    },
    #[error("reading {path}: {message}")]
    Io { path: String, message: String },
}

/// Decode mesh bytes, sniffing the format: a zip signature is 3MF; a length that equals
/// 84 + 50 × (header count) is binary STL (even if its header starts with "solid"); text
/// starting with `solid` is ASCII STL.
pub fn load_bytes(bytes: &[u8], limits: &MeshLimits) -> Result<(Mesh, MeshFormat), MeshError> {
    if bytes.is_empty() {
        return Err(MeshError::Empty);
    }
    if bytes.len() as u64 > limits.max_bytes {
        return Err(MeshError::TooLarge {
            size: bytes.len() as u64,
            limit: limits.max_bytes,
        });
    }
    if bytes.starts_with(b"PK\x03\x04") || bytes.starts_with(b"PK\x05\x06") {
        return threemf::load(bytes, limits).map(|m| (m, MeshFormat::ThreeMf));
    }
    if stl::binary_size_matches(bytes) {
        return stl::load_binary(bytes, limits).map(|m| (m, MeshFormat::StlBinary));
    }
    let text_start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(bytes.len());
    if bytes[text_start..].starts_with(b"solid") && stl::looks_like_text(bytes) {
        return stl::load_ascii(bytes, limits).map(|m| (m, MeshFormat::StlAscii));
    }
    if bytes.len() >= 84 {
        // Not text, not a zip: treat it as binary STL so the user hears about the count.
        return stl::load_binary(bytes, limits).map(|m| (m, MeshFormat::StlBinary));
    }
    if bytes.len() < 84 && !stl::looks_like_text(bytes) {
        return Err(MeshError::StlTruncatedHeader {
            size: bytes.len() as u64,
        });
    }
    Err(MeshError::UnknownFormat)
}

/// Load and repair in one call: what the planner wants from file bytes.
pub fn load_and_repair(
    bytes: &[u8],
    limits: &MeshLimits,
    options: &RepairOptions,
) -> Result<(Mesh, MeshReport), MeshError> {
    let (mesh, format) = load_bytes(bytes, limits)?;
    let (mesh, mut report) = repair(&mesh, options)?;
    report.format = Some(format);
    Ok((mesh, report))
}
