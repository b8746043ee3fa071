//! The machine as the API shows it (`docs/api.md`, Machine snapshot): the last report,
//! the link's health, and what an e-stop measured.

use serde::{Deserialize, Serialize};

use super::job::Progress;
use crate::machine::{MachineState, MoveRef};

/// The machine as last reported (`notify_machine_state`; `machine.status` adds the
/// progress).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MachineSnapshot {
    /// Serial port.
    pub port: String,
    /// Handshake done and the link alive.
    pub connected: bool,
    /// Why not, while not connected: the port's OS error (`"port /dev/ttyACM0: No such
    /// file or directory"`), a silent machine, a lost link.
    #[serde(default)]
    pub disconnected_reason: Option<String>,
    /// Machine identity.
    pub identity: Option<String>,
    /// Execution state (`Idle`, `Running`, `Held`, `EStopped`, `Faulted`); null when
    /// not known (not connected).
    pub state: Option<MachineState>,
    /// Last executed move.
    pub last_executed: Option<MoveRef>,
    /// Moves executed since the machine booted.
    pub executed_total: u64,
    /// Syringe volumes left (nl).
    pub remaining_nl: Vec<u32>,
    /// Moves in the machine's queue.
    pub queued: u32,
    /// Latched fault bits (`docs/protocol.md`).
    pub faults: u32,
    /// Nozzle position (mm).
    pub position_mm: [f64; 3],
    /// Job being streamed.
    pub active_job: Option<u32>,
    /// Why the job store cannot write (`"job store cannot write: disk full"`), while it
    /// cannot: no job starts or continues until it can (docs/api.md, Full disk).
    #[serde(default)]
    pub store_problem: Option<String>,
    /// The interrupted job the queue waits for (resume or cancel it, or
    /// `job.start_next`); null when the queue runs.
    #[serde(default)]
    pub queue_held_by: Option<u32>,
    /// While connected, why the machine does not answer as it should (a G-code firmware
    /// silent past its line's `ok`, being asked where it is); null while it answers.
    #[serde(default)]
    pub link_problem: Option<String>,
    /// Times the machine ran out of moves while a job still had moves to stream.
    pub underruns: u64,
    /// Frames retransmitted on the link.
    pub frames_retransmitted: u64,
    /// Smoothed round-trip time on the link (ms).
    pub srtt_ms: f64,
}

/// `machine.status`: the snapshot and the active job's progress (null when none).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MachineStatus {
    /// The snapshot's fields.
    #[serde(flatten)]
    pub machine: MachineSnapshot,
    /// The active job's progress.
    pub progress: Option<Progress>,
}

/// What an e-stop measured (`machine.estop`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct EStopTiming {
    /// From the request reaching the streamer to the frame written to the port (µs).
    pub written_after_us: u64,
    /// From the request to the machine's acknowledgement (µs), if it came within 1 s.
    pub acked_after_us: Option<u64>,
}
