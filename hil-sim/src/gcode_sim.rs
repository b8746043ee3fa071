//! `hil-sim --gcode rrf|marlin|klipper`: the firmware model of [`edo::gcode_link`] on the
//! pty instead of the edo link, with the same machine model and recorder. The firmware
//! model reads the lines (Marlin checks numbers and checksums and asks for resends, RRF
//! drops bad lines silently, Klipper ignores both), the [`GcodeMachine`] turns the
//! commands it ran into moves, and moves execute on simulated machine time, freeing the
//! firmware's planner blocks as they finish. Faults are per line (`docs/firmware.md`),
//! seeded: corrupted lines each way, lost lines and `ok`s, resend requests out of the
//! blue, busy periods, a firmware reset (its banner mid-job) and an unplug.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use anyhow::Context;
use edo::gcode_link::{Dialect, Firmware, FirmwareConfig, Micros, MixWriting};
use edo::link::testkit::SimRng;
use edo::machine::Move;

use crate::faults::Faults;
use crate::gcode_machine::GcodeMachine;
use crate::model::{Executed, MachineModel};
use crate::record::{write_line, RecordLine};
use crate::sim::{move_kind_name, um_to_mm, Command, PtyPort, SimConfig, Summary, UART_BANK_BYTES};

/// The G-code mode's settings (`--gcode`, `--gcode-mix`, ...).
#[derive(Debug, Clone, PartialEq)]
pub struct GcodeOptions {
    /// The firmware modelled.
    pub firmware: Dialect,
    /// How the mix is written on the lines.
    pub mix: MixWriting,
    /// Marlin `ADVANCED_OK`.
    pub advanced_ok: bool,
    /// The firmware's receive buffer (default: the model's).
    pub rx_buffer_bytes: Option<usize>,
    /// Marlin `BUFSIZE`, the command queue (default: the model's).
    pub command_slots: Option<usize>,
    /// Marlin: the `busy:` keepalive interval, ms (default: the model's 2 s, `M113 S2`);
    /// tests scale it down with their timeouts.
    pub keepalive_interval_ms: Option<u64>,
    /// A console log: every line the firmware ran, in order, one per line, as text (no
    /// `N`, no checksum; lines it refused are not in it). What a Klipper pty received
    /// across edod's restarts, which tests/peers/run_klipper_peer.sh runs through klippy.
    pub console: Option<PathBuf>,
}

impl GcodeOptions {
    /// `firmware` with its usual mix writing (RRF per-drive E, Marlin `M163`, Klipper axes
    /// A B C ...).
    pub fn new(firmware: Dialect, syringes: usize) -> Self {
        let mix = match firmware {
            Dialect::Rrf => MixWriting::PerDriveE,
            Dialect::Marlin => MixWriting::MarlinM163,
            Dialect::Klipper => MixWriting::Axes(('A'..='W').take(syringes).collect()),
        };
        Self {
            firmware,
            mix,
            advanced_ok: false,
            rx_buffer_bytes: None,
            command_slots: None,
            keepalive_interval_ms: None,
            console: None,
        }
    }

    fn firmware_config(&self) -> FirmwareConfig {
        let mut c = FirmwareConfig::for_dialect(self.firmware);
        c.advanced_ok = self.advanced_ok;
        // A lab building for edod builds Marlin with EMERGENCY_PARSER (docs/firmware.md).
        c.emergency_parser = true;
        if let Some(rx) = self.rx_buffer_bytes {
            c.rx_buffer_bytes = rx;
        }
        if let Some(slots) = self.command_slots {
            c.command_slots = slots.max(1);
        }
        if let Some(ms) = self
            .keepalive_interval_ms
            .filter(|_| c.keepalive_interval_us.is_some())
        {
            c.keepalive_interval_us = Some(ms.max(1) * 1000);
        }
        c
    }
}

/// Splits a byte stream into lines and applies the line faults, keeping order.
struct LineInjector {
    rng: SimRng,
    cur: Vec<u8>,
    queue: VecDeque<(u64, Vec<u8>)>,
    to_host: bool,
}

impl LineInjector {
    fn new(seed: u64, to_host: bool) -> Self {
        Self {
            rng: SimRng::new(seed),
            cur: Vec::new(),
            queue: VecDeque::new(),
            to_host,
        }
    }

    fn push(&mut self, bytes: &[u8], now_us: u64, f: &Faults, sum: &mut Summary) {
        for &b in bytes {
            self.cur.push(b);
            if b == b'\n' || self.cur.len() > 4096 {
                let line = std::mem::take(&mut self.cur);
                self.line(line, now_us, f, sum);
            }
        }
    }

