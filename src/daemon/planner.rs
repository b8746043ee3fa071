//! The planner stage: a blocking worker turns a job into moves layer by layer, ahead of
//! the streamer, through a bounded channel (`planner.layers_ahead` layers), so the first
//! layer streams while later ones are still being planned and memory stays bounded
//! however large the part.
//!
//! What produces the moves is a [`LayerSource`]: [`DryRunSource`] (zero-volume moves, to
//! qualify a machine through the whole daemon) and [`JobSource`] (a job file through the
//! EDO planner and the toolpath pipeline). Tests feed synthetic sources.

use tokio::sync::mpsc;

use crate::job::placement::{BuildVolume, Placement};
use crate::lifecycle::{PlannerOutput, ResumePoint};
// Placing a part is planning, shared with `edoctl plan` and `edoctl demo`; the daemon
// uses the core's (and keeps the old path for its API).
pub use crate::job::placement::{place_part, placed_settings};
use crate::machine::time::PlannedTimeBuilder;
use crate::machine::{Move, MoveKind, PositionUm, FACTOR_NOMINAL_PPT};

/// Produces a job's moves one layer at a time, indices counting from 0 without gaps.
pub trait LayerSource: Send {
    /// The next layer's moves, `None` after the last layer.
    fn next_layer(&mut self) -> Option<Result<Vec<Move>, String>>;

    /// How many layers the job has, once known (a mesh job's after its mesh is sliced,
    /// that is after the first [`LayerSource::next_layer`]).
    fn layer_count(&self) -> Option<u32> {
        None
    }

    /// Draw each layer's SVG preview from now on ([`crate::svg::layer_svg`], as
    /// `edoctl plan --svg` writes them), to be taken after each layer with
    /// [`LayerSource::take_preview_svg`]. A source with nothing to draw (a dry run)
    /// ignores it.
    fn draw_previews(&mut self) {}

    /// The SVG preview of the layer [`LayerSource::next_layer`] returned last, if drawn.
    fn take_preview_svg(&mut self) -> Option<String> {
        None
    }

    /// The job's allowed overhang (none for a dry run), for previews' warnings.
    fn overhang(&self) -> Option<crate::slice::overhang::Overhang> {
        None
    }

    /// The area resting on nothing of the layer last previewed, mm² (with
    /// [`LayerSource::take_preview_svg`]).
    fn take_preview_unsupported_mm2(&mut self) -> Option<f64> {
        None
    }

    /// The road each extrusion of the layer last previewed builds, as designed (with
    /// [`LayerSource::take_preview_svg`]), in move order.
    fn take_preview_roads(&mut self) -> Option<Vec<DesignedRoad>> {
        None
    }
}

/// What an extrusion move builds as designed: the move, the road's composition and
/// the colour the SVG previews give the road ([`crate::svg::road_colour`]: its
/// composition's, or the support's grey); and what the planner's model of the mixing
/// chamber predicts leaves the nozzle during the move. Compositions per material.
#[derive(Clone, Debug, PartialEq)]
pub struct DesignedRoad {
    pub move_index: u32,
    pub composition: Vec<f64>,
    pub colour: String,
    pub exit: Vec<f64>,
}

/// The designed road of every extrusion of `lm`, in move order (its exits taken).
fn designed_roads(lm: &mut crate::pipeline::LayerMoves) -> Vec<DesignedRoad> {
    let exits = std::mem::take(&mut lm.extrusion_exits);
    lm.extrusion_paths
        .iter()
        .zip(exits)
        .filter_map(|(&(move_index, path), exit)| {
            let p = lm.paths.get(path as usize)?;
            Some(DesignedRoad {
                move_index,
                composition: p.composition.clone(),
                colour: crate::svg::road_colour(p),
                exit,
            })
        })
        .collect()
}

/// Start a planner worker for job `job_id` that skips moves before `start_index`: on a
/// blocking thread, `source` makes the job's [`LayerSource`] (reading the store there,
/// never on a task), then the moves go out as the lifecycle's [`PlannerOutput`]: first
/// the layer count once known, where the job stands at the resume index (when
/// resuming), the moves layer by layer, then `Done` (or `Failed`). Dropping the
/// receiver stops the worker at its next layer.
///
/// Beside it, a second worker plans the job whole from a source of its own for its
/// planned machine time ([`PlannedTime`], sent as [`PlannerOutput::Estimate`]): what
/// progress and ETA are measured by. It keeps no moves, and stops when the receiver is
/// dropped; a planning failure is the first worker's to report.
pub fn spawn(
    source: impl Fn() -> Result<Box<dyn LayerSource>, String> + Send + Sync + 'static,
    job_id: u32,
    start_index: u32,
    layers_ahead: usize,
) -> mpsc::Receiver<PlannerOutput> {
    let (tx, rx) = mpsc::channel(layers_ahead.max(1));
    let source = std::sync::Arc::new(source);
    let (estimate_source, estimate_tx) = (std::sync::Arc::clone(&source), tx.clone());
    tokio::task::spawn_blocking(move || match source() {
        Ok(source) => plan(source, job_id, start_index, &tx),
        Err(e) => {
            let _ = tx.blocking_send(PlannerOutput::Failed(e));
        }
    });
    tokio::task::spawn_blocking(move || {
        if let Ok(source) = estimate_source() {
            estimate(source, &estimate_tx);
        }
    });
    rx
}

