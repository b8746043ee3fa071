//! The EDO method (§3 of the paper): pre-subdivision of a layer region into
//! iso-composition contours C1..Cm+1 (eq (1), (2), (4)) and the equal distance offset
//! fill of every sub-region S(n,n+1) (eq (5), (6), (7)).
//!
//! [`plan_region`] runs the paper's steps on one region (an outer loop Ce with holes
//! Ci), named as in the paper:
//!
//! 1. **Pre-subdivision** (§3.1): the contours C1..Cm+1 as the areas `A_j` they enclose.
//!    Growth rings use [`radial`] (the paper's radial lines and splines) when the region
//!    is star-shaped about the centre of Ci, else [`field`] (iso-contours of the
//!    normalised distance). Tooth-crown contours are equal distance offsets of Ce; fiber
//!    contours are parallel lines across the region (§5, Fig. 5).
//! 2. **Boundary offsets** (§3.2): C1 (when it is a real boundary) is offset outwards
//!    and Cm+1 inwards by `boundary_offset_mm` (D_noz/2 by default) so roads stay
//!    inside the part. The material the roads may cover is the region shrunk by the
//!    same distance, the *interior*.
//! 3. **Contour compositions**: eq (2) and eq (4).
//! 4. **EDO fill** per sub-region: D_max (largest gap between its bounding contours
//!    along the gradient), N_max by eq (5), the N_max − 1 equal distance offsets of the
//!    bounding contour clipped to the sub-region (closed loops where they stay closed,
//!    non-continuous segments where the neighbouring contour cuts them, Fig. 4(a)),
//!    their compositions by eq (6) and the step width W by eq (7). Offsets stop
//!    `offset_end_clearance_mm` short of the contour they run into (§4 narrow areas).
//!    Inner contour and offset roads shorter than `min_road_mm` are left out, and a
//!    loop round less than a line's area is printed once, as that line.
//!
//! The result is a compact [`LayerPlan`] (§3.2, last paragraph): per sub-region one
//! contour composition, W and N_max, plus the road geometry.

pub mod field;
pub mod radial;

use crate::geom::{self as shapes, ClipArea, Path, Shapes};
use crate::geom::{Region, RegionError, SegmentIndex, Tolerances};
use crate::material::{
    contour_composition, contour_distance, offset_composition, offset_count, segment_count,
    step_width, Composition, GradientFunction, OffsetDirection, StepWidth,
};
use crate::slice::support::SupportArea;
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// How the region between Ci and Ce is divided into contours (job key `subdivision`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Subdivision {
    /// Radial where the region is star-shaped about the centre of Ci, else distance.
    #[default]
    Auto,
    /// The paper's radial lines and splines; refused where a radial line leaves the region.
    Radial,
    /// Iso-contours of the normalised distance; works for any region with holes.
    Distance,
}

/// What to do with a region thinner than the machine resolves (eq (1) gives m = 0) or
/// narrower than one road (job key `[process] thin_regions`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ThinRegions {
    /// Refuse the plan with an error naming the region (right for a designed polygon).
    #[default]
    Refuse,
    /// Plan it with m = 1 (one sub-region from M(Ci) to M(Ce)), and skip an island no
    /// road fits in, saying so in the region's note (right for the tips of a real part).
    Fill,
}

/// Which method actually produced a region's contours (reported per region).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SubdivisionMethod {
    /// §3.1 radial lines and splines.
    Radial,
    /// Iso-contours of dist(p, Ci) / (dist(p, Ci) + dist(p, Ce)).
    Distance,
    /// Tooth-crown pattern: equal distance offsets of Ce.
    Offset,
    /// Fiber pattern: parallel lines across the region.
    Parallel,
}

/// The 2D gradient pattern of §5, Fig. 5.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Pattern {
    /// Closed contours about the holes (Ci) or, with no hole, about a centre point.
    GrowthRings,
    /// Contours following the outer surface inward over `depth_mm` (enamel over
    /// dentin); the core deeper than that has the inner composition.
    Crown { depth_mm: f64 },
    /// Open contours across the region along `angle_deg` (0 = along +x); the
    /// composition varies across them, from the `inner` side (smallest offset along the
    /// normal) to the `outer` side.
    Fibers { angle_deg: f64 },
}

/// A material gradient design: pattern, M(Ci), M(Ce) and f(d).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GradientDesign {
    pub pattern: Pattern,
    /// M(Ci): composition at the inner boundary (d = 0).
    pub inner: Composition,
    /// M(Ce): composition at the outer boundary (d = 1).
    pub outer: Composition,
    pub function: GradientFunction,
}

/// Planner settings; every tolerance and default documented here, not in the loops.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanOptions {
    /// R_mach: machine spatial resolution, mm (eq (1)).
    pub r_mach_mm: f64,
    /// D_noz: nozzle diameter, mm (eq (5)).
    pub nozzle_mm: f64,
    /// Offset of C1 outwards and Cm+1 inwards so roads stay inside the part (§3.2).
    /// Default D_noz / 2.
    pub boundary_offset_mm: f64,
    /// How far short of the contour they run towards the equal distance offsets of a
    /// sub-region stop, centreline to centreline, mm (§4, narrow sub-areas). An offset
    /// that meets C_n at a shallow angle would otherwise run beside C_n's road closer
    /// than a road width and overlap it; stopped half a road short, the gap it leaves
    /// is at most 1.5 road widths centre to centre, which the flow raise closes
    /// (`max_flow_factor` 1.5). Default D_noz / 2; 0 clips at the contour itself.
    pub offset_end_clearance_mm: f64,
    /// Roads shorter than this are left out, mm: the open pieces an offset leaves where
    /// it is trimmed or clipped twice close together, and loops round a vanishing
    /// area, which would build a start-stop blob rather than a road. Contours C1 and
    /// Cm+1 (the part's own surface) are never shortened. Default D_noz / 4.
    pub min_road_mm: f64,
    pub subdivision: Subdivision,
    /// Which bounding contour the equal distance offsets start from (eq (6)).
    pub direction: OffsetDirection,
    /// Radial lines at equal angular division (§3.1); doubled up to twice when the
    /// splines would cross.
    pub radial_lines: usize,
    /// Grid cell of the distance method, mm. Default R_mach / 2: contours R_mach apart
    /// are resolved by two cells, which settles how the level sets connect; their
    /// points are then placed on the exact level sets (see `field`). A coarser cell
    /// plans faster but rounds off more of the sharp tips level sets have where they
    /// cross the medial axis.
    pub field_cell_mm: Option<f64>,
    /// Cap on distance-field grid nodes (the cell grows to respect it).
    pub max_field_nodes: usize,
    /// How far the inner contours C2..Cm (the iso-composition curves the planner
    /// draws itself) may stray from the exact curve once sampled (radial splines) or
    /// simplified (distance level sets), mm. Default 0.025 (Cura's maximum deviation):
    /// on contours at least L_short / m apart it shifts where each composition lies
    /// by a few percent of one contour step. The part's own outline and the boundary
    /// offsets C1 and Cm+1 keep `tolerances.chord_mm`. Each offset's work grows with
    /// its source contour's vertex count, so a finer value plans more slowly.
    #[serde(default = "default_contour_deviation_mm")]
    pub contour_deviation_mm: f64,
    pub thin_regions: ThinRegions,
    pub tolerances: Tolerances,
}

impl PlanOptions {
    pub fn new(r_mach_mm: f64, nozzle_mm: f64) -> Self {
        PlanOptions {
            r_mach_mm,
            nozzle_mm,
            boundary_offset_mm: nozzle_mm / 2.0,
            offset_end_clearance_mm: nozzle_mm / 2.0,
            min_road_mm: nozzle_mm / 4.0,
            subdivision: Subdivision::Auto,
            direction: OffsetDirection::Inward,
            radial_lines: 360,
            field_cell_mm: None,
            max_field_nodes: 1 << 20,
            contour_deviation_mm: default_contour_deviation_mm(),
            thin_regions: ThinRegions::Refuse,
            tolerances: Tolerances::default(),
        }
    }

