//! The equal distance offset of §3.2: every boundary of [`Shapes`] moved by a distance,
//! with round joins ([`offset`]). Tried first: a direct offset whose result is certified
//! (the raw offset of `raw.rs`, swallowtails cut by `swallowtail.rs` and spikes by
//! `spike.rs`); where the certificate fails, i_overlay's outline (through
//! `i_overlay_integration.rs`). Either way the loops are then simplified well inside the
//! chord tolerance. Not booleans or clipping.

mod raw;
mod spike;
mod swallowtail;

use super::i_overlay_integration::outline_round;
use super::{
    boundary_index, first_crossing, loop_bounds, loops, remove_spikes, signed_area2,
    simplify_loop_greedy, SegmentIndex, Shapes,
};
use glam::DVec2;
use raw::raw_offset_loop;
use spike::cut_spike;
use swallowtail::cut_swallowtails;

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
    let mut out = offset_direct(shapes, index, delta_mm, chord_mm)
        .unwrap_or_else(|| outline_round(shapes, delta_mm, arc_angle(delta_mm, chord_mm)));
    for shape in &mut out {
        for l in shape.iter_mut() {
            // Round joins leave runs of micro-edges; later booleans and offsets slow
            // down badly on them. Simplify well inside the chord tolerance, so offsets
            // stay within a few µm of exact (clip margins rely on that).
            *l = simplify_loop_greedy(l, chord_mm / 20.0);
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
    let step = arc_angle(delta_mm, chord_mm);
    let merge_mm = chord_mm / 20.0;
    let (mut out, counter_clockwise) = raw_offset(shapes, delta_mm, step, merge_mm)?;
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
    let certificate = Certificate::new(index, delta_mm.abs(), merge_mm);
    let failed = certificate.uncertified_vertices(&out);
    if failed.is_empty() {
        return Some(out);
    }
    let spiked = cut_uncertified_spikes(&mut out, failed, cut_points, &certificate, delta_mm)?;
    // The cuts keep every loop simple and its orientation (a cut drops a sliver by the
    // apex only), but check both again rather than rely on it.
    (!spiked || simple_and_oriented(&out, &counter_clockwise)).then_some(out)
}

/// Step 1 of [`offset_direct`]: the raw offset of every loop of `shapes`
/// ([`raw_offset_loop`]), shapes and holes the offset swallows whole dropped, with
/// whether each raw loop (in the order of `loops`) runs counter-clockwise. None where a
/// loop has no raw offset or its raw offset turns the other way round.
fn raw_offset(
    shapes: &Shapes,
    delta_mm: f64,
    step: f64,
    merge_mm: f64,
) -> Option<(Shapes, Vec<bool>)> {
    let reach = delta_mm.abs();
    let mut out: Shapes = Vec::with_capacity(shapes.len());
    let mut counter_clockwise = Vec::new();
    'shapes: for shape in shapes {
        let mut loops = Vec::with_capacity(shape.len());
        for (k, l) in shape.iter().enumerate() {
            let a0 = signed_area2(l);
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
            let a1 = signed_area2(&raw);
            if a0 == 0.0 || (a0 > 0.0) != (a1 > 0.0) {
                return None;
            }
            counter_clockwise.push(a0 > 0.0);
            loops.push(raw);
        }
        out.push(loops);
    }
    Some((out, counter_clockwise))
}

/// Step 2 of [`offset_direct`]: the distances a raw vertex must lie at from the source
/// boundary (`index`) to be on the offset.
struct Certificate<'a> {
    index: &'a SegmentIndex,
    /// Nearer than this: off the offset.
    near: f64,
    /// Nearer than this for a swallowtail's or spike's cut point (see
    /// [`Certificate::cut_point_on_offset`]).
    near_cut: f64,
    /// At least one source edge nearer than this.
    far: f64,
}