/// The estimator: the planned machine time of all of `source`'s moves to `tx`.
fn estimate(mut source: Box<dyn LayerSource>, tx: &mpsc::Sender<PlannerOutput>) {
    let mut time = PlannedTimeBuilder::new();
    while let Some(layer) = source.next_layer() {
        let Ok(moves) = layer else {
            return;
        };
        if tx.is_closed() {
            return;
        }
        for mv in &moves {
            time.push(mv);
        }
    }
    let _ = tx.blocking_send(PlannerOutput::Estimate(time.finish()));
}

/// What the moves before the resume index left behind.
#[derive(Default)]
struct Skipped {
    position: Option<PositionUm>,
    layer_mark: Option<(u32, i32)>,
    volumes_nl: Option<Vec<u32>>,
}

impl Skipped {
    fn skip(&mut self, mv: &Move) {
        match &mv.kind {
            MoveKind::Travel { to, .. } => self.position = Some(*to),
            MoveKind::Extrude { to, volumes_nl, .. } => {
                self.position = Some(*to);
                self.volumes_nl = Some(volumes_nl.clone());
            }
            MoveKind::LayerMark { layer, z_um } => self.layer_mark = Some((*layer, *z_um)),
            _ => {}
        }
    }

    fn resume_point(&self) -> PlannerOutput {
        PlannerOutput::ResumeAt(ResumePoint {
            position: self.position,
            layer_mark: self.layer_mark,
            volumes_nl: self.volumes_nl.clone(),
        })
    }
}

/// The worker: `source`'s layers to `tx`, until the receiver is gone.
fn plan(
    mut source: Box<dyn LayerSource>,
    job_id: u32,
    start_index: u32,
    tx: &mpsc::Sender<PlannerOutput>,
) {
    let send = |out: PlannerOutput| tx.blocking_send(out).is_ok();
    let mut expected: u32 = 0;
    let mut skipped = Skipped::default();
    let mut resume_sent = start_index == 0;
    let mut count_sent = false;
    while let Some(layer) = source.next_layer() {
        if !count_sent {
            if let Some(count) = source.layer_count() {
                count_sent = true;
                if !send(PlannerOutput::Layers(count)) {
                    return;
                }
            }
        }
        let moves = match layer {
            Ok(m) => m,
            Err(e) => {
                send(PlannerOutput::Failed(e));
                return;
            }
        };
        let mut out = Vec::new();
        for mut mv in moves {
            if mv.index != expected {
                send(PlannerOutput::Failed(format!(
                    "planner produced move index {} where {expected} was due",
                    mv.index
                )));
                return;
            }
            expected += 1;
            mv.job_id = job_id;
            if mv.index < start_index {
                skipped.skip(&mv);
                continue;
            }
            if !resume_sent {
                resume_sent = true;
                if !send(skipped.resume_point()) {
                    return;
                }
            }
            out.push(mv);
        }
        if !out.is_empty() && !send(PlannerOutput::Moves(out)) {
            return;
        }
    }
    if !resume_sent {
        send(skipped.resume_point());
    }
    send(PlannerOutput::Done { total: expected });
}

/// What produces stored job `job`'s moves (`mesh`: a mesh job's mesh) on a machine of
/// `syringes` syringes configured by `config`.
pub fn source_of(
    job: &super::store::JobRecord,
    mesh: Option<&[u8]>,
    syringes: usize,
    config: &super::Config,
) -> Result<Box<dyn LayerSource>, String> {
    match &job.spec {
        super::store::JobSpec::DryRun { moves } => Ok(Box::new(DryRunSource::new(
            *moves,
            config.planner.dry_run_moves_per_layer,
            syringes,
            (config.machine.build_volume_mm[2] * 1000.0).round() as i32,
        ))),
        super::store::JobSpec::Toml { toml, .. } => {
            JobSource::new(toml, mesh, &format!("job {}", job.job.id), &config.machine)
                .map(|s| Box::new(s) as Box<dyn LayerSource>)
        }
    }
}

/// A dry-run job: `moves` zero-volume extrusion moves zig-zagging 1 mm along X at
/// 10 mm/s (100 ms of machine time each, so the machine, not the line, sets the pace),
/// with a layer mark opening every layer of `per_layer` moves.
///
/// Layers step up 0.2 mm from z = 0.2 mm and start again at the bottom once the next
/// would be above the build volume's top (nothing is extruded, so nothing is in the
/// way), so a dry run of any length stays inside the volume.
pub struct DryRunSource {
    moves: u32,
    per_layer: u32,
    next: u32,
    layer: u32,
    syringes: usize,
    /// The build volume's top, µm.
    top_z_um: i32,
}

