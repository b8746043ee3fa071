//! The streamer: the one task that owns the serial port (tokio-serial) and pumps the
//! sans-IO link host, and with it the job lifecycle.
//!
//! Progress is what the machine reports executed (`Status.last_executed`), never what was
//! sent; checkpoints (first move not executed, layer, composition, syringe volumes) are
//! written to the store as it advances.
//!
//! Restarting a job from its checkpoint (after a reset, a lost link, an e-stop, an edod
//! restart, or a syringe refill) is one procedure:
//! 1. *flush*: e-stop (the machine drops its queue and aborts the current move), wait for
//!    the acknowledgement and for a status in `EStopped`: its `last_executed` is final;
//! 2. *release*: clear faults, priority `Resume`, wait for its acknowledgement;
//! 3. *prelude*: service moves (job id 0): home, prime, travel (lifted) to where the last
//!    executed move ended, layer mark;
//! 4. stream the job from the first move not executed (the planner regenerates the plan
//!    and skips what was executed).

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{mpsc, oneshot};
use tokio_serial::{SerialPortBuilderExt, SerialStream};
use tracing::{debug, info, warn};

use super::checkpoints::{self, Record};
use super::planner::{self, DryRunSource, JobSource, LayerSource, PlannerMsg};
use super::store::{now_ms, Checkpoint, JobSpec, JobState, SERVICE_JOB_ID};
use super::{ApiError, Control, EStopTiming, MachineSnapshot, Progress, Reply, Shared};
use crate::link::{
    FaultKind, Host, HostEvent, HostState, LinkConfig, MachineInfo, MachineState, Micros,
    PriorityCmd, Status,
};
use crate::machine::{composition_of, Move, MoveKind, PositionUm};
use crate::proto::{Event, JobStateChanged};

/// Checkpoints are written at most this often while printing (and at every state change).
const CHECKPOINT_EVERY: Duration = Duration::from_millis(100);
/// How long a forced checkpoint waits for the disk (twice the store's busy timeout).
const FLUSH_LIMIT: Duration = Duration::from_secs(10);
/// Progress notifications at most this often.
const PROGRESS_EVERY: Duration = Duration::from_millis(100);
/// How long the port stays closed after an error before it is opened again.
const REOPEN_AFTER: Duration = Duration::from_millis(300);
/// Longest sleep of the loop when the link asks for nothing sooner.
const TICK: Duration = Duration::from_millis(20);

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum AfterFlush {
    Continue,
    Park,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// E-stop sent; waiting for its ack (`acked`) and then an `EStopped` status.
    Flushing { acked: bool, then: AfterFlush },
    /// Resume sent after clearing faults; waiting for its ack.
    Releasing { then: AfterFlush },
    /// Waiting for the planner's resume point to send the service prelude.
    Prelude,
    /// Moves flow.
    Streaming,
    /// Feed hold by the operator.
    Holding,
    /// A syringe ran empty; waiting for `machine.refill`.
    Empty,
    /// Stopped by a fault; waiting for `job.resume`.
    Interrupted,
}

struct Active {
    id: u32,
    phase: Phase,
    planner: Option<mpsc::Receiver<PlannerMsg>>,
    planning_done: bool,
    resume_point: Option<PlannerMsg>,
    queue: VecDeque<Move>,
    sent: VecDeque<Move>,
    total: Option<u32>,
    /// Layers in the job, once the planner knows.
    layers: Option<u32>,
    /// The layer the job (re)started at (0 before its first layer), for the estimate by
    /// layers.
    layer_at_start: u32,
    checkpoint: Checkpoint,
    saved: Instant,
    dirty: bool,
    submitted_ms: i64,
    first_move_after_ms: Option<i64>,
    started: Instant,
    executed_at_start: u32,
    notified: Instant,
    machine_was_empty: bool,
    /// Moves have gone out since the job (re)started: the store says `printing`.
    printing: bool,
    /// The machine has executed a move sent since the job (re)started.
    ran: bool,
}

/// Seconds left of a job that has run `elapsed_s` since it (re)started: from the move
/// rate once the move total is known (`moves`: total, executed, executed since the
/// start), else from the layer rate (`layers`: the job's layer count and the current
/// layer, 0-based; layers finished since `layer_at_start` over the time they took, for
/// the layers not finished, the current one counted whole). Layers differ in size, so
/// the second is the rougher estimate. `None` until there is a rate.
fn time_left_s(
    moves: Option<(u32, u32, u32)>,
    layers: Option<(u32, u32)>,
    layer_at_start: u32,
    elapsed_s: f64,
) -> Option<f64> {
    let elapsed_s = elapsed_s.max(1e-3);
    match (moves, layers) {
        (Some((total, executed, done_since)), _) => {
            let rate = f64::from(done_since) / elapsed_s;
            (rate > 0.0).then(|| f64::from(total.saturating_sub(executed)) / rate)
        }
        (None, Some((count, layer))) => {
            let finished = layer.saturating_sub(layer_at_start);
            (finished > 0)
                .then(|| f64::from(count.saturating_sub(layer)) * elapsed_s / f64::from(finished))
        }
        (None, None) => None,
    }
}

