//! Sans-IO models of the serial front ends of Marlin, RepRapFirmware and Klipper: bytes in
//! → lines read, checked and queued → lines processed (handed to the caller, which
//! executes them) → reply bytes out. Each follows its firmware's rules as cited in
//! `docs/firmware.md` ("Firmware models"):
//!
//! - **Marlin** (`Marlin/src/gcode/queue.cpp`): a line starting with `N` must be
//!   `last_N + 1` (unless it is the numbered `M110`) and carry a matching XOR checksum;
//!   otherwise `Error:<why>, Last Line: <last_N>`, `Resend: <last_N + 1>`, `ok`, and the
//!   receive buffer is drained (the rest of a line still arriving becomes an unnumbered
//!   line, run unchecked). Unnumbered lines are never checked. Lines are read only while
//!   the command queue (`BUFSIZE`) has room and no handler is blocked; `ok` (ADVANCED_OK:
//!   `ok N<n> P<planner free> B<BUFSIZE − length>`) when the handler returns; `busy:
//!   processing` every keepalive interval while a handler blocks; bytes past a full
//!   receive buffer are dropped (UART); `M112` at once with EMERGENCY_PARSER, else when
//!   read. `start` and the reset reason on boot.
//! - **RepRapFirmware** (`src/GCodes/GCodeBuffer/StringParser.cpp`, `GCodes.cpp`): `N` only
//!   recorded (`lineNumber`, set before the checksum test), a `*` checksum only after an
//!   `N`; a bad checksum drops the line with no reply. One command at a time; `ok` in
//!   Marlin mode (`M555 P2`), an empty line in its own mode; `M409 K"inputs"` and
//!   `K"move.axes"` (`userPosition`: the end of the last move queued); a bare
//!   `M112` at a line start is seen as it arrives. No busy protocol, no boot banner on USB.
//! - **Klipper** (`klippy/gcode.py`): `N<n>` skipped, `*` never checked, one `ok` per line
//!   (after `!! <error>` if it failed); `M112` is acted on as it is read while fewer than
//!   20 lines are pending; `// Klipper state: Ready|Shutdown|Disconnect` lines; while it
//!   restarts, every line is answered `!! Printer is not ready`, `ok` and not run.
//!
//! Planner model: `G0`–`G3` take a planner block until the caller reports the move done
//! ([`Firmware::moves_done`]); `M400` waits for an empty planner; other commands pass.

use std::collections::VecDeque;

use super::{checksum, command_word, Dialect, Micros};

/// Marlin's `STR_ERR_CHECKSUM_MISMATCH`.
pub const CHECKSUM_ERROR: &str = "checksum mismatch, Last Line: ";
/// Marlin's `STR_ERR_LINE_NO`.
pub const LINE_NUMBER_ERROR: &str = "Line Number is not Last Line Number+1, Last Line: ";
/// Marlin's `STR_ERR_NO_CHECKSUM`.
pub const NO_CHECKSUM_ERROR: &str = "No Checksum with line number, Last Line: ";

/// What happens to bytes that arrive while the receive buffer is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RxOverflow {
    /// UART: the byte is lost (Marlin's AVR `store_rxd_char`).
    DropBytes,
    /// USB CDC or a pty: the sender waits (USB NAKs, the pty buffers).
    Backpressure,
}

/// A firmware model's build options.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FirmwareConfig {
    /// Which firmware.
    pub dialect: Dialect,
    /// Receive buffer (Marlin `RX_BUFFER_SIZE`, RRF's 256-byte USB ring, a pty).
    pub rx_buffer_bytes: usize,
    /// What a full receive buffer does.
    pub rx_overflow: RxOverflow,
    /// Command queue (default [`Dialect::queues`]).
    pub command_slots: usize,
    /// Planner blocks (default [`Dialect::queues`]).
    pub planner_blocks: usize,
    /// Marlin `ADVANCED_OK`.
    pub advanced_ok: bool,
    /// Marlin `EMERGENCY_PARSER`.
    pub emergency_parser: bool,
    /// Marlin `HOST_KEEPALIVE_FEATURE` interval (`M113`), µs.
    pub keepalive_interval_us: Option<u64>,
    /// Time to parse and queue one command, µs (the main loop's cost per line).
    pub line_processing_us: u64,
    /// Marlin reads its receive buffer once per main-loop pass: bytes wait up to this
    /// long, µs (so a line error's drain catches the start of the next line). 0: at once.
    pub loop_period_us: u64,
    /// Longest line kept (Marlin `MAX_CMD_SIZE` − 1); the rest of a longer line is dropped.
    pub max_line_bytes: usize,
    /// RRF: the USB channel starts in Marlin compatibility (answers `ok`).
    pub rrf_marlin_mode: bool,
    /// Klipper: time a `FIRMWARE_RESTART` takes, µs; lines meanwhile are answered
    /// `!! Printer is not ready` and `ok`, and not run.
    pub restart_us: u64,
    /// The `M115` firmware name.
    pub firmware_name: String,
}

