//! Gap fill (§4, what is still left after the flow raise, filled the way PrusaSlicer's
//! gap fill and Arachne do): the part area no bead covers, where it is at least
//! `min_width` wide, gets thin roads along its centreline whose width follows the gap.
//!
//! Steps, per layer (after [`super::flow::raise`] and [`super::ends`]):
//!
//! 1. **Gaps**: cells no bead covers, on a raster of half the narrowest gap-fill road
//!    ([`Raster`], shared with the coverage measure), grouped into clusters; in a window
//!    around each cluster, the part (the layer's islands, clipped to the window without
//!    an overlay, [`crate::geom::clip_to_box`]) minus the beads that reach it
//!    (each edge as a trapezoid of its two vertices' widths, each joint that turns and
//!    each end as a disc), by i_overlay; then opened by half the narrowest gap-fill road
//!    (shrunk and grown back), so slivers no road could build vanish.
//! 2. **Centreline**: each gap is triangulated (constrained Delaunay, i_triangle, its
//!    boundary first divided to a quarter road width) and its chordal axis taken: the
//!    midpoints of the chords (edges shared by two triangles) joined across each
//!    triangle, through the centroid where three chords meet. Per connected part the
//!    longest path, then branches at least a road width long.
//! 3. **Widths**: the path resampled to a quarter road width, each point moved to the
//!    middle of the gap across the path and given the gap's width there, capped at
//!    `max_width`; points narrower than `min_width` dropped. The ends stop where the
//!    round end stays inside the part and rides at most half its radius on the road
//!    that closes the gap, and thin horns (where the gap meets a road's round end) go.
//! 4. **Composition and order**: each gap-fill road takes the composition of the road
//!    nearest its middle and is built right after it, so it needs no composition change
//!    (and no mixing-chamber lead).

use super::coverage::Raster;
use super::{PathRole, ToolPath};
use crate::geom::{
    self as shapes, edge_ends, loop_edge, loop_edges, next_in_loop, prev_in_loop, Region,
    SegmentIndex, Shapes,
};
use glam::DVec2;
use i_triangle::float::triangulatable::Triangulatable;
use std::collections::HashMap;

/// Settings of the gap fill (part of [`crate::pipeline::ProcessSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GapFillSettings {
    pub road_width_mm: f64,
    /// Narrowest gap-fill road, mm (gaps narrower are left).
    pub min_width_mm: f64,
    /// Widest gap-fill road, mm.
    pub max_width_mm: f64,
}

/// Sides of the polygon that stands for a bead's round joint or end.
const DISC_SIDES: usize = 16;
/// cos(π / DISC_SIDES): a disc's polygon is circumscribed, its corners 1/cos further.
const DISC_COS: f64 = 0.980_785_280_403_230_4;
/// Joints turning less than this (cosine, about 3°) need no disc: the two edges'
/// trapezoids share their end.
const STRAIGHT_COS: f64 = 0.9986;

/// Gap-fill roads for `paths` over the part `islands`, each with the index of the path
/// it is to be built after.
pub fn gap_fill(
    islands: &[Region],
    paths: &[ToolPath],
    s: &GapFillSettings,
) -> Vec<(usize, ToolPath)> {
    let w = s.road_width_mm;
    if !(w.is_finite() && w > 0.0 && s.min_width_mm > 0.0 && s.max_width_mm >= s.min_width_mm)
        || islands.is_empty()
        || paths.is_empty()
    {
        return Vec::new();
    }
    let gaps = gaps(islands, paths, s);
    if gaps.is_empty() {
        return Vec::new();
    }
    // Roads, to find the one nearest each gap-fill road; the part boundary, which no
    // gap-fill end may cross.
    let roads = super::RoadIndex::new(paths);
    let part = SegmentIndex::of_regions(islands);
    let mut out = Vec::new();
    for gap in &gaps {
        for (points, widths) in centrelines(gap, &part, s) {
            let mid = points[points.len() / 2];
            let Some((_, id)) = roads.index.nearest_skipping(mid, |_| false) else {
                continue;
            };
            let Some(&after) = roads.owner.get(id as usize) else {
                continue;
            };
            let after = after as usize;
            let near = &paths[after];
            let (island, n) = match near.role {
                PathRole::Contour { island, j } => (island, j),
                PathRole::Offset { island, n, .. } | PathRole::GapFill { island, n } => (island, n),
                PathRole::Support | PathRole::SupportInterface => continue,
            };
            out.push((
                after,
                ToolPath {
                    role: PathRole::GapFill { island, n },
                    width_factors: widths.iter().map(|wd| wd / w).collect(),
                    points,
                    closed: false,
                    composition: near.composition.clone(),
                    seam_at_corner: false,
                },
            ));
        }
    }
    out
}

