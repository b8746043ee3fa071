//! Coverage measure of a layer's roads: rasterise every road as the area its bead covers
//! (the centreline swept by a disc of the road's width, vertex width factors included)
//! on a square grid of `cell_mm` (10 µm for reports) and count, over cell centres:
//!
//! - **void**: part cells no road covers,
//! - **overlap**: part cells covered by two or more different roads (a road's own joints
//!   do not count),
//! - **outside**: cells outside the part some road covers.
//!
//! Fractions are of the part area (cells inside the part). The part is the layer's
//! islands (outer loops and holes, even-odd).
//!
//! The cell centres sit [`SAMPLE_PHASE`] of a cell off round coordinates: roads designed
//! exactly one width apart on round coordinates touch along a line, and a row of cell
//! centres lying on that line would count as covered by both (a 1-cell overlap line
//! along every such pair, 2.5 % of the area at 10 µm cells and 0.4 mm roads).

use super::ToolPath;
use crate::geom::Region;
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Offset of the cell centres from the grid origin's round coordinates, in cells
/// (1/π and e^(−π/2): no simple fraction).
pub const SAMPLE_PHASE: (f64, f64) = (std::f64::consts::FRAC_1_PI, 0.207_879_576_350_762);

/// Coverage of one layer (or a sum of layers: add the cell counts).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Coverage {
    pub cell_mm: f64,
    pub part_cells: u64,
    pub void_cells: u64,
    pub overlap_cells: u64,
    pub outside_cells: u64,
}

impl Coverage {
    pub fn void_fraction(&self) -> f64 {
        self.void_cells as f64 / self.part_cells.max(1) as f64
    }
    pub fn overlap_fraction(&self) -> f64 {
        self.overlap_cells as f64 / self.part_cells.max(1) as f64
    }
    pub fn outside_fraction(&self) -> f64 {
        self.outside_cells as f64 / self.part_cells.max(1) as f64
    }
    /// Sum of two layers' counts (same cell size).
    pub fn add(&mut self, o: &Coverage) {
        self.cell_mm = o.cell_mm;
        self.part_cells += o.part_cells;
        self.void_cells += o.void_cells;
        self.overlap_cells += o.overlap_cells;
        self.outside_cells += o.outside_cells;
    }
}

/// Grids larger than this many cells are measured at a coarser cell (memory bound).
pub const MAX_CELLS: usize = 200_000_000;

/// Measure the coverage of `paths` (road width `road_width_mm` times the vertex width
/// factors) over the part `islands` at `cell_mm` (coarsened by doubling if the grid would
/// pass [`MAX_CELLS`]; the cell used is in the result).
pub fn measure(
    islands: &[Region],
    paths: &[ToolPath],
    road_width_mm: f64,
    cell_mm: f64,
) -> Coverage {
    measure_with_voids(islands, paths, road_width_mm, cell_mm, 0).0
}

/// [`measure`] plus up to `max_void_points` centres of void cells.
pub fn measure_with_voids(
    islands: &[Region],
    paths: &[ToolPath],
    road_width_mm: f64,
    cell_mm: f64,
    max_void_points: usize,
) -> (Coverage, Vec<DVec2>) {
    let Some(raster) = Raster::of_roads(islands, paths, road_width_mm, cell_mm) else {
        return (Coverage::default(), Vec::new());
    };
    let mut cov = Coverage {
        cell_mm: raster.cell_mm,
        ..Default::default()
    };
    let mut voids = Vec::new();
    raster.scan_part(islands, |c, centre, inside| {
        let roads = raster.count[c];
        if inside {
            cov.part_cells += 1;
            if roads == 0 {
                cov.void_cells += 1;
                if voids.len() < max_void_points {
                    voids.push(centre);
                }
            } else if roads >= 2 {
                cov.overlap_cells += 1;
            }
        } else if roads > 0 {
            cov.outside_cells += 1;
        }
    });
    (cov, voids)
}

/// A square grid over a layer with, per cell, how many different roads cover its centre
/// (saturating at 255).
pub(crate) struct Raster {
    /// Corner of cell (0, 0); cell centres are half a cell in from it.
    pub lo: DVec2,
    pub cell_mm: f64,
    pub nx: usize,
    pub ny: usize,
    pub count: Vec<u8>,
}

