//! The simulator runtime: a pseudo-terminal pair, a baud-rate throttle, fault injection,
//! the machine end of the link ([`edo::link::MachineLink`]) and the [`MachineModel`].
//!
//! Link timers run on wall time (the host on the other side of the pty does too); move
//! durations run on simulated machine time, `--speed` times faster than wall time.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{BufWriter, ErrorKind, Read, Write};
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Receiver;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use edo::link::testkit::SimRng;
use edo::link::{FaultKind, MachineEvent, MachineLink, MachineLinkConfig, Micros, PriorityCmd};
use edo::machine::{Move, MoveKind};

use crate::faults::Faults;
use crate::model::MachineModel;
use crate::record::{write_line, RecordLine};

/// Simulator settings (the command line, as a struct).
#[derive(Debug, Clone)]
pub struct SimConfig {
    /// Create this path as a symlink to the pty the host should open.
    pub link: Option<PathBuf>,
    /// Line speed in baud (10 bits per byte), both directions.
    pub baud: u32,
    /// Machine time runs this many times faster than wall time.
    pub speed: f64,
    /// Number of syringes (1..=8).
    pub syringes: usize,
    /// Move queue depth.
    pub queue: u16,
    /// Seed of the fault injector and boot ids.
    pub seed: u64,
    /// Record executed moves (JSON lines) here.
    pub record: Option<PathBuf>,
    /// Faults.
    pub faults: Faults,
    /// Mixing chamber dead volume V_dead (nl).
    pub dead_volume_nl: u64,
    /// Capacity of each syringe (nl).
    pub capacity_nl: u32,
    /// Barrel cross-section of each syringe (µm²).
    pub barrel_area_um2: u32,
    /// Receive buffer advertised to the host (bytes).
    pub rx_buffer_bytes: u32,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            link: None,
            baud: 250_000,
            speed: 1.0,
            syringes: 2,
            queue: 128,
            seed: 1,
            record: None,
            faults: Faults::parse("").unwrap_or_default(),
            dead_volume_nl: 20_000,
            capacity_nl: 10_000_000,
            barrel_area_um2: 78_539_816,
            rx_buffer_bytes: 2048,
        }
    }
}

/// A command given at run time (stdin of the binary, or a channel in tests).
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Change a fault: a `--faults` item such as `drop=0.05`.
    Fault(String),
    /// Reset now.
    Reset,
    /// Unplug now (for `unplug-for`).
    Unplug,
    /// Stop answering for this many milliseconds.
    Stall(u64),
    /// Press the machine's e-stop button.
    EStop,
    /// Syringe N runs empty.
    Empty(u8),
    /// Limit switch of axis N trips.
    Limit(u8),
    /// Clear rate faults.
    Clear,
    /// Print the status on stderr.
    Status,
}

impl Command {
    /// Parse one command line (see `FAULTS_HELP`).
    pub fn parse(line: &str) -> Result<Self, String> {
        let mut words = line.split_whitespace();
        let first = words.next().ok_or("empty command")?;
        let arg = |w: Option<&str>| -> Result<u64, String> {
            w.ok_or(format!("{first}: needs a number"))?
                .parse::<u64>()
                .map_err(|_| format!("{first}: not a number"))
        };
        Ok(match first {
            "reset" => Command::Reset,
            "unplug" => Command::Unplug,
            "stall" => Command::Stall(arg(words.next())?),
            "estop" => Command::EStop,
            "empty" => Command::Empty(arg(words.next())?.min(7) as u8),
            "limit" => Command::Limit(arg(words.next())?.min(2) as u8),
            "clear" => Command::Clear,
            "status" => Command::Status,
            item if item.contains('=') => {
                Faults::default().apply(item).map_err(|e| e.to_string())?;
                Command::Fault(item.to_string())
            }
            other => return Err(format!("unknown command {other:?}")),
        })
    }
}

/// What a run did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Moves executed.
    pub executed: u64,
    /// Resets injected.
    pub resets: u64,
    /// Unplugs injected.
    pub unplugs: u64,
    /// Frames dropped by the injector.
    pub frames_dropped: u64,
    /// Frames duplicated by the injector.
    pub frames_duplicated: u64,
    /// Bits flipped by the injector.
    pub bits_flipped: u64,
    /// Bytes read from the host.
    pub bytes_from_host: u64,
    /// Bytes written to the host.
    pub bytes_to_host: u64,
}

struct Pty {
    master: File,
    _slave: OwnedFd,
    slave_path: PathBuf,
}

