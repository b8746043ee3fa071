//! From planned layers to machine moves: the stable entry point the daemon, the CLI and
//! the G-code export call.
//!
//! ```text
//! LayerPlan ──toolpath::fill_order──> Vec<ToolPath> ──layer_moves──> Vec<Move> + stats
//! ```
//!
//! # API
//!
//! - [`ProcessSettings`]: every process number with a documented default; serde with
//!   `deny_unknown_fields`, so a `[toolpath]` TOML table fills it
//!   ([`ProcessSettings::from_toml`]). [`ProcessSettings::for_nozzle`] gives the defaults
//!   for a nozzle.
//! - [`StreamState`]: what carries over from one layer to the next: the nozzle position,
//!   whether the syringes are pressurised (or retracted, and by how much), the per-syringe
//!   volumes planned (exact, `f64`) and commanded (fixed point) so far, and the mixing
//!   chamber's content. Create one per job with [`StreamState::new`] and pass it to every
//!   layer in order. Its fields are private; read it through its methods.
//! - [`layer_moves`]: one layer to moves, numbered from `first_index`, plus
//!   [`LayerStats`].
//! - [`job_layer_moves`]: every layer of a job to moves, the same as [`layer_moves`] on
//!   each in order, with most of the work on all cores (for previews, reports and
//!   G-code; the daemon plans and streams layer by layer); [`for_each_layer_moves`] the
//!   same a batch of layers at a time, handing each layer's moves over in order (the
//!   G-code file is written as it is planned).
//!
//! # Moves of a layer
//!
//! `LayerMark`, then for each path in Fig. 4(a) order (see [`crate::toolpath`]): if the
//! nozzle is not at the path start, extrusion cessation — `Retract` (when pressurised and
//! the travel is at least `retract_min_travel_mm`), `Travel`, `Prime` (exactly the volumes
//! retracted), `Dwell` — then one `Extrude` per centreline edge at constant scanning
//! speed (`print_feed_mm_s`). The edges are the path's merged within `move_deviation_mm`
//! where the width changes by at most `move_width_tolerance`, each move pushing the
//! volume of the edges it replaces (`toolpath::merge`), and split where the mixing
//! lead's commanded composition changes, so no move blends two compositions.
//!
//! # Mixing chamber
//!
//! The syringes feed a chamber of dead volume V_dead (`v_dead_ul`); under plug flow a
//! composition commanded now leaves the nozzle V_dead of extrusion later. With
//! `mixing_lead` each extrusion segment is commanded the composition designed V_dead
//! further along the layer's stream, so the designed composition leaves the nozzle where
//! each path starts (within a layer; past the layer's last road the last composition is
//! held). A layer whose start the chamber does not hold begins, with `purge_xy_mm` set,
//! with a purge pad off the part commanded with the layer's first V_dead of designed
//! composition (through a well-mixed or dispersing chamber: the first designed
//! composition for the model's washout, [`purge`]). [`StreamState`] carries the chamber's content across layers, and
//! [`LayerStats`] reports the designed-versus-delivered error (largest per-material
//! difference, volume-weighted mean and maximum, move by move and road by road) and the
//! roads whose error exceeds `mixer_tolerance` ([`MixerLimit`]: where and by how much).
//! With the lead, the per-syringe volumes are those of the commanded compositions.
//!
//! The chamber is the machine's [`crate::mixer`] model through V_dead (`mixer_model`,
//! plug flow by default, as above). With another model and `mixer_feed_forward`, each
//! extrusion move is commanded what [`crate::mixer::inverse::feed_forward`] chooses from
//! the lead's commands and the chamber's state before the layer (after any purge), and
//! edges are split so no move is longer than V_dead/32.
//!
//! # Volumes
//!
//! A road of width w (the nozzle, times the vertex width factor) on a layer of thickness h
//! is modelled as a rectangle w × h (roads one width apart tile the layer); an edge of
//! length L deposits w · h · L mm³ (1 mm³ = 1000 nl), split over the syringes by the
//! composition. The fixed-point volumes are rounded cumulatively per syringe: after every
//! move, each syringe's commanded total is its exact planned total rounded to the nearest
//! nanolitre, so totals never drift (at most 0.5 nl per syringe over a whole job) and a
//! move's volumes sum to its total exactly by construction.

use crate::machine::{Move, MoveKind, PositionUm, FACTOR_NOMINAL_PPT, MAX_SYRINGES};
use crate::mixer::{Mixer, MixerModel, MixerOptions};

mod mixing;
pub mod purge;
use crate::plan::LayerPlan;
use crate::toolpath::{self, OrderSettings, SeamMode, SubRegionOrder, ToolPath};
use glam::{DVec2, DVec3};
pub use mixing::MixerLimit;
use serde::{Deserialize, Serialize};

/// Default of [`ProcessSettings::move_deviation_mm`]: the largest that keeps a part's
/// coverage within 0.05 percentage points of one move per edge on the example jobs and
/// 3DBenchy, with merged edges in phase with their neighbours' and long edges leaning
/// less (`toolpath::merge`). Merged one by one and leaning freely, 0.0025 mm was the
/// largest (PrusaSlicer's `gcode_resolution`, 0.0125 mm, moved the paper annulus' void
/// and overlap by 0.23 points each); in phase, 0.01 mm keeps every example within 0.045
/// points and plans Benchy in 10 % fewer moves than 0.0025 did (`docs/job-format.md`).
pub const DEFAULT_MOVE_DEVIATION_MM: f64 = 0.01;

/// Default of [`ProcessSettings::move_width_tolerance`] (`docs/job-format.md`).
pub const DEFAULT_MOVE_WIDTH_TOLERANCE: f64 = 0.1;

/// Largest [`ProcessSettings::move_width_tolerance`] accepted: a move half again as wide
/// at one end as at the other is no longer one road width.
pub const MAX_MOVE_WIDTH_TOLERANCE: f64 = 0.5;

