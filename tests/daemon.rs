//! edod end to end against hil-sim over a pty: whole jobs, pause/resume, e-stop, machine
//! reset, SIGKILL of edod with the machine still running, bad requests while streaming,
//! many subscribers. Every test checks the simulator's recorder: each planned move index
//! of the job executed exactly once, in order.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

struct Daemon {
    child: Child,
    socket: PathBuf,
    config: PathBuf,
}

impl Daemon {
    fn start(dir: &Path, port: &Path) -> Daemon {
        Daemon::start_with_limit(dir, port, 4096)
    }

    fn start_with_limit(dir: &Path, port: &Path, max_request_bytes: usize) -> Daemon {
        Daemon::start_keeping(dir, port, max_request_bytes, 1000)
    }

    fn start_keeping(
        dir: &Path,
        port: &Path,
        max_request_bytes: usize,
        keep_finished_jobs: usize,
    ) -> Daemon {
        Daemon::write_config(dir, port, max_request_bytes, keep_finished_jobs, "");
        Daemon::spawn(dir.join("edod.sock"), dir.join("edod.toml"))
    }

    /// `dir/edod.toml`: the machine on `port`, the socket and state in `dir`, `api`
    /// added to the `[api]` table.
    fn write_config(
        dir: &Path,
        port: &Path,
        max_request_bytes: usize,
        keep_finished_jobs: usize,
        api: &str,
    ) {
        std::fs::write(
            dir.join("edod.toml"),
            format!(
                "[serial]\nport = {:?}\n[api]\nsocket = {:?}\nmax_request_bytes = {max_request_bytes}\n{api}\n\
                 [state]\ndir = {:?}\nkeep_finished_jobs = {keep_finished_jobs}\n[planner]\ndry_run_moves_per_layer = 100\n[http]\nenabled = false\n",
                port.display().to_string(),
                dir.join("edod.sock").display().to_string(),
                dir.join("state").display().to_string()
            ),
        )
        .unwrap();
    }

    /// A daemon with `api` added to its `[api]` table.
    fn start_with_api(dir: &Path, port: &Path, max_request_bytes: usize, api: &str) -> Daemon {
        Daemon::write_config(dir, port, max_request_bytes, 1000, api);
        Daemon::spawn(dir.join("edod.sock"), dir.join("edod.toml"))
    }

    fn spawn(socket: PathBuf, config: PathBuf) -> Daemon {
        Daemon::spawn_with(socket, config, None)
    }

    fn spawn_with(socket: PathBuf, config: PathBuf, notify: Option<&Path>) -> Daemon {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_edod"));
        if let Some(n) = notify {
            cmd.env("NOTIFY_SOCKET", n).env("WATCHDOG_USEC", "400000");
        }
        let child = cmd
            .arg("--config")
            .arg(&config)
            // EDOD_TEST_LOG=debug (any RUST_LOG filter) to see more of edod's log.
            .env(
                "RUST_LOG",
                std::env::var("EDOD_TEST_LOG").unwrap_or_else(|_| "warn".into()),
            )
            .stdin(Stdio::null())
            .spawn()
            .unwrap();
        Daemon::ready(child, socket, config)
    }

    /// A started edod, once its socket answers.
    fn ready(child: Child, socket: PathBuf, config: PathBuf) -> Daemon {
        let d = Daemon {
            child,
            socket,
            config,
        };
        let t = Instant::now();
        while UnixStream::connect(&d.socket).is_err() {
            assert!(t.elapsed() < Duration::from_secs(20), "edod did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        d
    }

    fn client(&self) -> Client {
        let s = UnixStream::connect(&self.socket).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        Client {
            r: BufReader::new(s.try_clone().unwrap()),
            w: s,
            next: 1,
        }
    }

    /// Run edoctl against this daemon.
    fn edoctl<S: AsRef<std::ffi::OsStr>>(&self, args: impl IntoIterator<Item = S>) -> Output {
        Command::new(env!("CARGO_BIN_EXE_edoctl"))
            .arg("--socket")
            .arg(&self.socket)
            .args(args)
            .output()
            .unwrap()
    }

    /// Run edoctl against this daemon, check it succeeded, and return what it printed.
    fn edoctl_ok<S: AsRef<std::ffi::OsStr>>(&self, args: impl IntoIterator<Item = S>) -> Vec<u8> {
        let out = self.edoctl(args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        out.stdout
    }

    fn sigterm(&mut self) -> std::process::ExitStatus {
        nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(self.child.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        )
        .unwrap();
        self.child.wait().unwrap()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        // A test failing on a closed connection: say whether edod had ended (and how)
        // or was still running, i.e. closed that connection itself.
        if std::thread::panicking() {
            match self.child.try_wait() {
                Ok(Some(status)) => eprintln!("edod {} had ended: {status}", self.child.id()),
                Ok(None) => eprintln!("edod {} was still running", self.child.id()),
                Err(e) => eprintln!("edod {}: {e}", self.child.id()),
            }
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

struct Client {
    r: BufReader<UnixStream>,
    w: UnixStream,
    next: u64,
}

impl Client {
    fn send_raw(&mut self, line: &str) -> Value {
        self.w.write_all(line.as_bytes()).unwrap();
        self.w.write_all(b"\n").unwrap();
        self.read_reply()
    }

    fn read_reply(&mut self) -> Value {
        loop {
            let mut l = String::new();
            assert!(self.r.read_line(&mut l).unwrap() > 0, "daemon closed");
            let v: Value = serde_json::from_str(&l).unwrap();
            if v.get("method").is_none() {
                return v;
            }
        }
    }

    fn call(&mut self, method: &str, params: Value) -> Result<Value, Value> {
        let id = self.next;
        self.next += 1;
        let v = self.send_raw(
            &json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params}).to_string(),
        );
        assert_eq!(v["id"], json!(id));
        match v.get("error") {
            Some(e) => Err(e.clone()),
            None => Ok(v["result"].clone()),
        }
    }

    fn job(&mut self, id: u64) -> Value {
        self.call("job.get", json!({"id": id})).unwrap()
    }

    fn wait(&mut self, what: &str, mut f: impl FnMut(&mut Client) -> bool) {
        let t = Instant::now();
        while !f(self) {
            assert!(t.elapsed() < Duration::from_secs(60), "timed out: {what}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn wait_state(&mut self, id: u64, state: &str) -> Value {
        let mut last = Value::Null;
        self.wait(&format!("job {id} {state}"), |c| {
            last = c.job(id);
            last["state"] == json!(state)
        });
        last
    }

    fn wait_connected(&mut self) {
        self.wait("machine connected", |c| {
            c.call("machine.status", json!({})).unwrap()["connected"] == json!(true)
        });
    }

    fn executed(&mut self, id: u64) -> u64 {
        self.job(id)["checkpoint"]["next_index"].as_u64().unwrap()
    }
}

fn sim(dir: &Path, seed: u64) -> (hil_sim::SimHandle, PathBuf) {
    sim_at(dir, seed, 50.0)
}

/// A simulator at `speed` (machine time / wall time).
fn sim_at(dir: &Path, seed: u64, speed: f64) -> (hil_sim::SimHandle, PathBuf) {
    let record = dir.join("run.jsonl");
    let h = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.join("tty")),
        speed,
        seed,
        record: Some(record.clone()),
        ..hil_sim::SimConfig::default()
    })
    .unwrap();
    (h, record)
}

/// The simulator recorder's lines for `job` (0: service moves), in execution order.
fn recorded(record: &Path, job: u64) -> Vec<Value> {
    let text = std::fs::read_to_string(record).unwrap();
    text.lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|v| v["job_id"] == json!(job))
        .collect()
}

/// The move indices of `job` the simulator executed, in order.
fn recorded_indices(record: &Path, job: u64) -> Vec<u64> {
    recorded(record, job)
        .iter()
        .map(|v| v["index"].as_u64().unwrap())
        .collect()
}

/// After a machine reset the moves it executed but had not yet reported (at most one
/// status interval of work) are executed again: the reset machine has forgotten them.
/// Check every index 0..total executed, in order, repeats only in one run right after
/// one reset. Returns how many were repeated.
fn assert_all_executed_repeats_only_at_reset(record: &Path, job: u64, total: u64) -> u64 {
    let idx = recorded_indices(record, job);
    let backs: Vec<usize> = (1..idx.len())
        .filter(|&k| idx[k] != idx[k - 1] + 1)
        .collect();
    assert!(backs.len() <= 1, "more than one jump: {backs:?}");
    let mut seen = std::collections::BTreeSet::new();
    seen.extend(idx.iter().copied());
    assert_eq!(seen.len() as u64, total, "every move executed");
    assert_eq!(idx.first(), Some(&0));
    assert_eq!(idx.last(), Some(&(total - 1)));
    idx.len() as u64 - total
}

/// Executed indices of `job` from the recorder, checked to be 0..total each exactly once
/// and in order.
fn assert_exactly_once(record: &Path, job: u64, total: u64) {
    let order = recorded_indices(record, job);
    let mut seen: BTreeMap<u64, u32> = BTreeMap::new();
    for &i in &order {
        *seen.entry(i).or_default() += 1;
    }
    let dup: Vec<_> = seen.iter().filter(|(_, &n)| n > 1).collect();
    assert!(dup.is_empty(), "moves executed twice: {dup:?}");
    assert_eq!(seen.len() as u64, total, "moves executed");
    assert!(order.windows(2).all(|w| w[0] + 1 == w[1]), "out of order");
}

/// A daemon on a simulator seeded `seed` in `dir`, streaming a dry run of `moves`
/// (past its 300th move): the simulator, its recorder, the daemon, a client, the job.
fn streaming(
    dir: &Path,
    seed: u64,
    moves: u32,
) -> (hil_sim::SimHandle, PathBuf, Daemon, Client, u64) {
    streaming_at(dir, seed, 50.0, moves, 300)
}

/// As [`streaming`], the simulator at `speed`, past move `past`.
fn streaming_at(
    dir: &Path,
    seed: u64,
    speed: f64,
    moves: u32,
    past: u64,
) -> (hil_sim::SimHandle, PathBuf, Daemon, Client, u64) {
    streaming_with_limit(dir, (seed, speed), moves, past, 4096)
}

/// [`streaming_at`] with requests of up to `max_request_bytes`.
fn streaming_with_limit(
    dir: &Path,
    (seed, speed): (u64, f64),
    moves: u32,
    past: u64,
    max_request_bytes: usize,
) -> (hil_sim::SimHandle, PathBuf, Daemon, Client, u64) {
    let (sim, record) = sim_at(dir, seed, speed);
    let d = Daemon::start_with_limit(dir, sim.path(), max_request_bytes);
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, moves);
    c.wait("streaming", |c| c.executed(a) > past);
    (sim, record, d, c, a)
}

fn submit(c: &mut Client, moves: u32) -> u64 {
    c.call("job.submit", json!({"dry_run_moves": moves}))
        .unwrap()["id"]
        .as_u64()
        .unwrap()
}

#[test]
fn whole_job_then_pause_resume_and_bad_requests_while_streaming() {
    let dir = tempfile::tempdir().unwrap();
    // 5 ms a move (see the SIGKILL test): "no underrun" is asserted at the end.
    let (sim, record) = sim_at(dir.path(), 1, 20.0);
    let d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    c.wait_connected();
    let info = c.call("server.info", json!({})).unwrap();
    assert_eq!(info["name"], json!("edod"));

    // A whole job: executed == planned.
    let a = submit(&mut c, 1000);
    let j = c.wait_state(a, "done");
    assert_eq!(j["total_moves"], json!(1000));
    assert_eq!(j["checkpoint"]["next_index"], json!(1000));

    // Second job: bad requests of every kind while it streams, and pause/resume.
    let b = submit(&mut c, 2000);
    c.wait("job b streaming", |c| c.executed(b) > 100);
    // Its progress counts layers too: 20 of 100 moves each (layer marks included). The
    // progress is published a little behind the checkpoint: wait for the second layer.
    let mut m = Value::Null;
    c.wait("job b's progress in its second layer", |c| {
        m = c.call("machine.status", json!({})).unwrap();
        m["progress"]["layer"].as_u64() >= Some(1)
    });
    assert_eq!(m["progress"]["layers"], json!(20), "{m}");
    let mut bad = d.client();
    let e = bad.send_raw("{not json");
    assert_eq!(e["error"]["code"], json!(-32700));
    let e = bad.send_raw(&"x".repeat(10_000));
    assert_eq!(e["error"]["code"], json!(-32600));
    let e = bad.send_raw(r#"{"jsonrpc":"1.0","id":1,"method":"server.info"}"#);
    assert_eq!(e["error"]["code"], json!(-32600));
    let e = bad.call("job.frobnicate", json!({})).unwrap_err();
    assert_eq!(e["code"], json!(-32601));
    let e = bad.call("job.get", json!({"id": "seven"})).unwrap_err();
    assert_eq!(e["code"], json!(-32602));
    let e = bad
        .call("job.get", json!({"id": 1, "extra": 2}))
        .unwrap_err();
    assert_eq!(e["code"], json!(-32602));
    let e = bad.call("job.get", json!({"id": 999})).unwrap_err();
    assert_eq!(e["code"], json!(-32001));
    let e = bad
        .call(
            "job.submit",
            json!({"dry_run_moves": 5, "name": "ok\u{1b}[2J\nfake line"}),
        )
        .unwrap_err();
    assert_eq!(e["code"], json!(-32602));
    assert!(
        e["message"]
            .as_str()
            .unwrap()
            .starts_with("name: contains the control"),
        "{e}"
    );
    let e = bad
        .call("job.submit", json!({"job": "name = 3"}))
        .unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    let e = bad.call("job.resume", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32002));
    // A client that never reads and then vanishes.
    {
        let mut s = UnixStream::connect(&d.socket).unwrap();
        s.write_all(b"{\"jsonrpc\":\"2.0\",\"id\":1,\"method\":\"subscribe\"}\n")
            .unwrap();
    }

    c.call("job.pause", json!({"id": b})).unwrap();
    let j = c.wait_state(b, "paused");
    std::thread::sleep(Duration::from_millis(300));
    let held_at = c.executed(b);
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(c.executed(b), held_at, "a paused job does not advance");
    assert!(j["checkpoint"]["next_index"].as_u64().unwrap() < 2000);
    c.call("job.resume", json!({"id": b})).unwrap();
    c.wait_state(b, "done");
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["underruns"], json!(0), "{m}");
    drop(c);
    drop(bad);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 1000);
    assert_exactly_once(&record, b, 2000);
}

