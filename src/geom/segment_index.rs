//! [`SegmentIndex`]: a uniform grid over the segments of a set of loops and polylines,
//! for nearest-distance, within-a-radius, ray and inside (even-odd) queries against many
//! segments at once; [`NearSegments`], the segments near one small area gathered for many
//! questions about it. Answers are those of the brute-force tests in `distance.rs` and
//! `loops.rs`, to the bit. Not a general spatial index (segments only, built once).

use super::{
    edge_count, edges, loop_edges, point_segment_distance, point_segment_distance2,
    segments_intersect, sqrt_within, Region,
};
use glam::DVec2;

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

/// How near [`SegmentIndex::ray_hit`]'s ray must come to a segment to hit it.
const RAY_HIT_MM: f64 = 1e-4;

/// The first `t` in `0..=limit` where `origin + t·dir` (`dir` a unit vector) lies
/// within `r` of the segment `a`–`b`: where the ray enters the segment's capsule (the
/// discs round its ends, the strip along it), or none.
fn capsule_entry(origin: DVec2, dir: DVec2, a: DVec2, b: DVec2, r: f64, limit: f64) -> Option<f64> {
    let mut first = f64::INFINITY;
    // The discs: |origin + t·dir − e|² <= r², t² + 2t·k + c <= 0.
    for e in [a, b] {
        let (k, c) = (dir.dot(origin - e), origin.distance_squared(e) - r * r);
        let disc = k * k - c;
        if disc >= 0.0 {
            let root = disc.sqrt();
            let (t0, t1) = (-k - root, -k + root);
            if t1 >= 0.0 {
                first = first.min(t0.max(0.0));
            }
        }
    }
    // The strip: |s0 + t·s1| <= r where the point projects inside the segment.
    let len = a.distance(b);
    if len > 0.0 {
        let along = (b - a) / len;
        let across = along.perp();
        let (s0, s1) = (across.dot(origin - a), across.dot(dir));
        let (t0, t1) = (along.dot(origin - a), along.dot(dir));
        let (mut lo, mut hi) = (0.0f64, f64::INFINITY);
        if s1.abs() > 1e-12 {
            let (x, y) = ((-r - s0) / s1, (r - s0) / s1);
            lo = lo.max(x.min(y));
            hi = hi.min(x.max(y));
        } else if s0.abs() > r {
            hi = f64::NEG_INFINITY;
        }
        if t1.abs() > 1e-12 {
            let (x, y) = (-t0 / t1, (len - t0) / t1);
            lo = lo.max(x.min(y));
            hi = hi.min(x.max(y));
        } else if !(0.0..=len).contains(&t0) {
            hi = f64::NEG_INFINITY;
        }
        if lo <= hi {
            first = first.min(lo);
        }
    }
    (first <= limit).then_some(first)
}

