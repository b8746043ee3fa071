//! Whole-part process planning speed (issue 4): 3DBenchy.stl sliced at 0.3 mm, every layer
//! planned (nozzle 0.4, r_mach 1.6, growth rings), ordered, flow-raised and turned into
//! moves. Target: at most 10 s on 2 cores. Thin tips are planned with `thin_regions =
//! "fill"` (m = 1, islands narrower than a road skipped), so every layer is built.
//!
//! 2026-12-01, with width matching traced against the part boundary and gap fill:
//! 8.56 s criterion median (8.15–9.02 s), 484,507 moves (was 3.23 s before both).
//! Later that day, with slanted road ends continued into their corners and boundary rays
//! and road probes bounded by their reach: 8.53 s (7.89–9.16 s, machine idle), 484,509
//! moves. On one core over Benchy's layers the flow raise takes 2.65 s (4.39 s before
//! the bounded probes), the slanted ends 0.09 s (no Benchy end qualifies), gap fill 4.6 s.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::edo::{plan_layer, GradientDesign, Pattern, PlanOptions};
use edo::material::{Composition, GradientFunction};
use edo::pipeline::{layer_paths, moves_for_paths, ProcessSettings, StreamState};
use rayon::prelude::*;
use std::time::Duration;

fn benchy_to_moves(mesh: &edo::mesh::Mesh) -> u32 {
    let design = GradientDesign {
        pattern: Pattern::GrowthRings,
        inner: Composition::new(vec![1.0, 0.0], 1e-9).unwrap(),
        outer: Composition::new(vec![0.0, 1.0], 1e-9).unwrap(),
        function: GradientFunction::LINEAR,
    };
    // A real part's tips are thinner than r_mach: plan them with m = 1 (`thin_regions =
    // "fill"`, as docs/job-format.md advises for meshes) rather than drop the layer.
    let mut opts = PlanOptions::new(1.6, 0.4);
    opts.thin_regions = edo::edo::ThinRegions::Fill;
    let s = ProcessSettings::for_nozzle(0.4);
    let (layers, _) =
        edo::slice::slice_mesh(mesh, &edo::slice::SliceOptions::uniform(0.3), None).unwrap();
    let plans: Vec<_> = layers
        .par_iter()
        .enumerate()
        .filter_map(|(k, l)| plan_layer(k, l.z_mm, l.thickness_mm, &l.islands, &design, &opts).ok())
        .collect();
    let mut state = StreamState::new();
    let mut index = 0;
    for l in &plans {
        let paths = layer_paths(l, &s, &state);
        index = moves_for_paths(l, paths, &s, 1, index, &mut state)
            .unwrap()
            .next_index;
    }
    index
}

fn bench(c: &mut Criterion) {
    let path = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/meshes/3DBenchy.stl"
    ));
    let Ok((mesh, _)) = edo::mesh::path::load_path(path, &Default::default(), &Default::default())
    else {
        eprintln!("{} not found: skipping", path.display());
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
