//! [`keep_clear_of`]: the parts of roads at least a clearance from a contour (the roads
//! run towards it), each near piece cut where it crosses that distance. Answers come
//! from the contour's [`SegmentIndex`], gathered once per window of edges
//! ([`NearSegments`]).

use super::{NearSegments, Path, SegmentIndex};
use glam::DVec2;

/// The parts of `roads` at least `clearance_mm` from every segment of `index` (the
/// contour the roads run towards): a piece that comes nearer is cut where it crosses
/// that distance (found by bisection along the edge) and the near part dropped.
pub fn keep_clear_of(roads: Vec<Path>, index: &SegmentIndex, clearance_mm: f64) -> Vec<Path> {
    if index.is_empty() {
        return roads;
    }
    // Gathered a hair beyond the clearance, so points a rounding off an edge are
    // still covered.
    let gather_mm = clearance_mm * (1.0 + 1e-6);
    let window_mm = KEEP_CLEAR_WINDOW * clearance_mm;
    let mut near = NearSegments::default();
    let mut out = Vec::with_capacity(roads.len());
    // Per point of a road being trimmed: the point, whether it is at least the
    // clearance from the contour, and the range of `near` that holds the contour's
    // segments near the edge it starts (they answer every question about points on
    // that edge as the whole index would).
    let mut pts: Vec<DVec2> = Vec::new();
    let mut far: Vec<bool> = Vec::new();
    let mut spans: Vec<std::ops::Range<usize>> = Vec::new();
    let mut run: Vec<DVec2> = Vec::new();
    for road in roads {
        // Edges that come within the clearance are split to at most the clearance, so
        // a near pass between their ends is seen; the rest are clear whole, and a road
        // with no such edge is kept as it is without the per-point lists.
        let m = road.points.len();
        let edges = if road.closed { m } else { m.saturating_sub(1) };
        pts.clear();
        far.clear();
        spans.clear();
        near.truncate(0);
        let mut split = false;
        let mut clear_before = false;
        let edge = |k: usize| {
            (
                road.points[k],
                road.points[if k + 1 == m { 0 } else { k + 1 }],
            )
        };
        // The contour's segments near a window: the box of a run of consecutive edges
        // at most `window_mm` across, gathered once for all of them (`win` in `near`;
        // dropped again when none of its edges came near).
        let (mut win_lo, mut win_hi) =
            (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        let mut win = 0..0;
        let mut win_used = false;
        for k in 0..edges {
            let (a, b) = edge(k);
            let (lo, hi) = (a.min(b), a.max(b));
            if !(lo.cmpge(win_lo).all() && hi.cmple(win_hi).all()) {
                if !win_used {
                    near.truncate(win.start);
                }
                (win_lo, win_hi) = (lo, hi);
                for j in k + 1..edges {
                    let (c, d) = edge(j);
                    let (grown_lo, grown_hi) = (win_lo.min(c.min(d)), win_hi.max(c.max(d)));
                    if (grown_hi - grown_lo).max_element() > window_mm {
                        break;
                    }
                    (win_lo, win_hi) = (grown_lo, grown_hi);
                }
                let from = near.len();
                index.near_box(win_lo, win_hi, gather_mm, &mut near);
                win = from..near.len();
                win_used = false;
            }
            // The window's segments answer as the index would for the edge inside it.
            let clear = !near.any_within(win.clone(), a, b, clearance_mm);
            if clear {
                if split {
                    pts.push(a);
                    far.push(true);
                    spans.push(0..0);
                }
            } else {
                if !split {
                    // The clear edges before this one, each point far (room for the
                    // points splitting a few edges without growing the lists).
                    split = true;
                    let room = 2 * m + 16;
                    pts.reserve(room);
                    far.reserve(room);
                    spans.reserve(room);
                    run.reserve(room);
                    near.reserve(room);
                    pts.extend_from_slice(&road.points[..k]);
                    far.resize(k, true);
                    spans.resize(k, 0..0);
                }
                win_used = true;
                let span = win.clone();
                let pieces = ((a.distance(b) / clearance_mm).ceil() as usize).clamp(1, 1 << 16);
                for q in 0..pieces {
                    let p = a.lerp(b, q as f64 / pieces as f64);
                    pts.push(p);
                    far.push(
                        (q == 0 && clear_before) || !near.within(span.clone(), p, clearance_mm),
                    );
                    spans.push(span.clone());
                }
            }
            clear_before = clear;
        }
        if !split {
            // Every edge clear: every point far.
            if edges + usize::from(!road.closed) >= 2 {
                out.push(road);
            }
            continue;
        }
        if road.closed {
            // The first point also ends the last edge.
            if let Some(f) = far.first_mut() {
                if clear_before {
                    *f = true;
                }
            }
        } else if let Some(&last) = road.points.last() {
            pts.push(last);
            far.push(clear_before || !index.within(last, clearance_mm));
            spans.push(near.len()..near.len());
        }
        let n = pts.len();
        if n < 2 {
            continue;
        }
        let Some(first_near) = far.iter().position(|&f| !f) else {
            out.push(road);
            continue;
        };
        // Where the distance crosses the clearance between a (far) and b (near).
        // Both lie on the edge point `k` starts, so its near segments answer.
        let cross = |a: DVec2, b: DVec2, k: usize| {
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..CLEARANCE_BISECTIONS {
                let mid = 0.5 * (lo + hi);
                if !near.within(spans[k].clone(), a.lerp(b, mid), clearance_mm) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            a.lerp(b, lo)
        };
        // A loop is walked from a near vertex, so no kept run wraps round its start.
        let (start, edges) = if road.closed {
            (first_near, n)
        } else {
            (0, n - 1)
        };
        let at = |k: usize| {
            if start + k >= n {
                start + k - n
            } else {
                start + k
            }
        };
        // Built in one buffer, each kept run copied out at its length.
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
        for e in 0..edges {
            let (i, j) = (at(e), at(e + 1));
            match (far[i], far[j]) {
                (true, true) => run.push(pts[j]),
                (true, false) => {
                    run.push(cross(pts[i], pts[j], i));
                    flush(&mut run);
                }
                (false, true) => {
                    run.push(cross(pts[j], pts[i], i));
                    run.push(pts[j]);
                }
                (false, false) => {}
            }
        }
        flush(&mut run);
    }
    out
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
