//! Plans kept for the page (`docs/http.md`, Previews and layer views): a preview's
//! layers, its SVG images and a stored job's layer views come from one plan per job
//! content (the job file and its mesh, or a dry run's size), made on a blocking thread
//! and kept, the least recently used dropped first, within `http.plan_cache_entries`
//! plans and `http.plan_cache_bytes` bytes (layer views, SVG previews, job files).
//!
//! A plan goes as far as it is asked: a preview plans every layer (up to
//! [`PREVIEW_LAYERS`]), a layer view up to its layer, and a later request goes on from
//! where the plan stopped. A plan whose layers would pass the byte bound keeps the
//! later ones as a summary only (height, moves); such a layer's view or image is
//! planned again when asked, and not kept.
//!
//! Plans are keyed by a keyed hash (SipHash, two random keys per run: 128 bits) of the
//! content, so a client can neither guess another's preview nor make two contents
//! collide. The cache's list is locked only on blocking threads, never on a runtime
//! worker, and never while a plan is being made.

use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hash, Hasher};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use serde_json::{json, Value};

use super::layers;
use crate::daemon::planner::{JobSource, LayerSource};
use crate::daemon::store::{JobRecord, JobSpec};
use crate::daemon::Config;
use crate::machine::time::{add_used_nl, PlannedTimeBuilder};
use crate::machine::{Move, MoveKind};

/// Most layers a preview plans (the rest are named, not planned).
pub const PREVIEW_LAYERS: u32 = 2000;

/// What a layer's summary (height, moves) is counted as, bytes.
const LAYER_SUMMARY_BYTES: usize = 32;

/// A plan's identity: a keyed hash of what it is made from.
pub type Key = [u64; 2];

/// A key as the page names a preview: 32 hex digits.
pub fn key_hex(k: &Key) -> String {
    format!("{:016x}{:016x}", k[0], k[1])
}

/// The key of `hex`, if it is one.
pub fn parse_key(hex: &str) -> Option<Key> {
    if hex.len() != 32 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    let half = |s: &str| u64::from_str_radix(s, 16).ok();
    Some([half(&hex[..16])?, half(&hex[16..])?])
}

/// What a plan is made from.
#[derive(Clone)]
pub enum Recipe {
    /// A job file not submitted, checked first as a submission would check it.
    Preview { toml: String, mesh: Option<Vec<u8>> },
    /// A stored job, as the streamer plans it.
    Stored {
        job: Box<JobRecord>,
        mesh: Option<Vec<u8>>,
    },
}

impl Recipe {
    /// Bytes it holds (counted against the cache's bound).
    fn bytes(&self) -> usize {
        let (toml, mesh) = match self {
            Recipe::Preview { toml, mesh } => (toml.len(), mesh.as_ref().map_or(0, Vec::len)),
            Recipe::Stored { job, mesh } => match &job.spec {
                JobSpec::Toml { toml, .. } => (toml.len(), mesh.as_ref().map_or(0, Vec::len)),
                JobSpec::DryRun { .. } => (0, 0),
            },
        };
        toml + mesh
    }

    /// Hash what the plan depends on: the job file and the mesh (however it came),
    /// or the dry run's size.
    fn hash_content(&self, h: &mut impl Hasher) {
        match self {
            Recipe::Preview { toml, mesh } => ("job", toml.as_str(), mesh.as_deref()).hash(h),
            Recipe::Stored { job, mesh } => match &job.spec {
                JobSpec::Toml { toml, .. } => ("job", toml.as_str(), mesh.as_deref()).hash(h),
                JobSpec::DryRun { moves } => ("dry-run", *moves).hash(h),
            },
        }
    }

    /// A plan of it, not started: what a submission would refuse, or the layer
    /// source drawing its previews.
    fn start(&self, config: &Config, limits: &crate::mesh::MeshLimits) -> Plan {
        let started = match self {
            Recipe::Preview { toml, mesh } => preview_source(toml, mesh.as_deref(), config, limits),
            Recipe::Stored { job, mesh } => {
                let drives = config.machine.syringes.len();
                crate::daemon::planner::source_of(job, mesh.as_deref(), drives, config)
                    .map(|s| (Some(job.job.name.clone()), s))
                    .map_err(|e| (Some(job.job.name.clone()), e))
            }
        };
        match started {
            Ok((name, mut source)) => {
                source.draw_previews();
                Plan::new(name, Some(source), Vec::new())
            }
            Err((name, problem)) => Plan::new(name, None, vec![problem]),
        }
    }
}

