//! What is written and told: job states with their checkpoints, periodic checkpoints,
//! the notifications and replies that wait for their record to be on disk, progress;
//! and what happens while the store cannot write.
//!
//! A store that cannot write (a full disk, an I/O error; not another process's lock,
//! which only delays the writes) changes what may happen, since no state change can be
//! made durable meanwhile: the moves already planned of a job that is moving go on
//! (its checkpoints wait in the writer), but no job starts or continues (no queued job
//! is started, no prelude sent, a resume or a refill's continue refused), a job whose
//! state change is not on disk is held (paused, "job store cannot write: <cause>"), and
//! replies waiting for a state are answered with a refusal saying it is not on disk.
//! The failures are warned about at once, then at most every
//! [`STORE_WARN_EVERY_US`] with the count between. Once the store reports everything
//! stored it all catches up: the states go to disk in order, their notifications out,
//! and the next job may start.

use super::active::Phase;
use super::io::{
    Action, Answer, Applied, Command, JobUpdate, Level, MachineCommand, Record, Refusal,
    RefusalKind, RequestId, StateNote,
};
use super::job::{time_left_planned_s, time_left_s, JobState, Progress};
use super::{Lifecycle, StoreFailing, WaitingReply};

/// While the store's writes fail, a warning at most this often (µs).
pub const STORE_WARN_EVERY_US: u64 = 10_000_000;

impl Lifecycle {
    /// Hand `record` to the store; returns its sequence number.
    pub(super) fn persist(&mut self, record: Record) -> u64 {
        self.last_seq += 1;
        let seq = self.last_seq;
        self.actions.push_back(Action::Persist { seq, record });
        seq
    }

    /// Job `id` is in `state` now (why: `reason`). It is persisted, with the active job's
    /// checkpoint if `with_checkpoint` (the checkpoint the state was reached at), and
    /// told to the clients once on disk.
    pub(super) fn set_state(
        &mut self,
        id: u32,
        state: JobState,
        reason: Option<String>,
        with_checkpoint: bool,
    ) {
        // What the log (and the dashboard's console) says of a job pausing or
        // cancelled; done, failed and interrupted are logged where they happen.
        if matches!(state, JobState::Paused | JobState::Cancelled) {
            let why = reason.as_deref().unwrap_or("no reason given");
            let message = format!("job {id} {}: {why}", state.as_str());
            self.log(Level::Info, Some(id), message);
        }
        self.jobs.set_state(id, state);
        let mut checkpoint = None;
        if let Some(a) = self.active.as_mut().filter(|a| a.id == id) {
            if with_checkpoint {
                a.dirty = false;
                checkpoint = Some(a.checkpoint.clone());
            }
            if let Some(k) = self.jobs.get_mut(id) {
                k.checkpoint = a.checkpoint.clone();
            }
        } else if let Some(t) = self.tracked.as_mut().filter(|t| t.id == id) {
            t.dirty = false;
            checkpoint = Some(t.checkpoint.clone());
            if let Some(k) = self.jobs.get_mut(id) {
                k.checkpoint = t.checkpoint.clone();
            }
        }
        let seq = self.persist(Record::Job(JobUpdate {
            job_id: id,
            checkpoint,
            total_moves: None,
            state: Some((state, reason.clone())),
        }));
        self.notes.push_back((
            seq,
            StateNote {
                job_id: id,
                state,
                reason,
            },
        ));
    }

    /// Persist the active and the tracked job's checkpoints if they moved, at most every
    /// [`super::Options::checkpoint_every_us`] unless `force`.
    pub(super) fn save_checkpoints(&mut self, force: bool, now_us: u64) {
        let every = self.opts.checkpoint_every_us;
        let mut records = Vec::new();
        if let Some(a) = self.active.as_mut() {
            if a.dirty && (force || now_us.saturating_sub(a.saved_at_us) >= every) {
                a.dirty = false;
                a.saved_at_us = now_us;
                records.push((a.id, a.checkpoint.clone()));
            }
        }
        if let Some(t) = self.tracked.as_mut() {
            if t.dirty && (force || now_us.saturating_sub(t.saved_at_us) >= every) {
                t.dirty = false;
                t.saved_at_us = now_us;
                records.push((t.id, t.checkpoint.clone()));
            }
        }
        for (id, checkpoint) in records {
            if let Some(k) = self.jobs.get_mut(id) {
                k.checkpoint = checkpoint.clone();
            }
            self.persist(Record::Job(JobUpdate {
                job_id: id,
                checkpoint: Some(checkpoint),
                ..JobUpdate::default()
            }));
        }
    }

