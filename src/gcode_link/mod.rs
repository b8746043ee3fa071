//! The G-code line link: streams G-code lines to RepRapFirmware (Duet), Marlin and Klipper
//! over a serial line, sans-IO, beside edo's own framed protocol ([`crate::link`]). The
//! user-facing contract (what edod sends to each firmware, what it can know, what is
//! promised exactly once) is `docs/firmware.md`; this module implements it.
//!
//! Driven like [`crate::link::Host`]: the caller owns the port and the clock.
//!
//! ```text
//! host.connect(now);
//! loop {
//!     host.handle_bytes(&bytes_read, now);          // what the port produced
//!     host.handle_timeout(now);                     // when next_timeout() passed
//!     while let Some(b) = host.poll_transmit(now) { port.write(&b) }
//!     while let Some(e) = host.poll_event() { ... } // Accepted { tag, .. }, Reset, ...
//!     sleep until host.next_timeout() or bytes arrive
//! }
//! ```
//!
//! - [`LineHost`]: the host end. Numbers and checksums lines, keeps a history for
//!   resends, windows lines by the firmware's receive buffer, handles `ok`, `Resend:`,
//!   `busy:`, errors, banners, timeouts, the e-stop lane and the last-accepted query.
//! - `Firmware`: sans-IO models of the three firmwares' serial front ends (bytes in →
//!   lines into a command queue, replies out), for tests, benches and `hil-sim`
//!   (feature `sim`).
//! - `testkit`: a seeded fault wire in simulated time and a host–firmware harness
//!   (feature `sim`).
//! - [`Dialect::queues`]: what each firmware holds by default (its command queue and
//!   planner), which the G-code adapter counts against.
//!
//! Per-firmware decisions (the reasons are in `docs/firmware.md`):
//!
//! | | Marlin | RepRapFirmware | Klipper |
//! |---|---|---|---|
//! | line | `N<n> <text>*<xor>` | `N<n> <text>*<xor>` | `<text>` (N and `*` are ignored by Klipper) |
//! | handshake | `N0 M110 N0*125`, `N1 M115*39` | `M555 P2`, then as Marlin | `M115` |
//! | window | 1 line; opt-in: the configured number or ADVANCED_OK's free command slots (`B`+1); bytes ≤ receive buffer − e-stop reserve | 1 line (a bad line is dropped silently and the lines after it would run) | 8 lines (Klipper scans for M112 only below 20 pending lines) |
//! | lost line / `ok` | overdue or timeout → out-of-sequence probe `N2000000000 M105`: its error names the last line accepted; go back to the one after | overdue or timeout → `M409 K"move.axes"`: the nozzle at the line's end → it ran; at the end of the line before → sent again; the two ends one place → sent again, reported as [`LineEvent::MaybeRepeated`] | nothing is lost on a pty: timeout → [`LineEvent::LinkLost`] |
//! | last accepted | the same probe | `M409 K"inputs"` → `lineNumber`, then the position as above (exact unless the two ends are one place) | not possible |
//! | e-stop | `\nM112\n` (at once with EMERGENCY_PARSER) | `\nM112\n` (urgent scan at line start) | `\nM112\n` (scanned while < 20 lines pending) |
//!
//! Rules of the RepRapFirmware window: RRF 3.5 drops a line whose checksum is bad with no
//! reply and goes on with the lines after it, so with two lines in flight a corrupted
//! first line would run after the second once resent: edod keeps one line in flight on
//! RRF, whatever the configured window, and recovers the silent drop by the ok timeout.

#[cfg(any(test, feature = "sim"))]
mod firmware;
mod host;
mod position;
mod reply;
#[cfg(any(test, feature = "sim"))]
pub mod testkit;
pub mod writer;

