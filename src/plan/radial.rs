//! The paper's pre-subdivision (§3.1): radial lines from the geometric centre of Ci at
//! equal angular division, each divided into m segments (m from eq (1)), and closed
//! spline contours C2..Cm through the corresponding division points.
//!
//! Steps:
//! 1. Centre: the centroid of the single hole (Ci), or of the outer loop when there is
//!    no hole (growth rings about a point), else the pole of inaccessibility.
//! 2. Star-shape test: every radial line must cross Ci once and Ce once, which holds
//!    exactly when every edge of both loops turns the same way about the centre.
//! 3. Radial lines: the Ci and Ce crossings of each line; L_short is the shortest
//!    Ci-to-Ce length, and eq (1) gives m.
//! 4. Division points at `r_i + (j − 1) / m · (r_e − r_i)` and a periodic centripetal
//!    Catmull-Rom spline (interpolating, no cusps) through them, sampled at the chord
//!    tolerance.
//! 5. Check the contours cross neither each other nor the boundaries; the caller falls
//!    back to the distance method (or refuses, if radial was asked for) when they do.

use crate::geom::{
    first_crossing, loop_edges, next_in_loop, point_in_loop, prev_in_loop, signed_area2,
};
use glam::DVec2;

/// Why the radial method cannot subdivide a region.
#[derive(Debug, Clone, PartialEq)]
pub enum RadialFailure {
    /// More than one hole: there is no single Ci centre.
    SeveralHoles(usize),
    /// Some radial line from the centre leaves the region (not star-shaped).
    NotStarShaped { centre: DVec2 },
    /// The spline contours cross each other or a boundary even at the finest division.
    ContoursCross,
}

/// The radial subdivision of one region.
#[derive(Debug, Clone)]
pub struct RadialSubdivision {
    pub centre: DVec2,
    pub l_short_mm: f64,
    /// Number of radial lines used.
    pub lines: usize,
    /// Ci and Ce crossing radii of each radial line.
    pub radii: Vec<(f64, f64)>,
}

/// Is the closed loop star-shaped about `c` (every edge turns strictly the same way)?
pub fn is_star_about(l: &[DVec2], c: DVec2) -> bool {
    let n = l.len();
    if n < 3 {
        return false;
    }
    let sign = signed_area2(l).signum();
    loop_edges(l).all(|(a, b)| (a - c).perp_dot(b - c) * sign > 0.0)
}

/// Distance from `c` along each of `k` equally spaced rays (angle 2πi/k) to the loop,
/// which must be star-shaped about `c`.
fn ray_radii(l: &[DVec2], c: DVec2, k: usize) -> Vec<f64> {
    let mut pts: Vec<DVec2> = l.to_vec();
    if signed_area2(&pts) < 0.0 {
        pts.reverse();
    }
    let step = std::f64::consts::TAU / k as f64;
    let mut out = vec![f64::NAN; k];
    let angle = |p: DVec2| (p - c).y.atan2((p - c).x).rem_euclid(std::f64::consts::TAU);
    for (a, b) in loop_edges(&pts) {
        let (ta, mut tb) = (angle(a), angle(b));
        if tb < ta {
            tb += std::f64::consts::TAU;
        }
        let first = (ta / step).ceil() as i64;
        let last = (tb / step).ceil() as i64 - 1;
        for q in first..=last {
            let theta = q as f64 * step;
            let dir = DVec2::new(theta.cos(), theta.sin());
            let e = b - a;
            let den = dir.perp_dot(e);
            if den.abs() < 1e-300 {
                continue;
            }
            let r = (a - c).perp_dot(e) / den;
            out[q.rem_euclid(k as i64) as usize] = r;
        }
    }
    // Rays through a vertex exactly, missed by rounding: intersect with every edge.
    for (q, slot) in out.iter_mut().enumerate() {
        if slot.is_nan() {
            let theta = q as f64 * step;
            let dir = DVec2::new(theta.cos(), theta.sin());
            let mut best = f64::INFINITY;
            for (a, b) in loop_edges(&pts) {
                let e = b - a;
                let den = dir.perp_dot(e);
                if den.abs() < 1e-300 {
                    continue;
                }
                let r = (a - c).perp_dot(e) / den;
                let s = (a - c).perp_dot(dir) / den;
                if r >= 0.0 && (-1e-9..=1.0 + 1e-9).contains(&s) {
                    best = best.min(r);
                }
            }
            *slot = best;
        }
    }
    out
}

impl RadialSubdivision {
    /// Step 1–3: find the centre, test star-shape, cast `lines` radial lines.
    pub fn new(
        outer: &[DVec2],
        holes: &[Vec<DVec2>],
        pole: Option<DVec2>,
        lines: usize,
    ) -> Result<RadialSubdivision, RadialFailure> {
        if holes.len() > 1 {
            return Err(RadialFailure::SeveralHoles(holes.len()));
        }
        let candidates: Vec<DVec2> = match holes.first() {
            Some(h) => vec![crate::geom::centroid(h)],
            None => std::iter::once(crate::geom::centroid(outer))
                .chain(pole)
                .collect(),
        };
        let centre = candidates.iter().copied().find(|&c| {
            point_in_loop(c, outer)
                && is_star_about(outer, c)
                && holes
                    .iter()
                    .all(|h| point_in_loop(c, h) && is_star_about(h, c))
        });
        let Some(centre) = centre else {
            return Err(RadialFailure::NotStarShaped {
                centre: candidates[0],
            });
        };
        let lines = lines.max(8);
        let re = ray_radii(outer, centre, lines);
        let ri = match holes.first() {
            Some(h) => ray_radii(h, centre, lines),
            None => vec![0.0; lines],
        };
        let radii: Vec<(f64, f64)> = ri.into_iter().zip(re).collect();
        let l_short_mm = radii
            .iter()
            .map(|(a, b)| b - a)
            .fold(f64::INFINITY, f64::min);
        Ok(RadialSubdivision {
            centre,
            l_short_mm,
            lines,
            radii,
        })
    }

