//! edoctl: the operator's command-line client. A thin skin over the `edo` library:
//! every subcommand's work lives in a library module.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand};

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
        id: u64,
    },
    /// Hold a printing job at the next move boundary.
    Pause {
        /// Job id.
        id: u64,
    },
    /// Continue a paused or interrupted job.
    Resume {
        /// Job id.
        id: u64,
    },
    /// Cancel a job; a printing one stops, retracts and parks (this waits until it has).
    Cancel {
        /// Job id.
        id: u64,
    },
    /// Delete a finished (done, failed or cancelled) job and its mesh from edod's store.
    Delete {
        /// Job id.
        id: u64,
    },
    /// Emergency stop: goes out ahead of everything queued.
    Estop,
    /// The syringes were refilled: clear the fault and continue.
    Refill,
}

fn daemon(cli: &Cli) -> anyhow::Result<ExitCode> {
    use edo::cli::client::{job_line, submit_params, watch, Client};
    use serde_json::json;
    let mut c = Client::connect(&cli.socket)?;
    let print = |v: &serde_json::Value, human: String| {
        if cli.json {
            println!("{v}");
        } else {
            println!("{human}");
        }
    };
    let ended_well = |j: &serde_json::Value| j["state"] == json!("done");
    match &cli.command {
        Commands::Submit {
            job,
            dry_run_moves,
            watch: w,
        } => {
            let params = match (job, dry_run_moves) {
                (Some(job), _) => submit_params(job)?,
                (None, n) => json!({"dry_run_moves": n}),
            };
            let r = c.call("job.submit", params)?;
            let id = r["id"].as_u64().unwrap_or(0);
            if *w {
                let j = watch(&mut c, id, cli.json)?;
                print(&j, job_line(&j));
                return Ok(if ended_well(&j) {
                    ExitCode::SUCCESS
                } else {
                    ExitCode::FAILURE
                });
            }
            print(&r, format!("job {id} queued"));
        }
        Commands::Jobs => {
            let r = c.call("job.list", json!({}))?;
            let lines: Vec<String> = r
                .as_array()
                .map(|a| a.iter().map(job_line).collect())
                .unwrap_or_default();
            print(&r, lines.join("\n"));
        }
        Commands::Status => {
            let m = c.call("machine.status", json!({}))?;
            let mut human = format!(
                "machine on {}: {}, {}",
                m["port"].as_str().unwrap_or("?"),
                if m["connected"] == json!(true) {
                    "connected"
                } else {
                    "not connected"
                },
                m["state"].as_str().unwrap_or("unknown state")
            );
            if let Some(p) = m.get("progress").filter(|p| p.is_object()) {
                human.push_str(&format!("\n{}", edo::cli::client::progress_line(p)));
            }
            print(&m, human);
        }
        Commands::Watch { id } => {
            let j = watch(&mut c, *id, cli.json)?;
            print(&j, job_line(&j));
            return Ok(if ended_well(&j) {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            });
        }
        Commands::Pause { id } => {
            let r = c.call("job.pause", json!({"id": id}))?;
            print(&r, format!("job {id} paused"));
        }
        Commands::Resume { id } => {
            let r = c.call("job.resume", json!({"id": id}))?;
            print(&r, format!("job {id} resumed"));
        }
        Commands::Cancel { id } => {
            let j = edo::cli::client::cancel(&mut c, *id, edo::cli::client::CANCEL_WAIT)?;
            print(&j, edo::cli::client::cancelled_line(&j));
            if j["state"] != json!("cancelled") {
                // It ended some other way (done or failed) before the cancel took.
                return Ok(ExitCode::FAILURE);
            }
        }
        Commands::Delete { id } => {
            let r = c.call("job.delete", json!({"id": id}))?;
            print(&r, format!("job {id} deleted"));
        }
        Commands::Estop => {
            let r = c.call("machine.estop", json!({}))?;
            print(
                &r,
                format!(
                    "e-stop sent after {} µs, acknowledged after {}",
                    r["written_after_us"],
                    r["acked_after_us"]
                        .as_u64()
                        .map_or("(no ack within 1 s)".to_string(), |a| format!("{a} µs"))
                ),
            );
        }
        Commands::Refill => {
            let r = c.call("machine.refill", json!({}))?;
            print(&r, "refill noted; the paused job continues".to_string());
        }
        Commands::Plan(_) | Commands::LinkTest { .. } | Commands::Demo(_) => {}
    }
    Ok(ExitCode::SUCCESS)
}

fn link_test(port: PathBuf, moves: u32, baud: u32, json: bool) -> anyhow::Result<ExitCode> {
    let report = edo::linktest::run(&edo::linktest::LinkTestConfig {
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
        Commands::LinkTest { port, moves, baud } => {
            link_test(port.clone(), *moves, *baud, cli.json)
        }
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
