//! The geometric tolerances every planning stage shares, in one place (docs/architecture.md
//! "Units and numbers"). Not the tolerances of single algorithms, which live with them.

use serde::{Deserialize, Serialize};

/// Geometric tolerances, in one place (ARCHITECTURE.md "Units and numbers").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tolerances {
    /// Two points closer than this are the same point, mm.
    pub point_eq_mm: f64,
    /// Loops with less area than this are degenerate, mm².
    pub min_loop_area_mm2: f64,
    /// Chord tolerance when sampling curves (splines, arcs) to polylines, mm.
    pub chord_mm: f64,
    /// Compositions must sum to 1 within this.
    pub composition_sum: f64,
    /// Roads lying on the boundary of the area they are clipped to are kept whole by
    /// clipping against that area grown by this much, mm. A loop farther than this from
    /// every boundary of the area it is clipped to is inside or outside it whole, and is
    /// taken or dropped without running the clipper.
    pub clip_margin_mm: f64,
}

impl Default for Tolerances {
    fn default() -> Self {
        Tolerances {
            point_eq_mm: 1e-9,
            min_loop_area_mm2: 1e-9,
            chord_mm: 0.01,
            composition_sum: 1e-9,
            clip_margin_mm: 1e-3,
        }
    }
}
