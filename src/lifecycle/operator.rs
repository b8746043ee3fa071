//! Operators' commands (pause, resume, cancel, e-stop, refill, shutdown), and the store
//! reads some of them wait for: a command about a job the lifecycle does not know waits
//! until the job is read, and the commands after it about the same job wait behind it,
//! so they take effect in the order given.

use super::active::{AfterFlush, Phase};
use super::io::{
    Action, Answer, Applied, Command, Level, MachineCommand, MachineState, Refusal, RefusalKind,
    RequestId,
};
use super::job::{JobInfo, JobState};
use super::{Lifecycle, Stopping};

fn bad_state(message: String) -> Refusal {
    Refusal::new(RefusalKind::BadState, message)
}

impl Lifecycle {
    pub(super) fn on_command(&mut self, request: RequestId, command: Command, now_us: u64) {
        if let Some(id) = command.job() {
            let behind = self.parked.iter().any(|(_, c)| c.job() == Some(id));
            if behind || (!self.jobs.knows(id) && self.active_job() != Some(id)) {
                self.parked.push((request, command));
                self.look_up(id);
                return;
            }
        }
        self.run_command(request, command, now_us);
    }

    fn run_command(&mut self, request: RequestId, command: Command, now_us: u64) {
        let result = match command {
            Command::Pause(id) => self.pause(request, id, now_us),
            Command::Resume(id) => self.resume(request, id, now_us),
            Command::Cancel(id) => self.cancel(request, id, now_us),
            Command::StartNext(id) => self.start_next(request, id, now_us),
            Command::EStop => {
                self.estop();
                Ok(Some(Answer::Done))
            }
            Command::Refill => self.refill().map(|()| Some(Answer::Done)),
            Command::Shutdown => {
                self.shutdown(request, now_us);
                Ok(None)
            }
        };
        match result {
            Ok(None) => {}
            Ok(Some(answer)) => self.actions.push_back(Action::Reply {
                request,
                result: Ok(answer),
            }),
            Err(refusal) => self.actions.push_back(Action::Reply {
                request,
                result: Err(refusal),
            }),
        }
    }

    /// Ask the store for job `id` (once while a read is under way).
    pub(super) fn look_up(&mut self, id: u32) {
        if self.looking_up.insert(id) {
            self.actions.push_back(Action::LookUpJob(id));
        }
    }

    pub(super) fn on_looked_up(
        &mut self,
        id: u32,
        job: Result<Option<JobInfo>, String>,
        now_us: u64,
    ) {
        self.looking_up.remove(&id);
        let failed = match job {
            Ok(Some(info)) if info.id == id => {
                self.jobs.learn(info);
                None
            }
            Ok(_) => None,
            Err(e) => Some(e),
        };
        let (mine, others): (Vec<_>, Vec<_>) = std::mem::take(&mut self.parked)
            .into_iter()
            .partition(|(_, c)| c.job() == Some(id));
        self.parked = others;
        for (request, command) in mine {
            match &failed {
                Some(e) => self.actions.push_back(Action::Reply {
                    request,
                    result: Err(Refusal::new(
                        RefusalKind::Internal,
                        format!("cannot read job {id}: {e}"),
                    )),
                }),
                None => self.run_command(request, command, now_us),
            }
        }
        if self.connect_lookup == Some(id) {
            self.connect_lookup = None;
            if self.active.is_none() && self.connected {
                let report = self.status.clone();
                self.check_last_job(id, &report, false);
            }
        }
    }

    pub(super) fn on_queued_jobs(&mut self, jobs: Result<Vec<JobInfo>, String>) {
        match jobs {
            Ok(list) => {
                for info in list {
                    self.jobs.learn(info);
                }
            }
            Err(e) => self.log(
                Level::Warn,
                None,
                format!("cannot read the queued jobs: {e}"),
            ),
        }
    }

    fn need_connected(&self) -> Result<(), Refusal> {
        if self.connected {
            Ok(())
        } else {
            Err(Refusal::new(
                RefusalKind::NotConnected,
                "the machine is not connected",
            ))
        }
    }

    /// The job's state, for refusals: `Err` if there is no such job.
    fn known_state(&self, id: u32) -> Result<JobState, Refusal> {
        self.jobs
            .get(id)
            .map(|k| k.state)
            .ok_or_else(|| Refusal::new(RefusalKind::NoSuchJob, format!("no job {id}")))
    }

