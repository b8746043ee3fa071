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
//! 3. **Width factor**: a bead's width is matched to its neighbours, each gap of g
//!    (centre to centre) being shared half and half by the two beads facing it:
//!    - neighbours on both sides (g1, g2 < 2w): width max(g1, g2), so roads spaced
//!      closer than a road width on both sides (eq (5) rounds N_max up, so the equal
//!      distance offsets of a sub-region are D_max/N_max ≤ D_noz apart) are narrowed to
//!      their spacing instead of overlapping, and roads beside a gap that needs a
//!      non-integer number of roads (w < g < 2w) widen into it; where the two spacings
//!      differ the bead fills its half of the wider one and overlaps on the narrower
//!      side (never a void);
//!    - a neighbour on one side only (the other is the part boundary or open space):
//!      width max(w, g) — raised into a gap, never narrowed, so the bead's far edge
//!      stays where nozzle radius compensation put it;
//!
//!    The factor is then clamped to [`FlowSettings::min_flow_factor`,
//!    `max_flow_factor`]; changes smaller than `min_gap_fraction` are left (noise). Gaps
//!    too wide for the cap stay (a gap-fill road would be needed: not implemented,
//!    reported by the coverage measure). A path's own edges within 1.5 w + 2 reach
//!    along it never count as its neighbour (on a loop's concave side they come nearer
//!    than the probe).

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
    /// Narrowest bead relative to nominal (≤ 1; 1 turns narrowing off).
    pub min_flow_factor: f64,
}

/// Raise the width factors of `paths` in place (steps 1–3).
pub fn raise(paths: &mut [ToolPath], s: &FlowSettings) {
    let w = s.road_width_mm;
    let adjusts = s.max_flow_factor > 1.0 || s.min_flow_factor < 1.0;
    if !w.is_finite() || w <= 0.0 || !adjusts || paths.is_empty() {
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
    // Segment ids of each path in the index (loops first, then open paths) and the arc
    // length at each of its vertices, so a probe can skip the path's own nearby edges:
    // on the concave side of a curve (a loop's inside) they come nearer than the probe
    // distance and would pass for a neighbour.
    let mut first_segment = vec![0u32; paths.len()];
    let mut next = 0u32;
    for closed in [true, false] {
        for (i, p) in paths.iter().enumerate().filter(|(_, p)| p.closed == closed) {
            first_segment[i] = next;
            let n = p.points.len() as u32;
            next += if closed { n } else { n.saturating_sub(1) };
        }
    }
    let step = w / 8.0;
    let reach = w; // probe up to a gap of 2w centre to centre
                   // Own edges nearer (along the path) than this are never a neighbour.
    let own_window = 1.5 * w + 2.0 * reach;
    for (i, p) in paths.iter_mut().enumerate() {
        let n = p.points.len();
        if n < 2 {
            continue;
        }
        let mut cum = Vec::with_capacity(n + 1);
        cum.push(0.0);
        for j in 0..n {
            let b = if j + 1 < n {
                p.points[j + 1]
            } else {
                p.points[0]
            };
            let last = cum[j];
            cum.push(last + p.points[j].distance(b));
        }
        let total = if p.closed { cum[n] } else { cum[n - 1] };
        let base = first_segment[i];
        let segments = if p.closed { n } else { n - 1 } as u32;
        let mut factors = Vec::with_capacity(n);
        for k in 0..n {
            let s0 = cum[k];
            let own_nearby = |id: u32| {
                let Some(j) = id.checked_sub(base).filter(|&j| j < segments) else {
                    return false;
                };
                let (a, b) = (cum[j as usize], cum[j as usize + 1]);
                let gap = |x: f64| {
                    if x < a {
                        a - x
                    } else if x > b {
                        x - b
                    } else {
                        0.0
                    }
                };
                let mut d = gap(s0);
                if p.closed {
                    d = d.min(gap(s0 + total)).min(gap(s0 - total));
                }
                d < own_window
            };
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
            let mut gaps = [None, None];
            for (g_side, side) in gaps.iter_mut().zip([1.0, -1.0]) {
                // Half the centre-to-centre gap: where another centreline becomes nearer
                // than our own. Neighbours closer than w/2 are not roads of this plan.
                let mut d = 0.25 * w + step;
                while d <= 0.5 * w + reach {
                    let q = q0 + nrm * (side * d);
                    let other = index.distance_skipping(q, own_nearby);
                    if other < d - 1e-3 * w {
                        // Parallel neighbour at g: other = g - d, so g = d + other.
                        *g_side = Some(d + other);
                        break;
                    }
                    d += step;
                }
            }
            let width = match gaps {
                [Some(a), Some(b)] => a.max(b),
                [Some(g), None] | [None, Some(g)] => g.max(w),
                [None, None] => w,
            };
            let mut f = width / w;
            if (f - 1.0).abs() <= s.min_gap_fraction {
                f = 1.0;
            }
            factors.push(f.clamp(s.min_flow_factor.min(1.0), s.max_flow_factor.max(1.0)));
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
            min_flow_factor: 0.6,
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

    #[test]
    fn roads_closer_than_a_road_width_on_both_sides_are_narrowed_to_their_spacing() {
        let s = FlowSettings {
            road_width_mm: 0.4,
            max_flow_factor: 1.5,
            min_gap_fraction: 0.02,
            min_flow_factor: 0.6,
        };
        let mut paths = vec![line(0.0), line(0.3), line(0.6), line(0.9)];
        raise(&mut paths, &s);
        let mid = |p: &ToolPath| p.width_factors[p.points.len() / 2];
        // Inner roads: neighbours 0.3 away on both sides: 0.3 wide.
        assert!((mid(&paths[1]) - 0.75).abs() < 0.02, "{}", mid(&paths[1]));
        assert!((mid(&paths[2]) - 0.75).abs() < 0.02, "{}", mid(&paths[2]));
        // Outer roads keep their far edge where it was: not narrowed.
        assert_eq!(mid(&paths[0]), 1.0);
        assert_eq!(mid(&paths[3]), 1.0);
        // Never below the floor.
        let mut tight = vec![line(0.0), line(0.12), line(0.24)];
        raise(&mut tight, &s);
        assert!(tight[1].width_factors.iter().all(|&f| f >= 0.6 - 1e-12));
    }

    #[test]
    fn a_loop_is_not_its_own_neighbour() {
        // On the inside of a polygonal circle the loop's own edges come nearer than the
        // probe distance; they must not count as a neighbour. The inner of two rings 0.3
        // apart (w = 0.4) has a neighbour on one side only: it keeps its nominal width.
        let ring = |r: f64| {
            let n = 24;
            let points: Vec<DVec2> = (0..n)
                .map(|k| {
                    let a = std::f64::consts::TAU * k as f64 / n as f64;
                    DVec2::new(a.cos(), a.sin()) * r
                })
                .collect();
            ToolPath {
                role: PathRole::Contour { island: 0, j: 1 },
                width_factors: vec![1.0; points.len()],
                points,
                closed: true,
                composition: vec![1.0],
                seam_at_corner: false,
            }
        };
        let mut paths = vec![ring(1.2), ring(1.5)];
        raise(
            &mut paths,
            &FlowSettings {
                road_width_mm: 0.4,
                max_flow_factor: 1.5,
                min_gap_fraction: 0.02,
                min_flow_factor: 0.6,
            },
        );
        assert!(
            paths[0].width_factors.iter().all(|&f| f == 1.0),
            "{:?}",
            paths[0].width_factors
        );
    }
}
