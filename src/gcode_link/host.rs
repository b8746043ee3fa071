//! The host end of the G-code line link (sans-IO): numbers, checksums and windows the
//! caller's lines, keeps them for resends, reads the firmware's replies and tells the
//! caller which lines the firmware accepted (`docs/firmware.md`).

use std::collections::VecDeque;

use super::position::{
    klipper_position_line, rrf_user_position, KlipperPositionLine, NozzleAt,
    KLIPPER_POSITION_QUERY, RRF_POSITION_QUERY,
};
use super::reply::{self, LineReader, OkReply, ReadItem, Reply};
use super::{
    command_word, numbered_line, Dialect, LineLinkConfig, Micros, Window, PROBE_LINE_NUMBER,
};

/// Where the host end is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkState {
    /// Created, nothing sent: call [`LineHost::connect`] or [`LineHost::recover_last_accepted`].
    Idle,
    /// The handshake is out.
    Connecting,
    /// Lines are streamed.
    Streaming,
    /// (Marlin) a timeout: the out-of-sequence probe is out; no line goes until it answers.
    Probing,
    /// [`LineHost::recover_last_accepted`] is waiting for the firmware's answer.
    Recovering,
    /// No answer after the timeouts; nothing is sent until [`LineHost::connect`].
    Lost,
    /// A protocol error stopped the link; nothing is sent until [`LineHost::connect`].
    Stopped,
    /// The firmware restarted; nothing is sent until [`LineHost::connect`].
    Reset,
    /// The firmware halted (kill, M112, Klipper shutdown) or the caller sent the e-stop.
    Halted,
}

/// What the firmware said about itself during the handshake.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FirmwareInfo {
    /// The dialect the link speaks.
    pub dialect: crate::gcode_link::Dialect,
    /// `FIRMWARE_NAME` of the `M115` answer.
    pub firmware_name: Option<String>,
    /// `FIRMWARE_VERSION` of the `M115` answer (Marlin puts it in the name).
    pub firmware_version: Option<String>,
    /// The whole `M115` answer line.
    pub identity: Option<String>,
    /// `Cap:<NAME>:<0|1>` lines (Marlin), in order.
    pub capabilities: Vec<(String, bool)>,
    /// Other lines seen while connecting (boot banner, settings dump), at most 32.
    pub banner: Vec<String>,
    /// The handshake's `ok`s carried ADVANCED_OK free counts.
    pub advanced_ok: bool,
    /// Free command slots reported at the handshake, corrected by one (Marlin `BUFSIZE`).
    pub command_slots: Option<u16>,
}

impl FirmwareInfo {
    fn new(dialect: crate::gcode_link::Dialect) -> Self {
        Self {
            dialect,
            firmware_name: None,
            firmware_version: None,
            identity: None,
            capabilities: Vec::new(),
            banner: Vec::new(),
            advanced_ok: false,
            command_slots: None,
        }
    }

    /// A `Cap:` flag, if the firmware reported it.
    pub fn capability(&self, name: &str) -> Option<bool> {
        self.capabilities
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| *v)
    }
}

/// Free counts of Marlin's last ADVANCED_OK `ok N<n> P<p> B<b>`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FreeCounts {
    /// `P`: free planner blocks (the planner holds `BLOCK_BUFFER_SIZE` − this many moves).
    pub planner_blocks: u16,
    /// `B` + 1: free command-queue slots (Marlin counts the acknowledged line as still in).
    pub command_slots: u16,
}

/// The answer of [`LineHost::recover_last_accepted`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LastAccepted {
    /// The firmware's last accepted line.
    Known {
        /// Its line number.
        line_number: u32,
        /// Its tag, if this host sent it.
        tag: Option<u64>,
        /// The first line to send again, if this host sent it: the line after
        /// `line_number` when `exact`, else `line_number` itself (RRF may have dropped it).
        resume_tag: Option<u64>,
        /// Marlin: the firmware accepted exactly the lines up to `line_number`. RRF: exact
        /// when the nozzle's position told whether that line ran (this host sent it and
        /// it ends elsewhere than the line before it: `line_number` is then the last line
        /// that ran); else the last line it *parsed*, which a bad checksum may have
        /// dropped.
        exact: bool,
        /// RRF: where the nozzle stood (`userPosition` X, Y, Z, µm), for a caller that
        /// knows where its lines end to tell whether `line_number` ran when this host
        /// could not (after a host restart).
        position_um: Option<[i64; 3]>,
    },
    /// Klipper, which numbers no lines: where the nozzle stopped once every move it held
    /// ran (`M400`, then `GET_POSITION`), for the caller to find the last move that ran.
    Position {
        /// X, Y, Z, µm.
        xyz_um: [i64; 3],
    },
    /// The firmware cannot tell, did not answer, or restarted.
    Unknown {
        /// Why.
        reason: String,
    },
}

/// Something the caller must know.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LineEvent {
    /// The handshake finished: lines can be streamed.
    Connected(FirmwareInfo),
    /// The firmware accepted the line (its `ok`, or Marlin stating it has it). In order,
    /// each line once.
    Accepted {
        /// The caller's tag.
        tag: u64,
        /// The line number it went out with (counted, not sent, on Klipper).
        line_number: u32,
    },
    /// RRF: no `ok` came in time and the nozzle's position could not tell whether the
    /// line ran (it ends where the line before it does), so it was sent again; it runs
    /// twice if only its `ok` was lost.
    MaybeRepeated {
        /// The caller's tag.
        tag: u64,
        /// Its line number.
        line_number: u32,
    },
    /// Firmware output that is not part of the protocol (`echo:`, `//`, reports).
    Echo {
        /// The line, without `echo:` / `//`.
        text: String,
    },
    /// A host action (`//action:<text>`: pause, resume, cancel, prompts).
    Action {
        /// What follows `//action:`.
        text: String,
    },
    /// The firmware is busy (`busy: processing`, `paused for user`); reported when it
    /// changes.
    Busy {
        /// What follows `busy:`.
        text: String,
    },
    /// A firmware error that is not a resend request (`Error:`, Klipper `!!`): the line
    /// its `ok` names was refused, and the link stops there ([`LineEvent::Stopped`]).
    Error {
        /// The message.
        text: String,
    },
    /// The firmware halted (Marlin kill, Klipper shutdown): nothing more is sent.
    Halted {
        /// The message.
        text: String,
        /// Tags sent or queued and never accepted, in order.
        unacknowledged: Vec<u64>,
    },
    /// The firmware restarted (start-up banner, Klipper ready again, line counter gone
    /// back, port closed): its queue is lost; nothing more is sent until `connect`.
    Reset {
        /// What showed it.
        banner: String,
        /// Tags sent or queued and never accepted, in order.
        unacknowledged: Vec<u64>,
    },
    /// No reply within the timeouts while lines were in flight; nothing more is sent.
    LinkLost {
        /// Time since the last sign of progress, µs.
        silent_us: u64,
        /// Tags sent or queued and never accepted, in order.
        unacknowledged: Vec<u64>,
    },
    /// The firmware asked for something the link cannot give without risk (a line never
    /// sent or no longer kept, a resend loop); nothing more is sent.
    Stopped {
        /// Why.
        reason: String,
        /// Tags sent or queued and never accepted, in order.
        unacknowledged: Vec<u64>,
    },
    /// Input from the firmware that was handled and ignored (garbage, over-long line,
    /// stale or inconsistent request, `ok` with nothing in flight).
    ProtocolError {
        /// What was wrong.
        what: String,
    },
    /// The answer of [`LineHost::recover_last_accepted`].
    LastAccepted(LastAccepted),
}

/// Why a line was refused by [`LineHost::send_line`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SendError {
    /// Lines are taken while connecting or streaming only.
    #[error("the G-code link takes no lines now (state {0:?})")]
    NotReady(LinkState),
    /// The text would not survive the firmware's line reader or the checksum.
    #[error("G-code line refused: {0}")]
    Invalid(String),
    /// The line with its number and checksum would be longer than the firmware reads.
    #[error("G-code line of {bytes} bytes with its number and checksum, more than {max}")]
    TooLong {
        /// Its length.
        bytes: usize,
        /// `LineLinkConfig::max_line_bytes`.
        max: usize,
    },
}

/// Why [`LineHost::recover_last_accepted`] cannot run now.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RecoverError {
    /// Only while nothing is streamed (idle, lost, stopped, reset, halted).
    #[error("cannot query the last accepted line while {0:?}")]
    Busy(LinkState),
}

/// Counters of the host end.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct LineStats {
    /// Bytes handed to the port.
    pub bytes_sent: u64,
    /// Bytes fed from the port.
    pub bytes_received: u64,
    /// Caller lines sent the first time.
    pub lines_sent: u64,
    /// Their bytes (line number, checksum and newline included).
    pub line_bytes_sent: u64,
    /// Lines sent again after a resend request or probe.
    pub lines_resent: u64,
    /// RRF lines sent again after a timeout ([`LineEvent::MaybeRepeated`]).
    pub lines_repeated: u64,
    /// `ok`s received.
    pub oks: u64,
    /// `ok`s that belonged to a resend request or a probe.
    pub oks_swallowed: u64,
    /// `ok`s with nothing in flight, or for a line the host did not send.
    pub oks_unexpected: u64,
    /// Resend requests received.
    pub resend_requests: u64,
    /// Resend requests for lines the firmware had already confirmed (ignored).
    pub resends_stale: u64,
    /// Repeats of a request already being served (ignored).
    pub resends_duplicate: u64,
    /// Requests whose `Error:` and `Resend:` lines disagree (ignored).
    pub resends_inconsistent: u64,
    /// Timeouts (ok, probe, handshake).
    pub timeouts: u64,
    /// Out-of-sequence probes sent (Marlin).
    pub probes: u64,
    /// Reply lines that were not UTF-8.
    pub garbage_lines: u64,
    /// Reply lines over `max_reply_line_bytes`.
    pub overlong_lines: u64,
    /// [`LineEvent::ProtocolError`]s.
    pub protocol_errors: u64,
    /// E-stops sent.
    pub estops: u64,
    /// Timed lines whose `ok` was overdue for what they wait for (probed before the
    /// timeout; [`LineHost::send_timed_line`]).
    pub oks_overdue: u64,
    /// RRF: position queries (`M409 K"move.axes"`) sent.
    pub position_probes: u64,
    /// RRF: lines whose `ok` was lost, known to have run by the nozzle's position.
    pub ran_by_position: u64,
    /// RRF: lines the firmware dropped, known by the nozzle's position and sent again
    /// (not repeated).
    pub dropped_by_position: u64,
}

