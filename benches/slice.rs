//! Slicing speed on 3DBenchy (225k triangles): sections at 0.2 mm uniform and adaptive
//! 0.1–0.3 mm, plus indexing and load + repair. Target: sections ≤ 150 ms on 2 cores.
//!
//! `cargo bench --bench slice` (needs `../shared/meshes/3DBenchy.stl` beside the repo).
//! trimesh on the same work: `tests/compare_trimesh.py` prints both times per mesh.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::mesh::{load_and_repair, MeshLimits, RepairOptions};
use edo::slice::{SliceOptions, SliceTolerances, Slicer};
use std::hint::black_box;
use std::time::Duration;

fn benchy(c: &mut Criterion) {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/meshes/3DBenchy.stl");
    let Ok(bytes) = std::fs::read(&path) else {
        eprintln!("note: {} missing, benchmark skipped", path.display());
        return;
    };
    let limits = MeshLimits::default();
    let (mesh, _) =
        load_and_repair(&bytes, &limits, &RepairOptions::default()).expect("benchy loads");
    let slicer = Slicer::new(&mesh).expect("benchy indexes");
    let uniform = SliceOptions::uniform(0.2);
    let adaptive = SliceOptions {
        layer_min_mm: 0.1,
        layer_max_mm: 0.3,
        ..Default::default()
    };
    let uniform_spans = slicer.layer_spans(&uniform).expect("spans");
    let adaptive_spans = slicer.layer_spans(&adaptive).expect("spans");
    eprintln!(
        "benchy: {} triangles, {} uniform layers, {} adaptive layers",
        mesh.triangles.len(),
        uniform_spans.len(),
        adaptive_spans.len()
    );
    let unvalidated = SliceTolerances {
        validate_regions: false,
        ..Default::default()
    };

    let mut g = c.benchmark_group("benchy");
    g.sample_size(10).measurement_time(Duration::from_secs(5));
    g.bench_function("sections_uniform_0.2", |b| {
        b.iter(|| {
            black_box(
                slicer
                    .slice(&uniform_spans, &unvalidated, None)
                    .expect("slices"),
            )
        })
    });
    g.bench_function("sections_uniform_0.2_validated", |b| {
        b.iter(|| {
            black_box(
                slicer
                    .slice(&uniform_spans, &SliceTolerances::default(), None)
                    .expect("slices"),
            )
        })
    });
    g.bench_function("adaptive_heights_and_sections", |b| {
        b.iter(|| {
            let spans = slicer.layer_spans(&adaptive).expect("spans");
            black_box(slicer.slice(&spans, &unvalidated, None).expect("slices"))
        })
    });
    g.bench_function("index", |b| {
        b.iter(|| black_box(Slicer::new(&mesh).expect("index")))
    });
    g.bench_function("load_and_repair", |b| {
        b.iter(|| {
            black_box(load_and_repair(&bytes, &limits, &RepairOptions::default()).expect("loads"))
        })
    });
    g.finish();
}

criterion_group!(benches, benchy);
criterion_main!(benches);
