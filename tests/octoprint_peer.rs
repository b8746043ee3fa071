//! A real peer: OctoPrint's virtual printer (a Marlin model written by others, PyPI
//! `octoprint`, pinned in `.ci/run`) on a pty through `tests/peers/octoprint_shim.py`,
//! with its own fault injection on (resend ratio, simulated errors, busy). The offline
//! Marlin G-code of a small example job is streamed through `LineHost` with a small IO
//! loop; the job completes, every line is acknowledged once and in order, and the
//! commands the virtual printer ran equal the file's (less comments; N and checksums are
//! the link's). Skipped, with the reason printed, unless `EDO_OCTOPRINT_PY` names the
//! python of a venv with octoprint installed (`.ci/run` sets it).

use std::fs::{File, OpenOptions};
use std::io::{ErrorKind, Read, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::{Duration, Instant};

use edo::gcode_link::writer::{write_gcode, GcodeSettings};
use edo::gcode_link::{Dialect, LineEvent, LineHost, LineLinkConfig, LinkState, Micros};
use edo::pipeline::{job_layer_moves, ProcessSettings, StreamState};
use edo::plan::plan_layers;
use peer::start_shim;

#[path = "peers/octoprint.rs"]
mod peer;

/// The first moves of the paper annulus' first layer as offline Marlin G-code
/// (`M163`/`M164` mixes), as `edoctl plan --gcode --flavor marlin` writes them.
fn offline_gcode(moves: usize) -> String {
    let path = format!(
        "{}/config/examples/paper-annulus.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    let text = std::fs::read_to_string(&path).unwrap();
    let job = edo::job::Job::from_toml(&text, &path).unwrap();
    let slices = job.layer_slices(0, job.extruded_layers().unwrap());
    let layers = plan_layers(&slices[..1], &job.plan, None).unwrap();
    let process = ProcessSettings::for_nozzle(job.plan.nozzle_mm);
    let mut state = StreamState::new();
    let mut all: Vec<edo::machine::Move> = job_layer_moves(&layers, &process, 0, 0, &mut state)
        .unwrap()
        .into_iter()
        .flat_map(|l| l.moves)
        .collect();
    all.truncate(moves);
    let settings = GcodeSettings {
        flavor: Dialect::Marlin,
        ..GcodeSettings::default()
    };
    let mut out = String::new();
    write_gcode(&all, job.materials.len(), &settings, &[], &mut out).unwrap();
    out
}

/// The commands of a G-code file as the link sends them: comments and blank lines gone.
fn commands(gcode: &str) -> Vec<String> {
    gcode
        .lines()
        .map(|l| l.split(';').next().unwrap_or("").trim().to_string())
        .filter(|l| !l.is_empty())
        .collect()
}

fn open_port(path: &Path) -> File {
    OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
        .open(path)
        .unwrap()
}

/// Stream `lines` through `LineHost` over `port`; the tags accepted, in order.
fn stream(port: &mut File, lines: &[String]) -> (Vec<u64>, edo::gcode_link::LineStats) {
    let start = Instant::now();
    let now = || Micros(start.elapsed().as_micros() as u64);
    let mut cfg = LineLinkConfig::for_dialect(Dialect::Marlin);
    cfg.ok_timeout_us = 3_000_000;
    let mut host = LineHost::new(cfg);
    host.connect(now());
    let mut accepted = Vec::new();
    let mut next = 0usize;
    let mut buf = [0u8; 4096];
    let deadline = Instant::now() + Duration::from_secs(240);
    while accepted.len() < lines.len() {
        assert!(Instant::now() < deadline, "timed out: {:?}", host.stats());
        if host.state() == LinkState::Streaming {
            while next < lines.len() && host.queued_len() < 4 {
                host.send_line(&lines[next], next as u64).unwrap();
                next += 1;
            }
        }
        match port.read(&mut buf) {
            Ok(n) => host.handle_bytes(&buf[..n], now()),
            Err(e) if e.kind() == ErrorKind::WouldBlock => {}
            Err(e) => panic!("read: {e}"),
        }
        host.handle_timeout(now());
        while let Some(b) = host.poll_transmit(now()) {
            port.write_all(&b).unwrap();
        }
        while let Some(e) = host.poll_event() {
            match e {
                LineEvent::Accepted { tag, .. } => accepted.push(tag),
                LineEvent::Error { .. } | LineEvent::ProtocolError { .. } => {
                    eprintln!("{:>8} µs {e:?}", now().0)
                }
                LineEvent::Reset { .. }
                | LineEvent::LinkLost { .. }
                | LineEvent::Stopped { .. }
                | LineEvent::Halted { .. } => panic!("{e:?} after {} lines", accepted.len()),
                _ => {}
            }
        }
        std::thread::sleep(Duration::from_micros(300));
    }
    (accepted, host.stats().clone())
}

#[test]
fn octoprint_virtual_printer_runs_the_offline_gcode_once_in_order() {
    let Some(python) = peer::python() else {
        return;
    };
    let gcode = offline_gcode(400);
    let lines = commands(&gcode);
    let dir = tempfile::tempdir().unwrap();
    let (_shim, ready) = start_shim(&python, dir.path(), peer::FAULTS);
    eprintln!("{ready}");
    let mut port = open_port(&dir.path().join("tty"));
    let (accepted, stats) = stream(&mut port, &lines);
    eprintln!("{stats:?}");
    let want: Vec<u64> = (0..lines.len() as u64).collect();
    assert_eq!(accepted, want, "every line acknowledged once, in order");
    assert!(stats.resend_requests >= 10, "its faults were on: {stats:?}");
    // What it ran, once its log has as many commands as the file (it writes the log as
    // it runs them, after the acknowledgements came).
    let ran = |received: &str| -> Vec<String> {
        received
            .lines()
            // Less the handshake's M115 and the empty lines the e-stop newline and the
            // probe's leading newline make.
            .filter(|l| !matches!(*l, "M115" | "M105" | ""))
            .map(str::to_owned)
            .collect()
    };
    let log = dir.path().join("received.log");
    let t = std::time::Instant::now();
    let ran = loop {
        let ran = ran(&std::fs::read_to_string(&log).unwrap_or_default());
        if ran.len() >= lines.len() || t.elapsed() > Duration::from_secs(10) {
            break ran;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!(ran, lines, "the printer ran the file's commands, each once");
}
