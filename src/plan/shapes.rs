//! Thin wrappers over i_overlay for the region algebra the EDO method needs: equal
//! distance offsets of contours (outline with round joins), booleans between the areas
//! enclosed by contours (nested contour levels need none: their difference is their
//! loops, [`nested_difference`]), and clipping of offset loops to a sub-region (which
//! turns a loop cut by the neighbouring contour into the non-continuous segments of
//! Fig. 4(a)).

use crate::geom::{
    loop_edge, next_in_loop, point_in_loop, prev_in_loop, sweep_rank, Crossing, SegmentIndex,
};
use glam::DVec2;
use i_overlay::core::fill_rule::FillRule;
use i_overlay::core::overlay_rule::OverlayRule;
use i_overlay::float::clip::FloatClip;
use i_overlay::float::simplify::SimplifyShape;
use i_overlay::float::single::SingleFloatOverlay;
use i_overlay::mesh::float::outline::offset::OutlineOffset;
use i_overlay::mesh::float::style::{LineJoin, OutlineStyle};
use i_overlay::string::clip::ClipRule;
use serde::{Deserialize, Serialize};

/// Polygons with holes as i_overlay returns them: each shape is an outer loop
/// (counter-clockwise) followed by its holes (clockwise).
pub type Shapes = Vec<Vec<Vec<DVec2>>>;

/// A road centreline: an open polyline, or a closed loop (last vertex joins the first).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Path {
    pub points: Vec<DVec2>,
    pub closed: bool,
}

impl Path {
    pub fn length_mm(&self) -> f64 {
        let open = crate::geom::polyline_length(&self.points);
        if self.closed && self.points.len() > 1 {
            open + self.points[0].distance(self.points[self.points.len() - 1])
        } else {
            open
        }
    }

    /// A loop round less than a line's area is both sides of that line to the printer
    /// (a road out and straight back, a needle of material): a closed road whose mean
    /// width, twice its area over its length, is under `width_mm` becomes the open road
    /// from one of its tips to the other along one side (the two sides lie within
    /// twice that width of each other). Any other road is returned as it is.
    pub fn flattened_if_thinner_than(self, width_mm: f64) -> Path {
        let n = self.points.len();
        if !self.closed || n < 3 {
            return self;
        }
        let length = self.length_mm();
        let area = crate::geom::signed_area(&self.points).abs();
        if !(length > 0.0 && 2.0 * area < width_mm * length) {
            return self;
        }
        // The tips: the vertex farthest from the first, and the one farthest from it
        // (the two ends of the line for a loop this thin).
        let farthest = |from: DVec2| {
            (0..n)
                .max_by(|&a, &b| {
                    from.distance_squared(self.points[a])
                        .total_cmp(&from.distance_squared(self.points[b]))
                })
                .unwrap_or(0)
        };
        let i = farthest(self.points[0]);
        let j = farthest(self.points[i]);
        let steps = (j + n - i) % n;
        Path {
            points: (0..=steps).map(|k| self.points[(i + k) % n]).collect(),
            closed: false,
        }
    }
}

/// Area of a set of shapes, mm² (holes subtracted).
pub fn area(shapes: &Shapes) -> f64 {
    shapes
        .iter()
        .flat_map(|s| s.iter())
        .map(|l| crate::geom::signed_area(l))
        .sum::<f64>()
}

/// All loops of a set of shapes.
pub fn loops(shapes: &Shapes) -> impl Iterator<Item = &Vec<DVec2>> {
    shapes.iter().flat_map(|s| s.iter())
}

/// The edges of every loop of `shapes`, indexed for distance queries.
pub fn boundary_index(shapes: &Shapes) -> SegmentIndex {
    let boundary: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
    SegmentIndex::new(&boundary, &[])
}

/// Clean loops into valid shapes (even-odd: a loop inside another is a hole).
pub fn from_loops(loops: &[Vec<DVec2>]) -> Shapes {
    if loops.is_empty() {
        return Vec::new();
    }
    from_simple_loops(loops).unwrap_or_else(|| loops.to_vec().simplify_shape(FillRule::EvenOdd))
}

/// [`from_loops`] without the overlay, where the loops already are a valid even-odd
/// set (contour level sets, validated region loops): no two edges touch or cross and
/// no loop is degenerate. Each loop is then a hole when an odd number of the others
/// enclose it, oriented as i_overlay orients them (outer loops counter-clockwise,
/// holes clockwise) and put with the smallest loop around it. None where the loops
/// are not such a set; the overlay then resolves them.
fn from_simple_loops(loops: &[Vec<DVec2>]) -> Option<Shapes> {
    let areas: Vec<f64> = loops.iter().map(|l| crate::geom::signed_area(l)).collect();
    if loops
        .iter()
        .zip(&areas)
        .any(|(l, a)| l.len() < 3 || a.is_nan() || a.abs() <= SIMPLE_LOOP_MIN_AREA_MM2)
    {
        return None;
    }
    let all: Vec<&[DVec2]> = loops.iter().map(|l| l.as_slice()).collect();
    if crate::geom::first_crossing(&all).is_some() {
        return None;
    }
    // The loops enclosing each (with no crossing, one vertex tells; a loop whose box
    // does not hold that vertex cannot).
    let boxes: Vec<(DVec2, DVec2)> = loops.iter().map(|l| crate::geom::loop_bounds(l)).collect();
    let around: Vec<Vec<usize>> = (0..loops.len())
        .map(|i| {
            let p = loops[i][0];
            (0..loops.len())
                .filter(|&j| {
                    let (lo, hi) = boxes[j];
                    j != i && p.cmpge(lo).all() && p.cmple(hi).all() && point_in_loop(p, &loops[j])
                })
                .collect()
        })
        .collect();
    let mut out: Shapes = Vec::new();
    let mut shape_of = vec![usize::MAX; loops.len()];
    // Outer loops first (even depth), then each hole with its smallest enclosing loop,
    // which has one depth less and is an outer loop.
    for (i, l) in loops.iter().enumerate() {
        if around[i].len().is_multiple_of(2) {
            let mut l = l.clone();
            if areas[i] < 0.0 {
                l.reverse();
            }
            shape_of[i] = out.len();
            out.push(vec![l]);
        }
    }
    for (i, l) in loops.iter().enumerate() {
        if !around[i].len().is_multiple_of(2) {
            let parent = *around[i]
                .iter()
                .min_by(|a, b| areas[**a].abs().total_cmp(&areas[**b].abs()))?;
            let shape = *shape_of.get(parent)?;
            let mut l = l.clone();
            if areas[i] > 0.0 {
                l.reverse();
            }
            out.get_mut(shape)?.push(l);
        }
    }
    Some(out)
}

/// Loops enclosing less than this (mm²) go through the overlay in [`from_loops`].
const SIMPLE_LOOP_MIN_AREA_MM2: f64 = 1e-9;

/// Round-join arc angle (segment length over radius) giving `chord_mm` sagitta at `radius`.
fn arc_angle(radius: f64, chord_mm: f64) -> f64 {
    let r = radius.abs().max(1e-9);
    (8.0 * chord_mm / r)
        .sqrt()
        .clamp(0.01 * std::f64::consts::PI, 0.25 * std::f64::consts::PI)
}

/// Offset every boundary of `shapes` by `delta_mm` (positive grows the area, negative
/// shrinks it), with round joins: the equal distance offset of §3.2.
pub fn offset(shapes: &Shapes, delta_mm: f64, chord_mm: f64) -> Shapes {
    offset_indexed(shapes, None, delta_mm, chord_mm)
}

