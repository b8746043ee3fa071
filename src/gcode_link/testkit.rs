//! A seeded serial wire with faults in simulated time, and a harness that streams G-code
//! lines from a [`LineHost`] to a [`Firmware`] model through it, playing the job
//! lifecycle's part (resume after a reset, recover after a lost link). No threads, no
//! clocks: a run is a pure function of its configuration and seed.
//!
//! The wire ([`SerialWire`]) sends bytes at `baud / 10` bytes per second, each direction
//! in order, delivered in pieces of `piece_bytes` (1 = a UART, where the firmware sees a
//! line arrive byte by byte; 64 = USB packets) after a fixed latency. Faults per written
//! chunk (one line): one byte corrupted (host → firmware: framing kept, see
//! [`WireFaults::protect_line_framing`]), a dropped `ok` line, an unplug (everything in
//! flight and written meanwhile is lost).

use std::collections::{HashMap, VecDeque};

use super::{
    Dialect, Firmware, FirmwareConfig, FirmwareStats, LastAccepted, LineEvent, LineHost,
    LineLinkConfig, LineStats, LinkState, Micros,
};
use crate::link::testkit::SimRng;

/// Faults of one direction of a [`SerialWire`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WireFaults {
    /// Probability that a written chunk has one byte corrupted.
    pub corrupt_chunk: f64,
    /// Keep line framing intact when corrupting: never the first byte of a line, its `*`
    /// or its `\n`, never into `\n`, `\r` or `;`. A corrupted `N` or line end defeats
    /// Marlin's checks, a corrupted `*` or a new `;` RRF's (`docs/firmware.md`, "What the
    /// checksum does not catch"); unit tests pin those cases.
    pub protect_line_framing: bool,
    /// Probability that a chunk that is an `ok` line is lost.
    pub drop_ok: f64,
}

/// One direction of a simulated serial line.
#[derive(Debug)]
pub struct SerialWire {
    byte_time_ns: u64,
    latency_us: u64,
    piece_bytes: usize,
    faults: WireFaults,
    rng: SimRng,
    free_at_ns: u64,
    in_flight: VecDeque<(Micros, Vec<u8>)>,
    connected: bool,
    /// Bytes put on the wire.
    pub bytes_on_wire: u64,
    /// Chunks corrupted.
    pub corrupted: u64,
    /// `ok` lines dropped.
    pub oks_dropped: u64,
}

impl SerialWire {
    /// A wire at `baud` (10 bits a byte) with `latency_us` added to every delivery.
    pub fn new(
        baud: u32,
        latency_us: u64,
        piece_bytes: usize,
        faults: WireFaults,
        seed: u64,
    ) -> Self {
        Self {
            byte_time_ns: 10_000_000_000 / u64::from(baud.max(1)),
            latency_us,
            piece_bytes: piece_bytes.max(1),
            faults,
            rng: SimRng::new(seed),
            free_at_ns: 0,
            in_flight: VecDeque::new(),
            connected: true,
            bytes_on_wire: 0,
            corrupted: 0,
            oks_dropped: 0,
        }
    }

    /// Plug or unplug: unplugging loses everything in flight and everything written
    /// until plugged again.
    pub fn set_connected(&mut self, connected: bool) {
        self.connected = connected;
        if !connected {
            self.in_flight.clear();
        }
    }

    /// Lose everything in flight (the other end rebooted).
    pub fn cut(&mut self) {
        self.in_flight.clear();
    }

    /// Time at which the wire is idle again.
    pub fn busy_until(&self) -> Micros {
        Micros(self.free_at_ns.div_ceil(1000))
    }

    /// Write a chunk at `now`.
    pub fn write(&mut self, bytes: &[u8], now: Micros) {
        if !self.connected || bytes.is_empty() {
            return;
        }
        if bytes.starts_with(b"ok") && self.rng.chance(self.faults.drop_ok) {
            self.oks_dropped += 1;
            return;
        }
        let mut data = bytes.to_vec();
        if self.rng.chance(self.faults.corrupt_chunk) && self.corrupt_one_byte(&mut data) {
            self.corrupted += 1;
        }
        let start = self.free_at_ns.max(now.0 * 1000);
        for (i, piece) in data.chunks(self.piece_bytes).enumerate() {
            let end_ns = start + ((i * self.piece_bytes + piece.len()) as u64) * self.byte_time_ns;
            let at = Micros(end_ns.div_ceil(1000) + self.latency_us);
            self.in_flight.push_back((at, piece.to_vec()));
        }
        self.free_at_ns = start + data.len() as u64 * self.byte_time_ns;
        self.bytes_on_wire += data.len() as u64;
    }

