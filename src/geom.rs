//! Planar geometry shared by every planning stage: closed loops, layer regions
//! (an outer loop plus holes, the paper's Ce and Ci), and the checks that a region
//! supplied by a user or a slicer is sound before the EDO method touches it.
//!
//! Conventions: millimetres, `f64`; a loop is closed implicitly (last vertex joins the
//! first, never repeated); a [`Region`]'s outer loop is counter-clockwise and its holes
//! clockwise once normalised with [`Region::normalised`].

use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Geometric tolerances, in one place (ARCHITECTURE.md "Units and numbers").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tolerances {
    /// Two points closer than this are the same point, mm.
    pub point_eq_mm: f64,
    /// Loops with less area than this are degenerate, mm².
    pub min_loop_area_mm2: f64,
    /// Chord tolerance when sampling curves (splines, arcs) to polylines, mm.
    pub chord_mm: f64,
    /// Compositions must sum to 1 within this.
    pub composition_sum: f64,
    /// Roads lying on the boundary of the area they are clipped to are kept whole by
    /// clipping against that area grown by this much, mm. A loop farther than this from
    /// every boundary of the area it is clipped to is inside or outside it whole, and is
    /// taken or dropped without running the clipper.
    pub clip_margin_mm: f64,
}

impl Default for Tolerances {
    fn default() -> Self {
        Tolerances {
            point_eq_mm: 1e-9,
            min_loop_area_mm2: 1e-9,
            chord_mm: 0.01,
            composition_sum: 1e-9,
            clip_margin_mm: 1e-3,
        }
    }
}

/// The vertex after `k` round a loop of `n` vertices (without an integer division).
#[inline]
pub fn next_in_loop(k: usize, n: usize) -> usize {
    if k + 1 == n {
        0
    } else {
        k + 1
    }
}

/// The vertex before `k` round a loop of `n` vertices.
#[inline]
pub fn prev_in_loop(k: usize, n: usize) -> usize {
    if k == 0 {
        n - 1
    } else {
        k - 1
    }
}

/// Edge `e` of a closed loop: from vertex `e` to the next.
#[inline]
pub fn loop_edge(pts: &[DVec2], e: usize) -> (DVec2, DVec2) {
    (pts[e], pts[next_in_loop(e, pts.len())])
}

