//! `edoctl demo --firmware F`: the recording of a G-code machine matched to the plan.
//!
//! Over G-code the simulator (`hil-sim --gcode F`) records each command that moved as a
//! move of its own numbering (job 0, indices from 0), with the command in `gcode`; layer
//! marks send no line, and Marlin's mix goes in `M163`/`M164` lines that move nothing.
//! So the plan is matched line by line: each planned move becomes the lines edod streams
//! for it (the offline writer's, [`MoveWriter`], less comments,
//! [`crate::gcode_link::writer::streamed_lines`]), and its motion line (`G0`, `G1`,
//! `G4`, `G28`) must be the next command the machine ran. The matched records get the
//! planned move's job, index and layer, so the composition, the previews and the
//! summary are computed as on the edo link.

use anyhow::Result;

use crate::gcode_link::command_word;
use crate::gcode_link::writer::{streamed_lines, Dialect, GcodeSettings, MoveWriter};
use crate::machine::record::RecordLine;
use crate::machine::{Move, MoveKind};
use crate::pipeline::LayerMoves;

/// The `[machine]` table of edod's configuration for `firmware` on the demo's machine
/// (two syringes; Klipper's manual steppers on axes A and B), with
/// `docs/firmware.md`'s defaults otherwise.
pub fn machine_toml(firmware: Dialect) -> String {
    let axes = match firmware {
        Dialect::Klipper => "axes = [\"A\", \"B\"]\n",
        _ => "",
    };
    format!(
        "[machine]\nprotocol = \"gcode\"\n[machine.gcode]\nfirmware = \"{}\"\n{axes}",
        firmware.name()
    )
}

/// The recording matched to the plan by lines.
#[derive(Debug, Default)]
pub struct Matched {
    /// The records of the planned moves' motion lines, in order, carrying the planned
    /// move's job id, index and layer (the layer's position in the plan).
    pub records: Vec<RecordLine>,
    /// Planned moves whose lines all ran, from the first up to the first that did not
    /// (a move without a motion line, a layer mark, counts once every line before it ran).
    pub moves_executed: u64,
    /// Motion lines planned, and commands that moved recorded.
    pub lines_planned: u64,
    pub lines_executed: u64,
    /// The first way the execution differs from the plan, if any.
    pub mismatch: Option<String>,
}

/// A planned motion line: the move it belongs to, its layer's position, its text.
struct PlannedLine<'a> {
    mv: &'a Move,
    layer: u32,
    text: String,
}

/// The motion lines edod streams for `planned` (one job from its first move, `drives`
/// syringes, written with `settings`).
fn planned_lines<'a>(
    planned: &'a [LayerMoves],
    drives: usize,
    settings: &GcodeSettings,
) -> Result<Vec<PlannedLine<'a>>> {
    let mut writer = MoveWriter::new(drives, settings)?;
    let mut lines = Vec::new();
    writer.preamble(&[], &mut lines);
    let mut out = Vec::new();
    for (k, lm) in planned.iter().enumerate() {
        for m in &lm.moves {
            lines.clear();
            writer.move_lines(m, &mut lines);
            let text = lines.join("\n");
            for line in streamed_lines(&text).filter(|l| is_motion(l)) {
                out.push(PlannedLine {
                    mv: m,
                    layer: k as u32,
                    text: line.to_string(),
                });
            }
        }
    }
    Ok(out)
}

/// A command the simulator turns into a move (and records).
fn is_motion(line: &str) -> bool {
    matches!(
        command_word(line).as_deref(),
        Some("G0" | "G1" | "G4" | "G28")
    )
}

