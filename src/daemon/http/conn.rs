//! The dashboard's connections, under the socket's connection budget
//! (`docs/http.md`, Limits):
//!
//! - At most `api.max_clients` ordinary TCP connections (a WebSocket is one: it keeps
//!   its connection's place). Beyond them up to `api.control_clients` more are
//!   accepted that may only load the page and ask `machine.estop` and
//!   `machine.status` (`GET /api/status`, `POST /api/rpc`); when those are all open a
//!   new connection takes the place of the oldest one waiting for its client, so idle
//!   connections cannot keep an operator from stopping the machine. Beyond both, a
//!   connection is answered 503 and closed at once.
//! - A connection must send a complete request within `api.idle_timeout_s` of opening
//!   or of its previous answer, or it is closed; a request's body must arrive within
//!   the same time ([`read_body`]).
//! - A body is read as it arrives: over `api.max_request_bytes` refused (413), and
//!   what it grows past a small line taken from the memory budget as it grows
//!   (refused at once, 503, when the budget has not got it).
//!
//! The socket's places and the dashboard's are counted apart: the socket is the local
//! operator's door, and no number of network clients may take its places.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::{Body, HttpBody};
use axum::extract::Request;
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Router;
use hyper_util::rt::TokioIo;
use hyper_util::service::TowerToHyperService;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};
use tower::ServiceExt;
use tracing::{debug, warn};

use crate::daemon::connections::{grow, idle_error, Held, Reserve, Ticket};
use crate::daemon::{ApiError, Shared};

/// A connection's place in the budget.
enum Place {
    /// One of `api.max_clients`.
    Ordinary(#[allow(dead_code)] OwnedSemaphorePermit),
    /// One of `api.control_clients`: control requests only.
    Control(Mutex<Ticket>),
}

/// One TCP connection: its place, held until the connection (or the WebSocket it
/// became) ends, and its requests in flight.
pub struct Conn {
    place: Place,
    requests: watch::Sender<usize>,
}

/// A request in flight on a [`Conn`]; the connection is idle again when it drops.
pub struct InFlight(Arc<Conn>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.requests.send_modify(|n| *n = n.saturating_sub(1));
    }
}

impl Conn {
    fn new(place: Place) -> Conn {
        Conn {
            place,
            requests: watch::Sender::new(0),
        }
    }

    /// Whether this connection may only ask control requests.
    pub fn control_only(&self) -> bool {
        matches!(self.place, Place::Control(_))
    }

    /// A request starts: the connection is busy (a control place is not taken from
    /// it) until the returned guard drops.
    fn begin(self: &Arc<Self>) -> InFlight {
        if let Place::Control(t) = &self.place {
            if let Ok(t) = t.lock() {
                t.busy();
            }
        }
        self.requests.send_modify(|n| *n += 1);
        InFlight(Arc::clone(self))
    }

    /// Returns when the connection has been idle (no request in flight) for `idle`,
    /// or when a newcomer took its control place while it was idle.
    async fn idle_out(&self, idle: Duration) {
        let mut requests = self.requests.subscribe();
        loop {
            if *requests.borrow_and_update() > 0 {
                if requests.changed().await.is_err() {
                    return;
                }
                continue;
            }
            let evicted = self.evicted();
            tokio::select! {
                _ = tokio::time::sleep(idle) => return,
                true = evicted => return,
                r = requests.changed() => if r.is_err() { return },
            }
        }
    }

    /// True when a newcomer takes this connection's control place while it waits for
    /// its client; false when it became busy first; never for an ordinary place.
    async fn evicted(&self) -> bool {
        let rx = match &self.place {
            Place::Control(t) => t.lock().ok().map(|mut t| t.waiting()),
            Place::Ordinary(_) => None,
        };
        match rx {
            Some(rx) => rx.await.is_ok(),
            None => std::future::pending().await,
        }
    }
}

/// The places of the dashboard's connections.
pub struct Places {
    slots: Arc<Semaphore>,
    reserve: Arc<Reserve>,
}

impl Places {
    pub fn new(api: &crate::daemon::config::ApiConfig) -> Places {
        Places {
            slots: Arc::new(Semaphore::new(api.max_clients)),
            reserve: Arc::new(Reserve::new(api.control_clients)),
        }
    }

    /// A place for a new connection: ordinary, else control, else none.
    fn admit(&self) -> Option<Conn> {
        if let Ok(p) = Arc::clone(&self.slots).try_acquire_owned() {
            return Some(Conn::new(Place::Ordinary(p)));
        }
        Reserve::admit(&self.reserve).map(|t| Conn::new(Place::Control(Mutex::new(t))))
    }
}

/// The answer to a connection beyond every place, written without waiting.
const REFUSED: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\n\
Connection: close\r\nContent-Length: 79\r\n\r\n\
edod is serving its most clients (api.max_clients, api.control_clients); retry\n";

