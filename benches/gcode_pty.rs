//! G-code streaming on a real pty: dry-run moves through `LineHost`
//! (`edo::cli::linktest_gcode`, what `edoctl link-test --protocol gcode` runs) to
//! `hil-sim --gcode marlin|klipper|rrf` in this process, throttled to the baud, at 115200
//! and 250000 baud, windowed and one line at a time (OctoPrint's way); beside them the
//! edo protocol (`edo::cli::linktest`) to hil-sim's edo mode on the same pty and baud.
//! Prints one table (moves/s, windowed / one-at-a-time, share of the line's bytes used).
//!
//! `cargo bench --bench gcode_pty` streams 2,000 moves per case (about 2 min in all);
//! `EDO_BENCH_MOVES=10000` streams the 10,000 (about 8 min).

use std::time::Duration;

use edo::cli::linktest_gcode::{GcodeLinkTestConfig, GcodeLinkTestReport};
use edo::gcode_link::{Dialect, Window};
use hil_sim::{GcodeOptions, SimConfig};

/// Moves executed this many times faster than wall time: the line sets the pace.
const SPEED: f64 = 1000.0;

fn sim(baud: u32, gcode: Option<GcodeOptions>, delay_ms: u64) -> hil_sim::SimHandle {
    hil_sim::spawn(SimConfig {
        baud,
        speed: SPEED,
        seed: 5,
        gcode,
        faults: hil_sim::Faults::parse(&format!("delay={delay_ms}")).expect("delay"),
        ..SimConfig::default()
    })
    .expect("hil-sim starts")
}

/// One case: `moves` dry-run moves to `firmware` with `window`, `delay_ms` of latency
/// added each way (a USB-serial adapter's frames).
fn gcode_case(
    (baud, delay_ms): (u32, u64),
    firmware: Dialect,
    window: Window,
    moves: u32,
) -> GcodeLinkTestReport {
    let mut opts = GcodeOptions::new(firmware, 2);
    if firmware == Dialect::Marlin && window != Window::Auto {
        // A board on native USB: ADVANCED_OK, a 1024-byte buffer, BUFSIZE 16.
        opts.advanced_ok = true;
        opts.rx_buffer_bytes = Some(1024);
        opts.command_slots = Some(16);
    }
    let sim = sim(baud, Some(opts), delay_ms);
    let report = edo::cli::linktest_gcode::run(&GcodeLinkTestConfig {
        port: sim.path().to_path_buf(),
        firmware,
        moves,
        baud,
        window,
        stall_timeout: Duration::from_secs(20),
    })
    .expect("link test runs");
    let _ = sim.stop();
    assert!(report.is_clean(), "{report}");
    report
}

fn edo_case(baud: u32, moves: u32) -> edo::cli::linktest::LinkTestReport {
    let sim = sim(baud, None, 0);
    let report = edo::cli::linktest::run(&edo::cli::linktest::LinkTestConfig {
        port: sim.path().to_path_buf(),
        moves,
        baud,
        stall_timeout: Duration::from_secs(20),
    })
    .expect("link test runs");
    let _ = sim.stop();
    report
}

fn main() {
    // `cargo test --benches` runs this too: keep that short.
    let moves: u32 = std::env::var("EDO_BENCH_MOVES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(if std::env::args().any(|a| a == "--bench") {
            2_000
        } else {
            200
        });
    println!("{moves} dry-run moves per case, hil-sim on a pty at --speed {SPEED}");
    println!(
        "| baud | latency each way | firmware | windowed (window) | one at a time | windowed / one | line used, windowed | line used, one |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (baud, delay) in [(115_200u32, 0u64), (250_000, 0), (250_000, 1), (250_000, 4)] {
        for (name, fw, window, label) in [
            (
                "Marlin",
                Dialect::Marlin,
                Window::AdvancedOk,
                "advanced-ok, BUFSIZE 16",
            ),
            ("Klipper", Dialect::Klipper, Window::Auto, "8 lines"),
        ] {
            let w = gcode_case((baud, delay), fw, window, moves);
            let one = gcode_case((baud, delay), fw, Window::Lines(1), moves);
            println!(
                "| {baud} | {delay} ms | {name} | {:.0} moves/s ({label}) | {:.0} moves/s | {:.2}× | {:.1} % | {:.1} % |",
                w.moves_per_s,
                one.moves_per_s,
                w.moves_per_s / one.moves_per_s.max(1e-9),
                w.utilisation * 100.0,
                one.utilisation * 100.0
            );
        }
        if delay > 0 {
            continue;
        }
        let rrf = gcode_case((baud, 0), Dialect::Rrf, Window::Auto, moves);
        println!(
            "| {baud} | 0 ms | RRF | — (one line, always) | {:.0} moves/s | — | — | {:.1} % |",
            rrf.moves_per_s,
            rrf.utilisation * 100.0
        );
        let edo = edo_case(baud, moves);
        println!(
            "| {baud} | 0 ms | edo protocol (hil-sim edo mode) | {:.0} moves/s | — | — | {:.1} % | — |",
            edo.moves_per_s,
            edo.utilisation * 100.0
        );
    }
}