    fn corrupt_one_byte(&mut self, data: &mut [u8]) -> bool {
        let eligible: Vec<usize> = (0..data.len())
            .filter(|&i| {
                !self.faults.protect_line_framing
                    || (data[i] != b'\n' && data[i] != b'*' && i > 0 && data[i - 1] != b'\n')
            })
            .collect();
        if eligible.is_empty() {
            return false;
        }
        let i = eligible[(self.rng.next_u64() % eligible.len() as u64) as usize];
        loop {
            let mask = (self.rng.next_u64() % 255 + 1) as u8;
            let b = data[i] ^ mask;
            if !self.faults.protect_line_framing || !matches!(b, b'\n' | b'\r' | b';') {
                data[i] = b;
                return true;
            }
        }
    }

    /// Earliest pending delivery.
    pub fn next_delivery(&self) -> Option<Micros> {
        self.in_flight.front().map(|d| d.0)
    }

    /// A piece due at `now`.
    pub fn deliver(&mut self, now: Micros) -> Option<Vec<u8>> {
        if self.in_flight.front()?.0 <= now {
            self.in_flight.pop_front().map(|d| d.1)
        } else {
            None
        }
    }
}

/// Faults of a harness run.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GcodeFaults {
    /// Probability that a line to the firmware has one byte corrupted (framing kept).
    pub corrupt_to_firmware: f64,
    /// Probability that a reply line has one byte corrupted (any byte).
    pub corrupt_to_host: f64,
    /// Probability that an `ok` line is lost.
    pub drop_ok: f64,
    /// Probability, per line sent, that Marlin rejects its next good line (a resend
    /// request nobody caused).
    pub spurious_resend: f64,
    /// Probability, per move executed, of a busy period (a stalled handler).
    pub busy_chance: f64,
    /// Length of a busy period, µs.
    pub busy_us: u64,
    /// Reset the firmware after this many job lines executed.
    pub reset_after_lines: Option<u32>,
    /// Unplug the cable after this many job lines executed...
    pub unplug_after_lines: Option<u32>,
    /// ...for this long, µs.
    pub unplug_us: u64,
}

/// A harness run's setup.
#[derive(Debug, Clone)]
pub struct GcodeHarnessConfig {
    /// Line speed, both ways.
    pub baud: u32,
    /// Latency added to every delivery, µs (USB frames, the bridge chip, the OS).
    pub latency_us: u64,
    /// Delivery piece host → firmware (1: UART byte by byte).
    pub piece_bytes: usize,
    /// Host end.
    pub host: LineLinkConfig,
    /// Firmware model.
    pub firmware: FirmwareConfig,
    /// Faults.
    pub faults: GcodeFaults,
    /// Time a move takes to execute once planned, µs (0: at once).
    pub exec_us_per_move: u64,
    /// Lines sent with their time (`exec_us_per_move`), as edod sends moves
    /// ([`LineHost::send_timed_line`]), not untimed.
    pub timed_lines: bool,
    /// Lines kept queued in the host.
    pub backlog: usize,
    /// Seed of everything random.
    pub seed: u64,
}

impl GcodeHarnessConfig {
    /// A clean run against `dialect`'s defaults at 250000 baud.
    pub fn new(dialect: Dialect) -> Self {
        Self {
            baud: 250_000,
            latency_us: 1_000,
            piece_bytes: 1,
            host: LineLinkConfig::for_dialect(dialect),
            firmware: FirmwareConfig::for_dialect(dialect),
            faults: GcodeFaults::default(),
            exec_us_per_move: 0,
            timed_lines: false,
            backlog: 32,
            seed: 1,
        }
    }
}