/// A job file's layer source for a preview, after the checks of a submission: its
/// name, or what is wrong (and the name if the file could be read).
#[allow(clippy::type_complexity)]
fn preview_source(
    toml: &str,
    mesh: Option<&[u8]>,
    config: &Config,
    limits: &crate::mesh::MeshLimits,
) -> Result<(Option<String>, Box<dyn LayerSource>), (Option<String>, String)> {
    let job = crate::job::Job::from_toml(toml, "job").map_err(|e| (None, e.to_string()))?;
    let name = Some(job.name.clone());
    layers::fits(&job, mesh, &config.machine, limits).map_err(|p| (name.clone(), p))?;
    let source =
        JobSource::new(toml, mesh, "job", &config.machine).map_err(|e| (name.clone(), e))?;
    Ok((name, Box::new(source)))
}

/// One planned layer.
struct Layer {
    z_mm: Option<f64>,
    moves: usize,
    /// Its view as the page draws it (JSON), unless past the byte bound.
    view: Option<String>,
    /// Its SVG preview, if drawn and not past the byte bound.
    svg: Option<String>,
    /// Whether the view and the image were kept.
    kept: bool,
    /// Its area resting on nothing beyond the allowed overhang, mm² (0 undrawn).
    unsupported_mm2: f64,
    /// Its planned machine time, s.
    time_s: f64,
}

/// What the planned layers take: machine time, material, and where on the bed.
#[derive(Default)]
struct Takes {
    time: PlannedTimeBuilder,
    used_nl: Vec<u64>,
    /// The extrusions' bounds in the machine frame, mm: min and max x, y, z.
    extent_mm: Option<[[f64; 3]; 2]>,
}

impl Takes {
    fn push(&mut self, mv: &Move) {
        self.time.push(mv);
        add_used_nl(&mut self.used_nl, &mv.kind);
        if let MoveKind::Extrude { to, .. } = &mv.kind {
            let p = [to.x_um, to.y_um, to.z_um].map(|v| f64::from(v) / 1000.0);
            let e = self.extent_mm.get_or_insert([p, p]);
            for k in 0..3 {
                e[0][k] = e[0][k].min(p[k]);
                e[1][k] = e[1][k].max(p[k]);
            }
        }
    }

    fn summary(&self) -> Value {
        json!({
            "time_s": self.time.so_far_us() as f64 / 1e6,
            "used_nl": self.used_nl,
            "extent_mm": self.extent_mm.map(|[min, max]| json!({"min": min, "max": max})),
        })
    }
}

/// Which planned layers keep their view and image.
#[derive(Clone, Copy)]
enum Keep {
    /// Every layer while the plan holds at most this many bytes.
    UpTo(usize),
    /// This layer alone (a plan made again for a layer not kept).
    Only(u32),
}

/// A job's plan, as far as it has gone.
pub struct Plan {
    name: Option<String>,
    /// What a submission would refuse, or where planning failed.
    problems: Vec<String>,
    /// Where the layers not planned yet come from; `None` once all are planned (or
    /// planning failed).
    source: Option<Box<dyn LayerSource>>,
    layers: Vec<Layer>,
    /// Where the nozzle stands after the layers planned.
    start: Option<(f64, f64)>,
    total_moves: u64,
    takes: Takes,
    bytes: usize,
    keep: Keep,
    /// Why the last request's planning stopped short of what it asked ([`Stop`]).
    stopped: Option<String>,
    /// The job's allowed overhang (none for a dry run).
    overhang: Option<crate::slice::overhang::Overhang>,
}

