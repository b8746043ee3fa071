//! Loading: every format, every bad-file error, size limits, repairs; random bytes never
//! panic the loaders.

use edo::mesh::{
    load_and_repair, load_bytes, path::load_path, primitives, repair, Mesh, MeshError, MeshFormat,
    MeshLimits, RepairOptions,
};
use proptest::prelude::*;
use std::io::Write;

fn binary_stl(m: &Mesh, header: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8; 80];
    out[..header.len()].copy_from_slice(header);
    out.extend_from_slice(&(m.triangles.len() as u32).to_le_bytes());
    for t in 0..m.triangles.len() {
        out.extend_from_slice(&[0u8; 12]);
        for v in m.corners(t) {
            for c in v.to_array() {
                out.extend_from_slice(&(c as f32).to_le_bytes());
            }
        }
        out.extend_from_slice(&[0, 0]);
    }
    out
}

fn ascii_stl(m: &Mesh, first_line: &str) -> String {
    let mut s = format!("{first_line}\n");
    for t in 0..m.triangles.len() {
        s += "  facet normal 0 0 0\n    outer loop\n";
        for v in m.corners(t) {
            s += &format!("      vertex {} {} {}\n", v.x, v.y, v.z);
        }
        s += "    endloop\n  endfacet\n";
    }
    s + "endsolid test\n"
}

fn zip_of(parts: &[(&str, &str)]) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, body) in parts {
        w.start_file(*name, opts).unwrap();
        w.write_all(body.as_bytes()).unwrap();
    }
    w.finish().unwrap().into_inner()
}

