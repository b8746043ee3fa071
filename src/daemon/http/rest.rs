//! `/api/...`: read-only JSON for scripts (each through the socket's dispatcher, so the
//! same answer as the method it names), one JSON-RPC call by POST, and plan previews
//! and layer views for the page.

use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::{json, Value};

use super::App;
use crate::daemon::connections::Session;
use crate::daemon::store::JobSpec;
use crate::proto::{ApiError, Id, Request};

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
    let body = json!({"error": {"code": e.code, "message": e.message}});
    json_response(status_of(&e), body.to_string())
}

/// Call `method` through the dispatcher; its result as the body, or its error with the
/// matching status.
async fn call(app: &App, method: &str, params: Option<Value>) -> Response {
    let line = match serde_json::to_vec(&Request::new(Some(Id::Number(1.into())), method, params)) {
        Ok(l) => l,
        Err(e) => return error_response(ApiError::new(ApiError::INTERNAL, e.to_string())),
    };
    let reply = Session::default().request(&line, &app.shared).await;
    let parsed = reply
        .as_deref()
        .and_then(|r| serde_json::from_str::<crate::proto::Response>(r).ok());
    match parsed.map(crate::proto::Response::into_result) {
        Some(Ok(v)) => json_response(StatusCode::OK, v.to_string()),
        Some(Err(e)) => error_response(e),
        None => error_response(ApiError::new(ApiError::INTERNAL, "no answer")),
    }
}

/// `GET /api/server`: `server.info`, and whether calls need a token.
pub async fn server(State(app): State<Arc<App>>) -> Response {
    let r = call(&app, "server.info", None).await;
    if r.status() != StatusCode::OK {
        return r;
    }
    let bytes = axum::body::to_bytes(r.into_body(), 1 << 20)
        .await
        .unwrap_or_default();
    let mut v: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    if let Value::Object(m) = &mut v {
        m.insert("token_required".into(), app.guard.token.is_some().into());
    }
    json_response(StatusCode::OK, v.to_string())
}

/// `GET /api/status`: `machine.status`.
pub async fn status(State(app): State<Arc<App>>) -> Response {
    call(&app, "machine.status", None).await
}

/// `GET /api/jobs`: `job.list`.
pub async fn jobs(State(app): State<Arc<App>>) -> Response {
    call(&app, "job.list", None).await
}

/// `GET /api/jobs/{id}`: `job.get`.
pub async fn job(State(app): State<Arc<App>>, Path(id): Path<u32>) -> Response {
    call(&app, "job.get", Some(json!({ "id": id }))).await
}

/// A body's bytes, over `api.max_request_bytes` refused (413), held from the memory
/// budget (twice its length, as a socket line) while `f` runs.
async fn with_budget<F, Fut>(app: &App, body: Bytes, f: F) -> Response
where
    F: FnOnce(Bytes) -> Fut,
    Fut: std::future::Future<Output = Response>,
{
    let held = if body.len() > crate::daemon::connections::SMALL_LINE {
        match app.shared.budget.take(2 * body.len(), "this request").await {
            Ok(h) => Some(h),
            Err(e) => return error_response(e),
        }
    } else {
        None
    };
    let r = f(body).await;
    drop(held);
    r
}

/// `POST /api/rpc`: one JSON-RPC request as the body, its response as the answer.
pub async fn rpc(State(app): State<Arc<App>>, body: Bytes) -> Response {
    let shared = Arc::clone(&app.shared);
    with_budget(&app, body, |body| async move {
        match Session::default().request(&body, &shared).await {
            Some(r) => json_response(StatusCode::OK, r),
            None => StatusCode::NO_CONTENT.into_response(),
        }
    })
    .await
}

/// What a preview is asked for: a job file, its mesh, and the layer to draw.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct PreviewAsk {
    job: String,
    #[serde(default)]
    mesh_base64: Option<String>,
}