    fn line(&mut self, mut line: Vec<u8>, now_us: u64, f: &Faults, sum: &mut Summary) {
        let is_ok = line.starts_with(b"ok");
        if self.rng.chance(f.drop) || (self.to_host && is_ok && self.rng.chance(f.drop_ok)) {
            sum.frames_dropped += 1;
            return;
        }
        let corrupt = if self.to_host {
            f.corrupt_reply
        } else {
            f.corrupt_line
        };
        if self.rng.chance(corrupt) && corrupt_one_byte(&mut self.rng, &mut line) {
            sum.bits_flipped += 1;
        }
        let copies = if self.rng.chance(f.dup) {
            sum.frames_duplicated += 1;
            2
        } else {
            1
        };
        let at = now_us + f.delay_ms * 1000;
        for _ in 0..copies {
            self.queue.push_back((at, line.clone()));
        }
    }

    fn pop_due(&mut self, now_us: u64) -> Option<Vec<u8>> {
        if self.queue.front()?.0 <= now_us {
            self.queue.pop_front().map(|q| q.1)
        } else {
            None
        }
    }

    fn clear(&mut self) {
        self.queue.clear();
        self.cur.clear();
    }
}

/// One byte of a line changed, its framing kept: not the first byte, a `*` or a line end,
/// and never into a line end or `;` (the checksum's blind spots, `docs/firmware.md`).
fn corrupt_one_byte(rng: &mut SimRng, line: &mut [u8]) -> bool {
    let eligible: Vec<usize> = (1..line.len())
        .filter(|&i| !matches!(line[i], b'\n' | b'\r' | b'*') && line[i - 1] != b'\n')
        .collect();
    if eligible.is_empty() {
        return false;
    }
    let i = eligible[(rng.next_u64() % eligible.len() as u64) as usize];
    loop {
        let b = line[i] ^ ((rng.next_u64() % 255 + 1) as u8);
        if !matches!(b, b'\n' | b'\r' | b';') {
            line[i] = b;
            return true;
        }
    }
}

/// A move under way: the move, what executing it did, when (simulated µs) it is done,
/// the command it came from, and whether it holds a planner block.
struct Executing {
    mv: Move,
    ex: Executed,
    done_at: u64,
    text: String,
    planner: bool,
}

/// The G-code mode's runtime; [`GcodeSim::tick`] is one turn of the loop.
struct GcodeSim<'a> {
    cfg: &'a SimConfig,
    opts: GcodeOptions,
    faults: Faults,
    port: PtyPort,
    /// Seeded draws of resend requests, one per numbered line received.
    rng: SimRng,
    /// Seeded draws of busy periods, one per move completed: apart from `rng`, so how
    /// the lines' arrival interleaves with the moves' completion (wall-clock timing)
    /// does not change which moves start a busy period.
    busy_rng: SimRng,
    recorder: Option<BufWriter<File>>,
    console: Option<BufWriter<File>>,
    start: Instant,
    firmware: Firmware,
    machine: GcodeMachine,
    model: MachineModel,
    to_firmware: LineInjector,
    to_host: LineInjector,
    tx: VecDeque<u8>,
    sum: Summary,
    last_tick: u64,
    waiting: VecDeque<(Move, String, bool)>,
    executing: Option<Executing>,
    sim_time_us: f64,
    stall_until: u64,
    timed_done: [bool; 3],
    reset_fired: bool,
    buf: Vec<u8>,
}

/// Run the G-code mode until `stop` is set.
pub fn run(
    cfg: &SimConfig,
    opts: &GcodeOptions,
    stop: &AtomicBool,
    commands: Option<Receiver<Command>>,
    on_ready: &mut dyn FnMut(&Path),
) -> anyhow::Result<Summary> {
    let (mut sim, ready) = GcodeSim::new(cfg, opts.clone())?;
    on_ready(&ready);
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_micros(300));
        sim.tick(commands.as_ref())?;
    }
    sim.finish()
}

