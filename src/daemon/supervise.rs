//! Supervision: start everything in order, tell systemd (READY, STATUS with job progress,
//! WATCHDOG at half of `WatchdogSec` while the streamer is alive), and stop cleanly on
//! SIGTERM/SIGINT (hold, checkpoint, exit).
//!
//! With `serial.port = "sim"` edod starts the `hil-sim` binary on a pty in the state
//! directory and stops it on exit.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use tokio::io::AsyncBufReadExt;
use tokio::net::UnixListener;
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tracing::{info, warn};

use super::config::{Config, SIM_PORT};
use super::streamer::Streamer;
use super::{api, instance, store, Control, Shared};

fn hil_sim_binary(cfg: &Config) -> PathBuf {
    if let Some(b) = &cfg.sim.binary {
        return b.clone();
    }
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|p| p.parent().map(Path::to_path_buf))
    {
        for d in [dir.clone(), dir.join("..")] {
            let c = d.join("hil-sim");
            if c.is_file() {
                return c;
            }
        }
    }
    PathBuf::from("hil-sim")
}

/// hil-sim's arguments for a mixing chamber other than its default (plug flow through
/// `--dead-volume-nl`).
fn mixer_sim_args(m: &crate::mixer::MixerOptions) -> Vec<String> {
    let mut args = vec![
        "--mixer".to_string(),
        m.model.name().to_string(),
        "--mixer-volume-nl".to_string(),
        m.volume_nl.to_string(),
    ];
    if let Some(pe) = m.peclet {
        args.extend(["--mixer-peclet".to_string(), pe.to_string()]);
    }
    args
}

/// Start hil-sim on a pty linked at `state/ttyEDO`; returns the child and the link.
async fn start_sim(cfg: &Config) -> Result<(tokio::process::Child, PathBuf)> {
    let link = cfg.state.dir.join("ttyEDO");
    let bin = hil_sim_binary(cfg);
    let mut cmd = tokio::process::Command::new(&bin);
    cmd.arg("--link")
        .arg(&link)
        .arg("--baud")
        .arg(cfg.serial.baud.to_string())
        .arg("--speed")
        .arg(cfg.sim.speed.to_string())
        .arg("--seed")
        .arg(cfg.sim.seed.to_string())
        .arg("--syringes")
        .arg(cfg.machine.syringes.len().to_string())
        .arg("--dead-volume-nl")
        .arg(cfg.machine.dead_volume_nl.to_string())
        .arg("--no-stdin")
        .arg("--exit-with-parent")
        .stdout(std::process::Stdio::piped())
        .stdin(std::process::Stdio::null())
        .kill_on_drop(true);
    if !cfg.sim.faults.is_empty() {
        cmd.arg("--faults").arg(&cfg.sim.faults);
    }
    if cfg.machine.mixer.is_some() {
        if let Ok(m) = cfg.machine.mixer() {
            cmd.args(mixer_sim_args(&m));
        }
    }
    if let Some(r) = &cfg.sim.record {
        cmd.arg("--record").arg(r);
    }
    if let Ok(Some(g)) = cfg.gcode_link() {
        cmd.args(gcode_sim_args(&g));
    }
    let mut child = cmd
        .spawn()
        .with_context(|| format!("cannot start the simulated machine {}", bin.display()))?;
    let Some(out) = child.stdout.take() else {
        bail!("hil-sim has no stdout");
    };
    let mut lines = tokio::io::BufReader::new(out).lines();
    let ready = tokio::time::timeout(Duration::from_secs(10), async {
        while let Ok(Some(l)) = lines.next_line().await {
            if l.starts_with("hil-sim ready") {
                return true;
            }
        }
        false
    })
    .await
    .unwrap_or(false);
    if !ready {
        bail!("hil-sim ({}) did not report ready", bin.display());
    }
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
    info!(link = %link.display(), "simulated machine started");
    Ok((child, link))
}

