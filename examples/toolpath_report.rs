//! Toolpath figures for the report: coverage (void / overlap / outside) of the example
//! jobs and of sampled layers of the shared meshes, and the whole 3DBenchy to moves
//! (time, moves). Run: `cargo run --release --example toolpath_report [CELL_MM]`;
//! peak memory with `/usr/bin/time -v`.

use edo::geom::Region;
use edo::material::{Composition, GradientFunction};
use edo::pipeline::{layer_paths, moves_for_paths, ProcessSettings, StreamState};
use edo::plan::{plan_layer, plan_layers, GradientDesign, Pattern, PlanOptions};
use edo::toolpath::coverage::{measure, Coverage};
use rayon::prelude::*;
use std::time::Instant;

fn line(name: &str, c: &Coverage, raised: &Coverage) {
    println!(
        "{name:<28} void {:>6.3} %  (no flow raise {:>6.3} %)  overlap {:>6.3} %  outside {:>6.3} %",
        100.0 * raised.void_fraction(),
        100.0 * c.void_fraction(),
        100.0 * raised.overlap_fraction(),
        100.0 * raised.outside_fraction()
    );
}

fn coverage_pair(
    islands: &[Region],
    layer: &edo::plan::LayerPlan,
    s: &ProcessSettings,
    cell: f64,
) -> (Coverage, Coverage) {
    let mut plain = s.clone();
    plain.flow_raise = false;
    plain.gap_fill = false;
    let st = StreamState::new();
    let a = measure(
        islands,
        &layer_paths(layer, &plain, &st),
        s.road_width(),
        cell,
    );
    let b = measure(islands, &layer_paths(layer, s, &st), s.road_width(), cell);
    (a, b)
}

fn main() -> anyhow::Result<()> {
    let cell: f64 = std::env::args()
        .nth(1)
        .map(|a| a.parse())
        .transpose()?
        .unwrap_or(0.01);
    println!("coverage at {} µm cells", cell * 1000.0);
    for name in ["paper-annulus", "tooth-crown", "fibers", "non-star"] {
        example_job(name, cell)?;
    }
    let design = GradientDesign {
        pattern: Pattern::GrowthRings,
        inner: Composition::new(vec![1.0, 0.0], 1e-9)?,
        outer: Composition::new(vec![0.0, 1.0], 1e-9)?,
        function: GradientFunction::LINEAR,
    };
    // A real part's tips are thinner than r_mach: plan them with m = 1 (`thin_regions =
    // "fill"`, as docs/job-format.md advises for meshes) rather than drop the layer.
    let mut opts = PlanOptions::new(1.6, 0.4);
    opts.thin_regions = edo::plan::ThinRegions::Fill;
    let s = ProcessSettings::for_nozzle(0.4);
    let meshes: &[&str] = if std::env::args().nth(2).as_deref() == Some("quick") {
        &["3DBenchy.stl"]
    } else {
        &["3DBenchy.stl", "femur.stl", "hip.stl"]
    };
    for mesh in meshes {
        whole_mesh(mesh, &design, &opts, &s, cell)?;
    }
    Ok(())
}

/// An example job's first layer: coverage without and with the flow raise, and the
/// composition error of its first three layers with a 2 µL dead volume, without and
/// with the mixing lead.
fn example_job(name: &str, cell: f64) -> anyhow::Result<()> {
    let root = env!("CARGO_MANIFEST_DIR");
    let job = edo::cli::plan::load_job(std::path::Path::new(&format!(
        "{root}/config/examples/{name}.toml"
    )))?;
    let slices = job.layer_slices(0, job.extruded_layers().unwrap_or_default());
    let layers = plan_layers(&slices[..1], &job.plan, None)?;
    let s = ProcessSettings::for_nozzle(job.plan.nozzle_mm);
    let (a, b) = coverage_pair(&slices[0].layer.islands, &layers[0], &s, cell);
    line(name, &a, &b);
    for lead in [false, true] {
        let mut s2 = s.clone();
        s2.v_dead_ul = 2.0;
        s2.mixing_lead = lead;
        let mut st = StreamState::new();
        let mut idx = 0;
        let (mut mean, mut max, mut n) = (0.0, 0.0f64, 0.0);
        for l in &plan_layers(&slices[..slices.len().min(3)], &job.plan, None)? {
            let out = edo::pipeline::layer_moves(l, &s2, 1, idx, &mut st)?;
            idx = out.next_index;
            mean += out.stats.composition_error_mean;
            max = max.max(out.stats.composition_error_max);
            n += 1.0;
        }
        println!(
            "  V_dead 2 uL, lead {lead}: composition error mean {:.4}, max {:.4}",
            mean / n,
            max
        );
    }
    Ok(())
}

/// A mesh from `../shared/meshes` whole: slice and plan time, paths and moves time,
/// moves and lengths, and coverage of every 10th plannable layer.
fn whole_mesh(
    mesh: &str,
    design: &GradientDesign,
    opts: &PlanOptions,
    s: &ProcessSettings,
    cell: f64,
) -> anyhow::Result<()> {
    let path = format!("{}/../shared/meshes/{mesh}", env!("CARGO_MANIFEST_DIR"));
    let (m, _) = edo::mesh::path::load_path(
        std::path::Path::new(&path),
        &Default::default(),
        &Default::default(),
    )?;
    let t0 = Instant::now();
    let (layers, _) = edo::slice::slice_mesh(&m, &edo::slice::SliceOptions::uniform(0.3), None)?;
    let plans: Vec<_> = layers
        .par_iter()
        .enumerate()
        .map(|(k, l)| plan_layer(k, l.z_mm, l.thickness_mm, &l.islands, design, opts))
        .collect();
    let planned = t0.elapsed();
    let failed = plans.iter().filter(|p| p.is_err()).count();
    // Paths, then moves in order (the stream state is sequential).
    let t1 = Instant::now();
    let ok: Vec<&edo::plan::LayerPlan> = plans.iter().filter_map(|p| p.as_ref().ok()).collect();
    let mut state = StreamState::new();
    let mut index = 0u32;
    let mut travel = 0.0;
    let mut extruded = 0.0;
    for l in &ok {
        let paths = layer_paths(l, s, &state);
        let out = moves_for_paths(l, paths, s, 1, index, &mut state)?;
        index = out.next_index;
        travel += out.stats.travel_mm;
        extruded += out.stats.extruded_mm;
    }
    let moved = t1.elapsed();
    println!(
        "{mesh}: {} layers ({failed} not plannable), slice+plan {:.2} s, paths+moves {:.2} s, {index} moves, road {:.0} mm, travel {:.0} mm",
        layers.len(),
        planned.as_secs_f64(),
        moved.as_secs_f64(),
        extruded,
        travel
    );
    let (mut a_sum, mut b_sum) = (Coverage::default(), Coverage::default());
    let mut worst: (f64, usize) = (0.0, 0);
    for (k, l) in layers.iter().enumerate().step_by(10) {
        if let Ok(p) = &plans[k] {
            let (a, b) = coverage_pair(&l.islands, p, s, cell);
            if b.void_fraction() > worst.0 {
                worst = (b.void_fraction(), k);
            }
            a_sum.add(&a);
            b_sum.add(&b);
        }
    }
    line(&format!("{mesh} (every 10th)"), &a_sum, &b_sum);
    println!("  worst layer {} void {:.3} %", worst.1, 100.0 * worst.0);
    Ok(())
}
