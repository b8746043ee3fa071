//! The store's writer thread: the one connection that writes `edod.db` while edod runs.
//!
//! It takes the lifecycle's records ([`Action::Persist`](crate::lifecycle::Action)),
//! writes every one waiting in one transaction (one fsync) in order, and reports back as
//! lifecycle events: [`Event::Stored`] with the last sequence number on disk, or
//! [`Event::StoreFailed`] for every write that fails, saying why ("disk full", SQLite's
//! or the OS's error) and whether it only waits for another process's lock (the
//! lifecycle decides what follows and rate-limits the warnings). Records that could not
//! be written stay and are tried again (after [`RETRY_AFTER`] behind a lock,
//! [`RETRY_FAILED_AFTER`] when the write failed otherwise: a full disk); a job's records merge while they wait (the newest checkpoint, move count
//! and state win), so a store locked for long costs writes, never memory or order.
//!
//! Each try waits at most [`LOCK_WAIT`] for another process's write lock (a backup, an
//! operator's `sqlite3` shell), so the thread keeps looking at its inbox: a submission or
//! a deletion from the API is tried at once, waiting for the lock only until its own
//! deadline, then answered [`StoreError::Busy`] with nothing written (the client retries).

use std::sync::mpsc as std_mpsc;
use std::time::{Duration, Instant};

use tokio::sync::{mpsc, oneshot};
use tracing::warn;

use super::sql::{GcodeMarkWrite, JobSpec, Store, StoreError};
use crate::lifecycle::{Event, JobState, Record};

/// How long one try of the lifecycle's records waits for the write lock before the
/// thread looks at its inbox again.
pub const LOCK_WAIT: Duration = Duration::from_millis(20);
/// Pause between tries of records that could not be written for another process's lock.
pub const RETRY_AFTER: Duration = Duration::from_millis(30);
/// Pause between tries of records whose write failed otherwise (a full disk).
pub const RETRY_FAILED_AFTER: Duration = Duration::from_millis(200);

/// A submission's outcome: the job's id and the finished jobs pruned.
pub type Submitted = Result<(u32, Vec<u32>), StoreError>;
/// A deletion's outcome: done, or the state of a job that is not finished.
pub type Deleted = Result<Result<(), JobState>, StoreError>;

/// What the writer is asked to do.
enum Write {
    Persist {
        seq: u64,
        record: Record,
    },
    Submit {
        name: String,
        spec: JobSpec,
        keep: usize,
        prune_at_most: usize,
        deadline: Instant,
        reply: oneshot::Sender<Submitted>,
    },
    Delete {
        id: u32,
        deadline: Instant,
        reply: oneshot::Sender<Deleted>,
    },
    GcodeMark(GcodeMarkWrite),
}

/// A handle on the writer thread (cheap to clone; the thread ends with the last one).
#[derive(Clone)]
pub struct Writer {
    tx: std_mpsc::Sender<Write>,
}

impl Writer {
    /// Start the writer thread on `store` (its own connection); its reports go to
    /// `events`.
    pub fn start(store: Store, events: mpsc::UnboundedSender<Event>) -> std::io::Result<Writer> {
        let (tx, rx) = std_mpsc::channel();
        std::thread::Builder::new()
            .name("edod-store-writer".into())
            .spawn(move || {
                let mut t = Thread {
                    store,
                    events,
                    pending: Vec::new(),
                    upto: 0,
                    failing: None,
                };
                if let Err(e) = t.store.set_busy_timeout(LOCK_WAIT) {
                    warn!(error = %e, "job store writer: cannot set the busy timeout");
                }
                t.run(&rx);
            })?;
        Ok(Writer { tx })
    }

    /// Hand over record `seq` (never waits).
    pub fn persist(&self, seq: u64, record: Record) {
        if self.tx.send(Write::Persist { seq, record }).is_err() {
            warn!(seq, "job store writer stopped: record not written");
        }
    }