impl Raster {
    /// Rasterise `paths` over the bounds of `islands` and the roads at `cell_mm`
    /// (coarsened by doubling past [`MAX_CELLS`]); none when nothing is finite.
    pub fn of_roads(
        islands: &[Region],
        paths: &[ToolPath],
        road_width_mm: f64,
        cell_mm: f64,
    ) -> Option<Raster> {
        let (mut lo, mut hi) = crate::geom::bounds_of(islands);
        let mut r_max: f64 = 0.0;
        for p in paths {
            for (q, f) in p.points.iter().zip(&p.width_factors) {
                lo = lo.min(*q);
                hi = hi.max(*q);
                r_max = r_max.max(0.5 * road_width_mm * f);
            }
        }
        if !(lo.x.is_finite()
            && hi.x.is_finite()
            && r_max.is_finite()
            && cell_mm.is_finite()
            && cell_mm > 0.0)
        {
            return None;
        }
        lo -= DVec2::splat(r_max + cell_mm) + DVec2::from(SAMPLE_PHASE) * cell_mm;
        hi += DVec2::splat(r_max + cell_mm);
        let mut cell = cell_mm;
        let size = |c: f64| {
            (
                ((hi.x - lo.x) / c).ceil() as usize + 1,
                ((hi.y - lo.y) / c).ceil() as usize + 1,
            )
        };
        while size(cell).0.saturating_mul(size(cell).1) > MAX_CELLS {
            cell *= 2.0;
        }
        let (nx, ny) = size(cell);
        let centre_y = |j: usize| lo.y + (j as f64 + 0.5) * cell;

        // Roads: count of different roads covering each cell.
        let mut count = vec![0u8; nx * ny];
        let mut last = vec![0u32; nx * ny];
        for (pid, p) in paths.iter().enumerate() {
            let id = pid as u32 + 1;
            let n = p.points.len();
            if n == 0 {
                continue;
            }
            let edges = if p.closed { n } else { n.saturating_sub(1) };
            let mut stamp = |a: DVec2, b: DVec2, r: f64| {
                let j0 = (((a.y.min(b.y) - r - lo.y) / cell - 0.5).ceil().max(0.0)) as usize;
                let j1 = (((a.y.max(b.y) + r - lo.y) / cell - 0.5).floor()) as isize;
                if j1 < 0 {
                    return;
                }
                let j1 = (j1 as usize).min(ny - 1);
                for j in j0..=j1 {
                    let y = centre_y(j);
                    if let Some((x0, x1)) = capsule_row(a, b, r, y) {
                        let i0 = (((x0 - lo.x) / cell - 0.5).ceil().max(0.0)) as usize;
                        let i1 = ((x1 - lo.x) / cell - 0.5).floor();
                        if i1 < 0.0 {
                            continue;
                        }
                        let i1 = (i1 as usize).min(nx - 1);
                        let row = j * nx;
                        for i in i0..=i1 {
                            let c = row + i;
                            if last[c] != id {
                                last[c] = id;
                                count[c] = count[c].saturating_add(1);
                            }
                        }
                    }
                }
            };
            if n == 1 {
                stamp(
                    p.points[0],
                    p.points[0],
                    0.5 * road_width_mm * p.width_factors[0],
                );
            }
            for k in 0..edges {
                let (a, b) = (p.points[k], p.points[(k + 1) % n]);
                let f = 0.5 * (p.width_factors[k] + p.width_factors[(k + 1) % n]);
                stamp(a, b, 0.5 * road_width_mm * f);
            }
        }
        Some(Raster {
            lo,
            cell_mm: cell,
            nx,
            ny,
            count,
        })
    }

    /// Visit every cell with its centre and whether that lies inside the part `islands`
    /// (even-odd scanline over all their loops).
    pub fn scan_part(&self, islands: &[Region], mut visit: impl FnMut(usize, DVec2, bool)) {
        let (nx, ny, cell, lo) = (self.nx, self.ny, self.cell_mm, self.lo);
        let mut xs: Vec<f64> = Vec::new();
        let loops: Vec<&Vec<DVec2>> = islands.iter().flat_map(|r| r.loops()).collect();
        for j in 0..ny {
            let y = lo.y + (j as f64 + 0.5) * cell;
            xs.clear();
            for l in &loops {
                let m = l.len();
                for k in 0..m {
                    let (a, b) = (l[k], l[(k + 1) % m]);
                    if (a.y <= y) != (b.y <= y) {
                        xs.push(a.x + (y - a.y) / (b.y - a.y) * (b.x - a.x));
                    }
                }
            }
            xs.sort_by(f64::total_cmp);
            let row = j * nx;
            let mut inside_spans = xs.chunks_exact(2).peekable();
            for i in 0..nx {
                let x = lo.x + (i as f64 + 0.5) * cell;
                while let Some(s) = inside_spans.peek() {
                    if s[1] < x {
                        inside_spans.next();
                    } else {
                        break;
                    }
                }
                let inside = inside_spans.peek().is_some_and(|s| s[0] <= x && x <= s[1]);
                visit(row + i, DVec2::new(x, y), inside);
            }
        }
    }
}

