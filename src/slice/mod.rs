//! Mesh to layers: choose layer heights (uniform, or adaptive from the local surface slope
//! and a caller's Z limit) and cut the mesh into each layer's islands.
//!
//! This is the paper's adaptive slicing step (§2–§3, ref. [12]): "layer thickness
//! determined by the Z-directional local slope and the desired gradient step-width in the
//! Z-direction". The slope part is the cusp-height criterion ([`AdaptiveCriterion`]); the
//! gradient step arrives through [`SliceOptions::max_thickness_at`].
//!
//! Step 1 ([`Slicer::new`]): index the mesh: one id per undirected edge, the z range of each
//! triangle. Step 2 ([`Slicer::layer_spans`]): the stack of layers, bottom to top.
//! Step 3 ([`Slicer::slice`]): for each layer, in parallel, cut the mesh with the plane at
//! the layer's mid-height, chain the cut segments into loops through shared edges, close
//! small gaps, and nest the loops into islands ([`crate::geom::Region`]).
//!
//! Robustness: a vertex whose z equals the plane height counts as *above* the plane (the
//! plane is taken infinitesimally below it, a symbolic perturbation), so every triangle is
//! either not cut or cut through exactly two of its edges, horizontal facets lying in the
//! plane are never cut, and loops are chained by edge identity, never by comparing
//! floating-point positions. See `docs/mesh-and-slicing.md`.

mod heights;
pub mod overhang;
mod section;
pub mod support;

pub use heights::{AdaptiveCriterion, LayerSpan};

use crate::geom::{Region, RegionError};
use crate::mesh::Mesh;
use serde::Serialize;
use std::sync::atomic::{AtomicUsize, Ordering};

/// One layer of the part.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct Layer {
    /// Top of the layer (where the nozzle deposits it), mm.
    pub z_mm: f64,
    pub thickness_mm: f64,
    /// The islands of the section at mid-height (`z_mm - thickness_mm / 2`): each an
    /// outer loop (counter-clockwise) and its holes (clockwise).
    pub islands: Vec<Region>,
}

impl Layer {
    /// Mid-height of the layer, where it was cut (and where a Z gradient is sampled), mm.
    pub fn mid_z_mm(&self) -> f64 {
        self.z_mm - 0.5 * self.thickness_mm
    }

    /// Net area of all islands, mm².
    pub fn area_mm2(&self) -> f64 {
        self.islands.iter().map(Region::area).sum()
    }
}

/// Tolerances of slicing, in one place.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct SliceTolerances {
    /// Largest gap between the ends of open section chains that is closed with a straight
    /// segment, mm. PrusaSlicer closes gaps up to 2 mm the same way. Default 2.0.
    pub max_gap_mm: f64,
    /// Consecutive loop points closer than this are merged, mm. Default 1e-7.
    pub point_eq_mm: f64,
    /// A cutting plane closer than half of this to a vertex height is moved away from it
    /// (up first, then down, in steps of this), so that a facet lying at a layer's
    /// mid-height is treated the same whether the file rounded it up or down, mm.
    /// Default 1e-4.
    pub plane_clearance_mm: f64,
    /// Loop points within this of the line through their neighbours are dropped
    /// (collinear points, and the zero-width spikes that µm-scale folds of real meshes
    /// leave), mm. Default 1e-4.
    pub collinear_mm: f64,
    /// Loops enclosing less area are dropped (slivers from touching facets), mm².
    /// Default 1e-6.
    pub min_loop_area_mm2: f64,
    /// Horizontal facets within this of a layer's top snap the layer to them, mm
    /// (adaptive only). Also the z tolerance for "touching" a facet. Default 1e-6.
    pub z_eps_mm: f64,
    /// Check every island with [`Region::validate`] and refuse a layer that fails.
    /// Default true.
    pub validate_regions: bool,
}

impl Default for SliceTolerances {
    fn default() -> Self {
        SliceTolerances {
            max_gap_mm: 2.0,
            point_eq_mm: 1e-7,
            plane_clearance_mm: 1e-4,
            collinear_mm: 1e-4,
            min_loop_area_mm2: 1e-6,
            z_eps_mm: 1e-6,
            validate_regions: true,
        }
    }
}

/// A caller-supplied upper bound on layer thickness as a function of the layer's bottom
/// z (mm -> mm), e.g. the Z gradient step where the composition changes along Z.
pub type ThicknessLimit<'a> = &'a (dyn Fn(f64) -> f64 + Sync);

/// How to stack and cut the layers. Uniform layers: `layer_min_mm == layer_max_mm`.
#[derive(Clone, Copy)]
pub struct SliceOptions<'a> {
    /// Thinnest layer, mm (> 0).
    pub layer_min_mm: f64,
    /// Thickest layer, mm (>= `layer_min_mm`).
    pub layer_max_mm: f64,
    /// Largest allowed cusp height (staircase deviation from the surface), mm; adaptive only.
    pub cusp_mm: f64,
    pub criterion: AdaptiveCriterion,
    /// Extra upper bound on a layer's thickness given its bottom z; values below
    /// `layer_min_mm` are raised to it.
    pub max_thickness_at: Option<ThicknessLimit<'a>>,
    pub tolerances: SliceTolerances,
}

