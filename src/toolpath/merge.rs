//! Fewer, longer edges for the same road: consecutive centreline edges of a path merge
//! into one move where the merged edge stays within a deviation of every vertex it
//! drops and the road's width changes by no more than a tolerance along them.
//!
//! Two ways, by [`MergeOptions::width_tolerance`]:
//!
//! - **0** (the width must not change): edges merge only where the width factor stays
//!   within the wire's resolution; the merged edge keeps its vertices' widths, so it
//!   deposits what its length and width say, less than its edges by the chord-to-arc
//!   difference (for a deviation d on a curve of radius r, edges of about `2·√(2rd)`,
//!   the relative length lost is about `2d/3r`: 0.03 % for d = 0.0125 mm on r = 30 mm,
//!   0.8 % on r = 1 mm, the tightest curves paths have).
//! - **t > 0**: edges merge across width changes while the widest and narrowest of the
//!   edges a move replaces differ by at most t of the narrowest (so each part's width
//!   is within t of the move's). The move pushes exactly the volume of the edges it
//!   replaces: its width factor is their length-weighted mean, raised on a curve by the
//!   chord's shortfall (`Σ L_k·f_k / L_chord`). A move's width is carried by its two
//!   vertices; where the next move's differs, its start vertex is repeated with the new
//!   width (a zero-length edge, which deposits nothing and makes no move), and a loop
//!   whose last move's width differs from its first ends with its first point again.
//!
//! Either way a path's first vertex (its seam, or where it starts) and its last stay;
//! the composition is one per path.
//!
//! Slicers do the same (PrusaSlicer's `resolution`, Cura's maximum deviation; Arachne
//! walls carry width steps within a path): a firmware that plans every line it is sent
//! moves as smoothly as its look-ahead over fewer lines allows.

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
    /// a resolution of 0.001: half of it). Used when `width_tolerance` is 0.
    pub width_factor_tolerance: f64,
    /// Largest relative spread of the edges' widths within one move ((widest −
    /// narrowest) / narrowest); 0: a move never spans a width change.
    pub width_tolerance: f64,
    /// Most vertices one merged edge may drop (bounds the work on long straight runs).
    pub max_dropped: usize,
}

impl MergeOptions {
    /// Merging within `deviation_mm` where the width does not change.
    pub fn within(deviation_mm: f64) -> Self {
        Self {
            deviation_mm,
            width_factor_tolerance: 0.0005,
            width_tolerance: 0.0,
            max_dropped: 256,
        }
    }