/// A 1500-move job streaming at 20x (5 ms a move: the machine's queue holds 0.64 s of
/// work), past move 200, and another process (a backup, an operator's sqlite3 shell)
/// holding the job store's write lock: the returned connection, in `BEGIN IMMEDIATE`.
fn streaming_with_the_store_locked(
    dir: &Path,
    seed: u64,
) -> (
    hil_sim::SimHandle,
    PathBuf,
    Daemon,
    Client,
    u64,
    rusqlite::Connection,
) {
    let (sim, record, d, c, a) = streaming_at(dir, seed, 20.0, 1500, 200);
    let db = rusqlite::Connection::open(dir.join("state").join("edod.db")).unwrap();
    db.execute_batch("BEGIN IMMEDIATE").unwrap();
    (sim, record, d, c, a, db)
}

#[test]
fn a_database_locked_by_another_process_does_not_stall_the_moves() {
    let dir = tempfile::tempdir().unwrap();
    // The write lock is held for 1.5 s, while the checkpoints go on falling due every
    // 100 ms.
    let (sim, record, d, mut c, a, db) = streaming_with_the_store_locked(dir.path(), 5);
    let progress = |c: &mut Client| {
        c.call("machine.status", json!({})).unwrap()["progress"]["executed"]
            .as_u64()
            .unwrap_or(0)
    };
    let before = progress(&mut c);
    std::thread::sleep(Duration::from_millis(1500));
    let during = progress(&mut c);
    // job.get is a read: it goes on too (WAL), with the last checkpoint committed.
    let held = c.executed(a);
    db.execute_batch("COMMIT").unwrap();
    assert!(
        during > before + 200,
        "executed {before} -> {during} while locked"
    );
    assert!(
        held <= before + 100,
        "a checkpoint was written through the lock"
    );
    c.wait_state(a, "done");
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["underruns"], json!(0), "{m}");
    assert_eq!(c.executed(a), 1500, "the checkpoints caught up");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 1500);
}

/// A call and how long it took to be answered.
fn timed(
    c: &mut Client,
    worst: &mut Duration,
    method: &str,
    params: Value,
) -> Result<Value, Value> {
    let t = Instant::now();
    let r = c.call(method, params);
    *worst = (*worst).max(t.elapsed());
    r
}

/// Every API call is answered within this, whatever holds the job store.
const API_ANSWER_LIMIT: Duration = Duration::from_millis(100);

#[test]
fn a_store_locked_for_3_s_delays_no_api_call_and_no_move() {
    let dir = tempfile::tempdir().unwrap();
    // 10 ms a move (the machine's queue holds 1.28 s): 2000 moves outlast the lock.
    let (sim, record, d, mut c, a) =
        streaming_with_limit(dir.path(), (12, 10.0), 2000, 100, 64 << 20);
    let db = rusqlite::Connection::open(dir.path().join("state").join("edod.db")).unwrap();
    db.execute_batch("BEGIN EXCLUSIVE").unwrap();
    let locked = Instant::now();
    // Two submissions of 64 MiB in flight meanwhile: parsed and their meshes decoded off
    // the runtime's workers, they delay no other call.
    let big: Vec<_> = (0..2).map(|_| d.client()).map(big_submission).collect();
    let mut worst = Duration::ZERO;
    let w = &mut worst;
    let executed = |c: &mut Client, w: &mut Duration| {
        timed(c, w, "machine.status", json!({})).unwrap()["progress"]["executed"]
            .as_u64()
            .unwrap_or(0)
    };
    let before = executed(&mut c, w);
    // A submission cannot be stored: answered "busy, retry" with nothing done.
    let e = timed(&mut c, w, "job.submit", json!({"dry_run_moves": 300})).unwrap_err();
    assert_eq!(e["code"], json!(-32005), "{e}");
    // Pause and resume take effect at once; their state is not on disk yet.
    let r = timed(&mut c, w, "job.pause", json!({"id": a})).unwrap();
    assert_eq!(r, json!({"id": a, "state": "paused", "stored": false}));
    std::thread::sleep(Duration::from_millis(400));
    let held = executed(&mut c, w);
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(executed(&mut c, w), held, "the machine holds");
    // Reads answer with what is on disk: still printing.
    let j = timed(&mut c, w, "job.get", json!({"id": a})).unwrap();
    assert_eq!(j["state"], json!("printing"), "{j}");
    let r = timed(&mut c, w, "job.resume", json!({"id": a})).unwrap();
    assert_eq!(r, json!({"id": a, "state": "printing", "stored": false}));
    // The operator retries the submission (as edoctl does) while the lock lasts.
    let mut busy = 1;
    let mut db = Some(db);
    let b = loop {
        if locked.elapsed() >= Duration::from_secs(3) {
            if let Some(db) = db.take() {
                db.execute_batch("COMMIT").unwrap();
            }
        }
        match timed(&mut c, w, "job.submit", json!({"dry_run_moves": 300})) {
            Ok(r) => break r["id"].as_u64().unwrap(),
            Err(e) => {
                assert_eq!(e["code"], json!(-32005), "{e}");
                busy += 1;
            }
        }
        let l = timed(&mut c, w, "job.list", json!({})).unwrap();
        assert!(l.as_array().is_some_and(|l| l.len() == 1), "{l}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let unlocked_after = locked.elapsed();
    assert!(
        unlocked_after >= Duration::from_secs(3),
        "{unlocked_after:?}"
    );
    let during = executed(&mut c, w);
    assert!(
        during > before + 100,
        "executed {before} -> {during} while locked"
    );
    c.wait_state(a, "done");
    c.wait_state(b, "done");
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["underruns"], json!(0), "{m}");
    eprintln!(
        "store locked {unlocked_after:?}: {busy} submissions answered busy, worst API \
         answer {worst:?}"
    );
    assert!(
        worst < API_ANSWER_LIMIT,
        "an API call took {worst:?} while the store was locked"
    );
    for h in big {
        let e = h.join().unwrap();
        // Read and decoded whole: refused for what the job is, not for its shape.
        assert_eq!(e["code"], json!(-32003), "{e}");
        assert!(
            e["message"].as_str().unwrap_or("").contains("not a mesh"),
            "{e}"
        );
    }
    // Large lines that are wrong, read on the blocking pool: each answered as a small
    // one would be, and edod serves on.
    let mb = "x".repeat(1 << 20);
    let e = c.send_raw(&format!(
        "{{\"jsonrpc\":\"2.0\",\"id\":90,\"method\":\"{mb}"
    ));
    assert_eq!(e["error"]["code"], json!(-32700), "{e}");
    let e = c.call("job.frobnicate", json!({"pad": mb})).unwrap_err();
    assert_eq!(e["code"], json!(-32601), "{e}");
    let e = c
        .call(
            "job.submit",
            json!({"job": SQUARE_JOB, "mesh_base64": format!("{mb}!")}),
        )
        .unwrap_err();
    assert_eq!(e["code"], json!(-32602), "{e}");
    assert!(
        e["message"].as_str().unwrap_or("").contains("not base64"),
        "{e}"
    );
    c.call("machine.status", json!({})).unwrap();
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 2000);
    assert_exactly_once(&record, b, 300);
}

/// Two materials graded in growth rings, on edod's default machine: the rest of a job
/// file after its geometry.
macro_rules! graded_two_materials {
    () => {
        r#"[materials]
names = ["A", "B"]
[gradient]
pattern = "growth-rings"
inner = [1.0, 0.0]
outer = [0.0, 1.0]
[process]
r_mach = 0.8
nozzle = 0.4
layer = 0.2
"#
    };
}

/// A polygon job edod plans on its default machine.
const SQUARE_JOB: &str = concat!(
    "name = \"graded square\"\n[geometry]\n",
    "polygon = { outer = { rect = { min = [0.0, 0.0], max = [3.0, 3.0] } } }\n",
    "height = 0.4\n",
    graded_two_materials!()
);

/// A `job.submit` line of almost 64 MiB (a polygon job with a mesh's base64, which
/// edod decodes before it refuses the pair), sent on its own thread; its error.
fn big_submission(mut c: Client) -> std::thread::JoinHandle<Value> {
    std::thread::spawn(move || {
        let mesh = "QUJD".repeat((63 << 20) / 4);
        let params = json!({"job": SQUARE_JOB, "mesh_base64": mesh});
        c.call("job.submit", params).unwrap_err()
    })
}

/// Architecture invariant: no SQLite on a tokio runtime worker. The store's threads are
/// the only SQLite callers: nothing outside `src/daemon/store/` names rusqlite or opens
/// a store (and the store refuses to run on a runtime thread, see its unit tests).
#[test]
fn sqlite_is_called_by_the_store_threads_alone() {
    fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                rust_files(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let store = src.join("daemon").join("store");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    assert!(files.len() > 20, "{files:?}");
    let outside: Vec<_> = files
        .iter()
        .filter(|f| !f.starts_with(&store))
        .filter(|f| {
            let text = std::fs::read_to_string(f).unwrap();
            text.contains("rusqlite") || text.contains("Store::open")
        })
        .collect();
    assert!(outside.is_empty(), "SQLite outside the store: {outside:?}");
}

#[test]
fn estop_and_machine_reset_then_resume_from_first_move_not_executed() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, a) = streaming(dir.path(), 2, 3000);
    let t = c.call("machine.estop", json!({})).unwrap();
    assert!(t["written_after_us"].as_u64().is_some(), "{t}");
    eprintln!("e-stop timing: {t}");
    // The machine's acknowledgement bounds when the e-stop reached it: within 50 ms.
    let acked = t["acked_after_us"].as_u64().expect("e-stop acknowledged");
    assert!(acked <= 50_000, "e-stop acknowledged after {acked} µs");
    let j = c.wait_state(a, "interrupted");
    assert!(j["reason"].as_str().unwrap().contains("emergency stop"));
    c.call("job.resume", json!({"id": a})).unwrap();
    c.wait("streaming again", |c| c.executed(a) > 1500);
    let before_reset = c.executed(a);
    sim.command(hil_sim::Command::Reset);
    let j = c.wait_state(a, "interrupted");
    assert!(j["reason"].as_str().unwrap().contains("reset"), "{j}");
    c.wait_connected();
    c.call("job.resume", json!({"id": a})).unwrap();
    c.wait_state(a, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let repeated = assert_all_executed_repeats_only_at_reset(&record, a, 3000);
    eprintln!("moves repeated after the reset at {before_reset}: {repeated}");
    assert!(repeated <= 100, "{repeated} moves repeated");
}

