//! Booleans between the areas of [`Shapes`] (non-zero fill): difference, intersection
//! and union through i_overlay, and the difference of nested areas, which needs none
//! ([`nested_difference`]). Not clipping of lines (`clip.rs`).

use super::i_overlay_integration::{overlay, BooleanOp};
use super::{point_in_loop, signed_area, Shapes};
use glam::DVec2;

/// `a` minus `b`.
pub fn difference(a: &Shapes, b: &Shapes) -> Shapes {
    if a.is_empty() || b.is_empty() {
        return a.clone();
    }
    overlay(a, b, BooleanOp::Difference)
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
    let areas: Vec<f64> = outers.iter().map(|l| signed_area(l)).collect();
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
    overlay(a, b, BooleanOp::Intersect)
}

/// `a` or `b`.
pub fn union(a: &Shapes, b: &Shapes) -> Shapes {
    if a.is_empty() {
        return b.clone();
    }
    if b.is_empty() {
        return a.clone();
    }
    overlay(a, b, BooleanOp::Union)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{area, from_loops};

    fn square(h: f64) -> Vec<DVec2> {
        vec![
            DVec2::new(-h, -h),
            DVec2::new(h, -h),
            DVec2::new(h, h),
            DVec2::new(-h, h),
        ]
    }

    #[test]
    fn booleans() {
        let a = from_loops(&[square(5.0)]);
        let b = from_loops(&[square(2.0)]);
        assert!((area(&difference(&a, &b)) - 84.0).abs() < 1e-6);
        assert!((area(&intersection(&a, &b)) - 16.0).abs() < 1e-6);
        assert!((area(&union(&a, &b)) - 100.0).abs() < 1e-6);
    }
}