/// When a request's planning stops short: its client left, edod is stopping, or it
/// planned longer than `http.plan_time_limit_s`. Checked between layers; the plan
/// stays where it stopped and a later request goes on from there.
#[derive(Clone)]
pub struct Stop {
    /// Set when the request is dropped (its client left) or edod stops.
    pub flags: Vec<Arc<std::sync::atomic::AtomicBool>>,
    /// When the request's time is up.
    pub deadline: std::time::Instant,
    /// `http.plan_time_limit_s`, for the message.
    pub limit_s: f64,
}

impl Stop {
    /// A stop that never comes (a plan made and read at once, in tests).
    pub fn never() -> Stop {
        Stop {
            flags: Vec::new(),
            deadline: std::time::Instant::now() + std::time::Duration::from_secs(86_400 * 365),
            limit_s: f64::INFINITY,
        }
    }

    /// Why planning must stop now, if it must.
    fn reason(&self) -> Option<String> {
        if self.flags.iter().any(|f| f.load(Ordering::Relaxed)) {
            return Some("the request was given up (its client left, or edod stopped)".into());
        }
        (std::time::Instant::now() >= self.deadline).then(|| {
            format!(
                "planning stopped after {} s (http.plan_time_limit_s); ask again to go on",
                self.limit_s
            )
        })
    }
}

/// How far a request needs a plan to go.
#[derive(Clone, Copy, Debug)]
pub enum Want {
    /// Up to this layer (from 0).
    Layer(u32),
    /// Every layer (a preview), up to [`PREVIEW_LAYERS`].
    All,
}

impl Want {
    fn last_layer(self) -> u32 {
        match self {
            Want::Layer(l) => l,
            Want::All => PREVIEW_LAYERS - 1,
        }
    }
}

/// Why a plan cannot answer for a layer.
pub enum Miss {
    /// The layer's view or image was not kept (the plan passed the byte bound).
    NotKept,
    /// No such layer, or no image of it: the reason.
    Refused(crate::proto::ApiError),
}

impl Plan {
    fn new(
        name: Option<String>,
        source: Option<Box<dyn LayerSource>>,
        problems: Vec<String>,
    ) -> Plan {
        Plan {
            name,
            problems,
            overhang: source.as_ref().and_then(|s| s.overhang()),
            source,
            layers: Vec::new(),
            start: None,
            total_moves: 0,
            takes: Takes {
                time: PlannedTimeBuilder::new(),
                ..Takes::default()
            },
            bytes: 0,
            keep: Keep::UpTo(usize::MAX),
            stopped: None,
        }
    }

    /// Whether the plan has gone as far as `want`.
    fn has(&self, want: Want) -> bool {
        self.source.is_none() || self.layers.len() > want.last_layer() as usize
    }

    /// Plan on until `want` is planned, or the job ends, or planning fails, or `stop`
    /// says so.
    fn extend(&mut self, want: Want, stop: &Stop) {
        self.stopped = None;
        let mut planned_here = 0;
        while !self.has(want) {
            // At least one layer a request, so that asking again always goes on.
            if let Some(why) = stop.reason().filter(|_| planned_here > 0) {
                self.stopped = Some(why);
                return;
            }
            planned_here += 1;
            let Some(source) = self.source.as_mut() else {
                return;
            };
            match source.next_layer() {
                Some(Ok(moves)) => self.push(&moves),
                Some(Err(e)) => {
                    self.problems.push(e);
                    self.source = None;
                }
                None => self.source = None,
            }
        }
    }

    /// Keep a layer just planned: its view and SVG preview while within the bound.
    fn push(&mut self, moves: &[Move]) {
        let k = self.layers.len() as u32;
        let (svg, count, unsupported_mm2, roads) = match self.source.as_mut() {
            Some(s) => (
                s.take_preview_svg(),
                s.layer_count(),
                s.take_preview_unsupported_mm2().unwrap_or(0.0),
                s.take_preview_roads().unwrap_or_default(),
            ),
            None => (None, None, 0.0, Vec::new()),
        };
        let mut view = layers::layer_value(k, moves, self.start, &roads);
        view["layers"] = json!(count);
        let view = view.to_string();
        self.start = layers::last_position(moves).or(self.start);
        self.total_moves += moves.len() as u64;
        let before_us = self.takes.time.so_far_us();
        for mv in moves {
            self.takes.push(mv);
        }
        let time_s = (self.takes.time.so_far_us() - before_us) as f64 / 1e6;
        let size = view.len() + svg.as_ref().map_or(0, String::len);
        let kept = match self.keep {
            Keep::UpTo(bound) => self.bytes + size <= bound,
            Keep::Only(l) => l == k,
        };
        self.bytes += LAYER_SUMMARY_BYTES + if kept { size } else { 0 };
        self.layers.push(Layer {
            z_mm: layers::layer_z(moves),
            moves: moves.len(),
            view: kept.then_some(view),
            svg: svg.filter(|_| kept),
            kept,
            unsupported_mm2,
            time_s,
        });
    }