/// What the operator must know before resuming a job that edod's own stop interrupted
/// on a G-code firmware (`docs/firmware.md`, "What edod learns ...").
/// `known`: the previous run's marks were replayed, so the firmware's last accepted line
/// will say which moves ran.
fn gcode_restart_advice(dialect: crate::gcode_link::Dialect, known: bool) -> &'static str {
    match dialect {
        _ if known => {
            "the firmware ran the lines it had accepted after edod stopped: edod asks it for \
             the last one before connecting and resumes each job after the moves it ran \
             (RepRapFirmware: the move after them may run twice, logged by index); if the \
             firmware cannot say, the job resumes from its last checkpoint and repeats the \
             moves after it (docs/firmware.md)"
        }
        crate::gcode_link::Dialect::Klipper => {
            "Klipper ran the lines it had accepted after edod stopped and cannot say which: \
             the moves after each job's checkpoint (up to the lines in flight and Klipper's \
             lookahead) may have run; check the part, or Klipper's gcode_move position \
             through its API, before resuming (docs/firmware.md)"
        }
        _ => {
            "the firmware ran the lines it had accepted after edod stopped: resuming repeats \
             the moves between each job's last checkpoint and those lines; check the part \
             before resuming (docs/firmware.md)"
        }
    }
}

/// hil-sim's options for the firmware `g` describes (`hil-sim --gcode FIRMWARE`).
fn gcode_sim_args(g: &super::config::GcodeLink) -> Vec<String> {
    use crate::gcode_link::{MixWriting, Window};
    let mut args = vec!["--gcode".to_string(), g.link.dialect.name().to_string()];
    let mix = match &g.mix {
        MixWriting::PerDriveE => "per-drive-e",
        MixWriting::MarlinM163 => "m163",
        MixWriting::MarlinDirect => "direct",
        MixWriting::Axes(letters) => {
            args.push("--gcode-axes".into());
            args.push(
                letters
                    .iter()
                    .map(char::to_string)
                    .collect::<Vec<_>>()
                    .join(","),
            );
            "axes"
        }
    };
    args.push("--gcode-mix".into());
    args.push(mix.into());
    if g.link.window == Window::AdvancedOk {
        args.push("--gcode-advanced-ok".into());
    }
    args.push("--gcode-rx-buffer".into());
    args.push(g.link.rx_buffer_bytes.to_string());
    args
}

fn bind(cfg: &Config) -> Result<UnixListener> {
    let path = &cfg.api.socket;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        use std::os::unix::fs::FileTypeExt;
        if !meta.file_type().is_socket() {
            bail!(
                "{} exists and is not a socket; refusing to replace it",
                path.display()
            );
        }
        if std::os::unix::net::UnixStream::connect(path).is_ok() {
            bail!("another edod is listening on {}", path.display());
        }
        std::fs::remove_file(path).with_context(|| format!("cannot remove {}", path.display()))?;
    }
    let l = UnixListener::bind(path).with_context(|| format!("cannot bind {}", path.display()))?;
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(cfg.socket_mode()))
        .with_context(|| format!("cannot set the mode of {}", path.display()))?;
    if let Some(g) = &cfg.api.group {
        let gid = nix::unistd::Group::from_name(g)
            .ok()
            .flatten()
            .with_context(|| format!("api.group: no group {g:?}"))?
            .gid;
        std::os::unix::fs::chown(path, None, Some(gid.as_raw()))
            .with_context(|| format!("cannot give {} to group {g}", path.display()))?;
    }
    Ok(l)
}

/// Messages to systemd, sent from a thread of their own: `sd_notify` blocks when the
/// manager's queue is full, and the daemon must never wait for it. Messages that do not
/// fit the small queue are dropped (the next tick sends fresh ones).
struct Notifier(Option<std::sync::mpsc::SyncSender<String>>);

