//! `edoctl plan JOB.toml [--report FILE|-] [--svg DIR] [--layers A..B]`: plan a job
//! offline. Reads the job and its mesh (relative paths are relative to the job file),
//! slices, runs the EDO method on every layer, writes the report and previews.

use crate::job::placement::{place_part, placed_settings, BuildVolume};
use crate::job::{Geometry, Job};
use crate::mesh::MeshLimits;
use crate::plan::LayerSlice;
use crate::plan::{plan_layers, LayerPlan};
use crate::report::MeshNotes;
use anyhow::{Context, Result};
use std::io::{IsTerminal, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Largest job file read, bytes (a job is a few kB; this keeps a wrong path from
/// reading a huge file).
pub const MAX_JOB_BYTES: u64 = 16 * 1024 * 1024;

#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    /// The job file (TOML, see docs/job-format.md).
    pub job: PathBuf,
    /// Write the plan report as JSON to FILE, or to standard output with "-".
    #[arg(long, value_name = "FILE|-")]
    pub report: Option<String>,
    /// Write one SVG preview per layer into DIR (created if missing).
    #[arg(long, value_name = "DIR")]
    pub svg: Option<PathBuf>,
    /// Plan only layers A to B−1 (0-based, like 10..20; "7" plans layer 7 alone).
    #[arg(long, value_name = "A..B", value_parser = parse_layer_range)]
    pub layers: Option<Range<usize>>,
    /// No progress bar even on a terminal.
    #[arg(long)]
    pub quiet: bool,
    /// Measure the roads' coverage (void, overlap, outside at 10 µm) into the report
    /// (always done for the layers drawn with --svg).
    #[arg(long)]
    pub coverage: bool,
    /// The machine's build volume X,Y,Z in mm (edod.toml `machine.build_volume_mm`):
    /// where `geometry.placement` puts the part, whether it fits, and the frame of the
    /// G-code.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_build_volume, default_value = "200,200,150")]
    pub build_volume: [f64; 3],
    #[command(flatten)]
    pub gcode: crate::cli::gcode::GcodeArgs,
    #[command(flatten)]
    pub mixer: MixerArgs,
    /// Plan as edod plans on the machine of this edod.toml: its syringes, flow cap,
    /// mixing chamber and build volume (`[machine]`) and, for --gcode, its firmware,
    /// mix writing, barrel and plunger limits (`[machine.gcode]`). The G-code file is
    /// then line for line what edod streams for the job (docs/gcode.md).
    #[arg(long, value_name = "EDOD.TOML", conflicts_with_all = MACHINE_OPTIONS)]
    pub machine: Option<PathBuf>,
}

/// The options `--machine` gives values to: it takes them from edod.toml.
const MACHINE_OPTIONS: [&str; 9] = [
    "build_volume",
    "flavor",
    "barrel_area",
    "marlin_direct_mixing",
    "axes",
    "mixer",
    "mixer_volume_nl",
    "mixer_peclet",
    "no_feed_forward",
];

/// edod's configuration, read for `--machine`.
struct Machine {
    path: PathBuf,
    config: crate::daemon::config::Config,
}

impl Machine {
    fn load(path: &Path) -> Result<Self> {
        let config = crate::daemon::config::Config::load(path)
            .map_err(|e| anyhow::anyhow!("--machine: {e}"))?;
        Ok(Self {
            path: path.to_path_buf(),
            config,
        })
    }

    /// The process settings edod streams `job` with on this machine.
    fn process_settings(
        &self,
        job: &Job,
        job_path: &Path,
    ) -> Result<crate::pipeline::ProcessSettings> {
        crate::setup::process_settings(job, &self.config.machine, &job_path.display().to_string())
            .map_err(|e| anyhow::anyhow!("--machine {}: {e}", self.path.display()))
    }

    /// How edod writes this machine's G-code.
    fn gcode_settings(&self) -> Result<crate::gcode_link::writer::GcodeSettings> {
        match self.config.gcode_link() {
            Ok(Some(g)) => Ok(g.settings()),
            Ok(None) => anyhow::bail!(
                "--machine {}: machine.protocol is \"edo\": edod streams edo's own link to this \
                 machine, not G-code (--gcode needs machine.protocol = \"gcode\")",
                self.path.display()
            ),
            Err((key, why)) => anyhow::bail!("--machine {}: {key}: {why}", self.path.display()),
        }
    }
}

/// The machine's mixing chamber (edod.toml `[machine.mixer]`), for planning offline.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct MixerArgs {
    /// The mixing chamber's residence-time distribution: plug (default: a pure delay
    /// of the volume), mixed (one well-mixed tank) or dispersion (plug flow with axial
    /// dispersion, needs --mixer-peclet).
    #[arg(long, value_name = "MODEL")]
    pub mixer: Option<String>,
    /// The chamber's volume V in nl (default: the job's `[toolpath] v_dead_ul`).
    #[arg(long, value_name = "NL", requires = "mixer")]
    pub mixer_volume_nl: Option<f64>,
    /// Peclet number of the dispersion model (more than 0).
    #[arg(long, value_name = "PE", requires = "mixer")]
    pub mixer_peclet: Option<f64>,
    /// Command the design V ahead only (the mixing lead), not the mixer's feed-forward
    /// inverse.
    #[arg(long)]
    pub no_feed_forward: bool,
}

