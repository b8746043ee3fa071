//! The API socket's connections: accepting, reading request lines, and the limits that
//! keep one client from starving the others (`docs/api.md`, Limits and robustness).
//!
//! - At most `api.max_clients` ordinary connections. Beyond them up to
//!   `api.control_clients` more are accepted that may only ask `machine.estop` and
//!   `machine.status`; when those are all open a new connection takes the place of the
//!   oldest one that is waiting for its client, so idle clients cannot keep an
//!   operator from stopping the machine.
//! - A connection must send a complete request within `api.idle_timeout_s` of opening
//!   or of its previous request (a subscriber: of the first byte of a request), or it
//!   is told so and closed.
//! - Every byte of memory a request takes beyond a small line is taken from one budget,
//!   `api.memory_budget_bytes`, shared by all clients: the line as it grows, twice its
//!   length while it is decoded and answered, and a mesh check's working memory. A line
//!   that cannot get its bytes is refused at once (-32006, naming the budget) and the
//!   rest of it skipped unread into memory; a decode or a mesh check waits for its
//!   bytes up to the idle timeout, then is refused the same way.
//!
//! Each ordinary client gets a reader (this loop) and a writer task joined by a bounded
//! queue of reply lines; a client that does not read its replies fills its queue and is
//! disconnected: the daemon never waits for a client.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::io::{AsyncBufRead, AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::{mpsc, oneshot, OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;
use tracing::{debug, warn};

use super::{api, ApiError, Shared};
use crate::proto::{Id, Response};

/// Lines up to this long are read without taking from the memory budget (at most
/// `max_clients` of them: 16 MiB with the defaults).
pub const SMALL_LINE: usize = 64 << 10;
/// Longest request on a control connection.
pub const CONTROL_LINE: usize = 4 << 10;

/// What a triangle of a mesh being checked takes: its three corners (3 x 24 bytes)
/// and its indices (12 bytes), before repair merges the corners.
pub const MESH_BYTES_PER_TRIANGLE: usize = 84;

/// The memory budget for requests in flight, in KiB permits.
pub struct Budget {
    permits: Arc<Semaphore>,
    total: usize,
    wait: Duration,
}

/// Bytes held from a [`Budget`]; given back when dropped.
#[derive(Default)]
pub struct Held {
    permit: Option<OwnedSemaphorePermit>,
}

impl Held {
    fn bytes(&self) -> usize {
        self.permit.as_ref().map_or(0, |p| p.num_permits() << 10)
    }
}

fn kib(bytes: usize) -> u32 {
    u32::try_from(bytes.div_ceil(1024)).unwrap_or(u32::MAX)
}

fn mib(bytes: usize) -> String {
    format!("{:.1} MiB", bytes as f64 / f64::from(1 << 20))
}

impl Budget {
    /// The budget of `api.memory_budget_bytes`; a wait for it lasts at most
    /// `api.idle_timeout_s`.
    pub fn new(cfg: &super::config::ApiConfig) -> Budget {
        let total = cfg.memory_budget();
        Budget {
            permits: Arc::new(Semaphore::new((total >> 10).min(Semaphore::MAX_PERMITS))),
            total,
            wait: cfg.idle_timeout(),
        }
    }

    /// The error for a request that cannot have `bytes` more.
    pub fn refusal(&self, bytes: usize, what: &str) -> ApiError {
        ApiError::new(
            ApiError::LIMIT,
            format!(
                "{what} needs {} more of edod's memory budget for requests \
                 (api.memory_budget_bytes = {}), which other requests hold; try again later",
                mib(bytes),
                mib(self.total)
            ),
        )
    }

    /// Add `bytes` to `held` now, or refuse.
    fn try_grow(&self, held: &mut Held, bytes: usize) -> bool {
        match Arc::clone(&self.permits).try_acquire_many_owned(kib(bytes)) {
            Ok(p) => {
                match &mut held.permit {
                    Some(h) => h.merge(p),
                    None => held.permit = Some(p),
                }
                true
            }
            Err(_) => false,
        }
    }

