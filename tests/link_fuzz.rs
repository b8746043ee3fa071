//! Fuzz-style tests: random and mutated bytes into the decoder and both link ends never
//! panic and never buffer without bound.

use edo::link::frame::{encode_frame, Decoder, Frame, FrameKind, MAX_ENCODED_FRAME};
use edo::link::testkit::SimRng;
use edo::link::{Host, LinkConfig, MachineLink, MachineLinkConfig, Micros};

#[test]
fn random_bytes_never_panic_and_stay_bounded() {
    let mut rng = SimRng::new(99);
    let mut d = Decoder::new();
    let mut host = Host::new(LinkConfig::default(), 1, Micros(0));
    let mut machine = MachineLink::new(MachineLinkConfig::default(), Micros(0));
    let mut buf = vec![0u8; 4096];
    for round in 0..2_000u64 {
        let len = (rng.next_u64() % 4096) as usize;
        // Mix densities of zero bytes so both long runs and short frames happen.
        let zero_bias = rng.next_u64() % 4;
        for b in buf.iter_mut().take(len) {
            let r = rng.next_u64();
            *b = if zero_bias == 0 && r.is_multiple_of(16) {
                0
            } else {
                (r >> 8) as u8
            };
        }
        for &b in &buf[..len] {
            let _ = d.push(b);
            assert!(d.buffered() <= MAX_ENCODED_FRAME);
        }
        let now = Micros(round * 1000);
        host.handle_bytes(&buf[..len], now);
        machine.handle_bytes(&buf[..len], now);
        while host.poll_transmit(now).is_some() {}
        while machine.poll_transmit(now).is_some() {}
        while host.poll_event().is_some() {}
        while machine.poll_event().is_some() {}
    }
}

#[test]
fn mutated_valid_frames_never_panic() {
    let mut rng = SimRng::new(5);
    let kinds = [
        FrameKind::Data,
        FrameKind::Ack,
        FrameKind::Nak,
        FrameKind::Priority,
        FrameKind::PriorityAck,
        FrameKind::Hello,
        FrameKind::HelloReply,
        FrameKind::Heartbeat,
        FrameKind::Unsynced,
    ];
    let mut host = Host::new(LinkConfig::default(), 1, Micros(0));
    let mut machine = MachineLink::new(MachineLinkConfig::default(), Micros(0));
    for i in 0..20_000u64 {
        let body_len = (rng.next_u64() % 200) as usize;
        let body: Vec<u8> = (0..body_len).map(|_| rng.next_u64() as u8).collect();
        let f = Frame {
            kind: kinds[(rng.next_u64() % kinds.len() as u64) as usize],
            seq: rng.next_u64() as u16,
            ack: rng.next_u64() as u16,
            credits: rng.next_u64() as u16,
            body,
        };
        // Valid CRC, garbage bodies: exercises every message decoder.
        let mut wire = Vec::new();
        encode_frame(&f, &mut wire);
        if i % 3 == 0 {
            let n = wire.len();
            wire[(rng.next_u64() as usize) % n] ^= 1 << (rng.next_u64() % 8);
        }
        let now = Micros(i * 100);
        host.handle_bytes(&wire, now);
        machine.handle_bytes(&wire, now);
        while host.poll_transmit(now).is_some() {}
        while machine.poll_transmit(now).is_some() {}
        while host.poll_event().is_some() {}
        while machine.poll_event().is_some() {}
        while machine.pop_move().is_some() {}
    }
}
