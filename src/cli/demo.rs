//! `edoctl demo`: edo end to end on the simulated machine, in one command.
//!
//! It starts edod (in this process, with its own temporary state directory and socket)
//! on hil-sim (the simulator binary on a pseudo-terminal, with its recorder on), submits
//! the bundled tooth-crown job (`config/examples/tooth-crown.toml`: enamel graded over a
//! 3 mm shell into dentin) over the socket exactly as `edoctl submit` does, shows the
//! progress bar, and when the machine has executed the last move:
//!
//! - plans the same job offline with the same settings and checks that the machine
//!   executed exactly the planned moves (same count, every index once, in order, same
//!   per-syringe volumes and positions);
//! - compares the composition that left the nozzle (the simulator's mixing chamber:
//!   plug flow, or with `--mixer` a well-mixed or dispersing one) with the designed
//!   composition of each road, and with `--mixer` the planner's prediction with the
//!   mixer's feed-forward on and off;
//! - measures the planned roads' coverage (void, overlap, outside at 10 µm);
//! - writes per layer the planned roads and the as-built roads side by side
//!   (`layer-NNNN.svg`), the summary (`summary.json`) and the machine's recording
//!   (`record.jsonl`, format in `hil-sim/README.md`) to `--out`.
//!
//! With `--port PATH --record FILE` it uses a machine that is already running (a hil-sim
//! started with `--link PATH --record FILE`) instead of starting one.
//!
//! With `--firmware rrf|marlin|klipper` edod streams G-code to that firmware instead
//! (`machine.protocol = "gcode"`, `docs/firmware.md`; the simulator runs as
//! `hil-sim --gcode FIRMWARE`), and the recording is matched to the plan by the lines
//! each move becomes ([`gcode`]).

mod gcode;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde::Serialize;
use serde_json::json;

use super::client::{watch, Client};
use crate::daemon::Config;
use crate::gcode_link::writer::GcodeSettings;
use crate::job::placement::{place_part, placed_settings};
use crate::job::Job;
use crate::machine::record::{self, RecordLine};
use crate::machine::MoveKind;
use crate::pipeline::{LayerMoves, StreamState};

pub use crate::gcode_link::Dialect;

/// The bundled job.
pub const DEMO_JOB: &str = include_str!("../../config/examples/tooth-crown.toml");

/// V_dead of the demo machine's mixing chamber, nl.
pub const DEMO_DEAD_VOLUME_NL: u64 = 1000;

/// Options of `edoctl demo`.
#[derive(clap::Args, Debug, Clone)]
pub struct DemoArgs {
    /// Where to write the side-by-side previews and summary.json.
    #[arg(long, value_name = "DIR", default_value = "out/demo")]
    pub out: PathBuf,
    /// Machine time runs this many times faster than wall time.
    #[arg(long, value_name = "X", default_value_t = 25.0)]
    pub speed: f64,
    /// The hil-sim executable (default: next to edoctl; under `cargo run` it is built
    /// on first use).
    #[arg(long, value_name = "PATH")]
    pub sim_binary: Option<PathBuf>,
    /// Use a machine that is already running on PATH instead of starting hil-sim
    /// (needs --record: the recording that machine writes).
    #[arg(long, value_name = "PATH", requires = "record")]
    pub port: Option<PathBuf>,
    /// The recording of the machine given with --port.
    #[arg(long, value_name = "FILE", requires = "port")]
    pub record: Option<PathBuf>,
    /// Stream G-code to this firmware (the simulator runs as `hil-sim --gcode FIRMWARE`;
    /// with --port, a machine started so) instead of over edo's own link.
    #[arg(long, value_name = "FIRMWARE", value_enum)]
    pub firmware: Option<Dialect>,
    /// The machine's mixing chamber (edod's `[machine.mixer]`; volume default 1000 nl):
    /// the simulator builds through it and edod plans for it (with --port, a machine
    /// started with the same `hil-sim --mixer`).
    #[command(flatten)]
    pub mixer: crate::cli::plan::MixerArgs,
}

/// The job the demo submits: the bundled crown, without the mixer's feed-forward
/// (`--no-feed-forward`) as its `[toolpath] mixer_feed_forward = false`.
fn demo_job_text(feed_forward: bool) -> String {
    if !feed_forward {
        format!("{DEMO_JOB}\n[toolpath]\nmixer_feed_forward = false\n")
    } else {
        DEMO_JOB.to_string()
    }
}