/// What a harness run observed.
#[derive(Debug, Clone, Default)]
pub struct GcodeReport {
    /// Job lines asked for.
    pub lines: u32,
    /// Job lines the firmware ran as sent (numbered and checked where the firmware checks),
    /// repeats included, in order of running.
    pub executed: Vec<u32>,
    /// Runs of a line already run.
    pub duplicates: u64,
    /// Of those, runs right after the same line (a repeated line).
    pub adjacent_duplicates: u64,
    /// Lines run before a line below them that had not run yet.
    pub reordered: u64,
    /// Job lines never run.
    pub lost: u64,
    /// Lines the firmware ran that the host never sent as such (fragments, garbage).
    pub foreign_lines_run: u64,
    /// Whole job lines the firmware ran again unchecked (a Marlin drain fragment that
    /// began at the command).
    pub fragment_repeats: u64,
    /// [`LineEvent::Accepted`] events.
    pub accepted_events: u64,
    /// Accepted events not for the tag after the previous one (within a session).
    pub accepted_out_of_order: u64,
    /// [`LineEvent::MaybeRepeated`] events.
    pub maybe_repeated: u64,
    /// Inexact recoveries (RRF), each may repeat one line.
    pub inexact_recoveries: u64,
    /// [`LineEvent::Reset`] events.
    pub resets: u64,
    /// [`LineEvent::LinkLost`] events.
    pub link_lost: u64,
    /// [`LineEvent::Stopped`] events.
    pub stopped: u64,
    /// [`LineEvent::Halted`] events.
    pub halted: u64,
    /// Recoveries through `recover_last_accepted`.
    pub recoveries: u64,
    /// [`LineEvent::ProtocolError`] events.
    pub protocol_errors: u64,
    /// Protocol errors saying the firmware ran an unnumbered line.
    pub unnumbered_reported: u64,
    /// Simulated time, µs.
    pub elapsed_us: u64,
    /// Bytes on the wire host → firmware.
    pub wire_bytes_to_firmware: u64,
    /// All job lines ran before the time limit.
    pub completed: bool,
    /// Host counters.
    pub host_stats: LineStats,
    /// Firmware counters.
    pub firmware_stats: FirmwareStats,
}

impl GcodeReport {
    /// Job lines run per second of simulated time.
    pub fn moves_per_s(&self) -> f64 {
        if self.elapsed_us == 0 {
            return 0.0;
        }
        self.executed.len() as f64 / (self.elapsed_us as f64 / 1e6)
    }

    /// Bytes of job lines sent (line number, checksum, newline included) over the line's
    /// capacity (baud / 10 bytes a second) for the run's time.
    pub fn utilisation(&self, baud: u32) -> f64 {
        let capacity = f64::from(baud) / 10.0 * self.elapsed_us as f64 / 1e6;
        if capacity <= 0.0 {
            return 0.0;
        }
        self.host_stats.line_bytes_sent as f64 / capacity
    }
}

/// A realistic extrusion line, unique per index (E grows with it).
pub fn test_line(index: u32) -> String {
    format!(
        "G1 X{:.3} Y{:.3} E{:.5} F1800",
        50.0 + f64::from(index % 1000) * 0.137,
        60.0 + f64::from(index % 97) * 0.211,
        0.01 + f64::from(index) * 1e-5
    )
}

/// What the lifecycle waits to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pending {
    None,
    /// Recover the last accepted line once the cable is back, then resume.
    Recover,
    /// Waiting for the answer of `recover_last_accepted`.
    Answer,
}

/// Host and firmware on two wires, with an executor and the lifecycle's recovery.
#[derive(Debug)]
pub struct GcodeHarness {
    cfg: GcodeHarnessConfig,
    /// Simulated now.
    pub now: Micros,
    /// The host end.
    pub host: LineHost,
    /// The firmware model.
    pub firmware: Firmware,
    to_firmware: SerialWire,
    to_host: SerialWire,
    rng: SimRng,
    index_of: HashMap<String, u32>,
    planned: VecDeque<Micros>,
    next_exec: Micros,
    ran: Vec<bool>,
    /// Lowest job line not yet run.
    ran_next: u32,
    next_tag: u32,
    expected_accept: Option<u64>,
    unplugged_until: Option<Micros>,
    pending: Pending,
    last_unacknowledged: Vec<u64>,
    report: GcodeReport,
}