fn model_xml(unit: &str, m: &Mesh, extra_objects: &str, build: &str) -> String {
    let mut s = format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<model unit="{unit}" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">
<resources><object id="1" type="model"><mesh><vertices>"#
    );
    for v in &m.vertices {
        s += &format!(r#"<vertex x="{}" y="{}" z="{}"/>"#, v.x, v.y, v.z);
    }
    s += "</vertices><triangles>";
    for t in &m.triangles {
        s += &format!(r#"<triangle v1="{}" v2="{}" v3="{}"/>"#, t[0], t[1], t[2]);
    }
    s += "</triangles></mesh></object>";
    s += extra_objects;
    s += "</resources><build>";
    s += build;
    s + "</build></model>"
}

const RELS: &str = r#"<?xml version="1.0" encoding="UTF-8"?>
<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">
<Relationship Target="/3D/3dmodel.model" Id="rel0" Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/>
</Relationships>"#;

fn part() -> Mesh {
    primitives::cylinder(5.0, 10.0, 16, 2)
}

fn limits() -> MeshLimits {
    MeshLimits::default()
}

#[test]
fn binary_and_ascii_stl_load_and_merge() {
    let m = part();
    for bytes in [
        binary_stl(&m, b"binary"),
        binary_stl(&m, b"solid but binary"),
        m.to_binary_stl().unwrap(),
        ascii_stl(&m, "solid test").into_bytes(),
        ascii_stl(&m, "solid").into_bytes(),
    ] {
        let (mesh, report) = load_and_repair(&bytes, &limits(), &RepairOptions::default())
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(mesh.triangles.len(), m.triangles.len());
        assert_eq!(mesh.vertices.len(), m.vertices.len());
        assert!(report.is_watertight());
        assert!(report.repairs.vertices_merged > 0);
        assert!(matches!(
            report.format,
            Some(MeshFormat::StlBinary) | Some(MeshFormat::StlAscii)
        ));
    }
}

#[test]
fn empty_and_short_files() {
    assert_eq!(load_bytes(b"", &limits()).unwrap_err(), MeshError::Empty);
    assert!(matches!(
        load_bytes(&[1, 2, 3, 0, 255], &limits()).unwrap_err(),
        MeshError::StlTruncatedHeader { size: 5 }
    ));
    assert_eq!(
        load_bytes(b"hello", &limits()).unwrap_err(),
        MeshError::UnknownFormat
    );
}

#[test]
fn truncated_binary_and_count_mismatch() {
    let good = binary_stl(&part(), b"x");
    let cut = &good[..good.len() - 7];
    let e = load_bytes(cut, &limits()).unwrap_err();
    assert!(matches!(e, MeshError::StlCountMismatch { .. }), "{e}");
    assert!(e.to_string().contains("truncated"), "{e}");
    let mut more = good.clone();
    more[80..84].copy_from_slice(&1_000_000u32.to_le_bytes());
    let e = load_bytes(&more, &limits()).unwrap_err();
    assert!(
        matches!(
            e,
            MeshError::StlCountMismatch {
                declared: 1_000_000,
                ..
            }
        ),
        "{e}"
    );
    let mut zero = good[..84].to_vec();
    zero[80..84].copy_from_slice(&0u32.to_le_bytes());
    assert_eq!(
        load_bytes(&zero, &limits()).unwrap_err(),
        MeshError::NoTriangles
    );
}

#[test]
fn ascii_garbage_and_nan() {
    let e = load_bytes(b"solid x\n  this is not a facet\n", &limits()).unwrap_err();
    assert!(matches!(e, MeshError::StlAscii { .. }), "{e}");
    let nan = ascii_stl(&part(), "solid t").replacen("vertex 5 0 0", "vertex NaN 0 0", 1);
    let e = load_bytes(nan.as_bytes(), &limits()).unwrap_err();
    assert!(
        matches!(e, MeshError::StlAscii { .. } | MeshError::NotFinite { .. }),
        "{e}"
    );
    let e = load_bytes(b"solid t\n", &limits()).unwrap_err();
    assert!(matches!(e, MeshError::StlAscii { .. }), "{e}");
}

#[test]
fn binary_nan_names_the_byte_offset() {
    let mut b = binary_stl(&part(), b"x");
    // Triangle 2, corner 1, x.
    let off = 84 + 2 * 50 + 12 + 12;
    b[off..off + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = load_bytes(&b, &limits()).unwrap_err();
    assert!(
        matches!(
            e,
            MeshError::NotFinite {
                triangle: 2,
                corner: 1,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains(&format!("byte offset {off}")), "{e}");
    let mut m = part();
    m.vertices[3].z = f64::INFINITY;
    assert!(matches!(
        repair(&m, &RepairOptions::default()),
        Err(MeshError::NotFinite { .. })
    ));
}

#[test]
fn size_limits() {
    let b = binary_stl(&part(), b"x");
    let small = MeshLimits {
        max_bytes: 100,
        ..limits()
    };
    assert!(matches!(
        load_bytes(&b, &small).unwrap_err(),
        MeshError::TooLarge { .. }
    ));
    let few = MeshLimits {
        max_triangles: 10,
        ..limits()
    };
    assert!(matches!(
        load_bytes(&b, &few).unwrap_err(),
        MeshError::TooManyTriangles { .. }
    ));
    let a = ascii_stl(&part(), "solid t");
    assert!(matches!(
        load_bytes(a.as_bytes(), &few).unwrap_err(),
        MeshError::TooManyTriangles { .. }
    ));
    let tmf = zip_of(&[
        ("_rels/.rels", RELS),
        (
            "3D/3dmodel.model",
            &model_xml("millimeter", &part(), "", r#"<item objectid="1"/>"#),
        ),
    ]);
    let e = load_bytes(&tmf, &few).unwrap_err();
    assert!(e.to_string().contains("max_triangles"), "{e}");
    // The path helper refuses by file size before reading.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("big.stl");
    std::fs::write(&p, &b).unwrap();
    assert!(matches!(
        load_path(&p, &small, &RepairOptions::default()).unwrap_err(),
        MeshError::TooLarge { .. }
    ));
    assert!(load_path(&p, &limits(), &RepairOptions::default()).is_ok());
    assert!(matches!(
        load_path(
            &dir.path().join("missing.stl"),
            &limits(),
            &RepairOptions::default()
        ),
        Err(MeshError::Io { .. })
    ));
}

#[test]
fn threemf_units_components_and_transforms() {
    let m = part();
    // Object 2 places object 1 twice via components; the build item moves it up by 1 cm.
    let extra = r#"<object id="2" type="model"><components>
        <component objectid="1"/>
        <component objectid="1" transform="1 0 0 0 1 0 0 0 1 3 0 0"/>
      </components></object>"#;
    let xml = model_xml(
        "centimeter",
        &m,
        extra,
        r#"<item objectid="2" transform="1 0 0 0 1 0 0 0 1 0 0 1"/>"#,
    );
    let bytes = zip_of(&[("_rels/.rels", RELS), ("3D/3dmodel.model", &xml)]);
    let (mesh, fmt) = load_bytes(&bytes, &limits()).unwrap();
    assert_eq!(fmt, MeshFormat::ThreeMf);
    assert_eq!(mesh.triangles.len(), 2 * m.triangles.len());
    let (lo, hi) = mesh.bounds().unwrap();
    // cm -> mm: radius 50, height 100, second copy shifted by 30 mm, all up by 10 mm.
    assert!(
        (lo.x + 50.0).abs() < 1e-9 && (hi.x - 80.0).abs() < 1e-9,
        "{lo} {hi}"
    );
    assert!(
        (lo.z - 10.0).abs() < 1e-9 && (hi.z - 110.0).abs() < 1e-9,
        "{lo} {hi}"
    );
    // Without _rels the default model path is used.
    let bytes = zip_of(&[("3D/3dmodel.model", &xml)]);
    assert!(load_bytes(&bytes, &limits()).is_ok());
}

/// A components bomb (9 levels of 10 components each over one small object) is counted
/// before anything is built: refused at once with the whole count, not after building
/// triangles up to the limit (10 million triangles took about 1 GB).
#[test]
fn threemf_component_bomb_is_counted_before_it_is_built() {
    let m = part();
    let mut levels = String::new();
    for id in 2..=10 {
        levels.push_str(&format!("<object id=\"{id}\" type=\"model\"><components>"));
        for _ in 0..10 {
            levels.push_str(&format!("<component objectid=\"{}\"/>", id - 1));
        }
        levels.push_str("</components></object>");
    }
    let xml = model_xml("millimeter", &m, &levels, r#"<item objectid="10"/>"#);
    let bytes = zip_of(&[("3D/3dmodel.model", &xml)]);
    let t = std::time::Instant::now();
    let e = load_bytes(&bytes, &limits()).unwrap_err();
    let want = m.triangles.len() as u64 * 1_000_000_000;
    assert!(
        matches!(e, MeshError::TooManyTriangles { count, .. } if count == want),
        "{e}"
    );
    assert!(
        t.elapsed() < std::time::Duration::from_secs(1),
        "{:?}",
        t.elapsed()
    );
}

#[test]
fn bad_threemf() {
    let e = load_bytes(b"PK\x03\x04 this is not really a zip", &limits()).unwrap_err();
    assert!(matches!(e, MeshError::ThreeMfZip(_)), "{e}");
    let e = load_bytes(&zip_of(&[("readme.txt", "hi")]), &limits()).unwrap_err();
    assert!(matches!(e, MeshError::ThreeMfNoModel(_)), "{e}");
    let e = load_bytes(
        &zip_of(&[("3D/3dmodel.model", "<model><resources><object")]),
        &limits(),
    )
    .unwrap_err();
    assert!(
        matches!(e, MeshError::ThreeMfXml { .. } | MeshError::ThreeMf { .. }),
        "{e}"
    );
    let cycle = r#"<object id="2"><components><component objectid="3"/></components></object>
                   <object id="3"><components><component objectid="2"/></components></object>"#;
    let xml = model_xml("millimeter", &part(), cycle, r#"<item objectid="2"/>"#);
    let e = load_bytes(&zip_of(&[("3D/3dmodel.model", &xml)]), &limits()).unwrap_err();
    assert!(e.to_string().contains("cycle"), "{e}");
    let xml = model_xml("millimeter", &part(), "", r#"<item objectid="9"/>"#);
    let e = load_bytes(&zip_of(&[("3D/3dmodel.model", &xml)]), &limits()).unwrap_err();
    assert!(e.to_string().contains("object 9"), "{e}");
    let mut bad = part();
    bad.triangles[0][1] = 999;
    let xml = model_xml("millimeter", &bad, "", r#"<item objectid="1"/>"#);
    let e = load_bytes(&zip_of(&[("3D/3dmodel.model", &xml)]), &limits()).unwrap_err();
    assert!(e.to_string().contains("vertex 999"), "{e}");
    let xml = model_xml("millimeter", &part(), "", "").replace("<build></build>", "<build/>");
    let e = load_bytes(&zip_of(&[("3D/3dmodel.model", &xml)]), &limits()).unwrap_err();
    assert!(e.to_string().contains("no items"), "{e}");
    let xml = model_xml("parsec", &part(), "", r#"<item objectid="1"/>"#);
    let e = load_bytes(&zip_of(&[("3D/3dmodel.model", &xml)]), &limits()).unwrap_err();
    assert!(e.to_string().contains("unit"), "{e}");
    let xml = model_xml("millimeter", &part(), "", r#"<item objectid="1"/>"#).replacen(
        r#"x="5""#,
        r#"x="inf""#,
        1,
    );
    let e = load_bytes(&zip_of(&[("3D/3dmodel.model", &xml)]), &limits()).unwrap_err();
    assert!(
        matches!(
            e,
            MeshError::NotFinite { .. } | MeshError::ThreeMfXml { .. }
        ),
        "{e}"
    );
}

#[test]
fn repairs_are_reported() {
    let mut m = part();
    let n = m.triangles.len();
    m.triangles.push(m.triangles[0]); // duplicate
    m.triangles
        .push([m.triangles[1][2], m.triangles[1][1], m.triangles[1][0]]); // reversed duplicate
    m.triangles.push([0, 0, 1]); // degenerate
    m.triangles[5].swap(0, 1); // inconsistent orientation
    let (fixed, report) = repair(&m, &RepairOptions::default()).unwrap();
    assert_eq!(fixed.triangles.len(), n);
    assert_eq!(report.repairs.duplicates_removed, 2);
    assert_eq!(report.repairs.degenerate_removed, 1);
    assert_eq!(report.inconsistent_orientation_edges, 3);
    assert_eq!(report.repairs.triangles_flipped, 1);
    assert!(report.is_watertight(), "{report:?}");
    assert!(report.volume_mm3 > 0.0);
    // An open mesh: drop a triangle.
    let mut open = part();
    open.triangles.remove(3);
    let (_, report) = repair(&open, &RepairOptions::default()).unwrap();
    assert_eq!(report.open_edges, 3);
    assert_eq!(report.open_edge_samples_mm.len(), 3);
    // A non-manifold edge: a fin glued onto an existing edge.
    let mut fin = part();
    let [a, b, _] = fin.triangles[0];
    fin.vertices.push(glam::DVec3::new(20.0, 20.0, 20.0));
    fin.triangles.push([a, b, fin.vertices.len() as u32 - 1]);
    let (_, report) = repair(&fin, &RepairOptions::default()).unwrap();
    assert_eq!(report.non_manifold_edges, 1);
    let json = serde_json::to_string(&report).unwrap();
    assert!(json.contains("\"non_manifold_edges\":1"));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        if let Ok((m, _)) = load_bytes(&bytes, &limits()) {
            let _ = repair(&m, &RepairOptions::default());
        }
    }

    #[test]
    fn prefixed_random_bytes_never_panic(
        kind in 0usize..3,
        tail in proptest::collection::vec(any::<u8>(), 0..400),
    ) {
        let mut bytes: Vec<u8> = match kind {
            0 => b"solid x\n".to_vec(),
            1 => b"PK\x03\x04".to_vec(),
            _ => {
                let mut h = vec![0u8; 80];
                h.extend_from_slice(&((tail.len() / 50) as u32).to_le_bytes());
                h
            }
        };
        bytes.extend_from_slice(&tail);
        if let Ok((m, _)) = load_bytes(&bytes, &limits()) {
            let _ = repair(&m, &RepairOptions::default());
        }
    }

    #[test]
    fn corrupted_files_never_panic(
        which in 0usize..3,
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        cut in any::<prop::sample::Index>(),
    ) {
        let m = primitives::cylinder(2.0, 3.0, 6, 1);
        let mut bytes = match which {
            0 => binary_stl(&m, b"x"),
            1 => ascii_stl(&m, "solid t").into_bytes(),
            _ => zip_of(&[
                ("_rels/.rels", RELS),
                ("3D/3dmodel.model", &model_xml("millimeter", &m, "", r#"<item objectid="1"/>"#)),
            ]),
        };
        for (i, b) in flips {
            let k = i.index(bytes.len());
            bytes[k] = b;
        }
        if cut.index(4) == 0 {
            let k = cut.index(bytes.len());
            bytes.truncate(k);
        }
        if let Ok((m, _)) = load_bytes(&bytes, &limits()) {
            if let Ok((m, _)) = repair(&m, &RepairOptions::default()) {
                let _ = edo::slice::slice_mesh(&m, &edo::slice::SliceOptions::uniform(0.5), None);
            }
        }
    }
}

/// Writing STL refuses a triangle whose vertex index is out of range instead of panicking.
#[test]
fn binary_stl_writer_refuses_bad_indices() {
    let mut m = part();
    m.triangles[0][1] = m.vertices.len() as u32;
    assert!(m.to_binary_stl().is_err());
}