impl<'a> GcodeSim<'a> {
    fn new(cfg: &'a SimConfig, opts: GcodeOptions) -> anyhow::Result<(Self, PathBuf)> {
        let mut rng = SimRng::new(cfg.seed);
        let (port, ready) = PtyPort::open(cfg.link.as_deref(), cfg.baud, UART_BANK_BYTES)?;
        let recorder = match &cfg.record {
            Some(p) => Some(BufWriter::new(
                File::create(p).with_context(|| format!("create record {}", p.display()))?,
            )),
            None => None,
        };
        let console = match &opts.console {
            Some(p) => {
                Some(BufWriter::new(File::create(p).with_context(|| {
                    format!("create console log {}", p.display())
                })?))
            }
            None => None,
        };
        let area_mm2 = f64::from(cfg.barrel_area_um2) / 1e6;
        let mixer = cfg
            .mixer_options()
            .map_err(|e| anyhow::anyhow!("mixer {e}"))?;
        let sim = GcodeSim {
            cfg,
            faults: cfg.faults.clone(),
            port,
            recorder,
            console,
            start: Instant::now(),
            firmware: Firmware::new(opts.firmware_config(), Micros(0)),
            machine: GcodeMachine::new(opts.mix.clone(), cfg.syringes, area_mm2),
            model: MachineModel::new(cfg.syringes, cfg.capacity_nl, cfg.barrel_area_um2, &mixer),
            to_firmware: LineInjector::new(rng.next_u64(), false),
            to_host: LineInjector::new(rng.next_u64(), true),
            rng: SimRng::new(rng.next_u64()),
            busy_rng: SimRng::new(rng.next_u64()),
            opts,
            tx: VecDeque::new(),
            sum: Summary::default(),
            last_tick: 0,
            waiting: VecDeque::new(),
            executing: None,
            sim_time_us: 0.0,
            stall_until: 0,
            timed_done: [false; 3],
            reset_fired: false,
            buf: vec![0u8; 4096],
        };
        Ok((sim, ready))
    }

    fn tick(&mut self, commands: Option<&Receiver<Command>>) -> anyhow::Result<()> {
        let now_us = self.start.elapsed().as_micros() as u64;
        let dt = now_us.saturating_sub(self.last_tick);
        self.last_tick = now_us;
        if let Some(rx) = commands {
            self.take_commands(rx, now_us);
        }
        self.timed_faults(now_us);
        self.port.replug_if_due(now_us)?;
        let stalled = now_us < self.stall_until;
        self.receive(now_us, dt, stalled)?;
        self.run_firmware(now_us);
        self.execute(now_us, dt)?;
        self.transmit(now_us, dt, stalled)
    }