impl MixerArgs {
    /// `settings` with this mixer (an error names the option).
    pub fn apply(
        &self,
        mut settings: crate::pipeline::ProcessSettings,
    ) -> Result<crate::pipeline::ProcessSettings> {
        if self.no_feed_forward {
            settings.mixer_feed_forward = false;
        }
        let Some(model) = &self.mixer else {
            return Ok(settings);
        };
        let volume = self.mixer_volume_nl.unwrap_or(settings.v_dead_ul * 1000.0);
        let m = crate::mixer::MixerOptions::new(model, volume, self.mixer_peclet)
            .map_err(|e| anyhow::anyhow!("{}: {}", e.option(), e.message))?;
        settings.v_dead_ul = m.volume_nl / 1000.0;
        settings.mixer_model = m.model;
        settings.mixer_peclet = m.peclet;
        Ok(settings)
    }
}

/// Parse a build volume `X,Y,Z` (mm).
pub fn parse_build_volume(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("\"{s}\" is not X,Y,Z in mm (e.g. 200,200,150)"))?;
    let v: [f64; 3] = v
        .try_into()
        .map_err(|_| format!("\"{s}\" is not three sides X,Y,Z in mm (e.g. 200,200,150)"))?;
    BuildVolume::new(v)?;
    Ok(v)
}

/// Parse `A..B` (half-open) or a single index `A`.
pub fn parse_layer_range(s: &str) -> Result<Range<usize>, String> {
    let num = |t: &str| {
        t.trim()
            .parse::<usize>()
            .map_err(|_| format!("\"{t}\" is not a layer index; use A..B (e.g. 10..20) or A"))
    };
    let r = match s.split_once("..") {
        Some((a, b)) => num(a)?..num(b)?,
        None => {
            let a = num(s)?;
            a..a + 1
        }
    };
    if r.start >= r.end {
        return Err(format!(
            "layer range {s} is empty; the end is exclusive (10..20 plans layers 10 to 19)"
        ));
    }
    Ok(r)
}

/// Read a job file with a size limit and parse it.
pub fn load_job(path: &Path) -> Result<Job> {
    let meta = std::fs::metadata(path)
        .with_context(|| format!("cannot read job file {}", path.display()))?;
    if meta.len() > MAX_JOB_BYTES {
        anyhow::bail!(
            "job file {} is {} bytes, over the {} byte limit",
            path.display(),
            meta.len(),
            MAX_JOB_BYTES
        );
    }
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read job file {}", path.display()))?;
    Ok(Job::from_toml(&text, &path.display().to_string())?)
}

