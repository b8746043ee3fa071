//! What goes into the lifecycle (events) and what comes out (actions), in terms of no
//! wire protocol: the pump translates its link's events into these and carries the
//! actions out on its link, its store and its clients.

use super::job::{Checkpoint, JobInfo, JobState, Progress};
pub use crate::machine::{MachineReport, MachineState, MoveRef};
use crate::machine::{Move, PositionUm};

/// A fault the machine reported.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MachineFault {
    /// A syringe ran empty (its number).
    SyringeEmpty(u8),
    /// The machine's own e-stop button.
    EStopPressed,
    /// Anything else, described for a person.
    Other(String),
}

/// A command to the machine other than a move. The stops and the resume go ahead of
/// every move already queued (the link's priority lane, or G-code's emergency commands).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MachineCommand {
    /// Stop now and drop the queue (moves arriving until `Resume` are dropped too).
    EmergencyStop,
    /// Make the active job's checkpoint final before it restarts or parks: the machine
    /// stops with nothing queued and reports `EStopped` (its last executed move is then
    /// final) until `Resume`. The edo link e-stops; a G-code firmware, whose `M112` only
    /// a reset undoes, drops the lines not sent and runs those in flight. Acknowledged
    /// as itself, never as an operator's e-stop.
    Flush,
    /// Hold at the next move boundary, keeping the queue.
    FeedHold,
    /// Leave feed hold or emergency stop.
    Resume,
    /// Clear latched faults (in order with the moves).
    ClearFaults,
    /// Ask for a status report.
    QueryStatus,
}

/// Identifies an operator's request; every one is answered by exactly one
/// [`Action::Reply`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct RequestId(pub u64);

/// An operator's command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// Hold a printing job at a move boundary.
    Pause(u32),
    /// Continue a paused or interrupted job.
    Resume(u32),
    /// Cancel a job (a printing one stops, retracts and parks).
    Cancel(u32),
    /// Start queued job `id` now although a job is interrupted: the operator's word that
    /// the machine is ready for it (the queue waits for it otherwise).
    StartNext(u32),
    /// Emergency stop now.
    EStop,
    /// The syringes were refilled: clear the faults, continue a job waiting for it.
    Refill,
    /// Hold, checkpoint, interrupt the job and answer once that is stored (or given up).
    Shutdown,
}

impl Command {
    /// The job the command is about.
    pub fn job(self) -> Option<u32> {
        match self {
            Command::Pause(id)
            | Command::Resume(id)
            | Command::Cancel(id)
            | Command::StartNext(id) => Some(id),
            Command::EStop | Command::Refill | Command::Shutdown => None,
        }
    }
}

/// Where a resumed job stands: what the moves before the resume index left behind.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ResumePoint {
    /// End position of the last skipped move that moves the nozzle.
    pub position: Option<PositionUm>,
    /// Last skipped layer mark (layer, z µm).
    pub layer_mark: Option<(u32, i32)>,
    /// Volumes of the last skipped extrusion.
    pub volumes_nl: Option<Vec<u32>>,
}

/// What a planner run produced.
#[derive(Debug, Clone, PartialEq)]
pub enum PlannerOutput {
    /// Where the job stands at the resume index (first, when resuming).
    ResumeAt(ResumePoint),
    /// The job has this many layers.
    Layers(u32),
    /// Moves to stream, in order.
    Moves(Vec<Move>),
    /// Every move is planned: the job has this many.
    Done {
        /// Total moves.
        total: u32,
    },
    /// The job's planned machine time, planned whole apart from the moves streamed
    /// (what progress and ETA are measured by).
    Estimate(crate::machine::time::PlannedTime),
    /// Planning failed.
    Failed(String),
    /// The planner stopped sending (after `Done`, `Failed`, or on its own).
    Ended,
}

/// Something that happened.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// The machine answered the handshake; its state then.
    MachineConnected(MachineReport),
    /// A status report.
    MachineStatus(MachineReport),
    /// A fault report.
    MachineFault(MachineFault),
    /// The machine reset (rebooted, or lost the session): its queue is gone.
    MachineReset {
        /// The last move it reported executed before.
        last_executed: Option<MoveRef>,
    },
    /// The machine went silent.
    LinkSilent,
    /// It answers again (same session).
    LinkRestored,
    /// The port itself went away (unplugged, closed).
    PortLost {
        /// Why, for the log.
        why: String,
    },
    /// The machine speaks a protocol we do not.
    MachineIncompatible,
    /// The machine confirmed a command ([`MachineCommand::Flush`] and
    /// [`MachineCommand::Resume`] move a restart on; an e-stop's is the operator's).
    CommandAcked(MachineCommand),
    /// The link would not take a move [`super::Lifecycle::poll_move`] gave.
    MoveRefused {
        /// The move.
        mv: Move,
        /// Why.
        reason: String,
    },
    /// An operator's command.
    Command {
        /// Answered with this id.
        request: RequestId,
        /// What to do.
        command: Command,
    },
    /// A job was submitted (the store has it as queued).
    Submitted,
    /// Output of planner run `run` ([`Action::StartPlanner`]).
    Planner {
        /// The run.
        run: u64,
        /// What it produced.
        output: PlannerOutput,
    },
    /// The queued and interrupted jobs, as [`Action::ListQueued`] asked.
    QueuedJobs(Result<Vec<JobInfo>, String>),
    /// Job `id` as the store has it (`None`: no such job), as [`Action::LookUpJob`] asked.
    JobLookedUp {
        /// The job asked for.
        id: u32,
        /// What the store said.
        job: Result<Option<JobInfo>, String>,
    },
    /// Every [`Action::Persist`] up to this sequence number is on disk.
    Stored {
        /// Sequence number.
        upto: u64,
    },
    /// A write failed (it is being tried again): every failed try is reported.
    StoreFailed {
        /// Why: "disk full", or the store's or the OS's error.
        error: String,
        /// Another process holds the store's write lock (the write waits for it); else
        /// the store cannot write (a full disk, an I/O error).
        busy: bool,
    },
}

