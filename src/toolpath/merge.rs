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
//! A merged edge longer than [`MergeOptions::full_deviation_length_mm`] may leave its
//! dropped vertices only `deviation × full length / its length` away: the sliver
//! between a merged edge and the edges it replaces grows with its length, and a long
//! straight run tilted by the full deviation (where it drops a corner vertex next to
//! its end) would leave a sliver that long between its bead and its neighbour's. With
//! the road width as that length, a long edge may lean only as far as a road-width
//! edge could in area, while curves (whose chords are short) merge as far as the
//! deviation allows.
//!
//! Roads merged one by one each keep vertices where their own chords run out of
//! deviation, out of phase with their neighbours': where one road's chord cuts inside
//! its curve its neighbour's vertex lies on its curve, and the gap between the beads
//! opens by the deviation. [`merge_edges_in_phase`] draws a merged edge back to end at
//! a station, the foot of a vertex a neighbour kept ([`Stations`]), where the edge sags
//! (at least [`MergeOptions::station_min_sag`] of the deviation) and keeps at least
//! [`MergeOptions::station_reach`] of its length, so neighbouring roads' chords span the
//! same stretch of their curves and stay the same distance apart.
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
    /// Merged edges up to this long may leave a dropped vertex `deviation_mm` away; a
    /// longer one only `deviation_mm × full_deviation_length_mm / its length`, mm (0:
    /// every edge the full deviation). See the module docs.
    pub full_deviation_length_mm: f64,
    /// A merged edge is drawn back to end at a station ([`Stations`]: the foot of a
    /// vertex its neighbour kept) when that keeps at least this fraction of its length...
    pub station_reach: f64,
    /// ...and the edge sags at least this fraction of the deviation from the vertices
    /// it drops (a straight run's phase does not matter).
    pub station_min_sag: f64,
}

impl MergeOptions {
    /// Merging within `deviation_mm` where the width does not change.
    pub fn within(deviation_mm: f64) -> Self {
        Self {
            deviation_mm,
            width_factor_tolerance: 0.0005,
            width_tolerance: 0.0,
            max_dropped: 256,
            full_deviation_length_mm: 0.0,
            station_reach: 0.5,
            station_min_sag: 0.5,
        }
    }

    /// These options, merged edges longer than `length_mm` leaning less (see
    /// [`MergeOptions::full_deviation_length_mm`]).
    pub fn with_full_deviation_length(self, length_mm: f64) -> Self {
        Self {
            full_deviation_length_mm: length_mm,
            ..self
        }
    }

    /// How far a merged edge `length_mm` long may leave the vertices it drops, mm.
    fn deviation_for(&self, length_mm: f64) -> f64 {
        let full = self.full_deviation_length_mm;
        if full > 0.0 && length_mm > full {
            self.deviation_mm * full / length_mm
        } else {
            self.deviation_mm
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
    merge_edges_in_phase(p, o, &Stations::new(0.0))
}

/// [`merge_edges`], the merged edges ending where possible at `stations`: the feet on
/// `p` of the vertices its neighbouring roads kept, so neighbouring roads' chords cut
/// their curves in phase (see [`Stations`]).
pub fn merge_edges_in_phase(p: &ToolPath, o: &MergeOptions, stations: &Stations) -> ToolPath {
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
    let at_station = stations.insert_feet(&mut points, &mut widths);
    let ends = ChordEnds {
        o,
        at_station: &at_station,
    };
    if o.width_tolerance > 0.0 {
        return merged_across_widths(p, &points, &widths, &ends);
    }
    let mut keep = ends.kept_vertices(&points, |a, b| same_width(&widths, a, b, o));
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
    ends: &ChordEnds,
) -> ToolPath {
    let factors: Vec<f64> = widths.windows(2).map(|w| 0.5 * (w[0] + w[1])).collect();
    let lengths: Vec<f64> = points.windows(2).map(|e| e[0].distance(e[1])).collect();
    let within = |a: usize, b: usize| width_spread_within(&factors, &lengths, a, b, ends.o);
    let keep = ends.kept_vertices(points, within);
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

/// Where merged edges may end: the options, and which vertices of the open polyline
/// are stations (the feet of neighbouring roads' kept vertices).
struct ChordEnds<'a> {
    o: &'a MergeOptions,
    at_station: &'a [bool],
}

impl ChordEnds<'_> {
    /// Indices of the vertices of an open polyline that stay: the first, the last, and
    /// the end of each merged edge, greedily as far as each may reach (`widths_fit(a,
    /// b)`: whether the widths from vertex a to b may be one move's), then drawn back to
    /// the last station on the way where that keeps at least
    /// [`MergeOptions::station_reach`] of the edge.
    fn kept_vertices(
        &self,
        points: &[DVec2],
        widths_fit: impl Fn(usize, usize) -> bool,
    ) -> Vec<usize> {
        let o = self.o;
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
            end = self.drawn_back_to_station(points, anchor, end);
            kept.push(end);
            anchor = end;
        }
        kept
    }

