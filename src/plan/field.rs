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
//!    vector distance transform seeded with exact nearest points near each boundary,
//!    swept over each row's stretch of the convex hull of Ce (the nodes outside it are
//!    read as far outside).
//! 4. d per node, extended continuously outside the material (negative in holes, above
//!    1 outside Ce) so every level set is a closed loop.
//! 5. Marching triangles (four triangles per cell around its mean) trace the level
//!    sets of the piecewise-linear interpolant: which cell sides each level crosses
//!    and how the crossings connect. Level sets of one continuous piecewise-linear
//!    function never cross each other. Which cell sides a level's piece joins is read
//!    off a 32-case table built from those triangles, and the pieces are linked into
//!    loops through the sides they share, as the cells are visited. Only cells with
//!    a corner where d < 1 (per row, from the first such node to the last) are
//!    visited: the levels, all below 1, cross no other cell.
//! 6. Each crossing of a cell side is moved along that side onto the exact level set
//!    (Newton steps on d computed from the boundary edges nearest the side's two
//!    nodes), within its own stretch of the side, so levels keep their order along
//!    every side; the piece of a level through a cell runs straight from side to side,
//!    and pieces whose ends keep their order do not cross. A first step under 0.01 mm
//!    where the walks from both nodes find the same nearest boundary points is not
//!    checked by a second (its quadratic error is far under 1e-4 mm). Every other
//!    crossing round a loop is placed first; one between two that lie on the level
//!    set, where the exact normal turns so little from one to the other that the
//!    straight piece joining them strays at most half the contour deviation, is left
//!    out (the planner simplifies the loops by the deviation anyway). Such a piece
//!    spans two cells and so is not held to the sides' order, but it strays at most
//!    a sixteenth of a nozzle (the deviation is at most a quarter), and consecutive
//!    levels lie about L_short / m (≈ R_mach) apart.
//! 7. Where the exact normal turns sharply between two crossings (a corner of the
//!    level set on the medial axis, where the nearest boundary point jumps), the
//!    corner is added: from where the two tangents meet, Newton steps along the
//!    gradient onto the exact level set. Only where the tangents meet ahead of one
//!    crossing and behind the other along the level set (a corner or tip between
//!    them); across an S-bend they meet beyond both, and the point is sought from the
//!    middle of the piece instead (a point placed from beyond an end would make the
//!    loop double back on itself there). A crossing the exact level set does not reach
//!    within its stretch (the grid cut the tip of a corner short) is left out between
//!    two that lie on it, so the corner between those is found.
//!
//! How far the contours lie from the exact level sets, on the bench region, the femur
//! and the non-star example, and how to measure it: docs/planner-accuracy.md.

use crate::geom::{loop_edges, next_in_loop, prev_in_loop, Region};
use glam::DVec2;
use pool::{give, take};
use std::ops::Range;

/// Grid-sized buffers kept by each thread between the fields it builds.
///
/// A layer's field and level sets fill a few MB of grid-sized arrays. Freed at the end
/// of every layer, they let the allocator return the pages to the kernel and fault
/// fresh ones in for the next layer, a measurable share of the planning time when one
/// thread plans layer after layer, as the daemon does while it streams (figures in
/// docs/planner-accuracy.md). Each thread (the daemon's planning thread, the rayon
/// workers of `plan_layers`) keeps the arrays of its last field instead: up to
/// `KEEP_COUNT` buffers of each element type (the level sets take one per level),
/// together at most `KEEP_BYTES`.
///
/// All of them, not only the largest: a big buffer kept while smaller ones come and go
/// leaves glibc's trim threshold at its default, and the heap's top is handed back and
/// faulted in again instead.
mod pool {
    use std::cell::RefCell;
    use std::thread::LocalKey;

    /// Buffers of one element type, kept by one thread.
    pub(super) type Shelf<T> = LocalKey<RefCell<Vec<Vec<T>>>>;

    /// The most a shelf keeps, bytes (two grids of a million nodes of f64).
    const KEEP_BYTES: usize = 16 << 20;
    /// How many buffers a shelf keeps.
    const KEEP_COUNT: usize = 32;

    /// A buffer of `n` copies of `fill`, reusing one from the shelf where it has one.
    pub(super) fn take<T: Clone + 'static>(shelf: &'static Shelf<T>, n: usize, fill: T) -> Vec<T> {
        let kept = shelf
            .try_with(|s| {
                let mut s = s.try_borrow_mut().ok()?;
                // The smallest that holds n, else the largest (grown once).
                let i = s
                    .iter()
                    .enumerate()
                    .filter(|(_, v)| v.capacity() >= n)
                    .min_by_key(|(_, v)| v.capacity())
                    .or_else(|| s.iter().enumerate().max_by_key(|(_, v)| v.capacity()))
                    .map(|(i, _)| i)?;
                Some(s.swap_remove(i))
            })
            .ok()
            .flatten();
        let mut v = kept.unwrap_or_default();
        v.clear();
        v.resize(n, fill);
        v
    }

    /// Put `v` back on the shelf for the next [`take`].
    pub(super) fn give<T: 'static>(shelf: &'static Shelf<T>, mut v: Vec<T>) {
        if v.capacity() == 0 {
            return;
        }
        v.clear();
        let bytes = |v: &Vec<T>| v.capacity() * std::mem::size_of::<T>();
        let _ = shelf.try_with(|s| {
            if let Ok(mut s) = s.try_borrow_mut() {
                let kept: usize = s.iter().map(bytes).sum();
                if s.len() < KEEP_COUNT && kept + bytes(&v) <= KEEP_BYTES {
                    s.push(v);
                }
            }
        });
    }

    thread_local! {
        pub(super) static F64: RefCell<Vec<Vec<f64>>> = const { RefCell::new(Vec::new()) };
        pub(super) static U32: RefCell<Vec<Vec<u32>>> = const { RefCell::new(Vec::new()) };
        pub(super) static I32: RefCell<Vec<Vec<i32>>> = const { RefCell::new(Vec::new()) };
        pub(super) static BOOL: RefCell<Vec<Vec<bool>>> = const { RefCell::new(Vec::new()) };
        pub(super) static NEAREST: RefCell<Vec<Vec<super::Nearest>>> = const { RefCell::new(Vec::new()) };
        pub(super) static SIDE: RefCell<Vec<Vec<(u64, u32)>>> = const { RefCell::new(Vec::new()) };
        pub(super) static SEGMENT: RefCell<Vec<Vec<super::Segment>>> = const { RefCell::new(Vec::new()) };
    }
}

/// `x.floor()` for the grid lookups: the same value wherever the result is clamped to
/// a grid (it differs only for NaN, infinities and |x| ≥ 2⁶³, which give 0 or the
/// clamped extreme either way), without the libm call the baseline x86-64 target makes
/// for `floor`.
#[inline]
fn floor_clamped(x: f64) -> f64 {
    let i = x as i64 as f64;
    if i > x {
        i - 1.0
    } else {
        i
    }
}

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
    /// Ce's edges and each node's nearest one.
    outer: Boundary,
    outer_seg: Vec<u32>,
    /// Ci: the holes' edges and each node's nearest one, or the centre point.
    inner: Inner,
}

