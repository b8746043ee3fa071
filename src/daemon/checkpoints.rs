//! Checkpoint writes off the streamer's task.
//!
//! While a job streams, the streamer records where it is (first move not executed,
//! layer, composition, syringe volumes) every 100 ms. Each record is a SQLite commit
//! with `synchronous = FULL`, an fsync: on a printer host's SD card, or a disk busy
//! with something else, that can take hundreds of milliseconds, and when another
//! process holds the database's write lock (a backup, an operator's `sqlite3` shell) it
//! waits up to the store's busy timeout. Made on the streaming task, such a write held
//! the moves back until the machine's queue ran dry (an underrun: the nozzle stands
//! still on the part).
//!
//! Here the records are written by a thread of their own on a connection of their own
//! (WAL: the daemon's readers do not wait for it either). The streamer hands over a
//! job's latest checkpoint and goes on. Only the latest per job is kept, since a
//! checkpoint supersedes the ones before it: a slow disk costs writes, never memory or
//! order. A record that cannot be written is kept and tried again (unless a newer one
//! replaced it). Where a record must be on disk before the streamer goes on (the job is
//! paused, ends or is interrupted, and its state is written next), [`Writer::flush`]
//! waits for everything handed over so far.

use std::collections::BTreeMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tracing::warn;

use super::store::{Checkpoint, Store};

/// How long to wait before trying a failed write again.
const RETRY_AFTER: Duration = Duration::from_millis(200);

/// What to record of one job: its latest checkpoint, its move count once known.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Record {
    /// Where the job is.
    pub checkpoint: Option<Checkpoint>,
    /// How many moves the job has (known once its planning finished).
    pub total_moves: Option<u32>,
}

impl Record {
    /// `newer` over `self`: a field `newer` leaves unset keeps this one's.
    fn merged(self, newer: Record) -> Record {
        Record {
            checkpoint: newer.checkpoint.or(self.checkpoint),
            total_moves: newer.total_moves.or(self.total_moves),
        }
    }
}

/// The records waiting for the writer thread.
#[derive(Default)]
struct Queue {
    /// Per job, what is still to be written.
    pending: BTreeMap<u32, Record>,
    /// Number of the last hand-over.
    handed: u64,
    /// Every hand-over up to this number is on disk.
    written: u64,
    /// The writer is to write what is pending and end.
    stop: bool,
}

struct Inner {
    queue: Mutex<Queue>,
    changed: Condvar,
}

impl Inner {
    fn lock(&self) -> MutexGuard<'_, Queue> {
        // A panic elsewhere while holding this lock leaves the queue consistent (every
        // change to it is one assignment), so carry on with it.
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The checkpoint writer: hands records to its thread.
pub struct Writer {
    inner: Arc<Inner>,
    thread: Option<JoinHandle<()>>,
}

impl Writer {
    /// Start a writer that records through `store` (its own connection).
    pub fn start(store: Store) -> std::io::Result<Writer> {
        let inner = Arc::new(Inner {
            queue: Mutex::new(Queue::default()),
            changed: Condvar::new(),
        });
        let thread = {
            let inner = Arc::clone(&inner);
            std::thread::Builder::new()
                .name("edod-checkpoints".into())
                .spawn(move || write_loop(&inner, &store))?
        };
        Ok(Writer {
            inner,
            thread: Some(thread),
        })
    }

    /// Hand over `record` for job `id`; it replaces what of that job is still waiting.
    pub fn record(&self, id: u32, record: Record) {
        let mut q = self.inner.lock();
        let merged = match q.pending.remove(&id) {
            Some(old) => old.merged(record),
            None => record,
        };
        q.pending.insert(id, merged);
        q.handed += 1;
        drop(q);
        self.inner.changed.notify_all();
    }

