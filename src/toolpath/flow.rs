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
//!    the vertex on that side, and which road and edge it is (none where no road is
//!    within 2w, e.g. the part boundary side of the outer contour).
//! 3. **Width matching**: every bead's half-width h takes the room between its
//!    centreline and the edges of the beads facing it (g − h_facing), iterated
//!    ([`MATCH_ITERATIONS`], damped by half, so two beads sharing a gap settle on half
//!    each):
//!    - beads facing it on both sides: the larger room, so it touches both (never a
//!      void) and overlaps the nearer as little as that allows. Roads spaced closer
//!      than a road width (eq (5) rounds N_max, so the equal distance offsets of a
//!      sub-region can be D_max/N_max < D_noz apart) are narrowed, and roads beside a
//!      gap that needs a non-integer number of roads (w < g < 2w) widen into it (Fig.
//!      4(a), the 1.3 x road at (iii));
//!    - a bead facing it on one side only (the other is the part boundary or open
//!      space): at least nominal, raised into a gap, never narrowed, so its far edge
//!      stays where nozzle radius compensation put it.
//!
//!    The factor 2h/w is clamped to [`FlowSettings::min_flow_factor`,
//!    `max_flow_factor`]; changes smaller than `min_gap_fraction` are left (noise). Gaps
//!    too wide for the cap stay (a gap-fill road would be needed: not implemented,
//!    reported by the coverage measure). A path's own edges within 1.5 w + 2 reach
//!    along it never count as its neighbour (on a loop's concave side they come nearer
//!    than the probe).

use super::ToolPath;
use crate::geom::SegmentIndex;
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
}

/// Damped iterations of the width matching (step 3); each halves what is left.
const MATCH_ITERATIONS: usize = 8;

/// Raise the width factors of `paths` in place (steps 1–3).
pub fn raise(paths: &mut [ToolPath], s: &FlowSettings) {
    let w = s.road_width_mm;
    let adjusts = s.max_flow_factor > 1.0 || s.min_flow_factor < 1.0;
    if !w.is_finite() || w <= 0.0 || !adjusts || paths.is_empty() {
        return;
    }
    // Step 1.
    for p in paths.iter_mut() {
        subdivide(p, w);
    }
    // Step 2: one index over every road.
    let loops: Vec<&[DVec2]> = paths
        .iter()
        .filter(|p| p.closed)
        .map(|p| p.points.as_slice())
        .collect();
    let lines: Vec<&[DVec2]> = paths
        .iter()
        .filter(|p| !p.closed)
        .map(|p| p.points.as_slice())
        .collect();
    let index = SegmentIndex::new(&loops, &lines);
    // Segment ids of each path in the index (loops first, then open paths) and the arc
    // length at each of its vertices, so a probe can skip the path's own nearby edges:
    // on the concave side of a curve (a loop's inside) they come nearer than the probe
    // distance and would pass for a neighbour.
    let mut first_segment = vec![0u32; paths.len()];
    let mut owner: Vec<u32> = Vec::new(); // path of each segment id
    for closed in [true, false] {
        for (i, p) in paths.iter().enumerate().filter(|(_, p)| p.closed == closed) {
            first_segment[i] = owner.len() as u32;
            let n = p.points.len();
            let edges = if closed { n } else { n.saturating_sub(1) };
            owner.extend(std::iter::repeat_n(i as u32, edges));
        }
    }
    let facing: Vec<Vec<[Option<Facing>; 2]>> = paths
        .iter()
        .enumerate()
        .map(|(i, p)| probe_path(p, first_segment[i], &owner, &first_segment, &index, w))
        .collect();

    // Step 3: width matching. Half-widths h, all nominal at first; each bead takes what
    // lies between its centreline and the facing beads' edges, damped so that two
    // beads sharing a gap settle on half each.
    let (h_min, h_max) = (
        0.5 * w * s.min_flow_factor.min(1.0),
        0.5 * w * s.max_flow_factor.max(1.0),
    );
    let mut h: Vec<Vec<f64>> = paths
        .iter()
        .map(|p| vec![0.5 * w; p.points.len()])
        .collect();
    let half_width_at = |h: &[Vec<f64>], f: &Facing| {
        let hp = &h[f.path as usize];
        let n = hp.len();
        let e = f.edge as usize;
        0.5 * (hp[e % n] + hp[(e + 1) % n])
    };
    for _ in 0..MATCH_ITERATIONS {
        let next: Vec<Vec<f64>> = facing
            .iter()
            .zip(&h)
            .map(|(fs, hs)| {
                fs.iter()
                    .zip(hs)
                    .map(|(sides, &old)| {
                        let room = |f: &Option<Facing>| f.map(|f| f.gap_mm - half_width_at(&h, &f));
                        let target = match [room(&sides[0]), room(&sides[1])] {
                            // Both sides: touch the farther bead (never a void), overlap
                            // the nearer one as little as that allows.
                            [Some(a), Some(b)] => a.max(b),
                            // One side (the other is the part boundary or open space):
                            // raised into a gap, never narrowed, so the far edge stays
                            // where nozzle radius compensation put it.
                            [Some(g), None] | [None, Some(g)] => g.max(0.5 * w),
                            [None, None] => 0.5 * w,
                        };
                        (0.5 * (old + target)).clamp(h_min, h_max)
                    })
                    .collect()
            })
            .collect();
        h = next;
    }
    for (p, hs) in paths.iter_mut().zip(&h) {
        p.width_factors = hs
            .iter()
            .map(|&hk| {
                let f = 2.0 * hk / w;
                if (f - 1.0).abs() <= s.min_gap_fraction {
                    1.0
                } else {
                    f
                }
            })
            .collect();
    }
}

