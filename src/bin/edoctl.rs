//! edoctl: the operator's command-line client. A thin skin over the `edo` library:
//! every subcommand's work lives in a library module.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand};
use edo::cli::client::{self, Answer, Client};
use edo::proto::{method, Job, JobIdParams, JobState, NoParams, StartNextParams, SubmitParams};

#[derive(Debug, Parser)]
#[command(
    name = "edoctl",
    version,
    about = "Plan and run graded-material (EDO) prints"
)]
struct Cli {
    /// edod's socket.
    #[arg(long, global = true, value_name = "PATH", default_value = edo::cli::client::DEFAULT_SOCKET)]
    socket: PathBuf,
    /// Print the daemon's JSON instead of a human summary.
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: Commands,
}

#[derive(Debug, Subcommand)]
enum Commands {
    /// Print a graded tooth crown on the simulated machine end to end (edod + hil-sim in a
    /// temporary directory) and write the planned and as-built previews side by side.
    Demo(edo::cli::demo::DemoArgs),
    /// The mixing chamber: fit its model to a measured step response.
    #[command(subcommand)]
    Mixer(edo::cli::mixer::MixerCommand),
    /// Plan a job offline: validate it, run the EDO method on every layer, and write
    /// the plan report and SVG previews.
    Plan(edo::cli::plan::PlanArgs),
    /// Qualify a cable and machine: stream N dry-run moves and count what was executed.
    LinkTest {
        /// Serial port (or hil-sim --link path).
        #[arg(long, value_name = "PATH")]
        port: PathBuf,
        /// Moves to stream.
        #[arg(long, value_name = "N")]
        moves: u32,
        /// Line speed (also the basis of the utilisation figure).
        #[arg(long, default_value_t = 250_000, value_name = "B")]
        baud: u32,
        /// The protocol on the port: edo's framed link, or G-code lines
        /// (docs/firmware.md).
        #[arg(long, value_enum, default_value = "edo")]
        protocol: LinkProtocol,
        /// With --protocol gcode: the firmware.
        #[arg(
            long,
            value_enum,
            value_name = "F",
            required_if_eq("protocol", "gcode")
        )]
        firmware: Option<edo::gcode_link::Dialect>,
        /// With --protocol gcode: lines in flight ("auto", "advanced-ok" or a number;
        /// a window over 1 only for boards on native USB, docs/firmware.md).
        #[arg(long, value_name = "W", default_value = "auto")]
        window: String,
    },
    /// Submit a job file (and its mesh) to edod.
    Submit {
        /// The job file (TOML, see docs/job-format.md).
        #[arg(required_unless_present = "dry_run_moves")]
        job: Option<PathBuf>,
        /// Instead of a job file: a dry run of N moves that extrude nothing.
        #[arg(long, value_name = "N", conflicts_with = "job")]
        dry_run_moves: Option<u32>,
        /// Show a progress bar until the job ends.
        #[arg(long)]
        watch: bool,
    },
    /// List edod's jobs.
    Jobs,
    /// Show the machine's state and the active job.
    Status,
    /// Follow a job with a progress bar (layer, moves, composition, ETA).
    Watch {
        /// Job id.
        id: u32,
    },
    /// Hold a printing job at the next move boundary.
    Pause {
        /// Job id.
        id: u32,
    },
    /// Continue a paused or interrupted job.
    Resume {
        /// Job id.
        id: u32,
    },
    /// Cancel a job; a printing one stops, retracts and parks (this waits until it has).
    Cancel {
        /// Job id.
        id: u32,
    },
    /// Start a queued job (the oldest without ID) although an interrupted job holds the
    /// queue: say so only once the machine is ready for a new part.
    StartNext {
        /// Job id (default: the oldest queued job).
        id: Option<u32>,
    },
    /// Delete a finished (done, failed or cancelled) job and its mesh from edod's store.
    Delete {
        /// Job id.
        id: u32,
    },
    /// Queue a finished job again as a new job, from the job file and mesh edod stored
    /// with it (nothing to send again).
    Reprint {
        /// Job id of the finished job.
        id: u32,
    },
    /// Emergency stop: goes out ahead of everything queued.
    Estop,
    /// The syringes were refilled: clear the fault and continue.
    Refill,
}

