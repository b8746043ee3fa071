//! The adapter between the job lifecycle and the G-code line link
//! ([`crate::gcode_link::LineHost`]): RepRapFirmware, Marlin and Klipper
//! (`docs/firmware.md`). The one place that knows both.
//!
//! - Each move becomes exactly the lines `edoctl plan --gcode --flavor F` writes for it
//!   ([`MoveWriter`], the offline writer's own formatting), less comments; a job's first
//!   move is preceded by the file's preamble, and every connection starts with the same
//!   lines (the resume prologue: tool, units, modes). Every line is tagged; a move is
//!   accepted when its last line is (a move with no line, a layer mark, when every line
//!   before it is).
//! - The firmware does not report execution. A move the firmware accepted (`ok`) is in
//!   its queue or planner and runs unless the machine resets or halts; a move is reported
//!   to the lifecycle as executed once as many moves were accepted after it as the
//!   firmware's queue and planner hold (Marlin 4 + 16, RRF 1 + 40, Klipper 20 + 32: a
//!   stock build), or once an `M400` sent after it is answered (sent whenever nothing
//!   else is left to send: at a job's end, a flush, an underrun). So the checkpoint never
//!   runs ahead of the machine, and after a reset the job resumes from the first move
//!   that may not have run.
//! - E-stop: `M112` ahead of every queued line ([`LineHost::emergency_stop`]); the
//!   firmware halts and only a reset brings it back. The lifecycle's flush (before a job
//!   restarts or a cancel parks) drops the lines not yet sent and waits for the ones in
//!   flight instead: their moves run, and then the checkpoint is final.
//! - Pause stops feeding (the firmware finishes what it accepted); resume feeds again.
//! - A start-up banner, a Klipper restart or RRF's port vanishing is a machine reset: the
//!   job is interrupted, as on the edo link, and the handshake starts again.
//! - After edod's SIGKILL (Marlin, RRF): the store's marks say where each connection's
//!   line numbers stand in the job's moves ([`GcodeMark`], handed over with
//!   [`LinkAdapter::poll_store_mark`]); at the next start [`ResumeLines`] replays them and
//!   the firmware's last accepted line, asked before the first handshake, names the last
//!   move that ran.

use std::collections::VecDeque;

use crate::gcode_link::writer::{GcodeSettings, MoveWriter};
use crate::gcode_link::{
    Dialect, FirmwareInfo, LastAccepted, LineEvent, LineHost, LinkState, NozzleAt,
};
use crate::lifecycle::{Event, MachineCommand, MachineFault, MoveRef};
use crate::link::Micros;
use crate::machine::{MachineReport, MachineState};
use crate::machine::{Move, MoveKind};

use super::{
    GcodeMark, GcodeMarkKind, GcodeMarkWrite, LinkAdapter, LinkCounters, LogLine, LogQueue,
};

use crate::gcode_link::writer::streamed;

/// A move (or the prologue, or an `M400`) sent and not yet accepted.
#[derive(Debug)]
struct Pending {
    /// The move (`None`: prologue lines or `M400`).
    mv: Option<MoveRef>,
    /// An `M400`: once accepted, every move before it ran.
    sync: bool,
    /// Where it ends, if it moves the nozzle.
    to: Option<crate::machine::PositionUm>,
    /// Tag of its last line (`None`: it has none).
    last_tag: Option<u64>,
}

/// How the firmware stands, as far as the host can tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stop {
    /// Running normally.
    None,
    /// The lifecycle's flush: nothing new goes out; acknowledged once nothing is in flight.
    Flushing { acked: bool },
    /// `M112` went out or the firmware halted by itself: only a reset brings it back.
    Halted,
}

/// The G-code line link under the lifecycle.
pub struct GcodeLink {
    host: LineHost,
    settings: GcodeSettings,
    drives: usize,
    /// The writer of the job being streamed (its id), started with the job's first move
    /// after a (re)connection or a flush.
    writer: Option<(u32, MoveWriter)>,
    /// A job ended: once every line went out and was acknowledged, Klipper's syringe
    /// axes are released (the writer's epilogue) so a macro can move the plungers.
    release_axes_when_idle: bool,
    next_tag: u64,
    /// Tags up to this one were accepted.
    accepted_upto: Option<u64>,
    pending: VecDeque<Pending>,
    /// Moves accepted and not known to have run, in order.
    accepted: VecDeque<Pending>,
    /// Moves the firmware's queue and planner hold at most.
    held_at_most: usize,
    /// The machine as far as the host can tell (what ran: what the firmware accepted
    /// behind its queue).
    status: MachineReport,
    info: Option<FirmwareInfo>,
    events: VecDeque<Event>,
    stop: Stop,
    paused: bool,
    /// The e-stop's `M112` is queued: acknowledged once written.
    estop_to_ack: bool,
    /// A link lost is being recovered (the last accepted line asked for).
    recovering: bool,
    /// The port closed: the reset it causes is the streamer's `PortLost`.
    port_closed: bool,
    /// The port closed with moves sent and not known run (Marlin, RRF): on reopening,
    /// the firmware's last accepted line is asked before the handshake (which starts
    /// numbering again), and the moves up to it ran.
    recover_after_open: bool,
    /// The port was just opened: what it reads until then is from before (a boot banner
    /// printed while nobody listened) and is dropped; the handshake starts then.
    settle_until: Option<Micros>,
    /// Lost or stopped links in a row with no line accepted between.
    link_failures: u32,
    /// When a protocol error was last logged, and how many were not since.
    protocol_errors_logged: Option<(Micros, u64)>,
    /// The host is asking the firmware where it is (an `ok` overdue), and it was logged.
    silence_noted: bool,
    /// Marks for the store: where this connection's line numbers stand in the job's
    /// moves (`None` on Klipper, which has no line numbers).
    marks: Option<Marks>,
    /// After edod's restart: the interrupted job's moves by line number, to learn from
    /// the firmware's last accepted line which ran.
    resume: Option<ResumeLines>,
    /// Lines for the daemon's log.
    log: LogQueue,
}

/// The store's G-code marks to write, and what the adapter needs to write them.
#[derive(Debug, Default)]
struct Marks {
    out: VecDeque<GcodeMarkWrite>,
    /// The store holds no mark (as far as was handed over).
    clear: bool,
    /// The last move of the writer's job sent.
    last_sent: Option<MoveRef>,
}

impl Marks {
    fn clear(&mut self) {
        self.last_sent = None;
        if !std::mem::replace(&mut self.clear, true) {
            self.out.push_back(GcodeMarkWrite::Clear);
        }
    }

    fn push(&mut self, w: GcodeMarkWrite) {
        self.clear = false;
        self.out.push_back(w);
    }
}

/// An interrupted job's moves by line number, replayed from the stored marks
/// ([`ResumeLines::replay`]): what edod's SIGKILL left for the next run to learn which
/// of them the firmware ran.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResumeLines {
    job_id: u32,
    /// Each move from the writer's mark on, in order: the number of its last line (or of
    /// the line before it, if it has none) and its index.
    moves: Vec<(u32, u32)>,
    /// Where each of them leaves the nozzle, µm ([`UNKNOWN_UM`] for an axis not known):
    /// what RRF's reported position is compared with.
    ends_um: Vec<[i32; 3]>,
    /// Klipper ([`ResumeLines::by_position`]): no line numbers, only where moves end.
    by_position: bool,
}

/// An axis position not known, in [`ResumeLines`]' ends.
const UNKNOWN_UM: i32 = i32::MIN;

/// Where `mv` leaves the nozzle, from where the moves before it left it (`at`, updated):
/// its target ([`end_of`]: what the writer writes, to the µm), unknown after a home.
fn move_end(at: &mut [i32; 3], mv: &Move) -> [i32; 3] {
    if let Some(to) = end_of(mv) {
        *at = [to.x_um, to.y_um, to.z_um];
    } else if matches!(mv.kind, MoveKind::Home) {
        *at = [UNKNOWN_UM; 3];
    }
    *at
}

