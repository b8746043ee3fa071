//! Dropping vertices from closed loops: repeated points ([`dedup_loop`]), vertices whose
//! removal moves the loop by at most a tolerance (Douglas–Peucker, [`simplify_loop`], and
//! the one-pass greedy chords, [`simplify_loop_greedy`]), and zero-area antennae
//! ([`remove_spikes`]). None of them moves a kept vertex.

use super::next_in_loop;
use glam::DVec2;

/// Remove consecutive duplicate points (and a closing duplicate) closer than `eps`.
pub fn dedup_loop(pts: &[DVec2], eps: f64) -> Vec<DVec2> {
    let mut out: Vec<DVec2> = Vec::with_capacity(pts.len());
    // Points clearly farther apart than `eps` (the square of the distance over that of
    // 2 eps) are told apart without the square root.
    let clear2 = 4.0 * eps * eps;
    for &p in pts {
        if out
            .last()
            .is_none_or(|q: &DVec2| q.distance_squared(p) > clear2 || q.distance(p) > eps)
        {
            out.push(p);
        }
    }
    while out.len() > 1 && out[0].distance(out[out.len() - 1]) <= eps {
        out.pop();
    }
    out
}

/// Douglas–Peucker simplification of a closed loop: drop vertices whose removal moves
/// the loop by at most `tolerance_mm`.
pub fn simplify_loop(pts: &[DVec2], tolerance_mm: f64) -> Vec<DVec2> {
    let n = pts.len();
    if n <= 4 || tolerance_mm <= 0.0 {
        return pts.to_vec();
    }
    // Split the loop at vertex 0 and the vertex farthest from it.
    let far = (1..n)
        .max_by(|&a, &b| {
            pts[a]
                .distance_squared(pts[0])
                .total_cmp(&pts[b].distance_squared(pts[0]))
        })
        .unwrap_or(n / 2);
    let mut keep = vec![false; n];
    keep[0] = true;
    keep[far] = true;
    let mut stack = vec![(0usize, far), (far, n)];
    let tolerance2 = tolerance_mm * tolerance_mm;
    while let Some((a, b)) = stack.pop() {
        if b <= a + 1 {
            continue;
        }
        let (pa, pb) = (pts[a], pts[b % n]);
        let mut worst = (0.0, a);
        // The squared `point_segment_distance(p, pa, pb)`, with the chord's terms
        // computed once (and no division or square root per point).
        let ab = pb - pa;
        let len2 = ab.length_squared();
        let inv_len2 = if len2 > 0.0 { 1.0 / len2 } else { 0.0 };
        for (k, p) in pts[a + 1..b].iter().enumerate() {
            let t = ((*p - pa).dot(ab) * inv_len2).clamp(0.0, 1.0);
            let d2 = p.distance_squared(pa + ab * t);
            if d2 > worst.0 {
                worst = (d2, a + 1 + k);
            }
        }
        if worst.0 > tolerance2 {
            keep[worst.1] = true;
            stack.push((a, worst.1));
            stack.push((worst.1, b));
        }
    }
    pts.iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(p, _)| *p)
        .collect()
}

/// Simplification of a closed loop in one pass, with the guarantee of [`simplify_loop`]:
/// every dropped vertex lies within `tolerance_mm` of the chord that replaces it. From
/// each kept vertex the next kept one is the farthest (at most [`GREEDY_RUN`] on) whose
/// chord passes within the tolerance of every vertex between. Where nearly every vertex
/// stays (an offset's moved edges and round joins), that is one chord test per vertex,
/// against Douglas–Peucker's scan of the whole remaining run at every split.
pub fn simplify_loop_greedy(pts: &[DVec2], tolerance_mm: f64) -> Vec<DVec2> {
    let n = pts.len();
    if n <= 4 || tolerance_mm <= 0.0 {
        return pts.to_vec();
    }
    let tol2 = tolerance_mm * tolerance_mm;
    let mut out = Vec::with_capacity(n);
    out.push(pts[0]);
    let mut a = 0;
    while a < n {
        let pa = pts[a];
        // `b`: the farthest end found so far whose chord from `a` holds every vertex
        // between (the next vertex trivially); index `n` is vertex 0 closing the loop.
        let mut b = a + 1;
        while b < n && b - a < GREEDY_RUN {
            let pc = pts[next_in_loop(b, n)];
            if pts[a + 1..=b]
                .iter()
                .all(|&p| chord_within(p, pa, pc, tol2))
            {
                b += 1;
            } else {
                break;
            }
        }
        if b < n {
            out.push(pts[b]);
        }
        a = b;
    }
    out
}

/// How many edges one chord of [`simplify_loop_greedy`] may replace (bounding its cost
/// on long straight runs at n times this).
const GREEDY_RUN: usize = 32;

