//! `edoctl link-test` (its library function) against hil-sim on a real pty, with faults.

use std::time::Duration;

use edo::cli::linktest::{run, LinkTestConfig};
use hil_sim::{Faults, SimConfig};

#[test]
fn link_test_against_hil_sim_with_faults_loses_nothing() {
    let faults = match Faults::parse("corrupt=1e-4,drop=0.01,dup=0.001") {
        Ok(f) => f,
        Err(e) => panic!("{e}"),
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let record = dir.path().join("record.jsonl");
    let sim = hil_sim::spawn(SimConfig {
        link: Some(dir.path().join("ttyEDO")),
        baud: 250_000,
        speed: 100.0,
        seed: 11,
        faults,
        record: Some(record.clone()),
        ..SimConfig::default()
    })
    .expect("start hil-sim");
    let report = run(&LinkTestConfig {
        port: sim.path().to_path_buf(),
        moves: 2_000,
        baud: 250_000,
        stall_timeout: Duration::from_secs(20),
    })
    .expect("link test");
    let summary = sim.stop().expect("stop hil-sim");
    eprintln!("{report}\n{summary:?}");
    assert_eq!(report.aborted, None);
    assert_eq!(report.sent, 2_000);
    assert_eq!(report.executed, 2_000);
    assert_eq!(
        (report.lost, report.duplicated, report.reordered),
        (0, 0, 0)
    );
    assert!(
        summary.frames_dropped + summary.bits_flipped > 0,
        "faults were injected"
    );
    // The recorder saw every move once, and the symlink is gone.
    let lines = std::fs::read_to_string(&record).expect("record");
    assert_eq!(lines.lines().count(), 2_000);
    let svgs = hil_sim::record::render(&record, &dir.path().join("svg")).expect("render");
    assert_eq!(svgs.len(), 1);
    let svg = std::fs::read_to_string(&svgs[0]).expect("svg");
    assert_eq!(svg.matches("<line ").count(), 2_000);
    assert!(!dir.path().join("ttyEDO").exists());
}

#[test]
fn machine_reset_over_the_pty_is_reported_not_resumed() {
    let faults = Faults::parse("reset-at=300").expect("faults");
    let dir = tempfile::tempdir().expect("tempdir");
    let sim = hil_sim::spawn(SimConfig {
        link: Some(dir.path().join("ttyEDO")),
        speed: 100.0,
        faults,
        ..SimConfig::default()
    })
    .expect("start hil-sim");
    let report = run(&LinkTestConfig {
        port: sim.path().to_path_buf(),
        moves: 2_000,
        baud: 250_000,
        stall_timeout: Duration::from_secs(20),
    })
    .expect("link test");
    let summary = sim.stop().expect("stop hil-sim");
    assert_eq!(summary.resets, 1);
    assert_eq!(report.resets, 1);
    assert!(report.aborted.is_some());
    // The host knows what the machine reported before it reset (reports are at most
    // 50 ms apart), never more than what was executed; the rest counts as lost.
    assert!(report.executed > 0 && report.executed <= 300, "{report}");
    assert_eq!(report.lost, report.sent - report.executed);
}