/// Ci of a [`DistanceField`].
enum Inner {
    Holes {
        holes: Boundary,
        seg: Vec<u32>,
    },
    Centre(DVec2),
    /// [`DistanceField::outer_only`]: no Ci.
    None,
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
        for (a, b) in loop_edges(l) {
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
    let mut inside = take(&pool::BOOL, grid.nx * grid.ny, false);
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

/// Nodes either side of the material that the distance transforms sweep (see
/// [`distance_to_loops`]): the crossings of the outermost levels lie on cell sides
/// from a material node to its neighbour.
const SPAN_MARGIN: usize = 2;

/// Per grid row, the columns the distance transforms sweep: the row's stretch of the
/// convex hull of the nodes inside Ce, [`SPAN_MARGIN`] wider, over the rows up to
/// [`SPAN_MARGIN`] either side; empty for a row with none near.
///
/// The hull, not the nodes inside Ce themselves: a material node's nearest point on Ci
/// can lie across a gap outside Ce (a C-shaped part), and the straight line to it
/// (along which the transform carries it) stays inside the hull.
fn row_spans(grid: &Grid, in_outer: &[bool]) -> Vec<Range<usize>> {
    let own: Vec<(f64, f64, f64)> = in_outer
        .chunks_exact(grid.nx)
        .enumerate()
        .filter_map(|(r, row)| {
            let first = row.iter().position(|&i| i)?;
            let last = row.iter().rposition(|&i| i)?;
            Some((r as f64, first as f64, last as f64))
        })
        .collect();
    let left = hull_side(own.iter().map(|&(r, first, _)| DVec2::new(r, first)), false);
    let right = hull_side(own.iter().map(|&(r, _, last)| DVec2::new(r, last)), true);
    let extent = |r: usize| -> Option<(f64, f64)> {
        Some((side_at(&left, r as f64)?, side_at(&right, r as f64)?))
    };
    (0..grid.ny)
        .map(|r| {
            let (first, last) = (r.saturating_sub(SPAN_MARGIN)..(r + SPAN_MARGIN + 1).min(grid.ny))
                .filter_map(extent)
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (f, l)| {
                    (a.min(f), b.max(l))
                });
            if first > last {
                0..0
            } else {
                (first.floor().max(0.0) as usize).saturating_sub(SPAN_MARGIN)
                    ..((last.ceil().max(0.0) as usize) + SPAN_MARGIN + 1).min(grid.nx)
            }
        })
        .collect()
}

/// One side of the convex hull of points given in increasing `x` (a row number, with
/// the column in `y`): the greatest convex function below them (`upper` false) or
/// the least concave one above them (`upper` true), as its corners.
fn hull_side(points: impl Iterator<Item = DVec2>, upper: bool) -> Vec<DVec2> {
    let mut hull: Vec<DVec2> = Vec::new();
    for p in points {
        while let [.., a, b] = hull[..] {
            let turn = (b - a).perp_dot(p - a);
            if (upper && turn >= 0.0) || (!upper && turn <= 0.0) {
                hull.pop();
            } else {
                break;
            }
        }
        hull.push(p);
    }
    hull
}

/// A [`hull_side`] at `x`; none outside its corners' range.
fn side_at(side: &[DVec2], x: f64) -> Option<f64> {
    let i = side.partition_point(|p| p.x < x);
    let b = *side.get(i)?;
    if b.x == x {
        return Some(b.y);
    }
    let a = *side.get(i.checked_sub(1)?)?;
    Some(a.y + (b.y - a.y) * (x - a.x) / (b.x - a.x))
}

/// A node's nearest boundary point so far (NaN: none yet), its squared distance and the
/// boundary segment it lies on (see [`Boundary`]).
#[derive(Clone, Copy)]
struct Nearest {
    q: DVec2,
    d2: f64,
    seg: u32,
}

/// The edges of a set of closed loops, numbered loop after loop, with each edge's loop
/// (to reach its neighbours along the loop).
struct Boundary {
    segs: Vec<Edge>,
    /// First edge and edge count of the loop of each edge.
    loop_of: Vec<(u32, u32)>,
}

/// A boundary edge from `a` to `a + ab`, with `1 / |ab|²` (0 for a point) for the
/// nearest-point projections.
#[derive(Clone, Copy)]
struct Edge {
    a: DVec2,
    ab: DVec2,
    inv_len2: f64,
}

impl Boundary {
    fn of(loops: &[&Vec<DVec2>]) -> Boundary {
        let mut segs = Vec::new();
        let mut loop_of = Vec::new();
        for l in loops {
            let (start, n) = (segs.len() as u32, l.len() as u32);
            for (a, b) in loop_edges(l) {
                let len2 = (b - a).length_squared();
                segs.push(Edge {
                    a,
                    ab: b - a,
                    inv_len2: if len2 > 0.0 { 1.0 / len2 } else { 0.0 },
                });
                loop_of.push((start, n));
            }
        }
        Boundary { segs, loop_of }
    }

    /// The distance from `p` to the boundary and the nearest point, for `p` near grid
    /// nodes whose nearest edges are `seeds`: from each of those edges, walk along its
    /// loop while the distance falls. The nearest point of a point between the nodes
    /// lies along the loop from one of theirs (it moves continuously, except across
    /// the medial axis, where it jumps from near one to near another).
    ///
    /// Also whether every seed's walk ended on the same nearest point (no other local
    /// minimum of the distance, as beside the medial axis).
    fn near(&self, seeds: impl IntoIterator<Item = u32>, p: DVec2) -> (f64, DVec2, bool) {
        let mut best = (f64::INFINITY, p);
        let mut last = None;
        let mut agree = true;
        for s in seeds {
            if last == Some(s) {
                continue;
            }
            let here = self.descend(s, p);
            if last.is_some() && here.1 != best.1 {
                agree = false;
            }
            last = Some(s);
            if here.0 < best.0 {
                best = here;
            }
        }
        (best.0.sqrt(), best.1, agree)
    }

    /// Squared distance and nearest point of `p` on edge `k`.
    fn to_edge(&self, k: u32, p: DVec2) -> (f64, DVec2) {
        let Edge { a, ab, inv_len2 } = self.segs[k as usize];
        let t = ((p - a).dot(ab) * inv_len2).clamp(0.0, 1.0);
        let q = a + ab * t;
        (p.distance_squared(q), q)
    }

