//! The recording of what a machine executed: one JSON object per executed move (JSON
//! lines), written by hil-sim's recorder (`hil-sim --record FILE`, format in
//! `hil-sim/README.md`) and read back to draw and check what was built against what was
//! planned (`hil-sim render`, `edoctl demo`).
//!
//! Pure: parses text and computes; reading the file is the caller's business.

use std::collections::BTreeMap;

use glam::DVec2;
use serde::{Deserialize, Serialize};

/// One executed move, as recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordLine {
    /// Job id.
    pub job_id: u32,
    /// Move index within the job.
    pub index: u32,
    /// Move kind: travel, extrude, retract, prime, dwell, layer, home.
    pub kind: String,
    /// Layer (from the last layer mark).
    pub layer: u32,
    /// Simulated machine time at the end of the move (s).
    pub t_s: f64,
    /// Start position (mm).
    pub from_mm: [f64; 3],
    /// End position (mm).
    pub to_mm: [f64; 3],
    /// Per-syringe volume of the move (nl).
    pub volumes_nl: Vec<u32>,
    /// Composition leaving the nozzle during the move (fractions summing to 1), after the
    /// mixing chamber's plug-flow delay; null for moves without extrusion.
    pub exit_composition: Option<Vec<f64>>,
    /// Remaining volume per syringe after the move (nl).
    pub remaining_nl: Vec<u32>,
    /// The G-code command the move came from (hil-sim's G-code modes), without line
    /// number and checksum; absent on the edo link.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gcode: Option<String>,
}

/// A recording that does not parse, with the line that is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("line {line}: not a record line: {message}")]
pub struct RecordError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong.
    pub message: String,
}

/// Parse a recording (blank lines are skipped).
pub fn parse(text: &str) -> Result<Vec<RecordLine>, RecordError> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(n, l)| {
            serde_json::from_str(l).map_err(|e| RecordError {
                line: n + 1,
                message: e.to_string(),
            })
        })
        .collect()
}

/// One road as built: an extrusion move's segment, the width its volume gives at the
/// layer's height, and the composition that left the nozzle.
#[derive(Debug, Clone, PartialEq)]
pub struct BuiltRoad {
    pub from: DVec2,
    pub to: DVec2,
    /// Deposited width: volume / (length × layer thickness), mm.
    pub width_mm: f64,
    /// Composition at the nozzle exit.
    pub composition: Vec<f64>,
}

/// The extrusions of a recording by layer, for one job (`None`: every job). A layer's
/// thickness is its z above the previous layer's (the first layer's z above the bed).
pub fn built_roads(lines: &[RecordLine], job_id: Option<u32>) -> BTreeMap<u32, Vec<BuiltRoad>> {
    let mut by_layer: BTreeMap<u32, Vec<&RecordLine>> = BTreeMap::new();
    for l in lines {
        if l.kind == "extrude" && job_id.is_none_or(|j| j == l.job_id) {
            by_layer.entry(l.layer).or_default().push(l);
        }
    }
    let mut out = BTreeMap::new();
    let mut below_z = 0.0;
    for (layer, moves) in by_layer {
        let z = moves.iter().map(|m| m.to_mm[2]).fold(f64::MIN, f64::max);
        let thickness = z - below_z;
        below_z = z;
        let roads = moves
            .iter()
            .map(|m| {
                let from = DVec2::new(m.from_mm[0], m.from_mm[1]);
                let to = DVec2::new(m.to_mm[0], m.to_mm[1]);
                let len = from.distance(to);
                let volume_mm3 = m.volumes_nl.iter().map(|&v| f64::from(v)).sum::<f64>() * 1e-3;
                let width_mm = if len > 1e-9 && thickness > 1e-9 {
                    volume_mm3 / (len * thickness)
                } else {
                    0.0
                };
                BuiltRoad {
                    from,
                    to,
                    width_mm,
                    composition: m.exit_composition.clone().unwrap_or_default(),
                }
            })
            .collect();
        out.insert(layer, roads);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(index: u32, layer: u32, to: [f64; 3], volumes_nl: Vec<u32>) -> RecordLine {
        RecordLine {
            job_id: 1,
            index,
            kind: "extrude".into(),
            layer,
            t_s: 0.0,
            from_mm: [0.0, 0.0, to[2]],
            to_mm: to,
            volumes_nl,
            exit_composition: Some(vec![0.25, 0.75]),
            remaining_nl: vec![0, 0],
            gcode: None,
        }
    }

    #[test]
    fn widths_come_from_volume_length_and_layer_height() {
        // 10 mm at 0.2 mm layers: 0.8 mm³ is a 0.4 mm road; at 0.1 mm above, 0.2 mm³ = 0.2 mm.
        let lines = vec![
            line(0, 0, [10.0, 0.0, 0.2], vec![400, 400]),
            line(1, 1, [10.0, 0.0, 0.3], vec![100, 100]),
        ];
        let text: String = lines
            .iter()
            .map(|l| serde_json::to_string(l).unwrap() + "\n\n")
            .collect();
        let parsed = parse(&text).unwrap();
        assert_eq!(parsed, lines);
        let roads = built_roads(&parsed, Some(1));
        assert!((roads[&0][0].width_mm - 0.4).abs() < 1e-12);
        assert!((roads[&1][0].width_mm - 0.2).abs() < 1e-12);
        assert!(built_roads(&parsed, Some(2)).is_empty());
        assert_eq!(parse("{\"job_id\": 1}\n").unwrap_err().line, 1);
    }
}
