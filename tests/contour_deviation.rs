//! The contour deviation (`process.contour_deviation`, issue: EDO layer planner): the
//! inner level-set contours of the `plan_layer` bench region simplified at the default
//! 0.025 mm have fewer vertices than at the 0.01 mm chord tolerance, and each version
//! lies near the other. Both simplify traced level sets, keeping their vertices; the
//! trace leaves out crossings where the straight piece between their neighbours strays
//! at most half the deviation, so the coarse trace keeps a subset of the fine one's
//! crossings. A coarse vertex, on the fine trace, lies within 0.01 mm of the fine
//! contour; a fine vertex within half of 0.025 mm of the coarse trace's pieces, so within
//! 1.5 × 0.025 mm of the coarse contour. Options built in code keep to the job's
//! limits.

use edo::geom::SegmentIndex;
use edo::plan::{plan_region, PlanOptions, RegionPlan, SubdivisionMethod};
use glam::DVec2;

#[path = "../benches/common/region.rs"]
mod region;

fn plan_at(deviation_mm: f64) -> RegionPlan {
    let mut opts = PlanOptions::new(1.0, 0.4);
    opts.contour_deviation_mm = deviation_mm;
    plan_region(&region::bench_region(), 0, &region::bench_design(), &opts).unwrap()
}

/// The loops of inner contour C_j.
fn contour(plan: &RegionPlan, j: u32) -> Vec<Vec<DVec2>> {
    plan.contours[(j - 1) as usize]
        .roads
        .iter()
        .map(|r| r.points.clone())
        .collect()
}

fn index(loops: &[Vec<DVec2>]) -> SegmentIndex {
    let l: Vec<&[DVec2]> = loops.iter().map(|l| l.as_slice()).collect();
    SegmentIndex::new(&l, &[])
}

#[test]
fn contours_keep_to_the_contour_deviation() {
    let (fine, coarse) = (plan_at(0.01), plan_at(0.025));
    assert_eq!(fine.method, SubdivisionMethod::Distance);
    assert!(fine.m >= 3, "m = {}", fine.m);
    assert_eq!(fine.m, coarse.m);
    let (mut fine_count, mut coarse_count) = (0, 0);
    for j in 2..=fine.m {
        let (f, c) = (contour(&fine, j), contour(&coarse, j));
        fine_count += f.iter().map(Vec::len).sum::<usize>();
        coarse_count += c.iter().map(Vec::len).sum::<usize>();
        let (fi, ci) = (index(&f), index(&c));
        for p in f.iter().flatten() {
            let d = ci.distance(*p);
            assert!(
                d <= 1.5 * 0.025 + 1e-9,
                "C{j}: {p} is {d} mm from the coarse contour"
            );
        }
        for p in c.iter().flatten() {
            let d = fi.distance(*p);
            assert!(
                d <= 0.01 + 1e-9,
                "C{j}: {p} is {d} mm from the fine contour"
            );
        }
    }
    assert!(
        (coarse_count as f64) < 0.8 * fine_count as f64,
        "{coarse_count} vertices at 0.025 mm against {fine_count} at 0.01 mm"
    );
}

#[test]
fn options_built_in_code_keep_to_the_limits() {
    let fine = plan_at(0.01);
    // Not finite, or under the chord tolerance: the finest.
    assert_eq!(plan_at(f64::NAN).contours, fine.contours);
    assert_eq!(plan_at(f64::INFINITY).contours, fine.contours);
    assert_eq!(plan_at(0.0).contours, fine.contours);
    // Beyond a quarter of the nozzle (0.1 mm here): a quarter of the nozzle.
    assert_eq!(plan_at(1.0).contours, plan_at(0.1).contours);
    assert_ne!(plan_at(0.1).contours, fine.contours);
}
