//! Planner speed and geometry checks (benches/README.md quotes its figures):
//!
//! - `plan_compare bench N [OUT.json]`: plan the bench region (2,000 vertices, two
//!   holes, m = 20) N times, for `valgrind --tool=callgrind` (instructions per layer
//!   are the total over N less the total over 0, over N); OUT gets the plan.
//! - `plan_compare job JOB.toml EVERY OUT.json`: plan every EVERY-th layer of a job and
//!   write the plans (`EDO_CELL_DIV=k`: field cell R_mach / k, here and in `bench`).
//! - `plan_compare diff A.json B.json`: the largest distance between the contours' roads
//!   and between the equal distance offsets of two such files, both ways (a symmetric,
//!   sampled Hausdorff distance per contour and per offset).
//! - `plan_compare levels PLAN.json`: how far the contours C2..Cm of the distance
//!   method lie from the exact level sets `d = d_j` of the normalised distance, sampled
//!   every 0.02 mm along their roads: `|d(p) − d_j| · (dist(p, Ci) + dist(p, Ce))`, which
//!   is the distance to the level set where the wall's two sides face each other.

use edo::geom::Path as RoadPath;
use edo::geom::SegmentIndex;
use edo::plan::{plan_layers, plan_region, LayerPlan, PlanOptions, RegionPlan};
use glam::DVec2;
use std::path::Path;

#[path = "../benches/common/region.rs"]
mod region;
use region::{bench_design, bench_region};

fn bench(n: usize, out: Option<&str>) -> anyhow::Result<()> {
    let region = bench_region();
    let design = bench_design();
    let probe = plan_region(&region, 0, &design, &PlanOptions::new(1.0, 0.4))?;
    let mut opts = PlanOptions::new(probe.l_short_mm / 20.0, 0.4);
    if let Some(div) = std::env::var("EDO_CELL_DIV")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
    {
        opts.field_cell_mm = Some(opts.r_mach_mm / div);
    }
    let mut last = None;
    for _ in 0..n {
        last = Some(plan_region(&region, 0, &design, &opts)?);
    }
    if let (Some(path), Some(plan)) = (out, last) {
        let layer = LayerPlan {
            index: 0,
            z_mm: 0.0,
            thickness_mm: 0.0,
            area_mm2: plan.area_mm2,
            regions: vec![plan],
            islands: vec![region],
            support: Default::default(),
        };
        std::fs::write(path, serde_json::to_string(&vec![layer])?)?;
    }
    Ok(())
}

fn job(path: &str, every: usize, out: &str) -> anyhow::Result<()> {
    let job_path = Path::new(path);
    let mut job = edo::cli::plan::load_job(job_path)?;
    if let Some(div) = std::env::var("EDO_CELL_DIV")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
    {
        job.plan.field_cell_mm = Some(job.plan.r_mach_mm / div);
    }
    let (slices, _) = edo::cli::plan::job_layers(&job, job_path, None, true)?;
    let picked: Vec<_> = slices.into_iter().step_by(every.max(1)).collect();
    let started = std::time::Instant::now();
    let layers = plan_layers(&picked, &job.plan, None)?;
    eprintln!(
        "{path}: {} layers planned in {:.1} ms",
        layers.len(),
        started.elapsed().as_secs_f64() * 1e3
    );
    std::fs::write(out, serde_json::to_string(&layers)?)?;
    Ok(())
}

/// Points along the paths, at most `step` apart.
fn samples(paths: &[&edo::geom::Path], step: f64) -> Vec<DVec2> {
    let mut out = Vec::new();
    for p in paths {
        let n = p.points.len();
        let edges = if p.closed { n } else { n.saturating_sub(1) };
        out.extend(p.points.first().copied());
        for k in 0..edges {
            let (a, b) = (p.points[k], p.points[(k + 1) % n]);
            let pieces = ((a.distance(b) / step).ceil() as usize).max(1);
            out.extend((1..=pieces).map(|q| a.lerp(b, q as f64 / pieces as f64)));
        }
    }
    out
}

/// The segments of some paths, closed ones as loops and open ones as polylines.
fn path_index(ps: &[&edo::geom::Path]) -> SegmentIndex {
    let loops: Vec<&[DVec2]> = ps
        .iter()
        .filter(|p| p.closed)
        .map(|p| p.points.as_slice())
        .collect();
    let lines: Vec<&[DVec2]> = ps
        .iter()
        .filter(|p| !p.closed)
        .map(|p| p.points.as_slice())
        .collect();
    SegmentIndex::new(&loops, &lines)
}