    /// From edge `s`, the local minimum of the squared distance to `p` along its loop.
    fn descend(&self, s: u32, p: DVec2) -> (f64, DVec2) {
        let Some(&(start, n)) = self.loop_of.get(s as usize) else {
            return (f64::INFINITY, p);
        };
        // The next edge round the loop.
        let step = |k: u32, forward: bool| {
            let (i, n) = ((k - start) as usize, n as usize);
            start
                + if forward {
                    next_in_loop(i, n)
                } else {
                    prev_in_loop(i, n)
                } as u32
        };
        let mut best = self.to_edge(s, p);
        for forward in [true, false] {
            let mut k = s;
            for _ in 1..n {
                k = step(k, forward);
                let here = self.to_edge(k, p);
                if here.0 >= best.0 {
                    break;
                }
                best = here;
            }
        }
        best
    }
}

/// Vector distance transform: distance from every node to the nearest point of the
/// loops' edges, exact near the edges and propagated (8SSEDT-style) elsewhere, and the
/// edge of `boundary` that point lies on. Nodes carry
/// their nearest boundary point and the squared distance to it: squared distances
/// order the same as distances and spare a square root per relaxation.
///
/// The passes sweep each row only over `spans[row]` (columns; see
/// [`row_spans`]): the nodes inside Ce and a margin about them, all that the
/// field's values are read at. Nodes beyond keep their exact distance where they lie
/// near an edge and infinity elsewhere.
fn distance_to_loops(
    grid: &Grid,
    boundary: &Boundary,
    spans: &[Range<usize>],
) -> (Vec<f64>, Vec<u32>) {
    let mut near = seed_near_edges(grid, boundary);
    // Node abscissae once (the same sums as `Grid::node`), not a conversion per relaxation.
    let xs = grid.xs();
    forward_pass(grid, &xs, spans, &mut near);
    backward_pass(grid, &xs, spans, &mut near);
    let n = grid.nx * grid.ny;
    let mut d = take(&pool::F64, n, 0.0);
    let mut seg = take(&pool::U32, n, 0);
    for ((d, seg), near) in d.iter_mut().zip(&mut seg).zip(&near) {
        *d = near.d2.sqrt();
        *seg = near.seg;
    }
    give(&pool::NEAREST, near);
    (d, seg)
}

/// The seeds of [`distance_to_loops`]: each node within 1.5 cells of a boundary edge's
/// box gets its exact nearest point on the nearest such edge; the rest none yet.
fn seed_near_edges(grid: &Grid, boundary: &Boundary) -> Vec<Nearest> {
    let (nx, ny) = (grid.nx, grid.ny);
    let mut near = take(
        &pool::NEAREST,
        nx * ny,
        Nearest {
            q: DVec2::splat(f64::NAN),
            d2: f64::INFINITY,
            seg: 0,
        },
    );
    let band = 1.5 * grid.h;
    for (k, edge) in boundary.segs.iter().enumerate() {
        let (a, b) = (edge.a, edge.a + edge.ab);
        let lo = (a.min(b) - DVec2::splat(band) - grid.origin) / grid.h;
        let hi = (a.max(b) + DVec2::splat(band) - grid.origin) / grid.h;
        let (c0, r0) = (lo.x.ceil().max(0.0) as usize, lo.y.ceil().max(0.0) as usize);
        let (c1, r1) = (
            (hi.x.floor().max(0.0) as usize).min(nx - 1),
            (hi.y.floor().max(0.0) as usize).min(ny - 1),
        );
        for r in r0..=r1 {
            for c in c0..=c1 {
                let (d2, q) = boundary.to_edge(k as u32, grid.node(c, r));
                let here = &mut near[r * nx + c];
                if d2 < here.d2 {
                    *here = Nearest {
                        q,
                        d2,
                        seg: k as u32,
                    };
                }
            }
        }
    }
    near
}

/// Offer a node (at `p`) the nearest point `q` of a neighbour. A neighbour with the
/// same nearest point offers the same distance, and a NaN point (none yet) a NaN
/// distance, neither of which is smaller: no test for them is needed.
#[inline(always)]
fn relax(here: &mut Nearest, p: DVec2, there: &Nearest) {
    let d2 = p.distance_squared(there.q);
    if d2 < here.d2 {
        *here = Nearest {
            q: there.q,
            d2,
            seg: there.seg,
        };
    }
}

/// The forward pass of [`distance_to_loops`]: rows upwards, each from the left (left,
/// lower-left, below, lower-right), then back from the right (right). Rows are split
/// off so the neighbours are plain slice reads. `xs`: the nodes' abscissae.
fn forward_pass(grid: &Grid, xs: &[f64], spans: &[Range<usize>], near: &mut [Nearest]) {
    let nx = grid.nx;
    let node = |c: usize, y: f64| DVec2::new(xs[c], y);
    for (r, span) in spans.iter().enumerate() {
        let y = grid.origin.y + r as f64 * grid.h;
        let (done, rest) = near.split_at_mut(r * nx);
        let row = &mut rest[..nx];
        let below = r.checked_sub(1).map(|b| &done[b * nx..(b + 1) * nx]);
        // Ends no further than the row (so the indexing needs no checks).
        let (lo, end) = (span.start, span.end.min(nx));
        for c in lo..end {
            let p = node(c, y);
            if c > 0 {
                let q = row[c - 1];
                relax(&mut row[c], p, &q);
            }
            if let Some(below) = below {
                if c > 0 {
                    relax(&mut row[c], p, &below[c - 1]);
                }
                relax(&mut row[c], p, &below[c]);
                if c + 1 < nx {
                    relax(&mut row[c], p, &below[c + 1]);
                }
            }
        }
        for c in (lo..end.min(nx - 1)).rev() {
            let q = row[c + 1];
            relax(&mut row[c], node(c, y), &q);
        }
    }
}

/// The backward pass of [`distance_to_loops`]: [`forward_pass`] mirrored.
fn backward_pass(grid: &Grid, xs: &[f64], spans: &[Range<usize>], near: &mut [Nearest]) {
    let (nx, ny) = (grid.nx, grid.ny);
    let node = |c: usize, y: f64| DVec2::new(xs[c], y);
    for (r, span) in spans.iter().enumerate().rev() {
        let y = grid.origin.y + r as f64 * grid.h;
        let (head, done) = near.split_at_mut((r + 1) * nx);
        let row = &mut head[r * nx..];
        let above = (r + 1 < ny).then(|| &done[..nx]);
        let (lo, end) = (span.start, span.end.min(nx));
        for c in (lo..end).rev() {
            let p = node(c, y);
            if c + 1 < nx {
                let q = row[c + 1];
                relax(&mut row[c], p, &q);
            }
            if let Some(above) = above {
                if c + 1 < nx {
                    relax(&mut row[c], p, &above[c + 1]);
                }
                relax(&mut row[c], p, &above[c]);
                if c > 0 {
                    relax(&mut row[c], p, &above[c - 1]);
                }
            }
        }
        for c in lo.max(1)..end {
            let q = row[c - 1];
            relax(&mut row[c], node(c, y), &q);
        }
    }
}

impl Drop for DistanceField {
    fn drop(&mut self) {
        for v in [&mut self.d, &mut self.de, &mut self.di] {
            give(&pool::F64, std::mem::take(v));
        }
        give(&pool::BOOL, std::mem::take(&mut self.inside));
        give(&pool::U32, std::mem::take(&mut self.outer_seg));
        if let Inner::Holes { seg, .. } = &mut self.inner {
            give(&pool::U32, std::mem::take(seg));
        }
    }
}

impl DistanceField {
    /// Distances to Ce only: enough to find the pole of inaccessibility.
    pub fn outer_only(region: &Region, cell_mm: f64, max_nodes: usize) -> DistanceField {
        let grid = Grid::over(region, cell_mm, max_nodes);
        let in_outer = fill_inside(&grid, &[&region.outer]);
        let holes: Vec<&Vec<DVec2>> = region.holes.iter().collect();
        let in_hole = fill_inside(&grid, &holes);
        let spans = row_spans(&grid, &in_outer);
        let mut inside = in_outer;
        for (i, h) in inside.iter_mut().zip(&in_hole) {
            *i = *i && !*h;
        }
        give(&pool::BOOL, in_hole);
        let (de, seg) = distance_to_loops(&grid, &Boundary::of(&[&region.outer]), &spans);
        give(&pool::U32, seg);
        // No Ci, so nothing is placed on exact level sets: no boundary edges kept.
        DistanceField {
            origin: grid.origin,
            h: grid.h,
            nx: grid.nx,
            ny: grid.ny,
            d: Vec::new(),
            de,
            di: Vec::new(),
            inside,
            outer: Boundary::of(&[]),
            outer_seg: Vec::new(),
            inner: Inner::None,
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
        let spans = row_spans(&grid, &in_outer);
        let outer = Boundary::of(&[&region.outer]);
        let (de, outer_seg) = distance_to_loops(&grid, &outer, &spans);
        let (di, inner): (Vec<f64>, Inner) = if holes.is_empty() {
            let c = centre.unwrap_or_else(|| crate::geom::centroid(&region.outer));
            let mut di = take(&pool::F64, grid.nx * grid.ny, 0.0);
            for (k, di) in di.iter_mut().enumerate() {
                *di = grid.node(k % grid.nx, k / grid.nx).distance(c);
            }
            (di, Inner::Centre(c))
        } else {
            let holes = Boundary::of(&holes);
            let (di, seg) = distance_to_loops(&grid, &holes, &spans);
            (di, Inner::Holes { holes, seg })
        };
        let mut d = take(&pool::F64, grid.nx * grid.ny, 0.0);
        let mut inside = take(&pool::BOOL, grid.nx * grid.ny, false);
        for k in 0..d.len() {
            let s = di[k] + de[k];
            let t = if s > 0.0 { di[k] / s } else { 0.0 };
            let e = if s > 0.0 { de[k] / s } else { 0.0 };
            d[k] = if !in_outer[k] {
                // Beyond the transforms' spans (no distance): as far out as d goes.
                if e.is_finite() {
                    1.0 + e
                } else {
                    2.0
                }
            } else if in_hole[k] {
                -t
            } else {
                inside[k] = true;
                t
            };
        }
        give(&pool::BOOL, in_outer);
        give(&pool::BOOL, in_hole);
        DistanceField {
            origin: grid.origin,
            h: grid.h,
            nx: grid.nx,
            ny: grid.ny,
            d,
            de,
            di,
            inside,
            outer,
            outer_seg,
            inner,
        }
    }

    /// The exact normalised distance at `p`, near grid `nodes` in the material, from
    /// the boundary edges near theirs, with its gradient; none where it is undefined.
    ///
    /// Also whether the walks from the nodes' nearest edges agreed (see [`Boundary::near`]).
    fn exact_at(&self, nodes: &[usize], p: DVec2) -> Option<(f64, DVec2, bool)> {
        let (a, qa, agree_a) = match &self.inner {
            Inner::Holes { holes, seg } => holes.near(nodes.iter().map(|&k| seg[k]), p),
            Inner::Centre(c) => (p.distance(*c), *c, true),
            Inner::None => return None,
        };
        let (e, qe, agree_e) = self.outer.near(nodes.iter().map(|&k| self.outer_seg[k]), p);
        let s = a + e;
        if !(a > 0.0 && e > 0.0 && s.is_finite()) {
            return None;
        }
        let (ga, ge) = ((p - qa) / a, (p - qe) / e);
        Some((a / s, (ga * e - ge * a) / (s * s), agree_a && agree_e))
    }

    /// Where level `t` crosses the grid edge from node `n0` to node `n1` (values on
    /// opposite sides of `t`): the crossing of the linear interpolant, moved by Newton
    /// steps along the edge onto the exact level set. Each level keeps to its own
    /// stretch of the edge, half the interpolant's spacing between levels either side
    /// of its crossing, so levels keep their order along every edge, and level sets
    /// that do not cross as interpolated do not cross as placed.
    fn place(&self, n0: usize, n1: usize, t: f64, spacing: f64) -> Placed {
        let (p0, p1) = (self.node_pos(n0), self.node_pos(n1));
        let (v0, v1) = (self.d[n0], self.d[n1]);
        let s_lin = (t - v0) / (v1 - v0);
        let linear = Placed {
            p: p0 + (p1 - p0) * s_lin,
            grad: None,
            on_level: false,
            node: n0,
        };
        if !(self.inside[n0] && self.inside[n1] && s_lin.is_finite()) {
            return linear;
        }
        let half = (LEVEL_STRETCH * spacing / (v1 - v0).abs()).min(1.0);
        let (lo, hi) = ((s_lin - half).max(0.0), (s_lin + half).min(1.0));
        let edge = p1 - p0;
        let mut s = s_lin;
        let mut last_grad = None;
        let mut on_level = false;
        for step in 0..NEWTON_STEPS {
            let p = p0 + edge * s;
            let Some((d, grad, agree)) = self.exact_at(&[n0, n1], p) else {
                break;
            };
            last_grad = Some(grad);
            let slope = grad.dot(edge);
            if slope.is_nan() || slope.abs() <= 1e-12 {
                break;
            }
            let free = s - (d - t) / slope;
            let next = free.clamp(lo, hi);
            let moved = (next - s).abs() * self.h;
            s = next;
            on_level = next == free && moved < NEWTON_CLOSE_MM;
            if moved < NEWTON_DONE_MM {
                break;
            }
            // A first step shorter than NEWTON_TRUST_MM, on a stretch where the walks from
            // both nodes found the same nearest points (no medial axis between them), is
            // within Newton's quadratic error of the level set, about moved² / (2 ×
            // the distances' radius of curvature): well under NEWTON_DONE_MM.
            if step == 0 && agree && next == free && moved < NEWTON_TRUST_MM {
                on_level = true;
                break;
            }
        }
        Placed {
            p: p0 + edge * s,
            grad: last_grad,
            on_level,
            node: n0,
        }
    }

    /// Place the crossings of one loop of level `t` (`keys`, the cell sides in order
    /// round the loop), every other one first. A crossing between two that lie on the
    /// level set is left out where the piece joining them strays at most `sparse_mm`
    /// from it: a piece whose ends' normals turn by θ strays at most chord × θ / 4
    /// (a corner at its middle; an arc strays half that), so the normals may turn up
    /// to 4 × `sparse_mm` / chord. A corner of the level set between them turns their
    /// normals by its own angle, so it keeps the crossing; two corners turning back
    /// within the cells spanned could cancel, which is why only every other crossing is
    /// placed first (docs/planner-accuracy.md). The crossing is placed wherever the
    /// normals turn more or either end is off the level set.
    fn place_loop(&self, keys: &[u64], t: f64, spacing: f64, sparse_mm: f64) -> Vec<Placed> {
        let at = |key: u64| {
            let (lo, hi) = ((key >> 32) as usize, (key & 0xffff_ffff) as usize);
            self.place(lo, hi, t, spacing)
        };
        let n = keys.len();
        if !sparse_mm.is_finite() || sparse_mm <= 0.0 || n < SPARSE_MIN_CROSSINGS {
            return keys.iter().map(|&k| at(k)).collect();
        }
        let straight = |a: &Placed, b: &Placed| {
            let (Some(ga), Some(gb)) = (a.grad, b.grad) else {
                return false;
            };
            if !(a.on_level && b.on_level) {
                return false;
            }
            // The turn θ at most x: sin θ ≤ x − x³ / 6 ≤ sin x, with the normals
            // pointing the same way (x under a right angle).
            let x = (4.0 * sparse_mm / a.p.distance(b.p)).min(1.0);
            let scale = (ga.length_squared() * gb.length_squared()).sqrt();
            ga.dot(gb) > 0.0 && ga.perp_dot(gb).abs() <= (x - x * x * x / 6.0) * scale
        };
        let even: Vec<Placed> = keys.iter().step_by(2).map(|&k| at(k)).collect();
        let mut out = Vec::with_capacity(n);
        for (i, a) in even.iter().enumerate() {
            out.push(*a);
            // Odd crossings lie between two even ones; with n odd, the last even one
            // is next to the first.
            let k = 2 * i + 1;
            if k < n && !straight(a, &even[(i + 1) % even.len()]) {
                out.push(at(keys[k]));
            }
        }
        out
    }

    /// The loop through placed crossings, with a point of the exact level set added
    /// between two crossings where the level set bends enough between them to stray
    /// [`BEND_MM`] from the straight piece (judged by how far its normal turns: the
    /// medial axis, where the nearest boundary point jumps, puts a corner there).
    fn bent(&self, placed: &[Placed], t: f64) -> Vec<DVec2> {
        // A crossing the exact level set does not reach within its stretch of the side
        // (the grid cut a tip of the level set short there) is left out between two
        // that lie on it, so the corner between those can be found.
        let n = placed.len();
        let keep: Vec<bool> = (0..n)
            .map(|k| {
                let (before, here, after) = (
                    &placed[prev_in_loop(k, n)],
                    &placed[k],
                    &placed[next_in_loop(k, n)],
                );
                here.on_level || here.grad.is_none() || !(before.on_level && after.on_level)
            })
            .collect();
        let kept: Vec<&Placed> = if keep.iter().filter(|k| **k).count() >= 3 {
            placed
                .iter()
                .zip(&keep)
                .filter(|(_, k)| **k)
                .map(|(p, _)| p)
                .collect()
        } else {
            placed.iter().collect()
        };
        let placed = kept;
        let n = placed.len();
        let mut out = Vec::with_capacity(n + n / 4);
        for k in 0..n {
            let (a, b) = (placed[k], placed[next_in_loop(k, n)]);
            out.push(a.p);
            self.bend_between(a, b, t, BEND_DEPTH, &mut out);
        }
        out
    }

    fn bend_between(&self, a: &Placed, b: &Placed, t: f64, depth: u32, out: &mut Vec<DVec2>) {
        let (Some(ga), Some(gb)) = (a.grad, b.grad) else {
            return;
        };
        // Most pieces turn less than BEND_TURN: their cosine says so without the acos.
        if depth == 0
            || ga.dot(gb) >= BEND_TURN.cos() * (ga.length_squared() * gb.length_squared()).sqrt()
        {
            return;
        }
        let chord = a.p.distance(b.p);
        let turn = ga.angle_to(gb).abs();
        let bends = turn > BEND_TURN && chord * turn / 4.0 > BEND_MM;
        if !bends {
            return;
        }
        // Newton steps along the gradient from where the level set's tangents at the two
        // ends meet (a corner), or from the middle of the piece.
        let mid = 0.5 * (a.p + b.p);
        let (ta, tb) = (ga.perp(), gb.perp());
        let across = ta.perp_dot(tb);
        // Only where the tangents meet ahead of one end and behind the other along the
        // level set (a corner or a tip between them). Across an S-bend they meet behind
        // both ends or ahead of both, and a point placed from there lies beyond an end:
        // the loop would double back on itself there.
        let (ahead_a, ahead_b) = ((b.p - a.p).perp_dot(tb), (b.p - a.p).perp_dot(ta));
        let corner = (across.abs() > 1e-12 * ta.length() * tb.length() && ahead_a * ahead_b < 0.0)
            .then(|| a.p + ta * (ahead_a / across))
            .filter(|c| c.distance(mid) <= BEND_REACH_CELLS * self.h);
        let start = corner.unwrap_or(mid);
        let mut x = start;
        let mut grad = None;
        for _ in 0..NEWTON_STEPS {
            // The node nearest the point too: a corner can lie near a third part of
            // the boundary.
            let Some((d, g, _)) = self.exact_at(&[a.node, b.node, self.node_near(x)], x) else {
                return;
            };
            let g2 = g.length_squared();
            if g2.is_nan() || g2 <= 1e-24 {
                return;
            }
            grad = Some(g);
            x -= g * ((d - t) / g2);
        }
        let reach = if corner.is_some() {
            BEND_REACH_CELLS * self.h
        } else {
            0.5 * chord
        };
        let moved = x.distance(mid);
        if moved.is_nan() || moved > reach {
            return;
        }
        let m = Placed {
            p: x,
            grad,
            on_level: true,
            node: a.node,
        };
        self.bend_between(a, &m, t, depth - 1, out);
        out.push(x);
        self.bend_between(&m, b, t, depth - 1, out);
    }

    /// The grid node nearest `p` (clamped to the grid).
    fn node_near(&self, p: DVec2) -> usize {
        let q = (p - self.origin) / self.h + DVec2::splat(0.5);
        let c = (floor_clamped(q.x).max(0.0) as usize).min(self.nx - 1);
        let r = (floor_clamped(q.y).max(0.0) as usize).min(self.ny - 1);
        r * self.nx + c
    }

    fn node_pos(&self, k: usize) -> DVec2 {
        let (c, r) = (k % self.nx, k / self.nx);
        DVec2::new(
            self.origin.x + c as f64 * self.h,
            self.origin.y + r as f64 * self.h,
        )
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
        best.map(|(k, de)| (self.node_pos(k), de))
    }

    /// Cell size actually used, mm.
    pub fn cell_mm(&self) -> f64 {
        self.h
    }

    /// Level sets at `d = k / m` for k = 1..m−1 (contours C2..Cm), each a list of closed
    /// loops, extracted by marching triangles.
    ///
    /// Each cell is four triangles about its centre (the mean of its corners); a level's
    /// pieces through the cell join side crossings, and which sides a piece joins (and
    /// where a loop starting in the cell starts) is read off [`CELL_PIECES`], built from
    /// those triangles. Every crossing lies on a cell side, named by its two end nodes;
    /// the two pieces of a level through one side join there. They are linked as the
    /// cells are visited row by row: a cell's bottom side is the top side of the cell
    /// below (kept from the previous row) and its left side the right side of the cell
    /// before it.
    ///
    /// Where the crossings either side of one lie on the exact level set and its
    /// normal turns so little between them that the straight piece joining them
    /// strays at most `sparse_mm` from it, that crossing is left out (see
    /// [`DistanceField::place_loop`]); 0 (or anything not a finite positive length)
    /// places every crossing.
    pub fn level_sets(&self, m: u32, sparse_mm: f64) -> Vec<Vec<Vec<DVec2>>> {
        let levels = m.saturating_sub(1) as usize;
        // A field from [`DistanceField::outer_only`] has no normalised distance to trace.
        if levels == 0 || self.d.len() != self.nx * self.ny {
            return Vec::new();
        }
        let segs = self.march(m, levels);
        self.place_levels(segs, m as f64, sparse_mm)
    }

    /// The pieces of each of the `levels` levels `k / m` through the cells, linked
    /// through the sides they share (see [`DistanceField::level_sets`]).
    fn march(&self, m: u32, levels: usize) -> Vec<Vec<Segment>> {
        let (nx, ny) = (self.nx, self.ny);
        let mut march = Marching::new(levels, nx, ny);
        let mf = m as f64;
        let below_m = m.min(i32::MAX as u32) as i32;
        let (band, rows) = self.level_bands(mf, below_m);
        for r in 0..ny - 1 {
            march.next_row();
            // Cells with a corner in either row's stretch (see `rows`).
            let (lo, hi) = (&rows[r], &rows[r + 1]);
            let cells = match (lo.is_empty(), hi.is_empty()) {
                (true, true) => 0..0,
                (false, true) => lo.clone(),
                (true, false) => hi.clone(),
                (false, false) => lo.start.min(hi.start)..lo.end.max(hi.end),
            };
            for c in cells.start.saturating_sub(1)..cells.end.min(nx - 1) {
                march.cell(&self.d, &band, r, c, mf, below_m);
            }
        }
        give(&pool::I32, band);
        march.finish()
    }

    /// floor(d m) per node (`mf` is m): a cell crosses level k when the least of its
    /// corners' is below k and the greatest at least k (floor is monotone, so this is
    /// floor(lo m) and floor(hi m) of the cell's least and greatest value).
    ///
    /// And per row, the columns from the first to the last node with floor(d m) below m
    /// (`below_m`): a cell crosses a level below m only where one of its corners' is, so
    /// cells further out (beyond Ce, or beyond the transforms' spans) are not visited.
    fn level_bands(&self, mf: f64, below_m: i32) -> (Vec<i32>, Vec<Range<usize>>) {
        let nx = self.nx;
        let mut band = take(&pool::I32, self.d.len(), 0);
        let mut rows: Vec<Range<usize>> = Vec::with_capacity(self.ny);
        for (bs, vs) in band.chunks_exact_mut(nx).zip(self.d.chunks_exact(nx)) {
            for (b, v) in bs.iter_mut().zip(vs) {
                // floor without a branch (d lies in [-1, 2], so d m fits).
                let x = v * mf;
                let i = x as i32;
                *b = i - i32::from(f64::from(i) > x);
            }
            rows.push(match bs.iter().position(|&b| b < below_m) {
                Some(first) => first..nx - bs.iter().rev().position(|&b| b < below_m).unwrap_or(0),
                None => 0..0,
            });
        }
        (band, rows)
    }

    /// The level sets' loops from their linked pieces (`segs`, per level; `mf` is m).
    ///
    /// Crossings on cell sides (between two grid nodes) are placed on the exact level
    /// set; those on cell diagonals (towards a cell's interpolated centre) only steer
    /// the marching through saddle cells and are left out. A level's piece through a
    /// cell then runs straight from side to side, and pieces of different levels, whose
    /// ends keep their order along every side, do not cross.
    fn place_levels(
        &self,
        segs: Vec<Vec<Segment>>,
        mf: f64,
        sparse_mm: f64,
    ) -> Vec<Vec<Vec<DVec2>>> {
        let spacing = 1.0 / mf;
        segs.into_iter()
            .enumerate()
            .map(|(level, segs)| {
                let t = (level + 1) as f64 / mf;
                let loops = chain_segments(&segs);
                give(&pool::SEGMENT, segs);
                loops
                    .into_iter()
                    .filter_map(|keys| {
                        let placed = self.place_loop(&keys, t, spacing, sparse_mm);
                        let l = crate::geom::dedup_loop(&self.bent(&placed, t), 1e-12);
                        (l.len() >= 3).then_some(l)
                    })
                    .collect()
            })
            .collect()
    }
}

/// The marching of [`DistanceField::level_sets`], cell by cell and row by row: each
/// level's pieces, linked as the cells are visited (a cell's bottom side is the top side
/// of the cell below, kept from the previous row, and its left side the right side of
/// the cell before it).
struct Marching {
    nx: usize,
    /// The pieces of each level.
    segs: Vec<Vec<Segment>>,
    /// Per level: the segment ending on each cell's top edge in the previous and the
    /// current row, and on the right edge of the cell just visited, with that edge's
    /// key (entries of cells that did not cross the level are stale, and the key tells
    /// them apart).
    top_below: Vec<(u64, u32)>,
    top_here: Vec<(u64, u32)>,
    right: Vec<(u64, u32)>,
}

impl Marching {
    fn new(levels: usize, nx: usize, ny: usize) -> Self {
        // Room for a level a few times round the grid's sides without regrowing.
        let segs: Vec<Vec<Segment>> = (0..levels)
            .map(|_| {
                let mut v = take(&pool::SEGMENT, 0, NO_PIECE);
                v.reserve(4 * (nx + ny));
                v
            })
            .collect();
        let none = (u64::MAX, NO_SEGMENT);
        Marching {
            nx,
            segs,
            top_below: take(&pool::SIDE, levels * nx, none),
            top_here: take(&pool::SIDE, levels * nx, none),
            right: vec![none; levels],
        }
    }

