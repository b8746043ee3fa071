//! `edoctl plan JOB --gcode FILE --flavor rrf|marlin|klipper`: the library side. The lead wires
//! [`GcodeArgs`] into `PlanArgs` (`#[command(flatten)]`) and calls [`write`] with the
//! planned layers.

use crate::job::Job;
use crate::machine::gcode::{Flavor, GcodeSettings, GcodeStats, MoveWriter};
use crate::machine::placement::{BuildVolume, Placement};
use crate::machine::{Move, MoveKind};
use crate::pipeline::{
    for_each_job_layer_moves, job_layer_moves, LayerStats, ProcessSettings, StreamState,
};
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
/// G-code to `path`, a layer at a time as the moves are made (the job's moves are
/// never all held). The lines go to `path` with `.part` added, renamed to `path` once
/// complete, so a refused job (a move off the machine) leaves no file.
pub fn write(
    job: &Job,
    layers: &[LayerPlan],
    process: &ProcessSettings,
    settings: &GcodeSettings,
    (placement, volume): (&Placement, &BuildVolume),
    path: &Path,
) -> Result<GcodeSummary> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
    }
    let mut part = path.as_os_str().to_owned();
    part.push(".part");
    let part = PathBuf::from(part);
    let written = write_lines(job, layers, process, settings, (placement, volume), &part);
    let summary = match written {
        Ok(s) => s,
        Err(e) => {
            let _ = std::fs::remove_file(&part);
            return Err(e);
        }
    };
    std::fs::rename(&part, path)
        .with_context(|| format!("cannot write {} (from {})", path.display(), part.display()))?;
    Ok(summary)
}

/// [`write`]'s lines into the file `to`.
fn write_lines(
    job: &Job,
    layers: &[LayerPlan],
    process: &ProcessSettings,
    settings: &GcodeSettings,
    (placement, volume): (&Placement, &BuildVolume),
    to: &Path,
) -> Result<GcodeSummary> {
    use std::io::Write;
    let file =
        std::fs::File::create(to).with_context(|| format!("cannot write {}", to.display()))?;
    let mut file = std::io::BufWriter::new(file);
    let header = vec![
        format!("edo job {}: {} layer(s)", job.name, layers.len()),
        format!(
            "drives (syringes) in order: {}; barrel area {} mm2",
            job.materials.join(", "),
            settings.barrel_area_mm2
        ),
    ];
    let mut w = MoveWriter::new(job.materials.len(), settings)?;
    let mut lines = Vec::new();
    let mut put = |w: &mut MoveWriter, ms: &[Move], lines: &mut Vec<String>| -> Result<()> {
        for m in ms {
            w.move_lines(m, lines);
        }
        for l in lines.drain(..) {
            file.write_all(l.as_bytes())?;
            file.write_all(b"\n")?;
        }
        Ok(())
    };
    w.preamble(&header, &mut lines);
    let home = Move {
        job_id: 0,
        index: 0,
        kind: MoveKind::Home,
    };
    put(&mut w, &[home], &mut lines)?;
    let (mut state, mut stats, mut moves, mut k) = (StreamState::new(), Vec::new(), 1, 0);
    for_each_job_layer_moves(layers, process, 0, 1, &mut state, |mut out| {
        let index = layers.get(k).map_or(k, |l| l.index);
        k += 1;
        placement
            .put_on_machine(&mut out.moves, volume)
            .map_err(|e| anyhow::anyhow!("job {} layer {index}: {e}", job.name))?;
        put(&mut w, &out.moves, &mut lines)?;
        moves += out.moves.len();
        stats.push(out.stats);
        Ok::<(), anyhow::Error>(())
    })
    .with_context(|| format!("job {}: turning layers into moves", job.name))?;
    put(&mut w, &[], &mut lines)?;
    file.flush()
        .with_context(|| format!("cannot write {}", to.display()))?;
    Ok(GcodeSummary {
        moves,
        layers: stats,
        gcode: w.stats(),
        commanded_nl: state.commanded_nl().to_vec(),
    })
}
