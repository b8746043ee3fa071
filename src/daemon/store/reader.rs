//! The store's reader thread: a connection of its own that answers reads in order —
//! the API's (`job.list`, `job.get`), the lifecycle's ([`Action::ListQueued`] and
//! [`Action::LookUpJob`], answered as [`Event::QueuedJobs`] and [`Event::JobLookedUp`])
//! and the planner's (a job's spec and mesh).
//!
//! In WAL mode a read does not wait for another connection's write lock, so reads go on
//! while the writer waits; a read that still finds the database busy (its recovery by
//! another process) gives up after [`READ_WAIT`] with [`StoreError::Busy`].
//!
//! [`Action::ListQueued`]: crate::lifecycle::Action::ListQueued
//! [`Action::LookUpJob`]: crate::lifecycle::Action::LookUpJob

use std::sync::mpsc as std_mpsc;
use std::time::Duration;

use tokio::sync::{mpsc, oneshot};
use tracing::warn;

use super::sql::{JobRecord, Store, StoreError};
use crate::lifecycle::Event;

/// How long a read waits for a busy database.
pub const READ_WAIT: Duration = Duration::from_millis(50);

/// A job as the planner needs it: its record and its mesh (mesh jobs).
pub type Source = Result<(JobRecord, Option<Vec<u8>>), StoreError>;

enum Read {
    List(oneshot::Sender<Result<Vec<JobRecord>, StoreError>>),
    Get(u32, oneshot::Sender<Result<JobRecord, StoreError>>),
    Queued,
    LookUp(u32),
    Source(u32, oneshot::Sender<Source>),
}

/// A handle on the reader thread (cheap to clone; the thread ends with the last one).
#[derive(Clone)]
pub struct Reader {
    tx: std_mpsc::Sender<Read>,
}

impl Reader {
    /// Start the reader thread on `store` (its own connection); the lifecycle's answers
    /// go to `events`.
    pub fn start(
        mut store: Store,
        events: mpsc::UnboundedSender<Event>,
    ) -> std::io::Result<Reader> {
        let (tx, rx) = std_mpsc::channel::<Read>();
        std::thread::Builder::new()
            .name("edod-store-reader".into())
            .spawn(move || {
                if let Err(e) = store.set_busy_timeout(READ_WAIT) {
                    warn!(error = %e, "job store reader: cannot set the busy timeout");
                }
                for r in rx {
                    answer(&store, r, &events);
                }
            })?;
        Ok(Reader { tx })
    }

    async fn ask<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<Result<T, StoreError>>) -> Read,
    ) -> Result<T, StoreError> {
        let (reply, rx) = oneshot::channel();
        self.tx.send(make(reply)).map_err(|_| StoreError::Stopped)?;
        rx.await.map_err(|_| StoreError::Stopped)?
    }

    /// Every job, oldest first.
    pub async fn list(&self) -> Result<Vec<JobRecord>, StoreError> {
        self.ask(Read::List).await
    }

    /// Job `id`.
    pub async fn get(&self, id: u32) -> Result<JobRecord, StoreError> {
        self.ask(|r| Read::Get(id, r)).await
    }

    /// Job `id` and its mesh (a mesh job's), for a task.
    pub async fn source(&self, id: u32) -> Source {
        self.ask(|r| Read::Source(id, r)).await
    }

    /// The queued and interrupted jobs, answered as [`Event::QueuedJobs`].
    pub fn queued(&self) {
        let _ = self.tx.send(Read::Queued);
    }

    /// Job `id`, answered as [`Event::JobLookedUp`].
    pub fn look_up(&self, id: u32) {
        let _ = self.tx.send(Read::LookUp(id));
    }

    /// Job `id` and its mesh, waiting for the answer: for a planner worker (a thread
    /// off the runtime), never for a task.
    pub fn source_blocking(&self, id: u32) -> Source {
        let (reply, rx) = oneshot::channel();
        self.tx
            .send(Read::Source(id, reply))
            .map_err(|_| StoreError::Stopped)?;
        rx.blocking_recv().map_err(|_| StoreError::Stopped)?
    }
}

fn busy_named(e: StoreError) -> StoreError {
    if e.is_busy() {
        StoreError::Busy
    } else {
        e
    }
}

fn answer(store: &Store, r: Read, events: &mpsc::UnboundedSender<Event>) {
    match r {
        Read::List(reply) => {
            let _ = reply.send(store.list().map_err(busy_named));
        }
        Read::Get(id, reply) => {
            let _ = reply.send(store.get(id).map_err(busy_named));
        }
        Read::Queued => {
            let jobs = store
                .waiting()
                .map(|v| v.iter().map(JobRecord::info).collect())
                .map_err(|e| e.to_string());
            let _ = events.send(Event::QueuedJobs(jobs));
        }
        Read::LookUp(id) => {
            let job = match store.get(id) {
                Ok(j) => Ok(Some(j.info())),
                Err(StoreError::NotFound(_)) => Ok(None),
                Err(e) => Err(e.to_string()),
            };
            let _ = events.send(Event::JobLookedUp { id, job });
        }
        Read::Source(id, reply) => {
            let source = store
                .get(id)
                .and_then(|j| {
                    if let Some(what) = j.unreadable.clone() {
                        return Err(StoreError::Unreadable { id, what });
                    }
                    let mesh = match j.spec {
                        super::JobSpec::Toml { .. } => store.mesh(id)?,
                        super::JobSpec::DryRun { .. } => None,
                    };
                    Ok((j, mesh))
                })
                .map_err(busy_named);
            let _ = reply.send(source);
        }
    }
}