    fn cell_mm(&self) -> f64 {
        self.field_cell_mm.unwrap_or(self.r_mach_mm / 2.0)
    }

    /// The range `contour_deviation_mm` may take, mm: from the chord tolerance (a
    /// finer contour than the curves it is traced from carries nothing) to a quarter
    /// of the nozzle (further, a contour's road would visibly leave its curve).
    pub fn contour_deviation_limits_mm(&self) -> (f64, f64) {
        let chord = self.tolerances.chord_mm;
        (chord, (self.nozzle_mm / 4.0).max(chord))
    }

    /// The deviation inner contours are sampled or simplified at: the job refuses a
    /// value outside [`Self::contour_deviation_limits_mm`], and options built in code
    /// are held to them (a value that is not finite counts as the finest).
    fn contour_deviation_mm(&self) -> f64 {
        let (lo, hi) = self.contour_deviation_limits_mm();
        let v = self.contour_deviation_mm;
        if v.is_finite() {
            v.clamp(lo, hi)
        } else {
            lo
        }
    }
}

/// Default of [`PlanOptions::contour_deviation_mm`].
pub const DEFAULT_CONTOUR_DEVIATION_MM: f64 = 0.025;

fn default_contour_deviation_mm() -> f64 {
    DEFAULT_CONTOUR_DEVIATION_MM
}

/// An iso-composition contour C_j and the roads that build it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Contour {
    /// j, 1-based: C1 is Ci, Cm+1 is Ce.
    pub j: u32,
    /// d_j of eq (2).
    pub d: f64,
    /// M(C_j) of eq (4).
    pub composition: Composition,
    /// Road centrelines (after the boundary offset for C1 and Cm+1, clipped to the part).
    pub roads: Vec<Path>,
}

/// A sub-region S(n,n+1) between contours C_n and C_n+1, stored compactly.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SubRegion {
    /// n: the sub-region lies between C_n and C_n+1. n = 0 is the crown pattern's core
    /// inside C1, filled at the inner composition.
    pub n: u32,
    /// Largest distance between the bounding contours along the gradient, mm.
    pub d_max_mm: f64,
    /// N_max of eq (5).
    pub n_max: u32,
    pub direction: OffsetDirection,
    /// Composition of the contour the offsets count from (C_n+1 inward, C_n outward).
    pub from: Composition,
    /// W of eq (7).
    pub w: StepWidth,
    /// The equal distance offsets i = 1..N_max − 1, in order of i.
    pub offsets: Vec<Vec<Path>>,
    /// Area of the sub-region, mm².
    pub area_mm2: f64,
    /// The sub-region itself (planning detail for previews and checks; not stored).
    #[serde(skip)]
    pub shape: Shapes,
}

impl SubRegion {
    /// M(S(n,n+1), i) from the compact form: `from + i · W`.
    pub fn composition_of(&self, i: u32) -> Composition {
        let v = self
            .from
            .fractions()
            .iter()
            .zip(self.w.components())
            .map(|(f, w)| f + i as f64 * w)
            .collect();
        Composition::new(v, COMPACT_COMPOSITION_SUM).unwrap_or_else(|_| self.from.clone())
    }
}

/// The plan of one region (island) of a layer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RegionPlan {
    /// Index of the island within its layer.
    pub island: usize,
    pub method: SubdivisionMethod,
    /// m of eq (1).
    pub m: u32,
    /// L_short of eq (1), mm.
    pub l_short_mm: f64,
    /// Centre of the growth rings (radial method, or a region with no hole).
    pub centre: Option<DVec2>,
    /// Net area of the region, mm².
    pub area_mm2: f64,
    pub contours: Vec<Contour>,
    pub sub_regions: Vec<SubRegion>,
    /// Why the region was planned differently from the method's rule (m clamped to 1,
    /// or skipped as narrower than one road), when it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// The compact plan of one layer (§3.2).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerPlan {
    pub index: usize,
    pub z_mm: f64,
    pub thickness_mm: f64,
    pub area_mm2: f64,
    pub regions: Vec<RegionPlan>,
    /// The part in this layer (the sliced islands the regions were planned from): the
    /// boundary the roads' beads stay inside (`toolpath::flow`).
    #[serde(default)]
    pub islands: Vec<Region>,
    /// The support to build in this layer beside the part (`slice::support`), set
    /// after planning where the job builds supports.
    #[serde(default, skip_serializing_if = "SupportArea::is_empty")]
    pub support: SupportArea,
}

/// Why a region could not be planned; every variant names the island.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error("island {island}: {problem}")]
    Region { island: usize, problem: RegionError },
    #[error("island {island} is too thin for the machine: L_short = {l_short_mm:.3} mm against R_mach = {r_mach_mm} mm gives m = 0 (eq (1)); lower r_mach, or set [process] thin_regions = \"fill\"")]
    TooThin {
        island: usize,
        l_short_mm: f64,
        r_mach_mm: f64,
    },
    #[error("island {island} is narrower than one road: nothing remains after offsetting its boundary by {offset_mm} mm")]
    NarrowerThanRoad { island: usize, offset_mm: f64 },
    #[error("island {island}: subdivision = \"radial\" needs a region star-shaped about the centre of its hole, but a radial line from ({x:.3}, {y:.3}) leaves it; use \"auto\" or \"distance\"")]
    NotStarShaped { island: usize, x: f64, y: f64 },
    #[error("island {island}: subdivision = \"radial\" needs exactly one hole (Ci) or none, it has {holes}; use \"auto\" or \"distance\"")]
    SeveralHoles { island: usize, holes: usize },
    #[error("island {island}: the radial spline contours cross a boundary or each other even with {lines} radial lines; use \"auto\" or \"distance\"")]
    RadialCross { island: usize, lines: usize },
    #[error("compositions have {inner} and {outer} fractions; M(Ci) and M(Ce) must name the same materials")]
    CompositionMismatch { inner: usize, outer: usize },
}

/// A contour level: the area A_j enclosed by C_j (material on the Ci side of C_j).
#[derive(Clone, Debug)]
enum Level {
    Shapes(Shapes),
    /// `{p : normal · p < s}`, within a box around the region (fiber pattern).
    HalfPlane {
        normal: DVec2,
        s: f64,
        lo: DVec2,
        hi: DVec2,
    },
}

impl Level {
    /// Offset by `delta`; `index` is the [`shapes::boundary_index`] of a shapes level
    /// where the caller has it.
    fn offset(&self, delta: f64, chord_mm: f64, index: Option<&SegmentIndex>) -> Level {
        match self {
            Level::Shapes(s) => Level::Shapes(shapes::offset_indexed(s, index, delta, chord_mm)),
            Level::HalfPlane { normal, s, lo, hi } => Level::HalfPlane {
                normal: *normal,
                s: s + delta,
                lo: *lo,
                hi: *hi,
            },
        }
    }

    fn to_shapes(&self) -> Shapes {
        match self {
            Level::Shapes(s) => s.clone(),
            Level::HalfPlane { normal, s, lo, hi } => {
                // The box corners' extent along the normal and along the line.
                let t = normal.perp();
                let corners = [*lo, DVec2::new(hi.x, lo.y), *hi, DVec2::new(lo.x, hi.y)];
                let (mut s_lo, mut t_lo, mut t_hi) =
                    (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY);
                for c in corners {
                    s_lo = s_lo.min(normal.dot(c));
                    t_lo = t_lo.min(t.dot(c));
                    t_hi = t_hi.max(t.dot(c));
                }
                if *s <= s_lo {
                    return Vec::new();
                }
                let s_lo = s_lo - 1.0;
                let (t_lo, t_hi) = (t_lo - 1.0, t_hi + 1.0);
                let p = |a: f64, b: f64| *normal * a + t * b;
                vec![vec![vec![
                    p(s_lo, t_lo),
                    p(*s, t_lo),
                    p(*s, t_hi),
                    p(s_lo, t_hi),
                ]]]
            }
        }
    }

