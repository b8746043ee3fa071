//! Slanted road ends (§4, a void the paper's Fig. 4(a) does not show but every
//! fiber-like part has): an open road that runs into the part boundary at a slant ends
//! with a round end that touches the boundary (nozzle radius compensation), which leaves
//! the acute corner of the road's own strip bare. At 30° that corner is about 0.6 w² per
//! end, and it narrows to a point, so gap fill can only take part of it.
//!
//! After the flow raise and before gap fill, each such end is continued into its corner
//! the way Arachne's variable-width beads fill a wedge: past the end, the road's strip
//! (between its two bead edges) is sampled every tenth of a road width; at each sample
//! the bead centre goes to the point of the strip's cross-section that is as far from
//! the boundary as from the acute edge (the wedge's medial axis), and no nearer another
//! road than that road's half width. A move builds the mean width of its two vertices, so
//! the vertex widths are chosen to give each move the radius that fits at its narrower
//! end. So the continuation touches the boundary and the edge of the road beside it,
//! never crosses either, and narrows into the corner until it is thinner than the
//! narrowest gap-fill road. It belongs to the road, so it has the road's composition and
//! needs no travel, start or stop of its own. (What it does to the coverage of the
//! fibers example: docs/planner-accuracy.md.)
//!
//! Only ends whose round end touches the boundary (within a tenth of a road width) and
//! that run at least 27° off square into it (one edge reaches the boundary half a road
//! width further than the other) are continued; a square end leaves only its two small
//! corners, which a sidestep would not be worth.

use super::{RoadIndex, ToolPath};
use crate::geom::{Region, SegmentIndex};
use glam::DVec2;

/// Settings of the end continuation (part of [`crate::pipeline::ProcessSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EndSettings {
    pub road_width_mm: f64,
    /// The narrowest bead the continuation builds, mm (where the corner is narrower, it
    /// stops).
    pub min_width_mm: f64,
}

/// Furthest a continuation reaches past the end, in road widths (a 15° slant needs 3.7).
const MAX_REACH: f64 = 4.0;
/// Sample spacing along the strip, in road widths. Each move is built at the width that
/// fits at its narrower end, so a move leaves a sliver of its length times the corner's
/// narrowing at its wider end: 0.1 w keeps that to a fraction of a percent of a corner.
const STEP: f64 = 0.1;
/// An end counts as at the boundary when its round end is this close to it (road widths).
const TOUCH: f64 = 0.1;
/// How much further (road widths) the acute edge must reach the boundary than the obtuse
/// one before the end is continued (0.5 for a full-width road: 27° off square).
const MIN_SLANT: f64 = 0.5;
/// Bisections to find the medial point of a cross-section (1/2^12 of half a road).
const BISECTIONS: usize = 12;
/// How far inside its bead edge (road widths) an end's reach is traced from.
const EDGE_INSET: f64 = 0.05;
/// Bisections for the last bead, where the corner is exactly the narrowest bead wide.
const TIP_BISECTIONS: usize = 10;

/// Continue the slanted open ends of `paths` into their corners (see the module doc),
/// in place, keeping inside the part `islands`.
pub fn continue_slanted_ends(paths: &mut [ToolPath], s: &EndSettings, islands: &[Region]) {
    let w = s.road_width_mm;
    if !(w.is_finite() && w > 0.0 && s.min_width_mm.is_finite() && s.min_width_mm > 0.0)
        || islands.is_empty()
        || paths.is_empty()
    {
        return;
    }
    let boundary = SegmentIndex::of_regions(islands);
    if boundary.is_empty() {
        return;
    }
    let roads = RoadIndex::new(paths);
    let ctx = Ctx {
        w,
        min_width: s.min_width_mm,
        islands,
        boundary: &boundary,
        roads: &roads,
        paths,
    };
    let added: Vec<[Vec<(DVec2, f64)>; 2]> = (0..paths.len())
        .map(|i| {
            let p = &paths[i];
            let n = p.points.len();
            if p.closed || n < 2 || p.width_factors.len() != n {
                return [Vec::new(), Vec::new()];
            }
            [ctx.corner(i, 0, 1), ctx.corner(i, n - 1, n - 2)]
        })
        .collect();
    for (p, [head, tail]) in paths.iter_mut().zip(added) {
        for (q, f) in tail {
            p.points.push(q);
            p.width_factors.push(f);
        }
        if !head.is_empty() {
            let (mut pts, mut fs): (Vec<DVec2>, Vec<f64>) = head.into_iter().rev().unzip();
            pts.append(&mut p.points);
            fs.append(&mut p.width_factors);
            p.points = pts;
            p.width_factors = fs;
        }
    }
}