impl ResumeLines {
    /// The lines the marks of `job_id` say went out for `moves` (the job's moves, from
    /// its first): a fresh writer's preamble at the writer mark, then each move's lines
    /// from the mark's move on, with an `M400` at each `M400` mark. `None` if no writer
    /// mark is stored for the job; an error if a mark is not where the replay puts it.
    pub fn replay(
        job_id: u32,
        marks: &[GcodeMark],
        moves: impl IntoIterator<Item = Result<Move, String>>,
        drives: usize,
        settings: &GcodeSettings,
    ) -> Result<Option<Self>, String> {
        let mine = || marks.iter().filter(|m| m.job_id == job_id);
        let Some(anchor) = mine().find(|m| m.kind == GcodeMarkKind::Writer) else {
            return Ok(None);
        };
        let mut m400s = mine()
            .filter(|m| m.kind == GcodeMarkKind::M400 && m.line_number > anchor.line_number)
            .peekable();
        let mut w = MoveWriter::new(drives.max(1), settings).map_err(|e| e.to_string())?;
        let mut lines = Vec::new();
        w.preamble(&[], &mut lines);
        let count = |lines: &[String]| lines.iter().filter_map(|l| streamed(l)).count() as u32;
        let mut next_line = anchor.line_number + count(&lines);
        let mut at = [UNKNOWN_UM; 3];
        let mut out = Vec::new();
        let mut ends_um = Vec::new();
        for mv in moves {
            let mv = mv?;
            if mv.index < anchor.move_index {
                continue;
            }
            while let Some(m) = m400s.next_if(|m| m.move_index <= mv.index) {
                if m.line_number != next_line || m.move_index != mv.index {
                    return Err(format!(
                        "the M400 mark at line {} before move {} is not where the replay                          puts it (line {next_line}, move {})",
                        m.line_number, m.move_index, mv.index
                    ));
                }
                next_line += 1;
            }
            lines.clear();
            w.move_lines(&mv, &mut lines);
            next_line += count(&lines);
            out.push((next_line.saturating_sub(1), mv.index));
            ends_um.push(move_end(&mut at, &mv));
        }
        Ok(Some(Self {
            job_id,
            moves: out,
            ends_um,
            by_position: false,
        }))
    }

    /// Klipper, which numbers no lines: the interrupted job's moves `from_index` (the
    /// last one its checkpoint says ran) to `from_index + span` (what Klipper may have
    /// held and run since), with where each leaves the nozzle, for
    /// [`ResumeLines::last_move_at`]. `moves`: the job's moves from its first.
    pub fn by_position(
        job_id: u32,
        from_index: u32,
        span: u32,
        moves: impl IntoIterator<Item = Result<Move, String>>,
    ) -> Result<Self, String> {
        let mut at = [UNKNOWN_UM; 3];
        let (mut out, mut ends_um) = (Vec::new(), Vec::new());
        for mv in moves {
            let mv = mv?;
            if mv.index > from_index.saturating_add(span) {
                break;
            }
            let end = move_end(&mut at, &mv);
            if mv.index >= from_index {
                out.push((0, mv.index));
                ends_um.push(end);
            }
        }
        Ok(Self {
            job_id,
            moves: out,
            ends_um,
            by_position: true,
        })
    }

    /// Klipper: the last move that ran, from where the nozzle stopped (`at_um`, `GET_POSITION`
    /// after `M400`): the moves ending there (within `tolerance_um`) that come first and
    /// in a row, the last of them. Moves in a row that end at one place are a road's end
    /// and its retract, a travel's end, its prime and dwell: taking the last never runs a
    /// retract twice (the plungers never run backwards), and the resume primes anyway.
    /// `None` when no move ends there.
    pub fn last_move_at(&self, at_um: [i64; 3], tolerance_um: u32) -> Option<u32> {
        let here = |k: usize| self.end(Some(k)).matches(at_um, tolerance_um);
        let first = (0..self.moves.len()).find(|&k| here(k))?;
        let run = (first..self.moves.len()).take_while(|&k| here(k)).count();
        Some(self.moves[first + run - 1].1)
    }

    /// Where move `k` (of this replay's) leaves the nozzle; nothing known for `None`.
    fn end(&self, k: Option<usize>) -> NozzleAt {
        let um = k.and_then(|k| self.ends_um.get(k)).copied();
        NozzleAt {
            xyz_um: um.map_or([None; 3], |um| {
                um.map(|v| (v != UNKNOWN_UM).then_some(i64::from(v)))
            }),
            relative: false,
        }
    }

    /// Whether this is [`ResumeLines::by_position`]'s.
    pub fn is_by_position(&self) -> bool {
        self.by_position
    }

    /// The job.
    pub fn job_id(&self) -> u32 {
        self.job_id
    }

    /// The last move all of whose lines are at or before line `line`.
    pub fn last_move_through(&self, line: u32) -> Option<u32> {
        self.position_through(line).map(|k| self.moves[k].1)
    }

    fn position_through(&self, line: u32) -> Option<usize> {
        let upto = self.moves.partition_point(|&(last, _)| last <= line);
        upto.checked_sub(1)
    }

    /// RRF, whose last line `line` may be one it dropped: the last move that ran, told by
    /// where the nozzle stands (`at_um`): `Some` when the moves through `line` and through
    /// the line before it are the same, or end at places `at_um` tells apart (within
    /// `tolerance_um`) and it is at one of them; the inner `None`: no move of the job ran.
    pub fn last_move_by_position(
        &self,
        line: u32,
        at_um: [i64; 3],
        tolerance_um: u32,
    ) -> Option<Option<u32>> {
        let with = self.position_through(line);
        let without = line.checked_sub(1).and_then(|l| self.position_through(l));
        if with == without {
            return Some(with.map(|k| self.moves[k].1));
        }
        let (ran, dropped) = (self.end(with), self.end(without));
        if !ran.tells_apart(&dropped, tolerance_um) {
            return None;
        }
        if ran.matches(at_um, tolerance_um) {
            Some(with.map(|k| self.moves[k].1))
        } else if dropped.matches(at_um, tolerance_um) {
            Some(without.map(|k| self.moves[k].1))
        } else {
            None
        }
    }
}

/// How long after opening the port its input is dropped before the handshake, µs.
const SETTLE_US: u64 = 300_000;

/// The first wait before connecting again after failures in a row ([`GcodeLink::back_off`]).
const BACK_OFF_FIRST_US: u64 = 1_000_000;
/// The longest.
const BACK_OFF_MAX_US: u64 = 30_000_000;
/// Protocol errors are logged at most once this often ([`GcodeLink::log_protocol_error`]).
const PROTOCOL_LOG_EVERY_US: u64 = 10_000_000;

impl GcodeLink {
    /// A link to the firmware configured by `cfg` for `drives` syringes holding
    /// `capacity_nl` each.
    pub fn new(cfg: &crate::setup::GcodeLink, drives: usize, capacity_nl: u32) -> Self {
        let drives = drives.max(1);
        Self {
            host: LineHost::new(cfg.link.clone()),
            settings: cfg.settings(),
            drives,
            writer: None,
            release_axes_when_idle: false,
            next_tag: 1,
            accepted_upto: None,
            pending: VecDeque::new(),
            accepted: VecDeque::new(),
            held_at_most: cfg.link.dialect.queues().held_at_most(),
            status: MachineReport {
                remaining_nl: vec![capacity_nl; drives],
                ..MachineReport::default()
            },
            info: None,
            events: VecDeque::new(),
            stop: Stop::None,
            paused: false,
            estop_to_ack: false,
            recovering: false,
            port_closed: false,
            recover_after_open: false,
            settle_until: None,
            link_failures: 0,
            protocol_errors_logged: None,
            silence_noted: false,
            marks: cfg.link.dialect.numbers_lines().then(Marks::default),
            resume: None,
            log: LogQueue::default(),
        }
    }