impl Notifier {
    fn start() -> Notifier {
        if std::env::var_os("NOTIFY_SOCKET").is_none() {
            return Notifier(None);
        }
        let (tx, rx) = std::sync::mpsc::sync_channel::<String>(8);
        let spawned = std::thread::Builder::new()
            .name("sd-notify".into())
            .spawn(move || {
                for m in rx {
                    let state = match m.as_str() {
                        "READY=1" => sd_notify::NotifyState::Ready,
                        "WATCHDOG=1" => sd_notify::NotifyState::Watchdog,
                        "STOPPING=1" => sd_notify::NotifyState::Stopping,
                        s => sd_notify::NotifyState::Status(s.trim_start_matches("STATUS=")),
                    };
                    let _ = sd_notify::notify(&[state]);
                }
            });
        Notifier(spawned.ok().map(|_| tx))
    }

    fn send(&self, m: &str) {
        if let Some(tx) = &self.0 {
            let _ = tx.try_send(m.to_string());
        }
    }
}

/// After edod's restart over G-code: the interrupted job's moves by line number,
/// replayed (off the runtime) from the marks the previous run stored, so the firmware's
/// last accepted line says which ran (`docs/firmware.md`). Plans the job once more.
async fn gcode_resume_lines(
    cfg: &Config,
    opened: &store::Opened,
) -> Option<crate::adapter::ResumeLines> {
    let g = cfg.gcode_link().ok().flatten()?;
    if g.link.dialect == crate::gcode_link::Dialect::Klipper {
        return klipper_resume_moves(cfg, opened).await;
    }
    let job_id = opened
        .gcode_marks
        .iter()
        .find(|m| m.kind == store::GcodeMarkKind::Writer)?
        .job_id;
    if !opened.interrupted.contains(&job_id) {
        return None;
    }
    let marks = opened.gcode_marks.clone();
    let drives = cfg.machine.syringes.len();
    replay_off_runtime(cfg, opened, job_id, move |moves| {
        crate::adapter::ResumeLines::replay(job_id, &marks, moves, drives, &g.settings())
    })
    .await
}

/// `replay` of interrupted job `job_id`'s moves, planned again on a blocking thread (off
/// the runtime: planning takes a core and the store's reader is waited for). What
/// fails is logged: the job then resumes from its checkpoint.
async fn replay_off_runtime(
    cfg: &Config,
    opened: &store::Opened,
    job_id: u32,
    replay: impl FnOnce(
            &mut dyn Iterator<Item = Result<crate::machine::Move, String>>,
        ) -> Result<Option<crate::adapter::ResumeLines>, String>
        + Send
        + 'static,
) -> Option<crate::adapter::ResumeLines> {
    let cfg = cfg.clone();
    let reader = opened.stores.reader.clone();
    let replayed = tokio::task::spawn_blocking(move || {
        let mut moves = replanned_moves(&reader, job_id, &cfg)?;
        replay(&mut moves)
    })
    .await;
    match replayed {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => {
            warn!(
                job = job_id,
                "the interrupted job's moves cannot be replayed, it resumes from its checkpoint: {e}"
            );
            None
        }
        Err(e) => {
            warn!(
                job = job_id,
                "the interrupted job's moves were not replayed: {e}"
            );
            None
        }
    }
}

/// Job `job_id`'s moves planned again from its stored source, layer by layer as they are
/// taken (on a blocking thread: it waits for the store's reader).
fn replanned_moves(
    reader: &store::Reader,
    job_id: u32,
    cfg: &Config,
) -> Result<impl Iterator<Item = Result<crate::machine::Move, String>>, String> {
    let (job, mesh) = reader
        .source_blocking(job_id)
        .map_err(|e| format!("job {job_id}: {e}"))?;
    let drives = cfg.machine.syringes.len();
    let mut source = super::planner::source_of(&job, mesh.as_deref(), drives, cfg)?;
    Ok(
        std::iter::from_fn(move || source.next_layer()).flat_map(|layer| match layer {
            Ok(moves) => moves.into_iter().map(Ok).collect::<Vec<_>>(),
            Err(e) => vec![Err(e)],
        }),
    )
}

/// How many moves past its checkpoint an interrupted Klipper job is matched against
/// where the nozzle stopped ([`klipper_resume_moves`]).
const KLIPPER_RESUME_SPAN_MOVES: u32 = 2_000;