/// The dry run's layer height, µm.
const DRY_RUN_LAYER_UM: i32 = 200;

impl DryRunSource {
    /// A dry run of `moves` moves (layer marks included) for `syringes` syringes, in a
    /// build volume `top_z_um` tall.
    pub fn new(moves: u32, per_layer: u32, syringes: usize, top_z_um: i32) -> Self {
        Self {
            moves,
            per_layer: per_layer.max(2),
            next: 0,
            layer: 0,
            syringes,
            top_z_um: top_z_um.max(0),
        }
    }

    /// The height of dry-run layer `layer`, µm.
    fn z_um(&self, layer: u32) -> i32 {
        // How many layers fit under the top (at least one, at the top itself).
        let levels = (self.top_z_um / DRY_RUN_LAYER_UM).max(1) as u32;
        (DRY_RUN_LAYER_UM * ((layer % levels) as i32 + 1)).min(self.top_z_um)
    }
}

impl LayerSource for DryRunSource {
    fn next_layer(&mut self) -> Option<Result<Vec<Move>, String>> {
        if self.next >= self.moves {
            return None;
        }
        let end = (self.next + self.per_layer).min(self.moves);
        let mut out = Vec::with_capacity((end - self.next) as usize);
        let z_um = self.z_um(self.layer);
        for index in self.next..end {
            let kind = if index == self.next {
                MoveKind::LayerMark {
                    layer: self.layer,
                    z_um,
                }
            } else {
                MoveKind::Extrude {
                    to: PositionUm {
                        x_um: (index % 2) as i32 * 1000,
                        y_um: 0,
                        z_um,
                    },
                    feed_um_s: 10_000,
                    volumes_nl: vec![0; self.syringes],
                    width_factor_ppt: FACTOR_NOMINAL_PPT,
                }
            };
            out.push(Move {
                job_id: 0,
                index,
                kind,
            });
        }
        self.next = end;
        self.layer += 1;
        Some(Ok(out))
    }

    fn layer_count(&self) -> Option<u32> {
        Some(self.moves.div_ceil(self.per_layer))
    }
}

/// A job file planned layer by layer: the EDO plan of each layer (`edo::plan_layer`),
/// then the toolpath pipeline (`pipeline::layer_moves`) turns it into moves, carrying
/// its stream state (position, pressure, volumes, mixing chamber) from layer to layer.
///
/// An extruded polygon's layers are known at once. A mesh job's part is loaded, repaired
/// and stacked on the planner worker (the first call of `next_layer`, never on the
/// streamer's task), then cut [`MESH_LAYERS_PER_CUT`] layers at a time, so memory holds
/// the mesh and a few layers however tall the part.
pub struct JobSource {
    job: crate::job::Job,
    layers: Layers,
    next_layer: usize,
    settings: crate::pipeline::ProcessSettings,
    state: crate::pipeline::StreamState,
    next_index: u32,
    volume: BuildVolume,
    /// Where the part goes on the bed (a mesh job's once its mesh is loaded).
    placement: Option<Placement>,
    /// Draw each layer's SVG preview ([`LayerSource::draw_previews`]).
    draw_previews: bool,
    /// The last layer's preview, not taken yet.
    preview_svg: Option<String>,
    /// The last layer's designed roads, not taken yet (while previews are drawn).
    preview_roads: Option<Vec<DesignedRoad>>,
    /// The last layer planned (index, islands) while previews are drawn: what the next
    /// rests on, for its area resting on nothing (red in the preview).
    below: Option<(usize, Vec<crate::geom::Region>)>,
    /// The supports of the layers previewed lately (index, top z, area), newest last:
    /// what holds up the next layer besides the one below (with a top gap, one a few
    /// layers down).
    recent_supports: std::collections::VecDeque<(usize, f64, crate::geom::Shapes)>,
    /// Each layer's support still to build, with `[support]` on (empty: none), found
    /// when the mesh is loaded.
    supports: Vec<crate::slice::support::SupportArea>,
    /// The last previewed layer's area resting on nothing, mm², not taken yet.
    preview_unsupported_mm2: Option<f64>,
}

/// Layers of support kept for the previews' judgement of what rests on nothing (a top
/// gap of up to this many layers).
const RECENT_SUPPORT_LAYERS: usize = 64;

/// Mesh layers cut (in parallel) per batch.
pub const MESH_LAYERS_PER_CUT: usize = 8;

enum Layers {
    Extruded(Vec<crate::plan::LayerSlice>),
    /// Mesh bytes not loaded yet.
    MeshBytes(Vec<u8>),
    Mesh {
        part: Box<crate::job::MeshLayers>,
        /// Cut layers not planned yet, in order.
        ready: std::collections::VecDeque<crate::plan::LayerSlice>,
    },
}

