//! The simulator runtime, one for both protocols: a pseudo-terminal throttled to the
//! baud rate (`port`), the wall and machine clocks, the run-time [`Command`]s, a fault
//! injector each way (`inject`, per frame or per line), the recorder and the
//! [`MachineModel`], with the protocol end plugged in behind a trait (`ProtocolEnd`):
//! the machine end of the edo link (`link_end`) or a G-code firmware model (`--gcode`,
//! [`crate::gcode_sim`]). One turn of the loop: commands and timed faults, host to
//! machine through the injector into the protocol end, moves executed, the protocol
//! end's replies through the other injector to the host.
//!
//! Link timers run on wall time (the host on the other side of the pty does too); move
//! durations run on simulated machine time, `--speed` times faster than wall time.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Receiver;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use edo::link::testkit::SimRng;
use edo::link::FaultKind;
use edo::machine::{Move, MoveKind};

use crate::faults::Faults;
use crate::gcode_sim::GcodeEnd;
use crate::inject::{Injector, Unit};
use crate::link_end::LinkEnd;
use crate::model::{Executed, MachineModel};
use crate::port::PtyPort;
use crate::record::{write_line, RecordLine};

/// Simulator settings (the command line, as a struct).
#[derive(Debug, Clone)]
pub struct SimConfig {
    /// Create this path as a symlink to the pty the host should open.
    pub link: Option<PathBuf>,
    /// Line speed in baud (10 bits per byte), both directions.
    pub baud: u32,
    /// Machine time runs this many times faster than wall time.
    pub speed: f64,
    /// Number of syringes (1..=8).
    pub syringes: usize,
    /// Move queue depth.
    pub queue: u16,
    /// Seed of the fault injector and boot ids.
    pub seed: u64,
    /// Record executed moves (JSON lines) here.
    pub record: Option<PathBuf>,
    /// Faults.
    pub faults: Faults,
    /// Mixing chamber dead volume V_dead (nl): the volume of the chamber, whatever its
    /// model.
    pub dead_volume_nl: u64,
    /// The chamber's residence-time distribution (`--mixer`, default plug flow).
    pub mixer: edo::mixer::MixerModel,
    /// Peclet number of the `dispersion` model (`--mixer-peclet`).
    pub mixer_peclet: Option<f64>,
    /// The chamber's volume in nl when not `dead_volume_nl` (`--mixer-volume-nl`).
    pub mixer_volume_nl: Option<f64>,
    /// Capacity of each syringe (nl).
    pub capacity_nl: u32,
    /// Barrel cross-section of each syringe (µm²).
    pub barrel_area_um2: u32,
    /// Receive buffer advertised to the host (bytes).
    pub rx_buffer_bytes: u32,
    /// Speak G-code as this firmware instead of the edo link (`hil-sim --gcode`).
    pub gcode: Option<crate::gcode_sim::GcodeOptions>,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            link: None,
            baud: 250_000,
            speed: 1.0,
            syringes: 2,
            queue: 128,
            seed: 1,
            record: None,
            faults: Faults::parse("").unwrap_or_default(),
            dead_volume_nl: 20_000,
            mixer: edo::mixer::MixerModel::Plug,
            mixer_peclet: None,
            mixer_volume_nl: None,
            capacity_nl: 10_000_000,
            barrel_area_um2: 78_539_816,
            rx_buffer_bytes: 2048,
            gcode: None,
        }
    }
}

impl SimConfig {
    /// The mixing chamber: `mixer` through `mixer_volume_nl`, else `dead_volume_nl` (an
    /// error names the key).
    pub fn mixer_options(&self) -> Result<edo::mixer::MixerOptions, edo::mixer::MixerError> {
        let o = edo::mixer::MixerOptions {
            model: self.mixer,
            volume_nl: self.mixer_volume_nl.unwrap_or(self.dead_volume_nl as f64),
            peclet: self.mixer_peclet,
        };
        o.validate()?;
        Ok(o)
    }
}