#[cfg(any(test, feature = "sim"))]
pub use firmware::{
    Firmware, FirmwareConfig, FirmwareStats, ProcessedLine, RxOverflow, CHECKSUM_ERROR,
    LINE_NUMBER_ERROR, NO_CHECKSUM_ERROR,
};
pub use host::{
    FirmwareInfo, FreeCounts, LastAccepted, LineEvent, LineHost, LineStats, LinkState,
    RecoverError, SendError,
};

pub use position::{
    klipper_get_position_lines, klipper_position_line, mm_to_um, rrf_axes_json, rrf_user_position,
    KlipperPositionLine, NozzleAt, KLIPPER_POSITION_QUERY, RRF_POSITION_QUERY,
};

pub use crate::link::Micros;

/// The firmware at the other end of the line, or that reads a G-code file: the one
/// name of the three for every place that names them (edod.toml's
/// `[machine.gcode] firmware`, `edoctl gcode --flavor`, `edoctl demo --firmware`,
/// `edoctl link-test --firmware`, `hil-sim --gcode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "daemon", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Dialect {
    /// Marlin 1.1 / 2.x: line numbers and checksums checked, `Resend:` on error.
    Marlin,
    /// RepRapFirmware 3.x (Duet): checksums checked when present, bad lines dropped
    /// silently, line numbers only recorded.
    Rrf,
    /// Klipper's G-code pty: line numbers and checksums ignored, one `ok` per line.
    Klipper,
}

impl Dialect {
    /// Every firmware, in the order they are listed to people.
    pub const ALL: [Dialect; 3] = [Dialect::Rrf, Dialect::Marlin, Dialect::Klipper];

    /// The name configurations and command lines use (`rrf`, `marlin`, `klipper`).
    pub fn name(self) -> &'static str {
        match self {
            Dialect::Rrf => "rrf",
            Dialect::Marlin => "marlin",
            Dialect::Klipper => "klipper",
        }
    }

    /// The firmware named `name` ([`Dialect::name`]), or what the names are.
    pub fn from_name(name: &str) -> Result<Dialect, String> {
        Dialect::ALL
            .into_iter()
            .find(|d| d.name() == name)
            .ok_or_else(|| format!("no firmware {name:?}: rrf, marlin or klipper"))
    }

    /// The firmware's own name, for people.
    pub fn display_name(self) -> &'static str {
        match self {
            Dialect::Rrf => "RepRapFirmware",
            Dialect::Marlin => "Marlin",
            Dialect::Klipper => "Klipper",
        }
    }

    /// Whether lines go out as `N<n> <text>*<checksum>` (else plain `<text>`).
    pub fn numbers_lines(self) -> bool {
        !matches!(self, Dialect::Klipper)
    }

    /// What the firmware holds in its stock build: lines it has acknowledged may wait
    /// there before they run.
    pub fn queues(self) -> FirmwareQueues {
        match self {
            // Marlin's AVR upstream configuration: BUFSIZE 4, BLOCK_BUFFER_SIZE 16.
            Dialect::Marlin => FirmwareQueues {
                command_slots: 4,
                planner_blocks: 16,
            },
            // RRF reads one command at a time into a DDA ring of 40.
            Dialect::Rrf => FirmwareQueues {
                command_slots: 1,
                planner_blocks: 40,
            },
            // Klipper stops reading at 20 pending lines; its lookahead holds 32 moves.
            Dialect::Klipper => FirmwareQueues {
                command_slots: 20,
                planner_blocks: 32,
            },
        }
    }
}

/// A firmware's queues ([`Dialect::queues`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FirmwareQueues {
    /// Command queue (Marlin `BUFSIZE`; RRF 1: one command at a time; Klipper: lines
    /// pending before it stops reading, 20).
    pub command_slots: usize,
    /// Planner blocks (Marlin `BLOCK_BUFFER_SIZE`, RRF's DDA ring, Klipper's lookahead).
    pub planner_blocks: usize,
}

impl FirmwareQueues {
    /// The most lines the firmware holds acknowledged and not yet run.
    pub fn held_at_most(self) -> usize {
        self.command_slots + self.planner_blocks
    }
}