/// Build `fill` into `paths`: each gap-fill road right after its road, several after one
/// road nearest first, each entered at its nearer end.
pub fn insert(paths: Vec<ToolPath>, fill: Vec<(usize, ToolPath)>) -> Vec<ToolPath> {
    if fill.is_empty() {
        return paths;
    }
    let mut after: Vec<Vec<ToolPath>> = vec![Vec::new(); paths.len()];
    for (k, p) in fill {
        if let Some(v) = after.get_mut(k) {
            v.push(p);
        }
    }
    let mut out = Vec::with_capacity(paths.len());
    for (p, mut extra) in paths.into_iter().zip(after) {
        let mut here = p.end();
        out.push(p);
        while !extra.is_empty() {
            let mut best = (f64::INFINITY, 0, false);
            for (i, e) in extra.iter().enumerate() {
                let (a, b) = (e.points[0], e.points[e.points.len() - 1]);
                let (da, db) = (a.distance(here), b.distance(here));
                if da.min(db) < best.0 {
                    best = (da.min(db), i, db < da);
                }
            }
            let mut e = extra.swap_remove(best.1);
            if best.2 {
                e.points.reverse();
                e.width_factors.reverse();
            }
            here = e.end();
            out.push(e);
        }
    }
    out
}

/// Step 1: the part minus the beads, opened by half the narrowest road. Found first on
/// a raster of half the narrowest road (cells no bead covers), then computed exactly
/// in a window around each cluster of such cells, with only the beads that reach it.
fn gaps(islands: &[Region], paths: &[ToolPath], s: &GapFillSettings) -> Shapes {
    let w = s.road_width_mm;
    let cell = 0.5 * s.min_width_mm;
    let Some(raster) = Raster::of_roads(islands, paths, w, cell) else {
        return Vec::new();
    };
    let windows = merge_boxes(bare_clusters(&raster, islands));
    if windows.is_empty() {
        return Vec::new();
    }
    let part: Vec<(DVec2, DVec2, &[DVec2])> = islands
        .iter()
        .flat_map(|r| r.loops())
        .map(|l| {
            let (lo, hi) = shapes::loop_bounds(l);
            (lo, hi, l.as_slice())
        })
        .collect();
    let edges = bead_boxes(paths, w);
    let mut out = Vec::new();
    for window in windows {
        out.extend(gap_in_window(window, &part, paths, &edges, s));
    }
    out
}

/// The boxes of the clusters of part cells of `raster` no bead covers (4-neighbour),
/// each grown by two cells (the gap reaches at most a cell past its cells' centres);
/// clusters of fewer than [`MIN_GAP_CELLS`] are left.
fn bare_clusters(raster: &Raster, islands: &[Region]) -> Vec<(DVec2, DVec2)> {
    let (nx, ny) = (raster.nx, raster.ny);
    let mut bare_cell = vec![false; nx * ny];
    raster.scan_part(islands, |c, _, inside| {
        bare_cell[c] = inside && raster.count[c] == 0;
    });
    let pad = 2.0 * raster.cell_mm;
    let mut windows: Vec<(DVec2, DVec2)> = Vec::new();
    let mut seen = vec![false; nx * ny];
    let mut stack = Vec::new();
    for start in 0..nx * ny {
        if !bare_cell[start] || seen[start] {
            continue;
        }
        let (mut lo, mut hi) = ((usize::MAX, usize::MAX), (0, 0));
        let mut cells = 0usize;
        seen[start] = true;
        stack.push(start);
        while let Some(c) = stack.pop() {
            let (i, j) = (c % nx, c / nx);
            cells += 1;
            lo = (lo.0.min(i), lo.1.min(j));
            hi = (hi.0.max(i), hi.1.max(j));
            let mut near = |k: usize| {
                if bare_cell[k] && !seen[k] {
                    seen[k] = true;
                    stack.push(k);
                }
            };
            if i > 0 {
                near(c - 1);
            }
            if i + 1 < nx {
                near(c + 1);
            }
            if j > 0 {
                near(c - nx);
            }
            if j + 1 < ny {
                near(c + nx);
            }
        }
        if cells < MIN_GAP_CELLS {
            continue;
        }
        let corner =
            |i: usize, j: usize| raster.lo + DVec2::new(i as f64, j as f64) * raster.cell_mm;
        windows.push((
            corner(lo.0, lo.1) - DVec2::splat(pad),
            corner(hi.0 + 1, hi.1 + 1) + DVec2::splat(pad),
        ));
    }
    windows
}

