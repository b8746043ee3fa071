//! `hil-sim --gcode` over a real pty, driven by the sans-IO G-code host
//! (`edo::gcode_link::LineHost`) with wall-clock timers: every firmware's job lands in the
//! recorder exactly as promised in `docs/firmware.md` through seeded line faults (both
//! ways), resend requests out of the blue, busy periods, a firmware reset and an unplug.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{ErrorKind, Read, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use edo::gcode_link::{
    Dialect, LastAccepted, LineEvent, LineHost, LineLinkConfig, LinkState, Micros,
};
use hil_sim::{Faults, GcodeOptions, SimConfig, Summary};

/// What a run saw.
#[derive(Debug, Default)]
struct Run {
    /// The commands the recorder saw executed, in order.
    executed: Vec<String>,
    maybe_repeated: u64,
    inexact: u64,
    resets: u64,
    recoveries: u64,
    /// Lines sent again (resend requests, probes, RRF timeouts).
    sent_again: u64,
    /// Times the port hung up (unplugged) and was opened again.
    reopened: u64,
    /// What the simulator injected.
    sim: Summary,
}

struct Driver {
    path: PathBuf,
    port: File,
    host: LineHost,
    start: Instant,
    /// The port hung up (EIO): the cable was pulled.
    hung_up: bool,
}

impl Driver {
    fn now(&self) -> Micros {
        Micros(self.start.elapsed().as_micros() as u64)
    }

    /// Bytes in, timers, bytes out; the events.
    fn pump(&mut self) -> Vec<LineEvent> {
        let mut buf = [0u8; 4096];
        loop {
            match self.port.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => {
                    let now = self.now();
                    self.host.handle_bytes(&buf[..n], now);
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => {
                    self.hung_up = true;
                    break;
                }
                Err(e) => panic!("read: {e}"),
            }
        }
        let now = self.now();
        self.host.handle_timeout(now);
        while let Some(bytes) = self.host.poll_transmit(now) {
            let mut rest = &bytes[..];
            while !rest.is_empty() {
                match self.port.write(rest) {
                    Ok(n) => rest = &rest[n..],
                    Err(e) if e.kind() == ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(1))
                    }
                    // Unplugged: the bytes are lost, as on a pulled cable.
                    Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => {
                        self.hung_up = true;
                        break;
                    }
                    Err(e) => panic!("write: {e}"),
                }
            }
        }
        std::iter::from_fn(|| self.host.poll_event()).collect()
    }
}

fn try_open_port(path: &Path) -> std::io::Result<File> {
    OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
        .open(path)
}

fn open_port(path: &Path) -> File {
    try_open_port(path).unwrap_or_else(|e| panic!("open {}: {e}", path.display()))
}

