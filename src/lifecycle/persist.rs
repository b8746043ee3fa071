//! What is written and told: job states with their checkpoints, periodic checkpoints,
//! the notifications and replies that wait for their record to be on disk, progress.

use super::io::{Action, Answer, Applied, JobUpdate, Level, Record, RequestId, StateNote};
use super::job::{time_left_s, JobState, Progress};
use super::{Lifecycle, WaitingReply};

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

    /// A write failed (the store tries again): replies waiting for it are answered now,
    /// `stored: false`.
    pub(super) fn on_store_failed(&mut self, error: &str) {
        self.log(
            Level::Warn,
            None,
            format!("job store write failed, trying again: {error}"),
        );
        for r in std::mem::take(&mut self.waiting_replies) {
            self.answer_applied(r.request, r.state, false);
        }
    }

    /// Replies that waited long enough for their state are answered `stored: false`.
    pub(super) fn expire_replies(&mut self, now_us: u64) {
        let (due, waiting): (Vec<_>, Vec<_>) = std::mem::take(&mut self.waiting_replies)
            .into_iter()
            .partition(|r| r.until_us <= now_us);
        self.waiting_replies = waiting;
        for r in due {
            self.answer_applied(r.request, r.state, false);
        }
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
        let p = Progress {
            job_id: a.id,
            executed,
            total: a.total,
            layers: a.layers,
            layer: a.checkpoint.layer,
            composition: a.checkpoint.composition.clone(),
            eta_s: time_left_s(
                a.total.map(|t| (t, executed, done_since)),
                a.layers.zip(a.checkpoint.layer),
                a.layer_at_start,
                elapsed_s,
            ),
            first_move_after_ms: a.first_move_after_ms,
        };
        if self.last_progress.as_ref() != Some(&p) {
            self.last_progress = Some(p.clone());
            self.actions.push_back(Action::Progress(Some(p)));
        }
    }
}
