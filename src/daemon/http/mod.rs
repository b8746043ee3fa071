//! The web dashboard (`docs/http.md`): the page, compiled into the binary, at `/`; the
//! same JSON-RPC methods and `notify_*` pushes as the Unix socket over a WebSocket at
//! `/websocket`; read-only JSON at `/api/...` for scripts; `POST /api/rpc` (one call)
//! and `POST /api/preview` (a job's plan before it is submitted).
//!
//! Every call goes through the socket's dispatcher ([`super::connections::Session`]),
//! under the same limits: `api.max_request_bytes` for a body or a message, the one
//! memory budget, `api.max_clients` WebSockets, `api.client_queue` replies and
//! notifications queued per WebSocket before a slow one is cut off. Who may call what
//! is [`guard`]'s. Nothing a client sends is used as a path on the host: the page's
//! files are a fixed table, and a job is named by its number.

pub mod conn;
pub mod guard;
mod layers;
mod page;
pub mod plans;
mod rest;
mod ws;

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::StatusCode;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use tokio::sync::Semaphore;

pub use guard::Guard;

use super::Shared;

/// What the handlers share.
pub struct App {
    /// The daemon's shared state.
    pub shared: Arc<Shared>,
    /// The listener's rules.
    pub guard: Guard,
    /// Plans made for previews and layer views, one at a time (they take a core).
    pub planning: Arc<Semaphore>,
    /// The plans kept for previews and layer views.
    pub plans: Arc<plans::Planning>,
}

/// The dashboard's routes, guarded.
pub fn router(shared: Arc<Shared>, guard: Guard) -> Router {
    routes(app(shared, guard))
}

/// What the handlers of a listener with `guard` share.
pub fn app(shared: Arc<Shared>, guard: Guard) -> Arc<App> {
    let http = &shared.config.http;
    let plans = Arc::new(plans::Planning {
        cache: Arc::new(plans::PlanCache::new(
            http.plan_cache_entries,
            http.plan_cache_bytes,
        )),
        config: shared.config.clone(),
        limits: shared.budget.mesh_limits(),
    });
    Arc::new(App {
        planning: Arc::new(Semaphore::new(1)),
        plans,
        shared,
        guard,
    })
}

/// The routes of `app`, guarded.
pub fn routes(app: Arc<App>) -> Router {
    Router::new()
        .route("/", get(page::index))
        .route("/app.js", get(page::script))
        .route("/app.css", get(page::style))
        .route("/websocket", get(ws::upgrade))
        .route("/api/server", get(rest::server))
        .route("/api/status", get(rest::status))
        .route("/api/jobs", get(rest::jobs))
        .route("/api/jobs/{id}", get(rest::job))
        .route("/api/jobs/{id}/layers/{layer}", get(rest::layer))
        .route("/api/rpc", post(rest::rpc))
        .route("/api/preview", post(rest::preview))
        .route("/api/previews/{id}/layers/{layer}", get(rest::preview_svg))
        .fallback(not_found)
        .layer(axum::middleware::from_fn_with_state(
            Arc::clone(&app),
            guarded,
        ))
        .layer(axum::middleware::from_fn_with_state(
            Arc::clone(&app),
            conn::counted,
        ))
        .with_state(app)
}

async fn not_found() -> Response {
    (StatusCode::NOT_FOUND, "not found").into_response()
}

/// Refuse what [`Guard::check`] refuses, before any handler runs.
async fn guarded(State(app): State<Arc<App>>, req: Request, next: Next) -> Response {
    let ask = guard::Ask {
        method: req.method(),
        path: req.uri().path(),
        query: req.uri().query(),
        headers: req.headers(),
        authority: req.uri().authority().map(|a| a.as_str()),
    };
    if let Err((status, why)) = app.guard.check(&ask) {
        return (status, why).into_response();
    }
    next.run(req).await
}

/// The dashboard's listener, bound before anything else starts, and its rules.
pub struct Listening {
    listener: tokio::net::TcpListener,
    guard: Guard,
}

/// Bind `[http] listen` (none when `[http] enabled = false`). A dashboard that cannot
/// be served (the port taken, the token file unreadable) is an error naming the key
/// and the address: edod does not start, as a service whose port is taken does not,
/// and systemd shows why. edod binds it before it opens the job store, so a refused
/// start leaves the store as it was.
pub async fn bind(http: &crate::daemon::config::HttpConfig) -> Result<Option<Listening>, String> {
    if !http.enabled {
        return Ok(None);
    }
    let addr = http
        .listen_addr()
        .map_err(|e| format!("[http] listen: {e}"))?;
    let token = http
        .token()
        .map_err(|e| format!("[http] token_file: {e}"))?;
    let listener = tokio::net::TcpListener::bind(addr).await.map_err(|e| {
        format!(
            "[http] listen = \"{addr}\": cannot bind {addr}: {e}; free the port, choose \
             another address, or set [http] enabled = false to run without the dashboard"
        )
    })?;
    let guard = Guard {
        token,
        loopback: addr.ip().is_loopback(),
    };
    Ok(Some(Listening { listener, guard }))
}

impl Listening {
    /// `listener` under `guard`'s rules (tests bind their own).
    pub fn new(listener: tokio::net::TcpListener, guard: Guard) -> Listening {
        Listening { listener, guard }
    }
}

/// Serve the dashboard on `listening` until the task is aborted, each connection under
/// the connection budget ([`conn`]).
pub async fn serve(shared: Arc<Shared>, listening: Listening) {
    if let Ok(addr) = listening.listener.local_addr() {
        tracing::info!("dashboard at http://{addr}/");
    }
    let app = router(Arc::clone(&shared), listening.guard);
    conn::serve(listening.listener, app, shared).await;
}

#[cfg(test)]
mod tests;
