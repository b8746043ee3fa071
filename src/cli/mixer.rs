//! `edoctl mixer fit RECORD [--model plug|mixed|dispersion]`: fit the mixing chamber's
//! model to a measured step response (format: [`crate::mixer::fit`], docs/toolpath.md)
//! and print the `[machine.mixer]` table to paste into edod.toml.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// Largest record read, bytes.
pub const MAX_RECORD_BYTES: u64 = 64 * 1024 * 1024;

/// `edoctl mixer ...`.
#[derive(clap::Subcommand, Debug)]
pub enum MixerCommand {
    /// Fit the mixing chamber's model to a step-response record (lines of pushed nl and
    /// the new material's fraction at the nozzle) and print the [machine.mixer] table.
    Fit {
        /// The record (text: "pushed_nl fraction" per line, # comments).
        record: PathBuf,
        /// Fit this model only (default: the simplest that fits within 10 % of the best).
        #[arg(long, value_name = "MODEL")]
        model: Option<String>,
    },
}

/// Run a `mixer` subcommand; `json`: print the fit as JSON.
pub fn run(command: &MixerCommand, json: bool) -> Result<()> {
    let MixerCommand::Fit { record, model } = command;
    let text = read_record(record)?;
    print!("{}", fit_text(&text, model.as_deref(), json, record)?);
    Ok(())
}

fn read_record(path: &Path) -> Result<String> {
    let meta =
        std::fs::metadata(path).with_context(|| format!("cannot read {}", path.display()))?;
    if meta.len() > MAX_RECORD_BYTES {
        anyhow::bail!(
            "{} is {} bytes, over the {MAX_RECORD_BYTES} byte limit",
            path.display(),
            meta.len()
        );
    }
    std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))
}

/// The fit of a record's text, as the table to paste (or JSON).
fn fit_text(text: &str, model: Option<&str>, json: bool, path: &Path) -> Result<String> {
    use crate::mixer::{fit, MixerModel};
    let samples = fit::parse_record(text).with_context(|| format!("record {}", path.display()))?;
    let model = model
        .map(MixerModel::from_name)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--model: {}", e.message))?;
    let f = fit::fit(&samples, model).map_err(|e| anyhow::anyhow!("fit: {e}"))?;
    let o = f.options;
    if json {
        return Ok(serde_json::json!({
            "model": o.model,
            "volume_nl": o.volume_nl,
            "peclet": o.peclet,
            "rms_residual": f.rms,
            "samples": samples.len(),
        })
        .to_string()
            + "\n");
    }
    let mut out = format!(
        "# fitted to {} samples of {}: rms residual {:.4}\n[machine.mixer]\nmodel = \"{}\"\nvolume_nl = {:.1}\n",
        samples.len(),
        path.display(),
        f.rms,
        o.model.name(),
        o.volume_nl
    );
    if let Some(pe) = o.peclet {
        out.push_str(&format!("peclet = {pe:.3}\n"));
    }
    Ok(out)
}