    /// `bytes` from the budget, waiting for them up to the idle timeout; `what` names
    /// the request in the refusal.
    pub async fn take(&self, bytes: usize, what: &str) -> Result<Held, ApiError> {
        if bytes > self.total {
            return Err(self.refusal(bytes, what));
        }
        let acquire = Arc::clone(&self.permits).acquire_many_owned(kib(bytes));
        match tokio::time::timeout(self.wait, acquire).await {
            Ok(Ok(p)) => Ok(Held { permit: Some(p) }),
            _ => Err(self.refusal(bytes, what)),
        }
    }

    /// The limits a mesh check runs under: a decompressed 3MF model part of at most a
    /// quarter of the budget, and no more triangles than the half of the budget a 3MF
    /// check holds can build ([`MESH_BYTES_PER_TRIANGLE`] each).
    pub fn mesh_limits(&self) -> crate::mesh::MeshLimits {
        let d = crate::mesh::MeshLimits::default();
        crate::mesh::MeshLimits {
            max_bytes: d.max_bytes.min((self.total / 4) as u64),
            max_triangles: d
                .max_triangles
                .min((self.total / 2 / MESH_BYTES_PER_TRIANGLE) as u64),
        }
    }

    /// Hold the working memory of checking `mesh` (its triangles; for a 3MF, its
    /// decompressed model, up to [`Budget::mesh_limits`]) until the check ends.
    pub async fn mesh_check(&self, mesh: &[u8]) -> Result<Held, ApiError> {
        let zip = mesh.starts_with(b"PK");
        let bytes = if zip {
            2 * self.mesh_limits().max_bytes as usize
        } else {
            mesh.len()
        };
        self.take(bytes.min(self.total / 2), "the mesh check").await
    }
}

/// What [`LineReader::next`] found.
#[derive(Debug, PartialEq, Eq)]
pub enum LineEvent {
    /// A complete line, in [`LineReader::line`].
    Line,
    /// A line over the size limit was skipped to its newline.
    TooLong,
    /// The budget could not give a growing line its bytes: the rest of it is skipped.
    OverBudget(usize),
    /// The client closed (a partial last line is dropped).
    Eof,
}

/// Why the rest of a line is being skipped.
#[derive(Debug, Clone, Copy)]
enum Skip {
    /// Over `max`: reported at its newline.
    TooLong,
    /// Over the budget: already reported.
    Quietly,
}

/// Reads request lines with bounded memory. `next` is cancel-safe (it awaits only
/// `fill_buf`, and a line begun is kept until it is delivered), so it can race
/// notifications and timers without losing bytes.
pub struct LineReader<R> {
    r: R,
    line: Vec<u8>,
    held: Held,
    max: usize,
    skipping: Option<Skip>,
    partial_since: Option<Instant>,
    /// The last call delivered `line`: the next one starts a new line.
    delivered: bool,
}

impl<R: AsyncBufRead + Unpin> LineReader<R> {
    /// A reader of lines up to `max` bytes.
    pub fn new(r: R, max: usize) -> Self {
        LineReader {
            r,
            line: Vec::new(),
            held: Held::default(),
            max,
            skipping: None,
            partial_since: None,
            delivered: false,
        }
    }

    /// The line [`LineEvent::Line`] reported.
    pub fn line(&self) -> &[u8] {
        &self.line
    }

    /// When the first byte of a line not yet complete arrived.
    pub fn partial_since(&self) -> Option<Instant> {
        self.partial_since
    }

    /// Take the line and its hold on the budget (the reader starts a new buffer).
    pub fn take_line(&mut self) -> (Vec<u8>, Held) {
        (
            std::mem::take(&mut self.line),
            std::mem::take(&mut self.held),
        )
    }

    /// Give back the line's buffer and its budget.
    fn drop_line(&mut self) {
        self.line = Vec::new();
        self.held = Held::default();
    }

    /// Forget the last line, giving back a large buffer and its budget.
    fn reset(&mut self) {
        if self.line.capacity() > SMALL_LINE {
            self.line = Vec::new();
            self.held = Held::default();
        } else {
            self.line.clear();
        }
    }