impl JobSource {
    /// Parse and validate a job file (`source_name` names it in errors) with the mesh
    /// bytes sent with it (a mesh job), for a machine (`[machine]` of edod.toml:
    /// syringes, max flow factor, V_dead). Cheap: a mesh is loaded on the worker.
    pub fn new(
        toml: &str,
        mesh: Option<&[u8]>,
        source_name: &str,
        machine: &crate::setup::MachineConfig,
    ) -> Result<Self, String> {
        let job = crate::job::Job::from_toml(toml, source_name).map_err(|e| e.to_string())?;
        let mut settings = crate::setup::process_settings(&job, machine, source_name)?;
        let volume = machine
            .build_volume()
            .map_err(|e| format!("machine.build_volume_mm: {e}"))?;
        let placement = match job.extruded_bounds() {
            Some(bounds) => {
                let p =
                    place_part(&job, bounds, &volume).map_err(|e| format!("{source_name}: {e}"))?;
                settings = placed_settings(&settings, &p);
                Some(p)
            }
            None => None,
        };
        let layers = match (job.extruded_layers(), mesh) {
            (Some(stack), _) => Layers::Extruded(job.layer_slices(0, stack)),
            (None, Some(bytes)) => Layers::MeshBytes(bytes.to_vec()),
            (None, None) => {
                return Err(format!(
                    "{source_name}: geometry.mesh: the mesh was not sent with the job (job.submit mesh_base64)"
                ))
            }
        };
        Ok(Self {
            job,
            layers,
            next_layer: 0,
            settings,
            state: crate::pipeline::StreamState::new(),
            next_index: 0,
            volume,
            placement,
            draw_previews: false,
            preview_svg: None,
            preview_roads: None,
            below: None,
            recent_supports: Default::default(),
            supports: Vec::new(),
            preview_unsupported_mm2: None,
        })
    }

    /// The SVG preview of a planned layer (part coordinates, as `edoctl plan --svg`),
    /// its area resting on nothing in red; the layer is kept as the next one's below.
    fn preview_of(&mut self, plan: &crate::plan::LayerPlan, layer: &crate::slice::Layer) -> String {
        let opts = self.job.overhang_options();
        // Layer 0 rests on the bed; a layer whose layer below was not planned here (a
        // preview from a later layer) is not judged.
        let bed_mm = match &self.layers {
            Layers::Mesh { part, .. } => part.spans().first().map_or(0.0, |s| s.z_bottom_mm),
            _ => 0.0,
        };
        let bottom = layer.z_mm - layer.thickness_mm - bed_mm;
        let on_bed = crate::slice::support::held_by_bed(bottom, self.job.support.top_gap_mm)
            && self.job.support.builds();
        let unsupported = match &self.below {
            Some((i, below)) if i + 1 == plan.index && !on_bed => {
                let mut resting = crate::slice::overhang::shapes_of(below);
                if let Some(held) = self.holding_support(plan, layer) {
                    resting = crate::geom::union(&resting, held);
                }
                crate::slice::overhang::hanging(&layer.islands, &resting, layer.thickness_mm, &opts)
            }
            _ => crate::geom::Shapes::new(),
        };
        let svg = crate::svg::layer_svg(
            plan,
            &crate::svg::PreviewInput {
                job_name: &self.job.name,
                materials: &self.job.materials,
                nozzle_mm: self.job.plan.nozzle_mm,
                islands: &layer.islands,
                unsupported: &unsupported,
            },
        );
        self.below = Some((plan.index, layer.islands.clone()));
        if self.job.support.builds() {
            if self.recent_supports.len() == RECENT_SUPPORT_LAYERS {
                self.recent_supports.pop_front();
            }
            self.recent_supports
                .push_back((plan.index, layer.z_mm, plan.support.all()));
        }
        self.preview_unsupported_mm2 = Some(crate::slice::overhang::area_mm2(&unsupported));
        svg
    }

    /// The support that holds up `layer` (planned as `plan`), of the layers planned
    /// lately: the highest whose top is the job's top gap or more under it.
    fn holding_support(
        &self,
        plan: &crate::plan::LayerPlan,
        layer: &crate::slice::Layer,
    ) -> Option<&crate::geom::Shapes> {
        let below = plan.index.checked_sub(1)?;
        let bottom = layer.z_mm - layer.thickness_mm;
        let top_of = |k: usize| {
            self.recent_supports
                .iter()
                .find(|(i, _, _)| *i == k)
                .map_or(f64::NEG_INFINITY, |(_, z, _)| *z)
        };
        let k = crate::slice::support::holding_layer(
            below,
            bottom,
            self.job.support.top_gap_mm,
            top_of,
        )?;
        self.recent_supports
            .iter()
            .find(|(i, _, _)| *i == k)
            .map(|(_, _, s)| s)
            .filter(|s| !s.is_empty())
    }

    /// Where the part goes on the bed (`None` for a mesh job until its mesh is loaded).
    pub fn placement(&self) -> Option<Placement> {
        self.placement
    }