impl std::fmt::Debug for SliceOptions<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SliceOptions")
            .field("layer_min_mm", &self.layer_min_mm)
            .field("layer_max_mm", &self.layer_max_mm)
            .field("cusp_mm", &self.cusp_mm)
            .field("criterion", &self.criterion)
            .field("max_thickness_at", &self.max_thickness_at.is_some())
            .field("tolerances", &self.tolerances)
            .finish()
    }
}

impl Default for SliceOptions<'_> {
    /// 0.1–0.3 mm adaptive layers with a 0.1 mm cusp.
    fn default() -> Self {
        SliceOptions {
            layer_min_mm: 0.1,
            layer_max_mm: 0.3,
            cusp_mm: 0.1,
            criterion: AdaptiveCriterion::CuspHeight,
            max_thickness_at: None,
            tolerances: SliceTolerances::default(),
        }
    }
}

impl SliceOptions<'_> {
    /// Uniform layers of `thickness_mm`.
    pub fn uniform(thickness_mm: f64) -> Self {
        SliceOptions {
            layer_min_mm: thickness_mm,
            layer_max_mm: thickness_mm,
            ..Default::default()
        }
    }
}

/// Why slicing failed, naming the layer and the place.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SliceError {
    #[error("bad layer heights: {0}")]
    BadOptions(String),
    #[error("the mesh has no triangles")]
    Empty,
    #[error("the mesh cannot be sliced: {0}")]
    BadMesh(#[from] crate::mesh::MeshError),
    #[error("the mesh is open at layer z = {z_mm:.4} mm: a section loop ends at ({x:.3}, {y:.3}) and no other loop end is within {max_gap_mm} mm{}; repair the mesh (close the hole) or allow a larger gap (job key [process] max_gap)", nearest_mm.map(|d| format!(" (nearest {d:.3} mm)")).unwrap_or_default())]
    OpenLoop {
        z_mm: f64,
        x: f64,
        y: f64,
        nearest_mm: Option<f64>,
        max_gap_mm: f64,
    },
    #[error("layer z = {z_mm:.4} mm, island {island}: {source}")]
    BadRegion {
        z_mm: f64,
        island: usize,
        source: RegionError,
    },
}

/// A gap closed while chaining a section.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GapClosed {
    /// Height of the cut, mm.
    pub z_mm: f64,
    /// Where the gap starts, mm.
    pub x_mm: f64,
    pub y_mm: f64,
    pub gap_mm: f64,
}

/// What slicing had to do beyond cutting.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct SliceReport {
    pub layers: usize,
    /// Gaps closed, bottom to top (at most 100 listed; the count is complete).
    pub gaps_closed: Vec<GapClosed>,
    pub gaps_closed_count: usize,
    pub max_gap_closed_mm: f64,
    /// Loops dropped for enclosing less than `min_loop_area_mm2`.
    pub slivers_dropped: usize,
    /// Layers whose loops touched or crossed themselves (µm-scale folds of real meshes)
    /// and were resolved with an even-odd union (i_overlay) before validation.
    pub layers_resolved_by_union: usize,
}

/// Progress callback: `(layers done, layers total)`, called from worker threads.
pub type Progress<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// A mesh indexed for slicing. Build once, then ask for layer spans and sections.
pub struct Slicer<'m> {
    mesh: std::borrow::Cow<'m, Mesh>,
    /// Undirected edge id of each triangle's edge k (corner k to corner k + 1).
    tri_edges: Vec<[u32; 3]>,
    edge_count: usize,
    z_range: (f64, f64),
    /// Sorted vertex heights.
    vertex_z: Vec<f64>,
}

impl<'m> Slicer<'m> {
    /// Index `mesh` (its triangles should have gone through [`crate::mesh::repair`]).
    pub fn new(mesh: &'m Mesh) -> Result<Self, SliceError> {
        Self::index(std::borrow::Cow::Borrowed(mesh))
    }