/// Sampled symmetric Hausdorff distance between two sets of paths, and the length (mm,
/// both ways) of the samples farther than `tol` from the other set.
fn hausdorff(a: &[&edo::geom::Path], b: &[&edo::geom::Path], tol: f64) -> (f64, f64) {
    let (ia, ib) = (path_index(a), path_index(b));
    let step = 0.02;
    let one_way = |from: &[&edo::geom::Path], to: &SegmentIndex| {
        samples(from, step)
            .into_iter()
            .map(|p| to.distance(p))
            .fold((0.0, 0.0), |(m, far): (f64, f64), d| {
                (m.max(d), far + if d > tol { step } else { 0.0 })
            })
    };
    let (x, y) = (one_way(a, &ib), one_way(b, &ia));
    (x.0.max(y.0), x.1 + y.1)
}

/// Distances between matching roads of one kind (contours or offsets) of two plans.
#[derive(Default)]
struct Tally {
    /// Road pairs compared.
    compared: usize,
    /// Length of the first plan's roads, mm.
    total_mm: f64,
    /// Length of roads farther than the tolerance from the other plan's, both ways, mm.
    far_mm: f64,
    /// The largest distance, mm, and where.
    worst: (f64, String),
}

impl Tally {
    /// Compare `x` with `y`; `at` names them (printed with VERBOSE when over `tol`).
    fn compare(&mut self, x: &[RoadPath], y: &[RoadPath], tol: f64, at: impl Fn() -> String) {
        let (h, far) = hausdorff(
            &x.iter().collect::<Vec<_>>(),
            &y.iter().collect::<Vec<_>>(),
            tol,
        );
        self.far_mm += far;
        self.total_mm += x.iter().map(|p| p.length_mm()).sum::<f64>();
        if std::env::var("VERBOSE").is_ok() && h > tol {
            println!("  {}: {h:.4} mm, {far:.2} mm beyond", at());
        }
        self.compared += 1;
        if h > self.worst.0 {
            self.worst = (h, at());
        }
    }
}

fn diff(a: &str, b: &str) -> anyhow::Result<()> {
    let read = |p: &str| -> anyhow::Result<Vec<LayerPlan>> {
        Ok(serde_json::from_str(&std::fs::read_to_string(p)?)?)
    };
    let (la, lb) = (read(a)?, read(b)?);
    anyhow::ensure!(la.len() == lb.len(), "layer counts differ");
    let (mut contours, mut offsets) = (Tally::default(), Tally::default());
    let mut structure = 0;
    let tol = 0.01;
    for (x, y) in la.iter().zip(&lb) {
        anyhow::ensure!(x.regions.len() == y.regions.len(), "layer {}", x.index);
        for (rx, ry) in x.regions.iter().zip(&y.regions) {
            structure += diff_region(x.index, rx, ry, tol, &mut contours, &mut offsets);
        }
    }
    println!(
        "{} contours ({:.0} mm), {} offsets ({:.0} mm) compared; largest contour distance {:.5} mm ({}), largest offset distance {:.5} mm ({}); beyond {tol} mm (both ways): contours {:.2} mm, offsets {:.2} mm; {structure} structural differences",
        contours.compared, contours.total_mm, offsets.compared, offsets.total_mm, contours.worst.0, contours.worst.1, offsets.worst.0, offsets.worst.1, contours.far_mm, offsets.far_mm
    );
    Ok(())
}

