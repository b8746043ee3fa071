//! edod: the edo printer-host daemon. A thin skin over [`edo::daemon`].

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

#[derive(Debug, Parser)]
#[command(
    name = "edod",
    version,
    about = "edo printer-host daemon: jobs over a local socket, streamed to the machine"
)]
struct Cli {
    /// Configuration file (see config/edod.toml).
    #[arg(long, value_name = "FILE", default_value = "/etc/edo/edod.toml")]
    config: PathBuf,
    /// Check a configuration file and exit (0 when it is valid).
    #[arg(long, value_name = "FILE", conflicts_with = "config")]
    check_config: Option<PathBuf>,
}

/// A file size limit (`RLIMIT_FSIZE`, `LimitFSIZE=`) must fail the write (EFBIG), which
/// the store handles as a full disk (docs/api.md), not kill edod with SIGXFSZ mid-print.
fn ignore_file_size_signal() {
    use nix::sys::signal::{signal, SigHandler, Signal};
    // SAFETY: SIG_IGN installs no handler code; set once at start, before any thread.
    if let Err(e) = unsafe { signal(Signal::SIGXFSZ, SigHandler::SigIgn) } {
        eprintln!("edod: cannot ignore SIGXFSZ ({e}): a file size limit would stop edod");
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Some(path) = cli.check_config {
        return match edo::daemon::Config::load(&path) {
            Ok(cfg) => {
                let findings = edo::daemon::preflight::check(&cfg);
                for f in &findings {
                    eprintln!("edod: {}: {f}", path.display());
                }
                if findings.iter().any(|f| f.error) {
                    return ExitCode::FAILURE;
                }
                println!("{}: ok", path.display());
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("edod: {e}");
                ExitCode::FAILURE
            }
        };
    }
    // Under systemd the journal adds its own timestamps; keep lines plain there.
    let journal = std::env::var_os("JOURNAL_STREAM").is_some();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // Beside the log on stderr (RUST_LOG, default info), the dashboard's console
    // (`log.recent`), which keeps edod's own info lines whatever RUST_LOG says.
    use tracing_subscriber::layer::SubscriberExt as _;
    use tracing_subscriber::util::SubscriberInitExt as _;
    use tracing_subscriber::Layer as _;
    let stderr = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_ansi(!journal && std::io::IsTerminal::is_terminal(&std::io::stderr()));
    let stderr = if journal {
        stderr.without_time().boxed()
    } else {
        stderr.boxed()
    };
    tracing_subscriber::registry()
        .with(stderr.with_filter(filter))
        .with(
            edo::daemon::log_feed::FeedLayer
                .with_filter(tracing_subscriber::filter::LevelFilter::INFO),
        )
        .init();
    ignore_file_size_signal();
    let cfg = match edo::daemon::Config::load(&cli.config) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("edod: {e}");
            return ExitCode::FAILURE;
        }
    };
    // What can only fail once running is refused now, before anything is started.
    let findings = edo::daemon::preflight::check(&cfg);
    for f in &findings {
        if f.error {
            eprintln!("edod: {}: {f}", cli.config.display());
        } else {
            tracing::warn!("{}: {f}", cli.config.display());
        }
    }
    if findings.iter().any(|f| f.error) {
        return ExitCode::FAILURE;
    }
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("edod: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match rt.block_on(edo::daemon::run(cfg)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            eprintln!("edod: {e:#}");
            ExitCode::FAILURE
        }
    }
}