    /// Step 4: the division points of contour j (1-based, 2..=m) on every radial line.
    pub fn division_points(&self, j: u32, m: u32) -> Vec<DVec2> {
        let t = crate::material::contour_distance(j, m);
        let step = std::f64::consts::TAU / self.lines as f64;
        self.radii
            .iter()
            .enumerate()
            .map(|(q, &(ri, re))| {
                let theta = q as f64 * step;
                self.centre + DVec2::new(theta.cos(), theta.sin()) * (ri + t * (re - ri))
            })
            .collect()
    }

    /// Step 4–5: the sampled spline contours C2..Cm, checked against each other and the
    /// boundaries.
    pub fn contours(
        &self,
        m: u32,
        outer: &[DVec2],
        holes: &[Vec<DVec2>],
        chord_mm: f64,
    ) -> Result<Vec<Vec<DVec2>>, RadialFailure> {
        let contours: Vec<Vec<DVec2>> = (2..=m)
            .map(|j| catmull_rom_closed(&self.division_points(j, m), chord_mm))
            .collect();
        let mut all: Vec<&[DVec2]> = vec![outer];
        all.extend(holes.iter().map(|h| h.as_slice()));
        all.extend(contours.iter().map(|c| c.as_slice()));
        if first_crossing(&all).is_some() {
            return Err(RadialFailure::ContoursCross);
        }
        // No crossings: a contour is inside the material iff one of its points is.
        for c in &contours {
            if !point_in_loop(c[0], outer) || holes.iter().any(|h| point_in_loop(c[0], h)) {
                return Err(RadialFailure::ContoursCross);
            }
        }
        Ok(contours)
    }
}

/// A closed centripetal Catmull-Rom spline through `p`, sampled so that each span's
/// sagitta stays under `chord_mm`.
pub fn catmull_rom_closed(p: &[DVec2], chord_mm: f64) -> Vec<DVec2> {
    let n = p.len();
    if n < 3 {
        return p.to_vec();
    }
    let mut out = Vec::with_capacity(n * 2);
    for i in 0..n {
        let p0 = p[prev_in_loop(i, n)];
        let p1 = p[i];
        let p2 = p[next_in_loop(i, n)];
        let p3 = p[next_in_loop(next_in_loop(i, n), n)];
        out.push(p1);
        let mid = centripetal(p0, p1, p2, p3, 0.5);
        let sag = mid.distance(0.5 * (p1 + p2));
        if sag <= chord_mm {
            continue;
        }
        let s = ((sag / chord_mm.max(1e-9)).sqrt().ceil() as usize).clamp(2, 16);
        for k in 1..s {
            out.push(centripetal(p0, p1, p2, p3, k as f64 / s as f64));
        }
    }
    crate::geom::dedup_loop(&out, 1e-12)
}

/// Barry–Goldman evaluation of the centripetal (alpha = 0.5) Catmull-Rom segment p1→p2.
fn centripetal(p0: DVec2, p1: DVec2, p2: DVec2, p3: DVec2, u: f64) -> DVec2 {
    let knot = |a: DVec2, b: DVec2| a.distance(b).sqrt().max(1e-12);
    let t0 = 0.0;
    let t1 = t0 + knot(p0, p1);
    let t2 = t1 + knot(p1, p2);
    let t3 = t2 + knot(p2, p3);
    let t = t1 + (t2 - t1) * u;
    let lerp = |a: DVec2, b: DVec2, ta: f64, tb: f64| {
        a * ((tb - t) / (tb - ta)) + b * ((t - ta) / (tb - ta))
    };
    let a1 = lerp(p0, p1, t0, t1);
    let a2 = lerp(p1, p2, t1, t2);
    let a3 = lerp(p2, p3, t2, t3);
    let b1 = lerp(a1, a2, t0, t2);
    let b2 = lerp(a2, a3, t1, t3);
    lerp(b1, b2, t1, t2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::circle;

    #[test]
    fn paper_annulus_gives_m_10() {
        let outer = circle(DVec2::ZERO, 30.0, 0.001);
        let mut hole = circle(DVec2::ZERO, 10.0, 0.001);
        hole.reverse();
        let holes = vec![hole];
        let rs = RadialSubdivision::new(&outer, &holes, None, 360).unwrap();
        assert!(rs.centre.length() < 1e-9);
        assert!((rs.l_short_mm - 20.0).abs() < 1e-3);
        assert_eq!(crate::material::segment_count(rs.l_short_mm, 2.0), 10);
        let cs = rs.contours(10, &outer, &holes, 0.01).unwrap();
        assert_eq!(cs.len(), 9);
        for (k, c) in cs.iter().enumerate() {
            let want = 10.0 + 2.0 * (k + 1) as f64;
            assert!(
                c.iter().all(|p| (p.length() - want).abs() < 0.01),
                "C{}",
                k + 2
            );
        }
    }

    #[test]
    fn detects_non_star_regions() {
        // A U shape: the centroid sees part of the outer loop from behind.
        let u = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(30.0, 0.0),
            DVec2::new(30.0, 30.0),
            DVec2::new(20.0, 30.0),
            DVec2::new(20.0, 10.0),
            DVec2::new(10.0, 10.0),
            DVec2::new(10.0, 30.0),
            DVec2::new(0.0, 30.0),
        ];
        assert!(matches!(
            RadialSubdivision::new(&u, &[], None, 360),
            Err(RadialFailure::NotStarShaped { .. })
        ));
    }
}
