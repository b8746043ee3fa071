//! `edoctl link-test --protocol gcode --firmware F --port PATH`: qualify a cable and a
//! G-code machine (RepRapFirmware, Marlin, Klipper) by streaming N dry-run moves through
//! the sans-IO [`LineHost`] and counting what the firmware acknowledged, resent and lost.
//!
//! Dry-run moves are relative (`G91`) `G1 X±0.001 Y0 Z0 E0 F1800`: the head moves a
//! micrometre back and forth, nothing is extruded, and every line has the size of a real
//! extrusion move (about 50 bytes with its number and checksum). Positioning goes back
//! to absolute (`G90`) at the end. I/O is blocking, as in [`super::linktest`].

use std::io::{ErrorKind, Read, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::linktest::LinkTestError;
use crate::gcode_link::{
    estop_bytes_for, Dialect, LineEvent, LineHost, LineLinkConfig, LinkState, Micros, Window,
};

/// What to test.
#[derive(Debug, Clone)]
pub struct GcodeLinkTestConfig {
    /// Serial port, Klipper's pty, or hil-sim's symlink.
    pub port: PathBuf,
    /// The firmware at the other end.
    pub firmware: Dialect,
    /// Dry-run moves to stream.
    pub moves: u32,
    /// Line speed; also the basis of the utilisation figure.
    pub baud: u32,
    /// Lines in flight (`Window::Auto`: the firmware's safe default).
    pub window: Window,
    /// Give up when nothing is acknowledged for this long.
    pub stall_timeout: Duration,
}

/// Result of a G-code link test. Counts are lines unless the name says bytes.
#[derive(Debug, Clone, Default, Serialize)]
pub struct GcodeLinkTestReport {
    /// Port tested.
    pub port: String,
    /// Baud rate assumed.
    pub baud: u32,
    /// Firmware the link was set up for.
    pub firmware: String,
    /// What the firmware says it is (`M115`).
    pub machine: String,
    /// Lines handed to the link (dry-run moves and the `G91`/`G90` around them).
    pub lines: u64,
    /// Lines the firmware acknowledged (`ok`), each once and in order.
    pub accepted: u64,
    /// Lines never acknowledged.
    pub lost: u64,
    /// Lines sent again after a resend request or a probe.
    pub resent: u64,
    /// RRF lines sent again after a timeout (may have run twice).
    pub maybe_repeated: u64,
    /// Resend requests the firmware sent.
    pub resend_requests: u64,
    /// `ok` timeouts.
    pub timeouts: u64,
    /// Replies that were garbage, over-long or inconsistent.
    pub protocol_errors: u64,
    /// Bytes written.
    pub bytes_sent: u64,
    /// Bytes read.
    pub bytes_received: u64,
    /// Bytes of the lines sent the first time (number, checksum, newline included).
    pub line_bytes: u64,
    /// Line bytes / (baud / 10 × elapsed).
    pub utilisation: f64,
    /// Acknowledged moves per second.
    pub moves_per_s: f64,
    /// Seconds from the handshake to the last acknowledgement.
    pub elapsed_s: f64,
    /// Why the test ended early, if it did.
    pub aborted: Option<String>,
}

impl GcodeLinkTestReport {
    /// Every line acknowledged once, none lost, nothing repeated, not aborted.
    pub fn is_clean(&self) -> bool {
        self.lost == 0 && self.maybe_repeated == 0 && self.aborted.is_none()
    }
}

/// The dry-run lines: `G91`, `moves` moves of ±1 µm in X, `G90`.
pub fn dry_run_lines(moves: u32) -> Vec<String> {
    let mut lines = Vec::with_capacity(moves as usize + 2);
    lines.push("G91".to_string());
    for i in 0..moves {
        let x = if i % 2 == 0 { "0.001" } else { "-0.001" };
        lines.push(format!("G1 X{x} Y0.000 Z0.000 E0.000000 F1800"));
    }
    lines.push("G90".to_string());
    lines
}

/// The link's settings for the test: the firmware's defaults, the window asked for, and
/// the bytes in flight capped for the e-stop at this baud.
fn link_config(cfg: &GcodeLinkTestConfig) -> LineLinkConfig {
    let mut link = LineLinkConfig::for_dialect(cfg.firmware);
    link.window = cfg.window;
    if matches!(cfg.window, Window::Lines(_) | Window::AdvancedOk)
        && cfg.firmware == Dialect::Marlin
    {
        // A window is for boards on native USB (docs/firmware.md): their buffer is
        // larger than an AVR's 128 bytes.
        link.rx_buffer_bytes = 1024;
    }
    link.max_bytes_in_flight = estop_bytes_for(cfg.baud, link.max_line_bytes);
    link
}

/// Run a G-code link test on `port` (any byte stream: a serial port, a pty).
pub fn run_on<P: Read + Write>(
    port: &mut P,
    cfg: &GcodeLinkTestConfig,
) -> Result<GcodeLinkTestReport, LinkTestError> {
    let lines = dry_run_lines(cfg.moves);
    let mut t = GcodeLinkTest {
        cfg,
        start: Instant::now(),
        host: LineHost::new(link_config(cfg)),
        report: GcodeLinkTestReport {
            port: cfg.port.display().to_string(),
            baud: cfg.baud,
            firmware: format!("{:?}", cfg.firmware).to_lowercase(),
            lines: lines.len() as u64,
            ..GcodeLinkTestReport::default()
        },
        connected_at: None,
        last_progress: Instant::now(),
        next: 0,
    };
    let now = t.clock();
    t.host.connect(now);
    let mut buf = [0u8; 4096];
    while !t.is_over()? {
        t.feed(&lines);
        let now = t.clock();
        while let Some(b) = t.host.poll_transmit(now) {
            port.write_all(&b).map_err(|e| t.io(e))?;
        }
        match port.read(&mut buf) {
            Ok(n) => t.host.handle_bytes(&buf[..n], t.clock()),
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {
                std::thread::sleep(Duration::from_micros(200))
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(t.io(e)),
        }
        t.host.handle_timeout(t.clock());
        while let Some(e) = t.host.poll_event() {
            t.on_event(e);
        }
    }
    Ok(t.finish())
}

/// Open `cfg.port` and run the test on it.
pub fn run(cfg: &GcodeLinkTestConfig) -> Result<GcodeLinkTestReport, LinkTestError> {
    let mut port = serialport::new(cfg.port.to_string_lossy(), cfg.baud)
        .timeout(Duration::from_millis(1))
        .dtr_on_open(true)
        .open()
        .map_err(|source| LinkTestError::Open {
            port: cfg.port.display().to_string(),
            source,
        })?;
    run_on(&mut port, cfg)
}

/// A test under way.
struct GcodeLinkTest<'a> {
    cfg: &'a GcodeLinkTestConfig,
    start: Instant,
    host: LineHost,
    report: GcodeLinkTestReport,
    connected_at: Option<Instant>,
    last_progress: Instant,
    /// The next line to hand the link.
    next: usize,
}

impl GcodeLinkTest<'_> {
    fn clock(&self) -> Micros {
        Micros(self.start.elapsed().as_micros() as u64)
    }

    fn io(&self, source: std::io::Error) -> LinkTestError {
        LinkTestError::Io {
            port: self.report.port.clone(),
            source,
        }
    }

    /// Keep a few lines queued ahead of the window.
    fn feed(&mut self, lines: &[String]) {
        if self.host.state() != LinkState::Streaming {
            return;
        }
        while self.next < lines.len() && self.host.queued_len() < 32 {
            if self
                .host
                .send_line(&lines[self.next], self.next as u64)
                .is_err()
            {
                break;
            }
            self.next += 1;
        }
    }

    fn on_event(&mut self, e: LineEvent) {
        let r = &mut self.report;
        match e {
            LineEvent::Connected(info) => {
                r.machine = info
                    .identity
                    .or(info.firmware_name)
                    .unwrap_or_else(|| "no M115 answer".into());
                self.connected_at = Some(Instant::now());
                self.last_progress = Instant::now();
            }
            LineEvent::Accepted { tag, .. } => {
                if tag != r.accepted {
                    r.aborted = Some(format!("line {tag} acknowledged out of order"));
                }
                r.accepted += 1;
                self.last_progress = Instant::now();
            }
            LineEvent::MaybeRepeated { .. } => r.maybe_repeated += 1,
            LineEvent::Halted { text, .. } => r.aborted = Some(format!("firmware halted: {text}")),
            LineEvent::Reset { banner, .. } => {
                r.aborted = Some(format!("firmware reset during the test ({banner})"))
            }
            LineEvent::LinkLost { silent_us, .. } => {
                r.aborted = Some(format!("link lost: no reply for {} ms", silent_us / 1000))
            }
            LineEvent::Stopped { reason, .. } => r.aborted = Some(reason),
            LineEvent::LastAccepted(_)
            | LineEvent::Echo { .. }
            | LineEvent::Action { .. }
            | LineEvent::Busy { .. }
            | LineEvent::Error { .. }
            | LineEvent::ProtocolError { .. } => {}
        }
    }

    /// Every line acknowledged, aborted, stalled, or no handshake within 20 s (the
    /// handshake's own attempts end in `LinkLost` sooner).
    fn is_over(&mut self) -> Result<bool, LinkTestError> {
        if self.report.accepted >= self.report.lines || self.report.aborted.is_some() {
            return Ok(true);
        }
        if self.connected_at.is_none() && self.start.elapsed() > Duration::from_secs(20) {
            return Err(LinkTestError::NoHandshake {
                port: self.report.port.clone(),
                secs: 20,
            });
        }
        if self.connected_at.is_some() && self.last_progress.elapsed() > self.cfg.stall_timeout {
            self.report.aborted = Some(format!(
                "nothing acknowledged for {} s",
                self.cfg.stall_timeout.as_secs()
            ));
            return Ok(true);
        }
        Ok(false)
    }

    fn finish(self) -> GcodeLinkTestReport {
        let mut r = self.report;
        let s = self.host.stats();
        r.lost = r.lines.saturating_sub(r.accepted);
        r.resent = s.lines_resent;
        r.resend_requests = s.resend_requests;
        r.timeouts = s.timeouts;
        r.protocol_errors = s.protocol_errors;
        r.bytes_sent = s.bytes_sent;
        r.bytes_received = s.bytes_received;
        r.line_bytes = s.line_bytes_sent;
        if let Some(a) = self.connected_at {
            let secs = self.last_progress.duration_since(a).as_secs_f64().max(1e-6);
            r.elapsed_s = secs;
            r.moves_per_s = r.accepted as f64 / secs;
            r.utilisation = r.line_bytes as f64 / (f64::from(self.cfg.baud) / 10.0 * secs);
        }
        r
    }
}

impl std::fmt::Display for GcodeLinkTestReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "G-code link test on {} at {} baud ({}: {})",
            self.port, self.baud, self.firmware, self.machine
        )?;
        writeln!(f, "  lines             {}", self.lines)?;
        writeln!(f, "  acknowledged      {}", self.accepted)?;
        writeln!(f, "  lost              {}", self.lost)?;
        writeln!(
            f,
            "  resent            {} ({} resend requests)",
            self.resent, self.resend_requests
        )?;
        writeln!(f, "  maybe repeated    {}", self.maybe_repeated)?;
        writeln!(f, "  timeouts          {}", self.timeouts)?;
        writeln!(f, "  bad replies       {}", self.protocol_errors)?;
        writeln!(f, "  utilisation       {:.1} %", self.utilisation * 100.0)?;
        writeln!(f, "  moves/s           {:.0}", self.moves_per_s)?;
        match &self.aborted {
            Some(a) => writeln!(f, "  verdict           FAIL: {a}"),
            None if self.is_clean() => writeln!(f, "  verdict           PASS"),
            None => writeln!(f, "  verdict           FAIL: lines lost or repeated"),
        }
    }
}
