//! Validation and safe repairs of a loaded mesh (see `docs/mesh-and-slicing.md`).
//!
//! Step 1: refuse non-finite coordinates and out-of-range indices.
//! Step 2: merge vertices at bit-identical positions (STL stores each corner anew).
//! Step 3: drop degenerate triangles (two corners the same vertex after merging).
//! Step 4: drop duplicate triangles (the same three vertices, either orientation).
//! Step 5: classify edges: open (one triangle), manifold (two), non-manifold (more).
//! Step 6: make orientation consistent across manifold edges, flipping the smaller part
//!         of each connected piece.
//!
//! Open edges are counted and located, not patched: the slicer closes small per-layer gaps.

use super::{Mesh, MeshError, MeshFormat};
use glam::DVec3;
use serde::Serialize;

/// Tolerances of the validation, in one place.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct RepairOptions {
    /// Triangles with less area than this are reported as zero-area (they are kept: with
    /// three distinct vertices they still connect their neighbours), mm². Default 1e-12.
    pub zero_area_mm2: f64,
    /// How many open-edge locations the report lists. Default 16.
    pub max_open_edge_samples: usize,
}

impl Default for RepairOptions {
    fn default() -> Self {
        RepairOptions {
            zero_area_mm2: 1e-12,
            max_open_edge_samples: 16,
        }
    }
}

/// What validation found and what repair did. Counts describe the mesh as loaded
/// (after vertex merging) unless named otherwise.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct MeshReport {
    /// The file format, when the mesh came from [`super::load_and_repair`].
    pub format: Option<MeshFormat>,
    /// Triangles as loaded.
    pub triangles_in: usize,
    /// Triangles after repair (what gets sliced).
    pub triangles: usize,
    /// Distinct vertices after merging.
    pub vertices: usize,
    pub bbox_min_mm: [f64; 3],
    pub bbox_max_mm: [f64; 3],
    /// Enclosed volume after repair, mm³ (meaningful for a closed mesh).
    pub volume_mm3: f64,
    /// Coordinates that are NaN or infinite (a mesh with any is refused, so this is 0 in
    /// every report that exists).
    pub non_finite_coordinates: usize,
    /// Triangles with two corners on the same vertex: removed.
    pub degenerate_triangles: usize,
    /// Triangles with three distinct vertices but (near) zero area: kept.
    pub zero_area_triangles: usize,
    /// Triangles with the same three vertices as an earlier one: removed.
    pub duplicate_triangles: usize,
    /// Edges used by one triangle only (holes in the surface).
    pub open_edges: usize,
    /// Edges used by three or more triangles.
    pub non_manifold_edges: usize,
    /// Manifold edges whose two triangles disagree on orientation, before repair.
    pub inconsistent_orientation_edges: usize,
    /// Manifold edges still inconsistent after repair (a non-orientable surface).
    pub orientation_conflicts: usize,
    /// Midpoints of the first open edges, mm, to find the holes.
    pub open_edge_samples_mm: Vec<[f64; 3]>,
    pub repairs: Repairs,
}

/// The repairs done.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Repairs {
    /// Corner records folded into shared vertices.
    pub vertices_merged: usize,
    pub degenerate_removed: usize,
    pub duplicates_removed: usize,
    /// Triangles whose vertex order was reversed to agree with their neighbours.
    pub triangles_flipped: usize,
}

impl MeshReport {
    /// Is the surface closed (no open edges, no non-manifold edges, orientable)?
    pub fn is_watertight(&self) -> bool {
        self.open_edges == 0 && self.non_manifold_edges == 0 && self.orientation_conflicts == 0
    }
}

/// Every edge occurrence, sorted so that the uses of one undirected edge are adjacent:
/// `(lo << 32 | hi, triangle, corner)` where the edge runs from corner to corner + 1.
pub(crate) fn edge_uses(triangles: &[[u32; 3]]) -> Vec<(u64, u32, u8)> {
    let mut uses: Vec<(u64, u32, u8)> = Vec::with_capacity(3 * triangles.len());
    for (t, tri) in triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let key = ((a.min(b) as u64) << 32) | a.max(b) as u64;
            uses.push((key, t as u32, k as u8));
        }
    }
    uses.sort_unstable();
    uses
}

