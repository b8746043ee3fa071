//! The job file (`docs/job-format.md`): what to build, from which materials, with which
//! gradient, on which process settings. TOML, parsed with serde, every unknown key
//! refused, every value validated with an error that names the key.
//!
//! Pure: [`Job::from_toml`] takes the text (and a name for messages); reading the file
//! is the caller's business.

pub mod placement;
mod support;
use crate::geom::{self as shapes, Region, Tolerances};
use crate::material::{Composition, GradientFunction, OffsetDirection};
use crate::plan::{GradientDesign, LayerSlice, Pattern, PlanOptions, Subdivision};
use glam::{DVec2, DVec3};
use placement::PlacementMode;
use serde::Deserialize;
pub use support::PartSupports;

/// A job file that cannot be used, with where and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum JobError {
    /// The TOML itself is malformed or has unknown/missing keys (message has line and column).
    #[error("{source_name}: {message}")]
    Syntax {
        source_name: String,
        message: String,
    },
    /// A value is out of range or inconsistent; `key` is its dotted path.
    #[error("{source_name}: {key}: {message}")]
    Invalid {
        source_name: String,
        key: String,
        message: String,
    },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawJob {
    name: String,
    geometry: RawGeometry,
    materials: RawMaterials,
    gradient: RawGradient,
    process: RawProcess,
    /// Process settings of the toolpath stage (`docs/toolpath.md`), all optional.
    toolpath: Option<crate::pipeline::ProcessSettings>,
    #[serde(default)]
    support: RawSupport,
}

/// `[support]` as written (`docs/job-format.md`).
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSupport {
    #[serde(default)]
    required: bool,
    mode: Option<String>,
    syringe: Option<String>,
    composition: Option<Vec<f64>>,
    top_gap_mm: Option<f64>,
    bottom_gap_mm: Option<f64>,
    xy_gap_mm: Option<f64>,
    interface_layers: Option<u32>,
    pattern: Option<String>,
    density: Option<f64>,
    angle_deg: Option<f64>,
}

/// What builds supports in, `[support] syringe` or `composition`.
#[derive(Clone, Debug, PartialEq)]
pub enum SupportMaterial {
    /// A syringe of its own (a fugitive ink such as Pluronic or wax), pushed pure:
    /// on the machine one with `role = "support"` of this name.
    Syringe(String),
    /// The part's materials at this composition (fractions in `materials.names`
    /// order).
    Composition(Vec<f64>),
}

/// `[support]`: what the job asks of what holds its layers up, defaults resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct Support {
    /// Refuse to print a part with area resting on nothing beyond the allowed
    /// overhang after supports (`edoctl plan` fails, `job.submit` refuses), rather
    /// than warn.
    pub required: bool,
    pub mode: crate::slice::support::SupportMode,
    /// What supports are built of (none when `mode` is off).
    pub material: Option<SupportMaterial>,
    pub top_gap_mm: f64,
    pub bottom_gap_mm: f64,
    pub xy_gap_mm: f64,
    pub interface_layers: u32,
    pub pattern: crate::toolpath::support::SupportPattern,
    pub density: f64,
    pub angle_deg: f64,
}

/// Dense layers at the top of a support column by default.
pub const DEFAULT_INTERFACE_LAYERS: u32 = 2;
/// The base's share of its area laid with road by default (lines 1.6 mm apart at a
/// 0.4 mm road).
pub const DEFAULT_SUPPORT_DENSITY: f64 = 0.25;

impl Support {
    /// Whether supports are built.
    pub fn builds(&self) -> bool {
        self.mode != crate::slice::support::SupportMode::Off
    }

