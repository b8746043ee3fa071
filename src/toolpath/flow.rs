//! Flow raise in narrow sub-areas (§4, Fig. 4(a) locations (i)–(iii)): where the space
//! between a road and its neighbour needs a non-integer number of roads (say 1.3 roads
//! between two beads that touch at 1), the extrusion rate of the roads along the gap is
//! raised from the point where the gap opens, at constant scanning speed, so the beads
//! widen and close it.
//!
//! Steps, per layer:
//!
//! 1. **Subdivide** long edges to at most `probe_step` (one road width), so the width can
//!    change where the gap opens and not only at the planner's vertices.
//! 2. **Probe the gap** on each side of every vertex: march from the bead edge along
//!    the normal of each edge meeting at the vertex, from a point one road width along
//!    that edge (not along the bisector from the vertex, which at a corner reaches the
//!    neighbour's corner √2 further off), and keep the nearer; the free gap ends where
//!    another road's centreline is nearer than the road's own (the midpoint between the
//!    two centrelines). This gives the centre-to-centre distance g to the road facing
//!    the vertex on that side, and which road and edge it is. The part boundary (the
//!    layer's islands) is traced along the same ray: where it comes first, that side
//!    faces a wall at its distance, so no bead widens across the outside (a slot, the
//!    gap between two islands) into the road beyond. Neither within 2w: open.
//! 3. **Width matching** (what Arachne does with variable-width beads, on the planner's
//!    roads): each bead vertex has a half-width h and a shift s of its centreline along
//!    its normal, and takes the room between the facing edges on its two sides, edge to
//!    edge: h = (left + right)/2, s = (left − right)/2, where a side's room is g −
//!    (how far the facing bead reaches towards us), a wall's distance, or w/2 when
//!    open (that edge stays where it is). Iterated ([`MATCH_ITERATIONS`], damped by
//!    half, so two beads sharing a gap settle on half each). So:
//!    - roads beside a gap that needs a non-integer number of roads widen into it from
//!      where it opens (Fig. 4(a), the 1.3 x road at (iii)) and roads spaced closer
//!      than a road width (eq (5) rounds N_max, so the offsets of a sub-region can be
//!      D_max/N_max < D_noz apart) are narrowed, each touching both neighbours without
//!      overlapping either, even when the two gaps differ;
//!    - a bead with the part boundary on one side keeps that edge where nozzle radius
//!      compensation put it, and widens or narrows on the other side only;
//!    - an offset that runs at a slant into a contour tapers and moves off it as the
//!      room on that side closes.
//!
//!    The factor 2h/w is clamped to [`FlowSettings::min_flow_factor`,
//!    `max_flow_factor`] and the shift to half a road width; changes smaller than
//!    `min_gap_fraction` are left where the nominal bead covers the matched one
//!    (rounding never opens a void). Gaps too wide for the cap stay (reported by the
//!    coverage measure). A path's own edges within 1.5 w + 2 reach along it never count
//!    as its neighbour (on a loop's concave side they come nearer than the probe).
//! 4. **Ends** of open roads are never widened, and are pulled back along the road
//!    where the last edge's bead would reach further than a nominal end (along the
//!    road, or sideways into the part boundary at a slant). Over the last two road
//!    widths of an end that runs into the boundary at a slant ([`super::ends::slant`]),
//!    the boundary does not count as a wall: [`super::ends`] fills that corner.

use super::ToolPath;
use crate::geom::{
    edge_count, edge_ends, loop_edge, loop_edges, neighbours, next_in_loop, Region, SegmentIndex,
};
use glam::DVec2;

/// Settings of the flow raise (part of [`crate::pipeline::ProcessSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlowSettings {
    pub road_width_mm: f64,
    pub max_flow_factor: f64,
    /// Gaps narrower than this fraction of a road width beyond touching are left (noise).
    pub min_gap_fraction: f64,
    /// Narrowest bead relative to nominal (≤ 1; 1 turns narrowing off).
    pub min_flow_factor: f64,
}

/// The road facing a vertex on one side: the centre-to-centre gap to it and where it
/// is (path, edge).
#[derive(Clone, Copy, Debug)]
struct Facing {
    gap_mm: f64,
    path: u32,
    edge: u32,
    /// Whether the facing bead's left side (its left edge) is the one towards us.
    left_faces_us: bool,
}

