//! Closed triangulated primitives with known cross-sections, for tests, benchmarks and
//! examples: cylinder, tube, UV sphere and cone, all with outward orientation, their axis
//! on Z and their base at z = 0 (the sphere's centre at z = r).

use super::Mesh;
use glam::DVec3;
use std::f64::consts::TAU;

fn ring(m: &mut Mesh, r: f64, z: f64, n: usize) -> u32 {
    let base = m.vertices.len() as u32;
    for i in 0..n {
        let a = TAU * i as f64 / n as f64;
        m.vertices.push(DVec3::new(r * a.cos(), r * a.sin(), z));
    }
    base
}

/// Quads between two rings of `n` vertices; `outward` picks the winding.
fn band(m: &mut Mesh, lo: u32, hi: u32, n: usize, outward: bool) {
    for i in 0..n as u32 {
        let j = (i + 1) % n as u32;
        let (a, b, c, d) = (lo + i, lo + j, hi + j, hi + i);
        if outward {
            m.triangles.push([a, b, c]);
            m.triangles.push([a, c, d]);
        } else {
            m.triangles.push([a, c, b]);
            m.triangles.push([a, d, c]);
        }
    }
}

/// A fan from a ring to a centre vertex; `up` means the cap faces +Z.
fn cap(m: &mut Mesh, ring_start: u32, n: usize, centre: DVec3, up: bool) {
    let c = m.vertices.len() as u32;
    m.vertices.push(centre);
    for i in 0..n as u32 {
        let j = (i + 1) % n as u32;
        if up {
            m.triangles.push([ring_start + i, ring_start + j, c]);
        } else {
            m.triangles.push([ring_start + j, ring_start + i, c]);
        }
    }
}

/// Cylinder of radius `r`, height `h`, `n` sides, `rows` bands along Z.
pub fn cylinder(r: f64, h: f64, n: usize, rows: usize) -> Mesh {
    let mut m = Mesh::default();
    let rings: Vec<u32> = (0..=rows)
        .map(|k| ring(&mut m, r, h * k as f64 / rows as f64, n))
        .collect();
    for w in rings.windows(2) {
        band(&mut m, w[0], w[1], n, true);
    }
    cap(&mut m, rings[0], n, DVec3::ZERO, false);
    cap(&mut m, rings[rows], n, DVec3::new(0.0, 0.0, h), true);
    m
}

/// Tube (a cylinder with a coaxial through hole): radii `r_in` < `r_out`, height `h`.
pub fn tube(r_in: f64, r_out: f64, h: f64, n: usize) -> Mesh {
    let mut m = Mesh::default();
    let o0 = ring(&mut m, r_out, 0.0, n);
    let o1 = ring(&mut m, r_out, h, n);
    let i0 = ring(&mut m, r_in, 0.0, n);
    let i1 = ring(&mut m, r_in, h, n);
    band(&mut m, o0, o1, n, true);
    band(&mut m, i0, i1, n, false);
    // Annular caps: bottom faces -Z, top faces +Z.
    band(&mut m, o1, i1, n, true);
    band(&mut m, i0, o0, n, true);
    m
}

/// UV sphere of radius `r` centred at (0, 0, r): `n` segments around, `rings` along Z.
pub fn sphere(r: f64, n: usize, rings: usize) -> Mesh {
    let mut m = Mesh::default();
    let south = m.vertices.len() as u32;
    m.vertices.push(DVec3::new(0.0, 0.0, 0.0));
    let mut ring_starts = Vec::new();
    for k in 1..rings {
        let theta = std::f64::consts::PI * k as f64 / rings as f64;
        ring_starts.push(ring(&mut m, r * theta.sin(), r - r * theta.cos(), n));
    }
    let north = m.vertices.len() as u32;
    m.vertices.push(DVec3::new(0.0, 0.0, 2.0 * r));
    for i in 0..n as u32 {
        let j = (i + 1) % n as u32;
        let s = ring_starts[0];
        m.triangles.push([south, s + j, s + i]);
        let t = *ring_starts.last().unwrap_or(&s);
        m.triangles.push([t + i, t + j, north]);
    }
    for w in ring_starts.windows(2) {
        band(&mut m, w[0], w[1], n, true);
    }
    m
}

/// An L-bracket lying on its side: the L drawn in the XY plane (a leg `long` mm along
/// X and one `short` mm along Y, both `width` mm wide, meeting at the origin),
/// `thick` mm along Z. Its largest face is the long leg's outer side (normal -Y).
pub fn l_bracket(long: f64, short: f64, width: f64, thick: f64) -> Mesh {
    let outline = [
        [0.0, 0.0],
        [long, 0.0],
        [long, width],
        [width, width],
        [width, short],
        [0.0, short],
    ];
    let mut m = Mesh::default();
    for z in [0.0, thick] {
        for [x, y] in outline {
            m.vertices.push(DVec3::new(x, y, z));
        }
    }
    // Bottom (facing -Z) and top: the L as a fan of 4 triangles from the corner.
    for [a, b, c] in [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]] {
        m.triangles.push([a, c, b]);
        m.triangles.push([a + 6, b + 6, c + 6]);
    }
    for i in 0..6u32 {
        let j = (i + 1) % 6;
        m.triangles.push([i, j, j + 6]);
        m.triangles.push([i, j + 6, i + 6]);
    }
    m
}

/// Cone: base radius `r` at z = 0, apex at z = `h`, `n` sides.
pub fn cone(r: f64, h: f64, n: usize) -> Mesh {
    let mut m = Mesh::default();
    let base = ring(&mut m, r, 0.0, n);
    let apex = m.vertices.len() as u32;
    m.vertices.push(DVec3::new(0.0, 0.0, h));
    for i in 0..n as u32 {
        let j = (i + 1) % n as u32;
        m.triangles.push([base + i, base + j, apex]);
    }
    cap(&mut m, base, n, DVec3::ZERO, false);
    m
}

/// Area of the regular `n`-gon inscribed in a circle of radius `r`, mm².
pub fn ngon_area(r: f64, n: usize) -> f64 {
    0.5 * n as f64 * r * r * (TAU / n as f64).sin()
}