fn open_pty(link: Option<&Path>) -> anyhow::Result<Pty> {
    use nix::fcntl::FdFlag;
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
    use std::os::fd::AsRawFd;
    let pty = nix::pty::openpty(None, None).context("openpty")?;
    // Neither end may leak into a process spawned meanwhile (a test's edod): an
    // inherited master keeps the pty alive, so an unplug would not hang up the host.
    for fd in [&pty.master, &pty.slave] {
        fcntl(fd, FcntlArg::F_SETFD(FdFlag::FD_CLOEXEC)).context("fcntl FD_CLOEXEC")?;
    }
    let mut t = tcgetattr(&pty.slave).context("tcgetattr on the pty")?;
    cfmakeraw(&mut t);
    tcsetattr(&pty.slave, SetArg::TCSANOW, &t).context("tcsetattr raw on the pty")?;
    let flags = fcntl(&pty.master, FcntlArg::F_GETFL).context("fcntl F_GETFL")?;
    fcntl(
        &pty.master,
        FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
    )
    .context("fcntl O_NONBLOCK")?;
    let slave_path = std::fs::read_link(format!("/proc/self/fd/{}", pty.slave.as_raw_fd()))
        .context("find the pty's path")?;
    if let Some(link) = link {
        match std::fs::symlink_metadata(link) {
            Ok(m) if m.file_type().is_symlink() => std::fs::remove_file(link)
                .with_context(|| format!("replace old symlink {}", link.display()))?,
            Ok(_) => bail!(
                "{} exists and is not a symlink: refusing to replace it",
                link.display()
            ),
            Err(_) => {}
        }
        std::os::unix::fs::symlink(&slave_path, link)
            .with_context(|| format!("symlink {} -> {}", link.display(), slave_path.display()))?;
    }
    Ok(Pty {
        master: File::from(pty.master),
        _slave: pty.slave,
        slave_path,
    })
}

/// Splits a byte stream into frames at 0x00 and applies drop / duplicate / bit errors /
/// delay / jitter per frame, keeping order.
struct Injector {
    rng: SimRng,
    cur: Vec<u8>,
    queue: VecDeque<(u64, Vec<u8>)>,
    last_at: u64,
    bits_to_error: u64,
}

impl Injector {
    fn new(seed: u64) -> Self {
        Self {
            rng: SimRng::new(seed),
            cur: Vec::new(),
            queue: VecDeque::new(),
            last_at: 0,
            bits_to_error: u64::MAX,
        }
    }

    fn next_error(&mut self, ber: f64) -> u64 {
        if ber <= 0.0 {
            return u64::MAX;
        }
        let u = self.rng.next_f64().max(f64::MIN_POSITIVE);
        (u.ln() / (1.0 - ber).ln()).floor().min(1e18) as u64
    }

    fn push(&mut self, bytes: &[u8], now_us: u64, f: &Faults, sum: &mut Summary) {
        for &b in bytes {
            self.cur.push(b);
            if b == 0 || self.cur.len() > 4096 {
                let frame = std::mem::take(&mut self.cur);
                self.frame(frame, now_us, f, sum);
            }
        }
    }

    fn frame(&mut self, frame: Vec<u8>, now_us: u64, f: &Faults, sum: &mut Summary) {
        if self.rng.chance(f.drop) {
            sum.frames_dropped += 1;
            return;
        }
        let copies = if self.rng.chance(f.dup) {
            sum.frames_duplicated += 1;
            2
        } else {
            1
        };
        if self.bits_to_error == u64::MAX && f.corrupt > 0.0 {
            self.bits_to_error = self.next_error(f.corrupt);
        }
        for _ in 0..copies {
            let mut data = frame.clone();
            let bits = data.len() as u64 * 8;
            let mut pos = 0u64;
            while f.corrupt > 0.0 && self.bits_to_error < bits - pos {
                pos += self.bits_to_error;
                if let Some(b) = data.get_mut((pos / 8) as usize) {
                    *b ^= 1 << (pos % 8);
                    sum.bits_flipped += 1;
                }
                pos += 1;
                self.bits_to_error = self.next_error(f.corrupt);
            }
            if self.bits_to_error != u64::MAX {
                self.bits_to_error -= (bits - pos).min(self.bits_to_error);
            }
            let jitter = if f.jitter_ms > 0 {
                self.rng.next_u64() % (f.jitter_ms * 1000)
            } else {
                0
            };
            let at = (now_us + f.delay_ms * 1000 + jitter).max(self.last_at);
            self.last_at = at;
            self.queue.push_back((at, data));
        }
    }

