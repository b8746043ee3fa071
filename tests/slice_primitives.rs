//! Sections of generated primitives against their analytic areas, and adaptive heights.

use edo::mesh::{primitives, repair, Mesh, RepairOptions};
use edo::slice::{slice_mesh, AdaptiveCriterion, SliceOptions, SliceTolerances, Slicer};
use std::f64::consts::PI;

fn repaired(m: &Mesh) -> Mesh {
    let (m, report) = repair(m, &RepairOptions::default()).expect("primitive repairs");
    assert!(report.is_watertight(), "{report:?}");
    assert!(report.volume_mm3 > 0.0, "outward orientation: {report:?}");
    m
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b
}

#[test]
fn cylinder_layers_match_polygon_area() {
    let n = 128;
    let m = repaired(&primitives::cylinder(10.0, 20.0, n, 7));
    let (layers, report) = slice_mesh(&m, &SliceOptions::uniform(0.2), None).unwrap();
    assert_eq!(layers.len(), 100);
    assert_eq!(report.gaps_closed_count, 0);
    let exact = primitives::ngon_area(10.0, n);
    assert!(rel(exact, PI * 100.0) < 0.005);
    for l in &layers {
        assert_eq!(l.islands.len(), 1, "z {}", l.z_mm);
        assert!(l.islands[0].holes.is_empty());
        assert!(
            rel(l.area_mm2(), exact) < 1e-9,
            "z {} area {}",
            l.z_mm,
            l.area_mm2()
        );
        assert!(rel(l.area_mm2(), PI * 100.0) < 0.005);
    }
}

#[test]
fn planes_through_vertex_rings_are_robust() {
    // The cylinder has rings of vertices every 20/7 mm and flat caps; cut exactly there.
    let m = repaired(&primitives::cylinder(5.0, 20.0, 64, 4));
    let slicer = Slicer::new(&m).unwrap();
    // Symbolic perturbation only (no plane clearance).
    let symbolic = SliceTolerances {
        plane_clearance_mm: 0.0,
        ..Default::default()
    };
    let sections = slicer
        .sections_at(&[5.0, 10.0, 15.0, 0.0, 20.0], &symbolic)
        .unwrap();
    let exact = primitives::ngon_area(5.0, 64);
    for s in &sections[..3] {
        assert_eq!(s.len(), 1);
        assert!(rel(s[0].area(), exact) < 1e-9);
    }
    // At the bottom face every vertex counts as above the plane: nothing is cut. At the top
    // face the plane is taken just below the vertices: the full section.
    assert!(sections[3].is_empty());
    assert_eq!(sections[4].len(), 1);
    assert!(rel(sections[4][0].area(), exact) < 1e-9);
    // With the default clearance, planes move 0.1 µm up off the vertex heights (and
    // corners cut within collinear_mm change the area by < 1e-6).
    let moved = slicer
        .sections_at(&[5.0, 10.0, 0.0, 20.0], &SliceTolerances::default())
        .unwrap();
    assert!(rel(moved[0][0].area(), exact) < 1e-6);
    assert!(rel(moved[1][0].area(), exact) < 1e-6);
    assert_eq!(moved[2].len(), 1);
    assert!(moved[3].is_empty());
}

#[test]
fn tube_has_a_hole() {
    let n = 128;
    let m = repaired(&primitives::tube(4.0, 10.0, 10.0, n));
    let (layers, _) = slice_mesh(&m, &SliceOptions::uniform(0.25), None).unwrap();
    let exact = primitives::ngon_area(10.0, n) - primitives::ngon_area(4.0, n);
    for l in &layers {
        assert_eq!(l.islands.len(), 1);
        assert_eq!(l.islands[0].holes.len(), 1);
        assert!(rel(l.area_mm2(), exact) < 1e-9);
        assert!(rel(l.area_mm2(), PI * (100.0 - 16.0)) < 0.005);
    }
}