/// [`offset`] where the caller already has the [`boundary_index`] of `shapes` (`index`),
/// so the direct offset's distance certificate need not build it again.
pub fn offset_indexed(
    shapes: &Shapes,
    index: Option<&SegmentIndex>,
    delta_mm: f64,
    chord_mm: f64,
) -> Shapes {
    if shapes.is_empty() {
        return Vec::new();
    }
    if delta_mm == 0.0 {
        return shapes.clone();
    }
    let mut out = offset_direct(shapes, index, delta_mm, chord_mm).unwrap_or_else(|| {
        let style =
            OutlineStyle::new(delta_mm).line_join(LineJoin::Round(arc_angle(delta_mm, chord_mm)));
        shapes.outline(&style)
    });
    for shape in &mut out {
        for l in shape.iter_mut() {
            // Round joins leave runs of micro-edges; later booleans and offsets slow
            // down badly on them. Simplify well inside the chord tolerance, so offsets
            // stay within a few µm of exact (clip margins rely on that).
            *l = crate::geom::simplify_loop_greedy(l, chord_mm / 20.0);
            remove_spikes(l);
        }
        shape.retain(|l| l.len() >= 3);
    }
    out.retain(|s| !s.is_empty());
    out
}

/// The offset of [`offset`] without the general outline, where the raw offset already
/// is the answer (the common case of a small step from a smooth contour):
///
/// 1. **Raw offset**: every edge moved `delta_mm` to its right (the material lies left of
///    every loop, outer loops counter-clockwise and holes clockwise), consecutive moved
///    edges cut off where they meet (mitre: exact for the corners the offset turns
///    into) or joined by a round arc about the vertex where they part, sampled as the
///    outline's round join is (a join within chord/20 of a point, that point).
///    An outer loop shrunk or a hole grown past its own width (every point it encloses
///    nearer to it than `|delta_mm|`: [`within_reach_of_itself`]) has no offset; its
///    shape or hole is dropped. Swallowtails are cut off at their crossing
///    ([`cut_swallowtails`]).
/// 2. **Certificate**: the raw loops are the offset's boundary when no two of their
///    edges touch or cross, each keeps the orientation (so the area it bounds) of its
///    source loop, and every raw vertex lies `|delta_mm|` (up to a hair) from the
///    nearest source edge; a swallowtail's cut point, on two raw edges, up to chord/20
///    nearer (where the edges are chords of merged joins). A raw vertex nearer than
///    that is the apex of a spike where a swallowtail's edges just miss each other
///    ([`cut_spike`]), which is cut off as a swallowtail is (its cut point certified
///    in turn). A loop vanishing otherwise, a neck that pinches off or an edge the
///    offset swallows fails one of these, and the caller runs the general outline.
///
/// `index` is the [`boundary_index`] of `shapes` where the caller has it.
fn offset_direct(
    shapes: &Shapes,
    index: Option<&SegmentIndex>,
    delta_mm: f64,
    chord_mm: f64,
) -> Option<Shapes> {
    let reach = delta_mm.abs();
    let step = arc_angle(delta_mm, chord_mm);
    let merge_mm = chord_mm / 20.0;
    let mut out: Shapes = Vec::with_capacity(shapes.len());
    // Whether each raw loop (in the order of `loops(&out)`) runs counter-clockwise.
    let mut counter_clockwise = Vec::new();
    'shapes: for shape in shapes {
        let mut loops = Vec::with_capacity(shape.len());
        for (k, l) in shape.iter().enumerate() {
            let a0 = crate::geom::signed_area2(l);
            // An outer loop shrunk or a hole grown by more than it can take: the shape
            // (all of whose material is inside its outer loop) or the hole vanishes.
            if delta_mm * a0 < 0.0
                && (k == 0) == (a0 > 0.0)
                && within_reach_of_itself(l, 0.5 * a0.abs(), reach)
            {
                if k == 0 {
                    continue 'shapes;
                }
                continue;
            }
            let raw = raw_offset_loop(l, delta_mm, step, merge_mm)?;
            let a1 = crate::geom::signed_area2(&raw);
            if a0 == 0.0 || (a0 > 0.0) != (a1 > 0.0) {
                return None;
            }
            counter_clockwise.push(a0 > 0.0);
            loops.push(raw);
        }
        out.push(loops);
    }
    // Little reversed loops (swallowtails) where the offset swallows a short edge
    // between two corners it turns into are cut off at their crossing; any other
    // crossing leaves the work to the outline.
    let mut cut_points = Vec::new();
    cut_swallowtails(&mut out, &mut cut_points)?;
    let built;
    let index = match index {
        Some(index) => index,
        None => {
            built = boundary_index(shapes);
            &built
        }
    };
    let near = reach * (1.0 - DIRECT_OFFSET_SLACK);
    let far = far_reach(reach);
    let mut failed: Vec<(usize, DVec2)> = Vec::new();
    for (li, l) in loops(&out).enumerate() {
        for &p in l {
            if index.within_both(p, near, far) != (false, true) {
                failed.push((li, p));
            }
        }
    }
    if failed.is_empty() {
        return Some(out);
    }
    // A cut point lies on two raw edges, which may be chords of merged joins: those lie
    // up to `merge_mm` nearer the source than the offset distance (the arcs they stand
    // for; see `raw_offset_loop`), and so may a point on them.
    let near_cut = near - merge_mm;
    let certified = |p: DVec2| index.within_both(p, near_cut, far) == (false, true);
    let mut spiked = false;
    for (li, p) in failed {
        if cut_points.contains(&p) && certified(p) {
            continue;
        }
        let l = out.iter_mut().flat_map(|s| s.iter_mut()).nth(li)?;
        // Gone with an earlier spike.
        let Some(k) = l.iter().position(|q| *q == p) else {
            continue;
        };
        let x = cut_spike(l, k, delta_mm)?;
        if !certified(x) {
            return None;
        }
        cut_points.push(x);
        spiked = true;
    }
    if spiked {
        // The cuts keep every loop simple and its orientation (a cut drops a sliver by
        // the apex only), but check both again rather than rely on it.
        let raw: Vec<&[DVec2]> = loops(&out).map(|l| l.as_slice()).collect();
        if raw
            .iter()
            .zip(&counter_clockwise)
            .any(|(l, ccw)| (crate::geom::signed_area2(l) > 0.0) != *ccw)
            || crate::geom::first_crossing(&raw).is_some()
        {
            return None;
        }
    }
    Some(out)
}

/// Is every point inside loop `l` nearer than `reach` to it (so that an offset moving
/// the loop inward by `reach` leaves nothing of what it encloses)? So where its box is
/// narrower than `2 reach` (a vertical or horizontal line through a point inside meets
/// the loop on both sides of it within the box), or where it encloses less than a disk
/// of radius `reach` (a point `reach` or more from the loop has that disk inside;
/// `area` is what the loop encloses).
fn within_reach_of_itself(l: &[DVec2], area: f64, reach: f64) -> bool {
    if area < std::f64::consts::PI * reach * reach {
        return true;
    }
    let (lo, hi) = crate::geom::loop_bounds(l);
    (hi - lo).min_element() < 2.0 * reach
}