#[test]
fn sigkill_of_edod_with_the_machine_running_loses_and_repeats_nothing() {
    let dir = tempfile::tempdir().unwrap();
    // 10 ms a move: the machine's 128-move queue holds 1.28 s, so "no underrun" measures
    // the daemon and not how long a loaded 2-core CI box deschedules it (at 50x a move
    // is 2 ms and any 0.26 s stall of the process empties the queue; at 20x, 0.64 s,
    // one run in a full suite on a loaded machine counted an underrun).
    let (sim, record) = sim_at(dir.path(), 3, 10.0);
    let mut d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 1200);
    c.wait("streaming", |c| c.executed(a) > 500);
    d.child.kill().unwrap(); // SIGKILL
    d.child.wait().unwrap();
    drop(c);
    std::thread::sleep(Duration::from_millis(300));
    // The restarted edod talks to systemd: READY, STATUS, WATCHDOG.
    let notify_path = dir.path().join("notify.sock");
    let notify = std::os::unix::net::UnixDatagram::bind(&notify_path).unwrap();
    notify
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut d2 = Daemon::spawn_with(d.socket.clone(), d.config.clone(), Some(&notify_path));
    let mut seen = String::new();
    let mut buf = [0u8; 512];
    while !(seen.contains("READY=1") && seen.contains("WATCHDOG=1") && seen.contains("STATUS=")) {
        let n = notify.recv(&mut buf).unwrap();
        seen.push_str(&String::from_utf8_lossy(&buf[..n]));
        seen.push('\n');
    }
    let mut c = d2.client();
    c.wait_connected();
    let j = c.wait_state(a, "interrupted");
    assert_eq!(j["reason"], json!("edod restarted"));
    c.call("job.resume", json!({"id": a})).unwrap();
    c.wait_state(a, "done");

    // 50 subscribers while a job streams; then SIGTERM stops cleanly.
    let mut subs: Vec<Client> = (0..50).map(|_| d2.client()).collect();
    for s in &mut subs {
        s.call("subscribe", json!({})).unwrap();
    }
    let b = submit(&mut c, 600);
    c.wait_state(b, "done");
    for s in &mut subs {
        let mut l = String::new();
        s.r.read_line(&mut l).unwrap();
        assert!(l.contains("notify_"), "{l}");
    }
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["underruns"], json!(0), "{m}");
    drop(subs);
    drop(c);
    assert!(d2.sigterm().success());
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 1200);
    assert_exactly_once(&record, b, 600);
}

#[test]
fn syringe_empty_pauses_until_refill() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, a) = streaming(dir.path(), 4, 2000);
    sim.command(hil_sim::Command::Empty(1));
    let j = c.wait_state(a, "paused");
    assert!(
        j["reason"].as_str().unwrap().contains("syringe 1 (B)"),
        "{j}"
    );
    let e = c.call("job.resume", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32002));
    c.call("machine.refill", json!({})).unwrap();
    c.wait_state(a, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 2000);
}

#[test]
fn check_config_reports_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("bad.toml");
    std::fs::write(&f, "[serial]\nport = \"sim\"\nspeed = 3\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_edod"))
        .arg("--check-config")
        .arg(&f)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.toml:3:1"), "{err}");
    let ok = Command::new(env!("CARGO_BIN_EXE_edod"))
        .arg("--check-config")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/edod.toml"))
        .output()
        .unwrap();
    assert!(ok.status.success());
}

/// The shipped G-code configurations pass `edod --check-config`; an impossible
/// combination is refused naming its key (docs/firmware.md, "Configuration").
#[test]
fn shipped_gcode_configs_pass_check_config() {
    let check = |path: &Path| {
        Command::new(env!("CARGO_BIN_EXE_edod"))
            .arg("--check-config")
            .arg(path)
            .output()
            .unwrap()
    };
    for f in [
        "config/edod-rrf.toml",
        "config/edod-marlin.toml",
        "config/edod-klipper.toml",
    ] {
        let out = check(&Path::new(env!("CARGO_MANIFEST_DIR")).join(f));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{f}: {err}");
    }
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("rrf-window.toml");
    std::fs::write(
        &f,
        "[machine]\nprotocol = \"gcode\"\n[machine.gcode]\nfirmware = \"rrf\"\nwindow = 4\n",
    )
    .unwrap();
    let out = check(&f);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("machine.gcode.window"), "{err}");
}

#[test]
fn edoctl_submits_watches_and_shows_daemon_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim(dir.path(), 5);
    let d = Daemon::start(dir.path(), sim.path());
    d.client().wait_connected();
    let edoctl = |args: &[&str]| d.edoctl(args);
    let out = d.edoctl_ok(["submit", "--dry-run-moves", "300", "--watch", "--json"]);
    let j: Value = serde_json::from_slice(&out).unwrap();
    assert_eq!(j["state"], json!("done"));
    assert_eq!(j["checkpoint"]["next_index"], json!(300));
    let out = edoctl(&["jobs"]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("done"));
    let out = edoctl(&["resume", "99"]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("edod: no job 99"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = Command::new(env!("CARGO_BIN_EXE_edoctl"))
        .args(["--socket", "/nonexistent/edod.sock", "status"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("is edod running?"));
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, 1, 300);
}

#[test]
fn cancel_stops_retracts_and_parks() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim(dir.path(), 6);
    let d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 3000);
    let queued = submit(&mut c, 100);
    c.call("job.cancel", json!({"id": queued})).unwrap();
    assert_eq!(c.job(queued)["state"], json!("cancelled"));
    c.wait("streaming", |c| c.executed(a) > 300);
    // edoctl cancel returns once the job is cancelled (stopped, then parking).
    let out = d.edoctl_ok(["cancel", &a.to_string()]);
    let j = c.job(a);
    assert_eq!(j["state"], json!("cancelled"), "{j}");
    let stopped_at = j["checkpoint"]["next_index"].as_u64().unwrap();
    assert_eq!(
        String::from_utf8_lossy(&out).trim(),
        format!("job {a} cancelled after {stopped_at} moves")
    );
    assert!(stopped_at < 3000);
    c.wait("parked", |c| {
        let m = c.call("machine.status", json!({})).unwrap();
        m["state"] == json!("Idle") && m["position_mm"] == json!([0.0, 0.0, 50.0])
    });
    let e = c.call("job.cancel", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32002));
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_eq!(
        recorded_indices(&record, a),
        (0..stopped_at).collect::<Vec<_>>()
    );
    assert!(recorded(&record, queued).is_empty());
    let service: Vec<Value> = recorded(&record, 0)
        .iter()
        .map(|v| v["kind"].clone())
        .collect();
    assert_eq!(service, ["retract", "travel", "travel"]);
}

#[test]
fn cancel_ends_the_job_when_the_link_is_lost_before_the_park() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, a) = streaming(dir.path(), 7, 3000);
    // The machine stops answering, so the cancel's e-stop is never acknowledged.
    sim.command(hil_sim::Command::Stall(4000));
    let r = c.call("job.cancel", json!({"id": a})).unwrap();
    // The reply names the state the cancel leads to; it is stored once the job ends.
    assert_eq!(r["state"], json!("cancelled"), "{r}");
    assert_eq!(r["stored"], json!(false), "{r}");
    let j = c.wait_state(a, "cancelled");
    let reason = j["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("cancelled by an operator; not parked: link"),
        "{reason}"
    );
    // It stays cancelled once the machine answers again, and nothing else starts.
    c.wait_connected();
    assert_eq!(c.job(a)["state"], json!("cancelled"));
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let idx = recorded_indices(&record, a);
    assert!(idx.len() < 3000);
    assert_eq!(idx, (0..idx.len() as u64).collect::<Vec<_>>());
}

#[test]
fn edod_stopped_during_a_cancel_leaves_the_job_cancelled_across_the_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, mut d, mut c, a) = streaming(dir.path(), 11, 3000);
    sim.command(hil_sim::Command::Stall(3000));
    c.call("job.cancel", json!({"id": a})).unwrap();
    drop(c);
    assert!(d.sigterm().success());
    let d2 = Daemon::spawn(d.socket.clone(), d.config.clone());
    let mut c = d2.client();
    let j = c.job(a);
    assert_eq!(j["state"], json!("cancelled"), "{j}");
    // The stalled machine's link is declared lost (1.5 s) before edod's 2 s stop
    // deadline; had it answered without confirming the e-stop, the reason would be
    // "edod stopped".
    let reason = j["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("cancelled by an operator; not parked: "),
        "{reason}"
    );
    // Nothing resumes it once the machine answers again.
    c.wait_connected();
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(c.job(a)["state"], json!("cancelled"));
    assert_eq!(
        c.call("machine.status", json!({})).unwrap()["active_job"],
        Value::Null
    );
    drop(c);
    drop(d2);
    drop(d);
    sim.stop().unwrap();
    let idx = recorded_indices(&record, a);
    assert_eq!(idx, (0..idx.len() as u64).collect::<Vec<_>>());
}

