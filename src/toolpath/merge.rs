//! Fewer, longer edges for the same road: consecutive centreline edges of a path merge
//! into one where the merged edge stays within a deviation of every vertex it drops
//! and the road's width does not change along them (beyond the wire's resolution of
//! the width factor). What a road deposits is what its edges' lengths and widths say,
//! so merging changes the deposit by at most the chord-to-arc difference (for a
//! deviation d on a curve of radius r, edges of about `2·√(2rd)`, the relative length
//! lost is about `2d/3r`: 0.03 % for d = 0.0125 mm on r = 30 mm, 0.8 % on r = 1 mm,
//! the tightest curves paths have). A path's first vertex (its seam, or where it
//! starts) and its last stay; so does every vertex where the width changes (the flow
//! raise), the composition is one per path.
//!
//! Slicers do the same (PrusaSlicer's `resolution`, Cura's maximum deviation): a
//! firmware that plans every line it is sent moves as smoothly as its look-ahead over
//! fewer lines allows.

use glam::DVec2;

use super::ToolPath;
use crate::geom::point_segment_distance;

/// How far merging may go.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MergeOptions {
    /// Largest distance of a dropped vertex from the edge that replaces it, mm
    /// (0: nothing merges).
    pub deviation_mm: f64,
    /// Width factors closer than this are the same width (the wire's width factor has
    /// a resolution of 0.001: half of it).
    pub width_factor_tolerance: f64,
    /// Most vertices one merged edge may drop (bounds the work on long straight runs).
    pub max_dropped: usize,
}

impl MergeOptions {
    /// Merging within `deviation_mm`.
    pub fn within(deviation_mm: f64) -> Self {
        Self {
            deviation_mm,
            width_factor_tolerance: 0.0005,
            max_dropped: 256,
        }
    }
}

/// `p` with its edges merged as [`MergeOptions`] allow (see the module docs).
pub fn merge_edges(p: &ToolPath, o: &MergeOptions) -> ToolPath {
    let n = p.points.len();
    if o.deviation_mm <= 0.0 || n < 3 || p.width_factors.len() != n {
        return p.clone();
    }
    // A loop is walked as the open polyline back to its first vertex.
    let mut points = p.points.clone();
    let mut widths = p.width_factors.clone();
    if p.closed {
        points.push(p.points[0]);
        widths.push(p.width_factors[0]);
    }
    let kept = kept_vertices(&points, &widths, o);
    let mut out = p.clone();
    let mut keep: Vec<usize> = kept;
    if p.closed {
        keep.pop(); // the closing vertex is the first again
        if keep.len() < 3 {
            return p.clone();
        }
    }
    out.points = keep.iter().map(|&k| points[k]).collect();
    out.width_factors = keep.iter().map(|&k| widths[k]).collect();
    out
}

/// Indices of the vertices of an open polyline that stay: the first, the last, and
/// the end of each merged edge, greedily as far as each may reach.
fn kept_vertices(points: &[DVec2], widths: &[f64], o: &MergeOptions) -> Vec<usize> {
    let n = points.len();
    let mut kept = vec![0];
    let mut anchor = 0;
    while anchor < n - 1 {
        let mut end = anchor + 1;
        while end + 1 < n
            && end - anchor <= o.max_dropped
            && can_merge(points, widths, anchor, end + 1, o)
        {
            end += 1;
        }
        kept.push(end);
        anchor = end;
    }
    kept
}

