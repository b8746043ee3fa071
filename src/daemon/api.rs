//! The API: a Unix socket speaking newline-delimited JSON-RPC 2.0 (`docs/api.md`).
//!
//! Each client gets a reader task and a writer task joined by a bounded queue of reply
//! lines; notifications come from a broadcast channel. A client that does not read its
//! replies fills its queue and is disconnected: the daemon never waits for a client.
//! Requests over `api.max_request_bytes`, malformed JSON, unknown methods and bad params
//! are answered with JSON-RPC errors and the connection stays usable.

use std::sync::Arc;

use serde::de::DeserializeOwned;
use serde::Deserialize;
use serde_json::{json, Value};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::{mpsc, oneshot, Semaphore};
use tracing::{debug, info, warn};

use super::store::JobSpec;
use super::{ApiError, Control, Shared};

/// Accept clients until the listener fails.
pub async fn serve(listener: UnixListener, shared: Arc<Shared>) {
    let slots = Arc::new(Semaphore::new(shared.config.api.max_clients));
    loop {
        let (stream, _) = match listener.accept().await {
            Ok(s) => s,
            Err(e) => {
                warn!(error = %e, "accept failed");
                tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(permit) = Arc::clone(&slots).try_acquire_owned() else {
            warn!("too many clients; refusing one");
            drop(stream);
            continue;
        };
        let shared = Arc::clone(&shared);
        tokio::spawn(async move {
            client(stream, shared).await;
            drop(permit);
        });
    }
}

fn error_line(id: Value, e: &ApiError) -> String {
    json!({"jsonrpc": "2.0", "id": id, "error": {"code": e.code, "message": e.message}}).to_string()
}

async fn client(stream: UnixStream, shared: Arc<Shared>) {
    let (rd, mut wr) = stream.into_split();
    let (tx, mut rx) = mpsc::channel::<Arc<str>>(shared.config.api.client_queue);
    let writer = tokio::spawn(async move {
        while let Some(line) = rx.recv().await {
            if wr.write_all(line.as_bytes()).await.is_err() || wr.write_all(b"\n").await.is_err() {
                break;
            }
        }
    });
    let mut reader = BufReader::new(rd);
    let max = shared.config.api.max_request_bytes;
    let mut notifications: Option<tokio::sync::broadcast::Receiver<Arc<str>>> = None;
    let mut line = Vec::new();
    loop {
        tokio::select! {
            r = read_line(&mut reader, &mut line, max) => {
                match r {
                    Ok(LineRead::Eof) | Err(_) => break,
                    Ok(LineRead::TooLong) => {
                        let e = ApiError::new(ApiError::INVALID_REQUEST,
                            format!("request over {max} bytes (api.max_request_bytes)"));
                        if tx.try_send(Arc::from(error_line(Value::Null, &e))).is_err() { break; }
                    }
                    Ok(LineRead::Line) => {
                        if line.iter().all(u8::is_ascii_whitespace) { continue; }
                        let (reply, subscribe) = handle(&line, &shared).await;
                        if subscribe && notifications.is_none() {
                            notifications = Some(shared.notify.subscribe());
                        }
                        if let Some(r) = reply {
                            if tx.try_send(Arc::from(r)).is_err() {
                                debug!("client too slow; disconnecting");
                                break;
                            }
                        }
                    }
                }
            }
            n = async {
                match notifications.as_mut() {
                    Some(rx) => rx.recv().await,
                    None => std::future::pending().await,
                }
            } => match n {
                Ok(line) => {
                    if tx.try_send(line).is_err() {
                        debug!("subscriber too slow; disconnecting");
                        break;
                    }
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                    debug!(missed = n, "subscriber lagged; disconnecting");
                    break;
                }
                Err(_) => notifications = None,
            },
        }
    }
    drop(tx);
    let _ = writer.await;
}

enum LineRead {
    Line,
    TooLong,
    Eof,
}

/// Read one line into `line` (without the newline); a line over `max` bytes is
/// skipped up to its newline and reported as `TooLong`, so memory stays bounded.
async fn read_line<R: tokio::io::AsyncBufRead + Unpin>(
    r: &mut R,
    line: &mut Vec<u8>,
    max: usize,
) -> std::io::Result<LineRead> {
    line.clear();
    let mut too_long = false;
    loop {
        let buf = r.fill_buf().await?;
        if buf.is_empty() {
            // A partial last line without a newline is dropped with the connection.
            return Ok(LineRead::Eof);
        }
        let (chunk, found) = match buf.iter().position(|&b| b == b'\n') {
            Some(i) => (&buf[..i], Some(i)),
            None => (buf, None),
        };
        if !too_long {
            if line.len() + chunk.len() > max {
                too_long = true;
                line.clear();
            } else {
                line.extend_from_slice(chunk);
            }
        }
        let used = found.map_or(buf.len(), |i| i + 1);
        r.consume(used);
        if found.is_some() {
            return Ok(if too_long {
                LineRead::TooLong
            } else {
                LineRead::Line
            });
        }
    }
}

fn params<T: DeserializeOwned>(p: Value) -> Result<T, ApiError> {
    let p = if p.is_null() { json!({}) } else { p };
    serde_json::from_value(p).map_err(|e| ApiError::new(ApiError::INVALID_PARAMS, e.to_string()))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Empty {}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JobId {
    id: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Submit {
    /// Job file text.
    #[serde(default)]
    job: Option<String>,
    /// Mesh bytes, base64.
    #[serde(default)]
    mesh_base64: Option<String>,
    /// A dry-run job of N moves instead of a job file.
    #[serde(default)]
    dry_run_moves: Option<u32>,
    /// Name shown in listings.
    #[serde(default)]
    name: Option<String>,
}

/// A mesh job needs its mesh, and the mesh must load and stack into layers; the part
/// must fit the machine's build volume where `geometry.placement` puts it. Checked here
/// (a mesh on a blocking worker) so a bad part is refused at submission, naming the
/// problem, instead of failing when it starts. A polygon job must not carry a mesh.
async fn check_part(
    job: &crate::job::Job,
    mesh: Option<Vec<u8>>,
    machine: &super::config::MachineConfig,
) -> Result<Option<Vec<u8>>, ApiError> {
    let bad = |m: String| ApiError::new(ApiError::INVALID_JOB, m);
    // Checked when the configuration was loaded.
    let volume = machine
        .build_volume()
        .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("machine.build_volume_mm: {e}")))?;
    match (&job.geometry, mesh) {
        (crate::job::Geometry::Extruded { .. }, None) => {
            if let Some(bounds) = job.extruded_bounds() {
                super::planner::place_part(job, bounds, &volume).map_err(bad)?;
            }
            Ok(None)
        }
        (crate::job::Geometry::Extruded { .. }, Some(_)) => Err(bad(
            "mesh_base64: the job builds a polygon ([geometry] polygon/regions), not a mesh"
                .into(),
        )),
        (crate::job::Geometry::Mesh { path }, None) => Err(bad(format!(
            "geometry.mesh = {path:?}: send the mesh's bytes with the job (mesh_base64); edod reads no files on a client's behalf"
        ))),
        (crate::job::Geometry::Mesh { path }, Some(bytes)) => {
            let job = job.clone();
            let path = path.clone();
            tokio::task::spawn_blocking(move || {
                match job.mesh_layers(&bytes, &crate::mesh::MeshLimits::default()) {
                    Ok(part) if part.is_empty() => {
                        Err(bad(format!("{path}: the mesh has no height to slice")))
                    }
                    Ok(part) => {
                        super::planner::place_part(&job, part.bounds(), &volume)
                            .map_err(|e| bad(format!("{path}: {e}")))?;
                        Ok(Some(bytes))
                    }
                    Err(e) => Err(bad(format!("{path}: {e}"))),
                }
            })
            .await
            .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("mesh check failed: {e}")))?
        }
    }
}

