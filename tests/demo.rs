//! `edoctl demo` end to end against a hil-sim on a pty (started here, in this process, so
//! the test does not depend on the hil-sim binary): the bundled graded crown is printed
//! through edod, the machine executes exactly the planned moves, the built gradient
//! matches the design, and the side-by-side previews and summary are written.

use std::process::Command;

use serde_json::Value;

#[test]
fn demo_prints_the_crown_as_planned_and_writes_previews() {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("machine.jsonl");
    let sim = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.path().join("tty")),
        speed: 60.0,
        seed: 11,
        record: Some(record.clone()),
        dead_volume_nl: edo::cli::demo::DEMO_DEAD_VOLUME_NL,
        ..hil_sim::SimConfig::default()
    })
    .unwrap();
    let out_dir = dir.path().join("out");
    let out = Command::new(env!("CARGO_BIN_EXE_edoctl"))
        .arg("--json")
        .arg("demo")
        .arg("--port")
        .arg(sim.path())
        .arg("--record")
        .arg(&record)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    sim.stop().unwrap();
    assert!(
        out.status.success(),
        "demo failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    let s: Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    assert_eq!(s["state"], "done", "{s}");
    assert_eq!(s["executed_as_planned"], true, "{s}");
    assert_eq!(s["mismatch"], Value::Null);
    let planned = s["moves_planned"].as_u64().unwrap();
    assert_eq!(s["moves_executed"].as_u64(), Some(planned));
    assert!(planned > 2000, "{planned} moves");
    assert_eq!(s["layers"], 4);
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
    for k in 0..4 {
        let svg = std::fs::read_to_string(out_dir.join(format!("layer-{k:04}.svg"))).unwrap();
        assert!(svg.contains("planned") && svg.contains("as built"));
        // One line per executed extrusion: the layer's ~850 moves.
        let lines = svg.matches("<line ").count();
        assert!(lines > 500, "layer {k} as built is drawn: {lines} lines");
    }
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["moves_planned"], s["moves_planned"]);
}
