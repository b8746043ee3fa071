//! edod over the G-code link (`docs/firmware.md`) against hil-sim's firmware models on a
//! pty: RepRapFirmware, Marlin and Klipper.
//! Each test starts its own simulator (in this process, with its recorder) and edod in a
//! temp dir. The recorder's `gcode` field is each line the firmware ran as a move: the
//! checks compare it with the lines the offline writer (`edoctl plan --gcode`) writes for
//! the same planned moves.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use edo::daemon::gcode_link::streamed_lines;
use edo::gcode_link::{command_word, Dialect, MixWriting};
use edo::machine::gcode::GcodeSettings;
use edo::machine::Move;
use serde_json::{json, Value};

struct Daemon {
    child: Child,
    socket: PathBuf,
}

impl Daemon {
    /// edod for `firmware` on `port` (a path, or `"sim"`), state in `dir`; `extra` is
    /// appended to the configuration.
    fn start(dir: &Path, port: &str, firmware: &str, extra: &str) -> Daemon {
        let socket = dir.join("edod.sock");
        let busy = match firmware {
            "marlin" => "busy_timeout_ms = 300\n",
            "klipper" => "axes = [\"A\", \"B\"]\n",
            _ => "",
        };
        let config = dir.join("edod.toml");
        std::fs::write(
            &config,
            format!(
                "[serial]\nport = {port:?}\nbaud = 250000\n\
                 [machine]\nprotocol = \"gcode\"\n\
                 [machine.gcode]\nfirmware = \"{firmware}\"\nok_timeout_ms = 300\n{busy}\
                 slow_command_timeout_s = 2\n\
                 [api]\nsocket = {:?}\n[state]\ndir = {:?}\n\
                 [planner]\ndry_run_moves_per_layer = 100\n[http]\nenabled = false\n{extra}",
                socket.display().to_string(),
                dir.join("state").display().to_string()
            ),
        )
        .unwrap();
        Daemon::spawn(socket, &config)
    }

    fn spawn(socket: PathBuf, config: &Path) -> Daemon {
        let child = Command::new(env!("CARGO_BIN_EXE_edod"))
            .arg("--config")
            .arg(config)
            .env(
                "RUST_LOG",
                std::env::var("EDOD_TEST_LOG").unwrap_or_else(|_| "warn".into()),
            )
            .stdin(Stdio::null())
            .spawn()
            .unwrap();
        let t = Instant::now();
        while UnixStream::connect(&socket).is_err() {
            assert!(t.elapsed() < Duration::from_secs(20), "edod did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        Daemon { child, socket }
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

    fn sigkill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        self.sigkill();
    }
}

struct Client {
    r: BufReader<UnixStream>,
    w: UnixStream,
    next: u64,
}

impl Client {
    fn call(&mut self, method: &str, params: Value) -> Result<Value, Value> {
        let id = self.next;
        self.next += 1;
        let req = json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params});
        self.w.write_all(format!("{req}\n").as_bytes()).unwrap();
        let v = loop {
            let mut l = String::new();
            assert!(self.r.read_line(&mut l).unwrap() > 0, "daemon closed");
            let v: Value = serde_json::from_str(&l).unwrap();
            if v.get("method").is_none() {
                break v;
            }
        };
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

fn dialect(firmware: &str) -> Dialect {
    match firmware {
        "rrf" => Dialect::Rrf,
        "marlin" => Dialect::Marlin,
        _ => Dialect::Klipper,
    }
}

/// hil-sim as `firmware`, in this process; its recorder.
fn sim(dir: &Path, firmware: &str, seed: u64) -> (hil_sim::SimHandle, PathBuf) {
    let record = dir.join("run.jsonl");
    let h = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.join("tty")),
        speed: 50.0,
        seed,
        record: Some(record.clone()),
        gcode: Some(hil_sim::GcodeOptions::new(dialect(firmware), 2)),
        ..hil_sim::SimConfig::default()
    })
    .unwrap();
    (h, record)
}

/// The `gcode` of every move the simulator ran, in order.
fn ran(record: &Path) -> Vec<String> {
    std::fs::read_to_string(record)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter_map(|v| v["gcode"].as_str().map(str::to_string))
        .collect()
}

/// Per-drive volume the simulator dispensed for extrusions (nl), a line run twice in a
/// row counted once.
fn extruded_nl(record: &Path) -> Vec<i64> {
    let mut sums = vec![0i64; 2];
    let mut last = Value::Null;
    for l in std::fs::read_to_string(record).unwrap().lines() {
        let v: Value = serde_json::from_str(l).unwrap();
        let again = v["gcode"] == last;
        last = v["gcode"].clone();
        if v["kind"] == json!("extrude") && !again {
            for (s, x) in sums.iter_mut().zip(v["volumes_nl"].as_array().unwrap()) {
                *s += x.as_i64().unwrap();
            }
        }
    }
    sums
}