#[derive(Debug)]
struct Sent {
    number: u32,
    tag: Option<u64>,
    wire: Vec<u8>,
    slow: bool,
    runs: Runs,
    /// Where the line leaves the nozzle if it and every line before it ran.
    end: NozzleAt,
}

#[derive(Debug)]
struct Flight {
    number: u32,
    bytes: usize,
    sent_at: Micros,
    slow: bool,
    runs: Runs,
}

#[derive(Debug)]
struct Queued {
    text: String,
    tag: u64,
    runs: Runs,
}

/// How long the firmware takes over a line, as the caller said
/// ([`LineHost::send_timed_line`]): what its `ok` may wait for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Runs {
    /// Not said: only the timeouts of [`LineLinkConfig`] apply.
    Unknown,
    /// A move of this many µs: its `ok` comes once the planner has a free block, after
    /// at most the oldest move it holds.
    Move(u64),
    /// A dwell (`G4`) of this many µs: it waits for every planned move, then dwells.
    Dwell(u64),
    /// Anything else the firmware answers at once (`M163`, `T0`, `G21`).
    Instant,
}

/// The last go-back: repeats of the same request that the lines sent before it can still
/// produce are ignored.
#[derive(Debug, Clone, Copy)]
struct Rewind {
    line: u32,
    stale_budget: u32,
    count: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum HandshakeStep {
    /// RRF `M555 P2`: answer with `ok` (or an empty line, in RRF's own mode).
    MarlinMode,
    /// `N0 M110 N0*125`.
    LineNumbers,
    /// `M115`.
    Identify,
}

#[derive(Debug)]
struct Handshake {
    step: HandshakeStep,
    attempts: u32,
    deadline: Micros,
    send_due: bool,
    failed: bool,
    /// The `M115` answer (`FIRMWARE_NAME:`) arrived.
    identified: bool,
}

/// What the nozzle's position says of a line ([`LineHost::line_by_position`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ByPosition {
    /// It stands where the line ends.
    Ran,
    /// Where the line before it ends.
    Dropped,
    /// The two ends are one place, or not known.
    Unknown,
    /// At neither.
    Elsewhere,
}

/// What a probe asks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ProbeStage {
    /// The last line accepted: Marlin's out-of-sequence `M105`, RRF's `M409 K"inputs"`.
    LastLine,
    /// RRF: where the nozzle stands (`M409 K"move.axes"`).
    Position,
}

#[derive(Debug)]
struct Probe {
    recover: bool,
    attempts: u32,
    deadline: Micros,
    send_due: bool,
    stage: ProbeStage,
    /// RRF recovery: the `lineNumber` read, waiting for the position.
    last_parsed: Option<u32>,
    /// RRF position probe: a reply line other than `ok` came since it was sent, so an
    /// `ok` now belongs to a query, not to the line in flight (RRF answers in order).
    other_line_seen: bool,
    /// `ok`s that answered the queries (RRF answers each with JSON and `ok`).
    query_oks_seen: u32,
    /// Klipper recovery: `GET_POSITION`'s `gcode:` line, waiting for `gcode base:`.
    klipper_gcode_um: Option<[i64; 3]>,
}

const BANNER_LINES: usize = 32;
const ESTOP_BYTES: &[u8] = b"\nM112\n";

/// The host end of the G-code line link. See [`crate::gcode_link`] for the driving loop.
#[derive(Debug)]
pub struct LineHost {
    cfg: LineLinkConfig,
    state: LinkState,
    before_recovery: LinkState,
    reader: LineReader,
    events: VecDeque<LineEvent>,
    stats: LineStats,
    queued: VecDeque<Queued>,
    /// Sent lines, numbers `hist_start..top` without gaps.
    history: VecDeque<Sent>,
    hist_start: u32,
    top: u32,
    next_send: u32,
    /// Every line below was reported accepted.
    accepted_next: u32,
    /// Every line below was stated accepted by the firmware (line errors, numbered `ok`s).
    confirmed_next: u32,
    in_flight: VecDeque<Flight>,
    in_flight_bytes: usize,
    /// `ok`s still to come for resend requests.
    swallow_oks: u32,
    rewind: Option<Rewind>,
    /// The `Last Line:` of a Marlin line error waiting for its `Resend:`.
    pending_error: Option<u32>,
    /// A Marlin line error whose `Last Line:` could not be read (a corrupted reply),
    /// waiting for its `Resend:`.
    pending_unreadable_error: bool,
    /// A firmware error reply (`Error:` that asks for no resend, Klipper's `!!`) waiting
    /// for the `ok` that names the line it refused: then the link stops.
    refused: Option<String>,
    /// An ADVANCED_OK line number ahead of the oldest line in flight, not yet confirmed.
    jump_hint: Option<u32>,
    last_progress: Micros,
    busy_known: bool,
    last_busy: Option<String>,
    timeouts_in_row: u32,
    handshake: Handshake,
    probe: Option<Probe>,
    info: FirmwareInfo,
    free: Option<FreeCounts>,
    max_free_slots: Option<u16>,
    paused: bool,
    priority: Option<Vec<u8>>,
    /// Recovery probes sent again after a timeout, whose answers (`Error:`, `Resend:`,
    /// `ok`) may still come during the handshake that follows.
    late_probe_answers: u32,
    /// The recovery's answer came (Marlin's `Error:` and `Resend:`, RRF's JSON) and the
    /// `ok` that ends it has not: when the read split there, it arrives after
    /// [`LineHost::connect`] and must not count as the handshake's.
    recovery_ok_owed: bool,
    /// The times of the last `planner_moves` timed moves accepted, µs.
    recent_moves_us: VecDeque<u64>,
    /// Where the last line put into the history leaves the nozzle.
    sent_end: NozzleAt,
    /// Where the line before the history's first leaves it.
    end_before_history: NozzleAt,
}

impl LineHost {
    /// An idle host end: call [`LineHost::connect`] to start the handshake, or first
    /// [`LineHost::recover_last_accepted`] after a host restart.
    pub fn new(cfg: LineLinkConfig) -> Self {
        let reader = LineReader::new(cfg.max_reply_line_bytes);
        let info = FirmwareInfo::new(cfg.dialect);
        Self {
            state: LinkState::Idle,
            before_recovery: LinkState::Idle,
            reader,
            events: VecDeque::new(),
            stats: LineStats::default(),
            queued: VecDeque::new(),
            history: VecDeque::new(),
            hist_start: 0,
            top: 0,
            next_send: 0,
            accepted_next: 0,
            confirmed_next: 0,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            swallow_oks: 0,
            rewind: None,
            pending_error: None,
            pending_unreadable_error: false,
            refused: None,
            jump_hint: None,
            last_progress: Micros(0),
            busy_known: false,
            last_busy: None,
            timeouts_in_row: 0,
            handshake: Handshake {
                step: HandshakeStep::Identify,
                attempts: 0,
                deadline: Micros(0),
                send_due: false,
                failed: false,
                identified: false,
            },
            probe: None,
            info,
            free: None,
            max_free_slots: None,
            paused: false,
            priority: None,
            late_probe_answers: 0,
            recovery_ok_owed: false,
            recent_moves_us: VecDeque::new(),
            sent_end: NozzleAt::UNKNOWN,
            end_before_history: NozzleAt::UNKNOWN,
            cfg,
        }
    }

    /// Start (or restart) the handshake; line numbers start again. Returns the tags sent
    /// or queued and never accepted, which are dropped.
    pub fn connect(&mut self, now: Micros) -> Vec<u64> {
        let dropped = self.unacknowledged();
        self.clear_stream();
        self.swallow_oks = u32::from(std::mem::take(&mut self.recovery_ok_owed));
        self.queued.clear();
        self.history.clear();
        self.sent_end = NozzleAt::UNKNOWN;
        self.end_before_history = NozzleAt::UNKNOWN;
        self.reader.clear();
        self.info = FirmwareInfo::new(self.cfg.dialect);
        self.busy_known = false;
        self.free = None;
        self.max_free_slots = None;
        self.timeouts_in_row = 0;
        self.last_progress = now;
        self.handshake = Handshake {
            step: self.first_handshake_step(),
            attempts: 0,
            deadline: now.plus_us(self.cfg.handshake_timeout_us),
            send_due: true,
            failed: false,
            identified: false,
        };
        self.state = LinkState::Connecting;
        dropped
    }

    /// Current state.
    pub fn state(&self) -> LinkState {
        self.state
    }

    /// The configuration.
    pub fn config(&self) -> &LineLinkConfig {
        &self.cfg
    }

    /// What the firmware said in the handshake.
    pub fn firmware_info(&self) -> &FirmwareInfo {
        &self.info
    }

    /// Marlin ADVANCED_OK's last free counts.
    pub fn free_counts(&self) -> Option<FreeCounts> {
        self.free
    }

    /// Counters.
    pub fn stats(&self) -> &LineStats {
        &self.stats
    }

    /// Lines taken but not yet sent.
    pub fn queued_len(&self) -> usize {
        self.queued.len()
    }