/// Process settings: feeds, road width, extrusion cessation, flow limits, mixing chamber,
/// seams. Units in the names; defaults documented per field (see [`Default`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ProcessSettings {
    /// Nozzle diameter D_noz, mm. Default 0.4 (set from the job's `process.nozzle`).
    pub nozzle_mm: f64,
    /// Nominal road width, mm. Default: `nozzle_mm`.
    pub road_width_mm: Option<f64>,
    /// Scanning speed while extruding, mm/s (constant; flow changes width, not speed).
    /// Default 10.
    pub print_feed_mm_s: f64,
    /// Travel speed, mm/s. Default 40.
    pub travel_feed_mm_s: f64,
    /// Volume pulled back over all syringes at each extrusion cessation, nl (split by the
    /// current composition; the prime pushes the same volumes back). Default 200.
    pub retract_nl: u32,
    /// Duration of a retract, ms. Default 150.
    pub retract_ms: u32,
    /// Duration of the re-prime, ms. Default 150.
    pub prime_ms: u32,
    /// Dwell after the re-prime so pressure settles before the road starts, ms. Default 100.
    pub dwell_ms: u32,
    /// Travels shorter than this keep the syringes pressurised (no retract/prime), mm.
    /// Default 0: every travel is an extrusion cessation, as in §4.
    pub retract_min_travel_mm: f64,
    /// Largest width (flow) factor a road may be raised to in narrow sub-areas.
    /// Default 1.5.
    pub max_flow_factor: f64,
    /// Narrowest bead relative to nominal: roads spaced closer than a road width are
    /// narrowed to their spacing down to this (≤ 1; 1 turns narrowing off). Default 0.6.
    pub min_flow_factor: f64,
    /// Match road widths to their neighbours (`toolpath::flow`): raise the flow where a
    /// gap needs a non-integer number of roads (§4, Fig. 4(a) (i)–(iii)), lower it where
    /// roads are closer than a road width, moving centrelines so each bead meets the
    /// facing edges on both sides (the part boundary edge stays). Default true.
    pub flow_raise: bool,
    /// Continue road ends that run into the boundary at a slant into their corners
    /// (`toolpath::ends`), then fill what is left with thin roads along the gaps'
    /// centrelines (`toolpath::gapfill`, Arachne / PrusaSlicer gap fill). Default true.
    pub gap_fill: bool,
    /// Narrowest gap-fill road relative to the road width (gaps narrower are left).
    /// Default 0.25. The widest is `max_flow_factor`.
    pub gap_fill_min_factor: f64,
    /// Width changes smaller than this fraction of the road width are left (noise:
    /// 2 µm on a 0.4 mm road). Default 0.0025.
    pub flow_min_gap_fraction: f64,
    /// Dead volume of the mixing chamber V_dead, µL. Default 0 (no chamber).
    pub v_dead_ul: f64,
    /// The mixing chamber's residence-time distribution (`crate::mixer`) through
    /// V_dead: plug flow (default), well-mixed, or plug flow with axial dispersion. Set
    /// by the machine (`[machine.mixer]`, `edoctl plan --mixer`), not by the job.
    #[serde(skip)]
    pub mixer_model: MixerModel,
    /// Peclet number of the `dispersion` mixer model. Set with `mixer_model`.
    #[serde(skip)]
    pub mixer_peclet: Option<f64>,
    /// With a mixer other than plug flow and `mixing_lead`, command each extrusion move
    /// the composition that makes the nozzle exit follow the design as closely as the
    /// chamber allows (`crate::mixer::inverse`: a bounded feed-forward inverse of the
    /// mixer), rather than the design V_dead ahead. Moves are then at most V_dead/32
    /// long. Default true.
    pub mixer_feed_forward: bool,
    /// A road whose predicted nozzle-exit composition misses its design by more than
    /// this (largest fraction difference) is reported as mixer-limited. Default 0.01.
    pub mixer_tolerance: f64,
    /// Command each composition change V_dead ahead so it reaches the nozzle exit where
    /// the path starts. Default true (no effect when `v_dead_ul` is 0).
    pub mixing_lead: bool,
    /// Purge position (x, y mm, off the part: a waste bin, or a spot on the bed where the
    /// purges stack into a tower). Where the mixing chamber does not hold what a layer
    /// starts with (the lead cannot reach back into the previous layer), the layer
    /// begins with a purge there, laid as a zig-zag pad: under plug flow V_dead
    /// commanded with the layer's first V_dead of designed composition, so the designed
    /// composition leaves the nozzle where the layer's first road starts; through a
    /// well-mixed or dispersing chamber the layer's first designed composition for the
    /// model's washout (`purge::washout_nl`: until the chamber holds it within
    /// `purge_min_error`, several V_dead for a well-mixed one). Default unset (no
    /// purge: the layer start's error is reported).
    pub purge_xy_mm: Option<[f64; 2]>,
    /// Side of the square purge pad, mm. Default 5.
    pub purge_pad_mm: f64,
    /// Purge only where the chamber's content differs from the layer's first V_dead
    /// (plug flow) or first designed composition (other mixers) by more than this
    /// (largest per-material difference); through other mixers also how close the
    /// purge washes the chamber to it. Default 0.02.
    pub purge_min_error: f64,
    /// Seam placement of closed loops. Default `aligned`.
    pub seam: SeamMode,
    /// Seam direction (aligned; start of staggered), degrees from +x. Default 90 (rear).
    pub seam_angle_deg: f64,
    /// Turn at a vertex that makes it a concave corner for seams, degrees. Default 30.
    pub seam_corner_min_deg: f64,
    /// Order of sub-regions. Default inner to outer.
    pub sub_region_order: SubRegionOrder,
    /// The machine's syringe of each material (a job's materials matched to the
    /// machine's syringes by name, or mapped by `materials.syringes`), where it is not
    /// the material's own position: every move's volumes are written in the machine's
    /// syringe order. Default unset (material i in syringe i).
    #[serde(skip)]
    pub syringe_of_material: Option<Vec<usize>>,
    /// Syringes on the machine; when set, every composition must have this many
    /// fractions. Default unset (taken from the plan).
    pub syringes: Option<usize>,
    /// Consecutive edges of a road merge into one move where the merged edge stays
    /// within this of every vertex it drops and the width does not change
    /// (`toolpath::merge`), mm; 0 merges nothing. Set by the job's
    /// `process.move_deviation`. Default [`DEFAULT_MOVE_DEVIATION_MM`] (0.01).
    #[serde(skip)]
    pub move_deviation_mm: f64,
    /// How much the width may change within one merged move: the largest relative
    /// spread ((widest − narrowest) / narrowest) of the edges' width factors a move
    /// replaces; each such move pushes exactly the volume of its edges
    /// (`toolpath::merge`). 0: a move never spans a width change. Set by the job's
    /// `process.move_width_tolerance`. Default [`DEFAULT_MOVE_WIDTH_TOLERANCE`].
    #[serde(skip)]
    pub move_width_tolerance: f64,
    /// How each layer's support (`LayerPlan::support`) is built, in which
    /// composition; unset: no support roads. Set from the job's `[support]`.
    #[serde(skip)]
    pub support: Option<crate::toolpath::support::SupportRoads>,
}

impl Default for ProcessSettings {
    fn default() -> Self {
        ProcessSettings {
            nozzle_mm: 0.4,
            road_width_mm: None,
            print_feed_mm_s: 10.0,
            travel_feed_mm_s: 40.0,
            retract_nl: 200,
            retract_ms: 150,
            prime_ms: 150,
            dwell_ms: 100,
            retract_min_travel_mm: 0.0,
            max_flow_factor: 1.5,
            min_flow_factor: 0.6,
            flow_raise: true,
            flow_min_gap_fraction: 0.005,
            gap_fill: true,
            gap_fill_min_factor: 0.25,
            v_dead_ul: 0.0,
            mixer_model: MixerModel::Plug,
            mixer_peclet: None,
            mixer_feed_forward: true,
            mixer_tolerance: 0.01,
            mixing_lead: true,
            purge_xy_mm: None,
            purge_pad_mm: 5.0,
            purge_min_error: 0.02,
            seam: SeamMode::Aligned,
            seam_angle_deg: 90.0,
            seam_corner_min_deg: 30.0,
            sub_region_order: SubRegionOrder::InnerToOuter,
            syringe_of_material: None,
            syringes: None,
            move_deviation_mm: DEFAULT_MOVE_DEVIATION_MM,
            move_width_tolerance: DEFAULT_MOVE_WIDTH_TOLERANCE,
            support: None,
        }
    }
}

/// Why a layer could not be turned into moves; names the layer, field or point.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PipelineError {
    /// A setting is out of range.
    #[error("process setting {field}: {message}")]
    Setting {
        field: &'static str,
        message: String,
    },
    /// A TOML settings table that does not parse (message has line and column).
    #[error("process settings {source_name}: {message}")]
    Toml {
        source_name: String,
        message: String,
    },
    /// Compositions of the wrong length for the machine.
    #[error("layer {layer}: a path has {got} material fractions but the machine has {expected} syringes")]
    Syringes {
        layer: usize,
        expected: usize,
        got: usize,
    },
    /// A point outside the machine's fixed-point range (±2147 m).
    #[error("layer {layer}: point ({x_mm}, {y_mm}, {z_mm}) mm is outside the machine's coordinate range")]
    OutOfRange {
        layer: usize,
        x_mm: f64,
        y_mm: f64,
        z_mm: f64,
    },
    /// Move indices would pass u32::MAX.
    #[error("layer {layer}: move index overflow (more than 4294967295 moves in the job)")]
    IndexOverflow { layer: usize },
}

impl ProcessSettings {
    /// How many fractions every composition has: the machine's syringes where known,
    /// else those of the support's composition (the part's materials and the support
    /// syringe); unset: the plan's.
    pub fn channels(&self) -> Option<usize> {
        self.syringes
            .or_else(|| self.support.as_ref().map(|s| s.composition.len()))
    }

    /// The defaults for a nozzle of `nozzle_mm`.
    pub fn for_nozzle(nozzle_mm: f64) -> Self {
        ProcessSettings {
            nozzle_mm,
            ..Default::default()
        }
    }