/// After edod's restart on Klipper, which numbers no lines: the interrupted job that had
/// run moves (its checkpoint past 0), its moves from the last its checkpoint says ran to
/// what Klipper may have held beyond, with where each ends; where Klipper's nozzle
/// stopped then says which ran (`docs/firmware.md`). Plans the job once more, up to
/// there.
async fn klipper_resume_moves(
    cfg: &Config,
    opened: &store::Opened,
) -> Option<crate::adapter::ResumeLines> {
    let mut started = Vec::new();
    for &id in &opened.interrupted {
        match opened.stores.reader.get(id).await {
            Ok(r) if r.job.checkpoint.next_index > 0 => {
                started.push((id, r.job.checkpoint.next_index))
            }
            Ok(_) => {}
            Err(e) => warn!(job = id, "interrupted job not read: {e}"),
        }
    }
    let [(job_id, next_index)] = started[..] else {
        return None;
    };
    // What Klipper holds (20 lines pending, 32 in its lookahead), the lines in flight
    // and what ran between two checkpoint writes (every 100 ms), many times over: a
    // wider span can only match a move too early (repeated), never skip one.
    let span = KLIPPER_RESUME_SPAN_MOVES;
    replay_off_runtime(cfg, opened, job_id, move |moves| {
        crate::adapter::ResumeLines::by_position(job_id, next_index - 1, span, moves).map(Some)
    })
    .await
}

/// Run the daemon until SIGTERM or SIGINT.
pub async fn run(cfg: Config) -> Result<()> {
    run_until(cfg, std::future::pending()).await
}

/// Run the daemon until SIGTERM, SIGINT or `stop` completes (`edoctl demo` runs edod in
/// its own process and stops it this way), then stop cleanly.
pub async fn run_until(cfg: Config, stop: impl std::future::Future<Output = ()>) -> Result<()> {
    // First of all: one edod per state directory and socket (nothing read or started
    // before), held until this function returns.
    let _instance = instance::lock(&cfg)?;
    // Descriptors for every connection place (the dashboard's too): else refuse.
    let open_files = instance::raise_open_files(&cfg)?;
    tracing::debug!(open_files, "open-file limit");
    // Then the dashboard's port: taken, edod refuses to start before it opens the store.
    let dashboard_listener = super::http::bind(&cfg.http)
        .await
        .map_err(anyhow::Error::msg)?;
    instance::secure_db_files(&cfg.state.dir)?;
    let (sim, port) = if cfg.serial.port == SIM_PORT {
        let (c, l) = start_sim(&cfg).await?;
        (Some(c), l)
    } else {
        (None, PathBuf::from(&cfg.serial.port))
    };
    // The store's threads: no SQLite on this thread either (it runs the runtime).
    let (events_tx, events_rx) = mpsc::unbounded_channel();
    let dir = cfg.state.dir.clone();
    let block = crate::lifecycle::Options::default().service_index_block;
    let opened = store::start(dir, block, events_tx).await?;
    instance::secure_db_files(&cfg.state.dir)?;
    for (job, what) in &opened.quarantined {
        warn!(job, "stored job unreadable, marked failed: {what}");
    }
    let resume = gcode_resume_lines(&cfg, &opened).await;
    if !opened.interrupted.is_empty() {
        warn!(jobs = ?opened.interrupted, "jobs interrupted by the previous stop; resume them with job.resume");
        if let Ok(Some(g)) = cfg.gcode_link() {
            let advice = gcode_restart_advice(g.link.dialect, resume.is_some());
            warn!(jobs = ?opened.interrupted, "{advice}");
        }
    }
    let listener = bind(&cfg)?;
    let (control_tx, control_rx) = mpsc::channel(64);
    let shared = Arc::new(Shared {
        store: opened.stores,
        notify: broadcast::channel(4096).0,
        machine: watch::channel(Default::default()).0,
        progress: watch::channel(None).0,
        control: control_tx,
        port,
        alive: Default::default(),
        budget: super::connections::Budget::new(&cfg.api),
        stopping: Default::default(),
        log: watch::channel(Default::default()).0,
        config: cfg,
    });
    let log_keeper = tokio::spawn(super::log_feed::keep(Arc::clone(&shared)));
    let streamer = tokio::spawn(
        Streamer::new(
            Arc::clone(&shared),
            opened.service_index,
            opened.service_reserved_until,
            events_rx,
        )
        .with_gcode_resume(resume)
        .run(control_rx),
    );
    let api = tokio::spawn(api::serve(listener, Arc::clone(&shared)));
    let dashboard =
        dashboard_listener.map(|l| tokio::spawn(super::http::serve(Arc::clone(&shared), l)));
    info!(socket = %shared.config.api.socket.display(), port = %shared.port.display(), "edod ready");
    let notifier = Notifier::start();
    notifier.send("READY=1");
    serve_until(&shared, &streamer, &notifier, stop).await?;
    info!("stopping");
    shared
        .stopping
        .store(true, std::sync::atomic::Ordering::Relaxed);
    notifier.send("STOPPING=1");
    let (tx, rx) = oneshot::channel();
    if shared.control.send(Control::Shutdown(tx)).await.is_ok() {
        let _ = tokio::time::timeout(Duration::from_secs(5), rx).await;
    }
    api.abort();
    log_keeper.abort();
    if let Some(d) = dashboard {
        d.abort();
    }
    let _ = std::fs::remove_file(&shared.config.api.socket);
    if let Some(c) = sim {
        stop_sim(c).await;
    }
    info!("stopped");
    Ok(())
}