/// The mix writing edod uses for `firmware` by default.
fn mix_of(firmware: &str) -> MixWriting {
    match firmware {
        "rrf" => MixWriting::PerDriveE,
        "marlin" => MixWriting::MarlinM163,
        _ => MixWriting::Axes(vec!['A', 'B']),
    }
}

/// Barrel area of the default syringes (10 mm bore), mm².
const AREA_MM2: f64 = std::f64::consts::PI / 4.0 * 100.0;

/// What the offline writer writes for `moves` as `firmware`: the whole text.
fn offline(moves: &[Move], firmware: &str) -> String {
    let settings = GcodeSettings::for_mix(&mix_of(firmware), AREA_MM2);
    let mut text = String::new();
    edo::machine::gcode::write_gcode(moves, 2, &settings, &[], &mut text).unwrap();
    text
}

/// The lines of `text` that are moves (what the recorder shows).
fn move_lines(text: &str) -> Vec<String> {
    streamed_lines(text)
        .filter(|l| matches!(command_word(l).as_deref(), Some("G0" | "G1" | "G4" | "G28")))
        .map(str::to_string)
        .collect()
}

const JOB: &str = r#"name = "graded square"
[geometry]
polygon = { outer = { rect = { min = [0.0, 0.0], max = [3.0, 3.0] } } }
height = 0.4
[materials]
names = ["A", "B"]
[gradient]
pattern = "growth-rings"
inner = [1.0, 0.0]
outer = [0.0, 1.0]
[process]
r_mach = 0.8
nozzle = 0.4
layer = 0.2
"#;

/// The planned moves of [`JOB`] on edod's default machine.
fn planned_job() -> Vec<Move> {
    let machine = edo::daemon::config::MachineConfig::default();
    let mut src = edo::daemon::planner::JobSource::new(JOB, None, "square", &machine).unwrap();
    let mut planned = Vec::new();
    while let Some(layer) = edo::daemon::planner::LayerSource::next_layer(&mut src) {
        planned.extend(layer.unwrap());
    }
    planned
}

/// The planned moves of a dry run of `moves`.
fn planned_dry_run(moves: u32) -> Vec<Move> {
    let mut src = edo::daemon::planner::DryRunSource::new(moves, 100, 2, 150_000);
    let mut planned = Vec::new();
    while let Some(layer) = edo::daemon::planner::LayerSource::next_layer(&mut src) {
        planned.extend(layer.unwrap());
    }
    planned
}

/// Every line in `expected` ran once and in order. `repeats_allowed`: RRF, where a line
/// whose `ok` was lost is sent again and runs twice, right after itself
/// (`docs/firmware.md`); returns how many ran twice.
fn assert_ran_once_in_order(ran: &[String], expected: &[String], repeats_allowed: bool) -> usize {
    let mut collapsed: Vec<&String> = Vec::with_capacity(ran.len());
    let mut repeats = 0;
    for l in ran {
        if repeats_allowed && collapsed.last() == Some(&l) {
            repeats += 1;
            continue;
        }
        collapsed.push(l);
    }
    assert_eq!(collapsed.len(), expected.len(), "lines run");
    for (k, (a, b)) in collapsed.iter().zip(expected).enumerate() {
        assert_eq!(*a, b, "line {k}");
    }
    repeats
}

/// A graded job on `firmware` with `faults`: done, every line of the offline file ran
/// once and in order, and the per-drive volumes are the file's E totals.
fn job_streams_the_offline_file(firmware: &str, faults: &str, seed: u64) {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim(dir.path(), firmware, seed);
    let d = Daemon::start(dir.path(), &sim.path().display().to_string(), firmware, "");
    let mut c = d.client();
    c.wait_connected();
    // Faults once connected (the handshake under faults is the line protocol's tests').
    for f in faults.split(',').filter(|f| !f.is_empty()) {
        sim.command(hil_sim::Command::parse(f).unwrap());
    }
    let id = c.call("job.submit", json!({"job": JOB})).unwrap()["id"]
        .as_u64()
        .unwrap();
    let done = c.wait_state(id, "done");
    let planned = planned_job();
    assert_eq!(done["total_moves"].as_u64(), Some(planned.len() as u64));
    drop(c);
    drop(d);
    let summary = sim.stop().unwrap();
    let text = offline(&planned, firmware);
    let expected = move_lines(&text);
    let repeats = assert_ran_once_in_order(&ran(&record), &expected, firmware == "rrf");
    assert!(
        expected.len() > 50,
        "{} move lines: too small a job",
        expected.len()
    );
    // Per-drive E of the file, in nl as the simulator turns travel into volume.
    let flavor = GcodeSettings::for_mix(&mix_of(firmware), AREA_MM2).flavor;
    let file_e = edo::machine::gcode::summed_drive_e(&text, 2, flavor);
    let built = extruded_nl(&record);
    for (k, (e, nl)) in file_e.iter().zip(&built).enumerate() {
        let want = e * AREA_MM2 * 1000.0;
        let slack = 2.0 + repeats as f64;
        assert!(
            (want - *nl as f64).abs() <= slack,
            "drive {k}: file {want:.1} nl, built {nl} nl"
        );
        assert!(want > 1000.0, "drive {k} extrudes {want} nl");
    }
    eprintln!(
        "{firmware} {faults:?}: {} lines, {repeats} repeated, {summary:?}",
        expected.len()
    );
}