#[test]
fn moves_a_cancel_could_not_stop_are_stopped_when_the_machine_is_back() {
    let dir = tempfile::tempdir().unwrap();
    // At 2x a dry-run move takes 50 ms: the machine's 128 queued moves outlast the
    // unplug (1 s) and the reconnection.
    let (sim, _record, d, mut c, a) = streaming_at(dir.path(), 8, 2.0, 3000, 30);
    sim.command(hil_sim::Command::Unplug);
    c.call("job.cancel", json!({"id": a})).unwrap();
    c.wait_state(a, "cancelled");
    c.wait_connected();
    let mut last = Value::Null;
    c.wait("the machine stopped", |c| {
        last = c.call("machine.status", json!({})).unwrap();
        last["state"] != json!("Running")
    });
    // Stopped by edod's e-stop, not by running out of moves.
    assert_eq!(last["state"], json!("EStopped"), "{last}");
    // The next job starts from a clean machine.
    let b = submit(&mut c, 20);
    c.wait_state(b, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

#[test]
fn unplugged_cable_mid_job_resumes_without_losing_or_repeating_a_move() {
    let dir = tempfile::tempdir().unwrap();
    // At 5x (20 ms a move) the machine is still running its queue when the port is back.
    let (sim, record, d, mut c, a) = streaming_at(dir.path(), 9, 5.0, 600, 50);
    sim.command(hil_sim::Command::Unplug);
    let j = c.wait_state(a, "interrupted");
    assert_eq!(j["reason"], json!("serial port lost"), "{j}");
    c.wait_connected();
    c.call("job.resume", json!({"id": a})).unwrap();
    c.wait_state(a, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 600);
}

#[test]
fn finished_jobs_are_deleted_on_request_and_beyond_the_newest_kept() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 10);
    let d = Daemon::start_keeping(dir.path(), sim.path(), 4096, 2);
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 3000);
    c.wait("streaming", |c| c.executed(a) > 50);
    let e = c.call("job.delete", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32002));
    assert!(
        e["message"].as_str().unwrap().contains("is printing"),
        "{e}"
    );
    let out = d.edoctl(["delete", &a.to_string()]);
    assert!(!out.status.success());
    // Nor printed again before it is finished.
    let e = c.call("job.reprint", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32002), "{e}");
    let e = c.call("job.reprint", json!({"id": 999})).unwrap_err();
    assert_eq!(e["code"], json!(-32001), "{e}");
    // Progress by planned machine time, once edod has planned the job whole: 3000
    // moves of 0.1 s, the ETA what is left of them at the pace measured.
    c.wait("the planned time", |c| {
        c.call("machine.status", json!({})).unwrap()["progress"]["planned_s"].is_number()
    });
    let p = c.call("machine.status", json!({})).unwrap()["progress"].clone();
    let planned_s = p["planned_s"].as_f64().unwrap();
    assert!((290.0..=310.0).contains(&planned_s), "{p}");
    let percent = p["percent"].as_f64().unwrap();
    let executed = p["executed"].as_f64().unwrap();
    assert!((percent - 100.0 * executed / 3000.0).abs() < 1.0, "{p}");
    assert_eq!(
        p["total"],
        json!(3000),
        "the total known from the plan: {p}"
    );
    assert!(p["eta_s"].as_f64().unwrap() > 0.0, "{p}");
    let e = c.call("job.delete", json!({"id": 999})).unwrap_err();
    assert_eq!(e["code"], json!(-32001));
    let e = c.call("job.delete", json!({"id": "one"})).unwrap_err();
    assert_eq!(e["code"], json!(-32602));
    let e = c.call("job.delete", json!({})).unwrap_err();
    assert_eq!(e["code"], json!(-32602));
    d.edoctl_ok(["cancel", &a.to_string()]);
    let out = d.edoctl_ok(["delete", &a.to_string()]);
    assert_eq!(
        String::from_utf8_lossy(&out).trim(),
        format!("job {a} deleted")
    );
    let e = c.call("job.get", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32001));
    // Three more finished jobs: each submission keeps the newest two finished.
    let mut done = Vec::new();
    for _ in 0..3 {
        let b = submit(&mut c, 20);
        c.wait_state(b, "done");
        done.push(b);
    }
    let q = submit(&mut c, 3000);
    let ids: Vec<u64> = c
        .call("job.list", json!({}))
        .unwrap()
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_u64().unwrap())
        .collect();
    assert_eq!(ids, [done[1], done[2], q]);
    // The history of a finished job: when it started and ended, what it used.
    let j = c.call("job.get", json!({"id": done[2]})).unwrap();
    let (started, ended) = (
        j["started_ms"].as_i64().unwrap(),
        j["ended_ms"].as_i64().unwrap(),
    );
    assert!(
        started >= j["submitted_ms"].as_i64().unwrap() && ended >= started,
        "{j}"
    );
    assert_eq!(
        j["checkpoint"]["used_nl"],
        json!([0, 0]),
        "a dry run extrudes nothing: {j}"
    );
    // Printed again from what edod stored: a new job of the same name.
    let out = d.edoctl_ok(["reprint", &done[2].to_string()]);
    let said = String::from_utf8_lossy(&out).trim().to_string();
    let again: u64 = said
        .rsplit(' ')
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{said}"));
    assert_eq!(said, format!("job {} queued again as job {again}", done[2]));
    let r = c.call("job.get", json!({"id": again})).unwrap();
    assert_eq!(r["name"], j["name"]);
    assert!(r["ended_ms"].is_null(), "{r}");
    c.call("job.cancel", json!({"id": again})).unwrap();
    // edod's log, numbered, the lines of a job naming it.
    let lines = c.call("log.recent", json!({})).unwrap();
    let lines = lines.as_array().unwrap();
    assert!(
        lines.iter().any(
            |l| l["job_id"] == json!(a) && l["message"].as_str().unwrap().contains("cancelled")
        ),
        "{lines:?}"
    );
    let last = lines.last().unwrap()["seq"].as_u64().unwrap();
    let after = c.call("log.recent", json!({"after": last - 1})).unwrap();
    assert_eq!(after.as_array().unwrap().len(), 1, "{after}");
    // Wrong params are refused, naming what is wrong; edod goes on.
    for bad in [
        json!({"after": -1}),
        json!({"after": "3"}),
        json!({"since": 3}),
        json!([1]),
    ] {
        let e = c.call("log.recent", bad.clone()).unwrap_err();
        assert_eq!(e["code"], json!(-32602), "{bad}: {e}");
    }
    for bad in [
        json!({}),
        json!({"id": "one"}),
        json!({"id": 1, "extra": 2}),
    ] {
        let e = c.call("job.reprint", bad.clone()).unwrap_err();
        assert_eq!(e["code"], json!(-32602), "{bad}: {e}");
    }
    // Unfinished jobs (the queued one) are never pruned.
    c.call("job.cancel", json!({"id": q})).unwrap();
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// A mesh as binary STL bytes.
fn stl_of(mesh: &edo::mesh::Mesh) -> Vec<u8> {
    mesh.to_binary_stl().unwrap()
}

/// A graded tube (STL) as a mesh job: sent over the socket with its mesh by `edoctl submit`,
/// sliced and planned by edod as it streams; the machine executes exactly the moves the
/// same job plans offline, each once and in order. Bad meshes are refused at submission.
#[test]
fn mesh_job_streams_exactly_the_planned_moves() {
    let dir = tempfile::tempdir().unwrap();
    let stl = stl_of(&edo::mesh::primitives::tube(4.0, 8.0, 0.8, 64));
    std::fs::write(dir.path().join("tube.stl"), &stl).unwrap();
    let job_toml = concat!(
        "name = \"graded tube\"\n[geometry]\nmesh = \"tube.stl\"\n",
        graded_two_materials!()
    );
    let job_path = dir.path().join("tube.toml");
    std::fs::write(&job_path, job_toml).unwrap();

    let (sim, record) = sim(dir.path(), 7);
    let d = Daemon::start_with_limit(dir.path(), sim.path(), 1 << 20);
    let mut c = d.client();
    c.wait_connected();
    // Refused at submission: a mesh job without its mesh, a mesh that is not one.
    let e = c.call("job.submit", json!({"job": job_toml})).unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    assert!(
        e["message"].as_str().unwrap().contains("mesh_base64"),
        "{e}"
    );
    let e = c
        .call(
            "job.submit",
            json!({"job": job_toml, "mesh_base64": "c29saWQgeAplbmRzb2xpZCB4Cg=="}),
        )
        .unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    assert!(e["message"].as_str().unwrap().contains("tube.stl"), "{e}");
    // Refused at submission: parts that do not fit the 200 x 200 x 150 mm build volume.
    let wide = job_toml.replace(
        "mesh = \"tube.stl\"",
        "polygon = { outer = { rect = { min = [0.0, 0.0], max = [300.0, 20.0] } } }\nheight = 0.4",
    );
    let e = c.call("job.submit", json!({"job": wide})).unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    assert!(
        e["message"]
            .as_str()
            .unwrap()
            .contains("100.0 mm too wide along x"),
        "{e}"
    );
    // Refused at submission: more materials than the machine has syringes.
    let three = wide
        .replace("max = [300.0, 20.0]", "max = [20.0, 20.0]")
        .replace("names = [\"A\", \"B\"]", "names = [\"A\", \"B\", \"C\"]")
        .replace("inner = [1.0, 0.0]", "inner = [1.0, 0.0, 0.0]")
        .replace("outer = [0.0, 1.0]", "outer = [0.0, 0.5, 0.5]");
    let e = c.call("job.submit", json!({"job": three})).unwrap_err();
    assert_eq!(e["code"], json!(-32003), "{e}");
    assert!(
        e["message"]
            .as_str()
            .unwrap()
            .contains("3 materials (A, B, C) but the machine has 2 syringes (A, B)"),
        "{e}"
    );
    // Refused at submission: materials in none of the machine's syringes (A, B),
    // rather than titanium pushed from whichever syringe comes first.
    let ti_ha = wide
        .replace("max = [300.0, 20.0]", "max = [20.0, 20.0]")
        .replace("names = [\"A\", \"B\"]", "names = [\"Ti\", \"HA\"]");
    assert!(ti_ha.contains("Ti"));
    let e = c.call("job.submit", json!({"job": ti_ha})).unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    assert!(
        e["message"]
            .as_str()
            .unwrap()
            .contains("the machine has no syringe \"Ti\" for material \"Ti\""),
        "{e}"
    );
    let tall = stl_of(&edo::mesh::primitives::tube(4.0, 8.0, 160.0, 16));
    let e = c
        .call(
            "job.submit",
            json!({"job": job_toml, "mesh_base64": edo::proto::mesh_bytes::base64_encode(&tall)}),
        )
        .unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    let msg = e["message"].as_str().unwrap();
    assert!(
        msg.contains("tube.stl") && msg.contains("10.0 mm too tall along z"),
        "{e}"
    );

    let out = d.edoctl_ok([
        "submit".as_ref(),
        "--watch".as_ref(),
        "--json".as_ref(),
        job_path.as_os_str(),
    ]);
    let j: Value = serde_json::from_slice(&out).unwrap();
    assert_eq!(j["state"], json!("done"), "{j}");
    let id = j["id"].as_u64().unwrap();
    let total = j["total_moves"].as_u64().unwrap();
    drop(c);
    drop(d);
    sim.stop().unwrap();

    // The same job planned offline, for the machine edod was configured with.
    let machine = edo::setup::MachineConfig::default();
    let mut src =
        edo::daemon::planner::JobSource::new(job_toml, Some(&stl), "tube", &machine).unwrap();
    let mut planned = Vec::new();
    while let Some(layer) = edo::daemon::planner::LayerSource::next_layer(&mut src) {
        planned.extend(layer.unwrap());
    }
    assert_eq!(planned.len() as u64, total);
    assert!(planned.len() > 100, "{} moves", planned.len());
    assert_exactly_once(&record, id, total);
    let executed = recorded(&record, id);
    let mut extrusions = 0;
    for (m, e) in planned.iter().zip(&executed) {
        assert_eq!(e["index"], json!(m.index));
        if let edo::machine::MoveKind::Extrude { to, volumes_nl, .. } = &m.kind {
            extrusions += 1;
            assert_eq!(e["kind"], json!("extrude"), "move {}", m.index);
            assert_eq!(e["volumes_nl"], json!(volumes_nl), "move {}", m.index);
            let at = [to.x_um, to.y_um, to.z_um].map(|v| v as f64 / 1000.0);
            for k in 0..3 {
                let got = e["to_mm"][k].as_f64().unwrap();
                assert!(
                    (got - at[k]).abs() < 1e-6,
                    "move {}: {got} vs {}",
                    m.index,
                    at[k]
                );
            }
        }
    }
    assert!(extrusions > 50, "{extrusions} extrusions");
    // Built mid-bed: the tube (outer radius 8 mm about the origin) centred at (100, 100).
    let xs: Vec<f64> = executed
        .iter()
        .filter(|e| e["kind"] == json!("extrude"))
        .map(|e| e["to_mm"][0].as_f64().unwrap())
        .collect();
    assert!(xs.iter().all(|x| (91.9..=108.1).contains(x)), "{xs:?}");
}

/// Run a second edod with `config` that must refuse to start: it exits at once,
/// non-zero; what it printed.
fn refused_to_start(config: &Path) -> String {
    let mut child = Command::new(env!("CARGO_BIN_EXE_edod"))
        .arg("--config")
        .arg(config)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > Duration::from_secs(10) {
            let _ = child.kill();
            panic!("the second edod did not exit");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let out = child.wait_with_output().unwrap();
    assert!(!status.success(), "the second edod exited {status}");
    eprintln!("second edod refused after {:?}", t.elapsed());
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A second edod on the same state directory (same config, or another socket) or on
/// the same socket (another state directory) exits at once naming the running one,
/// having touched nothing: the first's job goes on and finishes, every move exactly
/// once, and no job was marked interrupted.
#[test]
fn a_second_edod_on_the_same_state_or_socket_refuses_and_touches_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, a) = streaming_at(dir.path(), 11, 20.0, 1500, 100);
    let pid = format!("pid {}", d.child.id());
    let socket = d.socket.display().to_string();
    let text = std::fs::read_to_string(&d.config).unwrap();
    let other_socket = dir.path().join("other.sock");
    let other_state = dir.path().join("other-state");
    let configs = [
        ("same config", text.clone()),
        (
            "another socket",
            text.replace(&socket, &other_socket.display().to_string()),
        ),
        (
            "another state dir",
            text.replace(
                &dir.path().join("state").display().to_string(),
                &other_state.display().to_string(),
            ),
        ),
    ];
    for (what, body) in configs {
        let f = dir.path().join("second.toml");
        std::fs::write(&f, &body).unwrap();
        let err = refused_to_start(&f);
        assert!(
            err.contains("another edod") && err.contains(&pid) && err.contains(&socket),
            "{what}: {err}"
        );
        assert_eq!(c.job(a)["state"], json!("printing"), "{what}");
    }
    assert!(!other_socket.exists(), "the second edod bound its socket");
    c.wait_state(a, "done");
    let jobs = c.call("job.list", json!({})).unwrap();
    assert_eq!(jobs.as_array().map(Vec::len), Some(1), "{jobs}");
    assert_eq!(jobs[0]["reason"], Value::Null, "{jobs}");
    let lock = std::fs::read_to_string(dir.path().join("state").join("edod.lock")).unwrap();
    assert!(lock.starts_with(&format!("{pid}\n")), "{lock}");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 1500);
}