    fn pop_due(&mut self, now_us: u64) -> Option<Vec<u8>> {
        if self.queue.front()?.0 <= now_us {
            self.queue.pop_front().map(|q| q.1)
        } else {
            None
        }
    }

    fn clear(&mut self) {
        self.queue.clear();
        self.cur.clear();
    }
}

fn move_kind_name(k: &MoveKind) -> &'static str {
    match k {
        MoveKind::Travel { .. } => "travel",
        MoveKind::Extrude { .. } => "extrude",
        MoveKind::Retract { .. } => "retract",
        MoveKind::Prime { .. } => "prime",
        MoveKind::Dwell { .. } => "dwell",
        MoveKind::LayerMark { .. } => "layer",
        MoveKind::Home => "home",
    }
}

fn um_to_mm(p: edo::machine::PositionUm) -> [f64; 3] {
    [
        f64::from(p.x_um) / 1000.0,
        f64::from(p.y_um) / 1000.0,
        f64::from(p.z_um) / 1000.0,
    ]
}

/// Run the simulator until `stop` is set. `on_ready` gets the path the host should open
/// (the symlink if one was asked for, else the pty itself).
pub fn run(
    cfg: &SimConfig,
    stop: &AtomicBool,
    commands: Option<Receiver<Command>>,
    on_ready: &mut dyn FnMut(&Path),
) -> anyhow::Result<Summary> {
    if cfg.syringes == 0 || cfg.syringes > edo::machine::MAX_SYRINGES {
        bail!(
            "--syringes {}: must be 1..={}",
            cfg.syringes,
            edo::machine::MAX_SYRINGES
        );
    }
    if cfg.baud == 0 || cfg.speed.is_nan() || cfg.speed <= 0.0 {
        bail!("--baud and --speed must be positive");
    }
    let mut faults = cfg.faults.clone();
    let mut rng = SimRng::new(cfg.seed);
    let link_cfg = |boot_id: u64| MachineLinkConfig {
        identity: format!("hil-sim {}", env!("CARGO_PKG_VERSION")),
        boot_id,
        barrel_area_um2: vec![cfg.barrel_area_um2; cfg.syringes],
        capacity_nl: vec![cfg.capacity_nl; cfg.syringes],
        queue_depth: cfg.queue.max(1),
        rx_buffer_bytes: cfg.rx_buffer_bytes,
        ..MachineLinkConfig::default()
    };
    let mut pty = Some(open_pty(cfg.link.as_deref())?);
    let ready_path = cfg
        .link
        .clone()
        .or_else(|| pty.as_ref().map(|p| p.slave_path.clone()))
        .unwrap_or_default();
    let mut recorder = match &cfg.record {
        Some(p) => Some(BufWriter::new(
            File::create(p).with_context(|| format!("create record {}", p.display()))?,
        )),
        None => None,
    };
    let start = Instant::now();
    let mut link = MachineLink::new(link_cfg(rng.next_u64()), Micros(0));
    let mut model = MachineModel::new(
        cfg.syringes,
        cfg.capacity_nl,
        cfg.barrel_area_um2,
        cfg.dead_volume_nl,
    );
    let mut to_machine = Injector::new(rng.next_u64());
    let mut to_host = Injector::new(rng.next_u64());
    let mut tx: VecDeque<u8> = VecDeque::new();
    let mut sum = Summary::default();
    let byte_us = 10_000_000.0 / f64::from(cfg.baud);
    let (mut rx_credit, mut tx_credit) = (0.0f64, 0.0f64);
    let mut last_tick = 0u64;
    let mut executing: Option<(Move, crate::model::Executed, u64)> = None;
    let mut sim_time_us: f64 = 0.0;
    let mut stall_until = 0u64;
    let mut replug_at: Option<u64> = None;
    let (mut stall_done, mut reset_done, mut unplug_done) = (false, false, false);
    let mut fired = [false; 4];
    let mut buf = vec![0u8; 4096];
    on_ready(&ready_path);

    let reset = |link: &mut MachineLink,
                 rng: &mut SimRng,
                 tx: &mut VecDeque<u8>,
                 a: &mut Injector,
                 b: &mut Injector,
                 now: u64,
                 sum: &mut Summary| {
        *link = MachineLink::new(link_cfg(rng.next_u64()), Micros(now));
        tx.clear();
        a.clear();
        b.clear();
        tx.extend(b"\r\nhil-sim boot\r\n\xff\xfe");
        sum.resets += 1;
    };

    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_micros(300));
        let now_us = start.elapsed().as_micros() as u64;
        let now = Micros(now_us);
        let dt = now_us.saturating_sub(last_tick);
        last_tick = now_us;
        let secs = now_us as f64 / 1e6;

        // Run-time commands.
        let mut do_reset = false;
        let mut do_unplug = false;
        if let Some(rx) = &commands {
            while let Ok(c) = rx.try_recv() {
                match c {
                    Command::Fault(item) => {
                        let _ = faults.apply(&item);
                    }
                    Command::Reset => do_reset = true,
                    Command::Unplug => do_unplug = true,
                    Command::Stall(ms) => stall_until = now_us + ms * 1000,
                    Command::EStop => {
                        link.fault(FaultKind::EStopPressed);
                        executing = None;
                    }
                    Command::Empty(n) => {
                        if let Some(s) = model.syringes.get_mut(usize::from(n)) {
                            s.remaining_nl = 0;
                        }
                        link.fault(FaultKind::SyringeEmpty(n));
                    }
                    Command::Limit(a) => link.fault(FaultKind::LimitHit(a)),
                    Command::Clear => {
                        faults.corrupt = 0.0;
                        faults.drop = 0.0;
                        faults.dup = 0.0;
                        faults.delay_ms = 0;
                        faults.jitter_ms = 0;
                    }
                    Command::Status => {
                        eprintln!(
                            "{}",
                            serde_json::json!({
                                "status": format!("{:?}", link.status()),
                                "summary": sum,
                            })
                        );
                    }
                }
            }
        }
        // Timed faults.
        if let Some(at) = faults.stall_at_s {
            if !stall_done && secs >= at {
                stall_done = true;
                stall_until = now_us + faults.stall_for_ms * 1000;
            }
        }
        if let Some(at) = faults.reset_after_s {
            if !reset_done && secs >= at {
                reset_done = true;
                do_reset = true;
            }
        }
        if let Some(at) = faults.unplug_at_s {
            if !unplug_done && secs >= at {
                unplug_done = true;
                do_unplug = true;
            }
        }
        if do_reset {
            reset(
                &mut link,
                &mut rng,
                &mut tx,
                &mut to_machine,
                &mut to_host,
                now_us,
                &mut sum,
            );
            executing = None;
        }
        if do_unplug && pty.is_some() {
            pty = None; // closes master and slave: the host sees a hang-up
            if let Some(l) = &cfg.link {
                let _ = std::fs::remove_file(l);
            }
            tx.clear();
            to_machine.clear();
            sum.unplugs += 1;
            replug_at = Some(now_us + faults.unplug_for_ms * 1000);
        }
        if let Some(at) = replug_at {
            if now_us >= at {
                pty = Some(open_pty(cfg.link.as_deref())?);
                replug_at = None;
            }
        }
        let stalled = now_us < stall_until;

        // Host -> machine, throttled to the baud rate.
        rx_credit = (rx_credit + dt as f64 / byte_us).min(512.0);
        if let Some(p) = pty.as_mut() {
            let want = (rx_credit as usize).min(buf.len());
            if want > 0 && !stalled {
                match p.master.read(&mut buf[..want]) {
                    Ok(n) => {
                        rx_credit -= n as f64;
                        sum.bytes_from_host += n as u64;
                        to_machine.push(&buf[..n], now_us, &faults, &mut sum);
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => {}
                    Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => {}
                    Err(e) => return Err(e).context("read from the pty"),
                }
            }
        }
        while let Some(b) = to_machine.pop_due(now_us) {
            link.handle_bytes(&b, now);
        }
        while let Some(e) = link.poll_event() {
            // An emergency stop aborts the move being executed: it is not reported
            // executed, so a host resuming after the stop sends it again.
            if e == MachineEvent::Priority(PriorityCmd::EmergencyStop) {
                executing = None;
            }
        }

        // Execute moves on simulated machine time.
        sim_time_us += dt as f64 * cfg.speed;
        loop {
            if let Some((mv, ex, done_at)) = &executing {
                if (sim_time_us as u64) < *done_at {
                    break;
                }
                let remaining = model.remaining_nl();
                link.move_done(mv, ex.to, &remaining);
                sum.executed += 1;
                if let Some(w) = recorder.as_mut() {
                    let line = RecordLine {
                        job_id: mv.job_id,
                        index: mv.index,
                        kind: move_kind_name(&mv.kind).to_string(),
                        layer: ex.layer,
                        t_s: *done_at as f64 / 1e6,
                        from_mm: um_to_mm(ex.from),
                        to_mm: um_to_mm(ex.to),
                        volumes_nl: mv.kind.volumes_nl().to_vec(),
                        exit_composition: ex.exit_composition.clone(),
                        remaining_nl: remaining,
                    };
                    write_line(w, &line)?;
                }
                executing = None;
                let n = sum.executed;
                let triggers = [
                    faults.reset_at_moves,
                    faults.empty_at_moves,
                    faults.limit_at_moves,
                    faults.estop_at_moves,
                ];
                for (k, t) in triggers.iter().enumerate() {
                    if *t == Some(n) && !fired[k] {
                        fired[k] = true;
                        match k {
                            0 => reset(
                                &mut link,
                                &mut rng,
                                &mut tx,
                                &mut to_machine,
                                &mut to_host,
                                now_us,
                                &mut sum,
                            ),
                            1 => {
                                if let Some(s) = model.syringes.first_mut() {
                                    s.remaining_nl = 0;
                                }
                                link.fault(FaultKind::SyringeEmpty(0));
                            }
                            2 => link.fault(FaultKind::LimitHit(0)),
                            _ => link.fault(FaultKind::EStopPressed),
                        }
                    }
                }
            }
            let Some(mv) = link.pop_move() else {
                // Idle: make the recording complete on disk for whoever reads it now
                // (a no-op when nothing was written since the last flush).
                if let Some(w) = recorder.as_mut() {
                    w.flush()?;
                }
                break;
            };
            match model.execute(&mv) {
                Ok(ex) => {
                    let done_at = sim_time_us as u64 + ex.duration_us;
                    executing = Some((mv, ex, done_at));
                }
                Err(fault) => link.fault(fault),
            }
        }

        // Machine -> host.
        while let Some(t) = link.poll_transmit(now) {
            if !stalled {
                to_host.push(&t.bytes, now_us, &faults, &mut sum);
            }
        }
        while let Some(b) = to_host.pop_due(now_us) {
            tx.extend(b);
        }
        tx_credit = (tx_credit + dt as f64 / byte_us).min(512.0);
        if let Some(p) = pty.as_mut() {
            let n = (tx_credit as usize).min(tx.len());
            if n > 0 {
                let chunk: Vec<u8> = tx.iter().take(n).copied().collect();
                match p.master.write(&chunk) {
                    Ok(w) => {
                        tx.drain(..w);
                        tx_credit -= w as f64;
                        sum.bytes_to_host += w as u64;
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => {}
                    Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => {}
                    Err(e) => return Err(e).context("write to the pty"),
                }
            }
        } else {
            tx.clear();
        }
    }
    if let Some(w) = recorder.as_mut() {
        w.flush()?;
    }
    if let Some(l) = &cfg.link {
        let _ = std::fs::remove_file(l);
    }
    Ok(sum)
}

