//! edod, the printer-host daemon: takes jobs from operators over a local socket, plans
//! them ahead, streams them to the machine and survives every crash.
//!
//! It reads like mini-redis: one file per component, typed channels between tasks,
//! shared state as snapshots (a watch channel), never a lock held across an await.
//!
//! - [`config`]: `edod.toml` (unknown keys refused, line/column errors).
//! - [`store`]: jobs, states, checkpoints in SQLite (WAL); nothing accepted is lost.
//! - [`api`]: the Unix socket, newline-delimited JSON-RPC 2.0 (`docs/api.md`),
//!   requests and notifications; slow clients are cut off, never waited for.
//! - [`planner`]: blocking workers that turn a job into moves layer by layer, ahead of
//!   the streamer through a bounded channel.
//! - [`streamer`]: the one task that owns the serial port and pumps the sans-IO
//!   [`crate::link::Host`]; it runs the job lifecycle (start, pause, resume, cancel,
//!   e-stop, faults, checkpoints). Progress is what the machine reports executed.
//! - [`supervise`]: signals, systemd notify (READY, STATUS, WATCHDOG), the simulated
//!   machine child, graceful stop.

pub mod api;
pub mod checkpoints;
pub mod config;
pub mod planner;
pub mod store;
pub mod streamer;
pub mod supervise;

use std::sync::Arc;

use serde::Serialize;
use tokio::sync::{broadcast, mpsc, oneshot, watch};

pub use config::Config;
pub use supervise::{run, run_until};

/// A JSON-RPC error the API returns (code and message; `docs/api.md` lists the codes).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message} (code {code})")]
pub struct ApiError {
    /// JSON-RPC error code.
    pub code: i64,
    /// What went wrong, for a person.
    pub message: String,
}

impl ApiError {
    /// Invalid JSON.
    pub const PARSE: i64 = -32700;
    /// Not a JSON-RPC 2.0 request (or over the size limit).
    pub const INVALID_REQUEST: i64 = -32600;
    /// No such method.
    pub const METHOD_NOT_FOUND: i64 = -32601;
    /// Params missing, unknown or of the wrong type.
    pub const INVALID_PARAMS: i64 = -32602;
    /// The daemon failed.
    pub const INTERNAL: i64 = -32603;
    /// No such job.
    pub const NO_SUCH_JOB: i64 = -32001;
    /// The job is not in a state that allows this.
    pub const BAD_STATE: i64 = -32002;
    /// The job file does not validate.
    pub const INVALID_JOB: i64 = -32003;
    /// The machine is not connected.
    pub const NOT_CONNECTED: i64 = -32004;

    /// An error with a code and message.
    pub fn new(code: i64, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }
}

/// What the e-stop request measured.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct EStopTiming {
    /// From the request reaching the streamer to the frame written to the port (µs).
    pub written_after_us: u64,
    /// From the request to the machine's acknowledgement (µs), if it came within 1 s.
    pub acked_after_us: Option<u64>,
}

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

/// The machine as last reported, for `machine.status` and STATUS=.
#[derive(Debug, Clone, Default, Serialize)]
pub struct MachineSnapshot {
    /// Serial port.
    pub port: String,
    /// Handshake done and the link alive.
    pub connected: bool,
    /// Machine identity.
    pub identity: Option<String>,
    /// Execution state (`Idle`, `Running`, `Held`, `EStopped`, `Faulted`).
    pub state: Option<crate::link::MachineState>,
    /// Last executed move.
    pub last_executed: Option<crate::link::MoveRef>,
    /// Moves executed since the machine booted.
    pub executed_total: u64,
    /// Syringe volumes left (nl).
    pub remaining_nl: Vec<u32>,
    /// Moves in the machine's queue.
    pub queued: u16,
    /// Latched fault bits (`docs/protocol.md`).
    pub faults: u32,
    /// Nozzle position (mm).
    pub position_mm: [f64; 3],
    /// Job being streamed.
    pub active_job: Option<u32>,
    /// Times the machine ran out of moves while a job still had moves to stream.
    pub underruns: u64,
    /// Frames retransmitted on the link.
    pub frames_retransmitted: u64,
    /// Smoothed round-trip time on the link (ms).
    pub srtt_ms: f64,
}

/// Live progress of the active job.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct Progress {
    /// Job id.
    pub job_id: u32,
    /// Moves executed.
    pub executed: u32,
    /// Moves planned in total (once known).
    pub total: Option<u32>,
    /// Layers in the job (once known: a mesh job's after its mesh is sliced).
    pub layers: Option<u32>,
    /// Current layer (0-based: layer `layer` of `layers` is `layer + 1` of them).
    pub layer: Option<u32>,
    /// Composition of the last executed extrusion.
    pub composition: Option<Vec<f64>>,
    /// Estimated seconds left: from the move rate so far once `total` is known, before
    /// that from the layer rate (after the first layer finished since the start).
    pub eta_s: Option<f64>,
    /// From submission to the machine executing the first move (ms).
    pub first_move_after_ms: Option<i64>,
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
    pub fn notify(&self, method: &str, params: impl Serialize) {
        let v = serde_json::json!({"jsonrpc": "2.0", "method": method, "params": params});
        let _ = self.notify.send(Arc::from(v.to_string()));
    }
}
