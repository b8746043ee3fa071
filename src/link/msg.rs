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

/// What a machine is, as it says in its handshake: the one description the machine end
/// is built from ([`super::MachineLinkConfig`]), sends ([`HelloReply`]) and the host
/// keeps ([`super::MachineInfo`]). Nested in the reply, its fields go on the wire in
/// this order, where they always were (postcard writes a nested struct's fields in
/// place).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct MachineDescription {
    /// Free text: make, model, firmware version (at most 64 bytes are sent).
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
}

impl Default for MachineDescription {
    /// Two 10 ml syringes of 10 mm bore, a queue of 128 moves, 2 KiB of receive buffer.
    fn default() -> Self {
        Self {
            identity: "edo machine".into(),
            boot_id: 1,
            barrel_area_um2: vec![78_539_816; 2],
            capacity_nl: vec![10_000_000; 2],
            queue_depth: 128,
            rx_buffer_bytes: 2048,
        }
    }
}

/// Machine handshake reply (HelloReply frame body).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HelloReply {
    /// [`PROTOCOL_VERSION`] of the machine.
    pub protocol_version: u16,
    /// Echo of [`Hello::session_id`].
    pub session_id: u64,
    /// The machine.
    pub machine: MachineDescription,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The machine's description nested in the reply leaves its bytes on the wire as
    /// they were with the fields flat in the reply (protocol version 1 unchanged).
    #[test]
    fn the_hello_reply_s_bytes_are_its_fields_in_order() {
        let status = Status {
            state: MachineState::Idle,
            last_executed: Some(MoveRef {
                job_id: 3,
                index: 41,
            }),
            remaining_nl: vec![9, 8],
            ..Status::default()
        };
        let reply = HelloReply {
            protocol_version: PROTOCOL_VERSION,
            session_id: 0xfeed,
            machine: MachineDescription {
                identity: "hil-sim 0.1".into(),
                boot_id: 77,
                barrel_area_um2: vec![5, 6],
                capacity_nl: vec![1_000, 2_000],
                queue_depth: 128,
                rx_buffer_bytes: 2048,
            },
            max_frame: 512,
            status: status.clone(),
        };
        let flat = (
            PROTOCOL_VERSION,
            0xfeed_u64,
            "hil-sim 0.1",
            77_u64,
            vec![5_u32, 6],
            vec![1_000_u32, 2_000],
            128_u16,
            2048_u32,
            512_u16,
            status,
        );
        let bytes = postcard::to_allocvec(&reply).expect("encode");
        assert_eq!(bytes, postcard::to_allocvec(&flat).expect("encode"));
        assert_eq!(postcard::from_bytes::<HelloReply>(&bytes), Ok(reply));
    }
}