    /// Read up to the next line's end; lines past `max`, or past what `budget` gives,
    /// are skipped without being kept.
    pub async fn next(&mut self, budget: Option<&Budget>) -> std::io::Result<LineEvent> {
        // Only a delivered line is forgotten: a call cancelled mid-line (a notification
        // or a timer won the race) leaves the bytes it read for the next call.
        if std::mem::take(&mut self.delivered) {
            self.reset();
        }
        loop {
            let buf = self.r.fill_buf().await?;
            if buf.is_empty() {
                return Ok(LineEvent::Eof);
            }
            self.partial_since.get_or_insert_with(Instant::now);
            let found = buf.iter().position(|&b| b == b'\n');
            let chunk = &buf[..found.unwrap_or(buf.len())];
            let mut event = None;
            if self.skipping.is_none() {
                let need = self.line.len() + chunk.len();
                if need > self.max {
                    event = Some(LineEvent::TooLong);
                } else if !grow(&mut self.line, &mut self.held, need, self.max, budget) {
                    event = Some(LineEvent::OverBudget(need));
                } else {
                    self.line.extend_from_slice(chunk);
                }
            }
            let used = found.map_or(buf.len(), |i| i + 1);
            self.r.consume(used);
            if found.is_some() {
                self.partial_since = None;
            }
            match (event, found) {
                (Some(e), Some(_)) => {
                    self.drop_line();
                    return Ok(e);
                }
                (Some(LineEvent::OverBudget(n)), None) => {
                    // Say so now (the client may be waiting to send the rest), then
                    // skip the rest quietly.
                    self.skipping = Some(Skip::Quietly);
                    self.drop_line();
                    return Ok(LineEvent::OverBudget(n));
                }
                (Some(_), None) => {
                    self.skipping = Some(Skip::TooLong);
                    self.drop_line();
                }
                (None, Some(_)) => match self.skipping.take() {
                    Some(Skip::TooLong) => return Ok(LineEvent::TooLong),
                    Some(Skip::Quietly) => self.reset(),
                    None => {
                        self.delivered = true;
                        return Ok(LineEvent::Line);
                    }
                },
                (None, None) => {}
            }
        }
    }
}

/// Make room for `need` bytes in `line`, taking what it grows past [`SMALL_LINE`] from
/// `budget` (doubling, up to `max`); false if the budget has not got it.
pub(crate) fn grow(
    line: &mut Vec<u8>,
    held: &mut Held,
    need: usize,
    max: usize,
    budget: Option<&Budget>,
) -> bool {
    if need <= line.capacity() {
        return true;
    }
    let Some(budget) = budget.filter(|_| need > SMALL_LINE) else {
        line.reserve(need - line.len());
        return true;
    };
    let want = need.max(line.capacity().saturating_mul(2)).min(max);
    let got = budget.try_grow(held, want.saturating_sub(held.bytes()))
        || budget.try_grow(held, need.saturating_sub(held.bytes()));
    if got {
        line.reserve_exact(held.bytes().max(need) - line.len());
    }
    got
}

/// An error response line (id null unless known).
pub fn error_line(id: Id, e: ApiError) -> String {
    serde_json::to_string(&Response::<crate::proto::MethodResult>::new(id, Err(e)))
        .unwrap_or_else(|_| {
            r#"{"jsonrpc":"2.0","id":null,"error":{"code":-32603,"message":"cannot write an error"}}"#
                .to_string()
        })
}

pub fn idle_error(shared: &Shared) -> ApiError {
    ApiError::new(
        ApiError::LIMIT,
        format!(
            "no complete request within {} s (api.idle_timeout_s); closing the connection",
            shared.config.api.idle_timeout_s
        ),
    )
}