/// Cut the spike of raw loop `l` whose apex is vertex `k`, which lies nearer the source
/// than the offset distance (so is off the offset): a swallowtail whose crossing its
/// edges just miss. The offset turns back sharply at the apex along a reversed
/// micro-edge `b`–`c` (the apex is `b` or `c`), whose ends lie either side of the line
/// of the edge after it (`c`–`d`, the apex `b`) or before it (`a`–`b`, the apex `c`).
/// That line crosses the edge the apex ends, at `x`, outside its own edge (behind `c`,
/// beyond `b`), and the sliver `x`–`b`–`c` lies on the material's side of the loop
/// where the offset shrinks (it is cut off), on the other side where it grows (it is
/// filled in). `b` and `c` become `x`: the apex drops, and the other end now lies on
/// an edge through `x`. Returns `x`, None where vertex `k` is no such apex.
fn cut_spike(l: &mut Vec<DVec2>, k: usize, delta_mm: f64) -> Option<DVec2> {
    let n = l.len();
    if n < 4 {
        return None;
    }
    for apex_is_b in [true, false] {
        let ib = if apex_is_b { k } else { prev_in_loop(k, n) };
        let ic = next_in_loop(ib, n);
        let (a, b, c, d) = (l[prev_in_loop(ib, n)], l[ib], l[ic], l[next_in_loop(ic, n)]);
        let Some(x) = spike_cut_point(a, b, c, d, apex_is_b) else {
            continue;
        };
        // Left of the loop (counter-clockwise) for a shrinking offset.
        if (b - x).perp_dot(c - x) * delta_mm < 0.0 {
            l[ib] = x;
            l.remove(ic);
            return Some(x);
        }
    }
    None
}

/// Where [`cut_spike`] cuts the spike of `a`–`b`–`c`–`d` with the apex `b`
/// (`apex_is_b`) or `c`, if it is one.
fn spike_cut_point(a: DVec2, b: DVec2, c: DVec2, d: DVec2, apex_is_b: bool) -> Option<DVec2> {
    let (u, v, w) = (b - a, c - b, d - c);
    if apex_is_b {
        // Turning back at `b`; `a` and `b` either side of the line of `c`–`d`, which
        // meets `a`–`b` behind `c`.
        let (s0, s1) = (w.perp_dot(a - c), w.perp_dot(b - c));
        let x = a + u * (s0 / (s0 - s1));
        (u.dot(v) < 0.0 && s0 * s1 < 0.0 && (x - c).dot(w) < 0.0).then_some(x)
    } else {
        let (t0, t1) = (u.perp_dot(c - a), u.perp_dot(d - a));
        let x = c + w * (t0 / (t0 - t1));
        (v.dot(w) < 0.0 && t0 * t1 < 0.0 && (x - b).dot(u) > 0.0).then_some(x)
    }
}

/// Cut off every swallowtail of `shapes`, one crossing at a time in the order the sweep
/// of [`crate::geom::first_crossing`] would find them; None where a crossing is not a
/// swallowtail or there are more than [`MAX_SWALLOWTAIL_CUTS`].
///
/// One sweep finds every crossing pair. A cut keeps pieces of the two crossing edges
/// and drops the edges between, so the crossings left are pairs of the first sweep
/// whose edges stay whole, and pairs of the two shortened edges (found by testing
/// them against every edge); the other edges keep their order (a cut loop's edges keep
/// theirs round it), so picking the pair the sweep meets first (by [`sweep_rank`]) is
/// the crossing sweeping the cut loops again would find.
fn cut_swallowtails(shapes: &mut Shapes, cut_points: &mut Vec<DVec2>) -> Option<()> {
    let raw: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
    let Some(mut pending) = crate::geom::crossings(&raw, MAX_PENDING_CROSSINGS) else {
        // Too many to follow.
        return cut_swallowtails_by_sweeping(shapes, cut_points);
    };
    let mut cuts = 0;
    while !pending.is_empty() {
        let all: Vec<&Vec<DVec2>> = loops(shapes).collect();
        let starts = loop_starts(&all);
        let rank = |(l, e): (usize, usize)| {
            let (a, b) = loop_edge(all[l], e);
            sweep_rank(a, b, starts[l] + e)
        };
        let c = *pending
            .iter()
            .min_by_key(|c| (rank(c.second), rank(c.first)))?;
        cuts += 1;
        if cuts > MAX_SWALLOWTAIL_CUTS {
            return None;
        }
        let cut = cut_swallowtail(shapes, &c)?;
        cut_points.push(c.at);
        pending = crossings_after_cut(shapes, &pending, &c, &cut);
    }
    Some(())
}

/// [`cut_swallowtails`] sweeping the loops again after every cut.
fn cut_swallowtails_by_sweeping(shapes: &mut Shapes, cut_points: &mut Vec<DVec2>) -> Option<()> {
    for _ in 0..MAX_SWALLOWTAIL_CUTS {
        let raw: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
        let Some(c) = crate::geom::first_crossing(&raw) else {
            return Some(());
        };
        cut_swallowtail(shapes, &c)?;
        cut_points.push(c.at);
    }
    let raw: Vec<&[DVec2]> = loops(shapes).map(|l| l.as_slice()).collect();
    crate::geom::first_crossing(&raw).is_none().then_some(())
}

/// The first edge number of each loop in the order of all loops' edges.
fn loop_starts(all: &[&Vec<DVec2>]) -> Vec<usize> {
    all.iter()
        .scan(0, |n, l| {
            let start = *n;
            *n += l.len();
            Some(start)
        })
        .collect()
}

/// The crossings of `shapes` after [`cut_swallowtail`] cut crossing `c` (`cut`), given
/// every crossing before (`pending`): see [`cut_swallowtails`].
fn crossings_after_cut(
    shapes: &Shapes,
    pending: &[Crossing],
    c: &Crossing,
    cut: &Cut,
) -> Vec<Crossing> {
    let shortened = cut.shortened();
    let edge = |(l, e): (usize, usize)| {
        if l != cut.loop_index {
            return Some((l, e));
        }
        cut.edge(e)
            .filter(|e| !shortened.contains(e))
            .map(|e| (l, e))
    };
    let mut out: Vec<Crossing> = pending
        .iter()
        .filter(|p| (p.first, p.second) != (c.first, c.second))
        .filter_map(|p| {
            Some(Crossing {
                first: edge(p.first)?,
                second: edge(p.second)?,
                at: p.at,
            })
        })
        .collect();
    let all: Vec<&Vec<DVec2>> = loops(shapes).collect();
    let starts = loop_starts(&all);
    let seg = |(l, e): (usize, usize)| loop_edge(all[l], e);
    for s in shortened {
        let me = (cut.loop_index, s);
        let (a, b) = seg(me);
        let (lo, hi) = (a.min(b), a.max(b));
        let n = all[cut.loop_index].len();
        for (l, pts) in all.iter().enumerate() {
            for e in 0..pts.len() {
                // Itself and its neighbours round the loop (the other shortened edge
                // is one) cannot count.
                if l == cut.loop_index
                    && (e == s || e == next_in_loop(s, n) || next_in_loop(e, n) == s)
                {
                    continue;
                }
                let (p, q) = seg((l, e));
                if p.max(q).cmplt(lo).any() || hi.cmplt(p.min(q)).any() {
                    continue;
                }
                if crate::geom::segments_intersect(a, b, p, q) {
                    let (rs, re) = (
                        sweep_rank(a, b, starts[cut.loop_index] + s),
                        sweep_rank(p, q, starts[l] + e),
                    );
                    let (earlier, later) = if rs < re {
                        ((me, (a, b)), ((l, e), (p, q)))
                    } else {
                        (((l, e), (p, q)), (me, (a, b)))
                    };
                    out.push(Crossing {
                        first: earlier.0,
                        second: later.0,
                        at: crate::geom::crossing_point(
                            later.1 .0,
                            later.1 .1,
                            earlier.1 .0,
                            earlier.1 .1,
                        ),
                    });
                }
            }
        }
    }
    out
}