/// Serve until SIGTERM, SIGINT, `stop` or the streamer's end, telling systemd the
/// status line and petting its watchdog while the streamer is alive.
async fn serve_until(
    shared: &Shared,
    streamer: &tokio::task::JoinHandle<()>,
    notifier: &Notifier,
    stop: impl std::future::Future<Output = ()>,
) -> Result<()> {
    let watchdog = sd_notify::watchdog_enabled();

    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let mut int = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())?;
    let mut status_tick = tokio::time::interval(
        watchdog
            .map(|w| w / 2)
            .unwrap_or(Duration::from_secs(1))
            .min(Duration::from_secs(1)),
    );
    let mut last_alive = u64::MAX;
    let mut last_status = String::new();
    tokio::pin!(stop);
    loop {
        tokio::select! {
            _ = &mut stop => break,
            _ = term.recv() => break,
            _ = int.recv() => break,
            _ = status_tick.tick() => {
                if streamer.is_finished() {
                    warn!("streamer stopped; exiting");
                    break;
                }
                // The streamer publishes at least every tick while alive.
                let now_alive = shared.alive.load(std::sync::atomic::Ordering::Relaxed);
                let alive = now_alive != last_alive;
                last_alive = now_alive;
                if watchdog.is_some() && alive {
                    notifier.send("WATCHDOG=1");
                }
                let s = status_line(shared);
                if s != last_status {
                    notifier.send(&format!("STATUS={s}"));
                    last_status = s;
                }
            }
        }
    }
    Ok(())
}

/// SIGTERM lets hil-sim remove its link and flush its recording; after 3 s it is killed.
async fn stop_sim(mut c: tokio::process::Child) {
    if let Some(pid) = c.id() {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(pid as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
    }
    if tokio::time::timeout(Duration::from_secs(3), c.wait())
        .await
        .is_err()
    {
        let _ = c.start_kill();
        let _ = c.wait().await;
    }
}

fn status_line(shared: &Shared) -> String {
    let m = shared.machine.borrow().clone();
    let p = shared.progress.borrow().clone();
    match (m.connected, p) {
        (false, _) => format!("waiting for the machine on {}", m.port),
        (true, Some(p)) => format!(
            "job {}: {}/{} moves, layer {}",
            p.job_id,
            p.executed,
            p.total.map_or("?".to_string(), |t| t.to_string()),
            p.layer.map_or("-".to_string(), |l| l.to_string())
        ),
        (true, None) => "idle".to_string(),
    }
}