/// Each road edge's bead box (road width `w`), as (path, edge, box), to pick the beads
/// that reach a window.
fn bead_boxes(paths: &[ToolPath], w: f64) -> Vec<(usize, usize, DVec2, DVec2)> {
    let mut edges: Vec<(usize, usize, DVec2, DVec2)> = Vec::new();
    for (pi, p) in paths.iter().enumerate() {
        // A one-point road's bead is a disc: the one edge from the point to itself.
        for (k, j) in edge_ends(p.points.len(), p.closed || p.points.len() == 1) {
            let (a, b) = (p.points[k], p.points[j]);
            let f = p.width_factors[k].max(p.width_factors[j]);
            let r = 0.5 * w * f / DISC_COS;
            edges.push((
                pi,
                k,
                a.min(b) - DVec2::splat(r),
                a.max(b) + DVec2::splat(r),
            ));
        }
    }
    edges
}

/// The gaps inside the box `window`: the `part` there minus the beads (of the `edges`
/// whose boxes reach it), opened by half the narrowest road.
fn gap_in_window(
    (lo, hi): (DVec2, DVec2),
    part: &[(DVec2, DVec2, &[DVec2])],
    paths: &[ToolPath],
    edges: &[(usize, usize, DVec2, DVec2)],
    s: &GapFillSettings,
) -> Shapes {
    let w = s.road_width_mm;
    let r_open = 0.5 * s.min_width_mm - WIDTH_SLACK_MM;
    let chord = 0.05 * w;
    // The part in the window, clipped without an overlay (the difference below
    // resolves the clip's seams); with no bead to take away, by the overlay.
    let local_part = shapes::clip_to_box(part, lo, hi);
    let mut beads: Shapes = Vec::new();
    for &(pi, k, a, b) in edges {
        if a.x <= hi.x && b.x >= lo.x && a.y <= hi.y && b.y >= lo.y {
            edge_bead(&paths[pi], k, w, &mut beads);
        }
    }
    let bare = if beads.is_empty() {
        let rect = vec![vec![lo, DVec2::new(hi.x, lo.y), hi, DVec2::new(lo.x, hi.y)]];
        shapes::intersection(&local_part, &vec![rect])
    } else {
        shapes::difference(&local_part, &beads)
    };
    if bare.is_empty() {
        return Vec::new();
    }
    let opened = shapes::offset(&shapes::offset(&bare, -r_open, chord), r_open, chord);
    // Grown back, the opening may reach past the bare area at its corners.
    shapes::intersection(&opened, &bare)
}

/// A gap exactly the narrowest road wide (common: offsets are equally spaced) is one:
/// the opening and the width checks allow this much, more than the overlay's rounding
/// (under 1e-6 mm), so rounding does not decide whether it is filled.
const WIDTH_SLACK_MM: f64 = 1e-5;

/// Gaps of fewer raster cells (of half the narrowest road) than this are left.
const MIN_GAP_CELLS: usize = 4;

/// Boxes merged until none overlap.
fn merge_boxes(mut boxes: Vec<(DVec2, DVec2)>) -> Vec<(DVec2, DVec2)> {
    let overlap = |a: &(DVec2, DVec2), b: &(DVec2, DVec2)| {
        a.0.x <= b.1.x && b.0.x <= a.1.x && a.0.y <= b.1.y && b.0.y <= a.1.y
    };
    let mut merged = true;
    while merged {
        merged = false;
        let mut out: Vec<(DVec2, DVec2)> = Vec::with_capacity(boxes.len());
        for b in boxes {
            if let Some(o) = out.iter_mut().find(|o| overlap(o, &b)) {
                *o = (o.0.min(b.0), o.1.max(b.1));
                merged = true;
            } else {
                out.push(b);
            }
        }
        boxes = out;
    }
    boxes
}

