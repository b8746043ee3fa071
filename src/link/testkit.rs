//! A seeded, simulated-time serial line and a host–machine harness on top of it, for
//! tests and benchmarks: no threads, no clocks, fully deterministic for a given seed.
//!
//! The [`Line`] models one direction of a UART: bytes leave at `baud / 10` bytes per
//! second (start + 8 data + stop bits), frames queue behind each other (FIFO, never
//! reordered, like a real line), and faults are applied per frame (drop, duplicate) and
//! per bit (bit-error rate on the 8 data bits), plus fixed delay and jitter.

use std::collections::VecDeque;

use super::{
    Host, HostEvent, LinkConfig, LinkStats, MachineLink, MachineLinkConfig, Micros, MoveRef,
};
use crate::machine::{Move, MoveKind, PositionUm};

/// SplitMix64: small, fast, seeded; good enough for fault injection.
#[derive(Debug, Clone)]
pub struct SimRng(u64);

impl SimRng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.next_f64() < p
    }

    /// Bits until the next error at bit-error rate `ber` (geometric distribution).
    fn bits_to_next_error(&mut self, ber: f64) -> u64 {
        if ber <= 0.0 {
            return u64::MAX;
        }
        let u = self.next_f64().max(f64::MIN_POSITIVE);
        (u.ln() / (1.0 - ber).ln())
            .floor()
            .min(u64::MAX as f64 / 2.0) as u64
    }
}

/// Faults of one direction of the line.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LineFaults {
    /// Probability that any data bit is flipped.
    pub bit_error_rate: f64,
    /// Probability that a frame is lost.
    pub drop_rate: f64,
    /// Probability that a frame arrives twice.
    pub dup_rate: f64,
    /// Fixed extra latency (µs).
    pub delay_us: u64,
    /// Uniform random extra latency 0..jitter (µs); order is kept.
    pub jitter_us: u64,
}

/// One direction of a simulated UART.
#[derive(Debug)]
pub struct Line {
    baud: u32,
    faults: LineFaults,
    rng: SimRng,
    line_free_ns: u64,
    last_delivery: Micros,
    bits_to_error: u64,
    in_flight: VecDeque<(Micros, Vec<u8>)>,
    /// Bytes put on the line (after drops, including duplicates).
    pub bytes_on_wire: u64,
}

impl Line {
    /// A line at `baud` with `faults`.
    pub fn new(baud: u32, faults: LineFaults, seed: u64) -> Self {
        let mut rng = SimRng::new(seed);
        let bits_to_error = rng.bits_to_next_error(faults.bit_error_rate);
        Self {
            baud: baud.max(1),
            faults,
            rng,
            line_free_ns: 0,
            last_delivery: Micros(0),
            bits_to_error,
            in_flight: VecDeque::new(),
            bytes_on_wire: 0,
        }
    }

    /// Change the faults (e.g. mid-run).
    pub fn set_faults(&mut self, faults: LineFaults) {
        self.faults = faults;
        self.bits_to_error = self.rng.bits_to_next_error(faults.bit_error_rate);
    }

    fn byte_time_ns(&self) -> u64 {
        10_000_000_000 / u64::from(self.baud)
    }

    /// Time at which the line is idle again.
    pub fn busy_until(&self) -> Micros {
        Micros(self.line_free_ns.div_ceil(1000))
    }

