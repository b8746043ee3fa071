//! Step 1 of the direct offset: one loop's raw offset, every edge moved to its right and
//! consecutive moved edges joined (mitre where they meet, a round join sampled at the arc
//! step where they part, one point where the join is slight). The raw loop may cross
//! itself; `swallowtail.rs` and `spike.rs` cut what the offset swallows.

use crate::geom::{dedup_loop, loop_edges, prev_in_loop};
use glam::DVec2;

/// Step 1 of [`offset_direct`] for one loop; None where an edge is degenerate or a
/// corner turns back on itself (the mitre would run off far away).
///
/// A join so slight that its arc's midpoint lies within `merge_mm` of both moved edges'
/// lines is that one point (at the offset distance from the corner, as the arc is): the
/// loop then moves by at most `merge_mm` from the round join, inward, where the two arc
/// ends would have been a micro-edge that simplification mostly drops anyway.
pub(super) fn raw_offset_loop(
    l: &[DVec2],
    delta_mm: f64,
    step: f64,
    merge_mm: f64,
) -> Option<Vec<DVec2>> {
    let n = l.len();
    if n < 3 {
        return None;
    }
    // Unit directions of the edges; the right-hand normal of `u` is `-u.perp()`.
    let mut dirs = Vec::with_capacity(n);
    for (a, b) in loop_edges(l) {
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
    let raw = dedup_loop(&raw, 1e-9);
    (raw.len() >= 3).then_some(raw)
}
