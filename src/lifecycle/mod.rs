//! The job lifecycle as a sans-IO state machine: which job the machine works on, how it
//! starts, holds, stops, resumes and ends, and what must be written, sent and told on
//! the way. It is driven the way [`crate::link::Host`] is — the caller owns the port,
//! the store, the planner workers and the clock:
//!
//! ```text
//! loop {
//!     lifecycle.handle(event, now_us);                 // machine, operator, planner, store
//!     lifecycle.handle_timeout(now_us);                // when next_timeout() passed
//!     while let Some(a) = lifecycle.poll_action() { carry it out }
//!     while the link has room { send lifecycle.poll_move() }
//!     sleep until lifecycle.next_timeout() or the next event
//! }
//! ```
//!
//! It knows no wire protocol: events speak of the machine (connected, status, fault,
//! reset, silent, port lost, command acknowledged), of operators' commands, of the
//! planner's output and of the store's writes and reads; actions are commands to the
//! machine ([`MachineCommand`]: e-stop, feed hold, resume, clear faults, status query),
//! moves ([`Lifecycle::poll_move`]), records to persist, reads, replies and
//! notifications. In edod the streamer pumps it, and an adapter (`adapter::EdoLink`,
//! `adapter::GcodeLink`) translates the link's events into these and the machine commands into link calls.
//!
//! Job states (stored, shown to operators): queued → planning → printing ⇄ paused, →
//! interrupted (reset, lost link or port, e-stop, edod stopped) → printing again on
//! resume, and done, failed or cancelled at the end. Underneath, the active job is in
//! one [`Phase`]: restarting it from its checkpoint (after a reset, a lost link, an
//! e-stop, an edod restart, or a syringe refill) is one procedure:
//! 1. *flush* ([`MachineCommand::Flush`]: the edo machine e-stops, dropping its queue
//!    and aborting the current move; a G-code firmware runs the lines in flight), wait
//!    for its acknowledgement and for a status in `EStopped`: the last executed move is
//!    final;
//! 2. *release*: clear faults, resume, wait for its acknowledgement;
//! 3. *prelude*: service moves (job id 0): home, prime, travel (lifted) to where the last
//!    executed move ended, layer mark;
//! 4. stream the job from the first move not executed (the planner regenerates the plan
//!    and skips what was executed).
//!
//! A cancel is the same flush and release, then retract and park instead of continuing.
//!
//! Progress is what the machine reports executed, never what was sent. State changes
//! take effect on the machine at once; they are persisted with the job's checkpoint
//! ([`Action::Persist`]) and told to clients ([`Action::JobState`]) once the store says
//! they are on disk ([`Event::Stored`]). A pause, resume or cancel is answered when its
//! state is stored, or after [`Options::reply_wait_us`] with `stored: false`.

mod active;
mod flow;
mod io;
mod job;
mod machine;
mod operator;
mod options;
mod persist;
mod service;
#[cfg(test)]
mod tests;

use std::collections::{BTreeSet, VecDeque};

pub use active::{AfterFlush, Phase};
pub use io::{
    Action, Answer, Applied, Command, Event, JobUpdate, Level, MachineCommand, MachineFault,
    MachineReport, MachineState, MoveRef, PlannerOutput, Record, Refusal, RefusalKind, RequestId,
    ResumePoint, StateNote, Underrun,
};
pub use job::{
    time_left_planned_s, time_left_s, Checkpoint, JobInfo, JobState, Progress, SERVICE_JOB_ID,
};
pub use options::{Options, ServiceMoves};

use crate::machine::Move;
use active::Active;
use job::Jobs;

/// A job that is not active but whose moves the machine may still be executing (after
/// an edod restart): its checkpoint follows the machine's reports.
#[derive(Debug, Clone, PartialEq)]
struct Tracked {
    id: u32,
    checkpoint: Checkpoint,
    dirty: bool,
    saved_at_us: u64,
}

