//! Exact distances between points, segments and loops, and [`sqrt_within`], which
//! decides a distance against a radius without the square root where it cannot change
//! the answer. Brute force over the segments given: for many queries against many
//! segments, see [`super::SegmentIndex`].

use super::{loop_edges, segments_intersect};
use glam::DVec2;

/// Distance from `p` to the segment `a`–`b`.
pub fn point_segment_distance(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 <= 0.0 {
        return p.distance(a);
    }
    let t = ((p - a).dot(ab) / len2).clamp(0.0, 1.0);
    p.distance(a + ab * t)
}

/// Squared distance from `p` to the segment `a`–`b`: the square of
/// [`point_segment_distance`] before its square root (same projection, same rounding).
pub fn point_segment_distance2(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 <= 0.0 {
        return p.distance_squared(a);
    }
    let t = ((p - a).dot(ab) / len2).clamp(0.0, 1.0);
    p.distance_squared(a + ab * t)
}

/// `d2.sqrt() <= r`, deciding without the square root unless `d2` is within rounding
/// of `r²` (so it answers exactly as the square root would).
#[inline]
pub fn sqrt_within(d2: f64, r: f64) -> bool {
    let r2 = r * r;
    if r >= 0.0 && d2 < r2 * (1.0 - 4.0 * f64::EPSILON) {
        true
    } else if d2 > r2 * (1.0 + 4.0 * f64::EPSILON) {
        false
    } else {
        d2.sqrt() <= r
    }
}

/// Distance between the segments `a`–`b` and `c`–`d` (zero where they touch or cross).
pub fn segment_segment_distance(a: DVec2, b: DVec2, c: DVec2, d: DVec2) -> f64 {
    if segments_intersect(a, b, c, d) {
        return 0.0;
    }
    point_segment_distance(a, c, d)
        .min(point_segment_distance(b, c, d))
        .min(point_segment_distance(c, a, b))
        .min(point_segment_distance(d, a, b))
}

/// Distance from `p` to the closest point of a closed loop's boundary.
pub fn point_loop_distance(p: DVec2, pts: &[DVec2]) -> f64 {
    loop_edges(pts)
        .map(|(a, b)| point_segment_distance(p, a, b))
        .fold(f64::INFINITY, f64::min)
}