    /// Parse a `[toolpath]` table's text (unknown keys refused) and validate it.
    pub fn from_toml(text: &str, source_name: &str) -> Result<Self, PipelineError> {
        let s: ProcessSettings = toml::from_str(text).map_err(|e| PipelineError::Toml {
            source_name: source_name.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        s.validate()?;
        Ok(s)
    }

    /// The nominal road width, mm.
    pub fn road_width(&self) -> f64 {
        self.road_width_mm.unwrap_or(self.nozzle_mm)
    }

    /// Check every field's range.
    pub fn validate(&self) -> Result<(), PipelineError> {
        positive(self.nozzle_mm, "nozzle_mm")?;
        positive(self.road_width(), "road_width_mm")?;
        positive(self.print_feed_mm_s, "print_feed_mm_s")?;
        positive(self.travel_feed_mm_s, "travel_feed_mm_s")?;
        non_negative(self.retract_min_travel_mm, "retract_min_travel_mm")?;
        non_negative(self.v_dead_ul, "v_dead_ul")?;
        self.mixer().validate().map_err(|e| {
            let field = match e.key {
                "peclet" => "mixer_peclet",
                _ => "mixer_model",
            };
            setting_error(field, e.message)
        })?;
        positive(self.purge_pad_mm, "purge_pad_mm")?;
        non_negative(self.purge_min_error, "purge_min_error")?;
        non_negative(self.mixer_tolerance, "mixer_tolerance")?;
        non_negative(self.move_deviation_mm, "move_deviation_mm")?;
        if !(0.0..=MAX_MOVE_WIDTH_TOLERANCE).contains(&self.move_width_tolerance) {
            return Err(setting_error(
                "move_width_tolerance",
                format!(
                    "must be a fraction from 0 to {MAX_MOVE_WIDTH_TOLERANCE}, got {}",
                    self.move_width_tolerance
                ),
            ));
        }
        if let Some([x, y]) = self.purge_xy_mm {
            if !(x.is_finite() && y.is_finite() && x.abs() < MAX_COORD_MM && y.abs() < MAX_COORD_MM)
            {
                return Err(setting_error(
                    "purge_xy_mm",
                    format!("must be a finite position on the machine, got [{x}, {y}]"),
                ));
            }
        }
        if !(self.max_flow_factor.is_finite() && self.max_flow_factor >= 1.0) {
            return Err(setting_error(
                "max_flow_factor",
                format!("must be 1 or more, got {}", self.max_flow_factor),
            ));
        }
        fraction(self.min_flow_factor, "min_flow_factor")?;
        fraction(self.gap_fill_min_factor, "gap_fill_min_factor")?;
        non_negative(self.flow_min_gap_fraction, "flow_min_gap_fraction")?;
        if !self.seam_angle_deg.is_finite() {
            return Err(setting_error("seam_angle_deg", "must be finite".into()));
        }
        if !(0.0..180.0).contains(&self.seam_corner_min_deg) {
            return Err(setting_error(
                "seam_corner_min_deg",
                format!("must be in [0, 180), got {}", self.seam_corner_min_deg),
            ));
        }
        if let Some(n) = self.syringes {
            if n == 0 || n > MAX_SYRINGES {
                return Err(setting_error(
                    "syringes",
                    format!("must be 1 to {MAX_SYRINGES}, got {n}"),
                ));
            }
        }
        Ok(())
    }

    /// The mixing chamber: `mixer_model` through V_dead.
    pub fn mixer(&self) -> MixerOptions {
        MixerOptions {
            model: self.mixer_model,
            volume_nl: self.v_dead_ul * 1000.0,
            peclet: self.mixer_peclet,
        }
    }

    /// Whether extrusion moves are commanded through the mixer's feed-forward inverse.
    pub fn feed_forward(&self) -> bool {
        self.mixing_lead
            && self.mixer_feed_forward
            && self.mixer_model != MixerModel::Plug
            && self.v_dead_ul > 0.0
    }

    /// The toolpath module's share of the settings.
    pub fn order_settings(&self) -> OrderSettings {
        OrderSettings {
            seam: self.seam,
            seam_angle_deg: self.seam_angle_deg,
            seam_corner_min_deg: self.seam_corner_min_deg,
            sub_region_order: self.sub_region_order,
        }
    }
}

/// What carries over between layers of one job. Create with [`StreamState::new`], pass to
/// every [`layer_moves`] call in layer order; never share between jobs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StreamState {
    /// Nozzle position, mm; `None` before the first move.
    position: Option<DVec3>,
    /// Volumes retracted and not yet primed back, per syringe (nl); empty when pressurised.
    retracted_nl: Vec<u32>,
    /// Exact planned extrusion per syringe so far (nl).
    planned_nl: Vec<f64>,
    /// Commanded extrusion per syringe so far (nl): `planned_nl` rounded.
    commanded_nl: Vec<u64>,
    /// Layers done.
    layers: u32,
    /// The mixing chamber; `None` before the first extrusion.
    chamber: Option<Mixer>,
}

impl StreamState {
    /// A fresh job: nozzle position unknown, syringes pressurised, nothing extruded.
    pub fn new() -> Self {
        Self::default()
    }

    /// Nozzle position after the last move, mm.
    pub fn position_mm(&self) -> Option<DVec3> {
        self.position
    }

    /// Exact planned extrusion per syringe over the layers so far, nl.
    pub fn planned_nl(&self) -> &[f64] {
        &self.planned_nl
    }

    /// Commanded extrusion per syringe over the layers so far (the sum of the Extrude
    /// moves' volumes), nl.
    pub fn commanded_nl(&self) -> &[u64] {
        &self.commanded_nl
    }

    /// Whether the syringes are retracted (extrusion ceased).
    pub fn is_retracted(&self) -> bool {
        !self.retracted_nl.is_empty()
    }

    /// Layers processed.
    pub fn layers(&self) -> u32 {
        self.layers
    }
}

/// Per-layer figures.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LayerStats {
    pub layer: usize,
    pub paths: usize,
    pub moves: usize,
    pub extrude_moves: usize,
    pub travels: usize,
    pub retracts: usize,
    /// Length of road built, mm.
    pub extruded_mm: f64,
    /// Travel length, mm.
    pub travel_mm: f64,
    /// Closed loops whose seam sits at a concave corner.
    pub seams_at_corners: usize,
    pub closed_loops: usize,
    /// Exact planned volume per syringe in this layer, nl.
    pub planned_nl: Vec<f64>,
    /// Commanded volume per syringe in this layer (sum of Extrude moves), nl.
    pub commanded_nl: Vec<u64>,
    /// Largest width factor used.
    pub max_width_factor: f64,
    /// Designed-versus-delivered composition under plug flow through V_dead: volume-
    /// weighted mean of the largest per-material difference, and its maximum over moves.
    pub composition_error_mean: f64,
    pub composition_error_max: f64,
    /// Volume purged before the layer (all syringes), nl; 0 when no purge was needed.
    pub purge_nl: f64,
    /// The same error road by road (what is predicted to leave the nozzle over each
    /// road against its design): volume-weighted mean and worst road.
    pub composition_error_road_mean: f64,
    pub composition_error_road_max: f64,
    /// Roads whose error exceeds `mixer_tolerance`: how many, and the worst
    /// ([`mixing::MAX_LISTED`] at most, worst first).
    pub mixer_limited_roads: usize,
    pub mixer_limited: Vec<MixerLimit>,
}

/// One layer's moves, stats, and the paths they build (for previews and checks).
#[derive(Clone, Debug, PartialEq)]
pub struct LayerMoves {
    pub moves: Vec<Move>,
    pub stats: LayerStats,
    pub paths: Vec<ToolPath>,
    /// Index of the next move (`first_index + moves.len()`).
    pub next_index: u32,
    /// For every extrusion move: its index and the path in `paths` it builds (whose
    /// composition is the designed one there), to compare with what was built.
    pub extrusion_paths: Vec<(u32, u32)>,
    /// For every extrusion move (as `extrusion_paths`): the composition the chamber's
    /// model predicts leaves the nozzle during it (per material; the commanded one
    /// where there is no chamber).
    pub extrusion_exits: Vec<Vec<f64>>,
}

/// The ordered, flow-adjusted paths of a layer (steps 1–4 of [`crate::toolpath`]).
pub fn layer_paths(
    layer: &LayerPlan,
    settings: &ProcessSettings,
    state: &StreamState,
) -> Vec<ToolPath> {
    let start = state.position.map(|p| p.truncate());
    let paths = toolpath::fill_order(layer, &settings.order_settings(), start).paths;
    finish_paths(layer, settings, paths)
}

