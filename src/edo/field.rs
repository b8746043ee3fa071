//! The general pre-subdivision (§3.1 generalised): iso-contours of the normalised
//! distance `d(p) = dist(p, Ci) / (dist(p, Ci) + dist(p, Ce))`.
//!
//! The radial construction of §3.1 only works where every radial line from the centre
//! of Ci stays inside the region. This method works for any region with any number of
//! holes: d is 0 on every hole (Ci), 1 on the outer loop (Ce), and its level sets at
//! the eq (2) distances `d_j = (j − 1) / m` are the contours C2..Cm.
//!
//! Steps:
//! 1. Sample a grid of nodes over the region (cell size from the planner options).
//! 2. Classify nodes inside the outer loop / inside a hole by scanlines.
//! 3. Distances to Ce and to Ci (holes, or the centre point when there is none) by a
//!    vector distance transform seeded with exact nearest points near each boundary.
//! 4. d per node, extended continuously outside the material (negative in holes, above
//!    1 outside Ce) so every level set is a closed loop.
//! 5. Marching triangles (four triangles per cell around its mean) extract the level
//!    sets of the piecewise-linear interpolant. Level sets of one continuous
//!    piecewise-linear function never cross each other, so contours of different
//!    levels never intersect, by construction. A level's segments are linked into
//!    loops through the triangle edges they share, as the cells are visited.

use crate::geom::{floor_clamped, Region};
use glam::DVec2;

/// Sampled normalised distance over a region.
pub struct DistanceField {
    origin: DVec2,
    h: f64,
    nx: usize,
    ny: usize,
    /// Normalised distance d at each node, row-major.
    d: Vec<f64>,
    /// Distance to Ce at each node (for locating the pole of inaccessibility).
    pub(crate) de: Vec<f64>,
    /// Distance to Ci at each node (empty for [`DistanceField::outer_only`]).
    di: Vec<f64>,
    /// Node inside the material (inside Ce, outside every hole).
    inside: Vec<bool>,
}

struct Grid {
    origin: DVec2,
    h: f64,
    nx: usize,
    ny: usize,
}

impl Grid {
    fn over(region: &Region, cell_mm: f64, max_nodes: usize) -> Grid {
        let (lo, hi) = region.bounds();
        let ext = hi - lo;
        let mut h = cell_mm.max(1e-6);
        loop {
            let nx = (ext.x / h).ceil() as usize + 5;
            let ny = (ext.y / h).ceil() as usize + 5;
            if nx.saturating_mul(ny) <= max_nodes.max(64) {
                return Grid {
                    origin: lo - DVec2::splat(2.0 * h),
                    h,
                    nx,
                    ny,
                };
            }
            h *= 1.25;
        }
    }

    fn node(&self, c: usize, r: usize) -> DVec2 {
        self.origin + DVec2::new(c as f64, r as f64) * self.h
    }

    /// The x of every column of nodes, as [`Grid::node`] computes it.
    fn xs(&self) -> Vec<f64> {
        (0..self.nx)
            .map(|c| self.origin.x + c as f64 * self.h)
            .collect()
    }
}

/// Scanline parity fill of closed loops over grid nodes.
fn fill_inside(grid: &Grid, loops: &[&Vec<DVec2>]) -> Vec<bool> {
    let mut rows: Vec<Vec<f64>> = vec![Vec::new(); grid.ny];
    for l in loops {
        let n = l.len();
        for i in 0..n {
            let (a, b) = (l[i], l[(i + 1) % n]);
            let (ylo, yhi) = (a.y.min(b.y), a.y.max(b.y));
            let r0 = ((ylo - grid.origin.y) / grid.h).ceil().max(0.0) as usize;
            let r1 = (((yhi - grid.origin.y) / grid.h).floor().max(-1.0) + 1.0) as usize;
            for (r, row) in rows.iter_mut().enumerate().take(r1.min(grid.ny)).skip(r0) {
                let y = grid.origin.y + r as f64 * grid.h;
                if (a.y > y) != (b.y > y) {
                    row.push(a.x + (y - a.y) / (b.y - a.y) * (b.x - a.x));
                }
            }
        }
    }
    let mut inside = vec![false; grid.nx * grid.ny];
    for (r, xs) in rows.iter_mut().enumerate() {
        xs.sort_by(f64::total_cmp);
        for pair in xs.chunks_exact(2) {
            let c0 = ((pair[0] - grid.origin.x) / grid.h).ceil().max(0.0) as usize;
            let c1 = ((pair[1] - grid.origin.x) / grid.h).floor();
            if c1 < 0.0 {
                continue;
            }
            for c in c0..=(c1 as usize).min(grid.nx - 1) {
                inside[r * grid.nx + c] = true;
            }
        }
    }
    inside
}

