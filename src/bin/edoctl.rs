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
    #[command(subcommand)]
    command: Commands,
}

#[derive(Debug, Subcommand)]
enum Commands {
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
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
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
    let result = match cli.command {
        Commands::Plan(args) => edo::cli::plan::run(&args).map(|()| ExitCode::SUCCESS),
        Commands::LinkTest {
            port,
            moves,
            baud,
            json,
        } => link_test(port, moves, baud, json),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("edoctl: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