    fn take_commands(&mut self, rx: &Receiver<Command>, now_us: u64) {
        while let Ok(c) = rx.try_recv() {
            match c {
                Command::Fault(item) => {
                    let _ = self.faults.apply(&item);
                }
                Command::Reset => self.reset(now_us),
                Command::Unplug => self.unplug(now_us),
                Command::Stall(ms) => self.stall_until = now_us + ms * 1000,
                // The machine's own e-stop: the firmware halts as on M112.
                Command::EStop => self.firmware.handle_bytes(b"\nM112\n", Micros(now_us)),
                Command::Empty(_) | Command::Limit(_) => {
                    eprintln!("hil-sim: empty and limit are edo-protocol faults")
                }
                Command::Clear => {
                    let f = &mut self.faults;
                    f.drop = 0.0;
                    f.dup = 0.0;
                    f.delay_ms = 0;
                    f.corrupt_line = 0.0;
                    f.corrupt_reply = 0.0;
                    f.drop_ok = 0.0;
                    f.resend = 0.0;
                    f.busy = 0.0;
                }
                Command::Status => eprintln!(
                    "{}",
                    serde_json::json!({
                        "firmware": format!("{:?}", self.opts.firmware),
                        "halted": self.firmware.is_halted(),
                        "last_line": self.firmware.last_line_number(),
                        "queue": self.firmware.queue_len(),
                        "planner": self.firmware.planner_len(),
                        "summary": self.sum,
                    })
                ),
            }
        }
    }

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
                0 => self.stall_until = now_us + self.faults.stall_for_ms * 1000,
                1 => self.reset(now_us),
                _ => self.unplug(now_us),
            }
        }
    }

    /// The board restarts: queue, planner and line number lost. RRF's native USB port
    /// re-enumerates (the host sees the port close); Marlin prints its boot banner;
    /// Klipper says Disconnect, then Ready.
    fn reset(&mut self, now_us: u64) {
        self.firmware.reset(Micros(now_us));
        self.waiting.clear();
        self.executing = None;
        self.tx.clear();
        self.to_firmware.clear();
        self.to_host.clear();
        self.sum.resets += 1;
        if self.opts.firmware == Dialect::Rrf {
            self.unplug(now_us);
        }
    }

    /// The cable is pulled (the shared [`PtyPort`]): bytes on the line are lost.
    fn unplug(&mut self, now_us: u64) {
        if self.port.unplug(now_us, self.faults.unplug_for_ms) {
            self.tx.clear();
            self.to_firmware.clear();
            self.sum.unplugs += 1;
        }
    }

    fn receive(&mut self, now_us: u64, dt: u64, stalled: bool) -> anyhow::Result<()> {
        let n = self.port.read(&mut self.buf, dt, stalled, &mut self.sum)?;
        self.to_firmware
            .push(&self.buf[..n], now_us, &self.faults, &mut self.sum);
        while let Some(b) = self.to_firmware.pop_due(now_us) {
            // A resend request out of the blue: Marlin rejects this good numbered line
            // as line noise would (Error, Resend, ok), as OctoPrint's virtual printer's
            // resend ratio does.
            if b.first() == Some(&b'N') && self.rng.chance(self.faults.resend) {
                self.sum.resend_requests += 1;
                self.firmware.inject_spurious_resend();
            }
            self.firmware.handle_bytes(&b, Micros(now_us));
        }
        Ok(())
    }

    /// The firmware's timers, then the lines it ran: into moves for the executor.
    fn run_firmware(&mut self, now_us: u64) {
        let now = Micros(now_us);
        self.firmware.handle_timeout(now);
        while let Some(line) = self.firmware.poll_line() {
            if let Some(w) = self.console.as_mut() {
                // A console log that cannot be written is the test's loss, not the run's.
                let _ = writeln!(w, "{}", line.text).and_then(|_| w.flush());
            }
            match self.machine.command(&line.text) {
                Some(mv) => self.waiting.push_back((mv, line.text, line.is_move)),
                // An arc or a move the interpreter does not draw: its block frees at once.
                None if line.is_move => self.firmware.moves_done(1, now),
                None => {}
            }
        }
        if self.firmware.is_halted() {
            // Kill / M112 / shutdown: motion stops, what was planned is gone.
            self.waiting.clear();
            self.executing = None;
        }
    }

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
            let Some((mv, text, planner)) = self.waiting.pop_front() else {
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
                        text,
                        planner,
                    });
                }
                Err(fault) => {
                    eprintln!("hil-sim: {fault:?} on {text:?}: halting");
                    self.firmware.handle_bytes(b"\nM112\n", Micros(now_us));
                }
            }
        }
        Ok(())
    }

    fn complete(&mut self, done: Executing, now_us: u64) -> anyhow::Result<()> {
        self.sum.executed += 1;
        if let Some(w) = self.recorder.as_mut() {
            let line = RecordLine {
                job_id: done.mv.job_id,
                index: done.mv.index,
                kind: move_kind_name(&done.mv.kind).to_string(),
                layer: self.machine.layer(),
                t_s: done.done_at as f64 / 1e6,
                from_mm: um_to_mm(done.ex.from),
                to_mm: um_to_mm(done.ex.to),
                volumes_nl: done.mv.kind.volumes_nl().to_vec(),
                exit_composition: done.ex.exit_composition.clone(),
                remaining_nl: self.model.remaining_nl(),
                gcode: Some(done.text),
            };
            write_line(w, &line)?;
        }
        if done.planner {
            self.firmware.moves_done(1, Micros(now_us));
        }
        if self.busy_rng.chance(self.faults.busy) {
            // A busy period: the handler blocks (a long command, the user's pause);
            // Marlin sends `busy: processing` keepalives meanwhile.
            self.sum.busy_periods += 1;
            let until = now_us + self.faults.busy_for_ms * 1000;
            self.firmware.stall(Micros(until), Micros(now_us));
        }
        if !self.reset_fired && self.faults.reset_at_moves == Some(self.sum.executed) {
            self.reset_fired = true;
            if let Some(w) = self.recorder.as_mut() {
                w.flush()?;
            }
            self.reset(now_us);
        }
        if self.faults.estop_at_moves == Some(self.sum.executed) {
            self.firmware.handle_bytes(b"\nM112\n", Micros(now_us));
        }
        Ok(())
    }

    fn transmit(&mut self, now_us: u64, dt: u64, stalled: bool) -> anyhow::Result<()> {
        while let Some(b) = self.firmware.poll_transmit() {
            if !stalled {
                self.to_host.push(&b, now_us, &self.faults, &mut self.sum);
            }
        }
        while let Some(b) = self.to_host.pop_due(now_us) {
            self.tx.extend(b);
        }
        self.port.write(&mut self.tx, dt, &mut self.sum)
    }

    fn finish(mut self) -> anyhow::Result<Summary> {
        if let Some(w) = self.recorder.as_mut() {
            w.flush()?;
        }
        self.port.remove_link();
        Ok(self.sum)
    }
}
