//! `hil-sim`: run the simulated machine on a pseudo-terminal, or render a recording.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::{Parser, Subcommand};
use hil_sim::{Command, Faults, SimConfig, FAULTS_HELP};

/// A simulated multi-syringe slurry extruder speaking the edo link protocol on a pty.
///
/// Creates --link PATH as a symlink to its pseudo-terminal, prints
/// `hil-sim ready: PATH` on stdout, and runs until SIGTERM or SIGINT (then removes the
/// symlink). Both directions are throttled to --baud (10 bits per byte).
#[derive(Debug, Parser)]
#[command(version, after_help = FAULTS_HELP, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Cmd>,
    /// Symlink to create to the pty (the path the host opens).
    #[arg(long, value_name = "PATH")]
    link: Option<PathBuf>,
    /// Line speed, both directions.
    #[arg(long, default_value_t = 250_000, value_name = "B")]
    baud: u32,
    /// Machine time runs X times faster than wall time.
    #[arg(long, default_value_t = 1.0, value_name = "X")]
    speed: f64,
    /// Number of syringes (1..=8).
    #[arg(long, default_value_t = 2, value_name = "N")]
    syringes: usize,
    /// Move queue depth.
    #[arg(long, default_value_t = 128, value_name = "N")]
    queue: u16,
    /// Seed of fault injection and boot ids.
    #[arg(long, default_value_t = 1, value_name = "S")]
    seed: u64,
    /// Record every executed move as JSON lines (format: hil-sim/README.md).
    #[arg(long, value_name = "FILE")]
    record: Option<PathBuf>,
    /// Faults, comma separated key=value (list below).
    #[arg(long, default_value = "", value_name = "LIST")]
    faults: String,
    /// Mixing chamber dead volume V_dead in nl.
    #[arg(long, default_value_t = 20_000, value_name = "NL")]
    dead_volume_nl: u64,
    /// The mixing chamber's residence-time distribution: plug (plug flow through the
    /// volume), mixed (one well-mixed tank) or dispersion (plug flow with axial
    /// dispersion, needs --mixer-peclet); edo::mixer, hil-sim/README.md.
    #[arg(long, value_name = "MODEL", default_value = "plug")]
    mixer: String,
    /// The chamber's volume in nl (default: --dead-volume-nl).
    #[arg(long, value_name = "NL")]
    mixer_volume_nl: Option<f64>,
    /// Peclet number of the dispersion model (more than 0; large is nearly plug flow).
    #[arg(long, value_name = "PE")]
    mixer_peclet: Option<f64>,
    /// Do not read run-time commands from stdin.
    #[arg(long)]
    no_stdin: bool,
    /// Speak G-code as this firmware (model of edo::gcode_link) instead of the edo link.
    #[arg(long, value_name = "FIRMWARE", value_parser = edo::gcode_link::Dialect::from_name)]
    gcode: Option<edo::gcode_link::Dialect>,
    /// How the mix is written (default per firmware: rrf per-drive-e, marlin m163,
    /// klipper axes).
    #[arg(long, value_name = "MIX", requires = "gcode",
          value_parser = ["per-drive-e", "m163", "direct", "axes"])]
    gcode_mix: Option<String>,
    /// Axis letters, one per syringe, with --gcode-mix axes (default A,B,...).
    #[arg(
        long,
        value_name = "LETTERS",
        requires = "gcode",
        value_delimiter = ','
    )]
    gcode_axes: Vec<char>,
    /// Marlin: answer ADVANCED_OK `ok N P B`.
    #[arg(long, requires = "gcode")]
    gcode_advanced_ok: bool,
    /// The firmware's receive buffer in bytes (default: the model's).
    #[arg(long, value_name = "BYTES", requires = "gcode")]
    gcode_rx_buffer: Option<usize>,
    /// Marlin: the `busy:` keepalive interval in ms (default 2000, as `M113 S2`).
    #[arg(long, value_name = "MS", requires = "gcode")]
    gcode_keepalive_ms: Option<u64>,
    /// Stop (as on SIGTERM) when the process that started hil-sim dies, even by SIGKILL
    /// (edod's built-in simulated machine uses this; Linux only).
    #[arg(long)]
    exit_with_parent: bool,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Draw a recording as one SVG per layer, coloured by the composition at the nozzle.
    Render {
        /// Recording (JSON lines) written by --record.
        record: PathBuf,
        /// Output directory (layer-NNNN.svg).
        #[arg(long, value_name = "DIR")]
        svg: PathBuf,
    },
}

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: nix::libc::c_int) {
    STOP.store(true, Ordering::Relaxed);
}

