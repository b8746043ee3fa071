//! Load, repair and slice a mesh file whole, the way the planner will, and print a JSON
//! summary (mesh report, slice report, layer count, times):
//!
//! ```text
//! cargo run --release --example slice_file -- MESH [--uniform T | --adaptive MIN MAX CUSP] [--max-gap MM]
//! ```

use anyhow::{Context, Result};
use edo::mesh::{path::load_path, MeshLimits, RepairOptions};
use edo::slice::{slice_mesh, SliceOptions};
use std::time::Instant;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = args
        .first()
        .context("usage: slice_file MESH [--uniform T | --adaptive MIN MAX CUSP]")?;
    let num = |i: usize| -> Result<f64> {
        args.get(i)
            .with_context(|| format!("missing argument {i}"))?
            .parse::<f64>()
            .with_context(|| format!("argument {i}"))
    };
    let mut options = match args.get(1).map(String::as_str) {
        Some("--uniform") => SliceOptions::uniform(num(2)?),
        Some("--adaptive") => SliceOptions {
            layer_min_mm: num(2)?,
            layer_max_mm: num(3)?,
            cusp_mm: num(4)?,
            ..Default::default()
        },
        _ => SliceOptions::default(),
    };
    if let Some(i) = args.iter().position(|a| a == "--max-gap") {
        options.tolerances.max_gap_mm = num(i + 1)?;
    }
    let t0 = Instant::now();
    let (mesh, report) = load_path(
        std::path::Path::new(path),
        &MeshLimits::default(),
        &RepairOptions::default(),
    )?;
    let t1 = Instant::now();
    let (layers, slice_report) = slice_mesh(&mesh, &options, None)?;
    let t2 = Instant::now();
    let thickness: Vec<f64> = layers.iter().map(|l| l.thickness_mm).collect();
    let volume: f64 = layers.iter().map(|l| l.area_mm2() * l.thickness_mm).sum();
    println!(
        "{}",
        serde_json::json!({
            "mesh": path,
            "options": format!("{options:?}"),
            "layers": layers.len(),
            "thinnest_mm": thickness.iter().cloned().fold(f64::INFINITY, f64::min),
            "thickest_mm": thickness.iter().cloned().fold(0.0, f64::max),
            "islands": layers.iter().map(|l| l.islands.len()).sum::<usize>(),
            "layer_volume_mm3": volume,
            "load_repair_s": (t1 - t0).as_secs_f64(),
            "slice_s": (t2 - t1).as_secs_f64(),
            "mesh_report": report,
            "slice_report": slice_report,
        })
    );
    Ok(())
}
