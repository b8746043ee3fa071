//! edod, the printer-host daemon: takes jobs from operators over a local socket, plans
//! them ahead, streams them to the machine and survives every crash.
//!
//! It reads like mini-redis: one file per component, typed channels between tasks,
//! shared state as snapshots (a watch channel), never a lock held across an await.
//!
//! - [`config`]: `edod.toml` (unknown keys refused, line/column errors).
//! - [`preflight`]: what a parsed config may still get wrong about this host (group,
//!   socket path length, fault names, serial port, line speed).
//! - [`store`]: jobs, states, checkpoints in SQLite (WAL); nothing accepted is lost.
//! - [`connections`]: the socket's connections and their limits (idle timeout, a
//!   reserve for e-stop, one memory budget for requests in flight).
//! - [`api`]: the Unix socket, newline-delimited JSON-RPC 2.0 (`docs/api.md`),
//!   requests and notifications typed by [`crate::proto`]; slow clients are cut off,
//!   never waited for.
//! - [`planner`]: blocking workers that turn a job into moves layer by layer, ahead of
//!   the streamer through a bounded channel.
//! - [`streamer`]: the one task that owns the serial port and pumps the sans-IO
//!   [`crate::link::Host`]; it runs the job lifecycle (start, pause, resume, cancel,
//!   e-stop, faults, checkpoints). Progress is what the machine reports executed.
//! - [`instance`]: one edod per state directory and socket (locks taken first), the
//!   modes of the files it creates.
//! - [`supervise`]: signals, systemd notify (READY, STATUS, WATCHDOG), the simulated
//!   machine child, graceful stop.

pub mod api;
pub mod checkpoints;
pub mod config;
pub mod connections;
pub mod instance;
pub mod planner;
pub mod preflight;
pub mod store;
pub mod streamer;
pub mod supervise;

use std::sync::Arc;

use tokio::sync::{broadcast, mpsc, oneshot, watch};

pub use config::Config;
pub use supervise::{run, run_until};

// The API's vocabulary lives in `proto` (shared with edoctl); the daemon speaks it.
pub use crate::proto::{ApiError, EStopTiming, MachineSnapshot, Progress};

/// A reply channel for control requests.
pub type Reply<T> = oneshot::Sender<Result<T, ApiError>>;

/// Requests to the streamer.
#[derive(Debug)]
pub enum Control {
    /// A job was queued: start it when the machine is free.
    Submitted,
    /// Hold the job at a move boundary.
    Pause(u32, Reply<()>),
    /// Continue a paused or interrupted job.
    Resume(u32, Reply<()>),
    /// Cancel a job (stop, retract, park if it is printing).
    Cancel(u32, Reply<()>),
    /// Emergency stop now.
    EStop(std::time::Instant, Reply<EStopTiming>),
    /// The syringes were refilled: clear the fault and continue.
    Refill(Reply<()>),
    /// Hold, checkpoint and stop (SIGTERM).
    Shutdown(oneshot::Sender<()>),
}

/// What every task shares.
pub struct Shared {
    /// Configuration.
    pub config: Config,
    /// The job store (short statements only).
    pub store: std::sync::Mutex<store::Store>,
    /// A connection of its own for the API's writes (`job.submit`, `job.delete`): one
    /// that waits for the database's write lock (another process holding it, up to the
    /// busy timeout) holds neither `store`, which the streamer reads, nor a runtime
    /// worker (they run on tokio's blocking threads, see [`Shared::api_store`]).
    pub api_writes: std::sync::Mutex<store::Store>,
    /// Notification lines for subscribers (serialised once).
    pub notify: broadcast::Sender<Arc<str>>,
    /// Machine snapshot.
    pub machine: watch::Sender<MachineSnapshot>,
    /// Active job's progress.
    pub progress: watch::Sender<Option<Progress>>,
    /// Requests to the streamer.
    pub control: mpsc::Sender<Control>,
    /// Resolved serial port path.
    pub port: std::path::PathBuf,
    /// Incremented by every turn of the streamer's loop (watchdog liveness).
    pub alive: std::sync::atomic::AtomicU64,
    /// Memory for requests in flight across all clients (`api.memory_budget_bytes`).
    pub budget: connections::Budget,
}

/// Run `f` on the store behind `store`, its errors as the API's.
fn run_on<T>(
    store: &std::sync::Mutex<store::Store>,
    f: impl FnOnce(&store::Store) -> Result<T, store::StoreError>,
) -> Result<T, ApiError> {
    let guard = store
        .lock()
        .map_err(|_| ApiError::new(ApiError::INTERNAL, "job store lock poisoned"))?;
    f(&guard).map_err(|e| match e {
        store::StoreError::NotFound(id) => {
            ApiError::new(ApiError::NO_SUCH_JOB, format!("no job {id}"))
        }
        e => ApiError::new(ApiError::INTERNAL, e.to_string()),
    })
}

impl Shared {
    /// Run `f` on the store.
    pub fn with_store<T>(
        &self,
        f: impl FnOnce(&store::Store) -> Result<T, store::StoreError>,
    ) -> Result<T, ApiError> {
        run_on(&self.store, f)
    }

    /// Run `f` for an API request on a blocking thread, never on a runtime worker:
    /// on the API's own connection for a write (`write`), on `store` for a read (in WAL
    /// mode a read does not wait for another connection's write lock, but `store` can
    /// be held by the streamer while its state change waits for one).
    pub async fn api_store<T: Send + 'static>(
        self: &Arc<Self>,
        write: bool,
        f: impl FnOnce(&store::Store) -> Result<T, store::StoreError> + Send + 'static,
    ) -> Result<T, ApiError> {
        let shared = Arc::clone(self);
        tokio::task::spawn_blocking(move || {
            run_on(
                if write {
                    &shared.api_writes
                } else {
                    &shared.store
                },
                f,
            )
        })
        .await
        .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("job store call failed: {e}")))?
    }

    /// Send a notification to every subscriber (never blocks).
    pub fn notify(&self, event: crate::proto::Event) {
        match serde_json::to_string(&crate::proto::Notification::new(event)) {
            Ok(line) => {
                let _ = self.notify.send(Arc::from(line));
            }
            Err(e) => tracing::warn!(error = %e, "cannot serialise a notification"),
        }
    }
}
