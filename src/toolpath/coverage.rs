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
use crate::geom::{edge_ends, loop_edges, Region};
use glam::DVec2;
use serde::{Deserialize, Serialize};
use std::ops::Range;

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

/// Rasters ([`Raster`], the gap fill's) larger than this many cells are made at a
/// coarser cell (memory bound: 5 bytes a cell).
pub const MAX_CELLS: usize = 200_000_000;

/// Coverage measures over more than this many cells are made at a coarser cell (time
/// bound: a 2 m square at 10 µm). The measure keeps only a band of rows at a time, so
/// its memory does not grow with the cell count.
pub const MAX_MEASURE_CELLS: u64 = 40_000_000_000;

/// Rows the coverage measure works through at a time.
const BAND_ROWS: usize = 256;

/// Measure the coverage of `paths` (road width `road_width_mm` times the vertex width
/// factors) over the part `islands` at `cell_mm` (coarsened by doubling if the grid would
/// pass [`MAX_MEASURE_CELLS`]; the cell used is in the result).
pub fn measure(
    islands: &[Region],
    paths: &[ToolPath],
    road_width_mm: f64,
    cell_mm: f64,
) -> Coverage {
    measure_with_voids(islands, paths, road_width_mm, cell_mm, 0).0
}

/// [`measure`] plus up to `max_void_points` centres of void cells (row by row from the
/// lowest, each row from the left).
///
/// Counted row by row on runs of cells, not cell by cell: per row of cell centres, the
/// runs each road's capsules cover (merged per road, so a road's own joints count
/// once), swept into runs of equal road count and met with the runs inside the part.
/// The counts are those of a per-cell raster ([`Raster`] with [`Raster::scan_part`]),
/// cell for cell, at a cost that grows with the rows and the roads, not with the cells:
/// a 130 mm layer at 10 µm is 169 M cells.
pub fn measure_with_voids(
    islands: &[Region],
    paths: &[ToolPath],
    road_width_mm: f64,
    cell_mm: f64,
    max_void_points: usize,
) -> (Coverage, Vec<DVec2>) {
    let Some(cells) = Cells::over(islands, paths, road_width_mm, cell_mm, MAX_MEASURE_CELLS) else {
        return (Coverage::default(), Vec::new());
    };
    let mut count = RowCount {
        cells,
        cov: Coverage {
            cell_mm: cells.cell_mm,
            ..Default::default()
        },
        voids: Vec::new(),
        max_void_points,
    };
    let mut roads = capsules(&cells, paths, road_width_mm);
    let mut part = boundary_rows(&cells, islands);
    // Per row of the band: (road, first cell, end cell) of each capsule's run.
    let mut band: Vec<Vec<(u32, u32, u32)>> = vec![Vec::new(); BAND_ROWS];
    let mut merged: Vec<(u32, u32)> = Vec::new();
    let mut events: Vec<(u32, i32)> = Vec::new();
    let mut inside: Vec<(u32, u32)> = Vec::new();
    let mut xs: Vec<f64> = Vec::new();
    for first in (0..cells.ny).step_by(BAND_ROWS) {
        let rows = first..(first + BAND_ROWS).min(cells.ny);
        roads.advance(&rows);
        stamp_capsules(&cells, &roads, &rows, &mut band);
        part.advance(&rows);
        for j in rows {
            let runs = &mut band[j - first];
            merge_road_runs(runs, &mut merged);
            runs.clear();
            events.clear();
            for &(s, e) in &merged {
                events.push((s, 1));
                events.push((e, -1));
            }
            events.sort_unstable();
            inside_runs(&cells, &part, j, &mut xs, &mut inside);
            count.row(j, &events, &inside);
        }
    }
    (count.cov, count.voids)
}

