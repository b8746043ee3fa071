//! The streamer: the pump. It is the one task that owns the serial port (tokio-serial),
//! and it drives the sans-IO job lifecycle ([`Lifecycle`]) the way the lifecycle's
//! module docs show: it feeds it the machine's events (through the link adapter,
//! [`LinkAdapter`]: [`EdoLink`] or [`GcodeLink`] as `machine.protocol` says), the
//! operators' commands, the planner's output, the store's answers and
//! the clock, and carries out what it asks: machine commands and moves go to the link,
//! records to the store's writer thread, reads to its reader thread, replies to the
//! API's waiting requests, notifications to the subscribers.
//!
//! Nothing here decides what a job does next (that is the lifecycle's) and nothing here
//! waits for the store: a record is handed over and the loop goes on; the store reports
//! back as lifecycle events.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{mpsc, oneshot};
use tokio_serial::{SerialPortBuilderExt, SerialStream};
use tracing::{debug, info, warn};

use super::planner;
use super::port_watch::{PortLog, PortWatch, PortWatchOptions};
use super::store::now_ms;
use super::{ApiError, Control, EStopTiming, MachineSnapshot, Reply, Shared, StateChange};
use crate::adapter::GcodeLink;
use crate::adapter::{link_config, EdoLink};
use crate::adapter::{log_now, LinkAdapter};
use crate::lifecycle::{
    Action, Answer, Command, Event, JobState, Level, Lifecycle, MachineCommand, Options,
    PlannerOutput, Progress, Refusal, RefusalKind, RequestId, ServiceMoves, StateNote, Underrun,
};
use crate::link::Micros;
use crate::machine::PositionUm;
use crate::proto::JobStateChanged;

/// How long the port stays closed after an error before it is opened again.
/// Longest sleep of the loop when nothing asks for a wake-up sooner.
const TICK: Duration = Duration::from_millis(20);
/// How long `machine.estop` waits for the machine's acknowledgement.
const ESTOP_ACK_WAIT: Duration = Duration::from_secs(1);
/// Underrun warnings at most this often (the count of the ones between goes with the next).
const UNDERRUN_LOG_EVERY: Duration = Duration::from_secs(10);
/// While the machine moves (position, moves executed, syringe levels), the snapshot is
/// pushed (`notify_machine_state`) at most this often, as Moonraker's status updates.
const MACHINE_NOTIFY_EVERY: Duration = Duration::from_millis(250);

/// An operator's request waiting for the lifecycle's answer.
enum Waiting {
    Change {
        id: u32,
        reply: Reply<StateChange>,
    },
    Refill(Reply<()>),
    EStop {
        asked: Instant,
        reply: Reply<EStopTiming>,
    },
    Shutdown(oneshot::Sender<()>),
}

/// An e-stop the lifecycle carried out, waiting for the machine's acknowledgement.
struct EStopWait {
    asked: Instant,
    written_after_us: Option<u64>,
    reply: Reply<EStopTiming>,
}

