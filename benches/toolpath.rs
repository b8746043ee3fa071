//! Whole-part process planning speed (issue 4): 3DBenchy.stl sliced at 0.3 mm, every layer
//! planned (nozzle 0.4, r_mach 1.6, growth rings), ordered, flow-raised and turned into
//! moves. Target: at most 10 s on 2 cores. Thin tips are planned with `thin_regions =
//! "fill"` (m = 1, islands narrower than a road skipped), so every layer is built.
//!
//! `coverage/hip_largest_layer_10um`: the coverage measure (docs/toolpath.md) of the hip's
//! largest layer as built (25.7 M part cells at 10 µm).
//!
//! Figures: `benches/README.md`.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::material::{Composition, GradientFunction};
use edo::pipeline::{job_layer_moves, layer_paths, ProcessSettings, StreamState};
use edo::plan::{plan_layer, GradientDesign, Pattern, PlanOptions};
use edo::toolpath::coverage::measure;
use rayon::prelude::*;
use std::time::Duration;

fn design() -> GradientDesign {
    GradientDesign {
        pattern: Pattern::GrowthRings,
        inner: Composition::new(vec![1.0, 0.0], 1e-9).unwrap(),
        outer: Composition::new(vec![0.0, 1.0], 1e-9).unwrap(),
        function: GradientFunction::LINEAR,
    }
}

fn benchy_to_moves(mesh: &edo::mesh::Mesh) -> u32 {
    let design = design();
    // A real part's tips are thinner than r_mach: plan them with m = 1 (`thin_regions =
    // "fill"`, as docs/job-format.md advises for meshes) rather than drop the layer.
    let mut opts = PlanOptions::new(1.6, 0.4);
    opts.thin_regions = edo::plan::ThinRegions::Fill;
    let s = ProcessSettings::for_nozzle(0.4);
    let (layers, _) =
        edo::slice::slice_mesh(mesh, &edo::slice::SliceOptions::uniform(0.3), None).unwrap();
    let plans: Vec<_> = layers
        .par_iter()
        .enumerate()
        .filter_map(|(k, l)| plan_layer(k, l.z_mm, l.thickness_mm, &l.islands, &design, &opts).ok())
        .collect();
    let moves = job_layer_moves(&plans, &s, 1, 0, &mut StreamState::new()).unwrap();
    moves.last().map_or(0, |l| l.next_index)
}

/// The largest layer of the hip (by island area) as built: its islands and roads.
fn hip_layer(mesh: &edo::mesh::Mesh) -> (Vec<edo::geom::Region>, Vec<edo::toolpath::ToolPath>) {
    let mut opts = PlanOptions::new(1.6, 0.4);
    opts.thin_regions = edo::plan::ThinRegions::Fill;
    let s = ProcessSettings::for_nozzle(0.4);
    let (layers, _) =
        edo::slice::slice_mesh(mesh, &edo::slice::SliceOptions::uniform(0.3), None).unwrap();
    let area = |l: &edo::slice::Layer| l.islands.iter().map(|r| r.area()).sum::<f64>();
    let l = layers
        .iter()
        .max_by(|a, b| area(a).total_cmp(&area(b)))
        .unwrap();
    let plan = plan_layer(0, l.z_mm, l.thickness_mm, &l.islands, &design(), &opts).unwrap();
    (
        l.islands.clone(),
        layer_paths(&plan, &s, &StreamState::new()),
    )
}

fn mesh(name: &str) -> Option<edo::mesh::Mesh> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/meshes")
        .join(name);
    match edo::mesh::path::load_path(&path, &Default::default(), &Default::default()) {
        Ok((mesh, _)) => Some(mesh),
        Err(_) => {
            eprintln!("{} not found: skipping", path.display());
            None
        }
    }
}

fn bench(c: &mut Criterion) {
    if let Some(hip) = mesh("hip.stl") {
        let (islands, paths) = hip_layer(&hip);
        let cov = measure(&islands, &paths, 0.4, 0.01);
        eprintln!(
            "hip's largest layer: {} part cells at {} mm, void {:.3} %",
            cov.part_cells,
            cov.cell_mm,
            100.0 * cov.void_fraction()
        );
        let mut g = c.benchmark_group("coverage");
        g.sample_size(10);
        g.bench_function("hip_largest_layer_10um", |b| {
            b.iter(|| measure(&islands, &paths, 0.4, 0.01))
        });
        g.finish();
    }
    let Some(mesh) = mesh("3DBenchy.stl") else {
        return;
    };
    eprintln!("3DBenchy to moves: {} moves", benchy_to_moves(&mesh));
    let mut g = c.benchmark_group("toolpath");
    g.sample_size(10).measurement_time(Duration::from_secs(20));
    g.bench_function("benchy_0.3mm_to_moves", |b| {
        b.iter(|| benchy_to_moves(&mesh))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