    /// The preview's answer: `{id, ok, name, problems, warnings, layers: [{z_mm, moves,
    /// unsupported_area_mm2, time_s}], total_moves, time_s, used_nl, extent_mm, view}`,
    /// `view` being layer `layer`'s (null if not planned or not kept).
    pub fn summary(&self, key: &Key, layer: u32) -> Value {
        let mut problems = self.problems.clone();
        if let Some(why) = &self.stopped {
            problems.push(format!(
                "only the first {} layers were previewed: {why}",
                self.layers.len()
            ));
        } else if self.source.is_some() {
            problems.push(format!(
                "only the first {PREVIEW_LAYERS} layers were previewed"
            ));
        }
        let takes = self.takes.summary();
        let view = self
            .layers
            .get(layer as usize)
            .and_then(|l| l.view.as_deref())
            .and_then(|v| serde_json::from_str::<Value>(v).ok());
        json!({
            "id": key_hex(key),
            "ok": problems.is_empty(),
            "name": self.name,
            "problems": problems,
            "warnings": self.warnings(),
            "layers": self.layers.iter().map(|l| json!({"z_mm": l.z_mm, "moves": l.moves, "unsupported_area_mm2": l.unsupported_mm2, "time_s": l.time_s})).collect::<Vec<_>>(),
            "total_moves": self.total_moves,
            "time_s": takes["time_s"],
            "used_nl": takes["used_nl"],
            "extent_mm": takes["extent_mm"],
            "view": view,
        })
    }

    /// What the operator should know before submitting: the layers previewed so far
    /// with area resting on nothing beyond the allowed overhang.
    fn warnings(&self) -> Vec<String> {
        let hanging: Vec<(usize, f64)> = self
            .layers
            .iter()
            .enumerate()
            .filter(|(_, l)| l.unsupported_mm2 > crate::slice::overhang::MIN_REPORTED_MM2)
            .map(|(k, l)| (k, l.unsupported_mm2))
            .collect();
        self.overhang
            .and_then(|o| crate::slice::overhang::warning(&o, &hanging))
            .into_iter()
            .collect()
    }

    /// Layer `layer`'s planned layer, or why not.
    fn layer(&self, layer: u32) -> Result<&Layer, Miss> {
        use crate::proto::ApiError;
        match self.layers.get(layer as usize) {
            Some(l) if l.kept => Ok(l),
            Some(_) => Err(Miss::NotKept),
            None if self.stopped.is_some() => Err(Miss::Refused(ApiError::new(
                ApiError::LIMIT,
                format!(
                    "layer {layer} was not planned: {}",
                    self.stopped.as_deref().unwrap_or_default()
                ),
            ))),
            None if self.problems.is_empty() => Err(Miss::Refused(ApiError::new(
                ApiError::INVALID_PARAMS,
                format!("the job has no layer {layer} (layers count from 0)"),
            ))),
            None => Err(Miss::Refused(ApiError::new(
                ApiError::INVALID_JOB,
                self.problems.join("; "),
            ))),
        }
    }

    /// Layer `layer`'s view (JSON text), or why not.
    pub fn view(&self, layer: u32) -> Result<String, Miss> {
        self.layer(layer)
            .map(|l| l.view.clone().unwrap_or_else(|| "null".into()))
    }

