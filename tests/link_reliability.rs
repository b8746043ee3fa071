//! The link over a simulated lossy serial line: seeded, simulated time, no threads.
//!
//! `EDO_LINK_MOVES` sets the move count of the big stream test (default 1,000,000).

use edo::link::testkit::{test_move, Harness, HarnessConfig, LineFaults};
use edo::link::{HostEvent, LinkConfig, MachineDescription, MachineLinkConfig};
use proptest::prelude::*;

/// The channel: 1e-4 bit-error rate, 1 % dropped, 0.1 % duplicated frames.
fn lossy() -> LineFaults {
    LineFaults {
        bit_error_rate: 1e-4,
        drop_rate: 0.01,
        dup_rate: 0.001,
        ..LineFaults::default()
    }
}

fn lossy_config(seed: u64) -> HarnessConfig {
    HarnessConfig {
        seed,
        to_machine: lossy(),
        to_host: lossy(),
        ..HarnessConfig::default()
    }
}

#[test]
fn clean_line_streams_in_order() {
    let mut h = Harness::new(HarnessConfig::default());
    let r = h.stream(7, 20_000, 600_000_000, test_move);
    assert!(r.completed, "{r:?}");
    assert_eq!((r.lost, r.duplicated, r.reordered), (0, 0, 0));
    assert_eq!(r.host_stats.bytes_retransmitted, 0);
    assert_eq!(h.host.last_executed().map(|m| m.index), Some(19_999));
    assert!(r.utilisation(250_000) > 0.85, "{}", r.utilisation(250_000));
}

#[test]
fn million_moves_through_a_lossy_line() {
    let moves: u32 = std::env::var("EDO_LINK_MOVES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_000_000);
    let mut h = Harness::new(lossy_config(42));
    let r = h.stream(1, moves, u64::MAX / 4, test_move);
    eprintln!(
        "{moves} moves: {:.1} s simulated, {:.0} moves/s, {} bytes retransmitted, {} naks, {} timeouts, {} invalid frames at machine",
        r.elapsed_us as f64 / 1e6,
        r.moves_per_s(),
        r.host_stats.bytes_retransmitted,
        r.host_stats.naks_received,
        r.host_stats.timeouts,
        r.machine_stats.frames_invalid
    );
    assert!(r.completed, "{r:?}");
    assert_eq!(r.executed, u64::from(moves));
    assert_eq!((r.lost, r.duplicated, r.reordered), (0, 0, 0));
    // The faults really happened and were repaired.
    assert!(r.machine_stats.frames_invalid > 0);
    assert!(r.machine_stats.frames_duplicate > 0);
    assert!(r.host_stats.bytes_retransmitted > 0);
    assert_eq!(r.resets_reported, 0);
    assert_eq!(h.machine.status().duplicates, 0);
    assert_eq!(h.machine.status().gaps, 0);
}

#[test]
fn machine_resets_are_reported_never_silent() {
    let mut cfg = lossy_config(7);
    cfg.reset_after_moves = Some(3_000);
    let mut h = Harness::new(cfg);
    let r = h.stream(3, 10_000, 600_000_000, test_move);
    assert!(r.completed, "{r:?}");
    assert_eq!(r.resets_injected, 3);
    assert_eq!(r.resets_reported, r.resets_injected);
    assert_eq!((r.lost, r.duplicated, r.reordered), (0, 0, 0));
    let resets: Vec<_> = h
        .host_events
        .iter()
        .filter_map(|e| match e {
            HostEvent::MachineReset {
                previous_boot_id,
                boot_id,
                ..
            } => Some((*previous_boot_id, *boot_id)),
            _ => None,
        })
        .collect();
    assert_eq!(resets.len(), 3);
    for (old, new) in resets {
        assert_ne!(old, new);
    }
}

#[test]
fn link_loss_is_detected_within_two_seconds() {
    let mut h = Harness::new(HarnessConfig::default());
    let r = h.stream(1, 1_000, 60_000_000, test_move);
    assert!(r.completed);
    let dead = LineFaults {
        drop_rate: 1.0,
        ..LineFaults::default()
    };
    h.set_faults(dead, dead);
    let cut_at = h.now;
    let r = h.stream(1, 1_000_000, 2_000_000, test_move);
    assert!(r.link_lost_events >= 1);
    let lost_at = h
        .host_events
        .iter()
        .find_map(|e| match e {
            HostEvent::LinkLost { silent_us } => Some(*silent_us),
            _ => None,
        })
        .unwrap_or(u64::MAX);
    assert!(lost_at < 2_000_000, "{lost_at}");
    assert!(h.now.since(cut_at) >= 1_500_000);
}

#[test]
fn emergency_stop_overtakes_queued_moves() {
    let mut cfg = HarnessConfig {
        exec_us_per_move: 10_000,
        ..HarnessConfig::default()
    };
    cfg.machine.machine.queue_depth = 64;
    let mut h = Harness::new(cfg);
    let _ = h.stream(1, 200, 2_000_000, test_move);
    let now = h.now;
    h.host.priority(edo::link::PriorityCmd::EmergencyStop, now);
    let _ = h.stream(1, 0, 200_000, test_move);
    assert_eq!(h.machine.status().state, edo::link::MachineState::EStopped);
    assert_eq!(h.machine.queue_len(), 0);
    assert!(h.host_events.contains(&HostEvent::PriorityAcked(
        edo::link::PriorityCmd::EmergencyStop
    )));
}

#[test]
fn small_machine_limits_are_respected() {
    let mut cfg = lossy_config(3);
    cfg.host = LinkConfig {
        max_frame: 128,
        ..LinkConfig::default()
    };
    cfg.machine = MachineLinkConfig {
        machine: MachineDescription {
            queue_depth: 4,
            rx_buffer_bytes: 200,
            ..MachineDescription::default()
        },
        ..MachineLinkConfig::default()
    };
    cfg.exec_us_per_move = 2_000;
    let mut h = Harness::new(cfg);
    let r = h.stream(9, 2_000, 600_000_000, test_move);
    assert!(r.completed, "{r:?}");
    assert_eq!((r.lost, r.duplicated, r.reordered), (0, 0, 0));
    assert_eq!(
        h.machine.status().faults,
        0,
        "queue overflow means credits were ignored"
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, .. ProptestConfig::default() })]

    #[test]
    fn random_fault_schedules_never_lose_moves(
        seed in any::<u64>(),
        ber in 0.0f64..5e-4,
        drop in 0.0f64..0.05,
        dup in 0.0f64..0.02,
        delay in 0u64..5_000,
        jitter in 0u64..5_000,
        exec in 0u64..500,
        reset in proptest::option::of(500u64..3_000),
        baud in prop::sample::select(vec![57_600u32, 115_200, 250_000, 1_000_000]),
    ) {
        let f = LineFaults { bit_error_rate: ber, drop_rate: drop, dup_rate: dup, delay_us: delay, jitter_us: jitter };
        let cfg = HarnessConfig {
            seed, baud, to_machine: f, to_host: f, exec_us_per_move: exec, reset_after_moves: reset,
            ..HarnessConfig::default()
        };
        let mut h = Harness::new(cfg);
        let r = h.stream(5, 3_000, 3_600_000_000, test_move);
        prop_assert!(r.completed, "{:?}", r);
        prop_assert_eq!((r.lost, r.duplicated, r.reordered), (0, 0, 0));
        prop_assert_eq!(r.resets_reported, r.resets_injected);
    }
}