    /// `end`, or the last station after `anchor` before it that keeps at least
    /// `station_reach` of the edge's length (the road then turns where its neighbour
    /// does; a station much shorter would only add moves).
    fn drawn_back_to_station(&self, points: &[DVec2], anchor: usize, end: usize) -> usize {
        if self.at_station.is_empty() || self.at_station[end] || end + 1 == points.len() {
            return end;
        }
        let (pa, pb) = (points[anchor], points[end]);
        let reach = pa.distance(pb) * self.o.station_reach;
        let Some(station) = (anchor + 1..end)
            .rev()
            .find(|&k| self.at_station[k])
            .filter(|&k| pa.distance(points[k]) >= reach)
        else {
            return end;
        };
        // Where the edge is as good as straight its neighbour's phase does not matter
        // (nothing sags between them): keep the longer edge.
        let sag = points[anchor + 1..end]
            .iter()
            .map(|&q| point_segment_distance(q, pa, pb))
            .fold(0.0, f64::max);
        if sag < self.o.station_min_sag * self.o.deviation_mm {
            end
        } else {
            station
        }
    }
}

/// The vertices neighbouring roads kept once merged, found by grid cell, so the next
/// road merges in phase with them ([`merge_edges_in_phase`]): each vertex within
/// `reach_mm` of a road's centreline has its foot (the nearest point of the road) made
/// a station of that road, where the road's merged edges end when they can.
///
/// Roads merged one by one out of phase (each keeping vertices where its own chord
/// runs out of deviation) leave slivers between them: where one road's chord cuts
/// inside its curve by the deviation its neighbour's vertex lies on its curve, and the
/// gap between the beads widens by the deviation. Ending both roads' edges at the same
/// stations along the offset direction keeps the beads the same distance apart at
/// every station, as parallel curves' chords between the same normals are parallel.
#[derive(Clone, Debug, Default)]
pub struct Stations {
    reach_mm: f64,
    cells: std::collections::HashMap<Cell, Vec<DVec2>>,
}

/// A grid cell of [`Stations`].
type Cell = (i64, i64);

/// Where a station's foot is on a polyline: its distance from the station, the edge and
/// the fraction along it.
#[derive(Clone, Copy)]
struct Foot {
    distance: f64,
    edge: usize,
    along: f64,
}

impl Stations {
    /// No stations yet; vertices within `reach_mm` of a road become its stations (0:
    /// none ever do).
    pub fn new(reach_mm: f64) -> Self {
        Self {
            reach_mm: reach_mm.max(0.0),
            cells: Default::default(),
        }
    }

    fn cell_of(&self, p: DVec2) -> Cell {
        (
            (p.x / self.reach_mm).floor() as i64,
            (p.y / self.reach_mm).floor() as i64,
        )
    }