fn install_signal_handlers() -> anyhow::Result<()> {
    use nix::sys::signal::{sigaction, SaFlags, SigAction, SigHandler, SigSet, Signal};
    let action = SigAction::new(
        SigHandler::Handler(on_signal),
        SaFlags::empty(),
        SigSet::empty(),
    );
    for sig in [Signal::SIGTERM, Signal::SIGINT] {
        // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
        unsafe { sigaction(sig, &action) }.context("install signal handler")?;
    }
    Ok(())
}

/// `--gcode` and its options.
fn gcode_options(cli: &Cli) -> anyhow::Result<Option<hil_sim::GcodeOptions>> {
    use edo::gcode_link::MixWriting;
    let Some(dialect) = cli.gcode else {
        return Ok(None);
    };
    let mut opts = hil_sim::GcodeOptions::new(dialect, cli.syringes);
    opts.advanced_ok = cli.gcode_advanced_ok;
    opts.rx_buffer_bytes = cli.gcode_rx_buffer;
    opts.keepalive_interval_ms = cli.gcode_keepalive_ms;
    if let Some(mix) = &cli.gcode_mix {
        opts.mix = match mix.as_str() {
            "per-drive-e" => MixWriting::PerDriveE,
            "m163" => MixWriting::MarlinM163,
            "direct" => MixWriting::MarlinDirect,
            _ => MixWriting::Axes(('A'..='W').take(cli.syringes).collect()),
        };
    }
    if !cli.gcode_axes.is_empty() {
        if cli.gcode_axes.len() != cli.syringes {
            anyhow::bail!(
                "--gcode-axes: {} letters for {} syringes",
                cli.gcode_axes.len(),
                cli.syringes
            );
        }
        opts.mix = MixWriting::Axes(
            cli.gcode_axes
                .iter()
                .map(char::to_ascii_uppercase)
                .collect(),
        );
    }
    Ok(Some(opts))
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if let Some(Cmd::Render { record, svg }) = &cli.command {
        let files = hil_sim::record::render(record, svg)?;
        println!("wrote {} layer(s) to {}", files.len(), svg.display());
        return Ok(());
    }
    let faults = Faults::parse(&cli.faults).context("--faults")?;
    let gcode = gcode_options(&cli)?;
    let volume_nl = cli.mixer_volume_nl.unwrap_or(cli.dead_volume_nl as f64);
    let mixer = edo::mixer::MixerOptions::new(&cli.mixer, volume_nl, cli.mixer_peclet)
        .map_err(|e| anyhow::anyhow!("{}: {}", e.option(), e.message))?;
    let cfg = SimConfig {
        link: cli.link.clone(),
        baud: cli.baud,
        speed: cli.speed,
        syringes: cli.syringes,
        queue: cli.queue,
        seed: cli.seed,
        record: cli.record.clone(),
        faults,
        dead_volume_nl: cli.dead_volume_nl,
        mixer: mixer.model,
        mixer_peclet: mixer.peclet,
        mixer_volume_nl: cli.mixer_volume_nl,
        gcode,
        ..SimConfig::default()
    };
    install_signal_handlers()?;
    if cli.exit_with_parent {
        nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGTERM)
            .context("--exit-with-parent")?;
        if nix::unistd::getppid() == nix::unistd::Pid::from_raw(1) {
            // The parent died before the request took effect.
            return Ok(());
        }
    }
    let commands = if cli.no_stdin {
        None
    } else {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::stdin().lines() {
                let Ok(line) = line else { break };
                if line.trim().is_empty() {
                    continue;
                }
                match Command::parse(&line) {
                    Ok(c) => {
                        if tx.send(c).is_err() {
                            break;
                        }
                    }
                    Err(e) => eprintln!("hil-sim: {e}"),
                }
            }
        });
        Some(rx)
    };
    let summary = hil_sim::run(&cfg, &STOP, commands, &mut |path| {
        println!("hil-sim ready: {}", path.display());
    })?;
    eprintln!("hil-sim: {}", serde_json::to_string(&summary)?);
    Ok(())
}
