//! The API: a Unix socket speaking newline-delimited JSON-RPC 2.0 (`docs/api.md`).
//!
//! A request line is read into a [`Call`] (the types of [`crate::proto`]), answered by
//! one function per method, and the typed result written back as its response line.
//! Connections, their limits and the reading of lines are [`super::connections`]'s.
//! Malformed JSON, unknown methods and bad params are answered with JSON-RPC errors and
//! the connection stays usable.

use std::sync::Arc;

use tokio::sync::oneshot;
use tracing::{info, warn};

use super::store::{JobRecord, JobSpec};
use super::{api_error, api_write_error, ApiError, Control, Shared};
use crate::proto::{
    Call, Deleted, EStopTiming, Event, Id, Job, JobIdParams, JobSource, JobState, JobStateChanged,
    MachineStatus, MethodResult, Progress, Refilled, Refusal, Request, Response, ServerInfo,
    StateChange, Submission, SubmitParams, Submitted, Subscribed,
};

pub use super::connections::serve;

/// The response line to request `id`.
fn response_line(id: Id, outcome: Result<MethodResult, ApiError>) -> String {
    serde_json::to_string(&Response::new(id.clone(), outcome)).unwrap_or_else(|e| {
        let e = ApiError::new(ApiError::INTERNAL, format!("cannot write the result: {e}"));
        error_line(id, e)
    })
}

/// An error response line.
use super::connections::error_line;

/// A mesh job needs its mesh, and the mesh must load and stack into layers; the part
/// must fit the machine's build volume where `geometry.placement` puts it. Checked here
/// (a mesh on a blocking worker) so a bad part is refused at submission, naming the
/// problem, instead of failing when it starts. A polygon job must not carry a mesh.
async fn check_part(
    job: &crate::job::Job,
    mesh: Option<Vec<u8>>,
    machine: &crate::setup::MachineConfig,
    budget: &super::connections::Budget,
) -> Result<(Option<Vec<u8>>, Vec<String>), ApiError> {
    let bad = |m: String| ApiError::new(ApiError::INVALID_JOB, m);
    // Checked when the configuration was loaded.
    let volume = machine
        .build_volume()
        .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("machine.build_volume_mm: {e}")))?;
    match (&job.geometry, mesh) {
        (crate::job::Geometry::Extruded { .. }, None) => {
            // A prism: every layer rests on the one below.
            if let Some(bounds) = job.extruded_bounds() {
                super::planner::place_part(job, bounds, &volume).map_err(bad)?;
            }
            Ok((None, Vec::new()))
        }
        (crate::job::Geometry::Extruded { .. }, Some(_)) => Err(bad(
            "mesh_base64: the job builds a polygon ([geometry] polygon/regions), not a mesh"
                .into(),
        )),
        (crate::job::Geometry::Mesh { path }, None) => Err(bad(format!(
            "geometry.mesh = {path:?}: send the mesh's bytes with the job (mesh_base64); edod reads no files on a client's behalf"
        ))),
        (crate::job::Geometry::Mesh { path }, Some(bytes)) => {
            // Its working memory comes from the requests' budget (3MF bombs included).
            let held = budget.mesh_check(&bytes).await?;
            let limits = budget.mesh_limits();
            let job = job.clone();
            let path = path.clone();
            tokio::task::spawn_blocking(move || {
                let _held = held;
                match job.mesh_layers(&bytes, &limits) {
                    Ok(part) if part.is_empty() => {
                        Err(bad(format!("{path}: the mesh has no height to slice")))
                    }
                    Ok(part) => {
                        super::planner::place_part(&job, part.bounds(), &volume)
                            .map_err(|e| bad(format!("{path}: {e}")))?;
                        // With supports: what still rests on nothing with them.
                        let hanging = match part.supports(&job) {
                            Ok(Some(s)) => Ok(s.still_hanging),
                            Ok(None) => part.overhangs(&job.overhang_options()),
                            Err(e) => Err(e),
                        }
                        .map_err(|e| bad(format!("{path}: {e}")))?;
                        if job.support.required {
                            if let Some(why) = crate::slice::overhang::refusal(&job.overhang, &hanging) {
                                return Err(bad(format!("{path}: {why}")));
                            }
                        }
                        let warnings =
                            crate::slice::overhang::warning(&job.overhang, &hanging)
                                .map(|w| format!("{path}: {w}"));
                        Ok((Some(bytes), warnings.into_iter().collect()))
                    }
                    Err(e) => Err(bad(format!("{path}: {e}"))),
                }
            })
            .await
            .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("mesh check failed: {e}")))?
        }
    }
}

/// A request line read: its id (none for a notification) and its call, or why the
/// line is no request.
pub type Parsed = Result<(Option<Id>, Result<Call, ApiError>), Refusal>;