    /// Write bytes at `now`.
    pub fn write(&mut self, bytes: &[u8], now: Micros) {
        if self.rng.chance(self.faults.drop_rate) {
            return;
        }
        let copies = if self.rng.chance(self.faults.dup_rate) {
            2
        } else {
            1
        };
        for _ in 0..copies {
            let mut data = bytes.to_vec();
            let bits = data.len() as u64 * 8;
            let mut pos = 0u64;
            while self.bits_to_error < bits - pos.min(bits) {
                pos += self.bits_to_error;
                let (byte, bit) = ((pos / 8) as usize, pos % 8);
                if let Some(b) = data.get_mut(byte) {
                    *b ^= 1 << bit;
                }
                pos += 1;
                self.bits_to_error = self.rng.bits_to_next_error(self.faults.bit_error_rate);
            }
            self.bits_to_error -= bits - pos.min(bits);
            let start = self.line_free_ns.max(now.0 * 1000);
            self.line_free_ns = start + data.len() as u64 * self.byte_time_ns();
            let jitter = if self.faults.jitter_us > 0 {
                self.rng.next_u64() % self.faults.jitter_us
            } else {
                0
            };
            let at = Micros(self.line_free_ns.div_ceil(1000) + self.faults.delay_us + jitter)
                .max(self.last_delivery);
            self.last_delivery = at;
            self.bytes_on_wire += data.len() as u64;
            self.in_flight.push_back((at, data));
        }
    }

    /// Earliest pending delivery.
    pub fn next_delivery(&self) -> Option<Micros> {
        self.in_flight.front().map(|f| f.0)
    }

    /// Pop a delivery due at `now`.
    pub fn deliver(&mut self, now: Micros) -> Option<Vec<u8>> {
        if self.in_flight.front()?.0 <= now {
            self.in_flight.pop_front().map(|f| f.1)
        } else {
            None
        }
    }

    /// Forget everything in flight (the cable was pulled).
    pub fn cut(&mut self) {
        self.in_flight.clear();
    }
}

/// Configuration of a [`Harness`] run.
#[derive(Debug, Clone)]
pub struct HarnessConfig {
    /// Line speed, both directions.
    pub baud: u32,
    /// Faults host → machine.
    pub to_machine: LineFaults,
    /// Faults machine → host.
    pub to_host: LineFaults,
    /// Seed of everything random.
    pub seed: u64,
    /// Host link configuration.
    pub host: LinkConfig,
    /// Machine link configuration.
    pub machine: MachineLinkConfig,
    /// Time the executor needs per move (µs); 0 = as fast as moves arrive.
    pub exec_us_per_move: u64,
    /// Reset the machine (new boot id, boot garbage) after this many executed moves.
    pub reset_after_moves: Option<u64>,
    /// Keep at most this many moves waiting in the host.
    pub host_backlog: usize,
}

impl Default for HarnessConfig {
    fn default() -> Self {
        Self {
            baud: 250_000,
            to_machine: LineFaults::default(),
            to_host: LineFaults::default(),
            seed: 1,
            host: LinkConfig::default(),
            machine: MachineLinkConfig::default(),
            exec_us_per_move: 0,
            reset_after_moves: None,
            host_backlog: 256,
        }
    }
}

/// What a harness run observed.
#[derive(Debug, Clone, Default)]
pub struct HarnessReport {
    /// Moves handed to the host.
    pub sent: u64,
    /// Moves the executor ran.
    pub executed: u64,
    /// Moves executed more than once.
    pub duplicated: u64,
    /// Moves executed out of order (index not the next expected one).
    pub reordered: u64,
    /// Moves never executed (sent - distinct executed), at the end of the run.
    pub lost: u64,
    /// Simulated time of the run (µs).
    pub elapsed_us: u64,
    /// Host statistics.
    pub host_stats: LinkStats,
    /// Machine statistics.
    pub machine_stats: LinkStats,
    /// Bytes on the wire host → machine.
    pub wire_bytes_to_machine: u64,
    /// Machine resets the host reported.
    pub resets_reported: u64,
    /// Machine resets injected.
    pub resets_injected: u64,
    /// Link-loss events at the host.
    pub link_lost_events: u64,
    /// Whether all moves were executed before the time limit.
    pub completed: bool,
}

impl HarnessReport {
    /// Move bytes per second of simulated time over the line capacity (baud / 10).
    pub fn utilisation(&self, baud: u32) -> f64 {
        if self.elapsed_us == 0 {
            return 0.0;
        }
        let capacity = f64::from(baud) / 10.0 * self.elapsed_us as f64 / 1e6;
        self.host_stats.payload_bytes_acked as f64 / capacity
    }