    /// Move on to the next row of cells: this row's top sides are the next one's bottom.
    fn next_row(&mut self) {
        std::mem::swap(&mut self.top_below, &mut self.top_here);
    }

    /// The pieces of every level crossing the cell from node (`c`, `r`), from the node
    /// values `d` and their floor(d m) `band` (see [`DistanceField::level_bands`]).
    fn cell(&mut self, d: &[f64], band: &[i32], r: usize, c: usize, mf: f64, below_m: i32) {
        let nx = self.nx;
        let ids = [
            (r * nx + c) as u64,
            (r * nx + c + 1) as u64,
            ((r + 1) * nx + c + 1) as u64,
            ((r + 1) * nx + c) as u64,
        ];
        let b = [
            band[ids[0] as usize],
            band[ids[1] as usize],
            band[ids[2] as usize],
            band[ids[3] as usize],
        ];
        // Level k/m is crossed when lo < k/m <= hi.
        let k_lo = (b[0].min(b[1]).min(b[2]).min(b[3]) + 1).max(1);
        let k_hi = b[0].max(b[1]).max(b[2]).max(b[3]).min(below_m - 1);
        if k_lo > k_hi {
            return;
        }
        let val = [
            d[ids[0] as usize],
            d[ids[1] as usize],
            d[ids[2] as usize],
            d[ids[3] as usize],
        ];
        let centre_val = 0.25 * (val[0] + val[1] + val[2] + val[3]);
        // The cell's sides (bottom, right, top, left), as the crossings' keys.
        let sides = [
            edge_key(ids[0], ids[1]),
            edge_key(ids[1], ids[2]),
            edge_key(ids[2], ids[3]),
            edge_key(ids[3], ids[0]),
        ];
        for k in k_lo..=k_hi {
            let t = k as f64 / mf;
            let level = (k - 1) as usize;
            let case = usize::from(val[0] >= t)
                | usize::from(val[1] >= t) << 1
                | usize::from(val[2] >= t) << 2
                | usize::from(val[3] >= t) << 3
                | usize::from(centre_val >= t) << 4;
            let pieces = &CELL_PIECES[case];
            // The right edge of the cell before (this cell's left edge), before this
            // cell's right edge replaces it.
            let left = self.right[level];
            for piece in &pieces.pieces[..pieces.count as usize] {
                self.link_piece(level, c, &sides, piece, left);
            }
        }
    }

