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
    /// Mixing chamber dead volume V_dead (nl): the volume of the chamber, whatever its
    /// model.
    pub dead_volume_nl: u64,
    /// The chamber's residence-time distribution (`--mixer`, default plug flow).
    pub mixer: edo::mixer::MixerModel,
    /// Peclet number of the `dispersion` model (`--mixer-peclet`).
    pub mixer_peclet: Option<f64>,
    /// The chamber's volume in nl when not `dead_volume_nl` (`--mixer-volume-nl`).
    pub mixer_volume_nl: Option<f64>,
    /// Capacity of each syringe (nl).
    pub capacity_nl: u32,
    /// Barrel cross-section of each syringe (µm²).
    pub barrel_area_um2: u32,
    /// Receive buffer advertised to the host (bytes).
    pub rx_buffer_bytes: u32,
    /// Speak G-code as this firmware instead of the edo link (`hil-sim --gcode`).
    pub gcode: Option<crate::gcode_sim::GcodeOptions>,
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
            mixer: edo::mixer::MixerModel::Plug,
            mixer_peclet: None,
            mixer_volume_nl: None,
            capacity_nl: 10_000_000,
            barrel_area_um2: 78_539_816,
            rx_buffer_bytes: 2048,
            gcode: None,
        }
    }
}

impl SimConfig {
    /// The mixing chamber: `mixer` through `mixer_volume_nl`, else `dead_volume_nl` (an
    /// error names the key).
    pub fn mixer_options(&self) -> Result<edo::mixer::MixerOptions, edo::mixer::MixerError> {
        let o = edo::mixer::MixerOptions {
            model: self.mixer,
            volume_nl: self.mixer_volume_nl.unwrap_or(self.dead_volume_nl as f64),
            peclet: self.mixer_peclet,
        };
        o.validate()?;
        Ok(o)
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
    /// G-code modes: good lines answered with a resend request (`resend=P`).
    pub resend_requests: u64,
    /// G-code modes: busy periods injected (`busy=P`).
    pub busy_periods: u64,
}

/// The machine's end of the cable: a pty (behind the `--link` symlink when one is
/// asked for) throttled to the baud rate both ways, which can be unplugged (closed: the
/// host sees a hang-up, the symlink goes) and plugged in again as a new pty behind the
/// same symlink. Both simulators (edo and `--gcode`) use it.
pub(crate) struct PtyPort {
    link: Option<PathBuf>,
    /// `None` while unplugged.
    pty: Option<Pty>,
    replug_at: Option<u64>,
    /// Wall time one byte takes on the line, µs.
    byte_us: f64,
    /// Bytes the line may carry now, each way.
    rx_credit: f64,
    tx_credit: f64,
    /// Most line credit banked while idle, bytes.
    bank_bytes: f64,
}

/// Line credit the edo simulator banks while idle: its frames (up to 512 bytes) are read
/// at once after a pause.
pub(crate) const EDO_BANK_BYTES: f64 = 512.0;

/// Line credit the G-code simulator banks: about one tick of line time at 250 000 baud,
/// so a line that follows a pause still takes its bytes' time, as on a UART, and one
/// line at a time pays for the idle line between `ok` and the next line.
pub(crate) const UART_BANK_BYTES: f64 = 16.0;

impl PtyPort {
    /// A fresh pty at `baud` banking at most `bank_bytes` of line credit, and the path
    /// the host should open.
    pub(crate) fn open(
        link: Option<&Path>,
        baud: u32,
        bank_bytes: f64,
    ) -> anyhow::Result<(Self, PathBuf)> {
        let pty = open_pty(link)?;
        let ready = link.map_or_else(|| pty.slave_path.clone(), Path::to_path_buf);
        let port = PtyPort {
            link: link.map(Path::to_path_buf),
            pty: Some(pty),
            replug_at: None,
            byte_us: 10_000_000.0 / f64::from(baud.max(1)),
            rx_credit: 0.0,
            tx_credit: 0.0,
            bank_bytes,
        };
        Ok((port, ready))
    }

    /// Pull the cable (at `now_us`, for `for_ms`): the pty closes, master and slave, so
    /// the host sees a hang-up, and the symlink goes. False if it was already unplugged.
    pub(crate) fn unplug(&mut self, now_us: u64, for_ms: u64) -> bool {
        if self.pty.take().is_none() {
            return false;
        }
        self.remove_link();
        self.replug_at = Some(now_us + for_ms * 1000);
        true
    }