/// How many crossings [`cut_swallowtails`] follows from one sweep.
const MAX_PENDING_CROSSINGS: usize = 4 * MAX_SWALLOWTAIL_CUTS;

/// What [`cut_swallowtail`] did to its loop: crossing edges `i < j` of a loop of `n`
/// edges, keeping the piece outside them (`outside`: `..=i`, the crossing, `j + 1..`)
/// or between them (the crossing, `i + 1..=j`).
struct Cut {
    loop_index: usize,
    i: usize,
    j: usize,
    outside: bool,
}

impl Cut {
    /// The new number of edge `k` of the cut loop, None where the cut dropped it.
    fn edge(&self, k: usize) -> Option<usize> {
        let (i, j) = (self.i, self.j);
        if self.outside {
            if k <= i {
                Some(k)
            } else if k < j {
                None
            } else {
                Some(k + 1 + i - j)
            }
        } else {
            (i..=j).contains(&k).then(|| k - i)
        }
    }

    /// The new numbers of the two crossing edges, which the cut shortened to the crossing.
    fn shortened(&self) -> [usize; 2] {
        if self.outside {
            [self.i, self.i + 1]
        } else {
            [0, self.j - self.i]
        }
    }
}

/// Cut the loop crossing `c` closes off, if it is a swallowtail: both edges of one loop,
/// at most [`SWALLOWTAIL_EDGES`] apart along it, and the piece between them turning
/// the other way round from the loop. Returns what it cut, None where it did not.
fn cut_swallowtail(shapes: &mut Shapes, c: &Crossing) -> Option<Cut> {
    let ((la, i), (lb, j)) = (c.first, c.second);
    if la != lb {
        return None;
    }
    let (i, j) = (i.min(j), i.max(j));
    let l = shapes.iter_mut().flat_map(|s| s.iter_mut()).nth(la)?;
    let n = l.len();
    let inner = j - i;
    let outer = n - inner;
    let piece: Vec<DVec2> = if inner <= outer {
        std::iter::once(c.at)
            .chain(l[i + 1..=j].iter().copied())
            .collect()
    } else {
        std::iter::once(c.at)
            .chain(l[j + 1..].iter().copied())
            .chain(l[..=i].iter().copied())
            .collect()
    };
    if piece.len() > SWALLOWTAIL_EDGES + 1
        || (crate::geom::signed_area2(&piece) > 0.0) == (crate::geom::signed_area2(l) > 0.0)
    {
        return None;
    }
    let kept: Vec<DVec2> = if inner <= outer {
        l[..=i]
            .iter()
            .copied()
            .chain(std::iter::once(c.at))
            .chain(l[j + 1..].iter().copied())
            .collect()
    } else {
        std::iter::once(c.at)
            .chain(l[i + 1..=j].iter().copied())
            .collect()
    };
    if kept.len() < 3 {
        return None;
    }
    *l = kept;
    Some(Cut {
        loop_index: la,
        i,
        j,
        outside: inner <= outer,
    })
}

/// How many edges a swallowtail [`cut_swallowtail`] cuts may span.
const SWALLOWTAIL_EDGES: usize = 16;

/// How many swallowtails [`offset_direct`] cuts before leaving the work to the outline.
const MAX_SWALLOWTAIL_CUTS: usize = 64;

/// The outer radius of [`offset_direct`]'s distance certificate for offset distance `reach`.
fn far_reach(reach: f64) -> f64 {
    reach * (1.0 + DIRECT_OFFSET_SLACK)
}

/// Relative slack of the distance certificate of [`offset_direct`]: raw vertices lie at
/// the offset distance from their own edge up to rounding.
const DIRECT_OFFSET_SLACK: f64 = 1e-9;

/// Step 1 of [`offset_direct`] for one loop; None where an edge is degenerate or a
/// corner turns back on itself (the mitre would run off far away).
///
/// A join so slight that its arc's midpoint lies within `merge_mm` of both moved edges'
/// lines is that one point (at the offset distance from the corner, as the arc is): the
/// loop then moves by at most `merge_mm` from the round join, inward, where the two arc
/// ends would have been a micro-edge that simplification mostly drops anyway.
fn raw_offset_loop(l: &[DVec2], delta_mm: f64, step: f64, merge_mm: f64) -> Option<Vec<DVec2>> {
    let n = l.len();
    if n < 3 {
        return None;
    }
    // Unit directions of the edges; the right-hand normal of `u` is `-u.perp()`.
    let mut dirs = Vec::with_capacity(n);
    for (a, b) in crate::geom::loop_edges(l) {
        let e = b - a;
        let len = e.length();
        if len <= 1e-12 {
            return None;
        }
        dirs.push(e / len);
    }
    let mut raw = Vec::with_capacity(n + n / 2);
    // Turns certainly below one arc step (their tangent a hair under the step's) are
    // one piece, as `ceil(|turn| / step)` makes them, without the arc tangent.
    let one_piece = step.tan() * (1.0 - 1e-9);
    // The midpoint of a join turning by `t` lies `|delta| (1 - cos(t / 2))` inside the
    // moved edges' lines: within `merge_mm` where `(1 + cos t) / 2 >= (1 - merge_mm /
    // |delta|)²`.
    let keep = (1.0 - merge_mm / delta_mm.abs()).max(0.0);
    let merge_dot = 2.0 * keep * keep - 1.0;
    for k in 0..n {
        let (u0, u1) = (dirs[prev_in_loop(k, n)], dirs[k]);
        let p = l[k];
        let (n0, n1) = (-u0.perp() * delta_mm, -u1.perp() * delta_mm);
        let (cross, dot) = (u0.perp_dot(u1), u0.dot(u1));
        // Does the offset turn into the corner (the moved edges meet) or away from it?
        let meets = cross * delta_mm < 0.0;
        if cross == 0.0 && dot > 0.0 {
            raw.push(p + n1);
        } else if meets {
            if 1.0 + dot <= 1e-6 {
                return None;
            }
            raw.push(p + (n0 + n1) / (1.0 + dot));
        } else if dot > 0.0 && cross.abs() < dot * one_piece {
            if dot >= merge_dot {
                raw.push(p + (n0 + n1) / (2.0 * (1.0 + dot)).sqrt());
            } else {
                raw.push(p + n0);
                raw.push(p + n1);
            }
        } else {
            let turn = cross.atan2(dot);
            let pieces = ((turn.abs() / step).ceil() as usize).max(1);
            raw.push(p + n0);
            for q in 1..pieces {
                raw.push(p + DVec2::from_angle(turn * q as f64 / pieces as f64).rotate(n0));
            }
            raw.push(p + n1);
        }
    }
    let raw = crate::geom::dedup_loop(&raw, 1e-9);
    (raw.len() >= 3).then_some(raw)
}

/// Remove zero-area antennae (the path runs out and straight back) and repeated
/// vertices from a closed loop. The outline builder occasionally leaves such spikes
/// where a join meets an almost straight corner; a road along one would be a needle
/// of material.
pub fn remove_spikes(l: &mut Vec<DVec2>) {
    let mut out: Vec<DVec2> = Vec::with_capacity(l.len());
    for &p in l.iter() {
        push_unspiked(&mut out, p);
    }
    // The loop closes from the last vertex to the first: check across that seam too.
    loop {
        let m = out.len();
        if m < 3 {
            break;
        }
        if is_spike(out[m - 2], out[m - 1], out[0]) {
            out.pop();
        } else if is_spike(out[m - 1], out[0], out[1]) {
            out.remove(0);
        } else {
            break;
        }
    }
    *l = out;
}

