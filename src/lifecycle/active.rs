//! The active job: its phase, its moves waiting and sent, and its checkpoint as the
//! machine reports moves executed.

use std::collections::VecDeque;

use super::io::ResumePoint;
use super::job::Checkpoint;
use crate::machine::time::{add_used_nl, PlannedTime};
use crate::machine::{composition_of, Move, MoveKind};

/// What follows a flush.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AfterFlush {
    /// The prelude, then the job from its first move not executed.
    Continue,
    /// Retract and park: the job is cancelled.
    Park,
}

/// Where the active job is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// E-stop sent; waiting for its acknowledgement (`acked`) and then an `EStopped`
    /// status.
    Flushing {
        /// The e-stop was acknowledged.
        acked: bool,
        /// What follows.
        then: AfterFlush,
    },
    /// Resume sent after clearing faults; waiting for its acknowledgement.
    Releasing {
        /// What follows.
        then: AfterFlush,
    },
    /// Waiting for the planner's resume point to send the service prelude.
    Prelude,
    /// Moves flow.
    Streaming,
    /// Feed hold by the operator (or a shutdown).
    Holding,
    /// A syringe ran empty; waiting for a refill.
    Empty,
    /// Stopped by a fault; waiting for a resume.
    Interrupted,
}

impl Phase {
    /// Every phase.
    pub const ALL: [Phase; 11] = [
        Phase::Flushing {
            acked: false,
            then: AfterFlush::Continue,
        },
        Phase::Flushing {
            acked: true,
            then: AfterFlush::Continue,
        },
        Phase::Flushing {
            acked: false,
            then: AfterFlush::Park,
        },
        Phase::Flushing {
            acked: true,
            then: AfterFlush::Park,
        },
        Phase::Releasing {
            then: AfterFlush::Continue,
        },
        Phase::Releasing {
            then: AfterFlush::Park,
        },
        Phase::Prelude,
        Phase::Streaming,
        Phase::Holding,
        Phase::Empty,
        Phase::Interrupted,
    ];

    /// An operator's cancel is under way: the machine is being stopped before the
    /// nozzle retracts and parks.
    pub fn cancelling(self) -> bool {
        matches!(
            self,
            Phase::Flushing {
                then: AfterFlush::Park,
                ..
            } | Phase::Releasing {
                then: AfterFlush::Park
            }
        )
    }

    /// The machine is being flushed, released or brought back to where the job stopped:
    /// moves do not flow yet (or no more).
    pub fn stopping_or_starting(self) -> bool {
        matches!(
            self,
            Phase::Flushing { .. } | Phase::Releasing { .. } | Phase::Prelude
        )
    }

    /// Waiting for an operator (a refill or a resume).
    pub fn waits_for_operator(self) -> bool {
        matches!(self, Phase::Empty | Phase::Interrupted)
    }
}

/// The job the machine works on.
#[derive(Debug)]
pub(super) struct Active {
    pub id: u32,
    pub phase: Phase,
    /// The planner run producing its moves.
    pub planner_run: Option<u64>,
    pub planning_done: bool,
    pub resume_point: Option<ResumePoint>,
    /// Planned moves waiting for the link.
    pub queue: VecDeque<Move>,
    /// Moves sent and not reported executed.
    pub sent: VecDeque<Move>,
    pub total: Option<u32>,
    /// Layers in the job, once the planner knows.
    pub layers: Option<u32>,
    /// The layer the job (re)started at (0 before its first layer), for the estimate by
    /// layers.
    pub layer_at_start: u32,
    pub checkpoint: Checkpoint,
    pub saved_at_us: u64,
    /// The checkpoint moved since it was last persisted.
    pub dirty: bool,
    pub submitted_ms: i64,
    pub first_move_after_ms: Option<i64>,
    pub started_us: u64,
    pub executed_at_start: u32,
    /// The job's planned machine time, once the estimator planned it whole.
    pub planned: Option<PlannedTime>,
    /// Time spent printing since the job (re)started (not paused, interrupted or
    /// waiting for a refill), µs; counted up to `running_at_us`.
    pub running_us: u64,
    pub running_at_us: u64,
    pub machine_was_empty: bool,
    /// Moves have gone out since the job (re)started.
    pub printing: bool,
    /// The machine has executed a move sent since the job (re)started.
    pub ran: bool,
}

impl Active {
    pub fn new(
        id: u32,
        phase: Phase,
        checkpoint: Checkpoint,
        total: Option<u32>,
        submitted_ms: i64,
        now_us: u64,
    ) -> Self {
        Self {
            id,
            phase,
            planner_run: None,
            planning_done: false,
            resume_point: None,
            queue: VecDeque::new(),
            sent: VecDeque::new(),
            total,
            layers: None,
            layer_at_start: checkpoint.layer.unwrap_or(0),
            executed_at_start: checkpoint.next_index,
            checkpoint,
            planned: None,
            running_us: 0,
            running_at_us: now_us,
            saved_at_us: now_us,
            dirty: false,
            submitted_ms,
            first_move_after_ms: None,
            started_us: now_us,
            machine_was_empty: false,
            printing: false,
            ran: false,
        }
    }

    /// Drop what was planned and sent: the machine's queue is gone or going.
    pub fn forget_moves(&mut self) {
        self.queue.clear();
        self.sent.clear();
        self.resume_point = None;
        self.planning_done = false;
    }

    /// The machine executed move `index` (and every one before it), with `remaining_nl`
    /// left in the syringes. Returns whether the checkpoint moved.
    pub fn executed(&mut self, index: u32, remaining_nl: &[u32]) -> bool {
        if index < self.checkpoint.next_index {
            return false;
        }
        self.checkpoint.next_index = index.saturating_add(1);
        while self.sent.front().is_some_and(|m| m.index <= index) {
            if let Some(m) = self.sent.pop_front() {
                self.ran = true;
                add_used_nl(&mut self.checkpoint.used_nl, &m.kind);
                match &m.kind {
                    MoveKind::LayerMark { layer, .. } => self.checkpoint.layer = Some(*layer),
                    MoveKind::Extrude { volumes_nl, .. } => {
                        if let Some(c) = composition_of(volumes_nl) {
                            self.checkpoint.composition = Some(c);
                        }
                    }
                    _ => {}
                }
            }
        }
        self.checkpoint.remaining_nl = remaining_nl.to_vec();
        self.dirty = true;
        true
    }

    /// Count the time since the last event as printing if the job streamed (the phase
    /// changes only at events, so it held since the last).
    pub fn count_running(&mut self, now_us: u64) {
        if self.phase == Phase::Streaming {
            self.running_us += now_us.saturating_sub(self.running_at_us);
        }
        self.running_at_us = now_us;
    }

    /// Every move is planned and executed.
    pub fn finished(&self) -> bool {
        self.phase == Phase::Streaming
            && self.planning_done
            && self.total.is_some_and(|t| self.checkpoint.next_index >= t)
    }
}
