//! `edoctl link-test`: qualify a cable and a machine by streaming N dry-run moves and
//! counting what the machine reports it executed.
//!
//! Dry-run moves are extrusion moves with zero volumes that step X by ±1 µm, so a real
//! machine barely moves and nothing is deposited, while every frame has the size of a
//! real two-syringe extrusion move.
//!
//! I/O is blocking (`serialport`): one port, one loop, nothing to multiplex, so a tokio
//! runtime would only add weight. The protocol itself is the sans-IO [`crate::link::Host`].

use std::io::{ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::link::{Host, HostEvent, HostState, MachineState, Micros};
use crate::machine::{Move, MoveKind, PositionUm};

/// What to test.
#[derive(Debug, Clone)]
pub struct LinkTestConfig {
    /// Serial port (or hil-sim's symlink).
    pub port: PathBuf,
    /// Moves to stream.
    pub moves: u32,
    /// Line speed; also the basis of the utilisation figure.
    pub baud: u32,
    /// Give up when the machine executes nothing for this long.
    pub stall_timeout: Duration,
}

/// Result of a link test. All counts are moves unless the name says bytes.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LinkTestReport {
    /// Port tested.
    pub port: String,
    /// Baud rate assumed.
    pub baud: u32,
    /// Machine identity from the handshake.
    pub machine: String,
    /// Moves handed to the link.
    pub sent: u64,
    /// Moves the machine reported executed.
    pub executed: u64,
    /// Moves sent but never executed.
    pub lost: u64,
    /// Moves the machine executed twice (its own order check).
    pub duplicated: u64,
    /// Moves the machine executed after a skipped index.
    pub reordered: u64,
    /// Bytes written.
    pub bytes_sent: u64,
    /// Bytes read.
    pub bytes_received: u64,
    /// Bytes of retransmitted frames.
    pub retransmitted_bytes: u64,
    /// Bytes received that made no valid frame.
    pub invalid_bytes: u64,
    /// Move bytes acknowledged by the machine.
    pub payload_bytes: u64,
    /// Payload bytes / (baud / 10 × elapsed).
    pub utilisation: f64,
    /// Executed moves per second.
    pub moves_per_s: f64,
    /// Seconds from handshake to the last executed move.
    pub elapsed_s: f64,
    /// Smoothed RTT (ms).
    pub srtt_ms: f64,
    /// Retransmission timeout at the end (ms).
    pub rto_ms: f64,
    /// Machine resets seen (the test stops at the first).
    pub resets: u64,
    /// Link losses seen.
    pub link_losses: u64,
    /// Times the port had to be reopened (unplug).
    pub reopens: u64,
    /// Why the test ended early, if it did.
    pub aborted: Option<String>,
}

/// Errors that stop a link test before it has a report.
#[derive(Debug, thiserror::Error)]
pub enum LinkTestError {
    /// The port does not open.
    #[error("cannot open {port}: {source} (is the machine or hil-sim running?)")]
    Open {
        /// Port.
        port: String,
        /// Cause.
        source: serialport::Error,
    },
    /// No handshake.
    #[error("{port}: no handshake reply within {secs} s: is it an edo machine at this baud?")]
    NoHandshake {
        /// Port.
        port: String,
        /// Seconds waited.
        secs: u64,
    },
    /// I/O error.
    #[error("{port}: {source}")]
    Io {
        /// Port.
        port: String,
        /// Cause.
        source: std::io::Error,
    },
}

/// The dry-run move number `index` of job `job_id`.
pub fn dry_run_move(job_id: u32, index: u32, syringes: usize) -> Move {
    Move {
        job_id,
        index,
        kind: MoveKind::Extrude {
            to: PositionUm {
                x_um: (index % 2) as i32,
                y_um: 0,
                z_um: 0,
            },
            feed_um_s: 20_000,
            volumes_nl: vec![0; syringes],
            width_factor_ppt: crate::machine::FACTOR_NOMINAL_PPT,
        },
    }
}

fn open(port: &Path, baud: u32) -> Result<Box<dyn serialport::SerialPort>, LinkTestError> {
    serialport::new(port.to_string_lossy(), baud)
        .timeout(Duration::from_millis(2))
        .open()
        .map_err(|source| LinkTestError::Open {
            port: port.display().to_string(),
            source,
        })
}