    /// Executed moves per second of simulated time.
    pub fn moves_per_s(&self) -> f64 {
        if self.elapsed_us == 0 {
            return 0.0;
        }
        self.executed as f64 / (self.elapsed_us as f64 / 1e6)
    }
}

/// A realistic two-syringe extrusion move (the shape `edoctl link-test` sends).
pub fn test_move(job_id: u32, index: u32) -> Move {
    let x = (index % 1000) as i32 * 137;
    Move {
        job_id,
        index,
        kind: MoveKind::Extrude {
            to: PositionUm {
                x_um: 50_000 + x,
                y_um: 60_000 + (index % 97) as i32 * 211,
                z_um: 300 + (index / 10_000) as i32 * 200,
            },
            feed_um_s: 20_000,
            volumes_nl: vec![1_200 + index % 17, 800 + index % 13],
            width_factor_ppt: 1000,
        },
    }
}

/// Host and machine ends on two simulated lines, with an executor that checks exactly-
/// once, in-order execution.
#[derive(Debug)]
pub struct Harness {
    cfg: HarnessConfig,
    /// Simulated now.
    pub now: Micros,
    /// Host end.
    pub host: Host,
    /// Machine end.
    pub machine: MachineLink,
    to_machine: Line,
    to_host: Line,
    rng: SimRng,
    next_exec: Micros,
    expected_index: u32,
    /// Every host event, in order.
    pub host_events: Vec<HostEvent>,
    report: HarnessReport,
    boots: u64,
}

impl Harness {
    /// A harness at time 0.
    pub fn new(cfg: HarnessConfig) -> Self {
        let mut rng = SimRng::new(cfg.seed);
        let host = Host::new(cfg.host.clone(), rng.next_u64(), Micros(0));
        let mut mcfg = cfg.machine.clone();
        mcfg.machine.boot_id = rng.next_u64();
        let machine = MachineLink::new(mcfg, Micros(0));
        let to_machine = Line::new(cfg.baud, cfg.to_machine, rng.next_u64());
        let to_host = Line::new(cfg.baud, cfg.to_host, rng.next_u64());
        Self {
            cfg,
            now: Micros(0),
            host,
            machine,
            to_machine,
            to_host,
            rng,
            next_exec: Micros(0),
            expected_index: 0,
            host_events: Vec::new(),
            report: HarnessReport::default(),
            boots: 1,
        }
    }

    fn reset_machine(&mut self) {
        let mut mcfg = self.cfg.machine.clone();
        mcfg.machine.boot_id = self.rng.next_u64();
        self.machine = MachineLink::new(mcfg, self.now);
        self.to_host.cut();
        self.to_machine.cut();
        // Boot garbage: a bootloader banner on the line.
        self.to_host.write(b"\r\nboot v1.0 \x00\xff\xfe", self.now);
        self.boots += 1;
        self.report.resets_injected += 1;
    }

    /// Move time forward to the next thing that happens (at least 1 µs).
    fn advance(&mut self) {
        let mut next: Option<Micros> = None;
        let mut consider = |t: Option<Micros>| {
            if let Some(t) = t {
                next = Some(next.map_or(t, |n: Micros| n.min(t)));
            }
        };
        consider(self.to_machine.next_delivery());
        consider(self.to_host.next_delivery());
        consider(self.host.next_timeout());
        consider(self.machine.next_timeout());
        if self.machine.queue_len() > 0 {
            consider(Some(self.next_exec));
        }
        let next = next.unwrap_or(self.now.plus_us(1000));
        self.now = next.max(self.now.plus_us(1));
    }