/// The runs of the capsules reaching the band `rows` (those `roads` holds after
/// advancing to it), as (road, first cell, end cell), onto `band` (a list per row of
/// the band).
fn stamp_capsules(
    cells: &Cells,
    roads: &RowSweep<Capsule>,
    rows: &Range<usize>,
    band: &mut [Vec<(u32, u32, u32)>],
) {
    for &(j0, j1, (a, b, r, road)) in roads.active() {
        for j in j0.max(rows.start)..=j1.min(rows.end - 1) {
            if let Some((i0, i1)) = cells.capsule_run(a, b, r, j) {
                band[j - rows.start].push((road, i0 as u32, i1 as u32 + 1));
            }
        }
    }
}

/// One row's capsule runs (`runs`, as (road, first cell, end cell); sorted here), each
/// road's merged (a cell counts once per road), as (first cell, end cell) into `merged`.
fn merge_road_runs(runs: &mut [(u32, u32, u32)], merged: &mut Vec<(u32, u32)>) {
    runs.sort_unstable();
    merged.clear();
    let mut k = 0;
    while k < runs.len() {
        let (road, mut start, mut end) = runs[k];
        k += 1;
        while k < runs.len() && runs[k].0 == road {
            let (_, s, e) = runs[k];
            if s > end {
                merged.push((start, end));
                start = s;
            }
            end = end.max(e);
            k += 1;
        }
        merged.push((start, end));
    }
}

/// The counts of the measure so far, row by row.
struct RowCount {
    cells: Cells,
    cov: Coverage,
    voids: Vec<DVec2>,
    max_void_points: usize,
}

impl RowCount {
    /// Count row `j`: `events` are the roads' merged runs' starts (+1) and ends (−1) in
    /// cell order, `inside` the runs of cells inside the part.
    fn row(&mut self, j: usize, events: &[(u32, i32)], inside: &[(u32, u32)]) {
        let y = self.cells.centre_y(j);
        let mut spans = inside.iter().copied().peekable();
        let (mut at, mut count) = (0u32, 0i32);
        let mut k = 0;
        while k < events.len() {
            let pos = events[k].0;
            if pos > at {
                self.tally(y, &mut spans, at, pos, count);
                at = pos;
            }
            while k < events.len() && events[k].0 == pos {
                count += events[k].1;
                k += 1;
            }
        }
        if (at as usize) < self.cells.nx {
            self.tally(y, &mut spans, at, self.cells.nx as u32, count);
        }
    }

    /// Cells [s, e) of the row at `y` covered by `roads` different roads, met with the
    /// runs inside the part (`spans`, from the first that may reach past `s`).
    fn tally(
        &mut self,
        y: f64,
        spans: &mut std::iter::Peekable<impl Iterator<Item = (u32, u32)>>,
        s: u32,
        e: u32,
        roads: i32,
    ) {
        let cov = &mut self.cov;
        let mut inside_cells = 0u64;
        while let Some(&(a, b)) = spans.peek() {
            if b <= s {
                spans.next();
                continue;
            }
            if a >= e {
                break;
            }
            let (lo, hi) = (a.max(s), b.min(e));
            inside_cells += u64::from(hi - lo);
            if roads == 0 {
                for i in lo..hi {
                    if self.voids.len() >= self.max_void_points {
                        break;
                    }
                    self.voids
                        .push(DVec2::new(self.cells.centre_x(i as usize), y));
                }
            }
            if b > e {
                break;
            }
            spans.next();
        }
        cov.part_cells += inside_cells;
        match roads {
            0 => cov.void_cells += inside_cells,
            1 => {}
            _ => cov.overlap_cells += inside_cells,
        }
        if roads > 0 {
            cov.outside_cells += u64::from(e - s) - inside_cells;
        }
    }
}

/// A square grid of cells over a layer: cell (i, j) has its centre at `lo` + ((i + ½),
/// (j + ½)) cells.
#[derive(Clone, Copy, Debug)]
struct Cells {
    lo: DVec2,
    cell_mm: f64,
    nx: usize,
    ny: usize,
}

