//! The plan report (`docs/plan-report.md`): what will be built, layer by layer, as JSON.
//!
//! Per layer its z, thickness and area; per region the subdivision method, m, every
//! contour (index j, composition, length) and every sub-region (index n, D_max, N_max,
//! the composition of each equal distance offset in order by eq (6), W); totals,
//! the compact-representation size against a voxel composition grid, and planning time.

use crate::job::Job;
use crate::plan::{offset_composition_eq6, LayerPlan, RegionPlan, SubdivisionMethod};
use serde::Serialize;

/// Version tag of the report schema.
pub const SCHEMA: &str = "edo.plan-report/1";

#[derive(Debug, Clone, Serialize)]
pub struct PlanReport {
    pub schema: &'static str,
    pub job: String,
    pub materials: Vec<String>,
    pub settings: Settings,
    /// Mesh validation and repair (mesh jobs only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mesh: Option<crate::mesh::MeshReport>,
    /// What slicing had to do beyond cutting (mesh jobs only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub slicing: Option<crate::slice::SliceReport>,
    /// Which way up the part is built, and why (mesh jobs only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub orientation: Option<crate::mesh::orient::OrientationReport>,
    pub layers: Vec<LayerReport>,
    pub totals: Totals,
    /// Toolpath totals (when the toolpaths were made: `--report` of `edoctl plan`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub toolpath: Option<ToolpathTotals>,
    /// What rests on nothing (`attach_overhangs`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub overhang: Option<OverhangReport>,
    /// The supports built (`attach_supports`; a job with `[support]` on).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub support: Option<SupportReport>,
    /// Where the part goes on the machine and whether it fits (`edoctl plan`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub placement: Option<PlacementReport>,
    pub planning_time_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Settings {
    pub pattern: crate::plan::Pattern,
    pub function: crate::material::GradientFunction,
    pub inner: Vec<f64>,
    pub outer: Vec<f64>,
    pub subdivision: crate::plan::Subdivision,
    pub direction: crate::material::OffsetDirection,
    pub r_mach_mm: f64,
    pub nozzle_mm: f64,
    pub boundary_offset_mm: f64,
    pub offset_end_clearance_mm: f64,
    pub min_road_mm: f64,
    pub contour_deviation_mm: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct LayerReport {
    pub index: usize,
    pub z_mm: f64,
    pub thickness_mm: f64,
    pub area_mm2: f64,
    /// M(Ci) and M(Ce) of this layer (they vary with a Z gradient).
    pub inner: Vec<f64>,
    pub outer: Vec<f64>,
    pub regions: Vec<RegionReport>,
    /// Area not resting on the layer below beyond the allowed overhang (`[process]
    /// overhang`), mm²; absent for a layer whose layer below was not planned.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unsupported_area_mm2: Option<f64>,
    /// Support built in this layer (`[support]`), mm²: base and interface together;
    /// absent with supports off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub support_area_mm2: Option<f64>,
    /// The layer's roads as the machine will build them (see [`LayerToolpath`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub toolpath: Option<LayerToolpath>,
}

/// A layer's toolpath (`docs/toolpath.md`): paths, moves, travel, flow raise, and the
/// coverage of its roads.
#[derive(Debug, Clone, Serialize)]
pub struct LayerToolpath {
    pub paths: usize,
    pub moves: usize,
    pub extrude_moves: usize,
    pub retracts: usize,
    pub extruded_mm: f64,
    pub travel_mm: f64,
    /// Closed loops whose seam sits in a concave corner.
    pub seams_at_corners: usize,
    pub closed_loops: usize,
    /// Widest road relative to nominal (flow raise in narrow sub-areas).
    pub max_width_factor: f64,
    /// Volume each syringe pushes in this layer, µL.
    pub syringe_volumes_ul: Vec<f64>,
    /// Designed-versus-delivered composition error under the machine's mixing-chamber
    /// model (`edo::mixer`), with the mixing lead or the mixer's feed-forward inverse,
    /// move by move (volume-weighted mean and worst).
    pub composition_error_mean: f64,
    pub composition_error_max: f64,
    /// The same road by road (over each road's whole volume).
    pub composition_error_road_mean: f64,
    pub composition_error_road_max: f64,
    /// Roads whose predicted error exceeds `mixer_tolerance` (the design changes faster
    /// than the mixer can): how many, and the worst (at most 20).
    pub mixer_limited_roads: usize,
    pub mixer_limited: Vec<crate::pipeline::MixerLimit>,
    /// Volume purged before the layer (`[toolpath] purge_xy_mm`), µL; 0 without a purge.
    pub purge_ul: f64,
    /// Coverage of the roads (with `--coverage` or `--svg`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coverage: Option<CoverageReport>,
}

/// Coverage of roads rasterised at `cell_mm` (`toolpath::coverage`): fractions of the
/// part area.
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct CoverageReport {
    pub cell_mm: f64,
    /// Part area no road covers.
    pub void_fraction: f64,
    /// The same roads at nominal width (no flow raise): the raise's gain is the difference.
    pub void_fraction_without_raise: f64,
    /// Part area covered by two or more roads.
    pub overlap_fraction: f64,
    /// Deposited outside the part.
    pub outside_fraction: f64,
}

impl CoverageReport {
    /// From the coverage with and without the flow raise.
    pub fn new(
        with_raise: &crate::toolpath::coverage::Coverage,
        without_raise: &crate::toolpath::coverage::Coverage,
    ) -> Self {
        CoverageReport {
            cell_mm: with_raise.cell_mm,
            void_fraction: with_raise.void_fraction(),
            void_fraction_without_raise: without_raise.void_fraction(),
            overlap_fraction: with_raise.overlap_fraction(),
            outside_fraction: with_raise.outside_fraction(),
        }
    }
}

/// Toolpath totals over the planned layers.
#[derive(Debug, Clone, Serialize, Default)]
pub struct ToolpathTotals {
    pub moves: usize,
    pub extruded_mm: f64,
    pub travel_mm: f64,
    pub retracts: usize,
    pub syringe_volumes_ul: Vec<f64>,
    /// Worst layer's `composition_error_road_max`, and the mixer-limited roads in all.
    pub composition_error_road_max: f64,
    pub mixer_limited_roads: usize,
    /// Summed over layers (cell counts), when coverage was measured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coverage: Option<CoverageReport>,
}

#[derive(Debug, Clone, Serialize)]
pub struct RegionReport {
    pub island: usize,
    pub method: SubdivisionMethod,
    pub m: u32,
    pub l_short_mm: f64,
    pub centre: Option<[f64; 2]>,
    pub area_mm2: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    pub contours: Vec<ContourReport>,
    pub sub_regions: Vec<SubRegionReport>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ContourReport {
    pub j: u32,
    pub d: f64,
    pub composition: Vec<f64>,
    pub length_mm: f64,
    /// Closed loops and open pieces the contour's roads consist of.
    pub paths: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct SubRegionReport {
    pub n: u32,
    pub d_max_mm: f64,
    pub n_max: u32,
    pub direction: crate::material::OffsetDirection,
    pub w: Vec<f64>,
    pub area_mm2: f64,
    /// Equal distance offsets i = 1..N_max − 1 in order.
    pub offsets: Vec<OffsetReport>,
}

#[derive(Debug, Clone, Serialize)]
pub struct OffsetReport {
    pub i: u32,
    pub composition: Vec<f64>,
    pub length_mm: f64,
    pub paths: usize,
    /// Of those, how many are closed loops (the rest are non-continuous segments).
    pub closed: usize,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Totals {
    pub layers: usize,
    pub regions: usize,
    pub contours: usize,
    pub sub_regions: usize,
    pub offsets: usize,
    pub paths: usize,
    pub contour_length_mm: f64,
    pub offset_length_mm: f64,
    /// Bytes of the compact material information (§3.2): per sub-region one contour
    /// composition, W and N_max (f64 fractions, u32 count).
    pub compact_material_bytes: usize,
    /// Bytes of the whole plan with its geometry (postcard encoding).
    pub plan_bytes: usize,
    /// Bytes of a voxel composition grid at R_mach / 4 over each layer's bounding box
    /// (one f64 fraction per material per voxel).
    pub voxel_grid_bytes: usize,
}

fn region_report(r: &RegionPlan) -> RegionReport {
    RegionReport {
        island: r.island,
        method: r.method,
        m: r.m,
        l_short_mm: r.l_short_mm,
        centre: r.centre.map(|c| [c.x, c.y]),
        area_mm2: r.area_mm2,
        note: r.note.clone(),
        contours: r
            .contours
            .iter()
            .map(|c| ContourReport {
                j: c.j,
                d: c.d,
                composition: c.composition.fractions().to_vec(),
                length_mm: c.roads.iter().map(|p| p.length_mm()).sum(),
                paths: c.roads.len(),
            })
            .collect(),
        sub_regions: r
            .sub_regions
            .iter()
            .map(|s| SubRegionReport {
                n: s.n,
                d_max_mm: s.d_max_mm,
                n_max: s.n_max,
                direction: s.direction,
                w: s.w.components().to_vec(),
                area_mm2: s.area_mm2,
                offsets: s
                    .offsets
                    .iter()
                    .enumerate()
                    .map(|(k, paths)| OffsetReport {
                        i: k as u32 + 1,
                        composition: offset_composition_eq6(r, s, k as u32 + 1)
                            .fractions()
                            .to_vec(),
                        length_mm: paths.iter().map(|p| p.length_mm()).sum(),
                        paths: paths.len(),
                        closed: paths.iter().filter(|p| p.closed).count(),
                    })
                    .collect(),
            })
            .collect(),
    }
}

/// Bytes of the compact material information of one layer plan.
pub fn compact_material_bytes(layer: &LayerPlan) -> usize {
    layer
        .regions
        .iter()
        .map(|r| {
            r.sub_regions
                .iter()
                .map(|s| (s.from.len() + s.w.components().len()) * 8 + 4)
                .sum::<usize>()
        })
        .sum()
}

/// Bytes of a voxel composition grid at `r_mach / 4` over the layer's bounding box.
pub fn voxel_grid_bytes(
    islands: &[crate::geom::Region],
    materials: usize,
    r_mach_mm: f64,
) -> usize {
    let cell = r_mach_mm / 4.0;
    islands
        .iter()
        .map(|r| {
            let (lo, hi) = r.bounds();
            let nx = ((hi.x - lo.x) / cell).ceil() as usize;
            let ny = ((hi.y - lo.y) / cell).ceil() as usize;
            nx * ny * materials * 8
        })
        .sum()
}

/// What a mesh job's loading and slicing reported.
#[derive(Debug, Clone, Default)]
pub struct MeshNotes {
    pub mesh: Option<crate::mesh::MeshReport>,
    pub slicing: Option<crate::slice::SliceReport>,
    /// Which way up the part is built (mesh jobs only).
    pub orientation: Option<crate::mesh::orient::OrientationReport>,
    /// The mesh's bounding box (min, max), mm, in its own coordinates (turned).
    pub bounds: Option<(glam::DVec3, glam::DVec3)>,
}

/// Where the part goes on the machine (`geometry.placement`) and whether it fits the
/// build volume `edoctl plan` was given.
#[derive(Debug, Clone, Serialize)]
pub struct PlacementReport {
    pub mode: crate::job::placement::PlacementMode,
    pub build_volume_mm: [f64; 3],
    /// The part's bounding box in its own coordinates (the layers' and previews').
    pub part_min_mm: [f64; 3],
    pub part_max_mm: [f64; 3],
    /// Added to every move's position (`null` when the part does not fit).
    pub offset_mm: Option<[f64; 3]>,
    /// The bounding box on the machine (`null` when the part does not fit).
    pub machine_min_mm: Option<[f64; 3]>,
    pub machine_max_mm: Option<[f64; 3]>,
    /// Why the part cannot be built on this volume (`null` when it fits).
    pub problem: Option<String>,
}

impl PlacementReport {
    /// The report of placing a part with bounding box `bounds` (its own coordinates)
    /// into `build_volume_mm`: `placed` is the placement or why there is none.
    pub fn new(
        mode: crate::job::placement::PlacementMode,
        build_volume_mm: [f64; 3],
        bounds: (glam::DVec3, glam::DVec3),
        placed: &Result<crate::job::placement::Placement, String>,
    ) -> PlacementReport {
        let (lo, hi) = (bounds.0.to_array(), bounds.1.to_array());
        let offset = placed.as_ref().ok().map(|p| p.offset_mm());
        let shifted = |v: [f64; 3]| offset.map(|o| [v[0] + o[0], v[1] + o[1], v[2] + o[2]]);
        PlacementReport {
            mode,
            build_volume_mm,
            part_min_mm: lo,
            part_max_mm: hi,
            offset_mm: offset,
            machine_min_mm: shifted(lo),
            machine_max_mm: shifted(hi),
            problem: placed.as_ref().err().cloned(),
        }
    }
}

/// Build the report for a planned job.
pub fn build(
    job: &Job,
    slices: &[crate::plan::LayerSlice],
    layers: &[LayerPlan],
    notes: MeshNotes,
    planning_time_ms: f64,
) -> PlanReport {
    let mut totals = Totals {
        layers: layers.len(),
        ..Totals::default()
    };
    let mut reports = Vec::with_capacity(layers.len());
    for (k, l) in layers.iter().enumerate() {
        let regions: Vec<RegionReport> = l.regions.iter().map(region_report).collect();
        for r in &regions {
            totals.regions += 1;
            totals.contours += r.contours.len();
            totals.sub_regions += r.sub_regions.len();
            totals.contour_length_mm += r.contours.iter().map(|c| c.length_mm).sum::<f64>();
            totals.paths += r.contours.iter().map(|c| c.paths).sum::<usize>();
            for s in &r.sub_regions {
                totals.offsets += s.offsets.len();
                totals.offset_length_mm += s.offsets.iter().map(|o| o.length_mm).sum::<f64>();
                totals.paths += s.offsets.iter().map(|o| o.paths).sum::<usize>();
            }
        }
        totals.compact_material_bytes += compact_material_bytes(l);
        totals.plan_bytes += postcard::to_stdvec(l).map(|v| v.len()).unwrap_or(0);
        if let Some(s) = slices.get(k) {
            totals.voxel_grid_bytes +=
                voxel_grid_bytes(&s.layer.islands, job.materials.len(), job.plan.r_mach_mm);
        }
        let design = slices.get(k).map(|s| &s.design).unwrap_or(&job.design);
        reports.push(LayerReport {
            index: l.index,
            z_mm: l.z_mm,
            thickness_mm: l.thickness_mm,
            area_mm2: l.area_mm2,
            inner: design.inner.fractions().to_vec(),
            outer: design.outer.fractions().to_vec(),
            regions,
            unsupported_area_mm2: None,
            support_area_mm2: None,
            toolpath: None,
        });
    }
    PlanReport {
        schema: SCHEMA,
        job: job.name.clone(),
        materials: job.materials.clone(),
        settings: Settings {
            pattern: job.design.pattern.clone(),
            function: job.design.function.clone(),
            inner: job.design.inner.fractions().to_vec(),
            outer: job.design.outer.fractions().to_vec(),
            subdivision: job.plan.subdivision,
            direction: job.plan.direction,
            r_mach_mm: job.plan.r_mach_mm,
            nozzle_mm: job.plan.nozzle_mm,
            boundary_offset_mm: job.plan.boundary_offset_mm,
            offset_end_clearance_mm: job.plan.offset_end_clearance_mm,
            min_road_mm: job.plan.min_road_mm,
            contour_deviation_mm: job.plan.contour_deviation_mm,
        },
        mesh: notes.mesh,
        slicing: notes.slicing,
        orientation: notes.orientation,
        layers: reports,
        totals,
        toolpath: None,
        overhang: None,
        support: None,
        placement: None,
        planning_time_ms,
    }
}

/// The overhangs of a plan: what is allowed, and the layers with area beyond it.
#[derive(Debug, Clone, Serialize)]
pub struct OverhangReport {
    /// `[process] overhang`.
    pub allowed: crate::slice::overhang::Overhang,
    /// Area resting on nothing, all layers, mm².
    pub unsupported_area_mm2: f64,
    /// The layers with such area (over 0.01 mm²), bottom to top.
    pub layers: Vec<usize>,
    /// The layer with the most, and how much, mm².
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worst_layer: Option<usize>,
    pub worst_area_mm2: f64,
    /// With supports built: the area resting on nothing without them, all layers,
    /// mm² (the figures above are what still rests on nothing with them).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub without_supports_mm2: Option<f64>,
    /// `layers` with their areas, mm².
    #[serde(skip)]
    per_layer: Vec<(usize, f64)>,
}

impl OverhangReport {
    /// The warning for people: none when nothing hangs.
    pub fn warning(&self) -> Option<String> {
        crate::slice::overhang::warning(&self.allowed, &self.per_layer)
    }

    /// The refusal of a job with `[support] required`: none when nothing hangs.
    pub fn refusal(&self) -> Option<String> {
        crate::slice::overhang::refusal(&self.allowed, &self.per_layer)
    }
}

/// Each layer's unsupported area (`overhangs[k]` of `report.layers[k]`) and the
/// whole part's.
pub fn attach_overhangs(
    report: &mut PlanReport,
    allowed: crate::slice::overhang::Overhang,
    overhangs: &[Option<crate::geom::Shapes>],
) {
    use crate::slice::overhang::{area_mm2, MIN_REPORTED_MM2};
    let mut whole = OverhangReport {
        allowed,
        unsupported_area_mm2: 0.0,
        layers: Vec::new(),
        worst_layer: None,
        worst_area_mm2: 0.0,
        without_supports_mm2: None,
        per_layer: Vec::new(),
    };
    for (l, o) in report.layers.iter_mut().zip(overhangs) {
        let Some(shapes) = o else { continue };
        let a = area_mm2(shapes);
        l.unsupported_area_mm2 = Some(a);
        if a > MIN_REPORTED_MM2 {
            whole.unsupported_area_mm2 += a;
            whole.layers.push(l.index);
            whole.per_layer.push((l.index, a));
            if a > whole.worst_area_mm2 {
                whole.worst_area_mm2 = a;
                whole.worst_layer = Some(l.index);
            }
        }
    }
    report.overhang = Some(whole);
}

/// The supports of a plan (`[support]`, `slice::support`).
#[derive(Debug, Clone, Serialize)]
pub struct SupportReport {
    /// `buildplate` or `everywhere`.
    pub mode: crate::slice::support::SupportMode,
    /// What they are built of: `syringe "<name>"` or `composition [..]`.
    pub material: String,
    /// Layers with support.
    pub layers: usize,
    /// Volume of the support's area, all layers (area x thickness), mm³: the
    /// columns' outline, not the road laid in them.
    pub area_volume_mm3: f64,
    /// Of which the dense interface, mm³.
    pub interface_volume_mm3: f64,
    /// The support roads' length, mm (when the toolpaths were made).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roads_mm: Option<f64>,
    /// The material the support roads push (length x road width x layer), mm³.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub road_volume_mm3: Option<f64>,
}

/// Each layer's support area (`areas[k]` of `report.layers[k]`) and the totals.
pub fn attach_supports(
    report: &mut PlanReport,
    job: &crate::job::Job,
    areas: &[crate::slice::support::SupportArea],
) {
    use crate::geom::area;
    let mut whole = SupportReport {
        mode: job.support.mode,
        material: match &job.support.material {
            Some(crate::job::SupportMaterial::Syringe(name)) => format!("syringe {name:?}"),
            Some(crate::job::SupportMaterial::Composition(c)) => format!("composition {c:?}"),
            None => String::new(),
        },
        layers: 0,
        area_volume_mm3: 0.0,
        interface_volume_mm3: 0.0,
        roads_mm: None,
        road_volume_mm3: None,
    };
    for (l, a) in report.layers.iter_mut().zip(areas) {
        let all = area(&a.base).abs() + area(&a.interface).abs();
        l.support_area_mm2 = Some(all);
        if !a.is_empty() {
            whole.layers += 1;
        }
        whole.area_volume_mm3 += all * l.thickness_mm;
        whole.interface_volume_mm3 += area(&a.interface).abs() * l.thickness_mm;
    }
    report.support = Some(whole);
}

/// The support roads' length and volume into `report.support` from each layer's
/// paths (`layers[k]` of `report.layers[k]`), `road_width_mm` wide.
pub fn attach_support_roads(
    report: &mut PlanReport,
    paths: &[&[crate::toolpath::ToolPath]],
    road_width_mm: f64,
) {
    let Some(whole) = report.support.as_mut() else {
        return;
    };
    let (mut length, mut volume) = (0.0, 0.0);
    for (l, p) in report.layers.iter().zip(paths) {
        let here: f64 = p
            .iter()
            .filter(|p| p.role.is_support())
            .map(crate::toolpath::ToolPath::length_mm)
            .sum();
        length += here;
        volume += here * road_width_mm * l.thickness_mm;
    }
    whole.roads_mm = Some(length);
    whole.road_volume_mm3 = Some(volume);
}

/// Attach per-layer toolpaths (in layer order, one per report layer) and their totals;
/// `coverage` holds each layer's coverage with and without the flow raise when measured.
pub fn attach_toolpaths(
    report: &mut PlanReport,
    stats: &[crate::pipeline::LayerStats],
    coverage: Option<
        &[(
            crate::toolpath::coverage::Coverage,
            crate::toolpath::coverage::Coverage,
        )],
    >,
) {
    let mut totals = ToolpathTotals::default();
    let (mut with, mut without) = (
        crate::toolpath::coverage::Coverage::default(),
        crate::toolpath::coverage::Coverage::default(),
    );
    for (k, (layer, st)) in report.layers.iter_mut().zip(stats).enumerate() {
        let ul: Vec<f64> = st
            .commanded_nl
            .iter()
            .map(|&nl| nl as f64 / 1000.0)
            .collect();
        if totals.syringe_volumes_ul.len() < ul.len() {
            totals.syringe_volumes_ul.resize(ul.len(), 0.0);
        }
        for (t, v) in totals.syringe_volumes_ul.iter_mut().zip(&ul) {
            *t += v;
        }
        totals.moves += st.moves;
        totals.extruded_mm += st.extruded_mm;
        totals.travel_mm += st.travel_mm;
        totals.retracts += st.retracts;
        totals.composition_error_road_max = totals
            .composition_error_road_max
            .max(st.composition_error_road_max);
        totals.mixer_limited_roads += st.mixer_limited_roads;
        let cov = coverage.and_then(|c| c.get(k)).map(|(a, b)| {
            with.add(a);
            without.add(b);
            CoverageReport::new(a, b)
        });
        layer.toolpath = Some(LayerToolpath {
            paths: st.paths,
            moves: st.moves,
            extrude_moves: st.extrude_moves,
            retracts: st.retracts,
            extruded_mm: st.extruded_mm,
            travel_mm: st.travel_mm,
            seams_at_corners: st.seams_at_corners,
            closed_loops: st.closed_loops,
            max_width_factor: st.max_width_factor,
            syringe_volumes_ul: ul,
            composition_error_mean: st.composition_error_mean,
            composition_error_max: st.composition_error_max,
            composition_error_road_mean: st.composition_error_road_mean,
            composition_error_road_max: st.composition_error_road_max,
            mixer_limited_roads: st.mixer_limited_roads,
            mixer_limited: st.mixer_limited.clone(),
            purge_ul: st.purge_nl / 1000.0,
            coverage: cov,
        });
    }
    if coverage.is_some() {
        totals.coverage = Some(CoverageReport::new(&with, &without));
    }
    report.toolpath = Some(totals);
}
