//! `edoctl link-test --protocol gcode`: dry-run moves through `LineHost` to
//! `hil-sim --gcode` on a real pty, for every firmware, clean and with line faults; the
//! report's counts and verdict.

use std::time::Duration;

use edo::cli::linktest_gcode::{run, GcodeLinkTestConfig};
use edo::gcode_link::{Dialect, Window};
use hil_sim::{Faults, GcodeOptions, SimConfig};

fn test_on(
    firmware: Dialect,
    faults: &str,
    moves: u32,
) -> edo::cli::linktest_gcode::GcodeLinkTestReport {
    let sim = hil_sim::spawn(SimConfig {
        speed: 200.0,
        seed: 3,
        faults: Faults::parse(faults).unwrap(),
        gcode: Some(GcodeOptions::new(firmware, 2)),
        ..SimConfig::default()
    })
    .unwrap();
    let report = run(&GcodeLinkTestConfig {
        port: sim.path().to_path_buf(),
        firmware,
        moves,
        baud: 250_000,
        window: Window::Auto,
        stall_timeout: Duration::from_secs(20),
    })
    .unwrap();
    sim.stop().unwrap();
    report
}

#[test]
fn every_firmware_passes_on_a_clean_pty() {
    for fw in [Dialect::Marlin, Dialect::Rrf, Dialect::Klipper] {
        let r = test_on(fw, "", 300);
        assert!(r.is_clean(), "{fw:?}: {r}");
        assert_eq!((r.lines, r.accepted, r.lost), (302, 302, 0), "{fw:?}: {r}");
        assert!(r.utilisation > 0.3 && r.moves_per_s > 100.0, "{fw:?}: {r}");
        assert!(r.to_string().contains("verdict           PASS"), "{r}");
    }
}

#[test]
fn marlin_line_faults_are_counted_and_still_pass() {
    let r = test_on(
        Dialect::Marlin,
        "corrupt-line=0.03,drop-ok=0.02,resend=0.02",
        300,
    );
    assert!(r.is_clean(), "{r}");
    assert!(r.resend_requests > 0 && r.resent > 0, "{r}");
}

/// The dry run moves relatively (`G91`), so the position cannot tell a lost `ok` from a
/// dropped line: RRF lines are sent again and reported.
#[test]
fn rrf_lost_oks_show_as_maybe_repeated_and_fail() {
    let r = test_on(Dialect::Rrf, "drop-ok=0.05", 80);
    assert!(r.maybe_repeated > 0, "{r}");
    assert!(!r.is_clean());
    assert!(r.to_string().contains("FAIL"), "{r}");
}

#[test]
fn edoctl_link_test_protocol_gcode_prints_the_report() {
    let sim = hil_sim::spawn(SimConfig {
        speed: 200.0,
        gcode: Some(GcodeOptions::new(Dialect::Klipper, 2)),
        ..SimConfig::default()
    })
    .unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_edoctl"))
        .args(["link-test", "--protocol", "gcode", "--firmware", "klipper"])
        .args(["--moves", "100", "--port"])
        .arg(sim.path())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text} {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("acknowledged      102") && text.contains("PASS"),
        "{text}"
    );
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_edoctl"))
        .args(["link-test", "--protocol", "gcode", "--moves", "1", "--port"])
        .arg(sim.path())
        .output()
        .unwrap();
    assert!(!out.status.success(), "--firmware is required with gcode");
    sim.stop().unwrap();
}