    /// The road centrelines of this level's contour, clipped to `interior`.
    fn roads(&self, interior: &ClipArea, boundary_included: bool, eps: f64) -> Vec<Path> {
        match self {
            Level::Shapes(s) => shapes::loops(s)
                .flat_map(|l| interior.clip_loop(l, boundary_included, eps))
                .collect(),
            Level::HalfPlane { normal, s, lo, hi } => {
                let t = normal.perp();
                let reach = lo.distance(*hi) + 1.0;
                let mid = 0.5 * (*lo + *hi);
                let foot = mid + *normal * (s - normal.dot(mid));
                let line = [foot - t * reach, foot + t * reach];
                shapes::clip_polyline(&line, interior.shapes(), boundary_included)
            }
        }
    }

    fn is_empty(&self) -> bool {
        match self {
            Level::Shapes(s) => s.is_empty(),
            Level::HalfPlane { .. } => self.to_shapes().is_empty(),
        }
    }
}

/// Step 1 result: levels A_1..A_m+1 and what produced them.
struct PreSubdivision {
    method: SubdivisionMethod,
    m: u32,
    l_short_mm: f64,
    centre: Option<DVec2>,
    /// A_1..A_m+1 (index j − 1). Except for fibers (half-planes), A_m+1 is the area
    /// inside Ce, and A_1 is the holes when `inner_is_boundary`: [`plan_region`] takes
    /// their boundary offsets from the interior's own offsets of Ce and Ci.
    levels: Vec<Level>,
    /// Is C1 a real boundary of the part (holes), offset outwards by the boundary offset?
    inner_is_boundary: bool,
}

impl PreSubdivision {
    /// Step 2 on the levels: A_1 of growth rings is the holes and A_m+1 of growth
    /// rings and the crown is the area inside Ce, so their boundary offsets are the
    /// holes grown by b (`holes_out`, when C1 is a real boundary) and the outer loop
    /// shrunk by b (`outer_in`); fiber levels are half-planes, offset as such.
    fn offset_bounding_levels(
        &mut self,
        outer_in: Shapes,
        holes_out: Shapes,
        b: f64,
        chord_mm: f64,
    ) {
        let parallel = self.method == SubdivisionMethod::Parallel;
        let levels = &mut self.levels;
        if self.inner_is_boundary {
            levels[0] = if parallel {
                levels[0].offset(b, chord_mm, None)
            } else {
                Level::Shapes(holes_out)
            };
        }
        let last = levels.len() - 1;
        levels[last] = if parallel {
            levels[last].offset(-b, chord_mm, None)
        } else {
            Level::Shapes(outer_in)
        };
    }
}

/// Eq (1), and what `thin_regions` says to do when it gives m = 0.
fn resolved_m(l_short_mm: f64, island: usize, opts: &PlanOptions) -> Result<u32, PlanError> {
    match segment_count(l_short_mm, opts.r_mach_mm) {
        0 if opts.thin_regions == ThinRegions::Fill && l_short_mm > 0.0 => Ok(1),
        0 => Err(PlanError::TooThin {
            island,
            l_short_mm,
            r_mach_mm: opts.r_mach_mm,
        }),
        m => Ok(m),
    }
}

/// The roads of an inner contour or an equal distance offset as the printer is to lay
/// them down: a loop whose mean width is under the contour deviation (within the
/// tolerance the contours are traced to, a line: a level set touching a ridge of d, an
/// offset pinched off in a narrow sub-region) printed once along that line, not out
/// and back; then roads shorter than `min_road_mm` left out.
fn printable(roads: Vec<Path>, opts: &PlanOptions) -> Vec<Path> {
    let width = opts.contour_deviation_mm();
    roads
        .into_iter()
        .map(|r| r.flattened_if_thinner_than(width))
        .filter(|r| r.length_mm() >= opts.min_road_mm)
        .collect()
}

/// Plan one region: validate it, subdivide it, and fill every sub-region (steps 1–4 of
/// the module's doc).
pub fn plan_region(
    region: &Region,
    island: usize,
    design: &GradientDesign,
    opts: &PlanOptions,
) -> Result<RegionPlan, PlanError> {
    if design.inner.len() != design.outer.len() {
        return Err(PlanError::CompositionMismatch {
            inner: design.inner.len(),
            outer: design.outer.len(),
        });
    }
    let region = sound_region(region, island, &opts.tolerances)?;
    let eps = clip_eps_mm(&opts.tolerances);

    // Step 1: pre-subdivision.
    let mut pre = pre_subdivision(&region, island, &design.pattern, opts)?;

    // Step 2: boundary offsets and the interior the roads may occupy.
    let b = opts.boundary_offset_mm;
    let BoundaryOffsets {
        outer_in,
        holes_out,
        interior,
    } = boundary_offsets(&region, b, opts.tolerances.chord_mm);
    if interior.is_empty() {
        return skipped_narrower_than_road(&region, island, &pre, opts);
    }
    pre.offset_bounding_levels(outer_in, holes_out, b, opts.tolerances.chord_mm);
    let level_shapes: Vec<Shapes> = pre.levels.iter().map(Level::to_shapes).collect();
    let boundary_runs = if pre.method == SubdivisionMethod::Parallel {
        (Vec::new(), Vec::new())
    } else {
        split_boundary_runs(&interior, &region, b)
    };

    // Step 3: contours and their compositions, eq (2) and (4).
    let compositions = contour_compositions(design, pre.m);
    let interior_area = ClipArea::inside(&interior, opts.tolerances.clip_margin_mm);
    let contours = contours(
        &pre,
        &compositions,
        &interior_area,
        boundary_runs,
        eps,
        opts,
    );

    // Step 4: EDO fill of each sub-region, eq (5), (6) and (7).
    let sub_regions = SubRegionFill {
        pre: &pre,
        level_indices: level_shapes
            .iter()
            .map(|_| std::cell::OnceCell::new())
            .collect(),
        level_shapes,
        interior: &interior,
        contours: &contours,
        compositions: &compositions,
        opts,
        eps,
    }
    .sub_regions();
    Ok(RegionPlan {
        island,
        method: pre.method,
        m: pre.m,
        l_short_mm: pre.l_short_mm,
        centre: pre.centre,
        area_mm2: region.area(),
        contours,
        sub_regions,
        note: (segment_count(pre.l_short_mm, opts.r_mach_mm) == 0).then(|| {
            format!(
                "m clamped to 1: L_short = {:.3} mm is under half of R_mach = {} mm (thin_regions = fill)",
                pre.l_short_mm, opts.r_mach_mm
            )
        }),
    })
}

/// How close two points of a road and the line it is clipped against may be and still
/// count as one, mm: a thousand times the point tolerance, at least 1e-7 mm.
fn clip_eps_mm(tol: &Tolerances) -> f64 {
    (tol.point_eq_mm * 1e3).max(1e-7)
}

/// The region normalised and validated, then with the vertices that carry no shape
/// beyond the chord tolerance dropped (dense scans and slicer output: every later
/// offset and boolean scales with the vertex count), where the simpler region is
/// still sound.
fn sound_region(region: &Region, island: usize, tol: &Tolerances) -> Result<Region, PlanError> {
    let region = region.normalised(tol);
    region
        .validate(tol)
        .map_err(|problem| PlanError::Region { island, problem })?;
    let chord = tol.chord_mm;
    let simpler = Region::new(
        crate::geom::simplify_loop(&region.outer, chord),
        region
            .holes
            .iter()
            .map(|h| crate::geom::simplify_loop(h, chord))
            .collect(),
    );
    Ok(if simpler.validate(tol).is_ok() {
        simpler
    } else {
        region
    })
}

