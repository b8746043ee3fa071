//! Link throughput on the simulated line: moves per second and link utilisation (move
//! bytes / line capacity at baud/10 bytes per second) at 115200 and 250000 baud, clean and
//! with 1 % dropped frames. Simulated figures are printed once per case; criterion then
//! measures how fast the protocol core itself runs (wall time per simulated stream).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use edo::link::testkit::{test_move, Harness, HarnessConfig, LineFaults};

fn case(baud: u32, drop: f64, moves: u32) -> (f64, f64, u64) {
    let f = LineFaults {
        drop_rate: drop,
        ..LineFaults::default()
    };
    let mut h = Harness::new(HarnessConfig {
        baud,
        to_machine: f,
        to_host: f,
        seed: 17,
        ..HarnessConfig::default()
    });
    let r = h.stream(1, moves, u64::MAX / 4, test_move);
    assert!(r.completed && r.lost == 0 && r.duplicated == 0 && r.reordered == 0);
    (
        r.utilisation(baud),
        r.moves_per_s(),
        r.host_stats.bytes_retransmitted,
    )
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("link");
    g.sample_size(10);
    for baud in [115_200u32, 250_000] {
        for drop in [0.0, 0.01] {
            let (util, mps, retx) = case(baud, drop, 50_000);
            println!(
                "simulated {baud} baud, drop {:.0} %: utilisation {:.1} %, {mps:.0} moves/s, {retx} bytes retransmitted",
                drop * 100.0,
                util * 100.0
            );
            let moves = 5_000;
            g.throughput(Throughput::Elements(u64::from(moves)));
            g.bench_function(format!("{baud}baud_drop{}pct", drop * 100.0), |b| {
                b.iter(|| case(baud, drop, moves))
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
