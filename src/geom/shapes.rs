//! [`Shapes`], polygons with holes as i_overlay returns them (each shape an outer loop,
//! counter-clockwise, then its holes, clockwise), and what needs no overlay: their area,
//! loops, boundary index and containment, shapes from loops that already are a valid
//! even-odd set (the overlay resolves any others), and sampled circles. The algebra on
//! shapes is in `booleans.rs`, `clip.rs` and `offset/`.

use super::i_overlay_integration::even_odd_shapes;
use super::{first_crossing, loop_bounds, point_in_loop, signed_area, SegmentIndex};
use glam::DVec2;

/// Polygons with holes as i_overlay returns them: each shape is an outer loop
/// (counter-clockwise) followed by its holes (clockwise).
pub type Shapes = Vec<Vec<Vec<DVec2>>>;

/// Area of a set of shapes, mm² (holes subtracted).
pub fn area(shapes: &Shapes) -> f64 {
    shapes
        .iter()
        .flat_map(|s| s.iter())
        .map(|l| signed_area(l))
        .sum::<f64>()
}

/// Each loop of `loops` (with its bounds, [`loop_bounds`]) clipped to the box `lo`–`hi`
/// against its four sides in turn (Sutherland–Hodgman), one shape per loop that meets
/// the box: the same area inside the box under the non-zero rule the booleans use (a
/// clipped loop keeps its orientation; where a loop leaves the box and comes back, the
/// clipped loop runs along the box's side and back, a seam of no area the overlay drops).
/// For an overlay that needs only the box's part of a large area: the loops far from
/// the box cost nothing, the long ones only their pieces in it.
pub fn clip_to_box(loops: &[(DVec2, DVec2, &[DVec2])], lo: DVec2, hi: DVec2) -> Shapes {
    let mut out = Vec::new();
    for &(l_lo, l_hi, l) in loops {
        if l_hi.x < lo.x || l_lo.x > hi.x || l_hi.y < lo.y || l_lo.y > hi.y || l.len() < 3 {
            continue;
        }
        if l_lo.x >= lo.x && l_hi.x <= hi.x && l_lo.y >= lo.y && l_hi.y <= hi.y {
            out.push(vec![l.to_vec()]);
            continue;
        }
        let mut ring = l.to_vec();
        // Each side as (axis, bound, keep the side above the bound).
        for (axis, bound, above) in [
            (0, lo.x, true),
            (0, hi.x, false),
            (1, lo.y, true),
            (1, hi.y, false),
        ] {
            ring = clip_ring_to_side(&ring, axis, bound, above);
            if ring.len() < 3 {
                break;
            }
        }
        if ring.len() >= 3 {
            out.push(vec![ring]);
        }
    }
    out
}

