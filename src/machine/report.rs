//! The machine's state in words both links and the lifecycle use: what it is doing
//! ([`MachineState`]), a move's address ([`MoveRef`]) and its report ([`MachineReport`]).
//! The edo link carries the first two on the wire (`docs/protocol.md`); a G-code
//! firmware's state is inferred into them by its adapter.

use serde::{Deserialize, Serialize};

use super::PositionUm;

/// Overall machine state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum MachineState {
    /// Queue empty, nothing moving.
    #[default]
    Idle,
    /// Executing moves.
    Running,
    /// Feed hold: queue kept, nothing executes.
    Held,
    /// Emergency stop: queue discarded, incoming moves discarded until Resume.
    EStopped,
    /// A latched fault stops execution until ClearFaults.
    Faulted,
}

/// A move address: job id and index within the job.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct MoveRef {
    /// Job id.
    pub job_id: u32,
    /// Index within the job.
    pub index: u32,
}

/// A report of the machine's state.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct MachineReport {
    /// What it is doing.
    pub state: MachineState,
    /// The last move it executed.
    pub last_executed: Option<MoveRef>,
    /// Moves it executed since it booted.
    pub executed_total: u64,
    /// Moves waiting in its queue.
    pub queued: u32,
    /// Latched faults (0: none).
    pub faults: u32,
    /// Nozzle position after the last executed move.
    pub position: PositionUm,
    /// Volume left per syringe (nl); its length is the syringe count.
    pub remaining_nl: Vec<u32>,
}
