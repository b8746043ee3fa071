//! Where segments touch or cross: the exact segment intersection test, the point where
//! two segments' lines meet, and the sweep over x that finds the crossing pairs of
//! non-adjacent edges among a set of loops ([`first_crossing`], [`crossings`]), with the
//! order it meets them in ([`sweep_rank`]). Not the repair of crossings (the offset
//! engine cuts swallowtails; region validation refuses them).

use super::{edge_ends, prev_in_loop};
use glam::DVec2;

fn orient(a: DVec2, b: DVec2, c: DVec2) -> f64 {
    (b - a).perp_dot(c - a)
}

/// Do closed segments `p1p2` and `q1q2` share a point?
pub fn segments_intersect(p1: DVec2, p2: DVec2, q1: DVec2, q2: DVec2) -> bool {
    let d1 = orient(q1, q2, p1);
    let d2 = orient(q1, q2, p2);
    let d3 = orient(p1, p2, q1);
    let d4 = orient(p1, p2, q2);
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0))
        && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0))
    {
        return true;
    }
    let on = |a: DVec2, b: DVec2, p: DVec2, d: f64| {
        d == 0.0
            && p.x >= a.x.min(b.x)
            && p.x <= a.x.max(b.x)
            && p.y >= a.y.min(b.y)
            && p.y <= a.y.max(b.y)
    };
    on(q1, q2, p1, d1) || on(q1, q2, p2, d2) || on(p1, p2, q1, d3) || on(p1, p2, q2, d4)
}

/// Two edges that touch or cross: `(loop index, edge index)` of each, and where.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crossing {
    pub first: (usize, usize),
    pub second: (usize, usize),
    pub at: DVec2,
}

/// A segment of a set of loops, tagged with where it came from.
#[derive(Clone, Copy, Debug)]
struct TaggedSegment {
    a: DVec2,
    b: DVec2,
    /// The box of `a`–`b`.
    lo: DVec2,
    hi: DVec2,
    loop_index: usize,
    edge_index: usize,
    /// The numbers (in the order of all loops' edges) of the edges before and after it
    /// round its loop: the only ones it may touch.
    prev: u32,
    next: u32,
}

/// First pair of non-adjacent edges that touch or cross, over all `loops` together,
/// found with a sweep over x (near-linear for ordinary outlines).
pub fn first_crossing(loops: &[&[DVec2]]) -> Option<Crossing> {
    let mut first = None;
    sweep_crossings(loops, |c| {
        first = Some(c);
        false
    });
    first
}

/// Every pair of non-adjacent edges that touch or cross, over all `loops` together, in
/// the order [`first_crossing`]'s sweep meets them (so the first is its answer); None
/// where there are more than `limit`.
pub fn crossings(loops: &[&[DVec2]], limit: usize) -> Option<Vec<Crossing>> {
    let mut all = Vec::new();
    sweep_crossings(loops, |c| {
        all.push(c);
        all.len() <= limit
    });
    (all.len() <= limit).then_some(all)
}

/// The sweep of [`first_crossing`]: every crossing pair goes to `found` (the edge the
/// sweep reached first as `first`) until it returns false. The sweep meets the pairs in
/// the order of their later edge, then of their earlier one, each edge ranked by its
/// least x (`f64::total_cmp`) and then by its number in the order of all loops' edges.
fn sweep_crossings(loops: &[&[DVec2]], mut found: impl FnMut(Crossing) -> bool) {
    let mut segs: Vec<TaggedSegment> = Vec::with_capacity(loops.iter().map(|l| l.len()).sum());
    for (li, l) in loops.iter().enumerate() {
        let (n, first) = (l.len(), segs.len());
        for (i, j) in edge_ends(n, true) {
            let (a, b) = (l[i], l[j]);
            segs.push(TaggedSegment {
                a,
                b,
                lo: a.min(b),
                hi: a.max(b),
                loop_index: li,
                edge_index: i,
                prev: (first + prev_in_loop(i, n)) as u32,
                next: (first + j) as u32,
            });
        }
    }
    // Sweep order: by least x (a stable sort of the keys alone, not of the segments),
    // each key as the integer `f64::total_cmp` compares, converted once.
    let mut order: Vec<(i64, u32)> = segs
        .iter()
        .enumerate()
        .map(|(k, s)| (total_order_key(s.lo.x), k as u32))
        .collect();
    order.sort_by_key(|p| p.0);
    let max_x: Vec<f64> = segs.iter().map(|s| s.hi.x).collect();
    let mut active: Vec<u32> = Vec::new();
    for &(_, k) in &order {
        let s = &segs[k as usize];
        let min_x = s.lo.x;
        // One pass over the active edges, in order: those the sweep has passed are
        // dropped (kept ones move up), the others checked against `s`.
        let mut kept = 0;
        for q in 0..active.len() {
            let j = active[q];
            if max_x[j as usize] < min_x {
                continue;
            }
            active[kept] = j;
            kept += 1;
            let t = &segs[j as usize];
            // Apart in y, or neighbours round a loop: these cannot count.
            if s.hi.y < t.lo.y || t.hi.y < s.lo.y || j == s.next || j == s.prev {
                continue;
            }
            if segments_intersect(s.a, s.b, t.a, t.b) {
                let c = Crossing {
                    first: (t.loop_index, t.edge_index),
                    second: (s.loop_index, s.edge_index),
                    at: crossing_point(s.a, s.b, t.a, t.b),
                };
                if !found(c) {
                    return;
                }
            }
        }
        active.truncate(kept);
        active.push(k);
    }
}

/// Where segment `s1`–`s2` meets `t1`–`t2` (which touch or cross), as the sweep of
/// [`first_crossing`] places it, `s` being the edge it reached second.
pub fn crossing_point(s1: DVec2, s2: DVec2, t1: DVec2, t2: DVec2) -> DVec2 {
    segment_intersection_point(s1, s2, t1, t2).unwrap_or(s1)
}

/// The key [`first_crossing`]'s sweep ranks an edge `a`–`b` by, given the edge's number
/// in the order of all loops' edges: pairs are met in the order of the larger key of
/// their two edges, then of the smaller.
pub fn sweep_rank(a: DVec2, b: DVec2, number: usize) -> (i64, usize) {
    (total_order_key(a.x.min(b.x)), number)
}

/// The integer whose order is `f64::total_cmp`'s order of `x` (the transformation
/// `total_cmp` applies to both sides of each comparison).
#[inline]
fn total_order_key(x: f64) -> i64 {
    let bits = x.to_bits() as i64;
    bits ^ ((((bits >> 63) as u64) >> 1) as i64)
}

/// Intersection point of two segments' supporting lines, if they are not parallel.
pub fn segment_intersection_point(p1: DVec2, p2: DVec2, q1: DVec2, q2: DVec2) -> Option<DVec2> {
    let r = p2 - p1;
    let s = q2 - q1;
    let den = r.perp_dot(s);
    if den.abs() < 1e-300 {
        return None;
    }
    let t = (q1 - p1).perp_dot(s) / den;
    Some(p1 + r * t)
}