/// A period of [`UNDERRUN_LOG_EVERY`] passed between `last` and `now`.
fn underrun_period_over(last: Instant, now: Instant) -> bool {
    now.saturating_duration_since(last) >= UNDERRUN_LOG_EVERY
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

/// The planner's next output, while the lifecycle wants it (`wants`): moves are taken
/// only while few wait in the lifecycle, so the bounded planner channel
/// (`planner.layers_ahead` layers) is what holds a job's future, and memory stays
/// bounded however large the part.
async fn recv_planner(
    planner: &mut Option<(u64, mpsc::Receiver<PlannerOutput>)>,
    wants: bool,
) -> Option<PlannerOutput> {
    match planner.as_mut().filter(|_| wants) {
        Some((_, rx)) => rx.recv().await,
        None => std::future::pending().await,
    }
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

/// The lifecycle's settings for edod's configuration (`wall_ms_at_zero`: the wall
/// clock at the lifecycle clock's zero).
pub fn lifecycle_options(cfg: &super::Config, wall_ms_at_zero: i64) -> Options {
    let m = &cfg.machine;
    Options {
        // Moves held here besides the link's `moves_ahead`: the planner's layers come
        // whole, so keep a few windows' worth to ride out a slow worker.
        moves_waiting_max: 4 * cfg.planner.moves_ahead.max(1),
        wall_ms_at_zero,
        service: ServiceMoves {
            prime_nl: m.prime_nl,
            resume_lift_um: um(m.resume_lift_mm),
            feed_um_s: um(m.max_feed_mm_s).max(1) as u32,
            build_top_um: um(m.build_volume_mm[2]),
            park_um: m.park_mm.map(um),
            syringe_names: m.syringes.iter().map(|s| s.name.clone()).collect(),
        },
        ..Options::default()
    }
}

/// The machine link `cfg` asks for: edo's framed link, or G-code lines to a firmware.
fn machine_link(cfg: &super::Config) -> Box<dyn LinkAdapter> {
    match machine_link_gcode(cfg) {
        Some(g) => Box::new(g),
        None => Box::new(EdoLink::new(
            link_config(cfg.serial.baud),
            session_seed(),
            Micros(0),
        )),
    }
}

/// The G-code link `cfg` asks for, if it asks for one.
fn machine_link_gcode(cfg: &super::Config) -> Option<GcodeLink> {
    let g = cfg.gcode_link().ok().flatten()?;
    let syringes = &cfg.machine.syringes;
    let capacity_nl = syringes
        .first()
        .map_or(0, |s| (s.capacity_ml * 1e6).round().clamp(0.0, 4e9) as u32);
    Some(GcodeLink::new(&g, syringes.len(), capacity_nl))
}

/// Open the serial port without toggling DTR (`docs/firmware.md`, "Opening the port
/// without resetting the board"): DTR is never driven low on open, and `HUPCL` is
/// cleared so that closing the port, or edod dying, does not drop it either.
fn open_port(path: &str, baud: u32) -> tokio_serial::Result<SerialStream> {
    let port = tokio_serial::new(path, baud)
        .dtr_on_open(true)
        .open_native_async()?;
    clear_hupcl(&port);
    Ok(port)
}

fn clear_hupcl(port: &SerialStream) {
    use nix::sys::termios::{tcgetattr, tcsetattr, ControlFlags, SetArg};
    use std::os::fd::{AsRawFd, BorrowedFd};
    // SAFETY: the descriptor belongs to `port`, which outlives this borrow.
    let fd = unsafe { BorrowedFd::borrow_raw(port.as_raw_fd()) };
    match tcgetattr(fd) {
        Ok(mut t) => {
            t.control_flags.remove(ControlFlags::HUPCL);
            if let Err(e) = tcsetattr(fd, SetArg::TCSANOW, &t) {
                debug!(error = %e, "cannot clear HUPCL");
            }
        }
        Err(e) => debug!(error = %e, "cannot read the port's termios"),
    }
}

/// The serial port and its health (when to try opening it again, what went wrong).
struct Port {
    path: PathBuf,
    baud: u32,
    stream: Option<SerialStream>,
    /// An open under way on a blocking thread (`open(2)` and `tcsetattr` of a USB adapter
    /// can hang): its result, and when it was started.
    opening: Option<(oneshot::Receiver<Result<SerialStream, String>>, Instant)>,
    watch: PortWatch,
}

/// The port being opened, once its blocking open returns (never while none is).
async fn port_opened(
    opening: &mut Option<(oneshot::Receiver<Result<SerialStream, String>>, Instant)>,
) -> (Result<SerialStream, String>, Instant) {
    match opening.as_mut() {
        Some((rx, at)) => {
            let at = *at;
            let r = rx
                .await
                .unwrap_or_else(|_| Err("the port's open was abandoned".to_string()));
            (r, at)
        }
        None => std::future::pending().await,
    }
}

/// The streamer task.
pub struct Streamer {
    shared: Arc<Shared>,
    port: Port,
    /// The machine link: edo's ([`EdoLink`]) or G-code's ([`GcodeLink`]).
    link: Box<dyn LinkAdapter>,
    lc: Lifecycle,
    /// Time zero of the link's and the lifecycle's clock.
    epoch: Instant,
    /// The store's answers (writes done or failed, reads).
    store_events: mpsc::UnboundedReceiver<Event>,
    /// The planner run under way and its output.
    planner: Option<(u64, mpsc::Receiver<PlannerOutput>)>,
    waiting: BTreeMap<u64, Waiting>,
    next_request: u64,
    estops: Vec<EStopWait>,
    /// When an underrun was last logged, and how many came since.
    underrun_logged: Option<(Instant, u64)>,
    /// The snapshot last pushed (`notify_machine_state`), and when.
    machine_notified: (Instant, MachineSnapshot),
}

impl Streamer {
    /// A streamer for `shared.port`; the lifecycle's service move indices start at
    /// `service_index`, reserved up to `service_reserved_until`; the store's answers
    /// arrive on `store_events`.
    pub fn new(
        shared: Arc<Shared>,
        service_index: u32,
        service_reserved_until: u32,
        store_events: mpsc::UnboundedReceiver<Event>,
    ) -> Self {
        let epoch = Instant::now();
        let opts = lifecycle_options(&shared.config, now_ms());
        let baud = shared.config.serial.baud;
        Self {
            port: Port {
                path: shared.port.clone(),
                baud,
                stream: None,
                opening: None,
                watch: PortWatch::new(
                    PortWatchOptions::default(),
                    &shared.port.display().to_string(),
                    baud,
                    epoch,
                ),
            },
            link: machine_link(&shared.config),
            lc: Lifecycle::new(opts, service_index, service_reserved_until),
            shared,
            epoch,
            store_events,
            planner: None,
            waiting: BTreeMap::new(),
            next_request: 1,
            estops: Vec::new(),
            underrun_logged: None,
            machine_notified: (epoch, MachineSnapshot::default()),
        }
    }

    /// After edod's restart over G-code: what tells the interrupted job's moves by line
    /// number ([`GcodeLink::with_resume`]).
    pub fn with_gcode_resume(mut self, resume: Option<crate::adapter::ResumeLines>) -> Self {
        if resume.is_some() {
            self.link = match machine_link_gcode(&self.shared.config) {
                Some(g) => Box::new(g.with_resume(resume)),
                None => self.link,
            };
        }
        self
    }

    fn now(&self) -> Micros {
        Micros(self.epoch.elapsed().as_micros() as u64)
    }

    /// How long the loop may sleep: until the link's or the lifecycle's next timer; not
    /// at all while the lifecycle has actions (an event after the last settle: a port
    /// lost while writing).
    fn wake(&self) -> Duration {
        if self.lc.has_actions() {
            return Duration::ZERO;
        }
        let now = self.now().0;
        [
            self.link.next_timeout().map(|t| t.0),
            self.lc.next_timeout(),
        ]
        .into_iter()
        .flatten()
        .map(|t| Duration::from_micros(t.saturating_sub(now)))
        .fold(TICK, Duration::min)
    }

    /// Run until a `Shutdown` request has been served.
    pub async fn run(mut self, mut control: mpsc::Receiver<Control>) {
        let mut buf = vec![0u8; 4096];
        self.pump().await;
        loop {
            let wake = self.wake();
            let wants = self.lc.wants_planner_output();
            tokio::select! {
                biased;
                c = control.recv() => match c {
                    Some(c) => self.on_control(c),
                    None => break,
                },
                r = read_port(&mut self.port.stream, &mut buf) => match r {
                    Ok(0) => self.port_lost("end of file"),
                    Ok(n) => {
                        let now = self.now();
                        self.link.handle_bytes(&buf[..n], now);
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                    Err(e) => self.port_lost(&e.to_string()),
                },
                (r, at) = port_opened(&mut self.port.opening) => {
                    self.port.opening = None;
                    self.on_port_opened(r, at);
                }
                Some(e) = self.store_events.recv() => self.handle(e),
                m = recv_planner(&mut self.planner, wants) => self.on_planner(m),
                _ = tokio::time::sleep(wake) => {}
            }
            self.pump().await;
            self.shared
                .alive
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if self.lc.is_stopped() {
                break;
            }
        }
    }

    fn handle(&mut self, e: Event) {
        let now = self.now().0;
        self.lc.handle(e, now);
    }

    // ---- port -------------------------------------------------------------------------

    fn try_open(&mut self) {
        let at = Instant::now();
        if self.port.stream.is_some() {
            let connected = self.lc.is_connected();
            log_port(
                &self.port.path,
                self.port.watch.check_handshake(connected, at),
            );
            return;
        }
        if self.port.opening.is_some() || !self.port.watch.open_due(at) {
            return;
        }
        // Opened on a blocking thread: a hanging device holds that thread, never a
        // runtime worker, and the streamer goes on answering.
        let path = self.port.path.display().to_string();
        let baud = self.port.baud;
        let (tx, rx) = oneshot::channel();
        tokio::task::spawn_blocking(move || {
            let _ = tx.send(open_port(&path, baud).map_err(|e| os_error(&e)));
        });
        self.port.opening = Some((rx, at));
    }

    /// The blocking open started at `at` returned.
    fn on_port_opened(&mut self, r: Result<SerialStream, String>, at: Instant) {
        match r {
            Ok(mut p) => {
                let _ = p.set_exclusive(false);
                info!(port = %self.port.path.display(), "serial port open");
                log_port(&self.port.path, self.port.watch.opened(at));
                self.port.stream = Some(p);
                let now = self.now();
                self.link.reconnect(now);
            }
            Err(e) => {
                let log = self.port.watch.open_failed(&e, at);
                log_port(&self.port.path, log);
            }
        }
    }

    /// The link's G-code marks to the store's writer (`docs/firmware.md`).
    fn hand_marks_over(&mut self) {
        while let Some(m) = self.link.poll_store_mark() {
            self.shared.store.writer.gcode_mark(m);
        }
    }

    fn port_lost(&mut self, why: &str) {
        self.port.stream = None;
        self.link.port_lost();
        self.port.watch.lost(why, Instant::now());
        self.handle(Event::PortLost { why: why.into() });
    }

    async fn write_out(&mut self) {
        let now = self.now();
        self.hand_marks_over();
        while let Some(bytes) = self.link.poll_transmit(now) {
            // A mark goes to the store's writer before the line it names.
            self.hand_marks_over();
            let Some(p) = self.port.stream.as_mut() else {
                return;
            };
            if let Err(e) = p.write_all(&bytes).await {
                self.port_lost(&e.to_string());
                return;
            }
        }
    }

    // ---- the pump ---------------------------------------------------------------------

    /// One pass of the driver: the link's and the lifecycle's timers, then events in
    /// and actions out until both are quiet ([`Streamer::settle`]), then the bytes out.
    async fn pump(&mut self) {
        self.try_open();
        let now = self.now();
        self.link.handle_timeout(now);
        self.link_events_in(now);
        self.lc.handle_timeout(now.0);
        self.settle(now);
        self.write_out().await;
        self.time_estops();
        self.log_link_lines();
        self.publish();
    }

    /// The link's events into the lifecycle, the lifecycle's actions carried out in the
    /// order it decided them, and moves fed to the link while it has room, until none of
    /// the three has more. The order is the point: a command (a hold, a stop, a job's
    /// end) reaches the link before the next move asks it for room, and what a move
    /// brings about (its job now printing) is carried out before the next move.
    fn settle(&mut self, now: Micros) {
        let ahead = self.shared.config.planner.moves_ahead;
        loop {
            self.link_events_in(now);
            while let Some(a) = self.lc.poll_action() {
                self.carry_out(a);
            }
            if !self.link.has_room(ahead) {
                return;
            }
            let Some(mv) = self.lc.poll_move() else {
                return;
            };
            if let Err(reason) = self.link.send_move(mv.clone()) {
                self.handle(Event::MoveRefused { mv, reason });
            }
        }
    }

    /// The link adapter's log lines into edod's log.
    fn log_link_lines(&mut self) {
        use crate::adapter::LogLevel;
        while let Some(l) = self.link.poll_log() {
            match l.level {
                LogLevel::Debug => tracing::debug!(target: "edo::adapter", "{}", l.text),
                LogLevel::Info => tracing::info!(target: "edo::adapter", "{}", l.text),
                LogLevel::Warn => tracing::warn!(target: "edo::adapter", "{}", l.text),
            }
        }
    }

    /// The link's events into the lifecycle (an acknowledged e-stop answers the
    /// operators waiting for it).
    fn link_events_in(&mut self, now: Micros) {
        while let Some(e) = self.link.poll_event(now) {
            if e == Event::CommandAcked(MachineCommand::EmergencyStop) {
                self.estops_acked();
            }
            self.lc.handle(e, now.0);
        }
    }

    /// Carry out one of the lifecycle's actions.
    fn carry_out(&mut self, a: Action) {
        match a {
            Action::Machine(c) => {
                let now = self.now();
                self.link.command(c, now);
            }
            Action::StartPlanner {
                job_id,
                from_index,
                run,
            } => self.start_planner(job_id, from_index, run),
            Action::StopPlanner => self.planner = None,
            Action::Persist { seq, record } => self.shared.store.writer.persist(seq, record),
            Action::LookUpJob(id) => self.shared.store.reader.look_up(id),
            Action::ListQueued => self.shared.store.reader.queued(),
            Action::Reply { request, result } => self.reply(request, result),
            Action::JobState(note) => {
                if matches!(
                    note.state,
                    JobState::Done | JobState::Cancelled | JobState::Failed
                ) {
                    self.link.job_ended(note.job_id);
                }
                self.notify_state(note)
            }
            Action::Progress(p) => self.progress(p),
            Action::Underrun(u) => self.log_underrun(&u),
            Action::Log {
                level,
                job,
                message,
            } => match level {
                Level::Info => info!(job = ?job, "{message}"),
                Level::Warn => warn!(job = ?job, "{message}"),
            },
        }
    }

    /// Start planning `job_id` from `from_index` as run `run`: the job and its mesh are
    /// read from the store on the planner's thread.
    fn start_planner(&mut self, job_id: u32, from_index: u32, run: u64) {
        let shared = Arc::clone(&self.shared);
        let syringes = self.link.report().remaining_nl.len().max(1);
        let source = move || {
            let (job, mesh) = shared
                .store
                .reader
                .source_blocking(job_id)
                .map_err(|e| format!("job {job_id}: {e}"))?;
            planner::source_of(&job, mesh.as_deref(), syringes, &shared.config)
        };
        let layers_ahead = self.shared.config.planner.layers_ahead;
        self.planner = Some((
            run,
            planner::spawn(source, job_id, from_index, layers_ahead),
        ));
    }

    fn on_planner(&mut self, m: Option<PlannerOutput>) {
        let Some(run) = self.planner.as_ref().map(|p| p.0) else {
            return;
        };
        let output = m.unwrap_or_else(|| {
            self.planner = None;
            PlannerOutput::Ended
        });
        self.handle(Event::Planner { run, output });
    }

    // ---- operators ----------------------------------------------------------------------

    fn on_control(&mut self, c: Control) {
        match c {
            Control::Submitted => self.handle(Event::Submitted),
            Control::Pause(id, reply) => {
                self.command(Command::Pause(id), Waiting::Change { id, reply })
            }
            Control::Resume(id, reply) => {
                self.command(Command::Resume(id), Waiting::Change { id, reply })
            }
            Control::Cancel(id, reply) => {
                self.command(Command::Cancel(id), Waiting::Change { id, reply })
            }
            Control::StartNext(id, reply) => match id.or_else(|| self.lc.first_queued()) {
                Some(id) => self.command(Command::StartNext(id), Waiting::Change { id, reply }),
                None => {
                    let _ = reply.send(Err(ApiError::new(ApiError::BAD_STATE, "no job is queued")));
                }
            },
            Control::EStop(asked, reply) => {
                self.command(Command::EStop, Waiting::EStop { asked, reply })
            }
            Control::Refill(reply) => self.command(Command::Refill, Waiting::Refill(reply)),
            Control::Shutdown(reply) => self.command(Command::Shutdown, Waiting::Shutdown(reply)),
        }
    }

    fn command(&mut self, command: Command, waiting: Waiting) {
        let request = self.next_request;
        self.next_request += 1;
        self.waiting.insert(request, waiting);
        self.handle(Event::Command {
            request: RequestId(request),
            command,
        });
    }

    fn refusal(&self, r: Refusal) -> ApiError {
        match r.kind {
            RefusalKind::NoSuchJob => ApiError::new(ApiError::NO_SUCH_JOB, r.message),
            RefusalKind::BadState => ApiError::new(ApiError::BAD_STATE, r.message),
            RefusalKind::NotConnected => ApiError::new(
                ApiError::NOT_CONNECTED,
                format!(
                    "the machine on {} is not connected",
                    self.port.path.display()
                ),
            ),
            RefusalKind::Internal => ApiError::new(ApiError::INTERNAL, r.message),
            RefusalKind::StoreCannotWrite => ApiError::new(ApiError::STORE_CANNOT_WRITE, r.message),
        }
    }

    fn reply(&mut self, request: RequestId, result: Result<Answer, Refusal>) {
        let Some(waiting) = self.waiting.remove(&request.0) else {
            return;
        };
        let result = result.map_err(|r| self.refusal(r));
        match waiting {
            Waiting::Change { id, reply } => {
                let change = result.map(|a| match a {
                    Answer::Applied(a) => StateChange {
                        id,
                        state: a.state,
                        stored: a.stored,
                    },
                    Answer::Done => StateChange {
                        id,
                        state: self.lc.job_state(id).unwrap_or(JobState::Failed),
                        stored: true,
                    },
                });
                let _ = reply.send(change);
            }
            Waiting::Refill(reply) => {
                let _ = reply.send(result.map(|_| ()));
            }
            Waiting::EStop { asked, reply } => match result {
                Err(e) => {
                    let _ = reply.send(Err(e));
                }
                Ok(_) if self.port.stream.is_none() || !self.lc.is_connected() => {
                    let _ = reply.send(Err(ApiError::new(
                        ApiError::NOT_CONNECTED,
                        "e-stop queued but the machine is not connected: use the machine's own e-stop",
                    )));
                }
                Ok(_) => self.estops.push(EStopWait {
                    asked,
                    written_after_us: None,
                    reply,
                }),
            },
            Waiting::Shutdown(reply) => {
                let _ = reply.send(());
            }
        }
    }

    /// The machine acknowledged an e-stop: the operators' e-stops are answered.
    fn estops_acked(&mut self) {
        let t = Instant::now();
        for e in self.estops.drain(..) {
            let _ = e.reply.send(Ok(EStopTiming {
                written_after_us: e.written_after_us.unwrap_or(0),
                acked_after_us: Some(t.duration_since(e.asked).as_micros() as u64),
            }));
        }
    }

    /// After a write to the port: the e-stops waiting are written (their frame goes
    /// ahead of everything), and those not acknowledged in time are answered without.
    fn time_estops(&mut self) {
        let t = Instant::now();
        for e in &mut self.estops {
            if e.written_after_us.is_none() {
                e.written_after_us = Some(t.duration_since(e.asked).as_micros() as u64);
            }
        }
        let (late, waiting): (Vec<_>, Vec<_>) = std::mem::take(&mut self.estops)
            .into_iter()
            .partition(|e| e.asked.elapsed() > ESTOP_ACK_WAIT);
        self.estops = waiting;
        for e in late {
            let _ = e.reply.send(Ok(EStopTiming {
                written_after_us: e.written_after_us.unwrap_or(0),
                acked_after_us: None,
            }));
        }
    }

    // ---- notifications, snapshot --------------------------------------------------------

    fn notify_state(&self, note: StateNote) {
        self.shared
            .notify(crate::proto::Event::JobState(JobStateChanged {
                job_id: note.job_id,
                state: note.state,
                reason: note.reason,
            }));
    }

    fn progress(&self, p: Option<Progress>) {
        match p {
            Some(p) => {
                self.shared
                    .notify(crate::proto::Event::JobProgress(p.clone()));
                self.shared.progress.send_replace(Some(p));
            }
            None => {
                self.shared
                    .progress
                    .send_if_modified(|p| p.take().is_some());
            }
        }
    }

    fn log_underrun(&mut self, u: &Underrun) {
        let Some(since) = log_now(
            &mut self.underrun_logged,
            Instant::now(),
            underrun_period_over,
        ) else {
            return;
        };
        let (in_link, in_flight) = self.link.in_link();
        warn!(
            job = u.job_id,
            executed = u.executed,
            waiting_here = u.waiting_here,
            in_link,
            in_flight,
            planner_running = u.planner_running,
            underruns = u.count,
            not_logged_since_last = since,
            "queue underrun: the machine ran out of moves"
        );
    }

    /// Why the machine is not connected, in words an operator can act on.
    fn disconnected_reason(&self) -> String {
        match (self.port.watch.problem(), &self.port.stream) {
            (Some(p), _) => p.to_string(),
            (None, None) => format!("port {}: not open yet", self.port.path.display()),
            (None, Some(_)) => "waiting for the machine's handshake".to_string(),
        }
    }

    fn publish(&mut self) {
        let counters = self.link.counters();
        let s = self.link.report();
        let identity = self.link.identity();
        let connected = self.lc.is_connected() && self.port.stream.is_some();
        let snap = MachineSnapshot {
            port: self.port.path.display().to_string(),
            connected,
            disconnected_reason: (!connected).then(|| self.disconnected_reason()),
            identity: identity.map(str::to_string),
            // Not connected, the machine's state is not known (it may have been reset,
            // stopped or be running on): null, not the last report.
            state: identity.filter(|_| connected).map(|_| s.state),
            queue_held_by: self.lc.queue_held_by(),
            store_problem: self
                .lc
                .store_problem()
                .map(|c| format!("job store cannot write: {c}")),
            last_executed: s.last_executed,
            executed_total: s.executed_total,
            remaining_nl: s.remaining_nl.clone(),
            queued: s.queued,
            faults: s.faults,
            position_mm: mm(s.position),
            active_job: self.lc.active_job(),
            link_problem: self.link.link_problem().filter(|_| connected),
            underruns: self.lc.underruns(),
            frames_retransmitted: counters.resent,
            srtt_ms: counters.srtt_us.unwrap_or(0) as f64 / 1000.0,
        };
        let now = Instant::now();
        if machine_notice_due(&self.machine_notified, &snap, now) {
            self.shared
                .notify(crate::proto::Event::MachineState(snap.clone()));
            self.machine_notified = (now, snap.clone());
        }
        self.shared.machine.send_replace(snap);
    }
}

/// Whether `snap` is pushed to subscribers, the last push being `last`: at once when
/// the connection, the machine's state, its faults, the active job, the held queue or
/// the store's problem change; while the machine moves (position, moves executed,
/// syringe levels), at most every [`MACHINE_NOTIFY_EVERY`], so a dashboard's position
/// follows the print.
fn machine_notice_due(
    last: &(Instant, MachineSnapshot),
    snap: &MachineSnapshot,
    now: Instant,
) -> bool {
    let (at, old) = last;
    let changed = old.connected != snap.connected
        || old.disconnected_reason != snap.disconnected_reason
        || old.link_problem != snap.link_problem
        || old.queue_held_by != snap.queue_held_by
        || old.store_problem != snap.store_problem
        || old.state != snap.state
        || old.faults != snap.faults
        || old.active_job != snap.active_job;
    let moved = old.position_mm != snap.position_mm
        || old.executed_total != snap.executed_total
        || old.remaining_nl != snap.remaining_nl;
    changed || moved && now.duration_since(*at) >= MACHINE_NOTIFY_EVERY
}

/// An open error in the OS's words: "No such file or directory", not the crate's
/// wrapping of it.
fn os_error(e: &tokio_serial::Error) -> String {
    let d = e.description.trim();
    if d.is_empty() {
        e.to_string()
    } else {
        d.to_string()
    }
}

/// Log what the port watch says.
fn log_port(path: &std::path::Path, log: Option<PortLog>) {
    match log {
        Some(PortLog::Warn { message, tries: 0 }) => warn!(port = %path.display(), "{message}"),
        Some(PortLog::Warn { message, tries }) => warn!(
            port = %path.display(),
            tries,
            "{message}; retrying (every 5 s at most)"
        ),
        Some(PortLog::Recovered { after_tries }) => info!(
            port = %path.display(),
            after_tries,
            "serial port open after it could not be opened"
        ),
        None => {}
    }
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    #[test]
    fn the_machine_is_pushed_on_a_change_at_once_and_while_moving_four_times_a_second() {
        use super::{machine_notice_due, MachineSnapshot};
        let t0 = Instant::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let last = (t0, MachineSnapshot::default());
        assert!(!machine_notice_due(
            &last,
            &MachineSnapshot::default(),
            ms(5000)
        ));
        let moved = MachineSnapshot {
            position_mm: [1.0, 2.0, 0.2],
            executed_total: 7,
            ..MachineSnapshot::default()
        };
        assert!(!machine_notice_due(&last, &moved, ms(100)));
        assert!(machine_notice_due(&last, &moved, ms(250)));
        let faulted = MachineSnapshot {
            faults: 1,
            ..MachineSnapshot::default()
        };
        assert!(machine_notice_due(&last, &faulted, ms(1)));
        let levels = MachineSnapshot {
            remaining_nl: vec![5],
            ..MachineSnapshot::default()
        };
        assert!(machine_notice_due(&last, &levels, ms(300)));
    }

    #[test]
    fn underruns_are_logged_at_most_every_ten_seconds_with_the_count_between() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let log_now = |logged: &mut Option<(Instant, u64)>, now| {
            super::log_now(logged, now, super::underrun_period_over)
        };
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
}