impl Driver {
    /// After a hang-up: open the port again once the cable is back (the symlink points
    /// at the new pty).
    fn reopen_when_back(&mut self, run: &mut Run) {
        let deadline = Instant::now() + Duration::from_secs(10);
        // The old symlink may still be there for a moment: wait for it to go first.
        std::thread::sleep(Duration::from_millis(50));
        loop {
            assert!(Instant::now() < deadline, "the port did not come back");
            if let Ok(p) = try_open_port(&self.path) {
                self.port = p;
                break;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        self.hung_up = false;
        run.reopened += 1;
    }
}

/// A job line, unique per index, in the dialect's mix writing.
fn job_line(dialect: Dialect, i: u32) -> String {
    let x = 10.0 + f64::from(i % 50) * 0.5;
    let y = 10.0 + f64::from(i / 50) * 0.5;
    match dialect {
        Dialect::Rrf => format!("G1 X{x:.3} Y{y:.3} E0.0010:0.0020 F3000"),
        Dialect::Marlin => format!("G1 X{x:.3} Y{y:.3} E0.0030 F3000"),
        Dialect::Klipper => format!(
            "G1 X{x:.3} Y{y:.3} A{:.4} B{:.4} F3000",
            f64::from(i + 1) * 0.001,
            f64::from(i + 1) * 0.002
        ),
    }
}

fn recorded(record: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(record).unwrap_or_default();
    edo::machine::record::parse(&text)
        .unwrap_or_default()
        .into_iter()
        .filter_map(|l| l.gcode)
        .collect()
}

struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> Self {
        let p = std::env::temp_dir().join(format!("hil-sim-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Stream `lines` job lines to `hil-sim --gcode` with `faults`; resume as the lifecycle
/// does: after a reset from the first line not recorded, after a lost link from what the
/// firmware says it accepted.
fn stream(dialect: Dialect, lines: u32, faults: &str, name: &str) -> Run {
    let dir = TempDir::new(name);
    let record = dir.0.join("run.jsonl");
    let sim = hil_sim::spawn(SimConfig {
        link: Some(dir.0.join("tty")),
        speed: 50.0,
        seed: 7,
        record: Some(record.clone()),
        faults: Faults::parse(faults).unwrap(),
        gcode: Some(GcodeOptions::new(dialect, 2)),
        ..SimConfig::default()
    })
    .unwrap();
    let mut cfg = LineLinkConfig::for_dialect(dialect);
    cfg.ok_timeout_us = 400_000;
    cfg.busy_timeout_us = 400_000;
    cfg.handshake_timeout_us = 1_000_000;
    let text: Vec<String> = (0..lines).map(|i| job_line(dialect, i)).collect();
    let index: HashMap<&str, u32> = text
        .iter()
        .enumerate()
        .map(|(i, t)| (t.as_str(), i as u32))
        .collect();
    let mut d = Driver {
        path: sim.path().to_path_buf(),
        port: open_port(sim.path()),
        host: LineHost::new(cfg),
        start: Instant::now(),
        hung_up: false,
    };
    let mut run = Run::default();
    let mut next = 0u32;
    d.host.connect(d.now());
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        assert!(Instant::now() < deadline, "{dialect:?}: timed out: {run:?}");
        if d.host.state() == LinkState::Streaming {
            while next < lines && d.host.queued_len() < 16 {
                d.host
                    .send_line(&text[next as usize], u64::from(next))
                    .unwrap();
                next += 1;
            }
        }
        let mut resume = None;
        let events = d.pump();
        if d.hung_up && !(d.host.state() == LinkState::Reset && dialect == Dialect::Rrf) {
            d.reopen_when_back(&mut run);
        }
        for e in events {
            match e {
                LineEvent::MaybeRepeated { .. } => run.maybe_repeated += 1,
                LineEvent::Reset { .. } => {
                    run.resets += 1;
                    resume = Some(None);
                }
                LineEvent::LinkLost { .. } | LineEvent::Stopped { .. } => {
                    d.host.recover_last_accepted(d.now()).unwrap();
                }
                LineEvent::LastAccepted(LastAccepted::Known {
                    resume_tag, exact, ..
                }) => {
                    run.recoveries += 1;
                    run.inexact += u64::from(!exact);
                    resume = Some(resume_tag.map(|t| t as u32));
                }
                LineEvent::LastAccepted(LastAccepted::Unknown { .. }) => resume = Some(None),
                _ => {}
            }
        }
        if let Some(tag) = resume {
            // The machine lost its queue (or cannot say): go on after what it executed.
            std::thread::sleep(Duration::from_millis(300));
            if d.host.state() == LinkState::Reset && dialect == Dialect::Rrf {
                std::thread::sleep(Duration::from_millis(1500)); // USB re-enumerates
                d.port = open_port(sim.path());
                d.hung_up = false;
            }
            let done = recorded(&record);
            let after = done
                .last()
                .and_then(|t| index.get(t.as_str()))
                .map_or(0, |i| i + 1);
            next = tag.unwrap_or(after);
            d.host.connect(d.now());
        }
        let done = recorded(&record);
        if done.len() >= lines as usize
            && done.last().map(String::as_str) == Some(text[lines as usize - 1].as_str())
        {
            run.executed = done;
            break;
        }
        std::thread::sleep(Duration::from_micros(500));
    }
    let stats = d.host.stats();
    run.sent_again = stats.lines_resent + stats.lines_repeated;
    run.sim = sim.stop().unwrap();
    run
}

fn expected(dialect: Dialect, lines: u32) -> Vec<String> {
    (0..lines).map(|i| job_line(dialect, i)).collect()
}

#[test]
fn marlin_runs_every_line_exactly_once_through_line_faults_and_a_reset() {
    let lines = 300;
    let run = stream(
        Dialect::Marlin,
        lines,
        "corrupt-line=0.03,drop-ok=0.02,reset-at=150",
        "marlin",
    );
    assert_eq!(run.executed, expected(Dialect::Marlin, lines), "{run:?}");
    assert_eq!(run.resets, 1, "{run:?}");
    assert!(
        run.sent_again > 0,
        "the line faults were exercised: {run:?}"
    );
}

/// RRF drops a corrupted line silently and a lost `ok` looks the same: the nozzle's
/// position (`M409 K"move.axes"`, answered by hil-sim's RRF) tells which, so every line
/// runs exactly once.
#[test]
fn rrf_runs_every_line_exactly_once_through_line_faults() {
    let lines = 300;
    let run = stream(Dialect::Rrf, lines, "corrupt-line=0.03,drop-ok=0.02", "rrf");
    assert_eq!(run.executed, expected(Dialect::Rrf, lines), "{run:?}");
    assert_eq!((run.maybe_repeated, run.inexact), (0, 0), "{run:?}");
    assert!(
        run.sent_again > 0,
        "the line faults were exercised: {run:?}"
    );
}

#[test]
fn klipper_runs_every_line_once_through_a_restart() {
    let lines = 300;
    let run = stream(Dialect::Klipper, lines, "reset-at=150", "klipper");
    assert_eq!(run.executed, expected(Dialect::Klipper, lines), "{run:?}");
    assert_eq!(run.resets, 1, "{run:?}");
}

#[test]
fn marlin_runs_every_line_once_through_busy_periods_resend_requests_and_bad_replies() {
    let lines = 300;
    let run = stream(
        Dialect::Marlin,
        lines,
        "resend=0.03,busy=0.03,busy-for=300,corrupt-reply=0.02",
        "marlin-busy",
    );
    assert_eq!(run.executed, expected(Dialect::Marlin, lines), "{run:?}");
    assert!(run.sim.resend_requests > 0, "{run:?}");
    assert!(run.sim.busy_periods > 0, "{run:?}");
    assert!(run.sim.bits_flipped > 0, "{run:?}");
}

#[test]
fn marlin_resumes_exactly_after_an_unplug() {
    let lines = 300;
    let run = stream(
        Dialect::Marlin,
        lines,
        "unplug-at=0.3,unplug-for=700",
        "marlin-unplug",
    );
    assert_eq!(run.executed, expected(Dialect::Marlin, lines), "{run:?}");
    assert_eq!(run.sim.unplugs, 1, "{run:?}");
    assert_eq!(run.reopened, 1, "{run:?}");
}

#[test]
fn klipper_runs_every_line_once_through_busy_periods() {
    let lines = 300;
    let run = stream(
        Dialect::Klipper,
        lines,
        "busy=0.02,busy-for=300",
        "klipper-busy",
    );
    assert_eq!(run.executed, expected(Dialect::Klipper, lines), "{run:?}");
    assert!(run.sim.busy_periods > 0, "{run:?}");
}