    /// Change the stored G-code marks (never waits; written in order, ahead of the
    /// records still waiting for a lock).
    pub fn gcode_mark(&self, w: GcodeMarkWrite) {
        if self.tx.send(Write::GcodeMark(w)).is_err() {
            warn!("job store writer stopped: G-code mark not written");
        }
    }

    /// Store a new job and prune the finished ones beyond the newest `keep` (at most
    /// `prune_at_most`), waiting for another process's write lock at most `wait`.
    pub async fn submit(
        &self,
        name: String,
        spec: JobSpec,
        keep: usize,
        prune_at_most: usize,
        wait: Duration,
    ) -> Submitted {
        let (reply, rx) = oneshot::channel();
        let w = Write::Submit {
            name,
            spec,
            keep,
            prune_at_most,
            deadline: Instant::now() + wait,
            reply,
        };
        self.tx.send(w).map_err(|_| StoreError::Stopped)?;
        rx.await.map_err(|_| StoreError::Stopped)?
    }

    /// Delete finished job `id`, waiting for another process's write lock at most `wait`.
    pub async fn delete(&self, id: u32, wait: Duration) -> Deleted {
        let (reply, rx) = oneshot::channel();
        let w = Write::Delete {
            id,
            deadline: Instant::now() + wait,
            reply,
        };
        self.tx.send(w).map_err(|_| StoreError::Stopped)?;
        rx.await.map_err(|_| StoreError::Stopped)?
    }
}

struct Thread {
    store: Store,
    events: mpsc::UnboundedSender<Event>,
    /// Records not yet on disk, a job's merged into one.
    pending: Vec<Record>,
    /// The highest sequence number among them.
    upto: u64,
    /// Writes fail: the last one for another process's lock (else for another reason).
    failing: Option<bool>,
}

impl Thread {
    fn run(&mut self, rx: &std_mpsc::Receiver<Write>) {
        loop {
            let first = if self.pending.is_empty() {
                match rx.recv() {
                    Ok(w) => w,
                    Err(_) => return,
                }
            } else {
                let wait = match self.failing {
                    None => Duration::ZERO,
                    Some(true) => RETRY_AFTER,
                    Some(false) => RETRY_FAILED_AFTER,
                };
                match rx.recv_timeout(wait) {
                    Ok(w) => w,
                    Err(std_mpsc::RecvTimeoutError::Timeout) => {
                        self.write_pending();
                        continue;
                    }
                    Err(std_mpsc::RecvTimeoutError::Disconnected) => {
                        self.write_pending();
                        return;
                    }
                }
            };
            self.take(first);
            while let Ok(w) = rx.try_recv() {
                self.take(w);
            }
            if !self.pending.is_empty() {
                self.write_pending();
            }
        }
    }

    fn take(&mut self, w: Write) {
        match w {
            Write::Persist { seq, record } => self.add(seq, record),
            Write::Submit {
                name,
                spec,
                keep,
                prune_at_most,
                deadline,
                reply,
            } => {
                let r = self.within(deadline, |s| {
                    s.insert_pruning(&name, &spec, keep, prune_at_most)
                });
                let _ = reply.send(r);
            }
            Write::Delete {
                id,
                deadline,
                reply,
            } => {
                let r = self.within(deadline, |s| s.delete_finished(id));
                let _ = reply.send(r);
            }
            Write::GcodeMark(w) => {
                if let Err(e) = self.store.gcode_mark(w) {
                    warn!(error = %e, "job store: G-code mark not written");
                }
            }
        }
    }

    /// Add a record to the pending ones: a job's update merges into the one waiting.
    fn add(&mut self, seq: u64, record: Record) {
        self.upto = self.upto.max(seq);
        if let Record::Job(newer) = &record {
            let waiting = self.pending.iter_mut().find_map(|r| match r {
                Record::Job(u) if u.job_id == newer.job_id => Some(u),
                _ => None,
            });
            if let Some(u) = waiting {
                *u = std::mem::take(u).merged(newer.clone());
                return;
            }
        }
        self.pending.push(record);
    }