impl FirmwareConfig {
    /// The firmware's defaults (Marlin: AVR upstream configuration).
    pub fn for_dialect(dialect: Dialect) -> Self {
        match dialect {
            Dialect::Marlin => Self {
                dialect,
                rx_buffer_bytes: 128,
                rx_overflow: RxOverflow::DropBytes,
                command_slots: dialect.queues().command_slots,
                planner_blocks: dialect.queues().planner_blocks,
                advanced_ok: false,
                emergency_parser: false,
                keepalive_interval_us: Some(2_000_000),
                line_processing_us: 0,
                loop_period_us: 500,
                max_line_bytes: 95,
                rrf_marlin_mode: false,
                restart_us: 2_000_000,
                firmware_name: "Marlin 2.1.2.5 (edo model)".into(),
            },
            Dialect::Rrf => Self {
                dialect,
                rx_buffer_bytes: 256,
                rx_overflow: RxOverflow::Backpressure,
                command_slots: dialect.queues().command_slots,
                planner_blocks: dialect.queues().planner_blocks,
                advanced_ok: false,
                emergency_parser: true,
                keepalive_interval_us: None,
                line_processing_us: 0,
                loop_period_us: 0,
                max_line_bytes: 255,
                rrf_marlin_mode: false,
                restart_us: 2_000_000,
                firmware_name: "RepRapFirmware for Duet 3 MB6HC".into(),
            },
            Dialect::Klipper => Self {
                dialect,
                rx_buffer_bytes: 4096,
                rx_overflow: RxOverflow::Backpressure,
                command_slots: dialect.queues().command_slots,
                planner_blocks: dialect.queues().planner_blocks,
                advanced_ok: false,
                emergency_parser: true,
                keepalive_interval_us: None,
                line_processing_us: 0,
                loop_period_us: 0,
                max_line_bytes: 4095,
                rrf_marlin_mode: false,
                restart_us: 2_000_000,
                firmware_name: "Klipper".into(),
            },
        }
    }
}

/// A line the firmware processed (its handler ran), for the caller to execute.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProcessedLine {
    /// Its `N`, if it had one that the firmware checked or recorded.
    pub line_number: Option<u32>,
    /// The command, without line number and checksum.
    pub text: String,
    /// `G0`–`G3`: it holds a planner block until [`Firmware::moves_done`].
    pub is_move: bool,
}

/// Counters of a firmware model.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FirmwareStats {
    /// Bytes fed in.
    pub bytes_received: u64,
    /// Bytes lost to a full receive buffer.
    pub bytes_dropped: u64,
    /// Bytes thrown away by Marlin's drain after a line error.
    pub bytes_drained: u64,
    /// Lines accepted into the command queue.
    pub lines_accepted: u64,
    /// Lines accepted without a line number (never checked).
    pub lines_unnumbered: u64,
    /// Marlin line errors (each answered with `Resend:`).
    pub line_errors: u64,
    /// RRF lines dropped silently for a bad checksum.
    pub lines_dropped: u64,
    /// `busy:` keepalives sent.
    pub keepalives: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CommandKind {
    Move,
    WaitMoves,
    Other,
}

#[derive(Debug)]
struct Command {
    number: Option<u32>,
    text: String,
    kind: CommandKind,
}

/// Watches bytes at line starts for `M112` (Marlin's emergency parser, RRF's urgent scan).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum EStopScan {
    LineStart,
    LineNumber,
    Code(u8),
    Matched,
    /// Marlin: after `M112 ` or `M112*`, until the line end.
    MatchedTail,
    Ignore,
}

/// A sans-IO firmware serial front end. See the module docs.
#[derive(Debug)]
pub struct Firmware {
    cfg: FirmwareConfig,
    rx: VecDeque<u8>,
    /// Bytes the sender holds back (USB, pty) until the receive buffer has room.
    backlog: VecDeque<u8>,
    line: Vec<u8>,
    line_overflow: bool,
    in_comment: bool,
    scan: EStopScan,
    queue: VecDeque<Command>,
    planner_used: usize,
    out: VecDeque<Vec<u8>>,
    processed: VecDeque<ProcessedLine>,
    /// Marlin `last_N`; RRF `lineNumber`.
    last_n: i64,
    next_process_at: Micros,
    /// The next main-loop pass that reads the receive buffer.
    read_at: Option<Micros>,
    stall_until: Micros,
    keepalive_at: Option<Micros>,
    halted: bool,
    /// Klipper restarting: not ready until then.
    ready_at: Option<Micros>,
    reject_next: bool,
    rrf_marlin_mode: bool,
    /// Klipper: each `[manual_stepper]` registered as a G-code axis
    /// (`MANUAL_STEPPER ... GCODE_AXIS=A`), by name; a restart forgets them.
    klipper_axes: Vec<(String, char)>,
    /// Where the lines processed leave the nozzle (RRF's `userPosition`: the end of the
    /// last move handed to the planner).
    user_at: super::NozzleAt,
    stats: FirmwareStats,
}