/// A progress bar on standard error when it is a terminal and not `quiet`.
fn bar(len: u64, what: &str, quiet: bool) -> Option<indicatif::ProgressBar> {
    if quiet || !std::io::stderr().is_terminal() {
        return None;
    }
    let b = indicatif::ProgressBar::new(len);
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("{msg:>10} [{bar:40}] {pos}/{len} layers ({eta})")
    {
        b.set_style(style.progress_chars("=> "));
    }
    b.set_message(what.to_string());
    Some(b)
}

/// The job's layers (sliced from its mesh, or its extruded polygon), restricted to
/// `range`, with per-layer designs, and what loading and slicing reported.
pub fn job_layers(
    job: &Job,
    job_path: &Path,
    range: Option<Range<usize>>,
    quiet: bool,
) -> Result<(Vec<LayerSlice>, MeshNotes)> {
    let pick = |n: usize| -> Result<Range<usize>> {
        match &range {
            None => Ok(0..n),
            Some(r) if r.start < n => Ok(r.start..r.end.min(n)),
            Some(r) => anyhow::bail!(
                "--layers {}..{}: the job has {n} layers (0..{n})",
                r.start,
                r.end
            ),
        }
    };
    match &job.geometry {
        Geometry::Extruded { .. } => {
            let all = job.extruded_layers().unwrap_or_default();
            let r = pick(all.len())?;
            let layers = all[r.clone()].to_vec();
            Ok((job.layer_slices(r.start, layers), MeshNotes::default()))
        }
        Geometry::Mesh { path } => {
            let mesh_path = job_path.parent().unwrap_or(Path::new(".")).join(path);
            let limits = MeshLimits::default();
            let bytes = crate::mesh::path::read_limited(&mesh_path, &limits)
                .with_context(|| format!("geometry.mesh: cannot load {}", mesh_path.display()))?;
            let part = job
                .mesh_layers(&bytes, &limits)
                .with_context(|| mesh_path.display().to_string())?;
            let r = pick(part.len())?;
            let b = bar(r.len() as u64, "slicing", quiet);
            let progress = |done: usize, _total: usize| {
                if let Some(b) = &b {
                    b.set_position(done as u64);
                }
            };
            let (layers, slice_report) = part
                .cut(r.clone(), Some(&progress))
                .with_context(|| format!("slicing {}", mesh_path.display()))?;
            if let Some(b) = b {
                b.finish_and_clear();
            }
            let bounds = part.bounds();
            let mesh_report = part.mesh_report;
            Ok((
                job.layer_slices(r.start, layers),
                MeshNotes {
                    mesh: Some(mesh_report),
                    slicing: Some(slice_report),
                    orientation: Some(part.orientation),
                    bounds: Some(bounds),
                },
            ))
        }
    }
}

/// Plan the given layers with a progress bar.
pub fn plan_with_progress(job: &Job, slices: &[LayerSlice], quiet: bool) -> Result<Vec<LayerPlan>> {
    let b = bar(slices.len() as u64, "planning", quiet);
    let progress = |done: usize, _total: usize| {
        if let Some(b) = &b {
            b.set_position(done as u64);
        }
    };
    let layers = plan_layers(slices, &job.plan, Some(&progress))?;
    if let Some(b) = b {
        b.finish_and_clear();
    }
    Ok(layers)
}