    /// Layer `layer`'s SVG preview, or why not.
    pub fn svg(&self, layer: u32) -> Result<String, Miss> {
        let l = self.layer(layer)?;
        l.svg.clone().ok_or_else(|| {
            Miss::Refused(crate::proto::ApiError::new(
                crate::proto::ApiError::NO_SUCH_JOB,
                format!("layer {layer} has no preview image (a dry run draws none)"),
            ))
        })
    }
}

/// One kept plan.
pub struct Entry {
    key: Key,
    recipe: Recipe,
    plan: Mutex<Plan>,
    /// The plan's bytes and the recipe's, as last counted.
    bytes: AtomicUsize,
}

impl Entry {
    /// The plan, locked (on a blocking thread only).
    fn lock(&self) -> MutexGuard<'_, Plan> {
        self.plan.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The plans kept, least recently used first.
pub struct PlanCache {
    entries: Mutex<Vec<Arc<Entry>>>,
    seeds: [RandomState; 2],
    max_entries: usize,
    max_bytes: usize,
    plans_made: AtomicU64,
}

impl PlanCache {
    /// A cache of at most `max_entries` plans and `max_bytes` bytes.
    pub fn new(max_entries: usize, max_bytes: usize) -> PlanCache {
        PlanCache {
            entries: Mutex::new(Vec::new()),
            seeds: [RandomState::new(), RandomState::new()],
            max_entries: max_entries.max(1),
            max_bytes,
            plans_made: AtomicU64::new(0),
        }
    }

    /// Plans started since edod started (each planned from its first layer).
    pub fn plans_made(&self) -> u64 {
        self.plans_made.load(Ordering::Relaxed)
    }

    /// Plans kept, and the bytes they hold.
    pub fn held(&self) -> (usize, usize) {
        let list = self.list();
        let bytes = list.iter().map(|e| e.bytes.load(Ordering::Relaxed)).sum();
        (list.len(), bytes)
    }

    fn list(&self) -> MutexGuard<'_, Vec<Arc<Entry>>> {
        self.entries.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The key of `recipe`.
    pub fn key(&self, recipe: &Recipe) -> Key {
        self.seeds.each_ref().map(|s| {
            let mut h = s.build_hasher();
            recipe.hash_content(&mut h);
            h.finish()
        })
    }

    /// The plan kept under `key`, now the most recently used.
    pub fn get(&self, key: &Key) -> Option<Arc<Entry>> {
        let mut list = self.list();
        let at = list.iter().position(|e| e.key == *key)?;
        let e = list.remove(at);
        list.push(Arc::clone(&e));
        Some(e)
    }

    /// The plan of `recipe`, kept or started (and kept).
    fn get_or_start(
        &self,
        key: Key,
        recipe: Recipe,
        config: &Config,
        limits: &crate::mesh::MeshLimits,
    ) -> Arc<Entry> {
        if let Some(e) = self.get(&key) {
            return e;
        }
        let mut plan = self.start(&recipe, config, limits);
        let recipe_bytes = recipe.bytes();
        plan.keep = Keep::UpTo(self.max_bytes.saturating_sub(recipe_bytes));
        let e = Arc::new(Entry {
            key,
            recipe,
            plan: Mutex::new(plan),
            bytes: AtomicUsize::new(recipe_bytes),
        });
        self.list().push(Arc::clone(&e));
        self.trim(&e);
        e
    }

    fn start(&self, recipe: &Recipe, config: &Config, limits: &crate::mesh::MeshLimits) -> Plan {
        self.plans_made.fetch_add(1, Ordering::Relaxed);
        recipe.start(config, limits)
    }

    /// Drop the least recently used plans, but `current`, until the rest are within
    /// the bounds.
    fn trim(&self, current: &Arc<Entry>) {
        let mut list = self.list();
        let mut total: usize = list.iter().map(|e| e.bytes.load(Ordering::Relaxed)).sum();
        let mut k = 0;
        while k < list.len() && (list.len() > self.max_entries || total > self.max_bytes) {
            if Arc::ptr_eq(&list[k], current) {
                k += 1;
                continue;
            }
            let gone = list.remove(k);
            total -= gone.bytes.load(Ordering::Relaxed);
        }
    }

