//! Process planning (§4 of the paper, Fig. 4(a)): a layer's EDO plan becomes the ordered
//! list of paths the nozzle builds, each with its composition and a width (flow) factor
//! per vertex.
//!
//! Steps, named as in the paper and issue 4:
//!
//! 1. **Filling order** ([`fill_order`]): per island, sub-regions in
//!    [`SubRegionOrder`] (inner to outer by default). Within a sub-region S(n,n+1) first its
//!    iso-composition contours C_n and C_n+1 (closed loops, or open pieces where the part
//!    cuts them) that have not been built yet, then its equal distance offsets from the
//!    contour the offsets count from (eq (6)): paths 1, 2 (contours) then 3, 4, 5
//!    (offsets) of Fig. 4(a). Composition changes from path to path by W (eq (7)).
//! 2. **Start and end points** ([`choose_seam`]): a closed loop starts and ends at its
//!    seam, placed by [`SeamMode`] at a concave corner where there is one (the bead's
//!    start/stop blob hides in the corner); open segments start at the end nearer the
//!    nozzle.
//! 3. **Path order**: within one composition group (one contour, or one offset i), the
//!    pieces are visited nearest-neighbour from the nozzle position, each piece entered
//!    at its best end or seam; the group order itself is the paper's and is kept (it is
//!    what makes composition change by W from path to path).
//! 4. **Flow raise in narrow sub-areas** ([`flow`]): width factors per vertex.
//!
//! Travel between paths (with extrusion cessation) and the machine moves are made by
//! [`crate::pipeline`]; the coverage measure is [`coverage`].

pub mod coverage;
pub mod ends;
pub mod flow;
pub mod gapfill;
pub mod merge;
pub mod support;

use crate::geom::{next_in_loop, prev_in_loop, Path};
use crate::material::OffsetDirection;
use crate::plan::{offset_composition_eq6, LayerPlan};
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// Where closed loops start and end (job/settings key `seam`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum SeamMode {
    /// Seams line up across layers: the concave corner (else the vertex) furthest in the
    /// seam direction (`seam_angle_deg`, default the rear, +y).
    #[default]
    Aligned,
    /// Seams move round by the golden angle from layer to layer, so their blobs do not
    /// stack into a ridge; concave corners still preferred.
    Staggered,
    /// The vertex nearest the nozzle: least travel, seams wherever they fall.
    Nearest,
}

/// In which order a region's sub-regions are filled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum SubRegionOrder {
    /// From C1 (Ci) out to Cm+1 (Ce).
    #[default]
    InnerToOuter,
    /// From Cm+1 (Ce) in to C1 (Ci).
    OuterToInner,
    /// Inner to outer on even layers, outer to inner on odd ones: each layer starts with
    /// the composition the previous one ended with, so the mixing chamber needs no purge
    /// at layer changes.
    Alternating,
}

/// What a path builds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum PathRole {
    /// Iso-composition contour C_j of an island.
    Contour { island: u32, j: u32 },
    /// Equal distance offset i of sub-region S(n,n+1) of an island.
    Offset { island: u32, n: u32, i: u32 },
    /// Gap fill: a thin road in a gap wider flow cannot close (Arachne-style).
    GapFill { island: u32, n: u32 },
    /// The sparse body of a support column (`support`): not part of the part.
    Support,
    /// The dense top layers of a support column, right under the part.
    SupportInterface,
}

impl PathRole {
    /// Whether the road builds support, not the part: it counts in no coverage and in
    /// no designed-versus-built composition of the part.
    pub fn is_support(&self) -> bool {
        matches!(self, PathRole::Support | PathRole::SupportInterface)
    }
}

/// A road in building order: centreline from `points[0]` (its start) to the last point,
/// back to `points[0]` when `closed`. `width_factors[k]` is the bead width (flow)
/// relative to nominal at vertex k (1 = nominal road).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ToolPath {
    pub role: PathRole,
    pub points: Vec<DVec2>,
    pub closed: bool,
    pub width_factors: Vec<f64>,
    /// Designed composition (fractions in syringe order, sum 1).
    pub composition: Vec<f64>,
    /// Whether `points[0]` is a deliberately placed seam at a concave corner.
    pub seam_at_corner: bool,
}

