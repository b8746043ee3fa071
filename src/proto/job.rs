//! A job as the API shows it (`docs/api.md`, Job): its state, checkpoint and the live
//! progress of the active one.

use serde::{Deserialize, Serialize};

/// Where a job is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Accepted, waiting for the machine.
    Queued,
    /// Its first layer is being planned.
    Planning,
    /// Moves are streaming.
    Printing,
    /// Held at a move boundary (by an operator or a syringe running empty).
    Paused,
    /// Stopped by a fault (reset, lost link, e-stop, edod restart); resumable.
    Interrupted,
    /// Every move executed.
    Done,
    /// Cannot be planned or streamed.
    Failed,
    /// Cancelled by an operator.
    Cancelled,
}

impl JobState {
    /// Name as stored and shown.
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Planning => "planning",
            JobState::Printing => "printing",
            JobState::Paused => "paused",
            JobState::Interrupted => "interrupted",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    /// Done, failed or cancelled: nothing more will happen.
    pub fn is_final(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }
}

/// Where to continue a job: the first move not executed and the state there.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Index of the first move the machine has not executed.
    pub next_index: u32,
    /// Layer of the last executed layer mark.
    pub layer: Option<u32>,
    /// Composition of the last executed extrusion (fractions per syringe).
    pub composition: Option<Vec<f64>>,
    /// Syringe volumes left after the last executed move (nl).
    pub remaining_nl: Vec<u32>,
}

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
    /// Last change (ms since the Unix epoch).
    pub updated_ms: i64,
    /// Live progress, for the active job only (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub progress: Option<Progress>,
}

/// Live progress of the active job (`notify_job_progress`, `machine.status`).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
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