/// The area edge `k` of a road's bead covers, as polygons (counter-clockwise): a
/// trapezoid of its two vertices' widths, and a disc at its start where the road turns
/// there or ends (and at its end for an open road's last edge).
fn edge_bead(p: &ToolPath, k: usize, w: f64, out: &mut Shapes) {
    let n = p.points.len();
    if n == 0 {
        return;
    }
    let half = |k: usize| 0.5 * w * p.width_factors[k % n];
    let disc = |c: DVec2, r: f64| -> Vec<DVec2> {
        (0..DISC_SIDES)
            .map(|q| {
                let a = std::f64::consts::TAU * q as f64 / DISC_SIDES as f64;
                // Circumscribed, so the polygon covers the disc.
                c + DVec2::new(a.cos(), a.sin()) * (r / DISC_COS)
            })
            .collect()
    };
    if n == 1 {
        out.push(vec![disc(p.points[0], half(0))]);
        return;
    }
    let (a, b) = loop_edge(&p.points, k);
    let nrm = (b - a).normalize_or_zero().perp();
    if nrm != DVec2::ZERO {
        let (ha, hb) = (half(k), half(k + 1));
        out.push(vec![vec![
            a - nrm * ha,
            b - nrm * hb,
            b + nrm * hb,
            a + nrm * ha,
        ]]);
    }
    let joint = |v: usize| {
        if !p.closed && (v == 0 || v == n - 1) {
            return true;
        }
        let prev = p.points[prev_in_loop(v, n)];
        let next = p.points[next_in_loop(v, n)];
        let (u, t) = (
            (p.points[v] - prev).normalize_or_zero(),
            (next - p.points[v]).normalize_or_zero(),
        );
        u.dot(t) < STRAIGHT_COS
    };
    if joint(k) {
        out.push(vec![disc(a, half(k))]);
    }
    if !p.closed && k + 2 == n {
        out.push(vec![disc(b, half(k + 1))]);
    }
}

/// Steps 2 and 3 for one gap: centrelines with the road width at each vertex.
fn centrelines(
    gap: &[Vec<DVec2>],
    part: &SegmentIndex,
    s: &GapFillSettings,
) -> Vec<(Vec<DVec2>, Vec<f64>)> {
    let w = s.road_width_mm;
    let Some((nodes, adj)) = chordal_axis(gap, 0.25 * w) else {
        return Vec::new();
    };
    // Width at each node: twice the distance to the gap's boundary.
    let refs: Vec<&[DVec2]> = gap.iter().map(|l| l.as_slice()).collect();
    let boundary = SegmentIndex::new(&refs, &[]);
    let width: Vec<f64> = nodes.iter().map(|&p| 2.0 * boundary.distance(p)).collect();

    let mut out = Vec::new();
    for line in longest_paths(&adj, &nodes, w) {
        // Step 3: chords that hug the boundary (at a concave corner) give near-zero
        // widths inside a gap the opening made at least `min_width` wide: skipped.
        let axis: Vec<DVec2> = line
            .iter()
            .filter(|&&k| width[k] >= s.min_width_mm - 2.0 * WIDTH_SLACK_MM)
            .map(|&k| nodes[k])
            .collect();
        if axis.len() < 2 || crate::geom::polyline_length(&axis) < s.min_width_mm {
            continue;
        }
        let (points, widths) = recentre(&axis, &boundary, part, s);
        if points.len() >= 2 {
            out.push((points, widths));
        }
    }
    out
}