/// Where a shutdown is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stopping {
    /// Waiting (until `until_us`) for the machine to hold.
    Holding { until_us: u64 },
    /// Waiting (until `until_us`) for everything up to `seq` to be stored.
    Storing { seq: u64, until_us: u64 },
    /// Answered.
    Finished,
}

/// A reply that waits for a state to be stored.
#[derive(Debug, Clone, PartialEq)]
struct WaitingReply {
    request: RequestId,
    job_id: u32,
    seq: u64,
    state: JobState,
    until_us: u64,
}

/// The store's writes fail: since when, and the warnings about it.
#[derive(Debug, Clone, PartialEq)]
struct StoreFailing {
    /// The last failure's cause ("disk full", …).
    cause: String,
    /// Only another process's write lock (the writes wait, they do not fail).
    busy: bool,
    /// Failed tries in all.
    tries: u64,
    /// When the last warning was logged, and the failed tries not logged since.
    warned_at_us: u64,
    not_warned: u64,
}

/// The job lifecycle. See the module docs.
#[derive(Debug)]
pub struct Lifecycle {
    opts: Options,
    /// The machine answers (handshake done, link alive).
    connected: bool,
    /// Its last report.
    status: MachineReport,
    jobs: Jobs,
    active: Option<Active>,
    tracked: Option<Tracked>,
    /// Service moves to send before any job move.
    outbox: VecDeque<Move>,
    actions: VecDeque<Action>,
    /// Sequence number of the last record handed out.
    last_seq: u64,
    /// Every record up to this one is on disk.
    stored_upto: u64,
    /// State notifications waiting for their record (sequence number, note).
    notes: VecDeque<(u64, StateNote)>,
    waiting_replies: Vec<WaitingReply>,
    /// The store's writes fail (until it reports everything stored).
    store_failing: Option<StoreFailing>,
    /// Commands waiting for their job to be read from the store.
    parked: Vec<(RequestId, Command)>,
    /// Jobs being read.
    looking_up: BTreeSet<u32>,
    /// The job the machine executed last, read because it connected naming it.
    connect_lookup: Option<u32>,
    service: service::Indices,
    planner_runs: u64,
    underruns: u64,
    stopping: Option<(RequestId, Stopping)>,
    last_progress: Option<Progress>,
    progress_at_us: u64,
}

impl Lifecycle {
    /// A lifecycle at `now_us` whose service moves start at index `service_index`, the
    /// store having reserved the indices up to `service_reserved_until`. Its first
    /// action asks for the queued jobs.
    pub fn new(opts: Options, service_index: u32, service_reserved_until: u32) -> Self {
        let mut lc = Self {
            service: service::Indices::new(
                service_index,
                service_reserved_until,
                opts.service_index_block,
            ),
            opts,
            connected: false,
            status: MachineReport::default(),
            jobs: Jobs::default(),
            active: None,
            tracked: None,
            outbox: VecDeque::new(),
            actions: VecDeque::new(),
            last_seq: 0,
            stored_upto: 0,
            notes: VecDeque::new(),
            waiting_replies: Vec::new(),
            store_failing: None,
            parked: Vec::new(),
            looking_up: BTreeSet::new(),
            connect_lookup: None,
            planner_runs: 0,
            underruns: 0,
            stopping: None,
            last_progress: None,
            progress_at_us: 0,
        };
        lc.actions.push_back(Action::ListQueued);
        lc
    }