/// An open road's end that runs into the part boundary at a slant (see the module doc).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Slant {
    /// The end vertex.
    pub end: DVec2,
    /// Unit direction past the end (from the vertex before it).
    pub along: DVec2,
    /// Unit normal from the centreline towards the acute side.
    pub across_to_acute: DVec2,
    /// How far past the end the acute bead edge runs before it leaves the part, mm.
    pub acute_reach_mm: f64,
}

/// Whether the open road end `end` (the vertex before it `inner`, bead half-width
/// `half_width_mm`) touches the part boundary at a slant, and how.
pub(crate) fn slant(
    end: DVec2,
    inner: DVec2,
    half_width_mm: f64,
    w: f64,
    boundary: &SegmentIndex,
    islands: &[Region],
) -> Option<Slant> {
    let h = half_width_mm;
    let along = (end - inner).try_normalize()?;
    let inside = |p: DVec2| islands.iter().any(|r| r.contains(p));
    if !(h.is_finite() && h > 0.0 && end.is_finite() && inside(end)) {
        return None;
    }
    if boundary.distance(end) > h + TOUCH * w {
        return None;
    }
    let nrm = along.perp();
    let limit = MAX_REACH * w;
    // How far each bead edge runs on past the end before it leaves the part.
    // (From just inside each edge: a road whose edge runs along a wall into a corner
    // has that edge on the boundary, and it counts as reaching as far as the other.)
    let reach = |side: f64| -> f64 {
        let o = end + nrm * (side * (h - EDGE_INSET * w).max(0.0));
        if !inside(o) {
            return 0.0;
        }
        boundary.ray_hit(o, along, limit).unwrap_or(limit)
    };
    let (left, right) = (reach(1.0), reach(-1.0));
    let (across_to_acute, acute) = if left >= right {
        (nrm, left)
    } else {
        (-nrm, right)
    };
    (acute - left.min(right) >= MIN_SLANT * 2.0 * h).then_some(Slant {
        end,
        along,
        across_to_acute,
        acute_reach_mm: acute,
    })
}

/// Vertex width factors for a continuation from an end of half-width `h_end` through
/// `samples` (bead centres and the radius that fits at each). A move builds one width,
/// the mean of its two vertices' (as the coverage measure and the moves take it), and
/// that must fit at its narrower end: each vertex's half-width is chosen so that the
/// move into it has the smaller of the two radii, and the continuation stops where that
/// is narrower than `min_width` or cannot be built.
fn edge_widths(h_end: f64, samples: &[(DVec2, f64)], min_width: f64, w: f64) -> Vec<(DVec2, f64)> {
    let mut out = Vec::with_capacity(samples.len());
    let (mut v_prev, mut fit_prev) = (h_end, h_end);
    for &(c, fit) in samples {
        let edge = fit.min(fit_prev);
        let v = 2.0 * edge - v_prev;
        if 2.0 * edge < min_width || v < 0.0 || !v.is_finite() {
            break;
        }
        out.push((c, 2.0 * v / w));
        (v_prev, fit_prev) = (v, fit);
    }
    out
}

struct Ctx<'a> {
    w: f64,
    min_width: f64,
    islands: &'a [Region],
    boundary: &'a SegmentIndex,
    roads: &'a RoadIndex,
    paths: &'a [ToolPath],
}

