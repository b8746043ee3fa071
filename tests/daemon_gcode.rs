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

use edo::gcode_link::writer::streamed_lines;
use edo::gcode_link::writer::GcodeSettings;
use edo::gcode_link::{command_word, Dialect, MixWriting};
use edo::machine::Move;
use serde_json::{json, Value};

#[path = "peers/octoprint.rs"]
mod peer;

struct Daemon {
    child: Child,
    socket: PathBuf,
}

impl Daemon {
    /// edod for `firmware` on `port` (a path, or `"sim"`), state in `dir`; `extra` is
    /// appended to the configuration.
    fn start(dir: &Path, port: &str, firmware: &str, extra: &str) -> Daemon {
        // Busy: above hil-sim's keepalive interval in the busy tests (`KEEPALIVE_MS`).
        Daemon::start_timed(dir, port, firmware, (300, 300), extra)
    }

    /// [`Daemon::start`] with the `ok` and busy timeouts (ms).
    fn start_timed(
        dir: &Path,
        port: &str,
        firmware: &str,
        (ok_ms, busy_ms): (u64, u64),
        extra: &str,
    ) -> Daemon {
        let socket = dir.join("edod.sock");
        let busy = match firmware {
            "marlin" => format!("busy_timeout_ms = {busy_ms}\n"),
            "klipper" => "axes = [\"A\", \"B\"]\n".to_string(),
            _ => String::new(),
        };
        let config = dir.join("edod.toml");
        std::fs::write(
            &config,
            format!(
                "[serial]\nport = {port:?}\nbaud = 250000\n\
                 [machine]\nprotocol = \"gcode\"\n\
                 [machine.gcode]\nfirmware = \"{firmware}\"\nok_timeout_ms = {ok_ms}\n{busy}\
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

    /// Submit `job`: its id.
    fn submit(&mut self, job: &str) -> u64 {
        self.call("job.submit", json!({ "job": job })).unwrap()["id"]
            .as_u64()
            .unwrap()
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

    /// Job `id` interrupted, for a reason that contains `why`.
    fn wait_interrupted(&mut self, id: u64, why: &str) {
        let j = self.wait_state(id, "interrupted");
        let reason = j["reason"].as_str().unwrap_or_default();
        assert!(reason.contains(why), "not {why:?}: {j}");
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

/// Marlin's `busy:` keepalive interval in hil-sim, ms: 2 s (`M113 S2`) scaled to the
/// tests' 300 ms `ok` and busy timeouts, as the stock 10 s and 5 s are to 2 s.
const KEEPALIVE_MS: u64 = 100;

/// hil-sim as `firmware`, in this process; its recorder.
fn sim(dir: &Path, firmware: &str, seed: u64) -> (hil_sim::SimHandle, PathBuf) {
    sim_with_keepalive(dir, firmware, seed, None)
}

/// [`sim`] with Marlin's keepalive interval (`None`: the model's 2 s).
fn sim_with_keepalive(
    dir: &Path,
    firmware: &str,
    seed: u64,
    keepalive_ms: Option<u64>,
) -> (hil_sim::SimHandle, PathBuf) {
    let record = dir.join("run.jsonl");
    let mut gcode = hil_sim::GcodeOptions::new(dialect(firmware), 2);
    gcode.keepalive_interval_ms = keepalive_ms;
    gcode.console = Some(dir.join("console.gcode"));
    let h = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.join("tty")),
        speed: 50.0,
        seed,
        record: Some(record.clone()),
        gcode: Some(gcode),
        ..hil_sim::SimConfig::default()
    })
    .unwrap();
    (h, record)
}

/// The `gcode` of every move the simulator ran, in order (a last line the recorder is
/// still writing left out).
fn ran(record: &Path) -> Vec<String> {
    std::fs::read_to_string(record)
        .unwrap()
        .split_inclusive('\n')
        .filter(|l| l.ends_with('\n'))
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
    edo::gcode_link::writer::write_gcode(moves, 2, &settings, &[], &mut text).unwrap();
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
height = 0.8
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
    let machine = edo::setup::MachineConfig::default();
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

/// Whether a line names X, Y or Z: where it ends tells it from the line before it.
fn names_xyz(line: &str) -> bool {
    line.split_whitespace()
        .skip(1)
        .any(|w| w.starts_with(['X', 'Y', 'Z']))
}

/// Every line in `expected` ran once and in order. `repeats_allowed`: RRF, where a line
/// whose `ok` was lost and which ends where the line before it does (a retract, a prime,
/// a dwell) is sent again and runs twice, right after itself (`docs/firmware.md`, "Exactly
/// once by position"); a line that names X, Y or Z never does. Returns how many ran twice.
fn assert_ran_once_in_order(ran: &[String], expected: &[String], repeats_allowed: bool) -> usize {
    let mut collapsed: Vec<&String> = Vec::with_capacity(ran.len());
    let mut repeats = 0;
    for l in ran {
        if repeats_allowed && collapsed.last() == Some(&l) && !names_xyz(l) {
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

/// Lines a G-code connection sends of its own, in no file (`docs/firmware.md`, "What
/// edod streams"): the handshake, and `M400` when nothing else is left to send.
const LINK_ONLY: [&str; 4] = ["M110", "M115", "M555", "M400"];

/// `edoctl plan JOB --machine EDOD.TOML --gcode FILE` is what edod streams: on `firmware`,
/// what the simulated firmware ran for [`JOB`] (its console log, less the link's own
/// lines) is the connection prologue and then the file's lines, less comments, one for
/// one: the job's first line to the Klipper epilogue.
fn plan_machine_equals_what_edod_streams(firmware: &str) {
    let dir = tempfile::tempdir().unwrap();
    let (sim, _record) = sim(dir.path(), firmware, 3);
    let d = Daemon::start(dir.path(), &sim.path().display().to_string(), firmware, "");
    let mut c = d.client();
    c.wait_connected();
    let id = c.submit(JOB);
    c.wait_state(id, "done");
    let job = dir.path().join("job.toml");
    std::fs::write(&job, JOB).unwrap();
    let file = dir.path().join("job.gcode");
    let out = Command::new(env!("CARGO_BIN_EXE_edoctl"))
        .args(["plan", "--quiet", "--machine"])
        .arg(dir.path().join("edod.toml"))
        .arg("--gcode")
        .arg(&file)
        .arg(&job)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let config = edo::daemon::config::Config::load(&dir.path().join("edod.toml")).unwrap();
    let settings = config.gcode_link().unwrap().unwrap().settings();
    let mut prologue = Vec::new();
    edo::gcode_link::writer::MoveWriter::new(2, &settings)
        .unwrap()
        .connection_prologue(&mut prologue);
    let text = std::fs::read_to_string(&file).unwrap();
    let expected: Vec<String> = prologue
        .iter()
        .flat_map(|l| streamed_lines(l))
        .chain(streamed_lines(&text))
        .map(str::to_string)
        .collect();
    // The Klipper epilogue goes once every line was acknowledged: wait for the last.
    let console = dir.path().join("console.gcode");
    let ran = || -> Vec<String> {
        std::fs::read_to_string(&console)
            .unwrap()
            .lines()
            .filter(|l| !LINK_ONLY.contains(&command_word(l).unwrap_or_default().as_str()))
            .map(str::to_string)
            .collect()
    };
    let t = Instant::now();
    while ran().last() != expected.last() && t.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let ran = ran();
    let first_difference = ran.iter().zip(&expected).position(|(a, b)| a != b);
    assert_eq!(
        (first_difference, ran.len()),
        (None, expected.len()),
        "{firmware}: edod streamed {} lines, the file has {}; first difference at {:?}: ran {:?}, file {:?}",
        ran.len(),
        expected.len(),
        first_difference,
        first_difference.and_then(|k| ran.get(k)),
        first_difference.and_then(|k| expected.get(k)),
    );
    assert!(
        expected.len() > 200,
        "{} lines: too small a job",
        expected.len()
    );
}

#[test]
fn plan_machine_equals_what_edod_streams_to_rrf() {
    plan_machine_equals_what_edod_streams("rrf");
}

#[test]
fn plan_machine_equals_what_edod_streams_to_marlin() {
    plan_machine_equals_what_edod_streams("marlin");
}

#[test]
fn plan_machine_equals_what_edod_streams_to_klipper() {
    plan_machine_equals_what_edod_streams("klipper");
}

/// A graded job on `firmware` with `faults`: done, every line of the offline file ran
/// once and in order, and the per-drive volumes are the file's E totals. RRF: a line
/// may run twice, right after itself, and no more lines than edod sent again after a
/// timeout (`frames_retransmitted`: RRF has no resend requests). Busy periods run with
/// Marlin's keepalives at [`KEEPALIVE_MS`].
fn job_streams_the_offline_file(firmware: &str, faults: &str, seed: u64) {
    let dir = tempfile::tempdir().unwrap();
    let keepalive = faults.contains("busy=").then_some(KEEPALIVE_MS);
    let (sim, record) = sim_with_keepalive(dir.path(), firmware, seed, keepalive);
    let d = Daemon::start(dir.path(), &sim.path().display().to_string(), firmware, "");
    let mut c = d.client();
    c.wait_connected();
    // Faults once connected (the handshake under faults is the line protocol's tests').
    for f in faults.split(',').filter(|f| !f.is_empty()) {
        sim.command(hil_sim::Command::parse(f).unwrap());
    }
    let id = c.submit(JOB);
    let done = c.wait_state(id, "done");
    let planned = planned_job();
    assert_eq!(done["total_moves"].as_u64(), Some(planned.len() as u64));
    let status = c.call("machine.status", json!({})).unwrap();
    drop(c);
    drop(d);
    let summary = sim.stop().unwrap();
    let text = offline(&planned, firmware);
    let expected = move_lines(&text);
    let repeats = assert_ran_once_in_order(&ran(&record), &expected, firmware == "rrf");
    let sent_again = status["frames_retransmitted"].as_u64().unwrap_or(0);
    assert!(
        repeats as u64 <= sent_again,
        "{repeats} lines ran twice, {sent_again} sent again"
    );
    assert!(
        expected.len() > 50,
        "{} move lines: too small a job",
        expected.len()
    );
    // Per-drive E of the file, in nl as the simulator turns travel into volume.
    let flavor = GcodeSettings::for_mix(&mix_of(firmware), AREA_MM2).flavor;
    let file_e = edo::gcode_link::writer::summed_drive_e(&text, 2, flavor);
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
        "{firmware} {faults:?}: {} lines, {repeats} repeated, {sent_again} sent again, {summary:?}",
        expected.len()
    );
    // Each fault asked for happened (the seeds are fixed; a rate too low tests nothing).
    for (fault, count) in [
        ("corrupt-", summary.bits_flipped),
        ("drop-ok=", summary.frames_dropped),
        ("resend=", summary.resend_requests),
        ("busy=", summary.busy_periods),
    ] {
        assert!(
            !faults.contains(fault) || count > 0,
            "{fault} never happened: {summary:?}"
        );
    }
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

// The fault matrix (`docs/firmware.md`, "What is promised"): every line fault hil-sim
// puts on a firmware's link at once, through edod. Reset and unplug mid-job: below.

/// Marlin: lines corrupted on the way to the firmware (line errors, `Resend:`) and
/// replies corrupted on the way back, `ok`s lost (the probe), resend requests out of
/// the blue, busy periods longer than the `ok` timeout (the keepalives hold the link):
/// every line runs once, in order.
#[test]
fn marlin_every_line_fault_at_once_runs_every_line_once_in_order() {
    job_streams_the_offline_file(
        "marlin",
        "corrupt-line=0.03,corrupt-reply=0.02,drop-ok=0.01,resend=0.02,busy=0.01,busy-for=800",
        12,
    );
}

/// RRF: the same, less resend requests (RRF sends none: a bad line is dropped
/// silently). RRF has no busy protocol: its `ok` timeout must exceed the longest wait
/// for an `ok`, so the busy periods here are shorter than it (300 ms); a corrupted
/// `ok` is a lost one. Nothing is lost or reordered; a line runs twice only right after
/// itself, where edod sent it again.
#[test]
fn rrf_every_line_fault_at_once_loses_and_reorders_nothing() {
    job_streams_the_offline_file(
        "rrf",
        "corrupt-line=0.03,corrupt-reply=0.02,drop-ok=0.01,busy=0.01,busy-for=200",
        13,
    );
}

/// Klipper: its pseudo-terminal corrupts and loses nothing and Klipper sends no resend
/// requests, so of the line faults only busy periods apply (shorter than the link's
/// patience: 4 `ok` timeouts in a row mean Klipper stopped reading). Every line once,
/// in order.
#[test]
fn klipper_busy_periods_run_every_line_once_in_order() {
    job_streams_the_offline_file("klipper", "busy=0.01,busy-for=600", 14);
}

/// A dry run on `firmware`: paused mid-job (no line runs once the firmware finished what
/// it accepted), resumed, e-stopped (acknowledged, job interrupted), resumed while the
/// firmware is halted (interrupted again: reset the machine); what ran is the start of
/// the offline file, each line once.
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
    // The firmware stays halted until the machine is reset: a resume now does not wait
    // for ever, the job is interrupted again and says why.
    c.call("job.resume", json!({"id": id})).unwrap();
    let t = Instant::now();
    c.wait_interrupted(id, "reset the machine");
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
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

/// Each line without its plunger words (E, axes) and feed, its X Y Z made absolute
/// (lines leave out what did not change): where it goes. A resumed job's writer
/// starts afresh, so its first line spells out what the file's leaves out, and its E
/// (and a plunger move's F) may differ in the last digit.
fn motions(lines: &[String]) -> Vec<String> {
    let mut at: [Option<String>; 3] = [None, None, None];
    lines
        .iter()
        .map(|line| {
            let mut words = line.split_whitespace();
            let command = words.next().unwrap_or_default();
            if command == "G28" {
                at = [None, None, None];
            }
            let mut rest = Vec::new();
            for w in words {
                match w.chars().next() {
                    Some('X') => at[0] = Some(w.to_string()),
                    Some('Y') => at[1] = Some(w.to_string()),
                    Some('Z') => at[2] = Some(w.to_string()),
                    Some('E' | 'A' | 'B' | 'F') => {}
                    _ => rest.push(w),
                }
            }
            let moves = line
                .split_whitespace()
                .any(|w| w.starts_with(['X', 'Y', 'Z']));
            let mut out = vec![command.to_string()];
            if moves {
                out.extend(at.iter().flatten().cloned());
            }
            out.extend(rest.into_iter().map(str::to_string));
            out.join(" ")
        })
        .collect()
}

/// hil-sim as `firmware` and edod on it in `dir`, [`JOB`] submitted and past its 200th
/// move: the simulator, its recorder, edod, a client and the job's id.
fn job_streaming(
    dir: &Path,
    firmware: &str,
    seed: u64,
) -> (hil_sim::SimHandle, PathBuf, Daemon, Client, u64) {
    let (sim, record) = sim(dir, firmware, seed);
    let d = Daemon::start(dir, &sim.path().display().to_string(), firmware, "");
    let mut c = d.client();
    c.wait_connected();
    let id = c.submit(JOB);
    c.wait("streaming", |c| c.executed(id) > 200);
    (sim, record, d, c, id)
}

/// Marlin going silent mid-job (every line and reply lost) shows in `machine.status` as
/// `link_problem` while still connected, long before the link is declared lost: once the
/// oldest line's `ok` is overdue for what that line may wait for (a move: the `ok`
/// timeout, 300 ms here; a `G4` or `M400`: every move the planner may hold, twice, capped
/// by `slow_command_timeout_s`, 2 s here) edod asks it where it is. Answering again, the
/// problem clears and the job ends with every line run once.
#[test]
fn a_silent_marlin_is_reported_at_once_and_the_job_goes_on_when_it_answers() {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, id) = job_streaming(dir.path(), "marlin", 21);
    let silent = Instant::now();
    sim.command(hil_sim::Command::parse("drop=1").unwrap());
    let mut status = Value::Null;
    c.wait("link_problem reported", |c| {
        status = c.call("machine.status", json!({})).unwrap();
        status["link_problem"].is_string()
    });
    // The longest the oldest line may wait (a `G4` behind 16 moves of up to 265 ms:
    // capped at the 2 s slow-command timeout), plus the status polls.
    assert!(
        silent.elapsed() < Duration::from_millis(2_500),
        "{:?}",
        silent.elapsed()
    );
    assert_eq!(status["connected"], json!(true), "{status}");
    let problem = status["link_problem"].as_str().unwrap();
    assert!(problem.contains("Marlin has not acknowledged"), "{problem}");
    sim.command(hil_sim::Command::parse("drop=0").unwrap());
    c.wait("link_problem cleared", |c| {
        c.call("machine.status", json!({})).unwrap()["link_problem"].is_null()
    });
    c.wait_state(id, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let expected = move_lines(&offline(&planned_job(), "marlin"));
    assert_ran_once_in_order(&ran(&record), &expected, false);
}

/// edod killed with SIGKILL mid-job on `firmware`, restarted: the job is interrupted (not
/// resumed silently); resumed, it runs to the end, nothing skipped, the resume's service
/// moves between. Marlin and RRF name their last accepted line and edod the move it
/// belongs to (`docs/firmware.md`): at most `repeats_allowed` moves run twice (Marlin
/// none, RRF one); Klipper's nozzle position after `M400` (`GET_POSITION`) names the last move
/// that ran. Returns how many moves ran twice.
fn sigkill_mid_job_interrupts_and_resumes(
    firmware: &str,
    seed: u64,
    repeats_allowed: usize,
) -> usize {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, mut d, c, id) = job_streaming(dir.path(), firmware, seed);
    drop(c);
    let streaming = sim.status().expect("the simulator answers");
    assert_eq!(streaming["idle"], false, "{firmware} mid-job: {streaming}");
    d.sigkill();
    // The firmware runs what it accepted.
    assert!(
        sim.wait_idle(Duration::from_secs(10)),
        "{firmware}: the machine still runs 10 s after edod was killed: {:?}",
        sim.status()
    );
    let before = ran(&record).len();
    let d = Daemon::spawn(dir.path().join("edod.sock"), &dir.path().join("edod.toml"));
    let mut c = d.client();
    c.wait_connected();
    c.wait_interrupted(id, "restarted");
    c.call("job.resume", json!({"id": id})).unwrap();
    c.wait_state(id, "done");
    drop(c);
    drop(d);
    sim.stop().unwrap();
    let repeated = resumed_job_skipped_nothing(&record, firmware, before, repeats_allowed, true);
    keep_console_for_the_peer(dir.path(), firmware);
    repeated
}

/// What the firmware ran, for tests/peers/run_klipper_peer.sh to run through Klipper's
/// own klippy: copied to `EDO_RESUMED_STREAM_<FIRMWARE>` when that is set.
fn keep_console_for_the_peer(dir: &Path, firmware: &str) {
    let var = format!("EDO_RESUMED_STREAM_{}", firmware.to_uppercase());
    if let Some(to) = std::env::var_os(var) {
        std::fs::copy(dir.join("console.gcode"), to).unwrap();
    }
}

/// The recording of [`JOB`] run on `firmware`, interrupted after at least `before` lines
/// ran and resumed: the file's start, the resume's service moves, then the file from the
/// move resumed at to its end; nothing skipped, at most `repeats_allowed` of the file's
/// move lines ran twice (`after_sigkill`: on Klipper, only where the nozzle's position
/// could not tell). Returns how many did.
fn resumed_job_skipped_nothing(
    record: &Path,
    firmware: &str,
    before: usize,
    repeats_allowed: usize,
    after_sigkill: bool,
) -> usize {
    let expected = motions(&move_lines(&offline(&planned_job(), firmware)));
    let ran = motions(&ran(record));
    // The first run: the file's lines up to where the resume's service moves start.
    let first = ran
        .iter()
        .zip(&expected)
        .take_while(|(a, b)| a == b)
        .count();
    assert!(first >= before, "first run: {first} of {before} lines");
    // Then the resume's service moves: home, prime and, once any move ran, the lifted
    // travel and the descent to where the job stopped. Counted, not matched: the descent
    // reads as the job's own travel when that was the last move run (the same X Y Z).
    assert_eq!(
        ran.get(first).map(String::as_str),
        Some("G28"),
        "the resume homes first"
    );
    let position_known = ran[..first]
        .iter()
        .any(|l| l.starts_with("G0 X") || l.starts_with("G1 X"));
    let service = if position_known { 4 } else { 2 };
    // The tail after them is the file from the resumed move to its end.
    let tail = ran
        .len()
        .checked_sub(first + service)
        .expect("the service moves ran");
    let resumed_at = expected
        .len()
        .checked_sub(tail)
        .expect("no more lines after the resume than the file has");
    assert_eq!(
        &ran[first + service..],
        &expected[resumed_at..],
        "the job's end runs in order after the resume, nothing skipped"
    );
    // Klipper after edod's SIGKILL: the job's retract, prime and dwell where the nozzle
    // stopped count as run (a retract run twice drives the plungers back, and the
    // resume's own prime, after homing, stands in for them: docs/firmware.md). Those
    // plunger-only lines and dwells are all that may be left out; no line that moves
    // the nozzle is.
    let skippable = |l: &String| l == "G1" || l.starts_with("G4 ");
    let not_run = &expected[first.min(resumed_at)..resumed_at];
    assert!(
        resumed_at <= first
            || (firmware == "klipper" && after_sigkill && not_run.iter().all(skippable)),
        "resumed at {resumed_at}, after the {first} lines run: skipped {not_run:?}"
    );
    let repeated = first.saturating_sub(resumed_at);
    if firmware == "rrf" && repeats_allowed == 1 {
        // After a lost link or edod's SIGKILL (one move in doubt, not a reset's
        // checkpoint), RRF's position tells a line that ran from one it dropped unless the two end
        // at one place: only such a line may run twice.
        let xyz = |l: &str| -> Vec<String> {
            l.split_whitespace()
                .filter(|w| w.starts_with(['X', 'Y', 'Z']))
                .map(str::to_string)
                .collect()
        };
        for k in resumed_at..first {
            assert!(
                k > 0 && xyz(&expected[k]) == xyz(&expected[k - 1]),
                "rrf: line {k} ({}) ran twice although it ends elsewhere than the line before",
                expected[k]
            );
        }
    }
    if firmware == "klipper" && after_sigkill && first > 0 && resumed_at > 0 {
        // The move edod took for the last run ends where the nozzle stopped: a repeat
        // only where two stretches of the job end at one place. Where line k leaves the
        // nozzle: each axis' last word at or before it.
        let ends_at = |k: usize| -> Vec<Option<&str>> {
            ['X', 'Y', 'Z']
                .iter()
                .map(|&axis| {
                    expected[..=k]
                        .iter()
                        .rev()
                        .find_map(|l| l.split_whitespace().find(|w| w.starts_with(axis)))
                })
                .collect()
        };
        assert_eq!(
            ends_at(resumed_at - 1),
            ends_at(first - 1),
            "klipper: resumed after line {resumed_at}, but the nozzle stopped after line {first}"
        );
    }
    eprintln!(
        "{firmware}: ran {first} before the resume, resumed at {resumed_at}: {repeated} \
         repeated, {} plunger-only or dwell lines taken as run",
        not_run.len()
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

/// RRF: the nozzle's position says whether the last line parsed ran; only a line that
/// ends where the one before it does (a retract, a prime, a dwell) may run twice.
#[test]
fn rrf_sigkill_mid_job_resumes_running_every_positioned_move_once() {
    sigkill_mid_job_interrupts_and_resumes("rrf", 11, 1);
}

/// Klipper: where the nozzle stopped names the last move that ran; only where two
/// stretches of the job end at one place may moves run again.
#[test]
fn klipper_sigkill_mid_job_interrupts_and_resumes_skipping_nothing() {
    sigkill_mid_job_interrupts_and_resumes("klipper", 10, usize::MAX);
}

/// Moves the firmware's queue and planner hold on a stock build (`docs/firmware.md`,
/// "Which lines the firmware accepted"): after a machine reset the job resumes from its
/// checkpoint, which trails the accepted moves by at most this many.
fn held_at_most(firmware: &str) -> usize {
    match firmware {
        "marlin" => 4 + 16,
        "rrf" => 1 + 40,
        _ => 20 + 32,
    }
}

/// Why a job is interrupted by a pulled cable: the port's end of file, or, when the
/// firmware's silence outlasts the ok timeouts before edod reads it (a loaded host), the
/// lost link (`docs/firmware.md`, "What edod learns after a lost link").
const UNPLUG_REASONS: &[&str] = &["serial port lost", "link to the machine lost"];

/// `fault` (hil-sim's `reset` or `unplug`) mid-job on `firmware`: the job is interrupted
/// for one of `reasons`, and edod connects again; resumed, it runs to the end, nothing
/// skipped, the resume's service moves between, at most `repeats_allowed` moves twice.
fn fault_mid_job_interrupts_and_resumes(
    firmware: &str,
    seed: u64,
    fault: hil_sim::Command,
    reasons: &[&str],
    repeats_allowed: usize,
) -> usize {
    let dir = tempfile::tempdir().unwrap();
    let (sim, record, d, mut c, id) = job_streaming(dir.path(), firmware, seed);
    let before = ran(&record).len();
    sim.command(fault);
    let j = c.wait_state(id, "interrupted");
    let reason = j["reason"].as_str().unwrap_or_default();
    assert!(reasons.iter().any(|r| reason.contains(r)), "{j}");
    // Connected again, and not halted (Klipper's `Disconnect` halts it until `Ready`).
    c.wait("machine connected, not halted", |c| {
        let m = c.call("machine.status", json!({})).unwrap();
        m["connected"] == json!(true) && m["state"] != json!("EStopped")
    });
    c.call("job.resume", json!({"id": id})).unwrap();
    c.wait_state(id, "done");
    drop(c);
    drop(d);
    let summary = sim.stop().unwrap();
    eprintln!("{firmware} {reason:?}: {summary:?}");
    resumed_job_skipped_nothing(&record, firmware, before, repeats_allowed, false)
}

/// A machine reset loses the firmware's queue and planner: the job is interrupted, not
/// resumed silently; resumed, it starts from its checkpoint (the first move that may not
/// have run): nothing is skipped, at most the moves the firmware held run twice.
#[test]
fn marlin_reset_mid_job_resumes_skipping_nothing() {
    fault_mid_job_interrupts_and_resumes(
        "marlin",
        15,
        hil_sim::Command::Reset,
        &["machine reset"],
        held_at_most("marlin"),
    );
}

/// RRF's reset re-enumerates its native USB port: edod sees the port vanish.
#[test]
fn rrf_reset_mid_job_resumes_skipping_nothing() {
    fault_mid_job_interrupts_and_resumes(
        "rrf",
        16,
        hil_sim::Command::Reset,
        &["machine reset", "serial port lost"],
        held_at_most("rrf"),
    );
}

/// Klipper restarting (`Disconnect`, then `Ready`): its queue and lookahead are lost.
/// edod takes `Disconnect` for a halt it did not ask for (a machine fault) and `Ready`
/// for the restart.
#[test]
fn klipper_restart_mid_job_resumes_skipping_nothing() {
    fault_mid_job_interrupts_and_resumes(
        "klipper",
        17,
        hil_sim::Command::Reset,
        &["machine reset", "Klipper state: Disconnect"],
        held_at_most("klipper"),
    );
}

/// Marlin, cable pulled mid-job: the firmware runs what it accepted; on the port's
/// return the probe names the last line it accepted and the job resumes after it:
/// every move exactly once.
#[test]
fn marlin_unplug_mid_job_resumes_running_every_move_once() {
    fault_mid_job_interrupts_and_resumes("marlin", 18, hil_sim::Command::Unplug, UNPLUG_REASONS, 0);
}

/// RRF, cable pulled mid-job: `M409`'s `lineNumber` names the last line parsed (maybe
/// one it dropped) and the nozzle's position whether it ran: only a line ending where
/// the one before it does may run twice.
#[test]
fn rrf_unplug_mid_job_resumes_running_every_positioned_move_once() {
    fault_mid_job_interrupts_and_resumes("rrf", 19, hil_sim::Command::Unplug, UNPLUG_REASONS, 1);
}

/// Klipper, its pty gone mid-job: nothing says what ran; the job is interrupted and
/// resumed from its checkpoint: nothing skipped, at most what Klipper held runs twice,
/// and the lines in flight (the window, 8) whose `ok` did not come back before the pty
/// went.
#[test]
fn klipper_unplug_mid_job_resumes_skipping_nothing() {
    fault_mid_job_interrupts_and_resumes(
        "klipper",
        20,
        hil_sim::Command::Unplug,
        UNPLUG_REASONS,
        held_at_most("klipper") + 8,
    );
}

/// A real peer through edod: OctoPrint's virtual printer (`tests/peers/`, a Marlin model
/// written by others) as edod's machine (`firmware = "marlin"`, the port its pty), with
/// its own faults on ([`peer::FAULTS`]: every 20th line a checksum error, its simulated
/// errors, `busy` keepalives every 0.5 s). [`JOB`] runs to the end, and the commands the
/// printer ran are edod's connection prologue, then the offline file's (`edoctl plan
/// --gcode --flavor marlin`, less comments), each once and in order, less the handshake
/// and the `M400`s edod adds. Skipped unless `EDO_OCTOPRINT_PY` names the python of a
/// venv with octoprint (`tests/peers/run_octoprint_peer.sh`).
#[test]
fn octoprint_virtual_printer_through_edod_runs_the_offline_file() {
    let Some(python) = peer::python() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (_shim, ready) = peer::start_shim(&python, dir.path(), peer::FAULTS);
    eprintln!("{ready}");
    let port = dir.path().join("tty").display().to_string();
    // Its busy keepalives come every 0.5 s; its missing line number is found by the
    // timeout and the probe.
    let d = Daemon::start_timed(dir.path(), &port, "marlin", (2000, 2000), "");
    let mut c = d.client();
    c.wait_connected();
    let id = c.submit(JOB);
    c.wait_state(id, "done");
    let status = c.call("machine.status", json!({})).unwrap();
    drop(c);
    drop(d);
    eprintln!("{status}");
    let file = offline(&planned_job(), "marlin");
    let mut expected: Vec<String> = Vec::new();
    let settings = GcodeSettings::for_mix(&mix_of("marlin"), AREA_MM2);
    let mut prologue = Vec::new();
    edo::gcode_link::writer::MoveWriter::new(2, &settings)
        .unwrap()
        .preamble(&[], &mut prologue);
    expected.extend(streamed_lines(&prologue.join("\n")).map(str::to_string));
    expected.extend(streamed_lines(&file).map(str::to_string));
    let received = std::fs::read_to_string(dir.path().join("received.log")).unwrap();
    let ran: Vec<&str> = received
        .lines()
        // Less the handshake's M115, the probe's M105, the M400s and the empty lines the
        // probe's leading newline makes.
        .filter(|l| !matches!(*l, "M115" | "M105" | "M400" | ""))
        .collect();
    assert!(
        status["frames_retransmitted"].as_u64().unwrap_or(0) >= 10,
        "its faults were on: {status}"
    );
    assert_eq!(
        ran, expected,
        "the printer ran the file's commands, each once"
    );
}