    /// Take in `event` at `now_us`.
    pub fn handle(&mut self, event: Event, now_us: u64) {
        if self.is_stopped() {
            if let Event::Command { request, .. } = event {
                self.actions.push_back(Action::Reply {
                    request,
                    result: Err(Refusal::new(RefusalKind::Internal, "edod is stopping")),
                });
            }
            return;
        }
        if let Some(a) = self.active.as_mut() {
            a.count_running(now_us);
        }
        match event {
            Event::MachineConnected(r) => self.on_connected(r, now_us),
            Event::MachineStatus(r) => self.on_status(r, now_us),
            Event::MachineFault(f) => self.on_fault(f),
            Event::MachineReset { last_executed } => self.on_reset(last_executed, now_us),
            Event::LinkSilent => self.on_disconnected("link to the machine lost"),
            Event::LinkRestored => self.connected = true,
            Event::PortLost { why } => {
                self.log(Level::Warn, None, format!("serial port lost: {why}"));
                self.on_disconnected("serial port lost");
            }
            Event::MachineIncompatible => {
                self.connected = false;
                self.outbox.clear();
            }
            Event::CommandAcked(c) => self.on_acked(c),
            Event::MoveRefused { mv, reason } => self.on_move_refused(mv, &reason),
            Event::Command { request, command } => {
                if !self.refused_while_store_fails(request, command) {
                    self.on_command(request, command, now_us);
                }
            }
            Event::Submitted => self.actions.push_back(Action::ListQueued),
            Event::Planner { run, output } => self.on_planner(run, output, now_us),
            Event::QueuedJobs(r) => self.on_queued_jobs(r),
            Event::JobLookedUp { id, job } => self.on_looked_up(id, job, now_us),
            Event::Stored { upto } => self.on_stored(upto),
            Event::StoreFailed { error, busy } => self.on_store_failed(error, busy, now_us),
        }
        self.advance(now_us);
    }

    /// Run the timers due at `now_us`.
    pub fn handle_timeout(&mut self, now_us: u64) {
        if self.is_stopped() {
            return;
        }
        if let Some(a) = self.active.as_mut() {
            a.count_running(now_us);
        }
        self.expire_replies(now_us);
        self.advance(now_us);
    }

    /// When [`Lifecycle::handle_timeout`] is next due, if anything waits.
    pub fn next_timeout(&self) -> Option<u64> {
        if self.is_stopped() {
            return None;
        }
        let mut t: Option<u64> = None;
        let mut consider = |x: u64| t = Some(t.map_or(x, |t| t.min(x)));
        for r in &self.waiting_replies {
            consider(r.until_us);
        }
        match self.stopping {
            Some((_, Stopping::Holding { until_us } | Stopping::Storing { until_us, .. })) => {
                consider(until_us)
            }
            Some((_, Stopping::Finished)) | None => {}
        }
        if let Some(a) = &self.active {
            if a.dirty {
                consider(a.saved_at_us + self.opts.checkpoint_every_us);
            }
            consider(self.progress_at_us + self.opts.progress_every_us);
        }
        if let Some(t) = self.tracked.as_ref().filter(|t| t.dirty) {
            consider(t.saved_at_us + self.opts.checkpoint_every_us);
        }
        t
    }

    /// The next thing to do.
    pub fn poll_action(&mut self) -> Option<Action> {
        self.actions.pop_front()
    }

    /// Whether actions wait to be polled.
    pub fn has_actions(&self) -> bool {
        !self.actions.is_empty()
    }

    /// The next move to send, while the link has room: service moves first, then the
    /// active job's while it streams. `None` while the machine is not connected, and
    /// for a job that has not started moving while the store cannot write.
    pub fn poll_move(&mut self) -> Option<Move> {
        if !self.connected || self.is_stopped() {
            return None;
        }
        if let Some(m) = self.outbox.pop_front() {
            return Some(m);
        }
        let cannot_write = self.store_cannot_write().is_some();
        let a = self
            .active
            .as_mut()
            .filter(|a| a.phase == Phase::Streaming && (a.printing || !cannot_write))?;
        let mv = a.queue.pop_front()?;
        a.sent.push_back(mv.clone());
        if !a.printing {
            a.printing = true;
            let id = a.id;
            if self.jobs.get(id).map(|k| k.state) == Some(JobState::Planning) {
                self.set_state(id, JobState::Printing, None, false);
            }
        }
        Some(mv)
    }

