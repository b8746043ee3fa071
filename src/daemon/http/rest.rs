//! `/api/...`: read-only JSON for scripts (each through the socket's dispatcher, so the
//! same answer as the method it names), one JSON-RPC call by POST, and plan previews
//! and layer views for the page.

use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Extension;
use serde_json::Value;

use super::plans::{self, Find, Key, Miss, Plan, Want};
use super::{conn, App};
use crate::daemon::connections::Session;
use crate::proto::{ApiError, Call, JobIdParams};

/// A JSON body.
fn json_response(status: StatusCode, body: String) -> Response {
    (
        status,
        [(header::CONTENT_TYPE, "application/json")],
        Body::from(body),
    )
        .into_response()
}

/// The HTTP status of an API error.
fn status_of(e: &ApiError) -> StatusCode {
    match e.code {
        ApiError::NO_SUCH_JOB => StatusCode::NOT_FOUND,
        ApiError::INVALID_PARAMS | ApiError::INVALID_JOB => StatusCode::BAD_REQUEST,
        ApiError::BAD_STATE => StatusCode::CONFLICT,
        ApiError::STORE_BUSY | ApiError::LIMIT => StatusCode::SERVICE_UNAVAILABLE,
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

fn error_response(e: ApiError) -> Response {
    conn::rest_error(status_of(&e), &e, false)
}

/// Dispatch `call` as the socket does; its result as a JSON value, or its error.
async fn dispatch(app: &App, call: Call) -> Result<Value, ApiError> {
    let result = crate::daemon::api::dispatch(call, &app.shared).await?;
    serde_json::to_value(&result)
        .map_err(|e| ApiError::new(ApiError::INTERNAL, format!("cannot write the result: {e}")))
}

/// [`dispatch`]'s result as the body, or its error with the matching status.
async fn call(app: &App, call: Call) -> Response {
    match dispatch(app, call).await {
        Ok(v) => json_response(StatusCode::OK, v.to_string()),
        Err(e) => error_response(e),
    }
}

/// `GET /api/server`: `server.info`, and whether calls need a token.
pub async fn server(State(app): State<Arc<App>>) -> Response {
    match dispatch(&app, Call::ServerInfo).await {
        Ok(mut v) => {
            if let Value::Object(m) = &mut v {
                m.insert("token_required".into(), app.guard.token.is_some().into());
            }
            json_response(StatusCode::OK, v.to_string())
        }
        Err(e) => error_response(e),
    }
}

/// `GET /api/status`: `machine.status`.
pub async fn status(State(app): State<Arc<App>>) -> Response {
    call(&app, Call::MachineStatus).await
}

/// `GET /api/jobs`: `job.list`.
pub async fn jobs(State(app): State<Arc<App>>) -> Response {
    call(&app, Call::JobList).await
}

/// `GET /api/jobs/{id}`: `job.get`.
pub async fn job(State(app): State<Arc<App>>, Path(id): Path<u32>) -> Response {
    call(&app, Call::JobGet(JobIdParams { id })).await
}

/// A body read as it arrives ([`conn::read_body`]: 413 over `max`, 503 over the
/// memory budget, 408 when it does not arrive within the idle timeout), held from the
/// memory budget at twice its length (as a socket line) while `f` runs.
async fn with_budget<F, Fut>(app: &App, body: Body, max: usize, f: F) -> Response
where
    F: FnOnce(Bytes) -> Fut,
    Fut: std::future::Future<Output = Response>,
{
    let (bytes, reading) = match conn::read_body(&app.shared, body, max).await {
        Ok(b) => b,
        Err(r) => return r,
    };
    let decoding = if bytes.len() > crate::daemon::connections::SMALL_LINE {
        match app.shared.budget.take(bytes.len(), "this request").await {
            Ok(h) => Some(h),
            Err(e) => return error_response(e),
        }
    } else {
        None
    };
    let r = f(Bytes::from(bytes)).await;
    drop((reading, decoding));
    r
}

/// `POST /api/rpc`: one JSON-RPC request as the body, its response as the answer. On
/// a control connection ([`conn`]) only `machine.estop` and `machine.status`.
pub async fn rpc(
    State(app): State<Arc<App>>,
    place: Option<Extension<Arc<conn::Conn>>>,
    body: Body,
) -> Response {
    let shared = Arc::clone(&app.shared);
    let control = place.is_some_and(|Extension(c)| c.control_only());
    let max = if control {
        crate::daemon::connections::CONTROL_LINE
    } else {
        shared.config.api.max_request_bytes
    };
    with_budget(&app, body, max, |body| async move {
        let reply = if control {
            // Read once: a control call is answered from what was read, anything else
            // refused ([`Call::is_control`]).
            match crate::daemon::api::parse(&body) {
                Ok((id, Ok(call))) if call.is_control() => {
                    crate::daemon::api::answer(Ok((id, Ok(call))), &shared)
                        .await
                        .0
                }
                _ => return conn::control_refusal(&shared),
            }
        } else {
            Session::default().request(Vec::from(body), &shared).await
        };
        match reply {
            Some(r) => json_response(StatusCode::OK, r),
            None => StatusCode::NO_CONTENT.into_response(),
        }
    })
    .await
}

/// What a preview is asked for: a job file and its mesh.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct PreviewAsk {
    job: String,
    #[serde(default)]
    mesh_base64: Option<String>,
}

impl PreviewAsk {
    /// The job file and the mesh's bytes, or the error (400) that names what is wrong.
    fn parse(body: &[u8]) -> Result<(String, Option<Vec<u8>>), ApiError> {
        let ask: PreviewAsk = serde_json::from_slice(body)
            .map_err(|e| ApiError::new(ApiError::INVALID_PARAMS, e.to_string()))?;
        let mesh = ask
            .mesh_base64
            .as_deref()
            .map(crate::proto::mesh_bytes::base64_decode)
            .transpose()
            .map_err(|e| {
                ApiError::new(
                    ApiError::INVALID_PARAMS,
                    format!("mesh_base64: not base64: {e}"),
                )
            })?;
        Ok((ask.job, mesh))
    }
}

/// `?layer=N`.
#[derive(serde::Deserialize)]
pub struct LayerQuery {
    #[serde(default)]
    layer: Option<u32>,
}

/// `POST /api/preview?layer=N`: the plan of a job not submitted: its id (for its
/// layers' images), its layers (height, moves), the view of layer N (the first by
/// default), and what submitting it would refuse (a part that does not fit the build
/// volume, materials the machine has not). The plan is kept ([`plans`]).
pub async fn preview(
    State(app): State<Arc<App>>,
    Query(q): Query<LayerQuery>,
    body: Body,
) -> Response {
    let app2 = Arc::clone(&app);
    let max = app.shared.config.api.max_request_bytes;
    with_budget(&app, body, max, move |body| async move {
        let (toml, mesh) = match PreviewAsk::parse(&body) {
            Ok(a) => a,
            Err(e) => return error_response(e),
        };
        let held = match mesh.as_deref() {
            Some(m) => match app2.shared.budget.mesh_check(m).await {
                Ok(h) => Some(h),
                Err(e) => return error_response(e),
            },
            None => None,
        };
        let layer = q.layer.unwrap_or(0);
        let recipe = plans::Recipe::Preview { toml, mesh };
        let r = from_plan(&app2, Find::Recipe(recipe), Want::All, move |k, p| {
            Ok(p.summary(k, layer))
        })
        .await;
        drop(held);
        match r {
            Ok(v) => json_response(StatusCode::OK, v.to_string()),
            Err(r) => r,
        }
    })
    .await
}

/// `GET /api/previews/{id}/layers/{layer}`: a previewed layer's SVG image, as
/// `edoctl plan --svg` draws it (404 once the plan is no longer kept).
pub async fn preview_svg(
    State(app): State<Arc<App>>,
    Path((id, layer)): Path<(String, u32)>,
) -> Response {
    let Some(key) = plans::parse_key(&id) else {
        return error_response(ApiError::new(
            ApiError::NO_SUCH_JOB,
            "no such preview: a preview's id is 32 hex digits",
        ));
    };
    match from_plan(&app, Find::Key(key), Want::Layer(layer), move |_, p| {
        p.svg(layer)
    })
    .await
    {
        Ok(svg) => (
            StatusCode::OK,
            [
                (header::CONTENT_TYPE, "image/svg+xml"),
                // Drawn by edod, shown as an image: it runs nothing and loads nothing.
                (header::CONTENT_SECURITY_POLICY, "default-src 'none'"),
                (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
                (header::CACHE_CONTROL, "private, no-cache"),
            ],
            svg,
        )
            .into_response(),
        Err(r) => r,
    }
}

/// `GET /api/jobs/{id}/layers/{layer}`: the roads of a stored job's layer, as planned,
/// with the index of its first move (the page draws the moves executed over them),
/// from the job's kept plan ([`plans`]).
pub async fn layer(State(app): State<Arc<App>>, Path((id, layer)): Path<(u32, u32)>) -> Response {
    let reader = app.shared.store.reader.clone();
    let stored = match blocking(move || reader.source_blocking(id)).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return error_response(crate::daemon::api_error(e)),
        Err(r) => return r,
    };
    let (job, mesh) = stored;
    let recipe = plans::Recipe::Stored {
        job: Box::new(job),
        mesh,
    };
    match from_plan(
        &app,
        Find::Recipe(recipe),
        Want::Layer(layer),
        move |_, p| p.view(layer),
    )
    .await
    {
        Ok(v) => json_response(StatusCode::OK, v),
        Err(r) => r,
    }
}

/// `f` on a blocking thread (it plans, or reads the store, or locks the plans).
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<T, Response> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| error_response(ApiError::new(ApiError::INTERNAL, e.to_string())))
}