    /// Job name.
    pub fn name(&self) -> &str {
        &self.job.name
    }

    /// The next layer to plan, loading and cutting the mesh as needed.
    fn next_slice(&mut self) -> Option<Result<crate::plan::LayerSlice, String>> {
        if let Layers::MeshBytes(bytes) = &self.layers {
            let part = match self
                .job
                .mesh_layers(bytes, &crate::mesh::MeshLimits::default())
            {
                Ok(p) => p,
                Err(e) => return Some(Err(e.to_string())),
            };
            let placement = match place_part(&self.job, part.bounds(), &self.volume) {
                Ok(p) => p,
                Err(e) => return Some(Err(e)),
            };
            self.settings = placed_settings(&self.settings, &placement);
            self.placement = Some(placement);
            match part.supports(&self.job) {
                Ok(found) => self.supports = found.map(|s| s.areas).unwrap_or_default(),
                Err(e) => return Some(Err(e.to_string())),
            }
            self.layers = Layers::Mesh {
                part: Box::new(part),
                ready: Default::default(),
            };
        }
        let k = self.next_layer;
        match &mut self.layers {
            Layers::Extruded(slices) => {
                let s = slices.get(k)?.clone();
                self.next_layer += 1;
                Some(Ok(s))
            }
            Layers::Mesh { part, ready } => {
                if ready.is_empty() {
                    if k >= part.len() {
                        return None;
                    }
                    match part.cut(k..k + MESH_LAYERS_PER_CUT, None) {
                        Ok((layers, _)) => ready.extend(self.job.layer_slices(k, layers)),
                        Err(e) => return Some(Err(e.to_string())),
                    }
                }
                let s = ready.pop_front()?;
                self.next_layer += 1;
                Some(Ok(s))
            }
            Layers::MeshBytes(_) => None,
        }
    }
}

impl LayerSource for JobSource {
    fn next_layer(&mut self) -> Option<Result<Vec<Move>, String>> {
        let s = match self.next_slice()? {
            Ok(s) => s,
            Err(e) => return Some(Err(e)),
        };
        let l = &s.layer;
        let plan = crate::plan::plan_layer(
            s.index,
            l.z_mm,
            l.thickness_mm,
            &l.islands,
            &s.design,
            &self.job.plan,
        )
        .map_err(|e| format!("layer {} (z = {:.3} mm): {e}", s.index, l.z_mm));
        // The job starts by homing, as its G-code file does (`edoctl plan --gcode`).
        let home = (self.next_index == 0).then(|| {
            self.next_index = crate::pipeline::FIRST_LAYER_MOVE_INDEX;
            crate::pipeline::home_move(0)
        });
        Some(plan.and_then(|mut plan| {
            if let Some(area) = self.supports.get_mut(s.index) {
                plan.support = std::mem::take(area);
            }
            self.preview_svg = if self.draw_previews {
                Some(self.preview_of(&plan, l))
            } else {
                None
            };
            let mut lm = crate::pipeline::layer_moves(
                &plan,
                &self.settings,
                0,
                self.next_index,
                &mut self.state,
            )
            .map_err(|e| format!("layer {}: {e}", s.index))?;
            self.next_index = lm.next_index;
            self.preview_roads = self.draw_previews.then(|| designed_roads(&mut lm));
            // Into the machine frame, and nothing outside the build volume.
            let mut moves = home.into_iter().chain(lm.moves).collect::<Vec<_>>();
            self.placement
                .unwrap_or_default()
                .put_on_machine(&mut moves, &self.volume)
                .map_err(|e| format!("layer {}: {e}", s.index))?;
            Ok(moves)
        }))
    }

    fn layer_count(&self) -> Option<u32> {
        match &self.layers {
            Layers::Extruded(slices) => u32::try_from(slices.len()).ok(),
            Layers::Mesh { part, .. } => u32::try_from(part.len()).ok(),
            Layers::MeshBytes(_) => None,
        }
    }

    fn draw_previews(&mut self) {
        self.draw_previews = true;
    }

    fn take_preview_svg(&mut self) -> Option<String> {
        self.preview_svg.take()
    }

    fn overhang(&self) -> Option<crate::slice::overhang::Overhang> {
        Some(self.job.overhang)
    }

    fn take_preview_unsupported_mm2(&mut self) -> Option<f64> {
        self.preview_unsupported_mm2.take()
    }

    fn take_preview_roads(&mut self) -> Option<Vec<DesignedRoad>> {
        self.preview_roads.take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn annulus_on_default_machine() -> (String, crate::setup::MachineConfig) {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/examples/paper-annulus.toml"
        );
        let text = std::fs::read_to_string(path).unwrap();
        (text, crate::setup::MachineConfig::default())
    }