    /// Add the piece of `level` through cell column `c` joining `piece`'s two of the
    /// cell's `sides`, linked to the pieces on the sides shared with cells already
    /// visited (the bottom, from the row below; the left, `left`), and left on the sides
    /// the next cells share.
    fn link_piece(
        &mut self,
        level: usize,
        c: usize,
        sides: &[u64; 4],
        piece: &CellPiece,
        left: (u64, u32),
    ) {
        let nx = self.nx;
        let out = &mut self.segs[level];
        let i = out.len() as u32;
        let mut seg = Segment {
            keys: [
                sides[piece.sides[0] as usize],
                sides[piece.sides[1] as usize],
            ],
            links: [NO_SEGMENT; 2],
            rotate: piece.rotate,
        };
        for end in 0..2 {
            let key = seg.keys[end];
            match piece.sides[end] {
                // Sides shared with cells already visited: link.
                e @ (0 | 3) => {
                    let slot = if e == 0 {
                        self.top_below[level * nx + c]
                    } else {
                        left
                    };
                    if slot.0 == key && slot.1 != NO_SEGMENT {
                        let j = slot.1;
                        seg.links[end] = j;
                        let other = &mut out[j as usize];
                        let back = usize::from(other.keys[1] == key);
                        other.links[back] = i;
                    }
                }
                // Sides the next cells share: leave the segment there.
                1 => self.right[level] = (key, i),
                _ => self.top_here[level * nx + c] = (key, i),
            }
        }
        out.push(seg);
    }