/// What [`layer_paths`] does after the ordering (flow raise, slanted ends, gap fill) to
/// the paths as [`toolpath::fill_order`] ordered them: a function of those paths alone.
fn finish_paths(
    layer: &LayerPlan,
    settings: &ProcessSettings,
    mut paths: Vec<ToolPath>,
) -> Vec<ToolPath> {
    if settings.flow_raise {
        toolpath::flow::raise(
            &mut paths,
            &toolpath::flow::FlowSettings {
                road_width_mm: settings.road_width(),
                max_flow_factor: settings.max_flow_factor,
                min_gap_fraction: settings.flow_min_gap_fraction,
                min_flow_factor: settings.min_flow_factor,
            },
            &layer.islands,
        );
    }
    if settings.gap_fill {
        let w = settings.road_width();
        toolpath::ends::continue_slanted_ends(
            &mut paths,
            &toolpath::ends::EndSettings {
                road_width_mm: w,
                min_width_mm: w * settings.gap_fill_min_factor,
            },
            &layer.islands,
        );
        let fill = toolpath::gapfill::gap_fill(
            &layer.islands,
            &paths,
            &toolpath::gapfill::GapFillSettings {
                road_width_mm: w,
                min_width_mm: w * settings.gap_fill_min_factor,
                max_width_mm: w * settings.max_flow_factor,
            },
        );
        paths = toolpath::gapfill::insert(paths, fill);
    }
    add_support_roads(layer, settings, &mut paths);
    if let Some(n) = settings.channels() {
        pad_compositions(&mut paths, n);
    }
    paths
}

/// The layer's support roads after the part's, from where they end.
fn add_support_roads(layer: &LayerPlan, settings: &ProcessSettings, paths: &mut Vec<ToolPath>) {
    let Some(roads) = &settings.support else {
        return;
    };
    if layer.support.is_empty() {
        return;
    }
    let start = paths.last().map(ToolPath::end);
    paths.extend(toolpath::support::support_paths(
        &layer.support,
        layer.index,
        settings.road_width(),
        roads,
        start,
    ));
}

/// Every composition given `n` fractions: a part planned from fewer materials than
/// the machine has syringes (its support syringe) gets 0 of the rest.
fn pad_compositions(paths: &mut [ToolPath], n: usize) {
    for p in paths {
        if p.composition.len() < n {
            p.composition.resize(n, 0.0);
        }
    }
}

/// A job's first move: it homes (`G28` in G-code), as every job edod streams and every
/// file `edoctl plan --gcode` writes does. Its index is 0; the layers' moves are
/// numbered from [`FIRST_LAYER_MOVE_INDEX`].
pub fn home_move(job_id: u32) -> Move {
    Move {
        job_id,
        index: 0,
        kind: MoveKind::Home,
    }
}

/// The index of a job's first layer move, after [`home_move`].
pub const FIRST_LAYER_MOVE_INDEX: u32 = 1;

/// Turn one planned layer into machine moves numbered from `first_index`, continuing
/// from `state` (see the module doc).
pub fn layer_moves(
    layer: &LayerPlan,
    settings: &ProcessSettings,
    job_id: u32,
    first_index: u32,
    state: &mut StreamState,
) -> Result<LayerMoves, PipelineError> {
    settings.validate()?;
    let paths = layer_paths(layer, settings, state);
    moves_for_paths(layer, paths, settings, job_id, first_index, state)
}

/// Every layer of a job to moves, the same as [`layer_moves`] on each in order (moves
/// numbered from `first_index`, `state` carried through), with the layers' flow raise,
/// slanted ends and gap fill (most of the work) on all cores.
///
/// Those steps depend on the nozzle position before the layer only through the order
/// [`toolpath::fill_order`] gives the paths, and that ordering is cheap. So each layer is
/// first ordered from a guess of where the last layer ends (the end of its ordered last
/// path), the layers are finished in parallel, and then, in order, each is ordered again
/// from where the moves really left the nozzle: where that gives the same paths, the
/// finished ones are used, otherwise the layer is finished again there. The result is
/// that of the serial loop whatever the guesses.
pub fn job_layer_moves(
    layers: &[LayerPlan],
    settings: &ProcessSettings,
    job_id: u32,
    first_index: u32,
    state: &mut StreamState,
) -> Result<Vec<LayerMoves>, PipelineError> {
    let mut out = Vec::with_capacity(layers.len());
    for_each_layer_moves(
        layers,
        settings,
        (job_id, first_index),
        state,
        layers.len(),
        |_, lm| {
            out.push(lm);
            Ok::<(), PipelineError>(())
        },
    )?;
    Ok(out)
}

/// [`job_layer_moves`] `batch_layers` layers at a time, each layer's moves handed to
/// `each` in order as soon as its batch is finished: memory holds one batch's paths and
/// moves, not the job's (a G-code file of a tall part is written as it is planned).
/// The moves are the same whatever the batch size.
pub fn for_each_layer_moves<E: From<PipelineError>>(
    layers: &[LayerPlan],
    settings: &ProcessSettings,
    (job_id, first_index): (u32, u32),
    state: &mut StreamState,
    batch_layers: usize,
    mut each: impl FnMut(&LayerPlan, LayerMoves) -> Result<(), E>,
) -> Result<(), E> {
    settings.validate()?;
    let order = settings.order_settings();
    let mut next = first_index;
    for batch in layers.chunks(batch_layers.max(1)) {
        let mut at = state.position.map(|p| p.truncate());
        let guessed = batch
            .iter()
            .map(|l| {
                let paths = toolpath::fill_order(l, &order, at).paths;
                at = paths.last().map(ToolPath::end).or(at);
                paths
            })
            .collect();
        let mut layer = batch.iter();
        moves_from_guesses(batch, settings, (job_id, next), state, guessed, |lm| {
            next = lm.next_index;
            match layer.next() {
                Some(l) => each(l, lm),
                None => Ok(()),
            }
        })?;
    }
    Ok(())
}

/// [`for_each_layer_moves`] from the layers' paths as ordered from a guessed start
/// (moves of job `start.0` numbered from `start.1`); how many layers had to be finished
/// again (their order from the real start differed).
fn moves_from_guesses<E: From<PipelineError>>(
    layers: &[LayerPlan],
    settings: &ProcessSettings,
    (job_id, first_index): (u32, u32),
    state: &mut StreamState,
    guessed: Vec<Vec<ToolPath>>,
    mut each: impl FnMut(LayerMoves) -> Result<(), E>,
) -> Result<usize, E> {
    use rayon::prelude::*;
    let order = settings.order_settings();
    let finished: Vec<Vec<ToolPath>> = layers
        .par_iter()
        .zip(&guessed)
        .map(|(l, paths)| finish_paths(l, settings, paths.clone()))
        .collect();
    let (mut next, mut again) = (first_index, 0);
    for ((l, guess), done) in layers.iter().zip(guessed).zip(finished) {
        let start = state.position.map(|p| p.truncate());
        let ordered = toolpath::fill_order(l, &order, start).paths;
        let paths = if ordered == guess {
            done
        } else {
            again += 1;
            finish_paths(l, settings, ordered)
        };
        let lm = moves_for_paths(l, paths, settings, job_id, next, state)?;
        next = lm.next_index;
        each(lm)?;
    }
    Ok(again)
}