/// A command given at run time (stdin of the binary, or a channel in tests).
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Change a fault: a `--faults` item such as `drop=0.05`.
    Fault(String),
    /// Reset now.
    Reset,
    /// Unplug now (for `unplug-for`).
    Unplug,
    /// Stop answering for this many milliseconds.
    Stall(u64),
    /// Press the machine's e-stop button.
    EStop,
    /// Syringe N runs empty.
    Empty(u8),
    /// Limit switch of axis N trips.
    Limit(u8),
    /// Clear rate faults.
    Clear,
    /// Print the status on stderr.
    Status,
    /// Send the status to whoever asked ([`SimHandle::status`]).
    Report(StatusReply),
}

/// Where a [`Command::Report`] sends the status. Two are never equal (each is one
/// asker's channel), so a `Command` holding one equals no other.
#[derive(Debug, Clone)]
pub struct StatusReply(std::sync::mpsc::Sender<serde_json::Value>);

impl PartialEq for StatusReply {
    fn eq(&self, _: &Self) -> bool {
        false
    }
}

impl Command {
    /// Parse one command line (see `FAULTS_HELP`).
    pub fn parse(line: &str) -> Result<Self, String> {
        let mut words = line.split_whitespace();
        let first = words.next().ok_or("empty command")?;
        let arg = |w: Option<&str>| -> Result<u64, String> {
            w.ok_or(format!("{first}: needs a number"))?
                .parse::<u64>()
                .map_err(|_| format!("{first}: not a number"))
        };
        Ok(match first {
            "reset" => Command::Reset,
            "unplug" => Command::Unplug,
            "stall" => Command::Stall(arg(words.next())?),
            "estop" => Command::EStop,
            "empty" => Command::Empty(arg(words.next())?.min(7) as u8),
            "limit" => Command::Limit(arg(words.next())?.min(2) as u8),
            "clear" => Command::Clear,
            "status" => Command::Status,
            item if item.contains('=') => {
                Faults::default().apply(item).map_err(|e| e.to_string())?;
                Command::Fault(item.to_string())
            }
            other => return Err(format!("unknown command {other:?}")),
        })
    }
}

/// What a run did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Moves executed.
    pub executed: u64,
    /// Resets injected.
    pub resets: u64,
    /// Unplugs injected.
    pub unplugs: u64,
    /// Frames dropped by the injector.
    pub frames_dropped: u64,
    /// Frames duplicated by the injector.
    pub frames_duplicated: u64,
    /// Bits flipped by the injector.
    pub bits_flipped: u64,
    /// Bytes read from the host.
    pub bytes_from_host: u64,
    /// Bytes written to the host.
    pub bytes_to_host: u64,
    /// G-code modes: good lines answered with a resend request (`resend=P`).
    pub resend_requests: u64,
    /// G-code modes: busy periods injected (`busy=P`).
    pub busy_periods: u64,
}

/// Run the simulator until `stop` is set. `on_ready` gets the path the host should open
/// (the symlink if one was asked for, else the pty itself).
pub fn run(
    cfg: &SimConfig,
    stop: &AtomicBool,
    commands: Option<Receiver<Command>>,
    on_ready: &mut dyn FnMut(&Path),
) -> anyhow::Result<Summary> {
    if cfg.syringes == 0 || cfg.syringes > edo::machine::MAX_SYRINGES {
        bail!(
            "--syringes {}: must be 1..={}",
            cfg.syringes,
            edo::machine::MAX_SYRINGES
        );
    }
    if cfg.baud == 0 || cfg.speed.is_nan() || cfg.speed <= 0.0 {
        bail!("--baud and --speed must be positive");
    }
    match &cfg.gcode {
        Some(opts) => run_end(cfg, stop, commands, on_ready, |seeds| {
            GcodeEnd::boot(cfg, opts, seeds)
        }),
        None => run_end(cfg, stop, commands, on_ready, |seeds| {
            Ok(LinkEnd::boot(cfg, seeds))
        }),
    }
}

/// How a machine fault ([`FaultKind`]) went at the protocol end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FaultOutcome {
    /// The protocol has no such fault (G-code: an empty syringe, a limit switch).
    Unsupported,
    /// Reported; motion stops, if at all, through the protocol end (a halted firmware).
    Reported,
    /// Reported, and the move under way stops now (the edo link's e-stop).
    MotionStopped,
}

/// What a reset of the protocol end puts on the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Rebooted {
    /// Bytes the boot writes straight onto the line (past the injector).
    pub(crate) banner: &'static [u8],
    /// The port re-enumerates: the host sees it close (RRF's native USB).
    pub(crate) unplugs: bool,
}

