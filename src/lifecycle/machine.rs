//! What the machine reports: connection, status (moves executed, the flush's end,
//! underruns, the job's end), faults, resets, lost links, acknowledged commands.

use super::active::{AfterFlush, Phase};
use super::io::{
    Action, Level, MachineCommand, MachineFault, MachineReport, MachineState, MoveRef, Underrun,
};
use super::job::{JobState, SERVICE_JOB_ID};
use super::{Lifecycle, Tracked};
use crate::machine::Move;

impl Lifecycle {
    pub(super) fn on_connected(&mut self, report: MachineReport, now_us: u64) {
        self.connected = true;
        if self.active.is_none() {
            if let Some(m) = report.last_executed {
                self.check_last_job(m.job_id, &report, true);
            }
        }
        self.on_status(report, now_us);
    }

    /// The machine connected with job `id`'s move as its last executed, no job being
    /// active: follow it if it was interrupted (edod restarted while the machine ran
    /// on), stop it if it was cancelled (its cancel's e-stop went with a lost port),
    /// read it first (`may_look_up`) if it is not known.
    pub(super) fn check_last_job(&mut self, id: u32, report: &MachineReport, may_look_up: bool) {
        if id == SERVICE_JOB_ID {
            return;
        }
        let running = report.state == MachineState::Running || report.queued > 0;
        match self.jobs.get(id).map(|k| (k.state, k.checkpoint.clone())) {
            Some((JobState::Interrupted, checkpoint)) => {
                if self.tracked.as_ref().is_none_or(|t| t.id != id) {
                    self.tracked = Some(Tracked {
                        id,
                        checkpoint,
                        dirty: false,
                        saved_at_us: 0,
                    });
                }
            }
            Some((JobState::Cancelled, _)) if running => {
                self.log(
                    Level::Warn,
                    Some(id),
                    format!(
                        "the machine still runs moves of cancelled job {id} ({} queued): e-stop",
                        report.queued
                    ),
                );
                self.machine(MachineCommand::EmergencyStop);
            }
            Some(_) => {}
            None if !may_look_up => {}
            None => {
                self.connect_lookup = Some(id);
                self.look_up(id);
            }
        }
    }

    pub(super) fn on_status(&mut self, report: MachineReport, now_us: u64) {
        if let Some(m) = report.last_executed {
            self.apply_executed(m, &report.remaining_nl, now_us);
        }
        let state = report.state;
        self.status = report;
        if let Some(a) = self.active.as_mut() {
            if let Phase::Flushing { acked: true, then } = a.phase {
                if state == MachineState::EStopped {
                    a.phase = Phase::Releasing { then };
                    self.machine(MachineCommand::ClearFaults);
                    self.machine(MachineCommand::Resume);
                }
            }
        }
        self.count_underrun();
        self.check_done(now_us);
    }

    /// Queue underrun: the machine ran dry while the job had moves left. Only once the
    /// machine has executed a move sent in this run: right after a (re)start it is idle
    /// because nothing has reached it yet, not because the host fell behind.
    fn count_underrun(&mut self) {
        let empty = self.status.queued == 0 && self.status.state == MachineState::Idle;
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let left = a.total.is_none_or(|t| a.checkpoint.next_index < t);
        if !(a.phase == Phase::Streaming && left && empty && a.ran) {
            a.machine_was_empty = false;
            return;
        }
        if a.machine_was_empty {
            return;
        }
        a.machine_was_empty = true;
        self.underruns += 1;
        let report = Underrun {
            job_id: a.id,
            executed: a.checkpoint.next_index,
            waiting_here: a.queue.len(),
            planner_running: a.planner_run.is_some(),
            count: self.underruns,
        };
        self.actions.push_back(Action::Underrun(report));
    }

    /// The machine executed move `m`: the active or the tracked job advances.
    pub(super) fn apply_executed(&mut self, m: MoveRef, remaining_nl: &[u32], now_us: u64) {
        if let Some(a) = self.active.as_mut().filter(|a| a.id == m.job_id) {
            if a.executed(m.index, remaining_nl) && a.first_move_after_ms.is_none() {
                let wall_ms = self.opts.wall_ms_at_zero + (now_us / 1000) as i64;
                a.first_move_after_ms = Some(wall_ms - a.submitted_ms);
            }
        } else if let Some(t) = self.tracked.as_mut().filter(|t| t.id == m.job_id) {
            if m.index >= t.checkpoint.next_index {
                t.checkpoint.next_index = m.index.saturating_add(1);
                t.checkpoint.remaining_nl = remaining_nl.to_vec();
                t.dirty = true;
            }
        }
    }

    pub(super) fn on_fault(&mut self, fault: MachineFault) {
        match fault {
            MachineFault::SyringeEmpty(n) => self.syringe_empty(n),
            MachineFault::EStopPressed => self.interrupt("e-stop pressed on the machine"),
            MachineFault::Other(what) => self.interrupt(&format!("machine fault {what}")),
        }
    }

    /// A syringe ran empty: a job moving waits for a refill.
    fn syringe_empty(&mut self, n: u8) {
        let name = self
            .opts
            .service
            .syringe_names
            .get(usize::from(n))
            .map_or_else(|| format!("{n}"), |s| format!("{n} ({s})"));
        let Some(a) = self
            .active
            .as_mut()
            .filter(|a| matches!(a.phase, Phase::Streaming | Phase::Holding))
        else {
            return;
        };
        a.phase = Phase::Empty;
        a.forget_moves();
        let id = a.id;
        self.stop_planner();
        self.set_state(
            id,
            JobState::Paused,
            Some(format!(
                "syringe {name} is empty: swap it, then machine.refill"
            )),
            true,
        );
    }

    pub(super) fn on_reset(&mut self, last_executed: Option<MoveRef>, now_us: u64) {
        self.log(
            Level::Warn,
            self.active_job(),
            format!("machine reset; last executed {last_executed:?}"),
        );
        if let Some(m) = last_executed {
            let remaining = self.status.remaining_nl.clone();
            self.apply_executed(m, &remaining, now_us);
        }
        self.on_disconnected("machine reset");
    }

    /// The machine cannot be reached: a job moving is interrupted.
    pub(super) fn on_disconnected(&mut self, why: &str) {
        self.connected = false;
        self.outbox.clear();
        self.interrupt(why);
    }

    pub(super) fn on_acked(&mut self, cmd: MachineCommand) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        match (a.phase, cmd) {
            (Phase::Flushing { acked: false, then }, MachineCommand::Flush) => {
                a.phase = Phase::Flushing { acked: true, then };
                self.machine(MachineCommand::QueryStatus);
            }
            (Phase::Releasing { then }, MachineCommand::Resume) => match then {
                AfterFlush::Continue => {
                    a.phase = Phase::Prelude;
                    self.start_planner();
                }
                AfterFlush::Park => self.park(),
            },
            _ => {}
        }
    }

    /// The link would not take `mv`: a job's move fails the job (it cannot be streamed),
    /// a service move is dropped.
    pub(super) fn on_move_refused(&mut self, mv: Move, reason: &str) {
        let Some(id) = self.active_job().filter(|&id| id == mv.job_id) else {
            self.log(
                Level::Warn,
                None,
                format!("move {}/{} refused: {reason}", mv.job_id, mv.index),
            );
            return;
        };
        self.fail_active(
            id,
            format!("move {} refused by the link: {reason}", mv.index),
        );
    }
}