/// Moves for already ordered paths (what [`layer_moves`] does after ordering).
pub fn moves_for_paths(
    layer: &LayerPlan,
    paths: Vec<ToolPath>,
    settings: &ProcessSettings,
    job_id: u32,
    first_index: u32,
    state: &mut StreamState,
) -> Result<LayerMoves, PipelineError> {
    let syringes = syringe_count(layer, &paths, settings, state)?;
    let paths = roads_as_moves(&paths, settings, layer.thickness_mm);
    if state.planned_nl.len() < syringes {
        state.planned_nl.resize(syringes, 0.0);
        state.commanded_nl.resize(syringes, 0);
    }
    let planned_before = state.planned_nl.clone();
    let commanded_before = state.commanded_nl.clone();
    let mut b = Builder::new(layer, settings, job_id, first_index, state);
    let designed = designed_stream(&paths, settings, layer.thickness_mm);
    b.push(MoveKind::LayerMark {
        layer: layer.index as u32,
        z_um: to_um(layer.z_mm),
    })?;
    b.purge_if_needed(&designed)?;
    b.commanded = commanded_compositions(&designed, settings);
    if settings.feed_forward() {
        if let Some(first) = designed.first() {
            let opts = settings.mixer();
            let chamber = b
                .state
                .chamber
                .clone()
                .unwrap_or_else(|| Mixer::new(&opts, first.1));
            let lead = std::mem::take(&mut b.commanded);
            b.commanded = crate::mixer::inverse::feed_forward(&opts, &chamber, &designed, lead);
        }
    }
    for (i, p) in paths.iter().enumerate() {
        b.path_index = i as u32;
        b.support_path = p.role.is_support();
        b.path(p)?;
    }
    Ok(b.finish(paths, &planned_before, &commanded_before))
}

/// The syringes the layer's paths are mixed from: the settings' count, else the
/// compositions' length, else the stream's so far; every path must have that many.
fn syringe_count(
    layer: &LayerPlan,
    paths: &[ToolPath],
    settings: &ProcessSettings,
    state: &StreamState,
) -> Result<usize, PipelineError> {
    let syringes = match (settings.syringes, paths.first()) {
        (Some(n), _) => n,
        (None, Some(p)) => p.composition.len(),
        (None, None) => state.planned_nl.len().max(1),
    };
    for p in paths {
        if p.composition.len() != syringes {
            return Err(PipelineError::Syringes {
                layer: layer.index,
                expected: syringes,
                got: p.composition.len(),
            });
        }
    }
    Ok(syringes)
}

fn setting_error(field: &'static str, message: String) -> PipelineError {
    PipelineError::Setting { field, message }
}

/// A setting that must be a positive number.
fn positive(v: f64, field: &'static str) -> Result<(), PipelineError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(setting_error(
            field,
            format!("must be a positive number, got {v}"),
        ))
    }
}

/// A setting that must be 0 or more.
fn non_negative(v: f64, field: &'static str) -> Result<(), PipelineError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(setting_error(field, format!("must be 0 or more, got {v}")))
    }
}

/// A setting that must be in (0, 1].
fn fraction(v: f64, field: &'static str) -> Result<(), PipelineError> {
    if v.is_finite() && v > 0.0 && v <= 1.0 {
        Ok(())
    } else {
        Err(setting_error(
            field,
            format!("must be more than 0 and at most 1, got {v}"),
        ))
    }
}

fn to_um(mm: f64) -> i32 {
    (mm * 1000.0).round() as i32
}

/// Points beyond this (mm) do not fit the wire's i32 micrometres.
const MAX_COORD_MM: f64 = 2.0e6;

struct Builder<'a> {
    layer: usize,
    job_id: u32,
    next: u32,
    moves: Vec<Move>,
    stats: LayerStats,
    state: &'a mut StreamState,
    settings: &'a ProcessSettings,
    z_mm: f64,
    /// Road cross-section at nominal width, mm².
    section_mm2: f64,
    /// Commanded composition per extrusion segment of the layer, in order.
    commanded: Vec<Vec<f64>>,
    segment: usize,
    error_volume_nl: f64,
    /// Index in the layer's paths of the path being built.
    path_index: u32,
    /// Whether that path builds support (left out of the part's composition figures).
    support_path: bool,
    /// What is predicted to leave the nozzle over each road.
    road_exits: mixing::RoadExits,
    extrusion_paths: Vec<(u32, u32)>,
    extrusion_exits: Vec<Vec<f64>>,
}

impl<'a> Builder<'a> {
    /// A builder for `layer`'s moves from index `first_index` on.
    fn new(
        layer: &LayerPlan,
        settings: &'a ProcessSettings,
        job_id: u32,
        first_index: u32,
        state: &'a mut StreamState,
    ) -> Self {
        Builder {
            layer: layer.index,
            job_id,
            next: first_index,
            moves: Vec::new(),
            stats: LayerStats {
                layer: layer.index,
                max_width_factor: 0.0,
                ..Default::default()
            },
            state,
            settings,
            z_mm: layer.z_mm,
            section_mm2: settings.road_width() * layer.thickness_mm,
            commanded: Vec::new(),
            segment: 0,
            error_volume_nl: 0.0,
            path_index: 0,
            support_path: false,
            road_exits: mixing::RoadExits::default(),
            extrusion_paths: Vec::new(),
            extrusion_exits: Vec::new(),
        }
    }

    /// The layer's moves and statistics once every path is built: the volumes planned
    /// and commanded in this layer are the stream's totals less those `*_before` it.
    fn finish(
        mut self,
        paths: Vec<ToolPath>,
        planned_before: &[f64],
        commanded_before: &[u64],
    ) -> LayerMoves {
        self.stats.paths = paths.len();
        self.stats.moves = self.moves.len();
        self.stats.planned_nl = self
            .state
            .planned_nl
            .iter()
            .zip(planned_before)
            .map(|(a, c)| a - c)
            .collect();
        self.stats.commanded_nl = self
            .state
            .commanded_nl
            .iter()
            .zip(commanded_before)
            .map(|(a, c)| a - c)
            .collect();
        if self.error_volume_nl > 0.0 {
            self.stats.composition_error_mean /= self.error_volume_nl;
        }
        let (mean, max, limited, count) = self
            .road_exits
            .summarise(&paths, self.settings.mixer_tolerance);
        self.stats.composition_error_road_mean = mean;
        self.stats.composition_error_road_max = max;
        self.stats.mixer_limited = limited;
        self.stats.mixer_limited_roads = count;
        self.state.layers += 1;
        LayerMoves {
            moves: self.moves,
            stats: self.stats,
            paths,
            next_index: self.next,
            extrusion_paths: self.extrusion_paths,
            extrusion_exits: self.extrusion_exits,
        }
    }
}

/// How far from a road, in road widths, the vertices of the roads merged before it are
/// its stations (`toolpath::merge::Stations`): its neighbours', not the roads' beyond.
const STATION_REACH_ROADS: f64 = 1.25;

/// The edges the layer's paths are built with: merged within `move_deviation_mm` (edges
/// longer than a road width leaning less; in phase with the roads merged before) and
/// `move_width_tolerance` (`toolpath::merge`), then split where the mixing lead's commanded composition changes
/// so that no move straddles such a change (a merged edge would blend the two
/// compositions over its whole length).
fn roads_as_moves(paths: &[ToolPath], s: &ProcessSettings, h_mm: f64) -> Vec<ToolPath> {
    let merge = toolpath::merge::MergeOptions::within(s.move_deviation_mm)
        .with_width_tolerance(s.move_width_tolerance)
        .with_full_deviation_length(s.road_width());
    // Each road ends its merged edges where it can at the feet of the vertices its
    // neighbours kept, so neighbouring roads' chords cut their curves in phase.
    let mut stations = toolpath::merge::Stations::new(STATION_REACH_ROADS * s.road_width());
    let mut merged: Vec<ToolPath> = Vec::with_capacity(paths.len());
    for p in paths {
        if p.role.is_support() {
            merged.push(toolpath::merge::merge_edges(p, &merge));
            continue;
        }
        let m = toolpath::merge::merge_edges_in_phase(p, &merge, &stations);
        stations.add(&m);
        merged.push(m);
    }
    let lead = s.v_dead_ul * 1000.0;
    if s.mixing_lead && lead > 0.0 {
        let mut at = lead_changes_nl(&merged, s, h_mm, lead);
        if s.feed_forward() {
            at = with_every_volume(
                at,
                &merged,
                s,
                h_mm,
                lead / crate::mixer::inverse::CELLS_PER_VOLUME,
            );
        }
        split_at_volumes(&mut merged, &at, s, h_mm);
    }
    merged
}