impl ToolPath {
    /// Centreline length including the closing edge of a loop, mm.
    pub fn length_mm(&self) -> f64 {
        self.edges().map(|(a, b)| a.distance(b)).sum()
    }

    /// The road's edges in order (see [`crate::geom::edges`]).
    pub fn edges(&self) -> impl Iterator<Item = (DVec2, DVec2)> + '_ {
        crate::geom::edges(&self.points, self.closed)
    }

    /// Where the nozzle ends after building the path.
    pub fn end(&self) -> DVec2 {
        if self.closed {
            self.points[0]
        } else {
            self.points[self.points.len() - 1]
        }
    }
}

/// One segment index over every road of a layer (loops' edges first, then open paths'),
/// with the path each segment id belongs to and each path's first segment id.
pub(crate) struct RoadIndex {
    pub index: crate::geom::SegmentIndex,
    pub owner: Vec<u32>,
    pub first_segment: Vec<u32>,
}

impl RoadIndex {
    pub fn new(paths: &[ToolPath]) -> Self {
        let of = |closed: bool| -> Vec<&[DVec2]> {
            paths
                .iter()
                .filter(|p| p.closed == closed)
                .map(|p| p.points.as_slice())
                .collect()
        };
        let index = crate::geom::SegmentIndex::new(&of(true), &of(false));
        let mut first_segment = vec![0u32; paths.len()];
        let mut owner: Vec<u32> = Vec::new();
        for closed in [true, false] {
            for (i, p) in paths.iter().enumerate().filter(|(_, p)| p.closed == closed) {
                first_segment[i] = owner.len() as u32;
                let edges = crate::geom::edge_count(p.points.len(), closed);
                owner.extend(std::iter::repeat_n(i as u32, edges));
            }
        }
        RoadIndex {
            index,
            owner,
            first_segment,
        }
    }
}

/// The settings of this module (a part of [`crate::pipeline::ProcessSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrderSettings {
    pub seam: SeamMode,
    /// Seam direction for `aligned` (and the start of `staggered`), degrees from +x.
    pub seam_angle_deg: f64,
    /// A vertex is a concave corner when the loop turns away from its interior by at
    /// least this much there, degrees.
    pub seam_corner_min_deg: f64,
    pub sub_region_order: SubRegionOrder,
}

/// A group of pieces with one composition, built in one go (one contour or one offset).
struct Group {
    role: PathRole,
    composition: Vec<f64>,
    paths: Vec<Path>,
}

/// Step 1: the composition groups of a layer in Fig. 4(a) order.
fn groups(layer: &LayerPlan, order: SubRegionOrder) -> Vec<Group> {
    let order = match order {
        SubRegionOrder::Alternating if layer.index % 2 == 1 => SubRegionOrder::OuterToInner,
        SubRegionOrder::Alternating => SubRegionOrder::InnerToOuter,
        o => o,
    };
    let mut out = Vec::new();
    for region in &layer.regions {
        let island = region.island as u32;
        let mut built = vec![false; region.contours.len()];
        let mut subs: Vec<&crate::plan::SubRegion> = region.sub_regions.iter().collect();
        // Sub-regions by n; the crown core (n = 0) lies inside C1, so inner to outer puts
        // it first.
        subs.sort_by_key(|s| s.n);
        if order == SubRegionOrder::OuterToInner {
            subs.reverse();
        }
        let mut contour = |j: u32, out: &mut Vec<Group>| {
            let k = (j as usize).wrapping_sub(1);
            if let (Some(c), Some(done)) = (region.contours.get(k), built.get_mut(k)) {
                if !*done {
                    *done = true;
                    if !c.roads.is_empty() {
                        out.push(Group {
                            role: PathRole::Contour { island, j },
                            composition: c.composition.fractions().to_vec(),
                            paths: c.roads.clone(),
                        });
                    }
                }
            }
        };
        for sub in subs {
            // The contour the offsets count from is built last, next to offset 1.
            let (first, second) = if sub.n == 0 {
                (1, 1)
            } else {
                match sub.direction {
                    OffsetDirection::Inward => (sub.n, sub.n + 1),
                    OffsetDirection::Outward => (sub.n + 1, sub.n),
                }
            };
            contour(first, &mut out);
            contour(second, &mut out);
            for (k, roads) in sub.offsets.iter().enumerate() {
                let i = k as u32 + 1;
                if roads.is_empty() {
                    continue;
                }
                out.push(Group {
                    role: PathRole::Offset {
                        island,
                        n: sub.n,
                        i,
                    },
                    composition: offset_composition_eq6(region, sub, i).fractions().to_vec(),
                    paths: roads.clone(),
                });
            }
        }
        // Contours not bounding any filled sub-region (thin parts) are still built.
        for j in 1..=region.contours.len() as u32 {
            contour(j, &mut out);
        }
    }
    out
}

