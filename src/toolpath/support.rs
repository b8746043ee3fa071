//! Support roads: the roads that build a layer's [`SupportArea`], after the part's.
//!
//! Steps:
//!
//! 1. [`scan_lines`]: parallel lines across an area (inset by half a road so the beads
//!    stay inside it) on a grid fixed to the bed, so a line stands on the same line in
//!    the layer below and the columns are walls.
//! 2. [`zigzag`]: consecutive lines joined where the join runs inside the area, so a
//!    column is built in few roads (each road end is an extrusion cessation).
//! 3. [`support_paths`]: the interface densely (one road apart, across the base's
//!    direction, turning a quarter each layer), the base at the job's density and
//!    pattern, in the support's composition, ordered nearest first from where the
//!    part's roads ended.

use super::{PathRole, ToolPath};
use crate::geom::{loops, offset, Shapes};
use crate::slice::support::SupportArea;
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// `[support] pattern`: the base's lines.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SupportPattern {
    /// Parallel lines, the same in every layer (walls).
    #[default]
    Lines,
    /// Lines both ways in every layer (a grid of columns, stiffer, twice the road).
    Grid,
}

/// How a layer's support is built (from the job's `[support]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SupportRoads {
    pub pattern: SupportPattern,
    /// The base's share of its area covered by road (0 < density ≤ 1).
    pub density: f64,
    /// Direction of the base's lines, degrees from +x.
    pub angle_deg: f64,
    /// Composition of every support road (fractions in the plan's material order,
    /// with the support syringe's, if any, after the part's materials).
    pub composition: Vec<f64>,
}

/// Step 1: lines at `angle_deg` from +x, `spacing_mm` apart on a grid through the
/// origin, clipped to `area` (even-odd over its loops); each line's pieces left to
/// right, lines in order across.
pub fn scan_lines(area: &Shapes, angle_deg: f64, spacing_mm: f64) -> Vec<Vec<[DVec2; 2]>> {
    let (sin, cos) = angle_deg.to_radians().sin_cos();
    // Into the frame where the lines run along x.
    let to = |p: DVec2| DVec2::new(p.x * cos + p.y * sin, -p.x * sin + p.y * cos);
    let back = |p: DVec2| DVec2::new(p.x * cos - p.y * sin, p.x * sin + p.y * cos);
    let edges: Vec<(DVec2, DVec2)> = loops(area)
        .flat_map(|l| crate::geom::loop_edges(l).map(|(a, b)| (to(a), to(b))))
        .collect();
    let (lo, hi) = edges.iter().fold((f64::MAX, f64::MIN), |(lo, hi), (a, b)| {
        (lo.min(a.y).min(b.y), hi.max(a.y).max(b.y))
    });
    if edges.is_empty() || spacing_mm.is_nan() || spacing_mm <= 0.0 {
        return Vec::new();
    }
    let first = (lo / spacing_mm).ceil() as i64;
    let last = (hi / spacing_mm).floor() as i64;
    let mut out = Vec::new();
    let mut xs: Vec<f64> = Vec::new();
    for k in first..=last {
        let y = k as f64 * spacing_mm;
        xs.clear();
        for (a, b) in &edges {
            // Half-open in y so a vertex on the line counts once.
            if (a.y <= y) != (b.y <= y) {
                let t = (y - a.y) / (b.y - a.y);
                xs.push(a.x + t * (b.x - a.x));
            }
        }
        xs.sort_by(f64::total_cmp);
        let pieces: Vec<[DVec2; 2]> = xs
            .chunks_exact(2)
            .filter(|p| p[1] - p[0] > 1e-9)
            .map(|p| [back(DVec2::new(p[0], y)), back(DVec2::new(p[1], y))])
            .collect();
        if !pieces.is_empty() {
            out.push(pieces);
        }
    }
    out
}

/// Whether the straight join from `a` to `b` stays inside `area` (it meets no edge of
/// it, and its middle is inside).
fn join_inside(a: DVec2, b: DVec2, area: &Shapes) -> bool {
    if !crate::geom::contains(area, (a + b) / 2.0) {
        return false;
    }
    !loops(area).any(|l| {
        crate::geom::loop_edges(l).any(|(p, q)| crate::geom::segments_intersect(a, b, p, q))
    })
}

