//! `/websocket`: one JSON-RPC request per text message, answered through the socket's
//! [`Session`], and the `notify_*` pushes after `subscribe` (Moonraker's shape).
//!
//! Limits as on the socket: a message over `api.max_request_bytes` closes the
//! connection; a large one is taken from the memory budget while it is answered; a
//! client that has not subscribed must send a request within `api.idle_timeout_s`; a
//! client that does not read its replies fills its queue (`api.client_queue`) and is
//! cut off.

use std::sync::Arc;

use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::State;
use axum::response::Response;
use axum::Extension;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tracing::debug;

use super::conn::Conn;
use super::App;
use crate::daemon::connections::{error_line, idle_error, queue_notification, too_long, Session};
use crate::daemon::Shared;
use crate::proto::Id;

/// The upgrade. The WebSocket keeps its connection's place in the connection budget
/// ([`super::conn`]) until it ends; a control connection may not open one.
pub async fn upgrade(
    State(app): State<Arc<App>>,
    conn: Option<Extension<Arc<Conn>>>,
    ws: WebSocketUpgrade,
) -> Response {
    let place = conn.map(|Extension(c)| c);
    if place.as_ref().is_some_and(|c| c.control_only()) {
        return super::conn::control_refusal(&app.shared);
    }
    let max = app.shared.config.api.max_request_bytes;
    let shared = Arc::clone(&app.shared);
    ws.max_message_size(max)
        .max_frame_size(max)
        .on_upgrade(move |socket| client(socket, shared, place))
}

/// One WebSocket client, until it closes, idles or falls behind.
async fn client(socket: WebSocket, shared: Arc<Shared>, _place: Option<Arc<Conn>>) {
    use futures_util::{SinkExt, StreamExt};
    let (mut sink, mut stream) = socket.split();
    let (tx, mut rx) = mpsc::channel::<Arc<str>>(shared.config.api.client_queue);
    let writer = tokio::spawn(async move {
        while let Some(line) = rx.recv().await {
            if sink.send(Message::text(line.as_ref())).await.is_err() {
                break;
            }
        }
        let _ = sink.close().await;
    });
    let idle = shared.config.api.idle_timeout();
    let mut session = Session::default();
    let mut last_request = Instant::now();
    let send = |line: String| tx.try_send(Arc::from(line)).is_ok();
    loop {
        let idle_at = (!session.subscribed()).then_some(last_request + idle);
        tokio::select! {
            m = stream.next() => {
                let bytes = match m {
                    Some(Ok(Message::Text(t))) => t.as_str().as_bytes().to_vec(),
                    Some(Ok(Message::Binary(b))) => b.to_vec(),
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                    Some(Err(e)) if e.to_string().contains("too long") => {
                        let _ = send(too_long(&shared));
                        break;
                    }
                    Some(Ok(Message::Close(_)) | Err(_)) | None => break,
                };
                if bytes.iter().all(u8::is_ascii_whitespace) { continue; }
                let reply = session.request(bytes, &shared).await;
                last_request = Instant::now();
                if reply.is_some_and(|r| !send(r)) {
                    debug!("dashboard too slow; disconnecting");
                    break;
                }
            }
            n = session.notification() => if !queue_notification(n, &tx) { break },
            _ = tokio::time::sleep_until(idle_at.unwrap_or_else(Instant::now)), if idle_at.is_some() => {
                let _ = send(error_line(Id::Null, idle_error(&shared)));
                break;
            }
        }
    }
    drop(tx);
    let _ = writer.await;
}