    /// After edod's restart: `resume` says which of the interrupted job's moves ran once
    /// the firmware names its last accepted line, asked before the first handshake.
    pub fn with_resume(mut self, resume: Option<ResumeLines>) -> Self {
        self.resume = resume.filter(|r| self.marks.is_some() || r.is_by_position());
        if let Some(m) = self.marks.as_mut().filter(|_| self.resume.is_some()) {
            // The stored marks stay until the firmware answered (or did not).
            m.clear = true;
        }
        self
    }

    /// Queue `lines` (a writer's); the tag of the last sent, if any. `runs_us`: the
    /// move's time, given to the link with its motion line so that a lost `ok` is found
    /// once overdue (`LineHost::send_timed_line`).
    fn send_lines(
        &mut self,
        lines: &[String],
        runs_us: Option<u64>,
    ) -> Result<Option<u64>, String> {
        let mut last = None;
        for line in lines.iter().filter_map(|l| streamed(l)) {
            let tag = self.next_tag;
            self.next_tag += 1;
            match runs_us {
                Some(us) => self.host.send_timed_line(line, tag, us),
                None => self.host.send_line(line, tag),
            }
            .map_err(|e| e.to_string())?;
            last = Some(tag);
        }
        Ok(last)
    }

    /// The prologue every connection starts with: the writer's connection prologue (tool
    /// set-up, units, absolute positions, relative extrusion; Klipper's syringe axes
    /// released, which a job's preamble takes again at its first move).
    fn send_prologue(&mut self) {
        let mut lines = Vec::new();
        match MoveWriter::new(self.drives, &self.settings) {
            Ok(mut w) => w.connection_prologue(&mut lines),
            Err(e) => {
                self.log.warn(format!("G-code prologue error={e}"));
                return;
            }
        }
        self.send_lines_of_no_move(&lines, "prologue");
    }

    /// Queue `lines` that belong to no move (a prologue, an epilogue), in order with the
    /// moves; `what` names them in the log if the link refuses them.
    fn send_lines_of_no_move(&mut self, lines: &[String], what: &str) {
        match self.send_lines(lines, None) {
            Ok(last_tag) => self.pending.push_back(Pending {
                mv: None,
                sync: false,
                to: None,
                last_tag,
            }),
            Err(e) => self.log.warn(format!("G-code {what} refused error={e}")),
        }
    }

    /// Every pending move whose lines were all accepted moves to `accepted`; those the
    /// firmware cannot hold any more, or before an accepted `M400`, ran.
    fn drain_accepted(&mut self) {
        let mut moved = false;
        while let Some(p) = self.pending.front() {
            if p.last_tag.is_some_and(|t| Some(t) > self.accepted_upto) {
                break;
            }
            let Some(p) = self.pending.pop_front() else {
                break;
            };
            if p.sync {
                while let Some(a) = self.accepted.pop_front() {
                    moved |= self.ran(a);
                }
            } else if p.mv.is_some() {
                self.accepted.push_back(p);
            }
        }
        while self.accepted.len() > self.held_at_most {
            if let Some(a) = self.accepted.pop_front() {
                moved |= self.ran(a);
            }
        }
        moved |= self.update_state();
        if moved {
            self.events
                .push_back(Event::MachineStatus(self.status.clone()));
        }
        self.check_flushed();
        self.release_axes_if_idle();
    }

    /// Klipper, after a job ended: with nothing left to send or acknowledge and the
    /// machine running normally, the writer's epilogue releases the syringe axes; the
    /// next writer's preamble takes them again (at 0 where the plungers stand).
    fn release_axes_if_idle(&mut self) {
        if !self.release_axes_when_idle {
            return;
        }
        let idle = self.pending.is_empty()
            && self.host.queued_len() == 0
            && self.host.in_flight_len() == 0
            && self.stop == Stop::None
            && self.host.state() == LinkState::Streaming;
        if !idle {
            return;
        }
        self.release_axes_when_idle = false;
        // A flush (a cancel) dropped the job's writer: any writer releases the axes.
        let writer = match self.writer.take() {
            Some((_, w)) => Ok(w),
            None => MoveWriter::new(self.drives, &self.settings),
        };
        let Ok(mut w) = writer else {
            return;
        };
        let mut lines = Vec::new();
        w.epilogue(&mut lines);
        self.send_lines_of_no_move(&lines, "epilogue");
    }

    /// Move `p` ran; whether it was a move.
    fn ran(&mut self, p: Pending) -> bool {
        let Some(m) = p.mv else {
            return false;
        };
        self.status.last_executed = Some(m);
        self.status.executed_total += 1;
        if let Some(to) = p.to {
            self.status.position = to;
        }
        true
    }

    /// Nothing is left to send and moves were accepted and not known run: `M400`, whose
    /// `ok` says they ran.
    fn sync_if_idle(&mut self) {
        let idle = self.pending.is_empty()
            && self.host.queued_len() == 0
            && self.host.in_flight_len() == 0
            && self.host.state() == LinkState::Streaming;
        if !idle || self.accepted.is_empty() || matches!(self.stop, Stop::Halted) {
            return;
        }
        let tag = self.next_tag;
        let line_number = self.host.next_line_number();
        // Timed: its `ok` is overdue once every move the planner may hold had its time,
        // so a firmware gone silent under an `M400` is found as soon as under a move.
        if self.host.send_timed_line("M400", tag, 0).is_ok() {
            self.next_tag += 1;
            if let Some(m) = self.marks.as_mut() {
                if let Some(last) = m.last_sent {
                    m.push(GcodeMarkWrite::Add(GcodeMark {
                        job_id: last.job_id,
                        line_number,
                        move_index: last.index.saturating_add(1),
                        kind: GcodeMarkKind::M400,
                    }));
                }
            }
            self.pending.push_back(Pending {
                mv: None,
                sync: true,
                to: None,
                last_tag: Some(tag),
            });
        }
    }

    /// The machine state from what is pending; whether it changed.
    fn update_state(&mut self) -> bool {
        // The prologue is not the machine's work: only moves count.
        let moves = self.pending.iter().filter(|p| p.mv.is_some()).count() + self.accepted.len();
        let state = match self.stop {
            Stop::Halted => MachineState::EStopped,
            Stop::Flushing { acked: true } => MachineState::EStopped,
            _ if self.paused && self.host.in_flight_len() == 0 => MachineState::Held,
            _ if moves > 0 => MachineState::Running,
            _ => MachineState::Idle,
        };
        let queued = u32::try_from(moves).unwrap_or(u32::MAX);
        let changed = state != self.status.state || queued != self.status.queued;
        self.status.state = state;
        self.status.queued = queued;
        changed
    }

    /// The flush is done once nothing is in flight.
    fn check_flushed(&mut self) {
        if self.stop == (Stop::Flushing { acked: false })
            && self.host.in_flight_len() == 0
            && self.host.queued_len() == 0
            && self.accepted.is_empty()
        {
            self.stop = Stop::Flushing { acked: true };
            self.pending.clear();
            self.update_state();
            self.events
                .push_back(Event::CommandAcked(MachineCommand::Flush));
        }
    }

    /// Forget what was sent: the firmware's queue is gone (reset) or the session starts
    /// again.
    fn forget(&mut self) {
        self.pending.clear();
        self.accepted.clear();
        self.writer = None;
        if let Some(m) = self.marks.as_mut() {
            m.clear();
        }
        self.accepted_upto = None;
        self.update_state();
    }

    fn connect(&mut self, now: Micros) {
        if self.resume.take().is_some() {
            if let Some(m) = self.marks.as_mut() {
                // Line numbers start again: the previous run's marks no longer hold.
                m.clear = false;
            }
        }
        self.forget();
        self.info = None;
        let _ = self.host.connect(now);
    }