    /// The line number the next line taken by [`LineHost::send_line`] goes out with
    /// (while streaming; counted, not sent, on Klipper).
    pub fn next_line_number(&self) -> u32 {
        let queued = u32::try_from(self.queued.len()).unwrap_or(u32::MAX);
        self.top.max(2).saturating_add(queued)
    }

    /// Lines sent and not yet acknowledged.
    pub fn in_flight_len(&self) -> usize {
        self.in_flight.len()
    }

    /// Lines in flight allowed now.
    pub fn window_lines(&self) -> usize {
        match (self.cfg.dialect, self.cfg.window) {
            (Dialect::Rrf, _) => 1,
            (Dialect::Marlin, Window::Lines(n)) => usize::from(n.max(1)),
            (Dialect::Marlin, Window::Auto) => 1,
            (Dialect::Marlin, Window::AdvancedOk) => {
                usize::from(self.max_free_slots.unwrap_or(1).max(1))
            }
            (Dialect::Klipper, Window::Lines(n)) => usize::from(n.clamp(1, 19)),
            (Dialect::Klipper, Window::Auto | Window::AdvancedOk) => 8,
        }
    }

    /// Tags sent or queued and never accepted, in order.
    pub fn unacknowledged(&self) -> Vec<u64> {
        let sent = self
            .history
            .iter()
            .filter(|s| s.number >= self.accepted_next)
            .filter_map(|s| s.tag);
        sent.chain(self.queued.iter().map(|q| q.tag)).collect()
    }

    /// Take a line to send, tagged for [`LineEvent::Accepted`]. `text` is one G-code
    /// command: printable ASCII, no comment, no `*`, `\` or `(`, no line number, not
    /// `M110` (the link owns line numbers) and not `M112` (use [`LineHost::emergency_stop`]).
    pub fn send_line(&mut self, text: &str, tag: u64) -> Result<(), SendError> {
        if !matches!(
            self.state,
            LinkState::Connecting | LinkState::Streaming | LinkState::Probing
        ) {
            return Err(SendError::NotReady(self.state));
        }
        validate_line(text)?;
        let bytes = if self.cfg.dialect.numbers_lines() {
            let number = self.top.max(2) as usize + self.queued.len();
            format!("N{number} {text}*255").len()
        } else {
            text.len()
        };
        if bytes > self.cfg.max_line_bytes {
            return Err(SendError::TooLong {
                bytes,
                max: self.cfg.max_line_bytes,
            });
        }
        self.queued.push_back(Queued {
            text: text.to_string(),
            tag,
            runs: Runs::Unknown,
        });
        Ok(())
    }

    /// [`LineHost::send_line`] for a line the caller knows the firmware's time for:
    /// `runs_us`, a move's time at its feed or a dwell's length (`G4`); `M400` waits
    /// like a dwell of no length (for every move the planner holds); other commands (not
    /// slow ones, `G28`, heating: those keep their timeout) answer at once.
    /// Its `ok` is then due within what it may wait for (Marlin: the longest of the last
    /// `planner_moves` moves, for a free planner block; a dwell: all of them and itself)
    /// times `ok_overdue_factor`, plus `ok_overdue_floor_us`; past that, with every line
    /// in flight timed, the `ok` is taken for lost and the firmware probed
    /// (`docs/firmware.md`, "A lost ok").
    pub fn send_timed_line(&mut self, text: &str, tag: u64, runs_us: u64) -> Result<(), SendError> {
        self.send_line(text, tag)?;
        let runs = match command_word(text).as_deref() {
            Some("G0" | "G1" | "G2" | "G3") => Runs::Move(runs_us),
            Some("G4") => Runs::Dwell(runs_us),
            Some("M400") => Runs::Dwell(0),
            _ if self.is_slow(text) => Runs::Unknown,
            _ => Runs::Instant,
        };
        if let Some(q) = self.queued.back_mut() {
            q.runs = runs;
        }
        Ok(())
    }

    /// Pause (stop sending new lines; resends still go) or resume feeding.
    pub fn set_paused(&mut self, paused: bool) {
        self.paused = paused;
    }

    /// Drop the lines taken but not yet sent (cancel); returns their tags.
    pub fn drop_queued(&mut self) -> Vec<u64> {
        self.queued.drain(..).map(|q| q.tag).collect()
    }

    /// The e-stop: `\nM112\n` goes out on the next `poll_transmit`, ahead of everything;
    /// nothing else is sent afterwards. Returns the tags sent or queued and never accepted.
    /// The leading newline ends any partial line, so `M112` starts a line (RRF's urgent
    /// scan and Marlin's emergency parser look at line starts only).
    pub fn emergency_stop(&mut self) -> Vec<u64> {
        self.stats.estops += 1;
        self.priority = Some(ESTOP_BYTES.to_vec());
        let dropped = self.unacknowledged();
        self.clear_stream();
        self.queued.clear();
        self.state = LinkState::Halted;
        dropped
    }

    /// The caller's port closed or vanished (USB re-enumeration: on native-USB boards, a
    /// firmware restart). Reported as [`LineEvent::Reset`] unless nothing was going on.
    pub fn port_closed(&mut self) {
        // What the firmware still had to say went with the port.
        self.recovery_ok_owed = false;
        match self.state {
            LinkState::Idle | LinkState::Reset => {}
            LinkState::Recovering => {
                self.finish_recovery(LastAccepted::Unknown {
                    reason: "the port closed".into(),
                });
                self.reset("the port closed");
            }
            _ => self.reset("the port closed"),
        }
    }

    /// Ask the firmware for the last line it accepted (after a lost link or a host
    /// restart; before `connect`, which starts numbering again). The answer comes as
    /// [`LineEvent::LastAccepted`]: Marlin through the out-of-sequence probe (exact), RRF
    /// through `M409 K"inputs"` and its nozzle position (exact unless the line ends where
    /// the one before it does), Klipper as where `GET_POSITION` says it stopped after `M400`.
    pub fn recover_last_accepted(&mut self, now: Micros) -> Result<(), RecoverError> {
        match self.state {
            LinkState::Idle
            | LinkState::Lost
            | LinkState::Stopped
            | LinkState::Reset
            | LinkState::Halted => {}
            s => return Err(RecoverError::Busy(s)),
        }
        self.before_recovery = self.state;
        self.swallow_oks = 0;
        self.pending_error = None;
        self.pending_unreadable_error = false;
        self.start_probe(true, now);
        Ok(())
    }

    /// Next event for the caller.
    pub fn poll_event(&mut self) -> Option<LineEvent> {
        self.events.pop_front()
    }

    /// When the caller must call [`LineHost::handle_timeout`] next.
    pub fn next_timeout(&self) -> Option<Micros> {
        match self.state {
            LinkState::Connecting => Some(self.handshake.deadline),
            LinkState::Streaming => self.ok_deadline(),
            LinkState::Probing | LinkState::Recovering => self.probe.as_ref().map(|p| p.deadline),
            _ => None,
        }
    }

    /// Run the timers.
    pub fn handle_timeout(&mut self, now: Micros) {
        match self.state {
            LinkState::Connecting if now >= self.handshake.deadline => {
                self.handshake_timed_out(now)
            }
            LinkState::Streaming if self.ok_deadline().is_some_and(|d| now >= d) => {
                if self.ok_overdue_at().is_some_and(|d| now >= d) {
                    self.stats.oks_overdue += 1;
                }
                self.on_ok_timeout(now);
            }
            LinkState::Probing | LinkState::Recovering
                if self.probe.as_ref().is_some_and(|p| now >= p.deadline) =>
            {
                self.on_probe_timeout(now);
            }
            _ => {}
        }
    }

    /// Next bytes to write to the port: the e-stop, the handshake, a probe, or a line.
    pub fn poll_transmit(&mut self, now: Micros) -> Option<Vec<u8>> {
        self.handle_timeout(now);
        let out = match self.priority.take() {
            Some(b) => Some(b),
            None => match self.state {
                LinkState::Connecting => self.handshake_transmit(),
                LinkState::Streaming => self.take_line(now),
                LinkState::Probing | LinkState::Recovering => self.probe_transmit(),
                _ => None,
            },
        };
        if let Some(b) = &out {
            self.stats.bytes_sent += b.len() as u64;
        }
        out
    }

    /// Feed bytes read from the port.
    pub fn handle_bytes(&mut self, bytes: &[u8], now: Micros) {
        self.stats.bytes_received += bytes.len() as u64;
        let mut items = Vec::new();
        self.reader.push(bytes, &mut items);
        for item in items {
            match item {
                ReadItem::Line(raw) => match String::from_utf8(raw) {
                    Ok(line) => self.on_line(&line, now),
                    Err(e) => {
                        self.stats.garbage_lines += 1;
                        self.note_other_reply();
                        let raw = e.into_bytes();
                        let text = String::from_utf8_lossy(&raw);
                        self.protocol_error(format!(
                            "reply line of {} bytes is not UTF-8, ignored: {:?}",
                            raw.len(),
                            truncate(&text, 60)
                        ));
                    }
                },
                ReadItem::OverlongStarted => {
                    self.stats.overlong_lines += 1;
                    self.note_other_reply();
                    self.protocol_error(format!(
                        "reply line longer than {} bytes: dropped up to its end",
                        self.cfg.max_reply_line_bytes
                    ));
                }
                ReadItem::OverlongEnded(_) => {}
            }
        }
    }

    fn on_line(&mut self, line: &str, now: Micros) {
        let reply = reply::parse(line);
        match self.state {
            LinkState::Connecting => self.on_line_handshake(line, reply, now),
            LinkState::Probing if self.cfg.dialect == Dialect::Rrf => {
                self.on_line_position_probe(line, reply, now)
            }
            LinkState::Streaming | LinkState::Probing => self.on_line_streaming(line, reply, now),
            LinkState::Recovering => self.on_line_recovering(line, reply, now),
            LinkState::Idle
            | LinkState::Lost
            | LinkState::Stopped
            | LinkState::Reset
            | LinkState::Halted => self.on_line_passive(line, reply),
        }
    }