/// How many lines may be in flight (sent, not yet acknowledged).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Window {
    /// The window that keeps every promise on a link that corrupts bytes: Marlin 1, RRF 1,
    /// Klipper 8 (a pty corrupts nothing).
    Auto,
    /// At most this many (RRF stays at 1 whatever this says; Klipper at most 19). On
    /// Marlin over a UART, 2 or more let a line error run a whole line twice in rare cases
    /// (`docs/firmware.md`, "Windows on Marlin").
    Lines(u16),
    /// Marlin: ADVANCED_OK's free command slots (1 until the firmware reports them); for
    /// boards on native USB, where bytes are not corrupted. Other firmware: as `Auto`.
    AdvancedOk,
}

/// How a move's per-syringe amounts are written on its line (`docs/firmware.md`, "Writing
/// the mix").
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MixWriting {
    /// RRF: one tool over every drive (`M563`), `G1 ... E a:b:c`, relative per drive.
    PerDriveE,
    /// Marlin `MIXING_EXTRUDER`: `M163 S<drive> P<weight>` + `M164 S0`, E the total.
    MarlinM163,
    /// Marlin `DIRECT_MIXING_IN_G1`: the weights on the move, `A B C D H I`, E the total.
    MarlinDirect,
    /// One axis per syringe, by letter, in syringe order (Klipper `MANUAL_STEPPER ...
    /// GCODE_AXIS=`, Marlin multi-axis builds); positions in mm of plunger travel.
    Axes(Vec<char>),
}

/// The line number of the out-of-sequence probe (Marlin): never `last line + 1`, so the
/// firmware rejects it and its error names the last line it accepted.
pub const PROBE_LINE_NUMBER: u32 = 2_000_000_000;

/// Every tolerance and timeout of the host end. [`LineLinkConfig::for_dialect`] gives the
/// defaults (`docs/firmware.md`, "Timeouts and windows").
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LineLinkConfig {
    /// The firmware at the other end.
    pub dialect: Dialect,
    /// Lines in flight.
    pub window: Window,
    /// The firmware's receive buffer in bytes (Marlin AVR: 128, `RX_BUFFER_SIZE`; RRF USB:
    /// 256; Klipper pty: 4096). Bytes in flight never exceed it minus
    /// `estop_reserve_bytes`, so no byte is dropped by a full buffer and the e-stop fits.
    pub rx_buffer_bytes: usize,
    /// Room kept free in the receive buffer for the e-stop (`\nM112\n`, 6 bytes).
    pub estop_reserve_bytes: usize,
    /// Bytes in flight at most, whatever the buffer holds: what may be ahead of the e-stop
    /// on the wire ([`estop_bytes_for`]: 25 ms of line time, as on the edo link).
    pub max_bytes_in_flight: usize,
    /// Longest line sent, with its line number and checksum, without the newline
    /// (Marlin `MAX_CMD_SIZE` 96 − 1).
    pub max_line_bytes: usize,
    /// No `ok` for this long while lines are in flight → the link timed out (before the
    /// firmware showed it sends `busy:` keepalives).
    pub ok_timeout_us: u64,
    /// The same once the firmware showed it sends `busy:` keepalives (a `busy:` line, or
    /// `Cap:BUSY_PROTOCOL:1`): silence longer than this means a lost line or `ok`. Marlin
    /// sends one every 2 s by default (`M113`).
    pub busy_timeout_us: u64,
    /// The timeout while a slow command (see `slow_commands`) is in flight: these hold
    /// their `ok` until they finish and Marlin reads no line meanwhile.
    pub slow_command_timeout_us: u64,
    /// Command words whose `ok` may take minutes (homing, heating, waiting for moves).
    pub slow_commands: Vec<String>,
    /// Each handshake attempt waits this long for its `ok`s.
    pub handshake_timeout_us: u64,
    /// Handshake attempts before [`LineEvent::LinkLost`].
    pub handshake_attempts: u32,
    /// Consecutive timeouts (probes, repeats) without an `ok` before [`LineEvent::LinkLost`].
    pub max_timeouts: u32,
    /// Sent lines kept for resends, acknowledged or not; at least the window plus one.
    pub history_lines: usize,
    /// The same line requested this many times in a row → the job stops (a resend loop).
    pub max_consecutive_resends: u32,
    /// Longest reply line kept; longer ones are dropped up to their end, with an event.
    pub max_reply_line_bytes: usize,
    /// After a `wait` (Marlin `NO_TIMEOUTS`: queue empty, no serial data) with lines in
    /// flight for at least this long, the host probes at once instead of waiting for the
    /// timeout.
    pub wait_grace_us: u64,
    /// Moves the firmware's planner holds (Marlin `BLOCK_BUFFER_SIZE`, 16): a timed
    /// move's `ok` waits at most for the longest of the last this many.
    pub planner_moves: usize,
    /// A timed line's `ok` is overdue after what it may wait for times this...
    pub ok_overdue_factor: u32,
    /// ...plus this, µs (the line's time on the wire, the firmware's loop, acceleration
    /// the feed leaves out).
    pub ok_overdue_floor_us: u64,
    /// RRF: how far the firmware's reported position (`userPosition`, three decimals)
    /// may be from where a line ends and still be that line's end, µm; two lines whose
    /// ends are closer than twice this cannot be told apart by position.
    pub position_tolerance_um: u32,
    /// RRF: the `inputs[]` channel edod is on, for `M409 K"inputs"`.
    pub rrf_input_name: String,
    /// RRF: send `M555 P2` first so that the channel answers `ok` (Marlin compatibility).
    pub rrf_set_marlin_mode: bool,
}

