//! edoctl's daemon subcommands (`submit`, `jobs`, `status`, `watch`, `pause`, `resume`,
//! `cancel`, `delete`, `estop`, `refill`): a blocking JSON-RPC client of edod's socket
//! (`docs/api.md`) that reads each result into its type from [`crate::proto`]. Output is a
//! short human line, or the daemon's JSON with `--json`.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde::Deserialize;
use serde_json::Value;

use crate::link::MachineState;
use crate::proto::{
    method, ApiError, Event, Id, Job, JobIdParams, JobState, JobStateChanged, Method, NoParams,
    Notification, Progress, Request, Response, StateChange, SubmitParams,
};

/// Default socket of an installed edod.
pub const DEFAULT_SOCKET: &str = "/run/edo/edod.sock";

/// How long a call edod answers -32005 (job store busy: another process holds its
/// write lock) is tried again before the error is shown.
pub const STORE_BUSY_RETRY: Duration = Duration::from_secs(30);
/// The pause between those tries.
const STORE_BUSY_PAUSE: Duration = Duration::from_millis(200);

/// A connection to edod.
pub struct Client {
    socket: PathBuf,
    reader: BufReader<UnixStream>,
    writer: UnixStream,
    next_id: u64,
}

/// An error edod returned, shown as the daemon wrote it.
#[derive(Debug, thiserror::Error)]
#[error("edod: {message}")]
pub struct DaemonError {
    /// JSON-RPC code.
    pub code: i64,
    /// Message.
    pub message: String,
}

impl From<ApiError> for DaemonError {
    fn from(e: ApiError) -> DaemonError {
        DaemonError {
            code: e.code,
            message: e.message,
        }
    }
}

/// A method's result read into its type, and as the daemon sent it (what `--json`
/// prints, keys a newer daemon adds included).
#[derive(Debug, Clone)]
pub struct Answer<T> {
    /// The result.
    pub result: T,
    /// The result's JSON.
    pub json: Value,
}

/// A line from the daemon.
enum Incoming {
    /// The answer to a request.
    Response(Response<Value>),
    /// A notification (`None`: one edoctl does not know).
    Notification(Option<Event>),
}

impl Client {
    /// Connect to `socket`.
    pub fn connect(socket: &Path) -> Result<Client> {
        let s = UnixStream::connect(socket).with_context(|| {
            format!(
                "cannot connect to edod at {} (is edod running? pick another one with --socket)",
                socket.display()
            )
        })?;
        s.set_read_timeout(Some(Duration::from_secs(60)))?;
        Ok(Client {
            socket: socket.to_path_buf(),
            reader: BufReader::new(s.try_clone()?),
            writer: s,
            next_id: 1,
        })
    }

    /// Next line from the daemon.
    fn read_incoming(&mut self) -> Result<Incoming> {
        let mut l = String::new();
        if self.reader.read_line(&mut l)? == 0 {
            bail!("edod at {} closed the connection", self.socket.display());
        }
        let line = l.trim_end();
        let v: Value = serde_json::from_str(line)
            .with_context(|| format!("edod sent a line that is not JSON: {line}"))?;
        if v.get("id").is_some() {
            let r = Response::deserialize(&v).with_context(|| {
                format!("edod sent a response that is not JSON-RPC 2.0: {line}")
            })?;
            return Ok(Incoming::Response(r));
        }
        let method = v.get("method").and_then(Value::as_str);
        if !method.is_some_and(|m| Event::METHODS.contains(&m)) {
            return Ok(Incoming::Notification(None));
        }
        let n = Notification::deserialize(&v).with_context(|| {
            format!("edod sent a notification that is not what docs/api.md says: {line}")
        })?;
        Ok(Incoming::Notification(Some(n.event)))
    }

    /// The next notification edoctl knows (after `subscribe`), skipping other lines.
    pub fn next_event(&mut self) -> Result<Event> {
        loop {
            if let Incoming::Notification(Some(e)) = self.read_incoming()? {
                return Ok(e);
            }
        }
    }

    /// Call `method` with `params` as they are; the result as sent. Notifications
    /// arriving meanwhile are skipped. A call answered -32005 (job store busy, nothing
    /// done) is tried again for up to [`STORE_BUSY_RETRY`], saying so on stderr once.
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value> {
        let started = Instant::now();
        let mut told = false;
        loop {
            match self.call_once(method, params.clone()) {
                Err(e) if is_store_busy(&e) && started.elapsed() < STORE_BUSY_RETRY => {
                    if !told {
                        told = true;
                        eprintln!(
                            "edoctl: edod's job store is busy (another process holds the write \
                             lock of edod.db); trying again for up to {} s",
                            STORE_BUSY_RETRY.as_secs()
                        );
                    }
                    std::thread::sleep(STORE_BUSY_PAUSE);
                }
                r => return r,
            }
        }
    }