    // ---- handshake ----------------------------------------------------------------

    fn first_handshake_step(&self) -> HandshakeStep {
        match self.cfg.dialect {
            Dialect::Rrf if self.cfg.rrf_set_marlin_mode => HandshakeStep::MarlinMode,
            Dialect::Marlin | Dialect::Rrf => HandshakeStep::LineNumbers,
            Dialect::Klipper => HandshakeStep::Identify,
        }
    }

    fn handshake_transmit(&mut self) -> Option<Vec<u8>> {
        if !self.handshake.send_due {
            return None;
        }
        self.handshake.send_due = false;
        Some(match self.handshake.step {
            HandshakeStep::MarlinMode => b"M555 P2\n".to_vec(),
            HandshakeStep::LineNumbers => numbered_line(0, "M110 N0"),
            HandshakeStep::Identify if self.cfg.dialect.numbers_lines() => numbered_line(1, "M115"),
            HandshakeStep::Identify => b"M115\n".to_vec(),
        })
    }

    fn restart_handshake(&mut self, from_first: bool, now: Micros) {
        self.handshake.step = if from_first || !self.cfg.dialect.numbers_lines() {
            self.first_handshake_step()
        } else {
            HandshakeStep::LineNumbers
        };
        self.handshake.send_due = true;
        self.handshake.failed = false;
        self.handshake.identified = false;
        self.handshake.deadline = now.plus_us(self.cfg.handshake_timeout_us);
    }

    fn advance_handshake(&mut self, now: Micros) {
        let next = match self.handshake.step {
            HandshakeStep::MarlinMode => Some(HandshakeStep::LineNumbers),
            HandshakeStep::LineNumbers => Some(HandshakeStep::Identify),
            HandshakeStep::Identify => None,
        };
        match next {
            Some(step) => {
                self.handshake.step = step;
                self.handshake.send_due = true;
                self.handshake.deadline = now.plus_us(self.cfg.handshake_timeout_us);
            }
            None => self.connected(now),
        }
    }

    fn handshake_timed_out(&mut self, now: Micros) {
        self.stats.timeouts += 1;
        self.handshake.attempts += 1;
        if self.handshake.attempts >= self.cfg.handshake_attempts {
            self.link_lost(now);
        } else {
            self.swallow_oks = 0;
            self.restart_handshake(true, now);
        }
    }

    fn connected(&mut self, now: Micros) {
        self.late_probe_answers = 0;
        let first = if self.cfg.dialect.numbers_lines() {
            2
        } else {
            1
        };
        self.hist_start = first;
        self.top = first;
        self.next_send = first;
        self.accepted_next = first;
        self.confirmed_next = first;
        self.last_progress = now;
        self.timeouts_in_row = 0;
        self.state = LinkState::Streaming;
        self.events
            .push_back(LineEvent::Connected(self.info.clone()));
    }

    fn on_line_handshake(&mut self, line: &str, reply: Reply<'_>, now: Micros) {
        match reply {
            Reply::Ok(ok) => self.on_handshake_ok(ok, now),
            Reply::Empty if self.handshake.step == HandshakeStep::MarlinMode => {
                self.advance_handshake(now)
            }
            Reply::Resend(_) if self.late_probe_answers > 0 => {
                // The answer to a recovery probe sent again (its `ok` follows), not to a
                // line of this handshake: sending `M110` again behind `M115` would set
                // the firmware's line number back under the stream.
                self.late_probe_answers -= 1;
                self.swallow_oks += 1;
            }
            Reply::Resend(_) => {
                // Its `ok` follows. Either a line of this attempt was refused, or a
                // line sent before the firmware restarted was (after a reset Marlin
                // refuses each line still on the wire, `Last Line: 0`, `Resend: 1`,
                // the same words as a corrupted handshake line gets). Not sent again
                // at once: an `M110 N0` sent again while the first one's `ok` is still
                // to come is taken as answered by it, and runs behind `M115`, setting
                // the firmware's line number back under the stream. The line's own
                // `ok` comes within the ok timeout (or the handshake's, the shorter)
                // if it was not the one refused; if not, the handshake starts again, an attempt of its own
                // (a firmware that refuses every line draws no handshakes at line
                // speed).
                self.swallow_oks += 1;
                let due = now.plus_us(self.cfg.ok_timeout_us);
                if due < self.handshake.deadline {
                    self.handshake.deadline = due;
                }
            }
            Reply::Error {
                last_line: Some(_), ..
            } => {}
            Reply::Error { text, .. } | Reply::KlipperError(text) => {
                self.handshake.failed = true;
                self.events
                    .push_back(LineEvent::Error { text: text.into() });
            }
            Reply::Start => {
                self.note_banner(line);
                self.restart_handshake(true, now);
            }
            Reply::ResetReason(_) => self.note_banner(line),
            Reply::KlipperState(state) => {
                self.note_banner(line);
                if state == "Ready" {
                    self.restart_handshake(true, now);
                } else {
                    self.handshake.failed = true;
                }
            }
            Reply::Busy(_) => {
                self.handshake.deadline = now.plus_us(self.cfg.handshake_timeout_us);
            }
            Reply::Action(text) => self
                .events
                .push_back(LineEvent::Action { text: text.into() }),
            Reply::BadResend(text) => {
                self.protocol_error(format!("malformed resend request {text:?}"))
            }
            Reply::Empty | Reply::Wait => {}
            Reply::Echo(text) => {
                if !self.note_m115(line.trim()) {
                    self.note_banner(line);
                    self.events.push_back(LineEvent::Echo { text: text.into() });
                }
            }
            Reply::Json(text) => self.events.push_back(LineEvent::Echo { text: text.into() }),
        }
    }

    fn on_handshake_ok(&mut self, ok: OkReply<'_>, now: Micros) {
        self.stats.oks += 1;
        if self.swallow_oks > 0 {
            self.swallow_oks -= 1;
            self.stats.oks_swallowed += 1;
            return;
        }
        if self.handshake.failed {
            return; // wait for the deadline, then try again
        }
        if let (Some(_), Some(b)) = (ok.p, ok.b) {
            self.info.advanced_ok = true;
            self.info.command_slots = Some(b.saturating_add(1));
        }
        self.note_free_counts(&ok);
        self.note_m115(ok.rest);
        if self.handshake.step == HandshakeStep::Identify && !self.handshake.identified {
            // An `ok` left over from an earlier handshake line: M115's comes after its
            // FIRMWARE_NAME line (on the `ok` line itself on Klipper).
            return;
        }
        self.advance_handshake(now);
    }

    /// Takes `FIRMWARE_NAME:` and `Cap:` lines; false for other lines.
    fn note_m115(&mut self, line: &str) -> bool {
        if let Some(cap) = line.strip_prefix("Cap:") {
            let (name, value) = cap.rsplit_once(':').unwrap_or((cap, "0"));
            let on = value.trim() == "1";
            if name == "BUSY_PROTOCOL" && on {
                self.busy_known = true;
            }
            self.info.capabilities.push((name.to_string(), on));
            return true;
        }
        if !line.contains("FIRMWARE_NAME:") {
            return false;
        }
        for (key, value) in reply::m115_fields(line) {
            match key.as_str() {
                "FIRMWARE_NAME" => self.info.firmware_name = Some(value),
                "FIRMWARE_VERSION" => self.info.firmware_version = Some(value),
                _ => {}
            }
        }
        self.info.identity = Some(line.to_string());
        self.handshake.identified = true;
        true
    }

    fn note_banner(&mut self, line: &str) {
        if self.info.banner.len() < BANNER_LINES {
            self.info.banner.push(line.trim().to_string());
        }
    }

    // ---- streaming ------------------------------------------------------------------

    fn history_cap(&self) -> usize {
        self.cfg.history_lines.max(self.window_lines() + 1)
    }

    fn window_bytes(&self) -> usize {
        self.cfg
            .rx_buffer_bytes
            .saturating_sub(self.cfg.estop_reserve_bytes)
            .min(self.cfg.max_bytes_in_flight)
    }

    fn window_open(&self, bytes: usize) -> bool {
        self.in_flight.is_empty()
            || (self.in_flight.len() < self.window_lines()
                && self.in_flight_bytes + bytes <= self.window_bytes())
    }

    fn sent(&self, number: u32) -> Option<&Sent> {
        let i = number.checked_sub(self.hist_start)?;
        self.history.get(i as usize)
    }

    fn is_slow(&self, text: &str) -> bool {
        command_word(text).is_some_and(|w| self.cfg.slow_commands.contains(&w))
    }

    fn push_flight(&mut self, number: u32, bytes: usize, (slow, runs): (bool, Runs), now: Micros) {
        if self.in_flight.is_empty() {
            self.last_progress = now;
        }
        self.in_flight.push_back(Flight {
            number,
            bytes,
            sent_at: now,
            slow,
            runs,
        });
        self.in_flight_bytes += bytes;
    }