impl LineLinkConfig {
    /// The defaults for `dialect`.
    pub fn for_dialect(dialect: Dialect) -> Self {
        let (rx_buffer_bytes, max_line_bytes, ok_timeout_us) = match dialect {
            Dialect::Marlin => (128, 95, 10_000_000),
            // RRF has no busy protocol: a G1's ok waits at most for one move to free its
            // queue; a silently dropped line is only found by this timeout.
            Dialect::Rrf => (256, 200, 4_000_000),
            Dialect::Klipper => (4096, 400, 10_000_000),
        };
        Self {
            dialect,
            window: Window::Auto,
            rx_buffer_bytes,
            estop_reserve_bytes: 8,
            max_bytes_in_flight: usize::MAX,
            max_line_bytes,
            ok_timeout_us,
            busy_timeout_us: 5_000_000,
            slow_command_timeout_us: 900_000_000,
            slow_commands: [
                "G28", "G29", "G30", "G32", "G34", "G4", "M109", "M190", "M191", "M116", "M303",
                "M400", "M600",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect(),
            handshake_timeout_us: 3_000_000,
            handshake_attempts: 5,
            max_timeouts: 3,
            history_lines: 128,
            max_consecutive_resends: 10,
            max_reply_line_bytes: 16_384,
            wait_grace_us: 1_000_000,
            // Marlin `BLOCK_BUFFER_SIZE`; RRF's DDA ring.
            planner_moves: if dialect == Dialect::Rrf { 40 } else { 16 },
            ok_overdue_factor: 2,
            ok_overdue_floor_us: 250_000,
            position_tolerance_um: 2,
            rrf_input_name: "USB".into(),
            rrf_set_marlin_mode: true,
        }
    }
}

impl Default for LineLinkConfig {
    fn default() -> Self {
        Self::for_dialect(Dialect::Marlin)
    }
}

/// Bytes that take `PRIORITY_LATENCY_US` (25 ms) on a line at `baud` (10 bits a byte):
/// the cap on bytes in flight that keeps the e-stop within the edo link's bound (625 at
/// 250 000 baud, 288 at 115 200), never below one longest line.
pub fn estop_bytes_for(baud: u32, max_line_bytes: usize) -> usize {
    let bytes = u64::from(baud) / 10 * crate::link::PRIORITY_LATENCY_US / 1_000_000;
    usize::try_from(bytes)
        .unwrap_or(usize::MAX)
        .max(max_line_bytes + 1)
}

/// The XOR checksum of Marlin and RepRapFirmware: every byte before the `*`, from the `N`
/// on.
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0, |acc, b| acc ^ b)
}

