//! Property tests of the EDO planner over random regions (issue: EDO layer planner).
//!
//! For random star and non-star outlines with zero, one or two holes, random machine
//! resolution and nozzle, and every pattern and subdivision method:
//! - the planner never panics (it returns a plan or a named error);
//! - every equal distance offset lies inside its sub-region;
//! - adjacent contours do not intersect;
//! - every composition sums to 1, and compositions change monotonically from Ci to Ce
//!   for a monotone f(d).

use edo::geom::Path;
use edo::geom::{point_segment_distance, signed_area, Region};
use edo::material::{Composition, GradientFunction};
use edo::plan::{
    offset_composition_eq6, plan_region, GradientDesign, Pattern, PlanOptions, RegionPlan,
    Subdivision,
};
use glam::DVec2;
use proptest::prelude::*;

fn star(centre: DVec2, radii: &[f64], phase: f64) -> Vec<DVec2> {
    let n = radii.len();
    (0..n)
        .map(|k| {
            let a = phase + std::f64::consts::TAU * k as f64 / n as f64;
            centre + DVec2::new(a.cos(), a.sin()) * radii[k]
        })
        .collect()
}

/// A random region: a star-shaped or notched (non-star) outline with 0–2 holes that
/// fit inside it.
fn region_strategy() -> impl Strategy<Value = Region> {
    (
        prop::collection::vec(22.0f64..34.0, 6..40),
        0usize..3,
        prop::collection::vec(2.0f64..5.0, 5..12),
        any::<bool>(),
        0.0f64..1.0,
    )
        .prop_map(|(radii, holes, hole_radii, notch, phase)| {
            let mut outer = star(DVec2::ZERO, &radii, phase);
            if notch {
                // Cut a deep notch into the outline: no longer star-shaped about the centre.
                let k = outer.len() / 2;
                let a = outer[k];
                let b = outer[(k + 1) % outer.len()];
                let mid = 0.5 * (a + b);
                let inward = mid * 0.55;
                let side = (b - a) * 0.15;
                outer.splice(
                    k + 1..k + 1,
                    [
                        mid * 0.9 - side,
                        inward - side,
                        inward + side,
                        mid * 0.9 + side,
                    ],
                );
            }
            let centres: &[DVec2] = match holes {
                0 => &[],
                1 => &[DVec2::new(1.0, -0.5)],
                _ => &[DVec2::new(-9.0, 0.5), DVec2::new(9.0, -0.5)],
            };
            let holes = centres
                .iter()
                .map(|c| {
                    let mut h = star(*c, &hole_radii, phase * 2.0);
                    h.reverse();
                    h
                })
                .collect();
            Region::new(outer, holes)
        })
}

fn pattern_strategy() -> impl Strategy<Value = (Pattern, Subdivision)> {
    prop_oneof![
        Just((Pattern::GrowthRings, Subdivision::Auto)),
        Just((Pattern::GrowthRings, Subdivision::Radial)),
        Just((Pattern::GrowthRings, Subdivision::Distance)),
        (1.0f64..6.0).prop_map(|d| (Pattern::Crown { depth_mm: d }, Subdivision::Auto)),
        (-90.0f64..90.0).prop_map(|a| (Pattern::Fibers { angle_deg: a }, Subdivision::Auto)),
    ]
}

fn function_strategy() -> impl Strategy<Value = GradientFunction> {
    prop_oneof![
        Just(GradientFunction::LINEAR),
        (0.3f64..3.0).prop_map(GradientFunction::Power),
        Just(GradientFunction::Smoothstep),
        Just(GradientFunction::Table(vec![
            [0.0, 0.0],
            [0.4, 0.7],
            [1.0, 1.0]
        ])),
    ]
}

/// Is `p` inside the (even-odd) area bounded by `loops`, or within `tol` of its boundary?
fn inside_or_on(p: DVec2, loops: &[&Vec<DVec2>], tol: f64) -> bool {
    let mut inside = false;
    for l in loops {
        if edo::geom::point_in_loop(p, l) {
            inside = !inside;
        }
        let n = l.len();
        for i in 0..n {
            if point_segment_distance(p, l[i], l[(i + 1) % n]) <= tol {
                return true;
            }
        }
    }
    inside
}

fn segments(p: &Path) -> Vec<(DVec2, DVec2)> {
    let n = p.points.len();
    let mut s: Vec<(DVec2, DVec2)> = p.points.windows(2).map(|w| (w[0], w[1])).collect();
    if p.closed && n > 2 {
        s.push((p.points[n - 1], p.points[0]));
    }
    s
}

/// Do the two segments properly cross (each strictly separates the other's ends by more
/// than `tol`)? Touching, as a contour that stops on another's road does, is no crossing.
fn properly_cross(p1: DVec2, p2: DVec2, q1: DVec2, q2: DVec2, tol: f64) -> bool {
    let side = |a: DVec2, b: DVec2, c: DVec2| {
        let ab = b - a;
        let len = ab.length();
        if len == 0.0 {
            0.0
        } else {
            ab.perp_dot(c - a) / len
        }
    };
    let (d1, d2) = (side(q1, q2, p1), side(q1, q2, p2));
    let (d3, d4) = (side(p1, p2, q1), side(p1, p2, q2));
    ((d1 > tol && d2 < -tol) || (d1 < -tol && d2 > tol))
        && ((d3 > tol && d4 < -tol) || (d3 < -tol && d4 > tol))
}

