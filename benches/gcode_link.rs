//! G-code link throughput on the simulated line (`gcode_link::testkit`): lines per second
//! and the line's utilisation (line bytes / (baud / 10 × time)) against each firmware
//! model, one line at a time (OctoPrint's way) and windowed, at 115200 and 250000 baud
//! with 1 and 4 ms latency each way. The simulated figures are printed once per case
//! (they are simulated time: the same on every machine); criterion then measures how fast
//! the protocol core and the firmware model run (wall time per simulated stream).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use edo::gcode_link::testkit::{throughput, GcodeHarness, ThroughputCase};
use edo::gcode_link::{Dialect, Window};

/// (name, firmware, receive buffer, command queue, windowed mode).
const FIRMWARE: [(&str, Dialect, usize, usize, Window); 5] = [
    (
        "marlin_rx1024_advok",
        Dialect::Marlin,
        1024,
        16,
        Window::AdvancedOk,
    ),
    (
        "marlin_avr_rx128_advok",
        Dialect::Marlin,
        128,
        4,
        Window::AdvancedOk,
    ),
    (
        "marlin_rx1024_window2",
        Dialect::Marlin,
        1024,
        16,
        Window::Lines(2),
    ),
    ("klipper_pty", Dialect::Klipper, 4096, 20, Window::Auto),
    ("rrf", Dialect::Rrf, 256, 1, Window::Auto),
];

fn cases(
    baud: u32,
    latency_us: u64,
    (_, dialect, rx, slots, window): (&str, Dialect, usize, usize, Window),
) -> (ThroughputCase, ThroughputCase) {
    let mut one = ThroughputCase::one_at_a_time(dialect, baud, latency_us);
    one.rx_buffer_bytes = rx;
    one.command_slots = slots;
    let windowed = ThroughputCase {
        window,
        advanced_ok: dialect == Dialect::Marlin,
        ..one
    };
    (one, windowed)
}

fn print_figures() {
    let lines = 10_000;
    for baud in [115_200u32, 250_000] {
        for latency_us in [1_000u64, 4_000] {
            for fw in FIRMWARE {
                let (one, windowed) = cases(baud, latency_us, fw);
                let a = throughput(&one, lines);
                let b = throughput(&windowed, lines);
                assert!(a.completed && b.completed && a.lost == 0 && b.lost == 0);
                println!(
                    "simulated {baud} baud, {} ms latency, {}: one at a time {:.0} lines/s \
                     ({:.1} %), windowed {:.0} lines/s ({:.1} %), {:.2}x",
                    latency_us / 1000,
                    fw.0,
                    a.moves_per_s(),
                    a.utilisation(baud) * 100.0,
                    b.moves_per_s(),
                    b.utilisation(baud) * 100.0,
                    b.moves_per_s() / a.moves_per_s()
                );
            }
        }
    }
}

/// A lost `ok` with one line in flight (`docs/firmware.md`, "A lost ok"): 10,000 moves
/// of 20 ms, 0.2 % of the firmware's `ok`s lost, Marlin one line at a time (a UART) and
/// RRF: moves per second against the same run without loss, the lines sent untimed (the
/// timeouts alone) and timed (`send_timed_line`, as edod sends moves).
fn print_lost_ok_figures() {
    let lines = 10_000;
    for (name, dialect) in [("marlin one line", Dialect::Marlin), ("rrf", Dialect::Rrf)] {
        let run = |drop_ok: f64, timed: bool| {
            let case = ThroughputCase::one_at_a_time(dialect, 250_000, 1_000);
            let mut cfg = case.harness_config();
            cfg.exec_us_per_move = 20_000;
            cfg.faults.drop_ok = drop_ok;
            cfg.timed_lines = timed;
            cfg.seed = 7;
            let r = GcodeHarness::new(cfg).run(lines, u64::MAX / 4);
            assert!(r.completed && r.lost == 0, "{name}: {r:?}");
            r
        };
        let clean = run(0.0, true);
        for timed in [false, true] {
            let lossy = run(0.002, timed);
            println!(
                "lost oks, {name}, {}: {:.1} moves/s against {:.1} without loss ({:.1} %), \
                 {} timeouts, {} overdue probes, {} lines run twice",
                if timed {
                    "timed lines"
                } else {
                    "untimed lines"
                },
                lossy.moves_per_s(),
                clean.moves_per_s(),
                100.0 * lossy.moves_per_s() / clean.moves_per_s(),
                lossy.host_stats.timeouts,
                lossy.host_stats.oks_overdue,
                lossy.duplicates,
            );
        }
    }
}

fn bench(c: &mut Criterion) {
    print_lost_ok_figures();
    print_figures();
    let mut g = c.benchmark_group("gcode_link");
    g.sample_size(10);
    let lines = 2_000;
    g.throughput(Throughput::Elements(u64::from(lines)));
    for fw in [FIRMWARE[0], FIRMWARE[3], FIRMWARE[4]] {
        let (one, windowed) = cases(250_000, 1_000, fw);
        g.bench_function(format!("{}_one_at_a_time", fw.0), |b| {
            b.iter(|| throughput(&one, lines))
        });
        g.bench_function(format!("{}_windowed", fw.0), |b| {
            b.iter(|| throughput(&windowed, lines))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