/// Read a request line into its typed call (JSON parse and params: for a large line,
/// run it on a blocking thread, [`parse_off_runtime`]).
pub fn parse(line: &[u8]) -> Parsed {
    let request = Request::from_line(line)?;
    Ok((request.id, Call::new(&request.method, request.params)))
}

/// [`parse`] on tokio's blocking pool: a submission of tens of MiB is parsed there, not
/// on a runtime worker. `keep` (the line's hold on the memory budget) is given back
/// with the line once it is parsed.
pub async fn parse_off_runtime<K: Send + 'static>(line: Vec<u8>, keep: K) -> Parsed {
    tokio::task::spawn_blocking(move || {
        let parsed = parse(&line);
        drop((line, keep));
        parsed
    })
    .await
    .unwrap_or_else(|e| {
        Err(Refusal {
            id: Id::Null,
            error: ApiError::new(
                ApiError::INTERNAL,
                format!("reading the request failed: {e}"),
            ),
        })
    })
}

/// Handle one request line: the reply line (none for a notification) and whether the
/// client subscribed.
pub async fn handle(line: &[u8], shared: &Arc<Shared>) -> (Option<String>, bool) {
    answer(parse(line), shared).await
}

/// Answer a request read by [`parse`].
pub async fn answer(parsed: Parsed, shared: &Arc<Shared>) -> (Option<String>, bool) {
    let (id, call) = match parsed {
        Ok(p) => p,
        Err(Refusal { id, error }) => return (Some(error_line(id, error)), false),
    };
    let result = match call {
        Ok(call) => dispatch(call, shared).await,
        Err(e) => Err(e),
    };
    let subscribed = matches!(result, Ok(MethodResult::Subscribed(_)));
    (id.map(|id| response_line(id, result)), subscribed)
}

async fn ask<T>(
    shared: &Shared,
    make: impl FnOnce(oneshot::Sender<Result<T, ApiError>>) -> Control,
) -> Result<T, ApiError> {
    let (tx, rx) = oneshot::channel();
    shared
        .control
        .send(make(tx))
        .await
        .map_err(|_| ApiError::new(ApiError::INTERNAL, "the streamer has stopped"))?;
    rx.await
        .map_err(|_| ApiError::new(ApiError::INTERNAL, "the streamer has stopped"))?
}

/// Finished jobs deleted at most per submission (beyond `state.keep_finished_jobs`): a
/// store grown large before a lower setting shrinks over a few submissions instead of
/// holding the store (and the lifecycle's checkpoints) during one long delete.
const PRUNE_AT_MOST: usize = 20;

/// How long a submission or a deletion waits for another process's hold on the job
/// store's write lock before it is answered -32005 (store busy, retry), so that every
/// call is answered within 100 ms.
const STORE_WAIT: std::time::Duration = std::time::Duration::from_millis(60);

/// Answer one call (`docs/api.md`, Methods).
pub(crate) async fn dispatch(call: Call, shared: &Arc<Shared>) -> Result<MethodResult, ApiError> {
    Ok(match call {
        Call::ServerInfo => server_info(shared)?.into(),
        Call::Subscribe => Subscribed::all().into(),
        Call::JobSubmit(p) => job_submit(p, shared).await?.into(),
        Call::JobList => job_list(shared).await?.into(),
        Call::JobGet(JobIdParams { id }) => job_get(id, shared).await?.into(),
        Call::JobPause(JobIdParams { id }) => job_pause(id, shared).await?.into(),
        Call::JobResume(JobIdParams { id }) => job_resume(id, shared).await?.into(),
        Call::JobCancel(JobIdParams { id }) => job_cancel(id, shared).await?.into(),
        Call::JobStartNext(p) => ask(shared, |r| Control::StartNext(p.id, r)).await?.into(),
        Call::JobDelete(JobIdParams { id }) => job_delete(id, shared).await?.into(),
        Call::JobReprint(JobIdParams { id }) => job_reprint(id, shared).await?.into(),
        Call::MachineStatus => machine_status(shared).into(),
        Call::MachineEstop => machine_estop(shared).await?.into(),
        Call::MachineRefill => machine_refill(shared).await?.into(),
        Call::LogRecent(p) => super::log_feed::recent(&shared.log, p.after).into(),
    })
}

fn server_info(shared: &Shared) -> Result<ServerInfo, ApiError> {
    let machine = match serde_json::to_value(&shared.config.machine) {
        Ok(serde_json::Value::Object(table)) => table,
        _ => {
            return Err(ApiError::new(
                ApiError::INTERNAL,
                "cannot show the [machine] table",
            ))
        }
    };
    Ok(ServerInfo {
        name: "edod".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        api_version: crate::proto::API_VERSION,
        protocol_version: crate::link::PROTOCOL_VERSION,
        port: shared.port.display().to_string(),
        machine,
    })
}