fn roads_cross(a: &[Path], b: &[Path]) -> Option<(DVec2, DVec2)> {
    let sa: Vec<_> = a.iter().flat_map(segments).collect();
    let sb: Vec<_> = b.iter().flat_map(segments).collect();
    for (p1, p2) in &sa {
        let (lo, hi) = (p1.min(*p2), p1.max(*p2));
        for (q1, q2) in &sb {
            if q1.max(*q2).cmplt(lo).any() || q1.min(*q2).cmpgt(hi).any() {
                continue;
            }
            if properly_cross(*p1, *p2, *q1, *q2, 1e-6) {
                return Some((*p1, *q1));
            }
        }
    }
    None
}

fn check_plan(
    plan: &RegionPlan,
    region: &Region,
    f: &GradientFunction,
    inner: &Composition,
    outer: &Composition,
) {
    // Every contour road lies in the part's material.
    let material: Vec<&Vec<DVec2>> = region.loops().collect();
    for c in &plan.contours {
        for p in &c.roads {
            for v in &p.points {
                assert!(
                    inside_or_on(*v, &material, 2e-3),
                    "C{} road vertex {v} lies outside the part",
                    c.j
                );
            }
        }
    }
    // Compositions sum to 1.
    for c in &plan.contours {
        let s: f64 = c.composition.fractions().iter().sum();
        assert!((s - 1.0).abs() < 1e-9, "C{} sums to {s}", c.j);
        assert!(c.composition.fractions().iter().all(|v| *v >= -1e-12));
    }
    // Monotone from Ci to Ce, material by material, contour by contour.
    if f.is_monotone() {
        for k in 0..inner.len() {
            let sign = (outer.fractions()[k] - inner.fractions()[k]).signum();
            for w in plan.contours.windows(2) {
                let step = w[1].composition.fractions()[k] - w[0].composition.fractions()[k];
                assert!(
                    step * sign >= -1e-12,
                    "material {k} not monotone between C{} and C{}",
                    w[0].j,
                    w[1].j
                );
            }
        }
    }
    for s in &plan.sub_regions {
        let loops: Vec<&Vec<DVec2>> = s.shape.iter().flat_map(|sh| sh.iter()).collect();
        for (k, paths) in s.offsets.iter().enumerate() {
            let m = offset_composition_eq6(plan, s, k as u32 + 1);
            let sum: f64 = m.fractions().iter().sum();
            assert!(
                (sum - 1.0).abs() < 1e-9,
                "S{} offset {} sums to {sum}",
                s.n,
                k + 1
            );
            if s.n > 0 {
                // Between its bounding contours' compositions.
                let (a, b) = (
                    &plan.contours[(s.n - 1) as usize].composition,
                    &plan.contours[s.n as usize].composition,
                );
                for q in 0..m.len() {
                    let (lo, hi) = (
                        a.fractions()[q].min(b.fractions()[q]),
                        a.fractions()[q].max(b.fractions()[q]),
                    );
                    assert!(m.fractions()[q] >= lo - 1e-12 && m.fractions()[q] <= hi + 1e-12);
                }
            }
            // Every offset lies inside its sub-region.
            for p in paths {
                for v in &p.points {
                    assert!(
                        inside_or_on(*v, &loops, 2e-3),
                        "S{} offset {} vertex {v} lies outside its sub-region",
                        s.n,
                        k + 1
                    );
                }
            }
        }
    }
    // Adjacent contours do not intersect.
    for w in plan.contours.windows(2) {
        if let Some((a, b)) = roads_cross(&w[0].roads, &w[1].roads) {
            panic!("C{} and C{} cross near {a} / {b}", w[0].j, w[1].j);
        }
    }
}

proptest! {
    // A fixed seed keeps CI deterministic; set PROPTEST_RNG_SEED / PROPTEST_CASES by
    // hand to explore further (the cases found that way are kept in the tests below).
    #![proptest_config(ProptestConfig {
        cases: 48,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0xED0_2026),
        ..ProptestConfig::default()
    })]

    #[test]
    fn planner_invariants(
        region in region_strategy(),
        (pattern, subdivision) in pattern_strategy(),
        function in function_strategy(),
        r_mach in 1.0f64..4.0,
        nozzle_ratio in 0.2f64..0.6,
        mix in 0.0f64..1.0,
    ) {
        prop_assume!(signed_area(&region.outer).abs() > 1.0);
        let nozzle = r_mach * nozzle_ratio;
        let mut opts = PlanOptions::new(r_mach, nozzle);
        opts.subdivision = subdivision;
        let inner = Composition::new(vec![1.0 - mix, mix, 0.0], 1e-9).unwrap();
        let outer = Composition::new(vec![0.0, 1.0 - mix, mix], 1e-9).unwrap();
        let design = GradientDesign { pattern, inner: inner.clone(), outer: outer.clone(), function: function.clone() };
        // Never panics: a plan or a named error.
        match plan_region(&region, 0, &design, &opts) {
            Ok(plan) => check_plan(&plan, &region, &function, &inner, &outer),
            Err(e) => prop_assert!(!e.to_string().is_empty()),
        }
    }
}