impl GcodeHarness {
    /// A harness at time 0.
    pub fn new(cfg: GcodeHarnessConfig) -> Self {
        let mut rng = SimRng::new(cfg.seed);
        let host = LineHost::new(cfg.host.clone());
        let firmware = Firmware::new(cfg.firmware.clone(), Micros(0));
        let f = &cfg.faults;
        let to_firmware = SerialWire::new(
            cfg.baud,
            cfg.latency_us,
            cfg.piece_bytes,
            WireFaults {
                corrupt_chunk: f.corrupt_to_firmware,
                protect_line_framing: true,
                drop_ok: 0.0,
            },
            rng.next_u64(),
        );
        let to_host = SerialWire::new(
            cfg.baud,
            cfg.latency_us,
            64,
            WireFaults {
                corrupt_chunk: f.corrupt_to_host,
                protect_line_framing: false,
                drop_ok: f.drop_ok,
            },
            rng.next_u64(),
        );
        Self {
            cfg,
            now: Micros(0),
            host,
            firmware,
            to_firmware,
            to_host,
            rng,
            index_of: HashMap::new(),
            planned: VecDeque::new(),
            next_exec: Micros(0),
            ran: Vec::new(),
            ran_next: 0,
            next_tag: 0,
            expected_accept: None,
            unplugged_until: None,
            pending: Pending::None,
            last_unacknowledged: Vec::new(),
            report: GcodeReport::default(),
        }
    }

    /// Stream job lines `0..lines` (text from `test_line`) until every one ran or
    /// `max_time_us` of simulated time passed.
    pub fn run(&mut self, lines: u32, max_time_us: u64) -> GcodeReport {
        self.report.lines = lines;
        self.ran = vec![false; lines as usize];
        self.index_of = (0..lines).map(|i| (test_line(i), i)).collect();
        self.connect(0);
        let start = self.now;
        while self.ran_next < lines && self.now.since(start) < max_time_us {
            self.feed(lines);
            self.round();
            self.lifecycle();
            self.advance();
        }
        let mut r = self.report.clone();
        r.completed = self.ran_next >= lines;
        r.lost = self.ran.iter().filter(|r| !**r).count() as u64;
        r.elapsed_us = self.now.since(start);
        r.wire_bytes_to_firmware = self.to_firmware.bytes_on_wire;
        r.host_stats = self.host.stats().clone();
        r.firmware_stats = self.firmware.stats().clone();
        r
    }

    fn connect(&mut self, resume: u32) {
        self.host.connect(self.now);
        self.next_tag = resume;
        self.expected_accept = Some(u64::from(resume));
    }

    fn feed(&mut self, lines: u32) {
        if !matches!(self.host.state(), LinkState::Streaming | LinkState::Probing) {
            return;
        }
        while self.next_tag < lines && self.host.queued_len() < self.cfg.backlog {
            let (text, tag) = (test_line(self.next_tag), u64::from(self.next_tag));
            let sent = if self.cfg.timed_lines {
                self.host
                    .send_timed_line(&text, tag, self.cfg.exec_us_per_move)
            } else {
                self.host.send_line(&text, tag)
            };
            if sent.is_err() {
                break;
            }
            self.next_tag += 1;
        }
    }

    /// Deliver, execute, transmit, collect events.
    fn round(&mut self) {
        let now = self.now;
        while let Some(b) = self.to_firmware.deliver(now) {
            self.firmware.handle_bytes(&b, now);
        }
        while let Some(b) = self.to_host.deliver(now) {
            self.host.handle_bytes(&b, now);
        }
        self.firmware.handle_timeout(now);
        self.execute(now);
        while let Some(b) = self.host.poll_transmit(now) {
            if b.first() == Some(&b'N') && self.rng.chance(self.cfg.faults.spurious_resend) {
                self.firmware.inject_spurious_resend();
            }
            self.to_firmware.write(&b, now);
        }
        while let Some(b) = self.firmware.poll_transmit() {
            self.to_host.write(&b, now);
        }
        while let Some(e) = self.host.poll_event() {
            self.on_event(e);
        }
    }