    /// Plug a new pty in behind the same symlink once the unplug is over.
    pub(crate) fn replug_if_due(&mut self, now_us: u64) -> anyhow::Result<()> {
        if self.replug_at.is_some_and(|at| now_us >= at) {
            self.pty = Some(open_pty(self.link.as_deref())?);
            self.replug_at = None;
        }
        Ok(())
    }

    /// Remove the symlink (the simulator stops, or the cable is pulled).
    pub(crate) fn remove_link(&self) {
        if let Some(l) = &self.link {
            let _ = std::fs::remove_file(l);
        }
    }

    /// Host -> machine, throttled to the line: `dt_us` of line time is credited (at most
    /// the bank) and up to the credit is read into `buf`. Returns how many bytes
    /// were read: 0 when stalled, unplugged, or nothing came (a hang-up, EIO, is not an
    /// error: the host may reopen).
    pub(crate) fn read(
        &mut self,
        buf: &mut [u8],
        dt_us: u64,
        stalled: bool,
        sum: &mut Summary,
    ) -> anyhow::Result<usize> {
        let new = dt_us as f64 / self.byte_us;
        self.rx_credit = (self.rx_credit + new).min(self.bank_bytes.max(new));
        let want = (self.rx_credit as usize).min(buf.len());
        let Some(p) = self.pty.as_mut() else {
            return Ok(0);
        };
        if want == 0 || stalled {
            return Ok(0);
        }
        match p.master.read(&mut buf[..want]) {
            Ok(n) => {
                self.rx_credit -= n as f64;
                sum.bytes_from_host += n as u64;
                Ok(n)
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(0),
            Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => Ok(0),
            Err(e) => Err(e).context("read from the pty"),
        }
    }

    /// Machine -> host through the pty, throttled the same way: writes what the credit
    /// allows from the front of `tx`; unplugged, `tx` is dropped (nobody listens).
    pub(crate) fn write(
        &mut self,
        tx: &mut VecDeque<u8>,
        dt_us: u64,
        sum: &mut Summary,
    ) -> anyhow::Result<()> {
        let new = dt_us as f64 / self.byte_us;
        self.tx_credit = (self.tx_credit + new).min(self.bank_bytes.max(new));
        let Some(p) = self.pty.as_mut() else {
            tx.clear();
            return Ok(());
        };
        let n = (self.tx_credit as usize).min(tx.len());
        if n == 0 {
            return Ok(());
        }
        let chunk: Vec<u8> = tx.iter().take(n).copied().collect();
        match p.master.write(&chunk) {
            Ok(w) => {
                tx.drain(..w);
                self.tx_credit -= w as f64;
                sum.bytes_to_host += w as u64;
                Ok(())
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(()),
            Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => Ok(()),
            Err(e) => Err(e).context("write to the pty"),
        }
    }
}

struct Pty {
    master: File,
    _slave: OwnedFd,
    slave_path: PathBuf,
}

/// A pty whose two ends are close-on-exec from the start. Neither end may leak into a
/// process spawned meanwhile by another thread (a test's edod): an inherited master keeps
/// the pty alive, so an unplug would not hang up the host, and an inherited end holds
/// the tty past the simulator's own close. `openpty` and a later `FD_CLOEXEC` leave a
/// window for that; `posix_openpt(O_CLOEXEC)` and an `O_CLOEXEC` open of the slave do not.
fn open_pty_cloexec() -> anyhow::Result<nix::pty::OpenptyResult> {
    use nix::fcntl::{open, OFlag};
    use nix::pty::{grantpt, posix_openpt, ptsname_r, unlockpt};
    use std::os::fd::{FromRawFd, IntoRawFd, OwnedFd};
    let master =
        posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC).context("posix_openpt")?;
    grantpt(&master).context("grantpt")?;
    unlockpt(&master).context("unlockpt")?;
    let name = ptsname_r(&master).context("ptsname")?;
    let slave = open(
        name.as_str(),
        OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC,
        nix::sys::stat::Mode::empty(),
    )
    .with_context(|| format!("open {name}"))?;
    // SAFETY: `into_raw_fd` gives up the only owner of the master's descriptor.
    let master = unsafe { OwnedFd::from_raw_fd(master.into_raw_fd()) };
    Ok(nix::pty::OpenptyResult { master, slave })
}

fn open_pty(link: Option<&Path>) -> anyhow::Result<Pty> {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
    use std::os::fd::AsRawFd;
    let pty = open_pty_cloexec()?;
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

pub(crate) fn move_kind_name(k: &MoveKind) -> &'static str {
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

pub(crate) fn um_to_mm(p: edo::machine::PositionUm) -> [f64; 3] {
    [
        f64::from(p.x_um) / 1000.0,
        f64::from(p.y_um) / 1000.0,
        f64::from(p.z_um) / 1000.0,
    ]
}

/// The link's settings for a machine that booted with `boot_id`.
fn link_config(cfg: &SimConfig, boot_id: u64) -> MachineLinkConfig {
    MachineLinkConfig {
        identity: format!("hil-sim {}", env!("CARGO_PKG_VERSION")),
        boot_id,
        barrel_area_um2: vec![cfg.barrel_area_um2; cfg.syringes],
        capacity_nl: vec![cfg.capacity_nl; cfg.syringes],
        queue_depth: cfg.queue.max(1),
        rx_buffer_bytes: cfg.rx_buffer_bytes,
        ..MachineLinkConfig::default()
    }
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
    if let Some(opts) = &cfg.gcode {
        return crate::gcode_sim::run(cfg, opts, stop, commands, on_ready);
    }
    let (mut sim, ready_path) = Sim::new(cfg)?;
    on_ready(&ready_path);
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_micros(300));
        sim.tick(commands.as_ref())?;
    }
    sim.finish()
}

/// A running simulator: the pty, the machine end of the link and the machine model,
/// the fault injectors of both directions, and the clocks. [`Sim::tick`] is one turn
/// of the loop: commands and timed faults, host to machine, moves, machine to host.
struct Sim<'a> {
    cfg: &'a SimConfig,
    /// The faults now (run-time commands change them).
    faults: Faults,
    rng: SimRng,
    port: PtyPort,
    recorder: Option<BufWriter<File>>,
    /// Wall time starts here.
    start: Instant,
    link: MachineLink,
    model: MachineModel,
    to_machine: Injector,
    to_host: Injector,
    /// Bytes waiting for the line to the host.
    tx: VecDeque<u8>,
    sum: Summary,
    last_tick: u64,
    /// The move under way and when (simulated µs) it is done.
    executing: Option<(Move, crate::model::Executed, u64)>,
    sim_time_us: f64,
    stall_until: u64,
    /// Timed faults already fired: stall, reset, unplug.
    stall_done: bool,
    reset_done: bool,
    unplug_done: bool,
    /// Move-count faults already fired: reset, empty, limit, e-stop.
    fired: [bool; 4],
    buf: Vec<u8>,
}