fn is_spike(a: DVec2, b: DVec2, c: DVec2) -> bool {
    let (u, v) = (b - a, c - b);
    // Not turning back, between edges clearly longer than the degenerate 1e-12 (their
    // squares above 1e-20): no spike, known without the square roots.
    if u.dot(v) >= 0.0 && u.length_squared() > 1e-20 && v.length_squared() > 1e-20 {
        return false;
    }
    let (lu, lv) = (u.length(), v.length());
    if lu <= 1e-12 || lv <= 1e-12 {
        return true;
    }
    // Turning back by more than about 179.4 degrees.
    u.dot(v) < 0.0 && u.perp_dot(v).abs() <= 1e-2 * lu * lv
}

fn push_unspiked(out: &mut Vec<DVec2>, p: DVec2) {
    out.push(p);
    while out.len() >= 3 {
        let m = out.len();
        if is_spike(out[m - 3], out[m - 2], out[m - 1]) {
            out.remove(m - 2);
        } else {
            break;
        }
    }
}

fn boolean(a: &Shapes, b: &Shapes, rule: OverlayRule) -> Shapes {
    a.overlay(b, rule, FillRule::NonZero)
}

/// `a` minus `b`.
pub fn difference(a: &Shapes, b: &Shapes) -> Shapes {
    if a.is_empty() || b.is_empty() {
        return a.clone();
    }
    boolean(a, b, OverlayRule::Difference)
}

/// `upper` minus `lower` for nested areas: `lower` strictly inside `upper`, their
/// boundaries nowhere near each other (consecutive contour levels further apart than
/// the simplification moves them). The difference is then the loops of both, those of
/// `lower` reversed (its outer loops become holes, its holes islands), each hole with
/// the smallest outer loop around it, and needs no overlay. None where a hole finds no
/// outer loop around it (the areas were not nested after all).
pub fn nested_difference(upper: &Shapes, lower: &Shapes) -> Option<Shapes> {
    let mut outers: Vec<Vec<DVec2>> = Vec::new();
    let mut holes: Vec<Vec<DVec2>> = Vec::new();
    for shape in upper {
        for (k, l) in shape.iter().enumerate() {
            if k == 0 {
                outers.push(l.clone());
            } else {
                holes.push(l.clone());
            }
        }
    }
    for shape in lower {
        for (k, l) in shape.iter().enumerate() {
            let mut r = l.clone();
            r.reverse();
            if k == 0 {
                holes.push(r);
            } else {
                outers.push(r);
            }
        }
    }
    let areas: Vec<f64> = outers.iter().map(|l| crate::geom::signed_area(l)).collect();
    let mut out: Shapes = outers.into_iter().map(|l| vec![l]).collect();
    for h in holes {
        let p = *h.first()?;
        let around = out
            .iter()
            .enumerate()
            .filter(|(_, shape)| point_in_loop(p, &shape[0]))
            .min_by(|(a, _), (b, _)| areas[*a].total_cmp(&areas[*b]))
            .map(|(k, _)| k)?;
        out[around].push(h);
    }
    Some(out)
}

/// `a` and `b`.
pub fn intersection(a: &Shapes, b: &Shapes) -> Shapes {
    if a.is_empty() || b.is_empty() {
        return Vec::new();
    }
    boolean(a, b, OverlayRule::Intersect)
}

/// `a` or `b`.
pub fn union(a: &Shapes, b: &Shapes) -> Shapes {
    if a.is_empty() {
        return b.clone();
    }
    if b.is_empty() {
        return a.clone();
    }
    boolean(a, b, OverlayRule::Union)
}

/// The parts of closed loop `l` strictly inside `by` (or on its boundary when
/// `boundary_included`): the whole loop as one closed path when nothing cuts it, else
/// the open pieces, with the piece through the loop's start vertex joined up.
pub fn clip_loop(l: &[DVec2], by: &Shapes, boundary_included: bool, eps_mm: f64) -> Vec<Path> {
    let rule = ClipRule {
        invert: false,
        boundary_included,
    };
    clip_ring(l, by, rule, eps_mm)
}

/// [`clip_loop`] by any clip rule (`invert` keeps the parts outside `by`).
fn clip_ring(l: &[DVec2], by: &Shapes, rule: ClipRule, eps_mm: f64) -> Vec<Path> {
    if l.len() < 2 || (by.is_empty() && !rule.invert) {
        return Vec::new();
    }
    if by.is_empty() {
        return vec![Path {
            points: l.to_vec(),
            closed: true,
        }];
    }
    let mut ring = l.to_vec();
    ring.push(l[0]);
    let pieces: Vec<Vec<DVec2>> = ring.clip_by(by, FillRule::NonZero, rule);
    stitch_loop_pieces(pieces, crate::geom::loop_length(l), eps_mm)
}

/// An area many loops are clipped to (the inside of some shapes, or their outside),
/// with its boundary indexed: a loop that keeps clear of the boundary lies wholly in
/// or wholly out of the area, and is kept whole or dropped without running the clipper
/// (which would return such a loop whole).
pub struct ClipArea<'a> {
    shapes: &'a Shapes,
    /// The area is the outside of `shapes`.
    outside: bool,
    boundary: SegmentIndex,
    clear_mm: f64,
}

impl<'a> ClipArea<'a> {
    /// The inside of `shapes`. `clear_mm`: how far a loop must stay from the boundary
    /// to be taken whole.
    pub fn inside(shapes: &'a Shapes, clear_mm: f64) -> Self {
        Self::new(shapes, false, clear_mm)
    }

    /// The outside of `shapes`.
    pub fn outside(shapes: &'a Shapes, clear_mm: f64) -> Self {
        Self::new(shapes, true, clear_mm)
    }

    fn new(shapes: &'a Shapes, outside: bool, clear_mm: f64) -> Self {
        ClipArea {
            shapes,
            outside,
            boundary: boundary_index(shapes),
            clear_mm,
        }
    }

    /// The shapes whose inside (or outside) the area is.
    pub fn shapes(&self) -> &Shapes {
        self.shapes
    }

    /// [`clip_loop`] against this area.
    pub fn clip_loop(&self, l: &[DVec2], boundary_included: bool, eps_mm: f64) -> Vec<Path> {
        // With `invert`, i_overlay's `boundary_included` means the opposite: lines on
        // the boundary count as outside the shapes, so as inside the area, when false.
        let rule = ClipRule {
            invert: self.outside,
            boundary_included: boundary_included != self.outside,
        };
        let n = l.len();
        let clear = n >= 3 && self.boundary.clear_of_loop(l, self.clear_mm);
        if !clear {
            return clip_ring(l, self.shapes, rule, eps_mm);
        }
        if contains(self.shapes, l[0]) != self.outside {
            vec![Path {
                points: l.to_vec(),
                closed: true,
            }]
        } else {
            Vec::new()
        }
    }
}

/// Is `p` inside `shapes` (even-odd over all loops; points on a boundary go either way)?
pub fn contains(shapes: &Shapes, p: DVec2) -> bool {
    loops(shapes).filter(|l| point_in_loop(p, l)).count() % 2 == 1
}