/// `edoctl plan`: load and plan the job, then write what the options ask for (toolpaths
/// and coverage into the report, previews, the report, G-code) and a summary for people
/// (on standard error when the report goes to standard output).
pub fn run(args: &PlanArgs) -> Result<()> {
    let job = load_job(&args.job)?;
    let machine = args.machine.as_deref().map(Machine::load).transpose()?;
    let build_volume = machine
        .as_ref()
        .map_or(args.build_volume, |m| m.config.machine.build_volume_mm);
    let started = Instant::now();
    let (slices, notes) = job_layers(&job, &args.job, args.layers.clone(), args.quiet)?;
    let mut layers = plan_with_progress(&job, &slices, args.quiet)
        .with_context(|| format!("planning {}", args.job.display()))?;
    let hanging = overhangs_of(&job, &slices);
    let supports = support_areas_of(&job, &slices, &hanging);
    let planning_time_ms = started.elapsed().as_secs_f64() * 1e3;
    let bounds = notes.bounds.or_else(|| job.extruded_bounds());
    let mut report = crate::report::build(&job, &slices, &layers, notes, planning_time_ms);
    let overhangs = match &supports {
        Some(s) => still_hanging(&job, &slices, s),
        None => hanging,
    };
    crate::report::attach_overhangs(&mut report, job.overhang, &overhangs);
    if let Some(s) = supports {
        if let Some(o) = report.overhang.as_mut() {
            o.without_supports_mm2 = Some(s.without_mm2);
        }
        crate::report::attach_supports(&mut report, &job, &s.areas);
        for (layer, area) in layers.iter_mut().zip(s.areas) {
            layer.support = area;
        }
    }
    if job.support.required {
        if let Some(why) = report.overhang.as_ref().and_then(|o| o.refusal()) {
            anyhow::bail!("{}: {why}", args.job.display());
        }
    }
    // Where edod would put the part on a machine of this build volume (checked when
    // the option was parsed).
    let volume = BuildVolume::new(build_volume).map_err(|e| match &machine {
        Some(m) => anyhow::anyhow!(
            "--machine {}: machine.build_volume_mm: {e}",
            m.path.display()
        ),
        None => anyhow::anyhow!("--build-volume: {e}"),
    })?;
    let placed = bounds.map(|b| (b, place_part(&job, b, &volume)));
    report.placement = placed
        .as_ref()
        .map(|(b, p)| crate::report::PlacementReport::new(job.placement, build_volume, *b, p));

    let to_stdout = args.report.as_deref() == Some("-");
    let mut human: Box<dyn Write> = if to_stdout {
        Box::new(std::io::stderr())
    } else {
        Box::new(std::io::stdout())
    };
    // The purge position is a point of the bed: in the part's coordinates for planning.
    let process = match &machine {
        Some(m) => m.process_settings(&job, &args.job)?,
        None => args.mixer.apply(process_settings(&job))?,
    };
    let process = match &placed {
        Some((_, Ok(p))) => placed_settings(&process, p),
        _ => process,
    };
    let mut toolpath_line = None;
    if args.report.is_some() || args.svg.is_some() || args.coverage {
        let planned = Planned {
            job: &job,
            slices: &slices,
            layers: &layers,
            process: &process,
            overhangs: &overhangs,
        };
        attach_toolpaths(args, &planned, &mut report)?;
        toolpath_line = report.toolpath.as_ref().map(toolpath_summary);
    }
    if let Some(target) = &args.report {
        write_report(&report, target)?;
    }
    let gcode = match &args.gcode.gcode {
        Some(path) => {
            let placement = match &placed {
                Some((_, Ok(p))) => (p, &volume),
                Some((_, Err(e))) => anyhow::bail!("--gcode {}: {e}", path.display()),
                None => anyhow::bail!("--gcode {}: the part has no extent", path.display()),
            };
            let settings = match &machine {
                Some(m) => m.gcode_settings()?,
                None => args.gcode.settings(),
            };
            let g = crate::cli::gcode::write(&job, &layers, &process, &settings, placement, path)?;
            Some((path, settings.flavor, g))
        }
        None => None,
    };
    write_plan_summary(&mut human, &job, &report, &layers, planning_time_ms)?;
    if let Some(w) = report.overhang.as_ref().and_then(|o| o.warning()) {
        eprintln!("warning: {}: {w}", args.job.display());
    }
    if let Some(line) = toolpath_line {
        writeln!(human, "  {line}")?;
    }
    if let Some(o) = report.orientation.as_ref().filter(|o| o.mode != "keep") {
        writeln!(human, "  {}", orientation_summary(o))?;
    }
    if let Some(p) = &report.placement {
        writeln!(human, "  {}", placement_summary(p))?;
    }
    if let Some(dir) = &args.svg {
        writeln!(
            human,
            "  previews: {} (EDO contours and offsets), {} (roads: widths, travel, seams, voids)",
            dir.join("layer-*.svg").display(),
            dir.join("layer-*-roads.svg").display()
        )?;
    }
    if let Some((path, flavor, g)) = gcode {
        writeln!(human, "  {}", gcode_summary(flavor, &g, path))?;
    }
    Ok(())
}

