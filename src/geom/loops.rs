//! Measures of one closed loop or open polyline: bounding box, signed area (and so
//! orientation: positive counter-clockwise), length, area centroid, and the even-odd
//! point-in-loop test. Not distances (`distance.rs`) nor anything over several loops.

use super::loop_edges;
use glam::DVec2;

/// Axis-aligned bounding box (min, max) of points (infinite and inverted when empty).
pub fn loop_bounds(pts: &[DVec2]) -> (DVec2, DVec2) {
    pts.iter().fold(
        (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}

/// Twice the signed area of a closed loop (positive when counter-clockwise).
pub fn signed_area2(pts: &[DVec2]) -> f64 {
    let n = pts.len();
    if n < 3 {
        return 0.0;
    }
    let mut s = 0.0;
    for (a, b) in loop_edges(pts) {
        s += a.x * b.y - b.x * a.y;
    }
    s
}

/// Signed area of a closed loop, mm² (positive when counter-clockwise).
pub fn signed_area(pts: &[DVec2]) -> f64 {
    0.5 * signed_area2(pts)
}

/// Perimeter of a closed loop, mm.
pub fn loop_length(pts: &[DVec2]) -> f64 {
    let n = pts.len();
    if n < 2 {
        return 0.0;
    }
    loop_edges(pts).map(|(a, b)| a.distance(b)).sum()
}

/// Length of an open polyline, mm.
pub fn polyline_length(pts: &[DVec2]) -> f64 {
    pts.windows(2).map(|w| w[0].distance(w[1])).sum()
}

/// Area centroid of a closed loop (falls back to the vertex mean for zero area).
pub fn centroid(pts: &[DVec2]) -> DVec2 {
    let n = pts.len();
    if n == 0 {
        return DVec2::ZERO;
    }
    let a2 = signed_area2(pts);
    if a2.abs() < 1e-300 {
        return pts.iter().copied().sum::<DVec2>() / n as f64;
    }
    let mut c = DVec2::ZERO;
    for (p, q) in loop_edges(pts) {
        let cross = p.x * q.y - q.x * p.y;
        c += (p + q) * cross;
    }
    c / (3.0 * a2)
}

/// Even-odd point-in-loop test (points on the boundary may go either way).
pub fn point_in_loop(p: DVec2, pts: &[DVec2]) -> bool {
    let n = pts.len();
    let mut inside = false;
    let mut j = n.wrapping_sub(1);
    for i in 0..n {
        let a = pts[i];
        let b = pts[j];
        if (a.y > p.y) != (b.y > p.y) {
            let x = a.x + (p.y - a.y) / (b.y - a.y) * (b.x - a.x);
            if p.x < x {
                inside = !inside;
            }
        }
        j = i;
    }
    inside
}