/// The parts of open polyline `line` inside `by`.
pub fn clip_polyline(line: &[DVec2], by: &Shapes, boundary_included: bool) -> Vec<Path> {
    if line.len() < 2 || by.is_empty() {
        return Vec::new();
    }
    let rule = ClipRule {
        invert: false,
        boundary_included,
    };
    let pieces: Vec<Vec<DVec2>> = line.to_vec().clip_by(by, FillRule::NonZero, rule);
    pieces
        .into_iter()
        .filter(|p| p.len() >= 2)
        .map(|points| Path {
            points,
            closed: false,
        })
        .collect()
}

/// Join clipped pieces of one loop back together where they meet end to start, and
/// recognise the unclipped loop.
fn stitch_loop_pieces(mut pieces: Vec<Vec<DVec2>>, loop_len: f64, eps: f64) -> Vec<Path> {
    pieces.retain(|p| p.len() >= 2);
    // Join pieces whose end meets another's start (the clipper may split at the seam).
    let mut joined = true;
    while joined && pieces.len() > 1 {
        joined = false;
        'outer: for i in 0..pieces.len() {
            for j in 0..pieces.len() {
                if i == j {
                    continue;
                }
                let (ei, sj) = (pieces[i][pieces[i].len() - 1], pieces[j][0]);
                if ei.distance(sj) <= eps {
                    let tail = pieces.remove(j);
                    let i = if j < i { i - 1 } else { i };
                    pieces[i].extend_from_slice(&tail[1..]);
                    joined = true;
                    break 'outer;
                }
            }
        }
    }
    pieces
        .into_iter()
        .map(|mut points| {
            let n = points.len();
            let closes = n > 3 && points[0].distance(points[n - 1]) <= eps;
            let len = crate::geom::polyline_length(&points);
            if closes && (len - loop_len).abs() <= (loop_len * 1e-6).max(eps * 10.0) {
                points.pop();
                Path {
                    points,
                    closed: true,
                }
            } else {
                Path {
                    points,
                    closed: false,
                }
            }
        })
        .collect()
}

/// A regular polygon approximating a circle at chord tolerance `chord_mm`, counter-clockwise.
pub fn circle(centre: DVec2, radius_mm: f64, chord_mm: f64) -> Vec<DVec2> {
    let r = radius_mm.abs().max(1e-9);
    let step = (2.0 * (1.0 - (chord_mm / r).min(1.0)).acos()).max(1e-3);
    let n = ((std::f64::consts::TAU / step).ceil() as usize).clamp(8, 4096);
    (0..n)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / n as f64;
            centre + r * DVec2::new(a.cos(), a.sin())
        })
        .collect()
}

