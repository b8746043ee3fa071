//! Spikes of a raw offset loop: where a swallowtail's edges just miss each other, the
//! apex lies nearer the source than the offset distance; it is cut off where the edge
//! after (or before) the reversed micro-edge crosses the edge the apex ends.

use crate::geom::{next_in_loop, prev_in_loop};
use glam::DVec2;

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
pub(super) fn cut_spike(l: &mut Vec<DVec2>, k: usize, delta_mm: f64) -> Option<DVec2> {
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
