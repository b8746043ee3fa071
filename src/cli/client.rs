//! edoctl's daemon subcommands (`submit`, `jobs`, `status`, `watch`, `pause`, `resume`,
//! `cancel`, `delete`, `estop`, `refill`): a blocking JSON-RPC client of edod's socket
//! (`docs/api.md`). Output is a short human line, or the daemon's JSON with `--json`.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use serde_json::{json, Value};

/// Default socket of an installed edod.
pub const DEFAULT_SOCKET: &str = "/run/edo/edod.sock";

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
    pub fn read_line(&mut self) -> Result<Value> {
        let mut l = String::new();
        if self.reader.read_line(&mut l)? == 0 {
            bail!("edod at {} closed the connection", self.socket.display());
        }
        serde_json::from_str(&l).with_context(|| format!("edod sent a line that is not JSON: {l}"))
    }

    /// Call `method`; notifications arriving meanwhile go to `on_note`.
    pub fn call_with(
        &mut self,
        method: &str,
        params: Value,
        on_note: &mut dyn FnMut(&Value),
    ) -> Result<Value> {
        let id = self.next_id;
        self.next_id += 1;
        let line = json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params});
        self.writer.write_all(format!("{line}\n").as_bytes())?;
        loop {
            let v = self.read_line()?;
            if v.get("id").is_none() {
                on_note(&v);
                continue;
            }
            if let Some(e) = v.get("error") {
                return Err(DaemonError {
                    code: e["code"].as_i64().unwrap_or(0),
                    message: e["message"].as_str().unwrap_or("unknown error").to_string(),
                }
                .into());
            }
            return Ok(v["result"].clone());
        }
    }

    /// Call `method`.
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value> {
        self.call_with(method, params, &mut |_| {})
    }
}

/// The params of `job.submit` for a job file: its text, and its mesh (`[geometry] mesh`,
/// relative to the job file) as base64.
pub fn submit_params(job: &Path) -> Result<Value> {
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
    let mut params = json!({"job": text});
    let parsed: toml::Table =
        toml::from_str(&text).with_context(|| format!("{} is not TOML", job.display()))?;
    if let Some(mesh) = parsed
        .get("geometry")
        .and_then(|g| g.get("mesh"))
        .and_then(|m| m.as_str())
    {
        let path = job.parent().unwrap_or(Path::new(".")).join(mesh);
        let bytes =
            std::fs::read(&path).with_context(|| format!("cannot read mesh {}", path.display()))?;
        params["mesh_base64"] = json!(crate::daemon::api::base64_encode(&bytes));
    }
    Ok(params)
}

/// One line about a job.
pub fn job_line(j: &Value) -> String {
    let total = j["total_moves"]
        .as_u64()
        .map_or("?".to_string(), |t| t.to_string());
    // Numbers as strings: a JSON value's Display ignores width and alignment.
    let number = |v: &Value| v.as_u64().map_or("?".to_string(), |n| n.to_string());
    let mut s = format!(
        "{:>4}  {:<11}  {:>7}/{:<7}  {}",
        number(&j["id"]),
        j["state"].as_str().unwrap_or("?"),
        number(&j["checkpoint"]["next_index"]),
        total,
        j["name"].as_str().unwrap_or("")
    );
    if let Some(r) = j["reason"].as_str() {
        s.push_str(&format!("  ({r})"));
    }
    s
}

