//! OctoPrint's virtual printer on a pty (`tests/peers/octoprint_shim.py`), for the tests
//! that stream to it: `tests/octoprint_peer.rs` (through `LineHost`) and
//! `tests/daemon_gcode.rs` (through edod). Both are skipped unless `EDO_OCTOPRINT_PY`
//! names the python of a venv with octoprint installed (`tests/peers/run_octoprint_peer.sh`).

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Its fault injection: every 20th line answered with a checksum error, a resend request
/// and the `ok` after it; OctoPrint's simulated errors at lines 100-115 (a resend, a
/// missing line number, a checksum error); busy keepalives. Not its
/// `resend_with_timeout`: it takes the line (`lastN`), runs nothing, asks for it again
/// and ignores the copy: the line is lost whatever the host does.
pub const FAULTS: &[&str] = &[
    "--resend-ratio",
    "5",
    "--busy",
    "--simulated-errors",
    "100:resend,110:missing_lineno,115:checksum_mismatch",
];

/// The python of a venv with octoprint (`EDO_OCTOPRINT_PY`); `None`, with a note, when
/// it is not set: the test is skipped, unless `EDO_REQUIRE_PEERS` is set (`.ci/run`
/// sets both), where a missing peer is a failure.
pub fn python() -> Option<String> {
    let python = std::env::var("EDO_OCTOPRINT_PY").ok();
    assert!(
        python.is_some() || std::env::var_os("EDO_REQUIRE_PEERS").is_none(),
        "EDO_REQUIRE_PEERS is set and EDO_OCTOPRINT_PY is not (the python of a venv with octoprint)"
    );
    if python.is_none() {
        eprintln!(
            "skipped: EDO_OCTOPRINT_PY is not set (the python of a venv with octoprint; \
             .ci/run sets it through tests/peers/run_octoprint_peer.sh)"
        );
    }
    python
}

/// The shim's process; stopped (its stdin closed) on drop.
pub struct Shim {
    child: Child,
}

impl Drop for Shim {
    fn drop(&mut self) {
        drop(self.child.stdin.take()); // the shim stops when its stdin closes
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The shim on `dir/tty`, logging what the printer ran to `dir/received.log`, with
/// `faults` (its options); the shim and its `ready` line.
pub fn start_shim(python: &str, dir: &Path, faults: &[&str]) -> (Shim, String) {
    let shim = format!(
        "{}/tests/peers/octoprint_shim.py",
        env!("CARGO_MANIFEST_DIR")
    );
    let mut child = Command::new(python)
        .arg(shim)
        .arg("--link")
        .arg(dir.join("tty"))
        .arg("--log")
        .arg(dir.join("received.log"))
        .args(faults)
        .args(
            std::env::var("EDO_OCTOPRINT_TRACE")
                .map(|t| vec!["--trace".to_string(), t])
                .unwrap_or_default(),
        )
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut ready = String::new();
    let stdout = child.stdout.take().unwrap();
    BufReader::new(stdout).read_line(&mut ready).unwrap();
    assert!(
        ready.starts_with("ready "),
        "the shim did not start: {ready:?}"
    );
    (Shim { child }, ready.trim().to_string())
}
