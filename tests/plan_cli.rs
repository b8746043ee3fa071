//! `edoctl plan` end to end: the bundled example jobs plan, their reports follow
//! docs/plan-report.md, previews are written, and bad jobs fail with a message that
//! names the key and a non-zero status (never a panic).

use std::path::{Path, PathBuf};
use std::process::Command;

fn edoctl() -> Command {
    Command::new(env!("CARGO_BIN_EXE_edoctl"))
}

fn example(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("config/examples")
        .join(name)
}

fn plan_json(job: &Path, svg: Option<&Path>) -> serde_json::Value {
    let mut cmd = edoctl();
    cmd.arg("plan").arg(job).args(["--report", "-"]);
    if let Some(dir) = svg {
        cmd.arg("--svg").arg(dir);
    }
    json_of(&mut cmd)
}

/// What `cmd` (an edoctl run) printed as JSON; it must succeed.
fn json_of(cmd: &mut Command) -> serde_json::Value {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn paper_annulus_report_matches_the_paper() {
    let dir = tempfile::tempdir().unwrap();
    let r = plan_json(&example("paper-annulus.toml"), Some(dir.path()));
    assert_eq!(r["schema"], "edo.plan-report/1");
    assert_eq!(r["job"], "paper-annulus");
    let layers = r["layers"].as_array().unwrap();
    assert_eq!(layers.len(), 2);
    let region = &layers[0]["regions"][0];
    assert_eq!(region["method"], "radial");
    assert_eq!(region["m"], 10);
    assert_eq!(region["contours"].as_array().unwrap().len(), 11);
    let c4 = &region["contours"][3];
    assert_eq!(c4["j"], 4);
    assert!((c4["composition"][0].as_f64().unwrap() - 0.7).abs() < 1e-12);
    let s45 = region["sub_regions"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["n"] == 4)
        .unwrap();
    assert_eq!(s45["n_max"], 4);
    let want = [0.625, 0.65, 0.675];
    let offsets = s45["offsets"].as_array().unwrap();
    assert_eq!(offsets.len(), 3);
    for (o, w) in offsets.iter().zip(want) {
        assert!((o["composition"][0].as_f64().unwrap() - w).abs() < 1e-12);
        assert!(o["length_mm"].as_f64().unwrap() > 100.0);
    }
    assert!((s45["w"][0].as_f64().unwrap() - 0.025).abs() < 1e-12);
    let t = &r["totals"];
    assert!(t["planning_time_ms"].is_null()); // planning time is top level, not in totals
    assert!(r["planning_time_ms"].as_f64().unwrap() >= 0.0);
    // Compact material data is far smaller than a voxel grid at R_mach / 4.
    let compact = t["compact_material_bytes"].as_u64().unwrap();
    let voxels = t["voxel_grid_bytes"].as_u64().unwrap();
    eprintln!(
        "paper annulus: compact material {compact} B, plan {} B, voxel grid {voxels} B",
        t["plan_bytes"]
    );
    assert!(compact * 100 < voxels, "{compact} vs {voxels}");
    // One SVG per layer, with a legend naming the materials.
    for k in 0..2 {
        let svg = std::fs::read_to_string(dir.path().join(format!("layer-{k:04}.svg"))).unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert!(svg.contains(">A</text>") && svg.contains(">B</text>"));
        assert!(svg.contains("id=\"contours\"") && svg.contains("id=\"offsets\""));
        // And the roads as the machine builds them: travel dashed, seams marked.
        let roads =
            std::fs::read_to_string(dir.path().join(format!("layer-{k:04}-roads.svg"))).unwrap();
        assert!(roads.contains("stroke-dasharray") && roads.contains("<circle"));
    }
    // The toolpath and its coverage (measured because of --svg) are in the report.
    let tp = &layers[0]["toolpath"];
    assert!(tp["moves"].as_u64().unwrap() > 1000, "{tp}");
    let cov = &r["toolpath"]["coverage"];
    let void = cov["void_fraction"].as_f64().unwrap();
    assert!(void < 0.005, "void {void}");
    assert!(cov["void_fraction_without_raise"].as_f64().unwrap() < 0.005);
    assert!(cov["outside_fraction"].as_f64().unwrap() < 0.005, "{cov}");
    let ul = r["toolpath"]["syringe_volumes_ul"].as_array().unwrap();
    assert_eq!(ul.len(), 2);
    // Centred on the default 200 x 200 x 150 mm build volume.
    let p = &r["placement"];
    assert_eq!(p["mode"], "centre");
    assert_eq!(p["offset_mm"], serde_json::json!([100.0, 100.0, 0.0]));
    assert!(p["problem"].is_null(), "{p}");
    let lo = p["machine_min_mm"][0].as_f64().unwrap();
    assert!((lo - 70.0).abs() < 0.05, "{p}");
}

/// `--build-volume`: a value that is not three positive sides is refused; a part that
/// does not fit is planned and reported as edod would refuse it, and no G-code is
/// written for it.
#[test]
fn build_volume_is_checked_and_reported() {
    let job = example("paper-annulus.toml");
    for bad in ["5,5", "0,200,150", "200,x,150", "200,200,nan"] {
        let out = edoctl()
            .arg("plan")
            .arg(&job)
            .args(["--build-volume", bad, "--quiet"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: {err}");
        assert!(err.contains("--build-volume"), "{bad}: {err}");
    }
    let out = edoctl()
        .arg("plan")
        .arg(&job)
        .args(["--build-volume", "50,50,50", "--report", "-", "--quiet"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let problem = r["placement"]["problem"].as_str().unwrap_or_default();
    assert!(problem.contains("10.0 mm too wide along x"), "{problem}");
    assert!(r["placement"]["offset_mm"].is_null());
    let dir = tempfile::tempdir().unwrap();
    let gcode = dir.path().join("out.gcode");
    let out = edoctl()
        .arg("plan")
        .arg(&job)
        .args(["--build-volume", "50,50,50", "--quiet", "--gcode"])
        .arg(&gcode)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("too wide along x"),
        "{err}"
    );
    assert!(!gcode.exists());
}

#[test]
fn every_example_plans() {
    for (name, method) in [
        ("tooth-crown.toml", "offset"),
        ("fibers.toml", "parallel"),
        ("non-star.toml", "distance"),
    ] {
        let r = plan_json(&example(name), None);
        let region = &r["layers"][0]["regions"][0];
        assert_eq!(region["method"], method, "{name}");
        assert!(r["totals"]["offsets"].as_u64().unwrap() > 0, "{name}");
    }
}

fn plan_error(job_text: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("job.toml");
    std::fs::write(&path, job_text).unwrap();
    let out = edoctl().arg("plan").arg(&path).output().unwrap();
    assert!(!out.status.success(), "bad job accepted:\n{job_text}");
    assert_eq!(
        out.status.code(),
        Some(1),
        "exit status (a panic exits 101)"
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn bad_jobs_fail_with_named_errors() {
    let good = std::fs::read_to_string(example("paper-annulus.toml")).unwrap();
    let cases = [
        ("inner = [1.0, 0.0]", "inner = [0.6, 0.6]", "gradient.inner"),
        (
            "inner = [1.0, 0.0]",
            "inner = [1.0, 0.0, 0.0]",
            "gradient.inner",
        ),
        ("outer = [0.0, 1.0]", "outer = [nan, 1.0]", "gradient.outer"),
        ("r_mach = 2.0", "r_mach = 0.0", "process.r_mach"),
        ("nozzle = 0.5", "nozzle = -0.5", "process.nozzle"),
        ("radius = 10.0", "radius = 35.0", "geometry.polygon"),
        (
            "pattern = \"growth-rings\"",
            "pattern = \"spiral\"",
            "gradient.pattern",
        ),
        (
            "function = \"linear\"",
            "function = { table = [[0.0, 0.0], [0.5, 0.9], [0.4, 1.0], [1.0, 1.0]] }",
            "gradient.function",
        ),
        ("[process]", "[process]\nspeed = 3", "speed"),
        (
            "[process]",
            "[process]\noffset_end_clearance = 0.8",
            "process.offset_end_clearance",
        ),
        (
            "[process]",
            "[process]\nmin_road = -0.1",
            "process.min_road",
        ),
        ("[process]", "[process]\nmin_road = 0.9", "process.min_road"),
        ("[process]", "[process]\nmin_road = nan", "process.min_road"),
        (
            "[process]",
            "[process]\ncontour_deviation = 0.001",
            "process.contour_deviation",
        ),
        (
            "[process]",
            "[process]\ncontour_deviation = 0.5",
            "process.contour_deviation",
        ),
        (
            "[process]",
            "[process]\ncontour_deviation = inf",
            "process.contour_deviation",
        ),
        (
            "[process]",
            "[process]\ncontour_deviation = nan",
            "process.contour_deviation",
        ),
        (
            "[process]",
            "[process]\ncontour_deviation = -0.02",
            "process.contour_deviation",
        ),
        (
            "[process]",
            "[process]\ncontour_deviation = \"fine\"",
            "contour_deviation",
        ),
        (
            "[process]",
            "[toolpath]\npurge_pad_mm = -1.0\n[process]",
            "toolpath.purge_pad_mm",
        ),
        ("[process]", "[toolpath]\nfeed = 3\n[process]", "feed"),
        (
            "[process]",
            "[toolpath]\npurge_xy_mm = [nan, 0.0]\n[process]",
            "toolpath.purge_xy_mm",
        ),
        (
            "[process]",
            "[toolpath]\nv_dead_ul = -2.0\n[process]",
            "toolpath.v_dead_ul",
        ),
        (
            "[process]",
            "[toolpath]\nnozzle_mm = 0.3\n[process]",
            "toolpath.nozzle_mm",
        ),
        ("r_mach = 2.0", "r_mach = 50.0", "too thin"),
    ];
    for (from, to, want) in cases {
        assert!(good.contains(from), "{from}");
        let e = plan_error(&good.replace(from, to));
        assert!(e.contains(want), "{to}: {e}");
    }
    // A self-intersecting outline and a degenerate one.
    let bow = good.replace(
        "polygon = { outer = { circle = { center = [0.0, 0.0], radius = 30.0 } }, holes = [{ circle = { center = [0.0, 0.0], radius = 10.0 } }] }",
        "polygon = { outer = [[0.0, 0.0], [20.0, 20.0], [20.0, 0.0], [0.0, 20.0]] }",
    );
    assert!(plan_error(&bow).contains("crosses"));
    let flat = good.replace(
        "polygon = { outer = { circle = { center = [0.0, 0.0], radius = 30.0 } }, holes = [{ circle = { center = [0.0, 0.0], radius = 10.0 } }] }",
        "polygon = { outer = [[0.0, 0.0], [20.0, 0.0], [40.0, 0.0]] }",
    );
    assert!(plan_error(&flat).contains("no area"));
    // Not TOML at all, and a missing file.
    assert!(plan_error("\u{0}\u{1}garbage = [").contains("line"));
    let out = edoctl()
        .args(["plan", "/nonexistent/job.toml"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/job.toml"));
}

#[test]
fn radial_on_a_non_star_region_is_refused_with_advice() {
    let text = std::fs::read_to_string(example("non-star.toml"))
        .unwrap()
        .replace("subdivision = \"auto\"", "subdivision = \"radial\"");
    let e = plan_error(&text);
    assert!(e.contains("radial") && e.contains("distance"), "{e}");
}

/// A job's `[toolpath]` table reaches the toolpath: with a mixing chamber and a purge
/// position, the second layer (which starts at M(Ci) after a layer that ended at M(Ce))
/// begins with a purge of V_dead, reported per layer.
#[test]
fn toolpath_table_sets_the_purge() {
    let good = std::fs::read_to_string(example("paper-annulus.toml")).unwrap();
    let text = good.replace(
        "[process]",
        "[toolpath]\nv_dead_ul = 2.0\npurge_xy_mm = [5.0, 5.0]\n\n[process]",
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("job.toml");
    std::fs::write(&path, text).unwrap();
    let r = plan_json(&path, None);
    let layers = r["layers"].as_array().unwrap();
    let purge = |k: usize| layers[k]["toolpath"]["purge_ul"].as_f64().unwrap();
    assert_eq!(purge(0), 0.0);
    assert!((purge(1) - 2.0).abs() < 1e-3, "{}", purge(1));
    let err = layers[1]["toolpath"]["composition_error_max"]
        .as_f64()
        .unwrap();
    assert!(err < 0.1, "{err}");
}

/// `--mixer`: a bad model, volume or Peclet number is refused naming the option; a
/// well-mixed chamber's mixer-limited roads are reported per layer and ringed in the
/// roads preview.
#[test]
fn the_mixer_option_is_checked_and_its_limits_reported() {
    let job = example("tooth-crown.toml");
    for (args, option) in [
        (&["--mixer", "turbulent"][..], "--mixer:"),
        (&["--mixer", "dispersion"], "--mixer-peclet"),
        (
            &["--mixer", "dispersion", "--mixer-peclet", "0"],
            "--mixer-peclet",
        ),
        (
            &["--mixer", "mixed", "--mixer-volume-nl=-1"],
            "--mixer-volume-nl",
        ),
    ] {
        let out = edoctl().arg("plan").arg(&job).args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(option),
            "{args:?}: {err}"
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let report = json_of(
        edoctl()
            .arg("plan")
            .arg(&job)
            .args(["--layers", "0", "--report", "-", "--mixer", "mixed"])
            .args(["--mixer-volume-nl", "1000", "--svg"])
            .arg(dir.path()),
    );
    let t = &report["layers"][0]["toolpath"];
    let limited = t["mixer_limited"].as_array().unwrap();
    assert!(!limited.is_empty(), "{t}");
    assert_eq!(
        t["mixer_limited_roads"].as_u64(),
        Some(limited.len() as u64)
    );
    assert!(limited[0]["error"].as_f64().unwrap() > 0.01);
    assert!(limited[0]["at_mm"].as_array().unwrap().len() == 2);
    assert!(t["composition_error_road_max"].as_f64().unwrap() < 0.2);
    let svg = std::fs::read_to_string(dir.path().join("layer-0000-roads.svg")).unwrap();
    assert_eq!(svg.matches("mixer-limited road").count(), limited.len());
}

/// `edoctl mixer fit`: a step-response record taken from hil-sim's machine model (a
/// dispersing chamber of 1200 nl, Pe 15: dentin then enamel pushed in moves of 12 nl,
/// the recorded exit fraction with seeded noise of ± 0.02) gives back the chamber within
/// 5 %, as a `[machine.mixer]` table edod accepts; a bad record names its line.
#[test]
fn mixer_fit_recovers_a_simulated_chamber() {
    use edo::machine::{Move, MoveKind, PositionUm};
    let truth = edo::mixer::MixerOptions::new("dispersion", 1200.0, Some(15.0)).unwrap();
    let mut machine = hil_sim::model::MachineModel::new(2, u32::MAX, 1, &truth);
    let mut seed = 99u64;
    let mut text = String::from("# pushed_nl enamel_fraction\n");
    for k in 0..400u32 {
        let mv = Move {
            job_id: 1,
            index: k,
            kind: MoveKind::Extrude {
                to: PositionUm::default(),
                feed_um_s: 10_000,
                volumes_nl: vec![0, 12],
                width_factor_ppt: 1000,
            },
        };
        let exit = machine.execute(&mv).unwrap().exit_composition.unwrap();
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let noise = 0.04 * ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
        text.push_str(&format!(
            "{} {:.5}\n",
            12.0 * (f64::from(k) + 0.5),
            exit[1] + noise
        ));
    }
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("step.txt");
    std::fs::write(&record, &text).unwrap();
    let out = edoctl()
        .args(["--json", "mixer", "fit"])
        .arg(&record)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let fit: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(fit["model"], "dispersion", "{fit}");
    let v = fit["volume_nl"].as_f64().unwrap();
    let pe = fit["peclet"].as_f64().unwrap();
    assert!((v / 1200.0 - 1.0).abs() < 0.05, "{fit}");
    assert!((pe / 15.0 - 1.0).abs() < 0.05, "{fit}");
    // The table pastes into edod.toml.
    let out = edoctl()
        .args(["mixer", "fit"])
        .arg(&record)
        .output()
        .unwrap();
    let table = String::from_utf8_lossy(&out.stdout);
    let cfg = edo::daemon::Config::from_toml(&table, "pasted").unwrap();
    assert_eq!(cfg.machine.mixer().unwrap().model.name(), "dispersion");
    std::fs::write(&record, "0 0\n12 0.1\n24 much\n").unwrap();
    let out = edoctl()
        .args(["mixer", "fit"])
        .arg(&record)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("line 3"), "{err}");
}

/// edod, killed on drop.
struct Edod(std::process::Child);

impl Drop for Edod {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// One HTTP/1.1 request to `127.0.0.1:port` (the connection closed after it): the
/// status line's code and the body.
fn http(port: u16, method: &str, path: &str, body: &str) -> (u16, String) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(std::time::Duration::from_secs(60)))
        .unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let code = out
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = out
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (code, body)
}

/// The dashboard's preview (edod's planner) and `edoctl plan --machine` (the CLI's) plan
/// the crown alike on a G-code machine with a mixing chamber: the same layers, the same
/// moves in each (the preview's first layer also holds the job's home move, which the
/// file writes before its first layer), the same total.
#[test]
fn the_dashboard_preview_and_plan_machine_agree() {
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let config = dir.path().join("edod.toml");
    std::fs::write(
        &config,
        format!(
            "[serial]\nport = {:?}\n\
             [machine]\nprotocol = \"gcode\"\n[machine.mixer]\nmodel = \"mixed\"\nvolume_nl = 4000\n\
             [machine.gcode]\nfirmware = \"marlin\"\n\
             [api]\nsocket = {:?}\n[state]\ndir = {:?}\n\
             [http]\nlisten = \"127.0.0.1:{port}\"\n",
            dir.path().join("no-machine").display().to_string(),
            dir.path().join("edod.sock").display().to_string(),
            dir.path().join("state").display().to_string(),
        ),
    )
    .unwrap();
    let _edod = Edod(
        Command::new(env!("CARGO_BIN_EXE_edod"))
            .arg("--config")
            .arg(&config)
            .env("RUST_LOG", "warn")
            .stdin(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    let t = std::time::Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t.elapsed().as_secs() < 20, "edod's dashboard did not start");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let job = std::fs::read_to_string(example("tooth-crown.toml")).unwrap();
    let (code, body) = http(
        port,
        "POST",
        "/api/preview",
        &serde_json::json!({ "job": job }).to_string(),
    );
    assert_eq!(code, 200, "{body}");
    let preview: serde_json::Value = serde_json::from_str(&body).unwrap();
    let report = json_of(
        edoctl()
            .arg("plan")
            .arg(example("tooth-crown.toml"))
            .arg("--machine")
            .arg(&config)
            .args(["--report", "-"]),
    );
    let cli: Vec<u64> = report["layers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["toolpath"]["moves"].as_u64().unwrap())
        .collect();
    let shown: Vec<u64> = preview["layers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["moves"].as_u64().unwrap())
        .collect();
    let mut expected = cli.clone();
    expected[0] += 1; // the home move
    assert_eq!(shown, expected, "moves per layer: preview against the CLI");
    assert_eq!(
        preview["total_moves"].as_u64(),
        Some(cli.iter().sum::<u64>() + 1)
    );
    // Without --machine the CLI plans with the job's own settings: not what edod plans.
    let own = plan_json(&example("tooth-crown.toml"), None);
    let own: Vec<u64> = own["layers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["toolpath"]["moves"].as_u64().unwrap_or(0))
        .collect();
    assert_ne!(own, cli, "the machine's mixing chamber changes the plan");
}

/// `--machine` with what a user can get wrong: a file that is not there, a config edod
/// refuses, a machine on edo's own link asked for G-code, a job of more materials than
/// the machine has syringes, and an option that --machine gives a value to. Each fails
/// naming the file or the key, and writes no file.
#[test]
fn plan_machine_refuses_what_is_wrong_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let gcode = dir.path().join("out.gcode");
    let crown = example("tooth-crown.toml");
    let write = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let bad_key = write("bad.toml", "[machine]\nmax_flow_factor = -1.0\n");
    let edo_link = write("edo.toml", "");
    let three = write(
        "three.toml",
        "[machine]\nprotocol = \"gcode\"\nsyringes = [\
         { name = \"a\", barrel_diameter_mm = 10.0, capacity_ml = 10.0 }, \
         { name = \"b\", barrel_diameter_mm = 10.0, capacity_ml = 10.0 }, \
         { name = \"c\", barrel_diameter_mm = 10.0, capacity_ml = 10.0 }]\n\
         [machine.gcode]\nfirmware = \"marlin\"\n",
    );
    let missing = dir.path().join("missing.toml");
    for (machine, extra, says) in [
        (&missing, None, "cannot read"),
        (&bad_key, None, "machine.max_flow_factor"),
        (&edo_link, None, "machine.protocol is \"edo\""),
        (&three, None, "the machine has 3 syringes"),
        (&edo_link, Some("--flavor=klipper"), "cannot be used with"),
    ] {
        let mut cmd = edoctl();
        cmd.arg("plan").arg(&crown).arg("--machine").arg(machine);
        cmd.arg("--quiet").arg("--gcode").arg(&gcode);
        cmd.args(extra);
        let out = cmd.output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{says}: succeeded");
        assert!(err.contains(says), "{says}: {err}");
        assert!(!gcode.exists(), "{says}: a file was written");
    }
}

/// A sphere resting on the bed: its lower half leans out past the allowed overhang
/// (30 degrees from vertical by default), its upper half never does. `edoctl plan`
/// warns naming the layers, the report gives each layer's area resting on nothing and
/// the previews fill it red; a wider allowance (`[process] overhang`) finds none. The
/// prism examples rest on the layer below everywhere.
#[test]
fn overhangs_are_found_reported_drawn_and_warned() {
    let dir = tempfile::tempdir().unwrap();
    let stl = edo::mesh::primitives::sphere(5.0, 64, 32)
        .to_binary_stl()
        .unwrap();
    std::fs::write(dir.path().join("ball.stl"), stl).unwrap();
    let job = |overhang: &str| {
        format!(
            "name = \"ball\"\n[geometry]\nmesh = \"ball.stl\"\n[materials]\nnames = [\"A\", \"B\"]\n\
             [gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n[process]\nr_mach = 2.0\n\
             nozzle = 0.4\nlayer = 0.2\nthin_regions = \"fill\"\n{overhang}"
        )
    };
    let path = dir.path().join("ball.toml");
    std::fs::write(&path, job("")).unwrap();
    let svg = dir.path().join("svg");
    let out = edoctl()
        .arg("plan")
        .arg(&path)
        .args(["--report", "-", "--svg"])
        .arg(&svg)
        .output()
        .unwrap();
    let warned = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{warned}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let o = &r["overhang"];
    assert_eq!(o["allowed"], serde_json::json!({"angle_deg": 30.0}));
    let hanging: Vec<u64> = o["layers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l.as_u64().unwrap())
        .collect();
    assert!(hanging.len() >= 3, "{o}");
    let layers = r["layers"].as_array().unwrap();
    for l in layers {
        let (index, z) = (l["index"].as_u64().unwrap(), l["z_mm"].as_f64().unwrap());
        let a = l["unsupported_area_mm2"].as_f64().unwrap();
        assert_eq!(hanging.contains(&index), a > 0.01, "layer {index}: {a}");
        if z > 5.0 {
            assert_eq!(a, 0.0, "layer {index} at z {z} of the upper half hangs");
        }
    }
    let worst = o["worst_layer"].as_u64().unwrap();
    assert!(
        warned.contains("warning:")
            && warned.contains(&format!(
                "{} layers have area resting on nothing",
                hanging.len()
            ))
            && warned.contains(&format!("at layer {worst}")),
        "{warned}"
    );
    let drawn = |k: u64| std::fs::read_to_string(svg.join(format!("layer-{k:04}.svg"))).unwrap();
    assert!(drawn(worst).contains(r#"<g id="unsupported""#));
    assert!(!drawn(layers.len() as u64 - 5).contains("unsupported"));
    // Allowed to lean 80 degrees: nothing hangs, nothing is said.
    std::fs::write(&path, job("overhang = { angle_deg = 80.0 }\n")).unwrap();
    let out = edoctl()
        .arg("plan")
        .arg(&path)
        .args(["--report", "-"])
        .output()
        .unwrap();
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["overhang"]["layers"], serde_json::json!([]));
    assert!(!String::from_utf8_lossy(&out.stderr).contains("warning"));
    // A job that requires support is refused, naming the key and the layers.
    std::fs::write(&path, job("[support]\nrequired = true\n")).unwrap();
    let out = edoctl().arg("plan").arg(&path).output().unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        said.contains("support.required") && said.contains(&format!("at layer {worst}")),
        "{said}"
    );
    // Out of range, or neither form: refused naming the key.
    for bad in [
        "overhang = { angle_deg = 95.0 }",
        "overhang = { distance_mm = 20.0 }",
        "overhang = { degrees = 30.0 }",
    ] {
        std::fs::write(&path, job(&format!("{bad}\n"))).unwrap();
        let e = plan_error_of(&path);
        assert!(e.contains("overhang"), "{bad}: {e}");
    }
    for name in [
        "tooth-crown.toml",
        "fibers.toml",
        "non-star.toml",
        "paper-annulus.toml",
    ] {
        let r = plan_json(&example(name), None);
        assert_eq!(r["overhang"]["layers"], serde_json::json!([]), "{name}");
    }
}

/// `[geometry] orientation = "auto"` on an L-bracket lying on its side puts its largest
/// face (the long leg's outer side, 40 x 20 mm) on the bed and says why, with the
/// runner-up; `{ rotate = [..] }` turns it as asked; a polygon job is built as drawn.
#[test]
fn auto_orientation_puts_an_l_brackets_largest_face_down() {
    let dir = tempfile::tempdir().unwrap();
    let stl = edo::mesh::primitives::l_bracket(40.0, 30.0, 5.0, 20.0)
        .to_binary_stl()
        .unwrap();
    std::fs::write(dir.path().join("bracket.stl"), stl).unwrap();
    let job = |orientation: &str| {
        format!(
            "name = \"bracket\"\n[geometry]\nmesh = \"bracket.stl\"\n{orientation}\n[materials]\n\
             names = [\"A\", \"B\"]\n[gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n\
             [process]\nr_mach = 1.0\nnozzle = 0.6\nlayer = 0.5\nthin_regions = \"fill\"\n"
        )
    };
    let path = dir.path().join("bracket.toml");
    std::fs::write(&path, job("orientation = \"auto\"")).unwrap();
    let out = edoctl()
        .arg("plan")
        .arg(&path)
        .args(["--report", "-"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{said}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let o = &r["orientation"];
    assert_eq!(o["mode"], "auto");
    let down: Vec<f64> = serde_json::from_value(o["chosen"]["down"].clone()).unwrap();
    assert!(down[1] < -0.999, "{o}");
    assert!(
        (o["chosen"]["bed_contact_mm2"].as_f64().unwrap() - 800.0).abs() < 1e-6,
        "{o}"
    );
    assert!(
        o["runner_up"]["bed_contact_mm2"].as_f64().unwrap() < 800.0,
        "{o}"
    );
    assert!(
        said.contains("orientation auto: rotate = [") && said.contains("runner-up"),
        "{said}"
    );
    // 30 mm tall so turned: 60 layers of 0.5 mm; its first layer the 40 x 20 mm face.
    let layers = r["layers"].as_array().unwrap();
    assert_eq!(layers.len(), 60);
    assert!(
        (layers[0]["area_mm2"].as_f64().unwrap() - 800.0).abs() < 1.0,
        "{}",
        layers[0]
    );
    // Turned as asked: the same way up by its angles.
    let [x, y, z]: [f64; 3] = serde_json::from_value(o["chosen"]["rotate_deg"].clone()).unwrap();
    std::fs::write(
        &path,
        job(&format!("orientation = {{ rotate = [{x}, {y}, {z}] }}")),
    )
    .unwrap();
    let turned = plan_json(&path, None);
    assert_eq!(turned["orientation"]["mode"], "rotate");
    assert_eq!(turned["layers"].as_array().unwrap().len(), 60);
    // Kept: 20 mm tall, the L on the bed.
    std::fs::write(&path, job("")).unwrap();
    let kept = plan_json(&path, None);
    assert_eq!(kept["orientation"]["mode"], "keep");
    assert_eq!(kept["layers"].as_array().unwrap().len(), 40);
    // Bad values and a polygon job refused, naming the key.
    std::fs::write(&path, job("orientation = \"upside\"")).unwrap();
    let e = plan_error_of(&path);
    assert!(e.contains("geometry.orientation"), "{e}");
    std::fs::write(&path, job("orientation = { rotate = [1e9, 0.0, 0.0] }")).unwrap();
    let e = plan_error_of(&path);
    assert!(
        e.contains("geometry.orientation") && e.contains("-360 to 360"),
        "{e}"
    );
    // Neither form: the TOML error shows the line (serde's untagged enums name no key).
    std::fs::write(&path, job("orientation = { rotate = [90.0] }")).unwrap();
    let e = plan_error_of(&path);
    assert!(e.contains("line 4") && e.contains("orientation = {"), "{e}");
    let polygon = std::fs::read_to_string(example("paper-annulus.toml"))
        .unwrap()
        .replace("[geometry]\n", "[geometry]\norientation = \"auto\"\n");
    std::fs::write(&path, polygon).unwrap();
    let e = plan_error_of(&path);
    assert!(
        e.contains("geometry.orientation") && e.contains("polygon"),
        "{e}"
    );
}

fn plan_error_of(path: &Path) -> String {
    let out = edoctl().arg("plan").arg(path).output().unwrap();
    assert!(!out.status.success());
    String::from_utf8_lossy(&out.stderr).into_owned()
}