    fn pause(
        &mut self,
        request: RequestId,
        id: u32,
        now_us: u64,
    ) -> Result<Option<Answer>, Refusal> {
        match self.active.as_mut().filter(|a| a.id == id) {
            Some(a) if a.phase == Phase::Streaming => {
                a.phase = Phase::Holding;
                self.machine(MachineCommand::FeedHold);
                self.set_state(
                    id,
                    JobState::Paused,
                    Some("paused by an operator".into()),
                    true,
                );
                self.reply_applied(request, id, now_us);
                Ok(None)
            }
            Some(a) if a.phase.stopping_or_starting() => Err(bad_state(format!(
                "job {id} is starting or stopping (the machine is flushing or the nozzle \
                 moves to where it stopped); pause it once it prints"
            ))),
            Some(_) => Err(bad_state(format!("job {id} is not printing"))),
            None => Err(bad_state(format!(
                "job {id} is {}, only a printing job can be paused",
                self.known_state(id)?.as_str()
            ))),
        }
    }

    fn resume(
        &mut self,
        request: RequestId,
        id: u32,
        now_us: u64,
    ) -> Result<Option<Answer>, Refusal> {
        if let Some(a) = self.active.as_mut().filter(|a| a.id == id) {
            match a.phase {
                Phase::Holding => {
                    self.need_connected()?;
                    if let Some(a) = self.active.as_mut() {
                        a.phase = Phase::Streaming;
                    }
                    self.machine(MachineCommand::Resume);
                }
                Phase::Interrupted => {
                    self.need_connected()?;
                    self.restart_active(AfterFlush::Continue);
                }
                Phase::Empty => {
                    return Err(bad_state(format!(
                        "job {id} waits for a syringe: swap it, then machine.refill"
                    )))
                }
                _ => return Err(bad_state(format!("job {id} is already printing"))),
            }
            self.set_state(id, JobState::Printing, None, false);
            self.reply_applied(request, id, now_us);
            return Ok(None);
        }
        let state = self.known_state(id)?;
        if !matches!(state, JobState::Interrupted | JobState::Paused) {
            return Err(bad_state(format!(
                "job {id} is {}, only a paused or interrupted job can be resumed",
                state.as_str()
            )));
        }
        if let Some(other) = self.active_job() {
            return Err(bad_state(format!(
                "job {other} holds the machine; cancel it or let it finish first"
            )));
        }
        self.need_connected()?;
        self.activate(id, false, now_us);
        self.reply_applied(request, id, now_us);
        Ok(None)
    }

    fn cancel(
        &mut self,
        request: RequestId,
        id: u32,
        now_us: u64,
    ) -> Result<Option<Answer>, Refusal> {
        if self.active_job() == Some(id) {
            if self.connected {
                // Where the job stopped is kept; the flush makes it final. The reply
                // names the state the cancel leads to, not yet on disk: the job is
                // cancelled once the machine has stopped and parked.
                self.save_checkpoints(true, now_us);
                self.restart_active(AfterFlush::Park);
                if let Some(cause) = self.store_cannot_write() {
                    return Err(Refusal::new(
                        RefusalKind::StoreCannotWrite,
                        format!(
                            "job store cannot write: {cause}; job {id} is being cancelled on \
                             the machine but that is not on disk: it is written once the \
                             store can write again (free space for edod's state directory)"
                        ),
                    ));
                }
                return Ok(Some(Answer::Applied(Applied {
                    state: JobState::Cancelled,
                    stored: false,
                })));
            }
            self.end_active(JobState::Cancelled, Some("cancelled by an operator".into()));
            self.reply_applied(request, id, now_us);
            return Ok(None);
        }
        let state = self.known_state(id)?;
        if state.is_final() {
            return Err(bad_state(format!("job {id} is already {}", state.as_str())));
        }
        self.set_state(
            id,
            JobState::Cancelled,
            Some("cancelled by an operator".into()),
            false,
        );
        if self.tracked.as_ref().is_some_and(|t| t.id == id) {
            self.tracked = None;
            let s = &self.status;
            let running = s.state == MachineState::Running || s.queued > 0;
            if self.connected && running && s.last_executed.is_some_and(|m| m.job_id == id) {
                // The machine still runs moves of the job (edod restarted meanwhile).
                self.machine(MachineCommand::EmergencyStop);
            }
        }
        self.reply_applied(request, id, now_us);
        Ok(None)
    }

