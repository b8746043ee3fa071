//! The job database: every accepted job, its state, what is needed to plan it again, and
//! its checkpoint, in an embedded SQLite database (`edod.db` in the state directory).
//!
//! Crash safety: WAL journal with `synchronous = FULL`, so a `job.submit` answered with an
//! id has been written through to disk, and a checkpoint committed is never lost even on
//! power loss. Plans are not stored move by move: planning is deterministic, so the job
//! TOML (and its mesh) regenerates the exact move stream, and a checkpoint (first move not
//! executed, layer, composition, syringe volumes) says where to continue.
//!
//! The store is synchronous (rusqlite) and is only ever called on the store's own threads
//! (`writer`, `reader`): every call checks it is not on a tokio runtime thread
//! ([`StoreError::OnRuntime`]).

use std::path::Path;
use std::time::Duration;

use rusqlite::{params, Connection, OptionalExtension, Transaction, TransactionBehavior};
use serde::{Deserialize, Serialize};

pub use crate::adapter::{GcodeMark, GcodeMarkKind, GcodeMarkWrite};
use crate::lifecycle::{JobInfo, JobUpdate, Record};
pub use crate::proto::{Checkpoint, JobState};

/// How a job's moves are produced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobSpec {
    /// A job file (TOML) and its optional mesh.
    Toml {
        /// The job file text.
        toml: String,
        /// Mesh bytes (STL/3MF) sent with it.
        #[serde(skip)]
        mesh: Option<Vec<u8>>,
    },
    /// A dry-run job of this many zero-volume moves (qualifies the machine and the link
    /// the way `edoctl link-test` does, but through the whole daemon).
    DryRun {
        /// Moves.
        moves: u32,
    },
}

/// A job as stored: what the API shows of it ([`crate::proto::Job`], without live
/// progress, which is not stored), how its moves are produced, and what of its row
/// could not be read.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRecord {
    /// The job as `job.get` and `job.list` show it (`progress` always `None` here).
    pub job: crate::proto::Job,
    /// How its moves are produced.
    pub spec: JobSpec,
    /// What of its row could not be read (the job is then shown `failed` with the
    /// reason "stored job unreadable: …" and never planned).
    pub unreadable: Option<String>,
}

/// Store errors.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// SQLite failed.
    #[error("job store: {0}")]
    Sql(#[from] rusqlite::Error),
    /// Directory problems.
    #[error("job store {path}: {source}")]
    Io {
        /// Path.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// No such job.
    #[error("no job {0}")]
    NotFound(u32),
    /// Another process holds the database's write lock, past the time the caller waits.
    #[error("job store busy: another process holds the write lock of edod.db")]
    Busy,
    /// The store's thread has stopped.
    #[error("job store thread stopped")]
    Stopped,
    /// Called on a tokio runtime thread: a bug (the store has threads of its own).
    #[error("job store called on a tokio runtime thread (a bug: use the store's threads)")]
    OnRuntime,
    /// The database file fails SQLite's integrity check (or is no database at all).
    #[error(
        "job store {path} is damaged ({problems}); edod did not start. Stop anything \
         using the file and keep a copy of it, then recover what it holds into a new one \
         (sqlite3 {path} .recover | sqlite3 {path}.recovered) and move that in its place, \
         or move it away to start with an empty job store"
    )]
    Damaged {
        /// The file.
        path: String,
        /// What `PRAGMA quick_check` (or opening it) said.
        problems: String,
    },
    /// The database was written by a newer edod.
    #[error(
        "job store {path} has schema version {version}, newer than this edod knows \
         ({SCHEMA_VERSION}): a newer edod wrote it. Run that edod, or move the file \
         away to start with an empty job store"
    )]
    NewerSchema {
        /// The file.
        path: String,
        /// Its `PRAGMA user_version`.
        version: i64,
    },
    /// A job's row cannot be read (it is shown failed; it cannot be planned).
    #[error("job {id}: stored job unreadable: {what}")]
    Unreadable {
        /// Job id.
        id: u32,
        /// What could not be read.
        what: String,
    },
}

impl StoreError {
    /// The database is locked by another connection (SQLite's busy or locked).
    pub fn is_busy(&self) -> bool {
        match self {
            StoreError::Busy => true,
            StoreError::Sql(rusqlite::Error::SqliteFailure(e, _)) => matches!(
                e.code,
                rusqlite::ErrorCode::DatabaseBusy | rusqlite::ErrorCode::DatabaseLocked
            ),
            _ => false,
        }
    }

    /// The disk (or the file system's quota) is full: SQLite's `SQLITE_FULL`.
    pub fn is_full(&self) -> bool {
        matches!(
            self,
            StoreError::Sql(rusqlite::Error::SqliteFailure(e, _))
                if e.code == rusqlite::ErrorCode::DiskFull
        )
    }

    /// SQLite failed to write, for another reason than another process's lock.
    pub fn is_write_failure(&self) -> bool {
        matches!(self, StoreError::Sql(rusqlite::Error::SqliteFailure(..))) && !self.is_busy()
    }

    /// Why a write failed, for "job store cannot write: <cause>": `disk full`, else
    /// SQLite's or the OS's error.
    pub fn cause(&self) -> String {
        match self {
            e if e.is_full() => "disk full".into(),
            StoreError::Sql(e) => e.to_string(),
            e => e.to_string(),
        }
    }
}

