//! The one place the mesh stage touches the file system, for the binaries: check the file
//! size against [`MeshLimits::max_bytes`] before reading, then hand the bytes to
//! [`super::load_and_repair`].

use super::{load_and_repair, Mesh, MeshError, MeshLimits, MeshReport, RepairOptions};
use std::path::Path;

/// Read `path` (refusing files over the size limit before reading them) and return its bytes.
pub fn read_limited(path: &Path, limits: &MeshLimits) -> Result<Vec<u8>, MeshError> {
    let io = |e: std::io::Error| MeshError::Io {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let size = std::fs::metadata(path).map_err(io)?.len();
    if size > limits.max_bytes {
        return Err(MeshError::TooLarge {
            size,
            limit: limits.max_bytes,
        });
    }
    std::fs::read(path).map_err(io)
}

/// Load, validate and repair the mesh file at `path`.
pub fn load_path(
    path: &Path,
    limits: &MeshLimits,
    options: &RepairOptions,
) -> Result<(Mesh, MeshReport), MeshError> {
    let bytes = read_limited(path, limits)?;
    load_and_repair(&bytes, limits, options)
}