impl Firmware {
    /// A firmware just powered up at `now` (it prints its boot banner).
    pub fn new(cfg: FirmwareConfig, now: Micros) -> Self {
        let mut fw = Self {
            rx: VecDeque::new(),
            backlog: VecDeque::new(),
            line: Vec::new(),
            line_overflow: false,
            in_comment: false,
            scan: EStopScan::LineStart,
            queue: VecDeque::new(),
            planner_used: 0,
            out: VecDeque::new(),
            processed: VecDeque::new(),
            last_n: 0,
            next_process_at: now,
            read_at: None,
            stall_until: now,
            keepalive_at: None,
            halted: false,
            ready_at: None,
            reject_next: false,
            rrf_marlin_mode: cfg.rrf_marlin_mode,
            klipper_axes: Vec::new(),
            user_at: super::NozzleAt::UNKNOWN,
            stats: FirmwareStats::default(),
            cfg,
        };
        fw.boot("PowerUp", now);
        fw
    }

    /// The machine resets (reset button, watchdog, Klipper `FIRMWARE_RESTART`): queues,
    /// planner and line number are lost; the boot banner follows.
    pub fn reset(&mut self, now: Micros) {
        self.boot(" External Reset", now);
    }

    fn boot(&mut self, reason: &str, now: Micros) {
        self.rx.clear();
        self.backlog.clear();
        self.line.clear();
        self.line_overflow = false;
        self.in_comment = false;
        self.scan = EStopScan::LineStart;
        self.queue.clear();
        self.planner_used = 0;
        self.out.clear();
        self.processed.clear();
        self.last_n = 0;
        self.next_process_at = now;
        self.read_at = None;
        self.stall_until = now;
        self.keepalive_at = None;
        self.halted = false;
        self.ready_at = None;
        self.reject_next = false;
        self.rrf_marlin_mode = self.cfg.rrf_marlin_mode;
        self.klipper_axes.clear();
        match self.cfg.dialect {
            Dialect::Marlin => {
                let name = self.cfg.firmware_name.clone();
                for line in [
                    "start",
                    reason,
                    &format!("Marlin {name}"),
                    "echo: Last Updated: 2024-01-01 | Author: (edo model)",
                    "echo: Compiled: Jan  1 2024",
                    "echo: Free Memory: 2048  PlannerBufferBytes: 1024",
                ] {
                    self.say(line);
                }
            }
            // Native USB: the port re-enumerates; nothing is printed.
            Dialect::Rrf => {}
            Dialect::Klipper if reason == "PowerUp" => self.say("// Klipper state: Ready"),
            Dialect::Klipper => {
                self.say("// Klipper state: Disconnect");
                self.ready_at = Some(now.plus_us(self.cfg.restart_us));
            }
        }
    }

    /// The configuration.
    pub fn config(&self) -> &FirmwareConfig {
        &self.cfg
    }

    /// Counters.
    pub fn stats(&self) -> &FirmwareStats {
        &self.stats
    }

    /// Marlin `last_N` / RRF `lineNumber`.
    pub fn last_line_number(&self) -> i64 {
        self.last_n
    }

    /// Halted (Marlin kill, RRF emergency stop, Klipper shutdown).
    pub fn is_halted(&self) -> bool {
        self.halted
    }

    /// Commands read and not yet processed.
    pub fn queue_len(&self) -> usize {
        self.queue.len()
    }

    /// Moves in the planner.
    pub fn planner_len(&self) -> usize {
        self.planner_used
    }

    /// Bytes in the receive buffer.
    pub fn rx_len(&self) -> usize {
        self.rx.len()
    }

