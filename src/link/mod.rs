//! The machine link: a sans-IO protocol state machine for host and machine that streams
//! moves reliably over a serial line. The contract (byte layout, messages, timers, state
//! machines and why) is `docs/protocol.md`; this module implements it.
//!
//! Both ends are driven the quinn-proto way — the caller owns the port and the clock:
//!
//! ```text
//! loop {
//!     endpoint.handle_bytes(&bytes_read, now);        // feed what the port produced
//!     endpoint.handle_timeout(now);                   // when next_timeout() passed
//!     while let Some(t) = endpoint.poll_transmit(now) { port.write(&t.bytes) }
//!     while let Some(e) = endpoint.poll_event() { ... }
//!     sleep until endpoint.next_timeout() or bytes arrive
//! }
//! ```
//!
//! - [`frame`]: COBS + header + postcard + CRC-32C codec shared by both ends.
//! - [`msg`]: message types.
//! - [`Host`]: the host end (streams moves, priority lane, reports, reset/link-loss detection).
//! - [`MachineLink`]: the machine end (move queue with exactly-once delivery, credits,
//!   reports), used by `hil-sim` and meant to be ported to firmware.
//! - [`sim_faults`]: the faults hil-sim injects (`--faults`), named for edod's config too.
//! - `testkit`: a seeded, simulated-time lossy wire for tests and benchmarks (feature
//!   `sim`).

pub mod frame;
mod host;
mod machine_end;
pub mod msg;
pub mod sim_faults;
mod stream;
#[cfg(any(test, feature = "sim"))]
pub mod testkit;

pub use frame::{Decoder, Frame, FrameError, FrameKind, MAX_FRAME};
pub use host::{Host, HostEvent, HostState, MachineInfo};
pub use machine_end::{MachineEvent, MachineLink, MachineLinkConfig};
pub use msg::{
    FaultKind, FaultReport, HostMsg, MachineDescription, MachineMsg, MachineState, MoveRef,
    PriorityCmd, Status, PROTOCOL_VERSION,
};

/// A point in time in microseconds since an arbitrary epoch chosen by the caller. The core
/// never reads a clock: every call that needs time takes one of these.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct Micros(pub u64);

impl Micros {
    /// `self + us`, saturating.
    pub fn plus_us(self, us: u64) -> Micros {
        Micros(self.0.saturating_add(us))
    }

    /// Microseconds from `earlier` to `self` (0 if `earlier` is later).
    pub fn since(self, earlier: Micros) -> u64 {
        self.0.saturating_sub(earlier.0)
    }
}

/// Bytes to put on the wire: one complete encoded frame (with its 0x00 delimiter).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Transmit {
    /// Encoded frame.
    pub bytes: Vec<u8>,
    /// Frame kind (for logging and statistics).
    pub kind: FrameKind,
}

