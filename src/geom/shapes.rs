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