/// Where (stream volume, nl) the commanded composition changes under the mixing lead:
/// V_dead before each change of the designed composition.
fn lead_changes_nl(paths: &[ToolPath], s: &ProcessSettings, h_mm: f64, lead: f64) -> Vec<f64> {
    let segs = designed_stream(paths, s, h_mm);
    let mut at = 0.0;
    let mut out = Vec::new();
    for w in segs.windows(2) {
        at += w[0].0;
        if w[0].1 != w[1].1 && at - lead > 0.0 {
            out.push(at - lead);
        }
    }
    out
}

/// `at` (sorted) with every multiple of `step_nl` within the layer's stream added, so no
/// move is longer than `step_nl` once split there.
fn with_every_volume(
    mut at: Vec<f64>,
    paths: &[ToolPath],
    s: &ProcessSettings,
    h_mm: f64,
    step_nl: f64,
) -> Vec<f64> {
    let total: f64 = designed_stream(paths, s, h_mm).iter().map(|x| x.0).sum();
    if step_nl > 0.0 && total.is_finite() {
        let n = (total / step_nl).floor() as usize;
        at.extend((1..=n).map(|k| k as f64 * step_nl));
        at.sort_by(f64::total_cmp);
    }
    at
}

/// Insert a vertex into the edge holding each stream volume in `at_nl` (sorted), where
/// the volume before it is exactly that; the new vertex's width factor is interpolated,
/// so the edge deposits what it did. Volumes within 0.01 nl of a vertex are left.
fn split_at_volumes(paths: &mut [ToolPath], at_nl: &[f64], s: &ProcessSettings, h_mm: f64) {
    let section = s.road_width() * h_mm * 1000.0;
    let mut next = at_nl.iter().copied().peekable();
    let mut start = 0.0;
    for p in paths.iter_mut() {
        let mut k = 0;
        while p.points.len() >= 2 && k < edge_count(p) {
            let n = p.points.len();
            let (a, b) = (p.points[k], p.points[(k + 1) % n]);
            let (wa, wb) = (p.width_factors[k], p.width_factors[(k + 1) % n]);
            let len = a.distance(b);
            let v = len * section * 0.5 * (wa + wb);
            if len <= 0.0 {
                k += 1;
                continue;
            }
            while next.peek().is_some_and(|&x| x <= start + 0.01) {
                next.next();
            }
            match next.peek() {
                Some(&x) if x < start + v - 0.01 => {
                    let t = fraction_at_volume(x - start, len * section, wa, wb);
                    p.points.insert(k + 1, a.lerp(b, t));
                    p.width_factors.insert(k + 1, wa + (wb - wa) * t);
                    next.next();
                    start = x;
                }
                _ => start += v,
            }
            k += 1;
        }
    }
}

fn edge_count(p: &ToolPath) -> usize {
    if p.closed {
        p.points.len()
    } else {
        p.points.len() - 1
    }
}

/// The fraction t of an edge at which `v` of its volume has been laid, the width
/// factor going linearly from `wa` to `wb` (`full` = volume per unit factor).
fn fraction_at_volume(v: f64, full: f64, wa: f64, wb: f64) -> f64 {
    // v = full · (wa·t + (wb − wa)·t²/2)
    let (qa, qb, qc) = (0.5 * (wb - wa) * full, wa * full, -v);
    let t = if qa.abs() < 1e-12 * qb.abs().max(1e-300) {
        -qc / qb
    } else {
        (-qb + (qb * qb - 4.0 * qa * qc).max(0.0).sqrt()) / (2.0 * qa)
    };
    t.clamp(0.0, 1.0)
}

/// The designed extrusion stream of a layer: (volume nl, composition) per extrusion
/// segment, in building order.
fn designed_stream<'p>(
    paths: &'p [ToolPath],
    s: &ProcessSettings,
    h_mm: f64,
) -> Vec<(f64, &'p [f64])> {
    let section = s.road_width() * h_mm * 1000.0;
    let mut segs: Vec<(f64, &[f64])> = Vec::new();
    for p in paths {
        let n = p.points.len();
        if n < 2 {
            continue;
        }
        let edges = if p.closed { n } else { n - 1 };
        for k in 0..edges {
            let len = p.points[k].distance(p.points[(k + 1) % n]);
            if len <= 0.0 {
                continue;
            }
            let f = 0.5 * (p.width_factors[k] + p.width_factors[(k + 1) % n]);
            segs.push((len * section * f, &p.composition));
        }
    }
    segs
}

/// Walks a designed stream by volume: the composition over successive windows.
struct StreamWindow<'s, 'p> {
    segs: &'s [(f64, &'p [f64])],
    /// First segment that may overlap the next window, and the volume before it.
    j: usize,
    j_start: f64,
}

impl<'s, 'p> StreamWindow<'s, 'p> {
    fn new(segs: &'s [(f64, &'p [f64])]) -> Self {
        StreamWindow {
            segs,
            j: 0,
            j_start: 0.0,
        }
    }

    /// Volume-weighted designed composition over [w0, w1) (windows in increasing
    /// order); past the stream's end its last composition is held (`fallback` when the
    /// stream is empty).
    fn over(&mut self, w0: f64, w1: f64, fallback: &[f64]) -> Vec<f64> {
        let segs = self.segs;
        while self.j < segs.len() && self.j_start + segs[self.j].0 <= w0 {
            self.j_start += segs[self.j].0;
            self.j += 1;
        }
        let v = w1 - w0;
        let mut acc = vec![0.0; fallback.len()];
        let mut got = 0.0;
        let (mut q, mut q_start) = (self.j, self.j_start);
        while q < segs.len() && q_start < w1 {
            let a = q_start.max(w0);
            let b = (q_start + segs[q].0).min(w1);
            if b > a {
                for (x, y) in acc.iter_mut().zip(segs[q].1) {
                    *x += (b - a) * y;
                }
                got += b - a;
            }
            q_start += segs[q].0;
            q += 1;
        }
        let rest = v - got;
        if rest > 0.0 {
            let last = segs.last().map(|s| s.1).unwrap_or(fallback);
            for (x, y) in acc.iter_mut().zip(last) {
                *x += rest * y;
            }
        }
        if v > 0.0 {
            acc.iter().map(|x| x / v).collect()
        } else {
            fallback.to_vec()
        }
    }
}

/// The composition to command on each extrusion segment of a layer: with the mixing lead,
/// the designed composition V_dead of extrusion later (volume-weighted over the segment's
/// window), so it reaches the nozzle exit where designed; past the layer's last road the
/// last designed composition (the next layer is not known here). Without the lead, the
/// designed composition.
fn commanded_compositions(segs: &[(f64, &[f64])], s: &ProcessSettings) -> Vec<Vec<f64>> {
    let lead = s.v_dead_ul * 1000.0;
    if !(s.mixing_lead && lead > 0.0) {
        return segs.iter().map(|(_, c)| c.to_vec()).collect();
    }
    let mut window = StreamWindow::new(segs);
    let mut start = 0.0;
    segs.iter()
        .map(|(v, c)| {
            let out = window.over(start + lead, start + lead + v, c);
            start += v;
            out
        })
        .collect()
}

/// How far the chamber's content (front first, V_dead in all) is from the designed
/// stream's first V_dead: the largest per-material difference over the volume they share.
fn chamber_mismatch(chamber: &[(f64, Vec<f64>)], segs: &[(f64, &[f64])]) -> f64 {
    let mut window = StreamWindow::new(segs);
    let mut at = 0.0;
    let mut worst: f64 = 0.0;
    for (v, c) in chamber {
        if *v <= 0.0 {
            continue;
        }
        let want = window.over(at, at + v, c);
        at += v;
        let err = crate::material::max_fraction_difference(&want, c);
        worst = worst.max(err);
    }
    worst
}