/// Validate `mesh` and return a repaired copy with the report; refuses non-finite
/// coordinates, bad indices and an empty mesh. Runs steps 1–6 of the module's doc.
pub fn repair(mesh: &Mesh, options: &RepairOptions) -> Result<(Mesh, MeshReport), MeshError> {
    // Step 1.
    mesh.check_indices_and_coordinates()?;
    if mesh.triangles.is_empty() {
        return Err(MeshError::NoTriangles);
    }
    let mut report = MeshReport {
        triangles_in: mesh.triangles.len(),
        ..Default::default()
    };
    // Step 2.
    let (vertices, remap) = merge_identical_vertices(&mesh.vertices);
    // Step 3.
    let triangles = without_degenerate(&mesh.triangles, &remap, &mut report);
    // Step 4.
    let triangles = without_duplicates(triangles, &mut report);
    let mut out = compact(&vertices, triangles);
    if out.triangles.is_empty() {
        return Err(MeshError::NoTriangles);
    }
    report.repairs.vertices_merged = used_vertices(mesh).saturating_sub(vertices.len());
    report.repairs.degenerate_removed = report.degenerate_triangles;
    report.repairs.duplicates_removed = report.duplicate_triangles;
    report.zero_area_triangles = (0..out.triangles.len())
        .filter(|&t| {
            let [a, b, c] = out.corners(t);
            0.5 * (b - a).cross(c - a).length() < options.zero_area_mm2
        })
        .count();
    // Step 5.
    let links = classify_edges(&out, options, &mut report);
    // Step 6.
    if report.inconsistent_orientation_edges > 0 {
        orient_consistently(&mut out, &links, &mut report);
    }
    report.triangles = out.triangles.len();
    report.vertices = out.vertices.len();
    if let Some((lo, hi)) = out.bounds() {
        report.bbox_min_mm = lo.to_array();
        report.bbox_max_mm = hi.to_array();
    }
    report.volume_mm3 = out.signed_volume();
    Ok((out, report))
}

/// Step 2: one vertex per bit-identical position (-0.0 == 0.0), and where each input
/// vertex went.
fn merge_identical_vertices(input: &[DVec3]) -> (Vec<DVec3>, Vec<u32>) {
    let nv = input.len();
    let key = |v: DVec3| (v + DVec3::ZERO).to_array().map(f64::to_bits);
    let mut order: Vec<u32> = (0..nv as u32).collect();
    order.sort_unstable_by_key(|&i| key(input[i as usize]));
    let mut remap = vec![0u32; nv];
    let mut vertices: Vec<DVec3> = Vec::new();
    let mut last = None;
    for &i in &order {
        let k = key(input[i as usize]);
        if last != Some(k) {
            vertices.push(input[i as usize]);
            last = Some(k);
        }
        remap[i as usize] = vertices.len() as u32 - 1;
    }
    (vertices, remap)
}

/// Vertices some triangle uses: vertices no triangle uses are not "merged", so merges
/// are counted among used corners.
fn used_vertices(mesh: &Mesh) -> usize {
    let mut u = vec![false; mesh.vertices.len()];
    mesh.triangles
        .iter()
        .flatten()
        .for_each(|&i| u[i as usize] = true);
    u.iter().filter(|&&b| b).count()
}

/// Step 3: the triangles on the merged vertices, without those with two corners on
/// one vertex (counted in the report).
fn without_degenerate(
    triangles: &[[u32; 3]],
    remap: &[u32],
    report: &mut MeshReport,
) -> Vec<[u32; 3]> {
    let mut kept: Vec<[u32; 3]> = Vec::with_capacity(triangles.len());
    for tri in triangles {
        let t = tri.map(|i| remap[i as usize]);
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            report.degenerate_triangles += 1;
            continue;
        }
        kept.push(t);
    }
    kept
}

/// Step 4: the first triangle of each vertex set (either orientation); the others
/// are counted in the report.
fn without_duplicates(mut triangles: Vec<[u32; 3]>, report: &mut MeshReport) -> Vec<[u32; 3]> {
    let mut by_set: Vec<([u32; 3], u32)> = triangles
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let mut s = *t;
            s.sort_unstable();
            (s, i as u32)
        })
        .collect();
    by_set.sort_unstable();
    let mut keep = vec![true; triangles.len()];
    for w in by_set.windows(2) {
        if w[0].0 == w[1].0 {
            keep[w[1].1 as usize] = false;
            report.duplicate_triangles += 1;
        }
    }
    let mut k = 0;
    triangles.retain(|_| {
        k += 1;
        keep[k - 1]
    });
    triangles
}

/// The mesh of `triangles` with only the vertices they use, in order of first use.
fn compact(vertices: &[DVec3], mut triangles: Vec<[u32; 3]>) -> Mesh {
    let mut new_index = vec![u32::MAX; vertices.len()];
    let mut compact: Vec<DVec3> = Vec::new();
    for t in triangles.iter_mut() {
        for i in t.iter_mut() {
            if new_index[*i as usize] == u32::MAX {
                new_index[*i as usize] = compact.len() as u32;
                compact.push(vertices[*i as usize]);
            }
            *i = new_index[*i as usize];
        }
    }
    Mesh {
        vertices: compact,
        triangles,
    }
}