impl<'a> Certificate<'a> {
    fn new(index: &'a SegmentIndex, reach: f64, merge_mm: f64) -> Self {
        let near = reach * (1.0 - DIRECT_OFFSET_SLACK);
        Certificate {
            index,
            near,
            // A cut point lies on two raw edges, which may be chords of merged joins:
            // those lie up to `merge_mm` nearer the source than the offset distance
            // (the arcs they stand for; see `raw_offset_loop`), and so may a point on
            // them.
            near_cut: near - merge_mm,
            far: far_reach(reach),
        }
    }

    /// The vertices of `raw` not at the offset distance from the source, as (loop
    /// number in the order of `loops`, vertex).
    fn uncertified_vertices(&self, raw: &Shapes) -> Vec<(usize, DVec2)> {
        let mut failed: Vec<(usize, DVec2)> = Vec::new();
        for (li, l) in loops(raw).enumerate() {
            for &p in l {
                if self.index.within_both(p, self.near, self.far) != (false, true) {
                    failed.push((li, p));
                }
            }
        }
        failed
    }

    /// Is the cut point `p` at the offset distance from the source (allowing for the
    /// chords of merged joins)?
    fn cut_point_on_offset(&self, p: DVec2) -> bool {
        self.index.within_both(p, self.near_cut, self.far) == (false, true)
    }
}

/// Step 2 of [`offset_direct`] for the vertices the certificate failed (`failed`): a
/// swallowtail's cut point (in `cut_points`) passes on the cut points' allowance; any
/// other is the apex of a spike, which is cut ([`cut_spike`]) and its cut point
/// certified in turn. None where one is neither; else whether any spike was cut.
fn cut_uncertified_spikes(
    raw: &mut Shapes,
    failed: Vec<(usize, DVec2)>,
    mut cut_points: Vec<DVec2>,
    certificate: &Certificate,
    delta_mm: f64,
) -> Option<bool> {
    let mut spiked = false;
    for (li, p) in failed {
        if cut_points.contains(&p) && certificate.cut_point_on_offset(p) {
            continue;
        }
        let l = raw.iter_mut().flat_map(|s| s.iter_mut()).nth(li)?;
        // Gone with an earlier spike.
        let Some(k) = l.iter().position(|q| *q == p) else {
            continue;
        };
        let x = cut_spike(l, k, delta_mm)?;
        if !certificate.cut_point_on_offset(x) {
            return None;
        }
        cut_points.push(x);
        spiked = true;
    }
    Some(spiked)
}

/// Does every loop of `raw` keep the orientation `counter_clockwise` gives it (in the
/// order of `loops`), with no two edges touching or crossing?
fn simple_and_oriented(raw: &Shapes, counter_clockwise: &[bool]) -> bool {
    let all: Vec<&[DVec2]> = loops(raw).map(|l| l.as_slice()).collect();
    !(all
        .iter()
        .zip(counter_clockwise)
        .any(|(l, ccw)| (signed_area2(l) > 0.0) != *ccw)
        || first_crossing(&all).is_some())
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
    let (lo, hi) = loop_bounds(l);
    (hi - lo).min_element() < 2.0 * reach
}

/// How many swallowtails [`offset_direct`] cuts before leaving the work to the outline.
const MAX_SWALLOWTAIL_CUTS: usize = 64;

/// The outer radius of [`offset_direct`]'s distance certificate for offset distance `reach`.
fn far_reach(reach: f64) -> f64 {
    reach * (1.0 + DIRECT_OFFSET_SLACK)
}

/// Relative slack of the distance certificate of [`offset_direct`]: raw vertices lie at
/// the offset distance from their own edge up to rounding.
const DIRECT_OFFSET_SLACK: f64 = 1e-9;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{area, circle, from_loops};

    /// The outline alone, for comparison with [`offset`]'s shortcut.
    fn outline_only(shapes: &Shapes, delta_mm: f64, chord_mm: f64) -> Shapes {
        outline_round(shapes, delta_mm, arc_angle(delta_mm, chord_mm))
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
            let perimeter: f64 = loops(&shapes).map(|l| crate::geom::loop_length(l)).sum();
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
}