/// The parts of `roads` at least `clearance_mm` from every segment of `index` (the
/// contour the roads run towards): a piece that comes nearer is cut where it crosses
/// that distance (found by bisection along the edge) and the near part dropped.
pub fn keep_clear_of(
    roads: Vec<Path>,
    index: &crate::geom::SegmentIndex,
    clearance_mm: f64,
) -> Vec<Path> {
    if index.is_empty() {
        return roads;
    }
    // Gathered a hair beyond the clearance, so points a rounding off an edge are
    // still covered.
    let gather_mm = clearance_mm * (1.0 + 1e-6);
    let window_mm = KEEP_CLEAR_WINDOW * clearance_mm;
    let mut near = crate::geom::NearSegments::default();
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

    #[test]
    fn swallowtails_cut_as_sweeping_after_every_cut() {
        // Wavy loops shrunk past the waves' curvature: their raw offsets have several
        // swallowtails. Following the first sweep's crossings cuts them as sweeping
        // again after every cut does.
        let mut cut_some = 0;
        for (k, waves) in [7.0, 23.0, 37.0, 53.0].into_iter().enumerate() {
            for delta in [-0.05, -0.1, -0.2, -0.35] {
                let l: Vec<DVec2> = (0..300)
                    .map(|q| {
                        let t = q as f64 / 300.0 * std::f64::consts::TAU;
                        let r = 3.0 + 0.04 * (waves * t).sin() + 0.01 * k as f64 * (3.0 * t).cos();
                        DVec2::from_angle(t) * r
                    })
                    .collect();
                let Some(raw) = raw_offset_loop(&l, delta, arc_angle(delta, 0.01), 0.0005) else {
                    continue;
                };
                let uncut: Shapes = vec![vec![raw]];
                let (mut fast, mut slow) = (uncut.clone(), uncut.clone());
                let (mut fast_cuts, mut slow_cuts) = (Vec::new(), Vec::new());
                let fast_ok = cut_swallowtails(&mut fast, &mut fast_cuts).is_some();
                let slow_ok = cut_swallowtails_by_sweeping(&mut slow, &mut slow_cuts).is_some();
                assert_eq!(fast_ok, slow_ok, "waves {waves} delta {delta}");
                if slow_ok {
                    assert_eq!(fast, slow, "waves {waves} delta {delta}");
                    assert_eq!(fast_cuts, slow_cuts, "waves {waves} delta {delta}");
                    cut_some += usize::from(slow != uncut);
                }
            }
        }
        assert!(cut_some > 0);
    }

    /// The outline alone, for comparison with [`offset`]'s shortcut.
    fn outline_only(shapes: &Shapes, delta_mm: f64, chord_mm: f64) -> Shapes {
        let style =
            OutlineStyle::new(delta_mm).line_join(LineJoin::Round(arc_angle(delta_mm, chord_mm)));
        shapes.outline(&style)
    }

    #[test]
    fn the_direct_offset_agrees_with_the_outline_on_awkward_shapes() {
        // A dumbbell (its neck pinches off when shrunk), a star (concave corners), and
        // a plate with a small hole (which vanishes when grown), each offset both ways
        // by small and large steps: same area (within the chord tolerance along the
        // boundary) and the same number of loops.
        let dumbbell = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(4.0, 0.0),
            DVec2::new(4.0, 1.8),
            DVec2::new(6.0, 1.8),
            DVec2::new(6.0, 0.0),
            DVec2::new(10.0, 0.0),
            DVec2::new(10.0, 4.0),
            DVec2::new(6.0, 4.0),
            DVec2::new(6.0, 2.2),
            DVec2::new(4.0, 2.2),
            DVec2::new(4.0, 4.0),
            DVec2::new(0.0, 4.0),
        ];
        let star: Vec<DVec2> = (0..10)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / 10.0;
                let r = if k % 2 == 0 { 5.0 } else { 2.0 };
                DVec2::new(a.cos(), a.sin()) * r
            })
            .collect();
        let mut hole: Vec<DVec2> = circle(DVec2::new(0.0, 0.0), 0.3, 0.01);
        if crate::geom::signed_area2(&hole) > 0.0 {
            hole.reverse();
        }
        let plate = vec![square(3.0), hole];
        let chord = 0.01;
        for shape in [vec![dumbbell], vec![star], plate] {
            let shapes = vec![shape];
            let perimeter: f64 = loops(&shapes)
                .map(|l| crate::geom::polyline_length(l) + l[0].distance(l[l.len() - 1]))
                .sum();
            for delta in [-0.5, -0.15, 0.05, 0.4, 1.0] {
                let fast = offset(&shapes, delta, chord);
                let slow = outline_only(&shapes, delta, chord);
                let (a, b) = (area(&fast), area(&slow));
                assert!(
                    (a - b).abs() <= 2.0 * chord * (perimeter + 2.0 * std::f64::consts::PI),
                    "delta {delta}: {a} against {b}"
                );
                let count = |s: &Shapes| loops(s).filter(|l| l.len() >= 3).count();
                assert_eq!(count(&fast), count(&slow), "delta {delta}");
            }
        }
    }

    /// A loop drawn as a turtle walks: from `start` heading `heading_deg`, each step a
    /// length and then a turn (degrees, left positive); the last step need not close.
    fn turtle(start: DVec2, heading_deg: f64, steps: &[(f64, f64)]) -> Vec<DVec2> {
        let mut out = vec![start];
        let (mut p, mut heading) = (start, heading_deg.to_radians());
        for (len, turn) in steps {
            p += DVec2::from_angle(heading) * *len;
            out.push(p);
            heading += turn.to_radians();
        }
        out
    }

    /// A box whose top, traversed from right to left, has the corners `top` (a length
    /// and a turn at its end, as [`turtle`] takes them) from `(6, 0)`: an outer loop
    /// with the top's features and plain right-angled corners far below them.
    fn box_with_top(top: &[(f64, f64)]) -> Vec<DVec2> {
        let mut l = turtle(DVec2::new(6.0, 0.0), 180.0, top);
        let end = *l.last().unwrap_or(&DVec2::ZERO);
        l.push(DVec2::new(end.x, -6.0));
        l.push(DVec2::new(6.0, -6.0));
        l
    }

    /// `shapes` mirrored in the y axis (so their corners come in the opposite order
    /// round each loop), loops reversed to keep their orientation.
    fn mirrored(shapes: &Shapes) -> Shapes {
        shapes
            .iter()
            .map(|s| {
                s.iter()
                    .map(|l| l.iter().rev().map(|p| DVec2::new(-p.x, p.y)).collect())
                    .collect()
            })
            .collect()
    }

    /// The direct offset of `shapes` succeeds and is the outline's: as many loops, and
    /// every vertex of either within `chord` of the other's boundary (round joins are
    /// sampled within `chord` of their arcs, each offset's own way).
    fn direct_agrees_with_the_outline(shapes: &Shapes, delta: f64, chord: f64) {
        let Some(direct) = offset_direct(shapes, None, delta, chord) else {
            panic!("delta {delta}: the direct offset falls back");
        };
        let source = boundary_index(shapes);
        for p in loops(&direct).flat_map(|l| l.iter()) {
            let off = source.distance(*p) - delta.abs();
            assert!(
                off.abs() <= chord / 20.0,
                "delta {delta}: {p} is {off} off the offset"
            );
        }
        let slow = outline_only(shapes, delta, chord);
        assert_eq!(
            loops(&direct).count(),
            loops(&slow).count(),
            "delta {delta}"
        );
        for (a, b) in [(&direct, &slow), (&slow, &direct)] {
            let index = boundary_index(b);
            for p in loops(a).flat_map(|l| l.iter()) {
                let d = index.distance(*p);
                assert!(d <= chord, "delta {delta}: {p} is {d} off");
            }
        }
    }

    #[test]
    fn the_direct_offset_cuts_spikes_a_reversed_micro_edge_leaves() {
        // Shrunk, a long edge, a slight concave corner (a merged join), a micro-edge and
        // a convex corner that swallows it: the micro-edge's reversed offset backs up
        // along the first edge's, so their neighbours just miss each other, leaving a
        // spike a few µm nearer the contour than the offset distance (as on the bench
        // layer). Mirrored, the spike's apex comes after the micro-edge; as a hole's
        // offset grown, the spike is a notch.
        for (concave, micro, convex, delta) in [
            (-5.26, 0.0163, 23.9, -0.3781871527632471),
            (-4.59, 0.07222, 25.33, -0.40823597436488307),
            (-4.78, 0.0474, 21.03, -0.3939965441889213),
            (-2.64, 0.02797, 18.64, -0.3781871527632471),
        ] {
            let outer = box_with_top(&[(3.0, concave), (micro, convex), (3.0, 70.0)]);
            let shapes = vec![vec![outer.clone()]];
            direct_agrees_with_the_outline(&shapes, delta, 0.01);
            direct_agrees_with_the_outline(&mirrored(&shapes), delta, 0.01);
            let hole: Vec<DVec2> = outer.iter().rev().copied().collect();
            let plate = vec![vec![square(12.0), hole]];
            direct_agrees_with_the_outline(&plate, -delta, 0.01);
            direct_agrees_with_the_outline(&mirrored(&plate), -delta, 0.01);
        }
    }

    #[test]
    fn the_direct_offset_takes_swallowtail_cuts_on_merged_joins() {
        // A swallowtail whose crossing edges end at merged (slight concave) joins: the
        // cut lies on their chords, a fraction of a nanometre nearer the contour than
        // the offset distance.
        let outer = box_with_top(&[
            (1.0, -1.54),
            (2.75518, 1.40),
            (0.11715, 42.32),
            (1.43724, -3.54),
            (2.0, 60.0),
        ]);
        let shapes = vec![vec![outer]];
        direct_agrees_with_the_outline(&shapes, -0.4050949499850493, 0.01);
        direct_agrees_with_the_outline(&mirrored(&shapes), -0.4050949499850493, 0.01);
    }

    #[test]
    fn the_direct_offset_drops_loops_the_offset_swallows_whole() {
        // A sliver (as on the bench layer: 18 µm by 2 µm) next to a plate, shrunk: the
        // sliver vanishes. A plate with a sliver of a hole and a small round one,
        // grown: both holes fill in.
        let sliver = vec![
            DVec2::new(-0.016378598648691067, -0.08374670477683033),
            DVec2::new(-0.01647956891694058, -0.08424702616507496),
            DVec2::new(-0.01215149684586514, -0.10144916506583179),
            DVec2::new(-0.011678295570993313, -0.0993553134995171),
        ];
        let apart = |l: &[DVec2], by: DVec2| -> Vec<DVec2> { l.iter().map(|p| *p + by).collect() };
        let shapes = vec![
            vec![apart(&square(2.0), DVec2::new(5.0, 0.0))],
            vec![sliver.clone()],
        ];
        direct_agrees_with_the_outline(&shapes, -0.40860941437999504, 0.01);
        let mut hole: Vec<DVec2> = sliver.iter().rev().copied().collect();
        let mut round: Vec<DVec2> = circle(DVec2::new(1.5, 1.5), 0.3, 0.01);
        if crate::geom::signed_area2(&round) > 0.0 {
            round.reverse();
        }
        hole = apart(&hole, DVec2::new(-1.0, 0.0));
        let plate = vec![vec![square(3.0), hole, round]];
        direct_agrees_with_the_outline(&plate, 0.4, 0.01);
        // Grown a little, the round hole stays (and the sliver still fills in).
        let grown = offset_direct(&plate, None, 0.1, 0.01).map(|s| loops(&s).count());
        assert_eq!(grown, Some(2));
    }

    fn square(h: f64) -> Vec<DVec2> {
        vec![
            DVec2::new(-h, -h),
            DVec2::new(h, -h),
            DVec2::new(h, h),
            DVec2::new(-h, h),
        ]
    }

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

    #[test]
    fn offset_shrinks_and_grows() {
        let s = from_loops(&[square(5.0)]);
        assert!((area(&s) - 100.0).abs() < 1e-6);
        let inner = offset(&s, -1.0, 0.001);
        assert!((area(&inner) - 64.0).abs() < 1e-3, "{}", area(&inner));
        let outer = offset(&s, 1.0, 0.001);
        // 10x10 plus four 10x1 strips plus a unit circle.
        let want = 100.0 + 40.0 + std::f64::consts::PI;
        assert!((area(&outer) - want).abs() < 0.01, "{}", area(&outer));
    }

    #[test]
    fn clipping_a_loop_keeps_it_closed_or_cuts_it() {
        let by = from_loops(&[square(5.0)]);
        let inside = clip_loop(&square(2.0), &by, false, 1e-6);
        assert_eq!(inside.len(), 1);
        assert!(inside[0].closed);
        assert!((inside[0].length_mm() - 16.0).abs() < 1e-6);
        // A loop straddling the right edge keeps its left part as one open piece.
        let shifted: Vec<DVec2> = square(2.0)
            .iter()
            .map(|p| *p + DVec2::new(4.0, 0.0))
            .collect();
        let cut = clip_loop(&shifted, &by, false, 1e-6);
        assert_eq!(cut.len(), 1, "{cut:?}");
        assert!(!cut[0].closed);
        assert!(
            (cut[0].length_mm() - 10.0).abs() < 1e-6,
            "{}",
            cut[0].length_mm()
        );
    }

    #[test]
    fn clip_area_takes_clear_loops_whole_like_the_clipper() {
        let ring = difference(&from_loops(&[square(5.0)]), &from_loops(&[square(1.0)]));
        let area = ClipArea::inside(&ring, 1e-3);
        let shift = |l: Vec<DVec2>, d: DVec2| -> Vec<DVec2> { l.iter().map(|p| *p + d).collect() };
        let probes = [
            square(3.0),                              // inside, around the hole
            shift(square(0.5), DVec2::new(3.0, 3.0)), // inside, away from the hole
            square(0.5),                              // in the hole
            shift(square(0.5), DVec2::new(9.0, 0.0)), // outside
            shift(square(2.0), DVec2::new(4.0, 0.0)), // cut by the outer edge
            square(1.0),                              // on the hole's edge
        ];
        for l in &probes {
            assert_eq!(
                area.clip_loop(l, false, 1e-6),
                clip_loop(l, &ring, false, 1e-6),
                "{l:?}"
            );
        }
        // Inside the outer square, the ring is the outside of the hole.
        let hole = from_loops(&[square(1.0)]);
        let outside_hole = ClipArea::outside(&hole, 1e-3);
        for l in probes
            .iter()
            .filter(|l| l.iter().all(|p| p.abs().max_element() < 5.0))
        {
            let (got, want) = (
                outside_hole.clip_loop(l, false, 1e-6),
                clip_loop(l, &ring, false, 1e-6),
            );
            assert_eq!(got.len(), want.len(), "{l:?}");
            for (g, w) in got.iter().zip(&want) {
                assert_eq!(g.closed, w.closed);
                assert!((g.length_mm() - w.length_mm()).abs() < 1e-6, "{l:?}");
            }
        }
    }

    #[test]
    fn spikes_are_removed() {
        let mut l = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(2.0, 0.0),
            DVec2::new(3.0, 0.0),
            DVec2::new(2.0, 0.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(0.0, 2.0),
        ];
        remove_spikes(&mut l);
        assert_eq!(
            l,
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(2.0, 0.0),
                DVec2::new(2.0, 2.0),
                DVec2::new(0.0, 2.0)
            ]
        );
    }

    #[test]
    fn simple_loops_become_shapes_as_the_overlay_makes_them() {
        let shifted =
            |l: Vec<DVec2>, d: DVec2| -> Vec<DVec2> { l.into_iter().map(|p| p + d).collect() };
        let mut cw = square(3.0);
        cw.reverse();
        // An outer loop (clockwise as given), a hole in it, an island in the hole, and a
        // second outer loop beside it.
        let loops = vec![
            cw,
            square(2.0),
            square(1.0),
            shifted(square(1.0), DVec2::new(10.0, 0.0)),
        ];
        let direct = from_simple_loops(&loops).expect("a valid even-odd set");
        let overlay = loops.clone().simplify_shape(FillRule::EvenOdd);
        assert_eq!(direct.len(), 3);
        assert_eq!(overlay.len(), 3);
        assert!((area(&direct) - area(&overlay)).abs() < 1e-9);
        assert!((area(&direct) - (36.0 - 16.0 + 4.0 + 4.0)).abs() < 1e-9);
        for shape in &direct {
            assert!(crate::geom::signed_area(&shape[0]) > 0.0);
            for hole in &shape[1..] {
                assert!(crate::geom::signed_area(hole) < 0.0);
            }
        }
        assert_eq!(
            direct.iter().map(|s| s.len()).collect::<Vec<_>>(),
            vec![2, 1, 1]
        );
        // Crossing or degenerate loops are left to the overlay, which resolves them.
        let crossing = vec![square(2.0), shifted(square(2.0), DVec2::new(1.0, 0.0))];
        assert!(from_simple_loops(&crossing).is_none());
        // Even-odd: the overlap of the two squares is left out.
        assert!((area(&from_loops(&crossing)) - 8.0).abs() < 1e-6);
        let flat = vec![vec![DVec2::ZERO, DVec2::X, DVec2::X * 2.0]];
        assert!(from_simple_loops(&flat).is_none());
    }

    #[test]
    fn booleans() {
        let a = from_loops(&[square(5.0)]);
        let b = from_loops(&[square(2.0)]);
        assert!((area(&difference(&a, &b)) - 84.0).abs() < 1e-6);
        assert!((area(&intersection(&a, &b)) - 16.0).abs() < 1e-6);
        assert!((area(&union(&a, &b)) - 100.0).abs() < 1e-6);
    }

    #[test]
    fn loops_round_a_line_are_printed_once_along_it() {
        let v = |x: f64, y: f64| DVec2::new(x, y);
        // A femur layer 110 contour piece: 0.39 mm out and back, 3 um apart.
        let sliver = Path {
            points: vec![
                v(-36.8034, 17.6064),
                v(-36.8044, 17.6088),
                v(-36.6469, 17.2519),
            ],
            closed: true,
        };
        let line = sliver.clone().flattened_if_thinner_than(0.025);
        assert!(!line.closed);
        assert_eq!(line.points.len(), 3);
        // From one tip to the other, never turning back.
        let (first, last) = (line.points[0], line.points[2]);
        assert!((first.distance(last) - 0.3903).abs() < 1e-3, "{line:?}");
        let (u, w) = (line.points[1] - first, last - line.points[1]);
        assert!(u.dot(w) > 0.0, "{line:?}");
        // A thin loop of many vertices: one side of it, tip to tip.
        let mut thin: Vec<DVec2> = (0..=10).map(|i| v(i as f64 * 0.1, 0.0)).collect();
        thin.extend((1..10).rev().map(|i| v(i as f64 * 0.1, 0.01)));
        let line = Path {
            points: thin.clone(),
            closed: true,
        }
        .flattened_if_thinner_than(0.025);
        assert!(!line.closed);
        assert!(
            (line.length_mm() - 1.0).abs() < 0.01,
            "{}",
            line.length_mm()
        );
        // Wider than the limit, or open: unchanged.
        let kept = Path {
            points: thin.iter().map(|p| v(p.x, p.y * 4.0)).collect(),
            closed: true,
        };
        assert_eq!(kept.clone().flattened_if_thinner_than(0.025), kept);
        let open = Path {
            points: thin,
            closed: false,
        };
        assert_eq!(open.clone().flattened_if_thinner_than(0.025), open);
        let ring = Path {
            points: square(1.0),
            closed: true,
        };
        assert_eq!(ring.clone().flattened_if_thinner_than(0.025), ring);
    }
}