/// `job.submit`: check the params, the job file and its part, store the job (on disk
/// before the reply), tell subscribers and the streamer.
async fn job_submit(p: SubmitParams, shared: &Shared) -> Result<Submitted, ApiError> {
    if let Some(name) = &p.name {
        crate::job::check_name(name)
            .map_err(|m| ApiError::new(ApiError::INVALID_PARAMS, format!("name: {m}")))?;
    }
    let Submission { source, name } = p.submission()?;
    let (spec, name, warnings) = match source {
        JobSource::File { job, mesh_base64 } => {
            let (spec, job_name, warnings) = file_job(job, mesh_base64, shared).await?;
            (spec, name.unwrap_or(job_name), warnings)
        }
        JobSource::DryRun { moves } => (
            JobSpec::DryRun { moves },
            name.unwrap_or_else(|| format!("dry run of {moves} moves")),
            Vec::new(),
        ),
    };
    queue_job(shared, name, spec, warnings).await
}

/// `job.reprint`: finished job `id` queued again as a new job from the job file and
/// mesh stored with it, checked as a submission is (the machine may have changed).
async fn job_reprint(id: u32, shared: &Shared) -> Result<Submitted, ApiError> {
    let (job, mesh) = shared.store.reader.source(id).await.map_err(api_error)?;
    if !job.job.state.is_final() {
        return Err(ApiError::new(
            ApiError::BAD_STATE,
            format!(
                "job {id} is {}: only a done, failed or cancelled job is printed again",
                job.job.state.as_str()
            ),
        ));
    }
    if let Some(why) = &job.unreadable {
        return Err(ApiError::new(
            ApiError::INVALID_JOB,
            format!("job {id}: {why}"),
        ));
    }
    let (spec, warnings) = match job.spec {
        JobSpec::Toml { toml, .. } => {
            let (spec, _, warnings) = checked_file_job(toml, mesh, shared).await?;
            (spec, warnings)
        }
        dry_run @ JobSpec::DryRun { .. } => (dry_run, Vec::new()),
    };
    info!(job = id, "job printed again");
    queue_job(shared, job.job.name, spec, warnings).await
}

/// Store an accepted job (on disk before the reply), tell subscribers and the streamer.
async fn queue_job(
    shared: &Shared,
    name: String,
    spec: JobSpec,
    warnings: Vec<String>,
) -> Result<Submitted, ApiError> {
    let id = store_submission(shared, &name, spec).await?;
    info!(job = id, name = %name, "job accepted");
    shared.notify(Event::JobState(JobStateChanged {
        job_id: id,
        state: JobState::Queued,
        reason: None,
    }));
    let _ = shared.control.send(Control::Submitted).await;
    for w in &warnings {
        warn!(job = id, "{w}");
    }
    Ok(Submitted {
        id,
        state: JobState::Queued,
        warnings,
    })
}

/// A job file's spec, name and warnings: the file parsed (-32003), its mesh decoded
/// (-32602) and the part checked against the machine ([`check_part`]).
async fn file_job(
    toml: String,
    mesh_base64: Option<String>,
    shared: &Shared,
) -> Result<(JobSpec, String, Vec<String>), ApiError> {
    let mesh = match mesh_base64 {
        Some(b) => Some(decode_mesh(b).await?),
        None => None,
    };
    checked_file_job(toml, mesh, shared).await
}

/// A mesh's base64 decoded (-32602 if it is not base64); a large one on tokio's
/// blocking pool, not on a runtime worker.
async fn decode_mesh(b64: String) -> Result<Vec<u8>, ApiError> {
    let small = b64.len() <= super::connections::SMALL_LINE;
    let decode = move || {
        crate::proto::mesh_bytes::base64_decode(&b64).map_err(|e| {
            ApiError::new(
                ApiError::INVALID_PARAMS,
                format!("mesh_base64: not base64: {e}"),
            )
        })
    };
    if small {
        return decode();
    }
    tokio::task::spawn_blocking(decode)
        .await
        .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("decoding the mesh failed: {e}")))?
}