impl Ctx<'_> {
    /// The continuation of path `i` past its end vertex `end` (the vertex before it is
    /// `inner`): bead centres and width factors, in building order away from the end.
    fn corner(&self, i: usize, end: usize, inner: usize) -> Vec<(DVec2, f64)> {
        let p = &self.paths[i];
        let w = self.w;
        let h = 0.5 * w * p.width_factors[end];
        let Some(sl) = slant(
            p.points[end],
            p.points[inner],
            h,
            w,
            self.boundary,
            self.islands,
        ) else {
            return Vec::new();
        };
        // This path's own segments in the road index, which the clearance check skips.
        let own = |id: u32| self.roads.owner.get(id as usize) == Some(&(i as u32));
        let across = -sl.across_to_acute;
        // The bead at x past the end: centred on the medial point of the strip's
        // cross-section there, kept clear of any other bead beside the strip; its centre
        // and the radius that fits there.
        let bead = |x: f64| -> Option<(DVec2, f64)> {
            let o = sl.end + sl.along * x + sl.across_to_acute * h;
            let medial = self.medial(o, across, h);
            let c = o + across * medial;
            let r = match self.roads.index.nearest_skipping(c, own) {
                Some((d, id)) => medial.min(d - self.half_width_of(id)),
                None => medial,
            };
            (r.is_finite() && 2.0 * r >= self.min_width).then_some((c, r))
        };
        let mut samples = Vec::new();
        let step = STEP * w;
        let mut x = step;
        let mut last_ok = 0.0;
        while x < sl.acute_reach_mm {
            match bead(x) {
                Some(b) => samples.push(b),
                None => break,
            }
            last_ok = x;
            x += step;
        }
        // The last bead where the corner is exactly the narrowest bead wide (between the
        // last sample that fits and the first that does not).
        let (mut lo, mut hi) = (last_ok, x.min(sl.acute_reach_mm));
        let mut tip = None;
        for _ in 0..TIP_BISECTIONS {
            let mid = 0.5 * (lo + hi);
            match bead(mid) {
                Some(b) => {
                    lo = mid;
                    tip = Some(b);
                }
                None => hi = mid,
            }
        }
        if let Some(b) = tip {
            if lo > last_ok + 0.1 * step {
                samples.push(b);
            }
        }
        edge_widths(h, &samples, self.min_width, w)
    }

    /// The point of the cross-section `o + across * s`, 0 ≤ s ≤ `h`, that is as far from
    /// the part boundary as from `o` (the acute edge): that distance.
    fn medial(&self, o: DVec2, across: DVec2, h: f64) -> f64 {
        let gap = |s: f64| self.boundary.distance(o + across * s) - s;
        if gap(h) >= 0.0 {
            return h;
        }
        let (mut lo, mut hi) = (0.0, h);
        for _ in 0..BISECTIONS {
            let mid = 0.5 * (lo + hi);
            if gap(mid) >= 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    }

    /// Half the bead width of the road segment `id` of the road index (the wider of its
    /// two vertices).
    fn half_width_of(&self, id: u32) -> f64 {
        let Some(&path) = self.roads.owner.get(id as usize) else {
            return 0.5 * self.w;
        };
        let p = &self.paths[path as usize];
        let k = (id - self.roads.first_segment[path as usize]) as usize;
        let n = p.width_factors.len();
        if n == 0 {
            return 0.5 * self.w;
        }
        let f = p.width_factors[k % n].max(p.width_factors[(k + 1) % n]);
        0.5 * self.w * f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolpath::coverage::measure;
    use crate::toolpath::PathRole;

    const W: f64 = 0.4;
    const S: EndSettings = EndSettings {
        road_width_mm: W,
        min_width_mm: 0.25 * W,
    };

    fn rect(lo: DVec2, hi: DVec2) -> Region {
        Region::new(
            vec![lo, DVec2::new(hi.x, lo.y), hi, DVec2::new(lo.x, hi.y)],
            Vec::new(),
        )
    }

    /// Lines at `deg` to +x, `W` apart, across the part 10 x 4 mm, clipped to the part
    /// inset by half a road (nozzle radius compensation: each round end touches the
    /// boundary).
    fn fibers(deg: f64) -> (Region, Vec<ToolPath>) {
        let part = rect(DVec2::ZERO, DVec2::new(10.0, 4.0));
        let (lo, hi) = (DVec2::splat(0.5 * W), DVec2::new(10.0, 4.0) - 0.5 * W);
        let d = DVec2::from_angle(deg.to_radians());
        let n = d.perp();
        let mut paths = Vec::new();
        for k in -60..60 {
            let o = DVec2::new(5.0, 2.0) + n * (k as f64 * W);
            // Liang–Barsky clip of o + t d to the inset rectangle.
            let (mut t0, mut t1) = (-100.0f64, 100.0f64);
            for axis in 0..2 {
                let (p, v, a, b) = (o[axis], d[axis], lo[axis], hi[axis]);
                if v.abs() < 1e-12 {
                    if p < a || p > b {
                        t0 = 1.0;
                        t1 = 0.0;
                    }
                    continue;
                }
                let (ta, tb) = ((a - p) / v, (b - p) / v);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
            if t1 - t0 < 2.0 * W {
                continue;
            }
            paths.push(ToolPath {
                role: PathRole::Offset {
                    island: 0,
                    n: 0,
                    i: k as u32,
                },
                points: vec![o + d * t0, o + d * (0.5 * (t0 + t1)), o + d * t1],
                closed: false,
                width_factors: vec![1.0; 3],
                composition: vec![1.0],
                seam_at_corner: false,
            });
        }
        (part, paths)
    }

    #[test]
    fn slanted_ends_fill_their_corners_without_leaving_the_part() {
        let (part, mut paths) = fibers(30.0);
        let islands = vec![part];
        let before = measure(&islands, &paths, W, 0.005);
        let lengths: Vec<usize> = paths.iter().map(|p| p.points.len()).collect();
        continue_slanted_ends(&mut paths, &S, &islands);
        let after = measure(&islands, &paths, W, 0.005);
        assert!(
            paths
                .iter()
                .zip(&lengths)
                .filter(|(p, &l)| p.points.len() > l)
                .count()
                >= paths.len(),
            "most ends are continued"
        );
        assert!(
            after.void_fraction() < 0.4 * before.void_fraction(),
            "void {:.3} % -> {:.3} %",
            100.0 * before.void_fraction(),
            100.0 * after.void_fraction()
        );
        assert!(
            after.overlap_fraction() <= before.overlap_fraction() + 0.002,
            "overlap {:.3} % -> {:.3} %",
            100.0 * before.overlap_fraction(),
            100.0 * after.overlap_fraction()
        );
        assert!(
            after.outside_fraction() <= before.outside_fraction() + 0.001,
            "outside {:.3} % -> {:.3} %",
            100.0 * before.outside_fraction(),
            100.0 * after.outside_fraction()
        );
        let boundary = SegmentIndex::of_regions(&islands);
        // Each move builds the mean width of its two vertices, and fits at both ends.
        for p in &paths {
            for k in 0..p.points.len() - 1 {
                let f = 0.5 * (p.width_factors[k] + p.width_factors[k + 1]);
                assert!((0.25 - 1e-9..=1.0 + 1e-9).contains(&f), "width factor {f}");
                for q in [p.points[k], p.points[k + 1]] {
                    assert!(
                        boundary.distance(q) >= 0.5 * W * f - 1e-6,
                        "bead at {q} leaves"
                    );
                }
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig {
            cases: 24,
            rng_seed: proptest::test_runner::RngSeed::Fixed(0xED0_E4D5),
            ..proptest::prelude::ProptestConfig::default()
        })]

        /// At any slant the continuation stays inside the part, overlaps nothing it did
        /// not overlap before and never adds void.
        #[test]
        fn continuations_fit_at_any_slant(deg in 1.0f64..89.0) {
            let (part, mut paths) = fibers(deg);
            let islands = vec![part];
            let before = measure(&islands, &paths, W, 0.01);
            continue_slanted_ends(&mut paths, &S, &islands);
            let after = measure(&islands, &paths, W, 0.01);
            proptest::prop_assert!(after.void_fraction() <= before.void_fraction() + 1e-4);
            proptest::prop_assert!(after.overlap_fraction() <= before.overlap_fraction() + 1e-3);
            proptest::prop_assert!(after.outside_fraction() <= before.outside_fraction() + 1e-4);
            let boundary = SegmentIndex::of_regions(&islands);
            for p in &paths {
                for k in 0..p.points.len() - 1 {
                    let f = 0.5 * (p.width_factors[k] + p.width_factors[k + 1]);
                    for q in [p.points[k], p.points[k + 1]] {
                        proptest::prop_assert!(boundary.distance(q) >= 0.5 * W * f - 1e-6);
                    }
                }
            }
        }
    }

    #[test]
    fn square_ends_are_left_alone() {
        let (part, mut paths) = fibers(90.0);
        let islands = vec![part];
        let before = paths.clone();
        continue_slanted_ends(&mut paths, &S, &islands);
        assert!(paths == before, "a square end was continued");
    }

    #[test]
    fn broken_input_is_left_alone() {
        let (part, mut paths) = fibers(30.0);
        paths[3].points[2] = DVec2::new(f64::NAN, 1.0);
        paths[4].points[1] = paths[4].points[2];
        paths[5].width_factors.pop();
        let doubled_end = paths[4].points[2];
        let islands = vec![part];
        continue_slanted_ends(&mut paths, &S, &islands);
        // The NaN end and the end whose last edge has no length are not continued (the
        // other end of each may be); the path with a width missing is not touched.
        assert!(paths[3].points.last().is_some_and(|p| p.x.is_nan()));
        assert_eq!(paths[3].points.len(), paths[3].width_factors.len());
        assert_eq!(paths[4].points.last(), Some(&doubled_end));
        assert!(paths[5].points.len() == 3 && paths[5].width_factors.len() == 2);
        assert!(paths
            .iter()
            .flat_map(|p| &p.width_factors)
            .all(|f| f.is_finite() && *f >= 0.0));
        let mut bad = S;
        bad.road_width_mm = f64::NAN;
        let counts: Vec<usize> = paths.iter().map(|p| p.points.len()).collect();
        continue_slanted_ends(&mut paths, &bad, &islands);
        assert!(paths.iter().map(|p| p.points.len()).eq(counts));
    }
}