impl JobRecord {
    /// What the lifecycle needs of the job.
    pub fn info(&self) -> JobInfo {
        let j = &self.job;
        JobInfo {
            id: j.id,
            state: j.state,
            checkpoint: j.checkpoint.clone(),
            total_moves: j.total_moves,
            submitted_ms: j.submitted_ms,
        }
    }
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// The job database.
pub struct Store {
    conn: Connection,
}

/// The columns a [`JobRecord`] is read from (all but the mesh).
const COLUMNS: &str = "id, name, state, reason, spec, total_moves, next_index, layer, \
     composition, remaining_nl, used_nl, submitted_ms, started_ms, ended_ms, updated_ms";

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    name TEXT NOT NULL,
    state TEXT NOT NULL,
    reason TEXT,
    spec TEXT NOT NULL,
    mesh BLOB,
    total_moves INTEGER,
    next_index INTEGER NOT NULL DEFAULT 0,
    layer INTEGER,
    composition TEXT,
    remaining_nl TEXT NOT NULL DEFAULT '[]',
    used_nl TEXT NOT NULL DEFAULT '[]',
    submitted_ms INTEGER NOT NULL,
    started_ms INTEGER,
    ended_ms INTEGER,
    updated_ms INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
-- Meshes apart from the jobs table: a job's row is updated at every checkpoint, and
-- SQLite rewrites a whole row (its overflow pages too) on every update.
CREATE TABLE IF NOT EXISTS job_meshes (id INTEGER PRIMARY KEY, mesh BLOB NOT NULL);
-- G-code link: where the line numbers of the current connection stand in a job's moves
-- (docs/firmware.md); a few rows, replaced at each connection.
CREATE TABLE IF NOT EXISTS gcode_marks (
    job_id INTEGER NOT NULL,
    line_number INTEGER NOT NULL,
    move_index INTEGER NOT NULL,
    kind TEXT NOT NULL
);
";

/// The database file in the state directory.
pub const DB_FILE: &str = "edod.db";

/// The schema version this edod writes (`PRAGMA user_version`): 0 is the unversioned
/// schema of the first edods, migrated at open; a newer one is refused.
///
/// 1: the job id high-water mark is kept in `meta` (`job_id_high_water`) apart from the
/// jobs table, so ids stay unique even if that table is lost.
/// 2: `gcode_marks` ([`GcodeMark`]), created empty.
/// 3: a job's history: `used_nl` (material per syringe), `started_ms` (first printing),
/// `ended_ms` (done, failed or cancelled); older jobs have none of them.
pub const SCHEMA_VERSION: i64 = 3;

/// The columns schema 3 added to `jobs`, with their definitions.
const HISTORY_COLUMNS: [(&str, &str); 3] = [
    ("used_nl", "TEXT NOT NULL DEFAULT '[]'"),
    ("started_ms", "INTEGER"),
    ("ended_ms", "INTEGER"),
];

/// `meta` key of the highest job id ever given.
const HIGH_WATER: &str = "job_id_high_water";

/// The highest job id ever given: the largest of the kept mark, AUTOINCREMENT's and the
/// ids stored.
const HIGHEST_ID: &str = "MAX(
    COALESCE((SELECT value FROM meta WHERE key = 'job_id_high_water'), 0),
    COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'jobs'), 0),
    COALESCE((SELECT MAX(id) FROM jobs), 0))";

/// Schema 3's columns on a `jobs` table made before (a table made now has them).
fn add_history_columns(tx: &Transaction<'_>) -> Result<(), StoreError> {
    let mut have = Vec::new();
    {
        let mut st = tx.prepare("SELECT name FROM pragma_table_info('jobs')")?;
        for name in st.query_map([], |r| r.get::<_, String>(0))? {
            have.push(name?);
        }
    }
    for (name, definition) in HISTORY_COLUMNS {
        if !have.iter().any(|h| h == name) {
            tx.execute(
                &format!("ALTER TABLE jobs ADD COLUMN {name} {definition}"),
                [],
            )?;
        }
    }
    Ok(())
}

/// An error reading the file at start (while `doing`): damaged if SQLite says it is
/// corrupt or no database.
fn damaged(path: &str, doing: &str, e: rusqlite::Error) -> StoreError {
    match &e {
        rusqlite::Error::SqliteFailure(f, _)
            if matches!(
                f.code,
                rusqlite::ErrorCode::DatabaseCorrupt | rusqlite::ErrorCode::NotADatabase
            ) =>
        {
            StoreError::Damaged {
                path: path.to_string(),
                problems: format!("{doing}{e}"),
            }
        }
        _ => StoreError::Sql(e),
    }
}

/// How long a statement waits for another connection's write lock, as opened.
pub const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// A transaction that takes the write lock at once (`BEGIN IMMEDIATE`): waiting for the
/// lock happens at its start, under the busy timeout, never half way through.
fn write_tx(conn: &Connection) -> Result<Transaction<'_>, StoreError> {
    Ok(Transaction::new_unchecked(
        conn,
        TransactionBehavior::Immediate,
    )?)
}