    /// Plan `entry` on as far as `want` (the caller holds the one place to plan).
    fn extend(&self, entry: &Arc<Entry>, want: Want, stop: &Stop) {
        {
            let mut plan = entry.lock();
            plan.extend(want, stop);
            entry
                .bytes
                .store(plan.bytes + entry.recipe.bytes(), Ordering::Relaxed);
        }
        self.trim(entry);
    }

    /// `read` of a plan of `recipe` made again, not kept, keeping layer `layer` alone
    /// (for a layer the kept plan could not keep).
    fn read_again<T>(
        &self,
        recipe: &Recipe,
        layer: u32,
        config: &Config,
        limits: &crate::mesh::MeshLimits,
        read: impl Fn(&Plan) -> Result<T, Miss>,
        stop: &Stop,
    ) -> Result<T, Miss> {
        let mut plan = self.start(recipe, config, limits);
        plan.keep = Keep::Only(layer);
        plan.extend(Want::Layer(layer), stop);
        read(&plan)
    }
}

/// Where a request's plan comes from.
pub enum Find {
    /// Made from this recipe if not kept.
    Recipe(Recipe),
    /// Kept under this key (a preview's id), or nowhere.
    Key(Key),
}

/// What planning needs, on a blocking thread.
#[derive(Clone)]
pub struct Planning {
    pub cache: Arc<PlanCache>,
    pub config: Config,
    pub limits: crate::mesh::MeshLimits,
}

/// A plan's answer, read on a blocking thread.
pub type Answer<T> = Result<T, crate::proto::ApiError>;

impl Planning {
    /// Without planning: `read` of the kept plan if it has gone as far as `want`;
    /// `None` if it must be planned on (or made).
    pub fn lookup<T>(
        &self,
        find: &Find,
        want: Want,
        read: &dyn Fn(&Key, &Plan) -> Result<T, Miss>,
    ) -> Option<Answer<T>> {
        let key = match find {
            Find::Recipe(r) => self.cache.key(r),
            Find::Key(k) => *k,
        };
        let Some(e) = self.cache.get(&key) else {
            return match find {
                Find::Key(k) => Some(Err(no_preview(k))),
                Find::Recipe(_) => None,
            };
        };
        let plan = e.lock();
        if !plan.has(want) {
            return None;
        }
        match read(&key, &plan) {
            Ok(v) => Some(Ok(v)),
            Err(Miss::Refused(e)) => Some(Err(e)),
            Err(Miss::NotKept) => None,
        }
    }

    /// Plan as far as `want` (the caller holds the one place to plan), then `read`;
    /// a layer the kept plan could not keep is planned again, not kept.
    pub fn plan<T>(
        &self,
        find: Find,
        want: Want,
        read: &dyn Fn(&Key, &Plan) -> Result<T, Miss>,
        stop: &Stop,
    ) -> Answer<T> {
        let entry = match find {
            Find::Recipe(r) => {
                let key = self.cache.key(&r);
                self.cache.get_or_start(key, r, &self.config, &self.limits)
            }
            Find::Key(k) => self.cache.get(&k).ok_or_else(|| no_preview(&k))?,
        };
        self.cache.extend(&entry, want, stop);
        let first = read(&entry.key, &entry.lock());
        match first {
            Ok(v) => Ok(v),
            Err(Miss::Refused(e)) => Err(e),
            Err(Miss::NotKept) => {
                let again = self.cache.read_again(
                    &entry.recipe,
                    want.last_layer(),
                    &self.config,
                    &self.limits,
                    |p| read(&entry.key, p),
                    stop,
                );
                again.map_err(|m| match m {
                    Miss::Refused(e) => e,
                    Miss::NotKept => crate::proto::ApiError::new(
                        crate::proto::ApiError::INTERNAL,
                        "the layer planned again was not kept",
                    ),
                })
            }
        }
    }
}

fn no_preview(k: &Key) -> crate::proto::ApiError {
    crate::proto::ApiError::new(
        crate::proto::ApiError::NO_SUCH_JOB,
        format!(
            "no preview {}: it was never made or no longer kept (http.plan_cache_entries, \
             http.plan_cache_bytes); preview the job again",
            key_hex(k)
        ),
    )
}
