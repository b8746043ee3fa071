//! The recorder (one JSON object per executed move, JSON lines) and `hil-sim render`,
//! which draws the recorded layers as SVG coloured by the composition at the nozzle exit.
//! The line format is documented in `hil-sim/README.md`; its type, parser and drawing
//! live in the `edo` library ([`edo::machine::record`], [`edo::svg::built_svg`]) so the
//! host reads recordings with the same code (`edoctl demo`).

use std::io::Write;
use std::path::Path;

use anyhow::Context;

pub use edo::machine::record::RecordLine;

/// Append one line to a recorder.
pub fn write_line(out: &mut impl Write, line: &RecordLine) -> anyhow::Result<()> {
    serde_json::to_writer(&mut *out, line)?;
    out.write_all(b"\n")?;
    Ok(())
}

/// Draw every layer of `record` into `dir/layer-NNNN.svg`; returns the files written.
pub fn render(record: &Path, dir: &Path) -> anyhow::Result<Vec<std::path::PathBuf>> {
    let text = std::fs::read_to_string(record)
        .with_context(|| format!("open record {}", record.display()))?;
    let lines = edo::machine::record::parse(&text).with_context(|| record.display().to_string())?;
    std::fs::create_dir_all(dir).with_context(|| format!("create {}", dir.display()))?;
    let mut written = Vec::new();
    for (layer, roads) in edo::machine::record::built_roads(&lines, None) {
        let width = roads
            .iter()
            .map(|r| r.width_mm)
            .fold(0.0, f64::max)
            .max(0.1);
        let svg = edo::svg::built_svg(
            &roads,
            &[],
            width,
            &format!("layer {layer} as built: {} extrusions", roads.len()),
        );
        let path = dir.join(format!("layer-{layer:04}.svg"));
        std::fs::write(&path, svg).with_context(|| format!("write {}", path.display()))?;
        written.push(path);
    }
    Ok(written)
}