/// Compare the contours and offsets of one region of two plans of layer `layer`; the
/// structural differences (m, sub-region or offset counts) found.
fn diff_region(
    layer: usize,
    rx: &RegionPlan,
    ry: &RegionPlan,
    tol: f64,
    contours: &mut Tally,
    offsets: &mut Tally,
) -> usize {
    if rx.m != ry.m || rx.sub_regions.len() != ry.sub_regions.len() {
        eprintln!(
            "layer {layer} island {}: m {} / {}, sub-regions {} / {}",
            rx.island,
            rx.m,
            ry.m,
            rx.sub_regions.len(),
            ry.sub_regions.len()
        );
        return 1;
    }
    for (cx, cy) in rx.contours.iter().zip(&ry.contours) {
        contours.compare(&cx.roads, &cy.roads, tol, || {
            format!("layer {layer} island {} C{}", rx.island, cx.j)
        });
    }
    let mut structure = 0;
    for (sx, sy) in rx.sub_regions.iter().zip(&ry.sub_regions) {
        if sx.n_max != sy.n_max || sx.offsets.len() != sy.offsets.len() {
            structure += 1;
            eprintln!(
                "layer {layer} island {} S{}: N_max {} / {}, offsets {} / {}, D_max {:.4} / {:.4}",
                rx.island,
                sx.n,
                sx.n_max,
                sy.n_max,
                sx.offsets.len(),
                sy.offsets.len(),
                sx.d_max_mm,
                sy.d_max_mm
            );
            continue;
        }
        for (i, (ox, oy)) in sx.offsets.iter().zip(&sy.offsets).enumerate() {
            offsets.compare(ox, oy, tol, || {
                format!(
                    "layer {layer} island {} S{} offset {}",
                    rx.island,
                    sx.n,
                    i + 1
                )
            });
        }
    }
    structure
}

/// How the equal distance offsets of two plans differ at their ends and away from them:
/// for every pair of offsets, the ends of open roads (each end's distance to the
/// nearest end of the other plan's roads), the road counts, and the sampled distance of
/// the roads farther than `r` mm from every end of either.
fn ends(a: &str, b: &str, r: f64) -> anyhow::Result<()> {
    let read = |p: &str| -> anyhow::Result<Vec<LayerPlan>> {
        Ok(serde_json::from_str(&std::fs::read_to_string(p)?)?)
    };
    let (la, lb) = (read(a)?, read(b)?);
    anyhow::ensure!(la.len() == lb.len(), "layer counts differ");
    let ends_of = |ps: &[edo::geom::Path]| -> Vec<DVec2> {
        ps.iter()
            .filter(|p| !p.closed)
            .flat_map(|p| p.points.first().into_iter().chain(p.points.last()).copied())
            .collect()
    };
    let (mut moved, mut worst_end, mut roads) = (Vec::new(), 0.0f64, (0, 0));
    let mut interior = (0.0f64, String::new());
    let verbose = std::env::var("VERBOSE").is_ok();
    let mut changed_counts = 0;
    for (x, y) in la.iter().zip(&lb) {
        for (rx, ry) in x.regions.iter().zip(&y.regions) {
            for (sx, sy) in rx.sub_regions.iter().zip(&ry.sub_regions) {
                for (i, (ox, oy)) in sx.offsets.iter().zip(&sy.offsets).enumerate() {
                    roads.0 += ox.len();
                    roads.1 += oy.len();
                    if ox.len() != oy.len() {
                        changed_counts += 1;
                    }
                    let (ex, ey) = (ends_of(ox), ends_of(oy));
                    let nearest = |p: DVec2, es: &[DVec2]| {
                        es.iter()
                            .map(|e| e.distance(p))
                            .fold(f64::INFINITY, f64::min)
                    };
                    let at = format!("layer {} S{} offset {}", x.index, sx.n, i + 1);
                    if ex.len() != ey.len() {
                        println!("  {at}: {} / {} open road ends", ex.len(), ey.len());
                    }
                    for &p in ex.iter() {
                        let d = nearest(p, &ey);
                        worst_end = worst_end.max(d);
                        if d > 0.01 {
                            moved.push((d, at.clone()));
                        }
                    }
                    let all_ends: Vec<DVec2> = ex.iter().chain(&ey).copied().collect();
                    let (rx, ry): (Vec<_>, Vec<_>) = (ox.iter().collect(), oy.iter().collect());
                    let (ix, iy) = (path_index(&rx), path_index(&ry));
                    let mut here = 0.0f64;
                    for (from, to) in [(&rx, &iy), (&ry, &ix)] {
                        for p in samples(from, 0.02) {
                            let d = to.distance(p);
                            if d > here && nearest(p, &all_ends) > r {
                                here = d;
                            }
                        }
                    }
                    if verbose && here > 0.002 {
                        println!("  {at}: {here:.5} mm away from the ends");
                    }
                    if here > interior.0 {
                        interior = (here, at);
                    }
                }
            }
        }
    }
    moved.sort_by(|p, q| q.0.total_cmp(&p.0));
    println!(
        "roads {} / {} ({} offsets with another count); ends moved beyond 0.01 mm: {} (largest {:.4} mm); largest distance farther than {r} mm from every end: {:.5} mm ({})",
        roads.0, roads.1, changed_counts, moved.len(), worst_end, interior.0, interior.1
    );
    for (d, at) in moved.iter().take(16) {
        println!("  {d:.4} mm  {at}");
    }
    Ok(())
}