/// A move under way: the move, what executing it did, when (simulated µs) it is done,
/// and what the protocol end keeps with it ([`ProtocolEnd::Tag`]).
pub(crate) struct Executing<T> {
    pub(crate) mv: Move,
    pub(crate) ex: Executed,
    pub(crate) done_at: u64,
    pub(crate) tag: T,
}

/// The protocol end plugged into the [`Runtime`]: the edo link's machine end
/// ([`crate::link_end::LinkEnd`]) or a G-code firmware ([`crate::gcode_sim::GcodeEnd`]).
/// It reads the units the injector lets through, hands out moves, hears of them done,
/// and writes its replies; the runtime owns the line, the clocks, the faults, the
/// machine model and the recorder.
pub(crate) trait ProtocolEnd {
    /// The unit the fault injectors split the line into.
    type Unit: Unit;
    /// What a move carries besides itself (G-code: its line).
    type Tag;
    /// Line credit the port banks while idle (see [`PtyPort`]).
    const BANK_BYTES: f64;
    /// Resets and unplugs asked for within one turn (commands, timed faults) happen once,
    /// after the other commands (the edo link); else each at once, in order (G-code).
    const BATCHES_RESETS: bool;

    /// A unit from the host came through the injector at `now_us`.
    fn receive(&mut self, unit: &[u8], now_us: u64, f: &Faults, sum: &mut Summary);
    /// After receiving: timers, events, lines run. True if motion stops now.
    fn poll(&mut self, now_us: u64) -> bool;
    /// The next move to execute.
    fn next_move(&mut self) -> Option<(Move, Self::Tag)>;
    /// The machine model refused a move.
    fn move_failed(&mut self, fault: FaultKind, tag: &Self::Tag, now_us: u64);
    /// A move is done (`remaining`: the syringes after it).
    fn move_done(
        &mut self,
        done: &Executing<Self::Tag>,
        remaining: &[u32],
        now_us: u64,
        f: &Faults,
        sum: &mut Summary,
    );
    /// The recorded layer of a move done, and its G-code line if any.
    fn record_fields(&self, done: &Executing<Self::Tag>) -> (u32, Option<String>);
    /// A fault of the machine (e-stop button, empty syringe, limit switch).
    fn machine_fault(&mut self, fault: FaultKind, now_us: u64) -> FaultOutcome;
    /// The machine restarts.
    fn reset(&mut self, now_us: u64) -> Rebooted;
    /// Bytes for the host.
    fn poll_transmit(&mut self, now_us: u64) -> Option<Vec<u8>>;
    /// The `status` command's fields (the summary is added).
    fn status(&self) -> serde_json::Map<String, serde_json::Value>;
    /// Whether anything received is not yet handed to the machine model: bytes of a
    /// line or frame, commands queued, moves planned.
    fn holds_work(&self) -> bool;
}

/// Run a simulator with the protocol end `boot` makes from the seeds (with its
/// injectors, host to machine and machine to host) until `stop` is set.
fn run_end<E: ProtocolEnd>(
    cfg: &SimConfig,
    stop: &AtomicBool,
    commands: Option<Receiver<Command>>,
    on_ready: &mut dyn FnMut(&Path),
    boot: impl FnOnce(SimRng) -> anyhow::Result<Booted<E>>,
) -> anyhow::Result<Summary> {
    let (mut sim, ready_path) = Runtime::new(cfg, boot)?;
    on_ready(&ready_path);
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_micros(300));
        sim.tick(commands.as_ref())?;
    }
    sim.finish()
}

/// A protocol end at boot and its fault injectors: host to machine, machine to host.
pub(crate) type Booted<E> = (
    E,
    Injector<<E as ProtocolEnd>::Unit>,
    Injector<<E as ProtocolEnd>::Unit>,
);

/// Resets and unplugs waiting for the end of the commands ([`ProtocolEnd::BATCHES_RESETS`]).
#[derive(Debug, Default)]
struct Pending {
    reset: bool,
    unplug: bool,
}

