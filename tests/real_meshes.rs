//! The shared real meshes (`../shared/meshes/` beside the repository): load, validate,
//! slice whole. Skipped with a note when the directory is missing.

use edo::mesh::{load_and_repair, MeshFormat, MeshLimits, RepairOptions};
use edo::slice::{slice_mesh, SliceError, SliceOptions, SliceTolerances};
use std::path::PathBuf;

fn mesh_bytes(name: &str) -> Option<Vec<u8>> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/meshes")
        .join(name);
    match std::fs::read(&p) {
        Ok(b) => Some(b),
        Err(e) => {
            eprintln!("note: skipping, {} not readable: {e}", p.display());
            None
        }
    }
}

#[test]
fn femur_and_hip_are_watertight_and_slice_whole() {
    for (name, layers_at_least) in [("femur.stl", 2000), ("hip.stl", 700)] {
        let Some(bytes) = mesh_bytes(name) else {
            return;
        };
        let (mesh, report) =
            load_and_repair(&bytes, &MeshLimits::default(), &RepairOptions::default()).unwrap();
        assert_eq!(report.format, Some(MeshFormat::StlBinary));
        assert!(report.is_watertight(), "{name}: {report:?}");
        assert!(report.volume_mm3 > 0.0);
        let (layers, srep) = slice_mesh(&mesh, &SliceOptions::uniform(0.2), None).unwrap();
        assert!(layers.len() >= layers_at_least, "{name}: {}", layers.len());
        assert_eq!(srep.gaps_closed_count, 0, "{name}");
        // Volume from the layers agrees with the mesh volume.
        let v: f64 = layers.iter().map(|l| l.area_mm2() * l.thickness_mm).sum();
        let e = (v - report.volume_mm3).abs() / report.volume_mm3;
        assert!(
            e < 0.005,
            "{name}: layer volume {v} vs mesh {}",
            report.volume_mm3
        );
    }
}

#[test]
fn benchy_stl_and_3mf_agree() {
    let (Some(stl), Some(tmf)) = (mesh_bytes("3DBenchy.stl"), mesh_bytes("3DBenchy.3mf")) else {
        return;
    };
    let limits = MeshLimits::default();
    let (a, ra) = load_and_repair(&stl, &limits, &RepairOptions::default()).unwrap();
    let (b, rb) = load_and_repair(&tmf, &limits, &RepairOptions::default()).unwrap();
    assert_eq!(rb.format, Some(MeshFormat::ThreeMf));
    assert_eq!(ra.triangles, rb.triangles);
    assert!(ra.is_watertight() && rb.is_watertight(), "{ra:?}");
    assert_eq!(ra.repairs.degenerate_removed, 8);
    for opts in [
        SliceOptions::uniform(0.2),
        SliceOptions {
            layer_min_mm: 0.1,
            layer_max_mm: 0.3,
            ..Default::default()
        },
    ] {
        let (la, _) = slice_mesh(&a, &opts, None).unwrap();
        let (lb, _) = slice_mesh(&b, &opts, None).unwrap();
        assert_eq!(la.len(), lb.len());
        for (x, y) in la.iter().zip(&lb) {
            assert!(
                (x.area_mm2() - y.area_mm2()).abs() <= 1e-3 * x.area_mm2().max(1.0),
                "z {} stl {} 3mf {}",
                x.z_mm,
                x.area_mm2(),
                y.area_mm2()
            );
        }
        let v: f64 = la.iter().map(|l| l.area_mm2() * l.thickness_mm).sum();
        assert!((v - ra.volume_mm3).abs() / ra.volume_mm3 < 0.01, "{v}");
    }
}

#[test]
fn open_bunny_is_repaired_or_refused_with_a_location() {
    let Some(bytes) = mesh_bytes("stanford-bunny.stl") else {
        return;
    };
    let (mesh, report) =
        load_and_repair(&bytes, &MeshLimits::default(), &RepairOptions::default()).unwrap();
    assert!(report.open_edges > 0, "the bunny is open");
    assert!(!report.is_watertight());
    assert!(!report.open_edge_samples_mm.is_empty());
    match slice_mesh(&mesh, &SliceOptions::uniform(0.2), None) {
        Ok((layers, srep)) => {
            eprintln!(
                "bunny: {} layers, {} gaps closed, largest {:.3} mm",
                layers.len(),
                srep.gaps_closed_count,
                srep.max_gap_closed_mm
            );
            assert!(srep.gaps_closed_count > 0);
            assert!(srep.max_gap_closed_mm <= SliceTolerances::default().max_gap_mm);
        }
        Err(e @ SliceError::OpenLoop { .. }) => {
            let msg = e.to_string();
            eprintln!("bunny refused: {msg}");
            assert!(msg.contains("z = ") && msg.contains("open"), "{msg}");
        }
        Err(e) => panic!("unexpected error: {e}"),
    }
    // With gap closing off, it is refused and the error says where.
    let strict = SliceOptions {
        tolerances: SliceTolerances {
            max_gap_mm: 0.0,
            ..Default::default()
        },
        ..SliceOptions::uniform(0.2)
    };
    let e = slice_mesh(&mesh, &strict, None).unwrap_err();
    let SliceError::OpenLoop { z_mm, x, y, .. } = e else {
        panic!("{e}")
    };
    assert!((0.0..=60.0).contains(&z_mm) && x.is_finite() && y.is_finite());
}