    /// The next line to write: a line to send again, else a new one, if the window has
    /// room.
    fn take_line(&mut self, now: Micros) -> Option<Vec<u8>> {
        if self.next_send < self.top {
            let number = self.next_send;
            let Some(sent) = self.sent(number) else {
                self.stop(format!("line {number} to send again is no longer kept"));
                return None;
            };
            let (wire, slow, runs) = (sent.wire.clone(), sent.slow, sent.runs);
            if !self.window_open(wire.len()) {
                return None;
            }
            self.push_flight(number, wire.len(), (slow, runs), now);
            self.next_send += 1;
            self.stats.lines_resent += 1;
            return Some(wire);
        }
        if self.paused {
            return None;
        }
        if self.queued.is_empty() {
            return None;
        }
        if self.top >= PROBE_LINE_NUMBER - 1 {
            self.stop("line numbers used up: connect again".into());
            return None;
        }
        self.trim_history();
        if self.history.len() >= self.history_cap() {
            return None;
        }
        let text = &self.queued.front()?.text;
        let wire = if self.cfg.dialect.numbers_lines() {
            numbered_line(self.top, text)
        } else {
            format!("{text}\n").into_bytes()
        };
        if !self.window_open(wire.len()) {
            return None;
        }
        let q = self.queued.pop_front()?;
        let slow = self.is_slow(&q.text);
        let number = self.top;
        // Only RRF is asked where its nozzle stands while lines stream.
        if self.cfg.dialect == Dialect::Rrf {
            self.sent_end = self.sent_end.after(&q.text);
        }
        self.history.push_back(Sent {
            number,
            tag: Some(q.tag),
            wire: wire.clone(),
            slow,
            runs: q.runs,
            end: self.sent_end,
        });
        self.push_flight(number, wire.len(), (slow, q.runs), now);
        self.top += 1;
        self.next_send = self.top;
        self.stats.lines_sent += 1;
        self.stats.line_bytes_sent += wire.len() as u64;
        Some(wire)
    }

    fn trim_history(&mut self) {
        while self.history.len() > self.history_cap().saturating_sub(1)
            && self
                .history
                .front()
                .is_some_and(|s| s.number < self.accepted_next)
        {
            if let Some(s) = self.history.pop_front() {
                self.end_before_history = s.end;
            }
            self.hist_start += 1;
        }
    }

    fn current_timeout_us(&self) -> u64 {
        if self.in_flight.iter().any(|f| f.slow) {
            self.cfg.slow_command_timeout_us
        } else if self.busy_known {
            self.cfg.busy_timeout_us
        } else {
            self.cfg.ok_timeout_us
        }
    }

    fn ok_deadline(&self) -> Option<Micros> {
        if self.in_flight.is_empty() {
            return None;
        }
        let timeout = self.last_progress.plus_us(self.current_timeout_us());
        Some(self.ok_overdue_at().map_or(timeout, |at| at.min(timeout)))
    }

    /// When the oldest line's `ok` is overdue for what it may wait for, if every line in
    /// flight is timed ([`LineHost::send_timed_line`]) and a probe can say where the
    /// firmware is (Marlin, whose probe answers exactly, not while it keeps a handler
    /// busy with `busy:` keepalives; RRF, whose nozzle position says it).
    fn ok_overdue_at(&self) -> Option<Micros> {
        if self.cfg.dialect == Dialect::Klipper
            || self.last_busy.is_some()
            || self.in_flight.iter().any(|f| f.runs == Runs::Unknown)
        {
            return None;
        }
        let oldest = self.in_flight.front()?;
        let planned = self.recent_moves_us.iter();
        let waits_us = match oldest.runs {
            Runs::Move(_) => planned.max().copied().unwrap_or(0),
            Runs::Dwell(own) => planned.sum::<u64>().saturating_add(own),
            Runs::Instant | Runs::Unknown => 0,
        };
        let due_us = waits_us.saturating_mul(u64::from(self.cfg.ok_overdue_factor));
        Some(
            oldest
                .sent_at
                .plus_us(due_us.saturating_add(self.cfg.ok_overdue_floor_us)),
        )
    }

    fn on_line_streaming(&mut self, line: &str, reply: Reply<'_>, now: Micros) {
        if std::mem::take(&mut self.pending_unreadable_error) {
            if let Reply::Resend(j) = reply {
                self.on_resend(j, None, now);
                return;
            }
            self.on_unreadable_resend(line, now);
        }
        if let Some(last_line) = self.pending_error.take() {
            if let Reply::Resend(j) = reply {
                self.on_resend(j, Some(last_line), now);
                return;
            }
            // The `Resend:` line was lost: the error names the last line accepted.
            self.on_resend(last_line.saturating_add(1), None, now);
        }
        match reply {
            Reply::Ok(ok) => self.on_ok(ok, now),
            Reply::Resend(j) => self.on_resend(j, None, now),
            Reply::Error {
                last_line: Some(l), ..
            } if self.cfg.dialect != Dialect::Klipper => self.pending_error = Some(l),
            Reply::Error { text, .. }
                if self.cfg.dialect == Dialect::Marlin && text.contains("Last Line") =>
            {
                self.pending_unreadable_error = true
            }
            Reply::Error { text, .. } => self.on_firmware_error(text),
            Reply::KlipperError(text) => self.on_klipper_error(text),
            Reply::KlipperState(state) => self.on_klipper_state(state, line),
            Reply::Busy(text) => self.on_busy(text, now),
            Reply::Wait => self.on_wait(now),
            Reply::Start | Reply::ResetReason(_) if self.cfg.dialect == Dialect::Marlin => {
                self.reset(line.trim())
            }
            Reply::Action(text) => self
                .events
                .push_back(LineEvent::Action { text: text.into() }),
            Reply::BadResend(text) if self.cfg.dialect == Dialect::Marlin => {
                self.on_unreadable_resend(text, now)
            }
            Reply::BadResend(text) => {
                self.protocol_error(format!("malformed resend request {text:?}"))
            }
            Reply::Empty => {}
            Reply::Echo(text) => self.events.push_back(LineEvent::Echo { text: text.into() }),
            Reply::Json(_) | Reply::Start | Reply::ResetReason(_) => {
                self.events.push_back(LineEvent::Echo {
                    text: line.trim().into(),
                })
            }
        }
    }

    fn note_free_counts(&mut self, ok: &OkReply<'_>) {
        if let (Some(p), Some(b)) = (ok.p, ok.b) {
            let slots = b.saturating_add(1);
            self.free = Some(FreeCounts {
                planner_blocks: p,
                command_slots: slots,
            });
            self.max_free_slots = Some(self.max_free_slots.map_or(slots, |m| m.max(slots)));
            self.info.advanced_ok = true;
        }
    }

    fn on_ok(&mut self, ok: OkReply<'_>, now: Micros) {
        self.stats.oks += 1;
        self.last_progress = now;
        self.last_busy = None;
        if self.swallow_oks > 0 {
            self.swallow_oks -= 1;
            self.stats.oks_swallowed += 1;
            // An error before a swallowed `ok` was the answer to edod's own probe.
            self.refused = None;
            return;
        }
        self.note_free_counts(&ok);
        // An error before an `ok` with none of edod's lines in flight refused nothing
        // edod sent.
        if let Some(reply) = self.refused.take().filter(|_| !self.in_flight.is_empty()) {
            self.timeouts_in_row = 0;
            self.stop_refused(reply);
            return;
        }
        let Some(front) = self.in_flight.front().map(|f| f.number) else {
            self.stats.oks_unexpected += 1;
            self.protocol_error("`ok` with no line in flight, ignored".into());
            return;
        };
        if ok.n.is_none()
            && ok.p.is_some()
            && ok.b.is_some()
            && ok.rest.split_ascii_whitespace().count() == 2
            && self.cfg.dialect.numbers_lines()
        {
            // ADVANCED_OK echoes N for every numbered line: this one ran unnumbered.
            self.stats.oks_unexpected += 1;
            self.protocol_error(
                "the firmware ran a line without a line number (after draining its buffer on \
                 an error, the tail of a line that was arriving); its `ok` is ignored"
                    .into(),
            );
            return;
        }
        self.timeouts_in_row = 0;
        self.reconcile_ok_number(ok.n, front);
    }

    /// Acknowledge lines for an `ok`. Its ADVANCED_OK number is trusted when it is the
    /// oldest line in flight; one further ahead (an `ok` was lost, or a digit corrupted)
    /// only once the next `ok` follows it, else the `ok` counts for the oldest line.
    fn reconcile_ok_number(&mut self, n: Option<u32>, front: u32) {
        match n {
            Some(n) if n == front => {
                self.acknowledge_through(n);
                self.confirm(n);
                self.jump_hint = None;
            }
            Some(n) if n > front && n < self.next_send => {
                if self.jump_hint == Some(n - 1) {
                    self.acknowledge_through(n);
                    self.confirm(n);
                    self.jump_hint = None;
                } else {
                    self.acknowledge_front();
                    self.jump_hint = Some(n);
                }
            }
            Some(_) => {
                self.jump_hint = None;
                self.acknowledge_front();
            }
            None => self.acknowledge_front(),
        }
    }

    fn confirm(&mut self, number: u32) {
        self.confirmed_next = self.confirmed_next.max(number + 1);
    }

    fn acknowledge_front(&mut self) {
        if let Some(f) = self.in_flight.pop_front() {
            self.in_flight_bytes -= f.bytes;
            self.report_accepted_through(f.number);
        }
    }

    fn acknowledge_through(&mut self, number: u32) {
        while let Some(f) = self.in_flight.front() {
            if f.number > number {
                break;
            }
            self.in_flight_bytes -= f.bytes;
            self.in_flight.pop_front();
        }
        self.report_accepted_through(number);
    }

    fn report_accepted_through(&mut self, number: u32) {
        while self.accepted_next <= number && self.accepted_next < self.top {
            let n = self.accepted_next;
            if let Some(Runs::Move(us)) = self.sent(n).map(|s| s.runs) {
                // What the planner may hold: the last `planner_moves` moves accepted.
                self.recent_moves_us.push_back(us);
                while self.recent_moves_us.len() > self.cfg.planner_moves {
                    self.recent_moves_us.pop_front();
                }
            }
            if let Some(tag) = self.sent(n).and_then(|s| s.tag) {
                self.events.push_back(LineEvent::Accepted {
                    tag,
                    line_number: n,
                });
            }
            self.accepted_next += 1;
        }
    }

