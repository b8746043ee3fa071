//! Messages carried in frame bodies (postcard). Byte layout and meaning: `docs/protocol.md`.

use serde::{Deserialize, Serialize};

pub use crate::machine::{MachineState, MoveRef};
use crate::machine::{Move, PositionUm};

/// Version of the wire protocol; both ends must agree exactly.
pub const PROTOCOL_VERSION: u16 = 1;

/// Host to machine, reliable and in order (Data frames).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum HostMsg {
    /// A move to append to the machine's move queue (takes one credit).
    Move(Move),
    /// Ask for a status report now.
    Query,
    /// Clear latched faults (syringe empty, limit hit) after the operator fixed them.
    ClearFaults,
}

/// Machine to host, reliable and in order (Data frames).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum MachineMsg {
    /// Progress and state snapshot.
    Status(Status),
    /// A fault happened (also latched in `Status::faults`).
    Fault(FaultReport),
}

/// Commands on the priority lane: sent ahead of every queued frame, acted on at receipt.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum PriorityCmd {
    /// Stop all motion and plungers now, discard the move queue and every move received
    /// until the next `Resume`.
    EmergencyStop,
    /// Decelerate and hold; the queue is kept.
    FeedHold,
    /// Leave feed hold or emergency stop; execution continues with queued/new moves.
    Resume,
}

/// Host handshake (Hello frame body).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    /// [`PROTOCOL_VERSION`] of the host.
    pub protocol_version: u16,
    /// Random id of this host session; the machine echoes it and resets its link state
    /// only when it changes (a duplicated Hello never resets a running session).
    pub session_id: u64,
    /// Largest frame the host accepts (decoded bytes).
    pub max_frame: u16,
}

/// Machine handshake reply (HelloReply frame body).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HelloReply {
    /// [`PROTOCOL_VERSION`] of the machine.
    pub protocol_version: u16,
    /// Echo of [`Hello::session_id`].
    pub session_id: u64,
    /// Free text: make, model, firmware version (at most 64 bytes).
    pub identity: String,
    /// Random id drawn at every boot: a change means the machine reset.
    pub boot_id: u64,
    /// Barrel cross-section of each syringe in µm² (the length is the syringe count).
    pub barrel_area_um2: Vec<u32>,
    /// Capacity of each syringe in nl.
    pub capacity_nl: Vec<u32>,
    /// Move queue depth (credits when empty).
    pub queue_depth: u16,
    /// Receive buffer in bytes: the host keeps at most this many unacked bytes in flight.
    pub rx_buffer_bytes: u32,
    /// Largest frame the machine accepts (decoded bytes, at most [`super::MAX_FRAME`]).
    pub max_frame: u16,
    /// Where the machine is now (last executed move etc).
    pub status: Status,
}

/// Progress and state snapshot, sent by the machine on change, at most every report
/// interval while executing, on every layer mark and on Query.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Status {
    /// Machine state.
    pub state: MachineState,
    /// Last executed move.
    pub last_executed: Option<MoveRef>,
    /// Moves executed since boot.
    pub executed_total: u64,
    /// Moves executed whose index was not one more than the previous one of the same job
    /// and not higher: executed twice (must stay 0).
    pub duplicates: u32,
    /// Moves whose index skipped ahead within the same job: lost or reordered (must stay 0).
    pub gaps: u32,
    /// Position after the last executed move.
    pub position: PositionUm,
    /// Remaining volume per syringe (nl).
    pub remaining_nl: Vec<u32>,
    /// Moves waiting in the queue.
    pub queued: u16,
    /// Latched fault bits ([`FaultKind::bit`]).
    pub faults: u32,
}

/// Faults the machine reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FaultKind {
    /// A syringe ran empty (syringe number).
    SyringeEmpty(u8),
    /// An axis hit its limit switch (0 = X, 1 = Y, 2 = Z).
    LimitHit(u8),
    /// The operator pressed the machine's emergency stop button.
    EStopPressed,
    /// A move arrived that the queue could not take (host ignored credits).
    QueueOverflow,
    /// A CRC-valid frame whose body did not decode (version skew or host bug).
    BadMessage,
    /// A move the machine cannot execute (e.g. more volumes than syringes).
    BadMove,
}

impl FaultKind {
    /// Bit of this fault kind in [`Status::faults`].
    pub fn bit(self) -> u32 {
        match self {
            FaultKind::SyringeEmpty(_) => 1,
            FaultKind::LimitHit(_) => 1 << 1,
            FaultKind::EStopPressed => 1 << 2,
            FaultKind::QueueOverflow => 1 << 3,
            FaultKind::BadMessage => 1 << 4,
            FaultKind::BadMove => 1 << 5,
        }
    }
}

/// A fault and the move at which it happened.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FaultReport {
    /// What happened.
    pub kind: FaultKind,
    /// Last executed move when it happened.
    pub at: Option<MoveRef>,
}
