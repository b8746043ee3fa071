//! Layer heights: uniform, or adaptive from the surface slope (cusp height) and a
//! caller's Z limit.
//!
//! Step 1: for every sloped triangle, the thickest layer its slope allows
//! ([`AdaptiveCriterion::max_thickness_mm`]), written into a fine z grid (bins of
//! `layer_min_mm / 8`) as a running minimum. Horizontal triangles do not limit thickness
//! (a layer boundary on them leaves no staircase); they are collected as snap heights.
//! (At most 4 million bins: a very tall part at very thin layers gets coarser bins.)
//! Step 2: walk up from the part's bottom. A layer starts as thick as `layer_max_mm` and the
//! caller's [`super::SliceOptions::max_thickness_at`] allow; every grid bin it overlaps may
//! shrink it to that bin's limit, or, when the limit is smaller than the bin's distance
//! above the layer bottom, end the layer where the steeper surface begins (as PrusaSlicer's
//! `SlicingAdaptive::next_layer_height` does). The result is clamped to `layer_min_mm`; a
//! horizontal facet inside the layer (at least `layer_min_mm` above its bottom) ends it.
//! Step 3: the top: the stack ends at the part's top; a last piece thinner than
//! `layer_min_mm / 2` is dropped, a thicker one is printed at `layer_min_mm`.

use super::{SliceError, SliceOptions};
use crate::mesh::Mesh;
use serde::{Deserialize, Serialize};

/// Grid bins per minimum layer thickness.
const BINS_PER_MIN_LAYER: f64 = 8.0;
/// At most this many grid bins (32 MB); coarser bins for very tall parts at thin layers.
const MAX_BINS: f64 = 4_000_000.0;
/// Refuse stacks of more layers than this (a guard against absurd options).
const MAX_LAYERS: f64 = 10_000_000.0;

/// Which slope criterion limits adaptive layer thickness. `c` is
/// [`SliceOptions::cusp_mm`]; `cos` and `sin` are of the angle between the facet normal and
/// Z (`cos` = 1 for a horizontal facet, 0 for a vertical wall).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AdaptiveCriterion {
    /// The classic cusp height (Dolenc & Mäkelä 1994; old Slic3r's "max distance metric"):
    /// a layer of thickness h on a facet leaves a staircase cusp h·cos, so h ≤ c / cos.
    /// Vertical walls are unlimited.
    #[default]
    CuspHeight,
    /// PrusaSlicer's current `SlicingAdaptive` formula (constant area of the surface error
    /// triangle, clamped at vertical walls): h ≤ min(c / 0.184, 1.44·c·√(sin / cos)).
    PrusaArea,
}

impl AdaptiveCriterion {
    /// Thickest layer a facet with this slope allows, mm (may be infinite).
    pub fn max_thickness_mm(self, cusp_mm: f64, cos: f64, sin: f64) -> f64 {
        match self {
            AdaptiveCriterion::CuspHeight => {
                if cos > 1e-9 {
                    cusp_mm / cos
                } else {
                    f64::INFINITY
                }
            }
            AdaptiveCriterion::PrusaArea => {
                let area = if cos > 1e-5 {
                    1.44 * cusp_mm * (sin / cos).sqrt()
                } else {
                    f64::INFINITY
                };
                (cusp_mm / 0.184).min(area)
            }
        }
    }
}

/// One layer of the stack before cutting: from `z_bottom_mm` up by `thickness_mm`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerSpan {
    pub z_bottom_mm: f64,
    pub thickness_mm: f64,
}

impl LayerSpan {
    /// Where the layer is cut (and its composition sampled), mm.
    pub fn mid_z_mm(&self) -> f64 {
        self.z_bottom_mm + 0.5 * self.thickness_mm
    }
    pub fn z_top_mm(&self) -> f64 {
        self.z_bottom_mm + self.thickness_mm
    }
}

fn check(options: &SliceOptions, height: f64) -> Result<(), SliceError> {
    let (lo, hi) = (options.layer_min_mm, options.layer_max_mm);
    if !(lo.is_finite() && lo > 0.0) {
        return Err(SliceError::BadOptions(format!(
            "layer min = {lo} mm; it must be a positive number"
        )));
    }
    if !(hi.is_finite() && hi >= lo) {
        return Err(SliceError::BadOptions(format!(
            "layer max = {hi} mm; it must be at least layer min = {lo} mm"
        )));
    }
    if hi > lo && !(options.cusp_mm.is_finite() && options.cusp_mm > 0.0) {
        return Err(SliceError::BadOptions(format!(
            "cusp = {} mm; adaptive layers need a positive cusp height",
            options.cusp_mm
        )));
    }
    if height / lo > MAX_LAYERS {
        return Err(SliceError::BadOptions(format!(
            "a {height:.1} mm tall part at {lo} mm layers is more than {MAX_LAYERS} layers"
        )));
    }
    Ok(())
}

