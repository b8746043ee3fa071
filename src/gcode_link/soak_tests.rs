//! Soak tests: thousands of lines through the fault wire for each firmware.

use super::testkit::{GcodeFaults, GcodeHarness, GcodeHarnessConfig, GcodeReport};
use super::*;

fn run(cfg: GcodeHarnessConfig, lines: u32) -> GcodeReport {
    let mut h = GcodeHarness::new(cfg);
    h.run(lines, 36_000_000_000)
}

fn faults() -> GcodeFaults {
    GcodeFaults {
        corrupt_to_firmware: 0.02,
        corrupt_to_host: 0.02,
        drop_ok: 0.01,
        spurious_resend: 0.01,
        busy_chance: 0.002,
        busy_us: 3_000_000,
        reset_after_lines: Some(6000),
        unplug_after_lines: Some(3000),
        unplug_us: 60_000_000,
    }
}

fn show(name: &str, r: &GcodeReport) {
    eprintln!(
        "{name}: completed {} lost {} dup {} adj {} reord {} foreign {} unnumbered_rep {} acc_ooo {} maybe_rep {} inexact {} resets {} lost_ev {} stopped {} halted {} recov {} perr {} t {:.1}s timeouts {} probes {} resent {}",
        r.completed, r.lost, r.duplicates, r.adjacent_duplicates, r.reordered, r.foreign_lines_run,
        r.unnumbered_reported, r.accepted_out_of_order, r.maybe_repeated, r.inexact_recoveries, r.resets, r.link_lost, r.stopped, r.halted,
        r.recoveries, r.protocol_errors, r.elapsed_us as f64 / 1e6, r.host_stats.timeouts, r.host_stats.probes, r.host_stats.lines_resent
    );
}

#[test]
fn explore() {
    for seed in 1..4 {
        for d in [Dialect::Marlin, Dialect::Rrf, Dialect::Klipper] {
            let mut cfg = GcodeHarnessConfig::new(d);
            cfg.seed = seed;
            cfg.faults = faults();
            cfg.exec_us_per_move = 2000;
            if d == Dialect::Klipper {
                cfg.faults.corrupt_to_firmware = 0.0;
                cfg.faults.corrupt_to_host = 0.0;
                cfg.faults.drop_ok = 0.0;
                cfg.faults.unplug_after_lines = None;
            }
            show(&format!("{d:?} seed {seed}"), &run(cfg.clone(), 10_000));
            if d == Dialect::Marlin {
                cfg.firmware.advanced_ok = true;
                show(&format!("{d:?}+AOK seed {seed}"), &run(cfg, 10_000));
            }
        }
    }
}

#[test]
fn explore_rrf() {
    let none = GcodeFaults::default();
    let cases: Vec<(&str, GcodeFaults)> = vec![
        ("corrupt_fw", GcodeFaults { corrupt_to_firmware: 0.02, ..none.clone() }),
        ("corrupt_host", GcodeFaults { corrupt_to_host: 0.02, ..none.clone() }),
        ("drop_ok", GcodeFaults { drop_ok: 0.02, ..none.clone() }),
        ("busy", GcodeFaults { busy_chance: 0.002, busy_us: 3_000_000, ..none.clone() }),
        ("reset", GcodeFaults { reset_after_lines: Some(600), ..none.clone() }),
        ("unplug", GcodeFaults { unplug_after_lines: Some(600), unplug_us: 60_000_000, ..none.clone() }),
    ];
    for (name, f) in cases {
        let mut cfg = GcodeHarnessConfig::new(Dialect::Rrf);
        cfg.faults = f;
        cfg.exec_us_per_move = 2000;
        show(name, &run(cfg, 2000));
    }
}

#[test]
fn explore_rrf2() {
    let all = faults();
    let cases: Vec<(&str, GcodeFaults)> = vec![
        ("all", all.clone()),
        ("no_reset", GcodeFaults { reset_after_lines: None, ..all.clone() }),
        ("no_unplug", GcodeFaults { unplug_after_lines: None, ..all.clone() }),
        ("no_busy", GcodeFaults { busy_chance: 0.0, ..all.clone() }),
        ("no_corrupt", GcodeFaults { corrupt_to_firmware: 0.0, corrupt_to_host: 0.0, ..all.clone() }),
    ];
    for (name, f) in cases {
        let mut cfg = GcodeHarnessConfig::new(Dialect::Rrf);
        cfg.faults = f;
        cfg.exec_us_per_move = 2000;
        show(name, &run(cfg, 10000));
    }
}