/// Handle one request line: the reply line (none for a notification) and whether the
/// client subscribed.
pub async fn handle(line: &[u8], shared: &Arc<Shared>) -> (Option<String>, bool) {
    let v: Value = match serde_json::from_slice(line) {
        Ok(v) => v,
        Err(e) => {
            let e = ApiError::new(ApiError::PARSE, format!("not JSON: {e}"));
            return (Some(error_line(Value::Null, &e)), false);
        }
    };
    let id = v.get("id").cloned();
    let bad = |m: &str| {
        let e = ApiError::new(ApiError::INVALID_REQUEST, m);
        (
            Some(error_line(id.clone().unwrap_or(Value::Null), &e)),
            false,
        )
    };
    let Some(obj) = v.as_object() else {
        return bad("a request is a JSON object");
    };
    if obj.get("jsonrpc").and_then(Value::as_str) != Some("2.0") {
        return bad("\"jsonrpc\" must be \"2.0\"");
    }
    if id
        .as_ref()
        .is_some_and(|i| !(i.is_string() || i.is_number() || i.is_null()))
    {
        return bad("\"id\" must be a string, a number or null");
    }
    let Some(method) = obj.get("method").and_then(Value::as_str) else {
        return bad("\"method\" must be a string");
    };
    let p = obj.get("params").cloned().unwrap_or(Value::Null);
    let subscribe = method == "subscribe";
    let result = dispatch(method, p, shared).await;
    let Some(id) = id else {
        return (None, subscribe && result.is_ok());
    };
    let line = match &result {
        Ok(r) => json!({"jsonrpc": "2.0", "id": id, "result": r}).to_string(),
        Err(e) => error_line(id, e),
    };
    (Some(line), subscribe && result.is_ok())
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

fn job_view(shared: &Shared, j: &super::store::JobRecord) -> Value {
    let mut v = serde_json::to_value(j).unwrap_or(Value::Null);
    let live = shared.progress.borrow().clone();
    if let (Some(p), Some(o)) = (live.filter(|p| p.job_id == j.id), v.as_object_mut()) {
        o.insert(
            "progress".into(),
            serde_json::to_value(p).unwrap_or(Value::Null),
        );
    }
    v
}

/// Finished jobs deleted at most per submission (beyond `state.keep_finished_jobs`): a
/// store grown large before a lower setting shrinks over a few submissions instead of
/// holding the store (and the streamer's checkpoints) during one long delete.
const PRUNE_AT_MOST: usize = 20;

async fn dispatch(method: &str, p: Value, shared: &Arc<Shared>) -> Result<Value, ApiError> {
    match method {
        "server.info" => {
            params::<Empty>(p)?;
            Ok(json!({
                "name": "edod",
                "version": env!("CARGO_PKG_VERSION"),
                "api_version": 1,
                "protocol_version": crate::link::PROTOCOL_VERSION,
                "port": shared.port.display().to_string(),
                "machine": shared.config.machine,
            }))
        }
        "subscribe" => {
            params::<Empty>(p)?;
            Ok(
                json!({"subscribed": ["notify_job_progress", "notify_job_state", "notify_machine_state"]}),
            )
        }
        "job.submit" => {
            let s: Submit = params(p)?;
            if let Some(name) = &s.name {
                crate::job::check_name(name)
                    .map_err(|m| ApiError::new(ApiError::INVALID_PARAMS, format!("name: {m}")))?;
            }
            let (spec, name) = match (s.job, s.dry_run_moves) {
                (Some(toml), None) => {
                    let job = crate::job::Job::from_toml(&toml, "submitted job")
                        .map_err(|e| ApiError::new(ApiError::INVALID_JOB, e.to_string()))?;
                    let mesh = s
                        .mesh_base64
                        .as_deref()
                        .map(|b| {
                            base64_decode(b).map_err(|e| {
                                ApiError::new(
                                    ApiError::INVALID_PARAMS,
                                    format!("mesh_base64: not base64: {e}"),
                                )
                            })
                        })
                        .transpose()?;
                    let mesh = check_part(&job, mesh, &shared.config.machine).await?;
                    (JobSpec::Toml { toml, mesh }, s.name.unwrap_or(job.name))
                }
                (None, Some(moves)) if moves > 0 => (
                    JobSpec::DryRun { moves },
                    s.name
                        .unwrap_or_else(|| format!("dry run of {moves} moves")),
                ),
                (None, Some(_)) => {
                    return Err(ApiError::new(
                        ApiError::INVALID_PARAMS,
                        "dry_run_moves must be at least 1",
                    ))
                }
                _ => {
                    return Err(ApiError::new(
                        ApiError::INVALID_PARAMS,
                        "give either \"job\" (the job file text) or \"dry_run_moves\"",
                    ))
                }
            };
            let keep = shared.config.state.keep_finished_jobs;
            let stored_name = name.clone();
            let (id, pruned) = shared
                .api_store(true, move |st| {
                    let id = st.insert(&stored_name, &spec)?;
                    Ok((id, st.prune_finished(keep, PRUNE_AT_MOST)?))
                })
                .await?;
            info!(job = id, name = %name, "job accepted");
            if !pruned.is_empty() {
                info!(jobs = ?pruned, keep, "deleted the oldest finished jobs");
            }
            shared.notify(
                "notify_job_state",
                json!({"job_id": id, "state": "queued", "reason": null}),
            );
            let _ = shared.control.send(Control::Submitted).await;
            Ok(json!({"id": id, "state": "queued"}))
        }
        "job.list" => {
            params::<Empty>(p)?;
            let jobs = shared.api_store(false, |s| s.list()).await?;
            Ok(Value::Array(
                jobs.iter().map(|j| job_view(shared, j)).collect(),
            ))
        }
        "job.get" => {
            let JobId { id } = params(p)?;
            let j = shared.api_store(false, move |s| s.get(id)).await?;
            Ok(job_view(shared, &j))
        }
        "job.pause" => {
            let JobId { id } = params(p)?;
            ask(shared, |r| Control::Pause(id, r)).await?;
            Ok(json!({"id": id, "state": "paused"}))
        }
        "job.resume" => {
            let JobId { id } = params(p)?;
            ask(shared, |r| Control::Resume(id, r)).await?;
            Ok(json!({"id": id, "state": "printing"}))
        }
        "job.cancel" => {
            let JobId { id } = params(p)?;
            ask(shared, |r| Control::Cancel(id, r)).await?;
            // `cancelled`, or still `printing` while the machine stops and parks.
            let j = shared.api_store(false, move |s| s.get(id)).await?;
            Ok(json!({"id": id, "state": j.state}))
        }
        "job.delete" => {
            let JobId { id } = params(p)?;
            match shared
                .api_store(true, move |s| s.delete_finished(id))
                .await?
            {
                Ok(()) => {
                    info!(job = id, "job deleted");
                    Ok(json!({"id": id, "deleted": true}))
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
        "machine.status" => {
            params::<Empty>(p)?;
            let m = shared.machine.borrow().clone();
            let progress = shared.progress.borrow().clone();
            let mut v = serde_json::to_value(m).unwrap_or(Value::Null);
            if let Some(o) = v.as_object_mut() {
                o.insert(
                    "progress".into(),
                    serde_json::to_value(progress).unwrap_or(Value::Null),
                );
            }
            Ok(v)
        }
        "machine.estop" => {
            params::<Empty>(p)?;
            let t = std::time::Instant::now();
            let timing = ask(shared, |r| Control::EStop(t, r)).await?;
            Ok(serde_json::to_value(timing).unwrap_or(Value::Null))
        }
        "machine.refill" => {
            params::<Empty>(p)?;
            ask(shared, Control::Refill).await?;
            Ok(json!({"refilled": true}))
        }
        other => Err(ApiError::new(
            ApiError::METHOD_NOT_FOUND,
            format!("no method {other:?}; see docs/api.md"),
        )),
    }
}

/// Decode standard base64 (RFC 4648, padding optional).
pub fn base64_decode(s: &str) -> Result<Vec<u8>, base64::DecodeError> {
    use base64::Engine;
    base64::engine::general_purpose::GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        base64::engine::GeneralPurposeConfig::new()
            .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent),
    )
    .decode(s)
}

/// Encode standard base64 with padding.
pub fn base64_encode(b: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trips() {
        for n in 0..20u8 {
            let v: Vec<u8> = (0..n).map(|i| i.wrapping_mul(37)).collect();
            assert_eq!(base64_decode(&base64_encode(&v)).unwrap(), v);
        }
        assert!(base64_decode("ab$c").is_err());
        assert_eq!(base64_decode("AQI").unwrap(), vec![1, 2]);
    }

    #[tokio::test]
    async fn long_lines_are_skipped_with_bounded_memory() {
        let data = b"0123456789\nabc\n".to_vec();
        let mut r = BufReader::with_capacity(4, &data[..]);
        let mut line = Vec::new();
        assert!(matches!(
            read_line(&mut r, &mut line, 5).await.unwrap(),
            LineRead::TooLong
        ));
        assert!(matches!(
            read_line(&mut r, &mut line, 5).await.unwrap(),
            LineRead::Line
        ));
        assert_eq!(line, b"abc");
        assert!(matches!(
            read_line(&mut r, &mut line, 5).await.unwrap(),
            LineRead::Eof
        ));
    }
}