/// The purge pad's road: a zig-zag from `corner` along +x, one road width apart in +y,
/// `length_mm` long, within a square of `side_mm` (wrapping back to the corner when the
/// pad is full).
fn purge_zigzag(corner: DVec2, side_mm: f64, spacing_mm: f64, length_mm: f64) -> Vec<DVec2> {
    let rows = ((side_mm / spacing_mm).floor() as usize).max(1);
    let mut points = vec![corner];
    let mut left = length_mm;
    let mut row = 0usize;
    while left > 1e-9 {
        let y = corner.y + (row % rows) as f64 * spacing_mm;
        let forward = row.is_multiple_of(2);
        let (x0, x1) = if forward {
            (corner.x, corner.x + side_mm)
        } else {
            (corner.x + side_mm, corner.x)
        };
        let here = *points.last().unwrap_or(&corner);
        // Step over to this row's start.
        let start = DVec2::new(x0, y);
        let step = here.distance(start);
        if step > 1e-9 {
            if step >= left {
                points.push(here.lerp(start, left / step));
                break;
            }
            points.push(start);
            left -= step;
        }
        let run = (x1 - x0).abs();
        if run >= left {
            points.push(start.lerp(DVec2::new(x1, y), left / run));
            break;
        }
        points.push(DVec2::new(x1, y));
        left -= run;
        row += 1;
    }
    points
}

impl Builder<'_> {
    fn push(&mut self, mut kind: MoveKind) -> Result<(), PipelineError> {
        if let Some(syringe_of) = &self.settings.syringe_of_material {
            to_syringe_order(&mut kind, syringe_of);
        }
        let index = self.next;
        self.next = self
            .next
            .checked_add(1)
            .ok_or(PipelineError::IndexOverflow { layer: self.layer })?;
        self.moves.push(Move {
            job_id: self.job_id,
            index,
            kind,
        });
        Ok(())
    }

    fn position(&self, p: DVec2) -> Result<PositionUm, PipelineError> {
        let ok = |v: f64| v.is_finite() && v.abs() < MAX_COORD_MM;
        if !(ok(p.x) && ok(p.y) && ok(self.z_mm)) {
            return Err(PipelineError::OutOfRange {
                layer: self.layer,
                x_mm: p.x,
                y_mm: p.y,
                z_mm: self.z_mm,
            });
        }
        Ok(PositionUm {
            x_um: to_um(p.x),
            y_um: to_um(p.y),
            z_um: to_um(self.z_mm),
        })
    }

    fn feed(mm_s: f64) -> u32 {
        (mm_s * 1000.0).round().clamp(1.0, u32::MAX as f64) as u32
    }

    /// Extrusion cessation and travel to `to` (nothing when already there).
    fn travel_to(&mut self, to: DVec2, composition: &[f64]) -> Result<(), PipelineError> {
        let target = DVec3::new(to.x, to.y, self.z_mm);
        let here = self.state.position;
        if let Some(h) = here {
            if h.distance(target) <= 1e-4 {
                return Ok(());
            }
        }
        let distance = here.map_or(0.0, |h| h.truncate().distance(to));
        let s = self.settings;
        let cease = here.is_some() && distance >= s.retract_min_travel_mm && s.retract_nl > 0;
        if cease && !self.state.is_retracted() {
            let ratios = crate::machine::ratios_from_fractions(composition).unwrap_or_default();
            let volumes = crate::machine::split_volume_nl(s.retract_nl, &ratios);
            self.push(MoveKind::Retract {
                volumes_nl: volumes.clone(),
                duration_ms: s.retract_ms,
            })?;
            self.state.retracted_nl = volumes;
            self.stats.retracts += 1;
        }
        let pos = self.position(to)?;
        self.push(MoveKind::Travel {
            to: pos,
            feed_um_s: Self::feed(s.travel_feed_mm_s),
        })?;
        self.stats.travels += 1;
        self.stats.travel_mm += distance;
        self.state.position = Some(target);
        Ok(())
    }

    /// Re-prime (and dwell) after a cessation, before extruding.
    fn pressurise(&mut self) -> Result<(), PipelineError> {
        if self.state.is_retracted() {
            let volumes = std::mem::take(&mut self.state.retracted_nl);
            self.push(MoveKind::Prime {
                volumes_nl: volumes,
                duration_ms: self.settings.prime_ms,
            })?;
            if self.settings.dwell_ms > 0 {
                self.push(MoveKind::Dwell {
                    duration_ms: self.settings.dwell_ms,
                })?;
            }
        }
        Ok(())
    }

    fn path(&mut self, p: &ToolPath) -> Result<(), PipelineError> {
        if p.points.len() < 2 {
            return Ok(());
        }
        self.travel_to(p.points[0], &p.composition)?;
        self.pressurise()?;
        let n = p.points.len();
        let edges = if p.closed { n } else { n - 1 };
        for k in 0..edges {
            let (a, b) = (p.points[k], p.points[(k + 1) % n]);
            let f = 0.5 * (p.width_factors[k] + p.width_factors[(k + 1) % n]);
            self.extrude(a, b, f, &p.composition)?;
        }
        if p.closed {
            self.stats.closed_loops += 1;
            if p.seam_at_corner {
                self.stats.seams_at_corners += 1;
            }
        }
        Ok(())
    }

    /// Before the layer's first road: a purge at `purge_xy_mm` where the chamber does
    /// not hold what the layer starts with (and a purge position is set). Under plug
    /// flow the pad's segments are commanded the designed stream's window [0, V_dead)
    /// in order, so after it the chamber holds exactly that. Through another mixer the
    /// pad pushes the layer's first designed composition for the model's washout
    /// ([`purge::washout_nl`]), so after it the chamber holds that within
    /// `purge_min_error`.
    fn purge_if_needed(&mut self, designed: &[(f64, &[f64])]) -> Result<(), PipelineError> {
        let s = self.settings;
        let dead = s.v_dead_ul * 1000.0;
        let (Some([x, y]), Some(chamber), Some(first)) = (
            s.purge_xy_mm,
            self.state.chamber.as_ref(),
            designed.first().map(|d| d.1),
        ) else {
            return Ok(());
        };
        let plug = s.mixer_model == MixerModel::Plug;
        let volume_nl = if !(s.mixing_lead && dead > 0.0) {
            0.0
        } else if plug {
            if chamber_mismatch(&chamber.contents(), designed) <= s.purge_min_error {
                0.0
            } else {
                dead
            }
        } else {
            purge::washout_nl(chamber, &s.mixer(), first, s.purge_min_error)
        };
        let section_nl_per_mm = self.section_mm2 * 1000.0;
        let pad_mm = volume_nl / section_nl_per_mm;
        if !(volume_nl > 0.0 && section_nl_per_mm > 0.0 && pad_mm.is_finite()) {
            return Ok(());
        }
        let points = purge_zigzag(DVec2::new(x, y), s.purge_pad_mm, s.road_width(), pad_mm);
        self.travel_to(points[0], first)?;
        self.pressurise()?;
        let mut window = StreamWindow::new(designed);
        let mut at = 0.0;
        for w in points.windows(2) {
            let v = w[0].distance(w[1]) * section_nl_per_mm;
            if v <= 0.0 {
                continue;
            }
            let commanded = if plug {
                window.over(at, at + v, first)
            } else {
                first.to_vec()
            };
            at += v;
            self.push_through_chamber(v, &commanded);
            self.extrude_move(w[1], 1.0, v, &commanded)?;
            self.stats.purge_nl += v;
        }
        Ok(())
    }

    /// Push `volume_nl` of `commanded` into the chamber; what leaves the nozzle, or
    /// none without a chamber.
    fn push_through_chamber(&mut self, volume_nl: f64, commanded: &[f64]) -> Option<Vec<f64>> {
        if self.settings.v_dead_ul <= 0.0 || volume_nl <= 0.0 {
            return None;
        }
        self.state.chamber.as_mut()?.push(volume_nl, commanded)
    }

    /// Add `volume_nl` of `composition` to the job's planned and commanded totals; the
    /// move's per-syringe volumes (cumulatively rounded).
    fn account(&mut self, volume_nl: f64, composition: &[f64]) -> Vec<u32> {
        let mut volumes = Vec::with_capacity(composition.len());
        for (k, f) in composition.iter().enumerate() {
            self.state.planned_nl[k] += volume_nl * f.max(0.0);
            let target = self.state.planned_nl[k].round().max(0.0) as u64;
            let v = target.saturating_sub(self.state.commanded_nl[k]);
            self.state.commanded_nl[k] += v;
            volumes.push(v.min(u64::from(u32::MAX)) as u32);
        }
        volumes
    }

    /// Push `volume_nl` of `commanded` through the chamber; compare what leaves the
    /// nozzle with `designed`; what leaves it.
    fn through_chamber(&mut self, volume_nl: f64, commanded: &[f64], designed: &[f64]) -> Vec<f64> {
        if self.settings.v_dead_ul > 0.0 && self.state.chamber.is_none() {
            // A fresh chamber is full of the first designed composition (primed).
            self.state.chamber = Some(Mixer::new(&self.settings.mixer(), designed));
        }
        let delivered = self
            .push_through_chamber(volume_nl, commanded)
            .unwrap_or_else(|| commanded.to_vec());
        if self.support_path {
            return delivered;
        }
        self.road_exits.add(self.path_index, volume_nl, &delivered);
        let err = crate::material::max_fraction_difference(&delivered, designed);
        self.stats.composition_error_mean += err * volume_nl;
        self.error_volume_nl += volume_nl;
        self.stats.composition_error_max = self.stats.composition_error_max.max(err);
        delivered
    }

    fn extrude(
        &mut self,
        a: DVec2,
        b: DVec2,
        factor: f64,
        composition: &[f64],
    ) -> Result<(), PipelineError> {
        let len = a.distance(b);
        if len <= 0.0 {
            return Ok(());
        }
        let volume_nl = len * self.section_mm2 * factor * 1000.0;
        let commanded = self
            .commanded
            .get(self.segment)
            .cloned()
            .unwrap_or_else(|| composition.to_vec());
        self.segment += 1;
        let delivered = self.through_chamber(volume_nl, &commanded, composition);
        self.extrude_move(b, factor, volume_nl, &commanded)?;
        self.extrusion_paths
            .push((self.next.saturating_sub(1), self.path_index));
        self.extrusion_exits.push(delivered);
        self.stats.extruded_mm += len;
        self.stats.max_width_factor = self.stats.max_width_factor.max(factor);
        Ok(())
    }

    /// The `Extrude` move to `b` pushing `volume_nl` of `commanded` (accounted in the
    /// job's totals), at the print feed; the nozzle ends at `b`.
    fn extrude_move(
        &mut self,
        b: DVec2,
        factor: f64,
        volume_nl: f64,
        commanded: &[f64],
    ) -> Result<(), PipelineError> {
        let volumes = self.account(volume_nl, commanded);
        let to = self.position(b)?;
        self.push(MoveKind::Extrude {
            to,
            feed_um_s: Self::feed(self.settings.print_feed_mm_s),
            volumes_nl: volumes,
            width_factor_ppt: (factor * f64::from(FACTOR_NOMINAL_PPT))
                .round()
                .clamp(0.0, f64::from(u16::MAX)) as u16,
        })?;
        self.stats.extrude_moves += 1;
        self.state.position = Some(DVec3::new(b.x, b.y, self.z_mm));
        Ok(())
    }
}

