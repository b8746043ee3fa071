//! A layer as the page draws it: its moves, in the order the machine runs them, with
//! the position each ends at (mm, machine coordinates) and, for an extrusion, its
//! composition and the colour the SVG previews give it ([`crate::svg::mix_colour`]).
//! Moves that do not travel (layer marks, retracts, primes, dwells) are `null`, so the
//! n-th entry is move `first_index + n` and the page can draw the moves executed.
//!
//! Pure: [`super::plans`] calls it on a blocking thread as it plans.

use serde_json::{json, Value};

use crate::daemon::config::MachineConfig;
use crate::machine::{Move, MoveKind, PositionUm};

fn mm(um: i32) -> f64 {
    f64::from(um) / 1000.0
}

/// One move as the page draws it.
fn entry(m: &Move) -> Value {
    let at = |to: &PositionUm| (mm(to.x_um), mm(to.y_um));
    match &m.kind {
        MoveKind::Travel { to, .. } => {
            let (x, y) = at(to);
            json!([x, y])
        }
        MoveKind::Extrude { to, volumes_nl, .. } => {
            let (x, y) = at(to);
            let total: u64 = volumes_nl.iter().map(|&v| u64::from(v)).sum();
            if total == 0 {
                return json!([x, y, "#888888", null]);
            }
            let f: Vec<f64> = volumes_nl
                .iter()
                .map(|&v| (f64::from(v) / total as f64 * 1000.0).round() / 1000.0)
                .collect();
            json!([x, y, crate::svg::mix_colour(&f), f])
        }
        _ => Value::Null,
    }
}

/// The height of a layer's moves (its layer mark's, else its first move's), mm.
pub fn layer_z(moves: &[Move]) -> Option<f64> {
    moves.iter().find_map(|m| match &m.kind {
        MoveKind::LayerMark { z_um, .. } => Some(mm(*z_um)),
        MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => Some(mm(to.z_um)),
        _ => None,
    })
}

/// Where the nozzle is before a layer's first move: the last position of the layers
/// before it.
pub fn last_position(moves: &[Move]) -> Option<(f64, f64)> {
    moves.iter().rev().find_map(|m| match &m.kind {
        MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => {
            Some((mm(to.x_um), mm(to.y_um)))
        }
        _ => None,
    })
}

/// The view of one planned layer.
pub fn layer_value(layer: u32, moves: &[Move], start: Option<(f64, f64)>) -> Value {
    json!({
        "layer": layer,
        "z_mm": layer_z(moves),
        "first_index": moves.first().map(|m| m.index),
        "start": start.map(|(x, y)| [x, y]),
        "moves": moves.iter().map(entry).collect::<Vec<_>>(),
    })
}

/// The part against the machine, as a submission checks it: its materials and
/// settings, and for a mesh, that it loads and fits the build volume.
pub fn fits(
    job: &crate::job::Job,
    mesh: Option<&[u8]>,
    machine: &MachineConfig,
    limits: &crate::mesh::MeshLimits,
) -> Result<(), String> {
    crate::daemon::planner::process_settings(job, machine, "job")?;
    let volume = machine.build_volume()?;
    match (&job.geometry, mesh) {
        (crate::job::Geometry::Mesh { path }, Some(bytes)) => {
            let part = job
                .mesh_layers(bytes, limits)
                .map_err(|e| format!("{path}: {e}"))?;
            crate::machine::placement::place_part(job, part.bounds(), &volume)
                .map(|_| ())
                .map_err(|e| format!("{path}: {e}"))
        }
        (crate::job::Geometry::Mesh { path }, None) => Err(format!(
            "geometry.mesh = {path:?}: choose the mesh file to send with the job"
        )),
        _ => Ok(()),
    }
}