    fn translate(&mut self, e: LineEvent, now: Micros) {
        match e {
            LineEvent::Connected(i) => {
                self.log.info(format!(
                    "G-code firmware connected firmware={:?} identity={:?}",
                    i.firmware_name, i.identity
                ));
                if i.dialect == Dialect::Marlin && i.capability("EMERGENCY_PARSER") != Some(true) {
                    self.log.warn(
                        "Marlin without EMERGENCY_PARSER: M112 waits behind its queue \
                         (docs/firmware.md)"
                            .into(),
                    );
                }
                self.info = Some(i);
                self.stop = Stop::None;
                self.paused = false;
                self.send_prologue();
                self.update_state();
                self.events
                    .push_back(Event::MachineConnected(self.status.clone()));
            }
            LineEvent::Accepted { tag, .. } => {
                self.link_failures = 0;
                self.accepted_upto = Some(tag);
                self.drain_accepted();
            }
            LineEvent::MaybeRepeated { tag, line_number } => {
                self.log.warn(format!(
                    "no ok in time: line sent again; it runs twice if only its ok was lost \
                     tag={tag} line_number={line_number}"
                ));
            }
            LineEvent::Echo { text } => self.log.debug(format!("firmware text={text}")),
            LineEvent::Action { text } => {
                self.log.info(format!("firmware host action text={text}"))
            }
            LineEvent::Busy { text } => self.log.debug(format!("firmware busy text={text}")),
            LineEvent::Error { text } => self.log.warn(format!("firmware error text={text}")),
            LineEvent::ProtocolError { what } => self.log_protocol_error(&what, now),
            LineEvent::Halted { text, .. } => self.on_halted(text),
            LineEvent::Reset { banner, .. } => self.on_reset(&banner, now),
            LineEvent::LinkLost { silent_us, .. } => {
                self.log
                    .warn(format!("G-code link lost silent_ms={}", silent_us / 1000));
                self.events.push_back(Event::LinkSilent);
                let sent = !self.pending.is_empty() || !self.accepted.is_empty();
                if self.back_off(sent, now) {
                    return;
                }
                self.recovering =
                    self.recovery_useful() && self.host.recover_last_accepted(now).is_ok();
                if !self.recovering {
                    self.connect(now);
                }
            }
            LineEvent::Stopped { reason, .. } => {
                self.log
                    .warn(format!("G-code link stopped reason={reason}"));
                self.events
                    .push_back(Event::MachineFault(MachineFault::Other(reason)));
                if !self.back_off(false, now) {
                    self.connect(now);
                }
            }
            LineEvent::LastAccepted(last) => self.on_last_accepted(last, now),
        }
    }

    fn on_halted(&mut self, text: String) {
        let asked = self.stop == Stop::Halted;
        self.stop = Stop::Halted;
        self.forget();
        if asked {
            self.log
                .info(format!("firmware halted on the e-stop text={text}"));
        } else {
            self.log.warn(format!("firmware halted text={text}"));
            self.events
                .push_back(Event::MachineFault(MachineFault::Other(format!(
                    "firmware halted: {text}"
                ))));
        }
        self.events
            .push_back(Event::MachineStatus(self.status.clone()));
    }

    fn on_reset(&mut self, banner: &str, now: Micros) {
        if std::mem::take(&mut self.port_closed) {
            return;
        }
        self.log.warn(format!(
            "firmware restarted: its queue is lost banner={banner}"
        ));
        let last_executed = self.status.last_executed;
        self.events.push_back(Event::MachineReset { last_executed });
        self.stop = Stop::None;
        self.connect(now);
    }

    /// A protocol error (a stray `ok`, a garbage line, a stale resend request): logged at
    /// most once every [`PROTOCOL_LOG_EVERY_US`], the next one with how many were not, so
    /// a firmware spewing them cannot flood the journal (200,000 in a burst were 22 MB).
    fn log_protocol_error(&mut self, what: &str, now: Micros) {
        let period_over = |last: Micros, now: Micros| now.since(last) >= PROTOCOL_LOG_EVERY_US;
        if let Some(not_logged) = super::log_now(&mut self.protocol_errors_logged, now, period_over)
        {
            self.log
                .warn(format!("G-code link what={what} not_logged={not_logged}"));
        }
    }

    /// A lost or stopped link: the second failure in a row with no line accepted between
    /// waits before connecting again, twice as long each time (1 s up to 30 s), so a
    /// firmware that refuses every line draws no handshakes at line speed. True when it
    /// waits: the settle timer then recovers (`recover`: lines were sent) or connects.
    fn back_off(&mut self, recover: bool, now: Micros) -> bool {
        self.link_failures = self.link_failures.saturating_add(1);
        if self.link_failures < 2 {
            return false;
        }
        let wait_us = (BACK_OFF_FIRST_US << (self.link_failures - 2).min(5)).min(BACK_OFF_MAX_US);
        self.log.warn(format!(
            "G-code link: failed again with no line accepted; waiting before connecting \
             again failures={} wait_ms={}",
            self.link_failures,
            wait_us / 1000
        ));
        self.recover_after_open = recover && self.recovery_useful();
        self.settle_until = Some(now.plus_us(wait_us));
        true
    }

    /// Whether the firmware's answer to `recover_last_accepted` says which moves ran:
    /// always with line numbers (Marlin, RRF: the marks), on Klipper only for an
    /// interrupted job replayed by position after edod's restart (else where its nozzle
    /// stopped says nothing edod can use, and `M400` would wait for all it holds).
    fn recovery_useful(&self) -> bool {
        self.marks.is_some() || self.resume.is_some()
    }

    /// After a lost link: the moves up to the firmware's last accepted line ran; the
    /// session starts again.
    fn on_last_accepted(&mut self, last: LastAccepted, now: Micros) {
        self.recovering = false;
        if let Some(r) = self.resume.take() {
            self.resume_from(&r, &last);
            self.resume = Some(r);
            return self.connect(now);
        }
        match last {
            LastAccepted::Known {
                tag: Some(tag),
                exact,
                ..
            } => {
                // RRF names the last line parsed, which may be one it dropped: count it
                // as not run (it is sent again; at most that line runs twice).
                let upto = if exact { Some(tag) } else { tag.checked_sub(1) };
                self.accepted_upto = upto.max(self.accepted_upto);
                self.drain_accepted();
                // The firmware runs what it accepted while the link is down.
                while let Some(a) = self.accepted.pop_front() {
                    self.ran(a);
                }
                self.events
                    .push_back(Event::MachineStatus(self.status.clone()));
                self.log.info(format!(
                    "G-code link: last accepted line known tag={tag} exact={exact}"
                ));
            }
            other => self.log.warn(format!(
                "G-code link: last accepted line not known other={other:?}"
            )),
        }
        self.connect(now);
    }