/// Axis-aligned bounding box (min, max) of points (infinite and inverted when empty).
pub fn loop_bounds(pts: &[DVec2]) -> (DVec2, DVec2) {
    pts.iter().fold(
        (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}

/// The edges of a closed loop in order, from vertex 0: `(pts[i], pts[i + 1])`, the last
/// back to the first (without a division per edge).
pub fn loop_edges(pts: &[DVec2]) -> impl Iterator<Item = (DVec2, DVec2)> + '_ {
    let last = pts.last().copied();
    pts.windows(2)
        .map(|w| (w[0], w[1]))
        .chain(last.zip(pts.first().copied()).filter(|_| pts.len() > 1))
}

/// Twice the signed area of a closed loop (positive when counter-clockwise).
pub fn signed_area2(pts: &[DVec2]) -> f64 {
    let n = pts.len();
    if n < 3 {
        return 0.0;
    }
    let mut s = 0.0;
    for (a, b) in loop_edges(pts) {
        s += a.x * b.y - b.x * a.y;
    }
    s
}

/// Signed area of a closed loop, mm² (positive when counter-clockwise).
pub fn signed_area(pts: &[DVec2]) -> f64 {
    0.5 * signed_area2(pts)
}

/// Perimeter of a closed loop, mm.
pub fn loop_length(pts: &[DVec2]) -> f64 {
    let n = pts.len();
    if n < 2 {
        return 0.0;
    }
    loop_edges(pts).map(|(a, b)| a.distance(b)).sum()
}

/// Length of an open polyline, mm.
pub fn polyline_length(pts: &[DVec2]) -> f64 {
    pts.windows(2).map(|w| w[0].distance(w[1])).sum()
}

/// Area centroid of a closed loop (falls back to the vertex mean for zero area).
pub fn centroid(pts: &[DVec2]) -> DVec2 {
    let n = pts.len();
    if n == 0 {
        return DVec2::ZERO;
    }
    let a2 = signed_area2(pts);
    if a2.abs() < 1e-300 {
        return pts.iter().copied().sum::<DVec2>() / n as f64;
    }
    let mut c = DVec2::ZERO;
    for (p, q) in loop_edges(pts) {
        let cross = p.x * q.y - q.x * p.y;
        c += (p + q) * cross;
    }
    c / (3.0 * a2)
}

/// Even-odd point-in-loop test (points on the boundary may go either way).
pub fn point_in_loop(p: DVec2, pts: &[DVec2]) -> bool {
    let n = pts.len();
    let mut inside = false;
    let mut j = n.wrapping_sub(1);
    for i in 0..n {
        let a = pts[i];
        let b = pts[j];
        if (a.y > p.y) != (b.y > p.y) {
            let x = a.x + (p.y - a.y) / (b.y - a.y) * (b.x - a.x);
            if p.x < x {
                inside = !inside;
            }
        }
        j = i;
    }
    inside
}

/// Distance from `p` to the segment `a`–`b`.
pub fn point_segment_distance(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 <= 0.0 {
        return p.distance(a);
    }
    let t = ((p - a).dot(ab) / len2).clamp(0.0, 1.0);
    p.distance(a + ab * t)
}

/// Squared distance from `p` to the segment `a`–`b`: the square of
/// [`point_segment_distance`] before its square root (same projection, same rounding).
pub fn point_segment_distance2(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 <= 0.0 {
        return p.distance_squared(a);
    }
    let t = ((p - a).dot(ab) / len2).clamp(0.0, 1.0);
    p.distance_squared(a + ab * t)
}

/// `d2.sqrt() <= r`, deciding without the square root unless `d2` is within rounding
/// of `r²` (so it answers exactly as the square root would).
#[inline]
pub fn sqrt_within(d2: f64, r: f64) -> bool {
    let r2 = r * r;
    if r >= 0.0 && d2 < r2 * (1.0 - 4.0 * f64::EPSILON) {
        true
    } else if d2 > r2 * (1.0 + 4.0 * f64::EPSILON) {
        false
    } else {
        d2.sqrt() <= r
    }
}

/// `segment_segment_distance(a, b, c, d) <= r`, without square roots where they
/// cannot change the answer.
fn segments_within(a: DVec2, b: DVec2, c: DVec2, d: DVec2, r: f64) -> bool {
    sqrt_within(point_segment_distance2(a, c, d), r)
        || sqrt_within(point_segment_distance2(b, c, d), r)
        || sqrt_within(point_segment_distance2(c, a, b), r)
        || sqrt_within(point_segment_distance2(d, a, b), r)
        || (r >= 0.0 && segments_intersect(a, b, c, d))
}

/// One segment's part of [`SegmentIndex::within`]: is `c`–`d` within `r_mm` of `p`?
/// (`reach` is `r_mm` plus [`reject_slack`]: boxes farther apart are not looked at.)
#[inline]
fn point_hit(p: DVec2, c: DVec2, d: DVec2, r_mm: f64, reach: f64) -> bool {
    let gap = (c.min(d) - p).max(p - c.max(d));
    gap.x <= reach && gap.y <= reach && sqrt_within(point_segment_distance2(p, c, d), r_mm)
}

/// One segment's part of [`SegmentIndex::any_within`]: is `c`–`d` within `r_mm` of the
/// segment `a`–`b`? (`reach` as in [`point_hit`].)
/// `lo`–`hi` is the box of `a`–`b`.
#[inline]
fn segment_hit(
    a: DVec2,
    b: DVec2,
    lo: DVec2,
    hi: DVec2,
    seg: (DVec2, DVec2),
    r_mm: f64,
    reach: f64,
) -> bool {
    let (c, d) = seg;
    // Boxes farther apart than the reach along an axis cannot be within it.
    let gap = (c.min(d) - hi).max(lo - c.max(d));
    gap.x <= reach && gap.y <= reach && segment_near(a, b, c, d, r_mm, reach)
}

/// The exact part of [`segment_hit`], for segments whose boxes come within the reach:
/// out of line (only these few get here, the box test stays in the caller's loop).
#[inline(never)]
fn segment_near(a: DVec2, b: DVec2, c: DVec2, d: DVec2, r_mm: f64, reach: f64) -> bool {
    !beside_line(a, b, c, d, reach) && segments_within(a, b, c, d, r_mm)
}

/// Do `c` and `d` both lie on one side of the line through `a` and `b`, farther from it
/// than `reach` (allowing for the rounding of this test)? Then every point of `c`–`d` is
/// farther than `reach` from `a`–`b`: the four point-segment distances of
/// [`segments_within`] exceed any radius `reach` is [`reject_slack`] beyond, and its
/// crossing test sees both orientations (`orient(a, b, c)`, `orient(a, b, d)`, the same
/// products as here) nonzero of one sign. A cheap rejection before that exact test.
#[inline]
fn beside_line(a: DVec2, b: DVec2, c: DVec2, d: DVec2, reach: f64) -> bool {
    let ab = b - a;
    let (ca, da) = (c - a, d - a);
    let (sc, sd) = (ab.perp_dot(ca), ab.perp_dot(da));
    let s = if sc > 0.0 && sd > 0.0 {
        sc.min(sd)
    } else if sc < 0.0 && sd < 0.0 {
        (-sc).min(-sd)
    } else {
        return false;
    };
    // Each product is within 4 ulps of the 1-norms' product of the exact one.
    let l1 = |v: DVec2| v.x.abs() + v.y.abs();
    let s = s - 4.0 * f64::EPSILON * l1(ab) * l1(ca).max(l1(da));
    s > 0.0 && s * s > reach * reach * ab.length_squared() * (1.0 + 1e-12)
}

/// Some segments of a [`SegmentIndex`] gathered by [`SegmentIndex::near_box`], for
/// many questions about one small area: each answers as the index would, for points
/// and segments inside the box they were gathered for and radii up to its reach.
#[derive(Debug, Clone, Default)]
pub struct NearSegments {
    segments: Vec<(DVec2, DVec2)>,
    /// Per indexed segment, the gathering that last took it (`stamp`): each gathering
    /// takes a segment once, however many of its cells it spans.
    seen: Vec<u32>,
    stamp: u32,
}

impl NearSegments {
    /// How many are gathered (a mark for [`Self::truncate`] and for the ranges the
    /// questions take).
    pub fn len(&self) -> usize {
        self.segments.len()
    }

    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// Room for `additional` more without growing.
    pub fn reserve(&mut self, additional: usize) {
        self.segments.reserve(additional);
    }

    /// Forget those gathered after the first `len`.
    pub fn truncate(&mut self, len: usize) {
        self.segments.truncate(len);
    }

    /// [`SegmentIndex::within`] over the segments `range` of those gathered (none
    /// where the range is not theirs).
    pub fn within(&self, range: std::ops::Range<usize>, p: DVec2, r_mm: f64) -> bool {
        let reach = r_mm + reject_slack(r_mm);
        self.segments
            .get(range)
            .unwrap_or_default()
            .iter()
            .any(|&(c, d)| point_hit(p, c, d, r_mm, reach))
    }

    /// [`SegmentIndex::any_within`] over the segments `range` of those gathered (none
    /// where the range is not theirs).
    pub fn any_within(&self, range: std::ops::Range<usize>, a: DVec2, b: DVec2, r_mm: f64) -> bool {
        let (lo, hi) = (a.min(b), a.max(b));
        let reach = r_mm + reject_slack(r_mm);
        self.segments
            .get(range)
            .unwrap_or_default()
            .iter()
            .any(|&seg| segment_hit(a, b, lo, hi, seg, r_mm, reach))
    }
}

/// How far beyond a query radius a bounding-box gap must be before the box test rejects
/// a segment: far more than the rounding of the exact distance test it saves.
#[inline]
fn reject_slack(r_mm: f64) -> f64 {
    1e-9 * (1.0 + r_mm.abs())
}

/// `x.floor()` for the grid lookups: the same value wherever the result is clamped to
/// a grid (it differs only for NaN, infinities and |x| ≥ 2⁶³, which give 0 or the
/// clamped extreme either way), without the libm call the baseline x86-64 target makes
/// for `floor`.
#[inline]
pub(crate) fn floor_clamped(x: f64) -> f64 {
    let i = x as i64 as f64;
    if i > x {
        i - 1.0
    } else {
        i
    }
}

/// Distance between the segments `a`–`b` and `c`–`d` (zero where they touch or cross).
pub fn segment_segment_distance(a: DVec2, b: DVec2, c: DVec2, d: DVec2) -> f64 {
    if segments_intersect(a, b, c, d) {
        return 0.0;
    }
    point_segment_distance(a, c, d)
        .min(point_segment_distance(b, c, d))
        .min(point_segment_distance(c, a, b))
        .min(point_segment_distance(d, a, b))
}

/// Distance from `p` to the closest point of a closed loop's boundary.
pub fn point_loop_distance(p: DVec2, pts: &[DVec2]) -> f64 {
    loop_edges(pts)
        .map(|(a, b)| point_segment_distance(p, a, b))
        .fold(f64::INFINITY, f64::min)
}

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
        for i in 0..n {
            let (a, b) = (l[i], l[if i + 1 == n { 0 } else { i + 1 }]);
            segs.push(TaggedSegment {
                a,
                b,
                lo: a.min(b),
                hi: a.max(b),
                loop_index: li,
                edge_index: i,
                prev: (first + if i == 0 { n - 1 } else { i - 1 }) as u32,
                next: (first + if i + 1 == n { 0 } else { i + 1 }) as u32,
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

/// Remove consecutive duplicate points (and a closing duplicate) closer than `eps`.
pub fn dedup_loop(pts: &[DVec2], eps: f64) -> Vec<DVec2> {
    let mut out: Vec<DVec2> = Vec::with_capacity(pts.len());
    // Points clearly farther apart than `eps` (the square of the distance over that of
    // 2 eps) are told apart without the square root.
    let clear2 = 4.0 * eps * eps;
    for &p in pts {
        if out
            .last()
            .is_none_or(|q: &DVec2| q.distance_squared(p) > clear2 || q.distance(p) > eps)
        {
            out.push(p);
        }
    }
    while out.len() > 1 && out[0].distance(out[out.len() - 1]) <= eps {
        out.pop();
    }
    out
}

/// Douglas–Peucker simplification of a closed loop: drop vertices whose removal moves
/// the loop by at most `tolerance_mm`.
pub fn simplify_loop(pts: &[DVec2], tolerance_mm: f64) -> Vec<DVec2> {
    let n = pts.len();
    if n <= 4 || tolerance_mm <= 0.0 {
        return pts.to_vec();
    }
    // Split the loop at vertex 0 and the vertex farthest from it.
    let far = (1..n)
        .max_by(|&a, &b| {
            pts[a]
                .distance_squared(pts[0])
                .total_cmp(&pts[b].distance_squared(pts[0]))
        })
        .unwrap_or(n / 2);
    let mut keep = vec![false; n];
    keep[0] = true;
    keep[far] = true;
    let mut stack = vec![(0usize, far), (far, n)];
    let tolerance2 = tolerance_mm * tolerance_mm;
    while let Some((a, b)) = stack.pop() {
        if b <= a + 1 {
            continue;
        }
        let (pa, pb) = (pts[a], pts[b % n]);
        let mut worst = (0.0, a);
        // The squared `point_segment_distance(p, pa, pb)`, with the chord's terms
        // computed once (and no division or square root per point).
        let ab = pb - pa;
        let len2 = ab.length_squared();
        let inv_len2 = if len2 > 0.0 { 1.0 / len2 } else { 0.0 };
        for (k, p) in pts[a + 1..b].iter().enumerate() {
            let t = ((*p - pa).dot(ab) * inv_len2).clamp(0.0, 1.0);
            let d2 = p.distance_squared(pa + ab * t);
            if d2 > worst.0 {
                worst = (d2, a + 1 + k);
            }
        }
        if worst.0 > tolerance2 {
            keep[worst.1] = true;
            stack.push((a, worst.1));
            stack.push((worst.1, b));
        }
    }
    pts.iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(p, _)| *p)
        .collect()
}

/// Simplification of a closed loop in one pass, with the guarantee of [`simplify_loop`]:
/// every dropped vertex lies within `tolerance_mm` of the chord that replaces it. From
/// each kept vertex the next kept one is the farthest (at most [`GREEDY_RUN`] on) whose
/// chord passes within the tolerance of every vertex between. Where nearly every vertex
/// stays (an offset's moved edges and round joins), that is one chord test per vertex,
/// against Douglas–Peucker's scan of the whole remaining run at every split.
pub fn simplify_loop_greedy(pts: &[DVec2], tolerance_mm: f64) -> Vec<DVec2> {
    let n = pts.len();
    if n <= 4 || tolerance_mm <= 0.0 {
        return pts.to_vec();
    }
    let tol2 = tolerance_mm * tolerance_mm;
    let mut out = Vec::with_capacity(n);
    out.push(pts[0]);
    let mut a = 0;
    while a < n {
        let pa = pts[a];
        // `b`: the farthest end found so far whose chord from `a` holds every vertex
        // between (the next vertex trivially); index `n` is vertex 0 closing the loop.
        let mut b = a + 1;
        while b < n && b - a < GREEDY_RUN {
            let pc = pts[next_in_loop(b, n)];
            if pts[a + 1..=b]
                .iter()
                .all(|&p| chord_within(p, pa, pc, tol2))
            {
                b += 1;
            } else {
                break;
            }
        }
        if b < n {
            out.push(pts[b]);
        }
        a = b;
    }
    out
}

/// How many edges one chord of [`simplify_loop_greedy`] may replace (bounding its cost
/// on long straight runs at n times this).
const GREEDY_RUN: usize = 32;

/// Whether `p` lies within `sqrt(tol2)` of segment `ab`, without a division or square
/// root: the distance to the line first (never more than that to the segment), then to
/// the nearer end where `p` projects beyond one.
fn chord_within(p: DVec2, a: DVec2, b: DVec2, tol2: f64) -> bool {
    let (ab, ap) = (b - a, p - a);
    let len2 = ab.length_squared();
    let cross = ap.perp_dot(ab);
    if cross * cross > tol2 * len2 {
        return false;
    }
    let dot = ap.dot(ab);
    if dot <= 0.0 {
        ap.length_squared() <= tol2
    } else if dot >= len2 {
        p.distance_squared(b) <= tol2
    } else {
        true
    }
}

/// Bounding box (min, max) of several regions (infinite and inverted when empty).
pub fn bounds_of(regions: &[Region]) -> (DVec2, DVec2) {
    let mut lo = DVec2::splat(f64::INFINITY);
    let mut hi = DVec2::splat(f64::NEG_INFINITY);
    for r in regions {
        let (a, b) = r.bounds();
        lo = lo.min(a);
        hi = hi.max(b);
    }
    (lo, hi)
}

/// One connected area of a layer: an outer loop (the paper's external boundary Ce)
/// and zero or more holes (internal boundaries Ci).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Region {
    pub outer: Vec<DVec2>,
    #[serde(default)]
    pub holes: Vec<Vec<DVec2>>,
}

/// What is wrong with a region, naming the loop and where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegionError {
    #[error("{loop_name} has {count} distinct vertices; a loop needs at least 3")]
    TooFewVertices { loop_name: String, count: usize },
    #[error("{loop_name} vertex {index} is not a finite number")]
    NotFinite { loop_name: String, index: usize },
    #[error("{loop_name} encloses no area (|area| = {area_mm2:.3e} mm²)")]
    Degenerate { loop_name: String, area_mm2: f64 },
    #[error("{first} edge {first_edge} crosses {second} edge {second_edge} near ({x:.4}, {y:.4})")]
    SelfIntersecting {
        first: String,
        first_edge: usize,
        second: String,
        second_edge: usize,
        x: f64,
        y: f64,
    },
    #[error("{loop_name} is not inside the outer loop (vertex {index} at ({x:.4}, {y:.4}) lies outside)")]
    HoleOutside {
        loop_name: String,
        index: usize,
        x: f64,
        y: f64,
    },
    #[error("{inner} lies inside {outer}; nested holes are separate islands, give them as their own region")]
    NestedHoles { inner: String, outer: String },
}

impl Region {
    pub fn new(outer: Vec<DVec2>, holes: Vec<Vec<DVec2>>) -> Self {
        Region { outer, holes }
    }

    fn loop_name(i: usize) -> String {
        if i == 0 {
            "outer loop".to_string()
        } else {
            format!("hole {}", i - 1)
        }
    }

    /// All loops, outer first.
    pub fn loops(&self) -> impl Iterator<Item = &Vec<DVec2>> {
        std::iter::once(&self.outer).chain(self.holes.iter())
    }

    /// Net area, mm² (outer minus holes).
    pub fn area(&self) -> f64 {
        signed_area(&self.outer).abs()
            - self.holes.iter().map(|h| signed_area(h).abs()).sum::<f64>()
    }

    /// Axis-aligned bounding box (min, max).
    pub fn bounds(&self) -> (DVec2, DVec2) {
        loop_bounds(&self.outer)
    }

    /// Is `p` inside the material (inside outer, outside every hole)?
    pub fn contains(&self, p: DVec2) -> bool {
        point_in_loop(p, &self.outer) && !self.holes.iter().any(|h| point_in_loop(p, h))
    }

    /// A copy with duplicate points removed, the outer loop counter-clockwise and holes clockwise.
    pub fn normalised(&self, tol: &Tolerances) -> Region {
        let fix = |l: &[DVec2], ccw: bool| {
            let mut l = dedup_loop(l, tol.point_eq_mm);
            if (signed_area2(&l) > 0.0) != ccw {
                l.reverse();
            }
            l
        };
        Region {
            outer: fix(&self.outer, true),
            holes: self.holes.iter().map(|h| fix(h, false)).collect(),
        }
    }

    /// Check the region is a sound polygon with holes: enough vertices, finite,
    /// non-degenerate, no edge crossing any other, holes inside the outer loop and
    /// not inside each other. Call on a normalised region.
    pub fn validate(&self, tol: &Tolerances) -> Result<(), RegionError> {
        for (li, l) in self.loops().enumerate() {
            if let Some(index) = l.iter().position(|p| !p.is_finite()) {
                return Err(RegionError::NotFinite {
                    loop_name: Self::loop_name(li),
                    index,
                });
            }
            let distinct = dedup_loop(l, tol.point_eq_mm).len();
            if distinct < 3 {
                return Err(RegionError::TooFewVertices {
                    loop_name: Self::loop_name(li),
                    count: distinct,
                });
            }
        }
        let loops: Vec<&[DVec2]> = self.loops().map(|l| l.as_slice()).collect();
        if let Some(c) = first_crossing(&loops) {
            return Err(RegionError::SelfIntersecting {
                first: Self::loop_name(c.first.0),
                first_edge: c.first.1,
                second: Self::loop_name(c.second.0),
                second_edge: c.second.1,
                x: c.at.x,
                y: c.at.y,
            });
        }
        for (li, l) in self.loops().enumerate() {
            let a = signed_area(l).abs();
            if a < tol.min_loop_area_mm2 {
                return Err(RegionError::Degenerate {
                    loop_name: Self::loop_name(li),
                    area_mm2: a,
                });
            }
        }
        // No crossings: each hole is entirely inside or entirely outside the outer loop
        // (and each other), so one vertex decides.
        for (hi, h) in self.holes.iter().enumerate() {
            if !point_in_loop(h[0], &self.outer) {
                return Err(RegionError::HoleOutside {
                    loop_name: Self::loop_name(hi + 1),
                    index: 0,
                    x: h[0].x,
                    y: h[0].y,
                });
            }
            for (hj, g) in self.holes.iter().enumerate() {
                if hi != hj && point_in_loop(h[0], g) {
                    return Err(RegionError::NestedHoles {
                        inner: Self::loop_name(hi + 1),
                        outer: Self::loop_name(hj + 1),
                    });
                }
            }
        }
        Ok(())
    }
}

/// A uniform grid over the segments of a set of polylines, for nearest-distance queries
/// (the gap between adjacent contours, D_max of eq (5), and inside-ness checks).
#[derive(Debug, Clone)]
pub struct SegmentIndex {
    segments: Vec<(DVec2, DVec2)>,
    origin: DVec2,
    cell_mm: f64,
    nx: usize,
    ny: usize,
    /// Segments of cell `k` are `items[starts[k]..starts[k + 1]]`, in increasing order.
    starts: Vec<usize>,
    items: Vec<u32>,
}

/// Sphere-tracing steps of [`SegmentIndex::ray_hit`] and the distance that counts as a hit.
const RAY_STEPS: usize = 32;
const RAY_HIT_MM: f64 = 1e-4;

impl SegmentIndex {
    /// Index the edges of closed `loops` and open `polylines`.
    pub fn new(loops: &[&[DVec2]], polylines: &[&[DVec2]]) -> Self {
        let count = loops.iter().map(|l| l.len()).sum::<usize>()
            + polylines
                .iter()
                .map(|l| l.len().saturating_sub(1))
                .sum::<usize>();
        let mut segments = Vec::with_capacity(count);
        for l in loops {
            let n = l.len();
            for i in 0..n {
                segments.push((l[i], l[if i + 1 == n { 0 } else { i + 1 }]));
            }
        }
        for l in polylines {
            for w in l.windows(2) {
                segments.push((w[0], w[1]));
            }
        }
        let mut lo = DVec2::splat(f64::INFINITY);
        let mut hi = DVec2::splat(f64::NEG_INFINITY);
        let mut total = 0.0;
        for (a, b) in &segments {
            lo = lo.min(a.min(*b));
            hi = hi.max(a.max(*b));
            total += a.distance(*b);
        }
        if segments.is_empty() {
            return SegmentIndex {
                segments,
                origin: DVec2::ZERO,
                cell_mm: 1.0,
                nx: 0,
                ny: 0,
                starts: vec![0],
                items: Vec::new(),
            };
        }
        let extent = (hi - lo).max(DVec2::splat(1e-9));
        // About two segments per cell on average, at most ~1M cells.
        let mean = (total / segments.len() as f64).max(1e-9);
        let mut cell_mm = (mean * 2.0).max((extent.x * extent.y / 1.0e6).sqrt());
        if !cell_mm.is_finite() || cell_mm <= 0.0 {
            cell_mm = 1.0;
        }
        let nx = ((extent.x / cell_mm).ceil() as usize).clamp(1, 4096);
        let ny = ((extent.y / cell_mm).ceil() as usize).clamp(1, 4096);
        let cell_mm = (extent.x / nx as f64).max(extent.y / ny as f64);
        // Counting sort into cells: count, prefix sums, fill (in segment order). Cell
        // ranges here and in the queries are half-open (`r0..r1 + 1`): they step with
        // fewer instructions than inclusive ones.
        let spans: Vec<[usize; 4]> = segments
            .iter()
            .map(|(a, b)| {
                let (c0, r0) = Self::cell_of(lo, cell_mm, nx, ny, a.min(*b));
                let (c1, r1) = Self::cell_of(lo, cell_mm, nx, ny, a.max(*b));
                [c0, r0, c1, r1]
            })
            .collect();
        let mut starts = vec![0usize; nx * ny + 1];
        for &[c0, r0, c1, r1] in &spans {
            for r in r0..r1 + 1 {
                for c in c0..c1 + 1 {
                    starts[r * nx + c + 1] += 1;
                }
            }
        }
        for k in 1..starts.len() {
            starts[k] += starts[k - 1];
        }
        let mut fill: Vec<usize> = starts[..nx * ny].to_vec();
        let mut items = vec![0u32; starts[nx * ny]];
        for (k, &[c0, r0, c1, r1]) in spans.iter().enumerate() {
            for r in r0..r1 + 1 {
                for c in c0..c1 + 1 {
                    let slot = &mut fill[r * nx + c];
                    items[*slot] = k as u32;
                    *slot += 1;
                }
            }
        }
        SegmentIndex {
            segments,
            origin: lo,
            cell_mm,
            nx,
            ny,
            starts,
            items,
        }
    }

    fn cell_of(origin: DVec2, cell: f64, nx: usize, ny: usize, p: DVec2) -> (usize, usize) {
        let q = (p - origin) / cell;
        // `floor(x)` clamped to 0..n: truncation floors a positive x, saturates beyond
        // the grid (infinities too), and a negative x or NaN is cell 0.
        // (Below n - 1, at most 4095, truncation through i64 is the same and converts
        // in fewer instructions than to usize.)
        let clamp = |x: f64, n: usize| {
            if x > 0.0 {
                if x < (n - 1) as f64 {
                    x as i64 as usize
                } else {
                    n - 1
                }
            } else {
                0
            }
        };
        (clamp(q.x, nx), clamp(q.y, ny))
    }

    /// The segments of the cells `c0..=c1` of row `row`.
    fn row_items(&self, row: usize, c0: usize, c1: usize) -> &[u32] {
        // Cells of a row are consecutive, so their segments are one run of `items`
        // (a segment spanning several of them appears once per cell).
        let (k0, k1) = (row * self.nx + c0, row * self.nx + c1);
        &self.items[self.starts[k0]..self.starts[k1 + 1]]
    }

    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// Is `p` inside an odd number of the indexed loops? The answer of
    /// [`point_in_loop`] over each loop (crossings of the ray from `p` towards +x, each
    /// edge taken as it does), from the segments in the cells the ray passes: each
    /// counted in the first of those cells it lies in. (A point within rounding of an
    /// edge at a cell's side can go either way, as points on a loop do for
    /// `point_in_loop`.) Only for an index of closed loops alone (no polylines).
    pub fn inside_odd(&self, p: DVec2) -> bool {
        if self.segments.is_empty() {
            return false;
        }
        let (pc, pr) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, p);
        let mut inside = false;
        for c in pc..self.nx {
            let cell = pr * self.nx + c;
            for &k in &self.items[self.starts[cell]..self.starts[cell + 1]] {
                // `point_in_loop`'s edge: from the later vertex to the earlier.
                let (b, a) = self.segments[k as usize];
                if (a.y > p.y) == (b.y > p.y) {
                    continue;
                }
                let first = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, a.min(b)).0;
                if first.max(pc) != c {
                    continue;
                }
                let x = a.x + (p.y - a.y) / (b.y - a.y) * (b.x - a.x);
                if p.x < x {
                    inside = !inside;
                }
            }
        }
        inside
    }

    /// Does every edge of the closed loop `l` stay farther than `r_mm` from every indexed
    /// segment?
    pub fn clear_of_loop(&self, l: &[DVec2], r_mm: f64) -> bool {
        loop_edges(l).all(|(a, b)| !self.any_within(a, b, r_mm))
    }

    /// Does any indexed segment come within `r_mm` of the segment `a`–`b`?
    pub fn any_within(&self, a: DVec2, b: DVec2, r_mm: f64) -> bool {
        let reach = r_mm + reject_slack(r_mm);
        self.near_candidates(a.min(b), a.max(b), r_mm, |_, c, d| {
            segment_near(a, b, c, d, r_mm, reach)
        })
    }

    /// Offer `visit` the indexed segments (number and ends) in the cells over the box
    /// `lo`–`hi` grown by `r_mm` whose own boxes come within that reach of it (a
    /// segment spanning several cells comes once per cell), until it returns true;
    /// returns whether it did.
    fn near_candidates(
        &self,
        lo: DVec2,
        hi: DVec2,
        r_mm: f64,
        mut visit: impl FnMut(u32, DVec2, DVec2) -> bool,
    ) -> bool {
        if self.segments.is_empty() {
            return false;
        }
        let reach = r_mm + reject_slack(r_mm);
        let pad = DVec2::splat(r_mm);
        let (c0, r0) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, lo - pad);
        let (c1, r1) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, hi + pad);
        for row in r0..r1 + 1 {
            for &k in self.row_items(row, c0, c1) {
                let (c, d) = self.segments[k as usize];
                let gap = (c.min(d) - hi).max(lo - c.max(d));
                if gap.x <= reach && gap.y <= reach && visit(k, c, d) {
                    return true;
                }
            }
        }
        false
    }

    /// Does any indexed segment come within `r_mm` of `p`? Looks only at the cells
    /// within that reach, so it answers a bounded question faster than [`Self::distance`].
    pub fn within(&self, p: DVec2, r_mm: f64) -> bool {
        let reach = r_mm + reject_slack(r_mm);
        self.any_in_box(p, p, r_mm, |c, d| point_hit(p, c, d, r_mm, reach))
    }

    /// [`Self::within`], trying the segment `hint` first and leaving in it the segment
    /// found: for a run of nearby points, most of which one segment answers.
    pub fn within_hinted(&self, p: DVec2, r_mm: f64, hint: &mut Option<u32>) -> bool {
        let reach = r_mm + reject_slack(r_mm);
        if let Some(&(c, d)) = hint.and_then(|k| self.segments.get(k as usize)) {
            if point_hit(p, c, d, r_mm, reach) {
                return true;
            }
        }
        // The cells and box test of `within` (a segment within the radius passes both).
        self.near_candidates(p, p, r_mm, |k, c, d| {
            let found = sqrt_within(point_segment_distance2(p, c, d), r_mm);
            if found {
                *hint = Some(k);
            }
            found
        })
    }

    /// Append to `out` (each once) the indexed segments [`Self::within`] and
    /// [`Self::any_within`] could find for any point or segment inside the box `lo`–`hi`
    /// and any radius up to `r_mm`: those in the cells over the box grown by `r_mm` whose
    /// own boxes come within that reach of it. [`NearSegments`] asks those questions of
    /// them alone, with the same answers.
    pub fn near_box(&self, lo: DVec2, hi: DVec2, r_mm: f64, out: &mut NearSegments) {
        out.stamp = out.stamp.wrapping_add(1);
        if out.stamp == 0 {
            out.seen.fill(0);
            out.stamp = 1;
        }
        if out.seen.len() < self.segments.len() {
            out.seen.resize(self.segments.len(), 0);
        }
        let stamp = out.stamp;
        self.near_candidates(lo, hi, r_mm, |k, c, d| {
            if let Some(seen) = out.seen.get_mut(k as usize) {
                if *seen != stamp {
                    *seen = stamp;
                    out.segments.push((c, d));
                }
            }
            false
        });
    }

    /// `(self.within(p, near_mm), self.within(p, far_mm))` in one look at the cells,
    /// for `near_mm <= far_mm`.
    pub fn within_both(&self, p: DVec2, near_mm: f64, far_mm: f64) -> (bool, bool) {
        if self.segments.is_empty() {
            return (false, false);
        }
        let pad = DVec2::splat(far_mm);
        let (c0, r0) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, p - pad);
        let (c1, r1) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, p + pad);
        let mut far = false;
        let reach = far_mm + reject_slack(far_mm);
        for row in r0..r1 + 1 {
            for &k in self.row_items(row, c0, c1) {
                let (c, d) = self.segments[k as usize];
                let gap = (c.min(d) - p).max(p - c.max(d));
                if gap.x > reach || gap.y > reach {
                    continue;
                }
                let d2 = point_segment_distance2(p, c, d);
                if sqrt_within(d2, near_mm) {
                    return (true, true);
                }
                far = far || sqrt_within(d2, far_mm);
            }
        }
        (false, far)
    }

    /// Does `hit` hold for any segment in the cells over the box `lo`–`hi` grown by `pad`?
    fn any_in_box(
        &self,
        lo: DVec2,
        hi: DVec2,
        pad: f64,
        hit: impl Fn(DVec2, DVec2) -> bool,
    ) -> bool {
        if self.segments.is_empty() {
            return false;
        }
        let pad = DVec2::splat(pad);
        let (c0, r0) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, lo - pad);
        let (c1, r1) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, hi + pad);
        (r0..r1 + 1).any(|row| {
            self.row_items(row, c0, c1).iter().any(|&k| {
                let (c, d) = self.segments[k as usize];
                hit(c, d)
            })
        })
    }

    /// Index the boundary of `regions`: every outer loop and hole.
    pub fn of_regions(regions: &[Region]) -> Self {
        let loops: Vec<&[DVec2]> = regions
            .iter()
            .flat_map(|r| r.loops())
            .map(|l| l.as_slice())
            .collect();
        Self::new(&loops, &[])
    }

    /// How far along the ray from `origin` in direction `dir` (unit) the nearest indexed
    /// segment is, up to `limit` (sphere tracing: step by the distance to the nearest
    /// segment until within 0.1 µm); none beyond the limit or when empty.
    pub fn ray_hit(&self, origin: DVec2, dir: DVec2, limit: f64) -> Option<f64> {
        if self.segments.is_empty() {
            return None;
        }
        let mut t = 0.0;
        for _ in 0..RAY_STEPS {
            let p = origin + dir * t;
            // Nothing within what is left of the reach: no hit (a bounded look, where
            // the nearest-segment search would widen its rings until it found one).
            if !self.within(p, limit - t) {
                return None;
            }
            let d = self.distance(p);
            if d <= RAY_HIT_MM {
                return Some(t);
            }
            t += d;
            if t > limit {
                return None;
            }
        }
        None
    }

    /// Distance from `p` to the nearest indexed segment (infinity when empty).
    pub fn distance(&self, p: DVec2) -> f64 {
        self.distance_skipping(p, |_| false)
    }

    /// [`Self::distance`] ignoring the segments `skip` says yes to (segments are numbered
    /// in the order given to [`Self::new`]: loops' edges, then polylines' edges).
    pub fn distance_skipping(&self, p: DVec2, skip: impl Fn(u32) -> bool) -> f64 {
        self.nearest_skipping(p, skip)
            .map_or(f64::INFINITY, |(d, _)| d)
    }

    /// The distance from `p` to the nearest segment `skip` does not exclude, and that
    /// segment's number (see [`Self::distance_skipping`]); none when there is none.
    pub fn nearest_skipping(&self, p: DVec2, skip: impl Fn(u32) -> bool) -> Option<(f64, u32)> {
        if self.segments.is_empty() {
            return None;
        }
        let (pc, pr) = Self::cell_of(self.origin, self.cell_mm, self.nx, self.ny, p);
        // How far p lies outside the grid box along each axis: rings are counted from
        // the cell p projects to.
        let box_hi = self.origin + DVec2::new(self.nx as f64, self.ny as f64) * self.cell_mm;
        let outside = (self.origin - p).max(p - box_hi).max(DVec2::ZERO);
        let mut best = f64::INFINITY;
        let mut best_k = None;
        let max_ring = self.nx.max(self.ny);
        for ring in 0..=max_ring {
            let r = ring as isize;
            let (pc, pr) = (pc as isize, pr as isize);
            for row in (pr - r)..=(pr + r) {
                if row < 0 || row >= self.ny as isize {
                    continue;
                }
                let edge_row = row == pr - r || row == pr + r;
                let step = if edge_row { 1 } else { (2 * r).max(1) as usize };
                let mut col = pc - r;
                while col <= pc + r {
                    if col >= 0 && col < self.nx as isize {
                        let cell = row as usize * self.nx + col as usize;
                        let items = &self.items[self.starts[cell]..self.starts[cell + 1]];
                        for &k in items {
                            if skip(k) {
                                continue;
                            }
                            let (a, b) = self.segments[k as usize];
                            let d = point_segment_distance(p, a, b);
                            if d < best {
                                best = d;
                                best_k = Some(k);
                            }
                        }
                    }
                    col += step as isize;
                }
            }
            // A cell not yet visited lies more than `ring` columns or more than `ring`
            // rows from p's cell: at least `ring` cells beyond p along that axis (on
            // top of p's distance outside the box along it), and at least p's distance
            // outside the box along the other.
            let beyond = ring as f64 * self.cell_mm;
            let unvisited = DVec2::new(outside.x + beyond, outside.y)
                .length()
                .min(DVec2::new(outside.x, outside.y + beyond).length());
            if best <= unvisited {
                break;
            }
        }
        best_k.map(|k| (best, k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_index_tells_inside_as_point_in_loop_does() {
        // A wavy ring with a hole and a small island in the hole, and points on a grid
        // through them (many on the loops' vertex heights and beyond the index's box).
        let wavy = |r: f64, n: usize, rev: bool| -> Vec<DVec2> {
            let mut l: Vec<DVec2> = (0..n)
                .map(|k| {
                    let t = std::f64::consts::TAU * k as f64 / n as f64;
                    DVec2::from_angle(t) * (r + 0.3 * (7.0 * t).sin())
                })
                .collect();
            if rev {
                l.reverse();
            }
            l
        };
        let loops = [
            wavy(10.0, 300, false),
            wavy(5.0, 120, true),
            wavy(2.0, 40, false),
        ];
        let refs: Vec<&[DVec2]> = loops.iter().map(|l| l.as_slice()).collect();
        let index = SegmentIndex::new(&refs, &[]);
        let (mut inside, mut total) = (0, 0);
        for i in -60..=60 {
            for j in -60..=60 {
                let p = DVec2::new(i as f64 * 0.2 + 0.013, j as f64 * 0.2);
                let want = loops.iter().filter(|l| point_in_loop(p, l)).count() % 2 == 1;
                assert_eq!(index.inside_odd(p), want, "at {p}");
                inside += usize::from(want);
                total += 1;
            }
        }
        // Points that are not finite answer as point_in_loop does (outside), without
        // a panic.
        for p in [
            DVec2::NAN,
            DVec2::new(f64::INFINITY, 0.0),
            DVec2::new(0.0, -f64::INFINITY),
        ] {
            let want = loops.iter().filter(|l| point_in_loop(p, l)).count() % 2 == 1;
            assert_eq!(index.inside_odd(p), want, "at {p}");
        }
        // The vertices themselves, on the loops' own heights.
        for p in loops.iter().flatten() {
            let want = loops.iter().filter(|l| point_in_loop(*p, l)).count() % 2 == 1;
            assert_eq!(index.inside_odd(*p), want, "at {p}");
        }
        assert!(
            inside > total / 5 && inside < total / 2,
            "{inside} of {total}"
        );
    }

    /// Nearest distances from points far outside the index's box, where the nearest
    /// segment lies off to the side of the cell the point projects to, match the brute
    /// force answer (the ring search once stopped early there).
    #[test]
    fn nearest_from_outside_the_box_is_exact() {
        let hole = |c: DVec2| -> Vec<DVec2> {
            (0..96)
                .map(|k| c + DVec2::from_angle(std::f64::consts::TAU * k as f64 / 96.0) * 4.0)
                .collect()
        };
        let (a, b) = (hole(DVec2::new(-11.0, 0.0)), hole(DVec2::new(11.0, 0.0)));
        let index = SegmentIndex::new(&[a.as_slice(), b.as_slice()], &[]);
        let mut worst: f64 = 0.0;
        for k in 0..720 {
            let p = DVec2::from_angle(std::f64::consts::TAU * k as f64 / 720.0) * 15.0
                + DVec2::new(0.3, -0.2);
            let brute = [&a, &b]
                .iter()
                .map(|l| point_loop_distance(p, l))
                .fold(f64::INFINITY, f64::min);
            worst = worst.max((index.distance(p) - brute).abs());
        }
        assert!(worst < 1e-12, "largest difference {worst}");
    }

    fn square(c: DVec2, h: f64) -> Vec<DVec2> {
        vec![
            c + DVec2::new(-h, -h),
            c + DVec2::new(h, -h),
            c + DVec2::new(h, h),
            c + DVec2::new(-h, h),
        ]
    }

    #[test]
    fn area_and_orientation() {
        let r = Region::new(square(DVec2::ZERO, 2.0), vec![square(DVec2::ZERO, 1.0)]);
        let n = r.normalised(&Tolerances::default());
        assert!(signed_area(&n.outer) > 0.0);
        assert!(signed_area(&n.holes[0]) < 0.0);
        assert!((n.area() - 12.0).abs() < 1e-12);
        assert!(n.validate(&Tolerances::default()).is_ok());
        assert!(n.contains(DVec2::new(1.5, 0.0)));
        assert!(!n.contains(DVec2::new(0.5, 0.0)));
    }

    #[test]
    fn bowtie_is_self_intersecting() {
        let r = Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(1.0, 1.0),
                DVec2::new(1.0, 0.0),
                DVec2::new(0.0, 1.0),
            ],
            vec![],
        );
        let e = r.validate(&Tolerances::default()).unwrap_err();
        assert!(matches!(e, RegionError::SelfIntersecting { .. }), "{e}");
    }

    #[test]
    fn hole_outside_and_crossing_are_refused() {
        let tol = Tolerances::default();
        let outside = Region::new(
            square(DVec2::ZERO, 1.0),
            vec![square(DVec2::new(5.0, 0.0), 0.5)],
        );
        assert!(matches!(
            outside.normalised(&tol).validate(&tol),
            Err(RegionError::HoleOutside { .. })
        ));
        let crossing = Region::new(
            square(DVec2::ZERO, 1.0),
            vec![square(DVec2::new(1.0, 0.0), 0.5)],
        );
        assert!(matches!(
            crossing.normalised(&tol).validate(&tol),
            Err(RegionError::SelfIntersecting { .. })
        ));
    }

    #[test]
    fn segment_index_matches_brute_force() {
        let outer = square(DVec2::ZERO, 10.0);
        let hole = square(DVec2::new(2.0, 1.0), 1.5);
        let idx = SegmentIndex::new(&[&outer, &hole], &[]);
        for k in 0..200 {
            let p = DVec2::new(
                (k as f64 * 0.37).sin() * 14.0,
                (k as f64 * 0.91).cos() * 14.0,
            );
            let brute = point_loop_distance(p, &outer).min(point_loop_distance(p, &hole));
            assert!((idx.distance(p) - brute).abs() < 1e-12, "{p}");
        }
    }

    #[test]
    fn hinted_within_answers_as_within() {
        let outer = square(DVec2::ZERO, 10.0);
        let hole = square(DVec2::new(2.0, 1.0), 1.5);
        let idx = SegmentIndex::new(&[&outer, &hole], &[]);
        // No hint, a stale one, one past the last segment, and the one left behind.
        let mut hint = None;
        let (mut hits, mut misses) = (0, 0);
        for k in 0..400 {
            let p = DVec2::new(
                (k as f64 * 0.37).sin() * 12.0,
                (k as f64 * 0.91).cos() * 12.0,
            );
            let r = 0.2 + (k % 7) as f64 * 0.4;
            if k % 50 == 0 {
                hint = Some(if k % 100 == 0 { 3 } else { 99 });
            }
            let within = idx.within(p, r);
            assert_eq!(idx.within_hinted(p, r, &mut hint), within, "{p} {r}");
            if within {
                let k = hint.expect("a hit leaves its segment");
                let (c, d) = idx.segments[k as usize];
                assert!(point_segment_distance(p, c, d) <= r);
                hits += 1;
            } else {
                misses += 1;
            }
        }
        assert!(hits > 50 && misses > 50, "{hits} hits, {misses} misses");
    }

    /// A 10 mm square with nine collinear vertices on each of two sides.
    fn square_with_collinear_points() -> Vec<DVec2> {
        let mut l: Vec<DVec2> = (0..10).map(|k| DVec2::new(k as f64, 0.0)).collect();
        l.extend((0..10).map(|k| DVec2::new(10.0, k as f64)));
        l.push(DVec2::new(10.0, 10.0));
        l.push(DVec2::new(0.0, 10.0));
        l
    }

    #[test]
    fn simplify_keeps_corners_drops_collinear() {
        let l = square_with_collinear_points();
        let s = simplify_loop(&l, 1e-6);
        assert_eq!(s.len(), 4, "{s:?}");
        assert!((signed_area(&s) - signed_area(&l)).abs() < 1e-9);
    }

    #[test]
    fn greedy_simplify_keeps_within_tolerance() {
        // The square of `simplify_keeps_corners_drops_collinear`: the corners alone stay.
        let l = square_with_collinear_points();
        let s = simplify_loop_greedy(&l, 1e-6);
        assert_eq!(s.len(), 4, "{s:?}");
        // A wobbly circle: every dropped vertex within the tolerance of the loop left,
        // the vertices kept in order, and some dropped.
        let tol = 0.002;
        let l: Vec<DVec2> = (0..400)
            .map(|k| {
                let t = k as f64 / 400.0 * std::f64::consts::TAU;
                DVec2::from_angle(t) * (5.0 + 0.003 * (7.0 * t).sin() + 0.001 * (53.0 * t).sin())
            })
            .collect();
        let s = simplify_loop_greedy(&l, tol);
        assert!(s.len() < l.len() && s.len() >= 3, "{}", s.len());
        let mut next = 0;
        for p in &s {
            next += l[next..]
                .iter()
                .position(|q| q == p)
                .expect("kept vertex in order")
                + 1;
        }
        for p in &l {
            assert!(point_loop_distance(*p, &s) <= tol * (1.0 + 1e-9), "{p}");
        }
    }

    #[test]
    fn degenerate_and_nan() {
        let tol = Tolerances::default();
        let line = Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(1.0, 0.0),
                DVec2::new(2.0, 0.0),
            ],
            vec![],
        );
        assert!(matches!(
            line.validate(&tol),
            Err(RegionError::Degenerate { .. })
        ));
        let nan = Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(f64::NAN, 0.0),
                DVec2::new(2.0, 1.0),
            ],
            vec![],
        );
        assert!(matches!(
            nan.validate(&tol),
            Err(RegionError::NotFinite { index: 1, .. })
        ));
    }
}