/// What lies beside a vertex on one side.
#[derive(Clone, Copy, Debug)]
enum Side {
    /// Neither a road nor the part boundary within reach: the bead edge stays nominal.
    Open,
    /// Another road.
    Road(Facing),
    /// The part boundary, this far from the centreline (the bead may reach it, no
    /// further: roads never widen across the outside into a road beyond).
    Wall(f64),
}

/// Damped iterations of the width matching (step 3); each halves what is left.
const MATCH_ITERATIONS: usize = 16;

/// Raise the width factors of `paths` in place (steps 1–3), keeping every bead inside
/// the part `islands` (none: no boundary is known, only the roads count).
pub fn raise(paths: &mut [ToolPath], s: &FlowSettings, islands: &[Region]) {
    let w = s.road_width_mm;
    let adjusts = s.max_flow_factor > 1.0 || s.min_flow_factor < 1.0;
    if !w.is_finite() || w <= 0.0 || !adjusts || paths.is_empty() {
        return;
    }
    // Step 1.
    for p in paths.iter_mut() {
        subdivide(p, w);
    }
    let boundary = SegmentIndex::of_regions(islands);
    let facing = facing_sides(paths, w, &boundary, islands);
    let bead = match_widths(paths, &facing, s);
    apply_widths(paths, &bead, s, &boundary);
}

/// Step 2: what faces each vertex of each path on its left and right.
fn facing_sides(
    paths: &[ToolPath],
    w: f64,
    boundary: &SegmentIndex,
    islands: &[Region],
) -> Vec<Vec<[Side; 2]>> {
    // One index over every road. Segment ids of each path in the index (loops first,
    // then open paths) let a probe skip the path's own nearby edges: on the concave
    // side of a curve (a loop's inside) they come nearer than the probe distance and
    // would pass for a neighbour.
    let roads = super::RoadIndex::new(paths);
    let mut facing: Vec<Vec<[Side; 2]>> = (0..paths.len())
        .map(|i| probe_path(paths, i, &roads, boundary, w))
        .collect();
    // Over the last stretch of an open end that runs into the boundary at a slant, the
    // boundary does not count as a wall: the slanted-end continuation ([`super::ends`])
    // fills the corner there, and width matching against the slanting boundary would
    // narrow and shift the bead away from it. Neighbouring roads still count.
    for (p, sides) in paths.iter().zip(facing.iter_mut()) {
        for k in slanted_end_stretch(p, w, boundary, islands) {
            for side in sides[k].iter_mut() {
                if matches!(side, Side::Wall(_)) {
                    *side = Side::Open;
                }
            }
        }
    }
    facing
}

/// Step 3: width matching. Each bead vertex has a half-width h and a shift s of its
/// centreline along its left normal (its edges are at s + h on the left and s − h on
/// the right); all nominal and unshifted at first. Each takes what lies between the
/// facing beads' edges, damped so that two beads sharing a gap settle on half each.
/// Returns (h, s) per vertex of each path.
fn match_widths(
    paths: &[ToolPath],
    facing: &[Vec<[Side; 2]>],
    s: &FlowSettings,
) -> Vec<Vec<(f64, f64)>> {
    let w = s.road_width_mm;
    let (h_min, h_max) = (
        0.5 * w * s.min_flow_factor.min(1.0),
        0.5 * w * s.max_flow_factor.max(1.0),
    );
    let mut bead: Vec<Vec<(f64, f64)>> = paths
        .iter()
        .map(|p| vec![(0.5 * w, 0.0); p.points.len()])
        .collect();
    for _ in 0..MATCH_ITERATIONS {
        let next: Vec<Vec<(f64, f64)>> = facing
            .iter()
            .zip(&bead)
            .map(|(fs, bs)| {
                fs.iter()
                    .zip(bs)
                    .map(|(sides, &(h_old, s_old))| {
                        // Room from our centreline to the facing edge, left and right.
                        // Open space: that edge stays where it is.
                        let room = |side: &Side| match side {
                            Side::Open => 0.5 * w,
                            Side::Road(f) => f.gap_mm - reach_towards(&bead, f),
                            Side::Wall(d) => *d,
                        };
                        let (left, right) = (room(&sides[0]), room(&sides[1]));
                        let h = (0.5 * (left + right)).clamp(h_min, h_max);
                        let shift = (0.5 * (left - right)).clamp(-MAX_SHIFT * w, MAX_SHIFT * w);
                        (
                            (0.5 * (h_old + h)).clamp(h_min, h_max),
                            0.5 * (s_old + shift),
                        )
                    })
                    .collect()
            })
            .collect();
        bead = next;
    }
    bead
}