fn levels(path: &str) -> anyhow::Result<()> {
    let layers: Vec<LayerPlan> = serde_json::from_str(&std::fs::read_to_string(path)?)?;
    let tol = edo::geom::Tolerances::default();
    let mut errors: Vec<f64> = Vec::new();
    let mut worst = (0.0f64, String::new());
    let verbose = std::env::var("VERBOSE").is_ok();
    for layer in &layers {
        for plan in &layer.regions {
            if plan.method != edo::plan::SubdivisionMethod::Distance {
                continue;
            }
            let Some(island) = layer.islands.get(plan.island) else {
                continue;
            };
            // The planner's own boundary: normalised and simplified by the chord.
            let region = island.normalised(&tol);
            let simple = |l: &Vec<DVec2>| edo::geom::simplify_loop(l, tol.chord_mm);
            let outer = simple(&region.outer);
            let holes: Vec<Vec<DVec2>> = region.holes.iter().map(simple).collect();
            let ie = SegmentIndex::new(&[outer.as_slice()], &[]);
            let hole_refs: Vec<&[DVec2]> = holes.iter().map(|h| h.as_slice()).collect();
            let ii = SegmentIndex::new(&hole_refs, &[]);
            for c in &plan.contours {
                if c.j == 1 || c.j == plan.m + 1 {
                    continue;
                }
                let roads: Vec<&edo::geom::Path> = c.roads.iter().collect();
                for p in samples(&roads, 0.02) {
                    let (a, e) = match plan.centre {
                        Some(centre) if holes.is_empty() => (p.distance(centre), ie.distance(p)),
                        _ => (ii.distance(p), ie.distance(p)),
                    };
                    let err = ((a / (a + e)) - c.d).abs() * (a + e);
                    if err > worst.0 {
                        worst = (
                            err,
                            format!(
                                "layer {} island {} C{} at ({:.3}, {:.3})",
                                layer.index, plan.island, c.j, p.x, p.y
                            ),
                        );
                    }
                    errors.push(err);
                    if verbose && err > 0.1 {
                        println!(
                            "  layer {} island {} C{} of m = {} at ({:.3}, {:.3}): {err:.3} mm, dist to Ci {a:.3}, to Ce {e:.3}",
                            layer.index, plan.island, c.j, plan.m, p.x, p.y
                        );
                    }
                }
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    let at = |q: f64| {
        errors
            .get(((errors.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    let mean = errors.iter().sum::<f64>() / errors.len().max(1) as f64;
    println!(
        "{} samples: mean {:.5} mm, median {:.5}, p99 {:.5}, p99.9 {:.5}, max {:.5} mm ({})",
        errors.len(),
        mean,
        at(0.5),
        at(0.99),
        at(0.999),
        worst.0,
        worst.1
    );
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |k: usize| args.get(k).map(String::as_str);
    match arg(0) {
        Some("bench") => bench(arg(1).and_then(|s| s.parse().ok()).unwrap_or(1), arg(2)),
        Some("job") => match (arg(1), arg(2).and_then(|s| s.parse().ok()), arg(3)) {
            (Some(p), Some(every), Some(out)) => job(p, every, out),
            _ => anyhow::bail!("usage: plan_compare job JOB.toml EVERY OUT.json"),
        },
        Some("diff") => match (arg(1), arg(2)) {
            (Some(a), Some(b)) => diff(a, b),
            _ => anyhow::bail!("usage: plan_compare diff A.json B.json"),
        },
        Some("ends") => match (arg(1), arg(2), arg(3).and_then(|s| s.parse().ok())) {
            (Some(a), Some(b), Some(r)) => ends(a, b, r),
            _ => anyhow::bail!("usage: plan_compare ends A.json B.json R_MM"),
        },
        Some("levels") => match arg(1) {
            Some(p) => levels(p),
            None => anyhow::bail!("usage: plan_compare levels PLAN.json"),
        },
        _ => anyhow::bail!("usage: plan_compare bench N [OUT.json] | job JOB.toml EVERY OUT.json | diff A.json B.json | levels PLAN.json"),
    }
}