/// A layer number for people: layer `l` (0-based) of `count` is `l + 1` of them.
fn layer_of(layer: Option<u64>, count: Option<u64>) -> Option<String> {
    let l = layer? + 1;
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
pub fn progress_line(p: &Value) -> String {
    let executed = p["executed"].as_u64().unwrap_or(0);
    let mut s = match p["total"].as_u64() {
        Some(t) => format!("job {}: {executed} of {t} moves executed", p["job_id"]),
        None => format!(
            "job {}: {executed} moves executed (total known once every layer is planned)",
            p["job_id"]
        ),
    };
    if let Some(l) = layer_of(p["layer"].as_u64(), p["layers"].as_u64()) {
        s.push_str(&format!(", {l}"));
    }
    if let Some(e) = p["eta_s"].as_f64() {
        s.push_str(&format!(", about {} left", eta_text(e)));
    }
    s
}

/// How long `edoctl cancel` waits for a printing job to stop, retract and park.
pub const CANCEL_WAIT: Duration = Duration::from_secs(30);

/// Cancel job `id` and wait (up to `wait`) until it is cancelled: a printing job stays
/// `printing` while the machine stops, retracts and parks (about a second). Returns the
/// job; an error if it has not ended by then.
pub fn cancel(client: &mut Client, id: u64, wait: Duration) -> Result<Value> {
    let r = client.call("job.cancel", json!({"id": id}))?;
    let started = std::time::Instant::now();
    let mut job = if r["state"] == json!("cancelled") {
        client.call("job.get", json!({"id": id}))?
    } else {
        r
    };
    while !matches!(job["state"].as_str(), Some("done" | "failed" | "cancelled")) {
        if started.elapsed() >= wait {
            bail!(
                "job {id} is still {} {} s after the cancel (the machine has not confirmed \
                 the stop); 'edoctl watch {id}' follows it",
                job["state"].as_str().unwrap_or("in an unknown state"),
                wait.as_secs()
            );
        }
        std::thread::sleep(Duration::from_millis(100));
        job = client.call("job.get", json!({"id": id}))?;
    }
    Ok(job)
}

/// The line `edoctl cancel` prints for the job it cancelled.
pub fn cancelled_line(j: &Value) -> String {
    let id = j["id"].as_u64().map_or("?".to_string(), |i| i.to_string());
    let state = j["state"].as_str().unwrap_or("?");
    let mut line = format!("job {id} {state}");
    if let Some(n) = j["checkpoint"]["next_index"].as_u64().filter(|&n| n > 0) {
        line.push_str(&format!(" after {n} moves"));
    }
    if let Some(r) = j["reason"].as_str().filter(|_| state == "cancelled") {
        if let Some(extra) = r.strip_prefix("cancelled by an operator; ") {
            line.push_str(&format!("; {extra}"));
        }
    }
    line
}

/// Watch job `id` with a progress bar until it is done, failed or cancelled; returns its
/// final state.
pub fn watch(client: &mut Client, id: u64, json_out: bool) -> Result<Value> {
    use indicatif::{ProgressBar, ProgressStyle};
    let mut job = client.call("job.get", json!({"id": id}))?;
    client.call("subscribe", json!({}))?;
    // A bar once the move total is known; until then a count (a bar of unknown length
    // would show full, or empty, whatever the progress).
    let with_bar = || {
        ProgressStyle::with_template("{spinner} job {prefix} [{bar:30}] {pos}/{len} moves {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> ")
    };
    let counting = || {
        ProgressStyle::with_template("{spinner} job {prefix} {pos} moves {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_spinner())
    };
    let bar = match job["total_moves"].as_u64() {
        Some(t) => {
            let bar = ProgressBar::new(t);
            bar.set_style(with_bar());
            bar
        }
        None => {
            let bar = ProgressBar::no_length();
            bar.set_style(counting());
            bar
        }
    };
    if json_out {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    bar.set_prefix(id.to_string());
    bar.set_position(job["checkpoint"]["next_index"].as_u64().unwrap_or(0));
    let done = |s: &Value| matches!(s.as_str(), Some("done" | "failed" | "cancelled"));
    while !done(&job["state"]) {
        let v = client.read_line()?;
        let p = &v["params"];
        if p["job_id"].as_u64() != Some(id) {
            continue;
        }
        match v["method"].as_str() {
            Some("notify_job_progress") => {
                if let Some(t) = p["total"].as_u64() {
                    if bar.length() != Some(t) {
                        bar.set_length(t);
                        bar.set_style(with_bar());
                    }
                }
                bar.set_position(p["executed"].as_u64().unwrap_or(0));
                let comp = p["composition"]
                    .as_array()
                    .map(|c| {
                        c.iter()
                            .map(|x| format!("{:.2}", x.as_f64().unwrap_or(0.0)))
                            .collect::<Vec<_>>()
                            .join("/")
                    })
                    .unwrap_or_default();
                let eta = p["eta_s"]
                    .as_f64()
                    .map_or(String::new(), |e| format!(", about {} left", eta_text(e)));
                let layer = layer_of(p["layer"].as_u64(), p["layers"].as_u64())
                    .map_or(String::new(), |l| format!("{l}, "));
                bar.set_message(format!("{layer}composition {comp}{eta}"));
            }
            Some("notify_job_state") => {
                job["state"] = p["state"].clone();
                if !done(&job["state"]) {
                    bar.println(format!(
                        "job {id}: {}{}",
                        p["state"].as_str().unwrap_or("?"),
                        p["reason"]
                            .as_str()
                            .map_or(String::new(), |r| format!(" ({r})"))
                    ));
                }
            }
            _ => {}
        }
    }
    bar.finish_and_clear();
    client.call("job.get", json!({"id": id}))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cancelled_line_says_where_the_job_stopped_and_what_was_left_undone() {
        let parked = json!({"id": 4, "state": "cancelled", "reason": "cancelled by an operator",
            "checkpoint": {"next_index": 1201}});
        assert_eq!(cancelled_line(&parked), "job 4 cancelled after 1201 moves");
        let lost = json!({"id": 4, "state": "cancelled",
            "reason": "cancelled by an operator; not parked: link to the machine lost",
            "checkpoint": {"next_index": 1201}});
        assert_eq!(
            cancelled_line(&lost),
            "job 4 cancelled after 1201 moves; not parked: link to the machine lost"
        );
        let queued = json!({"id": 5, "state": "cancelled", "reason": "cancelled by an operator",
            "checkpoint": {"next_index": 0}});
        assert_eq!(cancelled_line(&queued), "job 5 cancelled");
        // It finished before the cancel took.
        let done = json!({"id": 6, "state": "done", "checkpoint": {"next_index": 300}});
        assert_eq!(cancelled_line(&done), "job 6 done after 300 moves");
    }

    #[test]
    fn progress_reads_as_people_count() {
        let planning = json!({"job_id": 1, "executed": 891, "total": null, "layers": 2,
            "layer": 0, "eta_s": null});
        assert_eq!(
            progress_line(&planning),
            "job 1: 891 moves executed (total known once every layer is planned), layer 1 of 2"
        );
        let planned = json!({"job_id": 3, "executed": 1201, "total": 48210, "layers": 12,
            "layer": 3, "eta_s": 412.5});
        assert_eq!(
            progress_line(&planned),
            "job 3: 1201 of 48210 moves executed, layer 4 of 12, about 7 min left"
        );
        // A mesh job before its mesh is sliced: no layer count, no layer yet.
        let early = json!({"job_id": 4, "executed": 0, "total": null, "layers": null,
            "layer": null, "eta_s": null});
        assert_eq!(
            progress_line(&early),
            "job 4: 0 moves executed (total known once every layer is planned)"
        );
        // Fields of the wrong type (an older or broken daemon) read as unknown.
        let odd = json!({"job_id": 5, "executed": "many", "total": -1, "layers": "x",
            "layer": 2.5, "eta_s": "soon"});
        assert_eq!(
            progress_line(&odd),
            "job 5: 0 moves executed (total known once every layer is planned)"
        );
    }

    #[test]
    fn job_lines_line_up() {
        let a = job_line(
            &json!({"id": 1, "state": "done", "checkpoint": {"next_index": 7721},
            "total_moves": 7721, "name": "tooth-crown", "reason": null}),
        );
        let b = job_line(
            &json!({"id": 12, "state": "failed", "checkpoint": {"next_index": 0},
            "total_moves": null, "name": "bunny", "reason": "the mesh is open"}),
        );
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