/// How far the facing bead `f` reaches towards us from its own centreline, given every
/// bead vertex's (half-width, shift).
fn reach_towards(bead: &[Vec<(f64, f64)>], f: &Facing) -> f64 {
    let b = &bead[f.path as usize];
    // The facing edge's two vertices (its number is below the vertex count).
    let (i, j) = (f.edge as usize, next_in_loop(f.edge as usize, b.len()));
    let (h, s) = (0.5 * (b[i].0 + b[j].0), 0.5 * (b[i].1 + b[j].1));
    if f.left_faces_us {
        h + s
    } else {
        h - s
    }
}

/// The matched beads (`bead`, per vertex) as width factors and shifted centrelines; a
/// change too small to matter is left, and open roads' end caps kept (step 4).
fn apply_widths(
    paths: &mut [ToolPath],
    bead: &[Vec<(f64, f64)>],
    s: &FlowSettings,
    boundary: &SegmentIndex,
) {
    let w = s.road_width_mm;
    for (p, bs) in paths.iter_mut().zip(bead) {
        let normals = vertex_normals(&p.points, p.closed);
        for (k, &(h, shift)) in bs.iter().enumerate() {
            let f = 2.0 * h / w;
            // A change too small to matter is left, but only where the nominal bead
            // covers the matched one (rounding never opens a void).
            let keep = f >= 1.0 - s.min_gap_fraction && h + shift.abs() <= 0.5 * w * (1.0 + 1e-9);
            if keep {
                p.width_factors[k] = 1.0;
            } else {
                p.width_factors[k] = f;
                p.points[k] += normals[k] * shift;
            }
        }
        if !p.closed {
            keep_end_caps(p, w, boundary);
        }
    }
}

/// How far back along an open road from an end that runs into the boundary at a slant
/// the boundary does not count as a wall, in road widths.
const SLANTED_END_STRETCH: f64 = 2.0;

/// The vertices of `p` within [`SLANTED_END_STRETCH`] of an end that runs into the part
/// boundary at a slant ([`super::ends::slant`]).
fn slanted_end_stretch(
    p: &ToolPath,
    w: f64,
    boundary: &SegmentIndex,
    islands: &[Region],
) -> Vec<usize> {
    let n = p.points.len();
    let mut out = Vec::new();
    if p.closed || n < 2 || boundary.is_empty() {
        return out;
    }
    for (end, inner, step) in [(0usize, 1usize, 1isize), (n - 1, n - 2, -1)] {
        let (e, q) = (p.points[end], p.points[inner]);
        if super::ends::slant(e, q, 0.5 * w, w, boundary, islands).is_none() {
            continue;
        }
        let mut k = end;
        let mut along = 0.0;
        loop {
            out.push(k);
            let next = k as isize + step;
            if next < 0 || next as usize >= n {
                break;
            }
            along += p.points[k].distance(p.points[next as usize]);
            if along > SLANTED_END_STRETCH * w {
                break;
            }
            k = next as usize;
        }
    }
    out
}