/// Run a link test.
pub fn run(cfg: &LinkTestConfig) -> Result<LinkTestReport, LinkTestError> {
    let mut port = open(&cfg.port, cfg.baud)?;
    let mut test = LinkTest::new(cfg);
    let mut buf = [0u8; 4096];
    loop {
        let now = test.clock();
        while let Some(e) = test.host.poll_event() {
            test.on_event(e);
        }
        if test.is_over()? {
            break;
        }
        test.feed_moves();
        // Write.
        while let Some(t) = test.host.poll_transmit(now) {
            if let Err(e) = port.write_all(&t.bytes) {
                if reopen(&mut port, cfg, &mut test.report, e).is_err() {
                    break;
                }
            }
        }
        // Read until the next timer.
        let wait_us = test
            .host
            .next_timeout()
            .map_or(2_000, |t| t.since(test.clock()))
            .clamp(100, 2_000);
        let _ = port.set_timeout(Duration::from_micros(wait_us));
        match port.read(&mut buf) {
            Ok(n) => test.host.handle_bytes(&buf[..n], test.clock()),
            Err(e) if e.kind() == ErrorKind::TimedOut || e.kind() == ErrorKind::WouldBlock => {}
            Err(e) => {
                if reopen(&mut port, cfg, &mut test.report, e).is_err() {
                    test.report.aborted = Some("port gone and did not come back".into());
                    break;
                }
            }
        }
    }
    Ok(test.finish())
}

/// The machine's counters: moves executed in all, duplicates and gaps it saw.
type MachineCounts = (u64, u32, u32);

/// A link test under way: the host end of the link, the dry-run job it streams, and
/// what the machine has reported.
struct LinkTest<'a> {
    cfg: &'a LinkTestConfig,
    /// The link's clock starts here.
    start: Instant,
    host: Host,
    job_id: u32,
    report: LinkTestReport,
    next_index: u32,
    syringes: usize,
    /// The counters at the handshake (the test counts from there) and the latest.
    baseline: Option<MachineCounts>,
    last: Option<MachineCounts>,
    connected_at: Option<Instant>,
    finished_at: Option<Instant>,
    last_progress: Instant,
}