/// The streamer task.
pub struct Streamer {
    shared: Arc<Shared>,
    port_path: PathBuf,
    baud: u32,
    port: Option<SerialStream>,
    reopen_at: Instant,
    host: Host,
    epoch: Instant,
    seed: u64,
    connected: bool,
    info: Option<MachineInfo>,
    status: Status,
    active: Option<Active>,
    /// A job not active whose checkpoint follows the machine (after an edod restart).
    tracked: Option<(u32, Checkpoint)>,
    estops: Vec<(Instant, Option<u64>, Reply<EStopTiming>)>,
    /// Writes checkpoints and move counts off this task.
    checkpoints: checkpoints::Writer,
    shutdown: Option<(oneshot::Sender<()>, Instant)>,
    underruns: u64,
    /// When an underrun was last logged, and how many came since (logged at most
    /// every [`UNDERRUN_LOG_EVERY`], so a link too slow for the job cannot flood the
    /// journal).
    underrun_logged: Option<(Instant, u64)>,
}

/// Underrun warnings at most this often (the count of the ones between goes with the next).
const UNDERRUN_LOG_EVERY: Duration = Duration::from_secs(10);

/// For an event logged at most every [`UNDERRUN_LOG_EVERY`]: whether to log the one
/// at `now`, with how many were not logged since the last (`logged`: when that was and
/// that count).
fn log_now(logged: &mut Option<(Instant, u64)>, now: Instant) -> Option<u64> {
    match logged {
        Some((at, since)) if now.saturating_duration_since(*at) < UNDERRUN_LOG_EVERY => {
            *since += 1;
            None
        }
        _ => {
            let since = logged.map_or(0, |(_, n)| n);
            *logged = Some((now, 0));
            Some(since)
        }
    }
}

fn session_seed() -> u64 {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    t ^ (u64::from(std::process::id()) << 32)
}

async fn read_port(port: &mut Option<SerialStream>, buf: &mut [u8]) -> std::io::Result<usize> {
    match port {
        Some(p) => p.read(buf).await,
        None => std::future::pending().await,
    }
}