/// One line: the way up chosen (`rotate = [x, y, z]`), why, and the runner-up.
fn orientation_summary(o: &crate::mesh::orient::OrientationReport) -> String {
    let c = &o.chosen;
    let [x, y, z] = c.rotate_deg;
    let mut line = format!(
        "orientation {}: rotate = [{x}, {y}, {z}] (support {:.0} mm³, {:.0} mm² on the bed, \
         {:.1} mm tall): {}",
        o.mode, c.support_volume_mm3, c.bed_contact_mm2, c.height_mm, o.why
    );
    if let Some(r) = &o.runner_up {
        let [x, y, z] = r.rotate_deg;
        line.push_str(&format!(
            "; runner-up rotate = [{x}, {y}, {z}] (support {:.0} mm³, {:.0} mm² on the bed)",
            r.support_volume_mm3, r.bed_contact_mm2
        ));
    }
    line
}

/// A planned job: what the toolpaths, coverage and previews are made from.
struct Planned<'a> {
    job: &'a Job,
    slices: &'a [LayerSlice],
    layers: &'a [LayerPlan],
    process: &'a crate::pipeline::ProcessSettings,
    /// Each layer's area resting on nothing (`slice::overhang::of_layers`).
    overhangs: &'a [Option<crate::geom::Shapes>],
}

/// Each planned layer's area resting on nothing beyond the job's allowed overhang.
fn overhangs_of(job: &Job, slices: &[LayerSlice]) -> Vec<Option<crate::geom::Shapes>> {
    let layers: Vec<(usize, &crate::slice::Layer)> =
        slices.iter().map(|s| (s.index, &s.layer)).collect();
    crate::slice::overhang::of_layers(&layers, &job.overhang_options())
}

/// What still rests on nothing with `supports` built.
fn still_hanging(
    job: &Job,
    slices: &[LayerSlice],
    supports: &PlannedSupports,
) -> Vec<Option<crate::geom::Shapes>> {
    let mut out: Vec<Option<crate::geom::Shapes>> =
        crate::slice::support::unsupported_with_support(
            &stack_of(slices),
            &supports.areas,
            &supports.overhangs,
            job.support.top_gap_mm,
            &job.overhang_options(),
        )
        .into_iter()
        .map(Some)
        .collect();
    // A range of layers planned on its own: its first layer's below is not here.
    if let Some(first) = out.first_mut().filter(|_| slices[0].index != 0) {
        *first = None;
    }
    out
}

/// The layers as supports see them.
fn stack_of(slices: &[LayerSlice]) -> Vec<crate::slice::support::StackLayer<'_>> {
    slices
        .iter()
        .map(|s| crate::slice::support::StackLayer {
            z_mm: s.layer.z_mm,
            thickness_mm: s.layer.thickness_mm,
            islands: &s.layer.islands,
        })
        .collect()
}

/// The supports of the layers planned, and what they were built under.
struct PlannedSupports {
    /// Each layer's support.
    areas: Vec<crate::slice::support::SupportArea>,
    /// Each layer's area hanging without supports (none: empty).
    overhangs: Vec<crate::geom::Shapes>,
    /// Their sum, mm².
    without_mm2: f64,
}

