//! What the lifecycle knows of a job: its state, where to continue it, its progress.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// Wire job id reserved for the daemon's own service moves (home, prime, park).
pub const SERVICE_JOB_ID: u32 = 0;

/// Where a job is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
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
    /// Every state, in the order of a job's life.
    pub const ALL: [JobState; 8] = [
        JobState::Queued,
        JobState::Planning,
        JobState::Printing,
        JobState::Paused,
        JobState::Interrupted,
        JobState::Done,
        JobState::Failed,
        JobState::Cancelled,
    ];

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

    /// The state named `name` ([`JobState::as_str`]).
    pub fn from_name(name: &str) -> Option<JobState> {
        JobState::ALL.into_iter().find(|s| s.as_str() == name)
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
    /// Material each syringe gave for the moves executed so far (nl; pushed by
    /// extrusions and primes less what retracts pulled back).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub used_nl: Vec<u64>,
}

/// A job as the store holds it, as far as the lifecycle needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct JobInfo {
    /// Job id (also the wire job id of its moves).
    pub id: u32,
    /// State.
    pub state: JobState,
    /// Where to continue.
    pub checkpoint: Checkpoint,
    /// Moves planned in total, once planning has finished.
    pub total_moves: Option<u32>,
    /// Submission time (ms since the Unix epoch).
    pub submitted_ms: i64,
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
    /// Estimated seconds left: the planned machine time of the moves not executed, at
    /// the pace measured since the job (re)started ([`time_left_planned_s`]); before the
    /// job is planned whole, from the move rate once `total` is known, else from the
    /// layer rate (after the first layer finished since the start).
    pub eta_s: Option<f64>,
    /// Share of the job's planned machine time executed, percent (once planned whole).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub percent: Option<f64>,
    /// The job's planned machine time, seconds (once planned whole).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub planned_s: Option<f64>,
    /// From submission to the machine executing the first move (ms).
    pub first_move_after_ms: Option<i64>,
}

/// Planned machine time of the job counted as if it were all this long before the
/// measured pace counts fully, µs: the first minutes' ETA is the plan's, then the
/// machine's own pace takes over.
const PACE_PRIOR_US: f64 = 30e6;

/// Seconds left of a job planned whole: the planned time of the moves not executed
/// (`left_us`) at the pace measured since it (re)started (`running_us` printing for
/// `done_us` of planned time; [`PACE_PRIOR_US`] of the plan's own pace blended in). The
/// clock stops while the job does not print, so the estimate holds while paused.
pub fn time_left_planned_s(left_us: u64, done_us: u64, running_us: u64) -> f64 {
    let pace = (running_us as f64 + PACE_PRIOR_US) / (done_us as f64 + PACE_PRIOR_US);
    left_us as f64 * pace.clamp(0.05, 100.0) / 1e6
}

/// Seconds left of a job that has run `elapsed_s` since it (re)started: from the move
/// rate once the move total is known (`moves`: total, executed, executed since the
/// start), else from the layer rate (`layers`: the job's layer count and the current
/// layer, 0-based; layers finished since `layer_at_start` over the time they took, for
/// the layers not finished, the current one counted whole). Layers differ in size, so
/// the second is the rougher estimate. `None` until there is a rate.
pub fn time_left_s(
    moves: Option<(u32, u32, u32)>,
    layers: Option<(u32, u32)>,
    layer_at_start: u32,
    elapsed_s: f64,
) -> Option<f64> {
    let elapsed_s = elapsed_s.max(1e-3);
    match (moves, layers) {
        (Some((total, executed, done_since)), _) => {
            let rate = f64::from(done_since) / elapsed_s;
            (rate > 0.0).then(|| f64::from(total.saturating_sub(executed)) / rate)
        }
        (None, Some((count, layer))) => {
            let finished = layer.saturating_sub(layer_at_start);
            (finished > 0)
                .then(|| f64::from(count.saturating_sub(layer)) * elapsed_s / f64::from(finished))
        }
        (None, None) => None,
    }
}

/// What the lifecycle knows of one job.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Known {
    pub state: JobState,
    pub checkpoint: Checkpoint,
    pub total_moves: Option<u32>,
    pub submitted_ms: i64,
}

/// The jobs the lifecycle knows: every job it has seen that is not finished, and the
/// most recently finished ones. What it knows is at least as new as the store (it
/// writes every state change), so a job read from the store is learnt only if unknown.
#[derive(Debug, Default)]
pub(super) struct Jobs {
    map: BTreeMap<u32, Known>,
}

impl Jobs {
    /// Finished jobs remembered (the oldest are forgotten; the store still has them).
    const FINISHED_KEPT: usize = 256;

    pub fn get(&self, id: u32) -> Option<&Known> {
        self.map.get(&id)
    }

    pub fn get_mut(&mut self, id: u32) -> Option<&mut Known> {
        self.map.get_mut(&id)
    }

    pub fn knows(&self, id: u32) -> bool {
        self.map.contains_key(&id)
    }

    /// Learn `info` unless the job is known already.
    pub fn learn(&mut self, info: JobInfo) {
        self.map.entry(info.id).or_insert(Known {
            state: info.state,
            checkpoint: info.checkpoint,
            total_moves: info.total_moves,
            submitted_ms: info.submitted_ms,
        });
        self.forget_old_finished();
    }

    /// Set job `id`'s state (a job not known is learnt with an empty checkpoint).
    pub fn set_state(&mut self, id: u32, state: JobState) {
        match self.map.get_mut(&id) {
            Some(k) => k.state = state,
            None => {
                self.map.insert(
                    id,
                    Known {
                        state,
                        checkpoint: Checkpoint::default(),
                        total_moves: None,
                        submitted_ms: 0,
                    },
                );
            }
        }
        self.forget_old_finished();
    }

    /// The oldest queued job.
    pub fn first_queued(&self) -> Option<u32> {
        self.first_in(JobState::Queued)
    }

    /// The oldest job in `state`.
    pub fn first_in(&self, state: JobState) -> Option<u32> {
        self.map
            .iter()
            .find(|(_, k)| k.state == state)
            .map(|(&id, _)| id)
    }

    fn forget_old_finished(&mut self) {
        let finished: Vec<u32> = self
            .map
            .iter()
            .filter(|(_, k)| k.state.is_final())
            .map(|(&id, _)| id)
            .collect();
        let excess = finished.len().saturating_sub(Self::FINISHED_KEPT);
        for id in finished.into_iter().take(excess) {
            self.map.remove(&id);
        }
    }
}