    /// Everything up to `upto` is on disk: tell the state changes, answer the replies
    /// waiting for them.
    pub(super) fn on_stored(&mut self, upto: u64) {
        self.stored_upto = self.stored_upto.max(upto);
        // A write went through (the store reports in order): it can write again. The
        // records handed over since are on their way.
        if let Some(f) = self.store_failing.take() {
            self.log(
                Level::Info,
                None,
                format!("job store written again, after {} failed tries", f.tries),
            );
        }
        while self
            .notes
            .front()
            .is_some_and(|(s, _)| *s <= self.stored_upto)
        {
            if let Some((_, note)) = self.notes.pop_front() {
                self.actions.push_back(Action::JobState(note));
            }
        }
        let stored_upto = self.stored_upto;
        let (done, waiting): (Vec<_>, Vec<_>) = std::mem::take(&mut self.waiting_replies)
            .into_iter()
            .partition(|r| r.seq <= stored_upto);
        self.waiting_replies = waiting;
        for r in done {
            self.answer_applied(r.request, r.state, true);
        }
        self.service_stored(stored_upto);
    }

    /// A write failed (the store tries again): warned about at once, then at most every
    /// [`STORE_WARN_EVERY_US`]; replies waiting for it are answered now.
    pub(super) fn on_store_failed(&mut self, cause: String, busy: bool, now_us: u64) {
        let f = self.store_failing.get_or_insert(StoreFailing {
            cause: cause.clone(),
            busy,
            tries: 0,
            warned_at_us: now_us,
            not_warned: 0,
        });
        let first = f.tries == 0;
        f.tries += 1;
        f.busy &= busy;
        f.cause = cause;
        let warn = if first {
            true
        } else if now_us.saturating_sub(f.warned_at_us) >= STORE_WARN_EVERY_US {
            f.warned_at_us = now_us;
            true
        } else {
            f.not_warned += 1;
            false
        };
        if warn {
            let since = std::mem::take(&mut f.not_warned);
            let message = match (f.busy, first) {
                (true, _) => format!(
                    "job store write failed, trying again: {} ({since} failed tries since \
                     the last warning)",
                    f.cause
                ),
                (false, true) => format!(
                    "job store cannot write: {}; trying again. Jobs moving go on, none \
                     starts or continues until it can",
                    f.cause
                ),
                (false, false) => format!(
                    "job store cannot write: {}; still trying ({since} failed tries since \
                     the last warning)",
                    f.cause
                ),
            };
            self.log(Level::Warn, None, message);
        }
        for r in std::mem::take(&mut self.waiting_replies) {
            self.answer_unstored(r);
        }
    }

    /// The store's writes fail for a reason other than another process's lock: the cause.
    pub(super) fn store_cannot_write(&self) -> Option<&str> {
        self.store_failing
            .as_ref()
            .filter(|f| !f.busy)
            .map(|f| f.cause.as_str())
    }

    /// While the store cannot write: a streaming job whose state change is not on disk
    /// is held (paused, "job store cannot write: <cause>").
    pub(super) fn hold_for_store(&mut self) {
        let Some(cause) = self.store_cannot_write().map(str::to_string) else {
            return;
        };
        let Some(a) = self.active.as_mut().filter(|a| a.phase == Phase::Streaming) else {
            return;
        };
        let id = a.id;
        if !self.notes.iter().any(|(_, n)| n.job_id == id) {
            return;
        }
        a.phase = Phase::Holding;
        self.machine(MachineCommand::FeedHold);
        let reason = format!("job store cannot write: {cause}");
        self.log(Level::Warn, Some(id), format!("job {id} paused: {reason}"));
        self.set_state(id, JobState::Paused, Some(reason), true);
    }

    /// While the store cannot write, a command that would start a job moving is refused
    /// (with nothing done): a resume, and a refill of a job waiting for one. Returns
    /// whether `command` was.
    pub(super) fn refused_while_store_fails(
        &mut self,
        request: RequestId,
        command: Command,
    ) -> bool {
        let Some(cause) = self.store_cannot_write() else {
            return false;
        };
        let message = match command {
            Command::Resume(id) => format!(
                "job store cannot write: {cause}; job {id} stays as it is until it can \
                 (free space for edod's state directory), then resume it"
            ),
            Command::Refill if self.phase() == Some(Phase::Empty) => format!(
                "job store cannot write: {cause}; the job waiting for the refill stays \
                 paused until it can (free space for edod's state directory), then refill"
            ),
            _ => return false,
        };
        self.actions.push_back(Action::Reply {
            request,
            result: Err(Refusal::new(RefusalKind::StoreCannotWrite, message)),
        });
        true
    }

