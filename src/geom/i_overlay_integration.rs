//! The adapter to i_overlay: every call geom makes into it, each a plain function on
//! [`Shapes`] and point lists, so nothing else here depends on its traits, rules or
//! styles. Booleans and even-odd resolution of loops, the round-joined outline, and the
//! clipping of lines. No geometry of its own.

use super::Shapes;
use glam::DVec2;
use i_overlay::core::fill_rule::FillRule;
use i_overlay::core::overlay_rule::OverlayRule;
use i_overlay::float::clip::FloatClip;
use i_overlay::float::overlay::OverlayOptions;
use i_overlay::float::simplify::SimplifyShape;
use i_overlay::float::single::SingleFloatOverlay;
use i_overlay::mesh::float::outline::offset::OutlineOffset;
use i_overlay::mesh::float::style::{LineJoin, OutlineStyle};
use i_overlay::string::clip::ClipRule;

/// Which boolean [`overlay`] takes.
#[derive(Clone, Copy, Debug)]
pub(super) enum BooleanOp {
    Difference,
    Intersect,
    Union,
}

/// `a` combined with `b` by `op`, both filled non-zero.
pub(super) fn overlay(a: &Shapes, b: &Shapes, op: BooleanOp) -> Shapes {
    let rule = match op {
        BooleanOp::Difference => OverlayRule::Difference,
        BooleanOp::Intersect => OverlayRule::Intersect,
        BooleanOp::Union => OverlayRule::Union,
    };
    a.overlay(b, rule, FillRule::NonZero)
}

/// The shapes `loops` enclose under the even-odd rule (a loop inside another is a hole).
pub(super) fn even_odd_shapes(loops: &[Vec<DVec2>]) -> Shapes {
    loops.to_vec().simplify_shape(FillRule::EvenOdd)
}

/// [`even_odd_shapes`] of `loops`, dropping loops of less than `min_area_mm2` and
/// writing the result in i_overlay's OGC form (the slicer's resolution of a layer whose
/// loops fold over themselves).
pub(crate) fn even_odd_shapes_ogc(loops: &[Vec<DVec2>], min_area_mm2: f64) -> Shapes {
    let contours: Vec<Vec<[f64; 2]>> = loops
        .iter()
        .map(|l| l.iter().map(|p| [p.x, p.y]).collect())
        .collect();
    let mut options = OverlayOptions::<f64>::default();
    options.ogc = true;
    options.min_output_area = min_area_mm2;
    let shapes = contours.simplify_shape_custom(
        FillRule::EvenOdd,
        options,
        i_overlay::core::solver::Solver::default(),
    );
    shapes
        .into_iter()
        .map(|shape| {
            shape
                .into_iter()
                .map(|c| c.into_iter().map(|[x, y]| DVec2::new(x, y)).collect())
                .collect()
        })
        .collect()
}

/// i_overlay's outline of `shapes` offset by `delta_mm` (positive grows the area), with
/// round joins sampled at `arc_angle` radians a segment.
pub(super) fn outline_round(shapes: &Shapes, delta_mm: f64, arc_angle: f64) -> Shapes {
    let style = OutlineStyle::new(delta_mm).line_join(LineJoin::Round(arc_angle));
    shapes.outline(&style)
}

/// The pieces of the polyline `line` inside `by` (filled non-zero), or outside it where
/// `invert`; lines on the boundary count as inside where `boundary_included` (with
/// `invert`, i_overlay reads it the other way: as outside the shapes).
pub(super) fn clip_lines(
    line: Vec<DVec2>,
    by: &Shapes,
    invert: bool,
    boundary_included: bool,
) -> Vec<Vec<DVec2>> {
    let rule = ClipRule {
        invert,
        boundary_included,
    };
    line.clip_by(by, FillRule::NonZero, rule)
}