    /// Reply bytes to write to the host, one line at a time.
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.out.pop_front()
    }

    /// The next processed line, for the caller to execute.
    pub fn poll_line(&mut self) -> Option<ProcessedLine> {
        self.processed.pop_front()
    }

    /// The caller finished `n` moves: their planner blocks are free.
    pub fn moves_done(&mut self, n: usize, now: Micros) {
        self.planner_used = self.planner_used.saturating_sub(n);
        self.run(now);
    }

    /// Block the command being processed until `until` (a long command: heating, a
    /// pause for the user). Marlin sends `busy:` keepalives meanwhile.
    pub fn stall(&mut self, until: Micros, now: Micros) {
        self.stall_until = self.stall_until.max(until);
        self.run(now);
    }

    /// Marlin: reject the next good numbered line as a checksum mismatch (line noise, or
    /// OctoPrint's virtual printer's `resend_ratio`).
    pub fn inject_spurious_resend(&mut self) {
        self.reject_next = true;
    }

    /// When [`Firmware::handle_timeout`] must run next.
    pub fn next_timeout(&self) -> Option<Micros> {
        let read = self.read_at.filter(|_| !self.rx.is_empty());
        let read = [read, self.ready_at].into_iter().flatten().min();
        if self.halted || self.queue.is_empty() {
            return read;
        }
        // A head waiting for planner space waits for `moves_done`, not for a timer.
        let waits_for_moves = self.planner_blocked() && self.ready_at.is_none();
        let process = (!waits_for_moves).then(|| self.next_process_at.max(self.stall_until));
        [process, self.keepalive_at, read]
            .into_iter()
            .flatten()
            .min()
    }

    /// Run the timers (processing pace, stalls, keepalives).
    pub fn handle_timeout(&mut self, now: Micros) {
        self.run(now);
        if let Some(k) = self.keepalive_at {
            if now >= k && !self.halted {
                self.stats.keepalives += 1;
                self.say("echo:busy: processing");
                self.keepalive_at = self
                    .cfg
                    .keepalive_interval_us
                    .map(|i| now.plus_us(i.max(1)));
            }
        }
    }

    /// Bytes from the host.
    pub fn handle_bytes(&mut self, bytes: &[u8], now: Micros) {
        self.stats.bytes_received += bytes.len() as u64;
        for &b in bytes {
            match self.cfg.rx_overflow {
                RxOverflow::Backpressure => self.backlog.push_back(b),
                RxOverflow::DropBytes => {
                    // The emergency parser sees every byte, even one the buffer drops.
                    self.scan_estop(b);
                    if self.rx.len() < self.cfg.rx_buffer_bytes {
                        self.rx.push_back(b);
                    } else {
                        self.stats.bytes_dropped += 1;
                    }
                }
            }
        }
        self.run(now);
    }

    fn say(&mut self, line: &str) {
        let mut bytes = line.as_bytes().to_vec();
        bytes.push(b'\n');
        self.out.push_back(bytes);
    }

    /// The firmware's main loop until nothing more happens at `now`.
    fn run(&mut self, now: Micros) {
        if self.ready_at.is_some_and(|t| now >= t) {
            self.ready_at = None;
            self.say("// Klipper state: Ready");
        }
        loop {
            self.fill_from_backlog();
            // Marlin reads serial only from its main loop, not while a handler blocks.
            let may_read = self.cfg.dialect != Dialect::Marlin || !self.head_blocked(now);
            if may_read && self.read_due(now) {
                self.read_lines();
                self.read_at = None;
            }
            if !self.process(now) {
                break;
            }
        }
        let marlin_blocked = self.cfg.dialect == Dialect::Marlin && self.head_blocked(now);
        if marlin_blocked || self.read_at.is_some_and(|t| t <= now) {
            self.read_at = None; // reading resumes when the handler returns
        }
        if !self.rx.is_empty() && self.read_at.is_none() && !marlin_blocked {
            self.read_at = Some(self.next_loop_pass(now));
        }
        self.update_keepalive(now);
    }

    fn read_due(&mut self, now: Micros) -> bool {
        if self.cfg.loop_period_us == 0 {
            return true;
        }
        let at = *self.read_at.get_or_insert_with(|| {
            let p = self.cfg.loop_period_us;
            Micros(now.0.div_ceil(p) * p)
        });
        now >= at
    }

    /// The first main-loop pass after `now`.
    fn next_loop_pass(&self, now: Micros) -> Micros {
        match self.cfg.loop_period_us {
            0 => now,
            p => Micros((now.0 / p + 1) * p),
        }
    }

    fn fill_from_backlog(&mut self) {
        while self.rx.len() < self.cfg.rx_buffer_bytes {
            let Some(b) = self.backlog.pop_front() else {
                break;
            };
            self.scan_estop(b);
            self.rx.push_back(b);
        }
    }

    fn scan_estop(&mut self, b: u8) {
        let watched = match self.cfg.dialect {
            Dialect::Marlin => self.cfg.emergency_parser,
            Dialect::Rrf => true,
            // Klipper checks whole lines as it reads them (see `read_klipper_line`).
            Dialect::Klipper => false,
        };
        if !watched || self.halted {
            return;
        }
        let eol = b == b'\n' || b == b'\r';
        let marlin = self.cfg.dialect == Dialect::Marlin;
        self.scan = match (self.scan, b) {
            // RRF: `M112` then a blank, a control byte or `;` (no line number allowed).
            (EStopScan::Matched, _) if !marlin && (b <= b' ' || b == b';') => {
                self.halt();
                EStopScan::LineStart
            }
            // Marlin: acted on at the line end; `N<n> M112*<cs>` counts too.
            (EStopScan::Matched | EStopScan::MatchedTail, _) if marlin && eol => {
                self.halt();
                EStopScan::LineStart
            }
            (EStopScan::Matched, b' ' | b'*') if marlin => EStopScan::MatchedTail,
            (EStopScan::MatchedTail, _) => EStopScan::MatchedTail,
            (_, _) if eol => EStopScan::LineStart,
            (EStopScan::LineStart, b' ') => EStopScan::LineStart,
            (EStopScan::LineStart, b'N') if marlin => EStopScan::LineNumber,
            (EStopScan::LineNumber, b'0'..=b'9' | b' ') => EStopScan::LineNumber,
            (EStopScan::LineStart | EStopScan::LineNumber, b'M' | b'm') => EStopScan::Code(0),
            (EStopScan::Code(0), b'1') => EStopScan::Code(1),
            (EStopScan::Code(1), b'1') => EStopScan::Code(2),
            (EStopScan::Code(2), b'2') => EStopScan::Matched,
            _ => EStopScan::Ignore,
        };
    }

    fn halt(&mut self) {
        if self.halted {
            return;
        }
        self.halted = true;
        self.queue.clear();
        self.rx.clear();
        self.keepalive_at = None;
        match self.cfg.dialect {
            Dialect::Marlin => self.say("Error:Printer halted. kill() called!"),
            Dialect::Rrf => {}
            Dialect::Klipper => self.say("// Klipper state: Shutdown"),
        }
    }

    fn queue_has_room(&self) -> bool {
        match self.cfg.dialect {
            Dialect::Rrf => self.queue.is_empty(),
            _ => self.queue.len() < self.cfg.command_slots.max(1),
        }
    }

    /// Read complete lines from the receive buffer while the queue has room.
    fn read_lines(&mut self) {
        while self.queue_has_room() && (!self.halted || self.cfg.dialect == Dialect::Klipper) {
            let Some(raw) = self.next_raw_line() else {
                return;
            };
            let go_on = match self.cfg.dialect {
                Dialect::Marlin => self.read_marlin_line(&raw),
                Dialect::Rrf => {
                    self.read_rrf_line(&raw);
                    true
                }
                Dialect::Klipper => {
                    self.read_klipper_line(&raw);
                    true
                }
            };
            if !go_on {
                return;
            }
        }
    }

    /// The next line from the receive buffer, assembled like Marlin's
    /// `process_stream_char`: `;` comments dropped, bytes past `max_line_bytes` dropped,
    /// `\n` or `\r` ends it, empty lines skipped.
    fn next_raw_line(&mut self) -> Option<Vec<u8>> {
        while let Some(b) = self.rx.pop_front() {
            if b == b'\n' || b == b'\r' {
                self.in_comment = false;
                self.line_overflow = false;
                if self.line.is_empty() {
                    continue;
                }
                return Some(std::mem::take(&mut self.line));
            }
            if self.in_comment || self.line_overflow {
                continue;
            }
            if b == b';' && self.cfg.dialect != Dialect::Klipper {
                self.in_comment = true;
            } else if self.line.len() >= self.cfg.max_line_bytes {
                self.line_overflow = true;
            } else {
                self.line.push(b);
            }
        }
        None
    }

    fn enqueue(&mut self, number: Option<u32>, command: &[u8]) {
        let text = String::from_utf8_lossy(command).trim().to_string();
        let kind = match command_word(&text).as_deref() {
            Some("G0" | "G1" | "G2" | "G3") => CommandKind::Move,
            Some("M400") => CommandKind::WaitMoves,
            _ => CommandKind::Other,
        };
        self.stats.lines_accepted += 1;
        if number.is_none() {
            self.stats.lines_unnumbered += 1;
        }
        self.queue.push_back(Command { number, text, kind });
    }

    // ---- Marlin --------------------------------------------------------------------

    /// `GCodeQueue::get_serial_commands` for one line; false after a line error (the
    /// port is not read again in this pass).
    fn read_marlin_line(&mut self, raw: &[u8]) -> bool {
        let start = raw.iter().position(|&b| b != b' ').unwrap_or(raw.len());
        let command = &raw[start..];
        if command.is_empty() {
            return true;
        }
        if !self.cfg.emergency_parser && is_m112(command, true) {
            self.halt();
            return false;
        }
        if command[0] != b'N' {
            self.enqueue(None, command);
            return true;
        }
        let m110 = find(command, b"M110").is_some();
        let npos = if m110 {
            command
                .iter()
                .skip(4)
                .position(|&b| b == b'N')
                .map_or(0, |p| p + 4)
        } else {
            0
        };
        let gcode_n = strtol(&command[npos + 1..]);
        if gcode_n != self.last_n + 1 && !m110 {
            return self.marlin_line_error(LINE_NUMBER_ERROR);
        }
        let Some(apos) = command.iter().rposition(|&b| b == b'*') else {
            return self.marlin_line_error(NO_CHECKSUM_ERROR);
        };
        if strtol(&command[apos + 1..]) != i64::from(checksum(&command[..apos])) {
            return self.marlin_line_error(CHECKSUM_ERROR);
        }
        if self.reject_next {
            self.reject_next = false;
            return self.marlin_line_error(CHECKSUM_ERROR);
        }
        self.last_n = gcode_n;
        let number = u32::try_from(gcode_n).ok();
        self.enqueue(number, strip_number_and_checksum(command));
        true
    }

    /// `gcode_line_error`: the error, drain the receive buffer, `Resend:`, `ok`.
    fn marlin_line_error(&mut self, what: &str) -> bool {
        self.stats.line_errors += 1;
        let last = self.last_n;
        self.say(&format!("Error:{what}{last}"));
        self.stats.bytes_drained += self.rx.len() as u64;
        self.rx.clear();
        self.line.clear();
        self.line_overflow = false;
        self.in_comment = false;
        self.say(&format!("Resend: {}", last + 1));
        self.say("ok");
        false
    }

    // ---- RepRapFirmware ------------------------------------------------------------

    /// `StringParser::Put` / `LineFinished` for one line.
    fn read_rrf_line(&mut self, raw: &[u8]) {
        let start = raw.iter().position(|&b| b != b' ').unwrap_or(raw.len());
        let line = &raw[start..];
        if line.first() != Some(&b'N') {
            self.last_n += 1;
            self.enqueue(None, line);
            return;
        }
        let digits = line[1..].iter().take_while(|b| b.is_ascii_digit()).count();
        let received = strtol(&line[1..]);
        // The line number is recorded before the checksum test.
        self.last_n = received;
        let body = &line[1 + digits..];
        if let Some(apos) = line.iter().rposition(|&b| b == b'*') {
            let cs = &line[apos + 1..];
            let ok = (1..=3).contains(&cs.len())
                && cs.iter().all(u8::is_ascii_digit)
                && strtol(cs) == i64::from(checksum(&line[..apos]));
            if !ok {
                self.stats.lines_dropped += 1;
                return; // dropped silently: no error, no resend request, no ok
            }
        }
        let number = u32::try_from(received).ok();
        let command = body.split(|&b| b == b'*').next().unwrap_or(body);
        self.enqueue(number, command);
    }

    // ---- Klipper -------------------------------------------------------------------

    /// `GCodeIO._process_data` for one line: M112 acted on at once while fewer than 20
    /// lines are pending; `N<n>` skipped.
    fn read_klipper_line(&mut self, raw: &[u8]) {
        if self.queue.len() < 20 && is_m112(raw, true) {
            self.halt();
            return;
        }
        self.enqueue(None, strip_number_and_checksum(raw));
    }

    // ---- processing ----------------------------------------------------------------

    fn head_blocked(&self, now: Micros) -> bool {
        !self.halted
            && self.ready_at.is_none()
            && !self.queue.is_empty()
            && (now < self.stall_until || self.planner_blocked())
    }

    /// The head of the queue waits for planner space (a move) or an empty planner (M400).
    fn planner_blocked(&self) -> bool {
        match self.queue.front().map(|c| c.kind) {
            Some(CommandKind::Move) => self.planner_used >= self.cfg.planner_blocks,
            Some(CommandKind::WaitMoves) => self.planner_used > 0,
            _ => false,
        }
    }

    fn update_keepalive(&mut self, now: Micros) {
        let blocked = self.cfg.dialect == Dialect::Marlin && self.head_blocked(now);
        match (blocked, self.keepalive_at, self.cfg.keepalive_interval_us) {
            (true, None, Some(i)) => self.keepalive_at = Some(now.plus_us(i.max(1))),
            (false, Some(_), _) => self.keepalive_at = None,
            _ => {}
        }
    }

    /// Process the command at the head of the queue if it can run now.
    fn process(&mut self, now: Micros) -> bool {
        if self.queue.is_empty() || now < self.next_process_at || self.head_blocked(now) {
            return false;
        }
        if self.halted && self.cfg.dialect != Dialect::Klipper {
            return false;
        }
        let length = self.queue.len();
        let Some(cmd) = self.queue.pop_front() else {
            return false;
        };
        self.next_process_at = now.plus_us(self.cfg.line_processing_us);
        if self.halted || self.ready_at.is_some() {
            // Klipper keeps answering while shut down or restarting, and runs nothing.
            self.say(if self.halted {
                "!! Shutdown due to M112 command"
            } else {
                "!! Printer is not ready"
            });
            self.say("ok");
            return true;
        }
        if cmd.kind == CommandKind::Move {
            self.planner_used += 1;
        }
        let word = command_word(&cmd.text).unwrap_or_default();
        if self.cfg.dialect == Dialect::Klipper && word == "MANUAL_STEPPER" {
            if let Err(why) = self.klipper_manual_stepper(&cmd.text) {
                // `gcode.py` `_respond_error`, then the line's `ok`; the line did nothing.
                self.say(&format!("!! {why}"));
                self.say("ok");
                return true;
            }
        }
        if self.cfg.dialect != Dialect::Marlin {
            // RRF's `userPosition`, Klipper's `GET_POSITION`.
            self.user_at = self.user_at.after(&cmd.text);
        }
        let replies = self.run_builtin(&word, &cmd.text);
        self.answer(&word, &cmd, replies, length);
        self.processed.push_back(ProcessedLine {
            line_number: cmd.number,
            text: cmd.text,
            is_move: cmd.kind == CommandKind::Move,
        });
        true
    }

    /// Klipper's `manual_stepper.py` `cmd_MANUAL_STEPPER`, as far as axis registration
    /// goes: its refusals, word for word (Kalico 2026.10; Klipper v0.13.0-106 and on).
    fn klipper_manual_stepper(&mut self, text: &str) -> Result<(), String> {
        let param = |key: &str| super::klipper_param(text, key);
        let Some(stepper) = param("STEPPER").map(|s| s.to_ascii_lowercase()) else {
            return Err("Error on 'MANUAL_STEPPER': missing STEPPER".into());
        };
        let registered = self.klipper_axes.iter().position(|(s, _)| *s == stepper);
        let Some(axis) = param("GCODE_AXIS") else {
            return match registered {
                Some(_) => Err("Must unregister from gcode axis first".into()),
                None => Ok(()),
            };
        };
        let axis = axis.to_ascii_uppercase();
        match (registered, axis.chars().next()) {
            (Some(_), Some(_)) => Err("Must unregister axis first".into()),
            (Some(i), None) => {
                self.klipper_axes.remove(i);
                Ok(())
            }
            (None, None) => Ok(()),
            (None, Some(c))
                if axis.len() != 1 || !c.is_ascii_uppercase() || "XYZEFN".contains(c) =>
            {
                Err("Not a valid GCODE_AXIS".into())
            }
            (None, Some(c)) if self.klipper_axes.iter().any(|(_, a)| *a == c) => {
                Err(format!("Axis '{c}' already registered"))
            }
            (None, Some(c)) => {
                self.klipper_axes.push((stepper, c));
                Ok(())
            }
        }
    }

    /// The commands the front end itself answers; their reply lines (before `ok`).
    fn run_builtin(&mut self, word: &str, text: &str) -> Vec<String> {
        match word {
            "M110" => {
                if let Some(n) = text
                    .split_ascii_whitespace()
                    .find_map(|w| w.strip_prefix('N'))
                {
                    if self.cfg.dialect != Dialect::Klipper {
                        self.last_n = strtol(n.as_bytes());
                    }
                }
                Vec::new()
            }
            "M113" => {
                if let Some(s) = text
                    .split_ascii_whitespace()
                    .find_map(|w| w.strip_prefix('S'))
                {
                    let s = strtol(s.as_bytes()).max(0) as u64;
                    self.cfg.keepalive_interval_us = (s > 0).then_some(s * 1_000_000);
                }
                Vec::new()
            }
            "M555" if self.cfg.dialect == Dialect::Rrf => {
                self.rrf_marlin_mode = text.contains("P2");
                Vec::new()
            }
            "M115" => self.m115_lines(),
            "M409" if self.cfg.dialect == Dialect::Rrf && text.contains("inputs") => {
                vec![self.rrf_inputs_json()]
            }
            "M409" if self.cfg.dialect == Dialect::Rrf && text.contains("move.axes") => {
                vec![super::rrf_axes_json(&self.user_at)]
            }
            "GET_POSITION" if self.cfg.dialect == Dialect::Klipper => {
                super::klipper_get_position_lines(&self.user_at)
            }
            _ => Vec::new(),
        }
    }

    fn m115_lines(&self) -> Vec<String> {
        let name = &self.cfg.firmware_name;
        match self.cfg.dialect {
            Dialect::Marlin => {
                let mut lines = vec![format!(
                    "FIRMWARE_NAME:{name} SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin \
                     PROTOCOL_VERSION:1.0 MACHINE_TYPE:edo EXTRUDER_COUNT:1"
                )];
                let busy = self.cfg.keepalive_interval_us.is_some();
                for (cap, on) in [
                    ("BUSY_PROTOCOL", busy),
                    ("EMERGENCY_PARSER", self.cfg.emergency_parser),
                ] {
                    lines.push(format!("Cap:{cap}:{}", u8::from(on)));
                }
                lines
            }
            Dialect::Rrf => vec![format!(
                "FIRMWARE_NAME: {name} FIRMWARE_VERSION: 3.5.1 ELECTRONICS: Duet 3 MB6HC v1.02 \
                 FIRMWARE_DATE: 2024-04-19 14:41:25"
            )],
            // Klipper answers on the ok line itself.
            Dialect::Klipper => Vec::new(),
        }
    }

    fn rrf_inputs_json(&self) -> String {
        let channel = |name: &str, line: i64| {
            serde_json::json!({
                "axesRelative": false, "compatibility": "Marlin", "distanceUnit": "mm",
                "drivesRelative": true, "feedRate": 50.0, "inMacro": false,
                "lineNumber": line, "name": name, "stackDepth": 0, "state": "idle",
                "volumetric": false
            })
        };
        let result = serde_json::json!([
            channel("HTTP", 0),
            channel("Telnet", 0),
            channel("File", 0),
            channel("USB", self.last_n),
            channel("Aux", 0),
            serde_json::Value::Null,
            channel("Trigger", 0),
        ]);
        serde_json::json!({"key": "inputs", "flags": "", "result": result}).to_string()
    }

    /// Reply lines and the `ok` in each firmware's format.
    fn answer(&mut self, word: &str, cmd: &Command, replies: Vec<String>, length: usize) {
        match self.cfg.dialect {
            Dialect::Marlin if word == "M105" => self.say("ok T:20.00 /0.00 @:0"),
            Dialect::Marlin => {
                for r in &replies {
                    self.say(r);
                }
                if self.cfg.advanced_ok {
                    let n = cmd.number.map(|n| format!(" N{n}")).unwrap_or_default();
                    let p = self.cfg.planner_blocks.saturating_sub(self.planner_used);
                    let b = self.cfg.command_slots.saturating_sub(length);
                    self.say(&format!("ok{n} P{p} B{b}"));
                } else {
                    self.say("ok");
                }
            }
            Dialect::Rrf => {
                for r in &replies {
                    self.say(r);
                }
                if self.rrf_marlin_mode {
                    self.say("ok");
                } else if replies.is_empty() {
                    self.say("");
                }
            }
            Dialect::Klipper if word == "M115" => {
                self.say(&format!(
                    "ok FIRMWARE_NAME:{} FIRMWARE_VERSION:v0.13.0-730-edo-model",
                    self.cfg.firmware_name
                ));
            }
            Dialect::Klipper => {
                for r in &replies {
                    self.say(&format!("// {r}"));
                }
                self.say("ok");
            }
        }
    }
}