    /// The pieces of each level, the side buffers given back.
    fn finish(self) -> Vec<Vec<Segment>> {
        give(&pool::SIDE, self.top_below);
        give(&pool::SIDE, self.top_here);
        self.segs
    }
}

/// The share of the interpolant's spacing between consecutive levels along an edge
/// that a placed crossing may move either side of the interpolated one (under a half,
/// so neighbouring levels never meet).
const LEVEL_STRETCH: f64 = 0.49;

/// Newton steps placing a crossing on the exact level set, and the move (mm) below
/// which it has converged.
const NEWTON_STEPS: usize = 2;
const NEWTON_DONE_MM: f64 = 1e-4;
/// A last Newton step under this (mm) counts as having reached the level set.
const NEWTON_CLOSE_MM: f64 = 1e-3;
/// A first Newton step under this (mm), where the nearest boundary points agree, is
/// not checked by a second (see [`DistanceField::place`]).
const NEWTON_TRUST_MM: f64 = 1e-2;
/// How far (cells) from the middle of a piece a corner of the level set may be found.
const BEND_REACH_CELLS: f64 = 2.0;

/// Loops with fewer crossings are placed whole by [`DistanceField::place_loop`].
const SPARSE_MIN_CROSSINGS: usize = 8;

/// No segment (an end whose edge no other segment of the level crosses).
const NO_SEGMENT: u32 = u32::MAX;

/// A blank [`Segment`] (to fill buffers with).
const NO_PIECE: Segment = Segment {
    keys: [u64::MAX; 2],
    links: [NO_SEGMENT; 2],
    rotate: false,
};

/// One piece of a level set through one cell: the keys of the cell sides its ends lie
/// on (see [`edge_key`]), and the pieces of the same level through those sides.
#[derive(Clone, Copy)]
struct Segment {
    keys: [u64; 2],
    links: [u32; 2],
    /// A loop starting with this piece starts at `keys[1]` and ends at `keys[0]` (see
    /// [`CellPiece`]).
    rotate: bool,
}

fn edge_key(a: u64, b: u64) -> u64 {
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    // Node ids stay far below 2^32 (the grid is capped), so the pair packs into a u64.
    (lo << 32) | hi
}

/// A piece of a level through a cell, joining two of its sides (0 bottom, 1 right, 2
/// top, 3 left). Where a loop starts with the piece, its first point is the crossing of
/// `sides[0]` and its second that of `sides[1]`, or (`rotate`) its first that of
/// `sides[1]`, running out of the cell, and its last that of `sides[0]`: where the
/// cell's four triangles, chained from the first one the level crosses, place them.
#[derive(Clone, Copy)]
struct CellPiece {
    sides: [u8; 2],
    rotate: bool,
}

/// The pieces of a level through a cell (two in a saddle), in the order the cell's
/// triangles (bottom, right, top, left) first meet them.
#[derive(Clone, Copy)]
struct CellPieces {
    count: u8,
    pieces: [CellPiece; 2],
}

/// [`CellPieces`] for each case: bit k (k < 4) set where corner k (counter-clockwise
/// from the cell's lower left) is at or above the level, bit 4 where the cell's centre
/// is.
static CELL_PIECES: [CellPieces; 32] = cell_pieces();

/// Marching triangles on one cell, case by case: triangle e has corners e, e + 1 and
/// the centre, and its piece of the level joins two of its edges: the cell side e, the
/// half-diagonal from corner e + 1 to the centre, and the half-diagonal from the centre
/// to corner e (tried in that order). Pieces joined through half-diagonals are one
/// piece between two sides; chained from a triangle, a loop places its crossings from
/// the first edge that triangle's piece meets, through its second.
const fn cell_pieces() -> [CellPieces; 32] {
    const SIDE: u8 = 0;
    const DIAG: u8 = 4;
    let none = CellPiece {
        sides: [0, 0],
        rotate: false,
    };
    let mut table = [CellPieces {
        count: 0,
        pieces: [none; 2],
    }; 32];
    let mut case = 0;
    while case < 32 {
        let centre = (case >> 4) & 1 == 1;
        // The triangles' pieces, each as its two edges (sides 0..3, half-diagonals
        // 4 + corner).
        let mut tri = [[0u8; 2]; 4];
        let mut crossed = [false; 4];
        let mut e = 0;
        while e < 4 {
            let f = (e + 1) % 4;
            let v = [(case >> e) & 1 == 1, (case >> f) & 1 == 1, centre];
            let edges = [SIDE + e as u8, DIAG + f as u8, DIAG + e as u8];
            let mut n = 0;
            let mut i = 0;
            while i < 3 {
                if v[i] != v[(i + 1) % 3] && n < 2 {
                    tri[e][n] = edges[i];
                    n += 1;
                }
                i += 1;
            }
            crossed[e] = n == 2;
            e += 1;
        }
        let mut used = [false; 4];
        let mut count = 0;
        let mut s = 0;
        while s < 4 {
            if crossed[s] && !used[s] {
                used[s] = true;
                let [first, second] = tri[s];
                let ahead = walk_to_side(&tri, &crossed, s, second, &mut used);
                let piece = if first < DIAG {
                    match ahead {
                        Some(b) => Some(CellPiece {
                            sides: [first, b],
                            rotate: false,
                        }),
                        None => None,
                    }
                } else {
                    match (walk_to_side(&tri, &crossed, s, first, &mut used), ahead) {
                        (Some(a), Some(b)) => Some(CellPiece {
                            sides: [a, b],
                            rotate: true,
                        }),
                        _ => None,
                    }
                };
                if let Some(p) = piece {
                    if count < 2 {
                        table[case].pieces[count] = p;
                        count += 1;
                    }
                }
            }
            s += 1;
        }
        table[case].count = count as u8;
        case += 1;
    }
    table
}

/// In [`cell_pieces`]: from triangle `from` out through its edge `edge`, through the
/// triangles sharing half-diagonals (marked `used`), to the side the piece reaches.
const fn walk_to_side(
    tri: &[[u8; 2]; 4],
    crossed: &[bool; 4],
    mut from: usize,
    mut edge: u8,
    used: &mut [bool; 4],
) -> Option<u8> {
    const DIAG: u8 = 4;
    let mut steps = 0;
    while edge >= DIAG && steps < 4 {
        // The other triangle with this half-diagonal.
        let corner = (edge - DIAG) as usize;
        let next = if from == corner {
            (corner + 3) % 4
        } else {
            corner
        };
        if !crossed[next] {
            return None;
        }
        used[next] = true;
        edge = if tri[next][0] == edge {
            tri[next][1]
        } else {
            tri[next][0]
        };
        from = next;
        steps += 1;
    }
    if edge < DIAG {
        Some(edge)
    } else {
        None
    }
}

/// Chain linked pieces into closed loops: the keys of the cell sides they cross, in order.
fn chain_segments(segs: &[Segment]) -> Vec<Vec<u64>> {
    let mut used = take(&pool::BOOL, segs.len(), false);
    let mut loops = Vec::new();
    let mut chained = 0;
    for start in 0..segs.len() {
        if used[start] {
            continue;
        }
        used[start] = true;
        let first_key = segs[start].keys[0];
        // Room for every piece not yet chained: a level is mostly one or two loops.
        let mut pts: Vec<u64> = Vec::with_capacity(segs.len().saturating_sub(chained) + 1);
        pts.push(first_key);
        let mut key = segs[start].keys[1];
        let mut next = segs[start].links[1];
        loop {
            if key == first_key {
                break;
            }
            pts.push(key);
            if next == NO_SEGMENT || used[next as usize] {
                break;
            }
            used[next as usize] = true;
            let s = &segs[next as usize];
            let enter = usize::from(s.keys[0] != key);
            key = s.keys[1 - enter];
            next = s.links[1 - enter];
        }
        chained += pts.len();
        if segs[start].rotate {
            pts.rotate_left(1);
        }
        if pts.len() >= 3 {
            loops.push(pts);
        }
    }
    give(&pool::BOOL, used);
    loops
}

/// A level crossing placed on a grid edge: the point, the exact gradient of the
/// normalised distance there (none where the linear interpolant placed it), and one
/// end node of its edge (whose nearest boundary edges start the walks of
/// [`Boundary::near`] for points nearby).
#[derive(Clone, Copy)]
struct Placed {
    p: DVec2,
    grad: Option<DVec2>,
    /// Newton's last step converged inside the crossing's stretch of the side.
    on_level: bool,
    node: usize,
}

/// How far (mm) the straight piece between two crossings may stray from the exact level
/// set before [`DistanceField::bent`] adds a point between them, and how many times it
/// halves a piece.
const BEND_MM: f64 = 0.005;
const BEND_DEPTH: u32 = 1;
const BEND_TURN: f64 = 0.15;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::circle;