/// Step 2: the pieces of consecutive lines joined end to start, turning back each
/// line, where the join is no longer than `max_join_mm` and inside `area` (the area
/// the lines were clipped to grown by half a road: a join along the clipped edge is
/// inside it).
pub fn zigzag(lines: Vec<Vec<[DVec2; 2]>>, area: &Shapes, max_join_mm: f64) -> Vec<Vec<DVec2>> {
    let mut done: Vec<Vec<DVec2>> = Vec::new();
    // Open polylines ending on the previous line, and whether they run +x there.
    let mut open: Vec<Vec<DVec2>> = Vec::new();
    for (k, pieces) in lines.into_iter().enumerate() {
        let forward = k.is_multiple_of(2);
        let mut next_open = Vec::with_capacity(pieces.len());
        for [a, b] in pieces {
            let (s, e) = if forward { (a, b) } else { (b, a) };
            let joined = open.iter().position(|p: &Vec<DVec2>| {
                p.last()
                    .is_some_and(|&end| end.distance(s) <= max_join_mm && join_inside(end, s, area))
            });
            match joined {
                Some(j) => {
                    let mut p = open.swap_remove(j);
                    p.push(s);
                    p.push(e);
                    next_open.push(p);
                }
                None => next_open.push(vec![s, e]),
            }
        }
        done.append(&mut open);
        open = next_open;
    }
    done.append(&mut open);
    done
}

/// Step 3: the roads of a layer's support, `road_width_mm` wide, in building order
/// from `start` (where the nozzle is after the part's roads).
pub fn support_paths(
    area: &SupportArea,
    layer_index: usize,
    road_width_mm: f64,
    roads: &SupportRoads,
    start: Option<DVec2>,
) -> Vec<ToolPath> {
    let chord = road_width_mm / 20.0;
    let mut pieces: Vec<Piece> = Vec::new();
    let mut build = |shapes: &Shapes, angle: f64, spacing: f64, role: PathRole| {
        let inside = offset(shapes, -road_width_mm / 2.0, chord);
        if inside.is_empty() {
            return;
        }
        // The interface is outlined first (a loop half a road in, so its edge is
        // laid whole, not in the scallops of line ends), its lines then inside the
        // loop.
        let lines_in = if role == PathRole::SupportInterface {
            pieces.extend(loops(&inside).map(|l| Piece {
                points: l.clone(),
                closed: true,
                role,
            }));
            offset(&inside, -road_width_mm / 2.0, chord)
        } else {
            inside
        };
        let lines = scan_lines(&lines_in, angle, spacing);
        // Joins run on the inset boundary: inside the area itself.
        for points in zigzag(lines, shapes, 2.0 * spacing) {
            pieces.push(Piece {
                points,
                closed: false,
                role,
            });
        }
    };
    let base_angle = roads.angle_deg;
    if !area.base.is_empty() {
        let density = roads.density.clamp(0.01, 1.0);
        let base = PathRole::Support;
        match roads.pattern {
            SupportPattern::Lines => build(&area.base, base_angle, road_width_mm / density, base),
            SupportPattern::Grid => {
                let spacing = 2.0 * road_width_mm / density;
                build(&area.base, base_angle, spacing, base);
                build(&area.base, base_angle + 90.0, spacing, base);
            }
        }
    }
    if !area.interface.is_empty() {
        let turn = if layer_index.is_multiple_of(2) {
            90.0
        } else {
            0.0
        };
        let interface = PathRole::SupportInterface;
        build(&area.interface, base_angle + turn, road_width_mm, interface);
    }
    pieces.retain(|p| {
        crate::geom::edges(&p.points, p.closed)
            .map(|(a, b)| a.distance(b))
            .sum::<f64>()
            >= road_width_mm
    });
    nearest_first(pieces, start)
        .into_iter()
        .map(|p| ToolPath {
            role: p.role,
            width_factors: vec![1.0; p.points.len()],
            points: p.points,
            closed: p.closed,
            composition: roads.composition.clone(),
            seam_at_corner: false,
        })
        .collect()
}

/// A support road before ordering.
struct Piece {
    points: Vec<DVec2>,
    closed: bool,
    role: PathRole,
}