impl<'a> Sim<'a> {
    /// A simulator on a fresh pty, and the path the host should open.
    fn new(cfg: &'a SimConfig) -> anyhow::Result<(Self, PathBuf)> {
        let faults = cfg.faults.clone();
        let mut rng = SimRng::new(cfg.seed);
        let (port, ready_path) = PtyPort::open(cfg.link.as_deref(), cfg.baud, EDO_BANK_BYTES)?;
        let recorder = match &cfg.record {
            Some(p) => Some(BufWriter::new(
                File::create(p).with_context(|| format!("create record {}", p.display()))?,
            )),
            None => None,
        };
        let start = Instant::now();
        let link = MachineLink::new(link_config(cfg, rng.next_u64()), Micros(0));
        let mixer = cfg
            .mixer_options()
            .map_err(|e| anyhow::anyhow!("mixer {e}"))?;
        let model = MachineModel::new(cfg.syringes, cfg.capacity_nl, cfg.barrel_area_um2, &mixer);
        let to_machine = Injector::new(rng.next_u64());
        let to_host = Injector::new(rng.next_u64());
        let sim = Sim {
            cfg,
            faults,
            rng,
            port,
            recorder,
            start,
            link,
            model,
            to_machine,
            to_host,
            tx: VecDeque::new(),
            sum: Summary::default(),
            last_tick: 0,
            executing: None,
            sim_time_us: 0.0,
            stall_until: 0,
            stall_done: false,
            reset_done: false,
            unplug_done: false,
            fired: [false; 4],
            buf: vec![0u8; 4096],
        };
        Ok((sim, ready_path))
    }