/// A manifold edge's two triangles, and whether they run the edge the same way (their
/// orientations disagree).
type ManifoldLink = (u32, u32, bool);

/// Step 5: count open, non-manifold and inconsistently oriented edges (with the first
/// open edges' midpoints) into the report; the manifold edges' links.
fn classify_edges(
    out: &Mesh,
    options: &RepairOptions,
    report: &mut MeshReport,
) -> Vec<ManifoldLink> {
    let uses = edge_uses(&out.triangles);
    let mut links: Vec<ManifoldLink> = Vec::new();
    let mut i = 0;
    while i < uses.len() {
        let mut j = i + 1;
        while j < uses.len() && uses[j].0 == uses[i].0 {
            j += 1;
        }
        match j - i {
            1 => {
                report.open_edges += 1;
                if report.open_edge_samples_mm.len() < options.max_open_edge_samples {
                    let (a, b) = (
                        (uses[i].0 >> 32) as usize,
                        (uses[i].0 & 0xffff_ffff) as usize,
                    );
                    let m = 0.5 * (out.vertices[a] + out.vertices[b]);
                    report.open_edge_samples_mm.push(m.to_array());
                }
            }
            2 => {
                let dir = |u: &(u64, u32, u8)| {
                    let t = out.triangles[u.1 as usize];
                    t[u.2 as usize] < t[(u.2 as usize + 1) % 3]
                };
                let same = dir(&uses[i]) == dir(&uses[i + 1]);
                if same {
                    report.inconsistent_orientation_edges += 1;
                }
                links.push((uses[i].1, uses[i + 1].1, same));
            }
            _ => report.non_manifold_edges += 1,
        }
        i = j;
    }
    links
}

/// Step 6: flip triangles so that manifold neighbours agree, flipping the smaller part
/// of each connected piece; flips and remaining conflicts go into the report.
fn orient_consistently(out: &mut Mesh, links: &[ManifoldLink], report: &mut MeshReport) {
    let flip = orientation_flips(out.triangles.len(), links);
    for (t, f) in flip.iter().enumerate() {
        if *f == Some(true) {
            out.triangles[t].swap(1, 2);
            report.repairs.triangles_flipped += 1;
        }
    }
    report.orientation_conflicts = links
        .iter()
        .filter(|&&(a, b, same)| {
            same ^ flip[a as usize].unwrap_or(false) ^ flip[b as usize].unwrap_or(false)
        })
        .count();
}

/// Which of `nt` triangles to flip: breadth first over the manifold links of each
/// connected piece, then the piece's choice inverted if it flips more than half.
fn orientation_flips(nt: usize, links: &[ManifoldLink]) -> Vec<Option<bool>> {
    let (adj_start, adj) = link_adjacency(nt, links);
    let mut flip: Vec<Option<bool>> = vec![None; nt];
    let mut queue = std::collections::VecDeque::new();
    for seed in 0..nt {
        if flip[seed].is_some() {
            continue;
        }
        let mut component = vec![seed as u32];
        flip[seed] = Some(false);
        queue.push_back(seed as u32);
        while let Some(t) = queue.pop_front() {
            let ft = flip[t as usize].unwrap_or(false);
            for &(n, same) in
                &adj[adj_start[t as usize] as usize..adj_start[t as usize + 1] as usize]
            {
                if flip[n as usize].is_none() {
                    // Same direction on the shared edge means one of them must flip.
                    flip[n as usize] = Some(ft ^ same);
                    component.push(n);
                    queue.push_back(n);
                }
            }
        }
        let flipped = component
            .iter()
            .filter(|&&t| flip[t as usize] == Some(true))
            .count();
        if 2 * flipped > component.len() {
            for &t in &component {
                flip[t as usize] = flip[t as usize].map(|f| !f);
            }
        }
    }
    flip
}

/// The links as adjacency lists (compressed rows): triangle t's neighbours are
/// `adj[adj_start[t]..adj_start[t + 1]]`, each with whether they disagree.
fn link_adjacency(nt: usize, links: &[ManifoldLink]) -> (Vec<u32>, Vec<(u32, bool)>) {
    let mut adj_start = vec![0u32; nt + 1];
    for &(a, b, _) in links {
        adj_start[a as usize + 1] += 1;
        adj_start[b as usize + 1] += 1;
    }
    for t in 0..nt {
        adj_start[t + 1] += adj_start[t];
    }
    let mut fill = adj_start.clone();
    let mut adj = vec![(0u32, false); 2 * links.len()];
    for &(a, b, same) in links {
        adj[fill[a as usize] as usize] = (b, same);
        fill[a as usize] += 1;
        adj[fill[b as usize] as usize] = (a, same);
        fill[b as usize] += 1;
    }
    (adj_start, adj)
}
