//! The bench region of `benches/plan_layer.rs` and its gradient design, shared with
//! `examples/plan_compare.rs` and `tests/contour_deviation.rs`.

use edo::geom::Region;
use edo::material::{Composition, GradientFunction};
use edo::plan::{GradientDesign, Pattern};
use glam::DVec2;

/// Growth rings from pure material A at the holes to pure B at the outer loop, linear.
pub fn bench_design() -> GradientDesign {
    let pure = |k: usize| {
        let mut f = vec![0.0; 2];
        f[k] = 1.0;
        Composition::new(f, 1e-9).expect("a pure material's fractions sum to 1")
    };
    GradientDesign {
        pattern: Pattern::GrowthRings,
        inner: pure(0),
        outer: pure(1),
        function: GradientFunction::LINEAR,
    }
}

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