    /// The vertices of `p` (a road once merged) are stations of the roads after it.
    pub fn add(&mut self, p: &ToolPath) {
        if self.reach_mm <= 0.0 {
            return;
        }
        // A width step repeats its vertex (`merged_across_widths`): one station.
        let mut last = None;
        for &q in &p.points {
            if q.is_finite() && last != Some(q) {
                let c = self.cell_of(q);
                self.cells.entry(c).or_default().push(q);
            }
            last = Some(q);
        }
    }

    /// Insert into the open polyline `points` (with its `widths`, interpolated) the
    /// feet of the stations within reach, and say which vertices are stations. Empty
    /// when there are none.
    fn insert_feet(&self, points: &mut Vec<DVec2>, widths: &mut Vec<f64>) -> Vec<bool> {
        let (at_vertex, mut on_edges) = self.feet_on(points);
        if on_edges.is_empty() && !at_vertex.contains(&true) {
            return Vec::new();
        }
        on_edges.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
        let (old_points, old_widths) = (std::mem::take(points), std::mem::take(widths));
        let mut at_station = Vec::with_capacity(old_points.len() + on_edges.len());
        let mut feet = on_edges.into_iter().peekable();
        for (k, (&p, &w)) in old_points.iter().zip(&old_widths).enumerate() {
            points.push(p);
            widths.push(w);
            at_station.push(at_vertex[k]);
            while let Some((_, t)) = feet.next_if(|f| f.0 == k) {
                let (q, wq) = (old_points[k + 1], old_widths[k + 1]);
                let foot = p.lerp(q, t);
                if points
                    .last()
                    .is_some_and(|l| l.distance(foot) > FOOT_AT_VERTEX_MM)
                {
                    points.push(foot);
                    widths.push(w + (wq - w) * t);
                    at_station.push(true);
                }
            }
        }
        at_station
    }

    /// The feet on the open polyline `points` of the stations within reach: at a
    /// vertex (by index) or inside an edge (its index and the fraction along it), each
    /// station's on the edge nearest it.
    fn feet_on(&self, points: &[DVec2]) -> (Vec<bool>, Vec<(usize, f64)>) {
        let mut at_vertex = vec![false; points.len()];
        let mut on_edges = Vec::new();
        if self.reach_mm <= 0.0 || self.cells.is_empty() {
            return (at_vertex, on_edges);
        }
        // Each station's foot on its nearest edge, by the station's cell and index
        // within it.
        let mut nearest: std::collections::HashMap<(Cell, usize), Foot> = Default::default();
        for (k, e) in points.windows(2).enumerate() {
            self.feet_on_edge(k, e[0], e[1], &mut nearest);
        }
        for Foot { edge, along, .. } in nearest.into_values() {
            let len = points[edge].distance(points[edge + 1]);
            if along * len <= FOOT_AT_VERTEX_MM {
                at_vertex[edge] = true;
            } else if (1.0 - along) * len <= FOOT_AT_VERTEX_MM {
                at_vertex[edge + 1] = true;
            } else {
                on_edges.push((edge, along));
            }
        }
        (at_vertex, on_edges)
    }