impl Store {
    /// Open (or create) `edod.db` in `dir`, migrating an older schema; refuses a newer
    /// one ([`StoreError::NewerSchema`]).
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        let (conn, version) = Self::connect(dir)?;
        Self::set_up(conn, version)
    }

    /// [`Store::open`] at edod's start: the file is checked first (`PRAGMA
    /// quick_check`, before anything is written), and refused
    /// ([`StoreError::Damaged`]) if it fails.
    pub fn open_checked(dir: &Path) -> Result<Store, StoreError> {
        let (conn, version) = Self::connect(dir)?;
        let path = dir.join(DB_FILE).display().to_string();
        let problems: Vec<String> = conn
            .prepare("PRAGMA quick_check(5)")
            .and_then(|mut st| {
                st.query_map([], |r| r.get::<_, String>(0))?
                    .collect::<Result<_, _>>()
            })
            .map_err(|e| damaged(&path, "PRAGMA quick_check: ", e))?;
        if problems != ["ok"] {
            return Err(StoreError::Damaged {
                path,
                problems: format!("PRAGMA quick_check: {}", problems.join("; ")),
            });
        }
        Self::set_up(conn, version)
    }

    /// The connection to `dir/edod.db` and its schema version.
    fn connect(dir: &Path) -> Result<(Connection, i64), StoreError> {
        off_runtime()?;
        std::fs::create_dir_all(dir).map_err(|source| StoreError::Io {
            path: dir.display().to_string(),
            source,
        })?;
        let path = dir.join(DB_FILE);
        let conn = Connection::open(&path)?;
        conn.busy_timeout(BUSY_TIMEOUT)?;
        let path = path.display().to_string();
        let version: i64 = conn
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .map_err(|e| damaged(&path, "", e))?;
        if version > SCHEMA_VERSION {
            return Err(StoreError::NewerSchema { path, version });
        }
        Ok((conn, version))
    }

    fn set_up(conn: Connection, version: i64) -> Result<Store, StoreError> {
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "FULL")?;
        let store = Store { conn };
        {
            let tx = write_tx(&store.conn)?;
            tx.execute_batch(SCHEMA)?;
            if version < 1 {
                // The unversioned schema: its id high-water mark is AUTOINCREMENT's alone.
                tx.execute(
                    &format!(
                        "INSERT INTO meta (key, value) VALUES ('{HIGH_WATER}', {HIGHEST_ID})
                         ON CONFLICT(key) DO UPDATE SET value = MAX(value, excluded.value)"
                    ),
                    [],
                )?;
            }
            if version < 3 {
                add_history_columns(&tx)?;
            }
            if version < SCHEMA_VERSION {
                tx.pragma_update(None, "user_version", SCHEMA_VERSION)?;
            }
            tx.commit()?;
        }
        Ok(store)
    }

    /// The connection, off the runtime.
    fn conn(&self) -> Result<&Connection, StoreError> {
        off_runtime()?;
        Ok(&self.conn)
    }

    /// Store a new job (queued) and return its id.
    pub fn insert(&self, name: &str, spec: &JobSpec) -> Result<u32, StoreError> {
        let tx = write_tx(self.conn()?)?;
        let id = Self::insert_in(&tx, name, spec)?;
        tx.commit()?;
        Ok(id)
    }

    fn insert_in(tx: &Transaction<'_>, name: &str, spec: &JobSpec) -> Result<u32, StoreError> {
        let spec_json = serde_json::to_string(spec).unwrap_or_default();
        let mesh = match spec {
            JobSpec::Toml { mesh, .. } => mesh.as_deref(),
            JobSpec::DryRun { .. } => None,
        };
        let t = now_ms();
        let highest: i64 = tx.query_row(&format!("SELECT {HIGHEST_ID}"), [], |r| r.get(0))?;
        let id = highest.saturating_add(1);
        if id > i64::from(u32::MAX) {
            return Err(StoreError::Sql(rusqlite::Error::IntegralValueOutOfRange(
                0, id,
            )));
        }
        tx.execute(
            "INSERT INTO jobs (id, name, state, spec, submitted_ms, updated_ms)
             VALUES (?1, ?2, 'queued', ?3, ?4, ?4)",
            params![id, name, spec_json, t],
        )?;
        tx.execute(
            &format!(
                "INSERT INTO meta (key, value) VALUES ('{HIGH_WATER}', ?1)
                 ON CONFLICT(key) DO UPDATE SET value = MAX(value, excluded.value)"
            ),
            [id],
        )?;
        if let Some(mesh) = mesh {
            tx.execute(
                "INSERT INTO job_meshes (id, mesh) VALUES (?1, ?2)",
                params![id, mesh],
            )?;
        }
        Ok(id as u32)
    }

    /// Store a new job (queued) and delete the finished jobs beyond the newest `keep`
    /// (at most `at_most` of them, see [`Store::prune_finished`]), in one transaction:
    /// the job's id and the ids deleted.
    pub fn insert_pruning(
        &self,
        name: &str,
        spec: &JobSpec,
        keep: usize,
        at_most: usize,
    ) -> Result<(u32, Vec<u32>), StoreError> {
        let tx = write_tx(self.conn()?)?;
        let id = Self::insert_in(&tx, name, spec)?;
        let pruned = Self::prune_in(&tx, keep, at_most)?;
        tx.commit()?;
        Ok((id, pruned))
    }

    /// A job's row. A column that cannot be read is not coerced: the job reads as
    /// `failed` with the reason "stored job unreadable: …" naming it (and what could be
    /// read), and is never planned.
    fn row(r: &rusqlite::Row<'_>) -> rusqlite::Result<JobRecord> {
        let mut bad = Vec::new();
        let id = r.get::<_, i64>("id")? as u32;
        let state_name: Option<String> = column(r, "state", &mut bad);
        let state = state_name.as_deref().and_then(|n| {
            let s = JobState::from_name(n);
            if s.is_none() {
                bad.push(format!("state: unknown state {n:?}"));
            }
            s
        });
        let reason: Option<String> = column(r, "reason", &mut bad).flatten();
        // The mesh stays in the database until the planner asks (`Store::mesh`).
        let spec = column::<String>(r, "spec", &mut bad)
            .and_then(|j| json(&j, "spec", &mut bad))
            .unwrap_or(JobSpec::DryRun { moves: 0 });
        let composition = column::<Option<String>>(r, "composition", &mut bad)
            .flatten()
            .and_then(|c| json(&c, "composition", &mut bad));
        let remaining_nl = column::<String>(r, "remaining_nl", &mut bad)
            .and_then(|v| json(&v, "remaining_nl", &mut bad))
            .unwrap_or_default();
        let used_nl = column::<String>(r, "used_nl", &mut bad)
            .and_then(|v| json(&v, "used_nl", &mut bad))
            .unwrap_or_default();
        let job = crate::proto::Job {
            id,
            name: column(r, "name", &mut bad).unwrap_or_default(),
            state: state.unwrap_or(JobState::Failed),
            reason,
            total_moves: count(r, "total_moves", &mut bad),
            checkpoint: Checkpoint {
                next_index: count(r, "next_index", &mut bad).unwrap_or(0),
                layer: count(r, "layer", &mut bad),
                composition,
                remaining_nl,
                used_nl,
            },
            submitted_ms: column(r, "submitted_ms", &mut bad).unwrap_or(0),
            started_ms: column(r, "started_ms", &mut bad).flatten(),
            ended_ms: column(r, "ended_ms", &mut bad).flatten(),
            updated_ms: column(r, "updated_ms", &mut bad).unwrap_or(0),
            progress: None,
        };
        let mut j = JobRecord {
            job,
            spec,
            unreadable: None,
        };
        if bad.is_empty() {
            check_row(&j, &mut bad);
        }
        if !bad.is_empty() {
            let what = bad.join("; ");
            // Quarantined earlier: the reason then written stays.
            let quarantined = state == Some(JobState::Failed)
                && j.job
                    .reason
                    .as_deref()
                    .is_some_and(|r| r.starts_with(UNREADABLE));
            if !quarantined {
                j.job.reason = Some(format!("{UNREADABLE} {what}"));
            }
            j.job.state = JobState::Failed;
            j.unreadable = Some(what);
        }
        Ok(j)
    }

    /// At start: every job whose row cannot be read (see [`Store::row`]) is stored as
    /// `failed`, "stored job unreadable: …", unless it already is. Returns those
    /// marked now, with what could not be read.
    pub fn quarantine_unreadable(&self) -> Result<Vec<(u32, String)>, StoreError> {
        let tx = write_tx(self.conn()?)?;
        let mut marked = Vec::new();
        for j in self.list()? {
            let Some(what) = j.unreadable else {
                continue;
            };
            let n = tx.execute(
                "UPDATE jobs SET state = 'failed', reason = ?2, updated_ms = ?3
                 WHERE id = ?1 AND (state IS NOT 'failed' OR reason IS NOT ?2)",
                params![j.job.id, j.job.reason, now_ms()],
            )?;
            if n > 0 {
                marked.push((j.job.id, what));
            }
        }
        tx.commit()?;
        Ok(marked)
    }

    /// One job.
    pub fn get(&self, id: u32) -> Result<JobRecord, StoreError> {
        self.conn()?
            .query_row(
                &format!("SELECT {COLUMNS} FROM jobs WHERE id = ?1"),
                [id],
                Store::row,
            )
            .optional()?
            .ok_or(StoreError::NotFound(id))
    }

    /// A job's mesh bytes (mesh jobs), read only when the planner needs them: listings
    /// and progress never load meshes.
    pub fn mesh(&self, id: u32) -> Result<Option<Vec<u8>>, StoreError> {
        self.get(id)?;
        Ok(self
            .conn()?
            .query_row("SELECT mesh FROM job_meshes WHERE id = ?1", [id], |r| {
                r.get(0)
            })
            .optional()?)
    }

    /// Every job, oldest first.
    pub fn list(&self) -> Result<Vec<JobRecord>, StoreError> {
        self.select("")
    }

    /// The queued jobs, oldest first.
    pub fn queued(&self) -> Result<Vec<JobRecord>, StoreError> {
        self.select("WHERE state = 'queued'")
    }

    /// The jobs the lifecycle must know at start: queued, and interrupted (one holds the
    /// queue until an operator decides), oldest first.
    pub fn waiting(&self) -> Result<Vec<JobRecord>, StoreError> {
        self.select("WHERE state IN ('queued', 'interrupted')")
    }

    fn select(&self, filter: &str) -> Result<Vec<JobRecord>, StoreError> {
        let mut st = self
            .conn()?
            .prepare(&format!("SELECT {COLUMNS} FROM jobs {filter} ORDER BY id"))?;
        let rows = st.query_map([], Store::row)?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// Change a job's state (and reason).
    pub fn set_state(
        &self,
        id: u32,
        state: JobState,
        reason: Option<&str>,
    ) -> Result<(), StoreError> {
        // History: the first time it prints, and when it ended.
        let n = self.conn()?.execute(
            "UPDATE jobs SET state = ?2, reason = ?3, updated_ms = ?4,
             started_ms = CASE WHEN ?2 = 'printing' THEN COALESCE(started_ms, ?4) ELSE started_ms END,
             ended_ms = CASE WHEN ?2 IN ('done', 'failed', 'cancelled') THEN ?4 ELSE ended_ms END
             WHERE id = ?1",
            params![id, state.as_str(), reason, now_ms()],
        )?;
        if n == 0 {
            return Err(StoreError::NotFound(id));
        }
        Ok(())
    }

    /// Record the total move count once planning finished.
    fn set_total(&self, id: u32, total: u32) -> Result<(), StoreError> {
        self.conn()?.execute(
            "UPDATE jobs SET total_moves = ?2 WHERE id = ?1",
            params![id, total],
        )?;
        Ok(())
    }

    /// Write a checkpoint.
    pub fn checkpoint(&self, id: u32, c: &Checkpoint) -> Result<(), StoreError> {
        self.conn()?.execute(
            "UPDATE jobs SET next_index = ?2, layer = ?3, composition = ?4, remaining_nl = ?5,
             updated_ms = ?6, used_nl = ?7 WHERE id = ?1",
            params![
                id,
                c.next_index,
                c.layer,
                c.composition
                    .as_ref()
                    .and_then(|v| serde_json::to_string(v).ok()),
                serde_json::to_string(&c.remaining_nl).unwrap_or_else(|_| "[]".into()),
                now_ms(),
                serde_json::to_string(&c.used_nl).unwrap_or_else(|_| "[]".into()),
            ],
        )?;
        Ok(())
    }

    /// Apply the lifecycle's records in one transaction (one fsync), in order: job
    /// checkpoints, move counts and states, and service index reservations. A job no
    /// longer stored (deleted) is skipped: returned are the ids skipped.
    pub fn apply(&self, records: &[Record]) -> Result<Vec<u32>, StoreError> {
        let tx = write_tx(self.conn()?)?;
        let mut missing = Vec::new();
        for r in records {
            match r {
                Record::Job(u) => {
                    if !self.apply_job(u)? {
                        missing.push(u.job_id);
                    }
                }
                Record::ServiceIndices { reserved_until } => {
                    self.set_service_reserved(*reserved_until)?
                }
            }
        }
        tx.commit()?;
        Ok(missing)
    }

    /// Change the stored G-code marks ([`GcodeMarkWrite`]).
    pub fn gcode_mark(&self, w: GcodeMarkWrite) -> Result<(), StoreError> {
        let tx = write_tx(self.conn()?)?;
        let add = match w {
            GcodeMarkWrite::Clear => None,
            GcodeMarkWrite::Writer(m) => Some(m),
            GcodeMarkWrite::Add(m) => {
                tx.execute(
                    "INSERT INTO gcode_marks (job_id, line_number, move_index, kind)
                     VALUES (?1, ?2, ?3, ?4)",
                    params![m.job_id, m.line_number, m.move_index, m.kind.as_str()],
                )?;
                return Ok(tx.commit()?);
            }
        };
        tx.execute("DELETE FROM gcode_marks", [])?;
        if let Some(m) = add {
            tx.execute(
                "INSERT INTO gcode_marks (job_id, line_number, move_index, kind)
                 VALUES (?1, ?2, ?3, ?4)",
                params![m.job_id, m.line_number, m.move_index, m.kind.as_str()],
            )?;
        }
        Ok(tx.commit()?)
    }

    /// The stored G-code marks, in line order; a row that cannot be read is left out.
    pub fn gcode_marks(&self) -> Result<Vec<GcodeMark>, StoreError> {
        let mut st = self.conn()?.prepare(
            "SELECT job_id, line_number, move_index, kind FROM gcode_marks ORDER BY line_number",
        )?;
        let rows = st.query_map([], |r| {
            Ok((
                r.get::<_, i64>(0)?,
                r.get::<_, i64>(1)?,
                r.get::<_, i64>(2)?,
                r.get::<_, String>(3)?,
            ))
        })?;
        let mut marks = Vec::new();
        for row in rows {
            let (job, line, index, kind) = row?;
            let kind = match kind.as_str() {
                "writer" => GcodeMarkKind::Writer,
                "m400" => GcodeMarkKind::M400,
                _ => continue,
            };
            if let (Ok(job_id), Ok(line_number), Ok(move_index)) = (
                u32::try_from(job),
                u32::try_from(line),
                u32::try_from(index),
            ) {
                marks.push(GcodeMark {
                    job_id,
                    line_number,
                    move_index,
                    kind,
                });
            }
        }
        Ok(marks)
    }

    /// Write one job's update; false if there is no such job.
    fn apply_job(&self, u: &JobUpdate) -> Result<bool, StoreError> {
        if let Some(c) = &u.checkpoint {
            self.checkpoint(u.job_id, c)?;
        }
        if let Some(t) = u.total_moves {
            self.set_total(u.job_id, t)?;
        }
        if let Some((state, reason)) = &u.state {
            match self.set_state(u.job_id, *state, reason.as_deref()) {
                Err(StoreError::NotFound(_)) => return Ok(false),
                r => r?,
            }
        }
        Ok(true)
    }

    /// Test only: the database may not grow beyond its size now (SQLite's
    /// `max_page_count`, for this connection): writes that need more fail as on a full
    /// disk (`SQLITE_FULL`).
    #[cfg(test)]
    pub fn limit_to_current_size(&self) {
        let pages: i64 = self
            .conn
            .pragma_query_value(None, "page_count", |r| r.get(0))
            .unwrap();
        self.conn
            .pragma_update(None, "max_page_count", pages)
            .unwrap();
    }

    /// How long a statement waits for another connection's write lock
    /// ([`BUSY_TIMEOUT`] as opened).
    pub fn set_busy_timeout(&mut self, t: Duration) -> Result<(), StoreError> {
        self.conn()?.busy_timeout(t)?;
        Ok(())
    }

    /// Delete job `id` and its mesh if it is finished (done, failed or cancelled);
    /// returns its state otherwise, and deletes nothing. Job ids are never reused
    /// (`AUTOINCREMENT`), so a machine's report of a deleted job's moves names no other.
    pub fn delete_finished(&self, id: u32) -> Result<Result<(), JobState>, StoreError> {
        let tx = write_tx(self.conn()?)?;
        let state = self.get(id)?.job.state;
        if !state.is_final() {
            return Ok(Err(state));
        }
        tx.execute("DELETE FROM job_meshes WHERE id = ?1", [id])?;
        tx.execute("DELETE FROM jobs WHERE id = ?1", [id])?;
        tx.commit()?;
        Ok(Ok(()))
    }

    /// Delete the finished jobs (and their meshes) older than the newest `keep` of them,
    /// at most `at_most` of them (the oldest) in one call, so that a database grown
    /// large before a lower `keep` holds the store's lock only briefly; returns the
    /// ids deleted, oldest first. Unfinished jobs are never touched.
    pub fn prune_finished(&self, keep: usize, at_most: usize) -> Result<Vec<u32>, StoreError> {
        let tx = write_tx(self.conn()?)?;
        let ids = Self::prune_in(&tx, keep, at_most)?;
        tx.commit()?;
        Ok(ids)
    }

    fn prune_in(tx: &Transaction<'_>, keep: usize, at_most: usize) -> Result<Vec<u32>, StoreError> {
        let ids: Vec<u32> = {
            let mut st = tx.prepare(
                "SELECT id FROM jobs WHERE state IN ('done', 'failed', 'cancelled')
                 ORDER BY id DESC LIMIT -1 OFFSET ?1",
            )?;
            let rows = st.query_map([keep as i64], |r| r.get::<_, i64>(0))?;
            rows.collect::<Result<Vec<_>, _>>()?
                .into_iter()
                .rev()
                .take(at_most)
                .map(|v| v as u32)
                .collect()
        };
        for &id in &ids {
            tx.execute("DELETE FROM job_meshes WHERE id = ?1", [id])?;
            tx.execute("DELETE FROM jobs WHERE id = ?1", [id])?;
        }
        Ok(ids)
    }

    /// At start-up: jobs that were planning, printing or paused when edod stopped are
    /// interrupted (they resume from their checkpoint). Returns their ids.
    pub fn interrupt_unfinished(&self, reason: &str) -> Result<Vec<u32>, StoreError> {
        let tx = write_tx(self.conn()?)?;
        let ids: Vec<u32> = {
            let mut st = tx.prepare(
                "SELECT id FROM jobs WHERE state IN ('planning', 'printing', 'paused') ORDER BY id",
            )?;
            let rows = st.query_map([], |r| r.get::<_, i64>(0))?;
            rows.collect::<Result<Vec<_>, _>>()?
                .into_iter()
                .map(|v| v as u32)
                .collect()
        };
        for &id in &ids {
            self.set_state(id, JobState::Interrupted, Some(reason))?;
        }
        tx.commit()?;
        Ok(ids)
    }

    /// The first service move index not reserved by an earlier run (0 at first).
    fn service_reserved(&self) -> Result<u32, StoreError> {
        let v: Option<i64> = self
            .conn()?
            .query_row(
                "SELECT value FROM meta WHERE key = 'service_index'",
                [],
                |r| r.get(0),
            )
            .optional()?;
        Ok(v.unwrap_or(0).clamp(0, i64::from(u32::MAX)) as u32)
    }

    fn set_service_reserved(&self, until: u32) -> Result<(), StoreError> {
        self.conn()?.execute(
            "INSERT INTO meta (key, value) VALUES ('service_index', ?1)
             ON CONFLICT(key) DO UPDATE SET value = MAX(value, excluded.value)",
            [i64::from(until)],
        )?;
        Ok(())
    }

    /// At start-up: reserve `block` service move indices for this run (the machine's
    /// order check of job 0 must never see an index twice across restarts). Returns the
    /// first index and the end of the reservation.
    pub fn reserve_service_indices(&self, block: u32) -> Result<(u32, u32), StoreError> {
        let tx = write_tx(self.conn()?)?;
        let first = self.service_reserved()?;
        let until = first.saturating_add(block);
        self.set_service_reserved(until)?;
        tx.commit()?;
        Ok((first, until))
    }
}