impl SegmentIndex {
    /// Index the edges of closed `loops` and open `polylines`.
    pub fn new(loops: &[&[DVec2]], polylines: &[&[DVec2]]) -> Self {
        let count = loops
            .iter()
            .map(|l| edge_count(l.len(), true))
            .chain(polylines.iter().map(|l| edge_count(l.len(), false)))
            .sum::<usize>();
        let mut segments = Vec::with_capacity(count);
        for l in loops {
            segments.extend(edges(l, true));
        }
        for l in polylines {
            segments.extend(edges(l, false));
        }
        let Some(grid) = Grid::over(&segments) else {
            return SegmentIndex {
                segments,
                origin: DVec2::ZERO,
                cell_mm: 1.0,
                nx: 0,
                ny: 0,
                starts: vec![0],
                items: Vec::new(),
            };
        };
        let (starts, items) = grid.bucket(&segments);
        SegmentIndex {
            segments,
            origin: grid.origin,
            cell_mm: grid.cell_mm,
            nx: grid.nx,
            ny: grid.ny,
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
    /// segment is, up to `limit`: where the ray first comes within 0.1 µm of one (solved
    /// per segment near the ray, [`capsule_entry`]); none beyond the limit or when empty.
    pub fn ray_hit(&self, origin: DVec2, dir: DVec2, limit: f64) -> Option<f64> {
        if self.segments.is_empty() || limit.is_nan() || limit < 0.0 {
            return None;
        }
        let end = origin + dir * limit;
        let mut first: Option<f64> = None;
        self.near_candidates(origin.min(end), origin.max(end), RAY_HIT_MM, |_, a, b| {
            if let Some(t) = capsule_entry(origin, dir, a, b, RAY_HIT_MM, limit) {
                if first.is_none_or(|f| t < f) {
                    first = Some(t);
                }
            }
            false
        });
        first
    }

    /// How far `p` is from every cell outside the block of `ring` cells round cell
    /// (`pc`, `pr`) (its columns `pc - ring ..= pc + ring`, its rows likewise): from the
    /// block's edge on each side where the grid has cells beyond it; infinite when it
    /// has none.
    fn to_unvisited(&self, p: DVec2, pc: isize, pr: isize, ring: isize) -> f64 {
        let (o, cell) = (self.origin, self.cell_mm);
        let (nx, ny) = (self.nx as isize, self.ny as isize);
        let mut d = f64::INFINITY;
        if pc - ring > 0 {
            d = d.min(p.x - (o.x + (pc - ring) as f64 * cell));
        }
        if pc + ring + 1 < nx {
            d = d.min(o.x + (pc + ring + 1) as f64 * cell - p.x);
        }
        if pr - ring > 0 {
            d = d.min(p.y - (o.y + (pr - ring) as f64 * cell));
        }
        if pr + ring + 1 < ny {
            d = d.min(o.y + (pr + ring + 1) as f64 * cell - p.y);
        }
        d.max(0.0)
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
            // outside the box along the other; and, on each side where such cells are
            // left, beyond the visited block's edge there.
            let beyond = ring as f64 * self.cell_mm;
            let rough = DVec2::new(outside.x + beyond, outside.y)
                .length()
                .min(DVec2::new(outside.x, outside.y + beyond).length());
            let unvisited = rough.max(self.to_unvisited(p, pc, pr, r));
            if best <= unvisited {
                break;
            }
        }
        best_k.map(|k| (best, k))
    }
}

/// The cells of a [`SegmentIndex`]: `nx` by `ny` square cells of `cell_mm` from `origin`.
struct Grid {
    origin: DVec2,
    cell_mm: f64,
    nx: usize,
    ny: usize,
}

impl Grid {
    /// Over the box of `segments`, about two segments a cell on average and at most
    /// ~1M cells; none for no segments.
    fn over(segments: &[(DVec2, DVec2)]) -> Option<Grid> {
        let mut lo = DVec2::splat(f64::INFINITY);
        let mut hi = DVec2::splat(f64::NEG_INFINITY);
        let mut total = 0.0;
        for (a, b) in segments {
            lo = lo.min(a.min(*b));
            hi = hi.max(a.max(*b));
            total += a.distance(*b);
        }
        if segments.is_empty() {
            return None;
        }
        let extent = (hi - lo).max(DVec2::splat(1e-9));
        let mean = (total / segments.len() as f64).max(1e-9);
        let mut cell_mm = (mean * 2.0).max((extent.x * extent.y / 1.0e6).sqrt());
        if !cell_mm.is_finite() || cell_mm <= 0.0 {
            cell_mm = 1.0;
        }
        let nx = ((extent.x / cell_mm).ceil() as usize).clamp(1, 4096);
        let ny = ((extent.y / cell_mm).ceil() as usize).clamp(1, 4096);
        let cell_mm = (extent.x / nx as f64).max(extent.y / ny as f64);
        Some(Grid {
            origin: lo,
            cell_mm,
            nx,
            ny,
        })
    }