/// A job file (and its mesh) checked as a submission: the file parsed (-32003), its
/// materials and process settings against the machine, its part placed
/// ([`check_part`]).
async fn checked_file_job(
    toml: String,
    mesh: Option<Vec<u8>>,
    shared: &Shared,
) -> Result<(JobSpec, String, Vec<String>), ApiError> {
    let job = crate::job::Job::from_toml(&toml, "submitted job")
        .map_err(|e| ApiError::new(ApiError::INVALID_JOB, e.to_string()))?;
    // What would fail when it starts is refused now: its materials against the
    // machine's syringes, its process settings against the machine's limits.
    crate::setup::process_settings(&job, &shared.config.machine, "submitted job")
        .map_err(|e| ApiError::new(ApiError::INVALID_JOB, e))?;
    let (mesh, warnings) = check_part(&job, mesh, &shared.config.machine, &shared.budget).await?;
    Ok((JobSpec::Toml { toml, mesh }, job.name, warnings))
}

/// Store a new job, and delete the oldest finished jobs beyond
/// `state.keep_finished_jobs` (at most [`PRUNE_AT_MOST`]); the job's id. Done by the
/// store's writer thread, waiting for the write lock at most [`STORE_WAIT`].
async fn store_submission(shared: &Shared, name: &str, spec: JobSpec) -> Result<u32, ApiError> {
    let keep = shared.config.state.keep_finished_jobs;
    let (id, pruned) = shared
        .store
        .writer
        .submit(name.to_string(), spec, keep, PRUNE_AT_MOST, STORE_WAIT)
        .await
        .map_err(api_write_error)?;
    if !pruned.is_empty() {
        info!(jobs = ?pruned, keep, "deleted the oldest finished jobs");
    }
    Ok(id)
}

/// Every stored job, oldest first.
async fn stored_jobs(shared: &Shared) -> Result<Vec<JobRecord>, ApiError> {
    shared.store.reader.list().await.map_err(api_error)
}

/// Stored job `id` (-32001 if there is none).
async fn stored_job(shared: &Shared, id: u32) -> Result<JobRecord, ApiError> {
    shared.store.reader.get(id).await.map_err(api_error)
}

/// Delete finished job `id` from the store; the state it is in if it is not finished.
async fn delete_stored(shared: &Shared, id: u32) -> Result<Result<(), JobState>, ApiError> {
    shared
        .store
        .writer
        .delete(id, STORE_WAIT)
        .await
        .map_err(api_write_error)
}

/// A stored job as the API shows it, with `live` progress if it is the active job.
fn job_view(j: JobRecord, live: Option<&Progress>) -> Job {
    let mut job = j.job;
    job.progress = live.filter(|p| p.job_id == job.id).cloned();
    job
}

async fn job_list(shared: &Shared) -> Result<Vec<Job>, ApiError> {
    let jobs = stored_jobs(shared).await?;
    let live = shared.progress.borrow().clone();
    Ok(jobs
        .into_iter()
        .map(|j| job_view(j, live.as_ref()))
        .collect())
}

async fn job_get(id: u32, shared: &Shared) -> Result<Job, ApiError> {
    let j = stored_job(shared, id).await?;
    let live = shared.progress.borrow().clone();
    Ok(job_view(j, live.as_ref()))
}

/// `job.pause`: `paused`, once stored (or `stored: false` after 75 ms).
async fn job_pause(id: u32, shared: &Shared) -> Result<StateChange, ApiError> {
    ask(shared, |r| Control::Pause(id, r)).await
}

/// `job.resume`: `printing`, once stored (or `stored: false` after 75 ms).
async fn job_resume(id: u32, shared: &Shared) -> Result<StateChange, ApiError> {
    ask(shared, |r| Control::Resume(id, r)).await
}

/// `job.cancel`: `cancelled`; `stored: false` while a printing or paused job stops and
/// parks (its `notify_job_state` follows).
async fn job_cancel(id: u32, shared: &Shared) -> Result<StateChange, ApiError> {
    ask(shared, |r| Control::Cancel(id, r)).await
}

async fn job_delete(id: u32, shared: &Shared) -> Result<Deleted, ApiError> {
    match delete_stored(shared, id).await? {
        Ok(()) => {
            info!(job = id, "job deleted");
            Ok(Deleted { id, deleted: true })
        }
        Err(state) => Err(ApiError::new(
            ApiError::BAD_STATE,
            format!(
                "job {id} is {}: only a done, failed or cancelled job can be deleted \
                 (cancel it first)",
                state.as_str()
            ),
        )),
    }
}

fn machine_status(shared: &Shared) -> MachineStatus {
    MachineStatus {
        machine: shared.machine.borrow().clone(),
        progress: shared.progress.borrow().clone(),
    }
}

async fn machine_estop(shared: &Shared) -> Result<EStopTiming, ApiError> {
    let t = std::time::Instant::now();
    ask(shared, |r| Control::EStop(t, r)).await
}

async fn machine_refill(shared: &Shared) -> Result<Refilled, ApiError> {
    ask(shared, Control::Refill).await?;
    Ok(Refilled { refilled: true })
}