impl<'a> LinkTest<'a> {
    /// A test about to start; its job id is random, so a machine that ran an earlier
    /// test does not take these moves for ones it executed.
    fn new(cfg: &'a LinkTestConfig) -> Self {
        let start = Instant::now();
        let seed = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64)
            ^ u64::from(std::process::id()) << 32;
        let job_id = (seed % 1_000_000_000) as u32 + 1;
        // The link edod streams with at this line speed.
        let link_cfg = crate::adapter::link_config(cfg.baud);
        let host = Host::new(link_cfg, seed, Micros(start.elapsed().as_micros() as u64));
        LinkTest {
            cfg,
            start,
            host,
            job_id,
            report: LinkTestReport {
                port: cfg.port.display().to_string(),
                baud: cfg.baud,
                ..LinkTestReport::default()
            },
            next_index: 0,
            syringes: 0,
            baseline: None,
            last: None,
            connected_at: None,
            finished_at: None,
            last_progress: Instant::now(),
        }
    }

    /// The link's time.
    fn clock(&self) -> Micros {
        Micros(self.start.elapsed().as_micros() as u64)
    }

    /// Take in what the link reports: the handshake, the machine's counters, resets,
    /// faults.
    fn on_event(&mut self, e: HostEvent) {
        let report = &mut self.report;
        match e {
            HostEvent::Connected(info) => {
                self.syringes = info.machine.barrel_area_um2.len();
                report.machine = info.machine.identity.clone();
                self.baseline = Some((
                    info.status.executed_total,
                    info.status.duplicates,
                    info.status.gaps,
                ));
                self.last = self.baseline;
                self.connected_at = Some(Instant::now());
                self.last_progress = Instant::now();
            }
            HostEvent::Status(s) => {
                if self.last.map(|l| l.0) != Some(s.executed_total) {
                    self.last_progress = Instant::now();
                }
                self.last = Some((s.executed_total, s.duplicates, s.gaps));
                let done = s
                    .last_executed
                    .is_some_and(|m| m.job_id == self.job_id && m.index + 1 == self.cfg.moves);
                if done && self.finished_at.is_none() {
                    self.finished_at = Some(Instant::now());
                }
                if matches!(s.state, MachineState::Faulted | MachineState::EStopped) {
                    report.aborted = Some(format!("machine state {:?}", s.state));
                }
            }
            HostEvent::MachineReset { .. } => {
                report.resets += 1;
                report.aborted = Some("machine reset during the test".into());
            }
            HostEvent::LinkLost { .. } => report.link_losses += 1,
            HostEvent::Incompatible { machine_version } => {
                report.aborted = Some(format!(
                    "machine speaks protocol {machine_version}, we speak {}",
                    crate::link::PROTOCOL_VERSION
                ));
            }
            HostEvent::Fault(f) => {
                report.aborted = Some(format!("machine fault {:?}", f.kind));
            }
            HostEvent::LinkRestored | HostEvent::PriorityAcked(_) => {}
        }
    }

    /// Whether the test has ended: every move executed, aborted, or stalled (no move
    /// executed for the stall timeout). No handshake within 5 s is an error.
    fn is_over(&mut self) -> Result<bool, LinkTestError> {
        if self.cfg.moves == 0 && self.connected_at.is_some() && self.finished_at.is_none() {
            self.finished_at = Some(Instant::now());
        }
        if self.finished_at.is_some() || self.report.aborted.is_some() {
            return Ok(true);
        }
        if self.connected_at.is_none() && self.start.elapsed() > Duration::from_secs(5) {
            return Err(LinkTestError::NoHandshake {
                port: self.report.port.clone(),
                secs: 5,
            });
        }
        if self.connected_at.is_some() && self.last_progress.elapsed() > self.cfg.stall_timeout {
            self.report.aborted = Some(format!(
                "no move executed for {} s",
                self.cfg.stall_timeout.as_secs()
            ));
            return Ok(true);
        }
        Ok(false)
    }

    /// Hand the link dry-run moves, up to 64 waiting.
    fn feed_moves(&mut self) {
        if self.host.state() != HostState::Connected {
            return;
        }
        while self.next_index < self.cfg.moves && self.host.pending() < 64 {
            if self
                .host
                .send_move(dry_run_move(self.job_id, self.next_index, self.syringes))
                .is_err()
            {
                break;
            }
            self.next_index += 1;
            self.report.sent += 1;
        }
    }

    /// The report: the machine's counters since the handshake, the link's statistics,
    /// rates over the time from handshake to the last move.
    fn finish(self) -> LinkTestReport {
        let mut report = self.report;
        let stats = self.host.stats();
        let (base, fin) = (
            self.baseline.unwrap_or_default(),
            self.last.unwrap_or_default(),
        );
        report.executed = fin.0.saturating_sub(base.0);
        report.duplicated = u64::from(fin.1.saturating_sub(base.1));
        report.reordered = u64::from(fin.2.saturating_sub(base.2));
        report.lost = report.sent.saturating_sub(report.executed);
        report.bytes_sent = stats.bytes_sent;
        report.bytes_received = stats.bytes_received;
        report.retransmitted_bytes = stats.bytes_retransmitted;
        report.invalid_bytes = stats.bytes_invalid;
        report.payload_bytes = stats.payload_bytes_acked;
        report.srtt_ms = stats.srtt_us as f64 / 1000.0;
        report.rto_ms = stats.rto_us as f64 / 1000.0;
        if let (Some(a), Some(b)) = (
            self.connected_at,
            self.finished_at.or_else(|| Some(Instant::now())),
        ) {
            let secs = b.duration_since(a).as_secs_f64().max(1e-6);
            report.elapsed_s = secs;
            report.moves_per_s = report.executed as f64 / secs;
            report.utilisation =
                report.payload_bytes as f64 / (f64::from(self.cfg.baud) / 10.0 * secs);
        }
        report
    }
}

/// The port failed (unplugged): reopen it for up to 5 s.
fn reopen(
    port: &mut Box<dyn serialport::SerialPort>,
    cfg: &LinkTestConfig,
    report: &mut LinkTestReport,
    err: std::io::Error,
) -> Result<(), LinkTestError> {
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
        if let Ok(p) = open(&cfg.port, cfg.baud) {
            *port = p;
            report.reopens += 1;
            return Ok(());
        }
    }
    Err(LinkTestError::Io {
        port: cfg.port.display().to_string(),
        source: err,
    })
}

impl std::fmt::Display for LinkTestReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "link test on {} at {} baud ({})",
            self.port, self.baud, self.machine
        )?;
        writeln!(f, "  sent              {}", self.sent)?;
        writeln!(f, "  executed          {}", self.executed)?;
        writeln!(f, "  lost              {}", self.lost)?;
        writeln!(f, "  duplicated        {}", self.duplicated)?;
        writeln!(f, "  reordered         {}", self.reordered)?;
        writeln!(f, "  retransmitted     {} bytes", self.retransmitted_bytes)?;
        writeln!(f, "  invalid received  {} bytes", self.invalid_bytes)?;
        writeln!(f, "  utilisation       {:.1} %", self.utilisation * 100.0)?;
        writeln!(f, "  moves/s           {:.0}", self.moves_per_s)?;
        writeln!(
            f,
            "  srtt / rto        {:.1} / {:.1} ms",
            self.srtt_ms, self.rto_ms
        )?;
        if let Some(a) = &self.aborted {
            writeln!(f, "  ABORTED: {a}")?;
        }
        Ok(())
    }
}
