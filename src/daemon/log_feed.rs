//! edod's log as the dashboard's console shows it (`log.recent`, docs/api.md): every
//! event edod's own code logs at `info` or above (the job lifecycle, faults, the link;
//! on a G-code link the firmware's errors, resends and halts), with its fields.
//!
//! [`FeedLayer`] is a `tracing` layer edod's `main` adds beside the log writer: it turns
//! each event into a [`LogLine`] and sends it on a process-wide broadcast channel, never
//! waiting. [`keep`] is a task that keeps the last [`KEPT`] lines and publishes them in
//! [`Shared::log`] for `log.recent`.

use std::collections::VecDeque;
use std::fmt::Write as _;
use std::sync::{Arc, OnceLock};

use tokio::sync::{broadcast, watch};
use tracing::field::{Field, Visit};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::Context;

use super::Shared;
use crate::proto::LogLine;

/// Lines kept for `log.recent`.
pub const KEPT: usize = 500;

/// Longest message kept, bytes (a firmware line echoed back can be long).
const MAX_MESSAGE_BYTES: usize = 2000;

/// Where edod's log events go, process-wide (a layer is global, as the subscriber is).
fn feed() -> &'static broadcast::Sender<LogLine> {
    static FEED: OnceLock<broadcast::Sender<LogLine>> = OnceLock::new();
    FEED.get_or_init(|| broadcast::channel(1024).0)
}

/// The `tracing` layer that feeds the console: events of edo's own modules at `info`
/// or above.
pub struct FeedLayer;

impl<S: Subscriber> tracing_subscriber::Layer<S> for FeedLayer {
    fn on_event(&self, event: &Event<'_>, _ctx: Context<'_, S>) {
        let meta = event.metadata();
        if *meta.level() > Level::INFO || !meta.target().starts_with("edo") {
            return;
        }
        let feed = feed();
        if feed.receiver_count() == 0 {
            return;
        }
        let mut fields = Fields::default();
        event.record(&mut fields);
        let level = match *meta.level() {
            Level::ERROR => "error",
            Level::WARN => "warn",
            _ => "info",
        };
        let mut message = fields.message;
        message.push_str(&fields.rest);
        if message.len() > MAX_MESSAGE_BYTES {
            let mut cut = MAX_MESSAGE_BYTES;
            while !message.is_char_boundary(cut) {
                cut -= 1;
            }
            message.truncate(cut);
            message.push('…');
        }
        let _ = feed.send(LogLine {
            seq: 0,
            at_ms: super::store::now_ms(),
            level: level.into(),
            job_id: fields.job_id,
            message,
        });
    }
}

/// An event's message, its job (a `job` field holding an id, or `Some(id)`), and the
/// other fields as ` name=value`.
#[derive(Default)]
struct Fields {
    message: String,
    job_id: Option<u32>,
    rest: String,
}

impl Visit for Fields {
    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        let text = format!("{value:?}");
        self.record_text(field, text);
    }

    fn record_str(&mut self, field: &Field, value: &str) {
        self.record_text(field, value.to_string());
    }
}

impl Fields {
    fn record_text(&mut self, field: &Field, text: String) {
        match field.name() {
            "message" => self.message = text,
            "job" | "job_id" => {
                let id = text.trim_start_matches("Some(").trim_end_matches(')');
                self.job_id = id.parse().ok();
                if self.job_id.is_none() && text != "None" {
                    let _ = write!(self.rest, " {}={text}", field.name());
                }
            }
            name => {
                let _ = write!(self.rest, " {name}={text}");
            }
        }
    }
}

/// Keep the last [`KEPT`] lines of the feed in `shared.log`, numbered, until edod
/// stops. Lines the task fell behind on (more than the channel holds at once) are
/// counted in a line of their own.
pub async fn keep(shared: Arc<Shared>) {
    let mut rx = feed().subscribe();
    let mut kept: VecDeque<LogLine> = VecDeque::with_capacity(KEPT);
    let mut seq = 0u64;
    loop {
        let line = match rx.recv().await {
            Ok(line) => line,
            Err(broadcast::error::RecvError::Lagged(n)) => LogLine {
                seq: 0,
                at_ms: super::store::now_ms(),
                level: "warn".into(),
                job_id: None,
                message: format!("{n} log lines were not kept (logged faster than kept)"),
            },
            Err(broadcast::error::RecvError::Closed) => return,
        };
        seq += 1;
        if kept.len() == KEPT {
            kept.pop_front();
        }
        kept.push_back(LogLine { seq, ..line });
        shared
            .log
            .send_replace(Arc::new(kept.iter().cloned().collect()));
    }
}

/// The lines kept after sequence number `after` (all kept when `None`).
pub fn recent(log: &watch::Sender<Arc<Vec<LogLine>>>, after: Option<u64>) -> Vec<LogLine> {
    let lines = Arc::clone(&log.borrow());
    let after = after.unwrap_or(0);
    let from = lines.partition_point(|l| l.seq <= after);
    lines[from..].to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracing_subscriber::layer::SubscriberExt;

    #[test]
    fn events_become_lines_with_their_job_and_fields() {
        let mut rx = feed().subscribe();
        let subscriber = tracing_subscriber::registry().with(FeedLayer);
        tracing::subscriber::with_default(subscriber, || {
            tracing::info!(job = 7u32, moves = 12, "job 7 done");
            tracing::warn!(job = ?Some(3u32), text = %"Error:Printer halted", "firmware error");
            tracing::debug!("not kept: below info");
        });
        let a = rx.try_recv().unwrap();
        assert_eq!((a.level.as_str(), a.job_id), ("info", Some(7)));
        assert_eq!(a.message, "job 7 done moves=12");
        let b = rx.try_recv().unwrap();
        assert_eq!((b.level.as_str(), b.job_id), ("warn", Some(3)));
        assert_eq!(b.message, "firmware error text=Error:Printer halted");
        assert!(rx.try_recv().is_err());
    }

    #[test]
    fn recent_gives_the_lines_after_a_number() {
        let line = |seq| LogLine {
            seq,
            at_ms: 0,
            level: "info".into(),
            job_id: None,
            message: String::new(),
        };
        let log = watch::channel(Arc::new((5..=9).map(line).collect::<Vec<_>>())).0;
        assert_eq!(recent(&log, None).len(), 5);
        assert_eq!(
            recent(&log, Some(7))
                .iter()
                .map(|l| l.seq)
                .collect::<Vec<_>>(),
            vec![8, 9]
        );
        assert!(recent(&log, Some(9)).is_empty());
        assert_eq!(recent(&log, Some(1)).len(), 5);
    }
}
