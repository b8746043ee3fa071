//! A job as the API shows it (`docs/api.md`, Job): its state, checkpoint and the live
//! progress of the active one.

use serde::{Deserialize, Serialize};

// A job's state, checkpoint and progress are the lifecycle's own types, as the API
// shows them.
pub use crate::lifecycle::{Checkpoint, JobState, Progress};

/// A job (`job.get`, `job.list`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Job {
    /// Job id (also the wire job id of its moves); ids are never reused.
    pub id: u32,
    /// Name.
    pub name: String,
    /// State.
    pub state: JobState,
    /// Why it is paused, interrupted, failed or cancelled.
    pub reason: Option<String>,
    /// Moves planned in total, once planning has finished.
    pub total_moves: Option<u32>,
    /// Where to continue (the last checkpoint on disk).
    pub checkpoint: Checkpoint,
    /// Submission time (ms since the Unix epoch).
    pub submitted_ms: i64,
    /// When it first printed (ms since the Unix epoch; null before, and for jobs
    /// stored by an edod before the history was kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_ms: Option<i64>,
    /// When it was done, failed or cancelled (ms since the Unix epoch; null before).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_ms: Option<i64>,
    /// Last change (ms since the Unix epoch).
    pub updated_ms: i64,
    /// Live progress, for the active job only (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub progress: Option<Progress>,
}

/// A job changed state (`notify_job_state`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobStateChanged {
    /// Job id.
    pub job_id: u32,
    /// Its new state.
    pub state: JobState,
    /// Why (as in [`Job::reason`]), or null.
    pub reason: Option<String>,
}