/// Timers and windows of one link end. Defaults are the protocol's (`docs/protocol.md`,
/// "Timers"); every field is in the unit its name says.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkConfig {
    /// Largest decoded frame this end sends and accepts (≤ [`MAX_FRAME`]).
    pub max_frame: usize,
    /// Smallest frame the sender shrinks to on a lossy line (adaptive framing).
    pub min_frame: usize,
    /// Most unacknowledged Data frames in flight.
    pub max_frames_in_flight: usize,
    /// This end's own cap on the wire bytes in flight, below the peer's advertised
    /// receive buffer: it bounds how long a priority frame (e-stop) can wait behind data
    /// already on the wire. `usize::MAX` leaves only the peer's limit; the daemon sets it
    /// from the baud rate with [`LinkConfig::with_priority_latency`].
    pub max_bytes_in_flight: usize,
    /// RTO before the first RTT sample.
    pub initial_rto_us: u64,
    /// Lower bound of the RTO (RFC 6298 says 1 s for the Internet; a serial line is
    /// deterministic, 25 ms is above any UART + scheduler jitter we expect).
    pub min_rto_us: u64,
    /// Upper bound of the RTO after doubling.
    pub max_rto_us: u64,
    /// Clock granularity G of RFC 6298.
    pub clock_granularity_us: u64,
    /// Duplicate pure acks that trigger a fast retransmit.
    pub dup_ack_threshold: u32,
    /// Send a Heartbeat after this long without sending anything.
    pub heartbeat_interval_us: u64,
    /// Declare the link lost after this long without a valid frame (must be < 2 s).
    pub link_timeout_us: u64,
    /// Host: repeat Hello this often until answered.
    pub hello_interval_us: u64,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            max_frame: 512,
            min_frame: 128,
            max_frames_in_flight: 32,
            max_bytes_in_flight: usize::MAX,
            initial_rto_us: 250_000,
            min_rto_us: 25_000,
            max_rto_us: 1_000_000,
            clock_granularity_us: 1_000,
            dup_ack_threshold: 3,
            heartbeat_interval_us: 250_000,
            link_timeout_us: 1_500_000,
            hello_interval_us: 250_000,
        }
    }
}

/// Data that may be ahead of an e-stop on the wire, µs: the daemon and `edoctl
/// link-test` cap their byte window to it (`docs/protocol.md` §5).
pub const PRIORITY_LATENCY_US: u64 = 25_000;

impl LinkConfig {
    /// Cap the bytes in flight so that at most `latency_us` of data (at `baud`, 10 bits a
    /// byte) can be ahead of a priority frame, but never below `min_frame` (one small
    /// frame always fits). A serial line's round trip is a few milliseconds, so a window
    /// of 25 ms still keeps the line full (see `docs/protocol.md` §5).
    pub fn with_priority_latency(mut self, baud: u32, latency_us: u64) -> Self {
        let bytes = (u64::from(baud) / 10).saturating_mul(latency_us) / 1_000_000;
        self.max_bytes_in_flight = (bytes as usize).max(self.min_frame);
        self
    }
}

/// Link statistics (like Klipper's `bytes_write`, `bytes_retransmit`, `srtt`, ...).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct LinkStats {
    /// Bytes handed to the wire (all frames, with framing).
    pub bytes_sent: u64,
    /// Bytes received (everything fed to `handle_bytes`).
    pub bytes_received: u64,
    /// Bytes of Data frames sent again.
    pub bytes_retransmitted: u64,
    /// Bytes that did not make a valid frame (garbage, CRC errors, bad COBS).
    pub bytes_invalid: u64,
    /// Frames sent.
    pub frames_sent: u64,
    /// Valid frames received.
    pub frames_received: u64,
    /// Data frames sent again.
    pub frames_retransmitted: u64,
    /// Frames that failed COBS/CRC/kind checks.
    pub frames_invalid: u64,
    /// Data frames received again (discarded: exactly-once).
    pub frames_duplicate: u64,
    /// Data frames received after a hole (kept in the reorder buffer).
    pub frames_out_of_order: u64,
    /// Message bytes (postcard) in first transmissions of Data frames.
    pub payload_bytes_sent: u64,
    /// Message bytes the peer acknowledged.
    pub payload_bytes_acked: u64,
    /// Messages sent in Data frames (first transmissions).
    pub messages_sent: u64,
    /// Naks received.
    pub naks_received: u64,
    /// Naks sent.
    pub naks_sent: u64,
    /// Retransmissions triggered by duplicate acks.
    pub fast_retransmits: u64,
    /// Retransmission timeouts.
    pub timeouts: u64,
    /// Acks outside the window (stale or bogus), ignored.
    pub acks_out_of_range: u64,
    /// Smoothed RTT (µs), 0 before the first sample.
    pub srtt_us: u64,
    /// RTT variation (µs).
    pub rttvar_us: u64,
    /// Current retransmission timeout (µs).
    pub rto_us: u64,
}