    /// The feet on edge `k` (from `a` to `b`) of the stations within reach of it,
    /// where nearer than their feet found so far. The edge is looked round a piece at
    /// a time (pieces of four reaches), so a long one looks at the cells along it only.
    fn feet_on_edge(
        &self,
        k: usize,
        a: DVec2,
        b: DVec2,
        nearest: &mut std::collections::HashMap<(Cell, usize), Foot>,
    ) {
        let (ab, len) = (b - a, a.distance(b));
        if !len.is_finite() {
            return;
        }
        let len2 = len * len;
        let pieces = (len / (4.0 * self.reach_mm)).ceil().max(1.0) as usize;
        let reach = DVec2::splat(self.reach_mm);
        for j in 0..pieces {
            let (p0, p1) = (
                a + ab * (j as f64 / pieces as f64),
                a + ab * ((j + 1) as f64 / pieces as f64),
            );
            let (lo, hi) = (
                self.cell_of(p0.min(p1) - reach),
                self.cell_of(p0.max(p1) + reach),
            );
            for cell in (lo.0..=hi.0).flat_map(|cx| (lo.1..=hi.1).map(move |cy| (cx, cy))) {
                let Some(qs) = self.cells.get(&cell) else {
                    continue;
                };
                for (i, &q) in qs.iter().enumerate() {
                    let along = if len2 > 0.0 {
                        ((q - a).dot(ab) / len2).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    let distance = q.distance(a + ab * along);
                    if distance > self.reach_mm {
                        continue;
                    }
                    let foot = Foot {
                        distance,
                        edge: k,
                        along,
                    };
                    let best = nearest.entry((cell, i)).or_insert(foot);
                    if distance < best.distance {
                        *best = foot;
                    }
                }
            }
        }
    }
}

/// A station's foot this close to a vertex is at the vertex, mm.
const FOOT_AT_VERTEX_MM: f64 = 1e-4;

/// Whether one edge from `a` to `b` stays within the deviation its length allows
/// ([`MergeOptions::deviation_for`]) of the vertices between.
fn within_deviation(points: &[DVec2], a: usize, b: usize, o: &MergeOptions) -> bool {
    let (pa, pb) = (points[a], points[b]);
    let length = pa.distance(pb);
    if length <= 0.0 {
        return false;
    }
    let deviation = o.deviation_for(length);
    points[a + 1..b]
        .iter()
        .all(|&q| point_segment_distance(q, pa, pb) <= deviation)
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
    fn a_long_run_keeps_the_corner_a_short_edge_may_drop() {
        // A 10 mm run that turns 0.009 mm aside over its last 0.1 mm: dropping that
        // corner tilts the whole run by the deviation (a sliver 10 mm long).
        let run = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(10.0, 0.0),
            DVec2::new(10.1, 0.009),
        ];
        let p = path(run, false);
        let o = MergeOptions::within(0.01);
        assert_eq!(
            merge_edges(&p, &o).points.len(),
            2,
            "tilted by the deviation"
        );
        let lean = o.with_full_deviation_length(0.4);
        assert_eq!(merge_edges(&p, &lean), p, "the run keeps its corner");
        // A curve's short chords merge as far as without the bound: a circle of
        // 5 mm radius has chords of 2·√(2·5·0.01) ≈ 0.63 mm, longer than 0.4 mm, so
        // they lean less and there are more of them, but not many more.
        let c = path(circle(5.0, 2000), true);
        let (free, bound) = (merge_edges(&c, &o), merge_edges(&c, &lean));
        assert!(within(&c, &bound, 0.01));
        let (n_free, n_bound) = (free.points.len(), bound.points.len());
        assert!(
            n_bound > n_free && n_bound < 2 * n_free,
            "{n_free} -> {n_bound}"
        );
        // A circle of 0.5 mm radius (chords ≈ 0.2 mm) merges the same.
        let small = path(circle(0.5, 400), true);
        assert_eq!(merge_edges(&small, &o), merge_edges(&small, &lean));
    }

    /// An open arc about the origin from angle 0 to `end_rad`, `n` edges, its vertices
    /// turned by `phase` of one edge (so two arcs' vertices need not line up).
    fn arc(r: f64, n: usize, end_rad: f64, phase: f64) -> Vec<DVec2> {
        let step = end_rad / n as f64;
        let mut pts = vec![DVec2::new(r, 0.0)];
        pts.extend((0..n - 1).map(|k| DVec2::from_angle((k as f64 + 0.5 + phase) * step) * r));
        pts.push(DVec2::from_angle(end_rad) * r);
        pts
    }

    /// Where the ray from the origin at angle `t` crosses the polyline, its distance.
    fn radius_at(pts: &[DVec2], t: f64) -> f64 {
        let d = DVec2::from_angle(t);
        pts.windows(2)
            .find_map(|e| {
                let (a, b) = (e[0], e[1]);
                let den = d.perp_dot(b - a);
                let s = d.perp_dot(a) / -den;
                (den != 0.0 && (0.0..=1.0).contains(&s)).then(|| (a + (b - a) * s).length())
            })
            .unwrap_or(f64::NAN)
    }

