//! The active job's transitions: start, restart from its checkpoint, interruption,
//! failure and end, and the planner's output.

use super::active::{Active, AfterFlush, Phase};
use super::io::JobUpdate;
use super::io::{Action, Level, MachineCommand, MachineState, PlannerOutput, Record};
use super::job::JobState;
use super::Lifecycle;

impl Lifecycle {
    /// Make job `id` active from its checkpoint. `fresh`: never started before.
    pub(super) fn activate(&mut self, id: u32, fresh: bool, now_us: u64) {
        let Some(known) = self.jobs.get(id).cloned() else {
            return;
        };
        let mut checkpoint = known.checkpoint;
        if let Some(t) = self.tracked.take_if(|t| t.id == id) {
            if t.checkpoint.next_index > checkpoint.next_index {
                checkpoint = t.checkpoint;
            }
        }
        let clean = self.status.state == MachineState::Idle
            && self.status.queued == 0
            && self.status.faults == 0;
        let phase = if fresh && clean {
            Phase::Streaming
        } else {
            Phase::Flushing {
                acked: false,
                then: AfterFlush::Continue,
            }
        };
        self.log(
            Level::Info,
            Some(id),
            format!(
                "job {id} starts from move {} ({phase:?})",
                checkpoint.next_index
            ),
        );
        self.active = Some(Active::new(
            id,
            phase,
            checkpoint,
            known.total_moves,
            known.submitted_ms,
            now_us,
        ));
        if phase == Phase::Streaming {
            self.start_planner();
        } else {
            self.machine(MachineCommand::Flush);
        }
        let state = if fresh {
            JobState::Planning
        } else {
            JobState::Printing
        };
        self.set_state(id, state, None, false);
    }

    /// Stop the machine and start the active job again from its checkpoint once the stop
    /// made it final; `then` says what follows.
    pub(super) fn restart_active(&mut self, then: AfterFlush) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        a.forget_moves();
        a.phase = Phase::Flushing { acked: false, then };
        // The planner starts again once the flush has made the checkpoint final.
        self.stop_planner();
        self.machine(MachineCommand::Flush);
    }

    pub(super) fn start_planner(&mut self) {
        self.planner_runs += 1;
        let run = self.planner_runs;
        let Some(a) = self.active.as_mut() else {
            return;
        };
        a.planning_done = false;
        a.planner_run = Some(run);
        let (job_id, from_index) = (a.id, a.checkpoint.next_index);
        self.actions.push_back(Action::StartPlanner {
            job_id,
            from_index,
            run,
        });
    }

    pub(super) fn stop_planner(&mut self) {
        if let Some(a) = self.active.as_mut() {
            if a.planner_run.take().is_some() {
                self.actions.push_back(Action::StopPlanner);
            }
        }
    }

    /// The job moving stops where the machine is (a fault, a lost link, an e-stop): it
    /// is interrupted, or, if an operator's cancel was under way, cancelled unparked.
    pub(super) fn interrupt(&mut self, why: &str) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if a.phase == Phase::Interrupted {
            return;
        }
        let id = a.id;
        if a.phase.cancelling() {
            // The operator asked for the job to end: it does, without the park.
            self.log(
                Level::Warn,
                Some(id),
                format!("cancel of job {id} interrupted before the nozzle was parked: {why}"),
            );
            self.end_active(
                JobState::Cancelled,
                Some(format!("cancelled by an operator; not parked: {why}")),
            );
            return;
        }
        a.phase = Phase::Interrupted;
        a.forget_moves();
        self.stop_planner();
        self.log(
            Level::Warn,
            Some(id),
            format!("job {id} interrupted: {why}"),
        );
        self.set_state(id, JobState::Interrupted, Some(why.to_string()), true);
    }

    /// The active job ends in `state`: its checkpoint and state are persisted.
    pub(super) fn end_active(&mut self, state: JobState, reason: Option<String>) {
        let Some(id) = self.active_job() else {
            return;
        };
        self.stop_planner();
        self.set_state(id, state, reason, true);
        self.active = None;
        self.actions.push_back(Action::Progress(None));
        self.last_progress = None;
    }

    /// The active job cannot go on: it fails, and the moves the machine still has of
    /// it are stopped.
    pub(super) fn fail_active(&mut self, id: u32, why: String) {
        self.log(Level::Warn, Some(id), format!("job {id} failed: {why}"));
        self.end_active(JobState::Failed, Some(why));
        if self.status.queued > 0 || self.status.state == MachineState::Running {
            self.machine(MachineCommand::EmergencyStop);
        }
    }

    pub(super) fn check_done(&mut self, now_us: u64) {
        let Some(a) = self.active.as_ref().filter(|a| a.finished()) else {
            return;
        };
        let (id, total) = (a.id, a.total.unwrap_or(0));
        self.publish_progress(true, now_us);
        self.log(
            Level::Info,
            Some(id),
            format!("job {id} done: {total} moves"),
        );
        self.end_active(JobState::Done, None);
    }

    pub(super) fn on_planner(&mut self, run: u64, output: PlannerOutput, now_us: u64) {
        let Some(a) = self.active.as_mut().filter(|a| a.planner_run == Some(run)) else {
            return;
        };
        let id = a.id;
        match output {
            PlannerOutput::Ended => a.planner_run = None,
            PlannerOutput::Layers(count) => a.layers = Some(count),
            PlannerOutput::Moves(v) => a.queue.extend(v),
            PlannerOutput::ResumeAt(r) => a.resume_point = Some(r),
            PlannerOutput::Estimate(t) => {
                a.planned = Some(t);
                self.publish_progress(true, now_us);
            }
            PlannerOutput::Done { total } => {
                a.total = Some(total);
                a.planning_done = true;
                if let Some(k) = self.jobs.get_mut(id) {
                    k.total_moves = Some(total);
                }
                self.persist(Record::Job(JobUpdate {
                    job_id: id,
                    total_moves: Some(total),
                    ..JobUpdate::default()
                }));
                self.check_done(now_us);
            }
            PlannerOutput::Failed(e) => self.fail_active(id, e),
        }
    }
}