    #[test]
    fn annulus_levels_are_circles() {
        let outer = circle(DVec2::ZERO, 30.0, 0.001);
        let mut hole = circle(DVec2::ZERO, 10.0, 0.001);
        hole.reverse();
        let region = Region::new(outer, vec![hole]);
        let field = DistanceField::new(&region, None, 0.25, 1 << 22);
        let levels = field.level_sets(10, 0.0);
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

    /// On a coarse grid (cell 0.4 mm, contours 1.1 mm apart at the thinnest), the
    /// level sets of a wavy region with two holes lie on the exact level sets (the
    /// linear interpolant alone is some µm off): all but a few vertices to 0.1 µm, and
    /// the few (crossings at a node, where the grid sees the level cross a side the
    /// exact level set only touches) within the chord tolerance. The corners where
    /// they cross the medial axis between the holes are found, and no two cross.
    /// A C-shaped region (a ring with a slot cut from it) with a hole in its thick
    /// part: the nearest boundary points of many nodes lie round a corner.
    fn slotted_ring() -> Region {
        let mut outer: Vec<DVec2> = (0..=300)
            .map(|k| DVec2::from_angle(0.3 + 5.68 * k as f64 / 300.0) * 20.0)
            .collect();
        outer.extend(
            (0..=300)
                .rev()
                .map(|k| DVec2::from_angle(0.3 + 5.68 * k as f64 / 300.0) * 9.0),
        );
        let mut hole = circle(DVec2::new(-14.5, 0.0), 2.0, 0.01);
        hole.reverse();
        Region::new(outer, vec![hole])
    }

    #[test]
    fn sweeping_the_material_spans_gives_the_whole_grid_distances() {
        let region = slotted_ring();
        let grid = Grid::over(&region, 0.35, 1 << 20);
        let in_outer = fill_inside(&grid, &[&region.outer]);
        let whole = vec![0..grid.nx; grid.ny];
        let spans = row_spans(&grid, &in_outer);
        assert!(spans.iter().map(|s| s.len()).sum::<usize>() < grid.nx * grid.ny * 9 / 10);
        let holes: Vec<&Vec<DVec2>> = region.holes.iter().collect();
        for boundary in [Boundary::of(&[&region.outer]), Boundary::of(&holes)] {
            let (d_whole, seg_whole) = distance_to_loops(&grid, &boundary, &whole);
            let (d_spans, seg_spans) = distance_to_loops(&grid, &boundary, &spans);
            let mut compared = 0;
            for k in 0..in_outer.len() {
                let (c, r) = (k % grid.nx, k / grid.nx);
                // Every node a level's crossing can be read at: inside Ce and its
                // neighbours.
                let near_material = (c.saturating_sub(1)..=(c + 1).min(grid.nx - 1))
                    .flat_map(|cc| {
                        (r.saturating_sub(1)..=(r + 1).min(grid.ny - 1)).map(move |rr| (cc, rr))
                    })
                    .any(|(cc, rr)| in_outer[rr * grid.nx + cc]);
                if near_material {
                    assert!(spans[r].contains(&c), "node {c},{r} outside its row's span");
                    assert_eq!(d_whole[k], d_spans[k], "node {c},{r}");
                    assert_eq!(seg_whole[k], seg_spans[k], "node {c},{r}");
                    compared += 1;
                }
            }
            assert!(compared > 1000);
        }
    }

    #[test]
    fn fields_built_from_reused_buffers_are_the_same() {
        let ring = slotted_ring();
        let first = DistanceField::new(&ring, None, 0.35, 1 << 20).level_sets(8, 0.0);
        // A larger and a smaller grid in between, so the buffers come back resized.
        let big = Region::new(circle(DVec2::ZERO, 40.0, 0.01), Vec::new());
        let centre = DistanceField::outer_only(&big, 0.3, 1 << 20)
            .pole()
            .map(|(p, _)| p);
        assert!(!DistanceField::new(&big, centre, 0.3, 1 << 20)
            .level_sets(5, 0.0)
            .is_empty());
        let small = Region::new(circle(DVec2::ZERO, 3.0, 0.01), Vec::new());
        assert!(!DistanceField::new(&small, None, 0.3, 1 << 20)
            .level_sets(3, 0.0)
            .is_empty());
        let again = DistanceField::new(&ring, None, 0.35, 1 << 20).level_sets(8, 0.0);
        assert!(!first.is_empty());
        assert_eq!(first, again);
    }

    #[test]
    fn pooled_buffers_come_back_filled() {
        // An empty shelf, whatever tests ran on this thread before.
        pool::F64.with(|s| s.borrow_mut().clear());
        let mut v = take(&pool::F64, 100, 0.0);
        v.iter_mut().for_each(|x| *x = 7.0);
        let (capacity, at) = (v.capacity(), v.as_ptr());
        give(&pool::F64, v);
        let w = take(&pool::F64, 50, 1.5);
        assert_eq!(w.len(), 50);
        assert!(w.iter().all(|&x| x == 1.5));
        // The buffer given back, not a new one.
        assert_eq!(w.as_ptr(), at);
        assert_eq!(w.capacity(), capacity);
    }

    /// A wavy outline about two round holes (and the loops it is made of).
    fn wavy_two_holes() -> (Region, Vec<DVec2>, Vec<Vec<DVec2>>) {
        let outer: Vec<DVec2> = (0..720)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / 720.0;
                DVec2::from_angle(a) * (30.0 + 1.5 * (5.0 * a).sin())
            })
            .collect();
        let hole = |c: DVec2| -> Vec<DVec2> {
            let mut h = circle(c, 4.0, 0.001);
            h.reverse();
            h
        };
        let holes = vec![hole(DVec2::new(-11.0, 0.0)), hole(DVec2::new(11.0, 0.0))];
        let region = Region::new(outer.clone(), holes.clone());
        (region, outer, holes)
    }

