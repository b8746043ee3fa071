//! `edoctl plan JOB --gcode FILE --flavor rrf|marlin|klipper`: the library side. The lead wires
//! [`GcodeArgs`] into `PlanArgs` (`#[command(flatten)]`) and calls [`write`] with the
//! planned layers.

use crate::job::Job;
use crate::machine::gcode::{write_gcode, Flavor, GcodeSettings, GcodeStats};
use crate::machine::placement::{BuildVolume, Placement};
use crate::machine::{Move, MoveKind};
use crate::pipeline::{job_layer_moves, LayerStats, ProcessSettings, StreamState};
use crate::plan::LayerPlan;
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};

/// G-code export options of `edoctl plan`.
#[derive(clap::Args, Debug, Clone)]
pub struct GcodeArgs {
    /// Write the job as G-code to FILE (see docs/gcode.md).
    #[arg(long, value_name = "FILE")]
    pub gcode: Option<PathBuf>,
    /// Firmware the G-code is for.
    #[arg(long, value_enum, default_value = "rrf")]
    pub flavor: Flavor,
    /// Syringe barrel cross-section, mm² (E is plunger travel in mm).
    #[arg(long, value_name = "MM2", default_value_t = 165.0)]
    pub barrel_area: f64,
    /// Marlin: put the mix into G1 as A B C weights (DIRECT_MIXING_IN_G1).
    #[arg(long)]
    pub marlin_direct_mixing: bool,
    /// Klipper: the G1 axis letter of each syringe, in syringe order (`A,B`; default
    /// A B C D H I ...), as `[machine.gcode] axes`.
    #[arg(long, value_name = "LETTERS", value_delimiter = ',')]
    pub axes: Vec<char>,
}

impl GcodeArgs {
    pub fn settings(&self) -> GcodeSettings {
        GcodeSettings {
            flavor: self.flavor,
            barrel_area_mm2: self.barrel_area,
            marlin_direct_mixing: self.marlin_direct_mixing,
            axes: self.axes.clone(),
        }
    }
}

/// What [`write`] produced.
#[derive(Debug, Clone)]
pub struct GcodeSummary {
    pub moves: usize,
    pub layers: Vec<LayerStats>,
    pub gcode: GcodeStats,
    /// Commanded volume per syringe over the job, nl.
    pub commanded_nl: Vec<u64>,
}

/// All moves of a job (job id 0), starting with `Home`, placed on the machine by
/// `placement` and each checked to lie inside `volume`.
pub fn job_moves(
    job: &Job,
    layers: &[LayerPlan],
    process: &ProcessSettings,
    (placement, volume): (&Placement, &BuildVolume),
) -> Result<(Vec<Move>, Vec<LayerStats>, StreamState)> {
    let mut state = StreamState::new();
    let mut moves = vec![Move {
        job_id: 0,
        index: 0,
        kind: MoveKind::Home,
    }];
    let mut stats = Vec::with_capacity(layers.len());
    let all = job_layer_moves(layers, process, 0, moves.len() as u32, &mut state)
        .with_context(|| format!("job {}: turning layers into moves", job.name))?;
    for (layer, mut out) in layers.iter().zip(all) {
        placement
            .put_on_machine(&mut out.moves, volume)
            .map_err(|e| anyhow::anyhow!("job {} layer {}: {e}", job.name, layer.index))?;
        moves.extend(out.moves);
        stats.push(out.stats);
    }
    Ok((moves, stats, state))
}

/// Turn planned layers into moves with `process` settings, place them on the machine
/// (`placement`, inside `volume`: see [`crate::machine::placement`]) and write them as
/// G-code to `path`.
pub fn write(
    job: &Job,
    layers: &[LayerPlan],
    process: &ProcessSettings,
    settings: &GcodeSettings,
    on_machine: (&Placement, &BuildVolume),
    path: &Path,
) -> Result<GcodeSummary> {
    let (moves, stats, state) = job_moves(job, layers, process, on_machine)?;
    let header = vec![
        format!(
            "edo job {}: {} layer(s), {} moves",
            job.name,
            layers.len(),
            moves.len()
        ),
        format!(
            "drives (syringes) in order: {}; barrel area {} mm2",
            job.materials.join(", "),
            settings.barrel_area_mm2
        ),
    ];
    let mut text = String::new();
    let gcode = write_gcode(&moves, job.materials.len(), settings, &header, &mut text)?;
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
    }
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(GcodeSummary {
        moves: moves.len(),
        layers: stats,
        gcode,
        commanded_nl: state.commanded_nl().to_vec(),
    })
}