/// The predicted nozzle-exit error road by road, with the mixer's feed-forward on and
/// off (`--mixer` other than plug only).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FeedForwardErrors {
    pub on: CompositionError,
    pub off: CompositionError,
    /// Roads over `mixer_tolerance` (0.01) as planned for the print.
    pub mixer_limited_roads: usize,
}

/// Designed-versus-built composition error: the largest volume-fraction difference
/// between a road's designed composition and what left the nozzle there.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct CompositionError {
    /// Extrusion-volume-weighted mean.
    pub mean: f64,
    /// Worst move.
    pub max: f64,
}

impl CompositionError {
    /// The volume-weighted mean and the worst of (error, volume) samples (0 for none).
    fn of(samples: impl IntoIterator<Item = (f64, f64)>) -> Self {
        let (mut sum, mut volume, mut max) = (0.0, 0.0, 0.0f64);
        for (err, v) in samples {
            sum += err * v;
            volume += v;
            max = max.max(err);
        }
        CompositionError {
            mean: if volume > 0.0 { sum / volume } else { 0.0 },
            max,
        }
    }
}

/// What `edoctl demo` prints (and writes to `summary.json`).
#[derive(Debug, Clone, Serialize)]
pub struct DemoSummary {
    pub job: String,
    pub job_id: u64,
    pub state: String,
    pub layers: usize,
    pub moves_planned: u64,
    pub moves_executed: u64,
    /// Every planned move executed once, in order, with the planned volumes and positions.
    pub executed_as_planned: bool,
    /// The first difference found, if any.
    pub mismatch: Option<String>,
    /// Built (simulator's nozzle exit) against designed, move by move. Moves carry whole
    /// nanolitres per syringe (cumulatively rounded), so on moves of about 10 nl each
    /// move's ratio is off by up to 1/20 while the road as a whole is not.
    pub composition_error_built: CompositionError,
    /// Built against designed road by road: what left the nozzle over each road.
    pub composition_error_built_per_road: CompositionError,
    /// Median volume of an extrusion move, nl.
    pub extrude_move_nl: f64,
    /// The planner's own plug-flow prediction of the same error (with the mixing lead).
    pub composition_error_predicted: CompositionError,
    /// Coverage of the planned roads at 10 µm (fractions of the part area).
    pub void_fraction: f64,
    pub overlap_fraction: f64,
    pub outside_fraction: f64,
    /// Volume pushed per syringe, µL (planned; the recording matches it exactly when
    /// `executed_as_planned`).
    pub syringe_volumes_ul: Vec<f64>,
    /// Wall time from submission to the last move executed, s.
    pub print_time_s: f64,
    /// Machine (simulated) time of the print, s.
    pub machine_time_s: f64,
    /// Wall time of the whole demo, s.
    pub total_time_s: f64,
    /// The previews and summary.
    pub out_dir: PathBuf,
    /// `--firmware`: the firmware streamed to over G-code (absent on edo's link).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub firmware: Option<String>,
    /// `--firmware`: the planned moves' motion lines (`G0`, `G1`, `G4`, `G28`) and the
    /// commands that moved the machine ran; `executed_as_planned` then means those ran
    /// one for one, in order.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gcode_lines_planned: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gcode_lines_executed: Option<u64>,
    /// `--mixer`: the machine's mixing chamber.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mixer: Option<crate::mixer::MixerOptions>,
    /// `--mixer` other than plug: whether the print used the mixer's feed-forward, and
    /// the planner's road-by-road prediction with it on and off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub feed_forward: Option<(bool, FeedForwardErrors)>,
}