/// Step 2: the chordal axis of a gap, its boundary first divided to at most `step` and
/// triangulated (constrained Delaunay): a node at the midpoint of each chord (an edge
/// two triangles share) and at the centroid of each triangle where three chords meet,
/// with each node's neighbours across the triangles. None where the gap has no
/// triangulation.
fn chordal_axis(gap: &[Vec<DVec2>], step: f64) -> Option<(Vec<DVec2>, Vec<Vec<usize>>)> {
    let shape: Vec<Vec<DVec2>> = gap.iter().map(|l| divide(l, step)).collect();
    if shape.iter().flatten().any(|p| !p.is_finite()) || shape.first().is_none_or(|l| l.len() < 3) {
        return None;
    }
    let tri = shape
        .triangulate()
        .into_delaunay()
        .to_triangulation::<u32>();
    let pts: Vec<DVec2> = tri.points;
    let idx: Vec<usize> = tri.indices.iter().map(|&i| i as usize).collect();
    if idx.len() < 3 || idx.iter().any(|&i| i >= pts.len()) {
        return None;
    }
    // Chords: edges two triangles share. Node per chord (its midpoint), plus the
    // centroid of each triangle where three chords meet.
    let mut edge_tris: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
    for (t, tr) in idx.chunks_exact(3).enumerate() {
        for (a, b) in [(tr[0], tr[1]), (tr[1], tr[2]), (tr[2], tr[0])] {
            edge_tris.entry((a.min(b), a.max(b))).or_default().push(t);
        }
    }
    let mut nodes: Vec<DVec2> = Vec::new();
    let mut chords_of = vec![Vec::new(); idx.len() / 3];
    let mut keys: Vec<_> = edge_tris.iter().filter(|(_, ts)| ts.len() == 2).collect();
    keys.sort_by_key(|(k, _)| **k);
    for (&(a, b), ts) in keys {
        let id = nodes.len();
        nodes.push(0.5 * (pts[a] + pts[b]));
        for &t in ts {
            chords_of[t].push(id);
        }
    }
    let mut adj: Vec<Vec<usize>> = vec![Vec::new(); nodes.len()];
    let link = |adj: &mut Vec<Vec<usize>>, a: usize, b: usize| {
        adj[a].push(b);
        adj[b].push(a);
    };
    for (t, cs) in chords_of.iter().enumerate() {
        match cs.as_slice() {
            [a, b] => link(&mut adj, *a, *b),
            [a, b, c] => {
                let tr = &idx[3 * t..3 * t + 3];
                let id = nodes.len();
                nodes.push((pts[tr[0]] + pts[tr[1]] + pts[tr[2]]) / 3.0);
                adj.push(Vec::new());
                for x in [*a, *b, *c] {
                    link(&mut adj, id, x);
                }
            }
            _ => {}
        }
    }
    Some((nodes, adj))
}

/// The axis resampled to a quarter road width, each point moved to the middle of the
/// gap across the axis and given the gap's width there (capped at `max_width`).
fn recentre(
    axis: &[DVec2],
    boundary: &SegmentIndex,
    part: &SegmentIndex,
    s: &GapFillSettings,
) -> (Vec<DVec2>, Vec<f64>) {
    let step = 0.25 * s.road_width_mm;
    let mut samples = Vec::new();
    for pair in axis.windows(2) {
        let pieces = ((pair[0].distance(pair[1]) / step).ceil() as usize).clamp(1, 1 << 12);
        samples.extend((0..pieces).map(|q| pair[0].lerp(pair[1], q as f64 / pieces as f64)));
    }
    samples.extend(axis.last().copied());
    let n = samples.len();
    let limit = 2.0 * s.max_width_mm;
    let mut points = Vec::with_capacity(n);
    let mut widths = Vec::with_capacity(n);
    for k in 0..n {
        let (a, b) = (samples[k.saturating_sub(1)], samples[(k + 1).min(n - 1)]);
        let across = (b - a).normalize_or_zero().perp();
        let p = samples[k];
        let (centre, wd) = match (
            boundary.ray_hit(p, across, limit),
            boundary.ray_hit(p, -across, limit),
        ) {
            (Some(l), Some(r)) if across != DVec2::ZERO => (p + across * (0.5 * (l - r)), l + r),
            _ => (p, 2.0 * boundary.distance(p)),
        };
        if wd >= s.min_width_mm - 2.0 * WIDTH_SLACK_MM {
            points.push(centre);
            widths.push(wd.min(s.max_width_mm));
        }
    }
    // The ends: where the gap closes ahead, a round end would reach past it; start and
    // stop where the bead's half-width fits.
    // A longest path ends in the corners where the gap meets a road's round end (thin
    // horns): ends narrower than HORN_FRACTION of the median width are dropped.
    let mut sorted = widths.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
    // Where the gap closes ahead, the round end reaches past it: into the road there by
    // at most half its half-width (END_FIT), never out of the part.
    let fits = |k: usize| {
        let h = 0.5 * widths[k];
        widths[k] >= HORN_FRACTION * median
            && boundary.distance(points[k]) >= h * END_FIT
            && part.distance(points[k]) >= h
    };
    let first = (0..points.len()).find(|&k| fits(k));
    let last = (0..points.len()).rev().find(|&k| fits(k));
    match (first, last) {
        (Some(a), Some(b)) if b > a => (points[a..=b].to_vec(), widths[a..=b].to_vec()),
        _ => (Vec::new(), Vec::new()),
    }
}