#[test]
fn nested_islands_inside_holes() {
    // A tube with a smaller solid cylinder standing in its hole: island, hole, island.
    let mut m = primitives::tube(6.0, 10.0, 10.0, 96);
    let inner = primitives::cylinder(3.0, 10.0, 96, 1);
    let base = m.vertices.len() as u32;
    m.vertices.extend(inner.vertices);
    m.triangles
        .extend(inner.triangles.iter().map(|t| t.map(|i| i + base)));
    let m = repaired(&m);
    let (layers, _) = slice_mesh(&m, &SliceOptions::uniform(1.0), None).unwrap();
    for l in &layers {
        assert_eq!(l.islands.len(), 2, "z {}", l.z_mm);
        let with_hole = l.islands.iter().filter(|r| r.holes.len() == 1).count();
        assert_eq!(with_hole, 1);
        let exact = primitives::ngon_area(10.0, 96) - primitives::ngon_area(6.0, 96)
            + primitives::ngon_area(3.0, 96);
        assert!(rel(l.area_mm2(), exact) < 1e-9);
    }
}

#[test]
fn sphere_sections_match_circles() {
    let r = 10.0;
    let m = repaired(&primitives::sphere(r, 256, 128));
    let (layers, _) = slice_mesh(&m, &SliceOptions::uniform(0.2), None).unwrap();
    assert_eq!(layers.len(), 100);
    let mut checked = 0;
    for l in &layers {
        let dz = l.mid_z_mm() - r;
        let rho2 = r * r - dz * dz;
        // Away from the poles (|dz| < 0.9 r) the tessellation error is below 0.5 %.
        if dz.abs() < 0.9 * r {
            let e = rel(l.area_mm2(), PI * rho2);
            assert!(
                e < 0.005,
                "z {} area {} exact {} ({e})",
                l.mid_z_mm(),
                l.area_mm2(),
                PI * rho2
            );
            checked += 1;
        }
    }
    assert!(checked > 80);
}

#[test]
fn cone_sections_match() {
    let (r, h, n) = (10.0, 30.0, 256);
    let m = repaired(&primitives::cone(r, h, n));
    let (layers, _) = slice_mesh(&m, &SliceOptions::uniform(0.3), None).unwrap();
    for l in layers.iter().filter(|l| l.mid_z_mm() < 0.95 * h) {
        let rho = r * (1.0 - l.mid_z_mm() / h);
        assert!(rel(l.area_mm2(), primitives::ngon_area(rho, n)) < 1e-9);
        assert!(rel(l.area_mm2(), PI * rho * rho) < 0.005);
    }
}

fn adaptive(criterion: AdaptiveCriterion) -> SliceOptions<'static> {
    SliceOptions {
        layer_min_mm: 0.05,
        layer_max_mm: 0.4,
        cusp_mm: 0.05,
        criterion,
        ..Default::default()
    }
}

#[test]
fn adaptive_is_thinner_where_the_sphere_is_flatter() {
    let r = 10.0;
    let m = repaired(&primitives::sphere(r, 128, 64));
    for criterion in [AdaptiveCriterion::CuspHeight, AdaptiveCriterion::PrusaArea] {
        let slicer = Slicer::new(&m).unwrap();
        let spans = slicer.layer_spans(&adaptive(criterion)).unwrap();
        // Contiguous, within bounds, covering the part.
        for w in spans.windows(2) {
            assert!((w[0].z_top_mm() - w[1].z_bottom_mm).abs() < 1e-9);
        }
        for s in &spans {
            assert!(s.thickness_mm >= 0.05 - 1e-12 && s.thickness_mm <= 0.4 + 1e-12);
        }
        assert!((spans.last().unwrap().z_top_mm() - 2.0 * r).abs() < 0.05);
        let near = |z: f64| {
            spans
                .iter()
                .find(|s| s.z_bottom_mm <= z && z < s.z_top_mm())
                .unwrap()
                .thickness_mm
        };
        // Flatter towards the poles: strictly thinner, monotonically in steps.
        let (pole, mid, equator) = (near(0.5), near(4.0), near(r));
        assert!(
            pole < mid && mid < equator,
            "{criterion:?}: {pole} {mid} {equator}"
        );
        assert!(near(2.0 * r - 0.5) < near(r + 6.0));
    }
}