/// Signed turn at vertex `k` of a closed loop, radians (positive = left turn).
fn turn_at(points: &[DVec2], k: usize) -> f64 {
    let n = points.len();
    let a = points[prev_in_loop(k, n)];
    let b = points[k];
    let c = points[next_in_loop(k, n)];
    let (u, v) = (b - a, c - b);
    if u.length_squared() == 0.0 || v.length_squared() == 0.0 {
        return 0.0;
    }
    u.perp_dot(v).atan2(u.dot(v))
}

/// Step 2: the seam vertex of a closed loop. `layer` staggers the seam direction;
/// `from` is the nozzle position. Returns the vertex index and whether it is a concave
/// corner.
pub fn choose_seam(
    points: &[DVec2],
    settings: &OrderSettings,
    layer: usize,
    from: DVec2,
) -> (usize, bool) {
    let n = points.len();
    if n == 0 {
        return (0, false);
    }
    if settings.seam == SeamMode::Nearest {
        let k = (0..n)
            .min_by(|&a, &b| {
                points[a]
                    .distance_squared(from)
                    .total_cmp(&points[b].distance_squared(from))
            })
            .unwrap_or(0);
        return (k, false);
    }
    let angle = match settings.seam {
        SeamMode::Staggered => {
            // Golden angle per layer: no two nearby layers share a seam direction.
            settings.seam_angle_deg.to_radians() + layer as f64 * 2.399_963_229_728_653
        }
        _ => settings.seam_angle_deg.to_radians(),
    };
    let dir = DVec2::new(angle.cos(), angle.sin());
    // Concave: the loop turns away from the area it encloses. For a counter-clockwise
    // loop that is a right (negative) turn.
    let orientation = crate::geom::signed_area(points).signum();
    let min_turn = settings.seam_corner_min_deg.to_radians();
    let concave = (0..n).filter(|&k| turn_at(points, k) * orientation <= -min_turn);
    let best = |it: &mut dyn Iterator<Item = usize>| {
        it.max_by(|&a, &b| {
            dir.dot(points[a])
                .total_cmp(&dir.dot(points[b]))
                .then(b.cmp(&a))
        })
    };
    if let Some(k) = best(&mut concave.into_iter()) {
        return (k, true);
    }
    (best(&mut (0..n)).unwrap_or(0), false)
}

/// A layer's paths in building order, plus the travel they need.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OrderedLayer {
    pub paths: Vec<ToolPath>,
    /// Travel between paths (from `start` to the first path, and path to path), mm.
    pub travel_mm: f64,
}