/// Step 1 (§3.1): the levels A_1..A_m+1 of the design's pattern.
fn pre_subdivision(
    region: &Region,
    island: usize,
    pattern: &Pattern,
    opts: &PlanOptions,
) -> Result<PreSubdivision, PlanError> {
    match pattern {
        Pattern::GrowthRings => growth_rings(region, island, opts),
        Pattern::Crown { depth_mm } => crown(region, island, *depth_mm, opts),
        Pattern::Fibers { angle_deg } => fibers(region, island, *angle_deg, opts),
    }
}

/// Step 2 (§3.2): the part's boundaries offset by b into the material.
struct BoundaryOffsets {
    /// The outer loop shrunk by b: Cm+1 of growth rings and crown.
    outer_in: Shapes,
    /// The holes grown by b: C1 of growth rings.
    holes_out: Shapes,
    /// The region shrunk by b, the material the roads may cover: `outer_in` less
    /// `holes_out`.
    interior: Shapes,
}

/// The region shrunk by b is its outer loop shrunk by b less its holes grown by b, and
/// those two offsets are also the offset Cm+1 (growth rings, crown) and C1 (growth
/// rings): each is computed once.
fn boundary_offsets(region: &Region, b: f64, chord_mm: f64) -> BoundaryOffsets {
    let outer_in = shapes::offset(
        &shapes::from_loops(std::slice::from_ref(&region.outer)),
        -b,
        chord_mm,
    );
    let holes_out = shapes::offset(&shapes::from_loops(&region.holes), b, chord_mm);
    let interior = shapes::difference(&outer_in, &holes_out);
    BoundaryOffsets {
        outer_in,
        holes_out,
        interior,
    }
}

/// A region with no interior: skipped with a note under `thin_regions = "fill"`, else
/// refused.
fn skipped_narrower_than_road(
    region: &Region,
    island: usize,
    pre: &PreSubdivision,
    opts: &PlanOptions,
) -> Result<RegionPlan, PlanError> {
    let b = opts.boundary_offset_mm;
    if opts.thin_regions == ThinRegions::Fill {
        return Ok(RegionPlan {
            island,
            method: pre.method,
            m: 0,
            l_short_mm: pre.l_short_mm,
            centre: pre.centre,
            area_mm2: region.area(),
            contours: Vec::new(),
            sub_regions: Vec::new(),
            note: Some(format!(
                "skipped: narrower than one road (nothing remains {b} mm inside its boundary)"
            )),
        });
    }
    Err(PlanError::NarrowerThanRoad {
        island,
        offset_mm: b,
    })
}

/// Step 3: M(C_j) of every contour C1..Cm+1, eq (2) and (4).
fn contour_compositions(design: &GradientDesign, m: u32) -> Vec<Composition> {
    (1..=m + 1)
        .map(|j| {
            contour_composition(
                &design.function,
                contour_distance(j, m),
                &design.inner,
                &design.outer,
            )
        })
        .collect()
}

/// Step 3: the contours C1..Cm+1 and their roads. Where C1 and Cm+1 are part surfaces
/// their roads are `boundary_runs` (the interior's own boundary, nearer the holes and
/// nearer the outer loop); inner contours are clipped strictly to the interior: where
/// one would run closer to a boundary than the boundary offset it stops, rather than
/// cross that boundary's road. Fiber lines C1 and Cm+1 lie inside the interior.
fn contours(
    pre: &PreSubdivision,
    compositions: &[Composition],
    interior_area: &ClipArea,
    boundary_runs: (Vec<Path>, Vec<Path>),
    eps: f64,
    opts: &PlanOptions,
) -> Vec<Contour> {
    let m = pre.m;
    let parallel = pre.method == SubdivisionMethod::Parallel;
    let (mut hole_runs, mut outer_runs) = boundary_runs;
    (1..=m + 1)
        .map(|j| Contour {
            j,
            d: contour_distance(j, m),
            composition: compositions[(j - 1) as usize].clone(),
            roads: if j == m + 1 && !parallel {
                std::mem::take(&mut outer_runs)
            } else if j == 1 && pre.inner_is_boundary && !parallel {
                std::mem::take(&mut hole_runs)
            } else {
                printable(
                    pre.levels[(j - 1) as usize].roads(
                        interior_area,
                        parallel && (j == 1 || j == m + 1),
                        eps,
                    ),
                    opts,
                )
            },
        })
        .collect()
}

/// Step 4: the EDO fill of every sub-region S(n,n+1) between the contour levels of a
/// region.
struct SubRegionFill<'a> {
    /// The levels, their boundary offsets applied (step 2).
    pre: &'a PreSubdivision,
    /// Each level as shapes.
    level_shapes: Vec<Shapes>,
    /// The boundary index of each level, built when first needed: the contour one
    /// sub-region's offsets face is the one the next (or previous) starts them from.
    level_indices: Vec<std::cell::OnceCell<SegmentIndex>>,
    interior: &'a Shapes,
    contours: &'a [Contour],
    compositions: &'a [Composition],
    opts: &'a PlanOptions,
    eps: f64,
}