/// A running simulator: the pty, the protocol end and the machine model, the fault
/// injectors of both directions, the recorder and the clocks. [`Runtime::tick`] is one
/// turn of the loop: commands and timed faults, host to machine, moves, machine to host.
struct Runtime<'a, E: ProtocolEnd> {
    cfg: &'a SimConfig,
    /// The faults now (run-time commands change them).
    faults: Faults,
    port: PtyPort,
    recorder: Option<BufWriter<File>>,
    /// Wall time starts here.
    start: Instant,
    end: E,
    model: MachineModel,
    to_machine: Injector<E::Unit>,
    to_host: Injector<E::Unit>,
    /// Bytes waiting for the line to the host.
    tx: VecDeque<u8>,
    sum: Summary,
    last_tick: u64,
    executing: Option<Executing<E::Tag>>,
    sim_time_us: f64,
    stall_until: u64,
    pending: Pending,
    /// Timed faults already fired: stall, reset, unplug.
    timed_done: [bool; 3],
    /// Move-count faults already fired: reset, empty, limit, e-stop.
    fired: [bool; 4],
    buf: Vec<u8>,
}

impl<'a, E: ProtocolEnd> Runtime<'a, E> {
    /// A simulator on a fresh pty, and the path the host should open.
    fn new(
        cfg: &'a SimConfig,
        boot: impl FnOnce(SimRng) -> anyhow::Result<Booted<E>>,
    ) -> anyhow::Result<(Self, PathBuf)> {
        let (port, ready_path) = PtyPort::open(cfg.link.as_deref(), cfg.baud, E::BANK_BYTES)?;
        let recorder = match &cfg.record {
            Some(p) => Some(BufWriter::new(
                File::create(p).with_context(|| format!("create record {}", p.display()))?,
            )),
            None => None,
        };
        let start = Instant::now();
        let (end, to_machine, to_host) = boot(SimRng::new(cfg.seed))?;
        let mixer = cfg
            .mixer_options()
            .map_err(|e| anyhow::anyhow!("mixer {e}"))?;
        let model = MachineModel::new(cfg.syringes, cfg.capacity_nl, cfg.barrel_area_um2, &mixer);
        let sim = Runtime {
            cfg,
            faults: cfg.faults.clone(),
            port,
            recorder,
            start,
            end,
            model,
            to_machine,
            to_host,
            tx: VecDeque::new(),
            sum: Summary::default(),
            last_tick: 0,
            executing: None,
            sim_time_us: 0.0,
            stall_until: 0,
            pending: Pending::default(),
            timed_done: [false; 3],
            fired: [false; 4],
            buf: vec![0u8; 4096],
        };
        Ok((sim, ready_path))
    }

    /// One turn of the loop.
    fn tick(&mut self, commands: Option<&Receiver<Command>>) -> anyhow::Result<()> {
        let now_us = self.start.elapsed().as_micros() as u64;
        let dt = now_us.saturating_sub(self.last_tick);
        self.last_tick = now_us;
        if let Some(rx) = commands {
            self.take_commands(rx, now_us);
        }
        self.timed_faults(now_us);
        self.run_pending(now_us);
        self.port.replug_if_due(now_us)?;
        let stalled = now_us < self.stall_until;
        self.receive(now_us, dt, stalled)?;
        self.execute(now_us, dt)?;
        self.transmit(now_us, dt, stalled)
    }

    /// Apply the run-time commands waiting.
    fn take_commands(&mut self, rx: &Receiver<Command>, now_us: u64) {
        while let Ok(c) = rx.try_recv() {
            match c {
                Command::Fault(item) => {
                    let _ = self.faults.apply(&item);
                }
                Command::Reset => self.ask_reset(now_us),
                Command::Unplug => self.ask_unplug(now_us),
                Command::Stall(ms) => self.stall_until = after_ms(now_us, ms),
                Command::EStop => {
                    self.machine_fault(FaultKind::EStopPressed, now_us);
                }
                Command::Empty(n) => self.command_fault(FaultKind::SyringeEmpty(n), now_us),
                Command::Limit(a) => self.command_fault(FaultKind::LimitHit(a), now_us),
                Command::Clear => clear_rate_faults(&mut self.faults),
                Command::Status => eprintln!("{}", self.status()),
                Command::Report(StatusReply(to)) => {
                    let _ = to.send(self.status());
                }
            }
        }
    }

