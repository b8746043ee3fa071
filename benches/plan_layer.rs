//! Planning speed of one layer (issue: EDO layer planner): a 2,000-vertex region with
//! two holes, subdivided into m = 20 contours, nozzle 0.4 mm. Target: at most 5 ms per
//! layer on one core. How to measure, the latest figures and what was tried:
//! `benches/README.md`.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::plan::{plan_region, PlanOptions};
use std::hint::black_box;

#[path = "common/region.rs"]
mod region;
use region::{bench_design, bench_region};

fn bench(c: &mut Criterion) {
    let region = bench_region();
    let design = bench_design();
    // Choose R_mach so that eq (1) gives m = 20 for this region's L_short.
    let probe = plan_region(&region, 0, &design, &PlanOptions::new(1.0, 0.4)).unwrap();
    let opts = PlanOptions::new(probe.l_short_mm / 20.0, 0.4);
    let plan = plan_region(&region, 0, &design, &opts).unwrap();
    assert_eq!(plan.m, 20);
    eprintln!(
        "bench region: {:?} subdivision, m = {}, {} sub-regions, {} offsets",
        plan.method,
        plan.m,
        plan.sub_regions.len(),
        plan.sub_regions
            .iter()
            .map(|s| s.offsets.len())
            .sum::<usize>()
    );
    c.bench_function("plan_layer_2000v_2holes_m20", |b| {
        b.iter(|| plan_region(black_box(&region), 0, &design, &opts).unwrap())
    });
    // The same with the inner contours simplified at the 0.01 mm chord tolerance
    // instead of the default contour deviation (0.025 mm).
    let fine = PlanOptions {
        contour_deviation_mm: 0.01,
        ..opts.clone()
    };
    c.bench_function("plan_layer_2000v_2holes_m20_contours_0.01mm", |b| {
        b.iter(|| plan_region(black_box(&region), 0, &design, &fine).unwrap())
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
