//! What the streamer needs of a machine link, whatever its wire protocol: the adapter
//! interface between the protocol-neutral job lifecycle and a sans-IO link core. Two
//! adapters implement it: [`EdoLink`] (edo's framed link, hil-sim and edo machines) and
//! [`GcodeLink`] (G-code lines to RepRapFirmware, Marlin and Klipper,
//! `docs/firmware.md`). Both are sans-IO like the cores they wrap and are tested in
//! simulated time; the daemon's streamer owns the port, the clock, the store and the log,
//! and pumps one of them; the lifecycle sees only [`Event`]s and [`MachineCommand`]s.

use std::collections::VecDeque;

use crate::lifecycle::{Event, MachineCommand};
use crate::link::Micros;
use crate::machine::{MachineReport, Move};

mod edo;
mod gcode;
mod marks;

pub use edo::{link_config, EdoLink};
pub use gcode::{GcodeLink, ResumeLines};
pub use marks::{GcodeMark, GcodeMarkKind, GcodeMarkWrite};

/// What a link counts, whatever its protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LinkCounters {
    /// Bytes written to the port.
    pub bytes_sent: u64,
    /// Bytes read from it.
    pub bytes_received: u64,
    /// Frames (edo link) or lines (G-code) sent again.
    pub resent: u64,
    /// Smoothed round-trip time, µs, where the link measures one (the edo link).
    pub srtt_us: Option<u64>,
}

/// How much a [`LogLine`] matters (the shell logs it at this level).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogLevel {
    /// Detail for the protocol log.
    Debug,
    /// Something an operator may want to know.
    Info,
    /// Something went wrong or may have.
    Warn,
}

/// A line for the daemon's log: what the link saw, in words, with its values.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogLine {
    /// How much it matters.
    pub level: LogLevel,
    /// The message, values as `key=value` after it.
    pub text: String,
}

/// Log lines an adapter keeps for the shell (at most [`LOG_LINES_KEPT`]; older ones are
/// dropped and counted, so a firmware that floods the line cannot grow memory).
#[derive(Debug, Default)]
pub struct LogQueue {
    lines: VecDeque<LogLine>,
    dropped: u64,
}

/// Log lines an adapter keeps until the shell takes them.
pub const LOG_LINES_KEPT: usize = 256;

impl LogQueue {
    /// Keep a line.
    pub fn push(&mut self, level: LogLevel, text: String) {
        if self.lines.len() >= LOG_LINES_KEPT {
            self.lines.pop_front();
            self.dropped += 1;
        }
        self.lines.push_back(LogLine { level, text });
    }
    /// [`LogLevel::Debug`].
    pub fn debug(&mut self, text: String) {
        self.push(LogLevel::Debug, text);
    }
    /// [`LogLevel::Info`].
    pub fn info(&mut self, text: String) {
        self.push(LogLevel::Info, text);
    }
    /// [`LogLevel::Warn`].
    pub fn warn(&mut self, text: String) {
        self.push(LogLevel::Warn, text);
    }
    /// The oldest line kept; lines dropped before it are told first.
    pub fn pop(&mut self) -> Option<LogLine> {
        if self.dropped > 0 {
            let n = std::mem::take(&mut self.dropped);
            return Some(LogLine {
                level: LogLevel::Warn,
                text: format!("{n} link log lines dropped (not taken in time)"),
            });
        }
        self.lines.pop_front()
    }
}

/// A machine link under the lifecycle. Driven like the sans-IO cores it wraps: bytes in,
/// bytes out, events out, the caller's clock.
pub trait LinkAdapter: Send {
    /// The port was (re)opened: start a new session (handshake).
    fn reconnect(&mut self, now: Micros);
    /// The port closed or vanished (the streamer reports [`Event::PortLost`] itself).
    fn port_lost(&mut self);
    /// Feed bytes read from the port.
    fn handle_bytes(&mut self, bytes: &[u8], now: Micros);
    /// Run the link's timers.
    fn handle_timeout(&mut self, now: Micros);
    /// When the link's timers are next due.
    fn next_timeout(&self) -> Option<Micros>;
    /// Bytes to write to the port.
    fn poll_transmit(&mut self, now: Micros) -> Option<Vec<u8>>;
    /// The next lifecycle event from the link, if any.
    fn poll_event(&mut self, now: Micros) -> Option<Event>;
    /// Carry out a machine command; its acknowledgement, if it has one, is
    /// [`Event::CommandAcked`] of the same command ([`MachineCommand::Flush`]'s never
    /// answers an e-stop, and the other way round).
    fn command(&mut self, c: MachineCommand, now: Micros);
    /// Whether the link takes another move now (`ahead`: moves it may hold unsent).
    fn has_room(&self, ahead: usize) -> bool;
    /// A job ended (done, cancelled or failed): a link may end the firmware's job state
    /// once the moves still in it ran (Klipper's syringe axes released).
    fn job_ended(&mut self, _job_id: u32) {}
    /// Queue a move; why not, if it cannot go.
    fn send_move(&mut self, mv: Move) -> Result<(), String>;
    /// Moves waiting in the link and moves sent and not acknowledged.
    fn in_link(&self) -> (usize, u64);
    /// The machine's identity, once it answered.
    fn identity(&self) -> Option<&str>;
    /// The machine's last report (for the machine snapshot; the lifecycle has its own
    /// copy).
    fn report(&self) -> &MachineReport;
    /// The link's counters.
    fn counters(&self) -> LinkCounters;
    /// A change to the store's G-code marks, to hand to the store's writer before the
    /// next bytes go out (`docs/firmware.md`; only the G-code link has any).
    fn poll_store_mark(&mut self) -> Option<GcodeMarkWrite> {
        None
    }
    /// While connected, why the machine does not answer as it should (the G-code link:
    /// an `ok` overdue and the firmware being asked where it is), for the snapshot's
    /// `link_problem`; `None` while it answers.
    fn link_problem(&self) -> Option<String> {
        None
    }
    /// The next line for the daemon's log, if any.
    fn poll_log(&mut self) -> Option<LogLine>;
}

/// For an event logged at most once a period: whether to log the one at `now`, with
/// how many were not logged since the last (`logged`: when that was and that count);
/// `period_over(last, now)` says whether a period has passed since the last logged.
pub fn log_now<T: Copy>(
    logged: &mut Option<(T, u64)>,
    now: T,
    period_over: impl Fn(T, T) -> bool,
) -> Option<u64> {
    match logged {
        Some((at, since)) if !period_over(*at, now) => {
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