    /// These options, moves spanning width changes up to `width_tolerance`.
    pub fn with_width_tolerance(self, width_tolerance: f64) -> Self {
        Self {
            width_tolerance,
            ..self
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
    if o.width_tolerance > 0.0 {
        return merged_across_widths(p, &points, &widths, o);
    }
    let mut keep = kept_vertices(&points, |a, b| same_width(&widths, a, b, o), o);
    let mut out = p.clone();
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

/// `p` as moves that may span width changes (`o.width_tolerance` > 0), each pushing
/// the volume of the edges it replaces; `points` and `widths` are `p`'s as an open
/// polyline.
fn merged_across_widths(
    p: &ToolPath,
    points: &[DVec2],
    widths: &[f64],
    o: &MergeOptions,
) -> ToolPath {
    let factors: Vec<f64> = widths.windows(2).map(|w| 0.5 * (w[0] + w[1])).collect();
    let lengths: Vec<f64> = points.windows(2).map(|e| e[0].distance(e[1])).collect();
    let within = |a: usize, b: usize| width_spread_within(&factors, &lengths, a, b, o);
    let keep = kept_vertices(points, within, o);
    if p.closed && keep.len() < 4 {
        return p.clone(); // fewer than three corners left
    }
    let mut out = p.clone();
    out.points.clear();
    out.width_factors.clear();
    for w in keep.windows(2) {
        let f = move_factor(points, &factors, &lengths, w[0], w[1]);
        if out.width_factors.last() != Some(&f) {
            out.points.push(points[w[0]]);
            out.width_factors.push(f);
        }
        out.points.push(points[w[1]]);
        out.width_factors.push(f);
    }
    if p.closed && out.width_factors.last() == out.width_factors.first() {
        out.points.pop(); // the closing edge returns to the first vertex
        out.width_factors.pop();
    }
    out
}

/// The width factor of one move from vertex `a` to `b` that pushes the volume of the
/// edges between them: `Σ L_k·f_k / |b − a|`.
fn move_factor(points: &[DVec2], factors: &[f64], lengths: &[f64], a: usize, b: usize) -> f64 {
    let chord = points[a].distance(points[b]);
    let laid: f64 = (a..b).map(|k| lengths[k] * factors[k]).sum();
    if chord > 0.0 && b > a + 1 {
        laid / chord
    } else {
        factors[a]
    }
}

/// Whether the edges from vertex `a` to `b` have widths within `o.width_tolerance` of
/// each other (relative to the narrowest; zero-length edges lay nothing and count not).
fn width_spread_within(
    factors: &[f64],
    lengths: &[f64],
    a: usize,
    b: usize,
    o: &MergeOptions,
) -> bool {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for k in (a..b).filter(|&k| lengths[k] > 0.0) {
        lo = lo.min(factors[k]);
        hi = hi.max(factors[k]);
    }
    hi <= lo || hi - lo <= o.width_tolerance * lo
}

/// Whether the vertices from `a` to `b` have one width (within the wire's resolution).
fn same_width(widths: &[f64], a: usize, b: usize, o: &MergeOptions) -> bool {
    let w = widths[a];
    widths[a..=b]
        .iter()
        .all(|&x| (x - w).abs() <= o.width_factor_tolerance)
}

/// Indices of the vertices of an open polyline that stay: the first, the last, and
/// the end of each merged edge, greedily as far as each may reach (`widths_fit(a, b)`:
/// whether the widths from vertex a to b may be one move's).
fn kept_vertices(
    points: &[DVec2],
    widths_fit: impl Fn(usize, usize) -> bool,
    o: &MergeOptions,
) -> Vec<usize> {
    let n = points.len();
    let mut kept = vec![0];
    let mut anchor = 0;
    while anchor < n - 1 {
        let mut end = anchor + 1;
        while end + 1 < n
            && end - anchor <= o.max_dropped
            && widths_fit(anchor, end + 1)
            && within_deviation(points, anchor, end + 1, o)
        {
            end += 1;
        }
        kept.push(end);
        anchor = end;
    }
    kept
}

/// Whether one edge from `a` to `b` stays within the deviation of the vertices between.
fn within_deviation(points: &[DVec2], a: usize, b: usize, o: &MergeOptions) -> bool {
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

    /// What a path deposits per unit section: Σ edge length × mean width factor.
    fn laid(p: &ToolPath) -> f64 {
        let n = p.points.len();
        crate::geom::edges(&p.points, p.closed)
            .enumerate()
            .map(|(k, (a, b))| {
                a.distance(b) * 0.5 * (p.width_factors[k] + p.width_factors[(k + 1) % n])
            })
            .sum()
    }

    #[test]
    fn a_width_ramp_within_the_tolerance_becomes_one_move_of_the_same_volume() {
        let pts: Vec<DVec2> = (0..=10).map(|k| DVec2::new(k as f64 * 0.1, 0.0)).collect();
        let mut p = path(pts, false);
        p.width_factors = (0..=10).map(|k| 1.0 + 0.004 * k as f64).collect();
        let o = MergeOptions::within(0.0025).with_width_tolerance(0.05);
        let m = merge_edges(&p, &o);
        assert_eq!(m.points, vec![p.points[0], p.points[10]]);
        assert!(
            (laid(&m) - laid(&p)).abs() < 1e-12,
            "{} vs {}",
            laid(&m),
            laid(&p)
        );
        // Nothing merges across the ramp without a tolerance.
        assert_eq!(merge_edges(&p, &MergeOptions::within(0.0025)), p);
    }

    #[test]
    fn a_width_step_past_the_tolerance_starts_a_move_at_the_same_vertex() {
        let pts: Vec<DVec2> = (0..=10).map(|k| DVec2::new(k as f64, 0.0)).collect();
        let mut p = path(pts, false);
        for k in 0..=10 {
            p.width_factors[k] = if k <= 5 { 1.0 + 0.001 * k as f64 } else { 1.3 };
        }
        let o = MergeOptions::within(0.0025).with_width_tolerance(0.02);
        let m = merge_edges(&p, &o);
        let xs: Vec<f64> = m.points.iter().map(|q| q.x).collect();
        // 0..5 one move; the edge 5-6 (factor 1.1525) one; 6..10 one: each move's
        // start repeated at its new width.
        assert_eq!(xs, [0.0, 5.0, 5.0, 6.0, 6.0, 10.0]);
        assert!(
            (m.width_factors[1] - 1.0025).abs() < 1e-12,
            "{:?}",
            m.width_factors
        );
        assert!((m.width_factors[3] - 1.1525).abs() < 1e-12);
        assert_eq!(m.width_factors[5], 1.3);
        assert!((laid(&m) - laid(&p)).abs() < 1e-12);
    }

    #[test]
    fn a_loop_of_varying_width_keeps_its_seam_and_volume() {
        let mut p = path(circle(5.0, 2000), true);
        p.width_factors = (0..2000)
            .map(|k| 1.0 + 0.2 * (std::f64::consts::TAU * k as f64 / 2000.0).sin().abs())
            .collect();
        let o = MergeOptions::within(0.0025).with_width_tolerance(0.05);
        let m = merge_edges(&p, &o);
        assert!(m.closed);
        assert_eq!(m.points[0], p.points[0], "the seam stays");
        assert!(within(&p, &m, 0.0025));
        let moves = crate::geom::edges(&m.points, true)
            .filter(|(a, b)| a.distance(*b) > 0.0)
            .count();
        assert!(moves < 300, "{moves} moves from 2000 edges");
        assert!(
            (laid(&m) / laid(&p) - 1.0).abs() < 1e-12,
            "{} vs {}",
            laid(&m),
            laid(&p)
        );
        // Every move's width is within the tolerance of the widths it replaces.
        let max = m.width_factors.iter().fold(0.0f64, |a, &b| a.max(b));
        assert!(max <= 1.2 * 1.05 + 1e-9, "{max}");
    }
}
