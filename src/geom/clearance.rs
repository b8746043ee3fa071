//! [`keep_clear_of`]: the parts of roads at least a clearance from a contour (the roads
//! run towards it), each near piece cut where it crosses that distance. Answers come
//! from the contour's [`SegmentIndex`], gathered once per window of edges
//! ([`NearSegments`]).

use super::{edge_count, loop_edge, NearSegments, Path, SegmentIndex};
use glam::DVec2;
use std::ops::Range;

/// The parts of `roads` at least `clearance_mm` from every segment of `index` (the
/// contour the roads run towards): a piece that comes nearer is cut where it crosses
/// that distance (found by bisection along the edge) and the near part dropped.
///
/// Per road: [`Trim::mark_points`] finds the edges that come within the clearance and
/// splits them into points marked far or near; a road with none is kept whole.
/// [`Trim::close_ends`] marks the point the last edge ends on, and [`Trim::cut_runs`]
/// keeps the runs of far points, each cut where it crosses the clearance.
pub fn keep_clear_of(roads: Vec<Path>, index: &SegmentIndex, clearance_mm: f64) -> Vec<Path> {
    if index.is_empty() {
        return roads;
    }
    let mut trim = Trim::new(index, clearance_mm);
    let mut out = Vec::with_capacity(roads.len());
    for road in roads {
        trim.road(road, &mut out);
    }
    out
}

/// The working state of [`keep_clear_of`], kept from road to road.
struct Trim<'a> {
    index: &'a SegmentIndex,
    clearance_mm: f64,
    /// How far beyond the clearance the contour's segments are gathered: a hair, so
    /// points a rounding off an edge are still covered.
    gather_mm: f64,
    /// The most a window of edges spans across.
    window_mm: f64,
    near: NearSegments,
    /// Per point of a road being trimmed: the point, whether it is at least the
    /// clearance from the contour, and the range of `near` that holds the contour's
    /// segments near the edge it starts (they answer every question about points on
    /// that edge as the whole index would).
    pts: Vec<DVec2>,
    far: Vec<bool>,
    spans: Vec<Range<usize>>,
    /// The kept run being built (one buffer, each run copied out at its length).
    run: Vec<DVec2>,
}

/// The contour's segments near a window: the box of a run of consecutive edges at most
/// `window_mm` across, gathered once for all of them (`range` in `near`; dropped again
/// when none of its edges came near).
struct Window {
    lo: DVec2,
    hi: DVec2,
    range: Range<usize>,
    used: bool,
}

impl<'a> Trim<'a> {
    fn new(index: &'a SegmentIndex, clearance_mm: f64) -> Self {
        Trim {
            index,
            clearance_mm,
            gather_mm: clearance_mm * (1.0 + 1e-6),
            window_mm: KEEP_CLEAR_WINDOW * clearance_mm,
            near: NearSegments::default(),
            pts: Vec::new(),
            far: Vec::new(),
            spans: Vec::new(),
            run: Vec::new(),
        }
    }

    /// The parts of `road` clear of the contour, onto `out`.
    fn road(&mut self, road: Path, out: &mut Vec<Path>) {
        let Some(clear_before) = self.mark_points(&road) else {
            // Every edge clear: every point far.
            if edge_count(road.points.len(), road.closed) + usize::from(!road.closed) >= 2 {
                out.push(road);
            }
            return;
        };
        self.close_ends(&road, clear_before);
        if self.pts.len() < 2 {
            return;
        }
        let Some(first_near) = self.far.iter().position(|&f| !f) else {
            out.push(road);
            return;
        };
        self.cut_runs(road.closed, first_near, out);
    }