impl Cells {
    /// Over the bounds of `islands` and of the roads at `cell_mm`, coarsened by
    /// doubling past `max_cells`; none when nothing is finite.
    fn over(
        islands: &[Region],
        paths: &[ToolPath],
        road_width_mm: f64,
        cell_mm: f64,
        max_cells: u64,
    ) -> Option<Cells> {
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
        // Finite extents, so that doubling the cell brings the count down.
        if !(hi - lo).is_finite() {
            return None;
        }
        let mut cell = cell_mm;
        let size = |c: f64| {
            (
                ((hi.x - lo.x) / c).ceil() as usize + 1,
                ((hi.y - lo.y) / c).ceil() as usize + 1,
            )
        };
        // Cell numbers along a row fit in a u32 (the measure's runs).
        while (size(cell).0 as u64).saturating_mul(size(cell).1 as u64) > max_cells
            || size(cell).0 > u32::MAX as usize
        {
            cell *= 2.0;
        }
        let (nx, ny) = size(cell);
        Some(Cells {
            lo,
            cell_mm: cell,
            nx,
            ny,
        })
    }

    fn centre_x(&self, i: usize) -> f64 {
        self.lo.x + (i as f64 + 0.5) * self.cell_mm
    }

    fn centre_y(&self, j: usize) -> f64 {
        self.lo.y + (j as f64 + 0.5) * self.cell_mm
    }

    /// The rows whose centres the capsule of radius `r` about segment ab can reach.
    fn capsule_rows(&self, a: DVec2, b: DVec2, r: f64) -> Option<(usize, usize)> {
        let (lo, cell) = (self.lo, self.cell_mm);
        let j0 = (((a.y.min(b.y) - r - lo.y) / cell - 0.5).ceil().max(0.0)) as usize;
        let j1 = (((a.y.max(b.y) + r - lo.y) / cell - 0.5).floor()) as isize;
        if j1 < 0 {
            return None;
        }
        Some((j0, (j1 as usize).min(self.ny - 1)))
    }

    /// The cells [i0, i1] of row `j` whose centres the capsule covers, if any.
    fn capsule_run(&self, a: DVec2, b: DVec2, r: f64, j: usize) -> Option<(usize, usize)> {
        let (x0, x1) = capsule_row(a, b, r, self.centre_y(j))?;
        let (lo, cell) = (self.lo, self.cell_mm);
        let i0 = (((x0 - lo.x) / cell - 0.5).ceil().max(0.0)) as usize;
        let i1 = ((x1 - lo.x) / cell - 0.5).floor();
        if i1 < 0.0 {
            return None;
        }
        let i1 = (i1 as usize).min(self.nx - 1);
        (i0 <= i1).then_some((i0, i1))
    }
}

/// Items each reaching rows [first, last] of a grid, taken band by band in row order:
/// after [`RowSweep::advance`] to a band, [`RowSweep::active`] gives those that reach it.
struct RowSweep<T> {
    /// (first row, last row, item), by first row.
    items: Vec<(usize, usize, T)>,
    /// Items before this one have been taken into `active`.
    next: usize,
    active: Vec<usize>,
}

impl<T> RowSweep<T> {
    fn new(mut items: Vec<(usize, usize, T)>) -> RowSweep<T> {
        items.sort_by_key(|e| e.0);
        RowSweep {
            items,
            next: 0,
            active: Vec::new(),
        }
    }

    /// Move on to the band `rows` (bands in order).
    fn advance(&mut self, rows: &Range<usize>) {
        while self.next < self.items.len() && self.items[self.next].0 < rows.end {
            self.active.push(self.next);
            self.next += 1;
        }
        let items = &self.items;
        self.active.retain(|&k| items[k].1 >= rows.start);
    }

    /// The items reaching the band last advanced to.
    fn active(&self) -> impl Iterator<Item = &(usize, usize, T)> {
        self.active.iter().map(|&k| &self.items[k])
    }
}

