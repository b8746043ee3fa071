//! Flow raise in narrow sub-areas (§4, Fig. 4(a) locations (i)–(iii)): where the space
//! between a road and its neighbour needs a non-integer number of roads (say 1.3 roads
//! between two beads that touch at 1), the extrusion rate of the roads along the gap is
//! raised from the point where the gap opens, at constant scanning speed, so the beads
//! widen and close it.
//!
//! Steps, per layer:
//!
//! 1. **Subdivide** long edges to at most `probe_step` (one road width), so the width can
//!    change where the gap opens and not only at the planner's vertices.
//! 2. **Probe the gap** on each side of every vertex: march along the normal from the
//!    bead edge; the free gap ends where another road's centreline is nearer than the
//!    road's own (the midpoint between the two centrelines). This gives the
//!    centre-to-centre distance g to the neighbour on that side (∞ where no road is
//!    within reach, e.g. the part boundary side of the outer contour).
//! 3. **Width factor**: the two beads facing a gap of g share the missing g − w, each
//!    widening by (g − w)/2 on that side; a bead widens on both sides, so its factor is
//!    1 + 2·max_side((g − w)/2)/w, only for gaps that need less than one more road
//!    (w < g < 2w), capped at `max_flow_factor`. Gaps too wide for the cap stay (a
//!    gap-fill road would be needed: not implemented, reported by the coverage measure).

use super::ToolPath;
use crate::geom::SegmentIndex;
use glam::DVec2;

/// Settings of the flow raise (part of [`crate::pipeline::ProcessSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlowSettings {
    pub road_width_mm: f64,
    pub max_flow_factor: f64,
    /// Gaps narrower than this fraction of a road width beyond touching are left (noise).
    pub min_gap_fraction: f64,
}

/// Raise the width factors of `paths` in place (steps 1–3).
pub fn raise(paths: &mut [ToolPath], s: &FlowSettings) {
    let w = s.road_width_mm;
    if !w.is_finite() || w <= 0.0 || s.max_flow_factor <= 1.0 || paths.is_empty() {
        return;
    }
    // Step 1.
    for p in paths.iter_mut() {
        subdivide(p, w);
    }
    // Step 2: one index over every road.
    let loops: Vec<&[DVec2]> = paths
        .iter()
        .filter(|p| p.closed)
        .map(|p| p.points.as_slice())
        .collect();
    let lines: Vec<&[DVec2]> = paths
        .iter()
        .filter(|p| !p.closed)
        .map(|p| p.points.as_slice())
        .collect();
    let index = SegmentIndex::new(&loops, &lines);
    let step = w / 8.0;
    let reach = w; // probe up to a gap of 2w centre to centre
    for p in paths.iter_mut() {
        let n = p.points.len();
        if n < 2 {
            continue;
        }
        let mut factors = Vec::with_capacity(n);
        for k in 0..n {
            let prev = if k > 0 {
                p.points[k - 1]
            } else if p.closed {
                p.points[n - 1]
            } else {
                p.points[k]
            };
            let next = if k + 1 < n {
                p.points[k + 1]
            } else if p.closed {
                p.points[0]
            } else {
                p.points[k]
            };
            let t = (next - prev).normalize_or_zero();
            if t == DVec2::ZERO {
                factors.push(1.0);
                continue;
            }
            let nrm = t.perp();
            let q0 = p.points[k];
            let mut extra: f64 = 0.0;
            for side in [1.0, -1.0] {
                // Half the centre-to-centre gap: where another centreline becomes nearer
                // than our own.
                let mut half = None;
                let mut d = 0.5 * w + step;
                while d <= 0.5 * w + reach {
                    let q = q0 + nrm * (side * d);
                    let other = index.distance(q);
                    if other < d - 1e-3 * w {
                        // Parallel neighbour at g: other = g - d, so g = d + other.
                        half = Some(0.5 * (d + other));
                        break;
                    }
                    d += step;
                }
                if let Some(h) = half {
                    let g = 2.0 * h;
                    let missing = 0.5 * (g - w);
                    if missing > s.min_gap_fraction * w && g < 2.0 * w {
                        extra = extra.max(missing);
                    }
                }
            }
            factors.push((1.0 + 2.0 * extra / w).min(s.max_flow_factor));
        }
        p.width_factors = factors;
    }
}

fn subdivide(p: &mut ToolPath, max_len: f64) {
    let n = p.points.len();
    if n < 2 {
        return;
    }
    let edges = if p.closed { n } else { n - 1 };
    let mut pts = Vec::with_capacity(n);
    let mut fs = Vec::with_capacity(n);
    for k in 0..edges {
        let (a, b) = (p.points[k], p.points[(k + 1) % n]);
        let (fa, fb) = (p.width_factors[k], p.width_factors[(k + 1) % n]);
        let pieces = ((a.distance(b) / max_len).ceil() as usize).max(1);
        for q in 0..pieces {
            let t = q as f64 / pieces as f64;
            pts.push(a.lerp(b, t));
            fs.push(fa + (fb - fa) * t);
        }
    }
    if !p.closed {
        pts.push(p.points[n - 1]);
        fs.push(p.width_factors[n - 1]);
    }
    p.points = pts;
    p.width_factors = fs;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::PathRole;

    fn line(y: f64) -> ToolPath {
        ToolPath {
            role: PathRole::Contour { island: 0, j: 1 },
            points: vec![DVec2::new(0.0, y), DVec2::new(10.0, y)],
            closed: false,
            width_factors: vec![1.0; 2],
            composition: vec![1.0],
            seam_at_corner: false,
        }
    }

    #[test]
    fn a_gap_of_one_and_a_third_roads_widens_both_neighbours() {
        // Centre to centre 1.3 w: each bead widens by 0.15 w on each side: factor 1.3.
        let mut paths = vec![line(0.0), line(0.52)];
        let s = FlowSettings {
            road_width_mm: 0.4,
            max_flow_factor: 1.5,
            min_gap_fraction: 0.02,
        };
        raise(&mut paths, &s);
        let mid = paths[0].width_factors[paths[0].points.len() / 2];
        assert!((mid - 1.3).abs() < 0.05, "{mid}");
        // Touching roads stay nominal; a wide gap is capped.
        let mut touching = vec![line(0.0), line(0.4)];
        raise(&mut touching, &s);
        assert!(touching[0].width_factors.iter().all(|&f| f == 1.0));
        let mut wide = vec![line(0.0), line(0.76)];
        raise(&mut wide, &s);
        let f = wide[0].width_factors[5];
        assert!((f - 1.5).abs() < 1e-9, "{f}");
    }
}