/// A simulator running in a thread of this process (for tests).
pub struct SimHandle {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    commands: std::sync::mpsc::Sender<Command>,
    thread: Option<std::thread::JoinHandle<anyhow::Result<Summary>>>,
}

impl SimHandle {
    /// Path the host should open.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Send a run-time command.
    pub fn command(&self, c: Command) {
        let _ = self.commands.send(c);
    }

    /// Stop the simulator and return its summary.
    pub fn stop(mut self) -> anyhow::Result<Summary> {
        self.stop.store(true, Ordering::Relaxed);
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => bail!("simulator thread panicked"),
            None => bail!("simulator already stopped"),
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Start a simulator on a fresh pty in a thread; returns once it is ready.
pub fn spawn(cfg: SimConfig) -> anyhow::Result<SimHandle> {
    let stop = Arc::new(AtomicBool::new(false));
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let (cmd_tx, cmd_rx) = std::sync::mpsc::channel();
    let stop2 = Arc::clone(&stop);
    let thread = std::thread::spawn(move || {
        let tx = ready_tx.clone();
        let r = run(&cfg, &stop2, Some(cmd_rx), &mut |p| {
            let _ = tx.send(Ok(p.to_path_buf()));
        });
        if let Err(e) = &r {
            let _ = ready_tx.send(Err(e.to_string()));
        }
        r
    });
    match ready_rx.recv_timeout(Duration::from_secs(10)) {
        Ok(Ok(path)) => Ok(SimHandle {
            path,
            stop,
            commands: cmd_tx,
            thread: Some(thread),
        }),
        Ok(Err(e)) => bail!("simulator failed to start: {e}"),
        Err(_) => bail!("simulator did not become ready within 10 s"),
    }
}