    /// The first layer's volumes of `text` on `machine`, move by move.
    fn first_layer_volumes(text: &str, machine: &crate::setup::MachineConfig) -> Vec<Vec<u32>> {
        let mut src = JobSource::new(text, None, "annulus", machine).unwrap();
        let layer = src.next_layer().unwrap().unwrap();
        layer
            .into_iter()
            .filter_map(|m| match m.kind {
                MoveKind::Extrude { volumes_nl, .. } => Some(volumes_nl),
                _ => None,
            })
            .collect()
    }

    /// Materials are pushed from the syringe of their name, or the one the job maps
    /// them to, whatever their order; a material in no syringe is refused naming the
    /// machine's syringes and the fix.
    #[test]
    fn materials_are_matched_to_syringes_by_name() {
        let (text, machine) = annulus_on_default_machine();
        assert!(text.contains("names = [\"A\", \"B\"]"));
        let own = first_layer_volumes(&text, &machine);
        assert!(own.iter().any(|v| v[0] != v[1]), "a graded layer");
        // The same design, its materials listed the other way round (and their
        // compositions with them): the same syringe pushes the same volume.
        let swapped_text = text
            .replace("names = [\"A\", \"B\"]", "names = [\"B\", \"A\"]")
            .replace("inner = [1.0, 0.0]", "inner = [0.0, 1.0]")
            .replace("outer = [0.0, 1.0]", "outer = [1.0, 0.0]");
        assert_ne!(swapped_text, text);
        assert_eq!(first_layer_volumes(&swapped_text, &machine), own);
        // Mapped explicitly: materials named otherwise, loaded in A and B.
        let mapped = text.replace(
            "names = [\"A\", \"B\"]",
            "names = [\"Ti\", \"HA\"]\nsyringes = [\"A\", \"B\"]",
        );
        assert_eq!(first_layer_volumes(&mapped, &machine), own);
        // Not in any syringe: refused, naming what is there and the fix.
        let unmapped = text.replace("names = [\"A\", \"B\"]", "names = [\"Ti\", \"HA\"]");
        let e = JobSource::new(&unmapped, None, "job.toml", &machine)
            .err()
            .unwrap();
        assert!(
            e.contains("materials.names: the machine has no syringe \"Ti\" for material \"Ti\"")
                && e.contains("its syringes: A, B")
                && e.contains("syringes = [\"A\", \"B\"]"),
            "{e}"
        );
        let wrong = text.replace(
            "names = [\"A\", \"B\"]",
            "names = [\"Ti\", \"HA\"]\nsyringes = [\"A\", \"C\"]",
        );
        let e = JobSource::new(&wrong, None, "job.toml", &machine)
            .err()
            .unwrap();
        assert!(
            e.contains("materials.syringes: the machine has no syringe \"C\" for material \"HA\""),
            "{e}"
        );
    }

    #[test]
    fn a_job_file_becomes_moves_layer_by_layer() {
        let (text, machine) = annulus_on_default_machine();
        let mut src = JobSource::new(&text, None, "annulus", &machine).unwrap();
        // 0.4 mm extruded in 0.2 mm layers: known before planning.
        assert_eq!(src.layer_count(), Some(2));
        let first = src.next_layer().unwrap().unwrap();
        // The job homes first, as its G-code file does.
        assert!(matches!(first[0].kind, MoveKind::Home));
        assert!(matches!(
            first[1].kind,
            MoveKind::LayerMark { layer: 0, .. }
        ));
        assert!(first.iter().enumerate().all(|(i, m)| m.index == i as u32));
        let second = src.next_layer().unwrap().unwrap();
        assert_eq!(second[0].index as usize, first.len());
        assert!(second
            .iter()
            .any(|m| matches!(m.kind, MoveKind::Extrude { .. })));
    }

    /// The default machine with a third syringe "S" of support ink.
    fn machine_with_support_syringe() -> crate::setup::MachineConfig {
        let mut machine = crate::setup::MachineConfig::default();
        let mut s = machine.syringes[0].clone();
        s.name = "S".into();
        s.role = crate::setup::SyringeRole::Support;
        machine.syringes.push(s);
        machine
    }

    /// A ball job (overhangs all round its lower half) with `support`.
    fn ball_job(support: &str) -> (String, Vec<u8>) {
        let stl = crate::mesh::primitives::sphere(3.0, 48, 24)
            .to_binary_stl()
            .unwrap();
        let text = format!(
            "name = \"ball\"\n[geometry]\nmesh = \"ball.stl\"\n[materials]\n\
             names = [\"A\", \"B\"]\n[gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n\
             [process]\nr_mach = 1.0\nnozzle = 0.4\nlayer = 0.2\nthin_regions = \"fill\"\n{support}"
        );
        (text, stl)
    }

    /// Every extrusion of a job on `machine`: its volumes, and whether S pushed.
    fn extrusions(src: &mut JobSource) -> Vec<Vec<u32>> {
        let mut out = Vec::new();
        while let Some(layer) = src.next_layer() {
            for m in layer.unwrap() {
                if let MoveKind::Extrude { volumes_nl, .. } = m.kind {
                    out.push(volumes_nl);
                }
            }
        }
        out
    }