/// The x interval of the capsule {p : dist(p, segment ab) ≤ r} on the line at height y.
fn capsule_row(a: DVec2, b: DVec2, r: f64, y: f64) -> Option<(f64, f64)> {
    let mut out: Option<(f64, f64)> = None;
    let mut join = |iv: (f64, f64)| {
        out = Some(match out {
            None => iv,
            Some((x0, x1)) => (x0.min(iv.0), x1.max(iv.1)),
        })
    };
    for c in [a, b] {
        let dy = y - c.y;
        if dy.abs() <= r {
            let h = (r * r - dy * dy).sqrt();
            join((c.x - h, c.x + h));
        }
    }
    let d = b - a;
    let len = d.length();
    if len > 0.0 {
        let u = d / len;
        let nrm = u.perp();
        let yy = y - a.y;
        // lo <= X * c + k <= hi, for (t along u in [0, len]) and (s along n in [-r, r]).
        let mut x0 = f64::NEG_INFINITY;
        let mut x1 = f64::INFINITY;
        for (c, k, lo, hi) in [(u.x, yy * u.y, 0.0, len), (nrm.x, yy * nrm.y, -r, r)] {
            if c.abs() < 1e-15 {
                if k < lo || k > hi {
                    return out;
                }
            } else {
                let (p, q) = ((lo - k) / c, (hi - k) / c);
                x0 = x0.max(p.min(q));
                x1 = x1.min(p.max(q));
            }
        }
        if x0 <= x1 {
            join((a.x + x0, a.x + x1));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::PathRole;

    fn road(points: Vec<DVec2>, closed: bool) -> ToolPath {
        ToolPath {
            role: PathRole::Contour { island: 0, j: 1 },
            width_factors: vec![1.0; points.len()],
            points,
            closed,
            composition: vec![1.0],
            seam_at_corner: false,
        }
    }

    fn rect(w: f64, h: f64) -> Region {
        Region::new(
            vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(w, 0.0),
                DVec2::new(w, h),
                DVec2::new(0.0, h),
            ],
            vec![],
        )
    }

    #[test]
    fn raster_lines_tile_a_rectangle() {
        // A 10 x 2 rectangle filled by 5 straight roads of width 0.4 (square ends
        // approximated by extending the centreline by nothing: round caps stick out).
        let part = rect(10.0, 2.0);
        let roads: Vec<ToolPath> = (0..5)
            .map(|k| {
                let y = 0.2 + 0.4 * k as f64;
                road(vec![DVec2::new(0.2, y), DVec2::new(9.8, y)], false)
            })
            .collect();
        let c = measure(&[part], &roads, 0.4, 0.01);
        assert_eq!(c.part_cells, 1000 * 200);
        // Voids only in the corners the round caps miss: 20 corners of (0.2² - π 0.2²/4).
        let corner = 0.04 - std::f64::consts::PI * 0.04 / 4.0;
        assert!(
            (c.void_fraction() - 20.0 * corner / 20.0).abs() < 5e-4,
            "{c:?}"
        );
        assert!(c.outside_fraction() < 1e-3, "{c:?}");
        // Neighbouring roads only touch: with the cell centres off round coordinates
        // (SAMPLE_PHASE) no line of cells on their shared edge counts for both.
        assert!(c.overlap_fraction() < 1e-4, "{c:?}");
        // A road of double width overlaps its neighbours.
        let mut wide = roads.clone();
        wide[2].width_factors = vec![2.0; 2];
        let c2 = measure(&[rect(10.0, 2.0)], &wide, 0.4, 0.01);
        assert!(c2.overlap_fraction() > 0.15, "{c2:?}");
    }

    #[test]
    fn roads_that_touch_on_a_cell_centre_line_do_not_overlap() {
        // The grid starts r_max + one cell below the part (y = -0.21), so without the
        // sample phase the cell centres lie on y = 0.005 + 0.01 j, and the two roads
        // below touch exactly on one of them (y = 0.405).
        let roads = vec![
            road(vec![DVec2::new(0.2, 0.205), DVec2::new(9.8, 0.205)], false),
            road(vec![DVec2::new(0.2, 0.605), DVec2::new(9.8, 0.605)], false),
        ];
        let c = measure(&[rect(10.0, 0.81)], &roads, 0.4, 0.01);
        assert_eq!(c.overlap_cells, 0, "{c:?}");
    }

    #[test]
    fn capsule_rows() {
        let a = DVec2::new(0.0, 0.0);
        let b = DVec2::new(4.0, 0.0);
        assert_eq!(capsule_row(a, b, 1.0, 0.0), Some((-1.0, 5.0)));
        assert!(capsule_row(a, b, 1.0, 1.5).is_none());
        let (x0, x1) = capsule_row(a, DVec2::new(0.0, 4.0), 1.0, 2.0).unwrap();
        assert!((x0 + 1.0).abs() < 1e-12 && (x1 - 1.0).abs() < 1e-12);
    }
}
