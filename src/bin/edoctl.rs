//! edoctl: the operator's command-line client. A thin skin over the `edo` library:
//! every subcommand's work lives in `edo::cli`.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "edoctl",
    version,
    about = "Plan and run graded-material (EDO) prints"
)]
struct Cli {
    #[command(subcommand)]
    command: Commands,
}

#[derive(Subcommand)]
enum Commands {
    /// Plan a job offline: validate it, run the EDO method on every layer, and write
    /// the plan report and SVG previews.
    Plan(edo::cli::plan::PlanArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Commands::Plan(args) => edo::cli::plan::run(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("edoctl: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