    /// On a machine with a support syringe, edod streams a job's supports of it (only
    /// S in a support road, never in the part's), runs a job without supports with S
    /// idle, and refuses a job naming a support syringe the machine does not have.
    #[test]
    fn supports_stream_from_the_machine_s_support_syringe() {
        let machine = machine_with_support_syringe();
        let (text, stl) = ball_job("[support]\nmode = \"everywhere\"\nsyringe = \"S\"\n");
        let mut src = JobSource::new(&text, Some(&stl), "ball", &machine).unwrap();
        src.draw_previews();
        let moves = extrusions(&mut src);
        let support: Vec<_> = moves.iter().filter(|v| v[2] > 0).collect();
        assert!(!support.is_empty(), "no support roads streamed");
        assert!(support.iter().all(|v| v[0] == 0 && v[1] == 0));
        assert!(moves.iter().any(|v| v[2] == 0 && v[0] + v[1] > 0));
        // Without supports: S idle.
        let (plain, _) = ball_job("");
        let mut src = JobSource::new(&plain, Some(&stl), "ball", &machine).unwrap();
        assert!(extrusions(&mut src)
            .iter()
            .all(|v| v.len() == 3 && v[2] == 0));
        // Supports of a syringe the machine has not: refused naming both.
        let (other, _) = ball_job("[support]\nmode = \"everywhere\"\nsyringe = \"W\"\n");
        let e = JobSource::new(&other, Some(&stl), "ball", &machine)
            .err()
            .unwrap();
        assert!(
            e.contains("support.syringe = \"W\"") && e.contains("\"S\""),
            "{e}"
        );
        let plain_machine = crate::setup::MachineConfig::default();
        let e = JobSource::new(&text, Some(&stl), "ball", &plain_machine)
            .err()
            .unwrap();
        assert!(e.contains("no support syringe"), "{e}");
        // A material may not be loaded in the support syringe.
        let in_s = plain.replace("names = [\"A\", \"B\"]", "names = [\"A\", \"S\"]");
        let e = JobSource::new(&in_s, Some(&stl), "ball", &machine)
            .err()
            .unwrap();
        assert!(e.contains("holds the support ink"), "{e}");
    }

    /// Supports of the part's materials stream at the job's composition, on any machine.
    #[test]
    fn supports_of_a_composition_stream_at_it() {
        let machine = crate::setup::MachineConfig::default();
        let (text, stl) = ball_job("[support]\nmode = \"everywhere\"\ncomposition = [0.0, 1.0]\n");
        let mut src = JobSource::new(&text, Some(&stl), "ball", &machine).unwrap();
        let moves = extrusions(&mut src);
        let with_supports = moves.len();
        let (plain, _) = ball_job("");
        let mut src = JobSource::new(&plain, Some(&stl), "ball", &machine).unwrap();
        assert!(with_supports > extrusions(&mut src).len());
    }

    /// A mesh job knows its layer count once its mesh is sliced (at the first layer).
    #[test]
    fn a_mesh_job_counts_its_layers_once_sliced() {
        let mesh = crate::mesh::primitives::tube(4.0, 8.0, 0.8, 32);
        let stl = mesh.to_binary_stl().unwrap();
        let text = "name = \"tube\"\n[geometry]\nmesh = \"tube.stl\"\n[materials]\n\
                    names = [\"A\", \"B\"]\n[gradient]\npattern = \"growth-rings\"\n\
                    inner = [1.0, 0.0]\nouter = [0.0, 1.0]\n[process]\nr_mach = 0.8\n\
                    nozzle = 0.4\nlayer = 0.2\n";
        let machine = crate::setup::MachineConfig::default();
        let mut src = JobSource::new(text, Some(&stl), "tube", &machine).unwrap();
        assert_eq!(src.layer_count(), None);
        let mut layers = 0;
        while let Some(layer) = src.next_layer() {
            layer.unwrap();
            layers += 1;
            assert_eq!(src.layer_count(), Some(4));
        }
        assert_eq!(layers, 4);
    }