/// While a job prints, the machine's snapshot follows it: `machine.status` carries the
/// nozzle's position (not 0, 0, 0), and subscribers get `notify_machine_state` as it
/// moves, at most 4 a second (a dashboard's machine panel shows the position from them).
#[test]
fn the_machine_snapshot_follows_the_print() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim_at(dir.path(), 17, 10.0);
    let d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    c.wait_connected();
    let mut sub = d.client();
    sub.call("subscribe", json!({})).unwrap();
    let a = submit(&mut c, 3000);
    c.wait("streaming", |c| c.executed(a) > 20);
    let status = c.call("machine.status", json!({})).unwrap();
    let at: Vec<f64> = serde_json::from_value(status["position_mm"].clone()).unwrap();
    assert!(at.iter().any(|&v| v != 0.0), "{status}");
    // Three seconds of notifications while it prints.
    let t = Instant::now();
    let mut seen = Vec::new();
    while t.elapsed() < Duration::from_secs(3) {
        let mut l = String::new();
        assert!(sub.r.read_line(&mut l).unwrap() > 0, "daemon closed");
        let v: Value = serde_json::from_str(&l).unwrap();
        if v["method"] == json!("notify_machine_state") {
            seen.push((t.elapsed(), v["params"].clone()));
        }
    }
    assert_eq!(c.job(a)["state"], json!("printing"), "printed too fast");
    let positions: std::collections::BTreeSet<String> = seen
        .iter()
        .map(|(_, p)| p["position_mm"].to_string())
        .collect();
    let executed: Vec<u64> = seen
        .iter()
        .filter_map(|(_, p)| p["executed_total"].as_u64())
        .collect();
    assert!(positions.len() >= 2, "the position pushed: {positions:?}");
    assert!(
        executed.windows(2).all(|w| w[0] <= w[1])
            && executed
                .iter()
                .collect::<std::collections::BTreeSet<_>>()
                .len()
                >= 8,
        "moves executed pushed: {executed:?}"
    );
    // At most 4 a second, and a few for changes of state.
    assert!(seen.len() <= 3 * 4 + 3, "{} pushes in 3 s", seen.len());
    drop(sub);
    c.call("job.cancel", json!({"id": a})).unwrap();
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// The dashboard's port taken by another program: edod refuses to start, naming
/// `[http] listen` and the address, exits non-zero, and has not opened the job store
/// (its file is byte for byte as it was; the job stored before is there after). With
/// `[http] enabled = false` it starts on the same host as before.
#[test]
fn a_taken_dashboard_port_refuses_the_start_and_leaves_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 16);
    let mut d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 50);
    c.wait_state(a, "done");
    drop(c);
    assert!(d.sigterm().success());
    let db = dir.path().join("state").join("edod.db");
    let before = std::fs::read(&db).unwrap();
    let held = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = held.local_addr().unwrap().to_string();
    let text = std::fs::read_to_string(&d.config).unwrap();
    let taken = text.replace(
        "[http]\nenabled = false\n",
        &format!("[http]\nlisten = {addr:?}\n"),
    );
    assert_ne!(taken, text);
    std::fs::write(&d.config, &taken).unwrap();
    let said = refused_to_start(&d.config);
    assert!(
        said.contains(&format!("[http] listen = \"{addr}\": cannot bind {addr}"))
            && said.contains("enabled = false"),
        "{said}"
    );
    assert!(
        std::fs::read(&db).unwrap() == before,
        "the store was touched"
    );
    assert!(!d.socket.exists(), "the refused edod bound its socket");
    // The dashboard off, the same edod starts and has the job.
    std::fs::write(&d.config, &text).unwrap();
    let d = Daemon::spawn(d.socket.clone(), d.config.clone());
    let mut c = d.client();
    assert_eq!(c.job(a)["state"], json!("done"));
    drop(held);
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// edod's peak resident memory (VmHWM), bytes.
fn peak_memory(d: &Daemon) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{}/status", d.child.id())).unwrap();
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap();
    kb * 1024
}

/// A reply line read from `s` within `timeout`, or None at end of stream.
fn read_line_within(s: &UnixStream, timeout: Duration) -> Option<Value> {
    s.set_read_timeout(Some(timeout)).unwrap();
    let mut l = String::new();
    let n = BufReader::new(s).read_line(&mut l).unwrap();
    (n > 0).then(|| serde_json::from_str(&l).unwrap())
}

/// 300 connections that send nothing, in a burst, take every ordinary slot (256) and the
/// control slots: an operator's status and e-stop still get in at once (it takes the place of the oldest idle
/// control connection) and is answered at once; an ordinary request on that connection
/// is refused naming the limit.
#[test]
fn three_hundred_idle_clients_do_not_lock_out_the_estop() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, a) = streaming_at(dir.path(), 12, 20.0, 3000, 100);
    let idle: Vec<UnixStream> = (0..300)
        .map(|_| UnixStream::connect(&d.socket).unwrap())
        .collect();
    // At once, with no pause after the burst (the reserve's own burst test is
    // `connections::a_burst_of_control_connections_never_locks_the_last_one_out`).
    let mut times = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        let s = UnixStream::connect(&d.socket).unwrap();
        (&s).write_all(b"{\"jsonrpc\":\"2.0\",\"id\":1,\"method\":\"machine.status\"}\n")
            .unwrap();
        let r = read_line_within(&s, Duration::from_secs(5)).expect("answered");
        times.push(t.elapsed());
        assert!(r["result"]["port"].is_string(), "{r}");
        (&s).write_all(b"{\"jsonrpc\":\"2.0\",\"id\":2,\"method\":\"job.list\"}\n")
            .unwrap();
        let r = read_line_within(&s, Duration::from_secs(5)).expect("answered");
        assert_eq!(r["error"]["code"], json!(-32006), "{r}");
        assert!(
            r["error"]["message"]
                .as_str()
                .unwrap()
                .contains("api.max_clients = 256"),
            "{r}"
        );
    }
    let t = Instant::now();
    let s = UnixStream::connect(&d.socket).unwrap();
    (&s).write_all(b"{\"jsonrpc\":\"2.0\",\"id\":9,\"method\":\"machine.estop\"}\n")
        .unwrap();
    let r = read_line_within(&s, Duration::from_secs(5)).expect("e-stop answered");
    let estop = t.elapsed();
    eprintln!("with 300 idle clients: machine.status {times:?}, machine.estop {estop:?}: {r}");
    assert!(r["result"]["written_after_us"].is_u64(), "{r}");
    assert!(estop < Duration::from_millis(500), "e-stop after {estop:?}");
    drop(idle);
    let j = c.wait_state(a, "interrupted");
    assert!(
        j["reason"].as_str().unwrap().contains("emergency stop"),
        "{j}"
    );
    c.call("job.resume", json!({"id": a})).unwrap();
    c.wait_state(a, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let _ = assert_all_executed_repeats_only_at_reset(&record, a, 3000);
}

/// 20 clients each send half of a 60 MiB request and stop. The ones the memory budget
/// (256 MiB) cannot hold are refused at once naming it; the others are closed after the
/// idle timeout; edod's peak memory stays within the budget and a margin.
#[test]
fn twenty_half_sent_large_requests_stay_within_the_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 13);
    let d = Daemon::start_with_api(dir.path(), sim.path(), 64 << 20, "idle_timeout_s = 4");
    let mut c = d.client();
    c.wait_connected();
    let before = peak_memory(&d);
    let half: Arc<Vec<u8>> = Arc::new({
        let mut v = br#"{"jsonrpc":"2.0","id":1,"method":"job.submit","params":{"job":""#.to_vec();
        v.resize(30 << 20, b'A');
        v
    });
    let t = Instant::now();
    let clients: Vec<_> = (0..20)
        .map(|_| {
            let half = Arc::clone(&half);
            let socket = d.socket.clone();
            std::thread::spawn(move || {
                let s = UnixStream::connect(socket).unwrap();
                // edod may close before the write ends: on a loaded machine 600 MiB
                // from 20 clients can take longer than the idle timeout, and closing a
                // client that is still sending then is the limit doing its work (its
                // reply is written first and is read below).
                let _ = (&s).write_all(&half);
                let r = read_line_within(&s, Duration::from_secs(30));
                (r, t.elapsed())
            })
        })
        .collect();
    let replies: Vec<(Option<Value>, Duration)> =
        clients.into_iter().map(|h| h.join().unwrap()).collect();
    let peak = peak_memory(&d);
    let mut refused = 0;
    let mut timed_out = 0;
    for (r, at) in &replies {
        let r = r.as_ref().expect("a reply before the close");
        assert_eq!(r["error"]["code"], json!(-32006), "{r}");
        let m = r["error"]["message"].as_str().unwrap();
        if m.contains("api.memory_budget_bytes = 256.0 MiB") {
            refused += 1;
            assert!(*at < Duration::from_secs(3), "refused after {at:?}");
        } else {
            assert!(m.contains("api.idle_timeout_s"), "{m}");
            timed_out += 1;
        }
    }
    eprintln!(
        "20 half-sent 60 MiB requests: {refused} refused over the budget, {timed_out} timed \
         out; edod VmHWM {} MiB before, {} MiB after",
        before >> 20,
        peak >> 20
    );
    assert!(refused >= 10, "{refused} refused");
    assert!(
        peak < before + (256 << 20) + (32 << 20),
        "peak {} MiB",
        peak >> 20
    );
    // The budget is free again: the daemon answers (on a new connection: the first one
    // was idle too).
    drop(c);
    let mut c = d.client();
    assert!(c.call("server.info", json!({})).is_ok());
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// A connection that sends nothing, or half a request, is told and closed after
/// `api.idle_timeout_s`; a subscriber waiting for notifications is not idle.
#[test]
fn idle_connections_are_closed_after_the_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 14);
    let d = Daemon::start_with_api(dir.path(), sim.path(), 4096, "idle_timeout_s = 1");
    let mut sub = d.client();
    sub.call("subscribe", json!({})).unwrap();
    for half in ["", "{\"jsonrpc\":\"2.0\","] {
        let t = Instant::now();
        let s = UnixStream::connect(&d.socket).unwrap();
        (&s).write_all(half.as_bytes()).unwrap();
        let r = read_line_within(&s, Duration::from_secs(5)).expect("told why");
        let after = t.elapsed();
        assert!(
            r["error"]["message"]
                .as_str()
                .unwrap()
                .contains("no complete request within 1 s (api.idle_timeout_s)"),
            "{r}"
        );
        assert!(
            read_line_within(&s, Duration::from_secs(5)).is_none(),
            "closed"
        );
        eprintln!("idle connection ({half:?} sent) closed after {after:?}");
        assert!(after >= Duration::from_millis(900) && after < Duration::from_secs(3));
    }
    // The subscriber, idle for over 2 s, still answers; params of the wrong shape are
    // refused naming the method.
    sub.wait_connected();
    for method in ["server.info", "machine.status", "job.list", "job.get"] {
        let e = sub.call(method, json!([])).unwrap_err();
        assert_eq!(e["code"], json!(-32602), "{method}: {e}");
        assert_eq!(
            e["message"],
            json!(format!(
                "params of {method} must be an object (named params, docs/api.md), not an array"
            ))
        );
    }
    drop(sub);
    drop(d);
    sim.stop().unwrap();
}