/// The planner's next message, once the active job's queue has room: moves are taken
/// from the planner only while fewer than `ahead` (4 × `planner.moves_ahead`) wait here, so the bounded planner
/// channel (`planner.layers_ahead` layers) is what holds a job's future, and memory
/// stays bounded however large the part.
async fn recv_planner(a: &mut Option<Active>, ahead: usize) -> Option<PlannerMsg> {
    match a
        .as_mut()
        .filter(|a| a.queue.len() < ahead)
        .and_then(|a| a.planner.as_mut())
    {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}

fn bad_state(msg: impl Into<String>) -> ApiError {
    ApiError::new(ApiError::BAD_STATE, msg)
}

fn mm(p: PositionUm) -> [f64; 3] {
    [
        f64::from(p.x_um) / 1000.0,
        f64::from(p.y_um) / 1000.0,
        f64::from(p.z_um) / 1000.0,
    ]
}

fn um(v: f64) -> i32 {
    (v * 1000.0).round() as i32
}

impl Streamer {
    /// A streamer for `shared.port`, recording checkpoints through `checkpoints`.
    pub fn new(shared: Arc<Shared>, checkpoints: checkpoints::Writer) -> Self {
        let seed = session_seed();
        let epoch = Instant::now();
        let link_cfg = LinkConfig::default()
            .with_priority_latency(shared.config.serial.baud, crate::link::PRIORITY_LATENCY_US);
        Self {
            port_path: shared.port.clone(),
            baud: shared.config.serial.baud,
            shared,
            port: None,
            reopen_at: epoch,
            host: Host::new(link_cfg, seed, Micros(0)),
            epoch,
            seed,
            connected: false,
            info: None,
            status: Status::default(),
            active: None,
            tracked: None,
            estops: Vec::new(),
            checkpoints,
            shutdown: None,
            underruns: 0,
            underrun_logged: None,
        }
    }

    fn now(&self) -> Micros {
        Micros(self.epoch.elapsed().as_micros() as u64)
    }

    /// Run until a `Shutdown` request has been served.
    pub async fn run(mut self, mut control: mpsc::Receiver<Control>) {
        let mut buf = vec![0u8; 4096];
        // Moves held here besides the link's `moves_ahead`: the planner channel's layers
        // come in whole, so keep a few windows' worth to ride out a slow worker.
        let ahead = 4 * self.shared.config.planner.moves_ahead.max(1);
        self.publish();
        loop {
            let wake = self
                .host
                .next_timeout()
                .map(|t| Duration::from_micros(t.0.saturating_sub(self.now().0)))
                .unwrap_or(TICK)
                .min(TICK);
            tokio::select! {
                biased;
                c = control.recv() => match c {
                    Some(c) => self.on_control(c),
                    None => break,
                },
                r = read_port(&mut self.port, &mut buf) => match r {
                    Ok(0) => self.port_lost("end of file"),
                    Ok(n) => {
                        let now = self.now();
                        self.host.handle_bytes(&buf[..n], now);
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                    Err(e) => self.port_lost(&e.to_string()),
                },
                m = recv_planner(&mut self.active, ahead) => self.on_planner(m),
                _ = tokio::time::sleep(wake) => {}
            }
            self.pump().await;
            self.shared
                .alive
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if let Some((_, deadline)) = &self.shutdown {
                let held = self.active.is_none()
                    || !self.connected
                    || self.status.state != MachineState::Running;
                if held || Instant::now() >= *deadline {
                    self.finish_shutdown();
                    break;
                }
            }
        }
    }

    fn finish_shutdown(&mut self) {
        if self.active.as_ref().is_some_and(Active::cancelling) {
            self.interrupt("edod stopped");
        }
        if let Some(a) = self.active.as_mut() {
            if !a.phase_is_final_wait() {
                a.phase = Phase::Interrupted;
            }
            let id = a.id;
            self.save_checkpoint(true);
            self.set_job_state(id, JobState::Interrupted, Some("edod stopped"));
        }
        if let Some((reply, _)) = self.shutdown.take() {
            let _ = reply.send(());
        }
    }

    // ---- port -------------------------------------------------------------------------

    fn try_open(&mut self) {
        if self.port.is_some() || Instant::now() < self.reopen_at {
            return;
        }
        let path = self.port_path.display().to_string();
        match tokio_serial::new(&path, self.baud).open_native_async() {
            Ok(mut p) => {
                let _ = p.set_exclusive(false);
                info!(port = %path, "serial port open");
                self.port = Some(p);
                self.seed = self.seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let now = self.now();
                self.host.reconnect(self.seed, now);
            }
            Err(e) => {
                debug!(port = %path, error = %e, "cannot open serial port yet");
                self.reopen_at = Instant::now() + REOPEN_AFTER;
            }
        }
    }

    fn port_lost(&mut self, why: &str) {
        warn!(port = %self.port_path.display(), why, "serial port lost");
        self.port = None;
        self.reopen_at = Instant::now() + REOPEN_AFTER;
        self.connected = false;
        self.interrupt("serial port lost");
        self.publish();
    }

    async fn write_out(&mut self) {
        let now = self.now();
        while let Some(t) = self.host.poll_transmit(now) {
            let Some(p) = self.port.as_mut() else {
                return;
            };
            if let Err(e) = p.write_all(&t.bytes).await {
                self.port_lost(&e.to_string());
                return;
            }
        }
    }

    // ---- the pump -----------------------------------------------------------------------

    async fn pump(&mut self) {
        self.try_open();
        let now = self.now();
        self.host.handle_timeout(now);
        while let Some(e) = self.host.poll_event() {
            self.on_event(e);
        }
        self.feed();
        self.write_out().await;
        if !self.estops.is_empty() {
            // Written: take the time of the first write after the request.
            let t = Instant::now();
            for (req, written, _) in &mut self.estops {
                if written.is_none() {
                    *written = Some(t.duration_since(*req).as_micros() as u64);
                }
            }
            let expired: Vec<_> = self
                .estops
                .iter()
                .enumerate()
                .filter(|(_, (req, _, _))| req.elapsed() > Duration::from_secs(1))
                .map(|(i, _)| i)
                .collect();
            for i in expired.into_iter().rev() {
                let (_, w, reply) = self.estops.remove(i);
                let _ = reply.send(Ok(EStopTiming {
                    written_after_us: w.unwrap_or(0),
                    acked_after_us: None,
                }));
            }
        }
        self.save_checkpoint(false);
        self.notify_progress(false);
    }

    fn feed(&mut self) {
        if !self.connected || self.host.state() != HostState::Connected {
            return;
        }
        let ahead = self.shared.config.planner.moves_ahead;
        let Some(a) = self.active.as_mut() else {
            self.start_next();
            return;
        };
        if a.phase == Phase::Prelude && (a.resume_point.is_some() || a.checkpoint.next_index == 0) {
            self.send_prelude();
            return;
        }
        if a.phase != Phase::Streaming {
            return;
        }
        while self.host.pending() < ahead {
            let Some(mv) = a.queue.pop_front() else {
                break;
            };
            match self.host.send_move(mv.clone()) {
                Ok(()) => a.sent.push_back(mv),
                Err(e) => {
                    warn!(job = a.id, error = %e, "move refused by the link");
                    a.queue.push_front(mv);
                    break;
                }
            }
        }
        if !a.printing && !a.sent.is_empty() {
            a.printing = true;
            let id = a.id;
            if self
                .shared
                .with_store(|s| s.get(id))
                .is_ok_and(|j| j.state == JobState::Planning)
            {
                self.set_job_state(id, JobState::Printing, None);
            }
        }
    }

    fn service_move(&mut self, kind: MoveKind) -> bool {
        let Ok(index) = self.shared.with_store(|s| s.next_service_index()) else {
            return false;
        };
        self.host
            .send_move(Move {
                job_id: SERVICE_JOB_ID,
                index,
                kind,
            })
            .is_ok()
    }

    fn send_prelude(&mut self) {
        let syringes = self.status.remaining_nl.len().max(1);
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let (position, layer_mark, volumes) = match a.resume_point.take() {
            Some(PlannerMsg::ResumeAt {
                position,
                layer_mark,
                volumes_nl,
            }) => (position, layer_mark, volumes_nl),
            _ => (None, None, None),
        };
        a.phase = Phase::Streaming;
        let m = &self.shared.config.machine;
        let prime_nl = m.prime_nl;
        let lift = um(m.resume_lift_mm);
        let ratios = volumes
            .as_deref()
            .and_then(composition_of)
            .and_then(|c| crate::machine::ratios_from_fractions(&c).ok())
            .unwrap_or_else(|| {
                let mut r = vec![0u16; syringes];
                r[0] = crate::machine::RATIO_ONE;
                r
            });
        let mut kinds = vec![
            MoveKind::Home,
            MoveKind::Prime {
                volumes_nl: crate::machine::split_volume_nl(prime_nl, &ratios),
                duration_ms: 1000,
            },
        ];
        if let Some(p) = position {
            let feed_um_s = um(m.max_feed_mm_s).max(1) as u32;
            kinds.push(MoveKind::Travel {
                to: PositionUm {
                    // Lifted, but not above the build volume's top.
                    z_um: p
                        .z_um
                        .saturating_add(lift)
                        .min(um(m.build_volume_mm[2]).max(p.z_um)),
                    ..p
                },
                feed_um_s,
            });
            kinds.push(MoveKind::Travel { to: p, feed_um_s });
        }
        if let Some((layer, z_um)) = layer_mark {
            kinds.push(MoveKind::LayerMark { layer, z_um });
        }
        for k in kinds {
            self.service_move(k);
        }
    }

    fn start_next(&mut self) {
        if self.shutdown.is_some() {
            return;
        }
        let Ok(Some(job)) = self.shared.with_store(|s| s.next_queued()) else {
            return;
        };
        self.activate(job.id, true);
    }

    /// Make job `id` active from its checkpoint. `fresh`: never started before.
    fn activate(&mut self, id: u32, fresh: bool) {
        let Ok(job) = self.shared.with_store(|s| s.get(id)) else {
            return;
        };
        if let Err(e) = self.source_for(id) {
            self.set_job_state(id, JobState::Failed, Some(&e));
            return;
        }
        let mut checkpoint = job.checkpoint.clone();
        if let Some((tid, c)) = self.tracked.take() {
            if tid == id && c.next_index > checkpoint.next_index {
                checkpoint = c;
            }
        }
        let clean = self.status.state == MachineState::Idle
            && self.status.queued == 0
            && self.status.faults == 0;
        let phase = if fresh && clean {
            Phase::Streaming
        } else {
            self.begin_flush();
            Phase::Flushing {
                acked: false,
                then: AfterFlush::Continue,
            }
        };
        info!(job = id, from = checkpoint.next_index, ?phase, "job starts");
        let executed_at_start = checkpoint.next_index;
        self.active = Some(Active {
            id,
            phase,
            planner: None,
            planning_done: false,
            resume_point: None,
            queue: VecDeque::new(),
            sent: VecDeque::new(),
            total: job.total_moves,
            layers: None,
            layer_at_start: checkpoint.layer.unwrap_or(0),
            checkpoint,
            saved: Instant::now(),
            dirty: false,
            submitted_ms: job.submitted_ms,
            first_move_after_ms: None,
            started: Instant::now(),
            executed_at_start,
            notified: Instant::now(),
            machine_was_empty: false,
            printing: false,
            ran: false,
        });
        if phase == Phase::Streaming {
            self.spawn_planner();
        }
        self.set_job_state(
            id,
            if fresh {
                JobState::Planning
            } else {
                JobState::Printing
            },
            None,
        );
    }

    fn begin_flush(&mut self) {
        let now = self.now();
        self.host.priority(PriorityCmd::EmergencyStop, now);
    }

    fn restart_active(&mut self, then: AfterFlush) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        a.queue.clear();
        a.sent.clear();
        a.resume_point = None;
        // The planner starts once the flush has made the checkpoint final.
        a.planner = None;
        a.planning_done = false;
        a.phase = Phase::Flushing { acked: false, then };
        self.begin_flush();
    }

    /// What produces job `id`'s moves.
    fn source_for(&self, id: u32) -> Result<Box<dyn LayerSource>, String> {
        let job = self
            .shared
            .with_store(|s| s.get(id))
            .map_err(|e| e.message)?;
        let syringes = self.status.remaining_nl.len().max(1);
        let mesh = match &job.spec {
            JobSpec::Toml { .. } => self
                .shared
                .with_store(|s| s.mesh(id))
                .map_err(|e| e.message)?,
            JobSpec::DryRun { .. } => None,
        };
        match &job.spec {
            JobSpec::DryRun { moves } => Ok(Box::new(DryRunSource::new(
                *moves,
                self.shared.config.planner.dry_run_moves_per_layer,
                syringes,
                um(self.shared.config.machine.build_volume_mm[2]),
            ))),
            JobSpec::Toml { toml, .. } => JobSource::new(
                toml,
                mesh.as_deref(),
                &format!("job {id}"),
                &self.shared.config.machine,
            )
            .map(|s| Box::new(s) as Box<dyn LayerSource>),
        }
    }

    /// Start the active job's planner from its checkpoint.
    fn spawn_planner(&mut self) {
        let Some(id) = self.active.as_ref().map(|a| a.id) else {
            return;
        };
        match self.source_for(id) {
            Ok(src) => {
                if let Some(a) = self.active.as_mut() {
                    a.planning_done = false;
                    a.planner = Some(planner::spawn(
                        src,
                        id,
                        a.checkpoint.next_index,
                        self.shared.config.planner.layers_ahead,
                    ));
                }
            }
            Err(e) => {
                self.active = None;
                self.set_job_state(id, JobState::Failed, Some(&e));
            }
        }
    }

    fn interrupt(&mut self, why: &str) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if matches!(a.phase, Phase::Interrupted) {
            return;
        }
        if a.cancelling() {
            // The operator asked for the job to end: it does, without the park.
            let id = a.id;
            warn!(
                job = id,
                why, "cancel interrupted before the nozzle was parked"
            );
            self.save_checkpoint(true);
            self.active = None;
            self.set_job_state(
                id,
                JobState::Cancelled,
                Some(&format!("cancelled by an operator; not parked: {why}")),
            );
            return;
        }
        a.phase = Phase::Interrupted;
        a.planner = None;
        a.queue.clear();
        a.sent.clear();
        let id = a.id;
        warn!(job = id, why, "job interrupted");
        self.save_checkpoint(true);
        self.set_job_state(id, JobState::Interrupted, Some(why));
    }

    // ---- events ---------------------------------------------------------------------------

    fn on_planner(&mut self, m: Option<PlannerMsg>) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let id = a.id;
        match m {
            None => a.planner = None,
            Some(PlannerMsg::Layers { count }) => a.layers = Some(count),
            Some(PlannerMsg::Moves(v)) => a.queue.extend(v),
            Some(r @ PlannerMsg::ResumeAt { .. }) => {
                a.resume_point = Some(r);
            }
            Some(PlannerMsg::Done { total }) => {
                a.total = Some(total);
                a.planning_done = true;
                self.checkpoints.record(
                    id,
                    Record {
                        checkpoint: None,
                        total_moves: Some(total),
                    },
                );
                self.check_done();
            }
            Some(PlannerMsg::Failed(e)) => {
                warn!(job = id, error = %e, "planning failed");
                self.active = None;
                self.set_job_state(id, JobState::Failed, Some(&e));
                self.begin_flush_if_running();
            }
        }
    }

    fn begin_flush_if_running(&mut self) {
        if self.status.queued > 0 {
            self.begin_flush();
        }
    }

    fn on_event(&mut self, e: HostEvent) {
        match e {
            HostEvent::Connected(info) => {
                info!(identity = %info.identity, boot_id = info.boot_id, last = ?info.status.last_executed, "machine connected");
                self.connected = true;
                let st = info.status.clone();
                self.info = Some(info);
                if self.active.is_none() {
                    if let Some(m) = st.last_executed {
                        if let Ok(j) = self.shared.with_store(|s| s.get(m.job_id)) {
                            if j.state == JobState::Interrupted {
                                self.tracked = Some((m.job_id, j.checkpoint));
                            } else if j.state == JobState::Cancelled
                                && (st.state == MachineState::Running || st.queued > 0)
                            {
                                // Cancelled while the link was down (the port lost, so
                                // the cancel's e-stop went with it): the machine still
                                // runs the moves it had queued. Stop them.
                                warn!(
                                    job = m.job_id,
                                    queued = st.queued,
                                    "the machine still runs moves of a cancelled job: e-stop"
                                );
                                self.begin_flush();
                            }
                        }
                    }
                }
                self.on_status(st);
            }
            HostEvent::Status(s) => self.on_status(s),
            HostEvent::Fault(f) => {
                warn!(fault = ?f.kind, at = ?f.at, "machine fault");
                match f.kind {
                    FaultKind::SyringeEmpty(n) => {
                        let name = self
                            .shared
                            .config
                            .machine
                            .syringes
                            .get(usize::from(n))
                            .map_or_else(|| format!("{n}"), |s| format!("{n} ({})", s.name));
                        if let Some(a) = self.active.as_mut() {
                            if matches!(a.phase, Phase::Streaming | Phase::Holding) {
                                a.phase = Phase::Empty;
                                a.queue.clear();
                                a.sent.clear();
                                a.planner = None;
                                let id = a.id;
                                self.save_checkpoint(true);
                                self.set_job_state(
                                    id,
                                    JobState::Paused,
                                    Some(&format!(
                                        "syringe {name} is empty: swap it, then machine.refill"
                                    )),
                                );
                            }
                        }
                    }
                    FaultKind::EStopPressed => self.interrupt("e-stop pressed on the machine"),
                    other => self.interrupt(&format!("machine fault {other:?}")),
                }
            }
            HostEvent::MachineReset { last_executed, .. } => {
                warn!(?last_executed, "machine reset");
                if let Some(m) = last_executed {
                    self.apply_executed(m.job_id, m.index);
                }
                self.connected = false;
                self.interrupt("machine reset");
                self.seed = self.seed.wrapping_add(1);
                let now = self.now();
                self.host.reconnect(self.seed, now);
            }
            HostEvent::LinkLost { silent_us } => {
                warn!(silent_ms = silent_us / 1000, "link lost");
                self.connected = false;
                self.interrupt("link to the machine lost");
            }
            HostEvent::LinkRestored => {
                info!("link restored");
                self.connected = true;
            }
            HostEvent::PriorityAcked(cmd) => self.on_priority_ack(cmd),
            HostEvent::Incompatible { machine_version } => {
                warn!(machine_version, "machine speaks another protocol version");
                self.connected = false;
            }
        }
        self.publish();
    }

    fn on_priority_ack(&mut self, cmd: PriorityCmd) {
        if cmd == PriorityCmd::EmergencyStop {
            let t = Instant::now();
            for (req, w, reply) in self.estops.drain(..) {
                let _ = reply.send(Ok(EStopTiming {
                    written_after_us: w.unwrap_or(0),
                    acked_after_us: Some(t.duration_since(req).as_micros() as u64),
                }));
            }
        }
        let Some(a) = self.active.as_mut() else {
            return;
        };
        match (a.phase, cmd) {
            (Phase::Flushing { acked: false, then }, PriorityCmd::EmergencyStop) => {
                a.phase = Phase::Flushing { acked: true, then };
                let _ = self.host.query();
            }
            (Phase::Releasing { then }, PriorityCmd::Resume) => match then {
                AfterFlush::Continue => {
                    a.phase = Phase::Prelude;
                    self.spawn_planner();
                }
                AfterFlush::Park => {
                    let id = a.id;
                    // The flush made the checkpoint final: keep where the job stopped.
                    self.save_checkpoint(true);
                    self.active = None;
                    let m = self.shared.config.machine.clone();
                    let n = self.status.remaining_nl.len().max(1);
                    let p = self.status.position;
                    self.service_move(MoveKind::Retract {
                        volumes_nl: vec![m.prime_nl / 4; n],
                        duration_ms: 500,
                    });
                    let feed_um_s = um(m.max_feed_mm_s).max(1) as u32;
                    self.service_move(MoveKind::Travel {
                        to: PositionUm {
                            z_um: p.z_um.max(um(m.park_mm[2])),
                            ..p
                        },
                        feed_um_s,
                    });
                    self.service_move(MoveKind::Travel {
                        to: PositionUm {
                            x_um: um(m.park_mm[0]),
                            y_um: um(m.park_mm[1]),
                            z_um: p.z_um.max(um(m.park_mm[2])),
                        },
                        feed_um_s,
                    });
                    self.set_job_state(id, JobState::Cancelled, Some("cancelled by an operator"));
                }
            },
            _ => {}
        }
    }

    fn on_status(&mut self, s: Status) {
        if let Some(m) = s.last_executed {
            self.apply_executed(m.job_id, m.index);
        }
        let state = s.state;
        self.status = s;
        if let Some(a) = self.active.as_mut() {
            if let Phase::Flushing { acked: true, then } = a.phase {
                if state == MachineState::EStopped {
                    a.phase = Phase::Releasing { then };
                    let _ = self.host.clear_faults();
                    let now = Micros(self.epoch.elapsed().as_micros() as u64);
                    self.host.priority(PriorityCmd::Resume, now);
                }
            }
            // Queue underrun: the machine ran dry while the job had moves left.
            let left = a.total.is_none_or(|t| a.checkpoint.next_index < t);
            let empty = self.status.queued == 0 && state == MachineState::Idle;
            // Only once the machine has executed a move sent in this run: right after a
            // (re)start it is idle because nothing has reached it yet, not because the
            // host fell behind.
            if a.phase == Phase::Streaming && left && empty && a.ran {
                if !a.machine_was_empty {
                    self.underruns += 1;
                    a.machine_was_empty = true;
                    if let Some(since) = log_now(&mut self.underrun_logged, Instant::now()) {
                        warn!(
                            job = a.id,
                            executed = a.checkpoint.next_index,
                            waiting_here = a.queue.len(),
                            in_link = self.host.pending(),
                            in_flight = self.host.moves_in_flight(),
                            planner_running = a.planner.is_some(),
                            underruns = self.underruns,
                            not_logged_since_last = since,
                            "queue underrun: the machine ran out of moves"
                        );
                    }
                }
            } else {
                a.machine_was_empty = false;
            }
        }
        self.check_done();
        self.publish();
    }

    fn apply_executed(&mut self, job_id: u32, index: u32) {
        let remaining = self.status.remaining_nl.clone();
        if let Some(a) = self.active.as_mut().filter(|a| a.id == job_id) {
            if index < a.checkpoint.next_index {
                return;
            }
            if a.first_move_after_ms.is_none() {
                a.first_move_after_ms = Some(now_ms() - a.submitted_ms);
            }
            a.checkpoint.next_index = index.saturating_add(1);
            while a.sent.front().is_some_and(|m| m.index <= index) {
                if let Some(m) = a.sent.pop_front() {
                    a.ran = true;
                    match &m.kind {
                        MoveKind::LayerMark { layer, .. } => a.checkpoint.layer = Some(*layer),
                        MoveKind::Extrude { volumes_nl, .. } => {
                            if let Some(c) = composition_of(volumes_nl) {
                                a.checkpoint.composition = Some(c);
                            }
                        }
                        _ => {}
                    }
                }
            }
            a.checkpoint.remaining_nl = remaining;
            a.dirty = true;
        } else if let Some((id, c)) = self.tracked.as_mut().filter(|t| t.0 == job_id) {
            if index >= c.next_index {
                c.next_index = index.saturating_add(1);
                c.remaining_nl = remaining;
                let (id, c) = (*id, c.clone());
                self.checkpoints.record(
                    id,
                    Record {
                        checkpoint: Some(c),
                        total_moves: None,
                    },
                );
            }
        }
    }

    fn check_done(&mut self) {
        let Some(a) = self.active.as_ref() else {
            return;
        };
        if a.phase == Phase::Streaming
            && a.planning_done
            && a.total.is_some_and(|t| a.checkpoint.next_index >= t)
        {
            let (id, total) = (a.id, a.total);
            self.save_checkpoint(true);
            self.notify_progress(true);
            info!(job = id, moves = total, "job done");
            self.active = None;
            self.set_job_state(id, JobState::Done, None);
        }
    }

    // ---- control -------------------------------------------------------------------------------

    fn on_control(&mut self, c: Control) {
        match c {
            Control::Submitted => {}
            Control::Pause(id, reply) => {
                let r = self.pause(id);
                let _ = reply.send(r);
            }
            Control::Resume(id, reply) => {
                let r = self.resume(id);
                let _ = reply.send(r);
            }
            Control::Cancel(id, reply) => {
                let r = self.cancel(id);
                let _ = reply.send(r);
            }
            Control::EStop(req, reply) => {
                let now = self.now();
                self.host.priority(PriorityCmd::EmergencyStop, now);
                if let Some(a) = self.active.as_mut() {
                    if !matches!(a.phase, Phase::Flushing { .. } | Phase::Releasing { .. }) {
                        self.interrupt("emergency stop by an operator");
                    }
                }
                if self.port.is_none() || !self.connected {
                    let _ = reply.send(Err(ApiError::new(
                        ApiError::NOT_CONNECTED,
                        "e-stop queued but the machine is not connected: use the machine's own e-stop",
                    )));
                } else {
                    self.estops.push((req, None, reply));
                }
            }
            Control::Refill(reply) => {
                let r = self.refill();
                let _ = reply.send(r);
            }
            Control::Shutdown(reply) => {
                info!("stopping: hold, checkpoint, exit");
                if let Some(a) = self.active.as_mut() {
                    if a.phase == Phase::Streaming {
                        a.phase = Phase::Holding;
                        let now = Micros(self.epoch.elapsed().as_micros() as u64);
                        self.host.priority(PriorityCmd::FeedHold, now);
                    }
                }
                self.shutdown = Some((reply, Instant::now() + Duration::from_secs(2)));
            }
        }
    }

    fn need_connected(&self) -> Result<(), ApiError> {
        if self.connected && self.host.state() == HostState::Connected {
            Ok(())
        } else {
            Err(ApiError::new(
                ApiError::NOT_CONNECTED,
                format!(
                    "the machine on {} is not connected",
                    self.port_path.display()
                ),
            ))
        }
    }

    fn pause(&mut self, id: u32) -> Result<(), ApiError> {
        match self.active.as_mut().filter(|a| a.id == id) {
            Some(a) if a.phase == Phase::Streaming => {
                a.phase = Phase::Holding;
                let now = self.now();
                self.host.priority(PriorityCmd::FeedHold, now);
                self.save_checkpoint(true);
                self.set_job_state(id, JobState::Paused, Some("paused by an operator"));
                Ok(())
            }
            Some(_) => Err(bad_state(format!("job {id} is not printing"))),
            None => {
                let j = self.shared.with_store(|s| s.get(id))?;
                Err(bad_state(format!(
                    "job {id} is {}, only a printing job can be paused",
                    j.state.as_str()
                )))
            }
        }
    }

    fn resume(&mut self, id: u32) -> Result<(), ApiError> {
        if let Some(a) = self.active.as_mut().filter(|a| a.id == id) {
            return match a.phase {
                Phase::Holding => {
                    self.need_connected()?;
                    let Some(a) = self.active.as_mut() else {
                        return Ok(());
                    };
                    a.phase = Phase::Streaming;
                    let now = self.now();
                    self.host.priority(PriorityCmd::Resume, now);
                    self.set_job_state(id, JobState::Printing, None);
                    Ok(())
                }
                Phase::Interrupted => {
                    self.need_connected()?;
                    self.restart_active(AfterFlush::Continue);
                    self.set_job_state(id, JobState::Printing, None);
                    Ok(())
                }
                Phase::Empty => Err(bad_state(format!(
                    "job {id} waits for a syringe: swap it, then machine.refill"
                ))),
                _ => Err(bad_state(format!("job {id} is already printing"))),
            };
        }
        let j = self.shared.with_store(|s| s.get(id))?;
        if !matches!(j.state, JobState::Interrupted | JobState::Paused) {
            return Err(bad_state(format!(
                "job {id} is {}, only a paused or interrupted job can be resumed",
                j.state.as_str()
            )));
        }
        if let Some(a) = &self.active {
            return Err(bad_state(format!(
                "job {} holds the machine; cancel it or let it finish first",
                a.id
            )));
        }
        self.need_connected()?;
        self.activate(id, false);
        Ok(())
    }

    fn cancel(&mut self, id: u32) -> Result<(), ApiError> {
        if self.active.as_ref().is_some_and(|a| a.id == id) {
            if self.need_connected().is_ok() {
                self.save_checkpoint(true);
                self.restart_active(AfterFlush::Park);
            } else {
                self.active = None;
                self.set_job_state(id, JobState::Cancelled, Some("cancelled by an operator"));
            }
            return Ok(());
        }
        let j = self.shared.with_store(|s| s.get(id))?;
        if j.state.is_final() {
            return Err(bad_state(format!(
                "job {id} is already {}",
                j.state.as_str()
            )));
        }
        self.set_job_state(id, JobState::Cancelled, Some("cancelled by an operator"));
        Ok(())
    }

    fn refill(&mut self) -> Result<(), ApiError> {
        self.need_connected()?;
        if let Some(a) = self.active.as_ref().filter(|a| a.phase == Phase::Empty) {
            let id = a.id;
            self.restart_active(AfterFlush::Continue);
            self.set_job_state(id, JobState::Printing, None);
        } else {
            let _ = self.host.clear_faults();
        }
        Ok(())
    }

    // ---- store, notifications, snapshot ----------------------------------------------------

    fn set_job_state(&mut self, id: u32, state: JobState, reason: Option<&str>) {
        if let Err(e) = self.shared.with_store(|s| s.set_state(id, state, reason)) {
            warn!(job = id, error = %e, "cannot record job state");
        }
        self.shared.notify(Event::JobState(JobStateChanged {
            job_id: id,
            state,
            reason: reason.map(str::to_string),
        }));
        self.publish();
    }

    /// Hand the active job's checkpoint to the writer, at most every
    /// [`CHECKPOINT_EVERY`] unless `force`. `force` also waits until everything handed
    /// over is on disk (at most [`FLUSH_LIMIT`]): the job's state is written next.
    fn save_checkpoint(&mut self, force: bool) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let id = a.id;
        if a.dirty && (force || a.saved.elapsed() >= CHECKPOINT_EVERY) {
            a.dirty = false;
            a.saved = Instant::now();
            self.checkpoints.record(
                id,
                Record {
                    checkpoint: Some(a.checkpoint.clone()),
                    total_moves: None,
                },
            );
        }
        if force && !self.checkpoints.flush(FLUSH_LIMIT) {
            warn!(
                job = id,
                "checkpoint not on disk after {} s; still trying",
                FLUSH_LIMIT.as_secs()
            );
        }
    }

    fn notify_progress(&mut self, force: bool) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if !force && a.notified.elapsed() < PROGRESS_EVERY {
            return;
        }
        a.notified = Instant::now();
        let executed = a.checkpoint.next_index;
        let done_since = executed.saturating_sub(a.executed_at_start);
        let eta_s = time_left_s(
            a.total.map(|t| (t, executed, done_since)),
            a.layers.zip(a.checkpoint.layer),
            a.layer_at_start,
            a.started.elapsed().as_secs_f64(),
        );
        let p = Progress {
            job_id: a.id,
            executed,
            total: a.total,
            layers: a.layers,
            layer: a.checkpoint.layer,
            composition: a.checkpoint.composition.clone(),
            eta_s,
            first_move_after_ms: a.first_move_after_ms,
        };
        if self.shared.progress.borrow().as_ref() != Some(&p) {
            self.shared.notify(Event::JobProgress(p.clone()));
            self.shared.progress.send_replace(Some(p));
        }
    }

    fn publish(&self) {
        let stats = self.host.stats();
        let s = &self.status;
        let snap = MachineSnapshot {
            port: self.port_path.display().to_string(),
            connected: self.connected && self.port.is_some(),
            identity: self.info.as_ref().map(|i| i.identity.clone()),
            state: self.info.as_ref().map(|_| s.state),
            last_executed: s.last_executed,
            executed_total: s.executed_total,
            remaining_nl: s.remaining_nl.clone(),
            queued: s.queued,
            faults: s.faults,
            position_mm: mm(s.position),
            active_job: self.active.as_ref().map(|a| a.id),
            underruns: self.underruns,
            frames_retransmitted: stats.frames_retransmitted,
            srtt_ms: stats.srtt_us as f64 / 1000.0,
        };
        let changed = {
            let old = self.shared.machine.borrow();
            old.connected != snap.connected
                || old.state != snap.state
                || old.faults != snap.faults
                || old.active_job != snap.active_job
        };
        if changed {
            self.shared.notify(Event::MachineState(snap.clone()));
        }
        self.shared.machine.send_replace(snap);
        if self.active.is_none() {
            self.shared
                .progress
                .send_if_modified(|p| p.take().is_some());
        }
    }
}