/// Accept dashboard connections on `listener` until the task is aborted, each served
/// by `router` under the connection budget.
pub async fn serve(listener: TcpListener, router: Router, shared: Arc<Shared>) {
    let places = Places::new(&shared.config.api);
    let idle = shared.config.api.idle_timeout();
    let mut warned: Option<Instant> = None;
    let mut refused = 0u64;
    loop {
        let stream = match listener.accept().await {
            Ok((s, _)) => s,
            Err(e) => {
                // Out of descriptors (EMFILE) or the like: wait for connections to
                // close rather than spin on the error.
                if warned.is_none_or(|w| w.elapsed() > Duration::from_secs(10)) {
                    warn!(error = %e, "dashboard: accept failed");
                    warned = Some(Instant::now());
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Some(conn) = places.admit() else {
            let _ = stream.try_write(REFUSED);
            refused += 1;
            if warned.is_none_or(|w| w.elapsed() > Duration::from_secs(10)) {
                warn!(
                    refused,
                    "dashboard: every connection place taken; refusing connections"
                );
                warned = Some(Instant::now());
                refused = 0;
            }
            continue;
        };
        tokio::spawn(connection(stream, router.clone(), Arc::new(conn), idle));
    }
}

/// Serve one connection until it closes, idles out or is evicted.
async fn connection(stream: TcpStream, router: Router, conn: Arc<Conn>, idle: Duration) {
    let _ = stream.set_nodelay(true);
    let own = Arc::clone(&conn);
    let service = router.map_request(move |mut req: Request<hyper::body::Incoming>| {
        req.extensions_mut().insert(Arc::clone(&own));
        req
    });
    let serving = hyper::server::conn::http1::Builder::new()
        .serve_connection(TokioIo::new(stream), TowerToHyperService::new(service))
        .with_upgrades();
    tokio::select! {
        // An eviction or the idle timeout first: a request that arrives after it is
        // not served.
        biased;
        () = conn.idle_out(idle) => debug!("dashboard connection idle; closing it"),
        r = serving => if let Err(e) = r { debug!(error = %e, "dashboard connection ended") },
    }
}

/// What a control connection may ask besides `POST /api/rpc` of a control method:
/// the page itself and the machine's status.
fn control_path(method: &axum::http::Method, path: &str) -> bool {
    use axum::http::Method;
    (method == Method::GET
        && matches!(
            path,
            "/" | "/app.js" | "/app.css" | "/api/server" | "/api/status"
        ))
        || (method == Method::POST && path == "/api/rpc")
}

/// The answer to what a control connection may not ask: 503, and the connection closed.
pub fn control_refusal(shared: &Shared) -> Response {
    let e = crate::daemon::connections::control_only(shared);
    rest_error(StatusCode::SERVICE_UNAVAILABLE, &e, true)
}

/// Count a request in flight on its connection (idle timing stops while it runs);
/// on a control connection, refuse what is not control.
pub async fn counted(
    axum::extract::State(app): axum::extract::State<Arc<super::App>>,
    req: Request,
    next: Next,
) -> Response {
    let Some(conn) = req.extensions().get::<Arc<Conn>>().cloned() else {
        return next.run(req).await;
    };
    let _in_flight = conn.begin();
    if conn.control_only() && !control_path(req.method(), req.uri().path()) {
        return control_refusal(&app.shared);
    }
    next.run(req).await
}

/// A request's body, read as it arrives, and the budget it holds: over `max` bytes
/// (its announced length, or as it adds up) 413; what it grows past a small line
/// taken from the memory budget as it grows, 503 when the budget has not got it;
/// not complete within `api.idle_timeout_s`, 408.
pub async fn read_body(
    shared: &Shared,
    body: Body,
    max: usize,
) -> Result<(Vec<u8>, Held), Response> {
    let announced = body.size_hint().lower();
    if announced > max as u64 {
        return Err(too_large(shared, max));
    }
    let idle = shared.config.api.idle_timeout();
    match tokio::time::timeout(idle, collect(shared, body, max)).await {
        Ok(r) => r,
        Err(_) => Err(rest_error(
            StatusCode::REQUEST_TIMEOUT,
            &idle_error(shared),
            true,
        )),
    }
}

async fn collect(shared: &Shared, body: Body, max: usize) -> Result<(Vec<u8>, Held), Response> {
    use futures_util::StreamExt;
    let mut stream = body.into_data_stream();
    let mut bytes = Vec::new();
    let mut held = Held::default();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| {
            let e = ApiError::new(ApiError::INVALID_PARAMS, format!("the request's body: {e}"));
            rest_error(StatusCode::BAD_REQUEST, &e, true)
        })?;
        let need = bytes.len() + chunk.len();
        if need > max {
            return Err(too_large(shared, max));
        }
        if !grow(&mut bytes, &mut held, need, max, Some(&shared.budget)) {
            let e = shared.budget.refusal(need, "this request");
            return Err(rest_error(StatusCode::SERVICE_UNAVAILABLE, &e, true));
        }
        bytes.extend_from_slice(&chunk);
    }
    Ok((bytes, held))
}

/// 413, naming the limit: `api.max_request_bytes`, or a control connection's.
fn too_large(shared: &Shared, max: usize) -> Response {
    let limit = if max == shared.config.api.max_request_bytes {
        "api.max_request_bytes".to_string()
    } else {
        "the most a connection beyond api.max_clients may send".to_string()
    };
    let e = ApiError::new(
        ApiError::LIMIT,
        format!("the request's body is longer than {max} bytes ({limit})"),
    );
    rest_error(StatusCode::PAYLOAD_TOO_LARGE, &e, true)
}

/// An API error as the REST answers carry it (`{"error": {code, message}}`); `close`
/// asks to close the connection (the rest of a refused body is not read).
pub fn rest_error(status: StatusCode, e: &ApiError, close: bool) -> Response {
    let body = serde_json::json!({"error": {"code": e.code, "message": e.message}});
    let mut r = (
        status,
        [(header::CONTENT_TYPE, "application/json")],
        body.to_string(),
    )
        .into_response();
    if close {
        r.headers_mut().insert(
            header::CONNECTION,
            header::HeaderValue::from_static("close"),
        );
    }
    r
}