/// `edod --check-config` refuses what can only fail once edod runs, each naming its
/// key, and warns (passing) about a port that does not exist yet; edod itself refuses
/// the same before it creates anything.
#[test]
fn check_config_catches_what_fails_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let check = |name: &str, text: &str| {
        let f = dir.path().join(name);
        std::fs::write(&f, text).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_edod"))
            .arg("--check-config")
            .arg(&f)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let long = format!("/tmp/{}/edod.sock", "d".repeat(100));
    for (name, text, says) in [
        (
            "group.toml",
            "[api]\ngroup = \"no-such-group-edo\"\n".to_string(),
            "error: api.group: no group \"no-such-group-edo\"",
        ),
        (
            "socket.toml",
            format!("[api]\nsocket = {long:?}\n"),
            "error: api.socket: ",
        ),
        (
            "faults.toml",
            "[sim]\nfaults = \"drop=0.01,frobnicate=1\"\n".to_string(),
            "error: sim.faults: unknown fault \"frobnicate\"",
        ),
        (
            "baud.toml",
            "[serial]\nbaud = 1\n".to_string(),
            "error: serial.baud: 1 is not a line speed",
        ),
    ] {
        let (ok, err) = check(name, &text);
        assert!(!ok && err.contains(says), "{name}: {err}");
        assert!(err.contains(name), "{name}: {err}");
    }
    let (ok, err) = check("port.toml", "[serial]\nport = \"/dev/ttyEDOmissing\"\n");
    assert!(ok, "{err}");
    assert!(
        err.contains("warning: serial.port: port /dev/ttyEDOmissing does not exist"),
        "{err}"
    );
    // edod refuses to start with an unknown fault before it creates its state dir.
    let state = dir.path().join("state");
    let f = dir.path().join("start.toml");
    std::fs::write(
        &f,
        format!(
            "[sim]\nfaults = \"frobnicate=1\"\n[api]\nsocket = {:?}\n[state]\ndir = {:?}\n",
            dir.path().join("s.sock").display().to_string(),
            state.display().to_string()
        ),
    )
    .unwrap();
    let err = refused_to_start(&f);
    assert!(err.contains("sim.faults"), "{err}");
    assert!(!state.exists(), "edod created its state dir");
}

/// With umask 0, the files edod creates are still private: the job database and its
/// -wal and -shm files 0600, the lock files 0640, the state directory 0750.
#[test]
fn files_edod_creates_are_private_whatever_the_umask() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 15);
    Daemon::write_config(dir.path(), sim.path(), 4096, 1000, "");
    let child = Command::new("sh")
        .arg("-c")
        .arg("umask 000; exec \"$0\" --config \"$1\"")
        .arg(env!("CARGO_BIN_EXE_edod"))
        .arg(dir.path().join("edod.toml"))
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    let mut d = Daemon::ready(
        child,
        dir.path().join("edod.sock"),
        dir.path().join("edod.toml"),
    );
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 50);
    c.wait_state(a, "done");
    let state = dir.path().join("state");
    let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    for (file, want) in [
        (state.join("edod.db"), 0o600),
        (state.join("edod.db-wal"), 0o600),
        (state.join("edod.db-shm"), 0o600),
        (state.join("edod.lock"), 0o640),
        (dir.path().join("edod.sock.lock"), 0o640),
        (state.clone(), 0o750),
    ] {
        assert_eq!(mode(&file), want, "{}: {:o}", file.display(), mode(&file));
    }
    assert_eq!(mode(&d.socket), 0o660, "the socket keeps api.mode");
    drop(c);
    assert!(d.sigterm().success());
    sim.stop().unwrap();
}

/// edod on `port` in `dir`, its log (warn and above) written to `dir/edod.log`.
fn daemon_logging_to_file(dir: &Path, port: &Path) -> Daemon {
    Daemon::write_config(dir, port, 4096, 1000, "");
    let log = std::fs::File::create(dir.join("edod.log")).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_edod"))
        .arg("--config")
        .arg(dir.join("edod.toml"))
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();
    Daemon::ready(child, dir.join("edod.sock"), dir.join("edod.toml"))
}

#[test]
fn a_missing_port_is_logged_once_named_in_the_status_and_retried_until_it_appears() {
    let dir = tempfile::tempdir().unwrap();
    let port = dir.path().join("tty");
    let d = daemon_logging_to_file(dir.path(), &port);
    let mut c = d.client();
    // Long enough for eight tries with back-off (0.3, 0.6, 1.2, 2.4 s...).
    std::thread::sleep(Duration::from_millis(3500));
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["connected"], json!(false), "{m}");
    assert_eq!(m["state"], Value::Null, "{m}");
    let why = format!("port {}: No such file or directory", port.display());
    assert_eq!(m["disconnected_reason"], json!(why), "{m}");
    let status = String::from_utf8(d.edoctl_ok(["status"])).unwrap();
    assert!(status.contains("state unknown"), "{status}");
    assert!(status.contains(&format!("why: {why}")), "{status}");
    let log = std::fs::read_to_string(dir.path().join("edod.log")).unwrap();
    let warned = log.matches("No such file or directory").count();
    assert_eq!(warned, 1, "warned {warned} times in 3.5 s:\n{log}");
    // The machine appears: edod finds it within the longest back-off (5 s).
    let (sim, _record) = sim(dir.path(), 21);
    let t = Instant::now();
    c.wait_connected();
    eprintln!("connected {:?} after the port appeared", t.elapsed());
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["disconnected_reason"], Value::Null, "{m}");
    assert_eq!(m["state"], json!("Idle"), "{m}");
    // Unplugged: the state is not known any more, and the reason says why.
    sim.command(hil_sim::Command::Unplug);
    c.wait("disconnected", |c| {
        c.call("machine.status", json!({})).unwrap()["connected"] == json!(false)
    });
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["state"], Value::Null, "{m}");
    assert!(m["disconnected_reason"].as_str().is_some(), "{m}");
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

#[test]
fn after_a_restart_an_interrupted_job_holds_the_queue_until_the_operator_decides() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim_at(dir.path(), 22, 50.0);
    let mut d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 3000);
    let b = submit(&mut c, 200);
    c.wait("streaming", |c| c.executed(a) > 300);
    d.child.kill().unwrap(); // SIGKILL
    d.child.wait().unwrap();
    drop(c);
    let d2 = Daemon::spawn(d.socket.clone(), d.config.clone());
    let mut c = d2.client();
    c.wait_connected();
    c.wait_state(a, "interrupted");
    // The next job waits: it would print onto the half-finished part.
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(c.job(b)["state"], json!("queued"));
    let m = c.call("machine.status", json!({})).unwrap();
    assert_eq!(m["queue_held_by"], json!(a), "{m}");
    let status = String::from_utf8(d2.edoctl_ok(["status"])).unwrap();
    assert!(
        status.contains(&format!("queue waits: job {a} is interrupted")),
        "{status}"
    );
    // The operator says the machine is ready: job b runs, a stays interrupted.
    let r = c.call("job.start_next", json!({})).unwrap();
    assert_eq!(r["id"], json!(b), "{r}");
    c.wait_state(b, "done");
    assert_eq!(c.job(a)["state"], json!("interrupted"));
    let e = c.call("job.start_next", json!({})).unwrap_err();
    assert_eq!(e["code"], json!(-32002), "{e}");
    // A paused job cancelled: the reply names where it leads.
    let from = c.executed(a);
    c.call("job.resume", json!({"id": a})).unwrap();
    c.wait("streaming again", |c| c.executed(a) > from + 100);
    c.call("job.pause", json!({"id": a})).unwrap();
    let r = c.call("job.cancel", json!({"id": a})).unwrap();
    assert_eq!(r["state"], json!("cancelled"), "{r}");
    c.wait_state(a, "cancelled");
    drop(c);
    drop(d2);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, b, 200);
}

/// A 3MF whose model part inflates to `mib` MiB (an XML header, then spaces), a few
/// hundred KiB on the wire; `lying`: its headers claim the part is 1000 bytes.
fn three_mf_bomb(mib: usize, lying: bool) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("3D/3dmodel.model", opts).unwrap();
    zip.write_all(b"<?xml version=\"1.0\"?><model unit=\"millimeter\">")
        .unwrap();
    let spaces = vec![b' '; 1 << 20];
    for _ in 0..mib {
        zip.write_all(&spaces).unwrap();
    }
    let mut bytes = zip.finish().unwrap().into_inner();
    if lying {
        // The uncompressed size: at 22 in the local header, at 24 in the central one.
        let claim = 1000u32.to_le_bytes();
        bytes[22..26].copy_from_slice(&claim);
        let central = (0..bytes.len() - 4)
            .rev()
            .find(|&i| bytes[i..i + 4] == *b"PK\x01\x02")
            .unwrap();
        bytes[central + 24..central + 28].copy_from_slice(&claim);
    }
    bytes
}

/// A 3MF of about 1 KB whose components (9 levels of 10 over one tetrahedron) name 4
/// billion triangles.
fn three_mf_component_bomb() -> Vec<u8> {
    let mut model = String::from(
        "<?xml version=\"1.0\"?><model unit=\"millimeter\" \
         xmlns=\"http://schemas.microsoft.com/3dmanufacturing/core/2015/02\"><resources>\
         <object id=\"1\" type=\"model\"><mesh><vertices>\
         <vertex x=\"0\" y=\"0\" z=\"0\"/><vertex x=\"10\" y=\"0\" z=\"0\"/>\
         <vertex x=\"0\" y=\"10\" z=\"0\"/><vertex x=\"0\" y=\"0\" z=\"10\"/></vertices>\
         <triangles><triangle v1=\"0\" v2=\"2\" v3=\"1\"/><triangle v1=\"0\" v2=\"1\" v3=\"3\"/>\
         <triangle v1=\"1\" v2=\"2\" v3=\"3\"/><triangle v1=\"0\" v2=\"3\" v3=\"2\"/>\
         </triangles></mesh></object>",
    );
    for id in 2..=10 {
        model.push_str(&format!("<object id=\"{id}\" type=\"model\"><components>"));
        for _ in 0..10 {
            model.push_str(&format!("<component objectid=\"{}\"/>", id - 1));
        }
        model.push_str("</components></object>");
    }
    model.push_str("</resources><build><item objectid=\"10\"/></build></model>");
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("3D/3dmodel.model", opts).unwrap();
    zip.write_all(model.as_bytes()).unwrap();
    zip.finish().unwrap().into_inner()
}

#[test]
fn four_3mf_bombs_at_once_stay_within_the_memory_budget() {
    for lying in [false, true] {
        four_3mf_bombs_at_once(&three_mf_bomb(500, lying));
    }
    // Components instanced past the limit are counted before any is built (four at
    // once took edod from 11 MB to 1.4-1.6 GB).
    four_3mf_bombs_at_once(&three_mf_component_bomb());
}

fn four_3mf_bombs_at_once(bomb: &[u8]) {
    use base64::Engine as _;
    let dir = tempfile::tempdir().unwrap();
    eprintln!("3MF bomb: {} bytes", bomb.len());
    let mesh_base64 = base64::engine::general_purpose::STANDARD.encode(bomb);
    let job =
        "name = \"bomb\"\n[geometry]\nmesh = \"part.3mf\"\n[materials]\nnames = [\"A\", \"B\"]\n\
               [gradient]\npattern = \"growth-rings\"\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n\
               [process]\nr_mach = 0.8\nnozzle = 0.4\nlayer = 0.2\n";
    let (sim, _record) = sim(dir.path(), 23);
    let d = Daemon::start_with_limit(dir.path(), sim.path(), 4 << 20);
    let before = peak_memory(&d);
    let params = Arc::new(json!({"job": job, "mesh_base64": mesh_base64}));
    let answers: Vec<Value> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..4)
            .map(|_| {
                let mut c = d.client();
                let p = Arc::clone(&params);
                let line = json!({"jsonrpc": "2.0", "id": 1, "method": "job.submit", "params": *p});
                s.spawn(move || c.send_raw(&line.to_string()))
            })
            .collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let after = peak_memory(&d);
    eprintln!(
        "VmHWM {} MiB before, {} MiB after",
        before >> 20,
        after >> 20
    );
    for a in &answers {
        let e = &a["error"];
        let code = e["code"].as_i64().unwrap();
        let msg = e["message"].as_str().unwrap();
        // Refused for its size, declared or found (-32003), or for the budget other
        // bombs hold (-32006).
        assert!(code == -32003 || code == -32006, "{e}");
        assert!(
            msg.contains("part.3mf") || msg.contains("memory budget"),
            "{e}"
        );
    }
    // The budget is 256 MiB; four 500 MiB models took edod to 2 GB before it.
    assert!(after < 400 << 20, "VmHWM {} MiB", after >> 20);
    // edod still serves.
    let mut c = d.client();
    c.call("machine.status", json!({})).unwrap();
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// `dir/state/edod.db` opened by another process (an operator's sqlite3 shell).
fn open_db(dir: &Path) -> rusqlite::Connection {
    rusqlite::Connection::open(dir.join("state").join("edod.db")).unwrap()
}

