//! edod, the printer-host daemon: takes jobs from operators over a local socket, plans
//! them ahead, streams them to the machine and survives every crash.
//!
//! It reads like mini-redis: one file per component, typed channels between tasks,
//! shared state as snapshots (a watch channel), never a lock held across an await.
//!
//! - [`config`]: `edod.toml` (unknown keys refused, line/column errors).
//! - [`preflight`]: what a parsed config may still get wrong about this host (group,
//!   socket path length, fault names, serial port, line speed).
//! - [`store`]: jobs, states, checkpoints in SQLite (WAL); nothing accepted is lost. It
//!   has two threads of its own (a writer, a reader) reached over channels: no SQLite
//!   call and no wait for one runs on a runtime worker.
//! - [`connections`]: the socket's connections and their limits (idle timeout, a
//!   reserve for e-stop, one memory budget for requests in flight).
//! - [`api`]: the Unix socket, newline-delimited JSON-RPC 2.0 (`docs/api.md`),
//!   requests and notifications typed by [`crate::proto`]; slow clients are cut off,
//!   never waited for.
//! - [`planner`]: blocking workers that turn a job into moves layer by layer, ahead of
//!   the streamer through a bounded channel.
//! - [`streamer`]: the pump: the one task that owns the serial port; it feeds the
//!   sans-IO job lifecycle ([`crate::lifecycle::Lifecycle`]) the machine's events, the
//!   operators' commands, the planner's output, the store's answers and the clock, and
//!   carries out its actions. Progress is what the machine reports executed.
//!   The link under it is one of the core's sans-IO adapters ([`crate::adapter`]: the
//!   edo link or a G-code firmware); the streamer hands it bytes, the clock, the store's
//!   marks and its log lines.
//! - [`log_feed`]: the last lines of edod's log for `log.recent` (the dashboard's
//!   console).
//! - [`instance`]: one edod per state directory and socket (locks taken first), the
//!   modes of the files it creates.
//! - [`supervise`]: signals, systemd notify (READY, STATUS, WATCHDOG), the simulated
//!   machine child, graceful stop.

pub mod api;
pub mod config;
pub mod connections;
pub mod http;
pub mod instance;
pub mod log_feed;
pub mod planner;
pub mod port_watch;
pub mod preflight;
pub mod store;
pub mod streamer;
pub mod supervise;

use std::sync::Arc;

use tokio::sync::{broadcast, mpsc, oneshot, watch};

pub use config::Config;
pub use supervise::{run, run_until};

// The API's vocabulary lives in `proto` (shared with edoctl); the daemon speaks it.
pub use crate::proto::{ApiError, EStopTiming, MachineSnapshot, Progress, StateChange};

/// A reply channel for control requests.
pub type Reply<T> = oneshot::Sender<Result<T, ApiError>>;

/// Requests to the streamer.
#[derive(Debug)]
pub enum Control {
    /// A job was queued: start it when the machine is free.
    Submitted,
    /// Hold the job at a move boundary.
    Pause(u32, Reply<StateChange>),
    /// Continue a paused or interrupted job.
    Resume(u32, Reply<StateChange>),
    /// Cancel a job (stop, retract, park if it is printing).
    Cancel(u32, Reply<StateChange>),
    /// Start a queued job (the oldest when `None`) although an interrupted one holds
    /// the queue.
    StartNext(Option<u32>, Reply<StateChange>),
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
    /// The job store's threads.
    pub store: store::Stores,
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
    /// Set when edod starts stopping: previews and layer views stop planning.
    pub stopping: Arc<std::sync::atomic::AtomicBool>,
    /// The last lines of edod's log ([`log_feed`]), for `log.recent`.
    pub log: watch::Sender<Arc<Vec<crate::proto::LogLine>>>,
}

/// A store error as the API's: -32001 for a job not there, -32005 when another process
/// holds the store's lock, -32603 otherwise.
pub fn api_error(e: store::StoreError) -> ApiError {
    match e {
        store::StoreError::NotFound(id) => {
            ApiError::new(ApiError::NO_SUCH_JOB, format!("no job {id}"))
        }
        store::StoreError::Busy => ApiError::new(
            ApiError::STORE_BUSY,
            "job store busy, retry: another process holds the write lock of edod.db",
        ),
        e => ApiError::new(ApiError::INTERNAL, e.to_string()),
    }
}

/// A write's store error as the API's: as [`api_error`], but -32007 when SQLite cannot
/// write (a full disk, an I/O error).
pub fn api_write_error(e: store::StoreError) -> ApiError {
    if !e.is_write_failure() {
        return api_error(e);
    }
    ApiError::new(
        ApiError::STORE_CANNOT_WRITE,
        format!(
            "job store cannot write: {}; nothing was done (free space for edod's state \
             directory, then retry)",
            e.cause()
        ),
    )
}

impl Shared {
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