/// Steps 1–3 for one layer: groups in Fig. 4(a) order, pieces nearest-neighbour within a
/// group, seams placed. `start` is the nozzle position before the layer.
pub fn fill_order(
    layer: &LayerPlan,
    settings: &OrderSettings,
    start: Option<DVec2>,
) -> OrderedLayer {
    let mut out = OrderedLayer::default();
    let mut at = start;
    for mut g in groups(layer, settings.sub_region_order) {
        let mut left: Vec<Path> = std::mem::take(&mut g.paths)
            .into_iter()
            .filter(|p| p.points.len() >= 2)
            .collect();
        while !left.is_empty() {
            let here = at.unwrap_or(left[0].points[0]);
            // Nearest piece by its best entry point.
            let mut best = (f64::INFINITY, 0usize);
            for (k, p) in left.iter().enumerate() {
                let d = entry_distance(p, here);
                if d < best.0 {
                    best = (d, k);
                }
            }
            let p = left.swap_remove(best.1);
            let tp = place(p, &g, settings, layer.index, here);
            out.travel_mm += at.map_or(0.0, |a| a.distance(tp.points[0]));
            at = Some(tp.end());
            out.paths.push(tp);
        }
    }
    out
}

fn entry_distance(p: &Path, here: DVec2) -> f64 {
    if p.closed {
        p.points
            .iter()
            .map(|q| q.distance(here))
            .fold(f64::INFINITY, f64::min)
    } else {
        let (a, b) = (p.points[0], p.points[p.points.len() - 1]);
        a.distance(here).min(b.distance(here))
    }
}

fn place(p: Path, g: &Group, settings: &OrderSettings, layer: usize, here: DVec2) -> ToolPath {
    let mut points = p.points;
    let mut seam_at_corner = false;
    if p.closed {
        let (k, corner) = choose_seam(&points, settings, layer, here);
        points.rotate_left(k);
        seam_at_corner = corner;
    } else if points[points.len() - 1].distance(here) < points[0].distance(here) {
        points.reverse();
    }
    let width_factors = vec![1.0; points.len()];
    ToolPath {
        role: g.role,
        points,
        closed: p.closed,
        width_factors,
        composition: g.composition.clone(),
        seam_at_corner,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(seam: SeamMode) -> OrderSettings {
        OrderSettings {
            seam,
            seam_angle_deg: 90.0,
            seam_corner_min_deg: 30.0,
            sub_region_order: SubRegionOrder::InnerToOuter,
        }
    }

    /// An L-shaped loop (counter-clockwise) with one concave corner at (1, 1).
    fn ell() -> Vec<DVec2> {
        [
            (0.0, 0.0),
            (2.0, 0.0),
            (2.0, 1.0),
            (1.0, 1.0),
            (1.0, 2.0),
            (0.0, 2.0),
        ]
        .iter()
        .map(|&(x, y)| DVec2::new(x, y))
        .collect()
    }

    #[test]
    fn seam_goes_to_the_concave_corner() {
        let (k, corner) = choose_seam(&ell(), &settings(SeamMode::Aligned), 0, DVec2::ZERO);
        assert_eq!(ell()[k], DVec2::new(1.0, 1.0));
        assert!(corner);
        // Clockwise the same corner is still the concave one.
        let mut cw = ell();
        cw.reverse();
        let (k, corner) = choose_seam(&cw, &settings(SeamMode::Aligned), 0, DVec2::ZERO);
        assert_eq!(cw[k], DVec2::new(1.0, 1.0));
        assert!(corner);
    }

    #[test]
    fn aligned_seams_stay_and_staggered_seams_move() {
        let sq: Vec<DVec2> = (0..64)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / 64.0;
                DVec2::new(a.cos(), a.sin())
            })
            .collect();
        let a: Vec<usize> = (0..4)
            .map(|l| choose_seam(&sq, &settings(SeamMode::Aligned), l, DVec2::ZERO).0)
            .collect();
        assert!(a.iter().all(|&k| k == 16), "{a:?}");
        let s: Vec<usize> = (0..4)
            .map(|l| choose_seam(&sq, &settings(SeamMode::Staggered), l, DVec2::ZERO).0)
            .collect();
        assert_eq!(s[0], 16);
        assert!(s.windows(2).all(|w| w[0] != w[1]), "{s:?}");
        let (k, _) = choose_seam(&sq, &settings(SeamMode::Nearest), 0, DVec2::new(-3.0, 0.0));
        assert_eq!(k, 32);
    }
}