/// An open road's ends were placed (clipped) so that a nominal bead's round end reaches
/// the part boundary or the road it runs into and no further. A widened end would reach
/// beyond: the end vertex is never widened, and where the last edge still is (its bead
/// is the mean of its two vertices), the end is pulled back along the road by the excess.
fn keep_end_caps(p: &mut ToolPath, w: f64, boundary: &SegmentIndex) {
    let n = p.points.len();
    if n < 2 {
        return;
    }
    for (end, inner) in [(0, 1), (n - 1, n - 2)] {
        p.width_factors[end] = p.width_factors[end].min(1.0);
        let r = 0.25 * w * (p.width_factors[end] + p.width_factors[inner]);
        let (a, b) = (p.points[end], p.points[inner]);
        let len = a.distance(b);
        if r <= 0.5 * w || len <= 0.0 {
            continue;
        }
        // Along the road: no further than a nominal end reached.
        let mut t = ((r - 0.5 * w) / len).min(0.5);
        // Sideways: the round end stays inside the part where the road meets the
        // boundary at a slant (it reached it at w/2 there).
        if !boundary.is_empty() && boundary.distance(a.lerp(b, t)) < r {
            let (mut lo, mut hi) = (t, 0.5);
            if boundary.distance(a.lerp(b, hi)) >= r {
                for _ in 0..CLEARANCE_BISECTIONS {
                    let mid = 0.5 * (lo + hi);
                    if boundary.distance(a.lerp(b, mid)) >= r {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
            }
            t = hi;
        }
        p.points[end] = a.lerp(b, t);
    }
}

/// Bisections of an end's pull-back (1/2^12 of half the last edge).
const CLEARANCE_BISECTIONS: usize = 12;

/// Largest shift of a bead's centreline, in road widths.
const MAX_SHIFT: f64 = 0.5;

/// The left normal at each vertex, scaled so that moving the vertex by `normal * s`
/// moves both edges meeting there by s (mitre, at most 2 for sharp corners).
fn vertex_normals(points: &[DVec2], closed: bool) -> Vec<DVec2> {
    let n = points.len();
    (0..n)
        .map(|k| {
            let (prev, next) = neighbours(k, n, closed);
            let (prev, next) = (prev.map(|i| points[i]), next.map(|i| points[i]));
            let q = points[k];
            let left = |a: DVec2, b: DVec2| (b - a).normalize_or_zero().perp();
            let (a, b) = match (prev, next) {
                (Some(p), Some(x)) => (left(p, q), left(q, x)),
                (Some(p), None) => (left(p, q), left(p, q)),
                (None, Some(x)) => (left(q, x), left(q, x)),
                (None, None) => (DVec2::ZERO, DVec2::ZERO),
            };
            let mid = (a + b).normalize_or_zero();
            let cos = mid.dot(a);
            if cos <= 0.5 {
                mid * 2.0
            } else {
                mid / cos
            }
        })
        .collect()
}

/// Step 2 for path `i`: what faces each vertex on its left and right.
fn probe_path(
    paths: &[ToolPath],
    i: usize,
    roads: &super::RoadIndex,
    boundary: &SegmentIndex,
    w: f64,
) -> Vec<[Side; 2]> {
    let p = &paths[i];
    let n = p.points.len();
    if n < 2 {
        return vec![[Side::Open, Side::Open]; n];
    }
    let prober = Prober::new(paths, roads, boundary, w);
    let own = OwnEdges::of(p, roads.first_segment[i], prober.own_window);
    (0..n)
        .map(|k| {
            let s0 = own.cum[k];
            let probes = probes_at(p, k, w);
            let mut sides = [Side::Open, Side::Open];
            for (facing, side) in sides.iter_mut().zip([1.0, -1.0]) {
                for (origin, nrm) in &probes {
                    let found = prober.march(*origin, *nrm * side, |id| own.near(id, s0));
                    if found.nearness(w) < facing.nearness(w) {
                        *facing = found;
                    }
                }
            }
            sides
        })
        .collect()
}

impl Side {
    /// How near a side's finding is: a road by its nominal edge (road width `w`), a wall
    /// by itself.
    fn nearness(&self, w: f64) -> f64 {
        match self {
            Side::Open => f64::INFINITY,
            Side::Road(f) => f.gap_mm - 0.5 * w,
            Side::Wall(t) => *t,
        }
    }
}

/// A path's own edges, which never count as its neighbour within `window` along it of
/// the vertex probed (on a loop's concave side they come nearer than the probe).
struct OwnEdges {
    /// The path's first segment in the road index, and how many it has.
    base: u32,
    segments: u32,
    /// Distance along the path to each vertex, and round the closing edge back to the
    /// first (open paths too: it is read only past their last vertex).
    cum: Vec<f64>,
    /// The path's length.
    total: f64,
    closed: bool,
    window: f64,
}

impl OwnEdges {
    fn of(p: &ToolPath, base: u32, window: f64) -> Self {
        let n = p.points.len();
        let mut cum = Vec::with_capacity(n + 1);
        cum.push(0.0);
        for (a, b) in loop_edges(&p.points) {
            let last = cum[cum.len() - 1];
            cum.push(last + a.distance(b));
        }
        let segments = edge_count(n, p.closed);
        OwnEdges {
            base,
            segments: segments as u32,
            total: cum[segments],
            cum,
            closed: p.closed,
            window,
        }
    }

    /// Is segment `id` of the road index one of the path's own edges within the window
    /// along it of the point `s0` along it?
    fn near(&self, id: u32, s0: f64) -> bool {
        let Some(j) = id.checked_sub(self.base).filter(|&j| j < self.segments) else {
            return false;
        };
        let (a, b) = (self.cum[j as usize], self.cum[j as usize + 1]);
        let gap = |x: f64| {
            if x < a {
                a - x
            } else if x > b {
                x - b
            } else {
                0.0
            }
        };
        let mut d = gap(s0);
        if self.closed {
            d = d.min(gap(s0 + self.total)).min(gap(s0 - self.total));
        }
        d < self.window
    }
}

/// The probes of vertex `k` of `p` (road width `w`), as (origin, left normal): beside
/// each edge meeting at the vertex, along that edge's normal and from a point a road
/// width along it, not along the bisector from the vertex: at a corner the bisector
/// reaches the neighbouring road's corner √2 times further off than the road beside
/// each edge, and a probe from the vertex along one edge's normal runs beside the other
/// edge. Along a straight run, one probe from the vertex.
fn probes_at(p: &ToolPath, k: usize, w: f64) -> Vec<(DVec2, DVec2)> {
    let (prev, next) = neighbours(k, p.points.len(), p.closed);
    let (prev, next) = (prev.map(|i| p.points[i]), next.map(|i| p.points[i]));
    let q0 = p.points[k];
    let edges: Vec<(f64, DVec2)> = [(-1.0, prev), (1.0, next)]
        .into_iter()
        .filter_map(|(dir, o)| o.map(|o| (dir, (o - q0).normalize_or_zero())))
        .filter(|(_, u)| *u != DVec2::ZERO)
        .collect();
    let straight = match edges.as_slice() {
        [(_, a), (_, b)] => -a.dot(*b) > STRAIGHT_COS,
        _ => true,
    };
    if straight {
        // Along a straight run (subdivided edges) one probe from the vertex serves
        // both edges; `perp` of the travel direction is the left side.
        let t = match (prev, next) {
            (Some(a), Some(b)) => b - a,
            (Some(a), None) => q0 - a,
            (None, Some(b)) => b - q0,
            (None, None) => DVec2::ZERO,
        };
        let nrm = t.normalize_or_zero().perp();
        if nrm == DVec2::ZERO {
            Vec::new()
        } else {
            vec![(q0, nrm)]
        }
    } else {
        // One road width back along the path: beside a right-angle corner the
        // parallel neighbour ends its spacing short of the corner.
        edges
            .iter()
            .map(|&(dir, u)| {
                let origin = walk(&p.points, p.closed, k, dir < 0.0, w);
                // Travel direction: into the vertex on the way in, out on the way out.
                (origin, (u * dir).perp())
            })
            .collect()
    }
}

/// What a probe marches through: the layer's roads and the part boundary.
struct Prober<'a> {
    paths: &'a [ToolPath],
    roads: &'a super::RoadIndex,
    boundary: &'a SegmentIndex,
    w: f64,
    /// The march's step along the probe.
    step: f64,
    /// How far beyond the nominal bead edge the probe looks: up to a gap of 2w centre
    /// to centre.
    reach: f64,
    /// Own edges nearer (along the path) than this are never a neighbour.
    own_window: f64,
}

impl<'a> Prober<'a> {
    fn new(
        paths: &'a [ToolPath],
        roads: &'a super::RoadIndex,
        boundary: &'a SegmentIndex,
        w: f64,
    ) -> Self {
        let reach = w;
        Prober {
            paths,
            roads,
            boundary,
            w,
            step: w / 8.0,
            reach,
            own_window: 1.5 * w + 2.0 * reach,
        }
    }

    /// What faces the probe from `origin` along `dir` (unit): the part boundary where
    /// it comes first, else the first road (not `own`) whose centreline becomes nearer
    /// than ours, else open.
    fn march(&self, origin: DVec2, dir: DVec2, own: impl Fn(u32) -> bool) -> Side {
        let (w, index) = (self.w, &self.roads.index);
        let limit = 2.0 * (0.5 * w + self.reach);
        let wall = self.boundary.ray_hit(origin, dir, limit);
        // Half the centre-to-centre gap: where another centreline becomes nearer than
        // our own. Neighbours closer than w/2 are not roads of this plan.
        let mut d = 0.25 * w + self.step;
        while d <= 0.5 * w + self.reach && wall.is_none_or(|t| d < t) {
            let q = origin + dir * d;
            // Only a segment within d − ε of q can be a neighbour found here; the
            // bounded look rules most steps out before the nearest-segment search
            // (which widens until it finds one, however far).
            let near = index.within(q, d - 1e-3 * w);
            if let Some((other, id)) = near.then(|| index.nearest_skipping(q, &own)).flatten() {
                if other < d - 1e-3 * w {
                    // Parallel neighbour at g: other = g - d, so g = d + other.
                    let g = d + other;
                    if wall.is_some_and(|t| t < g) {
                        break; // beyond the part boundary
                    }
                    return Side::Road(self.facing(id, g, dir));
                }
            }
            d += self.step;
        }
        wall.map_or(Side::Open, Side::Wall)
    }

    /// The road segment `id` of the road index, facing a probe along `dir` at the
    /// centre-to-centre gap `gap_mm`.
    fn facing(&self, id: u32, gap_mm: f64, dir: DVec2) -> Facing {
        let path = self.roads.owner[id as usize];
        let edge = id - self.roads.first_segment[path as usize];
        let (a, b) = loop_edge(&self.paths[path as usize].points, edge as usize);
        Facing {
            gap_mm,
            path,
            edge,
            left_faces_us: (b - a).perp().dot(dir) < 0.0,
        }
    }
}

/// The point `dist` along `points` from vertex `k`, backwards or forwards (stopping at
/// an open path's end, or halfway round a loop).
fn walk(points: &[DVec2], closed: bool, k: usize, backwards: bool, dist: f64) -> DVec2 {
    let n = points.len();
    let (mut at, mut left) = (k, dist);
    for _ in 0..n / 2 {
        let (prev, next) = neighbours(at, n, closed);
        let Some(next) = (if backwards { prev } else { next }) else {
            break;
        };
        let len = points[at].distance(points[next]);
        if len >= left {
            return points[at].lerp(points[next], left / len);
        }
        left -= len;
        at = next;
    }
    points[at]
}

/// Edges whose normals are closer than this (cosine, about 2.6°) count as one direction.
const STRAIGHT_COS: f64 = 0.999;

fn subdivide(p: &mut ToolPath, max_len: f64) {
    let n = p.points.len();
    if n < 2 {
        return;
    }
    let mut pts = Vec::with_capacity(n);
    let mut fs = Vec::with_capacity(n);
    for (k, j) in edge_ends(n, p.closed) {
        let (a, b) = (p.points[k], p.points[j]);
        let (fa, fb) = (p.width_factors[k], p.width_factors[j]);
        let pieces = ((a.distance(b) / max_len).ceil() as usize).max(1);
        for q in 0..pieces {
            let t = q as f64 / pieces as f64;
            pts.push(a.lerp(b, t));
            fs.push(fa + (fb - fa) * t);
        }
    }
    if !p.closed {
        pts.push(p.points[n - 1]);
        fs.push(p.width_factors[n - 1]);
    }
    p.points = pts;
    p.width_factors = fs;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::PathRole;

    const SETTINGS: FlowSettings = FlowSettings {
        road_width_mm: 0.4,
        max_flow_factor: 1.5,
        min_gap_fraction: 0.02,
        min_flow_factor: 0.6,
    };

    /// A closed road through `points` (counter-clockwise).
    fn closed_road(points: Vec<DVec2>) -> ToolPath {
        ToolPath {
            role: PathRole::Contour { island: 0, j: 1 },
            width_factors: vec![1.0; points.len()],
            points,
            closed: true,
            composition: vec![1.0],
            seam_at_corner: false,
        }
    }

    fn line(y: f64) -> ToolPath {
        ToolPath {
            role: PathRole::Contour { island: 0, j: 1 },
            points: vec![DVec2::new(0.0, y), DVec2::new(10.0, y)],
            closed: false,
            width_factors: vec![1.0; 2],
            composition: vec![1.0],
            seam_at_corner: false,
        }
    }

    /// Where the bead at the middle of `p` has its edges (below, above) for lines along x.
    fn edges(p: &ToolPath) -> (f64, f64) {
        let k = p.points.len() / 2;
        let (y, f) = (p.points[k].y, p.width_factors[k]);
        (y - 0.2 * f, y + 0.2 * f)
    }

    #[test]
    fn a_gap_between_two_roads_is_shared_and_their_far_edges_stay() {
        // Centre to centre 1.3 w, nothing beyond either road: each bead widens by 0.15 w
        // into the gap (factor 1.15) and its centreline moves 0.075 w towards it, so the
        // beads meet in the middle and their far edges stay where they were.
        let mut paths = vec![line(0.0), line(0.52)];
        raise(&mut paths, &SETTINGS, &[]);
        let (a, b) = (edges(&paths[0]), edges(&paths[1]));
        assert!(
            (a.0 + 0.2).abs() < 1e-6 && (b.1 - 0.72).abs() < 1e-6,
            "{a:?} {b:?}"
        );
        assert!(
            (a.1 - 0.26).abs() < 1e-6 && (b.0 - 0.26).abs() < 1e-6,
            "{a:?} {b:?}"
        );
        let mid = paths[0].width_factors[paths[0].points.len() / 2];
        assert!((mid - 1.15).abs() < 1e-6, "{mid}");
        // Touching roads stay nominal and in place; a wide gap is capped.
        let mut touching = vec![line(0.0), line(0.4)];
        raise(&mut touching, &SETTINGS, &[]);
        assert!(touching[0].width_factors.iter().all(|&f| f == 1.0));
        assert!(touching[0].points.iter().all(|q| q.y == 0.0));
        let mut wide = vec![line(0.0), line(0.9)];
        raise(&mut wide, &SETTINGS, &[]);
        let f = wide[0].width_factors[5];
        assert!((f - 1.5).abs() < 1e-4, "{f}");
    }

    #[test]
    fn a_road_between_two_roads_fills_the_space_between_their_edges() {
        // Neighbours at 0.5 below and 0.6 above (w = 0.4): the middle bead spans from
        // the lower bead's edge to the upper one's, off centre (the 1.3 x road of Fig.
        // 4(a) (iii) when the gap is even). The outer beads meet it half way.
        let mut paths = vec![line(0.0), line(0.5), line(1.1)];
        raise(&mut paths, &SETTINGS, &[]);
        let e: Vec<(f64, f64)> = paths.iter().map(edges).collect();
        assert!(
            (e[0].0 + 0.2).abs() < 1e-6 && (e[2].1 - 1.3).abs() < 1e-6,
            "{e:?}"
        );
        for k in 0..2 {
            assert!((e[k].1 - e[k + 1].0).abs() < 2e-3, "{e:?}");
        }
    }

    #[test]
    fn roads_closer_than_a_road_width_are_narrowed_to_share_the_space() {
        let mut paths = vec![line(0.0), line(0.3), line(0.6), line(0.9)];
        raise(&mut paths, &SETTINGS, &[]);
        let e: Vec<(f64, f64)> = paths.iter().map(edges).collect();
        // The outer beads keep their far edges where nozzle radius compensation put
        // them; the four share the 1.3 mm between (0.325 each on average), edge to edge.
        assert!(
            (e[0].0 + 0.2).abs() < 1e-6 && (e[3].1 - 1.1).abs() < 1e-6,
            "{e:?}"
        );
        for k in 0..3 {
            assert!((e[k].1 - e[k + 1].0).abs() < 0.01, "{e:?}");
        }
        for p in &paths {
            let f = p.width_factors[p.points.len() / 2];
            assert!((0.6..0.95).contains(&f), "{f}");
        }
        // Never below the floor.
        let mut tight = vec![line(0.0), line(0.12), line(0.24)];
        raise(&mut tight, &SETTINGS, &[]);
        assert!(tight[1].width_factors.iter().all(|&f| f >= 0.6 - 1e-12));
    }

    #[test]
    fn no_road_widens_across_the_part_boundary() {
        // Two roads 1.5 w apart with the part's edge between them (a slot), each a road
        // width from the edges: each stays nominal; without the boundary they would
        // widen into the slot.
        let slot = Region::new(
            vec![
                DVec2::new(-5.0, -0.2),
                DVec2::new(15.0, -0.2),
                DVec2::new(15.0, 0.8),
                DVec2::new(-5.0, 0.8),
            ],
            vec![vec![
                DVec2::new(-1.0, 0.2),
                DVec2::new(-1.0, 0.4),
                DVec2::new(11.0, 0.4),
                DVec2::new(11.0, 0.2),
            ]],
        );
        let mut paths = vec![line(0.0), line(0.6)];
        raise(&mut paths, &SETTINGS, &[slot]);
        for p in &paths {
            assert!(
                p.width_factors.iter().all(|&f| f == 1.0),
                "{:?}",
                p.width_factors
            );
        }
        let mut open = vec![line(0.0), line(0.6)];
        raise(&mut open, &SETTINGS, &[]);
        assert!(open[0].width_factors[5] > 1.2);
    }

    #[test]
    fn a_widened_open_road_ends_no_further_than_a_nominal_one() {
        // Two short roads 1.5 w apart, ending at x = 0 and x = 10: the beads widen to
        // 1.25, but their round ends reach no further than x = -0.2 and 10.2.
        let mut paths = vec![line(0.0), line(0.6)];
        raise(&mut paths, &SETTINGS, &[]);
        for p in &paths {
            let n = p.points.len();
            let r = |a: usize, b: usize| 0.1 * (p.width_factors[a] + p.width_factors[b]);
            assert!(p.points[0].x - r(0, 1) >= -0.2 - 1e-9, "{:?}", p.points[0]);
            assert!(p.points[n - 1].x + r(n - 1, n - 2) <= 10.2 + 1e-9);
        }
    }

    #[test]
    fn corners_of_nested_loops_one_road_apart_are_not_raised() {
        // Two squares one road width apart: along the bisector the outer square's corner
        // is √2 w away, but beside every edge the neighbour touches: no raise anywhere.
        let square = |h: f64| {
            closed_road(
                [(-h, -h), (h, -h), (h, h), (-h, h)]
                    .iter()
                    .map(|&(x, y)| DVec2::new(x, y))
                    .collect(),
            )
        };
        let mut paths = vec![square(3.0), square(3.4)];
        raise(&mut paths, &SETTINGS, &[]);
        for p in &paths {
            assert!(
                p.width_factors.iter().all(|&f| f == 1.0),
                "{:?}",
                p.width_factors
            );
        }
    }

    #[test]
    fn a_loop_is_not_its_own_neighbour() {
        // On the inside of a polygonal circle the loop's own edges come nearer than the
        // probe distance; they must not count as a neighbour. The inner of two rings 0.3
        // apart (w = 0.4) has a neighbour on one side only (the outer ring).
        let ring = |r: f64| {
            closed_road(
                (0..24)
                    .map(|k| {
                        let a = std::f64::consts::TAU * k as f64 / 24.0;
                        DVec2::new(a.cos(), a.sin()) * r
                    })
                    .collect(),
            )
        };
        // Its inner edge stays and it gives up half the 0.1 mm overlap to the outer
        // ring (factor about 0.875); its own edges would have narrowed it further.
        let mut paths = vec![ring(1.2), ring(1.5)];
        raise(&mut paths, &SETTINGS, &[]);
        assert!(
            paths[0]
                .width_factors
                .iter()
                .all(|&f| (f - 0.875).abs() < 0.02),
            "{:?}",
            paths[0].width_factors
        );
    }
}