    #[test]
    fn a_job_is_placed_on_the_bed_and_refused_where_it_does_not_fit() {
        let (text, machine) = annulus_on_default_machine();
        // Centred on the 200 x 200 mm bed: the annulus (outer radius 30 about the
        // origin) lands about (100, 100), every move inside the volume.
        let mut src = JobSource::new(&text, None, "annulus", &machine).unwrap();
        assert_eq!(
            src.placement().map(|p| p.offset_um),
            Some([100_000, 100_000, 0])
        );
        let volume = machine.build_volume().unwrap();
        let mut xs = Vec::new();
        while let Some(layer) = src.next_layer() {
            for m in layer.unwrap() {
                assert!(volume.check(&m).is_ok());
                if let MoveKind::Extrude { to, .. } = m.kind {
                    xs.push(f64::from(to.x_um) / 1000.0);
                }
            }
        }
        let (lo, hi) = xs
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(*x), b.max(*x)));
        assert!(
            lo > 69.0 && hi < 131.0 && lo < 72.0 && hi > 128.0,
            "{lo} {hi}"
        );
        // Kept at its own coordinates it lies off the bed; too small a machine.
        let keep = text.replace("[geometry]", "[geometry]\nplacement = \"keep\"");
        let e = JobSource::new(&keep, None, "annulus", &machine)
            .err()
            .unwrap();
        assert!(e.contains("\"keep\"") && e.contains("x = -30.000"), "{e}");
        let small = crate::setup::MachineConfig {
            build_volume_mm: [50.0, 200.0, 150.0],
            ..machine.clone()
        };
        let e = JobSource::new(&text, None, "annulus", &small)
            .err()
            .unwrap();
        assert!(e.contains("10.0 mm too wide along x"), "{e}");
        // A purge pad off the bed.
        let purge = text.replace(
            "[process]",
            "[toolpath]\npurge_xy_mm = [198.0, 5.0]\n\n[process]",
        );
        assert_ne!(purge, text);
        let e = JobSource::new(&purge, None, "annulus", &machine)
            .err()
            .unwrap();
        assert!(e.contains("purge_xy_mm"), "{e}");
    }

    #[test]
    fn a_dry_run_of_any_length_stays_inside_the_build_volume() {
        // 1 mm tall: five 0.2 mm layers, then back to the bottom.
        let volume = BuildVolume::new([200.0, 200.0, 1.0]).unwrap();
        let mut src = DryRunSource::new(100, 10, 2, 1_000);
        let mut marks = Vec::new();
        let mut count = 0;
        while let Some(layer) = src.next_layer() {
            for m in layer.unwrap() {
                assert!(volume.check(&m).is_ok(), "{m:?}");
                if let MoveKind::LayerMark { z_um, .. } = m.kind {
                    marks.push(z_um);
                }
                count += 1;
            }
        }
        assert_eq!(count, 100);
        assert_eq!(marks, [200, 400, 600, 800, 1000, 200, 400, 600, 800, 1000]);
        // A volume lower than one layer: every layer at its top.
        let mut src = DryRunSource::new(6, 3, 1, 150);
        let z: Vec<i32> = std::iter::from_fn(|| src.next_layer())
            .flat_map(|l| l.unwrap())
            .filter_map(|m| match m.kind {
                MoveKind::Extrude { to, .. } => Some(to.z_um),
                _ => None,
            })
            .collect();
        assert_eq!(z, [150, 150, 150, 150]);
    }

    #[tokio::test]
    async fn resume_skips_executed_moves_and_reports_where_it_stands() {
        let source = || Ok(Box::new(DryRunSource::new(25, 10, 2, 150_000)) as Box<dyn LayerSource>);
        let mut rx = spawn(source, 7, 13, 2);
        let mut got = Vec::new();
        let mut resume = None;
        let mut total = None;
        let mut layers = None;
        let mut estimate = None;
        while let Some(m) = rx.recv().await {
            match m {
                PlannerOutput::Estimate(t) => estimate = Some(t),
                PlannerOutput::Layers(count) => {
                    assert!(
                        layers.is_none() && got.is_empty(),
                        "the count comes once, first"
                    );
                    layers = Some(count);
                }
                PlannerOutput::ResumeAt(r) => resume = Some((r.position, r.layer_mark)),
                PlannerOutput::Moves(v) => got.extend(v),
                PlannerOutput::Done { total: t } => total = Some(t),
                PlannerOutput::Failed(e) => panic!("{e}"),
                PlannerOutput::Ended => panic!("not sent by the worker"),
            }
        }
        // The whole job's planned time, from its first move (not only the resumed
        // part): 25 moves, 3 of them layer marks, the others 1 mm at 10 mm/s (the
        // first from an unknown position, a layer's first a step up).
        let estimate = estimate.expect("the estimator's planned time");
        assert_eq!(estimate.moves(), 25);
        assert!(
            (1_900_000..=2_300_000).contains(&estimate.total_us()),
            "{}",
            estimate.total_us()
        );
        assert_eq!(total, Some(25));
        assert_eq!(layers, Some(3));
        assert_eq!(got.first().map(|m| (m.job_id, m.index)), Some((7, 13)));
        assert_eq!(got.len(), 12);
        let (pos, mark) = resume.unwrap();
        assert_eq!(mark, Some((1, 400)));
        assert_eq!(pos.map(|p| p.x_um), Some(0));
    }

    #[tokio::test]
    async fn a_source_that_cannot_be_made_fails_the_run() {
        let mut rx = spawn(|| Err("no job 3".to_string()), 3, 0, 2);
        assert_eq!(
            rx.recv().await,
            Some(PlannerOutput::Failed("no job 3".into()))
        );
        assert_eq!(rx.recv().await, None);
    }
}