/// Step 2 for one path: the road facing each vertex on its left and right.
fn probe_path(
    p: &ToolPath,
    base: u32,
    owner: &[u32],
    first_segment: &[u32],
    index: &SegmentIndex,
    w: f64,
) -> Vec<[Option<Facing>; 2]> {
    let n = p.points.len();
    if n < 2 {
        return vec![[None, None]; n];
    }
    let step = w / 8.0;
    let reach = w; // probe up to a gap of 2w centre to centre
                   // Own edges nearer (along the path) than this are never a neighbour.
    let own_window = 1.5 * w + 2.0 * reach;
    let mut cum = Vec::with_capacity(n + 1);
    cum.push(0.0);
    for j in 0..n {
        let b = if j + 1 < n {
            p.points[j + 1]
        } else {
            p.points[0]
        };
        let last = cum[j];
        cum.push(last + p.points[j].distance(b));
    }
    let total = if p.closed { cum[n] } else { cum[n - 1] };
    let segments = if p.closed { n } else { n - 1 } as u32;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let s0 = cum[k];
        let own_nearby = |id: u32| {
            let Some(j) = id.checked_sub(base).filter(|&j| j < segments) else {
                return false;
            };
            let (a, b) = (cum[j as usize], cum[j as usize + 1]);
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
            if p.closed {
                d = d.min(gap(s0 + total)).min(gap(s0 - total));
            }
            d < own_window
        };
        let prev = if k > 0 {
            Some(p.points[k - 1])
        } else if p.closed {
            Some(p.points[n - 1])
        } else {
            None
        };
        let next = if k + 1 < n {
            Some(p.points[k + 1])
        } else if p.closed {
            Some(p.points[0])
        } else {
            None
        };
        let q0 = p.points[k];
        // Probe beside each edge meeting at the vertex, along that edge's normal and
        // from a point a road width along it, not along the bisector from the vertex:
        // at a corner the bisector reaches the neighbouring road's corner √2 times
        // further off than the road beside each edge, and a probe from the vertex along
        // one edge's normal runs beside the other edge.
        let edges: Vec<(f64, DVec2)> = [(-1.0, prev), (1.0, next)]
            .into_iter()
            .filter_map(|(dir, o)| o.map(|o| (dir, (o - q0).normalize_or_zero())))
            .filter(|(_, u)| *u != DVec2::ZERO)
            .collect();
        let straight = match edges.as_slice() {
            [(_, a), (_, b)] => -a.dot(*b) > STRAIGHT_COS,
            _ => true,
        };
        let probes: Vec<(DVec2, DVec2)> = if straight {
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
        };
        let mut sides = [None, None];
        for (facing, side) in sides.iter_mut().zip([1.0, -1.0]) {
            for (origin, nrm) in &probes {
                // Half the centre-to-centre gap: where another centreline becomes nearer
                // than our own. Neighbours closer than w/2 are not roads of this plan.
                let mut d = 0.25 * w + step;
                while d <= 0.5 * w + reach {
                    let q = *origin + *nrm * (side * d);
                    if let Some((other, id)) = index.nearest_skipping(q, own_nearby) {
                        if other < d - 1e-3 * w {
                            // Parallel neighbour at g: other = g - d, so g = d + other.
                            let g = d + other;
                            let path = owner[id as usize];
                            let f = Facing {
                                gap_mm: g,
                                path,
                                edge: id - first_segment[path as usize],
                            };
                            if facing.is_none_or(|x: Facing| g < x.gap_mm) {
                                *facing = Some(f);
                            }
                            break;
                        }
                    }
                    d += step;
                }
            }
        }
        out.push(sides);
    }
    out
}