    /// A resend request for line `j`, with the `Last Line:` of its `Error:` line if that
    /// arrived.
    fn on_resend(&mut self, j: u32, error_last_line: Option<u32>, now: Micros) {
        self.stats.resend_requests += 1;
        if self.cfg.dialect == Dialect::Klipper {
            self.protocol_error(format!(
                "Klipper does not request resends: `Resend: {j}` ignored"
            ));
            return;
        }
        self.swallow_oks += 1; // Marlin follows every resend request with an `ok`
        self.last_progress = now;
        if j == 0 {
            self.protocol_error("resend request for line 0, ignored".into());
            return;
        }
        if let Some(l) = error_last_line {
            if l.checked_add(1) != Some(j) {
                self.stats.resends_inconsistent += 1;
                self.protocol_error(format!(
                    "the error names last line {l} but the resend request asks for {j}: both ignored"
                ));
                return;
            }
        }
        if self.state == LinkState::Probing {
            self.on_probe_answer(j - 1, error_last_line.is_some(), now);
        } else {
            self.go_back_to(j);
        }
    }

    /// Go back to line `j` as the firmware asks, unless the request is stale, a repeat of
    /// one being served, or for a line never sent or no longer kept (the job stops).
    fn go_back_to(&mut self, j: u32) {
        if j > self.top {
            return self.stop(format!(
                "the firmware asks for line {j}, which was never sent (last sent: {})",
                self.top.saturating_sub(1)
            ));
        }
        if j < self.confirmed_next {
            self.stats.resends_stale += 1;
            return;
        }
        if j < self.hist_start {
            return self.stop(format!(
                "the firmware asks for line {j}, no longer kept (oldest kept: {})",
                self.hist_start
            ));
        }
        if let Some(r) = self.rewind.as_mut() {
            if r.line == j && r.stale_budget > 0 {
                r.stale_budget -= 1;
                self.stats.resends_duplicate += 1;
                return;
            }
        }
        if j < self.accepted_next {
            // An `ok` without a line number can be miscounted by at most the lines that
            // were in flight; further back, the firmware's counter went back (or the
            // number is garbage): replaying lines it acknowledged would run them twice.
            let window = u32::try_from(self.window_lines()).unwrap_or(u32::MAX);
            if self.accepted_next - j > window {
                return self.stop(format!(
                    "the firmware asks for line {j}, acknowledged before its last \
                     acknowledged line {}: not sent again (it would run twice)",
                    self.accepted_next - 1
                ));
            }
            self.protocol_error(format!(
                "the firmware asks again for line {j}, reported accepted from an `ok` without a \
                 line number (an `ok` was miscounted); sending it again"
            ));
        }
        self.report_accepted_through(j - 1);
        self.confirmed_next = j;
        let count = match self.rewind {
            Some(r) if r.line == j => r.count + 1,
            _ => 1,
        };
        if count > self.cfg.max_consecutive_resends {
            return self.stop(format!(
                "the firmware asked for line {j} {count} times in a row"
            ));
        }
        // Each line in flight answers at most once; the one refused has answered.
        let removed = self.drop_flights_from(j);
        self.rewind = Some(Rewind {
            line: j,
            stale_budget: removed.saturating_sub(1),
            count,
        });
        self.next_send = j;
        self.jump_hint = None;
    }

    /// Forget lines in flight numbered `j` or above (drained or refused by the firmware:
    /// no `ok` comes for them); returns how many.
    fn drop_flights_from(&mut self, j: u32) -> u32 {
        let mut removed = 0;
        while self.in_flight.back().is_some_and(|f| f.number >= j) {
            if let Some(f) = self.in_flight.pop_back() {
                self.in_flight_bytes -= f.bytes;
                removed += 1;
            }
        }
        removed
    }

    /// Marlin refused a line but which one cannot be read (a corrupted `Resend:` or
    /// `Last Line:`): the `ok` that follows belongs to the request, not to the line in
    /// flight, so it is not counted; the probe asks the firmware for its last line.
    fn on_unreadable_resend(&mut self, text: &str, now: Micros) {
        self.stats.resend_requests += 1;
        self.swallow_oks += 1;
        self.protocol_error(format!(
            "resend request whose line cannot be read ({:?}): its `ok` is not counted; \
             asking the firmware for the last line it accepted",
            truncate(text.trim(), 60)
        ));
        if self.state == LinkState::Streaming && !self.in_flight.is_empty() {
            self.start_probe(false, now);
        }
    }

    fn on_firmware_error(&mut self, text: &str) {
        let lower = text.to_ascii_lowercase();
        if lower.contains("halted") || lower.contains("kill") || lower.contains("m999") {
            self.halt(text);
        } else if ["checksum", "line number", "last line"]
            .iter()
            .any(|w| lower.contains(w))
        {
            // A line error whose resend half was garbled: the resend request (or the
            // `ok` timeout's probe) that follows is what counts, not a refusal.
            self.events
                .push_back(LineEvent::Error { text: text.into() });
        } else {
            self.note_refusal(text, format!("Error:{text}"));
        }
    }

    /// Klipper's `!!`: its shutdown (`M112`, an MCU error) halts; any other is a refusal
    /// of the line its `ok` names.
    fn on_klipper_error(&mut self, text: &str) {
        if text.to_ascii_lowercase().contains("shutdown") {
            self.halt(text);
        } else {
            self.note_refusal(text, format!("!! {text}"));
        }
    }

    /// A line was refused: the reply precedes the `ok` that names the line (Klipper,
    /// Marlin and RepRapFirmware all answer an error, then `ok`). The first refusal
    /// stands; the link stops at that `ok` ([`LineHost::stop_refused`]).
    fn note_refusal(&mut self, text: &str, reply: String) {
        self.events
            .push_back(LineEvent::Error { text: text.into() });
        if self.refused.is_none() {
            self.refused = Some(reply);
        }
    }

    /// The `ok` for a refused line came: that line was taken (and refused), nothing
    /// more goes out and the job's owner hears which line and why.
    fn stop_refused(&mut self, reply: String) {
        let front = self.in_flight.front().map_or(0, |f| f.number);
        let text = self.sent(front).map_or_else(String::new, |s| {
            String::from_utf8_lossy(&s.wire).trim().to_string()
        });
        self.acknowledge_front();
        self.stop(format!(
            "the firmware refused line {front} `{text}`: {reply}"
        ));
    }

    fn on_klipper_state(&mut self, state: &str, line: &str) {
        match state {
            "Ready" => self.reset(line.trim()),
            "Shutdown" | "Disconnect" => self.halt(line.trim()),
            _ => self.events.push_back(LineEvent::Echo {
                text: line.trim().into(),
            }),
        }
    }

    fn on_busy(&mut self, text: &str, now: Micros) {
        self.last_progress = now;
        self.busy_known = true;
        if let Some(p) = self.probe.as_mut() {
            p.deadline = now.plus_us(self.cfg.busy_timeout_us);
        }
        if self.last_busy.as_deref() != Some(text) {
            self.last_busy = Some(text.to_string());
            self.events.push_back(LineEvent::Busy { text: text.into() });
        }
    }

    /// Marlin `NO_TIMEOUTS`: the firmware's queue is empty and no byte is coming. With lines
    /// in flight long enough, they or their `ok`s were lost: probe now.
    fn on_wait(&mut self, now: Micros) {
        let grace = self.cfg.wait_grace_us;
        if self.cfg.dialect == Dialect::Marlin
            && self.state == LinkState::Streaming
            && !self.in_flight.is_empty()
            && self.in_flight.iter().all(|f| now.since(f.sent_at) >= grace)
        {
            self.on_ok_timeout(now);
        }
    }

    fn on_ok_timeout(&mut self, now: Micros) {
        self.stats.timeouts += 1;
        self.timeouts_in_row += 1;
        self.swallow_oks = 0;
        self.pending_error = None;
        self.pending_unreadable_error = false;
        self.refused = None;
        self.jump_hint = None;
        if self.timeouts_in_row > self.cfg.max_timeouts {
            return self.link_lost(now);
        }
        match self.cfg.dialect {
            Dialect::Marlin | Dialect::Rrf => self.start_probe(false, now),
            Dialect::Klipper => self.last_progress = now,
        }
    }

    /// RRF: send the line in flight again (it was dropped for a bad checksum, or its `ok`
    /// was lost: the position could not tell which).
    fn repeat_oldest(&mut self, now: Micros) {
        let Some(number) = self.in_flight.front().map(|f| f.number) else {
            return;
        };
        if let Some(tag) = self.sent(number).and_then(|s| s.tag) {
            self.events.push_back(LineEvent::MaybeRepeated {
                tag,
                line_number: number,
            });
        }
        self.stats.lines_repeated += 1;
        self.drop_flights_from(number);
        self.next_send = number;
        self.last_progress = now;
    }

    // ---- probe and recovery ---------------------------------------------------------

    /// How long a probe waits for its answer: a recovery (after a lost port or a host
    /// restart) as long as a handshake attempt at least. Nothing is streamed meanwhile,
    /// and a recovery given up resumes from the checkpoint and repeats moves: a loaded
    /// host or a firmware finishing a long move must not cost that.
    fn probe_timeout_us(&self, recover: bool) -> u64 {
        let timeout = self.current_timeout_us();
        if recover && self.cfg.dialect == Dialect::Klipper {
            // `M400` waits for every move Klipper holds; asked once, not again.
            timeout.saturating_mul(u64::from(self.cfg.max_timeouts.max(1)))
        } else if recover {
            timeout.max(self.cfg.handshake_timeout_us)
        } else {
            timeout
        }
    }

