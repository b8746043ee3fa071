//! One section: cut triangles with a plane, chain the segments into loops by shared
//! edges, close small gaps, nest loops into islands.

use super::{GapClosed, SliceError, SliceTolerances};
use crate::geom::{self, Region};
use crate::mesh::Mesh;
use glam::{DVec2, DVec3};

/// For each plane, the triangles it cuts (`zmin < z <= zmax`), as one flat list.
pub(super) struct Buckets {
    start: Vec<u32>,
    tris: Vec<u32>,
}

impl Buckets {
    /// `planes` in any order.
    pub(super) fn new(mesh: &Mesh, planes: &[f64]) -> Self {
        let mut order: Vec<u32> = (0..planes.len() as u32).collect();
        order.sort_by(|&a, &b| planes[a as usize].total_cmp(&planes[b as usize]));
        let sorted: Vec<f64> = order.iter().map(|&i| planes[i as usize]).collect();
        let ranges: Vec<(u32, u32)> = (0..mesh.triangles.len())
            .map(|t| {
                let [a, b, c] = mesh.corners(t);
                let lo = a.z.min(b.z).min(c.z);
                let hi = a.z.max(b.z).max(c.z);
                let i0 = sorted.partition_point(|&p| p <= lo) as u32;
                let i1 = sorted.partition_point(|&p| p <= hi) as u32;
                (i0, i1)
            })
            .collect();
        let mut count = vec![0u32; planes.len() + 1];
        for &(i0, i1) in &ranges {
            for k in i0..i1 {
                count[order[k as usize] as usize + 1] += 1;
            }
        }
        for i in 0..planes.len() {
            count[i + 1] += count[i];
        }
        let mut fill = count.clone();
        let mut tris = vec![0u32; count[planes.len()] as usize];
        for (t, &(i0, i1)) in ranges.iter().enumerate() {
            for k in i0..i1 {
                let p = order[k as usize] as usize;
                tris[fill[p] as usize] = t as u32;
                fill[p] += 1;
            }
        }
        Buckets { start: count, tris }
    }

    pub(super) fn triangles(&self, plane: usize) -> &[u32] {
        &self.tris[self.start[plane] as usize..self.start[plane + 1] as usize]
    }
}

/// Per-thread working memory: for each edge id, the first segment starting on it.
pub(super) struct Scratch {
    head: Vec<u32>,
    /// For each edge id, how many segments end on it.
    ends: Vec<u32>,
}

impl Scratch {
    pub(super) fn new(edge_count: usize) -> Self {
        Scratch {
            head: vec![NONE; edge_count],
            ends: vec![0; edge_count],
        }
    }
}

/// More open chains than this in one layer: the mesh is too broken to close gaps in.
const MAX_OPEN_CHAINS: usize = 2000;

const NONE: u32 = u32::MAX;

#[derive(Default)]
pub(super) struct LayerNotes {
    pub gaps: Vec<GapClosed>,
    pub slivers_dropped: usize,
    pub resolved_by_union: bool,
}

struct Segment {
    start_edge: u32,
    end_edge: u32,
    start: DVec2,
    end: DVec2,
    /// Next segment starting on the same edge (non-manifold edges have several).
    next_same: u32,
    used: bool,
}

/// Where the plane crosses the edge `u`–`v`, computed from the endpoints in a fixed order
/// so both triangles sharing the edge get the same point.
fn edge_point(mesh: &Mesh, u: u32, v: u32, z: f64) -> DVec2 {
    let (u, v) = if u < v { (u, v) } else { (v, u) };
    let (a, b): (DVec3, DVec3) = (mesh.vertices[u as usize], mesh.vertices[v as usize]);
    let t = (z - a.z) / (b.z - a.z);
    DVec2::new(a.x + t * (b.x - a.x), a.y + t * (b.y - a.y))
}