/// A damaged job store: rows that cannot be read are failed naming the job and what is
/// wrong (not coerced: a spec that is not JSON used to run as a 0-move dry run and end
/// done, one bad `next_index` failed `job.list` for every job, an unknown state showed
/// as `failed` without a word); a lost jobs table does not bring ids back to 1; random
/// bytes over a page nobody reads at start, and a newer schema, stop edod at start with
/// a message naming the file and what to do.
#[test]
fn a_damaged_store_is_refused_or_its_unreadable_rows_quarantined() {
    let dir = tempfile::tempdir().unwrap();
    // Five jobs queued for a machine that is not there.
    let mut d = Daemon::start(dir.path(), &dir.path().join("no-such-tty"));
    let mut c = d.client();
    let ids: Vec<u64> = (0..5).map(|_| submit(&mut c, 50)).collect();
    assert_eq!(ids, [1, 2, 3, 4, 5]);
    drop(c);
    assert!(d.sigterm().success());
    {
        let db = open_db(dir.path());
        for sql in [
            "UPDATE jobs SET spec = 'not json' WHERE id = 1",
            "UPDATE jobs SET next_index = 'seven' WHERE id = 2",
            "UPDATE jobs SET state = 'frobbed' WHERE id = 3",
        ] {
            assert_eq!(db.execute(sql, []).unwrap(), 1, "{sql}");
        }
    }
    let (sim, record) = sim(dir.path(), 31);
    let mut d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    let list = c.call("job.list", json!({})).expect("job.list");
    let jobs = list.as_array().unwrap();
    assert_eq!(jobs.len(), 5, "{list}");
    for (j, what) in jobs[..3].iter().zip(["spec: ", "next_index: ", "state: "]) {
        assert_eq!(j["state"], json!("failed"), "{j}");
        let reason = j["reason"].as_str().unwrap_or_default();
        assert!(
            reason.starts_with("stored job unreadable: ") && reason.contains(what),
            "{j}"
        );
    }
    c.wait_state(4, "done");
    c.wait_state(5, "done");
    for id in 1..=3 {
        assert_eq!(c.job(id)["state"], json!("failed"), "job {id} never ran");
        assert!(recorded(&record, id).is_empty(), "job {id} never ran");
    }
    drop(c);
    assert!(d.sigterm().success());
    // The jobs table lost: ids go on from the highest ever given.
    open_db(dir.path())
        .execute_batch("DROP TABLE jobs")
        .unwrap();
    let mut d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    assert_eq!(submit(&mut c, 10), 6, "ids are never given twice");
    c.wait_state(6, "done");
    drop(c);
    assert!(d.sigterm().success());
    sim.stop().unwrap();
    // Random bytes over the meshes table's first page (nothing reads it at start).
    let page = {
        let db = open_db(dir.path());
        db.pragma_update(None, "wal_checkpoint", "TRUNCATE")
            .unwrap();
        db.query_row(
            "SELECT rootpage FROM sqlite_master WHERE name = 'job_meshes'",
            [],
            |r| r.get::<_, i64>(0),
        )
        .unwrap() as usize
    };
    let path = dir.path().join("state").join("edod.db");
    let mut bytes = std::fs::read(&path).unwrap();
    let mut x: u32 = 31;
    for b in &mut bytes[(page - 1) * 4096..page * 4096] {
        x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
        *b = (x >> 16) as u8;
    }
    std::fs::write(&path, &bytes).unwrap();
    let config = dir.path().join("edod.toml");
    let said = refused_to_start(&config);
    assert!(
        said.contains(&format!(
            "job store {} is damaged (PRAGMA quick_check",
            path.display()
        )) && said.contains(".recover"),
        "{said}"
    );
    // A schema newer than this edod's.
    std::fs::write(&path, []).unwrap();
    let _ = std::fs::remove_file(dir.path().join("state").join("edod.db-wal"));
    open_db(dir.path())
        .pragma_update(None, "user_version", 9)
        .unwrap();
    let said = refused_to_start(&config);
    assert!(
        said.contains("schema version 9, newer than this edod knows"),
        "{said}"
    );
}

/// Set edod's file size limit (RLIMIT_FSIZE, soft) to `limit` (`prlimit --fsize`): 0
/// makes every write of its to a regular file fail as on a full disk (EFBIG; edod
/// ignores SIGXFSZ), `unlimited` gives the room back.
fn file_size_limit(d: &Daemon, limit: &str) {
    let out = Command::new("prlimit")
        .arg("--pid")
        .arg(d.child.id().to_string())
        .arg(format!("--fsize={limit}:unlimited"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A full state disk while a job streams (edod's file size limit set to 0: every write
/// of edod.db fails, while the machine, the socket and edod's log go on). The job's
/// planned moves go on; a pause holds the machine and is answered -32007, not `paused`
/// as if stored; a resume and a cancel are refused or told as not on disk; warnings are
/// not repeated several times a second; once there is room again everything catches
/// up, and a restart then reverses no operator's decision.
#[test]
fn a_full_state_disk_holds_state_changes_and_loses_no_operator_decision() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim_at(dir.path(), 32, 20.0);
    Daemon::write_config(dir.path(), sim.path(), 4096, 1000, "");
    // edod itself ignores SIGXFSZ (started as systemd starts it: no shell trapping it).
    let mut child = Command::new(env!("CARGO_BIN_EXE_edod"))
        .arg("--config")
        .arg(dir.path().join("edod.toml"))
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let stderr = child.stderr.take().unwrap();
    let lines = Arc::clone(&log);
    std::thread::spawn(move || {
        for l in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("edod: {l}");
            lines.lock().unwrap().push(l);
        }
    });
    let mut d = Daemon::ready(
        child,
        dir.path().join("edod.sock"),
        dir.path().join("edod.toml"),
    );
    let mut c = d.client();
    c.wait_connected();
    let a = submit(&mut c, 1500);
    let b = submit(&mut c, 100);
    c.wait("streaming", |c| c.executed(a) > 200);
    let progress = |c: &mut Client| {
        c.call("machine.status", json!({})).unwrap()["progress"]["executed"]
            .as_u64()
            .unwrap_or(0)
    };
    file_size_limit(&d, "0");
    let full_at = log.lock().unwrap().len();
    let before = progress(&mut c);
    std::thread::sleep(Duration::from_millis(800));
    let during = progress(&mut c);
    assert!(during > before + 50, "fed on: {before} -> {during}");
    // The pause takes effect on the machine, and is not acknowledged as stored.
    let e = c.call("job.pause", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32007), "{e}");
    let m = e["message"].as_str().unwrap();
    assert!(
        m.starts_with("job store cannot write: ") && m.contains("is paused here"),
        "{m}"
    );
    std::thread::sleep(Duration::from_millis(700));
    let held = progress(&mut c);
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(progress(&mut c), held, "the machine holds");
    let e = c.call("job.resume", json!({"id": a})).unwrap_err();
    assert_eq!(e["code"], json!(-32007), "{e}");
    // machine.status and edoctl status say why.
    let m = c.call("machine.status", json!({})).unwrap();
    let problem = m["store_problem"].as_str().unwrap_or_default().to_string();
    assert!(problem.starts_with("job store cannot write: "), "{m}");
    let status = String::from_utf8(d.edoctl_ok(["status"])).unwrap();
    assert!(status.contains(&problem), "{status}");
    let e = c.call("job.cancel", json!({"id": b})).unwrap_err();
    assert_eq!(e["code"], json!(-32007), "{e}");
    let e = c
        .call("job.submit", json!({"dry_run_moves": 10}))
        .unwrap_err();
    assert_eq!(e["code"], json!(-32007), "{e}");
    std::thread::sleep(Duration::from_millis(1500));
    let warnings = log.lock().unwrap()[full_at..]
        .iter()
        .filter(|l| l.contains("job store"))
        .count();
    assert!(warnings <= 2, "{warnings} store warnings in 3.5 s");
    // Room again: the pause and the cancel reach the disk.
    file_size_limit(&d, "unlimited");
    c.wait_state(a, "paused");
    c.wait_state(b, "cancelled");
    c.wait("the store writes again", |c| {
        c.call("machine.status", json!({})).unwrap()["store_problem"].is_null()
    });
    let r = c.call("job.resume", json!({"id": a})).unwrap();
    assert_eq!(r["state"], json!("printing"), "{r}");
    // `stored` says whether the write was done within the 75 ms a reply waits for it:
    // true on a quiet host, false when fsync is slower (the store-lock test's 63 MiB
    // submissions in parallel made it so once). That the resume reached the disk is
    // what job.get (which reads the store) shows: printing, then done.
    assert!(r["stored"].is_boolean(), "{r}");
    c.wait("the resume on disk", |c| {
        matches!(c.job(a)["state"].as_str(), Some("printing" | "done"))
    });
    c.wait_state(a, "done");
    drop(c);
    assert!(d.sigterm().success());
    // Across a restart nothing is reversed.
    let d = Daemon::start(dir.path(), sim.path());
    let mut c = d.client();
    assert_eq!(c.job(a)["state"], json!("done"));
    let j = c.job(b);
    assert_eq!(j["state"], json!("cancelled"), "{j}");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    assert_exactly_once(&record, a, 1500);
    assert!(
        recorded(&record, b).is_empty(),
        "the cancelled job never ran"
    );
}

/// A daemon with the dashboard on a free loopback port, `api` added to its `[api]`
/// table; its address.
fn start_with_dashboard(
    dir: &Path,
    port: &Path,
    max_request_bytes: usize,
    api: &str,
) -> (Daemon, std::net::SocketAddr) {
    Daemon::write_config(dir, port, max_request_bytes, 1000, api);
    let addr = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let config = dir.join("edod.toml");
    let text = std::fs::read_to_string(&config).unwrap();
    let served = text.replace(
        "[http]\nenabled = false\n",
        &format!("[http]\nlisten = \"{addr}\"\n"),
    );
    assert_ne!(served, text);
    std::fs::write(&config, served).unwrap();
    (Daemon::spawn(dir.join("edod.sock"), config), addr)
}

/// This process's open-file limit raised to its hard limit (the tests below open
/// more than 1,024 connections); the limit.
fn raise_own_open_files() -> u64 {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    let (_, hard) = getrlimit(Resource::RLIMIT_NOFILE).unwrap();
    setrlimit(Resource::RLIMIT_NOFILE, hard, hard).unwrap();
    hard
}

/// `POST /api/rpc` of `method` on a new connection to `addr`: the answer, and how long
/// it took.
fn post_rpc(addr: std::net::SocketAddr, method: &str) -> (String, Duration) {
    post_body(
        addr,
        &format!(r#"{{"jsonrpc":"2.0","id":1,"method":"{method}"}}"#),
    )
}

/// `POST /api/rpc` of `body` on a new connection to `addr`: the answer, and how long
/// it took.
fn post_body(addr: std::net::SocketAddr, body: &str) -> (String, Duration) {
    use std::io::Read;
    let t = Instant::now();
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "POST /api/rpc HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut answer = String::new();
    s.read_to_string(&mut answer).unwrap();
    (answer, t.elapsed())
}

/// 1,100 idle connections to the dashboard (more than the 1,024 open files edod had
/// by default, all of which they took before): edod counts them against its places
/// (256 ordinary, 4 control), answers the rest 503 at once and keeps descriptors for
/// everyone else: `edoctl estop` and `status` on the socket and an e-stop by
/// `POST /api/rpc` (a newcomer takes an idle control place) are answered at once.
#[test]
fn a_thousand_idle_dashboard_connections_do_not_lock_out_the_estop() {
    assert!(
        raise_own_open_files() >= 2048,
        "the test needs 2,048 open files"
    );
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 17);
    let (d, addr) = start_with_dashboard(dir.path(), sim.path(), 4096, "");
    let mut c = d.client();
    c.wait_connected();
    let limits = std::fs::read_to_string(format!("/proc/{}/limits", d.child.id())).unwrap();
    let idle: Vec<std::net::TcpStream> = (0..1100)
        .map(|_| std::net::TcpStream::connect(addr).unwrap())
        .collect();
    // Wait until edod has accepted them all (the refused ones are answered and closed).
    let deadline = Instant::now() + Duration::from_secs(10);
    while accept_queue_len(addr) != Some(0) {
        assert!(
            Instant::now() < deadline,
            "edod left connections unaccepted for 10 s: {:?} waiting",
            accept_queue_len(addr)
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let fds = std::fs::read_dir(format!("/proc/{}/fd", d.child.id()))
        .unwrap()
        .count();
    let t = Instant::now();
    let status = d.edoctl_ok(["status"]);
    let status_took = t.elapsed();
    let t = Instant::now();
    let estop = d.edoctl_ok(["estop"]);
    let estop_took = t.elapsed();
    let (posted, post_took) = post_rpc(addr, "machine.estop");
    eprintln!(
        "1,100 idle dashboard connections: edod holds {fds} descriptors; edoctl status \
         {status_took:?}, edoctl estop {estop_took:?}, POST machine.estop {post_took:?}"
    );
    assert!(!status.is_empty() && !estop.is_empty());
    assert!(posted.starts_with("HTTP/1.1 200"), "{posted}");
    assert!(posted.contains("written_after_us"), "{posted}");
    // On a control place anything but a control call is refused, read once: another
    // method, a body that is no JSON, a control method with wrong params.
    for body in [
        r#"{"jsonrpc":"2.0","id":1,"method":"job.list"}"#,
        "not json",
        r#"{"jsonrpc":"2.0","id":1,"method":"machine.status","params":{"x":1}}"#,
    ] {
        let (refused, _) = post_body(addr, body);
        assert!(refused.starts_with("HTTP/1.1 503"), "{body}: {refused}");
        assert!(refused.contains("may only ask"), "{body}: {refused}");
    }
    let (status_posted, _) = post_rpc(addr, "machine.status");
    assert!(status_posted.starts_with("HTTP/1.1 200"), "{status_posted}");
    assert!(status_posted.contains("connected"), "{status_posted}");
    assert!(fds < 400, "edod holds {fds} descriptors");
    assert!(estop_took < Duration::from_secs(2) && post_took < Duration::from_secs(2));
    // edod raised its soft limit to the hard one.
    let soft = |l: &str| {
        l.lines()
            .find(|l| l.starts_with("Max open files"))
            .and_then(|l| l.split_whitespace().nth(3).map(str::to_owned))
    };
    assert_eq!(soft(&limits), Some(raise_own_open_files().to_string()));
    drop(idle);
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// Connections waiting in the accept queue of the socket listening on `addr` (the
/// `rx_queue` of its LISTEN row in /proc/net/tcp); `None` when no such socket listens.
fn accept_queue_len(addr: std::net::SocketAddr) -> Option<u32> {
    let std::net::SocketAddr::V4(v4) = addr else {
        return None;
    };
    // /proc/net/tcp writes the address as the u32 in host order, in hex, then the port.
    let local = format!(
        "{:08X}:{:04X}",
        u32::from_ne_bytes(v4.ip().octets()),
        v4.port()
    );
    let table = std::fs::read_to_string("/proc/net/tcp").ok()?;
    table.lines().skip(1).find_map(|row| {
        let f: Vec<&str> = row.split_whitespace().collect();
        let listening = f.get(1) == Some(&local.as_str()) && f.get(3) == Some(&"0A");
        let queues = f.get(4)?.split_once(':')?;
        listening
            .then(|| u32::from_str_radix(queues.1, 16).ok())
            .flatten()
    })
}

/// The accept queue read above counts connections not yet accepted.
#[test]
fn the_accept_queue_counts_connections_not_yet_accepted() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    assert_eq!(accept_queue_len(addr), Some(0));
    let _waiting: Vec<_> = (0..3)
        .map(|_| std::net::TcpStream::connect(addr).unwrap())
        .collect();
    let deadline = Instant::now() + Duration::from_secs(5);
    while accept_queue_len(addr) != Some(3) {
        assert!(Instant::now() < deadline, "{:?}", accept_queue_len(addr));
        std::thread::sleep(Duration::from_millis(5));
    }
    let _accepted = listener.accept().unwrap();
    assert_eq!(accept_queue_len(addr), Some(2));
    drop(listener);
    assert_eq!(accept_queue_len(addr), None);
}

/// With a hard limit of open files below what its connection places need, edod refuses
/// to start, naming the settings and the limit (it would otherwise run out of
/// descriptors before it refuses connections).
#[test]
fn too_few_open_files_for_the_connection_places_refuse_the_start() {
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 18);
    Daemon::write_config(dir.path(), sim.path(), 4096, 1000, "max_clients = 500");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_edod"));
    cmd.arg("--config")
        .arg(dir.path().join("edod.toml"))
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null());
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            nix::sys::resource::setrlimit(nix::sys::resource::Resource::RLIMIT_NOFILE, 400, 400)
                .map_err(std::io::Error::from)
        });
    }
    let out = cmd.output().unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{said}");
    assert!(
        said.contains("api.max_clients = 500")
            && said.contains("need 568 open files")
            && said.contains("only 400"),
        "{said}"
    );
    sim.stop().unwrap();
}