    #[test]
    fn coarse_levels_lie_on_the_exact_level_sets() {
        let (region, outer, holes) = wavy_two_holes();
        let m = 10;
        let levels = DistanceField::new(&region, None, 0.4, 1 << 22).level_sets(m, 0.0);
        let (mut worst, mut off, mut total, mut corners) = (0.0f64, 0, 0, 0);
        let lo = region.bounds().0 / 0.4;
        let on_side = |v: f64| (v - v.round()).abs() < 1e-6;
        for (k, loops) in levels.iter().enumerate() {
            let t = (k + 1) as f64 / m as f64;
            for p in loops.iter().flatten() {
                let a = holes
                    .iter()
                    .map(|h| crate::geom::point_loop_distance(*p, h))
                    .fold(f64::INFINITY, f64::min);
                let e = crate::geom::point_loop_distance(*p, &outer);
                let err = (a / (a + e) - t).abs() * (a + e);
                worst = worst.max(err);
                off += usize::from(err > 1e-4);
                total += 1;
                corners += usize::from(!on_side(p.x / 0.4 - lo.x) && !on_side(p.y / 0.4 - lo.y));
            }
        }
        assert!(worst < 0.01, "a vertex lies {worst} mm off its level set");
        assert!(
            off * 100 < total,
            "{off} of {total} vertices off their level set"
        );
        assert!(corners > 0, "no corner found on the medial axis");
        let all: Vec<&[DVec2]> = levels.iter().flatten().map(|l| l.as_slice()).collect();
        assert!(crate::geom::first_crossing(&all).is_none());
    }

    /// A field of distances to Ce only (the pole search) has no normalised distance:
    /// it traces no level sets. Broken regions (a NaN vertex, a hole outside the outer
    /// loop, a degenerate outer loop) give a field without a panic.
    #[test]
    fn sparse_levels_keep_to_their_share_of_the_deviation() {
        // Where crossings are left out, the straight pieces still lie within `sparse`
        // of the exact level sets, and the corners on the medial axis are kept.
        let (region, outer, holes) = wavy_two_holes();
        let to_outer = crate::geom::SegmentIndex::new(&[outer.as_slice()], &[]);
        let hole_refs: Vec<&[DVec2]> = holes.iter().map(|h| h.as_slice()).collect();
        let to_holes = crate::geom::SegmentIndex::new(&hole_refs, &[]);
        let m = 10;
        let field = DistanceField::new(&region, None, 0.4, 1 << 22);
        let sparse = 0.01;
        let dense = field.level_sets(m, 0.0);
        // Not a finite positive length: every crossing, as for 0.
        for bad in [f64::NAN, f64::INFINITY, -sparse] {
            assert_eq!(field.level_sets(m, bad), dense, "sparse = {bad}");
        }
        let levels = field.level_sets(m, sparse);
        // How far the sparse levels' pieces stray from the dense ones (which lie on
        // the exact level sets but where the grid cuts a corner, and keep every
        // vertex the sparse ones have).
        let (mut worst, mut off_level) = (0.0f64, 0.0f64);
        for (k, (sparse_loops, dense_loops)) in levels.iter().zip(&dense).enumerate() {
            let t = (k + 1) as f64 / m as f64;
            let refs: Vec<&[DVec2]> = dense_loops.iter().map(|l| l.as_slice()).collect();
            let to_dense = crate::geom::SegmentIndex::new(&refs, &[]);
            for l in sparse_loops {
                for (i, &a) in l.iter().enumerate() {
                    let (di, de) = (to_holes.distance(a), to_outer.distance(a));
                    off_level = off_level.max((di / (di + de) - t).abs() * (di + de));
                    let b = l[(i + 1) % l.len()];
                    for s in [0.25, 0.5, 0.75] {
                        worst = worst.max(to_dense.distance(a.lerp(b, s)));
                    }
                }
            }
        }
        let count =
            |levels: &[Vec<Vec<DVec2>>]| levels.iter().flatten().map(Vec::len).sum::<usize>();
        let (kept, all) = (count(&levels), count(&dense));
        assert!(
            worst <= sparse,
            "pieces stray {worst} mm from the dense levels"
        );
        assert!(
            off_level < 0.01,
            "a vertex lies {off_level} mm off its level set"
        );
        assert!(kept * 4 < all * 3, "{kept} vertices kept of {all}");
        let all: Vec<&[DVec2]> = levels.iter().flatten().map(|l| l.as_slice()).collect();
        assert!(crate::geom::first_crossing(&all).is_none());
    }

    #[test]
    fn odd_fields_trace_without_panicking() {
        let outer = circle(DVec2::ZERO, 10.0, 0.01);
        let region = Region::new(outer.clone(), Vec::new());
        assert!(DistanceField::outer_only(&region, 0.5, 1 << 16)
            .level_sets(5, 0.0)
            .is_empty());
        let mut nan = outer.clone();
        nan[3] = DVec2::new(f64::NAN, 0.0);
        let mut far_hole = circle(DVec2::new(40.0, 0.0), 2.0, 0.01);
        far_hole.reverse();
        let flat = vec![DVec2::ZERO, DVec2::X, DVec2::new(2.0, 0.0)];
        for region in [
            Region::new(nan, Vec::new()),
            Region::new(outer.clone(), vec![far_hole]),
            Region::new(flat, Vec::new()),
        ] {
            let field = DistanceField::new(&region, None, 0.5, 1 << 16);
            for loops in field.level_sets(5, 0.0) {
                assert!(loops.iter().all(|l| l.len() >= 3));
            }
        }
    }
}