impl Active {
    fn phase_is_final_wait(&self) -> bool {
        matches!(self.phase, Phase::Empty | Phase::Interrupted)
    }

    /// An operator's cancel is under way: the machine is being stopped before the
    /// nozzle retracts and parks.
    fn cancelling(&self) -> bool {
        matches!(
            self.phase,
            Phase::Flushing {
                then: AfterFlush::Park,
                ..
            } | Phase::Releasing {
                then: AfterFlush::Park
            }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::{log_now, time_left_s};
    use std::time::{Duration, Instant};

    #[test]
    fn underruns_are_logged_at_most_every_ten_seconds_with_the_count_between() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut logged = None;
        assert_eq!(log_now(&mut logged, at(0)), Some(0));
        // A burst of 500 over the next 5 s: none logged.
        for k in 1..=500 {
            assert_eq!(log_now(&mut logged, at(10 * k)), None);
        }
        // The first after 10 s carries the count.
        assert_eq!(log_now(&mut logged, at(10_000)), Some(500));
        assert_eq!(log_now(&mut logged, at(10_001)), None);
        assert_eq!(log_now(&mut logged, at(30_000)), Some(1));
        assert_eq!(log_now(&mut logged, at(45_000)), Some(0));
    }

    #[test]
    fn time_left_from_moves_once_known_else_from_layers() {
        // 1,000 of 4,000 moves in 10 s since a fresh start: 30 s left.
        assert_eq!(
            time_left_s(Some((4000, 1000, 1000)), Some((8, 2)), 0, 10.0),
            Some(30.0)
        );
        // Resumed at move 600: the rate counts only moves since the restart.
        assert_eq!(
            time_left_s(Some((4000, 1000, 400)), None, 0, 10.0),
            Some(75.0)
        );
        // Total not planned yet: layer 3 of 10 (0-based 2) after 20 s: 2 layers a 10 s,
        // 8 layers (the current one whole) left.
        assert_eq!(time_left_s(None, Some((10, 2)), 0, 20.0), Some(80.0));
        // Resumed at layer 5: only layers finished since then count.
        assert_eq!(time_left_s(None, Some((10, 7)), 5, 20.0), Some(30.0));
        // No rate yet: still in the first layer, nothing executed, or nothing known.
        assert_eq!(time_left_s(None, Some((10, 0)), 0, 20.0), None);
        assert_eq!(time_left_s(Some((4000, 0, 0)), None, 0, 5.0), None);
        assert_eq!(time_left_s(None, None, 0, 5.0), None);
        // Past the last layer (a count from an older plan): nothing left, not negative.
        assert_eq!(time_left_s(None, Some((10, 12)), 0, 20.0), Some(0.0));
    }
}