    fn start_probe(&mut self, recover: bool, now: Micros) {
        let timeout = self.probe_timeout_us(recover);
        let stage = if self.cfg.dialect == Dialect::Rrf && !recover {
            ProbeStage::Position
        } else {
            ProbeStage::LastLine
        };
        self.probe = Some(Probe {
            recover,
            attempts: 1,
            deadline: now.plus_us(timeout),
            send_due: true,
            stage,
            last_parsed: None,
            other_line_seen: false,
            query_oks_seen: 0,
            klipper_gcode_um: None,
        });
        self.state = if recover {
            LinkState::Recovering
        } else {
            LinkState::Probing
        };
    }

    fn probe_transmit(&mut self) -> Option<Vec<u8>> {
        let p = self.probe.as_mut()?;
        if !p.send_due {
            return None;
        }
        p.send_due = false;
        self.stats.probes += 1;
        if p.stage == ProbeStage::Position {
            // Numbered and checksummed, so that RRF drops a corrupted query rather than
            // run what the corruption made of it; RRF only records the number (the line
            // in flight's, or after `lineNumber` was read, the next).
            let number = match p.last_parsed {
                Some(n) => n.saturating_add(1),
                None => self.in_flight.front().map_or(self.top, |f| f.number),
            };
            self.stats.position_probes += 1;
            let mut bytes = b"\n".to_vec();
            bytes.extend_from_slice(&numbered_line(number, RRF_POSITION_QUERY));
            return Some(bytes);
        }
        if p.recover && self.cfg.dialect == Dialect::Rrf {
            return Some(b"\nM409 K\"inputs\"\n".to_vec());
        }
        if self.cfg.dialect == Dialect::Klipper {
            // Every move Klipper holds runs first; then where it stopped.
            return Some(format!("\nM400\n{KLIPPER_POSITION_QUERY}\n").into_bytes());
        }
        // The newline ends any partial line the firmware holds; an empty line is skipped.
        let mut bytes = b"\n".to_vec();
        bytes.extend_from_slice(&numbered_line(PROBE_LINE_NUMBER, "M105"));
        Some(bytes)
    }

    fn on_probe_timeout(&mut self, now: Micros) {
        self.stats.timeouts += 1;
        let Some(recover) = self.probe.as_ref().map(|p| p.recover) else {
            return;
        };
        let timeout = self.probe_timeout_us(recover);
        let Some(p) = self.probe.as_mut() else {
            return;
        };
        p.attempts += 1;
        let give_up = p.attempts > self.cfg.max_timeouts
            || (p.recover && self.cfg.dialect == Dialect::Klipper);
        if !give_up {
            p.send_due = true;
            p.deadline = now.plus_us(timeout);
        }
        let (recover, last_parsed) = (p.recover, p.last_parsed);
        if recover {
            if give_up {
                match last_parsed {
                    // RRF named its line but not the nozzle's position: not exact.
                    Some(n) => {
                        self.recovery_answer(n, false, None);
                        self.recovery_ok_owed = false;
                    }
                    None => self.finish_recovery(LastAccepted::Unknown {
                        reason: "no answer to the last-line query".into(),
                    }),
                }
            }
        } else {
            self.timeouts_in_row += 1;
            self.swallow_oks = 0;
            if give_up || self.timeouts_in_row > self.cfg.max_timeouts {
                self.link_lost(now);
            }
        }
    }

    /// The answer to the timeout probe: the firmware's last accepted line. A lone
    /// `Error:` or `Resend:` line that would go back is not trusted (a corrupted digit);
    /// the probe is sent again on its timeout.
    fn on_probe_answer(&mut self, last: u32, paired: bool, now: Micros) {
        if last + 1 < self.confirmed_next {
            if !paired {
                self.stats.resends_stale += 1;
                return;
            }
            return self.reset(&format!(
                "the firmware's last line went back from {} to {last} without a start banner",
                self.confirmed_next - 1
            ));
        }
        if last >= self.top {
            return self.stop(format!(
                "the firmware accepted line {last}, which was never sent (last sent: {})",
                self.top.saturating_sub(1)
            ));
        }
        self.report_accepted_through(last);
        self.confirm(last);
        let removed = self.drop_flights_from(0);
        self.next_send = last + 1;
        // The probe's own answer may still come if an earlier error was the answer.
        self.rewind = Some(Rewind {
            line: last + 1,
            stale_budget: removed + 1,
            count: 1,
        });
        self.probe = None;
        self.state = LinkState::Streaming;
        self.last_progress = now;
    }

    /// RRF while the position query is out. RRF answers in order: an `ok` before any
    /// other reply line is the line in flight's (late, not lost); the JSON says where the
    /// nozzle stands; the `ok`s after it are the queries'.
    fn on_line_position_probe(&mut self, line: &str, reply: Reply<'_>, now: Micros) {
        let Some(p) = self.probe.as_mut() else {
            return self.on_line_streaming(line, reply, now);
        };
        match reply {
            Reply::Ok(ok) if !p.other_line_seen && !self.in_flight.is_empty() => {
                self.on_ok(ok, now)
            }
            Reply::Ok(_) => {
                p.query_oks_seen += 1;
                self.stats.oks += 1;
                self.stats.oks_swallowed += 1;
            }
            Reply::Json(json) => {
                p.other_line_seen = true;
                match rrf_user_position(json) {
                    Ok(Some(at)) => self.on_position(at, now),
                    // A late answer to another query.
                    Ok(None) => {}
                    Err(what) => self.protocol_error(format!("M409 answer not understood: {what}")),
                }
            }
            Reply::Empty => {}
            _ => {
                // An answer to the query (a corrupted one refused), or the line's own
                // late refusal: which cannot be told, and the position decides anyway.
                p.other_line_seen = true;
                self.events.push_back(LineEvent::Echo {
                    text: line.trim().into(),
                });
            }
        }
    }

    /// A reply line that could not be read: during RRF's position query, the `ok`s after
    /// it are the query's.
    fn note_other_reply(&mut self) {
        if self.state == LinkState::Probing {
            if let Some(p) = self.probe.as_mut() {
                p.other_line_seen = true;
            }
        }
    }

    /// RRF's nozzle position after a line's `ok` was overdue: the line ran (its `ok` was
    /// lost) if the nozzle stands where it ends, it was dropped if where the line before
    /// it ends: acknowledged, or sent again, never run twice. When the position cannot
    /// tell (the two ends are one place, or the nozzle is at neither) the line is sent
    /// again ([`LineEvent::MaybeRepeated`]), the second case with a protocol error.
    fn on_position(&mut self, at: [i64; 3], now: Micros) {
        let Some(p) = self.probe.take() else {
            return;
        };
        self.swallow_oks += p.attempts.saturating_sub(p.query_oks_seen);
        self.state = LinkState::Streaming;
        self.last_progress = now;
        self.timeouts_in_row = 0;
        let Some(front) = self.in_flight.front().map(|f| f.number) else {
            return;
        };
        match self.line_by_position(front, at) {
            ByPosition::Ran => {
                self.stats.ran_by_position += 1;
                self.acknowledge_front();
            }
            ByPosition::Dropped => {
                self.stats.dropped_by_position += 1;
                self.drop_flights_from(front);
                self.next_send = front;
            }
            ByPosition::Elsewhere => {
                self.protocol_error(format!(
                    "the nozzle stands at X{} Y{} Z{} mm, neither where line {front} ends nor \
                     where the line before it ends: line {front} is sent again",
                    at[0] as f64 / 1000.0,
                    at[1] as f64 / 1000.0,
                    at[2] as f64 / 1000.0
                ));
                self.repeat_oldest(now);
            }
            ByPosition::Unknown => self.repeat_oldest(now),
        }
    }

    fn on_line_recovering(&mut self, line: &str, reply: Reply<'_>, now: Micros) {
        if self.cfg.dialect == Dialect::Klipper {
            match klipper_position_line(line) {
                Some(KlipperPositionLine::Gcode(at)) => {
                    if let Some(p) = self.probe.as_mut() {
                        p.klipper_gcode_um = Some(at);
                    }
                    return;
                }
                Some(KlipperPositionLine::GcodeBase(base)) => {
                    let Some(at) = self.probe.as_ref().and_then(|p| p.klipper_gcode_um) else {
                        return;
                    };
                    // The G-code position is the last move's less the `G92` offsets;
                    // `GET_POSITION`'s `ok` follows.
                    let xyz_um = [0, 1, 2].map(|k| at[k] - base[k]);
                    self.recovery_ok_owed = true;
                    return self.finish_recovery(LastAccepted::Position { xyz_um });
                }
                None => {}
            }
            if let Reply::KlipperError(text) = reply {
                // Not ready, shut down: it cannot say where it stopped.
                self.recovery_ok_owed = true;
                return self.finish_recovery(LastAccepted::Unknown {
                    reason: format!("Klipper answered `!! {text}`"),
                });
            }
        }
        if let Some(last_line) = self.pending_error.take() {
            if reply == Reply::Resend(last_line.saturating_add(1)) {
                return self.recovery_answer(last_line, true, None);
            }
        }
        match reply {
            Reply::Error {
                last_line: Some(l), ..
            } if self.cfg.dialect == Dialect::Marlin => self.pending_error = Some(l),
            Reply::Json(json) if self.cfg.dialect == Dialect::Rrf => {
                self.on_rrf_recovery_json(json, now)
            }
            Reply::Start | Reply::ResetReason(_) if self.cfg.dialect == Dialect::Marlin => {
                self.finish_recovery(LastAccepted::Unknown {
                    reason: "the firmware restarted".into(),
                });
                self.reset(line.trim());
            }
            Reply::Busy(text) => self.on_busy(text, now),
            Reply::Ok(_) | Reply::Resend(_) | Reply::Empty | Reply::Wait => {}
            other => self.on_line_passive(line, other),
        }
    }