/// How a daemon subcommand prints: the daemon's JSON (`--json`) or a line for people.
struct Output {
    json: bool,
}

impl Output {
    fn print<T>(&self, answer: &Answer<T>, human: impl FnOnce(&T) -> String) {
        if self.json {
            println!("{}", answer.json);
        } else {
            println!("{}", human(&answer.result));
        }
    }
}

/// Success if the job ended done.
fn ended_well(job: &Job) -> ExitCode {
    if job.state == JobState::Done {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}

fn daemon(cli: &Cli) -> anyhow::Result<ExitCode> {
    let mut c = Client::connect(&cli.socket)?;
    let out = Output { json: cli.json };
    let c = &mut c;
    match &cli.command {
        Commands::Submit {
            job,
            dry_run_moves,
            watch,
        } => return submit(c, &out, job.as_deref(), *dry_run_moves, *watch),
        Commands::Jobs => out.print(&c.request::<method::JobList>(&NoParams {})?, |jobs| {
            let lines: Vec<String> = jobs.iter().map(client::job_line).collect();
            lines.join("\n")
        }),
        Commands::Status => status(c, &out)?,
        Commands::Watch { id } => {
            let j = client::watch(c, *id, cli.json)?;
            out.print(&j, client::job_line);
            return Ok(ended_well(&j.result));
        }
        Commands::Pause { id } => out.print(
            &c.request::<method::JobPause>(&JobIdParams { id: *id })?,
            |r| client::applied_line(r, "paused"),
        ),
        Commands::Resume { id } => out.print(
            &c.request::<method::JobResume>(&JobIdParams { id: *id })?,
            |r| client::applied_line(r, "resumed"),
        ),
        Commands::Cancel { id } => {
            let j = client::cancel(c, *id, client::CANCEL_WAIT)?;
            out.print(&j, client::cancelled_line);
            if j.result.state != JobState::Cancelled {
                // It ended some other way (done or failed) before the cancel took.
                return Ok(ExitCode::FAILURE);
            }
        }
        Commands::StartNext { id } => out.print(
            &c.request::<method::JobStartNext>(&StartNextParams { id: *id })?,
            |r| client::applied_line(r, "started"),
        ),
        Commands::Delete { id } => out.print(
            &c.request::<method::JobDelete>(&JobIdParams { id: *id })?,
            |_| format!("job {id} deleted"),
        ),
        Commands::Reprint { id } => {
            let r = c.request::<method::JobReprint>(&JobIdParams { id: *id })?;
            for w in &r.result.warnings {
                eprintln!("warning: {w}");
            }
            out.print(&r, |r| format!("job {id} queued again as job {}", r.id))
        }
        Commands::Estop => out.print(&c.request::<method::MachineEstop>(&NoParams {})?, |r| {
            let acked = r
                .acked_after_us
                .map_or("(no ack within 1 s)".to_string(), |a| format!("{a} µs"));
            format!(
                "e-stop sent after {} µs, acknowledged after {acked}",
                r.written_after_us
            )
        }),
        Commands::Refill => out.print(&c.request::<method::MachineRefill>(&NoParams {})?, |_| {
            "refill noted; the paused job continues".to_string()
        }),
        Commands::Plan(_) | Commands::LinkTest { .. } | Commands::Demo(_) | Commands::Mixer(_) => {}
    }
    Ok(ExitCode::SUCCESS)
}

/// `edoctl submit`: a job file or a dry run; with `--watch`, follow it to the end.
fn submit(
    c: &mut Client,
    out: &Output,
    job: Option<&std::path::Path>,
    dry_run_moves: Option<u32>,
    watch: bool,
) -> anyhow::Result<ExitCode> {
    let params = match (job, dry_run_moves) {
        (Some(job), _) => client::submit_params(job)?,
        (None, Some(n)) => SubmitParams::dry_run(n),
        (None, None) => anyhow::bail!("give a job file or --dry-run-moves N"),
    };
    let r = c.request::<method::JobSubmit>(&params)?;
    for w in &r.result.warnings {
        eprintln!("warning: {w}");
    }
    if watch {
        let j = client::watch(c, r.result.id, out.json)?;
        out.print(&j, client::job_line);
        return Ok(ended_well(&j.result));
    }
    out.print(&r, |r| format!("job {} queued", r.id));
    Ok(ExitCode::SUCCESS)
}

/// `edoctl status`: the machine, and the active job's progress.
fn status(c: &mut Client, out: &Output) -> anyhow::Result<()> {
    let m = c.request::<method::MachineStatus>(&NoParams {})?;
    out.print(&m, |m| {
        let s = &m.machine;
        let mut human = format!(
            "machine on {}: {}, {}",
            s.port,
            if s.connected {
                "connected"
            } else {
                "not connected"
            },
            s.state.map_or("state unknown", client::machine_state_name)
        );
        if let Some(why) = &s.disconnected_reason {
            human.push_str(&format!("\n  why: {why}"));
        }
        if let Some(problem) = &s.link_problem {
            human.push_str(&format!("\n  not answering: {problem}"));
        }
        if let Some(problem) = &s.store_problem {
            human.push_str(&format!(
                "\n  {problem}: jobs hold until edod's state directory has room"
            ));
        }
        if let Some(held) = s.queue_held_by {
            human.push_str(&format!(
                "\n  queue waits: job {held} is interrupted; resume or cancel it, or \
                 'edoctl start-next' once the machine is ready for a new part"
            ));
        }
        if let Some(p) = &m.progress {
            human.push_str(&format!("\n{}", client::progress_line(p)));
        }
        human
    });
    Ok(())
}

/// `edoctl link-test --protocol`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum LinkProtocol {
    Edo,
    Gcode,
}

