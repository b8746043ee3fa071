//! `edoctl plan JOB --gcode FILE --flavor rrf|marlin|klipper`: the library side. The lead wires
//! [`GcodeArgs`] into `PlanArgs` (`#[command(flatten)]`) and calls [`write`] with the
//! planned layers.

use crate::gcode_link::writer::{Dialect, GcodeSettings, GcodeStats, MoveWriter};
use crate::job::placement::{BuildVolume, Placement};
use crate::job::Job;
use crate::pipeline::{for_each_layer_moves, LayerStats, ProcessSettings, StreamState};
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
    pub flavor: Dialect,
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
            ..GcodeSettings::default()
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

/// Layers planned into moves and written at a time: enough to keep every core busy
/// finishing paths, few enough that a tall part's moves never sit in memory at once.
const LAYERS_PER_BATCH: usize = 16;

/// Turn planned layers into moves with `process` settings, place them on the machine
/// (`placement`, inside `volume`: see [`crate::job::placement`]) and write them as
/// G-code to `path`, a batch of layers at a time. The file is written beside `path` and
/// renamed onto it at the end: a job refused half-way (a move outside the volume) leaves
/// no file, and an older file stays whole until the new one is.
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
    let partial = partial_path(path);
    let file = std::fs::File::create(&partial)
        .with_context(|| format!("cannot write {}", partial.display()))?;
    let mut out = LineSink {
        file: std::io::BufWriter::with_capacity(1 << 20, file),
        path: &partial,
        lines: Vec::new(),
    };
    let written = (|| {
        let drives = process.channels().unwrap_or(job.materials.len());
        let mut w = MoveWriter::new(drives, settings)?;
        w.preamble(&header(job, layers.len(), settings), &mut out.lines);
        let summary = write_moves(job, layers, process, (placement, volume), &mut w, &mut out)?;
        out.finish()?;
        Ok(summary)
    })();
    let summary = match written {
        Ok(summary) => summary,
        Err(e) => {
            let _ = std::fs::remove_file(&partial);
            return Err(e);
        }
    };
    if let Err(e) = std::fs::rename(&partial, path) {
        let _ = std::fs::remove_file(&partial);
        return Err(e).with_context(|| format!("cannot write {}", path.display()));
    }
    Ok(summary)
}

/// The job's moves, from `Home` on, through `w` into `out` a batch of layers at a time.
fn write_moves(
    job: &Job,
    layers: &[LayerPlan],
    process: &ProcessSettings,
    (placement, volume): (&Placement, &BuildVolume),
    w: &mut MoveWriter,
    out: &mut LineSink<'_>,
) -> Result<GcodeSummary> {
    w.move_lines(&crate::pipeline::home_move(0), &mut out.lines);
    out.flush_lines()?;
    let mut moves = 1;
    let mut stats = Vec::with_capacity(layers.len());
    let mut state = StreamState::new();
    for_each_layer_moves(
        layers,
        process,
        (0, crate::pipeline::FIRST_LAYER_MOVE_INDEX),
        &mut state,
        LAYERS_PER_BATCH,
        |layer, mut lm| -> Result<()> {
            placement
                .put_on_machine(&mut lm.moves, volume)
                .map_err(|e| anyhow::anyhow!("layer {}: {e}", layer.index))?;
            let mut features = Features::new(&lm, process.support.is_some());
            for m in &lm.moves {
                if let Some(name) = features.before(m.index) {
                    w.feature(name, &mut out.lines);
                }
                w.move_lines(m, &mut out.lines);
            }
            out.flush_lines()?;
            moves += lm.moves.len();
            stats.push(lm.stats);
            Ok(())
        },
    )
    .with_context(|| format!("job {}: turning layers into moves", job.name))?;
    w.epilogue(&mut out.lines);
    w.comment(
        &format!("end of job {}: {moves} moves", job.name),
        &mut out.lines,
    );
    Ok(GcodeSummary {
        moves,
        layers: stats,
        gcode: w.stats(),
        commanded_nl: state.commanded_nl().to_vec(),
    })
}

/// What the roads of a layer build, for `;TYPE:` lines where it changes (a job with
/// supports only: the others' files stay as they were).
struct Features<'a> {
    roles: std::iter::Peekable<std::slice::Iter<'a, (u32, u32)>>,
    paths: &'a [crate::toolpath::ToolPath],
    last: Option<&'static str>,
    on: bool,
}

impl<'a> Features<'a> {
    fn new(lm: &'a crate::pipeline::LayerMoves, on: bool) -> Self {
        Features {
            roles: lm.extrusion_paths.iter().peekable(),
            paths: &lm.paths,
            last: None,
            on,
        }
    }

    /// The feature to mark before move `index`, where it starts one.
    fn before(&mut self, index: u32) -> Option<&'static str> {
        if !self.on {
            return None;
        }
        while self.roles.next_if(|(i, _)| *i < index).is_some() {}
        let &(_, path) = self.roles.next_if(|(i, _)| *i == index)?;
        let name = feature_name(self.paths.get(path as usize)?.role);
        if self.last == Some(name) {
            return None;
        }
        self.last = Some(name);
        Some(name)
    }
}

/// PrusaSlicer's name of what a road builds: the EDO contours and offsets are the
/// part's perimeters.
fn feature_name(role: crate::toolpath::PathRole) -> &'static str {
    use crate::toolpath::PathRole;
    match role {
        PathRole::Contour { .. } | PathRole::Offset { .. } => "Perimeter",
        PathRole::GapFill { .. } => "Gap fill",
        PathRole::Support => "Support material",
        PathRole::SupportInterface => "Support material interface",
    }
}

/// The file's header comments.
fn header(job: &Job, layers: usize, settings: &GcodeSettings) -> Vec<String> {
    let mut drives = job.materials.clone();
    drives.extend(job.support.syringe().map(str::to_string));
    vec![
        format!("edo job {}: {layers} layer(s)", job.name),
        format!(
            "drives (syringes) in order: {}; barrel area {} mm2",
            drives.join(", "),
            settings.barrel_area_mm2
        ),
    ]
}

/// `dir/.name.partial`: where [`write`] writes before the rename.
fn partial_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map_or_else(|| "gcode".into(), |n| n.to_string_lossy().into_owned());
    path.with_file_name(format!(".{name}.partial"))
}

/// Lines from a [`MoveWriter`] on their way into the file.
struct LineSink<'a> {
    file: std::io::BufWriter<std::fs::File>,
    path: &'a Path,
    lines: Vec<String>,
}

impl LineSink<'_> {
    fn flush_lines(&mut self) -> Result<()> {
        use std::io::Write;
        for l in self.lines.drain(..) {
            self.file
                .write_all(l.as_bytes())
                .and_then(|()| self.file.write_all(b"\n"))
                .with_context(|| format!("cannot write {}", self.path.display()))?;
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        use std::io::Write;
        self.flush_lines()?;
        self.file
            .flush()
            .with_context(|| format!("cannot write {}", self.path.display()))
    }
}