    /// The protocol end's status, the run's summary and whether the machine is idle:
    /// no move running, none waiting in the protocol end, no bytes held by the injector.
    fn status(&self) -> serde_json::Value {
        let mut status = self.end.status();
        status.insert("summary".into(), serde_json::json!(self.sum));
        let idle = self.executing.is_none() && !self.end.holds_work() && self.to_machine.is_empty();
        status.insert("idle".into(), idle.into());
        serde_json::Value::Object(status)
    }

    /// A machine fault asked for on the command line.
    fn command_fault(&mut self, fault: FaultKind, now_us: u64) {
        if !self.machine_fault(fault, now_us) {
            eprintln!("hil-sim: empty and limit are edo-protocol faults");
        }
    }

    /// A machine fault at the protocol end (an empty syringe empties the model's too);
    /// false if the protocol has no such fault.
    fn machine_fault(&mut self, fault: FaultKind, now_us: u64) -> bool {
        match self.end.machine_fault(fault, now_us) {
            FaultOutcome::Unsupported => return false,
            FaultOutcome::MotionStopped => self.executing = None,
            FaultOutcome::Reported => {}
        }
        if let FaultKind::SyringeEmpty(n) = fault {
            if let Some(s) = self.model.syringes.get_mut(usize::from(n)) {
                s.remaining_nl = 0;
            }
        }
        true
    }

    /// Fire the faults timed in seconds from the start (each once): stall, reset, unplug.
    fn timed_faults(&mut self, now_us: u64) {
        let secs = now_us as f64 / 1e6;
        let due = [
            self.faults.stall_at_s,
            self.faults.reset_after_s,
            self.faults.unplug_at_s,
        ];
        for (k, at) in due.iter().enumerate() {
            if self.timed_done[k] || !at.is_some_and(|a| secs >= a) {
                continue;
            }
            self.timed_done[k] = true;
            match k {
                0 => self.stall_until = after_ms(now_us, self.faults.stall_for_ms),
                1 => self.ask_reset(now_us),
                _ => self.ask_unplug(now_us),
            }
        }
    }

    /// A reset asked for: now, or at the end of the commands.
    fn ask_reset(&mut self, now_us: u64) {
        if E::BATCHES_RESETS {
            self.pending.reset = true;
        } else {
            self.reset(now_us);
        }
    }

    /// An unplug asked for: now, or at the end of the commands.
    fn ask_unplug(&mut self, now_us: u64) {
        if E::BATCHES_RESETS {
            self.pending.unplug = true;
        } else {
            self.unplug(now_us);
        }
    }

    /// The reset, then the unplug, asked for this turn.
    fn run_pending(&mut self, now_us: u64) {
        let p = std::mem::take(&mut self.pending);
        if p.reset {
            self.reset(now_us);
        }
        if p.unplug {
            self.unplug(now_us);
        }
    }

    /// The machine resets: a new boot of the protocol end, the move under way and the
    /// bytes in flight lost, the boot banner on the line.
    fn reset(&mut self, now_us: u64) {
        let boot = self.end.reset(now_us);
        self.executing = None;
        self.tx.clear();
        self.to_machine.clear();
        self.to_host.clear();
        self.tx.extend(boot.banner);
        self.sum.resets += 1;
        if boot.unplugs {
            self.unplug(now_us);
        }
    }

    /// The cable is pulled: the pty closes (the host sees a hang-up) until the replug
    /// time; bytes on the line are lost.
    fn unplug(&mut self, now_us: u64) {
        if self.port.unplug(now_us, self.faults.unplug_for_ms) {
            self.tx.clear();
            self.to_machine.clear();
            self.sum.unplugs += 1;
        }
    }

    /// Host -> machine, throttled to the baud rate, through the injector into the
    /// protocol end.
    fn receive(&mut self, now_us: u64, dt: u64, stalled: bool) -> anyhow::Result<()> {
        let n = self.port.read(&mut self.buf, dt, stalled, &mut self.sum)?;
        self.to_machine
            .push(&self.buf[..n], now_us, &self.faults, &mut self.sum);
        while let Some(b) = self.to_machine.pop_due(now_us) {
            self.end.receive(&b, now_us, &self.faults, &mut self.sum);
        }
        if self.end.poll(now_us) {
            self.executing = None;
        }
        Ok(())
    }

