//! `edoctl demo` end to end against a hil-sim on a pty (started here, in this process, so
//! the test does not depend on the hil-sim binary): the bundled graded crown is printed
//! through edod, the machine executes exactly the planned moves, the built gradient
//! matches the design, and the side-by-side previews and summary are written — over
//! edo's own link, and streamed as G-code to the simulated Marlin and RepRapFirmware.

use std::process::Command;
use std::sync::OnceLock;

use edo::gcode_link::Dialect;
use serde_json::Value;

/// One demo run: its `--json` summary, and each layer's preview.
struct DemoRun {
    summary: Value,
    svgs: Vec<String>,
    summary_file: Value,
}

/// `edoctl --json demo` on a hil-sim started here (`firmware`: `hil-sim --gcode` and
/// `edoctl demo --firmware`; `None`: edo's link).
fn run_demo(firmware: Option<(&str, Dialect)>) -> DemoRun {
    run_demo_through(firmware, None)
}

/// [`run_demo`] through a mixing chamber of the demo's volume (`hil-sim --mixer` and
/// `edoctl demo --mixer`), with the feed-forward on or off.
fn run_demo_through(
    firmware: Option<(&str, Dialect)>,
    mixer: Option<(edo::mixer::MixerModel, bool)>,
) -> DemoRun {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("machine.jsonl");
    let sim = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.path().join("tty")),
        speed: 60.0,
        seed: 11,
        record: Some(record.clone()),
        dead_volume_nl: edo::cli::demo::DEMO_DEAD_VOLUME_NL,
        gcode: firmware.map(|(_, d)| hil_sim::GcodeOptions::new(d, 2)),
        mixer: mixer.map(|m| m.0).unwrap_or_default(),
        ..hil_sim::SimConfig::default()
    })
    .unwrap();
    let out_dir = dir.path().join("out");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_edoctl"));
    cmd.arg("--json")
        .arg("demo")
        .arg("--port")
        .arg(sim.path())
        .arg("--record")
        .arg(&record)
        .arg("--out")
        .arg(&out_dir);
    if let Some((name, _)) = firmware {
        cmd.args(["--firmware", name]);
    }
    if let Some((model, feed_forward)) = mixer {
        cmd.args(["--mixer", model.name()]);
        if !feed_forward {
            cmd.arg("--no-feed-forward");
        }
    }
    let out = cmd.output().unwrap();
    sim.stop().unwrap();
    assert!(
        out.status.success(),
        "demo {firmware:?} failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    let summary: Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let layers = summary["layers"].as_u64().unwrap_or(0);
    let svgs = (0..layers)
        .map(|k| std::fs::read_to_string(out_dir.join(format!("layer-{k:04}.svg"))).unwrap())
        .collect();
    let summary_file =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("summary.json")).unwrap())
            .unwrap();
    DemoRun {
        summary,
        svgs,
        summary_file,
    }
}

/// The demo over edo's link, run once for the tests that need it.
fn edo_demo() -> &'static DemoRun {
    static RUN: OnceLock<DemoRun> = OnceLock::new();
    RUN.get_or_init(|| run_demo(None))
}

/// Every layer drawn planned and as built, with one line per executed extrusion (a
/// layer has ~850 moves).
fn assert_previews(run: &DemoRun, what: &str) {
    assert_eq!(run.svgs.len(), 4, "{what}");
    for (k, svg) in run.svgs.iter().enumerate() {
        assert!(svg.contains("planned") && svg.contains("as built"));
        let lines = svg.matches("<line ").count();
        assert!(
            lines > 500,
            "{what} layer {k} as built is drawn: {lines} lines"
        );
    }
    assert_eq!(
        run.summary_file["moves_planned"],
        run.summary["moves_planned"]
    );
}