/// A node's nearest boundary point so far (NaN: none yet) and its squared distance.
#[derive(Clone, Copy)]
struct Nearest {
    q: DVec2,
    d2: f64,
}

/// Vector distance transform: distance from every node to the nearest point of the
/// loops' edges, exact near the edges and propagated (8SSEDT-style) elsewhere. Nodes
/// carry their nearest boundary point and the squared distance to it: squared
/// distances order the same as distances and spare a square root per relaxation.
fn distance_to_loops(grid: &Grid, loops: &[&Vec<DVec2>]) -> Vec<f64> {
    let (nx, ny) = (grid.nx, grid.ny);
    let n = nx * ny;
    let mut near = vec![
        Nearest {
            q: DVec2::splat(f64::NAN),
            d2: f64::INFINITY,
        };
        n
    ];
    let band = 1.5 * grid.h;
    for l in loops {
        let m = l.len();
        for i in 0..m {
            let (a, b) = (l[i], l[(i + 1) % m]);
            let lo = (a.min(b) - DVec2::splat(band) - grid.origin) / grid.h;
            let hi = (a.max(b) + DVec2::splat(band) - grid.origin) / grid.h;
            let (c0, r0) = (lo.x.ceil().max(0.0) as usize, lo.y.ceil().max(0.0) as usize);
            let (c1, r1) = (
                (hi.x.floor().max(0.0) as usize).min(nx - 1),
                (hi.y.floor().max(0.0) as usize).min(ny - 1),
            );
            let ab = b - a;
            let len2 = ab.length_squared();
            for r in r0..=r1 {
                for c in c0..=c1 {
                    let p = grid.node(c, r);
                    let t = if len2 > 0.0 {
                        ((p - a).dot(ab) / len2).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    let q = a + ab * t;
                    let d2 = p.distance_squared(q);
                    let k = r * nx + c;
                    if d2 < near[k].d2 {
                        near[k] = Nearest { q, d2 };
                    }
                }
            }
        }
    }
    // Offer a node (at `p`) the nearest point `q` of a neighbour. A neighbour with the
    // same nearest point offers the same distance, and a NaN point (none yet) a NaN
    // distance, neither of which is smaller: no test for them is needed.
    #[inline(always)]
    fn relax(here: &mut Nearest, p: DVec2, q: DVec2) {
        let d2 = p.distance_squared(q);
        if d2 < here.d2 {
            *here = Nearest { q, d2 };
        }
    }
    // Node abscissae once (the same sums as `Grid::node`), not a conversion per relaxation.
    let xs = grid.xs();
    let node = |c: usize, y: f64| DVec2::new(xs[c], y);
    // Forward pass: rows upwards, each from the left (left, lower-left, below,
    // lower-right), then back from the right (right). Rows are split off so the
    // neighbours are plain slice reads.
    for r in 0..ny {
        let y = grid.origin.y + r as f64 * grid.h;
        let (done, rest) = near.split_at_mut(r * nx);
        let row = &mut rest[..nx];
        let below = r.checked_sub(1).map(|b| &done[b * nx..(b + 1) * nx]);
        for c in 0..nx {
            let p = node(c, y);
            if c > 0 {
                let q = row[c - 1].q;
                relax(&mut row[c], p, q);
            }
            if let Some(below) = below {
                if c > 0 {
                    relax(&mut row[c], p, below[c - 1].q);
                }
                relax(&mut row[c], p, below[c].q);
                if c + 1 < nx {
                    relax(&mut row[c], p, below[c + 1].q);
                }
            }
        }
        for c in (0..nx.saturating_sub(1)).rev() {
            let q = row[c + 1].q;
            relax(&mut row[c], node(c, y), q);
        }
    }
    // Backward pass, mirrored.
    for r in (0..ny).rev() {
        let y = grid.origin.y + r as f64 * grid.h;
        let (head, done) = near.split_at_mut((r + 1) * nx);
        let row = &mut head[r * nx..];
        let above = (r + 1 < ny).then(|| &done[..nx]);
        for c in (0..nx).rev() {
            let p = node(c, y);
            if c + 1 < nx {
                let q = row[c + 1].q;
                relax(&mut row[c], p, q);
            }
            if let Some(above) = above {
                if c + 1 < nx {
                    relax(&mut row[c], p, above[c + 1].q);
                }
                relax(&mut row[c], p, above[c].q);
                if c > 0 {
                    relax(&mut row[c], p, above[c - 1].q);
                }
            }
        }
        for c in 1..nx {
            let q = row[c - 1].q;
            relax(&mut row[c], node(c, y), q);
        }
    }
    near.into_iter().map(|n| n.d2.sqrt()).collect()
}

impl DistanceField {
    /// Distances to Ce only: enough to find the pole of inaccessibility.
    pub fn outer_only(region: &Region, cell_mm: f64, max_nodes: usize) -> DistanceField {
        let grid = Grid::over(region, cell_mm, max_nodes);
        let in_outer = fill_inside(&grid, &[&region.outer]);
        let holes: Vec<&Vec<DVec2>> = region.holes.iter().collect();
        let in_hole = fill_inside(&grid, &holes);
        let inside: Vec<bool> = in_outer
            .iter()
            .zip(&in_hole)
            .map(|(o, h)| *o && !*h)
            .collect();
        let de = distance_to_loops(&grid, &[&region.outer]);
        DistanceField {
            origin: grid.origin,
            h: grid.h,
            nx: grid.nx,
            ny: grid.ny,
            d: Vec::new(),
            de,
            di: Vec::new(),
            inside,
        }
    }

    /// The normalised distance field of a region. Ci is the holes, or `centre` when the
    /// region has none (growth rings about a point).
    pub fn new(
        region: &Region,
        centre: Option<DVec2>,
        cell_mm: f64,
        max_nodes: usize,
    ) -> DistanceField {
        let grid = Grid::over(region, cell_mm, max_nodes);
        let in_outer = fill_inside(&grid, &[&region.outer]);
        let holes: Vec<&Vec<DVec2>> = region.holes.iter().collect();
        let in_hole = fill_inside(&grid, &holes);
        let de = distance_to_loops(&grid, &[&region.outer]);
        let di: Vec<f64> = if holes.is_empty() {
            let c = centre.unwrap_or_else(|| crate::geom::centroid(&region.outer));
            (0..grid.ny)
                .flat_map(|r| (0..grid.nx).map(move |cc| (cc, r)))
                .map(|(cc, r)| grid.node(cc, r).distance(c))
                .collect()
        } else {
            distance_to_loops(&grid, &holes)
        };
        let mut d = vec![0.0; grid.nx * grid.ny];
        let mut inside = vec![false; grid.nx * grid.ny];
        for k in 0..d.len() {
            let s = di[k] + de[k];
            let t = if s > 0.0 { di[k] / s } else { 0.0 };
            let e = if s > 0.0 { de[k] / s } else { 0.0 };
            d[k] = if !in_outer[k] {
                1.0 + e
            } else if in_hole[k] {
                -t
            } else {
                inside[k] = true;
                t
            };
        }
        DistanceField {
            origin: grid.origin,
            h: grid.h,
            nx: grid.nx,
            ny: grid.ny,
            d,
            de,
            di,
            inside,
        }
    }

    /// The thinnest wall between Ci and Ce: the smallest `dist(p, Ci) + dist(p, Ce)`
    /// over material nodes, which is attained on the segment joining the two closest
    /// points of the boundaries (L_short of eq (1) for the distance method).
    pub fn thinnest_wall(&self) -> Option<f64> {
        self.inside
            .iter()
            .zip(self.di.iter().zip(&self.de))
            .filter(|(inside, _)| **inside)
            .map(|(_, (a, b))| a + b)
            .min_by(f64::total_cmp)
    }

    /// The inside node farthest from Ce (pole of inaccessibility, to grid precision),
    /// and that distance.
    pub fn pole(&self) -> Option<(DVec2, f64)> {
        let mut best: Option<(usize, f64)> = None;
        for (k, &de) in self.de.iter().enumerate() {
            if self.inside[k] && best.is_none_or(|(_, b)| de > b) {
                best = Some((k, de));
            }
        }
        best.map(|(k, de)| {
            let (c, r) = (k % self.nx, k / self.nx);
            (self.origin + DVec2::new(c as f64, r as f64) * self.h, de)
        })
    }

    /// Cell size actually used, mm.
    pub fn cell_mm(&self) -> f64 {
        self.h
    }

    /// Level sets at `d = k / m` for k = 1..m−1 (contours C2..Cm), each a list of closed
    /// loops, extracted by marching triangles.
    ///
    /// Every crossing point lies on a triangle edge, named by its two end nodes (the
    /// cell centres numbered after the grid nodes); the two segments of a level through
    /// one edge join there. They are linked as the cells are visited row by row: a
    /// cell's own triangles meet on its diagonals, its bottom edge is the top edge of
    /// the cell below (kept from the previous row) and its left edge the right edge of
    /// the cell before it.
    pub fn level_sets(&self, m: u32) -> Vec<Vec<Vec<DVec2>>> {
        let levels = m.saturating_sub(1) as usize;
        if levels == 0 {
            return Vec::new();
        }
        let mut segs: Vec<Vec<Segment>> = vec![Vec::new(); levels];
        let (nx, ny) = (self.nx, self.ny);
        let nodes = (nx * ny) as u64;
        let mf = m as f64;
        // Node coordinates once, the same sums as `origin + (c, r) · h`.
        let xs: Vec<f64> = (0..nx).map(|c| self.origin.x + c as f64 * self.h).collect();
        let ys: Vec<f64> = (0..ny).map(|r| self.origin.y + r as f64 * self.h).collect();
        // Per level: the segment ending on each cell's top edge in the previous and the
        // current row, and on the right edge of the cell just visited, with that
        // edge's key (entries of cells that did not cross the level are stale, and
        // the key tells them apart).
        let none = (u64::MAX, NO_SEGMENT);
        let mut top_below = vec![none; levels * nx];
        let mut top_here = vec![none; levels * nx];
        let mut right = vec![none; levels];
        for r in 0..ny - 1 {
            std::mem::swap(&mut top_below, &mut top_here);
            for c in 0..nx - 1 {
                let ids = [
                    (r * nx + c) as u64,
                    (r * nx + c + 1) as u64,
                    ((r + 1) * nx + c + 1) as u64,
                    ((r + 1) * nx + c) as u64,
                ];
                let val = [
                    self.d[ids[0] as usize],
                    self.d[ids[1] as usize],
                    self.d[ids[2] as usize],
                    self.d[ids[3] as usize],
                ];
                let lo = val[0].min(val[1]).min(val[2]).min(val[3]);
                let hi = val[0].max(val[1]).max(val[2]).max(val[3]);
                // Level k/m is crossed when lo < k/m <= hi.
                let k_lo = (floor_clamped(lo * mf) as i64 + 1).max(1);
                let k_hi = (floor_clamped(hi * mf) as i64).min(m as i64 - 1);
                if k_lo > k_hi {
                    continue;
                }
                let pos = [
                    DVec2::new(xs[c], ys[r]),
                    DVec2::new(xs[c + 1], ys[r]),
                    DVec2::new(xs[c + 1], ys[r + 1]),
                    DVec2::new(xs[c], ys[r + 1]),
                ];
                let centre_id = nodes + (r * (nx - 1) + c) as u64;
                let centre_val = 0.25 * (val[0] + val[1] + val[2] + val[3]);
                let centre_pos = 0.25 * (pos[0] + pos[1] + pos[2] + pos[3]);
                for k in k_lo..=k_hi {
                    let t = k as f64 / mf;
                    let level = (k - 1) as usize;
                    let out = &mut segs[level];
                    let first = out.len();
                    // The right edge of the cell before (this cell's left edge), before
                    // this cell's right edge replaces it.
                    let mut left = right[level];
                    for e in 0..4 {
                        let f = (e + 1) % 4;
                        let tri = [
                            (ids[e], pos[e], val[e]),
                            (ids[f], pos[f], val[f]),
                            (centre_id, centre_pos, centre_val),
                        ];
                        let Some(mut seg) = triangle_crossing(&tri, t) else {
                            continue;
                        };
                        let i = out.len() as u32;
                        // The cell's outer edge of this triangle: bottom, right, top, left.
                        let outer = edge_key(ids[e], ids[f]);
                        for end in 0..2 {
                            if seg.keys[end] != outer {
                                continue;
                            }
                            let slot = match e {
                                0 => &mut top_below[level * nx + c],
                                1 => &mut right[level],
                                2 => &mut top_here[level * nx + c],
                                _ => &mut left,
                            };
                            match e {
                                // Edges shared with cells already visited: link.
                                0 | 3 => {
                                    if slot.0 == outer && slot.1 != NO_SEGMENT {
                                        let j = slot.1;
                                        seg.links[end] = j;
                                        let other = &mut out[j as usize];
                                        let back = usize::from(other.keys[1] == outer);
                                        other.links[back] = i;
                                    }
                                }
                                // Edges the next cells share: leave the segment there.
                                _ => *slot = (outer, i),
                            }
                        }
                        // Diagonals, shared with this cell's other triangles.
                        for end in 0..2 {
                            let key = seg.keys[end];
                            if key == outer {
                                continue;
                            }
                            for (j, other) in out.iter_mut().enumerate().skip(first) {
                                for back in 0..2 {
                                    if other.keys[back] == key {
                                        seg.links[end] = j as u32;
                                        other.links[back] = i;
                                    }
                                }
                            }
                        }
                        out.push(seg);
                    }
                }
            }
        }
        segs.into_iter().map(chain_segments).collect()
    }
}

/// No segment (an end whose edge no other segment of the level crosses).
const NO_SEGMENT: u32 = u32::MAX;

/// One piece of a level set inside one triangle: its end points, the keys of the
/// triangle edges they lie on (see [`edge_key`]), and the segments of the same level
/// through those edges.
#[derive(Clone, Copy)]
struct Segment {
    keys: [u64; 2],
    points: [DVec2; 2],
    links: [u32; 2],
}

fn edge_key(a: u64, b: u64) -> u64 {
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    // Node ids stay far below 2^32 (the grid is capped), so the pair packs into a u64.
    (lo << 32) | hi
}

fn triangle_crossing(tri: &[(u64, DVec2, f64); 3], t: f64) -> Option<Segment> {
    let above = [tri[0].2 >= t, tri[1].2 >= t, tri[2].2 >= t];
    let n_above = above.iter().filter(|a| **a).count();
    if n_above == 0 || n_above == 3 {
        return None;
    }
    let mut pts: [(u64, DVec2); 2] = [(0, DVec2::ZERO); 2];
    let mut n = 0;
    for i in 0..3 {
        let j = (i + 1) % 3;
        if above[i] != above[j] {
            let (pa, pb) = (tri[i], tri[j]);
            let s = (t - pa.2) / (pb.2 - pa.2);
            pts[n] = (edge_key(pa.0, pb.0), pa.1 + (pb.1 - pa.1) * s);
            n += 1;
        }
    }
    (n == 2).then_some(Segment {
        keys: [pts[0].0, pts[1].0],
        points: [pts[0].1, pts[1].1],
        links: [NO_SEGMENT; 2],
    })
}

/// Chain linked segments into closed loops.
fn chain_segments(segs: Vec<Segment>) -> Vec<Vec<DVec2>> {
    let mut used = vec![false; segs.len()];
    let mut loops = Vec::new();
    for start in 0..segs.len() {
        if used[start] {
            continue;
        }
        used[start] = true;
        let mut pts = vec![segs[start].points[0]];
        let first_key = segs[start].keys[0];
        let mut key = segs[start].keys[1];
        let mut point = segs[start].points[1];
        let mut next = segs[start].links[1];
        loop {
            pts.push(point);
            if key == first_key {
                break;
            }
            if next == NO_SEGMENT || used[next as usize] {
                break;
            }
            used[next as usize] = true;
            let s = &segs[next as usize];
            let enter = usize::from(s.keys[0] != key);
            key = s.keys[1 - enter];
            point = s.points[1 - enter];
            next = s.links[1 - enter];
        }
        let l = crate::geom::dedup_loop(&pts, 1e-12);
        if l.len() >= 3 {
            loops.push(l);
        }
    }
    loops
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::edo::shapes::circle;

    #[test]
    fn annulus_levels_are_circles() {
        let outer = circle(DVec2::ZERO, 30.0, 0.001);
        let mut hole = circle(DVec2::ZERO, 10.0, 0.001);
        hole.reverse();
        let region = Region::new(outer, vec![hole]);
        let field = DistanceField::new(&region, None, 0.25, 1 << 22);
        let levels = field.level_sets(10);
        assert_eq!(levels.len(), 9);
        for (k, loops) in levels.iter().enumerate() {
            assert_eq!(loops.len(), 1, "level {k}");
            let want = 10.0 + 20.0 * (k + 1) as f64 / 10.0;
            for p in &loops[0] {
                assert!(
                    (p.length() - want).abs() < 0.02,
                    "level {k}: {} vs {want}",
                    p.length()
                );
            }
        }
    }
}