    /// Step 1: edges that come within the clearance are split to at most the clearance,
    /// so a near pass between their ends is seen, and each point marked far or near;
    /// the rest are clear whole. None where every edge is clear (the per-point lists
    /// are then not filled); else whether the last edge is.
    fn mark_points(&mut self, road: &Path) -> Option<bool> {
        let m = road.points.len();
        let edges = edge_count(m, road.closed);
        self.pts.clear();
        self.far.clear();
        self.spans.clear();
        self.near.truncate(0);
        let mut split = false;
        let mut clear_before = false;
        let mut window = Window {
            lo: DVec2::splat(f64::INFINITY),
            hi: DVec2::splat(f64::NEG_INFINITY),
            range: 0..0,
            used: false,
        };
        for k in 0..edges {
            let (a, b) = loop_edge(&road.points, k);
            let (lo, hi) = (a.min(b), a.max(b));
            if !(lo.cmpge(window.lo).all() && hi.cmple(window.hi).all()) {
                self.next_window(&mut window, &road.points, k, edges);
            }
            // The window's segments answer as the index would for the edge inside it.
            let clear = !self
                .near
                .any_within(window.range.clone(), a, b, self.clearance_mm);
            if clear {
                if split {
                    self.pts.push(a);
                    self.far.push(true);
                    self.spans.push(0..0);
                }
            } else {
                if !split {
                    split = true;
                    self.start_split(&road.points, k);
                }
                window.used = true;
                self.split_edge(a, b, window.range.clone(), clear_before);
            }
            clear_before = clear;
        }
        split.then_some(clear_before)
    }

    /// Replace `window` by the one starting at edge `k` of the `edges` of the road
    /// through `points`: as many edges on as fit in `window_mm`, their contour segments
    /// gathered (the last window's dropped where none of its edges came near).
    fn next_window(&mut self, window: &mut Window, points: &[DVec2], k: usize, edges: usize) {
        if !window.used {
            self.near.truncate(window.range.start);
        }
        let (a, b) = loop_edge(points, k);
        let (mut lo, mut hi) = (a.min(b), a.max(b));
        for j in k + 1..edges {
            let (c, d) = loop_edge(points, j);
            let (grown_lo, grown_hi) = (lo.min(c.min(d)), hi.max(c.max(d)));
            if (grown_hi - grown_lo).max_element() > self.window_mm {
                break;
            }
            (lo, hi) = (grown_lo, grown_hi);
        }
        let from = self.near.len();
        self.index.near_box(lo, hi, self.gather_mm, &mut self.near);
        *window = Window {
            lo,
            hi,
            range: from..self.near.len(),
            used: false,
        };
    }

    /// The first edge that comes near is edge `k`: the points of the clear edges before
    /// it, each far (with room for the points splitting a few edges without growing the
    /// lists).
    fn start_split(&mut self, points: &[DVec2], k: usize) {
        let room = 2 * points.len() + 16;
        self.pts.reserve(room);
        self.far.reserve(room);
        self.spans.reserve(room);
        self.run.reserve(room);
        self.near.reserve(room);
        self.pts.extend_from_slice(&points[..k]);
        self.far.resize(k, true);
        self.spans.resize(k, 0..0);
    }

    /// The points splitting the edge `a`–`b` (whose contour segments are `span` of
    /// `near`) to at most the clearance, each marked far or near; the first is far where
    /// the edge before it is clear.
    fn split_edge(&mut self, a: DVec2, b: DVec2, span: Range<usize>, clear_before: bool) {
        let pieces = ((a.distance(b) / self.clearance_mm).ceil() as usize).clamp(1, 1 << 16);
        for q in 0..pieces {
            let p = a.lerp(b, q as f64 / pieces as f64);
            self.pts.push(p);
            self.far.push(
                (q == 0 && clear_before) || !self.near.within(span.clone(), p, self.clearance_mm),
            );
            self.spans.push(span.clone());
        }
    }

    /// Step 2: the point the last edge ends on. A loop's is its first point, far too
    /// where that edge is clear; an open road's is its last point.
    fn close_ends(&mut self, road: &Path, clear_before: bool) {
        if road.closed {
            if let Some(f) = self.far.first_mut() {
                if clear_before {
                    *f = true;
                }
            }
        } else if let Some(&last) = road.points.last() {
            self.pts.push(last);
            self.far
                .push(clear_before || !self.index.within(last, self.clearance_mm));
            self.spans.push(self.near.len()..self.near.len());
        }
    }