#[test]
fn rrf_job_runs_the_offline_file_once_in_order() {
    job_streams_the_offline_file("rrf", "", 1);
}

#[test]
fn marlin_job_runs_the_offline_file_once_in_order() {
    job_streams_the_offline_file("marlin", "", 2);
}

#[test]
fn klipper_job_runs_the_offline_file_once_in_order() {
    job_streams_the_offline_file("klipper", "", 7);
}

#[test]
fn rrf_corrupted_lines_and_lost_oks_lose_and_reorder_nothing() {
    job_streams_the_offline_file("rrf", "corrupt-line=0.03,drop-ok=0.01", 3);
}

#[test]

fn marlin_corrupted_lines_and_lost_oks_run_every_line_once() {
    job_streams_the_offline_file("marlin", "corrupt-line=0.03,drop-ok=0.01", 4);
}

/// A dry run on `firmware`: paused mid-job (no line runs once the firmware finished what
/// it accepted), resumed, e-stopped (acknowledged, job interrupted); what ran is the
/// start of the offline file, each line once.
fn pause_resume_and_estop(firmware: &str, seed: u64) {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim(dir.path(), firmware, seed);
    let d = Daemon::start(dir.path(), &sim.path().display().to_string(), firmware, "");
    let mut c = d.client();
    c.wait_connected();
    let total = 3000;
    let id = c
        .call("job.submit", json!({"dry_run_moves": total}))
        .unwrap()["id"]
        .as_u64()
        .unwrap();
    c.wait("streaming", |c| c.executed(id) > 150);
    let r = c.call("job.pause", json!({"id": id})).unwrap();
    assert_eq!(r["state"], json!("paused"));
    // What the firmware accepted runs; then nothing more.
    std::thread::sleep(Duration::from_millis(300));
    let held = ran(&record).len();
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(ran(&record).len(), held, "lines ran while paused");
    let at_pause = c.executed(id);
    let r = c.call("job.resume", json!({"id": id})).unwrap();
    assert_eq!(r["state"], json!("printing"));
    c.wait("streaming again", |c| c.executed(id) > at_pause + 150);
    let t = c.call("machine.estop", json!({})).unwrap();
    assert!(t["acked_after_us"].as_u64().is_some(), "{t}");
    c.wait_state(id, "interrupted");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let expected = move_lines(&offline(&planned_dry_run(total), firmware));
    let ran = ran(&record);
    assert!(
        ran.len() > 200 && ran.len() < expected.len(),
        "{} ran",
        ran.len()
    );
    assert_ran_once_in_order(&ran, &expected[..ran.len()], false);
}

#[test]
fn rrf_pause_resume_and_estop() {
    pause_resume_and_estop("rrf", 5);
}

#[test]
fn marlin_pause_resume_and_estop() {
    pause_resume_and_estop("marlin", 6);
}

#[test]
fn klipper_pause_resume_and_estop() {
    pause_resume_and_estop("klipper", 8);
}

