//! A layer as the page draws it: its moves, in the order the machine runs them, with
//! the position each ends at (mm, machine coordinates) and, for an extrusion, its
//! composition and the colour the SVG previews give it ([`crate::svg::mix_colour`]).
//! Moves that do not travel (layer marks, retracts, primes, dwells) are `null`, so the
//! n-th entry is move `first_index + n` and the page can draw the moves executed.
//!
//! Runs on a blocking thread: it plans.

use serde_json::{json, Value};

use crate::daemon::config::MachineConfig;
use crate::daemon::planner::{JobSource, LayerSource};
use crate::machine::{Move, MoveKind, PositionUm};

/// Most layers a preview plans (the rest are named, not planned).
pub const PREVIEW_LAYERS: u32 = 2000;

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
fn layer_z(moves: &[Move]) -> Option<f64> {
    moves.iter().find_map(|m| match &m.kind {
        MoveKind::LayerMark { z_um, .. } => Some(mm(*z_um)),
        MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => Some(mm(to.z_um)),
        _ => None,
    })
}

/// Where the nozzle is before a layer's first move: the last position of the layers
/// before it.
fn last_position(moves: &[Move]) -> Option<(f64, f64)> {
    moves.iter().rev().find_map(|m| match &m.kind {
        MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => {
            Some((mm(to.x_um), mm(to.y_um)))
        }
        _ => None,
    })
}

/// The view of one planned layer.
fn layer_value(layer: u32, moves: &[Move], start: Option<(f64, f64)>) -> Value {
    json!({
        "layer": layer,
        "z_mm": layer_z(moves),
        "first_index": moves.first().map(|m| m.index),
        "start": start.map(|(x, y)| [x, y]),
        "moves": moves.iter().map(entry).collect::<Vec<_>>(),
    })
}

/// Layer `layer` of `source` (planned up to it), with the job's layer count.
pub fn view(mut source: Box<dyn LayerSource>, layer: u32) -> Result<Value, String> {
    let mut start = None;
    for k in 0..=layer {
        match source.next_layer() {
            Some(Ok(moves)) if k == layer => {
                let mut v = layer_value(layer, &moves, start);
                v["layers"] = json!(source.layer_count());
                return Ok(v);
            }
            Some(Ok(moves)) => start = last_position(&moves).or(start),
            Some(Err(e)) => return Err(e),
            None => break,
        }
    }
    Err(format!(
        "the job has no layer {layer} (layers count from 0)"
    ))
}

/// A job file's plan before it is submitted: what submitting it would refuse
/// (`problems`), its layers (height and moves each), and the view of layer `layer`.
pub fn preview(
    toml: &str,
    mesh: Option<&[u8]>,
    machine: &MachineConfig,
    limits: &crate::mesh::MeshLimits,
    layer: u32,
) -> Value {
    let problems = |p: String| json!({"ok": false, "problems": [p], "layers": []});
    let job = match crate::job::Job::from_toml(toml, "job") {
        Ok(j) => j,
        Err(e) => return problems(e.to_string()),
    };
    if let Err(p) = fits(&job, mesh, machine, limits) {
        return json!({"ok": false, "name": job.name, "problems": [p], "layers": []});
    }
    let mut source = match JobSource::new(toml, mesh, "job", machine) {
        Ok(s) => s,
        Err(e) => return json!({"ok": false, "name": job.name, "problems": [e], "layers": []}),
    };
    let (mut layers, mut shown, mut start, mut total) = (Vec::new(), Value::Null, None, 0u64);
    let mut problems = Vec::new();
    for k in 0..PREVIEW_LAYERS {
        match source.next_layer() {
            Some(Ok(moves)) => {
                total += moves.len() as u64;
                layers.push(json!({"z_mm": layer_z(&moves), "moves": moves.len()}));
                if k == layer {
                    shown = layer_value(k, &moves, start);
                }
                start = last_position(&moves).or(start);
            }
            Some(Err(e)) => {
                problems.push(e);
                break;
            }
            None => break,
        }
    }
    if source.layer_count().is_some_and(|n| n > PREVIEW_LAYERS) {
        problems.push(format!(
            "only the first {PREVIEW_LAYERS} layers were previewed"
        ));
    }
    json!({
        "ok": problems.is_empty(),
        "name": job.name,
        "problems": problems,
        "layers": layers,
        "total_moves": total,
        "view": shown,
    })
}

/// The part against the machine, as a submission checks it: its materials and
/// settings, and for a mesh, that it loads and fits the build volume.
fn fits(
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