/// `link-test --protocol gcode`: dry-run moves through the G-code line protocol.
fn gcode_link_test(
    port: PathBuf,
    moves: u32,
    baud: u32,
    (firmware, window): (Option<edo::gcode_link::Dialect>, &str),
    json: bool,
) -> anyhow::Result<ExitCode> {
    use edo::gcode_link::Window;
    // clap requires it with --protocol gcode.
    let firmware = firmware.ok_or_else(|| anyhow::anyhow!("--firmware: rrf, marlin or klipper"))?;
    let window = match window {
        "auto" => Window::Auto,
        "advanced-ok" => Window::AdvancedOk,
        n => Window::Lines(
            n.parse::<u16>()
                .ok()
                .filter(|n| (1..=64).contains(n))
                .ok_or_else(|| anyhow::anyhow!("--window {n:?}: auto, advanced-ok or 1 to 64"))?,
        ),
    };
    let report = edo::cli::linktest_gcode::run(&edo::cli::linktest_gcode::GcodeLinkTestConfig {
        port,
        firmware,
        moves,
        baud,
        window,
        stall_timeout: Duration::from_secs(30),
    })?;
    if json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{report}");
    }
    Ok(if report.is_clean() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn link_test(port: PathBuf, moves: u32, baud: u32, json: bool) -> anyhow::Result<ExitCode> {
    let report = edo::cli::linktest::run(&edo::cli::linktest::LinkTestConfig {
        port,
        moves,
        baud,
        stall_timeout: Duration::from_secs(10),
    })?;
    if json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{report}");
    }
    let clean = report.lost == 0
        && report.duplicated == 0
        && report.reordered == 0
        && report.aborted.is_none();
    Ok(if clean {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Commands::Plan(args) => edo::cli::plan::run(args).map(|()| ExitCode::SUCCESS),
        Commands::Demo(args) => edo::cli::demo::run(args, cli.json),
        Commands::Mixer(command) => {
            edo::cli::mixer::run(command, cli.json).map(|()| ExitCode::SUCCESS)
        }
        Commands::LinkTest {
            port,
            moves,
            baud,
            protocol: LinkProtocol::Edo,
            ..
        } => link_test(port.clone(), *moves, *baud, cli.json),
        Commands::LinkTest {
            port,
            moves,
            baud,
            firmware,
            window,
            ..
        } => gcode_link_test(port.clone(), *moves, *baud, (*firmware, window), cli.json),
        _ => daemon(&cli),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("edoctl: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