    /// Execute moves on simulated machine time: finish the move under way when its
    /// time has come, start the next.
    fn execute(&mut self, now_us: u64, dt: u64) -> anyhow::Result<()> {
        self.sim_time_us += dt as f64 * self.cfg.speed;
        loop {
            if let Some(e) = &self.executing {
                if (self.sim_time_us as u64) < e.done_at {
                    break;
                }
                if let Some(done) = self.executing.take() {
                    self.complete(done, now_us)?;
                }
            }
            let Some((mv, tag)) = self.end.next_move() else {
                // Idle: make the recording complete on disk for whoever reads it now
                // (a no-op when nothing was written since the last flush).
                if let Some(w) = self.recorder.as_mut() {
                    w.flush()?;
                }
                break;
            };
            match self.model.execute(&mv) {
                Ok(ex) => {
                    let done_at = self.sim_time_us as u64 + ex.duration_us;
                    self.executing = Some(Executing {
                        mv,
                        ex,
                        done_at,
                        tag,
                    });
                }
                Err(fault) => self.end.move_failed(fault, &tag, now_us),
            }
        }
        Ok(())
    }

    /// A move done: recorded, reported, and the faults set at its count fired.
    fn complete(&mut self, done: Executing<E::Tag>, now_us: u64) -> anyhow::Result<()> {
        let remaining = self.model.remaining_nl();
        self.sum.executed += 1;
        self.record(&done, &remaining)?;
        self.end
            .move_done(&done, &remaining, now_us, &self.faults, &mut self.sum);
        self.fire_move_faults(now_us)
    }

    /// Record a move done (finished at simulated time `done.done_at`).
    fn record(&mut self, done: &Executing<E::Tag>, remaining: &[u32]) -> anyhow::Result<()> {
        let Some(w) = self.recorder.as_mut() else {
            return Ok(());
        };
        let (layer, gcode) = self.end.record_fields(done);
        let (mv, ex) = (&done.mv, &done.ex);
        let line = RecordLine {
            job_id: mv.job_id,
            index: mv.index,
            kind: move_kind_name(&mv.kind).to_string(),
            layer,
            t_s: done.done_at as f64 / 1e6,
            from_mm: um_to_mm(ex.from),
            to_mm: um_to_mm(ex.to),
            volumes_nl: mv.kind.volumes_nl().to_vec(),
            exit_composition: ex.exit_composition.clone(),
            remaining_nl: remaining.to_vec(),
            gcode,
        };
        write_line(w, &line)
    }

    /// Fire the faults set at a count of executed moves (each once).
    fn fire_move_faults(&mut self, now_us: u64) -> anyhow::Result<()> {
        let n = self.sum.executed;
        let triggers = [
            self.faults.reset_at_moves,
            self.faults.empty_at_moves,
            self.faults.limit_at_moves,
            self.faults.estop_at_moves,
        ];
        for (k, t) in triggers.iter().enumerate() {
            if *t != Some(n) || self.fired[k] {
                continue;
            }
            self.fired[k] = true;
            let fault = match k {
                0 => {
                    // The moves done so far are on disk before the machine goes.
                    if let Some(w) = self.recorder.as_mut() {
                        w.flush()?;
                    }
                    self.reset(now_us);
                    continue;
                }
                1 => FaultKind::SyringeEmpty(0),
                2 => FaultKind::LimitHit(0),
                _ => FaultKind::EStopPressed,
            };
            self.machine_fault(fault, now_us);
        }
        Ok(())
    }

    /// Machine -> host: the protocol end's bytes through the injector (lost while
    /// stalled), throttled to the baud rate onto the pty (dropped while unplugged).
    fn transmit(&mut self, now_us: u64, dt: u64, stalled: bool) -> anyhow::Result<()> {
        while let Some(b) = self.end.poll_transmit(now_us) {
            if !stalled {
                self.to_host.push(&b, now_us, &self.faults, &mut self.sum);
            }
        }
        while let Some(b) = self.to_host.pop_due(now_us) {
            self.tx.extend(b);
        }
        self.port.write(&mut self.tx, dt, &mut self.sum)
    }

    /// Stop: the recording flushed, the link's symlink removed.
    fn finish(mut self) -> anyhow::Result<Summary> {
        if let Some(w) = self.recorder.as_mut() {
            w.flush()?;
        }
        self.port.remove_link();
        Ok(self.sum)
    }
}