impl SubRegionFill<'_> {
    /// The crown's core (crown pattern), then S(1,2)..S(m,m+1), leaving out those with
    /// no area.
    fn sub_regions(&self) -> Vec<SubRegion> {
        let m = self.pre.m;
        let mut sub_regions = Vec::with_capacity(m as usize + 1);
        if self.pre.method == SubdivisionMethod::Offset {
            if let Some(core) = crown_core(
                &self.level_shapes[0],
                self.interior,
                &self.compositions[0],
                self.opts,
                self.eps,
            ) {
                sub_regions.push(core);
            }
        }
        sub_regions.extend((1..=m).filter_map(|n| self.sub_region(n)));
        sub_regions
    }

    fn level_index(&self, j: u32) -> &SegmentIndex {
        self.level_indices[j as usize]
            .get_or_init(|| shapes::boundary_index(&self.level_shapes[j as usize]))
    }

    /// S(n,n+1): D_max, N_max (eq (5)), the composition the offsets count from and W
    /// (eq (6), (7)), and the N_max − 1 equal distance offsets. `None` where the
    /// sub-region has no area.
    fn sub_region(&self, n: u32) -> Option<SubRegion> {
        let opts = self.opts;
        let s = self.sub_region_shape(n);
        let area = shapes::area(&s);
        if area <= opts.tolerances.min_loop_area_mm2 {
            return None;
        }
        let d_max_mm = self.d_max_mm(n);
        let n_max = offset_count(d_max_mm, opts.nozzle_mm);
        let (m_n, m_n1) = (
            &self.compositions[(n - 1) as usize],
            &self.compositions[n as usize],
        );
        let from = match opts.direction {
            OffsetDirection::Inward => m_n1.clone(),
            OffsetDirection::Outward => m_n.clone(),
        };
        let w = if n_max >= 2 {
            step_width(opts.direction, n_max, m_n, m_n1)
        } else {
            step_width(opts.direction, 2, m_n, m_n)
        };
        let offsets = self.equal_distance_offsets(n, &s, d_max_mm, n_max);
        Some(SubRegion {
            n,
            d_max_mm,
            n_max,
            direction: opts.direction,
            from,
            w,
            offsets,
            area_mm2: area,
            shape: s,
        })
    }

    /// S(n,n+1) = A_n+1 less A_n. Growth-ring levels nest between the offset
    /// boundaries, so their difference already lies in the interior; crown and fiber
    /// levels are cut to it.
    fn sub_region_shape(&self, n: u32) -> Shapes {
        let (m, chord) = (self.pre.m, self.opts.tolerances.chord_mm);
        let (lower_shape, upper_shape) = (
            &self.level_shapes[(n - 1) as usize],
            &self.level_shapes[n as usize],
        );
        match self.pre.method {
            SubdivisionMethod::Radial | SubdivisionMethod::Distance => {
                // Two contour levels of the subdivision (neither boundary offset) are
                // nested and at least about L_short / m apart: far enough apart
                // (beyond what sampling or simplifying each by the contour deviation
                // moves them), their difference is their loops, without the overlay.
                // Next to a boundary offset (n = 1 or m), whose arcs and the level's
                // simplification are not so far apart, the same holds where no edge of
                // the lower level comes within a chord tolerance of the upper one.
                let apart = || {
                    let upper_index = self.level_index(n);
                    shapes::loops(lower_shape).all(|l| upper_index.clear_of_loop(l, chord))
                };
                let nested = !lower_shape.is_empty()
                    && if n >= 2 && n < m {
                        self.pre.l_short_mm / m as f64
                            > NESTED_GAP_DEVIATIONS * self.opts.contour_deviation_mm()
                    } else {
                        apart()
                    };
                nested
                    .then(|| shapes::nested_difference(upper_shape, lower_shape))
                    .flatten()
                    .unwrap_or_else(|| shapes::difference(upper_shape, lower_shape))
            }
            SubdivisionMethod::Offset | SubdivisionMethod::Parallel => {
                shapes::intersection(&shapes::difference(upper_shape, lower_shape), self.interior)
            }
        }
    }

    /// D_max of S(n,n+1): the largest distance between C_n and C_n+1 along the
    /// gradient.
    fn d_max_mm(&self, n: u32) -> f64 {
        let (lower, upper) = (
            &self.pre.levels[(n - 1) as usize],
            &self.pre.levels[n as usize],
        );
        match (lower, upper) {
            // Parallel lines: the gap between them, as far as the part reaches (where
            // the boundary-offset C_m+1 or C1 misses the interior near a corner, the
            // material up to the interior's edge is still to be filled).
            (
                Level::HalfPlane {
                    s: s_lower, normal, ..
                },
                Level::HalfPlane { s: s_upper, .. },
            ) => {
                let (lo, hi) = shapes::loops(self.interior)
                    .flat_map(|l| l.iter())
                    .map(|p| normal.dot(*p))
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                        (a.min(x), b.max(x))
                    });
                (s_upper.min(hi) - s_lower.max(lo)).max(0.0)
            }
            _ => gap_along_gradient(
                &self.contours[n as usize].roads,
                self.pre.centre,
                self.level_index(n - 1),
                self.opts,
            ),
        }
    }

    /// The equal distance offsets i = 1..N_max − 1 of S(n,n+1) (eq (6)), from the
    /// contour the direction starts them at, each one step of D_max / N_max from the
    /// previous: eroding (or dilating) by r1 then r2 is eroding by r1 + r2, and small
    /// steps keep the outline cheap where a contour has many vertices. They stop
    /// `offset_end_clearance_mm` short of the contour they run towards (C_n inward,
    /// C_n+1 outward).
    fn equal_distance_offsets(
        &self,
        n: u32,
        s: &Shapes,
        d_max_mm: f64,
        n_max: u32,
    ) -> Vec<Vec<Path>> {
        let (opts, tol) = (self.opts, &self.opts.tolerances);
        let (lower, upper) = (
            &self.pre.levels[(n - 1) as usize],
            &self.pre.levels[n as usize],
        );
        let (lower_shape, upper_shape) = (
            &self.level_shapes[(n - 1) as usize],
            &self.level_shapes[n as usize],
        );
        let (facing_j, start_j) = match opts.direction {
            OffsetDirection::Inward => (n - 1, n),
            OffsetDirection::Outward => (n, n - 1),
        };
        let facing_index = self.level_index(facing_j);
        let step = d_max_mm / n_max.max(1) as f64;
        // Growth-ring offsets of one bounding contour already lie on the sub-region's
        // side of it, so only the other contour can cut them: clip against that
        // contour's area alone (half the edges of the sub-region).
        let growth = matches!(
            self.pre.method,
            SubdivisionMethod::Radial | SubdivisionMethod::Distance
        );
        let clearance = opts.offset_end_clearance_mm;
        // Trimmed to the clearance, a growth-ring offset's pieces each lie wholly on one
        // side of the facing contour: trim the whole offset and keep the pieces on the
        // sub-region's side, which is the clip then the trim without the clipper.
        let trim_only = growth && clearance > 0.0;
        let cut = OffsetCut {
            clip_area: (!trim_only).then(|| match (growth, opts.direction) {
                (true, OffsetDirection::Inward) => {
                    ClipArea::outside(lower_shape, tol.clip_margin_mm)
                }
                (true, OffsetDirection::Outward) => {
                    ClipArea::inside(upper_shape, tol.clip_margin_mm)
                }
                _ => ClipArea::inside(s, tol.clip_margin_mm),
            }),
            facing_index,
            clearance,
            keep_inside_facing: opts.direction == OffsetDirection::Outward,
            eps: self.eps,
        };
        let mut level = match opts.direction {
            OffsetDirection::Inward => upper.clone(),
            OffsetDirection::Outward => lower.clone(),
        };
        let mut offsets = Vec::new();
        for i in 1..n_max {
            // The first offset starts from a contour level, whose index is at hand.
            let index = (i == 1).then(|| self.level_index(start_j));
            level = match (opts.direction, lower.is_empty(), self.pre.centre) {
                (OffsetDirection::Inward, _, _) => level.offset(-step, tol.chord_mm, index),
                (OffsetDirection::Outward, true, Some(c)) => {
                    Level::Shapes(vec![vec![shapes::circle(c, i as f64 * step, tol.chord_mm)]])
                }
                (OffsetDirection::Outward, _, _) => level.offset(step, tol.chord_mm, index),
            };
            if level.is_empty() {
                break;
            }
            offsets.push(printable(cut.roads(&level), opts));
        }
        offsets
    }
}

/// How the equal distance offsets of one sub-region are cut to it.
struct OffsetCut<'a> {
    /// The area the offsets are clipped to; `None`: the whole offset is trimmed to the
    /// clearance and the pieces on the sub-region's side of the facing contour kept.
    clip_area: Option<ClipArea<'a>>,
    /// The contour the offsets run towards.
    facing_index: &'a SegmentIndex,
    /// How far short of the facing contour they stop, mm.
    clearance: f64,
    /// Is the sub-region's side of the facing contour its inside (outward offsets)?
    keep_inside_facing: bool,
    eps: f64,
}

impl OffsetCut<'_> {
    /// The roads of one offset level within the sub-region.
    fn roads(&self, level: &Level) -> Vec<Path> {
        match &self.clip_area {
            None => {
                let owned;
                let offset_shapes = match level {
                    Level::Shapes(s) => s,
                    _ => {
                        owned = level.to_shapes();
                        &owned
                    }
                };
                let whole = shapes::loops(offset_shapes)
                    .map(|l| Path {
                        points: l.clone(),
                        closed: true,
                    })
                    .collect();
                let mut kept = shapes::keep_clear_of(whole, self.facing_index, self.clearance);
                kept.retain(|p| {
                    p.points.get(p.points.len() / 2).is_some_and(|q| {
                        self.facing_index.inside_odd(*q) == self.keep_inside_facing
                    })
                });
                kept
            }
            Some(area) if self.clearance > 0.0 => shapes::keep_clear_of(
                level.roads(area, false, self.eps),
                self.facing_index,
                self.clearance,
            ),
            Some(area) => level.roads(area, false, self.eps),
        }
    }
}

/// The share of the contour deviation that the straight pieces of a traced level set
/// may stray where crossings are left out of it (see
/// [`field::DistanceField::level_sets`]); the simplification takes the rest.
const LEVEL_SPARSE_SHARE: f64 = 0.5;

/// How many contour deviations apart consecutive contour levels must be (L_short / m)
/// for [`plan_region`] to take their difference as nested loops: each may stray that
/// far from its exact level set.
const NESTED_GAP_DEVIATIONS: f64 = 4.0;

/// How far the fractions `from + i · W` of a sub-region's compact form may sum from 1
/// (the rounding of i steps of W); beyond it [`SubRegion::composition_of`] gives `from`.
const COMPACT_COMPOSITION_SUM: f64 = 1e-6;