/// The closed `ring` cut to the half-plane where coordinate `axis` is at least `bound`
/// (`above`) or at most it.
fn clip_ring_to_side(ring: &[DVec2], axis: usize, bound: f64, above: bool) -> Vec<DVec2> {
    let inside = |p: DVec2| {
        if above {
            p[axis] >= bound
        } else {
            p[axis] <= bound
        }
    };
    let cross = |a: DVec2, b: DVec2| {
        let t = (bound - a[axis]) / (b[axis] - a[axis]);
        let mut p = a.lerp(b, t);
        p[axis] = bound;
        p
    };
    let mut out = Vec::with_capacity(ring.len() + 4);
    let Some(&last) = ring.last() else {
        return out;
    };
    let mut prev = last;
    for &p in ring {
        match (inside(prev), inside(p)) {
            (true, true) => out.push(p),
            (true, false) => out.push(cross(prev, p)),
            (false, true) => {
                out.push(cross(prev, p));
                out.push(p);
            }
            (false, false) => {}
        }
        prev = p;
    }
    out
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

/// Is `p` inside `shapes` (even-odd over all loops; points on a boundary go either way)?
pub fn contains(shapes: &Shapes, p: DVec2) -> bool {
    loops(shapes).filter(|l| point_in_loop(p, l)).count() % 2 == 1
}

/// Clean loops into valid shapes (even-odd: a loop inside another is a hole).
pub fn from_loops(loops: &[Vec<DVec2>]) -> Shapes {
    if loops.is_empty() {
        return Vec::new();
    }
    from_simple_loops(loops).unwrap_or_else(|| even_odd_shapes(loops))
}

/// [`from_loops`] without the overlay, where the loops already are a valid even-odd
/// set (contour level sets, validated region loops): no two edges touch or cross and
/// no loop is degenerate. Each loop is then a hole when an odd number of the others
/// enclose it, oriented as i_overlay orients them (outer loops counter-clockwise,
/// holes clockwise) and put with the smallest loop around it. None where the loops
/// are not such a set; the overlay then resolves them.
fn from_simple_loops(loops: &[Vec<DVec2>]) -> Option<Shapes> {
    let areas: Vec<f64> = loops.iter().map(|l| signed_area(l)).collect();
    if loops
        .iter()
        .zip(&areas)
        .any(|(l, a)| l.len() < 3 || a.is_nan() || a.abs() <= SIMPLE_LOOP_MIN_AREA_MM2)
    {
        return None;
    }
    let all: Vec<&[DVec2]> = loops.iter().map(|l| l.as_slice()).collect();
    if first_crossing(&all).is_some() {
        return None;
    }
    // The loops enclosing each (with no crossing, one vertex tells; a loop whose box
    // does not hold that vertex cannot).
    let boxes: Vec<(DVec2, DVec2)> = loops.iter().map(|l| loop_bounds(l)).collect();
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

#[cfg(test)]
mod tests {
    use super::*;

    fn square(h: f64) -> Vec<DVec2> {
        vec![
            DVec2::new(-h, -h),
            DVec2::new(h, -h),
            DVec2::new(h, h),
            DVec2::new(-h, h),
        ]
    }

    /// The box clip covers what the overlay's intersection with the box covers: a U
    /// that leaves the box and comes back (a seam along the box's side), a hole that
    /// holds the whole box, a loop clear of it, a loop inside it.
    #[test]
    fn a_box_clip_covers_what_the_overlay_intersection_covers() {
        let u = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(6.0, 0.0),
            DVec2::new(6.0, 6.0),
            DVec2::new(4.0, 6.0),
            DVec2::new(4.0, 2.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(2.0, 6.0),
            DVec2::new(0.0, 6.0),
        ];
        let mut hole = square(20.0);
        hole.reverse();
        let sets: Vec<Vec<Vec<DVec2>>> = vec![
            vec![u.clone()],
            vec![square(30.0), hole],
            vec![u.iter().map(|&p| p + DVec2::new(50.0, 0.0)).collect()],
            vec![square(0.5).iter().map(|&p| p + DVec2::splat(3.0)).collect()],
        ];
        let (lo, hi) = (DVec2::new(1.0, 1.0), DVec2::new(5.0, 4.0));
        let rect = vec![vec![lo, DVec2::new(hi.x, lo.y), hi, DVec2::new(lo.x, hi.y)]];
        for loops in sets {
            let with_bounds: Vec<(DVec2, DVec2, &[DVec2])> = loops
                .iter()
                .map(|l| {
                    let (a, b) = loop_bounds(l);
                    (a, b, l.as_slice())
                })
                .collect();
            let clipped = clip_to_box(&with_bounds, lo, hi);
            let shapes: Shapes = loops.iter().map(|l| vec![l.clone()]).collect();
            let want = crate::geom::intersection(&shapes, &vec![rect.clone()]);
            // Resolved by an overlay (a difference with nothing near), as the gap fill
            // does with the beads.
            let far = vec![vec![square(0.1)
                .iter()
                .map(|&p| p + DVec2::splat(90.0))
                .collect()]];
            let got = crate::geom::difference(&clipped, &far);
            assert!(
                (area(&got) - area(&want)).abs() < 1e-9,
                "{got:?} vs {want:?}"
            );
            assert!((area(&clipped) - area(&want)).abs() < 1e-9);
            for p in [
                DVec2::new(3.0, 3.0),
                DVec2::new(1.5, 1.5),
                DVec2::new(4.5, 3.5),
            ] {
                assert_eq!(contains(&got, p), contains(&want, p), "{p}");
            }
        }
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
        let overlay = even_odd_shapes(&loops);
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
}