/// `?layer=N`.
#[derive(serde::Deserialize)]
pub struct LayerQuery {
    #[serde(default)]
    layer: Option<u32>,
}

/// `POST /api/preview?layer=N`: the plan of a job not submitted: its layers (height,
/// moves), the roads of layer N (the first by default), and what submitting it would
/// refuse (a part that does not fit the build volume, materials the machine has not).
pub async fn preview(
    State(app): State<Arc<App>>,
    Query(q): Query<LayerQuery>,
    body: Bytes,
) -> Response {
    let app2 = Arc::clone(&app);
    with_budget(&app, body, move |body| async move {
        let ask: PreviewAsk = match serde_json::from_slice(&body) {
            Ok(a) => a,
            Err(e) => {
                return error_response(ApiError::new(ApiError::INVALID_PARAMS, e.to_string()))
            }
        };
        let mesh = match ask
            .mesh_base64
            .as_deref()
            .map(crate::daemon::api::base64_decode)
        {
            Some(Ok(m)) => Some(m),
            Some(Err(e)) => {
                return error_response(ApiError::new(
                    ApiError::INVALID_PARAMS,
                    format!("mesh_base64: not base64: {e}"),
                ))
            }
            None => None,
        };
        let spec = JobSpec::Toml {
            toml: ask.job,
            mesh,
        };
        plan_view(&app2, spec, q.layer.unwrap_or(0)).await
    })
    .await
}

/// `GET /api/jobs/{id}/layers/{layer}`: the roads of a stored job's layer, as planned,
/// with the index of its first move (the page draws the moves executed over them).
pub async fn layer(State(app): State<Arc<App>>, Path((id, layer)): Path<(u32, u32)>) -> Response {
    let reader = app.shared.store.reader.clone();
    let planning = match plan_slot(&app).await {
        Ok(p) => p,
        Err(r) => return r,
    };
    let cfg = app.shared.config.clone();
    let done = tokio::task::spawn_blocking(move || {
        let _planning = planning;
        let (job, mesh) = reader
            .source_blocking(id)
            .map_err(crate::daemon::api_error)?;
        let drives = cfg.machine.syringes.len();
        let source = crate::daemon::planner::source_of(&job, mesh.as_deref(), drives, &cfg)
            .map_err(|e| ApiError::new(ApiError::INVALID_JOB, e))?;
        super::layers::view(source, layer).map_err(|e| ApiError::new(ApiError::INVALID_PARAMS, e))
    })
    .await;
    match done {
        Ok(Ok(v)) => json_response(StatusCode::OK, v.to_string()),
        Ok(Err(e)) => error_response(e),
        Err(e) => error_response(ApiError::new(ApiError::INTERNAL, e.to_string())),
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

/// Plan `spec` on a blocking thread for a preview: its problems as a submission would
/// find them, and the view of `layer`.
async fn plan_view(app: &App, spec: JobSpec, layer: u32) -> Response {
    let JobSpec::Toml { toml, mesh } = spec else {
        return error_response(ApiError::new(ApiError::INVALID_PARAMS, "not a job file"));
    };
    let held = match mesh.as_deref() {
        Some(m) => match app.shared.budget.mesh_check(m).await {
            Ok(h) => Some(h),
            Err(e) => return error_response(e),
        },
        None => None,
    };
    let planning = match plan_slot(app).await {
        Ok(p) => p,
        Err(r) => return r,
    };
    let machine = app.shared.config.machine.clone();
    let limits = app.shared.budget.mesh_limits();
    let done = tokio::task::spawn_blocking(move || {
        let _held = (held, planning);
        super::layers::preview(&toml, mesh.as_deref(), &machine, &limits, layer)
    })
    .await;
    match done {
        Ok(v) => json_response(StatusCode::OK, v.to_string()),
        Err(e) => error_response(ApiError::new(ApiError::INTERNAL, e.to_string())),
    }
}