    /// Whether the active job's planner output is wanted now (fewer than
    /// [`Options::moves_waiting_max`] moves wait here).
    pub fn wants_planner_output(&self) -> bool {
        self.active
            .as_ref()
            .is_some_and(|a| a.planner_run.is_some() && a.queue.len() < self.opts.moves_waiting_max)
    }

    /// The machine answers.
    pub fn is_connected(&self) -> bool {
        self.connected
    }

    /// The interrupted job that holds the queue: while a job is interrupted and not
    /// active (edod restarted), the next queued job waits for the operator to resume
    /// or cancel it, or to start the next one anyway (`job.start_next`), so that no job
    /// is printed onto a half-finished part.
    pub fn queue_held_by(&self) -> Option<u32> {
        if self.active.is_some() {
            return None;
        }
        self.jobs.first_in(JobState::Interrupted)
    }

    /// Why the job store cannot write (a full disk: "disk full"), while it cannot; a
    /// store only waiting for another process's lock is not a problem here.
    pub fn store_problem(&self) -> Option<&str> {
        self.store_cannot_write()
    }

    /// The oldest queued job.
    pub fn first_queued(&self) -> Option<u32> {
        self.jobs.first_queued()
    }

    /// The job the machine works on.
    pub fn active_job(&self) -> Option<u32> {
        self.active.as_ref().map(|a| a.id)
    }

    /// The active job's phase.
    pub fn phase(&self) -> Option<Phase> {
        self.active.as_ref().map(|a| a.phase)
    }

    /// A job's state as the lifecycle knows it (ahead of the store while it writes).
    pub fn job_state(&self, id: u32) -> Option<JobState> {
        self.jobs.get(id).map(|k| k.state)
    }

    /// Times the machine ran out of moves while a job still had moves to stream.
    pub fn underruns(&self) -> u64 {
        self.underruns
    }

    /// Moves waiting here for the link.
    pub fn moves_waiting(&self) -> usize {
        self.active.as_ref().map_or(0, |a| a.queue.len()) + self.outbox.len()
    }

    /// A shutdown has been answered: nothing more happens.
    pub fn is_stopped(&self) -> bool {
        matches!(self.stopping, Some((_, Stopping::Finished)))
    }

    /// Everything that is due whatever the event: the shutdown's progress, the next
    /// job, the prelude, checkpoints and progress.
    fn advance(&mut self, now_us: u64) {
        self.advance_shutdown(now_us);
        if self.is_stopped() {
            return;
        }
        // While the store cannot write, no job starts or continues (a state change it
        // would need could not be made durable); one whose change is not is held.
        let cannot_write = self.store_cannot_write().is_some();
        self.hold_for_store();
        if self.connected
            && self.stopping.is_none()
            && self.active.is_none()
            && !cannot_write
            && self.queue_held_by().is_none()
        {
            if let Some(id) = self.jobs.first_queued() {
                self.activate(id, true, now_us);
            }
        }
        if self.connected
            && !cannot_write
            && self.active.as_ref().is_some_and(|a| {
                a.phase == Phase::Prelude
                    && (a.resume_point.is_some() || a.checkpoint.next_index == 0)
            })
        {
            self.send_prelude();
        }
        self.save_checkpoints(false, now_us);
        self.publish_progress(false, now_us);
    }

    fn log(&mut self, level: Level, job: Option<u32>, message: impl Into<String>) {
        self.actions.push_back(Action::Log {
            level,
            job,
            message: message.into(),
        });
    }

    fn machine(&mut self, c: MachineCommand) {
        if matches!(c, MachineCommand::EmergencyStop | MachineCommand::Flush) {
            // Service moves not yet sent are for a state the stop ends.
            self.outbox.clear();
        }
        self.actions.push_back(Action::Machine(c));
    }
}
