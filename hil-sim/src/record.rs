//! The recorder (one JSON object per executed move, JSON lines) and `hil-sim render`,
//! which draws the recorded layers as SVG coloured by the composition at the nozzle exit.
//! The line format is documented in `hil-sim/README.md`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{BufRead, Write};
use std::path::Path;

use anyhow::Context;
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
}

/// Append one line to a recorder.
pub fn write_line(out: &mut impl Write, line: &RecordLine) -> anyhow::Result<()> {
    serde_json::to_writer(&mut *out, line)?;
    out.write_all(b"\n")?;
    Ok(())
}

/// Colour of a composition: the planner's preview colours (`edo::svg::mix_colour`), so
/// planned and as-built drawings compare side by side.
pub fn colour(composition: &[f64]) -> String {
    edo::svg::mix_colour(composition)
}

/// Draw every layer of `record` into `dir/layer-NNNN.svg`; returns the files written.
pub fn render(record: &Path, dir: &Path) -> anyhow::Result<Vec<std::path::PathBuf>> {
    let file =
        std::fs::File::open(record).with_context(|| format!("open record {}", record.display()))?;
    let mut layers: BTreeMap<u32, Vec<RecordLine>> = BTreeMap::new();
    for (n, line) in std::io::BufReader::new(file).lines().enumerate() {
        let line = line.with_context(|| format!("{}: read line {}", record.display(), n + 1))?;
        if line.trim().is_empty() {
            continue;
        }
        let rec: RecordLine = serde_json::from_str(&line)
            .with_context(|| format!("{}: line {}: not a record line", record.display(), n + 1))?;
        if rec.kind == "extrude" {
            layers.entry(rec.layer).or_default().push(rec);
        }
    }
    std::fs::create_dir_all(dir).with_context(|| format!("create {}", dir.display()))?;
    let mut written = Vec::new();
    for (layer, moves) in layers {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for m in &moves {
            for p in [m.from_mm, m.to_mm] {
                x0 = x0.min(p[0]);
                y0 = y0.min(p[1]);
                x1 = x1.max(p[0]);
                y1 = y1.max(p[1]);
            }
        }
        let margin = 1.0;
        let (w, h) = (
            (x1 - x0).max(1.0) + 2.0 * margin,
            (y1 - y0).max(1.0) + 2.0 * margin,
        );
        let mut svg = String::new();
        let _ = writeln!(
            svg,
            r#"<svg xmlns="http://www.w3.org/2000/svg" viewBox="{} {} {w:.3} {h:.3}" width="800" height="{:.0}">"#,
            x0 - margin,
            -(y1 + margin),
            800.0 * h / w
        );
        let _ = writeln!(svg, "<title>layer {layer}: {} moves</title>", moves.len());
        for m in &moves {
            let c = m
                .exit_composition
                .as_deref()
                .map_or_else(|| "#000000".to_string(), colour);
            let _ = writeln!(
                svg,
                r#"<line x1="{:.3}" y1="{:.3}" x2="{:.3}" y2="{:.3}" stroke="{c}" stroke-width="0.4" stroke-linecap="round"/>"#,
                m.from_mm[0], -m.from_mm[1], m.to_mm[0], -m.to_mm[1]
            );
        }
        svg.push_str("</svg>\n");
        let path = dir.join(format!("layer-{layer:04}.svg"));
        std::fs::write(&path, svg).with_context(|| format!("write {}", path.display()))?;
        written.push(path);
    }
    Ok(written)
}