    /// After edod's restart: the moves of the interrupted job up to the firmware's last
    /// accepted line ran (RRF: up to the line before it, which it may have dropped); the
    /// lifecycle learns it from the connection's report and resumes after them.
    fn resume_from(&mut self, r: &ResumeLines, last: &LastAccepted) {
        if let LastAccepted::Position { xyz_um } = *last {
            let tolerance_um = self.host.config().position_tolerance_um;
            match r.last_move_at(xyz_um, tolerance_um) {
                Some(index) => {
                    self.log.info(format!(
                        "G-code link: where Klipper's nozzle stopped tells which of the \
                         interrupted job's moves ran job={} ran_through={index} xyz_um={xyz_um:?}",
                        r.job_id()
                    ));
                    self.status.last_executed = Some(MoveRef {
                        job_id: r.job_id(),
                        index,
                    });
                }
                None => self.log.warn(format!(
                    "G-code link: Klipper's nozzle stopped where none of the interrupted \
                     job's last moves ends: the job resumes from its checkpoint job={} \
                     xyz_um={xyz_um:?}",
                    r.job_id()
                )),
            }
            return;
        }
        let LastAccepted::Known {
            line_number,
            exact,
            position_um,
            ..
        } = *last
        else {
            self.log.warn(format!(
                "G-code link: last accepted line not known after edod's restart: the job \
                 resumes from its checkpoint last={last:?} job={}",
                r.job_id()
            ));
            return;
        };
        let tolerance_um = self.host.config().position_tolerance_um;
        let by_position = position_um
            .filter(|_| !exact)
            .and_then(|at| r.last_move_by_position(line_number, at, tolerance_um));
        if let Some(ran_through) = by_position {
            self.log.info(format!(
                "G-code link: the nozzle's position tells which of the interrupted job's \
                 moves ran line_number={line_number} job={} ran_through={ran_through:?} \
                 position_um={position_um:?}",
                r.job_id()
            ));
            if let Some(index) = ran_through {
                self.status.last_executed = Some(MoveRef {
                    job_id: r.job_id(),
                    index,
                });
            }
            return;
        }
        let through = if exact {
            Some(line_number)
        } else {
            line_number.checked_sub(1)
        };
        let Some(index) = through.and_then(|l| r.last_move_through(l)) else {
            self.log.info(format!(
                "G-code link: no move of the interrupted job ran in the last connection \
                 line_number={line_number} job={}",
                r.job_id()
            ));
            return;
        };
        if exact {
            self.log.info(format!(
                "G-code link: the firmware accepted the interrupted job's moves up to this \
                 one line_number={line_number} job={} ran_through={index}",
                r.job_id()
            ));
        } else {
            self.log.warn(format!(
                "G-code link: RepRapFirmware's last line may be one it dropped: the move after \
                 the last known run is sent again and runs twice if it did run \
                 line_number={line_number} job={} ran_through={index} may_run_twice={}",
                r.job_id(),
                index.saturating_add(1)
            ));
        }
        self.status.last_executed = Some(MoveRef {
            job_id: r.job_id(),
            index,
        });
    }

    /// The e-stop proper: `M112` ahead of everything; the firmware halts.
    fn emergency_stop(&mut self) {
        let _ = self.host.emergency_stop();
        self.stop = Stop::Halted;
        self.estop_to_ack = true;
        self.forget();
    }

    /// The lifecycle's flush: the lines not sent are dropped, the ones in flight run.
    fn flush(&mut self) {
        if self.stop == Stop::Halted || self.host.state() != LinkState::Streaming {
            self.forget();
            self.events
                .push_back(Event::CommandAcked(MachineCommand::Flush));
            if self.stop != Stop::Halted {
                self.stop = Stop::Flushing { acked: true };
            }
            self.update_state();
            return;
        }
        // A move any of whose lines was not sent is dropped, and every move after it.
        let dropped = self.host.drop_queued();
        // Only the `M400` that makes the checkpoint final goes out now.
        self.host.set_paused(false);
        if let Some(first) = dropped.first() {
            let keep = self
                .pending
                .iter()
                .position(|p| p.last_tag.is_some_and(|t| t >= *first))
                .unwrap_or(self.pending.len());
            self.pending.truncate(keep);
        }
        self.writer = None;
        if let Some(m) = self.marks.as_mut() {
            m.clear();
        }
        self.stop = Stop::Flushing { acked: false };
        self.check_flushed();
    }

    fn resume(&mut self) {
        self.paused = false;
        self.host.set_paused(false);
        match self.stop {
            Stop::Halted => {
                // Only a reset brings the firmware back: the resume cannot be carried
                // out, and the job waiting for it is interrupted, saying what to do.
                let why = "the firmware halted (M112): reset the machine (Marlin: its reset \
                           button; RRF: M999 or reset; Klipper: FIRMWARE_RESTART); edod \
                           reconnects when it restarts";
                self.log.warn(why.into());
                self.events
                    .push_back(Event::MachineFault(MachineFault::Other(why.into())));
            }
            _ => {
                self.stop = Stop::None;
                self.update_state();
                self.events
                    .push_back(Event::CommandAcked(MachineCommand::Resume));
            }
        }
    }

    /// The lines of `mv`. A job's first move after a (re)connection or a flush starts a
    /// writer of its own, and its preamble goes first (as in the file; for Klipper it also
    /// sets the syringe axes to 0, where the new writer's positions start).
    fn lines_of(&mut self, mv: &Move) -> Result<Vec<String>, String> {
        let fresh = match &self.writer {
            Some((job, _)) => mv.job_id != crate::lifecycle::SERVICE_JOB_ID && *job != mv.job_id,
            None => true,
        };
        let mut lines = Vec::new();
        if fresh {
            let mut w = MoveWriter::new(self.drives, &self.settings).map_err(|e| e.to_string())?;
            w.preamble(&[], &mut lines);
            self.writer = Some((mv.job_id, w));
        }
        self.mark(mv, fresh);
        if let Some((_, w)) = self.writer.as_mut() {
            w.move_lines(mv, &mut lines);
        }
        Ok(lines)
    }
}

impl GcodeLink {
    /// The store's marks for `mv`, about to be written (`fresh`: by a new writer): a job's
    /// new writer marks its first line; a service move written by a job's writer leaves
    /// the lines after it no longer the job's moves alone.
    fn mark(&mut self, mv: &Move, fresh: bool) {
        let line_number = self.host.next_line_number();
        let Some(m) = self.marks.as_mut() else {
            return;
        };
        let at = MoveRef {
            job_id: mv.job_id,
            index: mv.index,
        };
        if mv.job_id == crate::lifecycle::SERVICE_JOB_ID {
            if !fresh && m.last_sent.is_some() {
                m.clear();
            }
        } else if fresh {
            m.last_sent = Some(at);
            m.push(GcodeMarkWrite::Writer(GcodeMark {
                job_id: mv.job_id,
                line_number,
                move_index: mv.index,
                kind: GcodeMarkKind::Writer,
            }));
        } else if m.last_sent.is_some() {
            m.last_sent = Some(at);
        }
    }
}

fn end_of(mv: &Move) -> Option<crate::machine::PositionUm> {
    match &mv.kind {
        MoveKind::Travel { to, .. } | MoveKind::Extrude { to, .. } => Some(*to),
        _ => None,
    }
}

impl LinkAdapter for GcodeLink {
    fn reconnect(&mut self, now: Micros) {
        self.port_closed = false;
        if !self.recover_after_open {
            self.forget();
        }
        self.settle_until = Some(now.plus_us(SETTLE_US));
    }

    fn port_lost(&mut self) {
        self.port_closed = true;
        self.host.port_closed();
        // A pulled cable does not stop the firmware: it runs what it accepted. Which
        // lines that was, Marlin and RRF say once the port is back (the host keeps its
        // history until the next handshake); a reset behind the port's loss shows as
        // their line counter going back, and the job resumes from its checkpoint.
        let sent = !self.pending.is_empty() || !self.accepted.is_empty();
        self.recover_after_open = self.marks.is_some() && self.stop != Stop::Halted && sent;
        if !self.recover_after_open {
            self.forget();
        }
    }

    fn handle_bytes(&mut self, bytes: &[u8], now: Micros) {
        if self.settle_until.is_some() {
            self.log.debug(format!(
                "dropped: read before the handshake bytes={}",
                bytes.len()
            ));
            return;
        }
        self.host.handle_bytes(bytes, now);
    }

    fn handle_timeout(&mut self, now: Micros) {
        if self.settle_until.is_some_and(|t| now >= t) {
            self.settle_until = None;
            // After edod's restart or a lost port, the firmware's last accepted line
            // first: the handshake starts numbering again.
            let recover = std::mem::take(&mut self.recover_after_open) || self.resume.is_some();
            self.recovering = recover && self.host.recover_last_accepted(now).is_ok();
            if !self.recovering {
                self.connect(now);
            }
        }
        self.host.handle_timeout(now);
    }