    /// The support syringe's name, when supports are built of their own syringe.
    pub fn syringe(&self) -> Option<&str> {
        match (&self.material, self.builds()) {
            (Some(SupportMaterial::Syringe(name)), true) => Some(name),
            _ => None,
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGeometry {
    polygon: Option<RawRegion>,
    regions: Option<Vec<RawRegion>>,
    height: Option<f64>,
    mesh: Option<String>,
    placement: Option<PlacementSpec>,
    orientation: Option<OrientationSpec>,
}

/// `geometry.orientation`: "keep" | "auto" | { rotate = [x, y, z] }.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum OrientationSpec {
    Named(String),
    Rotate { rotate: [f64; 3] },
}

/// `geometry.placement`: "centre" | "keep" | { at = [x, y] }.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum PlacementSpec {
    Named(String),
    At { at: [f64; 2] },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRegion {
    outer: LoopSpec,
    #[serde(default)]
    holes: Vec<LoopSpec>,
}

/// A closed loop: explicit points, or a primitive.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum LoopSpec {
    Points(Vec<[f64; 2]>),
    Circle { circle: CircleSpec },
    Ellipse { ellipse: EllipseSpec },
    Rect { rect: RectSpec },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CircleSpec {
    center: [f64; 2],
    radius: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct EllipseSpec {
    center: [f64; 2],
    radii: [f64; 2],
    #[serde(default)]
    rotation: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RectSpec {
    min: [f64; 2],
    max: [f64; 2],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMaterials {
    names: Vec<String>,
    #[serde(default)]
    syringes: Option<Vec<String>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGradient {
    #[serde(default = "default_pattern")]
    pattern: String,
    inner: Vec<f64>,
    outer: Vec<f64>,
    #[serde(default)]
    function: Option<FunctionSpec>,
    #[serde(default)]
    subdivision: Option<Subdivision>,
    #[serde(default)]
    direction: Option<OffsetDirection>,
    depth: Option<f64>,
    angle: Option<f64>,
    #[serde(default)]
    z: Vec<RawZStation>,
    z_step: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawZStation {
    z: f64,
    inner: Vec<f64>,
    outer: Vec<f64>,
}

fn default_pattern() -> String {
    "growth-rings".to_string()
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum FunctionSpec {
    Named(String),
    Power { power: f64 },
    Table { table: Vec<[f64; 2]> },
    Linear { linear: LinearSpec },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LinearSpec {
    a: f64,
    b: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawProcess {
    r_mach: f64,
    nozzle: f64,
    layer: Option<LayerSpec>,
    boundary_offset: Option<f64>,
    offset_end_clearance: Option<f64>,
    min_road: Option<f64>,
    radial_lines: Option<usize>,
    field_cell: Option<f64>,
    contour_deviation: Option<f64>,
    move_deviation: Option<f64>,
    move_width_tolerance: Option<f64>,
    cusp: Option<f64>,
    max_gap: Option<f64>,
    thin_regions: Option<crate::plan::ThinRegions>,
    #[serde(default)]
    overhang: Option<crate::slice::overhang::Overhang>,
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum LayerSpec {
    Uniform(f64),
    Range { min: f64, max: f64 },
}

/// Layer heights: uniform when `min_mm == max_mm`, else adaptive (mesh slope and the
/// Z gradient step).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LayerHeights {
    pub min_mm: f64,
    pub max_mm: f64,
    /// Largest staircase (cusp) height of adaptive layers on a sloped surface, mm.
    pub cusp_mm: f64,
    /// Largest gap in a mesh section closed with a straight segment, mm.
    pub max_gap_mm: f64,
}

/// What the job builds.
#[derive(Clone, Debug, PartialEq)]
pub enum Geometry {
    /// Islands (outer loop + holes) extruded from z = 0 to `height_mm`.
    Extruded {
        islands: Vec<Region>,
        height_mm: f64,
    },
    /// A triangle mesh (STL or 3MF), its path as written in the job: relative paths are
    /// relative to the job file. Reading it is the caller's business.
    Mesh { path: String },
}

/// M(Ci) and M(Ce) at a height: a station of a Z-varying gradient.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ZStation {
    pub z_mm: f64,
    pub inner: Composition,
    pub outer: Composition,
}

/// A validated job.
#[derive(Clone, Debug, PartialEq)]
pub struct Job {
    pub name: String,
    pub geometry: Geometry,
    /// One material per syringe.
    pub materials: Vec<String>,
    /// The machine's syringe (`[[machine.syringes]] name`) each material is loaded in,
    /// in the order of [`Job::materials`] (`materials.syringes`); unset: each material
    /// is in the syringe of its own name.
    pub syringes: Option<Vec<String>>,
    /// The 2D gradient design; with [`Job::z_stations`] its compositions vary with height.
    pub design: GradientDesign,
    /// Stations of a Z-varying gradient, ascending in z (empty: the same in every layer).
    pub z_stations: Vec<ZStation>,
    /// Largest change of any volume fraction allowed across one layer where the
    /// composition varies along Z (limits the layer thickness).
    pub z_step: f64,
    /// How far a layer may reach past the one below without support (`[process]
    /// overhang`).
    pub overhang: crate::slice::overhang::Overhang,
    /// `[support]`.
    pub support: Support,
    /// Which way up a mesh part is built (`geometry.orientation`).
    pub orientation: crate::mesh::orient::Orientation,
    pub plan: PlanOptions,
    pub layers: LayerHeights,
    /// The `[toolpath]` table: feeds, cessation, flow limits, mixing chamber, purge,
    /// seams (defaults where absent), with `nozzle_mm` = `process.nozzle`.
    pub toolpath: crate::pipeline::ProcessSettings,
    /// Where the part goes on the machine's bed (`geometry.placement`, see
    /// [`crate::job::placement`]).
    pub placement: PlacementMode,
}

impl Job {
    /// Parse and validate a job from TOML text. `source_name` (usually the file path)
    /// prefixes every message. The tables are checked in a fixed order (name,
    /// materials, process, gradient, geometry, Z stations, size limits, toolpath), so a
    /// file with several mistakes always reports the same one first.
    pub fn from_toml(text: &str, source_name: &str) -> Result<Job, JobError> {
        let raw: RawJob = toml::from_str(text).map_err(|e| JobError::Syntax {
            source_name: source_name.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let bad = |key: &str, message: String| JobError::Invalid {
            source_name: source_name.to_string(),
            key: key.to_string(),
            message,
        };
        let tolerances = Tolerances::default();

        check_name(&raw.name).map_err(|m| bad("name", m))?;
        let materials = materials(raw.materials.names, "materials.names", &bad)?;
        let syringes = raw
            .materials
            .syringes
            .map(|s| material_syringes(s, materials.len(), &bad))
            .transpose()?;
        let nozzle_mm = raw.process.nozzle;
        let mut plan = plan_options(&raw.process, tolerances, &bad)?;
        let layers = layer_heights(&raw.process, &bad)?;
        let g = raw.gradient;
        let design = gradient_design(&g, materials.len(), &tolerances, &bad)?;
        gradient_plan_options(&g, &design.pattern, &mut plan, &bad)?;
        let placement = placement(&raw.geometry.placement, &bad)?;
        let orientation = orientation(&raw.geometry, &bad)?;
        let geometry = geometry(raw.geometry, &tolerances, &bad)?;
        let z_stations = z_stations(g.z, materials.len(), &tolerances, &bad)?;
        let z_step = z_step(g.z_step, !z_stations.is_empty(), &bad)?;
        check_extruded_size(&geometry, &layers, !z_stations.is_empty(), nozzle_mm, &bad)?;
        let overhang = raw.process.overhang.unwrap_or_default();
        overhang.check().map_err(|m| bad("process.overhang", m))?;
        let mut toolpath = toolpath_settings(raw.toolpath, nozzle_mm, &bad)?;
        move_merging(&raw.process, nozzle_mm, &mut toolpath, &bad)?;
        let support = support::support(
            raw.support,
            &materials,
            &layers,
            toolpath.road_width(),
            &bad,
        )?;
        toolpath.support = support::support_roads(&support, materials.len());
        Ok(Job {
            toolpath,
            placement,
            name: raw.name,
            geometry,
            materials,
            syringes,
            design,
            z_stations,
            z_step,
            overhang,
            support,
            orientation,
            plan,
            layers,
        })
    }

    /// What choosing this job's orientation needs: its allowed overhang as an angle
    /// (a distance: over the thickest layer), half its thinnest layer for the bed.
    pub fn orient_options(&self) -> crate::mesh::orient::OrientOptions {
        use crate::slice::overhang::Overhang;
        let angle = match self.overhang {
            Overhang::AngleDeg(a) => a,
            Overhang::DistanceMm(d) => (d / self.layers.max_mm).atan().to_degrees(),
        };
        crate::mesh::orient::OrientOptions {
            overhang_angle_deg: angle,
            on_bed_mm: self.layers.min_mm / 2.0,
            ..Default::default()
        }
    }

    /// What finding this job's overhangs needs: the allowed overhang, the narrowest
    /// strip that counts (twice the contour deviation: the most two layers' chords
    /// can part where the surface leans at the allowed angle; anything wider is the
    /// surface leaning past it, so the reach stays the angle the job names), the
    /// offsets' chord (the contour deviation).
    pub fn overhang_options(&self) -> crate::slice::overhang::OverhangOptions {
        crate::slice::overhang::OverhangOptions {
            overhang: self.overhang,
            min_width_mm: 2.0 * self.plan.contour_deviation_mm,
            min_area_mm2: self.plan.nozzle_mm * self.plan.nozzle_mm,
            chord_mm: self.plan.contour_deviation_mm,
        }
    }

    /// The gradient design at height `z_mm`: M(Ci) and M(Ce) interpolated between the
    /// Z stations by the job's own f(d) (clamped beyond the first and last station).
    pub fn design_at(&self, z_mm: f64) -> GradientDesign {
        let mut d = self.design.clone();
        let st = &self.z_stations;
        if st.is_empty() {
            return d;
        }
        let k = st.partition_point(|s| s.z_mm <= z_mm);
        let (inner, outer) = if k == 0 {
            (st[0].inner.clone(), st[0].outer.clone())
        } else if k == st.len() {
            (st[k - 1].inner.clone(), st[k - 1].outer.clone())
        } else {
            let (a, b) = (&st[k - 1], &st[k]);
            let t = (z_mm - a.z_mm) / (b.z_mm - a.z_mm);
            (
                crate::material::contour_composition(&d.function, t, &a.inner, &b.inner),
                crate::material::contour_composition(&d.function, t, &a.outer, &b.outer),
            )
        };
        d.inner = inner;
        d.outer = outer;
        d
    }

    /// The thickest layer starting at `z_bottom_mm` across which no volume fraction of
    /// M(Ci) or M(Ce) changes by more than `z_step` (infinite without Z stations).
    pub fn z_step_limit_mm(&self, z_bottom_mm: f64) -> f64 {
        if self.z_stations.is_empty() {
            return f64::INFINITY;
        }
        let at = self.design_at(z_bottom_mm);
        let change = |t: f64| {
            let d = self.design_at(z_bottom_mm + t);
            d.inner
                .max_abs_diff(&at.inner)
                .max(d.outer.max_abs_diff(&at.outer))
        };
        let hi = self.layers.max_mm;
        if change(hi) <= self.z_step {
            return hi;
        }
        let (mut lo, mut hi) = (0.0, hi);
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if change(mid) <= self.z_step {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    }

    /// An extruded part's bounding box (min, max), mm, in the job's coordinates: its
    /// islands' outline from z = 0 to the height. `None` for a mesh job (see
    /// [`MeshLayers::bounds`]).
    pub fn extruded_bounds(&self) -> Option<(DVec3, DVec3)> {
        let Geometry::Extruded { islands, height_mm } = &self.geometry else {
            return None;
        };
        let (lo, hi) = crate::geom::bounds_of(islands);
        Some((lo.extend(0.0), hi.extend(*height_mm)))
    }

    /// The layer stack of an extruded polygon: equal layers no thicker than the maximum
    /// layer height, thinner where a Z gradient needs it. `z_mm` is each layer's top.
    /// `None` for a mesh job (see [`crate::slice`]).
    pub fn extruded_layers(&self) -> Option<Vec<crate::slice::Layer>> {
        let Geometry::Extruded { islands, height_mm } = &self.geometry else {
            return None;
        };
        let layer = |z_mm: f64, thickness_mm: f64| crate::slice::Layer {
            z_mm,
            thickness_mm,
            islands: islands.clone(),
        };
        if self.z_stations.is_empty() {
            let count = ((height_mm / self.layers.max_mm) - 1e-9).ceil().max(1.0) as usize;
            let t = height_mm / count as f64;
            return Some((0..count).map(|k| layer(t * (k + 1) as f64, t)).collect());
        }
        let mut out = Vec::new();
        let mut z = 0.0;
        while z < height_mm - 1e-9 && out.len() < 10_000_000 {
            let want = self
                .z_step_limit_mm(z)
                .clamp(self.layers.min_mm, self.layers.max_mm);
            let left = height_mm - z;
            // Never leave a sliver thinner than the minimum layer for the top.
            let t = if left <= want + 1e-9 {
                left
            } else if left < want + self.layers.min_mm {
                left / 2.0
            } else {
                want
            };
            z += t;
            out.push(layer(z, t));
        }
        Some(out)
    }

    /// Attach indices and per-layer gradient designs (sampled at mid-height) to a stack
    /// of layers that starts at index `first_index`.
    pub fn layer_slices(
        &self,
        first_index: usize,
        layers: Vec<crate::slice::Layer>,
    ) -> Vec<LayerSlice> {
        layers
            .into_iter()
            .enumerate()
            .map(|(k, layer)| LayerSlice {
                index: first_index + k,
                design: self.design_at(layer.mid_z_mm()),
                layer,
            })
            .collect()
    }
}

/// Why a mesh job's part could not be made into layers.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshJobError {
    /// The job builds an extruded polygon, not a mesh.
    #[error("geometry: the job builds a polygon, not a mesh")]
    NotAMesh,
    /// The mesh bytes do not decode or cannot be repaired.
    #[error("geometry.mesh: {0}")]
    Mesh(#[from] crate::mesh::MeshError),
    /// The mesh is taller than [`MAX_LAYERS`] of the thinnest layer allowed.
    #[error("geometry.mesh: the part is {height_mm} mm tall, {layers} layers of at least {layer_mm} mm (process.layer), more than a job may have ({MAX_LAYERS}); is the mesh in mm?")]
    TooManyLayers {
        height_mm: f64,
        layer_mm: f64,
        layers: f64,
    },
    /// The mesh's footprint would take more than [`MAX_ROAD_PER_LAYER_MM`] of road.
    #[error("geometry.mesh: the part is {x_mm} x {y_mm} mm across, up to {} mm of road a layer at the {nozzle_mm} mm nozzle, more than a job may have ({MAX_ROAD_PER_LAYER_MM} mm); is the mesh in mm?", (x_mm * y_mm / nozzle_mm).round())]
    TooWide {
        x_mm: f64,
        y_mm: f64,
        nozzle_mm: f64,
    },
    /// The mesh cannot be sliced soundly (names the layer and the place).
    #[error("slicing the mesh: {0}")]
    Slice(#[from] crate::slice::SliceError),
}

/// A mesh job's part: loaded, repaired, indexed and stacked into layers (adaptive
/// heights, thinner where a Z gradient needs it). Layers are cut a range at a time with
/// [`MeshLayers::cut`]: `edoctl plan` cuts them all at once, the daemon as it streams, so
/// its memory does not grow with the part. Pure: the mesh comes as bytes.
pub struct MeshLayers {
    slicer: crate::slice::Slicer<'static>,
    spans: Vec<crate::slice::LayerSpan>,
    tolerances: crate::slice::SliceTolerances,
    /// What was found in the mesh and what was repaired.
    pub mesh_report: crate::mesh::MeshReport,
    /// Which way up it is built (`geometry.orientation`), and why.
    pub orientation: crate::mesh::orient::OrientationReport,
}

impl MeshLayers {
    /// The part's bounding box (min, max), mm, in the mesh's coordinates.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        self.slicer
            .mesh()
            .bounds()
            .unwrap_or((DVec3::ZERO, DVec3::ZERO))
    }

    /// Layers in the stack.
    pub fn len(&self) -> usize {
        self.spans.len()
    }

    /// Whether the stack is empty (a mesh with no height).
    pub fn is_empty(&self) -> bool {
        self.spans.is_empty()
    }

    /// Bottom and thickness of every layer.
    pub fn spans(&self) -> &[crate::slice::LayerSpan] {
        &self.spans
    }

    /// Cut layers `range` (clamped to the stack) in parallel.
    pub fn cut(
        &self,
        range: std::ops::Range<usize>,
        progress: Option<crate::slice::Progress>,
    ) -> Result<(Vec<crate::slice::Layer>, crate::slice::SliceReport), crate::slice::SliceError>
    {
        let end = range.end.min(self.spans.len());
        let start = range.start.min(end);
        self.slicer
            .slice(&self.spans[start..end], &self.tolerances, progress)
    }

    /// Each layer's area resting on nothing beyond the allowed overhang (layer index
    /// and mm², over [`crate::slice::overhang::MIN_REPORTED_MM2`] only), cut
    /// [`OVERHANG_CHUNK_LAYERS`] at a time so memory does not grow with the part.
    pub fn overhangs(
        &self,
        opts: &crate::slice::overhang::OverhangOptions,
    ) -> Result<Vec<(usize, f64)>, crate::slice::SliceError> {
        use crate::slice::overhang::{area_mm2, of_layers, MIN_REPORTED_MM2};
        let mut found = Vec::new();
        let mut start = 0;
        while start < self.spans.len() {
            // One layer of overlap: the first of a chunk rests on the last of the one
            // before.
            let from = start.saturating_sub(1);
            let end = (start + OVERHANG_CHUNK_LAYERS).min(self.spans.len());
            let (layers, _) = self.cut(from..end, None)?;
            let indexed: Vec<(usize, &crate::slice::Layer)> = layers
                .iter()
                .enumerate()
                .map(|(k, l)| (from + k, l))
                .collect();
            for ((index, _), hanging) in indexed.iter().zip(of_layers(&indexed, opts)) {
                let a = hanging.as_ref().map_or(0.0, area_mm2);
                if *index >= start && a > MIN_REPORTED_MM2 {
                    found.push((*index, a));
                }
            }
            start = end;
        }
        Ok(found)
    }
}

/// Layers cut at a time when a mesh job's overhangs are found at submission.
pub const OVERHANG_CHUNK_LAYERS: usize = 64;

impl Job {
    /// Load, repair, index and stack a mesh job's part from the mesh file's bytes
    /// (`[process] layer`, `cusp`, `max_gap` and the Z gradient step apply).
    pub fn mesh_layers(
        &self,
        bytes: &[u8],
        limits: &crate::mesh::MeshLimits,
    ) -> Result<MeshLayers, MeshJobError> {
        if !matches!(self.geometry, Geometry::Mesh { .. }) {
            return Err(MeshJobError::NotAMesh);
        }
        let (mut mesh, mesh_report) =
            crate::mesh::load_and_repair(bytes, limits, &crate::mesh::RepairOptions::default())?;
        let (turn, orientation) = crate::mesh::orient::choose(
            &mesh,
            self.orientation,
            !self.z_stations.is_empty(),
            &self.orient_options(),
        );
        crate::mesh::orient::turn(&mut mesh, turn);
        if let Some((lo, hi)) = mesh.bounds() {
            // No layer is thinner than the minimum (uniform layers are the maximum).
            let layers = ((hi.z - lo.z) / self.layers.min_mm).ceil();
            if layers > MAX_LAYERS as f64 {
                return Err(MeshJobError::TooManyLayers {
                    height_mm: hi.z - lo.z,
                    layer_mm: self.layers.min_mm,
                    layers,
                });
            }
            // No section is larger than the footprint.
            let footprint_mm2 = (hi.x - lo.x) * (hi.y - lo.y);
            if footprint_mm2 / self.plan.nozzle_mm > MAX_ROAD_PER_LAYER_MM {
                return Err(MeshJobError::TooWide {
                    x_mm: hi.x - lo.x,
                    y_mm: hi.y - lo.y,
                    nozzle_mm: self.plan.nozzle_mm,
                });
            }
        }
        let limit = |z: f64| self.z_step_limit_mm(z);
        let tolerances = crate::slice::SliceTolerances {
            max_gap_mm: self.layers.max_gap_mm,
            ..crate::slice::SliceTolerances::default()
        };
        let opts = crate::slice::SliceOptions {
            layer_min_mm: self.layers.min_mm,
            layer_max_mm: self.layers.max_mm,
            cusp_mm: self.layers.cusp_mm,
            max_thickness_at: if self.z_stations.is_empty() {
                None
            } else {
                Some(&limit)
            },
            tolerances,
            ..crate::slice::SliceOptions::default()
        };
        let slicer = crate::slice::Slicer::new_owned(mesh)?;
        let spans = slicer.layer_spans(&opts)?;
        Ok(MeshLayers {
            slicer,
            spans,
            tolerances,
            mesh_report,
            orientation,
        })
    }
}

/// Longest job name, characters.
pub const MAX_NAME_CHARS: usize = 200;

/// A job's name, as listings and the journal show it: not blank, at most
/// [`MAX_NAME_CHARS`], and no control characters (a newline or an escape sequence in
/// a name would rewrite the operator's terminal in `edoctl jobs`).
pub fn check_name(name: &str) -> Result<(), String> {
    if name.trim().is_empty() {
        return Err("must not be empty".into());
    }
    let n = name.chars().count();
    if n > MAX_NAME_CHARS {
        return Err(format!("{n} characters; at most {MAX_NAME_CHARS}"));
    }
    if let Some(c) = name.chars().find(|c| c.is_control()) {
        return Err(format!("contains the control character {c:?}"));
    }
    if let Some(c) = name.chars().find(|c| is_bidi_control(*c)) {
        return Err(format!(
            "contains the bidirectional control {c:?} (it would reorder what listings show)"
        ));
    }
    Ok(())
}

/// Unicode's bidirectional formatting characters (marks, embeddings, overrides,
/// isolates): invisible, they reorder the text around them in a terminal or a page.
fn is_bidi_control(c: char) -> bool {
    matches!(c, '\u{200E}' | '\u{200F}' | '\u{061C}' | '\u{202A}'..='\u{202E}' | '\u{2066}'..='\u{2069}')
}

/// The finest nozzle a job may name, mm. Eq (5) puts D_max / D_noz offsets in each
/// sub-region, so a nozzle typed in metres (0.0004 for 0.4 mm) asked for hundreds of
/// thousands of offsets a layer and gigabytes of roads.
pub const MIN_NOZZLE_MM: f64 = 0.01;

/// Most road a job's layer may have, mm (10 km, the section over the nozzle: a 200 x
/// 200 mm bed full at a 0.01 mm nozzle is 4 km). More is coordinates in the wrong unit,
/// which would plan for hours.
pub const MAX_ROAD_PER_LAYER_MM: f64 = 1e7;

/// Most layers a job may have: 20 m of 0.2 mm layers, 5 m of 0.05 mm ones. A taller
/// stack is a wrong unit or a typo (a mesh in micrometres, `height = 4000` for 0.4),
/// which would otherwise plan for hours and fill the host's memory.
pub const MAX_LAYERS: usize = 100_000;

/// Default largest fraction change across one layer of a Z-varying gradient.
pub const DEFAULT_Z_STEP: f64 = 0.02;

/// How far f(0) and f(1) of a job's gradient function may be from 0 and 1 (eq 3).
pub const GRADIENT_FUNCTION_TOLERANCE: f64 = 1e-9;

/// `geometry.orientation`: keep (default), auto, or a turn of finite degrees; a
/// polygon job is built as drawn.
fn orientation(
    g: &RawGeometry,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<crate::mesh::orient::Orientation, JobError> {
    use crate::mesh::orient::Orientation;
    let key = "geometry.orientation";
    let o = match &g.orientation {
        None => Orientation::Keep,
        Some(OrientationSpec::Named(n)) if n == "keep" => Orientation::Keep,
        Some(OrientationSpec::Named(n)) if n == "auto" => Orientation::Auto,
        Some(OrientationSpec::Named(n)) => {
            return Err(bad(
                key,
                format!("\"{n}\": \"keep\", \"auto\" or {{ rotate = [x, y, z] }} (degrees)"),
            ))
        }
        Some(OrientationSpec::Rotate { rotate }) => {
            if let Some(a) = rotate.iter().find(|a| !a.is_finite() || a.abs() > 360.0) {
                return Err(bad(key, format!("rotate: {a}: from -360 to 360 degrees")));
            }
            Orientation::Rotate(*rotate)
        }
    };
    if o != Orientation::Keep && g.mesh.is_none() {
        return Err(bad(
            key,
            "a polygon job is built as drawn; orientation turns a mesh part".into(),
        ));
    }
    Ok(o)
}

/// `materials.names` (or the `key` of another list of names): one material per
/// syringe, 1 to 8 of them, none blank, listed twice, or holding control characters.
fn materials(
    names: Vec<String>,
    key: &str,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<Vec<String>, JobError> {
    if names.is_empty() {
        return Err(bad(
            key,
            "list at least one material (one per syringe)".into(),
        ));
    }
    if names.len() > 8 {
        return Err(bad(
            key,
            format!(
                "{} names listed; the machine has at most 8 syringes",
                names.len()
            ),
        ));
    }
    for (i, n) in names.iter().enumerate() {
        if n.trim().is_empty() {
            return Err(bad(key, format!("name {i} is empty")));
        }
        check_name(n).map_err(|m| bad(key, format!("name {i} {m}")))?;
        if names[..i].contains(n) {
            return Err(bad(key, format!("\"{n}\" is listed twice")));
        }
    }
    Ok(names)
}

/// `materials.syringes`: the machine's syringe of each material, one per material,
/// each named once.
fn material_syringes(
    syringes: Vec<String>,
    materials: usize,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<Vec<String>, JobError> {
    let syringes = self::materials(syringes, "materials.syringes", bad)?;
    if syringes.len() != materials {
        return Err(bad(
            "materials.syringes",
            format!(
                "{} syringes for {materials} materials: name the syringe of each material, \
                 in the order of materials.names",
                syringes.len()
            ),
        ));
    }
    Ok(syringes)
}

/// `[process]` without the layer keys: the planner's options (r_mach, nozzle,
/// boundary offset, offset-end clearance, shortest road, radial lines, thin regions,
/// field cell, contour deviation) on `tolerances`.
fn plan_options(
    p: &RawProcess,
    tolerances: Tolerances,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<PlanOptions, JobError> {
    positive(p.r_mach, "process.r_mach", bad)?;
    positive(p.nozzle, "process.nozzle", bad)?;
    if p.nozzle < MIN_NOZZLE_MM {
        return Err(bad(
            "process.nozzle",
            format!(
                "{} mm is finer than any extrusion nozzle (at least {MIN_NOZZLE_MM} mm; the finest dispensing needles are about 0.05 mm); is it in mm?",
                p.nozzle
            ),
        ));
    }
    if p.nozzle > p.r_mach {
        return Err(bad(
            "process.nozzle",
            format!(
                "the nozzle ({} mm) is wider than the machine resolution r_mach ({} mm): contours about r_mach apart would get overlapping roads; use r_mach >= nozzle",
                p.nozzle, p.r_mach
            ),
        ));
    }
    let mut plan = PlanOptions::new(p.r_mach, p.nozzle);
    plan.tolerances = tolerances;
    if let Some(b) = p.boundary_offset {
        if !b.is_finite() || b < 0.0 {
            return Err(bad(
                "process.boundary_offset",
                format!("must be a distance of 0 or more in mm, got {b}"),
            ));
        }
        plan.boundary_offset_mm = b;
    }
    if let Some(c) = p.offset_end_clearance {
        up_to_nozzle(c, p.nozzle, "process.offset_end_clearance", bad)?;
        plan.offset_end_clearance_mm = c;
    }
    if let Some(l) = p.min_road {
        up_to_nozzle(l, p.nozzle, "process.min_road", bad)?;
        plan.min_road_mm = l;
    }
    if let Some(n) = p.radial_lines {
        if !(8..=100_000).contains(&n) {
            return Err(bad(
                "process.radial_lines",
                format!("must be between 8 and 100000, got {n}"),
            ));
        }
        plan.radial_lines = n;
    }
    if let Some(t) = p.thin_regions {
        plan.thin_regions = t;
    }
    if let Some(c) = p.field_cell {
        positive(c, "process.field_cell", bad)?;
        plan.field_cell_mm = Some(c);
    }
    if let Some(c) = p.contour_deviation {
        let (lo, hi) = plan.contour_deviation_limits_mm();
        if !(c.is_finite() && c >= lo && c <= hi) {
            return Err(bad(
                "process.contour_deviation",
                format!("must be a length from the planner's chord tolerance ({lo} mm) to a quarter of the nozzle ({hi} mm), got {c}"),
            ));
        }
        plan.contour_deviation_mm = c;
    }
    Ok(plan)
}

/// The thinnest layer: 1 µm, the step of the Z positions edod plans (µm) and writes.
pub const MIN_LAYER_MM: f64 = 0.001;

/// `process.layer`, `process.cusp` and `process.max_gap`: the layer heights (half
/// the nozzle, uniform, when `layer` is absent), from 1 µm to the nozzle.
fn layer_heights(
    p: &RawProcess,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<LayerHeights, JobError> {
    let (min_mm, max_mm) = match p.layer {
        None => (p.nozzle / 2.0, p.nozzle / 2.0),
        Some(LayerSpec::Uniform(h)) => {
            positive(h, "process.layer", bad)?;
            (h, h)
        }
        Some(LayerSpec::Range { min, max }) => {
            positive(min, "process.layer.min", bad)?;
            positive(max, "process.layer.max", bad)?;
            if min > max {
                return Err(bad(
                    "process.layer",
                    format!("min ({min}) is above max ({max})"),
                ));
            }
            (min, max)
        }
    };
    if max_mm > p.nozzle {
        return Err(bad(
            "process.layer",
            format!(
                "a layer of {max_mm} mm is thicker than the nozzle ({} mm): its roads would \
                 not bond to the layer below; at most the nozzle (slicers keep to 75 % of it)",
                p.nozzle
            ),
        ));
    }
    if min_mm < MIN_LAYER_MM {
        return Err(bad(
            "process.layer",
            format!(
                "a layer of {min_mm} mm is thinner than {MIN_LAYER_MM} mm, the step of the \
                 Z positions edod plans and writes"
            ),
        ));
    }
    let cusp_mm = p.cusp.unwrap_or(max_mm / 2.0);
    positive(cusp_mm, "process.cusp", bad)?;
    let max_gap_mm = p
        .max_gap
        .unwrap_or(crate::slice::SliceTolerances::default().max_gap_mm);
    if !max_gap_mm.is_finite() || max_gap_mm < 0.0 {
        return Err(bad(
            "process.max_gap",
            format!("must be a distance of 0 or more in mm, got {max_gap_mm}"),
        ));
    }
    Ok(LayerHeights {
        min_mm,
        max_mm,
        cusp_mm,
        max_gap_mm,
    })
}

/// `[gradient]` without its Z stations: M(Ci), M(Ce) (eq 2), f(d) (eq 3) and the
/// pattern.
fn gradient_design(
    g: &RawGradient,
    n_materials: usize,
    tolerances: &Tolerances,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<GradientDesign, JobError> {
    let inner = Composition::with_len(g.inner.clone(), n_materials, tolerances.composition_sum)
        .map_err(|e| bad("gradient.inner", format!("M(Ci): {e}")))?;
    let outer = Composition::with_len(g.outer.clone(), n_materials, tolerances.composition_sum)
        .map_err(|e| bad("gradient.outer", format!("M(Ce): {e}")))?;
    let function = gradient_function(g.function.as_ref(), bad)?;
    let pattern = gradient_pattern(g, bad)?;
    Ok(GradientDesign {
        pattern,
        inner,
        outer,
        function,
    })
}

/// `gradient.function`: f(d) of eq (3), linear when absent.
fn gradient_function(
    spec: Option<&FunctionSpec>,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<GradientFunction, JobError> {
    let function = match spec {
        None => GradientFunction::LINEAR,
        Some(FunctionSpec::Named(s)) => match s.as_str() {
            "linear" => GradientFunction::LINEAR,
            "smoothstep" => GradientFunction::Smoothstep,
            other => {
                return Err(bad(
                    "gradient.function",
                    format!("unknown function \"{other}\"; use \"linear\", \"smoothstep\", {{ power = P }}, {{ table = [[d, f], ...] }} or {{ linear = {{ a = A, b = B }} }}"),
                ))
            }
        },
        Some(FunctionSpec::Power { power }) => GradientFunction::Power(*power),
        Some(FunctionSpec::Table { table }) => GradientFunction::Table(table.clone()),
        Some(FunctionSpec::Linear { linear }) => GradientFunction::Linear {
            a: linear.a,
            b: linear.b,
        },
    };
    function
        .validate(GRADIENT_FUNCTION_TOLERANCE)
        .map_err(|e| bad("gradient.function", e.to_string()))?;
    Ok(function)
}

/// `gradient.pattern` with its own keys (`depth` for a crown, `angle` for fibers),
/// refusing a key of another pattern.
fn gradient_pattern(
    g: &RawGradient,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<Pattern, JobError> {
    let only_for = |key: &str, value: &Option<f64>, pattern: &str| -> Result<(), JobError> {
        if value.is_some() && g.pattern != pattern {
            return Err(bad(
                &format!("gradient.{key}"),
                format!(
                    "applies to pattern = \"{pattern}\" only, this job's pattern is \"{}\"",
                    g.pattern
                ),
            ));
        }
        Ok(())
    };
    only_for("depth", &g.depth, "crown")?;
    only_for("angle", &g.angle, "fibers")?;
    match g.pattern.as_str() {
        "growth-rings" => Ok(Pattern::GrowthRings),
        "crown" => {
            let depth = g.depth.ok_or_else(|| {
                bad(
                    "gradient.depth",
                    "pattern = \"crown\" needs depth, the graded shell thickness under the outer surface in mm".into(),
                )
            })?;
            positive(depth, "gradient.depth", bad)?;
            Ok(Pattern::Crown { depth_mm: depth })
        }
        "fibers" => {
            let angle = g.angle.unwrap_or(0.0);
            if !angle.is_finite() {
                return Err(bad(
                    "gradient.angle",
                    format!("must be a finite angle in degrees, got {angle}"),
                ));
            }
            Ok(Pattern::Fibers { angle_deg: angle })
        }
        other => Err(bad(
            "gradient.pattern",
            format!("unknown pattern \"{other}\"; use \"growth-rings\", \"crown\" or \"fibers\""),
        )),
    }
}

/// `gradient.subdivision` and `gradient.direction`, which are planner options.
fn gradient_plan_options(
    g: &RawGradient,
    pattern: &Pattern,
    plan: &mut PlanOptions,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<(), JobError> {
    if let Some(s) = g.subdivision {
        if !matches!(pattern, Pattern::GrowthRings) && s != Subdivision::Auto {
            return Err(bad(
                "gradient.subdivision",
                "applies to pattern = \"growth-rings\" only (crown contours are offsets, fiber contours lines)".into(),
            ));
        }
        plan.subdivision = s;
    }
    if let Some(d) = g.direction {
        plan.direction = d;
    }
    Ok(())
}

/// `geometry.placement`: where the part goes on the bed (centred by default).
fn placement(
    spec: &Option<PlacementSpec>,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<PlacementMode, JobError> {
    match spec {
        None => Ok(PlacementMode::Centre),
        Some(PlacementSpec::Named(n)) => match n.as_str() {
            "centre" | "center" => Ok(PlacementMode::Centre),
            "keep" => Ok(PlacementMode::Keep),
            other => Err(bad(
                "geometry.placement",
                format!("unknown placement {other:?}; use \"centre\" (the default), \"keep\" or {{ at = [x, y] }}"),
            )),
        },
        Some(PlacementSpec::At { at }) => {
            if !at.iter().all(|v| v.is_finite() && *v >= 0.0) {
                return Err(bad(
                    "geometry.placement.at",
                    format!("{at:?} is not a point of the bed (x, y in mm, not negative)"),
                ));
            }
            Ok(PlacementMode::At(*at))
        }
    }
}

/// `[geometry]` without the placement: a mesh's path, or extruded islands.
fn geometry(
    geo: RawGeometry,
    tolerances: &Tolerances,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<Geometry, JobError> {
    match (geo.mesh, geo.polygon.is_some() || geo.regions.is_some()) {
        (Some(_), true) => Err(bad(
            "geometry",
            "give either mesh = \"part.stl\" or polygon/regions, not both".into(),
        )),
        (Some(path), false) => {
            if geo.height.is_some() {
                return Err(bad(
                    "geometry.height",
                    "applies to an extruded polygon; a mesh has its own height".into(),
                ));
            }
            if path.trim().is_empty() {
                return Err(bad(
                    "geometry.mesh",
                    "is empty; give the path of an STL or 3MF file".into(),
                ));
            }
            Ok(Geometry::Mesh { path })
        }
        (None, _) => {
            let height = geo.height.ok_or_else(|| {
                bad(
                    "geometry.height",
                    "missing: the extrusion height of the polygon, mm".into(),
                )
            })?;
            positive(height, "geometry.height", bad)?;
            let islands = extruded_islands(geo.polygon, geo.regions, tolerances, bad)?;
            Ok(Geometry::Extruded {
                islands,
                height_mm: height,
            })
        }
    }
}

/// `geometry.polygon` (one island) or `geometry.regions` (several): each island's
/// loops, normalised and validated, and no two islands overlapping.
fn extruded_islands(
    polygon: Option<RawRegion>,
    regions: Option<Vec<RawRegion>>,
    tolerances: &Tolerances,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<Vec<Region>, JobError> {
    let specs: Vec<(String, RawRegion)> = match (polygon, regions) {
        (Some(_), Some(_)) => {
            return Err(bad(
                "geometry",
                "give either polygon (one island) or regions (several), not both".into(),
            ))
        }
        (None, None) => {
            return Err(bad(
                "geometry",
                "missing mesh = \"part.stl\", polygon = { outer = [...], holes = [...] } or regions = [...]".into(),
            ))
        }
        (Some(r), None) => vec![("geometry.polygon".to_string(), r)],
        (None, Some(rs)) => {
            if rs.is_empty() {
                return Err(bad("geometry.regions", "is empty".into()));
            }
            rs.into_iter()
                .enumerate()
                .map(|(i, r)| (format!("geometry.regions[{i}]"), r))
                .collect()
        }
    };
    let mut islands = Vec::with_capacity(specs.len());
    for (key, r) in specs {
        let outer = loop_points(&r.outer, &format!("{key}.outer"), tolerances.chord_mm, bad)?;
        let holes = r
            .holes
            .iter()
            .enumerate()
            .map(|(i, h)| loop_points(h, &format!("{key}.holes[{i}]"), tolerances.chord_mm, bad))
            .collect::<Result<Vec<_>, _>>()?;
        let region = Region::new(outer, holes).normalised(tolerances);
        region
            .validate(tolerances)
            .map_err(|e| bad(&key, e.to_string()))?;
        islands.push(region);
    }
    for i in 0..islands.len() {
        for j in 0..i {
            if islands_overlap(&islands[i], &islands[j]) {
                return Err(bad(
                    "geometry.regions",
                    format!("regions {j} and {i} overlap; islands must be disjoint (put a region inside another's hole, not over it)"),
                ));
            }
        }
    }
    Ok(islands)
}

/// `[[gradient.z]]`: the stations of a Z-varying gradient, ascending in z.
fn z_stations(
    stations: Vec<RawZStation>,
    n_materials: usize,
    tolerances: &Tolerances,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<Vec<ZStation>, JobError> {
    let mut z_stations = Vec::with_capacity(stations.len());
    for (k, st) in stations.into_iter().enumerate() {
        let key = format!("gradient.z[{k}]");
        if !st.z.is_finite() {
            return Err(bad(
                &format!("{key}.z"),
                format!("must be a finite height in mm, got {}", st.z),
            ));
        }
        if let Some(prev) = z_stations.last().map(|p: &ZStation| p.z_mm) {
            if st.z <= prev {
                return Err(bad(
                    &format!("{key}.z"),
                    format!("stations must ascend in z; {} follows {prev}", st.z),
                ));
            }
        }
        let inner = Composition::with_len(st.inner, n_materials, tolerances.composition_sum)
            .map_err(|e| bad(&format!("{key}.inner"), format!("M(Ci): {e}")))?;
        let outer = Composition::with_len(st.outer, n_materials, tolerances.composition_sum)
            .map_err(|e| bad(&format!("{key}.outer"), format!("M(Ce): {e}")))?;
        z_stations.push(ZStation {
            z_mm: st.z,
            inner,
            outer,
        });
    }
    Ok(z_stations)
}

/// `gradient.z_step`: a fraction in (0, 1], only with Z stations.
fn z_step(
    z_step: Option<f64>,
    z_gradient: bool,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<f64, JobError> {
    let step = z_step.unwrap_or(DEFAULT_Z_STEP);
    if !step.is_finite() || step <= 0.0 || step > 1.0 {
        return Err(bad(
            "gradient.z_step",
            format!("must be a fraction in (0, 1], got {step}"),
        ));
    }
    if z_step.is_some() && !z_gradient {
        return Err(bad(
            "gradient.z_step",
            "applies only with a Z-varying gradient ([[gradient.z]] stations)".into(),
        ));
    }
    Ok(step)
}

/// An extruded part no bigger than a job may be: [`MAX_ROAD_PER_LAYER_MM`] of road a
/// layer and [`MAX_LAYERS`] layers (a mesh's size is checked when it is loaded).
fn check_extruded_size(
    geometry: &Geometry,
    layers: &LayerHeights,
    z_gradient: bool,
    nozzle_mm: f64,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<(), JobError> {
    let Geometry::Extruded { islands, height_mm } = geometry else {
        return Ok(());
    };
    let area_mm2: f64 = islands.iter().map(|r| r.area()).sum();
    let road_mm = area_mm2 / nozzle_mm;
    if road_mm > MAX_ROAD_PER_LAYER_MM {
        return Err(bad(
            "geometry",
            format!(
                "the part's section is {area_mm2:.0} mm², about {road_mm:.0} mm of road a layer at the {nozzle_mm} mm nozzle, more than a job may have ({MAX_ROAD_PER_LAYER_MM} mm: days of printing a layer); are the coordinates in mm?"
            ),
        ));
    }
    // Uniform layers of the maximum, or (a Z gradient) no thinner than the minimum.
    let (thinnest, key) = if z_gradient {
        (layers.min_mm, "process.layer.min")
    } else {
        (layers.max_mm, "process.layer")
    };
    // At least one layer: a height under the thinnest layer (1e-300 mm) would be one
    // layer at z = 0, the nozzle on the bed.
    if *height_mm < layers.min_mm {
        return Err(bad(
            "geometry.height",
            format!(
                "{height_mm} mm is less than one layer ({} mm, process.layer); is the height in mm?",
                layers.min_mm
            ),
        ));
    }
    let count = (height_mm / thinnest).ceil();
    if count > MAX_LAYERS as f64 {
        return Err(bad(
            "geometry.height",
            format!(
                "{height_mm} mm is {count} layers of {thinnest} mm ({key}), more than a job may have ({MAX_LAYERS}); is the height in mm?"
            ),
        ));
    }
    Ok(())
}

/// `[toolpath]`, defaults where absent, its nozzle the process's.
fn toolpath_settings(
    raw: Option<crate::pipeline::ProcessSettings>,
    nozzle_mm: f64,
    bad: &impl Fn(&str, String) -> JobError,
) -> Result<crate::pipeline::ProcessSettings, JobError> {
    let default_nozzle = crate::pipeline::ProcessSettings::default().nozzle_mm;
    let mut toolpath = raw.unwrap_or_default();
    if toolpath.nozzle_mm != default_nozzle && toolpath.nozzle_mm != nozzle_mm {
        return Err(bad(
            "toolpath.nozzle_mm",
            format!(
                "is {} mm but process.nozzle is {nozzle_mm} mm: set the nozzle once, in [process]",
                toolpath.nozzle_mm
            ),
        ));
    }
    toolpath.nozzle_mm = nozzle_mm;
    if let Err(e) = toolpath.validate() {
        return Err(match e {
            crate::pipeline::PipelineError::Setting { field, message } => {
                bad(&format!("toolpath.{field}"), message)
            }
            other => bad("toolpath", other.to_string()),
        });
    }
    Ok(toolpath)
}

fn positive<E>(v: f64, key: &str, bad: &impl Fn(&str, String) -> E) -> Result<(), E> {
    if !v.is_finite() || v <= 0.0 {
        return Err(bad(
            key,
            format!("must be a positive number of mm, got {v}"),
        ));
    }
    Ok(())
}

/// `process.move_deviation` and `process.move_width_tolerance` into `toolpath`.
fn move_merging<E>(
    p: &RawProcess,
    nozzle_mm: f64,
    toolpath: &mut crate::pipeline::ProcessSettings,
    bad: &impl Fn(&str, String) -> E,
) -> Result<(), E> {
    if let Some(d) = p.move_deviation {
        // Up to a quarter of the nozzle, as the contour deviation.
        up_to_nozzle(d, nozzle_mm / 4.0, "process.move_deviation", bad)?;
        toolpath.move_deviation_mm = d;
    }
    if let Some(t) = p.move_width_tolerance {
        use crate::pipeline::MAX_MOVE_WIDTH_TOLERANCE as MAX;
        if !(0.0..=MAX).contains(&t) {
            return Err(bad(
                "process.move_width_tolerance",
                format!("must be a fraction from 0 to {MAX}, got {t}"),
            ));
        }
        toolpath.move_width_tolerance = t;
    }
    Ok(())
}

/// A length from 0 to the nozzle diameter, mm.
fn up_to_nozzle<E>(
    v: f64,
    nozzle_mm: f64,
    key: &str,
    bad: &impl Fn(&str, String) -> E,
) -> Result<(), E> {
    if !v.is_finite() || v < 0.0 || v > nozzle_mm {
        return Err(bad(
            key,
            format!("must be a length from 0 to the nozzle ({nozzle_mm} mm), got {v}"),
        ));
    }
    Ok(())
}

fn loop_points<E>(
    spec: &LoopSpec,
    key: &str,
    chord_mm: f64,
    bad: &impl Fn(&str, String) -> E,
) -> Result<Vec<DVec2>, E> {
    let finite = |v: &[f64], what: &str| -> Result<(), E> {
        if v.iter().all(|x| x.is_finite()) {
            Ok(())
        } else {
            Err(bad(key, format!("{what} is not finite")))
        }
    };
    match spec {
        LoopSpec::Points(pts) => {
            if let Some(i) = pts
                .iter()
                .position(|p| !p[0].is_finite() || !p[1].is_finite())
            {
                return Err(bad(key, format!("point {i} is not a finite number")));
            }
            Ok(pts.iter().map(|p| DVec2::new(p[0], p[1])).collect())
        }
        LoopSpec::Circle { circle } => {
            finite(
                &[circle.center[0], circle.center[1], circle.radius],
                "circle",
            )?;
            positive(circle.radius, &format!("{key}.circle.radius"), bad)?;
            Ok(shapes::circle(
                DVec2::from(circle.center),
                circle.radius,
                chord_mm,
            ))
        }
        LoopSpec::Ellipse { ellipse } => {
            finite(
                &[
                    ellipse.center[0],
                    ellipse.center[1],
                    ellipse.radii[0],
                    ellipse.radii[1],
                    ellipse.rotation,
                ],
                "ellipse",
            )?;
            positive(ellipse.radii[0], &format!("{key}.ellipse.radii[0]"), bad)?;
            positive(ellipse.radii[1], &format!("{key}.ellipse.radii[1]"), bad)?;
            let c = DVec2::from(ellipse.center);
            let rot = DVec2::from_angle(ellipse.rotation.to_radians());
            let big = ellipse.radii[0].max(ellipse.radii[1]);
            Ok(shapes::circle(DVec2::ZERO, big, chord_mm)
                .into_iter()
                .map(|p| {
                    c + rot.rotate(DVec2::new(
                        p.x * ellipse.radii[0] / big,
                        p.y * ellipse.radii[1] / big,
                    ))
                })
                .collect())
        }
        LoopSpec::Rect { rect } => {
            finite(
                &[rect.min[0], rect.min[1], rect.max[0], rect.max[1]],
                "rect",
            )?;
            let (lo, hi) = (DVec2::from(rect.min), DVec2::from(rect.max));
            if hi.x <= lo.x || hi.y <= lo.y {
                return Err(bad(
                    key,
                    format!(
                        "rect max {:?} must be above min {:?} in x and y",
                        rect.max, rect.min
                    ),
                ));
            }
            Ok(vec![lo, DVec2::new(hi.x, lo.y), hi, DVec2::new(lo.x, hi.y)])
        }
    }
}

/// Do two islands' materials overlap (an edge crossing, or one inside the other's material)?
fn islands_overlap(a: &Region, b: &Region) -> bool {
    let loops: Vec<&[DVec2]> = a.loops().chain(b.loops()).map(|l| l.as_slice()).collect();
    if crate::geom::first_crossing(&loops).is_some() {
        return true;
    }
    a.contains(b.outer[0]) || b.contains(a.outer[0])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placement_is_centre_by_default_keep_or_a_bed_point() {
        let base = GOOD;
        let with = |line: &str| base.replace("[geometry]", &format!("[geometry]\n{line}"));
        let job = Job::from_toml(base, "j").unwrap();
        assert_eq!(job.placement, PlacementMode::Centre);
        let job = Job::from_toml(&with("placement = \"keep\""), "j").unwrap();
        assert_eq!(job.placement, PlacementMode::Keep);
        let job = Job::from_toml(&with("placement = { at = [40.0, 60.0] }"), "j").unwrap();
        assert_eq!(job.placement, PlacementMode::At([40.0, 60.0]));
        let e = Job::from_toml(&with("placement = \"middle\""), "j").unwrap_err();
        assert!(e.to_string().contains("geometry.placement"), "{e}");
        for at in ["[-1.0, 60.0]", "[nan, 60.0]", "[40.0, inf]"] {
            let e =
                Job::from_toml(&with(&format!("placement = {{ at = {at} }}")), "j").unwrap_err();
            assert!(e.to_string().contains("geometry.placement.at"), "{at}: {e}");
        }
        let e = Job::from_toml(&with("placement = 3"), "j").unwrap_err();
        assert!(e.to_string().contains("placement"), "{e}");
        let (lo, hi) = job.extruded_bounds().unwrap();
        assert_eq!((lo.z, hi.z), (0.0, 0.4));
        assert!(
            (lo.x + 30.0).abs() < 0.02 && (hi.y - 30.0).abs() < 0.02,
            "{lo} {hi}"
        );
    }

    const GOOD: &str = r#"
name = "t"
[geometry]
polygon = { outer = { circle = { center = [0.0, 0.0], radius = 30.0 } }, holes = [{ circle = { center = [0.0, 0.0], radius = 10.0 } }] }
height = 0.4
[materials]
names = ["A", "B"]
[gradient]
pattern = "growth-rings"
inner = [1.0, 0.0]
outer = [0.0, 1.0]
function = "linear"
subdivision = "auto"
[process]
r_mach = 2.0
nozzle = 0.5
"#;

    fn err(text: &str) -> String {
        Job::from_toml(text, "job.toml").unwrap_err().to_string()
    }

    #[test]
    fn good_job_parses() {
        let job = Job::from_toml(GOOD, "job.toml").unwrap();
        assert_eq!(job.materials, ["A", "B"]);
        assert_eq!(job.plan.r_mach_mm, 2.0);
        assert_eq!(
            job.plan.contour_deviation_mm,
            crate::plan::DEFAULT_CONTOUR_DEVIATION_MM
        );
        let finer = GOOD.replace("[process]", "[process]\ncontour_deviation = 0.01");
        let job2 = Job::from_toml(&finer, "job.toml").unwrap();
        assert_eq!(job2.plan.contour_deviation_mm, 0.01);
        assert_eq!(
            job.toolpath.move_width_tolerance,
            crate::pipeline::DEFAULT_MOVE_WIDTH_TOLERANCE
        );
        let strict = GOOD.replace("[process]", "[process]\nmove_width_tolerance = 0.0");
        let job3 = Job::from_toml(&strict, "job.toml").unwrap();
        assert_eq!(job3.toolpath.move_width_tolerance, 0.0);
        let layers = job.extruded_layers().unwrap();
        assert_eq!(layers.len(), 2);
        assert!((layers[1].z_mm - 0.4).abs() < 1e-12);
    }

    /// Cut a chunk at a time, a mesh's overhangs are those of the whole stack cut at
    /// once (each chunk's first layer judged on the last of the chunk before).
    #[test]
    fn overhangs_cut_in_chunks_equal_the_whole_stack() {
        let stl = crate::mesh::primitives::sphere(5.0, 48, 24)
            .to_binary_stl()
            .unwrap();
        let text = "name = \"ball\"\n[geometry]\nmesh = \"ball.stl\"\n[materials]\n\
                    names = [\"A\", \"B\"]\n[gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n\
                    [process]\nr_mach = 2.0\nnozzle = 0.4\nlayer = 0.04\n";
        let job = Job::from_toml(text, "ball.toml").unwrap();
        let part = job
            .mesh_layers(&stl, &crate::mesh::MeshLimits::default())
            .unwrap();
        assert!(
            part.len() > 3 * OVERHANG_CHUNK_LAYERS,
            "{} layers",
            part.len()
        );
        let chunked = part.overhangs(&job.overhang_options()).unwrap();
        let (layers, _) = part.cut(0..part.len(), None).unwrap();
        let indexed: Vec<(usize, &crate::slice::Layer)> = layers.iter().enumerate().collect();
        let whole: Vec<(usize, f64)> =
            crate::slice::overhang::of_layers(&indexed, &job.overhang_options())
                .into_iter()
                .enumerate()
                .filter_map(|(k, u)| {
                    let a = crate::slice::overhang::area_mm2(&u?);
                    (a > crate::slice::overhang::MIN_REPORTED_MM2).then_some((k, a))
                })
                .collect();
        assert!(!whole.is_empty());
        assert_eq!(chunked, whole);
    }

    #[test]
    fn material_syringes_are_one_per_material_each_named_once() {
        let with = |syringes: &str| {
            GOOD.replace(
                "names = [\"A\", \"B\"]",
                &format!("names = [\"Ti\", \"HA\"]\nsyringes = {syringes}"),
            )
        };
        let job = Job::from_toml(&with("[\"B\", \"A\"]"), "job.toml").unwrap();
        assert_eq!(job.syringes, Some(vec!["B".into(), "A".into()]));
        let e = err(&with("[\"A\"]"));
        assert!(
            e.contains("materials.syringes") && e.contains("1 syringes for 2"),
            "{e}"
        );
        let e = err(&with("[\"A\", \"A\"]"));
        assert!(
            e.contains("materials.syringes") && e.contains("listed twice"),
            "{e}"
        );
        let e = err(&with("[\"A\", \"B\\u202e\"]"));
        assert!(
            e.contains("materials.syringes") && e.contains("bidirectional"),
            "{e}"
        );
        let e = err(&GOOD.replace("names = [\"A\", \"B\"]", "names = [\"A\", \"\\u001b[2J\"]"));
        assert!(
            e.contains("materials.names") && e.contains("control character"),
            "{e}"
        );
    }

    #[test]
    fn errors_name_the_key() {
        let e = err(&GOOD.replace("inner = [1.0, 0.0]", "inner = [0.5, 0.6]"));
        assert!(e.contains("gradient.inner") && e.contains("sum"), "{e}");
        let e = err(&GOOD.replace("inner = [1.0, 0.0]", "inner = [1.0]"));
        assert!(
            e.contains("gradient.inner") && e.contains("2 materials"),
            "{e}"
        );
        let e = err(&GOOD.replace("nozzle = 0.5", "nozzle = 0.5\nlayer = 0.6"));
        assert!(
            e.contains("process.layer") && e.contains("thicker than the nozzle (0.5 mm)"),
            "{e}"
        );
        let e = err(&GOOD.replace(
            "nozzle = 0.5",
            "nozzle = 0.5\nlayer = { min = 0.0001, max = 0.3 }",
        ));
        assert!(
            e.contains("process.layer") && e.contains("thinner than 0.001 mm"),
            "{e}"
        );
        let e = err(&GOOD.replace("height = 0.4", "height = 1e-300"));
        assert!(
            e.contains("geometry.height") && e.contains("less than one layer"),
            "{e}"
        );
        let e = err(&GOOD.replace("height = 0.4", "height = 400000.0"));
        assert!(
            e.contains("geometry.height") && e.contains("1600000 layers of 0.25 mm"),
            "{e}"
        );
        let e = err(&GOOD.replace("r_mach = 2.0", "r_mach = -2.0"));
        assert!(e.contains("process.r_mach"), "{e}");
        for (name, why) in [
            ("  ", "must not be empty"),
            ("crown\\u001b[2J", "control character '\\u{1b}'"),
            ("evil\\u202etxt.crown", "bidirectional control '\\u{202e}'"),
            ("a\\u2066b", "bidirectional control '\\u{2066}'"),
            ("two\\nlines", "control character '\\n'"),
        ] {
            let e = err(&GOOD.replace("name = \"t\"", &format!("name = \"{name}\"")));
            assert!(e.contains("name") && e.contains(why), "{name}: {e}");
        }
        let long = "x".repeat(MAX_NAME_CHARS + 1);
        let e = err(&GOOD.replace("name = \"t\"", &format!("name = \"{long}\"")));
        assert!(e.contains("201 characters; at most 200"), "{e}");
        let e = err(&GOOD.replace("nozzle = 0.5", "nozzle = 0.0"));
        assert!(e.contains("process.nozzle"), "{e}");
        let e = err(&GOOD.replace("radius = 30.0", "radius = 30000.0"));
        assert!(
            e.contains("geometry: the part's section is") && e.contains("in mm?"),
            "{e}"
        );
        let e = err(&GOOD.replace("nozzle = 0.5", "nozzle = 0.0005"));
        assert!(
            e.contains("process.nozzle") && e.contains("0.0005 mm is finer"),
            "{e}"
        );
        let e = err(&GOOD.replace("nozzle = 0.5", "nozzle = 2.5"));
        assert!(e.contains("process.nozzle") && e.contains("r_mach"), "{e}");
        let e = err(&GOOD.replace("r_mach = 2.0", "r_mach = nan"));
        assert!(e.contains("process.r_mach"), "{e}");
        let e = err(&GOOD.replace("pattern = \"growth-rings\"", "pattern = \"zebra\""));
        assert!(e.contains("gradient.pattern"), "{e}");
        for t in ["0.6", "-0.1", "nan"] {
            let e = err(&GOOD.replace(
                "[process]",
                &format!("[process]\nmove_width_tolerance = {t}"),
            ));
            assert!(e.contains("process.move_width_tolerance"), "{t}: {e}");
        }
        let e = err(&GOOD.replace("[process]", "[process]\ncolour = 1"));
        assert!(e.contains("colour"), "{e}");
        let e = err(&GOOD.replace("function = \"linear\"", "function = { power = -1.0 }"));
        assert!(e.contains("gradient.function"), "{e}");
        let e = err(&GOOD.replace("radius = 10.0", "radius = 40.0"));
        assert!(e.contains("geometry.polygon"), "{e}");
        let e = err(&GOOD.replace(
            "function = \"linear\"",
            "function = { linear = { a = 2.0, b = 0.0 } }",
        ));
        assert!(e.contains("eq (3)"), "{e}");
        let e = err("name = ");
        assert!(e.contains("job.toml") && e.contains("line"), "{e}");
    }

    #[test]
    fn bowtie_and_hole_outside_are_refused() {
        let bow = GOOD.replace(
            "outer = { circle = { center = [0.0, 0.0], radius = 30.0 } }, holes = [{ circle = { center = [0.0, 0.0], radius = 10.0 } }]",
            "outer = [[0.0, 0.0], [10.0, 10.0], [10.0, 0.0], [0.0, 10.0]]",
        );
        assert!(err(&bow).contains("crosses"), "{}", err(&bow));
        let outside = GOOD.replace(
            "center = [0.0, 0.0], radius = 10.0",
            "center = [100.0, 0.0], radius = 10.0",
        );
        assert!(err(&outside).contains("not inside"), "{}", err(&outside));
    }
}