/// Whether `p` lies within `sqrt(tol2)` of segment `ab`, without a division or square
/// root: the distance to the line first (never more than that to the segment), then to
/// the nearer end where `p` projects beyond one.
fn chord_within(p: DVec2, a: DVec2, b: DVec2, tol2: f64) -> bool {
    let (ab, ap) = (b - a, p - a);
    let len2 = ab.length_squared();
    let cross = ap.perp_dot(ab);
    if cross * cross > tol2 * len2 {
        return false;
    }
    let dot = ap.dot(ab);
    if dot <= 0.0 {
        ap.length_squared() <= tol2
    } else if dot >= len2 {
        p.distance_squared(b) <= tol2
    } else {
        true
    }
}

/// Remove zero-area antennae (the path runs out and straight back) and repeated
/// vertices from a closed loop. The outline builder occasionally leaves such spikes
/// where a join meets an almost straight corner; a road along one would be a needle
/// of material.
pub fn remove_spikes(l: &mut Vec<DVec2>) {
    let mut out: Vec<DVec2> = Vec::with_capacity(l.len());
    for &p in l.iter() {
        push_unspiked(&mut out, p);
    }
    // The loop closes from the last vertex to the first: check across that seam too.
    loop {
        let m = out.len();
        if m < 3 {
            break;
        }
        if is_spike(out[m - 2], out[m - 1], out[0]) {
            out.pop();
        } else if is_spike(out[m - 1], out[0], out[1]) {
            out.remove(0);
        } else {
            break;
        }
    }
    *l = out;
}

fn is_spike(a: DVec2, b: DVec2, c: DVec2) -> bool {
    let (u, v) = (b - a, c - b);
    // Not turning back, between edges clearly longer than the degenerate 1e-12 (their
    // squares above 1e-20): no spike, known without the square roots.
    if u.dot(v) >= 0.0 && u.length_squared() > 1e-20 && v.length_squared() > 1e-20 {
        return false;
    }
    let (lu, lv) = (u.length(), v.length());
    if lu <= 1e-12 || lv <= 1e-12 {
        return true;
    }
    // Turning back by more than about 179.4 degrees.
    u.dot(v) < 0.0 && u.perp_dot(v).abs() <= 1e-2 * lu * lv
}

fn push_unspiked(out: &mut Vec<DVec2>, p: DVec2) {
    out.push(p);
    while out.len() >= 3 {
        let m = out.len();
        if is_spike(out[m - 3], out[m - 2], out[m - 1]) {
            out.remove(m - 2);
        } else {
            break;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{point_loop_distance, signed_area};

    /// A 10 mm square with nine collinear vertices on each of two sides.
    fn square_with_collinear_points() -> Vec<DVec2> {
        let mut l: Vec<DVec2> = (0..10).map(|k| DVec2::new(k as f64, 0.0)).collect();
        l.extend((0..10).map(|k| DVec2::new(10.0, k as f64)));
        l.push(DVec2::new(10.0, 10.0));
        l.push(DVec2::new(0.0, 10.0));
        l
    }

    #[test]
    fn simplify_keeps_corners_drops_collinear() {
        let l = square_with_collinear_points();
        let s = simplify_loop(&l, 1e-6);
        assert_eq!(s.len(), 4, "{s:?}");
        assert!((signed_area(&s) - signed_area(&l)).abs() < 1e-9);
    }

    #[test]
    fn greedy_simplify_keeps_within_tolerance() {
        // The square of `simplify_keeps_corners_drops_collinear`: the corners alone stay.
        let l = square_with_collinear_points();
        let s = simplify_loop_greedy(&l, 1e-6);
        assert_eq!(s.len(), 4, "{s:?}");
        // A wobbly circle: every dropped vertex within the tolerance of the loop left,
        // the vertices kept in order, and some dropped.
        let tol = 0.002;
        let l: Vec<DVec2> = (0..400)
            .map(|k| {
                let t = k as f64 / 400.0 * std::f64::consts::TAU;
                DVec2::from_angle(t) * (5.0 + 0.003 * (7.0 * t).sin() + 0.001 * (53.0 * t).sin())
            })
            .collect();
        let s = simplify_loop_greedy(&l, tol);
        assert!(s.len() < l.len() && s.len() >= 3, "{}", s.len());
        let mut next = 0;
        for p in &s {
            next += l[next..]
                .iter()
                .position(|q| q == p)
                .expect("kept vertex in order")
                + 1;
        }
        for p in &l {
            assert!(point_loop_distance(*p, &s) <= tol * (1.0 + 1e-9), "{p}");
        }
    }

    #[test]
    fn spikes_are_removed() {
        let mut l = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(2.0, 0.0),
            DVec2::new(3.0, 0.0),
            DVec2::new(2.0, 0.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(0.0, 2.0),
        ];
        remove_spikes(&mut l);
        assert_eq!(
            l,
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(2.0, 0.0),
                DVec2::new(2.0, 2.0),
                DVec2::new(0.0, 2.0)
            ]
        );
    }
}