/// The point `dist` along `points` from vertex `k`, backwards or forwards (stopping at
/// an open path's end, or halfway round a loop).
fn walk(points: &[DVec2], closed: bool, k: usize, backwards: bool, dist: f64) -> DVec2 {
    let n = points.len();
    let (mut at, mut left) = (k, dist);
    for _ in 0..n / 2 {
        let next = match (backwards, closed) {
            (true, _) if at > 0 => at - 1,
            (true, true) => n - 1,
            (false, _) if at + 1 < n => at + 1,
            (false, true) => 0,
            _ => break,
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
    let edges = if p.closed { n } else { n - 1 };
    let mut pts = Vec::with_capacity(n);
    let mut fs = Vec::with_capacity(n);
    for k in 0..edges {
        let (a, b) = (p.points[k], p.points[(k + 1) % n]);
        let (fa, fb) = (p.width_factors[k], p.width_factors[(k + 1) % n]);
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

    #[test]
    fn a_gap_of_one_and_a_third_roads_widens_both_neighbours() {
        // Centre to centre 1.3 w: each bead widens by 0.15 w on each side: factor 1.3.
        let mut paths = vec![line(0.0), line(0.52)];
        let s = SETTINGS;
        raise(&mut paths, &s);
        let mid = paths[0].width_factors[paths[0].points.len() / 2];
        assert!((mid - 1.3).abs() < 0.05, "{mid}");
        // Touching roads stay nominal; a wide gap is capped.
        let mut touching = vec![line(0.0), line(0.4)];
        raise(&mut touching, &s);
        assert!(touching[0].width_factors.iter().all(|&f| f == 1.0));
        let mut wide = vec![line(0.0), line(0.76)];
        raise(&mut wide, &s);
        let f = wide[0].width_factors[5];
        assert!((f - 1.5).abs() < 1e-9, "{f}");
    }

    #[test]
    fn roads_closer_than_a_road_width_on_both_sides_are_narrowed_to_their_spacing() {
        let s = SETTINGS;
        let mut paths = vec![line(0.0), line(0.3), line(0.6), line(0.9)];
        raise(&mut paths, &s);
        let mid = |p: &ToolPath| p.width_factors[p.points.len() / 2];
        // Inner roads: neighbours 0.3 away on both sides: 0.3 wide.
        assert!((mid(&paths[1]) - 0.75).abs() < 0.02, "{}", mid(&paths[1]));
        assert!((mid(&paths[2]) - 0.75).abs() < 0.02, "{}", mid(&paths[2]));
        // Outer roads keep their far edge where it was: not narrowed.
        assert_eq!(mid(&paths[0]), 1.0);
        assert_eq!(mid(&paths[3]), 1.0);
        // Never below the floor.
        let mut tight = vec![line(0.0), line(0.12), line(0.24)];
        raise(&mut tight, &s);
        assert!(tight[1].width_factors.iter().all(|&f| f >= 0.6 - 1e-12));
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
        raise(&mut paths, &SETTINGS);
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
        // apart (w = 0.4) has a neighbour on one side only: it keeps its nominal width.
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
        let mut paths = vec![ring(1.2), ring(1.5)];
        raise(&mut paths, &SETTINGS);
        assert!(
            paths[0].width_factors.iter().all(|&f| f == 1.0),
            "{:?}",
            paths[0].width_factors
        );
    }
}