    fn next_timeout(&self) -> Option<Micros> {
        self.settle_until.or(self.host.next_timeout())
    }

    fn poll_transmit(&mut self, now: Micros) -> Option<Vec<u8>> {
        let mut out = self.host.poll_transmit(now);
        if out.is_none() {
            self.sync_if_idle();
            out = self.host.poll_transmit(now);
        }
        if out.is_some() && std::mem::take(&mut self.estop_to_ack) {
            // M112 is acted on as it arrives (Marlin's emergency parser, RRF's urgent
            // scan, Klipper below 20 pending lines); RRF says nothing back.
            self.events
                .push_back(Event::CommandAcked(MachineCommand::EmergencyStop));
        }
        out
    }

    fn poll_event(&mut self, now: Micros) -> Option<Event> {
        while let Some(e) = self.host.poll_event() {
            self.translate(e, now);
        }
        let probing = self.host.state() == LinkState::Probing;
        if probing && !self.silence_noted {
            self.log_protocol_error(
                "the firmware did not acknowledge a line in time: asking it where it is",
                now,
            );
        }
        self.silence_noted = probing;
        if self.port_closed && self.host.state() == LinkState::Reset {
            self.port_closed = false;
        }
        self.events.pop_front()
    }

    fn command(&mut self, c: MachineCommand, _now: Micros) {
        match c {
            MachineCommand::Flush => self.flush(),
            MachineCommand::EmergencyStop => self.emergency_stop(),
            MachineCommand::FeedHold => {
                self.paused = true;
                self.host.set_paused(true);
                self.update_state();
                self.events
                    .push_back(Event::CommandAcked(MachineCommand::FeedHold));
            }
            MachineCommand::Resume => self.resume(),
            MachineCommand::ClearFaults => {}
            MachineCommand::QueryStatus => {
                self.update_state();
                self.events
                    .push_back(Event::MachineStatus(self.status.clone()));
            }
        }
    }

    fn has_room(&self, ahead: usize) -> bool {
        self.host.state() == LinkState::Streaming
            && self.info.is_some()
            && self.stop == Stop::None
            && !self.paused
            && self.host.queued_len() < ahead.clamp(1, 16)
    }

    fn job_ended(&mut self, _job_id: u32) {
        if self.settings.flavor == crate::gcode_link::writer::Dialect::Klipper {
            self.release_axes_when_idle = true;
            self.release_axes_if_idle();
        }
    }

    fn send_move(&mut self, mv: Move) -> Result<(), String> {
        if mv.job_id != crate::lifecycle::SERVICE_JOB_ID {
            self.release_axes_when_idle = false;
        }
        let lines = self.lines_of(&mv)?;
        // Where the nozzle will stand: the last motion not yet run, else where it is.
        let from = self
            .pending
            .iter()
            .rev()
            .find_map(|p| p.to)
            .unwrap_or(self.status.position);
        let last_tag = self.send_lines(&lines, mv.kind.run_time_us(Some(from)))?;
        self.pending.push_back(Pending {
            sync: false,
            mv: Some(MoveRef {
                job_id: mv.job_id,
                index: mv.index,
            }),
            to: end_of(&mv),
            last_tag,
        });
        self.drain_accepted();
        Ok(())
    }

    fn in_link(&self) -> (usize, u64) {
        (self.host.queued_len(), self.host.in_flight_len() as u64)
    }

    fn link_problem(&self) -> Option<String> {
        let firmware = match self.host.config().dialect {
            Dialect::Marlin => "Marlin",
            Dialect::Rrf => "RepRapFirmware",
            Dialect::Klipper => "Klipper",
        };
        (self.host.state() == LinkState::Probing).then(|| {
            format!(
                "{firmware} has not acknowledged a line in time: edod is asking it where it \
                 is (the link is declared lost if it stays silent through {} timeouts)",
                self.host.config().max_timeouts
            )
        })
    }

    fn identity(&self) -> Option<&str> {
        let i = self.info.as_ref()?;
        i.firmware_name
            .as_deref()
            .or(i.identity.as_deref())
            .or(Some(match i.dialect {
                Dialect::Marlin => "Marlin",
                Dialect::Rrf => "RepRapFirmware",
                Dialect::Klipper => "Klipper",
            }))
    }

    fn report(&self) -> &MachineReport {
        &self.status
    }

    fn poll_store_mark(&mut self) -> Option<GcodeMarkWrite> {
        self.marks.as_mut()?.out.pop_front()
    }

    fn counters(&self) -> LinkCounters {
        let s = self.host.stats();
        LinkCounters {
            bytes_sent: s.bytes_sent,
            bytes_received: s.bytes_received,
            resent: s.lines_resent + s.lines_repeated,
            srtt_us: None,
        }
    }

