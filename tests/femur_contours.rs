//! The EDO planner on real layers of the graded femur job
//! (`config/examples/femur-graded.toml`), loaded as `edoctl plan` loads it: its contour
//! roads are clean loops. Needs the `daemon` feature for the command line's job loader.

use edo::geom::Path;
use edo::plan::{plan_layers, SubdivisionMethod};
use glam::DVec2;

/// Each vertex of a road where it turns, with the vertices before and after it
/// (every vertex of a loop; all but the ends of an open road).
fn turns(p: &Path) -> impl Iterator<Item = (DVec2, DVec2, DVec2)> + '_ {
    let n = p.points.len();
    let count = if p.closed { n } else { n.saturating_sub(2) };
    (0..count).map(move |k| (p.points[k], p.points[(k + 1) % n], p.points[(k + 2) % n]))
}

/// Contour roads of real layers do not double back on themselves: no vertex where
/// the road turns back by more than 150° with an edge beside it shorter than 0.2
/// mm (a spike; level-set tips on the medial axis turn as sharply but over edges
/// about a field cell long). Femur layers 65 and 1000 had such spikes where the
/// corner search between two crossings started from tangents that meet beyond
/// both (an S-bend); layer 110 a loop of C8 3 µm wide round a ridge of d (now
/// printed once along it). No contour is a loop round less than a line's area.
#[test]
fn femur_contours_have_no_spikes() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/femur-graded.toml");
    let job = edo::cli::plan::load_job(&path).unwrap();
    for k in [65, 110, 1000] {
        let (slices, _) = edo::cli::plan::job_layers(&job, &path, Some(k..k + 1), true).unwrap();
        let layers = plan_layers(&slices, &job.plan, None).unwrap();
        let mut checked = 0;
        for plan in layers.iter().flat_map(|l| &l.regions) {
            assert_eq!(plan.method, SubdivisionMethod::Distance, "layer {k}");
            for c in &plan.contours {
                for r in c.roads.iter().filter(|r| r.closed) {
                    let width = 2.0 * edo::geom::signed_area(&r.points).abs() / r.length_mm();
                    assert!(
                        width >= job.plan.contour_deviation_mm,
                        "layer {k} C{}: a loop {width:.4} mm wide at {:?}",
                        c.j,
                        r.points[0]
                    );
                }
                for (a, b, d) in c.roads.iter().flat_map(turns) {
                    let (u, v) = (b - a, d - b);
                    let shortest = u.length().min(v.length());
                    let cos = u.dot(v) / (u.length() * v.length());
                    assert!(
                        !(cos < 150f64.to_radians().cos() && shortest < 0.2),
                        "layer {k} C{} turns back at ({:.3}, {:.3}) (cos {cos:.3}, edge {shortest:.3} mm)",
                        c.j,
                        b.x,
                        b.y
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 100, "layer {k}: only {checked} contour vertices");
    }
}