/// Each layer's support under the layers' `hanging` area, with `[support]` on (of the
/// layers planned: a range of layers planned on its own holds up only the overhangs
/// within it).
fn support_areas_of(
    job: &Job,
    slices: &[LayerSlice],
    hanging: &[Option<crate::geom::Shapes>],
) -> Option<PlannedSupports> {
    let opts = job.support_area_options()?;
    let overhangs: Vec<crate::geom::Shapes> = hanging
        .iter()
        .map(|h| h.clone().unwrap_or_default())
        .collect();
    let without_mm2 = overhangs.iter().map(crate::slice::overhang::area_mm2).sum();
    let areas = crate::slice::support::support_areas(&stack_of(slices), &overhangs, &opts);
    Some(PlannedSupports {
        areas,
        overhangs,
        without_mm2,
    })
}

/// Make every layer's toolpaths, measure their coverage when asked (or when previews
/// are drawn), put both into the report and draw the previews into `--svg`.
fn attach_toolpaths(
    args: &PlanArgs,
    planned: &Planned,
    report: &mut crate::report::PlanReport,
) -> Result<()> {
    let Planned {
        job,
        slices,
        layers,
        process,
        ..
    } = *planned;
    let toolpaths = layer_toolpaths(job, layers, process)?;
    let coverage = (args.coverage || args.svg.is_some()).then(|| {
        measure_coverage(
            &toolpaths,
            layers,
            slices,
            process,
            args.svg.is_some(),
            args.quiet,
        )
    });
    let stats: Vec<_> = toolpaths.iter().map(|t| t.stats.clone()).collect();
    let pairs: Option<Vec<_>> = coverage
        .as_ref()
        .map(|c| c.iter().map(|l| (l.with_raise, l.without_raise)).collect());
    crate::report::attach_toolpaths(report, &stats, pairs.as_deref());
    let paths: Vec<&[crate::toolpath::ToolPath]> =
        toolpaths.iter().map(|t| t.paths.as_slice()).collect();
    crate::report::attach_support_roads(report, &paths, process.road_width());
    if let Some(dir) = &args.svg {
        write_previews(dir, planned, &toolpaths, coverage.as_deref())?;
    }
    Ok(())
}

/// Into `dir`, per layer: `layer-NNNN.svg` (the EDO contours and offsets) and, for a
/// layer with toolpaths and coverage, `layer-NNNN-roads.svg` (roads at their widths,
/// travel, seams, voids).
fn write_previews(
    dir: &Path,
    planned: &Planned,
    toolpaths: &[crate::pipeline::LayerMoves],
    coverage: Option<&[LayerCoverage]>,
) -> Result<()> {
    let Planned {
        job,
        slices,
        layers,
        process,
        overhangs,
    } = *planned;
    let none = crate::geom::Shapes::new();
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    for (k, (layer, slice)) in layers.iter().zip(slices).enumerate() {
        let svg = crate::svg::layer_svg(
            layer,
            &crate::svg::PreviewInput {
                job_name: &job.name,
                materials: &job.materials,
                nozzle_mm: job.plan.nozzle_mm,
                islands: &slice.layer.islands,
                unsupported: overhangs.get(k).and_then(Option::as_ref).unwrap_or(&none),
            },
        );
        let file = dir.join(format!("layer-{:04}.svg", layer.index));
        std::fs::write(&file, svg).with_context(|| format!("cannot write {}", file.display()))?;
        let (Some(t), Some(c)) = (toolpaths.get(k), coverage.and_then(|c| c.get(k))) else {
            continue;
        };
        let roads = crate::svg::roads_svg(
            &t.paths,
            &crate::svg::RoadsInput {
                title: &format!(
                    "{} layer {}: roads, void {:.2} %, overlap {:.2} %",
                    job.name,
                    layer.index,
                    100.0 * c.with_raise.void_fraction(),
                    100.0 * c.with_raise.overlap_fraction()
                ),
                islands: &slice.layer.islands,
                road_width_mm: process.road_width(),
                voids: &c.voids,
                void_cell_mm: c.with_raise.cell_mm,
                mixer_limited: &t.stats.mixer_limited,
            },
        );
        let file = dir.join(format!("layer-{:04}-roads.svg", layer.index));
        std::fs::write(&file, roads).with_context(|| format!("cannot write {}", file.display()))?;
    }
    Ok(())
}