/// The reason of a job whose row cannot be read starts so.
pub const UNREADABLE: &str = "stored job unreadable:";

/// What a row that parsed holds that the API would never have stored (a damaged or
/// edited file): a dry run of no moves, a checkpoint past the job's last move. Such a
/// job would end `done` with nothing run; it is failed instead, naming the column.
fn check_row(j: &JobRecord, bad: &mut Vec<String>) {
    if matches!(j.spec, JobSpec::DryRun { moves: 0 }) {
        bad.push("spec: a dry run of 0 moves (the API takes 1 or more)".into());
    }
    if let Some(total) = j
        .job
        .total_moves
        .filter(|t| j.job.checkpoint.next_index > *t)
    {
        bad.push(format!(
            "next_index: {} is past the job's {total} moves",
            j.job.checkpoint.next_index
        ));
    }
}

/// Column `name` of `r`, or `None` with what is wrong with it added to `bad`.
fn column<T: rusqlite::types::FromSql>(
    r: &rusqlite::Row<'_>,
    name: &str,
    bad: &mut Vec<String>,
) -> Option<T> {
    match r.get::<_, T>(name) {
        Ok(v) => Some(v),
        Err(e) => {
            bad.push(format!("{name}: {e}"));
            None
        }
    }
}

/// Count column `name` (NULL or a whole number 0 ..= 2^32 - 1).
fn count(r: &rusqlite::Row<'_>, name: &str, bad: &mut Vec<String>) -> Option<u32> {
    let v = column::<Option<i64>>(r, name, bad).flatten()?;
    match u32::try_from(v) {
        Ok(v) => Some(v),
        Err(_) => {
            bad.push(format!("{name}: {v} is out of range"));
            None
        }
    }
}