    /// One turn of the loop.
    fn tick(&mut self, commands: Option<&Receiver<Command>>) -> anyhow::Result<()> {
        let now_us = self.start.elapsed().as_micros() as u64;
        let dt = now_us.saturating_sub(self.last_tick);
        self.last_tick = now_us;
        let (mut do_reset, mut do_unplug) = match commands {
            Some(rx) => self.take_commands(rx, now_us),
            None => (false, false),
        };
        let (timed_reset, timed_unplug) = self.timed_faults(now_us);
        do_reset |= timed_reset;
        do_unplug |= timed_unplug;
        if do_reset {
            self.reset(now_us);
            self.executing = None;
        }
        if do_unplug {
            self.unplug(now_us);
        }
        self.port.replug_if_due(now_us)?;
        let stalled = now_us < self.stall_until;
        self.receive(now_us, dt, stalled)?;
        self.execute(now_us, dt)?;
        self.transmit(now_us, dt, stalled)
    }

    /// Apply the run-time commands waiting; whether one asked for a reset, an unplug.
    fn take_commands(&mut self, rx: &Receiver<Command>, now_us: u64) -> (bool, bool) {
        let (mut do_reset, mut do_unplug) = (false, false);
        while let Ok(c) = rx.try_recv() {
            match c {
                Command::Fault(item) => {
                    let _ = self.faults.apply(&item);
                }
                Command::Reset => do_reset = true,
                Command::Unplug => do_unplug = true,
                Command::Stall(ms) => self.stall_until = now_us + ms * 1000,
                Command::EStop => {
                    self.link.fault(FaultKind::EStopPressed);
                    self.executing = None;
                }
                Command::Empty(n) => {
                    if let Some(s) = self.model.syringes.get_mut(usize::from(n)) {
                        s.remaining_nl = 0;
                    }
                    self.link.fault(FaultKind::SyringeEmpty(n));
                }
                Command::Limit(a) => self.link.fault(FaultKind::LimitHit(a)),
                Command::Clear => {
                    let f = &mut self.faults;
                    f.corrupt = 0.0;
                    f.drop = 0.0;
                    f.dup = 0.0;
                    f.delay_ms = 0;
                    f.jitter_ms = 0;
                }
                Command::Status => {
                    eprintln!(
                        "{}",
                        serde_json::json!({
                            "status": format!("{:?}", self.link.status()),
                            "summary": self.sum,
                        })
                    );
                }
            }
        }
        (do_reset, do_unplug)
    }

    /// Fire the faults timed in seconds from the start (each once): a stall starts
    /// here; whether a reset, an unplug is due.
    fn timed_faults(&mut self, now_us: u64) -> (bool, bool) {
        let secs = now_us as f64 / 1e6;
        let (mut do_reset, mut do_unplug) = (false, false);
        if let Some(at) = self.faults.stall_at_s {
            if !self.stall_done && secs >= at {
                self.stall_done = true;
                self.stall_until = now_us + self.faults.stall_for_ms * 1000;
            }
        }
        if let Some(at) = self.faults.reset_after_s {
            if !self.reset_done && secs >= at {
                self.reset_done = true;
                do_reset = true;
            }
        }
        if let Some(at) = self.faults.unplug_at_s {
            if !self.unplug_done && secs >= at {
                self.unplug_done = true;
                do_unplug = true;
            }
        }
        (do_reset, do_unplug)
    }

    /// The machine resets: a new boot of the link, bytes in flight lost, the boot
    /// banner on the line.
    fn reset(&mut self, now_us: u64) {
        self.link = MachineLink::new(link_config(self.cfg, self.rng.next_u64()), Micros(now_us));
        self.tx.clear();
        self.to_machine.clear();
        self.to_host.clear();
        self.tx.extend(b"\r\nhil-sim boot\r\n\xff\xfe");
        self.sum.resets += 1;
    }

    /// The cable is pulled: the pty closes (the host sees a hang-up) until the replug
    /// time.
    fn unplug(&mut self, now_us: u64) {
        if self.port.unplug(now_us, self.faults.unplug_for_ms) {
            self.tx.clear();
            self.to_machine.clear();
            self.sum.unplugs += 1;
        }
    }