    /// Replies that waited long enough for their state are answered.
    pub(super) fn expire_replies(&mut self, now_us: u64) {
        let (due, waiting): (Vec<_>, Vec<_>) = std::mem::take(&mut self.waiting_replies)
            .into_iter()
            .partition(|r| r.until_us <= now_us);
        self.waiting_replies = waiting;
        for r in due {
            self.answer_unstored(r);
        }
    }

    /// A reply whose state is not on disk: `stored: false` while the store only waits
    /// for another process's lock, a refusal saying so when it cannot write.
    fn answer_unstored(&mut self, r: WaitingReply) {
        let Some(cause) = self.store_cannot_write() else {
            self.answer_applied(r.request, r.state, false);
            return;
        };
        let message = format!(
            "job store cannot write: {cause}; job {} is {} here but that is not on disk: \
             it is written once the store can write again (free space for edod's state \
             directory)",
            r.job_id,
            r.state.as_str()
        );
        self.actions.push_back(Action::Reply {
            request: r.request,
            result: Err(Refusal::new(RefusalKind::StoreCannotWrite, message)),
        });
    }

    /// Answer `request` with job `id`'s state once that is stored, or after
    /// [`super::Options::reply_wait_us`] with `stored: false`.
    pub(super) fn reply_applied(&mut self, request: RequestId, id: u32, now_us: u64) {
        let state = self.jobs.get(id).map_or(JobState::Failed, |k| k.state);
        let pending = self
            .notes
            .iter()
            .filter(|(_, n)| n.job_id == id)
            .map(|(s, _)| *s)
            .max();
        match pending {
            Some(seq) => self.waiting_replies.push(WaitingReply {
                request,
                job_id: id,
                seq,
                state,
                until_us: now_us.saturating_add(self.opts.reply_wait_us),
            }),
            None => self.answer_applied(request, state, true),
        }
    }

    fn answer_applied(&mut self, request: RequestId, state: JobState, stored: bool) {
        self.actions.push_back(Action::Reply {
            request,
            result: Ok(Answer::Applied(Applied { state, stored })),
        });
    }

    /// Publish the active job's progress if it changed, at most every
    /// [`super::Options::progress_every_us`] unless `force`.
    pub(super) fn publish_progress(&mut self, force: bool, now_us: u64) {
        let Some(a) = self.active.as_ref() else {
            return;
        };
        if !force && now_us.saturating_sub(self.progress_at_us) < self.opts.progress_every_us {
            return;
        }
        self.progress_at_us = now_us;
        let executed = a.checkpoint.next_index;
        let done_since = executed.saturating_sub(a.executed_at_start);
        let elapsed_s = now_us.saturating_sub(a.started_us) as f64 / 1e6;
        let planned = a.planned.as_ref().filter(|t| t.total_us() > 0);
        let eta_s = match planned {
            Some(t) => {
                let done_us = t.before_us(executed);
                let done_since_us = done_us.saturating_sub(t.before_us(a.executed_at_start));
                Some(time_left_planned_s(
                    t.total_us().saturating_sub(done_us),
                    done_since_us,
                    a.running_us,
                ))
            }
            None => time_left_s(
                a.total.map(|t| (t, executed, done_since)),
                a.layers.zip(a.checkpoint.layer),
                a.layer_at_start,
                elapsed_s,
            ),
        };
        let p = Progress {
            job_id: a.id,
            executed,
            total: a.total.or(planned.map(|t| t.moves())),
            layers: a.layers,
            layer: a.checkpoint.layer,
            composition: a.checkpoint.composition.clone(),
            eta_s,
            percent: planned
                .map(|t| (100.0 * t.before_us(executed) as f64 / t.total_us() as f64).min(100.0)),
            planned_s: planned.map(|t| t.total_us() as f64 / 1e6),
            first_move_after_ms: a.first_move_after_ms,
        };
        if self.last_progress.as_ref() != Some(&p) {
            self.last_progress = Some(p.clone());
            self.actions.push_back(Action::Progress(Some(p)));
        }
    }
}