    fn execute(&mut self, now: Micros) {
        while let Some(line) = self.firmware.poll_line() {
            // Klipper checks nothing: every line it runs counts as sent.
            let checked =
                line.line_number.is_some() || self.cfg.firmware.dialect == Dialect::Klipper;
            let command = line
                .text
                .rsplit_once('*')
                .map_or(line.text.as_str(), |(c, _)| c);
            match self.index_of.get(command.trim()) {
                Some(&i) if checked => self.ran_line(i),
                Some(_) => self.report.fragment_repeats += 1,
                None if is_link_line(&line.text) => {}
                None => self.report.foreign_lines_run += 1,
            }
            if line.is_move {
                let at = self.next_exec.max(now).plus_us(self.cfg.exec_us_per_move);
                self.next_exec = at;
                self.planned.push_back(at);
            }
        }
        let mut done = 0;
        while self.planned.front().is_some_and(|t| *t <= now) {
            self.planned.pop_front();
            done += 1;
            if self.rng.chance(self.cfg.faults.busy_chance) {
                self.firmware
                    .stall(now.plus_us(self.cfg.faults.busy_us), now);
            }
        }
        if done > 0 {
            self.firmware.moves_done(done, now);
        }
        self.inject_scheduled_faults(now);
    }

    fn ran_line(&mut self, i: u32) {
        let seen = &mut self.ran[i as usize];
        if *seen {
            self.report.duplicates += 1;
            if self.report.executed.last() == Some(&i) {
                self.report.adjacent_duplicates += 1;
            }
        } else if i > self.ran_next {
            self.report.reordered += 1;
        }
        *seen = true;
        self.report.executed.push(i);
        while self.ran.get(self.ran_next as usize) == Some(&true) {
            self.ran_next += 1;
        }
    }

    fn inject_scheduled_faults(&mut self, now: Micros) {
        let ran = self.report.executed.len() as u32;
        if self.cfg.faults.reset_after_lines.is_some_and(|n| ran >= n) {
            self.cfg.faults.reset_after_lines = None;
            self.firmware.reset(now);
            self.planned.clear();
            self.to_firmware.cut();
            self.to_host.cut();
            if self.cfg.firmware.dialect == Dialect::Rrf {
                // Native USB: the board's port vanishes and comes back.
                self.host.port_closed();
            }
        }
        if self.cfg.faults.unplug_after_lines.is_some_and(|n| ran >= n) {
            self.cfg.faults.unplug_after_lines = None;
            self.to_firmware.set_connected(false);
            self.to_host.set_connected(false);
            self.unplugged_until = Some(now.plus_us(self.cfg.faults.unplug_us));
        }
        if self.unplugged_until.is_some_and(|t| now >= t) {
            self.unplugged_until = None;
            self.to_firmware.set_connected(true);
            self.to_host.set_connected(true);
        }
    }

    fn on_event(&mut self, e: LineEvent) {
        match e {
            LineEvent::Accepted { tag, .. } => {
                self.report.accepted_events += 1;
                if self.expected_accept.is_some_and(|t| t != tag) {
                    self.report.accepted_out_of_order += 1;
                }
                self.expected_accept = Some(tag + 1);
            }
            LineEvent::MaybeRepeated { .. } => self.report.maybe_repeated += 1,
            LineEvent::Reset { .. } => {
                self.report.resets += 1;
                // The firmware's queue and planner are lost: resume after the last line
                // that ran (the daemon asks the operator first).
                self.pending = Pending::None;
                let resume = self.ran_next;
                self.connect(resume);
            }
            LineEvent::LinkLost { unacknowledged, .. } => {
                self.report.link_lost += 1;
                self.last_unacknowledged = unacknowledged;
                self.pending = Pending::Recover;
            }
            LineEvent::Stopped { unacknowledged, .. } => {
                self.report.stopped += 1;
                self.last_unacknowledged = unacknowledged;
                self.pending = Pending::Recover;
            }
            LineEvent::Halted { .. } => self.report.halted += 1,
            LineEvent::ProtocolError { what } => {
                self.report.protocol_errors += 1;
                if what.contains("without a line number") {
                    self.report.unnumbered_reported += 1;
                }
            }
            LineEvent::LastAccepted(answer) => self.on_last_accepted(answer),
            LineEvent::Connected(_)
            | LineEvent::Echo { .. }
            | LineEvent::Action { .. }
            | LineEvent::Busy { .. }
            | LineEvent::Error { .. } => {}
        }
    }