/// Ends narrower than this fraction of the median width are horns (dropped).
const HORN_FRACTION: f64 = 0.5;
/// How much of a gap-fill end's half-width must fit inside the gap (the rest may ride
/// on the road that closes it; not past the part boundary).
const END_FIT: f64 = 0.5;

/// The centreline roads of a chordal-axis graph: in each connected part the longest
/// path (double sweep), then, with its nodes taken out, any branch left at least
/// `min_branch_mm` long, the longest first.
fn longest_paths(adj: &[Vec<usize>], nodes: &[DVec2], min_branch_mm: f64) -> Vec<Vec<usize>> {
    let n = adj.len();
    let mut taken = vec![false; n];
    let mut out = Vec::new();
    // Distances and parents from `from` over nodes not taken (Dijkstra).
    let sweep = |from: usize, taken: &[bool]| -> (Vec<f64>, Vec<usize>) {
        let mut dist = vec![f64::INFINITY; n];
        let mut parent = vec![usize::MAX; n];
        let mut heap = std::collections::BinaryHeap::new();
        dist[from] = 0.0;
        heap.push((std::cmp::Reverse(Ordered(0.0)), from));
        while let Some((std::cmp::Reverse(Ordered(d)), u)) = heap.pop() {
            if d > dist[u] {
                continue;
            }
            for &v in &adj[u] {
                if taken[v] {
                    continue;
                }
                let nd = d + nodes[u].distance(nodes[v]);
                if nd < dist[v] {
                    dist[v] = nd;
                    parent[v] = u;
                    heap.push((std::cmp::Reverse(Ordered(nd)), v));
                }
            }
        }
        (dist, parent)
    };
    let farthest = |dist: &[f64]| {
        dist.iter()
            .enumerate()
            .filter(|(_, d)| d.is_finite())
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map(|(k, &d)| (k, d))
    };
    for start in 0..n {
        if taken[start] {
            continue;
        }
        let mut first_of_part = true;
        // Up to a few branches per connected part.
        let mut seed = start;
        for _ in 0..MAX_BRANCHES {
            if taken[seed] {
                break;
            }
            let (d0, _) = sweep(seed, &taken);
            let Some((a, _)) = farthest(&d0) else {
                break;
            };
            let (d1, parent) = sweep(a, &taken);
            let Some((b, len)) = farthest(&d1) else {
                break;
            };
            if !first_of_part && len < min_branch_mm {
                break;
            }
            let mut path = vec![b];
            let mut at = b;
            while at != a && parent[at] != usize::MAX {
                at = parent[at];
                path.push(at);
            }
            for &k in &path {
                taken[k] = true;
            }
            out.push(path);
            first_of_part = false;
            // Next branch: from a node of this part not taken yet, if any.
            match (0..n).find(|&k| !taken[k] && d0[k].is_finite()) {
                Some(k) => seed = k,
                None => break,
            }
        }
    }
    out
}

/// Branches taken per connected part of a gap's centreline graph.
const MAX_BRANCHES: usize = 8;

/// An f64 ordered by `total_cmp`, for the heap.
#[derive(Clone, Copy, PartialEq)]
struct Ordered(f64);
impl Eq for Ordered {}
impl PartialOrd for Ordered {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Ordered {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&o.0)
    }
}