/// The reach within which [`split_boundary_runs`] looks for each boundary: the boundary
/// offset, relatively this much more ...
const RUN_REACH_SLACK: f64 = 1e-6;
/// ... and this much more again, mm, so the boundary the interior was offset from is
/// within reach despite the offset's rounding.
const RUN_REACH_SLACK_MM: f64 = 1e-9;

/// D_max samples a road in pieces at most a nozzle long; with a nozzle under this, mm,
/// in pieces at most this long.
const MIN_D_MAX_SAMPLE_MM: f64 = 1e-3;

/// Most concentric offsets of a crown's core (a guard: the offsets end when the core is
/// used up, after its width over the nozzle).
const MAX_CORE_OFFSETS: usize = 100_000;

/// Split the loops of the interior (the region shrunk by the boundary offset) into
/// runs nearer a hole and runs nearer the outer loop. A loop wholly on one side stays
/// one closed path; otherwise each run ends on the first vertex of the next, so the
/// runs share end points and together trace the whole loop.
///
/// `offset_mm` is how far the interior lies inside the region: most of its vertices
/// lie that far from one boundary and farther from the other, which two bounded looks
/// tell without measuring either distance.
fn split_boundary_runs(
    interior: &Shapes,
    region: &Region,
    offset_mm: f64,
) -> (Vec<Path>, Vec<Path>) {
    let to_outer = SegmentIndex::new(&[region.outer.as_slice()], &[]);
    let holes: Vec<&[DVec2]> = region.holes.iter().map(|h| h.as_slice()).collect();
    let to_holes = SegmentIndex::new(&holes, &[]);
    let (mut hole_runs, mut outer_runs) = (Vec::new(), Vec::new());
    for l in shapes::loops(interior) {
        let n = l.len();
        if n < 2 {
            continue;
        }
        // `dist(p, outer) <= dist(p, holes)`, measuring first the boundary the previous
        // vertex was nearer: the far one needs measuring only if it comes within that.
        let mut last = true;
        let reach = offset_mm.abs() * (1.0 + RUN_REACH_SLACK) + RUN_REACH_SLACK_MM;
        let near_outer: Vec<bool> = l
            .iter()
            .map(|&p| {
                // Only one boundary within the reach: that one is the nearer.
                let (outer, holes) = (to_outer.within(p, reach), to_holes.within(p, reach));
                last = if outer != holes {
                    outer
                } else if last {
                    let d = to_outer.distance(p);
                    !to_holes.within(p, d) || d <= to_holes.distance(p)
                } else {
                    let d = to_holes.distance(p);
                    to_outer.within(p, d) && to_outer.distance(p) <= d
                };
                last
            })
            .collect();
        let Some(start) = (0..n).find(|&k| near_outer[k] != near_outer[(k + n - 1) % n]) else {
            let path = Path {
                points: l.clone(),
                closed: true,
            };
            if near_outer[0] {
                outer_runs.push(path);
            } else {
                hole_runs.push(path);
            }
            continue;
        };
        let mut k = start;
        let mut walked = 0;
        while walked < n {
            let class = near_outer[k];
            let mut points = vec![l[k]];
            loop {
                k = (k + 1) % n;
                walked += 1;
                points.push(l[k]);
                if near_outer[k] != class || walked >= n {
                    break;
                }
            }
            let path = Path {
                points,
                closed: false,
            };
            if class {
                outer_runs.push(path);
            } else {
                hole_runs.push(path);
            }
        }
    }
    (hole_runs, outer_runs)
}

/// Plan every island of a layer.
pub fn plan_layer(
    index: usize,
    z_mm: f64,
    thickness_mm: f64,
    islands: &[Region],
    design: &GradientDesign,
    opts: &PlanOptions,
) -> Result<LayerPlan, PlanError> {
    let regions = islands
        .iter()
        .enumerate()
        .map(|(k, r)| plan_region(r, k, design, opts))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(LayerPlan {
        index,
        z_mm,
        thickness_mm,
        area_mm2: regions.iter().map(|r| r.area_mm2).sum(),
        regions,
        islands: islands.to_vec(),
        support: SupportArea::default(),
    })
}

/// One layer to plan, the planner's input: its index in the job's stack, its geometry
/// and the gradient design at its mid-height. The job file builds these
/// ([`crate::job::Job`]); the planner does not know the job file.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerSlice {
    pub index: usize,
    pub layer: crate::slice::Layer,
    pub design: GradientDesign,
}

/// A layer planning failure, naming the layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("layer {index} (z = {z_mm:.3} mm): {problem}")]
pub struct LayerError {
    pub index: usize,
    pub z_mm: f64,
    pub problem: PlanError,
}