pub(super) fn cut(
    mesh: &Mesh,
    tri_edges: &[[u32; 3]],
    tris: &[u32],
    z: f64,
    tol: &SliceTolerances,
    scratch: &mut Scratch,
) -> Result<(Vec<Region>, LayerNotes), SliceError> {
    let mut notes = LayerNotes::default();
    let mut segs = plane_segments(mesh, tri_edges, tris, z);
    let (mut loops, mut open) = chain_segments(&mut segs, scratch);

    // Step 3: join open chains that meet on an edge (a chain begun mid-way), then close
    // gaps up to max_gap_mm, shortest first.
    if open.len() > MAX_OPEN_CHAINS {
        let end = *open[0].0.last().unwrap_or(&DVec2::ZERO);
        return Err(SliceError::OpenLoop {
            z_mm: z,
            x: end.x,
            y: end.y,
            nearest_mm: None,
            max_gap_mm: tol.max_gap_mm,
        });
    }
    if !open.is_empty() {
        join_open(&mut open, &mut loops, z, tol, &mut notes)?;
    }
    let islands = islands_of(loops, z, tol, &mut notes)?;
    Ok((islands, notes))
}

/// Step 1: the segment each triangle of `tris` leaves in the plane at `z`. Corner above
/// = z >= plane. The segment runs from the edge going down (above -> below) to the edge
/// going up, which is z × normal: material on the left.
fn plane_segments(mesh: &Mesh, tri_edges: &[[u32; 3]], tris: &[u32], z: f64) -> Vec<Segment> {
    let mut segs: Vec<Segment> = Vec::with_capacity(tris.len());
    for &t in tris {
        let tri = mesh.triangles[t as usize];
        let above = tri.map(|i| mesh.vertices[i as usize].z >= z);
        let (mut down, mut up) = (None, None);
        for k in 0..3 {
            let k1 = geom::next_in_loop(k, 3);
            if above[k] && !above[k1] {
                down = Some(k);
            } else if !above[k] && above[k1] {
                up = Some(k);
            }
        }
        let (Some(d), Some(u)) = (down, up) else {
            continue;
        };
        let edges = tri_edges[t as usize];
        segs.push(Segment {
            start_edge: edges[d],
            end_edge: edges[u],
            start: edge_point(mesh, tri[d], tri[geom::next_in_loop(d, 3)], z),
            end: edge_point(mesh, tri[u], tri[geom::next_in_loop(u, 3)], z),
            next_same: NONE,
            used: false,
        });
    }
    segs
}

/// An open chain of segments: its points (the last is the chain's end), and the edges
/// it starts and ends on.
type OpenChain = (Vec<DVec2>, u32, u32);

/// Step 2: chain `segs` by edge id into closed loops and open chains (`scratch` is left
/// as it was found).
fn chain_segments(
    segs: &mut [Segment],
    scratch: &mut Scratch,
) -> (Vec<Vec<DVec2>>, Vec<OpenChain>) {
    for (i, s) in segs.iter_mut().enumerate() {
        s.next_same = scratch.head[s.start_edge as usize];
        scratch.head[s.start_edge as usize] = i as u32;
        scratch.ends[s.end_edge as usize] += 1;
    }
    let take = |segs: &mut [Segment], head: &[u32], edge: u32| -> Option<usize> {
        let mut i = head[edge as usize];
        while i != NONE {
            if !segs[i as usize].used {
                segs[i as usize].used = true;
                return Some(i as usize);
            }
            i = segs[i as usize].next_same;
        }
        None
    };
    let mut loops: Vec<Vec<DVec2>> = Vec::new();
    let mut open: Vec<OpenChain> = Vec::new();
    // Chains of an open mesh start where no segment ends (pass 0); closed loops start
    // anywhere (pass 1).
    let order = (0..segs.len())
        .filter(|&s| scratch.ends[segs[s].start_edge as usize] == 0)
        .chain(0..segs.len())
        .collect::<Vec<_>>();
    for s in order {
        if segs[s].used {
            continue;
        }
        segs[s].used = true;
        let first_edge = segs[s].start_edge;
        let mut pts = vec![segs[s].start];
        let mut cur = s;
        loop {
            let e = segs[cur].end_edge;
            if e == first_edge {
                loops.push(pts);
                break;
            }
            match take(segs, &scratch.head, e) {
                Some(n) => {
                    pts.push(segs[n].start);
                    cur = n;
                }
                None => {
                    pts.push(segs[cur].end);
                    open.push((pts, first_edge, e));
                    break;
                }
            }
        }
    }
    for s in segs.iter() {
        scratch.head[s.start_edge as usize] = NONE;
        scratch.ends[s.end_edge as usize] = 0;
    }
    (loops, open)
}