/// Every road edge's capsule (the bead it lays down) as (a, b, radius, road number from
/// 1), swept by the rows it can reach: what the coverage measure stamps band by band.
fn capsules(cells: &Cells, paths: &[ToolPath], road_width_mm: f64) -> RowSweep<Capsule> {
    let mut edges = Vec::new();
    for_each_capsule(paths, road_width_mm, |id, a, b, r| {
        if let Some((j0, j1)) = cells.capsule_rows(a, b, r) {
            edges.push((j0, j1, (a, b, r, id)));
        }
    });
    RowSweep::new(edges)
}

/// A road edge's capsule: ends, radius, road number from 1.
type Capsule = (DVec2, DVec2, f64, u32);

/// Each road edge's capsule as (road number from 1, a, b, radius): an edge at the mean
/// of its two vertices' widths; a one-point road as a disc.
fn for_each_capsule(
    paths: &[ToolPath],
    road_width_mm: f64,
    mut f: impl FnMut(u32, DVec2, DVec2, f64),
) {
    for (pid, p) in paths.iter().enumerate() {
        let id = pid as u32 + 1;
        let n = p.points.len();
        if n == 0 {
            continue;
        }
        let w = |i: usize| p.width_factors.get(i).copied().unwrap_or(1.0);
        if n == 1 {
            f(id, p.points[0], p.points[0], 0.5 * road_width_mm * w(0));
        }
        for (k, j) in edge_ends(n, p.closed) {
            let (a, b) = (p.points[k], p.points[j]);
            let f_mean = 0.5 * (w(k) + w(j));
            f(id, a, b, 0.5 * road_width_mm * f_mean);
        }
    }
}

/// The part's boundary edges (loops of `islands`), swept by the rows whose centre lines
/// they can cross (a row more either side: [`inside_runs`] decides exactly).
fn boundary_rows(cells: &Cells, islands: &[Region]) -> RowSweep<(DVec2, DVec2)> {
    let row = |y: f64| (y - cells.lo.y) / cells.cell_mm - 0.5;
    let mut edges = Vec::new();
    for l in islands.iter().flat_map(|r| r.loops()) {
        for (a, b) in loop_edges(l) {
            let (j0, j1) = (row(a.y.min(b.y)).floor(), row(a.y.max(b.y)).ceil());
            if !(j0.is_finite() && j1.is_finite()) || j1 < 0.0 {
                continue;
            }
            edges.push((j0.max(0.0) as usize, j1 as usize, (a, b)));
        }
    }
    RowSweep::new(edges)
}

/// The runs [start, end) of row `j`'s cells whose centres lie inside the part (even-odd
/// over the `boundary` edges reaching the row's band), in order; `xs` is scratch.
fn inside_runs(
    cells: &Cells,
    boundary: &RowSweep<(DVec2, DVec2)>,
    j: usize,
    xs: &mut Vec<f64>,
    out: &mut Vec<(u32, u32)>,
) {
    let y = cells.centre_y(j);
    xs.clear();
    for &(_, _, (a, b)) in boundary.active() {
        if (a.y <= y) != (b.y <= y) {
            xs.push(a.x + (y - a.y) / (b.y - a.y) * (b.x - a.x));
        }
    }
    xs.sort_by(f64::total_cmp);
    out.clear();
    let nx = cells.nx;
    for s in xs.chunks_exact(2) {
        let (s0, s1) = (s[0], s[1]);
        // First cell whose centre is at or past s0, first past s1 (the centres' own
        // sums decide, so a centre on an edge counts as the scan would).
        let guess = |x: f64| ((x - cells.lo.x) / cells.cell_mm - 0.5).ceil();
        let clamp = |g: f64| if g <= 0.0 { 0 } else { (g as usize).min(nx) };
        let mut i = clamp(guess(s0));
        while i > 0 && cells.centre_x(i - 1) >= s0 {
            i -= 1;
        }
        while i < nx && cells.centre_x(i) < s0 {
            i += 1;
        }
        let mut e = clamp(guess(s1)).max(i);
        while e > i && cells.centre_x(e - 1) > s1 {
            e -= 1;
        }
        while e < nx && cells.centre_x(e) <= s1 {
            e += 1;
        }
        // Runs touching on a shared centre count it once.
        let i = out.last().map_or(i, |&(_, end)| i.max(end as usize));
        if i < e {
            out.push((i as u32, e as u32));
        }
    }
}