    fn call_once(&mut self, method: &str, params: Value) -> Result<Value> {
        let id = self.next_id;
        self.next_id += 1;
        let request = Request::new(Some(Id::from(id)), method, Some(params));
        let line = serde_json::to_string(&request)?;
        self.writer.write_all(format!("{line}\n").as_bytes())?;
        loop {
            if let Incoming::Response(r) = self.read_incoming()? {
                return r.into_result().map_err(|e| DaemonError::from(e).into());
            }
        }
    }

    /// Call method `M`; its result read into its type.
    pub fn request<M: Method>(&mut self, params: &M::Params) -> Result<Answer<M::Result>> {
        let json = self.call(M::NAME, serde_json::to_value(params)?)?;
        let result = M::Result::deserialize(&json).with_context(|| {
            format!(
                "edod's result of {} is not what docs/api.md says: {json}",
                M::NAME
            )
        })?;
        Ok(Answer { result, json })
    }

    /// `job.get`.
    pub fn job(&mut self, id: u32) -> Result<Answer<Job>> {
        self.request::<method::JobGet>(&JobIdParams { id })
    }
}

/// Whether `e` is edod's -32005 (job store busy, retry).
pub fn is_store_busy(e: &anyhow::Error) -> bool {
    e.downcast_ref::<DaemonError>()
        .is_some_and(|d| d.code == ApiError::STORE_BUSY)
}

/// The line `edoctl pause` or `resume` prints (`done`: "paused", "resumed").
pub fn applied_line(r: &StateChange, done: &str) -> String {
    let mut line = format!("job {} {done}", r.id);
    if !r.stored {
        line.push_str(" (not on disk yet: the job store is busy; it is written once free)");
    }
    line
}

/// The params of `job.submit` for a job file: its text, and its mesh (`[geometry] mesh`,
/// relative to the job file) as base64.
pub fn submit_params(job: &Path) -> Result<SubmitParams> {
    let meta = std::fs::metadata(job)
        .with_context(|| format!("cannot read job file {}", job.display()))?;
    if meta.len() > super::plan::MAX_JOB_BYTES {
        bail!(
            "job file {} is over {} bytes",
            job.display(),
            super::plan::MAX_JOB_BYTES
        );
    }
    let text = std::fs::read_to_string(job)
        .with_context(|| format!("cannot read job file {}", job.display()))?;
    let parsed: toml::Table =
        toml::from_str(&text).with_context(|| format!("{} is not TOML", job.display()))?;
    let mut mesh_base64 = None;
    if let Some(mesh) = parsed
        .get("geometry")
        .and_then(|g| g.get("mesh"))
        .and_then(|m| m.as_str())
    {
        let path = job.parent().unwrap_or(Path::new(".")).join(mesh);
        let bytes =
            std::fs::read(&path).with_context(|| format!("cannot read mesh {}", path.display()))?;
        mesh_base64 = Some(crate::proto::mesh_bytes::base64_encode(&bytes));
    }
    Ok(SubmitParams::file(text, mesh_base64))
}

/// One line about a job.
pub fn job_line(j: &Job) -> String {
    let total = j.total_moves.map_or("?".to_string(), |t| t.to_string());
    let mut s = format!(
        "{:>4}  {:<11}  {:>7}/{:<7}  {}",
        j.id,
        j.state.as_str(),
        j.checkpoint.next_index,
        total,
        j.name
    );
    if let Some(r) = &j.reason {
        s.push_str(&format!("  ({r})"));
    }
    s
}

/// The machine's state as `machine.status` names it.
pub fn machine_state_name(s: MachineState) -> &'static str {
    match s {
        MachineState::Idle => "Idle",
        MachineState::Running => "Running",
        MachineState::Held => "Held",
        MachineState::EStopped => "EStopped",
        MachineState::Faulted => "Faulted",
    }
}

/// A layer number for people: layer `l` (0-based) of `count` is `l + 1` of them.
fn layer_of(layer: Option<u32>, count: Option<u32>) -> Option<String> {
    let l = u64::from(layer?) + 1;
    Some(match count {
        Some(n) => format!("layer {l} of {n}"),
        None => format!("layer {l}"),
    })
}

