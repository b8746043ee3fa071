//! Planning speed of one layer (issue: EDO layer planner): a 2,000-vertex region with
//! two holes, subdivided into m = 20 contours, nozzle 0.4 mm. Target: at most 5 ms per
//! layer on one core.

use criterion::{criterion_group, criterion_main, Criterion};
use edo::edo::{plan_region, GradientDesign, Pattern, PlanOptions};
use edo::geom::Region;
use edo::material::{Composition, GradientFunction};
use glam::DVec2;
use std::hint::black_box;

/// A wavy outline of 2,000 vertices around two round holes.
pub fn bench_region() -> Region {
    let outer: Vec<DVec2> = (0..2000)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / 2000.0;
            let r = 30.0 + 1.5 * (5.0 * a).sin() + 0.6 * (13.0 * a).cos();
            DVec2::new(a.cos(), a.sin()) * r
        })
        .collect();
    let hole = |c: DVec2| -> Vec<DVec2> {
        (0..96)
            .rev()
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / 96.0;
                c + DVec2::new(a.cos(), a.sin()) * 4.0
            })
            .collect()
    };
    Region::new(
        outer,
        vec![hole(DVec2::new(-11.0, 0.0)), hole(DVec2::new(11.0, 0.0))],
    )
}

fn bench(c: &mut Criterion) {
    let region = bench_region();
    let design = GradientDesign {
        pattern: Pattern::GrowthRings,
        inner: Composition::new(vec![1.0, 0.0], 1e-9).unwrap(),
        outer: Composition::new(vec![0.0, 1.0], 1e-9).unwrap(),
        function: GradientFunction::LINEAR,
    };
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
}

criterion_group!(benches, bench);
criterion_main!(benches);