    fn on_last_accepted(&mut self, answer: LastAccepted) {
        if self.pending != Pending::Answer {
            return;
        }
        self.pending = Pending::None;
        let resume = match answer {
            LastAccepted::Known {
                resume_tag, exact, ..
            } => {
                self.report.recoveries += 1;
                if !exact {
                    self.report.inexact_recoveries += 1;
                }
                resume_tag
                    .or_else(|| self.last_unacknowledged.first().copied())
                    .map_or(self.next_tag, |t| t as u32)
            }
            LastAccepted::Unknown { .. } if self.unplugged_until.is_some() => {
                self.pending = Pending::Recover;
                return;
            }
            // The harness's lines are not matched by position: from what it saw run.
            LastAccepted::Unknown { .. } | LastAccepted::Position { .. } => self.ran_next,
        };
        self.connect(resume);
    }

    fn lifecycle(&mut self) {
        if self.pending == Pending::Recover && self.unplugged_until.is_none() {
            self.pending = Pending::Answer;
            if self.host.recover_last_accepted(self.now).is_err() {
                self.pending = Pending::Recover;
            }
        }
    }

    /// Move time to the next thing that happens (at least 1 µs on).
    fn advance(&mut self) {
        let candidates = [
            self.to_firmware.next_delivery(),
            self.to_host.next_delivery(),
            self.host.next_timeout(),
            self.firmware.next_timeout(),
            self.planned.front().copied(),
            self.unplugged_until,
        ];
        let next = candidates.into_iter().flatten().min();
        let next = next.unwrap_or(self.now.plus_us(1000));
        self.now = next.max(self.now.plus_us(1));
    }
}

/// Lines the link itself sends (handshake, probe, queries).
fn is_link_line(text: &str) -> bool {
    matches!(
        super::command_word(text).as_deref(),
        Some("M110" | "M115" | "M105" | "M555" | "M409")
    )
}

/// One case of the throughput measurement (`benches/gcode_link.rs`, `docs/firmware.md`
/// "Throughput"): a clean line, every move executed at once, so the link alone sets the
/// pace.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThroughputCase {
    /// The firmware.
    pub dialect: Dialect,
    /// Line speed, both ways.
    pub baud: u32,
    /// Latency added to every delivery, each way, µs.
    pub latency_us: u64,
    /// The firmware's receive buffer (the host is told the same).
    pub rx_buffer_bytes: usize,
    /// The firmware's command queue (Marlin `BUFSIZE`).
    pub command_slots: usize,
    /// The host's window.
    pub window: super::Window,
    /// Marlin `ADVANCED_OK` (the free slots open the `Auto` window).
    pub advanced_ok: bool,
}

impl ThroughputCase {
    /// `dialect`'s defaults at `baud` and `latency_us`, one line at a time.
    pub fn one_at_a_time(dialect: Dialect, baud: u32, latency_us: u64) -> Self {
        let fw = FirmwareConfig::for_dialect(dialect);
        Self {
            dialect,
            baud,
            latency_us,
            rx_buffer_bytes: fw.rx_buffer_bytes,
            command_slots: fw.command_slots,
            window: super::Window::Lines(1),
            advanced_ok: false,
        }
    }

    /// The harness configuration of this case.
    pub fn harness_config(&self) -> GcodeHarnessConfig {
        let mut cfg = GcodeHarnessConfig::new(self.dialect);
        cfg.baud = self.baud;
        cfg.latency_us = self.latency_us;
        cfg.host.window = self.window;
        cfg.host.rx_buffer_bytes = self.rx_buffer_bytes;
        cfg.firmware.rx_buffer_bytes = self.rx_buffer_bytes;
        cfg.firmware.command_slots = self.command_slots;
        cfg.firmware.advanced_ok = self.advanced_ok;
        cfg.backlog = 64;
        if self.dialect == Dialect::Klipper {
            cfg.piece_bytes = 64;
        }
        cfg
    }
}

/// Stream `lines` job lines through `case`; the report's `moves_per_s` and `utilisation`
/// are the figures.
pub fn throughput(case: &ThroughputCase, lines: u32) -> GcodeReport {
    GcodeHarness::new(case.harness_config()).run(lines, u64::MAX / 4)
}
