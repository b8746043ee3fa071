//! `edoctl plan JOB.toml [--report FILE|-] [--svg DIR]`: plan a job offline.

use crate::edo::plan_layers;
use crate::job::{Geometry, Job};
use anyhow::{Context, Result};
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

/// Largest job file read, bytes (a job is a few kB; this keeps a wrong path from
/// reading a huge file).
pub const MAX_JOB_BYTES: u64 = 16 * 1024 * 1024;

#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    /// The job file (TOML, see docs/job-format.md).
    pub job: PathBuf,
    /// Write the plan report as JSON to FILE, or to standard output with "-".
    #[arg(long, value_name = "FILE|-")]
    pub report: Option<String>,
    /// Write one SVG preview per layer into DIR (created if missing).
    #[arg(long, value_name = "DIR")]
    pub svg: Option<PathBuf>,
}

/// Read a job file with a size limit and parse it.
pub fn load_job(path: &std::path::Path) -> Result<Job> {
    let meta = std::fs::metadata(path)
        .with_context(|| format!("cannot read job file {}", path.display()))?;
    if meta.len() > MAX_JOB_BYTES {
        anyhow::bail!(
            "job file {} is {} bytes, over the {} byte limit",
            path.display(),
            meta.len(),
            MAX_JOB_BYTES
        );
    }
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read job file {}", path.display()))?;
    Ok(Job::from_toml(&text, &path.display().to_string())?)
}

pub fn run(args: &PlanArgs) -> Result<()> {
    let job = load_job(&args.job)?;
    let slices = job.layer_slices();
    let started = Instant::now();
    let layers = plan_layers(&slices, &job.design, &job.plan)
        .with_context(|| format!("planning {}", args.job.display()))?;
    let planning_time_ms = started.elapsed().as_secs_f64() * 1e3;
    let report = crate::report::build(&job, &slices, &layers, planning_time_ms);

    let to_stdout = args.report.as_deref() == Some("-");
    let mut human: Box<dyn Write> = if to_stdout {
        Box::new(std::io::stderr())
    } else {
        Box::new(std::io::stdout())
    };
    if let Some(target) = &args.report {
        let json = serde_json::to_string_pretty(&report)?;
        if to_stdout {
            println!("{json}");
        } else {
            if let Some(parent) = std::path::Path::new(target)
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
            {
                std::fs::create_dir_all(parent)
                    .with_context(|| format!("cannot create {}", parent.display()))?;
            }
            std::fs::write(target, json + "\n")
                .with_context(|| format!("cannot write report {target}"))?;
        }
    }
    if let Some(dir) = &args.svg {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let Geometry::Extruded { .. } = &job.geometry;
        for (layer, slice) in layers.iter().zip(&slices) {
            let svg = crate::svg::layer_svg(
                layer,
                &crate::svg::PreviewInput {
                    job_name: &job.name,
                    materials: &job.materials,
                    nozzle_mm: job.plan.nozzle_mm,
                    islands: &slice.islands,
                },
            );
            let file = dir.join(format!("layer-{:04}.svg", layer.index));
            std::fs::write(&file, svg)
                .with_context(|| format!("cannot write {}", file.display()))?;
        }
    }
    let t = &report.totals;
    writeln!(
        human,
        "{}: {} layer(s) planned in {:.1} ms",
        job.name, t.layers, planning_time_ms
    )?;
    if let Some(l) = layers.first() {
        for r in &l.regions {
            writeln!(
                human,
                "  island {}: {:?} subdivision, m = {}, L_short = {:.3} mm, {} sub-regions, {} offsets",
                r.island,
                r.method,
                r.m,
                r.l_short_mm,
                r.sub_regions.len(),
                r.sub_regions.iter().map(|s| s.offsets.len()).sum::<usize>()
            )?;
        }
    }
    writeln!(
        human,
        "  roads: {:.1} mm of contours, {:.1} mm of equal distance offsets, {} paths",
        t.contour_length_mm, t.offset_length_mm, t.paths
    )?;
    writeln!(
        human,
        "  compact material data {} B, whole plan {} B, voxel grid at R_mach/4 {} B",
        t.compact_material_bytes, t.plan_bytes, t.voxel_grid_bytes
    )?;
    if let Some(dir) = &args.svg {
        writeln!(human, "  previews: {}/layer-*.svg", dir.display())?;
    }
    Ok(())
}