/// `ms` milliseconds after `now_us`, in µs (saturating: a fault's duration comes from
/// the command line or stdin, unchecked).
pub(crate) fn after_ms(now_us: u64, ms: u64) -> u64 {
    now_us.saturating_add(ms.saturating_mul(1000))
}

/// The `clear` command: the rate faults of both protocols off (each protocol reads only
/// its own).
fn clear_rate_faults(f: &mut Faults) {
    f.corrupt = 0.0;
    f.drop = 0.0;
    f.dup = 0.0;
    f.delay_ms = 0;
    f.jitter_ms = 0;
    f.corrupt_line = 0.0;
    f.corrupt_reply = 0.0;
    f.drop_ok = 0.0;
    f.resend = 0.0;
    f.busy = 0.0;
}

pub(crate) fn move_kind_name(k: &MoveKind) -> &'static str {
    match k {
        MoveKind::Travel { .. } => "travel",
        MoveKind::Extrude { .. } => "extrude",
        MoveKind::Retract { .. } => "retract",
        MoveKind::Prime { .. } => "prime",
        MoveKind::Dwell { .. } => "dwell",
        MoveKind::LayerMark { .. } => "layer",
        MoveKind::Home => "home",
    }
}

pub(crate) fn um_to_mm(p: edo::machine::PositionUm) -> [f64; 3] {
    [
        f64::from(p.x_um) / 1000.0,
        f64::from(p.y_um) / 1000.0,
        f64::from(p.z_um) / 1000.0,
    ]
}

/// A simulator running in a thread of this process (for tests).
pub struct SimHandle {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    commands: std::sync::mpsc::Sender<Command>,
    thread: Option<std::thread::JoinHandle<anyhow::Result<Summary>>>,
}

impl SimHandle {
    /// Path the host should open.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Send a run-time command.
    pub fn command(&self, c: Command) {
        let _ = self.commands.send(c);
    }

    /// The simulator's status (`status` on the binary's stdin), read at the start of its
    /// next turn; `None` when it has stopped or does not answer within 10 s.
    pub fn status(&self) -> Option<serde_json::Value> {
        let (tx, rx) = std::sync::mpsc::channel();
        self.commands.send(Command::Report(StatusReply(tx))).ok()?;
        rx.recv_timeout(Duration::from_secs(10)).ok()
    }

    /// Wait until the machine is idle in two turns in a row (every byte the host sent
    /// before has been read and run); false after `timeout`, or at once when the
    /// simulator does not answer (stopped).
    pub fn wait_idle(&self, timeout: Duration) -> bool {
        let deadline = std::time::Instant::now() + timeout;
        let mut idle_turns = 0;
        while std::time::Instant::now() < deadline {
            let Some(status) = self.status() else {
                return false;
            };
            idle_turns = if status["idle"] == true {
                idle_turns + 1
            } else {
                0
            };
            if idle_turns == 2 {
                return true;
            }
        }
        false
    }

    /// Stop the simulator and return its summary.
    pub fn stop(mut self) -> anyhow::Result<Summary> {
        self.stop.store(true, Ordering::Relaxed);
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => bail!("simulator thread panicked"),
            None => bail!("simulator already stopped"),
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Start a simulator on a fresh pty in a thread; returns once it is ready.
pub fn spawn(cfg: SimConfig) -> anyhow::Result<SimHandle> {
    let stop = Arc::new(AtomicBool::new(false));
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let (cmd_tx, cmd_rx) = std::sync::mpsc::channel();
    let stop2 = Arc::clone(&stop);
    let thread = std::thread::spawn(move || {
        let tx = ready_tx.clone();
        let r = run(&cfg, &stop2, Some(cmd_rx), &mut |p| {
            let _ = tx.send(Ok(p.to_path_buf()));
        });
        if let Err(e) = &r {
            let _ = ready_tx.send(Err(e.to_string()));
        }
        r
    });
    match ready_rx.recv_timeout(Duration::from_secs(10)) {
        Ok(Ok(path)) => Ok(SimHandle {
            path,
            stop,
            commands: cmd_tx,
            thread: Some(thread),
        }),
        Ok(Err(e)) => bail!("simulator failed to start: {e}"),
        Err(_) => bail!("simulator did not become ready within 10 s"),
    }
}