    #[test]
    fn neighbouring_roads_merge_in_phase() {
        let o = MergeOptions::within(0.01);
        let outer = merge_edges(&path(arc(5.0, 1000, 1.5, 0.0), false), &o);
        let inner = path(arc(4.6, 777, 1.5, 0.37), false);
        let mut stations = Stations::new(0.5);
        stations.add(&outer);
        let alone = merge_edges(&inner, &o);
        let in_phase = merge_edges_in_phase(&inner, &o, &stations);
        assert!(within(&inner, &in_phase, 0.01));
        // The gap between the two roads' centrelines along every ray.
        let spread = |m: &ToolPath| {
            (1..300)
                .map(|k| {
                    let t = 1.5 * k as f64 / 300.0;
                    (radius_at(&outer.points, t) - radius_at(&m.points, t) - 0.4).abs()
                })
                .fold(0.0f64, f64::max)
        };
        let (apart, together) = (spread(&alone), spread(&in_phase));
        assert!(apart > 0.005, "out of phase: the gap varies by {apart}");
        assert!(together < 0.002, "in phase: the gap varies by {together}");
        // No more moves than merged alone, give or take one.
        let (n_alone, n_phase) = (alone.points.len(), in_phase.points.len());
        assert!(n_phase <= n_alone + 1, "{n_alone} -> {n_phase}");
        // No stations: the same as merged alone.
        assert_eq!(merge_edges_in_phase(&inner, &o, &Stations::new(0.5)), alone);
    }

    #[test]
    fn stations_take_bad_reaches_and_points_without_harm() {
        let o = MergeOptions::within(0.01);
        let outer = merge_edges(&path(arc(5.0, 1000, 1.5, 0.0), false), &o);
        let inner = path(arc(4.6, 777, 1.5, 0.37), false);
        let alone = merge_edges(&inner, &o);
        // A reach that is no number, negative or nothing: no stations at all.
        for reach in [f64::NAN, -1.0, 0.0] {
            let mut s = Stations::new(reach);
            s.add(&outer);
            assert_eq!(merge_edges_in_phase(&inner, &o, &s), alone, "{reach}");
        }
        // An endless reach: every vertex is in reach of every edge; still a merge
        // within the deviation.
        let mut s = Stations::new(f64::INFINITY);
        s.add(&outer);
        assert!(within(&inner, &merge_edges_in_phase(&inner, &o, &s), 0.01));
        // A neighbour with vertices that are no numbers: those are no stations.
        let mut bad = outer.clone();
        bad.points[3] = DVec2::new(f64::NAN, 1.0);
        bad.points[4] = DVec2::new(f64::INFINITY, 1.0);
        let mut s = Stations::new(0.5);
        s.add(&bad);
        assert!(within(&inner, &merge_edges_in_phase(&inner, &o, &s), 0.01));
        // A road with a vertex that is no number merges without a panic.
        let mut broken = inner.clone();
        broken.points[10] = DVec2::new(f64::NAN, f64::NAN);
        let mut s = Stations::new(0.5);
        s.add(&outer);
        let _ = merge_edges_in_phase(&broken, &o, &s);
    }

    #[test]
    fn a_straight_road_beside_a_curve_stays_one_move() {
        let o = MergeOptions::within(0.01);
        let curve = merge_edges(&path(arc(5.0, 1000, 1.5, 0.0), false), &o);
        let mut stations = Stations::new(0.5);
        stations.add(&curve);
        // A chord of the curve 0.3 mm inside it, sampled finely.
        let (a, b) = (DVec2::new(4.7, 0.0), DVec2::from_angle(1.5) * 4.7);
        let pts: Vec<DVec2> = (0..=100).map(|k| a.lerp(b, k as f64 / 100.0)).collect();
        let m = merge_edges_in_phase(&path(pts, false), &o, &stations);
        assert_eq!(m.points, vec![a, b]);
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
