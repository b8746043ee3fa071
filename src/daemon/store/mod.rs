//! The job store: every accepted job, its state, what is needed to plan it again, and its
//! checkpoint, in SQLite (`edod.db` in the state directory; the database itself is
//! [`sql`]), reached only through two threads of its own:
//!
//! - [`writer`]: the lifecycle's records (checkpoints, move counts, states, service
//!   index reservations), written in order and reported back as lifecycle events, and
//!   the API's submissions and deletions, each waiting for another process's write lock
//!   only until its deadline.
//! - [`reader`]: the API's reads, the lifecycle's reads (queued jobs, a job looked up)
//!   and the planner's (a job's spec and mesh).
//!
//! Architecture invariant: no SQLite call and no wait for one runs on a tokio runtime
//! thread. Tasks hand requests over channels and await the answers; [`sql::Store`]
//! refuses to run on a runtime thread ([`StoreError::OnRuntime`]), and `rusqlite` is
//! used nowhere outside this module (a test in `tests/daemon.rs` checks the source).

pub mod reader;
pub mod sql;
pub mod writer;

use std::path::Path;

use tokio::sync::mpsc;

pub use reader::Reader;
pub use sql::{
    now_ms, GcodeMark, GcodeMarkKind, GcodeMarkWrite, JobRecord, JobSpec, Store, StoreError,
    BUSY_TIMEOUT, DB_FILE,
};
pub use writer::Writer;

use crate::lifecycle::Event;

/// The store's two threads.
#[derive(Clone)]
pub struct Stores {
    /// Reads.
    pub reader: Reader,
    /// Writes.
    pub writer: Writer,
}

/// The store as opened at start-up.
pub struct Opened {
    /// Its threads.
    pub stores: Stores,
    /// Jobs the previous run left planning, printing or paused, now interrupted.
    pub interrupted: Vec<u32>,
    /// Jobs whose rows could not be read, now failed ("stored job unreadable"), with
    /// what could not be read.
    pub quarantined: Vec<(u32, String)>,
    /// The first service move index of this run.
    pub service_index: u32,
    /// The end of the service indices reserved for it.
    pub service_reserved_until: u32,
    /// Where the previous run's G-code line numbers stood in a job's moves.
    pub gcode_marks: Vec<GcodeMark>,
}

/// [`open`] on a thread of its own, awaited (for the runtime).
pub async fn start(
    dir: std::path::PathBuf,
    service_block: u32,
    events: mpsc::UnboundedSender<Event>,
) -> Result<Opened, StoreError> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("edod-store-open".into())
        .spawn(move || {
            let _ = tx.send(open(&dir, service_block, events));
        })
        .map_err(|source| StoreError::Io {
            path: "edod-store-open thread".into(),
            source,
        })?;
    rx.await.map_err(|_| StoreError::Stopped)?
}

/// Open the store in `dir` and start its threads, whose lifecycle events go to
/// `events`. Blocking (call it off the runtime): the file is checked first (a damaged
/// one or a newer schema is refused), jobs whose rows cannot be read are failed, the
/// jobs the previous run left unfinished are interrupted, and `service_block` service
/// move indices reserved.
pub fn open(
    dir: &Path,
    service_block: u32,
    events: mpsc::UnboundedSender<Event>,
) -> Result<Opened, StoreError> {
    let store = Store::open_checked(dir)?;
    let quarantined = store.quarantine_unreadable()?;
    let interrupted = store.interrupt_unfinished("edod restarted")?;
    let (service_index, service_reserved_until) = store.reserve_service_indices(service_block)?;
    let gcode_marks = store.gcode_marks()?;
    let thread_error = |source| StoreError::Io {
        path: dir.display().to_string(),
        source,
    };
    let reader = Reader::start(Store::open(dir)?, events.clone()).map_err(thread_error)?;
    let writer = Writer::start(store, events).map_err(thread_error)?;
    Ok(Opened {
        stores: Stores { reader, writer },
        interrupted,
        quarantined,
        service_index,
        service_reserved_until,
        gcode_marks,
    })
}