/// The summary's first lines: layers and planning time, the mesh, the first layer's
/// islands, road lengths and the plan's size.
fn write_plan_summary(
    human: &mut dyn Write,
    job: &Job,
    report: &crate::report::PlanReport,
    layers: &[LayerPlan],
    planning_time_ms: f64,
) -> Result<()> {
    let t = &report.totals;
    writeln!(
        human,
        "{}: {} layer(s) planned in {:.1} ms",
        job.name, t.layers, planning_time_ms
    )?;
    if let Some(m) = &report.mesh {
        writeln!(
            human,
            "  mesh: {} triangles, {:.1} mm³, {} open edges, {} non-manifold edges, {} degenerate and {} duplicate triangles removed",
            m.triangles, m.volume_mm3, m.open_edges, m.non_manifold_edges, m.degenerate_triangles, m.duplicate_triangles
        )?;
    }
    if let Some(l) = layers.first() {
        for r in &l.regions {
            writeln!(
                human,
                "  layer {} island {}: {:?} subdivision, m = {}, L_short = {:.3} mm, {} sub-regions, {} offsets",
                l.index,
                r.island,
                r.method,
                r.m,
                r.l_short_mm,
                r.sub_regions.len(),
                r.sub_regions.iter().map(|s| s.offsets.len()).sum::<usize>()
            )?;
        }
    }
    writeln!(
        human,
        "  roads: {:.1} mm of contours, {:.1} mm of equal distance offsets, {} paths",
        t.contour_length_mm, t.offset_length_mm, t.paths
    )?;
    writeln!(
        human,
        "  compact material data {} B, whole plan {} B, voxel grid at R_mach/4 {} B",
        t.compact_material_bytes, t.plan_bytes, t.voxel_grid_bytes
    )?;
    Ok(())
}

/// One line: the G-code file written, its moves and syringe volumes.
fn gcode_summary(
    flavor: crate::gcode_link::writer::Dialect,
    g: &crate::cli::gcode::GcodeSummary,
    path: &Path,
) -> String {
    let ul: Vec<String> = g
        .commanded_nl
        .iter()
        .map(|nl| format!("{:.1}", *nl as f64 / 1000.0))
        .collect();
    format!(
        "G-code ({:?}): {} moves, syringes [{}] µL -> {}",
        flavor,
        g.moves,
        ul.join(", "),
        path.display()
    )
}

/// One line: where the part goes on the machine, or why it does not fit.
fn placement_summary(p: &crate::report::PlacementReport) -> String {
    let [sx, sy, sz] = p.build_volume_mm;
    match (&p.problem, p.machine_min_mm, p.machine_max_mm) {
        (None, Some(lo), Some(hi)) => format!(
            "placement ({}): on the machine x {:.1} to {:.1}, y {:.1} to {:.1}, z {:.1} to {:.1} mm of the {sx} × {sy} × {sz} mm build volume",
            serde_json::to_value(p.mode)
                .ok()
                .map(|v| v.to_string())
                .unwrap_or_default(),
            lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]
        ),
        (Some(e), _, _) => format!(
            "placement: does not fit the {sx} × {sy} × {sz} mm build volume (--build-volume), edod would refuse it: {e}"
        ),
        _ => String::new(),
    }
}

/// The process settings `edoctl plan` makes toolpaths and G-code with.
pub fn process_settings(job: &Job) -> crate::pipeline::ProcessSettings {
    job.toolpath.clone()
}

/// Every layer's ordered paths and moves, continuing the stream state from layer to
/// layer (as edod streams them).
fn layer_toolpaths(
    job: &Job,
    layers: &[LayerPlan],
    process: &crate::pipeline::ProcessSettings,
) -> Result<Vec<crate::pipeline::LayerMoves>> {
    crate::pipeline::job_layer_moves(
        layers,
        process,
        0,
        0,
        &mut crate::pipeline::StreamState::new(),
    )
    .with_context(|| format!("job {}: turning layers into moves", job.name))
}