/// Run the demo; the exit status is failure unless the job finished and the machine
/// executed exactly what was planned.
pub fn run(args: &DemoArgs, json_out: bool) -> Result<ExitCode> {
    let started = Instant::now();
    let work = std::env::temp_dir().join(format!("edo-demo-{}", std::process::id()));
    std::fs::create_dir_all(&work).with_context(|| format!("cannot create {}", work.display()))?;
    let result = run_in(args, json_out, &work, started);
    let _ = std::fs::remove_dir_all(&work);
    let summary = result?;
    if json_out {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        print!("{}", human(&summary));
    }
    Ok(if summary.state == "done" && summary.executed_as_planned {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// The demo in the work directory `work`: print the job on edod and the machine, then
/// compare the recording with the plan, draw the previews and write the summary.
fn run_in(args: &DemoArgs, json_out: bool, work: &Path, started: Instant) -> Result<DemoSummary> {
    let feed_forward = !args.mixer.no_feed_forward;
    let job_text = demo_job_text(feed_forward);
    let job = Job::from_toml(&job_text, "tooth-crown.toml (bundled)")?;
    let (cfg, record_path) = demo_config(args, work)?;
    let machine = cfg.machine.clone();
    let writing = gcode_writing(&cfg)?;
    let (final_job, print_time_s) = print_on_edod(cfg, &job, &job_text, args, json_out)?;

    let record_text = std::fs::read_to_string(&record_path)
        .with_context(|| format!("cannot read the recording {}", record_path.display()))?;
    let recording = record::parse(&record_text).context("the machine's recording")?;
    let job_id = final_job["id"].as_u64().unwrap_or(0);
    let planned = plan_offline(&job, &machine)?;
    let feed_forward_errors = match machine.mixer() {
        Ok(m) if m.model != crate::mixer::MixerModel::Plug => {
            let other = Job::from_toml(&demo_job_text(!feed_forward), "tooth-crown.toml")?;
            let other = predicted_per_road(&plan_offline(&other, &machine)?.layers);
            let this = predicted_per_road(&planned.layers);
            let (on, off) = if feed_forward {
                (this, other)
            } else {
                (other, this)
            };
            Some(FeedForwardErrors {
                on,
                off,
                mixer_limited_roads: planned
                    .layers
                    .iter()
                    .map(|l| l.stats.mixer_limited_roads)
                    .sum(),
            })
        }
        _ => None,
    };
    let executed = Executed::of(&planned.layers, recording, job_id as u32, writing)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let coverage = previews(&job, &planned, &executed.records, job_id as u32, &args.out)?;
    let kept = args.out.join("record.jsonl");
    if record_path != kept {
        std::fs::write(&kept, &record_text)
            .with_context(|| format!("cannot write {}", kept.display()))?;
    }
    let summary = DemoSummary {
        job: job.name.clone(),
        job_id,
        state: final_job["state"].as_str().unwrap_or("unknown").to_string(),
        print_time_s,
        total_time_s: started.elapsed().as_secs_f64(),
        out_dir: args.out.clone(),
        firmware: args.firmware.map(|f| f.display_name().to_string()),
        mixer: machine.mixer.as_ref().and_then(|_| machine.mixer().ok()),
        feed_forward: feed_forward_errors.map(|e| (feed_forward, e)),
        ..summarize(&planned, &executed, &coverage)
    };
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(summary)
}

/// What the machine executed of the job, as records of the planned moves.
struct Executed {
    /// The job's records (on the G-code link: matched to the planned moves by lines).
    records: Vec<RecordLine>,
    moves: u64,
    mismatch: Option<String>,
    /// G-code link: motion lines planned and ran.
    lines: Option<(u64, u64)>,
}

impl Executed {
    /// The job `job_id`'s part of `recording`, compared with `planned`; `writing`: the
    /// G-code link's lines (`None`: edo's link).
    fn of(
        planned: &[LayerMoves],
        recording: Vec<RecordLine>,
        job_id: u32,
        writing: Option<(GcodeSettings, usize)>,
    ) -> Result<Self> {
        if let Some((settings, drives)) = writing {
            let m = gcode::match_lines(planned, &recording, drives, &settings, job_id)?;
            return Ok(Executed {
                records: m.records,
                moves: m.moves_executed,
                mismatch: m.mismatch,
                lines: Some((m.lines_planned, m.lines_executed)),
            });
        }
        let records: Vec<RecordLine> = recording
            .into_iter()
            .filter(|l| l.job_id == job_id)
            .collect();
        let refs: Vec<&RecordLine> = records.iter().collect();
        let mismatch = compare(planned, &refs);
        Ok(Executed {
            moves: records.len() as u64,
            records,
            mismatch,
            lines: None,
        })
    }
}

/// The summary's figures from the plan, the execution and the coverage (the job's
/// identity, state, times and output directory are the caller's).
fn summarize(
    planned: &Planned,
    executed: &Executed,
    coverage: &crate::toolpath::coverage::Coverage,
) -> DemoSummary {
    let records: Vec<&RecordLine> = executed.records.iter().collect();
    let (built, built_per_road, predicted) = composition_errors(&planned.layers, &records);
    DemoSummary {
        job: String::new(),
        job_id: 0,
        state: String::new(),
        layers: planned.layers.len(),
        moves_planned: planned.moves,
        moves_executed: executed.moves,
        executed_as_planned: executed.mismatch.is_none(),
        mismatch: executed.mismatch.clone(),
        composition_error_built: built,
        composition_error_built_per_road: built_per_road,
        extrude_move_nl: median_extrusion_nl(&records),
        composition_error_predicted: predicted,
        void_fraction: coverage.void_fraction(),
        overlap_fraction: coverage.overlap_fraction(),
        outside_fraction: coverage.outside_fraction(),
        syringe_volumes_ul: planned
            .state
            .commanded_nl()
            .iter()
            .map(|&nl| nl as f64 / 1000.0)
            .collect(),
        print_time_s: 0.0,
        machine_time_s: records.last().map_or(0.0, |l| l.t_s)
            - records.first().map_or(0.0, |l| l.t_s),
        total_time_s: 0.0,
        out_dir: PathBuf::new(),
        firmware: None,
        gcode_lines_planned: executed.lines.map(|l| l.0),
        gcode_lines_executed: executed.lines.map(|l| l.1),
        mixer: None,
        feed_forward: None,
    }
}

/// The G-code link's writing (settings and syringes) with `machine.protocol = "gcode"`.
fn gcode_writing(cfg: &Config) -> Result<Option<(GcodeSettings, usize)>> {
    let link = cfg
        .gcode_link()
        .map_err(|(key, why)| anyhow::anyhow!("{key}: {why}"))?;
    Ok(link.map(|g| (g.settings(), cfg.machine.syringes.len())))
}

/// edod's configuration for the demo, and the recording the machine writes: hil-sim
/// started by edod (recording into `work`), or the machine of `--port`.
fn demo_config(args: &DemoArgs, work: &Path) -> Result<(Config, PathBuf)> {
    let mut cfg = match args.firmware {
        None => Config::from_toml("", "demo")?,
        Some(f) => Config::from_toml(&gcode::machine_toml(f), "demo")?,
    };
    let record_path = match (&args.port, &args.record) {
        (Some(port), Some(rec)) => {
            cfg.serial.port = port.display().to_string();
            rec.clone()
        }
        _ => {
            let rec = work.join("record.jsonl");
            cfg.sim.binary = Some(sim_binary(args.sim_binary.as_deref())?);
            cfg.sim.speed = args.speed;
            cfg.sim.record = Some(rec.clone());
            rec
        }
    };
    if !(args.speed.is_finite() && args.speed > 0.0) {
        bail!("--speed must be a positive number, got {}", args.speed);
    }
    // A 1 µL mixing chamber: the crown is small (about 80 µL in all), and the default
    // 20 µL chamber of config/edod.toml would hold a quarter of the part.
    cfg.machine.dead_volume_nl = DEMO_DEAD_VOLUME_NL;
    if let Some(model) = &args.mixer.mixer {
        cfg.machine.mixer = Some(crate::setup::MixerConfig {
            model: model.clone(),
            volume_nl: args.mixer.mixer_volume_nl,
            peclet: args.mixer.mixer_peclet,
        });
        cfg.machine
            .mixer()
            .map_err(|e| anyhow::anyhow!("{}: {}", e.option(), e.message))?;
    }
    cfg.api.socket = work.join("edod.sock");
    cfg.state.dir = work.join("state");
    // No dashboard: the demo watches edod through its socket, and an edod already
    // serving its dashboard on the host must not stop the demo.
    cfg.http.enabled = false;
    Ok((cfg, record_path))
}

/// Run edod with `cfg` in this process (on its own runtime thread), print `job` through
/// it and stop it: the job as edod last reported it, and the print's wall time (s).
fn print_on_edod(
    cfg: Config,
    job: &Job,
    job_text: &str,
    args: &DemoArgs,
    json_out: bool,
) -> Result<(serde_json::Value, f64)> {
    let socket = cfg.api.socket.clone();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let daemon = std::thread::spawn(move || -> Result<()> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        rt.block_on(crate::daemon::run_until(cfg, async {
            let _ = stop_rx.await;
        }))
    });
    let stop_daemon = move || -> Result<()> {
        let _ = stop_tx.send(());
        match daemon.join() {
            Ok(r) => r.context("edod"),
            Err(_) => bail!("edod stopped abnormally"),
        }
    };
    let printed = submit_and_watch(&socket, job, job_text, args, json_out);
    let stopped = stop_daemon();
    let printed = printed?;
    stopped?;
    Ok(printed)
}

/// Wait for the machine to connect, submit the job as `edoctl submit` does and follow
/// it to its end.
fn submit_and_watch(
    socket: &Path,
    job: &Job,
    job_text: &str,
    args: &DemoArgs,
    json_out: bool,
) -> Result<(serde_json::Value, f64)> {
    let mut c = connect(socket)?;
    let t = Instant::now();
    loop {
        let m = c.call("machine.status", json!({}))?;
        if m["connected"] == json!(true) {
            break;
        }
        if t.elapsed() > Duration::from_secs(15) {
            bail!("the simulated machine did not connect within 15 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let submitted = Instant::now();
    let r = c.call(
        "job.submit",
        json!({"job": job_text, "name": format!("{} (demo)", job.name)}),
    )?;
    let id = r["id"]
        .as_u64()
        .and_then(|i| u32::try_from(i).ok())
        .context("edod returned no job id")?;
    if !json_out {
        let over = match args.firmware {
            Some(f) => format!(", G-code to {}", f.display_name()),
            None => String::new(),
        };
        eprintln!(
            "edoctl demo: printing {:?} on the simulated machine ({}x speed{over})",
            job.name, args.speed
        );
    }
    let j = watch(&mut c, id, json_out)?.json;
    Ok((j, submitted.elapsed().as_secs_f64()))
}

/// Connect to the demo's edod, waiting for its socket.
fn connect(socket: &Path) -> Result<Client> {
    let t = Instant::now();
    loop {
        match Client::connect(socket) {
            Ok(c) => return Ok(c),
            Err(e) if t.elapsed() > Duration::from_secs(15) => return Err(e),
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

/// The hil-sim executable: `explicit`, else next to this program; under `cargo run`
/// (which sets `CARGO` and `CARGO_MANIFEST_DIR`) it is built there once, with the same
/// profile, the way an xtask builds its tools.
fn sim_binary(explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = explicit {
        if !p.is_file() {
            bail!("--sim-binary {}: no such file", p.display());
        }
        return Ok(p.to_path_buf());
    }
    let exe = std::env::current_exe().context("cannot locate edoctl")?;
    let dir = exe.parent().map(Path::to_path_buf).unwrap_or_default();
    let beside = dir.join("hil-sim");
    if beside.is_file() {
        return Ok(beside);
    }
    if let (Some(cargo), Some(manifest)) = (
        std::env::var_os("CARGO"),
        std::env::var_os("CARGO_MANIFEST_DIR"),
    ) {
        let profile = match dir.file_name().and_then(|n| n.to_str()) {
            Some("debug") | None => "dev".to_string(),
            Some(p) => p.to_string(),
        };
        eprintln!("edoctl demo: building the simulated machine (hil-sim) once ...");
        let status = std::process::Command::new(cargo)
            .args([
                "build",
                "--quiet",
                "--package",
                "hil-sim",
                "--bin",
                "hil-sim",
            ])
            .args(["--profile", &profile, "--manifest-path"])
            .arg(Path::new(&manifest).join("Cargo.toml"))
            .status()
            .context("cannot run cargo to build hil-sim")?;
        if status.success() && beside.is_file() {
            return Ok(beside);
        }
    }
    bail!(
        "the simulated machine `hil-sim` is not next to {} ; build it with `cargo build --release -p hil-sim` or pass --sim-binary PATH",
        exe.display()
    )
}

/// The job planned offline exactly as edod plans it for this machine.
struct Planned {
    layers: Vec<LayerMoves>,
    islands: Vec<Vec<crate::geom::Region>>,
    moves: u64,
    state: StreamState,
    road_width_mm: f64,
    /// Where edod puts the part on the bed (the moves are placed; `layers`' paths and
    /// `islands` stay in the part's coordinates).
    placement: crate::job::placement::Placement,
}

fn plan_offline(job: &Job, machine: &crate::setup::MachineConfig) -> Result<Planned> {
    let settings =
        crate::setup::process_settings(job, machine, &job.name).map_err(anyhow::Error::msg)?;
    let bounds = job
        .extruded_bounds()
        .context("the demo job is an extruded polygon")?;
    let volume = machine.build_volume().map_err(anyhow::Error::msg)?;
    let placement = place_part(job, bounds, &volume).map_err(anyhow::Error::msg)?;
    let settings = placed_settings(&settings, &placement);
    let stack = job
        .extruded_layers()
        .context("the demo job is an extruded polygon")?;
    let slices = job.layer_slices(0, stack);
    let plans = crate::plan::plan_layers(&slices, &job.plan, None)?;
    let mut state = StreamState::new();
    let first = crate::pipeline::FIRST_LAYER_MOVE_INDEX;
    let mut layers = crate::pipeline::job_layer_moves(&plans, &settings, 0, first, &mut state)?;
    // edod homes first (its planner's move 0).
    if let Some(lm) = layers.first_mut() {
        lm.moves.insert(0, crate::pipeline::home_move(0));
    }
    for lm in &mut layers {
        placement
            .put_on_machine(&mut lm.moves, &volume)
            .map_err(anyhow::Error::msg)?;
    }
    let next = layers.last().map_or(0, |lm| lm.next_index);
    Ok(Planned {
        layers,
        islands: slices.into_iter().map(|s| s.layer.islands).collect(),
        moves: u64::from(next),
        state,
        road_width_mm: settings.road_width(),
        placement,
    })
}

/// The first way the execution differs from the plan, if any.
fn compare(planned: &[LayerMoves], executed: &[&RecordLine]) -> Option<String> {
    let moves: Vec<_> = planned.iter().flat_map(|l| &l.moves).collect();
    if moves.len() != executed.len() {
        return Some(format!(
            "{} moves planned, {} executed",
            moves.len(),
            executed.len()
        ));
    }
    for (m, e) in moves.iter().zip(executed) {
        if m.index != e.index {
            return Some(format!(
                "move {} executed where {} was planned",
                e.index, m.index
            ));
        }
        let (to, volumes) = match &m.kind {
            MoveKind::Extrude { to, volumes_nl, .. } => (Some(to), Some(volumes_nl)),
            MoveKind::Travel { to, .. } => (Some(to), None),
            MoveKind::Retract { volumes_nl, .. } | MoveKind::Prime { volumes_nl, .. } => {
                (None, Some(volumes_nl))
            }
            _ => (None, None),
        };
        if let Some(v) = volumes {
            if *v != e.volumes_nl {
                return Some(format!(
                    "move {}: volumes {:?} nl executed, {:?} planned",
                    m.index, e.volumes_nl, v
                ));
            }
        }
        if let Some(to) = to {
            let want = [to.x_um, to.y_um, to.z_um].map(|v| f64::from(v) / 1000.0);
            if want.iter().zip(&e.to_mm).any(|(a, b)| (a - b).abs() > 1e-6) {
                return Some(format!(
                    "move {}: ended at {:?} mm, planned {:?} mm",
                    m.index, e.to_mm, want
                ));
            }
        }
    }
    None
}

/// The median volume of the executed moves that extrude, nl (0 if none do).
fn median_extrusion_nl(executed: &[&RecordLine]) -> f64 {
    let mut v: Vec<u64> = executed
        .iter()
        .filter(|e| e.exit_composition.is_some())
        .map(|e| e.volumes_nl.iter().map(|&x| u64::from(x)).sum())
        .collect();
    v.sort_unstable();
    v.get(v.len() / 2).map_or(0.0, |&x| x as f64)
}

/// Built (recorded nozzle exit) and predicted (planner's plug-flow model) composition
/// errors against the designed composition of each road: the built error per move and
/// per road (what left the nozzle over the whole road), and the predicted one.
fn composition_errors(
    planned: &[LayerMoves],
    executed: &[&RecordLine],
) -> (CompositionError, CompositionError, CompositionError) {
    // Move index -> (layer, road) and the road's designed composition.
    let mut designed: std::collections::HashMap<u32, ((usize, u32), &[f64])> = Default::default();
    for (k, l) in planned.iter().enumerate() {
        for &(index, path) in &l.extrusion_paths {
            if let Some(p) = l.paths.get(path as usize) {
                designed.insert(index, ((k, path), &p.composition));
            }
        }
    }
    use crate::material::max_fraction_difference;
    // Per road (layer, path): its designed composition, the volume so far and the
    // volume-weighted exit composition.
    type RoadExit<'a> = (&'a [f64], f64, Vec<f64>);
    let mut roads: std::collections::BTreeMap<(usize, u32), RoadExit> = Default::default();
    let mut per_move = Vec::new();
    for e in executed {
        let (Some(&(road, d)), Some(exit)) = (designed.get(&e.index), &e.exit_composition) else {
            continue;
        };
        let v: f64 = e.volumes_nl.iter().map(|&x| f64::from(x)).sum();
        per_move.push((max_fraction_difference(d, exit), v));
        let r = roads
            .entry(road)
            .or_insert_with(|| (d, 0.0, vec![0.0; exit.len()]));
        r.1 += v;
        for (acc, x) in r.2.iter_mut().zip(exit) {
            *acc += x * v;
        }
    }
    let built = CompositionError::of(per_move);
    let built_per_road =
        CompositionError::of(roads.values().filter(|r| r.1 > 0.0).map(|(d, v, acc)| {
            let exit: Vec<f64> = acc.iter().map(|x| x / v).collect();
            (max_fraction_difference(d, &exit), *v)
        }));
    let predicted = CompositionError {
        // The planner reports each layer's mean and worst.
        max: planned
            .iter()
            .map(|l| l.stats.composition_error_max)
            .fold(0.0, f64::max),
        ..CompositionError::of(planned.iter().map(|l| {
            (
                l.stats.composition_error_mean,
                l.stats.planned_nl.iter().sum(),
            )
        }))
    };
    (built, built_per_road, predicted)
}

/// The planner's predicted nozzle-exit error road by road over the layers.
fn predicted_per_road(layers: &[LayerMoves]) -> CompositionError {
    CompositionError {
        max: layers
            .iter()
            .map(|l| l.stats.composition_error_road_max)
            .fold(0.0, f64::max),
        ..CompositionError::of(layers.iter().map(|l| {
            (
                l.stats.composition_error_road_mean,
                l.stats.planned_nl.iter().sum(),
            )
        }))
    }
}

/// Write `layer-NNNN.svg` (planned roads with voids | as built) per layer; returns the
/// planned roads' coverage summed over the layers.
fn previews(
    job: &Job,
    planned: &Planned,
    recording: &[RecordLine],
    job_id: u32,
    out: &Path,
) -> Result<crate::toolpath::coverage::Coverage> {
    // As built on the machine, drawn in the part's coordinates over the planned roads.
    let [dx, dy, _] = planned.placement.offset_mm();
    let shift = glam::DVec2::new(dx, dy);
    let mut built = record::built_roads(recording, Some(job_id));
    for r in built.values_mut().flatten() {
        r.from -= shift;
        r.to -= shift;
    }
    let mut total = crate::toolpath::coverage::Coverage::default();
    for (k, (lm, islands)) in planned.layers.iter().zip(&planned.islands).enumerate() {
        let (cov, voids) = crate::toolpath::coverage::measure_with_voids(
            islands,
            &lm.paths,
            planned.road_width_mm,
            0.01,
            20_000,
        );
        total.add(&cov);
        let planned_svg = crate::svg::roads_svg(
            &lm.paths,
            &crate::svg::RoadsInput {
                title: &format!("{} layer {k}: planned", job.name),
                islands,
                road_width_mm: planned.road_width_mm,
                voids: &voids,
                void_cell_mm: cov.cell_mm,
                mixer_limited: &lm.stats.mixer_limited,
            },
        );
        let roads = built
            .get(&(k as u32))
            .map(Vec::as_slice)
            .unwrap_or_default();
        let built_svg = crate::svg::built_svg(
            roads,
            islands,
            planned.road_width_mm,
            &format!("{} layer {k}: as built", job.name),
        );
        let svg = crate::svg::side_by_side(
            &[
                (
                    &format!(
                        "layer {k} planned: void {:.2} %, overlap {:.2} %",
                        100.0 * cov.void_fraction(),
                        100.0 * cov.overlap_fraction()
                    ),
                    &planned_svg,
                ),
                (
                    &format!("layer {k} as built ({} extrusions)", roads.len()),
                    &built_svg,
                ),
            ],
            &format!("{}: layer {k}, planned and as built", job.name),
        );
        let path = out.join(format!("layer-{k:04}.svg"));
        std::fs::write(&path, svg).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(total)
}

fn human(s: &DemoSummary) -> String {
    let pct = |f: f64| format!("{:.2} %", 100.0 * f);
    let ul: Vec<String> = s
        .syringe_volumes_ul
        .iter()
        .map(|v| format!("{v:.1}"))
        .collect();
    // Over G-code: the firmware, and the motion lines matched.
    let (over, lines) = match (&s.firmware, s.gcode_lines_planned, s.gcode_lines_executed) {
        (Some(f), Some(p), Some(e)) => (
            format!(", streamed as G-code to {f} (simulated)"),
            format!(" (G-code motion lines planned {p}, ran {e})"),
        ),
        _ => (String::new(), String::new()),
    };
    let mut text = format!(
        "{job}: {state} ({layers} layers){over}\n\
         \x20 moves planned {planned}, executed {executed}{lines}: {as_planned}\n\
         \x20 composition designed vs built, per road: mean {rmean:.4}, max {rmax:.4}\n\
         \x20   per move: mean {bmean:.4}, max {bmax:.4} (moves of {move_nl:.0} nl carry whole nl per syringe; planner predicted mean {pmean:.4}, max {pmax:.4})\n\
         \x20 planned roads: void {void}, overlap {overlap}, outside {outside}\n\
         \x20 syringes pushed [{ul}] µL\n\
         \x20 printed in {print:.1} s ({machine:.1} s of machine time), demo {total:.1} s\n\
         \x20 previews (planned | as built): {out}/layer-*.svg, summary: {out}/summary.json, recording: {out}/record.jsonl\n",
        job = s.job,
        state = s.state,
        layers = s.layers,
        planned = s.moves_planned,
        executed = s.moves_executed,
        as_planned = match &s.mismatch {
            None => "identical".to_string(),
            Some(m) => format!("DIFFERENT: {m}"),
        },
        rmean = s.composition_error_built_per_road.mean,
        rmax = s.composition_error_built_per_road.max,
        move_nl = s.extrude_move_nl,
        bmean = s.composition_error_built.mean,
        bmax = s.composition_error_built.max,
        pmean = s.composition_error_predicted.mean,
        pmax = s.composition_error_predicted.max,
        void = pct(s.void_fraction),
        overlap = pct(s.overlap_fraction),
        outside = pct(s.outside_fraction),
        ul = ul.join(", "),
        print = s.print_time_s,
        machine = s.machine_time_s,
        total = s.total_time_s,
        out = s.out_dir.display(),
    );
    text.push_str(&mixer_lines(s));
    text
}

/// `--mixer`: the chamber, and the planner's road-by-road prediction with the
/// feed-forward on and off.
fn mixer_lines(s: &DemoSummary) -> String {
    let Some(m) = &s.mixer else {
        return String::new();
    };
    let pe = m.peclet.map(|p| format!(", Pe {p}")).unwrap_or_default();
    let mut text = format!(
        "  mixing chamber: {} {:.0} nl{pe}",
        m.model.name(),
        m.volume_nl
    );
    if let Some((used, e)) = &s.feed_forward {
        text.push_str(&format!(
            ", printed with the feed-forward {}\n    predicted per road: feed-forward on mean {:.4}, max {:.4}; off mean {:.4}, max {:.4}; {} road(s) the mixer cannot follow within 0.01",
            if *used { "on" } else { "off" },
            e.on.mean,
            e.on.max,
            e.off.mean,
            e.off.max,
            e.mixer_limited_roads
        ));
    }
    text.push('\n');
    text
}