    /// RRF's answers to the recovery: `lineNumber` (`M409 K"inputs"`), then the nozzle's
    /// position (`M409 K"move.axes"`), which tells whether that line ran.
    fn on_rrf_recovery_json(&mut self, json: &str, now: Micros) {
        let stage = self.probe.as_ref().map(|p| p.stage);
        if stage == Some(ProbeStage::Position) {
            match rrf_user_position(json) {
                Ok(Some(at)) => return self.on_recovery_position(at),
                Ok(None) => return,
                Err(what) => {
                    return self.protocol_error(format!("M409 answer not understood: {what}"))
                }
            }
        }
        match rrf_input_line_number(json, &self.cfg.rrf_input_name) {
            Ok(None) => {}
            // The query's own unnumbered line counted one.
            Ok(Some(n)) => {
                let n = u32::try_from(n.saturating_sub(1)).unwrap_or(u32::MAX);
                let timeout = self.probe_timeout_us(true);
                if let Some(p) = self.probe.as_mut() {
                    p.stage = ProbeStage::Position;
                    p.last_parsed = Some(n);
                    p.attempts = 1;
                    p.send_due = true;
                    p.deadline = now.plus_us(timeout);
                }
            }
            Err(what) => self.protocol_error(format!("M409 answer not understood: {what}")),
        }
    }

    /// RRF recovery: the line `lineNumber` names ran if the nozzle stands where it ends
    /// and that is not where the line before it ends; it was dropped if the nozzle stands
    /// where the line before ends. Else (this host did not send it, or the two end at one
    /// place) the caller is told the position and `lineNumber`, not exact.
    fn on_recovery_position(&mut self, at: [i64; 3]) {
        let Some(n) = self.probe.as_ref().and_then(|p| p.last_parsed) else {
            return;
        };
        match self.line_by_position(n, at) {
            ByPosition::Ran => self.recovery_answer(n, true, Some(at)),
            ByPosition::Dropped if n > 0 => self.recovery_answer(n - 1, true, Some(at)),
            _ => self.recovery_answer(n, false, Some(at)),
        }
    }

    /// Whether line `number` ran, by where the nozzle stands (`at`).
    fn line_by_position(&self, number: u32, at: [i64; 3]) -> ByPosition {
        let tol = self.cfg.position_tolerance_um;
        let before = if number == self.hist_start {
            Some(self.end_before_history)
        } else {
            number
                .checked_sub(1)
                .and_then(|b| self.sent(b))
                .map(|s| s.end)
        };
        let (Some(end), Some(before)) = (self.sent(number).map(|s| s.end), before) else {
            return ByPosition::Unknown;
        };
        if !end.tells_apart(&before, tol) {
            ByPosition::Unknown
        } else if end.matches(at, tol) {
            ByPosition::Ran
        } else if before.matches(at, tol) {
            ByPosition::Dropped
        } else {
            ByPosition::Elsewhere
        }
    }

    fn recovery_answer(&mut self, last: u32, exact: bool, position_um: Option<[i64; 3]>) {
        let known_next = if exact {
            self.confirmed_next
        } else {
            self.accepted_next
        };
        if last + 1 < known_next {
            self.finish_recovery(LastAccepted::Unknown {
                reason: format!(
                    "the firmware's last line went back from {} to {last}: it restarted",
                    known_next - 1
                ),
            });
            return self.reset("the firmware's line counter went back");
        }
        // Marlin's `ok` follows its `Resend:`, RRF's its JSON.
        self.recovery_ok_owed = true;
        let tag = self.sent(last).and_then(|s| s.tag);
        let from = if exact { last + 1 } else { last };
        let resume_tag = (from..self.top)
            .find_map(|n| self.sent(n).and_then(|s| s.tag))
            .or_else(|| self.queued.front().map(|q| q.tag));
        self.finish_recovery(LastAccepted::Known {
            line_number: last,
            tag,
            resume_tag,
            exact,
            position_um,
        });
    }

    fn finish_recovery(&mut self, answer: LastAccepted) {
        self.late_probe_answers = self
            .probe
            .as_ref()
            .map_or(0, |p| p.attempts.saturating_sub(1));
        self.probe = None;
        self.pending_error = None;
        self.pending_unreadable_error = false;
        self.state = self.before_recovery;
        self.events.push_back(LineEvent::LastAccepted(answer));
    }

    // ---- passive states and terminal transitions -----------------------------------

    fn on_line_passive(&mut self, line: &str, reply: Reply<'_>) {
        let restarted = match reply {
            Reply::Start | Reply::ResetReason(_) => self.cfg.dialect == Dialect::Marlin,
            Reply::KlipperState("Ready") => self.cfg.dialect == Dialect::Klipper,
            _ => false,
        };
        if restarted {
            if matches!(
                self.state,
                LinkState::Lost | LinkState::Stopped | LinkState::Halted
            ) {
                self.state = LinkState::Reset;
                self.events.push_back(LineEvent::Reset {
                    banner: line.trim().into(),
                    unacknowledged: Vec::new(),
                });
            }
            return;
        }
        match reply {
            Reply::Error { text, .. } | Reply::KlipperError(text) => self
                .events
                .push_back(LineEvent::Error { text: text.into() }),
            Reply::Action(text) => self
                .events
                .push_back(LineEvent::Action { text: text.into() }),
            Reply::Echo(text) => self.events.push_back(LineEvent::Echo { text: text.into() }),
            Reply::Json(_) | Reply::KlipperState(_) | Reply::Start | Reply::ResetReason(_) => {
                self.events.push_back(LineEvent::Echo {
                    text: line.trim().into(),
                })
            }
            Reply::Ok(_) => self.recovery_ok_owed = false,
            Reply::Resend(_)
            | Reply::BadResend(_)
            | Reply::Busy(_)
            | Reply::Wait
            | Reply::Empty => {}
        }
    }

    /// Forget what is in flight (kept: the history and the queued lines, for the tags of
    /// a later `recover_last_accepted`; `connect` drops them).
    fn clear_stream(&mut self) {
        self.in_flight.clear();
        self.in_flight_bytes = 0;
        self.swallow_oks = 0;
        self.rewind = None;
        self.pending_error = None;
        self.pending_unreadable_error = false;
        self.jump_hint = None;
        self.probe = None;
        self.last_busy = None;
        self.next_send = self.top;
    }

    fn terminate(&mut self, state: LinkState) -> Vec<u64> {
        let unacknowledged = self.unacknowledged();
        self.clear_stream();
        self.state = state;
        unacknowledged
    }

    fn link_lost(&mut self, now: Micros) {
        let silent_us = now.since(self.last_progress);
        let unacknowledged = self.terminate(LinkState::Lost);
        self.events.push_back(LineEvent::LinkLost {
            silent_us,
            unacknowledged,
        });
    }

    fn stop(&mut self, reason: String) {
        let unacknowledged = self.terminate(LinkState::Stopped);
        self.events.push_back(LineEvent::Stopped {
            reason,
            unacknowledged,
        });
    }

    fn reset(&mut self, banner: &str) {
        let unacknowledged = self.terminate(LinkState::Reset);
        self.events.push_back(LineEvent::Reset {
            banner: banner.into(),
            unacknowledged,
        });
    }

    fn halt(&mut self, text: &str) {
        let unacknowledged = self.terminate(LinkState::Halted);
        self.events.push_back(LineEvent::Halted {
            text: text.into(),
            unacknowledged,
        });
    }

    fn protocol_error(&mut self, what: String) {
        self.stats.protocol_errors += 1;
        self.events.push_back(LineEvent::ProtocolError { what });
    }
}

/// `lineNumber` of the input named `input` in an RRF `M409 K"inputs"` answer
/// (`{"key":"inputs","flags":"","result":[{"name":"HTTP",...,"lineNumber":0},...]}`);
/// `Ok(None)` for a JSON line that is not that answer.
fn rrf_input_line_number(json: &str, input: &str) -> Result<Option<u64>, String> {
    let v: serde_json::Value = serde_json::from_str(json).map_err(|e| e.to_string())?;
    if v.get("key").and_then(|k| k.as_str()) != Some("inputs") {
        return Ok(None);
    }
    let inputs = v
        .get("result")
        .and_then(|r| r.as_array())
        .ok_or("no result array")?;
    let channel = inputs
        .iter()
        .find(|i| i.get("name").and_then(|n| n.as_str()) == Some(input))
        .ok_or_else(|| format!("no input named {input:?}"))?;
    channel
        .get("lineNumber")
        .and_then(|n| n.as_u64())
        .map(Some)
        .ok_or_else(|| format!("input {input:?} has no lineNumber"))
}

fn validate_line(text: &str) -> Result<(), SendError> {
    let refuse = |why: &str| {
        Err(SendError::Invalid(format!(
            "{why}: {:?}",
            truncate(text, 60)
        )))
    };
    if text.trim().is_empty() {
        return refuse("empty line");
    }
    if let Some(b) = text.bytes().find(|b| !(0x20..0x7f).contains(b)) {
        return refuse(&format!("byte 0x{b:02x} is not printable ASCII"));
    }
    if text.starts_with(' ') {
        return refuse("leading space");
    }
    if text.contains(';') {
        return refuse("comment (`;`): Marlin leaves comments out of the checksum");
    }
    if text.contains('*') {
        return refuse("`*` marks the checksum");
    }
    if text.contains('\\') || text.contains('(') {
        return refuse("`\\` and `(` are removed by Marlin before the checksum");
    }
    let mut first = text.chars();
    if matches!(first.next(), Some('N' | 'n')) && first.next().is_some_and(|c| c.is_ascii_digit()) {
        return refuse("the link numbers lines itself");
    }
    match command_word(text).as_deref() {
        Some("M110") => refuse("M110: the link owns line numbers"),
        Some("M112") => refuse("M112 goes through emergency_stop()"),
        _ => Ok(()),
    }
}

fn truncate(s: &str, max_chars: usize) -> String {
    s.chars().take(max_chars).collect()
}

#[cfg(test)]
#[path = "host_tests.rs"]
mod tests;