/// Accept clients until the listener fails.
pub async fn serve(listener: UnixListener, shared: Arc<Shared>) {
    let slots = Arc::new(Semaphore::new(shared.config.api.max_clients));
    let reserve = Arc::new(Reserve::new(shared.config.api.control_clients));
    loop {
        let (stream, _) = match listener.accept().await {
            Ok(s) => s,
            Err(e) => {
                warn!(error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let shared = Arc::clone(&shared);
        if let Ok(permit) = Arc::clone(&slots).try_acquire_owned() {
            tokio::spawn(async move {
                client(stream, shared).await;
                drop(permit);
            });
        } else if let Some(ticket) = Reserve::admit(&reserve) {
            tokio::spawn(control_client(stream, shared, ticket));
        } else {
            warn!("too many clients, every control slot busy; refusing one");
        }
    }
}

/// What one client holds, whichever transport carries it (this socket, or the
/// dashboard's WebSocket in [`super::http`]): requests answered by the one dispatcher
/// under the memory budget, and its subscription to notifications.
#[derive(Default)]
pub struct Session {
    notifications: Option<tokio::sync::broadcast::Receiver<Arc<str>>>,
}

/// Why a subscriber's notifications ended.
pub enum NotifyEnd {
    /// It fell behind by this many notifications: it is cut off.
    Lagged(u64),
    /// The daemon stopped sending.
    Closed,
}

impl Session {
    /// Whether the client has subscribed (it is then idle only mid-request).
    pub fn subscribed(&self) -> bool {
        self.notifications.is_some()
    }

    /// Answer one complete request (a line, a WebSocket message): the reply (none for
    /// a JSON-RPC notification); a `subscribe` starts the client's notifications.
    pub async fn request(&mut self, line: Vec<u8>, shared: &Arc<Shared>) -> Option<String> {
        self.request_held(line, Held::default(), shared).await
    }

    /// [`Session::request`] for a line still holding `held` of the budget, given back
    /// once it is parsed.
    pub async fn request_held(
        &mut self,
        line: Vec<u8>,
        held: Held,
        shared: &Arc<Shared>,
    ) -> Option<String> {
        let (reply, subscribe) = answer(line, held, shared).await;
        if subscribe && self.notifications.is_none() {
            self.notifications = Some(shared.notify.subscribe());
        }
        reply
    }

    /// The next notification line; pending for ever before `subscribe`. Cancel-safe.
    pub async fn notification(&mut self) -> Result<Arc<str>, NotifyEnd> {
        use tokio::sync::broadcast::error::RecvError;
        let Some(rx) = self.notifications.as_mut() else {
            return std::future::pending().await;
        };
        match rx.recv().await {
            Ok(line) => Ok(line),
            Err(RecvError::Lagged(n)) => Err(NotifyEnd::Lagged(n)),
            Err(RecvError::Closed) => {
                self.notifications = None;
                Err(NotifyEnd::Closed)
            }
        }
    }
}

/// Queue a notification for a client's writer; false when the client is to be cut off
/// (its queue is full, or it fell behind the notifications).
pub fn queue_notification(n: Result<Arc<str>, NotifyEnd>, tx: &mpsc::Sender<Arc<str>>) -> bool {
    match n {
        Ok(line) => {
            let queued = tx.try_send(line).is_ok();
            if !queued {
                debug!("subscriber too slow; disconnecting");
            }
            queued
        }
        Err(NotifyEnd::Lagged(n)) => {
            debug!(missed = n, "subscriber lagged; disconnecting");
            false
        }
        Err(NotifyEnd::Closed) => true,
    }
}

/// The refusal of a request over `api.max_request_bytes`.
pub fn too_long(shared: &Shared) -> String {
    let max = shared.config.api.max_request_bytes;
    let e = ApiError::new(
        ApiError::INVALID_REQUEST,
        format!("request over {max} bytes (api.max_request_bytes)"),
    );
    error_line(Id::Null, e)
}

/// An ordinary client: requests answered in order, notifications after `subscribe`.
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
    let api = &shared.config.api;
    let (max, idle) = (api.max_request_bytes, api.idle_timeout());
    let mut reader = LineReader::new(BufReader::new(rd), max);
    let mut session = Session::default();
    let mut last_request = Instant::now();
    let send = |line: String| tx.try_send(Arc::from(line)).is_ok();
    let closed = loop {
        // A subscriber waits for notifications as long as it likes, not mid-request.
        let idle_since = match (session.subscribed(), reader.partial_since()) {
            (true, since) => since,
            (false, _) => Some(last_request),
        };
        tokio::select! {
            r = reader.next(Some(&shared.budget)) => match r {
                Ok(LineEvent::Eof) => break "the client closed",
                Err(_) => break "a read error",
                Ok(LineEvent::TooLong) => {
                    if !send(too_long(&shared)) { break "its queue is full"; }
                }
                Ok(LineEvent::OverBudget(n)) => {
                    let e = shared.budget.refusal(n, "this request");
                    debug!("request refused: over the memory budget");
                    if !send(error_line(Id::Null, e)) { break "its queue is full"; }
                }
                Ok(LineEvent::Line) => {
                    if reader.line().iter().all(u8::is_ascii_whitespace) { continue; }
                    let (line, held) = reader.take_line();
                    let reply = session.request_held(line, held, &shared).await;
                    last_request = Instant::now();
                    if let Some(r) = reply {
                        if !send(r) {
                            break "its queue is full (a client too slow)";
                        }
                    }
                }
            },
            n = session.notification() => if !queue_notification(n, &tx) {
                break "it fell behind the notifications";
            },
            _ = tokio::time::sleep_until(idle_since.unwrap_or_else(Instant::now) + idle),
                if idle_since.is_some() => {
                let _ = send(error_line(Id::Null, idle_error(&shared)));
                break "idle (api.idle_timeout_s)";
            }
        }
    };
    debug!(why = closed, "client connection closed");
    drop(tx);
    let _ = writer.await;
}

/// Answer a complete line, holding twice its length from the budget while it is
/// decoded and answered (a small line holds nothing). A large line is parsed on a
/// blocking thread, and it (with `line_held`, its own hold) is given back once parsed.
async fn answer(line: Vec<u8>, line_held: Held, shared: &Arc<Shared>) -> (Option<String>, bool) {
    if line.len() <= SMALL_LINE {
        return api::handle(&line, shared).await;
    }
    let _held = match shared.budget.take(2 * line.len(), "this request").await {
        Ok(h) => h,
        Err(e) => return (Some(error_line(Id::Null, e)), false),
    };
    let parsed = api::parse_off_runtime(line, line_held).await;
    api::answer(parsed, shared).await
}

/// The connections beyond `max_clients`, for control requests only.
pub(crate) struct Reserve {
    cap: usize,
    inner: Mutex<ReserveState>,
}

#[derive(Default)]
struct ReserveState {
    open: usize,
    next_id: u64,
    /// Connections waiting for their client, oldest first: the one to close for a
    /// newcomer.
    waiting: VecDeque<(u64, oneshot::Sender<()>)>,
}

/// A control connection's place in the [`Reserve`].
pub(crate) struct Ticket {
    reserve: Arc<Reserve>,
    id: u64,
    /// The eviction of its first wait, which starts at admission: a connection whose
    /// task has not run yet waits for its client too, so a burst of connects can always
    /// take the oldest place (else, admitted faster than their tasks ran, every place
    /// read as busy and `edoctl status` behind 300 connects was refused).
    first_wait: Option<oneshot::Receiver<()>>,
}

impl Reserve {
    pub(crate) fn new(cap: usize) -> Reserve {
        Reserve {
            cap,
            inner: Mutex::new(ReserveState::default()),
        }
    }

    /// A place for a new control connection: a free one, or the one of the oldest
    /// connection waiting for its client (which is closed); none if every one is
    /// answering a request.
    pub(crate) fn admit(reserve: &Arc<Reserve>) -> Option<Ticket> {
        let mut s = reserve.inner.lock().ok()?;
        if s.open >= reserve.cap {
            let (_, evict) = s.waiting.pop_front()?;
            let _ = evict.send(());
        }
        s.open += 1;
        s.next_id += 1;
        let (tx, rx) = oneshot::channel();
        let id = s.next_id;
        s.waiting.push_back((id, tx));
        Some(Ticket {
            reserve: Arc::clone(reserve),
            id,
            first_wait: Some(rx),
        })
    }
}

impl Ticket {
    /// Mark the connection as waiting for its client: the receiver fires when a
    /// newcomer takes its place.
    pub(crate) fn waiting(&mut self) -> oneshot::Receiver<()> {
        if let Some(first) = self.first_wait.take() {
            return first;
        }
        let (tx, rx) = oneshot::channel();
        if let Ok(mut s) = self.reserve.inner.lock() {
            s.waiting.retain(|(id, _)| *id != self.id);
            s.waiting.push_back((self.id, tx));
        }
        rx
    }

    /// Mark the connection as answering a request: it keeps its place.
    pub(crate) fn busy(&self) {
        if let Ok(mut s) = self.reserve.inner.lock() {
            s.waiting.retain(|(id, _)| *id != self.id);
        }
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if let Ok(mut s) = self.reserve.inner.lock() {
            s.waiting.retain(|(id, _)| *id != self.id);
            s.open = s.open.saturating_sub(1);
        }
    }
}

/// The error for an ordinary request on a control connection.
pub(crate) fn control_only(shared: &Shared) -> ApiError {
    ApiError::new(
        ApiError::LIMIT,
        format!(
            "edod is serving its most clients (api.max_clients = {}): this connection may \
             only ask {}; try again later",
            shared.config.api.max_clients,
            crate::proto::CONTROL_METHODS.join(" or ")
        ),
    )
}

/// A control connection: `machine.estop` and `machine.status` answered, anything else
/// refused and the connection closed; closed too when idle or when a newcomer takes its
/// place while it waits for its client.
async fn control_client(stream: UnixStream, shared: Arc<Shared>, mut ticket: Ticket) {
    let (rd, mut wr) = stream.into_split();
    let mut reader = LineReader::new(BufReader::new(rd), CONTROL_LINE);
    let idle = shared.config.api.idle_timeout();
    loop {
        let evicted = ticket.waiting();
        let event = tokio::select! {
            r = reader.next(None) => r,
            _ = evicted => break,
            _ = tokio::time::sleep(idle) => {
                let _ = write_line(&mut wr, error_line(Id::Null, idle_error(&shared))).await;
                break;
            }
        };
        ticket.busy();
        let (reply, close) = match event {
            Ok(LineEvent::Line) => control_answer(reader.line(), &shared).await,
            Ok(LineEvent::TooLong | LineEvent::OverBudget(_)) => {
                (Some(error_line(Id::Null, control_only(&shared))), true)
            }
            Ok(LineEvent::Eof) | Err(_) => break,
        };
        if let Some(r) = reply {
            if write_line(&mut wr, r).await.is_err() {
                break;
            }
        }
        if close {
            break;
        }
    }
}

/// A control connection's answer to `line`, and whether to close it after.
async fn control_answer(line: &[u8], shared: &Arc<Shared>) -> (Option<String>, bool) {
    if line.iter().all(u8::is_ascii_whitespace) {
        return (None, false);
    }
    match api::parse(line) {
        Ok((id, Ok(call))) if call.is_control() => {
            (api::answer(Ok((id, Ok(call))), shared).await.0, false)
        }
        Ok((id, _)) => (
            Some(error_line(id.unwrap_or(Id::Null), control_only(shared))),
            true,
        ),
        Err(refusal) => (Some(error_line(refusal.id, refusal.error)), true),
    }
}

/// Write one line to a control client, giving up after a second.
async fn write_line(
    wr: &mut tokio::net::unix::OwnedWriteHalf,
    line: String,
) -> std::io::Result<()> {
    let write = async {
        wr.write_all(line.as_bytes()).await?;
        wr.write_all(b"\n").await
    };
    tokio::time::timeout(Duration::from_secs(1), write)
        .await
        .unwrap_or_else(|_| Err(std::io::ErrorKind::TimedOut.into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn budget(total: usize) -> Budget {
        let cfg = crate::daemon::config::ApiConfig {
            memory_budget_bytes: Some(total),
            idle_timeout_s: 0.05,
            ..Default::default()
        };
        Budget::new(&cfg)
    }

    #[tokio::test]
    async fn long_lines_are_skipped_with_bounded_memory() {
        let data = b"0123456789\nabc\n".to_vec();
        let mut r = LineReader::new(BufReader::with_capacity(4, &data[..]), 5);
        assert_eq!(r.next(None).await.unwrap(), LineEvent::TooLong);
        assert_eq!(r.next(None).await.unwrap(), LineEvent::Line);
        assert_eq!(r.line(), b"abc");
        assert_eq!(r.next(None).await.unwrap(), LineEvent::Eof);
    }

    #[tokio::test]
    async fn a_read_cancelled_mid_line_loses_none_of_it() {
        use tokio::io::AsyncWriteExt as _;
        let (mut client, server) = tokio::io::duplex(64);
        let mut r = LineReader::new(BufReader::new(server), 1024);
        client.write_all(b"{\"id\":").await.unwrap();
        // A notification (here a timer) wins the race while the line is half read.
        let wait = tokio::time::timeout(Duration::from_millis(20), r.next(None)).await;
        assert!(wait.is_err(), "no line yet: {wait:?}");
        assert!(r.partial_since().is_some());
        client.write_all(b"7}\nnext\n").await.unwrap();
        assert_eq!(r.next(None).await.unwrap(), LineEvent::Line);
        assert_eq!(r.line(), b"{\"id\":7}");
        assert_eq!(r.next(None).await.unwrap(), LineEvent::Line);
        assert_eq!(r.line(), b"next");
    }

    #[tokio::test]
    async fn a_line_the_budget_cannot_hold_is_refused_at_once_and_skipped() {
        let b = budget(1 << 20);
        let mut data = vec![b'x'; 900 << 10];
        data.push(b'\n');
        data.extend_from_slice(b"ok\n");
        let mut held = Held::default();
        assert!(b.try_grow(&mut held, 600 << 10));
        let mut r = LineReader::new(BufReader::with_capacity(8192, &data[..]), 4 << 20);
        let e = r.next(Some(&b)).await.unwrap();
        assert!(
            matches!(e, LineEvent::OverBudget(n) if n > (400 << 10)),
            "{e:?}"
        );
        assert!(r.line().is_empty());
        // The rest of that line is skipped, then the next one is read.
        assert_eq!(r.next(Some(&b)).await.unwrap(), LineEvent::Line);
        assert_eq!(r.line(), b"ok");
        drop(held);
        // With the budget free, the long line fits and its bytes come back after.
        let mut r = LineReader::new(BufReader::with_capacity(8192, &data[..]), 4 << 20);
        assert_eq!(r.next(Some(&b)).await.unwrap(), LineEvent::Line);
        assert_eq!(r.line().len(), 900 << 10);
        assert!(b.permits.available_permits() < 200);
        assert_eq!(r.next(Some(&b)).await.unwrap(), LineEvent::Line);
        assert_eq!(b.permits.available_permits(), 1024);
    }

    #[tokio::test]
    async fn a_wait_for_the_budget_ends_in_a_refusal_naming_it() {
        let b = budget(1 << 20);
        let held = b.take(1 << 20, "x").await.unwrap();
        let e = b.take(1024, "the mesh check").await.err().unwrap();
        assert_eq!(e.code, ApiError::LIMIT);
        assert!(
            e.message.contains("api.memory_budget_bytes = 1.0 MiB"),
            "{e:?}"
        );
        drop(held);
        assert!(b.take(1024, "x").await.is_ok());
    }

    #[test]
    fn a_newcomer_takes_the_place_of_the_oldest_waiting_control_connection() {
        let r = Arc::new(Reserve::new(2));
        let mut a = Reserve::admit(&r).unwrap();
        let b = Reserve::admit(&r).unwrap();
        let mut a_wait = a.waiting();
        b.busy();
        let c = Reserve::admit(&r).unwrap();
        assert!(a_wait.try_recv().is_ok(), "a was closed for c");
        drop(a);
        c.busy();
        assert!(Reserve::admit(&r).is_none(), "b and c are answering");
        drop(b);
        assert!(Reserve::admit(&r).is_some());
    }

    /// A burst: places admitted before their tasks ran wait for their clients from
    /// admission, so each newcomer takes the oldest, and the last one (an operator's
    /// `edoctl status`) gets a place.
    #[test]
    fn a_burst_of_control_connections_never_locks_the_last_one_out() {
        let r = Arc::new(Reserve::new(4));
        let mut admitted: Vec<Ticket> = (0..300)
            .map(|k| Reserve::admit(&r).unwrap_or_else(|| panic!("connect {k} refused")))
            .collect();
        let last = admitted.pop().unwrap();
        // Those evicted learn it at their first wait, and close.
        let mut evicted = 0;
        for t in &mut admitted {
            if t.waiting().try_recv().is_ok() {
                evicted += 1;
            }
        }
        assert_eq!(evicted, 296, "all but the newest four were closed");
        drop(admitted);
        last.busy();
        assert_eq!(r.inner.lock().unwrap().open, 1);
    }
}