    /// The segments of each cell, by a counting sort: count, prefix sums, fill (in
    /// segment order). Returns (`starts`, `items`) as [`SegmentIndex`] keeps them. Cell
    /// ranges here and in the queries are half-open (`r0..r1 + 1`): they step with fewer
    /// instructions than inclusive ones.
    fn bucket(&self, segments: &[(DVec2, DVec2)]) -> (Vec<usize>, Vec<u32>) {
        let (lo, cell_mm, nx, ny) = (self.origin, self.cell_mm, self.nx, self.ny);
        let spans: Vec<[usize; 4]> = segments
            .iter()
            .map(|(a, b)| {
                let (c0, r0) = SegmentIndex::cell_of(lo, cell_mm, nx, ny, a.min(*b));
                let (c1, r1) = SegmentIndex::cell_of(lo, cell_mm, nx, ny, a.max(*b));
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
        (starts, items)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{point_in_loop, point_loop_distance};

    /// A ray hits where it first comes within 0.1 µm of a segment: square-on, at a
    /// slant, past a corner, from on the boundary, running beside a side, and missing
    /// (beyond the limit, or passing clear); each against stepping along the ray.
    #[test]
    fn a_ray_hits_where_it_first_comes_near_a_segment() {
        let square = [
            DVec2::new(0.0, 0.0),
            DVec2::new(4.0, 0.0),
            DVec2::new(4.0, 4.0),
            DVec2::new(0.0, 4.0),
        ];
        let index = SegmentIndex::new(&[&square], &[]);
        let h = RAY_HIT_MM;
        let cases: [(DVec2, DVec2, f64, Option<f64>); 7] = [
            (DVec2::new(1.0, 1.0), DVec2::X, 5.0, Some(3.0 - h)),
            (DVec2::new(1.0, 1.0), DVec2::X, 2.0, None),
            (
                DVec2::new(2.0, 2.0),
                DVec2::new(0.6, 0.8),
                5.0,
                Some((2.0 - h) / 0.8),
            ),
            (DVec2::new(2.0, 0.0), DVec2::Y, 5.0, Some(0.0)),
            // Beside the bottom side, 0.05 µm off: within reach from the start.
            (DVec2::new(1.0, 0.5 * h), DVec2::X, 1.0, Some(0.0)),
            // Beside it 1 µm off, clear of it, to the right side.
            (DVec2::new(1.0, 1e-3), DVec2::X, 5.0, Some(3.0 - h)),
            // Outside, passing the corner (4, 4) 0.14 mm off.
            (
                DVec2::new(5.0, 3.2),
                DVec2::new(-1.0, 1.0).normalize(),
                3.0,
                None,
            ),
        ];
        // A limit that is no number or below zero, and a ray with no direction (a
        // point: a hit where it is within reach, else none).
        assert_eq!(
            index.ray_hit(DVec2::new(1.0, 1.0), DVec2::X, f64::NAN),
            None
        );
        assert_eq!(index.ray_hit(DVec2::new(1.0, 1.0), DVec2::X, -1.0), None);
        assert_eq!(index.ray_hit(DVec2::new(1.0, 1.0), DVec2::ZERO, 5.0), None);
        assert_eq!(
            index.ray_hit(DVec2::new(2.0, 0.0), DVec2::ZERO, 5.0),
            Some(0.0)
        );
        assert_eq!(
            SegmentIndex::new(&[], &[]).ray_hit(DVec2::ZERO, DVec2::X, 5.0),
            None
        );
        for (origin, dir, limit, want) in cases {
            let got = index.ray_hit(origin, dir, limit);
            match (got, want) {
                (Some(g), Some(w)) => assert!((g - w).abs() < 1e-9, "{origin} {dir}: {g} vs {w}"),
                _ => assert_eq!(got, want, "{origin} {dir}"),
            }
            // Stepping along the ray finds nothing nearer before the hit, and the hit
            // is within reach.
            let end = got.unwrap_or(limit);
            let steps = 2000;
            for k in 0..steps {
                let t = end * k as f64 / steps as f64;
                if got.is_none() || t < end - 1e-9 {
                    assert!(
                        index.distance(origin + dir * t) > h - 1e-12,
                        "{origin} {dir} at {t}"
                    );
                }
            }
            if let Some(t) = got {
                assert!(index.distance(origin + dir * t) <= h + 1e-12);
            }
        }
    }

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
    /// force answer (the ring search must not stop before it has seen that segment).
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

    /// Among many short segments (many cells), the search that stops at the visited
    /// block's edges finds what brute force finds, the segment too, with some skipped.
    #[test]
    fn nearest_among_many_cells_is_the_brute_force_one() {
        let rings: Vec<Vec<DVec2>> = (1..12)
            .map(|k| {
                let r = 0.4 * k as f64;
                (0..(40 * k))
                    .map(|j| {
                        DVec2::from_angle(std::f64::consts::TAU * j as f64 / (40 * k) as f64) * r
                    })
                    .collect()
            })
            .collect();
        let refs: Vec<&[DVec2]> = rings.iter().map(|l| l.as_slice()).collect();
        let index = SegmentIndex::new(&refs, &[]);
        let segments = &index.segments;
        let skip = |k: u32| k % 7 == 3;
        for k in 0..2000 {
            let p = DVec2::new(
                (k as f64 * 0.377).sin() * 5.0,
                (k as f64 * 0.911).cos() * 5.0,
            );
            let mut brute = (f64::INFINITY, u32::MAX);
            for (id, &(a, b)) in segments.iter().enumerate() {
                let d = point_segment_distance(p, a, b);
                if !skip(id as u32) && d < brute.0 {
                    brute = (d, id as u32);
                }
            }
            let (d, id) = index.nearest_skipping(p, skip).unwrap();
            assert!((d - brute.0).abs() < 1e-12, "{p}: {d} vs {}", brute.0);
            assert!(
                id == brute.1
                    || (point_segment_distance(
                        p,
                        segments[brute.1 as usize].0,
                        segments[brute.1 as usize].1
                    ) - d)
                        .abs()
                        < 1e-12
            );
        }
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
}