/// `N<n> <text>*<checksum>\n`.
pub fn numbered_line(number: u32, text: &str) -> Vec<u8> {
    let mut line = format!("N{number} {text}").into_bytes();
    let cs = checksum(&line);
    line.extend_from_slice(format!("*{cs}\n").as_bytes());
    line
}

/// A Klipper extended command's parameter (`MANUAL_STEPPER STEPPER=syringe_a
/// SET_POSITION=0`): the value of the first `KEY=value` word whose key is `key`, in any
/// case, as Klipper's `gcode.py` reads them; `Some("")` for `KEY=`.
pub fn klipper_param<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    text.split_ascii_whitespace().find_map(|w| {
        let (k, v) = w.split_once('=')?;
        k.eq_ignore_ascii_case(key).then_some(v)
    })
}

/// The first word of a G-code line (`G1`, `M112`, ...), upper case, after an optional
/// `N<n>` prefix; `G01` reads as `G1`.
pub fn command_word(text: &str) -> Option<String> {
    let mut words = text.split_ascii_whitespace();
    let mut word = words.next()?;
    if is_line_number_word(word) {
        word = words.next()?;
    }
    let word = word.split('*').next().unwrap_or(word);
    let mut chars = word.chars();
    let letter = chars.next()?.to_ascii_uppercase();
    let digits: String = chars.collect();
    if !letter.is_ascii_alphabetic() {
        return None;
    }
    let number = digits.trim_start_matches('0');
    let number = if number.is_empty() && !digits.is_empty() {
        "0"
    } else {
        number
    };
    Some(format!("{letter}{}", number.to_ascii_uppercase()))
}

fn is_line_number_word(word: &str) -> bool {
    let mut chars = word.chars();
    matches!(chars.next(), Some('N' | 'n')) && word.len() > 1 && chars.all(|c| c.is_ascii_digit())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_name_per_firmware_everywhere() {
        for d in Dialect::ALL {
            assert_eq!(Dialect::from_name(d.name()), Ok(d));
            // serde (edod.toml, GcodeSettings) reads the same name.
            let json = serde_json::to_string(&d).unwrap();
            assert_eq!(json, format!("\"{}\"", d.name()));
        }
        let e = Dialect::from_name("repetier").unwrap_err();
        assert!(e.contains("rrf, marlin or klipper"), "{e}");
    }

    #[test]
    fn handshake_line_has_the_well_known_checksum() {
        assert_eq!(numbered_line(0, "M110 N0"), b"N0 M110 N0*125\n");
        assert_eq!(numbered_line(1, "M115"), b"N1 M115*39\n");
    }

    #[test]
    fn estop_cap_is_25_ms_of_line_time() {
        assert_eq!(estop_bytes_for(250_000, 95), 625);
        assert_eq!(estop_bytes_for(115_200, 95), 288);
        assert_eq!(estop_bytes_for(9_600, 95), 96);
    }

    #[test]
    fn command_words() {
        assert_eq!(command_word("G1 X1").as_deref(), Some("G1"));
        assert_eq!(command_word("N12 g01 X1*33").as_deref(), Some("G1"));
        assert_eq!(command_word("M400").as_deref(), Some("M400"));
        assert_eq!(command_word("G0").as_deref(), Some("G0"));
        assert_eq!(command_word("  ").as_deref(), None);
        assert_eq!(command_word("*12").as_deref(), None);
    }
}

#[cfg(test)]
mod soak_tests;