/// `kind`'s volumes, given per material, put in the machine's syringe order:
/// material i's volume on syringe `syringe_of[i]`.
fn to_syringe_order(kind: &mut MoveKind, syringe_of: &[usize]) {
    let volumes = match kind {
        MoveKind::Extrude { volumes_nl, .. }
        | MoveKind::Retract { volumes_nl, .. }
        | MoveKind::Prime { volumes_nl, .. } => volumes_nl,
        _ => return,
    };
    let mut by_syringe = vec![0; volumes.len()];
    for (material, &v) in volumes.iter().enumerate() {
        if let Some(slot) = syringe_of
            .get(material)
            .and_then(|&s| by_syringe.get_mut(s))
        {
            *slot = v;
        }
    }
    *volumes = by_syringe;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The non-star example's layers planned, with its process settings.
    fn non_star() -> (Vec<LayerPlan>, ProcessSettings) {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/examples/non-star.toml");
        let job =
            crate::job::Job::from_toml(&std::fs::read_to_string(path).unwrap(), path).unwrap();
        let slices = job.layer_slices(0, job.extruded_layers().unwrap());
        let plans = crate::plan::plan_layers(&slices, &job.plan, None).unwrap();
        (plans, ProcessSettings::for_nozzle(job.plan.nozzle_mm))
    }

    /// [`layer_moves`] on each layer in order: what the parallel version must give.
    fn serial(layers: &[LayerPlan], s: &ProcessSettings) -> (Vec<LayerMoves>, StreamState) {
        let mut state = StreamState::new();
        let mut next = 5;
        let out = layers
            .iter()
            .map(|l| {
                let lm = layer_moves(l, s, 3, next, &mut state).unwrap();
                next = lm.next_index;
                lm
            })
            .collect();
        (out, state)
    }

    #[test]
    fn layers_in_parallel_give_the_serial_moves() {
        let (layers, mut s) = non_star();
        assert!(layers.len() >= 2);
        for seam in [SeamMode::Aligned, SeamMode::Nearest] {
            s.seam = seam;
            let mut state = StreamState::new();
            let all = job_layer_moves(&layers, &s, 3, 5, &mut state).unwrap();
            assert_eq!((all, state), serial(&layers, &s), "{seam:?}");
        }
    }

    #[test]
    fn layers_in_batches_give_the_serial_moves() {
        let (layers, mut s) = non_star();
        s.seam = SeamMode::Nearest;
        let serial = serial(&layers, &s);
        for batch in [1, 2, layers.len() + 1] {
            let mut state = StreamState::new();
            let mut all = Vec::new();
            let mut seen = Vec::new();
            for_each_layer_moves(&layers, &s, (3, 5), &mut state, batch, |l, lm| {
                seen.push(l.index);
                all.push(lm);
                Ok::<(), PipelineError>(())
            })
            .unwrap();
            let indices: Vec<_> = layers.iter().map(|l| l.index).collect();
            assert_eq!(seen, indices, "layers handed over in order");
            assert_eq!((all, state), serial, "batches of {batch}");
        }
    }

    #[test]
    fn a_wrong_guess_of_the_start_is_finished_again() {
        // Every layer ordered from a start far off: each first seam is chosen
        // differently (seams nearest the nozzle), and the layer is finished again from
        // where the nozzle really is.
        let (layers, mut s) = non_star();
        s.seam = SeamMode::Nearest;
        let far = Some(DVec2::new(-500.0, 300.0));
        let guessed = layers
            .iter()
            .map(|l| toolpath::fill_order(l, &s.order_settings(), far).paths)
            .collect();
        let mut state = StreamState::new();
        let mut all = Vec::new();
        let again = moves_from_guesses(&layers, &s, (3, 5), &mut state, guessed, |lm| {
            all.push(lm);
            Ok::<(), PipelineError>(())
        })
        .unwrap();
        assert_eq!(again, layers.len());
        assert_eq!((all, state), serial(&layers, &s));
    }

    #[test]
    fn settings_parse_and_refuse_unknown_keys() {
        let s = ProcessSettings::from_toml("nozzle_mm = 0.5\nseam = \"staggered\"\n", "t").unwrap();
        assert_eq!(s.road_width(), 0.5);
        assert_eq!(s.seam, SeamMode::Staggered);
        assert!(matches!(
            ProcessSettings::from_toml("nozle_mm = 0.5\n", "t"),
            Err(PipelineError::Toml { .. })
        ));
        assert!(matches!(
            ProcessSettings::from_toml("max_flow_factor = 0.5\n", "t"),
            Err(PipelineError::Setting {
                field: "max_flow_factor",
                ..
            })
        ));
        for bad in ["0.0", "1.5", "nan"] {
            assert!(matches!(
                ProcessSettings::from_toml(&format!("gap_fill_min_factor = {bad}\n"), "t"),
                Err(PipelineError::Setting {
                    field: "gap_fill_min_factor",
                    ..
                })
            ));
        }
        // Set from the job's [process] table, checked again before use.
        for bad in [-0.1, 0.6, f64::NAN] {
            let s = ProcessSettings {
                move_width_tolerance: bad,
                ..ProcessSettings::for_nozzle(0.4)
            };
            assert!(matches!(
                s.validate(),
                Err(PipelineError::Setting {
                    field: "move_width_tolerance",
                    ..
                })
            ));
        }
        let off = ProcessSettings::from_toml("gap_fill = false\n", "t").unwrap();
        assert!(!off.gap_fill);
    }
}