    fn poll_log(&mut self) -> Option<LogLine> {
        self.log.pop()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gcode_link::MixWriting;
    use crate::machine::PositionUm;

    /// Moves of job 7 whose Marlin mix changes now and then (so `M163`/`M164` lines come
    /// between some of them).
    fn job_moves(n: u32) -> Vec<Move> {
        (0..n)
            .map(|index| Move {
                job_id: 7,
                index,
                kind: MoveKind::Extrude {
                    to: PositionUm {
                        x_um: 1000 * index as i32,
                        y_um: 0,
                        z_um: 200,
                    },
                    feed_um_s: 10_000,
                    volumes_nl: if index % 10 < 5 {
                        vec![300, 0]
                    } else {
                        vec![0, 300]
                    },
                    width_factor_ppt: 1000,
                },
            })
            .collect()
    }

    /// An adapter for Marlin (two syringes) and the Marlin model it talks to.
    /// A Klipper link's settings: two syringes on axes A and B.
    fn klipper_config() -> crate::setup::GcodeLink {
        crate::setup::GcodeLink {
            link: crate::gcode_link::LineLinkConfig::for_dialect(Dialect::Klipper),
            mix: MixWriting::Axes(vec!['A', 'B']),
            barrel_area_mm2: 78.5,
            plunger_limits: Vec::new(),
        }
    }

    fn marlin_rig() -> (GcodeLink, crate::gcode_link::Firmware) {
        use crate::gcode_link::{Firmware, FirmwareConfig, LineLinkConfig};
        let cfg = crate::setup::GcodeLink {
            link: LineLinkConfig::for_dialect(Dialect::Marlin),
            mix: MixWriting::MarlinM163,
            barrel_area_mm2: 78.5,
            plunger_limits: Vec::new(),
        };
        let link = GcodeLink::new(&cfg, 2, 1_000_000);
        let fw = Firmware::new(FirmwareConfig::for_dialect(Dialect::Marlin), Micros(0));
        (link, fw)
    }

    /// One millisecond of an instant wire between `link` and `fw` (the cable in when
    /// `plugged`); the firmware runs each move at once. Returns the moves (`G1`) it ran.
    fn pump(
        link: &mut GcodeLink,
        fw: &mut crate::gcode_link::Firmware,
        now: Micros,
        plugged: bool,
        events: &mut Vec<Event>,
    ) -> usize {
        let ran = pump_lines(link, fw, now, plugged, events);
        ran.iter().filter(|l| l.starts_with("G1")).count()
    }

    /// [`pump`], returning every line the firmware ran.
    fn pump_lines(
        link: &mut GcodeLink,
        fw: &mut crate::gcode_link::Firmware,
        now: Micros,
        plugged: bool,
        events: &mut Vec<Event>,
    ) -> Vec<String> {
        link.handle_timeout(now);
        while let Some(b) = link.poll_transmit(now) {
            if plugged {
                fw.handle_bytes(&b, now);
            }
        }
        fw.handle_timeout(now);
        let mut ran = Vec::new();
        while let Some(line) = fw.poll_line() {
            if line.is_move {
                fw.moves_done(1, now);
            }
            ran.push(line.text);
        }
        while let Some(b) = fw.poll_transmit() {
            if plugged {
                link.handle_bytes(&b, now);
            }
        }
        while let Some(e) = link.poll_event(now) {
            events.push(e);
        }
        ran
    }

    /// Klipper: once a job ended and every line was acknowledged, edod releases each
    /// syringe's axis and steps it to where it stands (the file's epilogue), so a refill
    /// macro can move the plunger and the next job's `SET_POSITION=0` is clean; nothing
    /// more is sent until the next job's preamble takes the axes again.
    #[test]
    fn klipper_axes_are_released_once_a_job_ended_and_ran() {
        use crate::gcode_link::{Firmware, FirmwareConfig};
        let cfg = klipper_config();
        let mut link = GcodeLink::new(&cfg, 2, 1_000_000);
        let mut fw = Firmware::new(FirmwareConfig::for_dialect(Dialect::Klipper), Micros(0));
        let (mut ran, mut events) = (Vec::new(), Vec::new());
        let mut t = 0u64;
        link.reconnect(Micros(0));
        while !link.has_room(4) {
            t += 1000;
            assert!(t < 10_000_000, "did not connect");
            ran.extend(pump_lines(&mut link, &mut fw, Micros(t), true, &mut events));
        }
        for mv in job_moves(6) {
            link.send_move(mv).unwrap();
        }
        link.job_ended(7);
        for _ in 0..200 {
            t += 1000;
            ran.extend(pump_lines(&mut link, &mut fw, Micros(t), true, &mut events));
        }
        let last_move = ran.iter().rposition(|l| l.starts_with("G1")).unwrap();
        let after: Vec<&str> = ran[last_move + 1..]
            .iter()
            .map(String::as_str)
            .filter(|l| *l != "M400")
            .collect();
        assert_eq!(
            after,
            [
                "MANUAL_STEPPER STEPPER=syringe_a GCODE_AXIS=",
                "MANUAL_STEPPER STEPPER=syringe_a MOVE=0.019108",
                "MANUAL_STEPPER STEPPER=syringe_b GCODE_AXIS=",
                "MANUAL_STEPPER STEPPER=syringe_b MOVE=0.003822",
            ],
            "{ran:#?}"
        );
    }

    /// A firmware spewing garbage or stray `ok`s: one warning, then at most one every
    /// 10 s carrying how many were not logged.
    #[test]
    fn protocol_errors_are_logged_at_most_every_ten_seconds() {
        let (mut link, _fw) = marlin_rig();
        let error = || LineEvent::ProtocolError {
            what: "`ok` with no line in flight".into(),
        };
        for k in 0..200_000u64 {
            link.translate(error(), Micros(k * 25));
        }
        assert_eq!(link.protocol_errors_logged, Some((Micros(0), 199_999)));
        link.translate(error(), Micros(10_000_000));
        assert_eq!(link.protocol_errors_logged, Some((Micros(10_000_000), 0)));
        // What reaches edod's log: two lines, the second counting those not logged.
        let lines: Vec<LogLine> = std::iter::from_fn(|| link.poll_log()).collect();
        assert_eq!(lines.len(), 2, "{lines:?}");
        assert!(lines
            .iter()
            .all(|l| l.level == crate::adapter::LogLevel::Warn));
        assert!(lines[0].text.ends_with("not_logged=0"), "{}", lines[0].text);
        assert!(
            lines[1].text.ends_with("not_logged=199999"),
            "{}",
            lines[1].text
        );
    }

    /// A firmware that floods the line with lines for the log while nobody takes them:
    /// the adapter keeps the newest and says how many it dropped.
    #[test]
    fn log_lines_not_taken_are_bounded() {
        let (mut link, _fw) = marlin_rig();
        for k in 0..10_000u32 {
            link.translate(
                LineEvent::Echo {
                    text: format!("echo {k}"),
                },
                Micros(0),
            );
        }
        let lines: Vec<LogLine> = std::iter::from_fn(|| link.poll_log()).collect();
        assert_eq!(lines.len(), crate::adapter::LOG_LINES_KEPT + 1);
        assert_eq!(
            lines[0].text,
            format!(
                "{} link log lines dropped (not taken in time)",
                10_000 - crate::adapter::LOG_LINES_KEPT
            )
        );
        assert_eq!(
            lines.last().map(|l| l.text.as_str()),
            Some("firmware text=echo 9999")
        );
    }

    /// A firmware that refuses every line: after the first lost link, each next one waits
    /// before connecting again, 1 s, then 2 s ... up to 30 s, until a line is accepted.
    #[test]
    fn failed_links_in_a_row_back_off_before_connecting_again() {
        let (mut link, _fw) = marlin_rig();
        let now = Micros(5_000_000);
        assert!(
            !link.back_off(false, now),
            "the first failure connects at once"
        );
        for (failures, wait_s) in [(2, 1), (3, 2), (4, 4), (5, 8), (6, 16), (7, 30), (9, 30)] {
            while link.link_failures + 1 < failures {
                link.back_off(false, now);
            }
            assert!(link.back_off(false, now));
            assert_eq!(link.next_timeout(), Some(now.plus_us(wait_s * 1_000_000)));
        }
        link.translate(
            LineEvent::Accepted {
                tag: 0,
                line_number: 2,
            },
            now,
        );
        assert!(
            !link.back_off(false, now),
            "a line accepted starts the count again"
        );
    }

    /// Marlin, the cable pulled mid-job: the firmware runs what it accepted while the
    /// port is gone; on its return the adapter asks for the last accepted line before
    /// the handshake and reports every move up to it as run, so the job resumes after
    /// the firmware's last move (not from the checkpoint, which trails it by up to
    /// `BUFSIZE + BLOCK_BUFFER_SIZE` moves: those ran twice before).
    #[test]
    fn a_pulled_cable_counts_the_moves_the_firmware_accepted_as_run() {
        let (mut link, mut fw) = marlin_rig();
        let mut events = Vec::new();
        let mut t = 0u64;
        link.reconnect(Micros(t));
        let mut to_send = job_moves(60).into_iter();
        let mut ran = 0;
        // Stream until the firmware ran 40 moves: lines still in flight, no M400 yet.
        while ran < 40 {
            t += 1000;
            assert!(t < 10_000_000, "stuck: {ran} moves ran");
            while link.has_room(4) {
                let Some(mv) = to_send.next() else { break };
                link.send_move(mv).unwrap();
            }
            ran += pump(&mut link, &mut fw, Micros(t), true, &mut events);
        }
        let counted = link.report().last_executed.map(|m| m.index);
        assert!(
            counted.is_some_and(|i| i + 1 < 40),
            "before the cable is pulled, the checkpoint trails the firmware: {counted:?}"
        );
        link.port_lost();
        for _ in 0..100 {
            t += 1000;
            ran += pump(&mut link, &mut fw, Micros(t), false, &mut events);
        }
        events.clear();
        link.reconnect(Micros(t));
        let mut connected = false;
        while !connected {
            t += 1000;
            assert!(t < 20_000_000, "did not connect again: {events:?}");
            ran += pump(&mut link, &mut fw, Micros(t), true, &mut events);
            connected = events
                .iter()
                .any(|e| matches!(e, Event::MachineConnected(_)));
        }
        let last = events.iter().find_map(|e| match e {
            Event::MachineStatus(r) | Event::MachineConnected(r) => r.last_executed,
            _ => None,
        });
        assert_eq!(
            last.map(|m| (m.job_id, m.index)),
            Some((7, ran as u32 - 1)),
            "the firmware ran {ran} moves"
        );
    }

    /// After the e-stop's `M112` the firmware stays halted until the machine is reset: a
    /// resume is not acknowledged (the lifecycle would wait for it for ever) but reported
    /// as a fault that says to reset the machine.
    #[test]
    fn a_resume_while_the_firmware_is_halted_is_a_fault_saying_reset_it() {
        let (mut link, mut fw) = marlin_rig();
        let mut events = Vec::new();
        let mut t = 0;
        link.reconnect(Micros(t));
        while !events
            .iter()
            .any(|e| matches!(e, Event::MachineConnected(_)))
        {
            t += 1000;
            assert!(t < 10_000_000, "did not connect: {events:?}");
            pump(&mut link, &mut fw, Micros(t), true, &mut events);
        }
        link.command(MachineCommand::EmergencyStop, Micros(t));
        for _ in 0..10 {
            t += 1000;
            pump(&mut link, &mut fw, Micros(t), true, &mut events);
        }
        assert!(fw.is_halted());
        events.clear();
        link.command(MachineCommand::ClearFaults, Micros(t));
        link.command(MachineCommand::Resume, Micros(t));
        pump(&mut link, &mut fw, Micros(t + 1000), true, &mut events);
        assert!(
            !events
                .iter()
                .any(|e| matches!(e, Event::CommandAcked(MachineCommand::Resume))),
            "{events:?}"
        );
        assert!(
            events.iter().any(|e| matches!(
                e,
                Event::MachineFault(MachineFault::Other(why)) if why.contains("reset the machine")
            )),
            "{events:?}"
        );
    }

    /// Klipper's link lost with no interrupted job to place: connected again at once, not
    /// first asked where it stopped (`M400` waits for all it holds, and the answer would
    /// go unused); with one, asked.
    #[test]
    fn a_lost_klipper_link_asks_where_it_stopped_only_to_place_a_job() {
        let cfg = klipper_config();
        let lost = || LineEvent::LinkLost {
            silent_us: 1,
            unacknowledged: Vec::new(),
        };
        let mut link = GcodeLink::new(&cfg, 2, 1_000_000);
        link.translate(lost(), Micros(1));
        assert!(!link.recovering);
        assert_eq!(link.host.state(), LinkState::Connecting);
        let r = ResumeLines::by_position(3, 0, 10, job_moves(4).into_iter().map(Ok)).unwrap();
        let mut link = GcodeLink::new(&cfg, 2, 1_000_000).with_resume(Some(r));
        link.translate(lost(), Micros(1));
        assert!(link.recovering);
        assert_eq!(link.host.state(), LinkState::Recovering);
    }

    #[test]
    fn klipper_resume_takes_the_last_move_of_the_first_run_ending_where_the_nozzle_stopped() {
        let to = |x_um: i32| PositionUm {
            x_um,
            y_um: 0,
            z_um: 200,
        };
        let kinds = [
            MoveKind::Home,
            MoveKind::Travel {
                to: to(1_000),
                feed_um_s: 10_000,
            },
            MoveKind::Dwell { duration_ms: 100 },
            MoveKind::Travel {
                to: to(2_000),
                feed_um_s: 10_000,
            },
            MoveKind::Dwell { duration_ms: 100 },
            MoveKind::Travel {
                to: to(1_000),
                feed_um_s: 10_000,
            },
            MoveKind::Travel {
                to: to(3_000),
                feed_um_s: 10_000,
            },
        ];
        let moves = kinds.into_iter().enumerate().map(|(i, kind)| {
            Ok(Move {
                job_id: 3,
                index: i as u32,
                kind,
            })
        });
        let r = ResumeLines::by_position(3, 1, 100, moves).unwrap();
        assert!(r.is_by_position());
        // A travel and the dwell after it: the dwell (never a retract run twice).
        assert_eq!(r.last_move_at([2_000, 0, 200], 2), Some(4));
        assert_eq!(r.last_move_at([3_001, 0, 200], 2), Some(6));
        // Two runs end at X1: the first (repeats, never skips).
        assert_eq!(r.last_move_at([1_000, 0, 200], 2), Some(2));
        assert_eq!(r.last_move_at([9_000, 0, 200], 2), None);
        // Moves before the span's start are not candidates; after it, not planned.
        let short = ResumeLines::by_position(3, 3, 1, r_moves()).unwrap();
        assert_eq!(short.last_move_at([1_000, 0, 200], 2), None);
        assert_eq!(short.last_move_at([2_000, 0, 200], 2), Some(4));
        fn r_moves() -> impl Iterator<Item = Result<Move, String>> {
            (0..7u32).map(|i| {
                Ok(Move {
                    job_id: 3,
                    index: i,
                    kind: MoveKind::Travel {
                        to: PositionUm {
                            x_um: [0, 1_000, 1_000, 2_000, 2_000, 1_000, 3_000][i as usize],
                            y_um: 0,
                            z_um: 200,
                        },
                        feed_um_s: 10_000,
                    },
                })
            })
        }
    }

    #[test]
    fn the_replay_puts_each_line_number_in_the_move_it_belongs_to() {
        let settings = GcodeSettings::for_mix(&MixWriting::MarlinM163, 78.5);
        let moves = job_moves(40);
        // What went out: a fresh writer at move 12 from line 9, an M400 before move 20.
        let mut w = MoveWriter::new(2, &settings).unwrap();
        let mut lines = Vec::new();
        w.preamble(&[], &mut lines);
        let mut line =
            9 + crate::gcode_link::writer::streamed_lines(&lines.join("\n")).count() as u32;
        let mut last_line_of = Vec::new();
        for mv in &moves[12..] {
            if mv.index == 20 {
                line += 1;
            }
            lines.clear();
            w.move_lines(mv, &mut lines);
            line += crate::gcode_link::writer::streamed_lines(&lines.join("\n")).count() as u32;
            last_line_of.push((line - 1, mv.index));
        }
        assert!(
            last_line_of.windows(2).any(|p| p[1].0 - p[0].0 > 1),
            "some moves carry a mix"
        );
        let mark = |line_number, move_index, kind| GcodeMark {
            job_id: 7,
            line_number,
            move_index,
            kind,
        };
        let m400_line = last_line_of[7].0 + 1;
        let marks = [
            mark(9, 12, GcodeMarkKind::Writer),
            mark(m400_line, 20, GcodeMarkKind::M400),
        ];
        let r = ResumeLines::replay(7, &marks, moves.iter().cloned().map(Ok), 2, &settings)
            .unwrap()
            .unwrap();
        assert_eq!(r.moves, last_line_of);
        assert_eq!(r.last_move_through(9), None, "the preamble only");
        for &(last, index) in &last_line_of {
            assert_eq!(r.last_move_through(last), Some(index));
        }
        assert_eq!(r.last_move_through(m400_line), Some(19));
        // RRF's nozzle position: at a move's end that move ran, at the end of the move
        // before it did not; elsewhere, or where the two ends are one, it cannot tell.
        let mut told = 0;
        for k in 1..r.moves.len() {
            let ((prev_last, prev_index), (last, index)) = (r.moves[k - 1], r.moves[k]);
            let (end, before) = (r.ends_um[k].map(i64::from), r.ends_um[k - 1].map(i64::from));
            let unknown = i64::from(UNKNOWN_UM);
            if prev_last + 1 != last || end.contains(&unknown) || before.contains(&unknown) {
                continue;
            }
            if end == before {
                assert_eq!(r.last_move_by_position(last, end, 2), None);
                continue;
            }
            assert_eq!(r.last_move_by_position(last, end, 2), Some(Some(index)));
            assert_eq!(
                r.last_move_by_position(last, before, 2),
                Some(Some(prev_index))
            );
            assert_eq!(r.last_move_by_position(last, [-9_999_999; 3], 2), None);
            told += 1;
        }
        assert!(told > 10, "{told} moves told apart by position");
        // Another job's marks say nothing of this one; a misplaced M400 is refused.
        assert_eq!(
            ResumeLines::replay(8, &marks, moves.iter().cloned().map(Ok), 2, &settings),
            Ok(None)
        );
        let wrong = [marks[0], mark(m400_line + 1, 20, GcodeMarkKind::M400)];
        assert!(ResumeLines::replay(7, &wrong, moves.into_iter().map(Ok), 2, &settings).is_err());
    }
}