    /// Host -> machine, throttled to the baud rate, through the injector into the link.
    fn receive(&mut self, now_us: u64, dt: u64, stalled: bool) -> anyhow::Result<()> {
        let n = self.port.read(&mut self.buf, dt, stalled, &mut self.sum)?;
        self.to_machine
            .push(&self.buf[..n], now_us, &self.faults, &mut self.sum);
        let now = Micros(now_us);
        while let Some(b) = self.to_machine.pop_due(now_us) {
            self.link.handle_bytes(&b, now);
        }
        while let Some(e) = self.link.poll_event() {
            // An emergency stop aborts the move being executed: it is not reported
            // executed, so a host resuming after the stop sends it again.
            if e == MachineEvent::Priority(PriorityCmd::EmergencyStop) {
                self.executing = None;
            }
        }
        Ok(())
    }

    /// Execute moves on simulated machine time: finish the move under way when its
    /// time has come, start the next.
    fn execute(&mut self, now_us: u64, dt: u64) -> anyhow::Result<()> {
        self.sim_time_us += dt as f64 * self.cfg.speed;
        loop {
            if let Some((_, _, done_at)) = &self.executing {
                if (self.sim_time_us as u64) < *done_at {
                    break;
                }
                if let Some((mv, ex, done_at)) = self.executing.take() {
                    self.complete(&mv, &ex, done_at)?;
                    self.fire_move_faults(now_us);
                }
            }
            let Some(mv) = self.link.pop_move() else {
                // Idle: make the recording complete on disk for whoever reads it now
                // (a no-op when nothing was written since the last flush).
                if let Some(w) = self.recorder.as_mut() {
                    w.flush()?;
                }
                break;
            };
            match self.model.execute(&mv) {
                Ok(ex) => {
                    let done_at = self.sim_time_us as u64 + ex.duration_us;
                    self.executing = Some((mv, ex, done_at));
                }
                Err(fault) => self.link.fault(fault),
            }
        }
        Ok(())
    }

    /// Report a move done (finished at simulated time `done_at_us`) and record it.
    fn complete(
        &mut self,
        mv: &Move,
        ex: &crate::model::Executed,
        done_at_us: u64,
    ) -> anyhow::Result<()> {
        let remaining = self.model.remaining_nl();
        self.link.move_done(mv, ex.to, &remaining);
        self.sum.executed += 1;
        if let Some(w) = self.recorder.as_mut() {
            let line = RecordLine {
                job_id: mv.job_id,
                index: mv.index,
                kind: move_kind_name(&mv.kind).to_string(),
                layer: ex.layer,
                t_s: done_at_us as f64 / 1e6,
                from_mm: um_to_mm(ex.from),
                to_mm: um_to_mm(ex.to),
                volumes_nl: mv.kind.volumes_nl().to_vec(),
                exit_composition: ex.exit_composition.clone(),
                remaining_nl: remaining,
                gcode: None,
            };
            write_line(w, &line)?;
        }
        Ok(())
    }

    /// Fire the faults set at a count of executed moves (each once).
    fn fire_move_faults(&mut self, now_us: u64) {
        let n = self.sum.executed;
        let triggers = [
            self.faults.reset_at_moves,
            self.faults.empty_at_moves,
            self.faults.limit_at_moves,
            self.faults.estop_at_moves,
        ];
        for (k, t) in triggers.iter().enumerate() {
            if *t == Some(n) && !self.fired[k] {
                self.fired[k] = true;
                match k {
                    0 => self.reset(now_us),
                    1 => {
                        if let Some(s) = self.model.syringes.first_mut() {
                            s.remaining_nl = 0;
                        }
                        self.link.fault(FaultKind::SyringeEmpty(0));
                    }
                    2 => self.link.fault(FaultKind::LimitHit(0)),
                    _ => self.link.fault(FaultKind::EStopPressed),
                }
            }
        }
    }

    /// Machine -> host: the link's frames through the injector, throttled to the baud
    /// rate onto the pty (dropped while unplugged).
    fn transmit(&mut self, now_us: u64, dt: u64, stalled: bool) -> anyhow::Result<()> {
        while let Some(t) = self.link.poll_transmit(Micros(now_us)) {
            if !stalled {
                self.to_host
                    .push(&t.bytes, now_us, &self.faults, &mut self.sum);
            }
        }
        while let Some(b) = self.to_host.pop_due(now_us) {
            self.tx.extend(b);
        }
        self.port.write(&mut self.tx, dt, &mut self.sum)
    }

    /// Stop: the recording flushed, the link's symlink removed.
    fn finish(mut self) -> anyhow::Result<Summary> {
        if let Some(w) = self.recorder.as_mut() {
            w.flush()?;
        }
        self.port.remove_link();
        Ok(self.sum)
    }
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