    /// `job.start_next`: start queued job `id` now, although an unfinished job holds the
    /// queue ([`Lifecycle::queue_held_by`]): the operator says the machine is ready for it.
    fn start_next(
        &mut self,
        request: RequestId,
        id: u32,
        now_us: u64,
    ) -> Result<Option<Answer>, Refusal> {
        let state = self.known_state(id)?;
        if state != JobState::Queued {
            return Err(bad_state(format!(
                "job {id} is {}, only a queued job can be started",
                state.as_str()
            )));
        }
        if let Some(other) = self.active_job() {
            return Err(bad_state(format!(
                "job {other} holds the machine; cancel it or let it finish first"
            )));
        }
        if self.stopping.is_some() {
            return Err(bad_state("edod is stopping".into()));
        }
        self.need_connected()?;
        if let Some(held) = self.queue_held_by() {
            self.log(
                Level::Info,
                Some(id),
                format!("job {id} starts by an operator's word while job {held} is interrupted"),
            );
        }
        self.activate(id, true, now_us);
        self.reply_applied(request, id, now_us);
        Ok(None)
    }

    /// Emergency stop: the machine stops now; a job moving is interrupted (a cancel
    /// under way ends unparked).
    fn estop(&mut self) {
        self.machine(MachineCommand::EmergencyStop);
        if self
            .active
            .as_ref()
            .is_some_and(|a| !a.phase.waits_for_operator())
        {
            self.interrupt("emergency stop by an operator");
        }
    }

    fn refill(&mut self) -> Result<(), Refusal> {
        self.need_connected()?;
        match self.active.as_ref().filter(|a| a.phase == Phase::Empty) {
            Some(a) => {
                let id = a.id;
                self.restart_active(AfterFlush::Continue);
                self.set_state(id, JobState::Printing, None, false);
            }
            None => self.machine(MachineCommand::ClearFaults),
        }
        Ok(())
    }

    /// Hold the machine, then interrupt the job ("edod stopped") and answer once that is
    /// stored, or after the waits of [`super::Options`].
    fn shutdown(&mut self, request: RequestId, now_us: u64) {
        self.log(Level::Info, None, "stopping: hold, checkpoint, exit");
        if let Some(a) = self.active.as_mut().filter(|a| a.phase == Phase::Streaming) {
            a.phase = Phase::Holding;
            self.machine(MachineCommand::FeedHold);
        }
        if self.stopping.is_none() {
            let until_us = now_us.saturating_add(self.opts.shutdown_hold_us);
            self.stopping = Some((request, Stopping::Holding { until_us }));
        } else {
            // A second shutdown: answered at once, the first one goes on.
            self.actions.push_back(Action::Reply {
                request,
                result: Ok(Answer::Done),
            });
        }
    }

    /// Where the shutdown is: once the machine holds (or it waited long enough) the job
    /// is interrupted; once that is stored (or it waited long enough) it is answered.
    pub(super) fn advance_shutdown(&mut self, now_us: u64) {
        let Some((request, stage)) = self.stopping else {
            return;
        };
        if let Stopping::Holding { until_us } = stage {
            let held = self.active.is_none()
                || !self.connected
                || self.status.state != MachineState::Running;
            if !held && now_us < until_us {
                return;
            }
            self.interrupt_for_shutdown();
            self.save_checkpoints(true, now_us);
            let until_us = now_us.saturating_add(self.opts.shutdown_store_wait_us);
            let seq = self.last_seq;
            self.stopping = Some((request, Stopping::Storing { seq, until_us }));
        }
        if let Some((_, Stopping::Storing { seq, until_us })) = self.stopping {
            if self.stored_upto < seq && now_us < until_us {
                return;
            }
            if self.stored_upto < seq {
                self.log(
                    Level::Warn,
                    self.active_job(),
                    "stopping before the job's state is on disk",
                );
            }
            self.stopping = Some((request, Stopping::Finished));
            self.actions.push_back(Action::Reply {
                request,
                result: Ok(Answer::Done),
            });
        }
    }

    fn interrupt_for_shutdown(&mut self) {
        if self.active.as_ref().is_some_and(|a| a.phase.cancelling()) {
            self.interrupt("edod stopped");
        }
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if !a.phase.waits_for_operator() {
            a.phase = Phase::Interrupted;
        }
        let id = a.id;
        self.stop_planner();
        self.set_state(id, JobState::Interrupted, Some("edod stopped".into()), true);
    }
}
