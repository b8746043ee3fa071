//! `hil-sim --gcode rrf|marlin|klipper`: the G-code protocol end of the [`crate::sim`]
//! runtime, the firmware model of [`edo::gcode_link`] in place of the edo link, with the
//! same port, machine model and recorder. The firmware model reads the lines (Marlin
//! checks numbers and checksums and asks for resends, RRF drops bad lines silently,
//! Klipper ignores both), the [`GcodeMachine`] turns the commands it ran into moves, and
//! moves execute on simulated machine time, freeing the firmware's planner blocks as they
//! finish. Faults are per line (`inject::Lines`, `docs/firmware.md`), seeded: corrupted
//! lines each way, lost lines and `ok`s, resend requests out of the blue, busy periods,
//! a firmware reset (its banner mid-job) and an unplug.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;

use anyhow::Context;
use edo::gcode_link::{Dialect, Firmware, FirmwareConfig, Micros, MixWriting};
use edo::link::testkit::SimRng;
use edo::link::FaultKind;
use edo::machine::Move;

use crate::faults::Faults;
use crate::gcode_machine::GcodeMachine;
use crate::inject::{Injector, Lines};
use crate::sim::{
    after_ms, Booted, Executing, FaultOutcome, ProtocolEnd, Rebooted, SimConfig, Summary,
};

/// Line credit the G-code simulator banks: about one tick of line time at 250 000 baud,
/// so a line that follows a pause still takes its bytes' time, as on a UART, and one
/// line at a time pays for the idle line between `ok` and the next line.
const UART_BANK_BYTES: f64 = 16.0;

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
            c.keepalive_interval_us = Some(ms.max(1).saturating_mul(1000));
        }
        c
    }
}

/// A line the firmware ran that became a move: its text, and whether the move holds a
/// planner block.
pub(crate) struct Line {
    text: String,
    planner: bool,
}

/// The G-code protocol end: the firmware model and the interpreter turning the lines
/// it ran into moves, waiting for the executor.
pub(crate) struct GcodeEnd {
    opts: GcodeOptions,
    firmware: Firmware,
    machine: GcodeMachine,
    console: Option<BufWriter<File>>,
    /// Seeded draws of resend requests, one per numbered line received.
    rng: SimRng,
    /// Seeded draws of busy periods, one per move completed: apart from `rng`, so how
    /// the lines' arrival interleaves with the moves' completion (wall-clock timing)
    /// does not change which moves start a busy period.
    busy_rng: SimRng,
    waiting: VecDeque<(Move, Line)>,
}

impl GcodeEnd {
    /// The firmware booted, seeded from `seeds` (the injectors, then resends, then busy
    /// periods); the console log created.
    pub(crate) fn boot(
        cfg: &SimConfig,
        opts: &GcodeOptions,
        mut seeds: SimRng,
    ) -> anyhow::Result<Booted<Self>> {
        let console = match &opts.console {
            Some(p) => {
                Some(BufWriter::new(File::create(p).with_context(|| {
                    format!("create console log {}", p.display())
                })?))
            }
            None => None,
        };
        let area_mm2 = f64::from(cfg.barrel_area_um2) / 1e6;
        let to_firmware = Injector::new(seeds.next_u64(), Lines::to_firmware());
        let to_host = Injector::new(seeds.next_u64(), Lines::to_host());
        let end = GcodeEnd {
            opts: opts.clone(),
            firmware: Firmware::new(opts.firmware_config(), Micros(0)),
            machine: GcodeMachine::new(opts.mix.clone(), cfg.syringes, area_mm2),
            console,
            rng: SimRng::new(seeds.next_u64()),
            busy_rng: SimRng::new(seeds.next_u64()),
            waiting: VecDeque::new(),
        };
        Ok((end, to_firmware, to_host))
    }

    /// Emergency stop (M112 through the emergency parser).
    fn kill(&mut self, now_us: u64) {
        self.firmware.handle_bytes(b"\nM112\n", Micros(now_us));
    }
}

impl ProtocolEnd for GcodeEnd {
    type Unit = Lines;
    type Tag = Line;
    const BANK_BYTES: f64 = UART_BANK_BYTES;
    const BATCHES_RESETS: bool = false;