/// Whether one edge from `a` to `b` may replace the edges between them.
fn can_merge(points: &[DVec2], widths: &[f64], a: usize, b: usize, o: &MergeOptions) -> bool {
    let w = widths[a];
    if widths[a..=b]
        .iter()
        .any(|&x| (x - w).abs() > o.width_factor_tolerance)
    {
        return false;
    }
    let (pa, pb) = (points[a], points[b]);
    if pa.distance(pb) <= 0.0 {
        return false;
    }
    points[a + 1..b]
        .iter()
        .all(|&q| point_segment_distance(q, pa, pb) <= o.deviation_mm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::PathRole;

    fn path(points: Vec<DVec2>, closed: bool) -> ToolPath {
        let n = points.len();
        ToolPath {
            role: PathRole::Offset {
                island: 0,
                n: 0,
                i: 0,
            },
            points,
            closed,
            width_factors: vec![1.0; n],
            composition: vec![0.5, 0.5],
            seam_at_corner: false,
        }
    }

    fn circle(r: f64, n: usize) -> Vec<DVec2> {
        (0..n)
            .map(|k| {
                let t = std::f64::consts::TAU * k as f64 / n as f64;
                DVec2::new(r * t.cos(), r * t.sin())
            })
            .collect()
    }

    /// Every vertex of `before` lies within `d` of `after`'s polyline.
    fn within(before: &ToolPath, after: &ToolPath, d: f64) -> bool {
        before.points.iter().all(|&q| {
            after
                .edges()
                .map(|(a, b)| point_segment_distance(q, a, b))
                .fold(f64::INFINITY, f64::min)
                <= d + 1e-12
        })
    }

    #[test]
    fn a_finely_sampled_circle_merges_to_chords_within_the_deviation() {
        let p = path(circle(5.0, 2000), true);
        let m = merge_edges(&p, &MergeOptions::within(0.0125));
        // Chords of 2·√(2·5·0.0125) ≈ 0.71 mm: about 44 of them.
        assert!((40..=50).contains(&m.points.len()), "{}", m.points.len());
        assert!(m.closed);
        assert_eq!(m.points[0], p.points[0], "the seam stays");
        assert!(within(&p, &m, 0.0125));
        let lost = 1.0 - m.length_mm() / p.length_mm();
        assert!(lost > 0.0 && lost < 0.002, "{lost}");
    }

    #[test]
    fn a_straight_run_becomes_one_edge_and_ends_stay() {
        let pts: Vec<DVec2> = (0..=100)
            .map(|k| DVec2::new(k as f64 * 0.01, 0.0))
            .collect();
        let p = path(pts, false);
        let m = merge_edges(&p, &MergeOptions::within(0.0125));
        assert_eq!(m.points, vec![p.points[0], p.points[100]]);
        assert_eq!(m.width_factors, vec![1.0, 1.0]);
    }

    #[test]
    fn a_width_change_keeps_its_vertices() {
        let pts: Vec<DVec2> = (0..=10).map(|k| DVec2::new(k as f64, 0.0)).collect();
        let mut p = path(pts, false);
        for k in 5..=10 {
            p.width_factors[k] = 1.2;
        }
        // Below the wire's resolution: still one width.
        p.width_factors[2] = 1.0004;
        let m = merge_edges(&p, &MergeOptions::within(0.0125));
        let xs: Vec<f64> = m.points.iter().map(|q| q.x).collect();
        assert_eq!(xs, [0.0, 4.0, 5.0, 10.0]);
        assert_eq!(m.width_factors, [1.0, 1.0, 1.2, 1.2]);
    }

    #[test]
    fn corners_stay_and_nothing_merges_at_zero_deviation() {
        let square = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(1.0, 0.0),
            DVec2::new(1.0, 1.0),
            DVec2::new(0.0, 1.0),
        ];
        let p = path(square, true);
        assert_eq!(merge_edges(&p, &MergeOptions::within(0.0125)), p);
        let c = path(circle(5.0, 100), true);
        assert_eq!(merge_edges(&c, &MergeOptions::within(0.0)), c);
    }

    #[test]
    fn a_tiny_loop_keeps_at_least_a_triangle() {
        let p = path(circle(0.005, 12), true);
        let m = merge_edges(&p, &MergeOptions::within(0.0125));
        assert!(m.points.len() >= 3);
        assert!(m.closed);
    }
}