/// C `strtol(s, nullptr, 10)`: leading spaces, an optional sign, digits; 0 if none.
fn strtol(s: &[u8]) -> i64 {
    let s = &s[s.iter().position(|&b| b != b' ').unwrap_or(s.len())..];
    let (neg, digits) = match s.first() {
        Some(b'-') => (true, &s[1..]),
        Some(b'+') => (false, &s[1..]),
        _ => (false, s),
    };
    let mut v: i64 = 0;
    for &b in digits.iter().take_while(|b| b.is_ascii_digit()) {
        v = v.saturating_mul(10).saturating_add(i64::from(b - b'0'));
    }
    if neg {
        -v
    } else {
        v
    }
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// `M112` as the command of a line (after an optional `N<n>` prefix when `allow_n`).
fn is_m112(line: &[u8], allow_n: bool) -> bool {
    let text = String::from_utf8_lossy(line);
    let mut words = text.split_ascii_whitespace();
    let Some(mut first) = words.next() else {
        return false;
    };
    if allow_n
        && first.len() > 1
        && first.starts_with(['N', 'n'])
        && first[1..].bytes().all(|b| b.is_ascii_digit())
    {
        let Some(next) = words.next() else {
            return false;
        };
        first = next;
    }
    let code = first.split('*').next().unwrap_or(first);
    code.eq_ignore_ascii_case("M112")
}

/// The command of a stored line: without its `N<n>` prefix and `*<checksum>` suffix.
fn strip_number_and_checksum(line: &[u8]) -> &[u8] {
    let mut s = line;
    if s.first().is_some_and(|b| *b == b'N' || *b == b'n') {
        let digits = s[1..].iter().take_while(|b| b.is_ascii_digit()).count();
        if digits > 0 {
            s = &s[1 + digits..];
        }
    }
    match s.iter().rposition(|&b| b == b'*') {
        Some(a) => &s[..a],
        None => s,
    }
}

#[cfg(test)]
#[path = "firmware_tests.rs"]
mod tests;