    fn receive(&mut self, unit: &[u8], now_us: u64, f: &Faults, sum: &mut Summary) {
        // A resend request out of the blue: Marlin rejects this good numbered line as
        // line noise would (Error, Resend, ok), as OctoPrint's virtual printer's resend
        // ratio does.
        if unit.first() == Some(&b'N') && self.rng.chance(f.resend) {
            sum.resend_requests += 1;
            self.firmware.inject_spurious_resend();
        }
        self.firmware.handle_bytes(unit, Micros(now_us));
    }

    /// The firmware's timers, then the lines it ran: into moves for the executor.
    fn poll(&mut self, now_us: u64) -> bool {
        let now = Micros(now_us);
        self.firmware.handle_timeout(now);
        while let Some(line) = self.firmware.poll_line() {
            if let Some(w) = self.console.as_mut() {
                // A console log that cannot be written is the test's loss, not the run's.
                let _ = writeln!(w, "{}", line.text).and_then(|_| w.flush());
            }
            match self.machine.command(&line.text) {
                Some(mv) => {
                    let tag = Line {
                        text: line.text,
                        planner: line.is_move,
                    };
                    self.waiting.push_back((mv, tag));
                }
                // An arc or a move the interpreter does not draw: its block frees at once.
                None if line.is_move => self.firmware.moves_done(1, now),
                None => {}
            }
        }
        // Kill / M112 / shutdown: motion stops, what was planned is gone.
        let halted = self.firmware.is_halted();
        if halted {
            self.waiting.clear();
        }
        halted
    }

    fn next_move(&mut self) -> Option<(Move, Line)> {
        self.waiting.pop_front()
    }

    fn move_failed(&mut self, fault: FaultKind, tag: &Line, now_us: u64) {
        eprintln!("hil-sim: {fault:?} on {:?}: halting", tag.text);
        self.kill(now_us);
    }

    fn move_done(
        &mut self,
        done: &Executing<Line>,
        _remaining: &[u32],
        now_us: u64,
        f: &Faults,
        sum: &mut Summary,
    ) {
        if done.tag.planner {
            self.firmware.moves_done(1, Micros(now_us));
        }
        if self.busy_rng.chance(f.busy) {
            // A busy period: the handler blocks (a long command, the user's pause);
            // Marlin sends `busy: processing` keepalives meanwhile.
            sum.busy_periods += 1;
            let until = after_ms(now_us, f.busy_for_ms);
            self.firmware.stall(Micros(until), Micros(now_us));
        }
    }

    fn record_fields(&self, done: &Executing<Line>) -> (u32, Option<String>) {
        (self.machine.layer(), Some(done.tag.text.clone()))
    }

    /// The e-stop button halts the firmware as M112 does; G-code has no empty syringe
    /// or limit switch to report.
    fn machine_fault(&mut self, fault: FaultKind, now_us: u64) -> FaultOutcome {
        match fault {
            FaultKind::EStopPressed => {
                self.kill(now_us);
                FaultOutcome::Reported
            }
            _ => FaultOutcome::Unsupported,
        }
    }

    /// The board restarts: queue, planner and line number lost. RRF's native USB port
    /// re-enumerates (the host sees the port close); Marlin prints its boot banner;
    /// Klipper says Disconnect, then Ready.
    fn reset(&mut self, now_us: u64) -> Rebooted {
        self.firmware.reset(Micros(now_us));
        self.waiting.clear();
        Rebooted {
            banner: b"",
            unplugs: self.opts.firmware == Dialect::Rrf,
        }
    }

    fn poll_transmit(&mut self, _now_us: u64) -> Option<Vec<u8>> {
        self.firmware.poll_transmit()
    }

    fn holds_work(&self) -> bool {
        !self.waiting.is_empty()
            || self.firmware.rx_len() > 0
            || self.firmware.queue_len() > 0
            || self.firmware.planner_len() > 0
    }

    fn status(&self) -> serde_json::Map<String, serde_json::Value> {
        let status = serde_json::json!({
            "firmware": format!("{:?}", self.opts.firmware),
            "halted": self.firmware.is_halted(),
            "last_line": self.firmware.last_line_number(),
            "queue": self.firmware.queue_len(),
            "planner": self.firmware.planner_len(),
        });
        match status {
            serde_json::Value::Object(m) => m,
            _ => serde_json::Map::new(),
        }
    }
}