/// Seconds left, as people read them.
fn eta_text(s: f64) -> String {
    let s = s.max(0.0).round() as u64;
    match s {
        0..=99 => format!("{s} s"),
        100..=5999 => format!("{} min", (s + 30) / 60),
        _ => {
            let min = (s + 30) / 60;
            format!("{} h {:02} min", min / 60, min % 60)
        }
    }
}

/// One line about the active job's progress (`machine.status` / `job.get` `progress`):
/// moves executed (of how many, once every move is planned), layer of layers, ETA.
pub fn progress_line(p: &Progress) -> String {
    let (id, executed) = (p.job_id, p.executed);
    let mut s = match p.total {
        Some(t) => format!("job {id}: {executed} of {t} moves executed"),
        None => {
            format!("job {id}: {executed} moves executed (total known once every layer is planned)")
        }
    };
    if let Some(l) = layer_of(p.layer, p.layers) {
        s.push_str(&format!(", {l}"));
    }
    if let (Some(pc), Some(t)) = (p.percent, p.planned_s) {
        s.push_str(&format!(", {pc:.0} % of {} planned", eta_text(t)));
    }
    if let Some(e) = p.eta_s {
        s.push_str(&format!(", about {} left", eta_text(e)));
    }
    s
}

/// How long `edoctl cancel` waits for a printing job to stop, retract and park.
pub const CANCEL_WAIT: Duration = Duration::from_secs(30);