#[test]
fn adaptive_is_thinner_on_the_flatter_cone() {
    let steep = repaired(&primitives::cone(5.0, 20.0, 64));
    let flat = repaired(&primitives::cone(20.0, 5.0, 64));
    let opts = adaptive(AdaptiveCriterion::CuspHeight);
    let t = |m: &Mesh| {
        let s = Slicer::new(m).unwrap().layer_spans(&opts).unwrap();
        s[s.len() / 2].thickness_mm
    };
    assert!(t(&flat) < t(&steep), "{} {}", t(&flat), t(&steep));
    // Cusp criterion: h = c / cos(normal, z).
    let cos_flat = 20.0 / (20.0f64 * 20.0 + 5.0 * 5.0).sqrt();
    assert!(
        (t(&flat) - (0.05 / cos_flat).max(0.05)).abs() < 1e-4,
        "{} {}",
        t(&flat),
        0.05 / cos_flat
    );
}

#[test]
fn z_limit_hook_caps_thickness() {
    let m = repaired(&primitives::cylinder(5.0, 10.0, 32, 1));
    let limit = |z: f64| if z > 5.0 { 0.1 } else { f64::INFINITY };
    let opts = SliceOptions {
        layer_min_mm: 0.05,
        layer_max_mm: 0.4,
        max_thickness_at: Some(&limit),
        ..Default::default()
    };
    let spans = Slicer::new(&m).unwrap().layer_spans(&opts).unwrap();
    for s in &spans {
        if s.z_bottom_mm > 5.0 + 1e-9 {
            assert!(s.thickness_mm <= 0.1 + 1e-12, "{s:?}");
        } else if s.z_top_mm() < 4.5 {
            assert!((s.thickness_mm - 0.4).abs() < 1e-12, "{s:?}");
        }
    }
}

#[test]
fn progress_reaches_total() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let m = repaired(&primitives::cylinder(5.0, 10.0, 32, 1));
    let max = AtomicUsize::new(0);
    let cb = |done: usize, total: usize| {
        assert_eq!(total, 50);
        max.fetch_max(done, Ordering::Relaxed);
    };
    slice_mesh(&m, &SliceOptions::uniform(0.2), Some(&cb)).unwrap();
    assert_eq!(max.load(Ordering::Relaxed), 50);
}

#[test]
fn unusable_meshes_are_errors() {
    let mut m = primitives::cylinder(1.0, 1.0, 8, 1);
    m.triangles[2][1] = 10_000;
    assert!(matches!(
        slice_mesh(&m, &SliceOptions::uniform(0.2), None),
        Err(edo::slice::SliceError::BadMesh(_))
    ));
    assert!(matches!(
        slice_mesh(&Mesh::default(), &SliceOptions::uniform(0.2), None),
        Err(edo::slice::SliceError::Empty)
    ));
    let m = primitives::cylinder(1.0, 1.0, 8, 1);
    for (lo, hi) in [
        (0.0, 0.2),
        (0.3, 0.2),
        (f64::NAN, 0.2),
        (0.1, f64::INFINITY),
    ] {
        let o = SliceOptions {
            layer_min_mm: lo,
            layer_max_mm: hi,
            ..Default::default()
        };
        assert!(matches!(
            slice_mesh(&m, &o, None),
            Err(edo::slice::SliceError::BadOptions(_))
        ));
    }
}

mod random_soup {
    use super::*;
    use glam::DVec3;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

        /// Triangle soups on a coarse grid (vertices on planes, horizontal facets, open and
        /// non-manifold edges everywhere): slicing returns layers or an error, never panics.
        #[test]
        fn slicing_soup_never_panics(
            pts in proptest::collection::vec((0i32..5, 0i32..5, 0i32..5), 4..20),
            tris in proptest::collection::vec((0usize..20, 0usize..20, 0usize..20), 1..40),
            adaptive in any::<bool>(),
        ) {
            let vertices: Vec<DVec3> = pts
                .iter()
                .map(|&(x, y, z)| DVec3::new(x as f64, y as f64, z as f64 * 0.25))
                .collect();
            let n = vertices.len();
            let triangles = tris
                .iter()
                .map(|&(a, b, c)| [(a % n) as u32, (b % n) as u32, (c % n) as u32])
                .collect();
            let m = Mesh { vertices, triangles };
            if let Ok((m, _)) = repair(&m, &RepairOptions::default()) {
                let opts = if adaptive {
                    SliceOptions { layer_min_mm: 0.05, layer_max_mm: 0.3, ..Default::default() }
                } else {
                    SliceOptions::uniform(0.25)
                };
                let _ = slice_mesh(&m, &opts, None);
            }
        }
    }
}
