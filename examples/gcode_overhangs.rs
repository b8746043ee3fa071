//! What rests on nothing in a G-code file, from its beads (the check of
//! `tests/supports.rs`): every extrusion laid on a raster per layer with its width
//! from its volume; a layer's part beads must rest, within `t · tan(30°)`, on the
//! layer below's beads (part or `;TYPE:Support…`). Reads the RRF form edo writes
//! (`;LAYER:n Zz`, relative `E`, the header's barrel area);
//! `benches/supports_vs_prusaslicer.sh` turns PrusaSlicer's G-code into it.
//!
//! ```text
//! cargo run --release --example gcode_overhangs -- FILE NOZZLE_MM
//! ```
//!
//! Output: `{"unsupported_mm2": .., "layers": [[layer, mm²], ..]}` on standard output.

#[path = "../tests/beads/mod.rs"]
mod beads;

use anyhow::{bail, Context, Result};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [file, nozzle] = args.as_slice() else {
        bail!("usage: gcode_overhangs FILE NOZZLE_MM");
    };
    let nozzle_mm: f64 = nozzle
        .parse()
        .with_context(|| format!("nozzle {nozzle:?}"))?;
    let text = std::fs::read_to_string(file).with_context(|| format!("reading {file}"))?;
    let layers = beads::parse_gcode(&text);
    let hanging = beads::unsupported_layers(&layers, &beads::Allowance { nozzle_mm });
    let total: f64 = hanging.iter().map(|h| h.1).sum();
    println!(
        "{}",
        serde_json::json!({"unsupported_mm2": total, "layers": hanging})
    );
    Ok(())
}