/// `read` of the plan `find` names: from the kept plan if it has gone as far as
/// `want`, else planned on, one plan at a time, on a blocking thread.
async fn from_plan<T: Send + 'static>(
    app: &App,
    find: Find,
    want: Want,
    read: impl Fn(&Key, &Plan) -> Result<T, Miss> + Send + Sync + 'static,
) -> Result<T, Response> {
    let read = Arc::new(read);
    let (planning, r) = (Arc::clone(&app.plans), Arc::clone(&read));
    let (find, kept) = blocking(move || {
        let kept = planning.lookup(&find, want, &*r);
        (find, kept)
    })
    .await?;
    if let Some(answer) = kept {
        return answer.map_err(error_response);
    }
    let place = plan_slot(app).await?;
    let planning = Arc::clone(&app.plans);
    // Planning stops between layers when this request is dropped (its client left),
    // when edod stops, or past `http.plan_time_limit_s`.
    let given_up = GivenUp::default();
    let limit_s = app.shared.config.http.plan_time_limit_s;
    let stop = plans::Stop {
        flags: vec![Arc::clone(&given_up.0), Arc::clone(&app.shared.stopping)],
        deadline: std::time::Instant::now()
            + std::time::Duration::try_from_secs_f64(limit_s).unwrap_or(std::time::Duration::MAX),
        limit_s,
    };
    let answer = blocking(move || {
        let _place = place;
        planning.plan(find, want, &*read, &stop)
    })
    .await?;
    answer.map_err(error_response)
}

/// Set when dropped: a request's future dropped before its plan was answered (its
/// client left) tells the planning thread to stop; dropped after, the planning is over
/// and the flag, this request's own, is read by no one.
#[derive(Default)]
struct GivenUp(Arc<std::sync::atomic::AtomicBool>);

impl Drop for GivenUp {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// The one place to plan, waited for up to the idle timeout.
async fn plan_slot(app: &App) -> Result<tokio::sync::OwnedSemaphorePermit, Response> {
    let wait = app.shared.config.api.idle_timeout();
    match tokio::time::timeout(wait, Arc::clone(&app.planning).acquire_owned()).await {
        Ok(Ok(p)) => Ok(p),
        _ => Err(error_response(ApiError::new(
            ApiError::LIMIT,
            "edod is planning another preview; try again later",
        ))),
    }
}