/// Step 4: clean `loops` and nest them into islands; where they do not make sound
/// regions (and the tolerances ask for validation), resolve them by an even-odd union.
fn islands_of(
    loops: Vec<Vec<DVec2>>,
    z: f64,
    tol: &SliceTolerances,
    notes: &mut LayerNotes,
) -> Result<Vec<Region>, SliceError> {
    let mut clean: Vec<(Vec<DVec2>, f64)> = Vec::with_capacity(loops.len());
    for l in loops {
        let l = drop_collinear(&l, tol.collinear_mm.max(tol.point_eq_mm));
        let a = geom::signed_area(&l);
        if l.len() < 3 || a.abs() < tol.min_loop_area_mm2 {
            notes.slivers_dropped += 1;
            continue;
        }
        clean.push((l, a.abs()));
    }
    let loops: Vec<Vec<DVec2>> = clean.iter().map(|(l, _)| l.clone()).collect();
    let mut islands = nest(clean);
    if tol.validate_regions {
        let gt = geom::Tolerances {
            point_eq_mm: tol.point_eq_mm,
            min_loop_area_mm2: tol.min_loop_area_mm2,
            ..Default::default()
        };
        if first_invalid(&islands, &gt).is_some() {
            // Step 5: real meshes leave µm-scale folds (a loop doubling back on itself);
            // resolve the layer with an even-odd union, as PrusaSlicer does with Clipper.
            islands = union_even_odd(&loops, tol);
            notes.resolved_by_union = true;
        }
        if let Some((i, source)) = first_invalid(&islands, &gt) {
            return Err(SliceError::BadRegion {
                z_mm: z,
                island: i,
                source,
            });
        }
    }
    Ok(islands)
}

fn join_open(
    open: &mut Vec<(Vec<DVec2>, u32, u32)>,
    loops: &mut Vec<Vec<DVec2>>,
    z: f64,
    tol: &SliceTolerances,
    notes: &mut LayerNotes,
) -> Result<(), SliceError> {
    // Exact joins by edge id.
    let mut changed = true;
    while changed {
        changed = false;
        'outer: for i in 0..open.len() {
            for j in 0..open.len() {
                if i != j && open[i].2 == open[j].1 {
                    let (mut pts_j, _, end_j) = open.swap_remove(j);
                    let i = if i == open.len() { j } else { i };
                    // Chain i ends on the point chain j starts with.
                    open[i].0.pop();
                    open[i].0.append(&mut pts_j);
                    open[i].2 = end_j;
                    if open[i].1 == open[i].2 {
                        let (mut pts, _, _) = open.swap_remove(i);
                        pts.pop();
                        loops.push(pts);
                    }
                    changed = true;
                    break 'outer;
                }
            }
        }
    }
    // Gap closing: repeatedly join the globally closest end -> start pair within max_gap.
    while !open.is_empty() {
        let mut best: Option<(f64, usize, usize)> = None;
        for (i, a) in open.iter().enumerate() {
            let end = *a.0.last().unwrap_or(&DVec2::ZERO);
            for (j, b) in open.iter().enumerate() {
                let d = end.distance(b.0[0]);
                if best.is_none_or(|(bd, _, _)| d < bd) {
                    best = Some((d, i, j));
                }
            }
        }
        let Some((d, i, j)) = best else { break };
        let end = *open[i].0.last().unwrap_or(&DVec2::ZERO);
        if d > tol.max_gap_mm {
            return Err(SliceError::OpenLoop {
                z_mm: z,
                x: end.x,
                y: end.y,
                nearest_mm: Some(d),
                max_gap_mm: tol.max_gap_mm,
            });
        }
        notes.gaps.push(GapClosed {
            z_mm: z,
            x_mm: end.x,
            y_mm: end.y,
            gap_mm: d,
        });
        if i == j {
            let (pts, _, _) = open.swap_remove(i);
            loops.push(pts);
        } else {
            let (mut pts_j, _, end_j) = open.swap_remove(j);
            let i = if i == open.len() { j } else { i };
            open[i].0.append(&mut pts_j);
            open[i].2 = end_j;
        }
    }
    Ok(())
}