/// A change to one job's stored record.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct JobUpdate {
    /// Job id.
    pub job_id: u32,
    /// Its latest checkpoint.
    pub checkpoint: Option<Checkpoint>,
    /// Its move count, once planned.
    pub total_moves: Option<u32>,
    /// Its new state, and why.
    pub state: Option<(JobState, Option<String>)>,
}

impl JobUpdate {
    /// `newer` over `self`: a field `newer` leaves unset keeps this one's.
    pub fn merged(self, newer: JobUpdate) -> JobUpdate {
        JobUpdate {
            job_id: newer.job_id,
            checkpoint: newer.checkpoint.or(self.checkpoint),
            total_moves: newer.total_moves.or(self.total_moves),
            state: newer.state.or(self.state),
        }
    }
}

/// Something to write to the store.
#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    /// A job's checkpoint, move count or state.
    Job(JobUpdate),
    /// Service move indices below this one may be in use: the next run starts here.
    ServiceIndices {
        /// First index not reserved.
        reserved_until: u32,
    },
}

/// What a pause, resume or cancel did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Applied {
    /// The job's state now.
    pub state: JobState,
    /// Whether that state is on disk (else it is being written, and its notification
    /// follows once it is).
    pub stored: bool,
}

/// The answer to a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// Pause, resume, cancel: what was done.
    Applied(Applied),
    /// E-stop, refill, shutdown: done.
    Done,
}

/// Why a command was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RefusalKind {
    /// No such job.
    NoSuchJob,
    /// The job's state does not allow it.
    BadState,
    /// The machine is not connected.
    NotConnected,
    /// The store could not be read.
    Internal,
    /// The store cannot write (a full disk): the change is not on disk (what took
    /// effect on the machine is said in the message), or it was not made.
    StoreCannotWrite,
}

/// A refused command.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refusal {
    /// Why.
    pub kind: RefusalKind,
    /// For a person: names the job, its state and what to do.
    pub message: String,
}

impl Refusal {
    pub(super) fn new(kind: RefusalKind, message: impl Into<String>) -> Self {
        Self {
            kind,
            message: message.into(),
        }
    }
}

/// A job's state changed (and is on disk).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StateNote {
    /// Job id.
    pub job_id: u32,
    /// New state.
    pub state: JobState,
    /// Why.
    pub reason: Option<String>,
}

/// The machine ran out of moves while the job had moves left.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Underrun {
    /// Job id.
    pub job_id: u32,
    /// Moves executed.
    pub executed: u32,
    /// Moves waiting in the lifecycle for the link.
    pub waiting_here: usize,
    /// Whether the planner still runs.
    pub planner_running: bool,
    /// Underruns since start.
    pub count: u64,
}

/// How much a log line matters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    /// Normal operation.
    Info,
    /// Something went wrong.
    Warn,
}

/// Something to do.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Send a command to the machine.
    Machine(MachineCommand),
    /// Start planning job `job_id` from move `from_index`; its output comes back as
    /// [`Event::Planner`] with `run` (a run replaces any before it).
    StartPlanner {
        /// Job id.
        job_id: u32,
        /// First move wanted (the ones before are skipped, see [`ResumePoint`]).
        from_index: u32,
        /// Run number.
        run: u64,
    },
    /// Stop the planner run.
    StopPlanner,
    /// Write `record`; [`Event::Stored`] with `seq` or later says it is on disk.
    Persist {
        /// Sequence number (increasing).
        seq: u64,
        /// What.
        record: Record,
    },
    /// Read job `id` from the store ([`Event::JobLookedUp`]).
    LookUpJob(u32),
    /// Read the queued and interrupted jobs from the store ([`Event::QueuedJobs`]).
    ListQueued,
    /// Answer request `request`.
    Reply {
        /// The request.
        request: RequestId,
        /// The answer.
        result: Result<Answer, Refusal>,
    },
    /// Tell the clients a job's state changed (sent once the change is on disk).
    JobState(StateNote),
    /// The active job's progress changed (`None`: no job is active any more).
    Progress(Option<Progress>),
    /// The machine's queue ran dry.
    Underrun(Underrun),
    /// Something to log.
    Log {
        /// How much it matters.
        level: Level,
        /// The job it is about.
        job: Option<u32>,
        /// What happened.
        message: String,
    },
}
