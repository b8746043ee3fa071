//! A layer as the page draws it: its moves, in the order the machine runs them, with
//! the position each ends at (mm, machine coordinates) and, for an extrusion, the
//! road's designed composition and the colour the SVG previews give it
//! ([`crate::svg::road_colour`]), and what the planner's model of the mixing chamber
//! predicts leaves the nozzle meanwhile (the commanded volumes run the chamber's
//! volume ahead of the nozzle, so they are neither).
//! Moves that do not travel (layer marks, retracts, primes, dwells) are `null`, so the
//! n-th entry is move `first_index + n` and the page can draw the moves executed.
//!
//! Pure: [`super::plans`] calls it on a blocking thread as it plans.

use serde_json::{json, Value};

use crate::daemon::planner::DesignedRoad;
use crate::machine::{Move, MoveKind, PositionUm};
use crate::setup::MachineConfig;

fn mm(um: i32) -> f64 {
    f64::from(um) / 1000.0
}

/// Fractions of `volumes_nl`'s total (none when nothing is pushed).
fn fractions(volumes_nl: &[u32]) -> Option<Vec<f64>> {
    let total: u64 = volumes_nl.iter().map(|&v| u64::from(v)).sum();
    (total > 0).then(|| {
        volumes_nl
            .iter()
            .map(|&v| f64::from(v) / total as f64)
            .collect()
    })
}

fn rounded(f: f64) -> f64 {
    (f * 1000.0).round() / 1000.0
}

/// One move as the page draws it: `[x, y]` for a travel; for an extrusion `[x, y,
/// colour, composition, exit colour, exit composition]`, the first pair the road's
/// design (what the previews draw; the commanded mix where the design is not known),
/// the second what the planner's model of the mixing chamber predicts leaves the
/// nozzle meanwhile (none where nothing is pushed or the design is not known).
fn entry(m: &Move, designed: Option<&DesignedRoad>) -> Value {
    let at = |to: &PositionUm| (mm(to.x_um), mm(to.y_um));
    let round_all = |c: &[f64]| c.iter().copied().map(rounded).collect::<Vec<f64>>();
    match &m.kind {
        MoveKind::Travel { to, .. } => {
            let (x, y) = at(to);
            json!([x, y])
        }
        MoveKind::Extrude { to, volumes_nl, .. } => {
            let (x, y) = at(to);
            let pushed = volumes_nl.iter().any(|&v| v > 0);
            match (designed, fractions(volumes_nl)) {
                (Some(d), _) => {
                    let exit = pushed.then(|| round_all(&d.exit));
                    let exit_colour = pushed.then(|| crate::svg::mix_colour(&d.exit));
                    json!([x, y, d.colour, round_all(&d.composition), exit_colour, exit])
                }
                (None, Some(f)) => {
                    json!([x, y, crate::svg::mix_colour(&f), round_all(&f), null, null])
                }
                (None, None) => json!([x, y, "#888888", null, null, null]),
            }
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

/// The view of one planned layer: its moves, each extrusion with the road it builds
/// (`roads`, in move order, from the planner).
pub fn layer_value(
    layer: u32,
    moves: &[Move],
    start: Option<(f64, f64)>,
    roads: &[DesignedRoad],
) -> Value {
    let mut roads = roads.iter().peekable();
    let entries: Vec<Value> = moves
        .iter()
        .map(|m| {
            while roads.next_if(|r| r.move_index < m.index).is_some() {}
            entry(m, roads.next_if(|r| r.move_index == m.index))
        })
        .collect();
    json!({
        "layer": layer,
        "z_mm": layer_z(moves),
        "first_index": moves.first().map(|m| m.index),
        "start": start.map(|(x, y)| [x, y]),
        "moves": entries,
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
    crate::setup::process_settings(job, machine, "job")?;
    let volume = machine.build_volume()?;
    match (&job.geometry, mesh) {
        (crate::job::Geometry::Mesh { path }, Some(bytes)) => {
            let part = job
                .mesh_layers(bytes, limits)
                .map_err(|e| format!("{path}: {e}"))?;
            crate::job::placement::place_part(job, part.bounds(), &volume)
                .map(|_| ())
                .map_err(|e| format!("{path}: {e}"))
        }
        (crate::job::Geometry::Mesh { path }, None) => Err(format!(
            "geometry.mesh = {path:?}: choose the mesh file to send with the job"
        )),
        _ => Ok(()),
    }
}