    /// Index a mesh the slicer keeps (for a job that cuts its layers over time, as the
    /// daemon's planner does).
    pub fn new_owned(mesh: Mesh) -> Result<Slicer<'static>, SliceError> {
        Slicer::index(std::borrow::Cow::Owned(mesh))
    }

    fn index(mesh: std::borrow::Cow<'m, Mesh>) -> Result<Self, SliceError> {
        mesh.check_indices_and_coordinates()?;
        let (lo, hi) = mesh.bounds().ok_or(SliceError::Empty)?;
        let uses = crate::mesh::edge_uses(&mesh.triangles);
        let mut tri_edges = vec![[0u32; 3]; mesh.triangles.len()];
        let mut id: u32 = 0;
        for (i, u) in uses.iter().enumerate() {
            if i > 0 && uses[i - 1].0 != u.0 {
                id += 1;
            }
            tri_edges[u.1 as usize][u.2 as usize] = id;
        }
        let mut vertex_z: Vec<f64> = mesh.vertices.iter().map(|v| v.z).collect();
        vertex_z.sort_by(f64::total_cmp);
        Ok(Slicer {
            vertex_z,
            mesh,
            tri_edges,
            edge_count: id as usize + 1,
            z_range: (lo.z, hi.z),
        })
    }

    /// The height a plane asked for at `z` is actually cut at: `z` moved off vertex
    /// heights by [`SliceTolerances::plane_clearance_mm`] steps when it is too close to one.
    pub fn cut_height_mm(&self, z: f64, tolerances: &SliceTolerances) -> f64 {
        let step = tolerances.plane_clearance_mm;
        if step <= 0.0 {
            return z;
        }
        let near = |p: f64| {
            let i = self.vertex_z.partition_point(|&v| v < p - 0.5 * step);
            self.vertex_z.get(i).is_some_and(|&v| v <= p + 0.5 * step)
        };
        for k in 0..16 {
            // Offsets 0, +1, -1, +2, -2, ... steps.
            let sign = if k % 2 == 1 { 1.0 } else { -1.0 };
            let p = z + sign * ((k + 1) / 2) as f64 * step;
            if !near(p) {
                return p;
            }
        }
        z
    }

    /// The mesh being sliced.
    pub fn mesh(&self) -> &Mesh {
        &self.mesh
    }

    /// Bottom and top of the part, mm.
    pub fn z_range_mm(&self) -> (f64, f64) {
        self.z_range
    }

    /// The stack of layers from the part's bottom to its top (see `heights`).
    pub fn layer_spans(&self, options: &SliceOptions) -> Result<Vec<LayerSpan>, SliceError> {
        heights::layer_spans(&self.mesh, self.z_range, options)
    }

    /// Cut the given layers (any subset of [`Self::layer_spans`], e.g. a `--layers A..B`
    /// range) in parallel; `progress` hears `(done, total)` after each layer.
    pub fn slice(
        &self,
        spans: &[LayerSpan],
        tolerances: &SliceTolerances,
        progress: Option<Progress>,
    ) -> Result<(Vec<Layer>, SliceReport), SliceError> {
        use rayon::prelude::*;
        let done = AtomicUsize::new(0);
        let total = spans.len();
        let planes: Vec<f64> = spans
            .iter()
            .map(|s| self.cut_height_mm(s.mid_z_mm(), tolerances))
            .collect();
        let buckets = section::Buckets::new(&self.mesh, &planes);
        let results: Vec<Result<(Vec<Region>, section::LayerNotes), SliceError>> = (0..total)
            .into_par_iter()
            .map_init(
                || section::Scratch::new(self.edge_count),
                |scratch, i| {
                    let r = section::cut(
                        &self.mesh,
                        &self.tri_edges,
                        buckets.triangles(i),
                        planes[i],
                        tolerances,
                        scratch,
                    );
                    if let Some(p) = progress {
                        p(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                    }
                    r
                },
            )
            .collect();
        let mut report = SliceReport {
            layers: total,
            ..Default::default()
        };
        let mut layers = Vec::with_capacity(total);
        for (span, r) in spans.iter().zip(results) {
            let (islands, notes) = r?;
            report.slivers_dropped += notes.slivers_dropped;
            report.layers_resolved_by_union += notes.resolved_by_union as usize;
            for g in notes.gaps {
                report.gaps_closed_count += 1;
                report.max_gap_closed_mm = report.max_gap_closed_mm.max(g.gap_mm);
                if report.gaps_closed.len() < 100 {
                    report.gaps_closed.push(g);
                }
            }
            layers.push(Layer {
                z_mm: span.z_bottom_mm + span.thickness_mm,
                thickness_mm: span.thickness_mm,
                islands,
            });
        }
        Ok((layers, report))
    }

    /// The islands of plain sections at the given heights (no layer stacking), mm.
    pub fn sections_at(
        &self,
        z_mm: &[f64],
        tolerances: &SliceTolerances,
    ) -> Result<Vec<Vec<Region>>, SliceError> {
        let spans: Vec<LayerSpan> = z_mm
            .iter()
            .map(|&z| LayerSpan {
                z_bottom_mm: z,
                thickness_mm: 0.0,
            })
            .collect();
        let (layers, _) = self.slice(&spans, tolerances, None)?;
        Ok(layers.into_iter().map(|l| l.islands).collect())
    }
}

/// Mesh to layers in one call: index, stack, cut. The mesh should come from
/// [`crate::mesh::load_and_repair`] (or [`crate::mesh::repair`]).
pub fn slice_mesh(
    mesh: &Mesh,
    options: &SliceOptions,
    progress: Option<Progress>,
) -> Result<(Vec<Layer>, SliceReport), SliceError> {
    let slicer = Slicer::new(mesh)?;
    let spans = slicer.layer_spans(options)?;
    slicer.slice(&spans, &options.tolerances, progress)
}