/// Nest loops by containment: depth 0 outer, 1 hole, 2 island in a hole, and so on.
/// Orientation is set here from the depth, not trusted from the mesh.
fn nest(mut loops: Vec<(Vec<DVec2>, f64)>) -> Vec<Region> {
    loops.sort_by(|a, b| b.1.total_cmp(&a.1));
    let bounds: Vec<(DVec2, DVec2)> = loops
        .iter()
        .map(|(l, _)| {
            l.iter().fold(
                (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
                |(lo, hi), p| (lo.min(*p), hi.max(*p)),
            )
        })
        .collect();
    let mut parent: Vec<Option<usize>> = vec![None; loops.len()];
    let mut depth: Vec<usize> = vec![0; loops.len()];
    for i in 0..loops.len() {
        let p = loops[i].0[0];
        // The smallest larger loop containing it: scan from the nearest in size down.
        for j in (0..i).rev() {
            let (lo, hi) = bounds[j];
            if p.x < lo.x || p.y < lo.y || p.x > hi.x || p.y > hi.y {
                continue;
            }
            if geom::point_in_loop(p, &loops[j].0) {
                parent[i] = Some(j);
                depth[i] = depth[j] + 1;
                break;
            }
        }
    }
    let mut region_of: Vec<usize> = vec![usize::MAX; loops.len()];
    let mut regions: Vec<Region> = Vec::new();
    let mut taken: Vec<Option<Vec<DVec2>>> = loops.into_iter().map(|(l, _)| Some(l)).collect();
    for i in 0..taken.len() {
        let Some(mut l) = taken[i].take() else {
            continue;
        };
        let ccw = geom::signed_area2(&l) > 0.0;
        if depth[i].is_multiple_of(2) {
            if !ccw {
                l.reverse();
            }
            region_of[i] = regions.len();
            regions.push(Region::new(l, Vec::new()));
        } else {
            if ccw {
                l.reverse();
            }
            if let Some(r) = parent[i].map(|p| region_of[p]) {
                if let Some(region) = regions.get_mut(r) {
                    region.holes.push(l);
                }
            }
        }
    }
    regions
}

fn first_invalid(islands: &[Region], tol: &geom::Tolerances) -> Option<(usize, geom::RegionError)> {
    islands
        .iter()
        .enumerate()
        .find_map(|(i, r)| r.validate(tol).err().map(|e| (i, e)))
}

/// Islands of `loops` under the even-odd rule, computed by i_overlay.
fn union_even_odd(loops: &[Vec<DVec2>], tol: &SliceTolerances) -> Vec<Region> {
    let shapes = geom::i_overlay_integration::even_odd_shapes_ogc(loops, tol.min_loop_area_mm2);
    let gt = geom::Tolerances {
        point_eq_mm: tol.point_eq_mm,
        ..Default::default()
    };
    shapes
        .into_iter()
        .filter_map(|shape| {
            let mut it = shape.into_iter();
            let outer = it.next()?;
            let holes: Vec<Vec<DVec2>> = it
                .filter(|h| geom::signed_area(h).abs() >= tol.min_loop_area_mm2)
                .collect();
            if geom::signed_area(&outer).abs() < tol.min_loop_area_mm2 {
                return None;
            }
            Some(Region::new(outer, holes).normalised(&gt))
        })
        .collect()
}

/// Remove points within `eps` of the line through their neighbours: collinear points and
/// the zero-width spikes (a loop doubling back on itself) that µm-scale folds of real
/// meshes leave. Changes the area by at most `eps` × the perimeter.
fn drop_collinear(l: &[DVec2], eps: f64) -> Vec<DVec2> {
    let off_line = |a: DVec2, b: DVec2, c: DVec2| {
        let ac = c - a;
        let len = ac.length();
        if len < eps {
            return true; // a -> b -> back to a: a spike
        }
        (b - a).perp_dot(ac).abs() / len >= eps
    };
    let mut out: Vec<DVec2> = Vec::with_capacity(l.len());
    for &p in l {
        while out.len() >= 2 && !off_line(out[out.len() - 2], out[out.len() - 1], p) {
            out.pop();
        }
        if out.last().is_none_or(|q| q.distance(p) >= eps) {
            out.push(p);
        }
    }
    // The seam where the loop closes.
    loop {
        let n = out.len();
        if n < 3 {
            break;
        }
        if out[n - 1].distance(out[0]) < eps || !off_line(out[n - 2], out[n - 1], out[0]) {
            out.pop();
        } else if !off_line(out[n - 1], out[0], out[1]) {
            out.remove(0);
        } else {
            break;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(x: f64, y: f64) -> DVec2 {
        DVec2::new(x, y)
    }

    #[test]
    fn spikes_and_collinear_points_are_dropped() {
        // A square with a collinear point, a zero-width spike doubling back, and a
        // duplicate point at the seam.
        let l = vec![
            v(0.0, 0.0),
            v(1.0, 0.0),
            v(2.0, 0.0),
            v(2.0, 1.0),
            v(2.0, 1.5),
            v(2.0, 1.2),
            v(2.0, 2.0),
            v(0.0, 2.0),
            v(0.0, 0.0),
        ];
        let out = drop_collinear(&l, 1e-4);
        assert_eq!(out.len(), 4, "{out:?}");
        assert!((geom::signed_area(&out) - 4.0).abs() < 1e-12);
    }

    #[test]
    fn nesting_depths_alternate() {
        let sq = |h: f64| vec![v(-h, -h), v(h, -h), v(h, h), v(-h, h)];
        let loops: Vec<(Vec<DVec2>, f64)> = [1.0, 4.0, 2.0, 3.0]
            .iter()
            .map(|&h| (sq(h), 4.0 * h * h))
            .collect();
        let r = nest(loops);
        assert_eq!(r.len(), 2);
        assert!(r.iter().all(|r| r.holes.len() == 1));
        assert!(r.iter().all(|r| geom::signed_area(&r.outer) > 0.0));
        assert!(r.iter().all(|r| geom::signed_area(&r.holes[0]) < 0.0));
    }

    #[test]
    fn even_odd_union_resolves_self_touching_loops() {
        // A figure-eight: two squares sharing a corner, as one loop.
        let l = vec![
            v(0.0, 0.0),
            v(1.0, 0.0),
            v(1.0, 1.0),
            v(2.0, 1.0),
            v(2.0, 2.0),
            v(1.0, 2.0),
            v(1.0, 1.0),
            v(0.0, 1.0),
        ];
        let r = union_even_odd(&[l], &SliceTolerances::default());
        let area: f64 = r.iter().map(Region::area).sum();
        assert!((area - 2.0).abs() < 1e-6, "{r:?}");
    }
}