/// One layer's coverage, with and without the flow raise, and void cells to draw.
struct LayerCoverage {
    with_raise: crate::toolpath::coverage::Coverage,
    without_raise: crate::toolpath::coverage::Coverage,
    voids: Vec<glam::DVec2>,
}

/// Coverage of every layer at 10 µm, layers in parallel.
fn measure_coverage(
    toolpaths: &[crate::pipeline::LayerMoves],
    layers: &[LayerPlan],
    slices: &[LayerSlice],
    process: &crate::pipeline::ProcessSettings,
    with_voids: bool,
    quiet: bool,
) -> Vec<LayerCoverage> {
    use crate::toolpath::coverage::{measure, measure_with_voids};
    use rayon::prelude::*;
    let b = bar(toolpaths.len() as u64, "coverage", quiet);
    let road_width_mm = process.road_width();
    // The same plan without the flow raise: nominal widths on the unshifted centrelines.
    let mut plain = process.clone();
    plain.flow_raise = false;
    plain.gap_fill = false;
    // The part's roads only: support roads count in no coverage.
    plain.support = None;
    let out = toolpaths
        .par_iter()
        .zip(layers)
        .zip(slices)
        .map(|((t, layer), s)| {
            let islands = &s.layer.islands;
            let (with_raise, voids) = measure_with_voids(
                islands,
                part_roads(&t.paths),
                road_width_mm,
                COVERAGE_CELL_MM,
                if with_voids { 20_000 } else { 0 },
            );
            let nominal =
                crate::pipeline::layer_paths(layer, &plain, &crate::pipeline::StreamState::new());
            let without_raise = measure(islands, &nominal, road_width_mm, COVERAGE_CELL_MM);
            if let Some(b) = &b {
                b.inc(1);
            }
            LayerCoverage {
                with_raise,
                without_raise,
                voids,
            }
        })
        .collect();
    if let Some(b) = b {
        b.finish_and_clear();
    }
    out
}

/// The part's roads of a layer's paths (support roads come after them and count in
/// no coverage of the part).
fn part_roads(paths: &[crate::toolpath::ToolPath]) -> &[crate::toolpath::ToolPath] {
    let n = paths
        .iter()
        .position(|p| p.role.is_support())
        .unwrap_or(paths.len());
    &paths[..n]
}

/// Raster of the coverage measure (issue 4: 10 µm).
pub const COVERAGE_CELL_MM: f64 = 0.01;

fn toolpath_summary(t: &crate::report::ToolpathTotals) -> String {
    let ul: Vec<String> = t
        .syringe_volumes_ul
        .iter()
        .map(|v| format!("{v:.1}"))
        .collect();
    let mut line = format!(
        "toolpath: {} moves, {:.1} mm extruded, {:.1} mm travel, {} retracts, syringes [{}] µL",
        t.moves,
        t.extruded_mm,
        t.travel_mm,
        t.retracts,
        ul.join(", ")
    );
    line.push_str(&format!(
        "\n  nozzle exit against the design, worst road {:.4}; {} road(s) where the design changes faster than the mixer can",
        t.composition_error_road_max, t.mixer_limited_roads
    ));
    if let Some(c) = &t.coverage {
        line.push_str(&format!(
            "\n  coverage at {:.0} µm: void {:.2} % ({:.2} % without the flow raise), overlap {:.2} %, outside {:.2} %",
            c.cell_mm * 1000.0,
            100.0 * c.void_fraction,
            100.0 * c.void_fraction_without_raise,
            100.0 * c.overlap_fraction,
            100.0 * c.outside_fraction
        ));
    }
    line
}

fn write_report(report: &crate::report::PlanReport, target: &str) -> Result<()> {
    let json = serde_json::to_string_pretty(&report)?;
    if target == "-" {
        println!("{json}");
    } else {
        if let Some(parent) = Path::new(target)
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
        {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        std::fs::write(target, json + "\n")
            .with_context(|| format!("cannot write report {target}"))?;
    }
    Ok(())
}