    /// Run `f` waiting for another process's write lock until `deadline` at most. A
    /// request whose time ran out in this thread's own inbox (a burst of submissions) is
    /// still tried, without waiting: with no other process holding the lock it is
    /// written at once, so [`StoreError::Busy`] (-32005) means another process, never
    /// edod's own queue (2,000 concurrent submissions drew 81 false -32005s).
    fn within<T>(
        &mut self,
        deadline: Instant,
        f: impl FnOnce(&Store) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        let left = deadline.saturating_duration_since(Instant::now());
        self.store.set_busy_timeout(left)?;
        let r = f(&self.store);
        if let Err(e) = self.store.set_busy_timeout(LOCK_WAIT) {
            warn!(error = %e, "job store writer: cannot set the busy timeout");
        }
        r.map_err(|e| if e.is_busy() { StoreError::Busy } else { e })
    }

    fn write_pending(&mut self) {
        match self.store.apply(&self.pending) {
            Ok(missing) => {
                if !missing.is_empty() {
                    warn!(jobs = ?missing, "job store: records of jobs no longer stored skipped");
                }
                self.pending.clear();
                self.failing = None;
                let _ = self.events.send(Event::Stored { upto: self.upto });
            }
            Err(e) => {
                let busy = e.is_busy();
                self.failing = Some(busy);
                let _ = self.events.send(Event::StoreFailed {
                    error: e.cause(),
                    busy,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lifecycle::JobUpdate;
    use crate::proto::Checkpoint;

    fn checkpoint(job_id: u32, next_index: u32) -> Record {
        Record::Job(JobUpdate {
            job_id,
            checkpoint: Some(Checkpoint {
                next_index,
                ..Checkpoint::default()
            }),
            ..JobUpdate::default()
        })
    }

    /// Another process's connection holding the store's write lock.
    fn lock(dir: &tempfile::TempDir) -> rusqlite::Connection {
        let other = rusqlite::Connection::open(dir.path().join("edod.db")).unwrap();
        other.execute_batch("BEGIN EXCLUSIVE").unwrap();
        other
    }

    fn next(rx: &mut mpsc::UnboundedReceiver<Event>, within: Duration) -> Option<Event> {
        let t = Instant::now();
        loop {
            if let Ok(e) = rx.try_recv() {
                return Some(e);
            }
            if t.elapsed() > within {
                return None;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// The next event but the failures reported meanwhile.
    fn stored(rx: &mut mpsc::UnboundedReceiver<Event>, within: Duration) -> Option<Event> {
        loop {
            match next(rx, within)? {
                Event::StoreFailed { .. } => {}
                e => return Some(e),
            }
        }
    }

    /// A submission whose wait ran out in the writer's own inbox is written, not
    /// answered busy: -32005 is for another process's lock only.
    #[test]
    fn a_submission_past_its_wait_with_no_other_lock_is_written() {
        let dir = tempfile::tempdir().unwrap();
        let (events, _rx) = mpsc::unbounded_channel();
        let writer = Writer::start(Store::open(dir.path()).unwrap(), events).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap();
        let submit = |name: &str| {
            rt.block_on(writer.submit(
                name.into(),
                JobSpec::DryRun { moves: 3 },
                10,
                10,
                Duration::ZERO,
            ))
        };
        assert!(submit("a").is_ok(), "no other process: written");
        let other = lock(&dir);
        assert!(matches!(submit("b"), Err(StoreError::Busy)));
        drop(other);
        assert!(submit("c").is_ok());
    }

    #[test]
    fn records_wait_out_a_lock_in_order_and_submissions_are_answered_busy_meanwhile() {
        let dir = tempfile::tempdir().unwrap();
        let main = Store::open(dir.path()).unwrap();
        let id = main.insert("a", &JobSpec::DryRun { moves: 10 }).unwrap();
        let (events, mut rx) = mpsc::unbounded_channel();
        let writer = Writer::start(Store::open(dir.path()).unwrap(), events).unwrap();
        writer.persist(1, checkpoint(id, 1));
        assert_eq!(
            next(&mut rx, Duration::from_secs(5)),
            Some(Event::Stored { upto: 1 })
        );
        let other = lock(&dir);
        let t = Instant::now();
        for seq in 2..=50 {
            writer.persist(seq, checkpoint(id, seq as u32));
        }
        writer.persist(
            51,
            Record::Job(JobUpdate {
                job_id: id,
                state: Some((JobState::Paused, Some("paused by an operator".into()))),
                ..JobUpdate::default()
            }),
        );
        assert!(
            matches!(
                next(&mut rx, Duration::from_secs(2)),
                Some(Event::StoreFailed { .. })
            ),
            "the failure is reported"
        );
        assert!(
            t.elapsed() < Duration::from_millis(500),
            "{:?}",
            t.elapsed()
        );
        // A submission meanwhile is answered within its wait, with nothing written.
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap();
        let asked = Instant::now();
        let r = rt.block_on(writer.submit(
            "b".into(),
            JobSpec::DryRun { moves: 3 },
            10,
            10,
            Duration::from_millis(60),
        ));
        assert!(matches!(r, Err(StoreError::Busy)), "{r:?}");
        assert!(
            asked.elapsed() < Duration::from_millis(100),
            "{:?}",
            asked.elapsed()
        );
        // Readers go on meanwhile (WAL) and see the last records committed.
        assert_eq!(main.get(id).unwrap().job.checkpoint.next_index, 1);
        other.execute_batch("COMMIT").unwrap();
        assert_eq!(
            stored(&mut rx, Duration::from_secs(5)),
            Some(Event::Stored { upto: 51 })
        );
        let j = main.get(id).unwrap();
        assert_eq!(
            j.job.checkpoint.next_index, 50,
            "the latest checkpoint wins"
        );
        assert_eq!(
            j.job.state,
            JobState::Paused,
            "and the state written with it"
        );
        assert_eq!(
            main.list().unwrap().len(),
            1,
            "the busy submission left nothing"
        );
        let (b, pruned) = rt
            .block_on(writer.submit(
                "b".into(),
                JobSpec::DryRun { moves: 3 },
                10,
                10,
                Duration::from_millis(60),
            ))
            .unwrap();
        assert_eq!((b, pruned), (id + 1, vec![]));
    }

    #[test]
    fn a_full_disk_is_reported_on_every_try_and_the_records_go_once_there_is_room() {
        let dir = tempfile::tempdir().unwrap();
        let main = Store::open(dir.path()).unwrap();
        let id = main.insert("a", &JobSpec::DryRun { moves: 10 }).unwrap();
        // Another program's data fills what the database may grow to.
        let other = rusqlite::Connection::open(dir.path().join("edod.db")).unwrap();
        other
            .execute_batch(
                "CREATE TABLE pad (b BLOB);
                 WITH RECURSIVE n(k) AS (SELECT 1 UNION ALL SELECT k + 1 FROM n WHERE k < 40)
                 INSERT INTO pad SELECT zeroblob(4000) FROM n;",
            )
            .unwrap();
        let store = Store::open(dir.path()).unwrap();
        store.limit_to_current_size();
        let (events, mut rx) = mpsc::unbounded_channel();
        let writer = Writer::start(store, events).unwrap();
        let reason = "r".repeat(60_000);
        writer.persist(
            1,
            Record::Job(JobUpdate {
                job_id: id,
                state: Some((JobState::Paused, Some(reason.clone()))),
                ..JobUpdate::default()
            }),
        );
        for _ in 0..3 {
            assert_eq!(
                next(&mut rx, Duration::from_secs(2)),
                Some(Event::StoreFailed {
                    error: "disk full".into(),
                    busy: false
                }),
                "every try is reported"
            );
        }
        assert_eq!(main.get(id).unwrap().job.state, JobState::Queued);
        // Room again.
        other.execute_batch("DELETE FROM pad").unwrap();
        assert_eq!(
            stored(&mut rx, Duration::from_secs(5)),
            Some(Event::Stored { upto: 1 })
        );
        let j = main.get(id).unwrap();
        assert_eq!(
            (j.job.state, j.job.reason),
            (JobState::Paused, Some(reason))
        );
    }
}