    /// Wait until everything handed over so far is on disk, at most `limit`; whether it is.
    pub fn flush(&self, limit: Duration) -> bool {
        let deadline = Instant::now() + limit;
        let mut q = self.inner.lock();
        let target = q.handed;
        while q.written < target {
            let now = Instant::now();
            if now >= deadline {
                return false;
            }
            q = match self.inner.changed.wait_timeout(q, deadline - now) {
                Ok((q, _)) => q,
                Err(p) => p.into_inner().0,
            };
        }
        true
    }
}

impl Drop for Writer {
    /// Write what is pending (one try each), then end the thread.
    fn drop(&mut self) {
        self.inner.lock().stop = true;
        self.inner.changed.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn write_loop(inner: &Inner, store: &Store) {
    let mut q = inner.lock();
    loop {
        while q.pending.is_empty() && !q.stop {
            q = match inner.changed.wait(q) {
                Ok(q) => q,
                Err(p) => p.into_inner(),
            };
        }
        if q.pending.is_empty() {
            return;
        }
        let batch = std::mem::take(&mut q.pending);
        let upto = q.handed;
        let stopping = q.stop;
        drop(q);
        let result = store.record_progress(
            batch
                .iter()
                .map(|(&id, r)| (id, r.checkpoint.as_ref(), r.total_moves)),
        );
        q = inner.lock();
        match result {
            Ok(()) => q.written = upto,
            Err(e) if stopping => {
                warn!(error = %e, jobs = ?batch.keys().collect::<Vec<_>>(), "cannot write checkpoints; edod is stopping, so they are lost");
                q.written = upto;
                return;
            }
            Err(e) => {
                warn!(error = %e, jobs = ?batch.keys().collect::<Vec<_>>(), "cannot write checkpoints; trying again");
                for (id, r) in batch {
                    let newer = q.pending.remove(&id);
                    let merged = match newer {
                        Some(newer) => r.merged(newer),
                        None => r,
                    };
                    q.pending.insert(id, merged);
                }
                q = match inner.changed.wait_timeout(q, RETRY_AFTER) {
                    Ok((q, _)) => q,
                    Err(p) => p.into_inner().0,
                };
            }
        }
        inner.changed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::store::JobSpec;

    /// A store in a temporary directory holding one job, and that job's id.
    fn store_with_a_job() -> (tempfile::TempDir, Store, u32) {
        let dir = tempfile::tempdir().unwrap();
        let main = Store::open(dir.path()).unwrap();
        let id = main.insert("a", &JobSpec::DryRun { moves: 10 }).unwrap();
        (dir, main, id)
    }

    fn record(next_index: Option<u32>, total_moves: Option<u32>) -> Record {
        Record {
            checkpoint: next_index.map(|next_index| Checkpoint {
                next_index,
                ..Checkpoint::default()
            }),
            total_moves,
        }
    }

    /// Another process's connection holding the store's write lock.
    fn lock(dir: &tempfile::TempDir) -> rusqlite::Connection {
        let other = rusqlite::Connection::open(dir.path().join("edod.db")).unwrap();
        other.execute_batch("BEGIN IMMEDIATE").unwrap();
        other
    }

    #[test]
    fn records_wait_out_a_locked_database_without_holding_the_caller() {
        let (dir, main, id) = store_with_a_job();
        let writer = Writer::start(Store::open(dir.path()).unwrap()).unwrap();
        let other = lock(&dir);
        let t = Instant::now();
        for i in 1..=50 {
            writer.record(id, record(Some(i), None));
        }
        writer.record(id, record(None, Some(10)));
        assert!(
            t.elapsed() < Duration::from_millis(100),
            "{:?}",
            t.elapsed()
        );
        assert!(
            !writer.flush(Duration::from_millis(300)),
            "written through a lock"
        );
        // Readers go on meanwhile (WAL), and see the last record committed: none.
        assert_eq!(main.get(id).unwrap().checkpoint.next_index, 0);
        other.execute_batch("COMMIT").unwrap();
        assert!(writer.flush(Duration::from_secs(10)));
        let j = main.get(id).unwrap();
        assert_eq!(j.checkpoint.next_index, 50, "the latest checkpoint wins");
        assert_eq!(j.total_moves, Some(10), "and the total handed over with it");
    }

    #[test]
    fn a_failed_write_is_tried_again_and_a_newer_record_wins() {
        let (dir, main, id) = store_with_a_job();
        let mut store = Store::open(dir.path()).unwrap();
        // Fail at once on the lock instead of waiting it out.
        store.set_busy_timeout(Duration::ZERO).unwrap();
        let writer = Writer::start(store).unwrap();
        let other = lock(&dir);
        writer.record(id, record(Some(3), Some(10)));
        assert!(!writer.flush(Duration::from_millis(500)));
        writer.record(id, record(Some(7), None));
        other.execute_batch("COMMIT").unwrap();
        assert!(writer.flush(Duration::from_secs(10)));
        let j = main.get(id).unwrap();
        assert_eq!(j.checkpoint.next_index, 7);
        assert_eq!(j.total_moves, Some(10), "kept from the failed write");
    }

    #[test]
    fn dropping_the_writer_writes_what_is_pending() {
        let (dir, main, id) = store_with_a_job();
        let writer = Writer::start(Store::open(dir.path()).unwrap()).unwrap();
        writer.record(id, record(Some(9), None));
        drop(writer);
        assert_eq!(main.get(id).unwrap().checkpoint.next_index, 9);
    }
}