/// `pieces` in nearest-neighbour order from `start`: an open one entered at its
/// nearer end, a loop at its nearest vertex.
fn nearest_first(mut pieces: Vec<Piece>, start: Option<DVec2>) -> Vec<Piece> {
    let mut out = Vec::with_capacity(pieces.len());
    let mut at = start.unwrap_or(DVec2::ZERO);
    while !pieces.is_empty() {
        // (squared distance, piece, vertex to start at)
        let mut best = (f64::MAX, 0, 0);
        for (k, p) in pieces.iter().enumerate() {
            let ends: Vec<usize> = if p.closed {
                (0..p.points.len()).collect()
            } else {
                vec![0, p.points.len().saturating_sub(1)]
            };
            for v in ends {
                let d = p
                    .points
                    .get(v)
                    .map_or(f64::MAX, |q| at.distance_squared(*q));
                if d < best.0 {
                    best = (d, k, v);
                }
            }
        }
        let mut p = pieces.swap_remove(best.1);
        if p.closed {
            p.points.rotate_left(best.2);
        } else if best.2 > 0 {
            p.points.reverse();
        }
        at = match p.closed {
            true => p.points.first(),
            false => p.points.last(),
        }
        .copied()
        .unwrap_or(at);
        out.push(p);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(lo: f64, hi: f64) -> Shapes {
        vec![vec![vec![
            DVec2::new(lo, lo),
            DVec2::new(hi, lo),
            DVec2::new(hi, hi),
            DVec2::new(lo, hi),
        ]]]
    }

    fn roads(pattern: SupportPattern, density: f64) -> SupportRoads {
        SupportRoads {
            pattern,
            density,
            angle_deg: 0.0,
            composition: vec![0.0, 0.0, 1.0],
        }
    }

    fn length(paths: &[ToolPath]) -> f64 {
        paths.iter().map(ToolPath::length_mm).sum()
    }

    #[test]
    fn a_square_base_is_one_zigzag_at_its_density() {
        let area = SupportArea {
            base: square(0.0, 10.0),
            interface: Vec::new(),
        };
        let paths = support_paths(&area, 0, 0.4, &roads(SupportPattern::Lines, 0.25), None);
        assert_eq!(paths.len(), 1, "{paths:?}");
        assert!(paths.iter().all(|p| p.role == PathRole::Support));
        // Lines 1.6 mm apart across 9.6 mm: 6 lines of 9.6 mm, 5 joins of 1.6 mm.
        let l = length(&paths);
        assert!((l - (6.0 * 9.6 + 5.0 * 1.6)).abs() < 0.5, "{l}");
        // Every point inside the area less half a road.
        assert!(paths[0]
            .points
            .iter()
            .all(|p| p.x >= 0.2 - 1e-6 && p.x <= 9.8 + 1e-6 && p.y >= 0.2 - 1e-6));
        // A grid lays both ways: about twice the lines at twice the spacing.
        let grid = support_paths(&area, 0, 0.4, &roads(SupportPattern::Grid, 0.25), None);
        let g = length(&grid);
        assert!((g - l).abs() < 0.25 * l, "{g} against {l}");
    }

    #[test]
    fn the_interface_is_outlined_dense_and_turns_each_layer() {
        let area = SupportArea {
            base: Vec::new(),
            interface: square(0.05, 4.05),
        };
        let even = support_paths(&area, 0, 0.4, &roads(SupportPattern::Lines, 0.25), None);
        let odd = support_paths(&area, 1, 0.4, &roads(SupportPattern::Lines, 0.25), None);
        assert!(even.iter().all(|p| p.role == PathRole::SupportInterface));
        // A loop half a road in (0.25-3.85 mm: 4 x 3.6 mm), first from the origin.
        assert!(even[0].closed && (even[0].length_mm() - 14.4).abs() < 0.01);
        assert_eq!(even[0].points[0], DVec2::new(0.25, 0.25));
        // Then lines 0.4 mm apart on the bed's grid within the loop (0.45-3.65 mm):
        // 8 lines of 3.2 mm, joined.
        let lines: Vec<ToolPath> = even.iter().filter(|p| !p.closed).cloned().collect();
        let l = length(&lines);
        assert!((l - (8.0 * 3.2 + 7.0 * 0.4)).abs() < 0.1, "{l}");
        let first = |p: &[ToolPath]| {
            let open = p.iter().find(|p| !p.closed).unwrap();
            open.points[1] - open.points[0]
        };
        assert!(first(&even).x.abs() < 1e-9, "even layers run along y");
        assert!(first(&odd).y.abs() < 1e-9, "odd layers run along x");
    }

    #[test]
    fn lines_are_not_joined_across_a_notch() {
        // A U: two 2 mm prongs 6 mm apart joined at the bottom.
        let u: Shapes = vec![vec![vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(10.0, 0.0),
            DVec2::new(10.0, 10.0),
            DVec2::new(8.0, 10.0),
            DVec2::new(8.0, 2.0),
            DVec2::new(2.0, 2.0),
            DVec2::new(2.0, 10.0),
            DVec2::new(0.0, 10.0),
        ]]];
        let lines = scan_lines(&u, 90.0, 1.0);
        let paths = zigzag(lines, &u, 2.0);
        for p in &paths {
            for w in p.windows(2) {
                assert!(
                    join_inside(w[0], w[1], &u) || (w[0] - w[1]).x.abs() < 1e-9,
                    "{w:?}"
                );
            }
        }
    }
}