/// `l` (a closed loop) with every edge divided to at most `step`.
fn divide(l: &[DVec2], step: f64) -> Vec<DVec2> {
    let mut out = Vec::with_capacity(l.len());
    for (a, b) in loop_edges(l) {
        let pieces = ((a.distance(b) / step).ceil() as usize).clamp(1, 1 << 12);
        out.extend((0..pieces).map(|q| a.lerp(b, q as f64 / pieces as f64)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::coverage::measure;

    const S: GapFillSettings = GapFillSettings {
        road_width_mm: 0.4,
        min_width_mm: 0.1,
        max_width_mm: 0.6,
    };

    fn line(y: f64, composition: f64) -> ToolPath {
        ToolPath {
            role: PathRole::Offset {
                island: 0,
                n: 2,
                i: 1,
            },
            points: vec![DVec2::new(0.0, y), DVec2::new(10.0, y)],
            closed: false,
            width_factors: vec![1.0; 2],
            composition: vec![composition, 1.0 - composition],
            seam_at_corner: false,
        }
    }

    /// The part x from -0.2 to 10.2, y from -0.2 to `top`.
    fn part(top: f64) -> Region {
        let (lo, hi) = (DVec2::new(-0.2, -0.2), DVec2::new(10.2, top));
        Region::new(
            vec![lo, DVec2::new(hi.x, lo.y), hi, DVec2::new(lo.x, hi.y)],
            Vec::new(),
        )
    }

    /// A bar up to y = 1.2 with roads along its two edges: a gap 0.6 mm wide between.
    fn bar() -> (Vec<Region>, Vec<ToolPath>) {
        (vec![part(1.2)], vec![line(0.0, 0.2), line(1.0, 0.8)])
    }

    #[test]
    fn a_gap_between_two_roads_gets_one_road_as_wide_as_the_gap() {
        let (islands, paths) = bar();
        let fill = gap_fill(&islands, &paths, &S);
        assert_eq!(fill.len(), 1, "{fill:?}");
        let (after, road) = &fill[0];
        assert_eq!(road.role, PathRole::GapFill { island: 0, n: 2 });
        assert!(!road.closed);
        // Along the middle of the gap, most of its length, 0.6 mm (1.5 w) wide.
        assert!(road.length_mm() > 8.0, "{}", road.length_mm());
        let k = road.points.len() / 2;
        assert!(
            (road.points[k].y - 0.5).abs() < 0.02,
            "{:?}",
            road.points[k]
        );
        assert!(
            (road.width_factors[k] - 1.5).abs() < 0.05,
            "{:?}",
            road.width_factors
        );
        // Its composition is that of the road nearest its middle, built right after it.
        assert_eq!(road.composition, paths[*after].composition);
        // The gap is covered: void 6.2 mm² of 14.56 before, under 2 % after, and the
        // fill road stays inside the part and off the roads.
        let before = measure(&islands, &paths, 0.4, 0.01);
        let all = insert(paths.clone(), fill);
        assert_eq!(all.len(), 3);
        let after_fill = measure(&islands, &all, 0.4, 0.01);
        assert!(before.void_fraction() > 0.35, "{before:?}");
        assert!(after_fill.void_fraction() < 0.02, "{after_fill:?}");
        assert!(after_fill.overlap_fraction() < 0.02, "{after_fill:?}");
        assert!(after_fill.outside_fraction() < 0.005, "{after_fill:?}");
    }

    #[test]
    fn gaps_narrower_than_the_narrowest_road_are_left() {
        // Roads 0.45 apart: a 0.05 mm sliver, under min_width 0.1.
        let fill = gap_fill(&[part(0.65)], &[line(0.0, 0.5), line(0.45, 0.5)], &S);
        assert!(fill.is_empty(), "{fill:?}");
    }

    #[test]
    fn several_fills_after_one_road_are_entered_at_their_nearer_ends() {
        let (_, paths) = bar();
        let mut a = line(0.5, 0.2);
        a.role = PathRole::GapFill { island: 0, n: 2 };
        a.points = vec![DVec2::new(20.0, 0.5), DVec2::new(12.0, 0.5)];
        let mut b = a.clone();
        b.points = vec![DVec2::new(11.0, 0.5), DVec2::new(10.5, 0.5)];
        let out = insert(paths, vec![(0, a), (0, b)]);
        // After road 0 (ends at x = 10): b (nearer) then a, b entered at x = 10.5.
        assert_eq!(out.len(), 4);
        assert_eq!(out[1].points[0], DVec2::new(10.5, 0.5));
        assert_eq!(out[2].points[0], DVec2::new(12.0, 0.5));
        assert_eq!(out[3].points[0], DVec2::new(0.0, 1.0));
    }

    #[test]
    fn nothing_to_fill_on_bad_input() {
        let (islands, paths) = bar();
        let mut bad = S;
        bad.road_width_mm = f64::NAN;
        assert!(gap_fill(&islands, &paths, &bad).is_empty());
        assert!(gap_fill(&[], &paths, &S).is_empty());
        assert!(gap_fill(&islands, &[], &S).is_empty());
        let mut nan = paths.clone();
        nan[0].points[1] = DVec2::new(f64::NAN, 0.0);
        // A road with a NaN vertex: no panic, and whatever is filled is finite.
        for (after, road) in gap_fill(&islands, &nan, &S) {
            assert!(after < nan.len());
            assert!(road.points.iter().all(|p| p.is_finite()), "{road:?}");
            assert!(road.width_factors.iter().all(|f| f.is_finite() && *f > 0.0));
        }
    }
}