/// 20 clients each send half of a 60 MiB `POST /api/rpc` body and stop: bodies are
/// read as they arrive and counted against the memory budget (256 MiB), so the ones it
/// cannot hold are refused at once (503 naming it) and the others answered 408 after
/// the idle timeout; edod's peak memory stays within the budget and a margin (before:
/// 11 -> 632 MB, no answer after 30 s).
#[test]
fn twenty_half_sent_dashboard_bodies_stay_within_the_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 19);
    let (d, addr) = start_with_dashboard(dir.path(), sim.path(), 64 << 20, "idle_timeout_s = 4");
    let mut c = d.client();
    c.wait_connected();
    let before = peak_memory(&d);
    let half: Arc<Vec<u8>> = Arc::new({
        let mut v = format!(
            "POST /api/rpc HTTP/1.1\r\nHost: {addr}\r\nContent-Length: {}\r\n\r\n\
             {{\"jsonrpc\":\"2.0\",\"id\":1,\"method\":\"job.submit\",\"params\":{{\"job\":\"",
            60 << 20
        )
        .into_bytes();
        v.resize(30 << 20, b'A');
        v
    });
    let t = Instant::now();
    let clients: Vec<_> = (0..20)
        .map(|_| {
            let half = Arc::clone(&half);
            std::thread::spawn(move || {
                use std::io::Read;
                let mut s = std::net::TcpStream::connect(addr).unwrap();
                // edod may answer and close before the write ends.
                let _ = s.write_all(&half);
                s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
                let mut answer = Vec::new();
                let _ = s.read_to_end(&mut answer);
                (String::from_utf8_lossy(&answer).into_owned(), t.elapsed())
            })
        })
        .collect();
    let replies: Vec<(String, Duration)> = clients.into_iter().map(|h| h.join().unwrap()).collect();
    let peak = peak_memory(&d);
    let (mut refused, mut timed_out) = (0, 0);
    for (r, at) in &replies {
        if r.starts_with("HTTP/1.1 503") {
            assert!(r.contains("api.memory_budget_bytes = 256.0 MiB"), "{r}");
            refused += 1;
        } else {
            assert!(r.starts_with("HTTP/1.1 408"), "{r:.300}");
            assert!(r.contains("api.idle_timeout_s"), "{r}");
            timed_out += 1;
        }
        assert!(*at < Duration::from_secs(15), "answered after {at:?}");
    }
    eprintln!(
        "20 half-sent 60 MiB dashboard bodies: {refused} refused over the budget, \
         {timed_out} timed out; edod VmHWM {} MiB before, {} MiB after",
        before >> 20,
        peak >> 20
    );
    assert!(refused >= 10, "{refused} refused");
    assert!(
        peak < before + (256 << 20) + (32 << 20),
        "peak {} MiB",
        peak >> 20
    );
    let (answer, _) = post_rpc(addr, "server.info");
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// A ball with supports of the part's materials (`[support]` everywhere, at B): edod
/// accepts it with no warning (nothing rests on nothing with them), prints it whole,
/// every move once and in order, and its support roads push B alone.
#[test]
fn a_job_with_supports_is_printed_whole_with_them() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim_at(dir.path(), 21, 200.0);
    let d = Daemon::start_with_limit(dir.path(), sim.path(), 4 << 20);
    let mut c = d.client();
    c.wait_connected();
    let ball = stl_of(&edo::mesh::primitives::sphere(2.0, 32, 16));
    let job =
        "name = \"ball\"\n[geometry]\nmesh = \"ball.stl\"\n[materials]\nnames = [\"A\", \"B\"]\n\
               [gradient]\ninner = [1.0, 0.0]\nouter = [1.0, 0.0]\n[process]\nr_mach = 2.0\n\
               nozzle = 0.4\nlayer = 0.2\nthin_regions = \"fill\"\n\
               [support]\nmode = \"everywhere\"\ncomposition = [0.0, 1.0]\n";
    let r = c
        .call(
            "job.submit",
            json!({"job": job, "mesh_base64": edo::proto::mesh_bytes::base64_encode(&ball)}),
        )
        .unwrap();
    assert!(r.get("warnings").is_none(), "{r}");
    let id = r["id"].as_u64().unwrap();
    let j = c.wait_state(id, "done");
    let total = j["total_moves"].as_u64().unwrap();
    let indices = recorded_indices(&record, id);
    assert_eq!(indices, (0..total).collect::<Vec<_>>());
    // The part is all A; B is pushed only by the support roads (and the mixer's lead
    // into them): some extrusions push B.
    let b_pushed = recorded(&record, id)
        .iter()
        .filter(|m| m["kind"] == json!("extrude") && m["volumes_nl"][1].as_u64() > Some(0))
        .count();
    assert!(b_pushed > 0, "no support road was built");
    drop(c);
    drop(d);
    sim.stop().unwrap();
}

/// `job.submit` of a mesh job whose lower half leans out past the allowed overhang
/// (a sphere on the bed) is accepted with a warning naming the layers (cut 64 at a time
/// before the reply); a tube gets none.
#[test]
fn a_submitted_job_that_hangs_in_mid_air_is_warned_about() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), 20);
    let d = Daemon::start_with_limit(dir.path(), sim.path(), 4 << 20);
    let mut c = d.client();
    c.wait_connected();
    let ball = stl_of(&edo::mesh::primitives::sphere(5.0, 64, 32));
    let job =
        "name = \"ball\"\n[geometry]\nmesh = \"ball.stl\"\n[materials]\nnames = [\"A\", \"B\"]\n\
               [gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n[process]\nr_mach = 2.0\n\
               nozzle = 0.4\nlayer = 0.2\nthin_regions = \"fill\"\n";
    let r = c
        .call(
            "job.submit",
            json!({"job": job, "mesh_base64": edo::proto::mesh_bytes::base64_encode(&ball)}),
        )
        .unwrap();
    let warnings = r["warnings"].as_array().expect("warnings");
    assert_eq!(warnings.len(), 1, "{r}");
    let w = warnings[0].as_str().unwrap();
    assert!(
        w.starts_with("ball.stl: ") && w.contains("resting on nothing") && w.contains("layers 1-"),
        "{w}"
    );
    c.call("job.cancel", json!({"id": r["id"]})).unwrap();
    // Required to rest on something: refused, naming the key.
    let e = c
        .call(
            "job.submit",
            json!({"job": format!("{job}[support]\nrequired = true\n"),
                   "mesh_base64": edo::proto::mesh_bytes::base64_encode(&ball)}),
        )
        .unwrap_err();
    assert_eq!(e["code"], json!(-32003));
    assert!(
        e["message"].as_str().unwrap().contains("support.required"),
        "{e}"
    );
    // A tube stands on the bed: every layer rests on the one below.
    let tube = stl_of(&edo::mesh::primitives::tube(4.0, 8.0, 3.0, 64));
    let r = c
        .call(
            "job.submit",
            json!({"job": job.replace("r_mach = 2.0", "r_mach = 0.8"),
                   "mesh_base64": edo::proto::mesh_bytes::base64_encode(&tube)}),
        )
        .unwrap();
    assert!(r.get("warnings").is_none(), "{r}");
    drop(c);
    drop(d);
    sim.stop().unwrap();
}