/// `serial.port = "sim"` with `protocol = "gcode"`: edod starts `hil-sim --gcode` (the
/// binary beside edod, built with the workspace) and the job runs on it.
#[test]
fn sim_port_starts_hil_sim_as_the_firmware() {
    let Some(bin) = Path::new(env!("CARGO_BIN_EXE_edod"))
        .parent()
        .map(|d| d.join("hil-sim"))
        .filter(|b| b.is_file())
    else {
        eprintln!("skipped: no hil-sim binary beside edod (cargo build -p hil-sim)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("sim.jsonl");
    let d = Daemon::start(
        dir.path(),
        "sim",
        "rrf",
        &format!(
            "[sim]\nspeed = 50.0\nbinary = {:?}\nrecord = {:?}\n",
            bin.display().to_string(),
            record.display().to_string()
        ),
    );
    let mut c = d.client();
    c.wait_connected();
    let status = c.call("machine.status", json!({})).unwrap();
    assert!(
        status["identity"]
            .as_str()
            .is_some_and(|i| i.contains("RepRapFirmware")),
        "{status}"
    );
    let id = c.call("job.submit", json!({"dry_run_moves": 120})).unwrap()["id"]
        .as_u64()
        .unwrap();
    c.wait_state(id, "done");
    drop(c);
    drop(d);
    let expected = move_lines(&offline(&planned_dry_run(120), "rrf"));
    // edod's SIGKILL in Drop stops hil-sim (--exit-with-parent); its recorder was
    // flushed as the job ended (the M400 after the last move was answered).
    let t = Instant::now();
    while ran(&record).len() < expected.len() && t.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_ran_once_in_order(&ran(&record), &expected, false);
}

/// A line without its plunger words (E, axes) and feed: where it goes. A resumed
/// job's writer starts its E rounding afresh, so E (and a plunger move's F) may differ
/// in the last digit.
fn motion(line: &str) -> String {
    line.split_whitespace()
        .filter(|w| !w.starts_with(['E', 'A', 'B', 'F']))
        .collect::<Vec<_>>()
        .join(" ")
}

/// edod killed with SIGKILL mid-job on `firmware`, restarted: the job is interrupted (not
/// resumed silently); resumed, it runs to the end, nothing skipped, the resume's service
/// moves between. Marlin and RRF name their last accepted line and edod the move it
/// belongs to (`docs/firmware.md`): at most `repeats_allowed` moves run twice (Marlin
/// none, RRF one); Klipper resumes from the last stored checkpoint. Returns how many
/// moves ran twice.
fn sigkill_mid_job_interrupts_and_resumes(
    firmware: &str,
    seed: u64,
    repeats_allowed: usize,
) -> usize {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record) = sim(dir.path(), firmware, seed);
    let port = sim.path().display().to_string();
    let mut d = Daemon::start(dir.path(), &port, firmware, "");
    let mut c = d.client();
    c.wait_connected();
    let id = c.call("job.submit", json!({"job": JOB})).unwrap()["id"]
        .as_u64()
        .unwrap();
    c.wait("streaming", |c| c.executed(id) > 200);
    drop(c);
    d.sigkill();
    // The firmware runs what it accepted.
    std::thread::sleep(Duration::from_millis(500));
    let before = ran(&record).len();
    let d = Daemon::spawn(dir.path().join("edod.sock"), &dir.path().join("edod.toml"));
    let mut c = d.client();
    c.wait_connected();
    let j = c.wait_state(id, "interrupted");
    assert!(
        j["reason"]
            .as_str()
            .is_some_and(|r| r.contains("restarted")),
        "{j}"
    );
    c.call("job.resume", json!({"id": id})).unwrap();
    c.wait_state(id, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let expected: Vec<String> = move_lines(&offline(&planned_job(), firmware))
        .iter()
        .map(|l| motion(l))
        .collect();
    let ran: Vec<String> = ran(&record).iter().map(|l| motion(l)).collect();
    // The first run: the file's lines up to where the resume's service moves start.
    let first = ran
        .iter()
        .zip(&expected)
        .take_while(|(a, b)| a == b)
        .count();
    assert!(first >= before, "first run: {first} of {before} lines");
    // The tail after the resume's service moves is the file from the resumed move on.
    let resumed_at = (0..=first)
        .find(|&s| ran.ends_with(&expected[s..]) && ran.len() - (expected.len() - s) >= first)
        .expect("the job's end runs in order after the resume, nothing skipped");
    let service = ran.len() - (expected.len() - resumed_at) - first;
    // Home, prime, the lifted travel and the descent to where the job stopped.
    assert!(service <= 4, "{service} service moves");
    let repeated = first - resumed_at;
    eprintln!(
        "{firmware}: ran {first} before the resume, resumed at {resumed_at}: {repeated} repeated"
    );
    assert!(
        repeated <= repeats_allowed,
        "{firmware}: {repeated} moves ran twice"
    );
    repeated
}

#[test]
fn marlin_sigkill_mid_job_resumes_running_every_move_once() {
    sigkill_mid_job_interrupts_and_resumes("marlin", 9, 0);
}

#[test]
fn rrf_sigkill_mid_job_resumes_running_at_most_one_move_twice() {
    sigkill_mid_job_interrupts_and_resumes("rrf", 11, 1);
}

#[test]
fn klipper_sigkill_mid_job_interrupts_and_resumes_skipping_nothing() {
    sigkill_mid_job_interrupts_and_resumes("klipper", 10, usize::MAX);
}