/// `text` (column `name`) as JSON of a `T`, or `None` with why added to `bad`.
fn json<T: serde::de::DeserializeOwned>(
    text: &str,
    name: &str,
    bad: &mut Vec<String>,
) -> Option<T> {
    match serde_json::from_str(text) {
        Ok(v) => Some(v),
        Err(e) => {
            bad.push(format!("{name}: {e}"));
            None
        }
    }
}

/// Fails on a tokio runtime thread (its workers and its blocking pool alike): SQLite
/// waits for locks and for the disk, and the store has threads of its own for that.
fn off_runtime() -> Result<(), StoreError> {
    if tokio::runtime::Handle::try_current().is_ok() {
        return Err(StoreError::OnRuntime);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_write_through_another_process_lock_fails_naming_the_locked_database() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        s.set_busy_timeout(std::time::Duration::from_millis(50))
            .unwrap();
        let other = Connection::open(dir.path().join("edod.db")).unwrap();
        other.execute_batch("BEGIN IMMEDIATE").unwrap();
        let e = s.insert("j", &JobSpec::DryRun { moves: 3 }).unwrap_err();
        assert_eq!(e.to_string(), "job store: database is locked");
        // Reads go on through the lock (WAL), and the write goes through once it is gone.
        assert!(s.list().unwrap().is_empty());
        other.execute_batch("COMMIT").unwrap();
        let id = s.insert("j", &JobSpec::DryRun { moves: 3 }).unwrap();
        assert_eq!(s.get(id).unwrap().job.name, "j");
    }

    #[test]
    fn finished_jobs_are_deleted_on_request_or_beyond_the_newest_kept() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        let mesh_job = JobSpec::Toml {
            toml: "name = 'm'".into(),
            mesh: Some(vec![1, 2, 3]),
        };
        let ids: Vec<u32> = (0..6)
            .map(|k| {
                let spec = if k % 2 == 0 {
                    mesh_job.clone()
                } else {
                    JobSpec::DryRun { moves: 5 }
                };
                s.insert(&format!("j{k}"), &spec).unwrap()
            })
            .collect();
        assert_eq!(ids, [1, 2, 3, 4, 5, 6]);
        // 1 done, 2 printing, 3 failed, 4 cancelled, 5 done, 6 queued.
        for (id, st) in [
            (1, JobState::Done),
            (2, JobState::Printing),
            (3, JobState::Failed),
            (4, JobState::Cancelled),
            (5, JobState::Done),
        ] {
            s.set_state(id, st, None).unwrap();
        }
        assert_eq!(s.delete_finished(2).unwrap(), Err(JobState::Printing));
        assert_eq!(s.delete_finished(6).unwrap(), Err(JobState::Queued));
        assert!(matches!(s.delete_finished(9), Err(StoreError::NotFound(9))));
        assert_eq!(s.delete_finished(3).unwrap(), Ok(()));
        assert!(matches!(s.get(3), Err(StoreError::NotFound(3))));
        assert!(matches!(s.mesh(3), Err(StoreError::NotFound(3))));
        // Finished now: 1, 4, 5. Keep the newest two.
        assert_eq!(s.prune_finished(2, 10).unwrap(), vec![1]);
        assert_eq!(s.prune_finished(2, 10).unwrap(), Vec::<u32>::new());
        let left: Vec<u32> = s.list().unwrap().iter().map(|j| j.job.id).collect();
        assert_eq!(left, vec![2, 4, 5, 6]);
        // The meshes went with their jobs, and ids are not reused.
        let meshes: i64 = s
            .conn
            .query_row("SELECT COUNT(*) FROM job_meshes", [], |r| r.get(0))
            .unwrap();
        assert_eq!(meshes, 1, "job 5's mesh");
        assert_eq!(s.insert("new", &JobSpec::DryRun { moves: 1 }).unwrap(), 7);
        // At most one a call: the oldest first.
        assert_eq!(s.prune_finished(0, 1).unwrap(), vec![4]);
        assert_eq!(s.prune_finished(0, 1).unwrap(), vec![5]);
        // Not even the newest id comes back once deleted.
        s.set_state(7, JobState::Done, None).unwrap();
        assert_eq!(s.delete_finished(7).unwrap(), Ok(()));
        assert_eq!(s.insert("newer", &JobSpec::DryRun { moves: 1 }).unwrap(), 8);
    }

    #[test]
    fn jobs_survive_reopen_and_unfinished_ones_are_interrupted() {
        let dir = tempfile::tempdir().unwrap();
        {
            let s = Store::open(dir.path()).unwrap();
            let a = s.insert("a", &JobSpec::DryRun { moves: 10 }).unwrap();
            let b = s
                .insert(
                    "b",
                    &JobSpec::Toml {
                        toml: "name = 'b'".into(),
                        mesh: Some(vec![0, 1, 2, 255]),
                    },
                )
                .unwrap();
            assert_eq!((a, b), (1, 2));
            s.set_state(a, JobState::Printing, None).unwrap();
            let c = Checkpoint {
                next_index: 7,
                layer: Some(1),
                composition: Some(vec![0.25, 0.75]),
                remaining_nl: vec![5, 6],
                used_nl: vec![4_000_000_000_000, 0],
            };
            s.checkpoint(a, &c).unwrap();
            assert_eq!(s.reserve_service_indices(100).unwrap(), (0, 100));
            // A reservation recorded by the lifecycle moves the end on.
            s.apply(&[Record::ServiceIndices {
                reserved_until: 150,
            }])
            .unwrap();
        }
        let s = Store::open(dir.path()).unwrap();
        assert_eq!(s.interrupt_unfinished("restart").unwrap(), vec![1]);
        let a = s.get(1).unwrap();
        assert_eq!(a.job.state, JobState::Interrupted);
        assert_eq!(a.job.checkpoint.next_index, 7);
        assert_eq!(a.job.checkpoint.composition, Some(vec![0.25, 0.75]));
        let b = s.get(2).unwrap();
        // Records come without their mesh; the planner asks for it.
        assert_eq!(
            b.spec,
            JobSpec::Toml {
                toml: "name = 'b'".into(),
                mesh: None
            }
        );
        assert_eq!(s.mesh(2).unwrap(), Some(vec![0, 1, 2, 255]));
        assert_eq!(s.mesh(1).unwrap(), None);
        assert!(matches!(s.mesh(9), Err(StoreError::NotFound(9))));
        let queued: Vec<u32> = s.queued().unwrap().iter().map(|j| j.job.id).collect();
        assert_eq!(queued, [2]);
        assert_eq!(s.reserve_service_indices(100).unwrap(), (150, 250));
        assert!(matches!(s.get(9), Err(StoreError::NotFound(9))));
    }

    #[test]
    fn records_apply_in_one_go_and_a_deleted_job_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        let a = s.insert("a", &JobSpec::DryRun { moves: 10 }).unwrap();
        let c = |next_index| Checkpoint {
            next_index,
            ..Checkpoint::default()
        };
        let job = |checkpoint, total_moves, state| {
            Record::Job(JobUpdate {
                job_id: a,
                checkpoint,
                total_moves,
                state,
            })
        };
        let missing = s
            .apply(&[
                job(Some(c(3)), None, Some((JobState::Printing, None))),
                job(None, Some(10), None),
                job(
                    Some(c(7)),
                    None,
                    Some((JobState::Paused, Some("paused by an operator".into()))),
                ),
                Record::Job(JobUpdate {
                    job_id: 99,
                    state: Some((JobState::Done, None)),
                    ..JobUpdate::default()
                }),
            ])
            .unwrap();
        assert_eq!(missing, [99]);
        let j = s.get(a).unwrap();
        assert_eq!(j.job.state, JobState::Paused);
        assert_eq!(j.job.reason.as_deref(), Some("paused by an operator"));
        assert_eq!(j.job.checkpoint.next_index, 7);
        assert_eq!(j.job.total_moves, Some(10));
    }

    #[test]
    fn the_store_refuses_to_run_on_a_tokio_runtime_thread() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let on_worker = rt.block_on(async { s.list().map(|_| ()) });
        assert!(matches!(on_worker, Err(StoreError::OnRuntime)));
        let path = dir.path().to_path_buf();
        let on_blocking_pool = rt.block_on(async move {
            tokio::task::spawn_blocking(move || Store::open(&path).map(|_| ()))
                .await
                .unwrap()
        });
        assert!(matches!(on_blocking_pool, Err(StoreError::OnRuntime)));
        assert!(s.list().is_ok(), "off the runtime");
    }

    /// A database as the unversioned (first) edods wrote it: jobs 1..=3, job 3 deleted.
    fn unversioned(dir: &Path) {
        let c = Connection::open(dir.join(DB_FILE)).unwrap();
        c.execute_batch(SCHEMA_V0).unwrap();
        for k in 1..=3 {
            c.execute(
                "INSERT INTO jobs (name, state, spec, submitted_ms, updated_ms)
                 VALUES (?1, 'done', '{\"dry_run\":{\"moves\":3}}', 0, 0)",
                [format!("j{k}")],
            )
            .unwrap();
        }
        c.execute("DELETE FROM jobs WHERE id = 3", []).unwrap();
    }

    /// The schema of the first edods (no version, no id high-water mark).
    const SCHEMA_V0: &str = "
        CREATE TABLE jobs (id INTEGER PRIMARY KEY AUTOINCREMENT, name TEXT NOT NULL,
            state TEXT NOT NULL, reason TEXT, spec TEXT NOT NULL, mesh BLOB,
            total_moves INTEGER, next_index INTEGER NOT NULL DEFAULT 0, layer INTEGER,
            composition TEXT, remaining_nl TEXT NOT NULL DEFAULT '[]',
            submitted_ms INTEGER NOT NULL, updated_ms INTEGER NOT NULL);
        CREATE TABLE meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
        CREATE TABLE job_meshes (id INTEGER PRIMARY KEY, mesh BLOB NOT NULL);";

    fn user_version(dir: &Path) -> i64 {
        Connection::open(dir.join(DB_FILE))
            .unwrap()
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .unwrap()
    }

    #[test]
    fn an_unversioned_store_is_migrated_and_ids_survive_a_lost_jobs_table() {
        let dir = tempfile::tempdir().unwrap();
        unversioned(dir.path());
        assert_eq!(user_version(dir.path()), 0);
        let s = Store::open_checked(dir.path()).unwrap();
        assert_eq!(user_version(dir.path()), SCHEMA_VERSION);
        assert_eq!(s.list().unwrap().len(), 2);
        // Job 3 was deleted: its id is not given again.
        assert_eq!(s.insert("a", &JobSpec::DryRun { moves: 1 }).unwrap(), 4);
        drop(s);
        // The jobs table lost (AUTOINCREMENT's counter goes with it).
        Connection::open(dir.path().join(DB_FILE))
            .unwrap()
            .execute_batch("DROP TABLE jobs")
            .unwrap();
        let s = Store::open_checked(dir.path()).unwrap();
        assert!(s.list().unwrap().is_empty());
        assert_eq!(s.insert("b", &JobSpec::DryRun { moves: 1 }).unwrap(), 5);
        // And the mark lost instead: AUTOINCREMENT's and the ids stored still count.
        s.conn.execute("DELETE FROM meta", []).unwrap();
        assert_eq!(s.insert("c", &JobSpec::DryRun { moves: 1 }).unwrap(), 6);
    }

    #[test]
    fn a_version_1_store_gains_gcode_marks_replaced_at_each_writer() {
        let dir = tempfile::tempdir().unwrap();
        drop(Store::open(dir.path()).unwrap());
        let c = Connection::open(dir.path().join(DB_FILE)).unwrap();
        c.execute_batch("DROP TABLE gcode_marks; PRAGMA user_version = 1;")
            .unwrap();
        drop(c);
        let s = Store::open_checked(dir.path()).unwrap();
        assert_eq!(user_version(dir.path()), SCHEMA_VERSION);
        assert!(s.gcode_marks().unwrap().is_empty());
        let mark = |job_id, line_number, kind| GcodeMark {
            job_id,
            line_number,
            move_index: 5,
            kind,
        };
        s.gcode_mark(GcodeMarkWrite::Writer(mark(1, 2, GcodeMarkKind::Writer)))
            .unwrap();
        s.gcode_mark(GcodeMarkWrite::Add(mark(1, 40, GcodeMarkKind::M400)))
            .unwrap();
        assert_eq!(
            s.gcode_marks().unwrap(),
            [
                mark(1, 2, GcodeMarkKind::Writer),
                mark(1, 40, GcodeMarkKind::M400)
            ]
        );
        s.gcode_mark(GcodeMarkWrite::Writer(mark(2, 9, GcodeMarkKind::Writer)))
            .unwrap();
        assert_eq!(
            s.gcode_marks().unwrap(),
            [mark(2, 9, GcodeMarkKind::Writer)]
        );
        s.gcode_mark(GcodeMarkWrite::Clear).unwrap();
        assert!(s.gcode_marks().unwrap().is_empty());
    }

    #[test]
    fn a_newer_schema_is_refused_naming_the_file_and_its_version() {
        let dir = tempfile::tempdir().unwrap();
        drop(Store::open(dir.path()).unwrap());
        Connection::open(dir.path().join(DB_FILE))
            .unwrap()
            .pragma_update(None, "user_version", 7)
            .unwrap();
        let e = Store::open_checked(dir.path()).err().unwrap();
        assert!(
            matches!(e, StoreError::NewerSchema { version: 7, .. }),
            "{e}"
        );
        let m = e.to_string();
        assert!(
            m.contains(&dir.path().join(DB_FILE).display().to_string()),
            "{m}"
        );
        assert!(
            m.contains("schema version 7, newer than this edod knows (3)"),
            "{m}"
        );
        assert_eq!(user_version(dir.path()), 7, "left as it was");
    }

    #[test]
    fn random_bytes_over_pages_are_noticed_at_open() {
        let dir = tempfile::tempdir().unwrap();
        {
            let s = Store::open(dir.path()).unwrap();
            for k in 0..200 {
                s.insert(
                    &format!("job {k} {}", "x".repeat(200)),
                    &JobSpec::DryRun { moves: 1 },
                )
                .unwrap();
            }
            s.conn
                .pragma_update(None, "wal_checkpoint", "TRUNCATE")
                .unwrap();
        }
        let path = dir.path().join(DB_FILE);
        let mut bytes = std::fs::read(&path).unwrap();
        assert!(bytes.len() > 8 * 4096, "{}", bytes.len());
        // Page 4 (of 4 KiB pages): a leaf of the jobs table.
        let mut x: u32 = 12345;
        for b in &mut bytes[3 * 4096..4 * 4096] {
            x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
            *b = (x >> 16) as u8;
        }
        std::fs::write(&path, &bytes).unwrap();
        let e = Store::open_checked(dir.path()).err().unwrap();
        let m = e.to_string();
        assert!(matches!(e, StoreError::Damaged { .. }), "{m}");
        assert!(m.contains(&path.display().to_string()), "{m}");
        assert!(m.contains("quick_check") && m.contains(".recover"), "{m}");
        // Not a database at all.
        std::fs::write(&path, vec![0x55; 8192]).unwrap();
        let m = Store::open_checked(dir.path()).err().unwrap().to_string();
        assert!(m.contains("is damaged (file is not a database)"), "{m}");
    }

    /// The ids [`Store::quarantine_unreadable`] marks failed now.
    fn quarantined(s: &Store) -> Vec<u32> {
        s.quarantine_unreadable()
            .unwrap()
            .iter()
            .map(|m| m.0)
            .collect()
    }

    /// Rows that parse but hold what the API never stores (issue 41's probe: a dry run of
    /// 0 moves ended `done 0/0`; `next_index = 100000` on a 100-move job ended `done
    /// 100000/100`, nothing run): failed, naming the column, never planned.
    #[test]
    fn rows_the_api_would_never_store_are_quarantined() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        for k in 1..=3 {
            s.insert(&format!("j{k}"), &JobSpec::DryRun { moves: 100 })
                .unwrap();
        }
        for (id, sql) in [
            (
                1,
                r#"UPDATE jobs SET spec = '{"dry_run":{"moves":0}}' WHERE id = 1"#,
            ),
            (
                2,
                "UPDATE jobs SET total_moves = 100, next_index = 100000 WHERE id = 2",
            ),
        ] {
            assert_eq!(s.conn.execute(sql, []).unwrap(), 1, "job {id}");
        }
        let list = s.list().unwrap();
        let reason = |k: usize| list[k].job.reason.clone().unwrap_or_default();
        assert!(
            reason(0).contains("spec: a dry run of 0 moves"),
            "{}",
            reason(0)
        );
        assert!(
            reason(1).contains("next_index: 100000 is past the job's 100 moves"),
            "{}",
            reason(1)
        );
        assert!(list[..2].iter().all(|j| j.job.state == JobState::Failed));
        assert_eq!(list[2].job.state, JobState::Queued);
        let marked = quarantined(&s);
        assert_eq!(marked, [1, 2]);
    }

    #[test]
    fn rows_that_cannot_be_read_are_quarantined_not_coerced() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        for k in 1..=5 {
            s.insert(&format!("j{k}"), &JobSpec::DryRun { moves: 10 })
                .unwrap();
        }
        s.set_state(4, JobState::Printing, None).unwrap();
        for (id, sql) in [
            (1, "UPDATE jobs SET spec = 'not json' WHERE id = 1"),
            (2, "UPDATE jobs SET next_index = 'seven' WHERE id = 2"),
            (3, "UPDATE jobs SET state = 'frobbed' WHERE id = 3"),
            (
                4,
                "UPDATE jobs SET next_index = -1, remaining_nl = '{' WHERE id = 4",
            ),
        ] {
            assert_eq!(s.conn.execute(sql, []).unwrap(), 1, "job {id}");
        }
        // Every job is listed; the bad ones as failed, naming what is wrong.
        let list = s.list().unwrap();
        let view: Vec<(u32, JobState, String)> = list
            .iter()
            .map(|j| {
                (
                    j.job.id,
                    j.job.state,
                    j.job.reason.clone().unwrap_or_default(),
                )
            })
            .collect();
        assert_eq!(view[4], (5, JobState::Queued, String::new()));
        for (id, _, reason) in &view[..4] {
            assert!(
                reason.starts_with("stored job unreadable: "),
                "job {id}: {reason}"
            );
        }
        assert!(view[0].2.contains("spec: expected value"), "{}", view[0].2);
        assert!(view[1].2.contains("next_index: "), "{}", view[1].2);
        assert!(
            view[2].2.contains("state: unknown state \"frobbed\""),
            "{}",
            view[2].2
        );
        assert!(
            view[3].2.contains("next_index: -1 is out of range"),
            "{}",
            view[3].2
        );
        assert!(view[3].2.contains("remaining_nl: "), "{}", view[3].2);
        assert!(list[..4].iter().all(|j| j.job.state == JobState::Failed));
        // Marked failed on disk at start, once; the queued list leaves them out.
        let marked = quarantined(&s);
        assert_eq!(marked, [1, 2, 3, 4]);
        assert!(s.quarantine_unreadable().unwrap().is_empty());
        assert_eq!(
            s.interrupt_unfinished("restart").unwrap(),
            Vec::<u32>::new()
        );
        let queued: Vec<u32> = s.queued().unwrap().iter().map(|j| j.job.id).collect();
        assert_eq!(queued, [5]);
        assert_eq!(
            s.get(3).unwrap().job.reason,
            list[2].job.reason,
            "the reason stays"
        );
        assert!(s.get(1).unwrap().unreadable.is_some());
        // A quarantined job can be deleted.
        assert_eq!(s.delete_finished(1).unwrap(), Ok(()));
    }
}
