//! Print section areas of a mesh as JSON, for comparison with other slicers
//! (`tests/compare_trimesh.py`):
//!
//! ```text
//! cargo run --release --example slice_areas -- MESH Z1 Z2 ...
//! cargo run --release --example slice_areas -- MESH --uniform 0.2      # layer mid-heights
//! ```
//!
//! Output: `{"mesh": .., "report": {..}, "sections": [{"z_mm": .., "cut_z_mm": .., "area_mm2": ..,
//! "islands": ..}], "seconds": ..}`; `cut_z_mm` is where the plane was really cut (moved off
//! vertex heights, see `SliceTolerances::plane_clearance_mm`), `seconds` the time of the
//! sections alone.

use anyhow::{bail, Context, Result};
use edo::mesh::{path::load_path, MeshLimits, RepairOptions};
use edo::slice::{SliceOptions, SliceTolerances, Slicer};
use std::time::Instant;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        bail!("usage: slice_areas MESH (Z... | --uniform THICKNESS)");
    };
    let (mesh, report) = load_path(
        std::path::Path::new(path),
        &MeshLimits::default(),
        &RepairOptions::default(),
    )
    .with_context(|| format!("loading {path}"))?;
    let slicer = Slicer::new(&mesh)?;
    let heights: Vec<f64> = if args.get(1).map(String::as_str) == Some("--uniform") {
        let t: f64 = args
            .get(2)
            .context("--uniform needs a thickness")?
            .parse()?;
        slicer
            .layer_spans(&SliceOptions::uniform(t))?
            .iter()
            .map(|s| s.mid_z_mm())
            .collect()
    } else {
        args[1..]
            .iter()
            .map(|s| s.parse::<f64>().with_context(|| format!("height {s:?}")))
            .collect::<Result<_>>()?
    };
    let tol = SliceTolerances {
        validate_regions: false,
        ..Default::default()
    };
    let start = Instant::now();
    let sections = slicer.sections_at(&heights, &tol)?;
    let seconds = start.elapsed().as_secs_f64();
    let out: Vec<serde_json::Value> = heights
        .iter()
        .zip(&sections)
        .map(|(z, s)| {
            serde_json::json!({
                "z_mm": z,
                "cut_z_mm": slicer.cut_height_mm(*z, &tol),
                "area_mm2": s.iter().map(|r| r.area()).sum::<f64>() + 0.0,
                "islands": s.len(),
            })
        })
        .collect();
    println!(
        "{}",
        serde_json::json!({ "mesh": path, "report": report, "sections": out, "seconds": seconds })
    );
    Ok(())
}