/// Match `recording` (the G-code machine's, every command that moved) to `planned`:
/// every planned motion line ran once and in order, ending where planned, and each
/// syringe pushed its planned volume over the job.
pub fn match_lines(
    planned: &[LayerMoves],
    recording: &[RecordLine],
    drives: usize,
    settings: &GcodeSettings,
    job_id: u32,
) -> Result<Matched> {
    let want = planned_lines(planned, drives, settings)?;
    let ran: Vec<&RecordLine> = recording.iter().filter(|r| r.gcode.is_some()).collect();
    let mut mismatch = None;
    let mut records = Vec::with_capacity(want.len());
    for (k, (p, r)) in want.iter().zip(&ran).enumerate() {
        let text = r.gcode.as_deref().unwrap_or_default();
        if text != p.text {
            mismatch = Some(format!(
                "line {k}: {text:?} ran where {:?} (move {}) was planned",
                p.text, p.mv.index
            ));
            break;
        }
        if let Some(m) = position_mismatch(p.mv, r) {
            mismatch = Some(m);
            break;
        }
        records.push(RecordLine {
            job_id,
            index: p.mv.index,
            layer: p.layer,
            ..(*r).clone()
        });
    }
    let moves_executed = moves_up_to(planned, want.get(records.len()).map(|p| p.mv.index));
    if mismatch.is_none() && want.len() != ran.len() {
        mismatch = Some(format!(
            "{} move lines planned, {} ran",
            want.len(),
            ran.len()
        ));
    }
    if mismatch.is_none() {
        mismatch = volume_mismatch(planned, &records, drives, settings);
    }
    Ok(Matched {
        moves_executed,
        lines_planned: want.len() as u64,
        lines_executed: ran.len() as u64,
        records,
        mismatch,
    })
}

/// Planned moves before the move `first_missing` (every move if `None`).
fn moves_up_to(planned: &[LayerMoves], first_missing: Option<u32>) -> u64 {
    planned
        .iter()
        .flat_map(|l| &l.moves)
        .take_while(|m| Some(m.index) != first_missing)
        .count() as u64
}

/// A travel or extrusion recorded ending elsewhere than planned.
fn position_mismatch(m: &Move, r: &RecordLine) -> Option<String> {
    let to = match &m.kind {
        MoveKind::Extrude { to, .. } | MoveKind::Travel { to, .. } => to,
        _ => return None,
    };
    let want = [to.x_um, to.y_um, to.z_um].map(|v| f64::from(v) / 1000.0);
    if want.iter().zip(&r.to_mm).any(|(a, b)| (a - b).abs() > 1e-6) {
        return Some(format!(
            "move {}: ended at {:?} mm, planned {:?} mm",
            m.index, r.to_mm, want
        ));
    }
    None
}

/// Each syringe's extruded volume over the job against the plan. The firmware turns
/// plunger travel back into volume; RRF's and Klipper's per-drive travel is rounded
/// cumulatively to 10⁻⁶ mm, so it comes back to the nanolitre (1 nl of slack for the
/// simulator's own rounding across retracts); Marlin splits each move's total by the
/// last `M163` mix, which the writer keeps within 5·10⁻⁵ mm of the plan per drive
/// (`docs/gcode.md`). Single moves on Marlin differ by a few nl: per move, the volume
/// recorded is what the firmware split.
fn volume_mismatch(
    planned: &[LayerMoves],
    records: &[RecordLine],
    drives: usize,
    settings: &GcodeSettings,
) -> Option<String> {
    let mut want = vec![0i64; drives];
    for m in planned.iter().flat_map(|l| &l.moves) {
        if let MoveKind::Extrude { volumes_nl, .. } = &m.kind {
            for (w, &v) in want.iter_mut().zip(volumes_nl) {
                *w += i64::from(v);
            }
        }
    }
    let mut built = vec![0i64; drives];
    for r in records.iter().filter(|r| r.kind == "extrude") {
        for (b, &v) in built.iter_mut().zip(&r.volumes_nl) {
            *b += i64::from(v);
        }
    }
    let slack_nl = match settings.flavor {
        Dialect::Marlin => 1.0 + 5e-5 * settings.barrel_area_mm2 * 1000.0,
        _ => 1.0,
    };
    let off = want
        .iter()
        .zip(&built)
        .any(|(w, b)| (w - b).abs() as f64 > slack_nl);
    off.then(|| format!("syringes extruded {built:?} nl, planned {want:?} nl"))
}