/// The layer stack of `mesh` between `z0` and `z1` (steps 1–3 of the module's doc).
pub(super) fn layer_spans(
    mesh: &Mesh,
    (z0, z1): (f64, f64),
    options: &SliceOptions,
) -> Result<Vec<LayerSpan>, SliceError> {
    let height = z1 - z0;
    check(options, height)?;
    let (min, max) = (options.layer_min_mm, options.layer_max_mm);
    let eps = options.tolerances.z_eps_mm;
    let adaptive = max > min;

    // Step 1.
    let mut slopes = SlopeLimits::new(mesh, z0, height, adaptive, options);

    // Step 2.
    let mut spans = Vec::new();
    let mut z = z0;
    while z1 - z > eps {
        let mut h = max;
        if let Some(limit) = options.max_thickness_at {
            let l = limit(z);
            if l.is_finite() {
                h = h.min(l);
            }
        }
        h = h.max(min);
        if adaptive && h > min {
            h = slopes.thickness_from(z, h, min, eps);
        }
        // Step 3.
        let Some(h) = fitted_to_top(z1 - z, h, min, eps, adaptive, spans.is_empty()) else {
            break;
        };
        spans.push(LayerSpan {
            z_bottom_mm: z,
            thickness_mm: h,
        });
        z += h;
    }
    Ok(spans)
}

/// Step 1: the thickest layer the surface's slope allows in every bin of a fine z grid,
/// and the heights of horizontal facets.
struct SlopeLimits {
    /// Bottom of the grid, mm.
    z0: f64,
    /// Bin height, mm.
    res: f64,
    /// Thickest layer allowed over each bin, mm (infinite: unlimited).
    bin_limit: Vec<f64>,
    /// Heights of horizontal facets, ascending, one per `z_eps_mm`.
    flats: Vec<f64>,
    /// The first flat above the layers walked so far.
    next_flat: usize,
}

impl SlopeLimits {
    /// Every sloped triangle's limit written into the bins it spans as a running
    /// minimum; horizontal triangles collected as flats. Empty unless `adaptive`.
    fn new(
        mesh: &Mesh,
        z0: f64,
        height: f64,
        adaptive: bool,
        options: &SliceOptions,
    ) -> SlopeLimits {
        let (min, max) = (options.layer_min_mm, options.layer_max_mm);
        let eps = options.tolerances.z_eps_mm;
        let res = (min / BINS_PER_MIN_LAYER).max(height / MAX_BINS);
        let nbins = if adaptive {
            (height / res).ceil() as usize + 1
        } else {
            0
        };
        let mut bin_limit = vec![f64::INFINITY; nbins];
        let mut flats: Vec<f64> = Vec::new();
        if adaptive {
            for t in 0..mesh.triangles.len() {
                let [a, b, c] = mesh.corners(t);
                let n = (b - a).cross(c - a);
                let len = n.length();
                if len <= 0.0 {
                    continue;
                }
                let lo = a.z.min(b.z).min(c.z);
                let hi = a.z.max(b.z).max(c.z);
                if hi - lo <= eps {
                    flats.push(lo);
                    continue;
                }
                let cos = (n.z / len).abs().min(1.0);
                let sin = (1.0 - cos * cos).sqrt();
                let limit = options
                    .criterion
                    .max_thickness_mm(options.cusp_mm, cos, sin);
                if limit >= max {
                    continue;
                }
                let b0 = (((lo - z0) / res).floor().max(0.0) as usize).min(nbins - 1);
                let b1 = (((hi - z0) / res).ceil() as usize).clamp(b0 + 1, nbins);
                for l in &mut bin_limit[b0..b1] {
                    *l = l.min(limit);
                }
            }
            flats.sort_by(f64::total_cmp);
            flats.dedup_by(|a, b| (*a - *b).abs() <= eps);
        }
        SlopeLimits {
            z0,
            res,
            bin_limit,
            flats,
            next_flat: 0,
        }
    }

    /// Step 2: a layer from `z` of at most `h`, shrunk to the limit of every bin it
    /// overlaps, or ended where a steeper surface begins; at least `min`; ended at a
    /// horizontal facet at least `min` above `z`. Layers are asked for bottom-up.
    fn thickness_from(&mut self, z: f64, mut h: f64, min: f64, eps: f64) -> f64 {
        let (z0, res) = (self.z0, self.res);
        let mut b = ((z - z0) / res).floor().max(0.0) as usize;
        while b < self.bin_limit.len() {
            let start = z0 + b as f64 * res;
            if start >= z + h {
                break;
            }
            let lim = self.bin_limit[b];
            if lim < h {
                let d = start - z;
                h = if d > eps && lim < d { d } else { lim };
            }
            b += 1;
        }
        h = h.max(min);
        let flats = &self.flats;
        while self.next_flat < flats.len() && flats[self.next_flat] <= z + eps {
            self.next_flat += 1;
        }
        if let Some(&f) = flats.get(self.next_flat) {
            if f < z + h - eps && f - z >= min {
                h = f - z;
            }
        }
        h
    }
}

/// Step 3: a layer of `h` with `remaining` mm of the part above its bottom. The last
/// layer ends at the part's top; a last piece thinner than `min / 2` is dropped
/// (`None`, unless it is the only layer) and a thicker one printed at `min`. An adaptive
/// layer that would leave less than `min` above it leaves `min`.
fn fitted_to_top(
    remaining: f64,
    h: f64,
    min: f64,
    eps: f64,
    adaptive: bool,
    first: bool,
) -> Option<f64> {
    if remaining <= h + eps {
        if remaining < min {
            if remaining < 0.5 * min && !first {
                return None;
            }
            Some(min)
        } else {
            Some(remaining)
        }
    } else if adaptive && remaining - h < min {
        Some((remaining - min).max(min))
    } else {
        Some(h)
    }
}