    /// Step 3: the runs of far points onto `out`, each ended (or begun) where the edge
    /// to a near point crosses the clearance. A loop is walked from a near point
    /// (`first_near`), so no kept run wraps round its start.
    fn cut_runs(&mut self, closed: bool, first_near: usize, out: &mut Vec<Path>) {
        let Trim {
            near,
            pts,
            far,
            spans,
            run,
            clearance_mm,
            ..
        } = self;
        let n = pts.len();
        // Where the distance crosses the clearance between a (far) and b (near).
        // Both lie on the edge point `k` starts, so its near segments answer.
        let cross = |a: DVec2, b: DVec2, k: usize| {
            clearance_crossing(near, spans[k].clone(), a, b, *clearance_mm)
        };
        let start = if closed { first_near } else { 0 };
        let at = |k: usize| {
            if start + k >= n {
                start + k - n
            } else {
                start + k
            }
        };
        run.clear();
        if far[at(0)] {
            run.push(pts[at(0)]);
        }
        let mut flush = |run: &mut Vec<DVec2>| {
            if run.len() >= 2 {
                out.push(Path {
                    points: run.clone(),
                    closed: false,
                });
            }
            run.clear();
        };
        for e in 0..edge_count(n, closed) {
            let (i, j) = (at(e), at(e + 1));
            match (far[i], far[j]) {
                (true, true) => run.push(pts[j]),
                (true, false) => {
                    run.push(cross(pts[i], pts[j], i));
                    flush(run);
                }
                (false, true) => {
                    run.push(cross(pts[j], pts[i], i));
                    run.push(pts[j]);
                }
                (false, false) => {}
            }
        }
        flush(run);
    }
}

/// Where the distance to the contour crosses `clearance_mm` between `far` (clear) and
/// `near`, both on one edge whose contour segments are `span` of `segments`: bisection,
/// the last point found clear.
fn clearance_crossing(
    segments: &NearSegments,
    span: Range<usize>,
    far: DVec2,
    near: DVec2,
    clearance_mm: f64,
) -> DVec2 {
    let (mut lo, mut hi) = (0.0, 1.0);
    for _ in 0..CLEARANCE_BISECTIONS {
        let mid = 0.5 * (lo + hi);
        if !segments.within(span.clone(), far.lerp(near, mid), clearance_mm) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    far.lerp(near, lo)
}

/// The most a window of [`keep_clear_of`] spans across (in clearances).
const KEEP_CLEAR_WINDOW: f64 = 8.0;

/// Bisection steps placing a road's end at the clearance (2⁻¹² of an edge).
const CLEARANCE_BISECTIONS: usize = 12;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::circle;

    #[test]
    fn roads_stop_the_clearance_short_of_the_contour() {
        // A contour along y = 0 and a road slanting down onto it from (0, 1) to (4, 0):
        // kept only where it is 0.2 or more from the contour, i.e. up to x = 3.2.
        let contour = [DVec2::new(-1.0, 0.0), DVec2::new(5.0, 0.0)];
        let index = crate::geom::SegmentIndex::new(&[], &[&contour]);
        let road = Path {
            points: vec![DVec2::new(0.0, 1.0), DVec2::new(4.0, 0.0)],
            closed: false,
        };
        let kept = keep_clear_of(vec![road], &index, 0.2);
        assert_eq!(kept.len(), 1);
        let end = *kept[0].points.last().unwrap();
        assert!(
            (end.y - 0.2).abs() < 1e-3 && (end.x - 3.2).abs() < 5e-3,
            "{end:?}"
        );
        // A loop that dips near the contour in one place is cut open there; one that
        // stays clear is kept whole and closed.
        let ring = |cy: f64| Path {
            points: circle(DVec2::new(2.0, cy), 1.0, 0.01),
            closed: true,
        };
        let kept = keep_clear_of(vec![ring(1.1), ring(3.0)], &index, 0.2);
        assert_eq!(kept.len(), 2);
        assert!(!kept[0].closed && kept[1].closed);
        for q in &kept[0].points {
            assert!(index.distance(*q) >= 0.2 - 1e-3, "{q:?}");
        }
    }
}