/// Cancel job `id` and wait (up to `wait`) until it is cancelled: a printing job stays
/// `printing` while the machine stops, retracts and parks (about a second). Returns the
/// job; an error if it has not ended by then.
pub fn cancel(client: &mut Client, id: u32, wait: Duration) -> Result<Answer<Job>> {
    let mut state = client
        .request::<method::JobCancel>(&JobIdParams { id })?
        .result
        .state;
    let started = std::time::Instant::now();
    loop {
        if !state.is_final() {
            if started.elapsed() >= wait {
                bail!(
                    "job {id} is still {} {} s after the cancel (the machine has not confirmed \
                     the stop); 'edoctl watch {id}' follows it",
                    state.as_str(),
                    wait.as_secs()
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let job = client.job(id)?;
        if job.result.state.is_final() {
            return Ok(job);
        }
        state = job.result.state;
    }
}

/// The line `edoctl cancel` prints for the job it cancelled.
pub fn cancelled_line(j: &Job) -> String {
    let mut line = format!("job {} {}", j.id, j.state.as_str());
    let executed = j.checkpoint.next_index;
    if executed > 0 {
        line.push_str(&format!(" after {executed} moves"));
    }
    let extra = j
        .reason
        .as_deref()
        .filter(|_| j.state == JobState::Cancelled)
        .and_then(|r| r.strip_prefix("cancelled by an operator; "));
    if let Some(extra) = extra {
        line.push_str(&format!("; {extra}"));
    }
    line
}

/// Watch job `id` with a progress bar until it is done, failed or cancelled; returns its
/// final state.
pub fn watch(client: &mut Client, id: u32, json_out: bool) -> Result<Answer<Job>> {
    // Subscribed before the job is read, so no state change falls between the two.
    client.request::<method::Subscribe>(&NoParams {})?;
    let job = client.job(id)?.result;
    let bar = JobBar::new(&job, json_out);
    let mut state = job.state;
    while !state.is_final() {
        match client.next_event()? {
            Event::JobProgress(p) if p.job_id == id => bar.show(&p),
            Event::JobState(s) if s.job_id == id => {
                state = s.state;
                if !state.is_final() {
                    bar.bar.println(state_change_line(&s));
                }
            }
            _ => {}
        }
    }
    bar.bar.finish_and_clear();
    client.job(id)
}

/// A line about a job's state change (`notify_job_state`) while it is watched.
fn state_change_line(s: &JobStateChanged) -> String {
    let reason = s
        .reason
        .as_ref()
        .map_or(String::new(), |r| format!(" ({r})"));
    format!("job {}: {}{reason}", s.job_id, s.state.as_str())
}

/// The progress bar of `edoctl watch`: a bar once the move total is known; until then a
/// count (a bar of unknown length would show full, or empty, whatever the progress).
struct JobBar {
    bar: indicatif::ProgressBar,
}

impl JobBar {
    fn with_length() -> indicatif::ProgressStyle {
        indicatif::ProgressStyle::with_template(
            "{spinner} job {prefix} [{bar:30}] {pos}/{len} moves {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> ")
    }

    fn counting() -> indicatif::ProgressStyle {
        indicatif::ProgressStyle::with_template("{spinner} job {prefix} {pos} moves {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner())
    }

    /// A bar for `job` where it stands now; drawn nowhere with `--json`.
    fn new(job: &Job, json_out: bool) -> JobBar {
        use indicatif::ProgressBar;
        let bar = match job.total_moves {
            Some(t) => ProgressBar::new(u64::from(t)).with_style(Self::with_length()),
            None => ProgressBar::no_length().with_style(Self::counting()),
        };
        if json_out {
            bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
        }
        bar.set_prefix(job.id.to_string());
        bar.set_position(u64::from(job.checkpoint.next_index));
        JobBar { bar }
    }

    /// Moves executed, and layer, composition and time left as the message.
    fn show(&self, p: &Progress) {
        if let Some(t) = p.total.map(u64::from) {
            if self.bar.length() != Some(t) {
                self.bar.set_length(t);
                self.bar.set_style(Self::with_length());
            }
        }
        self.bar.set_position(u64::from(p.executed));
        let comp = p
            .composition
            .as_ref()
            .map(|c| {
                c.iter()
                    .map(|x| format!("{x:.2}"))
                    .collect::<Vec<_>>()
                    .join("/")
            })
            .unwrap_or_default();
        let eta = p
            .eta_s
            .map_or(String::new(), |e| format!(", about {} left", eta_text(e)));
        let layer = layer_of(p.layer, p.layers).map_or(String::new(), |l| format!("{l}, "));
        self.bar
            .set_message(format!("{layer}composition {comp}{eta}"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::proto::Checkpoint;

    fn job(id: u32, state: JobState, reason: Option<&str>, next_index: u32) -> Job {
        Job {
            id,
            name: "tooth-crown".into(),
            state,
            reason: reason.map(str::to_string),
            total_moves: None,
            checkpoint: Checkpoint {
                next_index,
                ..Checkpoint::default()
            },
            submitted_ms: 0,
            started_ms: None,
            ended_ms: None,
            updated_ms: 0,
            progress: None,
        }
    }

    #[test]
    fn cancelled_line_says_where_the_job_stopped_and_what_was_left_undone() {
        let cancelled = JobState::Cancelled;
        let parked = job(4, cancelled, Some("cancelled by an operator"), 1201);
        assert_eq!(cancelled_line(&parked), "job 4 cancelled after 1201 moves");
        let lost = job(
            4,
            cancelled,
            Some("cancelled by an operator; not parked: link to the machine lost"),
            1201,
        );
        assert_eq!(
            cancelled_line(&lost),
            "job 4 cancelled after 1201 moves; not parked: link to the machine lost"
        );
        let queued = job(5, cancelled, Some("cancelled by an operator"), 0);
        assert_eq!(cancelled_line(&queued), "job 5 cancelled");
        // It finished before the cancel took.
        let done = job(6, JobState::Done, None, 300);
        assert_eq!(cancelled_line(&done), "job 6 done after 300 moves");
    }

    #[test]
    fn progress_reads_as_people_count() {
        let progress = |job_id, executed, total, layers, layer, eta_s| Progress {
            job_id,
            executed,
            total,
            layers,
            layer,
            eta_s,
            ..Progress::default()
        };
        assert_eq!(
            progress_line(&progress(1, 891, None, Some(2), Some(0), None)),
            "job 1: 891 moves executed (total known once every layer is planned), layer 1 of 2"
        );
        assert_eq!(
            progress_line(&progress(
                3,
                1201,
                Some(48210),
                Some(12),
                Some(3),
                Some(412.5)
            )),
            "job 3: 1201 of 48210 moves executed, layer 4 of 12, about 7 min left"
        );
        // A mesh job before its mesh is sliced: no layer count, no layer yet.
        assert_eq!(
            progress_line(&progress(4, 0, None, None, None, None)),
            "job 4: 0 moves executed (total known once every layer is planned)"
        );
    }

    /// A daemon on a socket in `dir` that answers one request with `lines`.
    fn fake_daemon(dir: &Path, lines: &'static [&'static str]) -> std::thread::JoinHandle<()> {
        let listener = std::os::unix::net::UnixListener::bind(dir.join("edod.sock")).unwrap();
        std::thread::spawn(move || {
            let (mut s, _) = listener.accept().unwrap();
            let mut request = String::new();
            BufReader::new(s.try_clone().unwrap())
                .read_line(&mut request)
                .unwrap();
            for l in lines {
                s.write_all(format!("{l}\n").as_bytes()).unwrap();
            }
        })
    }

    #[test]
    fn results_are_read_into_their_types_past_notifications() {
        let dir = tempfile::tempdir().unwrap();
        let daemon = fake_daemon(
            dir.path(),
            &[
                r#"{"jsonrpc":"2.0","method":"notify_something_new","params":[1]}"#,
                r#"{"jsonrpc":"2.0","method":"notify_job_state","params":{"job_id":1,"state":"done","reason":null}}"#,
                r#"{"jsonrpc":"2.0","id":1,"result":{"id":1,"state":"paused","stored":true}}"#,
            ],
        );
        let mut c = Client::connect(&dir.path().join("edod.sock")).unwrap();
        let r = c
            .request::<method::JobPause>(&JobIdParams { id: 1 })
            .unwrap();
        assert_eq!(r.result.state, JobState::Paused);
        // `--json` shows what the daemon sent, keys edoctl does not know included.
        assert_eq!(r.json["stored"], serde_json::json!(true));
        daemon.join().unwrap();
    }

    #[test]
    fn a_busy_store_is_tried_again_and_other_errors_are_not() {
        let dir = tempfile::tempdir().unwrap();
        let listener =
            std::os::unix::net::UnixListener::bind(dir.path().join("edod.sock")).unwrap();
        let daemon = std::thread::spawn(move || {
            let (s, _) = listener.accept().unwrap();
            let mut r = BufReader::new(s.try_clone().unwrap());
            let mut w = s;
            let mut asked = Vec::new();
            for reply in [
                r#"{"jsonrpc":"2.0","id":1,"error":{"code":-32005,"message":"job store busy, retry"}}"#,
                r#"{"jsonrpc":"2.0","id":2,"error":{"code":-32005,"message":"job store busy, retry"}}"#,
                r#"{"jsonrpc":"2.0","id":3,"result":{"id":9,"state":"queued"}}"#,
                r#"{"jsonrpc":"2.0","id":4,"error":{"code":-32001,"message":"no job 9"}}"#,
            ] {
                let mut l = String::new();
                r.read_line(&mut l).unwrap();
                asked.push(l);
                w.write_all(format!("{reply}\n").as_bytes()).unwrap();
            }
            asked
        });
        let mut c = Client::connect(&dir.path().join("edod.sock")).unwrap();
        let t = Instant::now();
        let r = c
            .request::<method::JobSubmit>(&SubmitParams::dry_run(5))
            .unwrap();
        assert_eq!(r.result.id, 9);
        assert!(t.elapsed() >= 2 * STORE_BUSY_PAUSE, "{:?}", t.elapsed());
        let e = c.job(9).unwrap_err();
        assert!(!is_store_busy(&e));
        assert_eq!(e.to_string(), "edod: no job 9");
        let asked = daemon.join().unwrap();
        assert!(
            asked[..3].iter().all(|l| l.contains("job.submit")),
            "{asked:?}"
        );
    }

    #[test]
    fn a_result_not_as_documented_is_an_error_naming_the_method() {
        let dir = tempfile::tempdir().unwrap();
        let daemon = fake_daemon(
            dir.path(),
            &[r#"{"jsonrpc":"2.0","id":1,"result":{"job_id":5,"executed":"many"}}"#],
        );
        let mut c = Client::connect(&dir.path().join("edod.sock")).unwrap();
        let e = c
            .request::<method::MachineStatus>(&NoParams {})
            .unwrap_err();
        let e = format!("{e:#}");
        assert!(
            e.starts_with("edod's result of machine.status is not what docs/api.md says"),
            "{e}"
        );
        daemon.join().unwrap();
    }

    #[test]
    fn job_lines_line_up() {
        let a = Job {
            total_moves: Some(7721),
            ..job(1, JobState::Done, None, 7721)
        };
        let b = Job {
            name: "bunny".into(),
            ..job(12, JobState::Failed, Some("the mesh is open"), 0)
        };
        let (a, b) = (job_line(&a), job_line(&b));
        assert_eq!(a, "   1  done            7721/7721     tooth-crown");
        assert_eq!(
            b,
            "  12  failed             0/?        bunny  (the mesh is open)"
        );
        assert_eq!(a.find('/'), b.find('/'));
    }

    #[test]
    fn time_left_in_seconds_minutes_or_hours() {
        assert_eq!(eta_text(42.4), "42 s");
        assert_eq!(eta_text(-3.0), "0 s");
        assert_eq!(eta_text(412.5), "7 min");
        assert_eq!(eta_text(7170.0), "2 h 00 min");
        assert_eq!(eta_text(5.0 * 3600.0 + 7.0 * 60.0), "5 h 07 min");
    }
}