/// A square grid over a layer with, per cell, how many different roads cover its centre
/// (saturating at 255): the gap fill's raster, whose cells it groups into gaps.
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
        let cells = Cells::over(islands, paths, road_width_mm, cell_mm, MAX_CELLS as u64)?;
        let (nx, ny) = (cells.nx, cells.ny);
        // Roads: count of different roads covering each cell.
        let mut count = vec![0u8; nx * ny];
        let mut last = vec![0u32; nx * ny];
        for_each_capsule(paths, road_width_mm, |id, a, b, r| {
            let Some((j0, j1)) = cells.capsule_rows(a, b, r) else {
                return;
            };
            for j in j0..=j1 {
                if let Some((i0, i1)) = cells.capsule_run(a, b, r, j) {
                    for c in j * nx + i0..=j * nx + i1 {
                        if last[c] != id {
                            last[c] = id;
                            count[c] = count[c].saturating_add(1);
                        }
                    }
                }
            }
        });
        Some(Raster {
            lo: cells.lo,
            cell_mm: cells.cell_mm,
            nx,
            ny,
            count,
        })
    }

    fn cells(&self) -> Cells {
        Cells {
            lo: self.lo,
            cell_mm: self.cell_mm,
            nx: self.nx,
            ny: self.ny,
        }
    }

    /// Visit every cell with its centre and whether that lies inside the part `islands`
    /// (even-odd scanline over all their loops).
    pub fn scan_part(&self, islands: &[Region], mut visit: impl FnMut(usize, DVec2, bool)) {
        let cells = self.cells();
        let mut part = boundary_rows(&cells, islands);
        let (mut xs, mut inside) = (Vec::new(), Vec::new());
        for first in (0..cells.ny).step_by(BAND_ROWS) {
            let rows = first..(first + BAND_ROWS).min(cells.ny);
            part.advance(&rows);
            for j in rows {
                inside_runs(&cells, &part, j, &mut xs, &mut inside);
                let y = cells.centre_y(j);
                let mut runs = inside.iter().peekable();
                for i in 0..cells.nx {
                    while runs.next_if(|r| r.1 as usize <= i).is_some() {}
                    let is_in = runs.peek().is_some_and(|r| r.0 as usize <= i);
                    visit(j * cells.nx + i, DVec2::new(cells.centre_x(i), y), is_in);
                }
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
    fn roads_spanning_more_than_a_float_measure_nothing() {
        // Each end is finite but the extent is not: no cell size can cover it.
        let roads = vec![road(
            vec![DVec2::new(-1e308, 0.0), DVec2::new(1e308, 0.0)],
            false,
        )];
        let c = measure(&[rect(10.0, 2.0)], &roads, 0.4, 0.01);
        assert_eq!(c, Coverage::default());
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

    /// The coverage counted cell by cell on the gap fill's raster: what the measure's
    /// runs must give, cell for cell.
    fn per_cell(
        islands: &[Region],
        paths: &[ToolPath],
        w: f64,
        cell_mm: f64,
        max_voids: usize,
    ) -> (Coverage, Vec<DVec2>) {
        let raster = Raster::of_roads(islands, paths, w, cell_mm).unwrap();
        let mut cov = Coverage {
            cell_mm: raster.cell_mm,
            ..Default::default()
        };
        let mut voids = Vec::new();
        raster.scan_part(islands, |c, centre, inside| {
            match (inside, raster.count[c]) {
                (true, 0) => {
                    cov.part_cells += 1;
                    cov.void_cells += 1;
                    if voids.len() < max_voids {
                        voids.push(centre);
                    }
                }
                (true, 1) => cov.part_cells += 1,
                (true, _) => {
                    cov.part_cells += 1;
                    cov.overlap_cells += 1;
                }
                (false, 0) => {}
                (false, _) => cov.outside_cells += 1,
            }
        });
        (cov, voids)
    }

    /// A star-shaped loop about `c` with the given radii at equal angles.
    fn star(c: DVec2, radii: &[f64]) -> Vec<DVec2> {
        let n = radii.len() as f64;
        radii
            .iter()
            .enumerate()
            .map(|(k, r)| c + DVec2::from_angle(std::f64::consts::TAU * k as f64 / n) * *r)
            .collect()
    }

    #[test]
    fn runs_count_what_the_raster_counts_on_a_real_layer() {
        // The fibers example's layer 0 as built (flow raise, slanted ends, gap fill):
        // roads of every kind, at the report's 10 µm.
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/examples/fibers.toml");
        let job =
            crate::job::Job::from_toml(&std::fs::read_to_string(path).unwrap(), path).unwrap();
        let slices = job.layer_slices(0, job.extruded_layers().unwrap());
        let s = &slices[0];
        let plan = crate::plan::plan_layer(
            0,
            s.layer.z_mm,
            s.layer.thickness_mm,
            &s.layer.islands,
            &s.design,
            &job.plan,
        )
        .unwrap();
        let settings = crate::pipeline::ProcessSettings::for_nozzle(job.plan.nozzle_mm);
        let paths =
            crate::pipeline::layer_paths(&plan, &settings, &crate::pipeline::StreamState::new());
        let islands = &s.layer.islands;
        let w = settings.road_width();
        let runs = measure_with_voids(islands, &paths, w, 0.01, 50_000);
        assert_eq!(runs, per_cell(islands, &paths, w, 0.01, 50_000));
        assert!(
            runs.0.void_cells > 0 && runs.0.overlap_cells > 0,
            "{:?}",
            runs.0
        );
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig {
            cases: 64,
            rng_seed: proptest::test_runner::RngSeed::Fixed(0xC0_7E4A),
            ..proptest::prelude::ProptestConfig::default()
        })]

        /// Random roads (open, closed, single points, any widths) over a random part with
        /// a hole, and a second island touching nothing: the runs give the raster's
        /// counts and the same void cells in the same order.
        #[test]
        fn runs_count_what_the_raster_counts(
            outer in proptest::collection::vec(3.0f64..6.0, 5..24),
            hole in proptest::collection::vec(0.5f64..2.0, 3..12),
            roads in proptest::collection::vec(
                (proptest::collection::vec((-7.0f64..7.0, -7.0f64..7.0, 0.3f64..1.8), 1..12),
                 proptest::bool::ANY),
                0..14),
            cell in 0.02f64..0.08,
        ) {
            let islands = vec![
                Region::new(star(DVec2::ZERO, &outer), vec![star(DVec2::ZERO, &hole)]),
                Region::new(star(DVec2::new(9.0, 2.0), &[1.0, 1.5, 1.2, 0.8]), vec![]),
            ];
            let paths: Vec<ToolPath> = roads
                .iter()
                .map(|(pts, closed)| ToolPath {
                    width_factors: pts.iter().map(|p| p.2).collect(),
                    ..road(pts.iter().map(|p| DVec2::new(p.0, p.1)).collect(), *closed)
                })
                .collect();
            let runs = measure_with_voids(&islands, &paths, 0.4, cell, 300);
            proptest::prop_assert_eq!(runs, per_cell(&islands, &paths, 0.4, cell, 300));
        }
    }
}