/// Plan layers in parallel (rayon), each with its own gradient design. A layer whose
/// islands and design equal the previous layer's is planned once and reused with its
/// own index and z. `progress` hears `(layers done, layers total)`.
pub fn plan_layers(
    slices: &[LayerSlice],
    opts: &PlanOptions,
    progress: Option<&(dyn Fn(usize, usize) + Sync)>,
) -> Result<Vec<LayerPlan>, LayerError> {
    use rayon::prelude::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let firsts: Vec<usize> = (0..slices.len())
        .filter(|&k| {
            k == 0
                || slices[k].layer.islands != slices[k - 1].layer.islands
                || slices[k].design != slices[k - 1].design
        })
        .collect();
    let done = AtomicUsize::new(0);
    let planned: Vec<LayerPlan> = firsts
        .par_iter()
        .map(|&k| {
            let s = &slices[k];
            let l = &s.layer;
            let r = plan_layer(s.index, l.z_mm, l.thickness_mm, &l.islands, &s.design, opts)
                .map_err(|problem| LayerError {
                    index: s.index,
                    z_mm: l.z_mm,
                    problem,
                });
            if let Some(p) = progress {
                p(done.fetch_add(1, Ordering::Relaxed) + 1, firsts.len());
            }
            r
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut out: Vec<LayerPlan> = Vec::with_capacity(slices.len());
    let mut next = 0;
    for (k, s) in slices.iter().enumerate() {
        if next < firsts.len() && firsts[next] == k {
            out.push(planned[next].clone());
            next += 1;
        } else if let Some(prev) = out.last() {
            let mut p = prev.clone();
            p.index = s.index;
            p.z_mm = s.layer.z_mm;
            p.thickness_mm = s.layer.thickness_mm;
            out.push(p);
        }
    }
    Ok(out)
}

/// D_max: the largest distance from the upper contour's roads to the lower contour
/// (or the growth-ring centre), i.e. the widest gap between C_n and C_n+1 along the
/// gradient (parallel contours have it exactly, see the caller).
fn gap_along_gradient(
    upper_roads: &[Path],
    centre: Option<DVec2>,
    index: &SegmentIndex,
    opts: &PlanOptions,
) -> f64 {
    let step = opts.nozzle_mm.max(MIN_D_MAX_SAMPLE_MM);
    let mut best: f64 = 0.0;
    // The segment that last answered: the next sample, a piece further on, mostly has
    // it within `best` too.
    let mut hint = None;
    // Raise `best` to the distance of `p`; a point with a segment within `best` cannot
    // raise it, and saying so looks at fewer cells than the distance itself.
    let mut farther = |p: DVec2| {
        let d = if index.is_empty() {
            centre.map_or(0.0, |c| p.distance(c))
        } else if index.within_hinted(p, best, &mut hint) {
            return;
        } else {
            index.distance(p)
        };
        best = best.max(d);
    };
    for road in upper_roads {
        let pts = &road.points;
        let n = pts.len();
        let edges = if road.closed { n } else { n.saturating_sub(1) };
        for k in 0..edges {
            let (a, b) = (pts[k], pts[crate::geom::next_in_loop(k, n)]);
            // Sampled at the middle of pieces at most a nozzle long, never at a vertex:
            // from a convex corner the nearest point of the lower contour lies along
            // the bisector, d / sin(α/2) away, further than the gap beside the edges.
            let pieces = ((a.distance(b) / step).ceil() as usize).max(1);
            for q in 0..pieces {
                farther(a.lerp(b, (q as f64 + 0.5) / pieces as f64));
            }
        }
    }
    best
}

/// Growth rings (§3.1): the paper's radial lines and splines where the subdivision
/// allows them and they apply, else iso-contours of the normalised distance (unless
/// `subdivision = "radial"`, which refuses the region instead).
fn growth_rings(
    region: &Region,
    island: usize,
    opts: &PlanOptions,
) -> Result<PreSubdivision, PlanError> {
    if opts.subdivision != Subdivision::Distance {
        match radial_rings(region, island, opts)? {
            Ok(pre) => return Ok(pre),
            Err(radial_err) if opts.subdivision == Subdivision::Radial => return Err(radial_err),
            Err(_) => {}
        }
    }
    distance_rings(region, island, opts)
}

/// The centre growth rings grow from in a region with no hole: the pole of
/// inaccessibility of its outer loop.
fn ring_centre(region: &Region, opts: &PlanOptions) -> Option<DVec2> {
    field::DistanceField::outer_only(region, opts.cell_mm(), opts.max_field_nodes)
        .pole()
        .map(|(p, _)| p)
}

/// A_1 (the holes), the levels of the inner contours C2..Cm, and A_m+1 (the area
/// inside Ce).
fn ring_levels(region: &Region, inner: impl IntoIterator<Item = Shapes>) -> Vec<Level> {
    let mut levels = vec![Level::Shapes(shapes::from_loops(&region.holes))];
    levels.extend(inner.into_iter().map(Level::Shapes));
    levels.push(Level::Shapes(shapes::from_loops(std::slice::from_ref(
        &region.outer,
    ))));
    levels
}

/// Growth rings by radial lines from the centre of Ci at equal angular division, each
/// divided into m segments, and splines through the division points (§3.1, eq (1)).
/// `Ok(Err(why))` where the method does not apply to the region (the distance method
/// may); `Err` where the region cannot be planned at all.
fn radial_rings(
    region: &Region,
    island: usize,
    opts: &PlanOptions,
) -> Result<Result<PreSubdivision, PlanError>, PlanError> {
    let centre = if region.holes.is_empty() {
        ring_centre(region, opts)
    } else {
        None
    };
    let first = match radial::RadialSubdivision::new(
        &region.outer,
        &region.holes,
        centre,
        opts.radial_lines,
    ) {
        Ok(rs) => rs,
        Err(radial::RadialFailure::SeveralHoles(holes)) => {
            return Ok(Err(PlanError::SeveralHoles { island, holes }))
        }
        Err(radial::RadialFailure::NotStarShaped { centre }) => {
            return Ok(Err(PlanError::NotStarShaped {
                island,
                x: centre.x,
                y: centre.y,
            }))
        }
        Err(radial::RadialFailure::ContoursCross) => {
            return Ok(Err(PlanError::RadialCross {
                island,
                lines: opts.radial_lines,
            }))
        }
    };
    let m = resolved_m(first.l_short_mm, island, opts)?;
    Ok(match radial_splines(first, m, region, opts) {
        Ok((rs, splines)) => Ok(PreSubdivision {
            method: SubdivisionMethod::Radial,
            m,
            l_short_mm: rs.l_short_mm,
            centre: Some(rs.centre),
            levels: ring_levels(
                region,
                splines.into_iter().map(|c| shapes::from_loops(&[c])),
            ),
            inner_is_boundary: !region.holes.is_empty(),
        }),
        Err(lines) => Err(PlanError::RadialCross { island, lines }),
    })
}

/// The spline contours C2..Cm of a radial subdivision, with the radial lines doubled
/// (up to twice) while the splines cross a boundary or each other; with the
/// subdivision they came from. `Err(lines)`: they still cross with `lines` radial
/// lines.
fn radial_splines(
    first: radial::RadialSubdivision,
    m: u32,
    region: &Region,
    opts: &PlanOptions,
) -> Result<(radial::RadialSubdivision, Vec<Vec<DVec2>>), usize> {
    let mut lines = first.lines;
    let mut rs = first;
    for _ in 0..3 {
        match rs.contours(m, &region.outer, &region.holes, opts.contour_deviation_mm()) {
            Ok(cs) => return Ok((rs, cs)),
            Err(_) => {
                lines *= 2;
                match radial::RadialSubdivision::new(
                    &region.outer,
                    &region.holes,
                    Some(rs.centre),
                    lines,
                ) {
                    Ok(r) => rs = r,
                    Err(_) => break,
                }
            }
        }
    }
    Err(lines)
}

/// Growth rings by the general method: iso-contours of the normalised distance
/// dist(p, Ci) / (dist(p, Ci) + dist(p, Ce)). Without a hole the rings grow from the
/// pole of inaccessibility; with holes L_short is the thinnest wall, read off the same
/// distance field.
fn distance_rings(
    region: &Region,
    island: usize,
    opts: &PlanOptions,
) -> Result<PreSubdivision, PlanError> {
    let centre = if region.holes.is_empty() {
        ring_centre(region, opts)
    } else {
        None
    };
    let f = field::DistanceField::new(region, centre, opts.cell_mm(), opts.max_field_nodes);
    let l_short_mm = match centre {
        Some(c) => crate::geom::point_loop_distance(c, &region.outer),
        None => f.thinnest_wall().unwrap_or(0.0),
    };
    let m = resolved_m(l_short_mm, island, opts)?;
    let deviation = opts.contour_deviation_mm();
    let level_sets = f
        .level_sets(m, deviation * LEVEL_SPARSE_SHARE)
        .into_iter()
        .map(|loops| {
            let loops: Vec<Vec<DVec2>> = loops
                .iter()
                .map(|l| crate::geom::simplify_loop(l, deviation))
                .collect();
            shapes::from_loops(&loops)
        });
    Ok(PreSubdivision {
        method: SubdivisionMethod::Distance,
        m,
        l_short_mm,
        centre,
        levels: ring_levels(region, level_sets),
        inner_is_boundary: !region.holes.is_empty(),
    })
}

fn crown(
    region: &Region,
    island: usize,
    depth_mm: f64,
    opts: &PlanOptions,
) -> Result<PreSubdivision, PlanError> {
    let m = resolved_m(depth_mm, island, opts)?;
    let outer_shape = shapes::from_loops(std::slice::from_ref(&region.outer));
    let chord = opts.tolerances.chord_mm;
    let levels = (1..=m + 1)
        .map(|j| {
            let depth = depth_mm * (1.0 - contour_distance(j, m));
            Level::Shapes(shapes::offset(&outer_shape, -depth, chord))
        })
        .collect();
    Ok(PreSubdivision {
        method: SubdivisionMethod::Offset,
        m,
        l_short_mm: depth_mm,
        centre: None,
        levels,
        inner_is_boundary: false,
    })
}

/// The crown core inside C1, at the inner composition (W = 0): first the walls of any
/// hole inside the core (they are part surface, offset by the boundary offset like
/// every surface), then equal distance offsets of the core one nozzle apart, each one
/// step from the previous (concentric fill).
fn crown_core(
    a1: &Shapes,
    interior: &Shapes,
    m1: &Composition,
    opts: &PlanOptions,
    eps: f64,
) -> Option<SubRegion> {
    let chord = opts.tolerances.chord_mm;
    let core = shapes::intersection(a1, interior);
    let area = shapes::area(&core);
    if area <= opts.tolerances.min_loop_area_mm2 {
        return None;
    }
    let mut offsets = Vec::new();
    // The walls lie on the core's boundary: clip them against the core grown by a
    // hair, so they stay whole along the core and stop within that hair of it.
    let core_grown = shapes::offset(&core, opts.tolerances.clip_margin_mm, chord);
    let walls: Vec<Path> = interior
        .iter()
        .flat_map(|shape| shape.iter().skip(1))
        .flat_map(|hole| shapes::clip_loop(hole, &core_grown, true, eps))
        .collect();
    if !walls.is_empty() {
        offsets.push(walls);
    }
    let mut level = core.clone();
    for _ in 0..MAX_CORE_OFFSETS {
        level = shapes::offset(&level, -opts.nozzle_mm, chord);
        if level.is_empty() {
            break;
        }
        let roads: Vec<Path> = shapes::loops(&level)
            .map(|l| Path {
                points: l.clone(),
                closed: true,
            })
            .collect();
        offsets.push(roads);
    }
    let n_max = offsets.len() as u32 + 1;
    Some(SubRegion {
        n: 0,
        d_max_mm: n_max as f64 * opts.nozzle_mm,
        n_max,
        direction: OffsetDirection::Inward,
        from: m1.clone(),
        w: step_width(OffsetDirection::Inward, 2, m1, m1),
        offsets,
        area_mm2: area,
        shape: core,
    })
}

fn fibers(
    region: &Region,
    island: usize,
    angle_deg: f64,
    opts: &PlanOptions,
) -> Result<PreSubdivision, PlanError> {
    let a = angle_deg.to_radians();
    let normal = DVec2::new(-a.sin(), a.cos());
    let (lo, hi) = region.bounds();
    let (mut s_min, mut s_max) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in &region.outer {
        s_min = s_min.min(normal.dot(*p));
        s_max = s_max.max(normal.dot(*p));
    }
    let l_short_mm = s_max - s_min;
    let m = resolved_m(l_short_mm, island, opts)?;
    let pad = DVec2::splat(1.0);
    let levels = (1..=m + 1)
        .map(|j| Level::HalfPlane {
            normal,
            s: s_min + contour_distance(j, m) * l_short_mm,
            lo: lo - pad,
            hi: hi + pad,
        })
        .collect();
    Ok(PreSubdivision {
        method: SubdivisionMethod::Parallel,
        m,
        l_short_mm,
        centre: None,
        levels,
        inner_is_boundary: true,
    })
}

/// The composition of equal distance offset `i` of `sub` exactly by eq (6), from the
/// bounding contours' compositions.
pub fn offset_composition_eq6(plan: &RegionPlan, sub: &SubRegion, i: u32) -> Composition {
    if sub.n == 0 {
        return sub.from.clone();
    }
    let m_n = &plan.contours[(sub.n - 1) as usize].composition;
    let m_n1 = &plan.contours[sub.n as usize].composition;
    offset_composition(sub.direction, i, sub.n_max, m_n, m_n1)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn comp(v: &[f64]) -> Composition {
        Composition::new(v.to_vec(), 1e-12).unwrap()
    }

    pub(crate) fn annulus(r_in: f64, r_out: f64) -> Region {
        let outer = shapes::circle(DVec2::ZERO, r_out, 0.002);
        let mut hole = shapes::circle(DVec2::ZERO, r_in, 0.002);
        hole.reverse();
        Region::new(outer, vec![hole])
    }

    fn design(pattern: Pattern) -> GradientDesign {
        GradientDesign {
            pattern,
            inner: comp(&[1.0, 0.0]),
            outer: comp(&[0.0, 1.0]),
            function: GradientFunction::LINEAR,
        }
    }

    #[test]
    fn paper_annulus_reproduces_section_3() {
        let opts = PlanOptions::new(2.0, 0.5);
        let plan = plan_region(
            &annulus(10.0, 30.0),
            0,
            &design(Pattern::GrowthRings),
            &opts,
        )
        .unwrap();
        assert_eq!(plan.method, SubdivisionMethod::Radial);
        assert_eq!(plan.m, 10);
        assert_eq!(plan.contours.len(), 11);
        let c4 = &plan.contours[3];
        let c5 = &plan.contours[4];
        assert!(c4.composition.max_abs_diff(&comp(&[0.7, 0.3])) <= 1e-12);
        assert!(c5.composition.max_abs_diff(&comp(&[0.6, 0.4])) <= 1e-12);
        let s45 = plan.sub_regions.iter().find(|s| s.n == 4).unwrap();
        assert_eq!(s45.n_max, 4);
        assert!((s45.d_max_mm - 2.0).abs() < 0.01, "{}", s45.d_max_mm);
        assert!((s45.w.components()[0] - 0.025).abs() <= 1e-12);
        let want = [[0.625, 0.375], [0.65, 0.35], [0.675, 0.325]];
        for (i, w) in (1..=3).zip(want) {
            let m = offset_composition_eq6(&plan, s45, i);
            assert!(m.max_abs_diff(&comp(&w)) <= 1e-12);
            assert!(s45.composition_of(i).max_abs_diff(&comp(&w)) <= 1e-12);
            // Offset i of C5 inward lies at r = 18 - i * 0.5, as one closed loop.
            let roads = &s45.offsets[(i - 1) as usize];
            assert_eq!(roads.len(), 1);
            assert!(roads[0].closed);
            let r = 18.0 - 0.5 * i as f64;
            assert!(
                roads[0]
                    .points
                    .iter()
                    .all(|p| (p.length() - r).abs() < 0.02),
                "offset {i}"
            );
        }
        // C1 and C11 roads are the boundaries offset by D_noz / 2 into the part.
        assert!(plan.contours[0].roads[0]
            .points
            .iter()
            .all(|p| (p.length() - 10.25).abs() < 0.02));
        assert!(plan.contours[10].roads[0]
            .points
            .iter()
            .all(|p| (p.length() - 29.75).abs() < 0.02));
    }

    /// No road may double back on itself (a needle of material): the outline builder's
    /// occasional spikes must be cleaned away. Uses the job file's circle tolerance.
    #[test]
    fn no_road_doubles_back() {
        let mut opts = PlanOptions::new(2.0, 0.5);
        for subdivision in [Subdivision::Radial, Subdivision::Distance] {
            opts.subdivision = subdivision;
            let outer = shapes::circle(DVec2::ZERO, 30.0, 0.01);
            let mut hole = shapes::circle(DVec2::ZERO, 10.0, 0.01);
            hole.reverse();
            let plan = plan_region(
                &Region::new(outer, vec![hole]),
                0,
                &design(Pattern::GrowthRings),
                &opts,
            )
            .unwrap();
            let roads = plan.contours.iter().flat_map(|c| c.roads.iter()).chain(
                plan.sub_regions
                    .iter()
                    .flat_map(|s| s.offsets.iter().flatten()),
            );
            for p in roads {
                for (a, b, c) in turns(p) {
                    let (u, v) = (b - a, c - b);
                    assert!(
                        u.dot(v) > -0.5 * u.length() * v.length(),
                        "{subdivision:?}: road turns back at {b} ({a} -> {b} -> {c})"
                    );
                }
            }
        }
    }

    /// Each vertex of a road where it turns, with the vertices before and after it
    /// (every vertex of a loop; all but the ends of an open road).
    fn turns(p: &Path) -> impl Iterator<Item = (DVec2, DVec2, DVec2)> + '_ {
        let n = p.points.len();
        let count = if p.closed { n } else { n.saturating_sub(2) };
        (0..count).map(move |k| (p.points[k], p.points[(k + 1) % n], p.points[(k + 2) % n]))
    }

    #[test]
    fn distance_method_agrees_on_the_annulus() {
        let mut opts = PlanOptions::new(2.0, 0.5);
        opts.subdivision = Subdivision::Distance;
        let plan = plan_region(
            &annulus(10.0, 30.0),
            0,
            &design(Pattern::GrowthRings),
            &opts,
        )
        .unwrap();
        assert_eq!(plan.method, SubdivisionMethod::Distance);
        assert_eq!(plan.m, 10);
        let s45 = plan.sub_regions.iter().find(|s| s.n == 4).unwrap();
        assert_eq!(s45.n_max, 4);
    }
}