    /// One round: deliver, execute, transmit.
    fn round(&mut self, job_id: u32) {
        let now = self.now;
        while let Some(b) = self.to_machine.deliver(now) {
            self.machine.handle_bytes(&b, now);
        }
        while let Some(b) = self.to_host.deliver(now) {
            self.host.handle_bytes(&b, now);
        }
        while self.next_exec <= now {
            let Some(mv) = self.machine.pop_move() else {
                break;
            };
            self.check_executed(job_id, &mv);
            let remaining = self.machine.status().remaining_nl.clone();
            self.machine
                .move_done(&mv, PositionUm::default(), &remaining);
            self.next_exec = self.next_exec.max(now).plus_us(self.cfg.exec_us_per_move);
            if self.cfg.exec_us_per_move > 0 {
                break;
            }
            if let Some(n) = self.cfg.reset_after_moves {
                if self.report.executed == n * self.boots {
                    self.reset_machine();
                    break;
                }
            }
        }
        if self.next_exec < now {
            self.next_exec = now;
        }
        while let Some(t) = self.host.poll_transmit(now) {
            self.to_machine.write(&t.bytes, now);
        }
        while let Some(t) = self.machine.poll_transmit(now) {
            self.to_host.write(&t.bytes, now);
        }
        while let Some(e) = self.host.poll_event() {
            match &e {
                HostEvent::MachineReset { .. } => self.report.resets_reported += 1,
                HostEvent::LinkLost { .. } => self.report.link_lost_events += 1,
                _ => {}
            }
            self.host_events.push(e);
        }
        while self.machine.poll_event().is_some() {}
    }

    fn check_executed(&mut self, job_id: u32, mv: &Move) {
        self.report.executed += 1;
        if mv.job_id != job_id {
            return;
        }
        if mv.index == self.expected_index {
            self.expected_index += 1;
        } else if mv.index < self.expected_index {
            self.report.duplicated += 1;
        } else {
            self.report.reordered += 1;
            self.expected_index = mv.index + 1;
        }
    }

    /// Stream `moves` moves of job `job_id` (built by `make`) until all are executed or
    /// `max_time_us` of simulated time passed. After a machine reset the harness
    /// reconnects and resumes from the move after the last one the machine executed —
    /// what the daemon does after the operator confirms.
    pub fn stream(
        &mut self,
        job_id: u32,
        moves: u32,
        max_time_us: u64,
        make: impl Fn(u32, u32) -> Move,
    ) -> HarnessReport {
        let start = self.now;
        let mut next_index: u32 = 0;
        let mut resets_seen = 0;
        while self.expected_index < moves && self.now.since(start) < max_time_us {
            if self.report.resets_reported > resets_seen {
                resets_seen = self.report.resets_reported;
                // Resume after the last executed move (what we observed executing).
                next_index = self.expected_index;
                let session = self.rng.next_u64();
                self.host.reconnect(session, self.now);
            }
            if self.host.state() == super::HostState::Connected {
                while next_index < moves && self.host.pending() < self.cfg.host_backlog {
                    if self.host.send_move(make(job_id, next_index)).is_err() {
                        break;
                    }
                    next_index += 1;
                    self.report.sent += 1;
                }
            }
            self.round(job_id);
            self.advance();
        }
        // Let the last reports and acks settle.
        let settle_until = self.now.plus_us(100_000);
        while self.now < settle_until {
            self.round(job_id);
            self.advance();
        }
        let mut r = self.report.clone();
        r.completed = self.expected_index >= moves;
        r.lost = u64::from(moves.saturating_sub(self.expected_index));
        r.elapsed_us = self.now.since(start);
        r.host_stats = self.host.stats();
        r.machine_stats = self.machine.stats();
        r.wire_bytes_to_machine = self.to_machine.bytes_on_wire;
        r
    }

    /// Last executed move as the host knows it.
    pub fn host_last_executed(&self) -> Option<MoveRef> {
        self.host.last_executed()
    }

    /// Inject faults from now on.
    pub fn set_faults(&mut self, to_machine: LineFaults, to_host: LineFaults) {
        self.to_machine.set_faults(to_machine);
        self.to_host.set_faults(to_host);
    }
}