#[test]
fn demo_prints_the_crown_as_planned_and_writes_previews() {
    let run = edo_demo();
    let s = &run.summary;
    assert_eq!(s["state"], "done", "{s}");
    assert_eq!(s["executed_as_planned"], true, "{s}");
    assert_eq!(s["mismatch"], Value::Null);
    let planned = s["moves_planned"].as_u64().unwrap();
    assert_eq!(s["moves_executed"].as_u64(), Some(planned));
    assert!(planned > 2000, "{planned} moves");
    assert_eq!(s["layers"], 4);
    // Over edo's link the summary has no G-code fields.
    assert!(s.get("firmware").is_none() && s.get("gcode_lines_planned").is_none());
    // The built gradient follows the design (plug-flow chamber of 1 µL, mixing lead on).
    let built = s["composition_error_built"]["mean"].as_f64().unwrap();
    assert!(built < 0.03, "designed-vs-built composition error {built}");
    // Road by road the whole-nanolitre jitter of single moves averages out: what left
    // the nozzle over a road is what the planner predicted for it.
    let per_road = s["composition_error_built_per_road"]["mean"]
        .as_f64()
        .unwrap();
    let predicted = s["composition_error_predicted"]["mean"].as_f64().unwrap();
    assert!(per_road < built, "per road {per_road}, per move {built}");
    // Merged moves keep the lead's changes (split there): no worse than the 0.0018 of
    // one move per edge.
    assert!(per_road < 0.002, "per road {per_road}");
    assert!(
        (per_road - predicted).abs() < 0.002,
        "per road {per_road}, predicted {predicted}"
    );
    assert!(s["void_fraction"].as_f64().unwrap() < 0.01, "{s}");
    let ul: Vec<f64> = s["syringe_volumes_ul"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert!(ul.len() == 2 && ul.iter().all(|&v| v > 10.0), "{ul:?}");
    assert_previews(run, "edo");
}

/// `--firmware marlin` and `--firmware rrf` (at the same time, ~10 s each: the link
/// sends one line at a time): done, every planned motion line ran once and in order,
/// the road-by-road composition within 0.01 of edo's link (Marlin's `M163` mix is the
/// last 8 moves' composition, so it lags a road change; RRF's per-drive E is exact).
#[test]
fn demo_streams_the_crown_as_gcode_to_marlin_and_rrf() {
    let runs: Vec<(&str, DemoRun)> = std::thread::scope(|scope| {
        let started: Vec<_> = [("marlin", Dialect::Marlin), ("rrf", Dialect::Rrf)]
            .into_iter()
            .map(|f| (f.0, scope.spawn(move || run_demo(Some(f)))))
            .collect();
        // The edo link's figures, while these run.
        let _ = edo_demo();
        started
            .into_iter()
            .map(|(name, h)| (name, h.join().unwrap()))
            .collect()
    });
    let edo = &edo_demo().summary;
    let edo_per_road = edo["composition_error_built_per_road"]["mean"]
        .as_f64()
        .unwrap();
    for (name, run) in &runs {
        let s = &run.summary;
        assert_eq!(s["state"], "done", "{name}: {s}");
        assert_eq!(s["executed_as_planned"], true, "{name}: {s}");
        assert_eq!(s["mismatch"], Value::Null, "{name}");
        assert_eq!(s["moves_planned"], edo["moves_planned"], "{name}");
        assert_eq!(s["moves_executed"], s["moves_planned"], "{name}");
        let lines = s["gcode_lines_planned"].as_u64().unwrap();
        assert_eq!(s["gcode_lines_executed"].as_u64(), Some(lines), "{name}");
        assert!(lines > 2000, "{name}: {lines} motion lines");
        let want = if *name == "rrf" {
            "RepRapFirmware"
        } else {
            "Marlin"
        };
        assert_eq!(s["firmware"], want);
        assert_eq!(run.summary_file["firmware"], want);
        let per_road = s["composition_error_built_per_road"]["mean"]
            .as_f64()
            .unwrap();
        assert!(
            (per_road - edo_per_road).abs() < 0.01,
            "{name}: per road {per_road}, edo's link {edo_per_road}"
        );
        assert_eq!(s["syringe_volumes_ul"], edo["syringe_volumes_ul"], "{name}");
        eprintln!(
            "{name}: per road mean {per_road:.4} (edo {edo_per_road:.4}), {lines} lines, \
             printed in {:.1} s",
            s["print_time_s"].as_f64().unwrap_or(0.0)
        );
        assert_previews(run, name);
    }
}

/// `--mixer mixed` (a well-mixed chamber of 1 µL, the simulator building through the
/// same model): what left the nozzle road by road is what the planner predicted, and
/// the feed-forward builds the crown closer to its design than the lead alone
/// (docs/toolpath.md: 0.0243 against 0.0623 per road).
#[test]
fn demo_through_a_well_mixed_chamber_builds_what_the_feed_forward_predicts() {
    let run = run_demo_through(None, Some((edo::mixer::MixerModel::Mixed, true)));
    let s = &run.summary;
    assert_eq!(s["state"], "done", "{s}");
    assert_eq!(s["executed_as_planned"], true, "{s}");
    assert_eq!(s["mixer"]["model"], "mixed", "{s}");
    let built = s["composition_error_built_per_road"]["mean"]
        .as_f64()
        .unwrap();
    let (used, ff) = (&s["feed_forward"][0], &s["feed_forward"][1]);
    assert_eq!(used, true);
    let on = ff["on"]["mean"].as_f64().unwrap();
    let off = ff["off"]["mean"].as_f64().unwrap();
    assert!((built - on).abs() < 0.002, "built {built}, predicted {on}");
    assert!(on < 0.5 * off, "feed-forward on {on}, off {off}");
    let max = s["composition_error_built_per_road"]["max"]
        .as_f64()
        .unwrap();
    assert!(
        (max - ff["on"]["max"].as_f64().unwrap()).abs() < 0.005,
        "{s}"
    );
    assert_previews(&run, "mixed");
}
