//! Direct frame-level checks of the machine end: exactly-once under duplicated frames and
//! handshakes, the priority lane's rules, and reset announcement.

use edo::link::frame::{encode_frame, Decoder, Frame, FrameKind};
use edo::link::msg::Hello;
use edo::link::testkit::test_move;
use edo::link::{
    HostMsg, MachineDescription, MachineLink, MachineLinkConfig, MachineState, Micros, PriorityCmd,
    PROTOCOL_VERSION,
};

fn wire(kind: FrameKind, seq: u16, body: Vec<u8>) -> Vec<u8> {
    let mut out = Vec::new();
    encode_frame(
        &Frame {
            kind,
            seq,
            ack: 0,
            credits: 100,
            body,
        },
        &mut out,
    );
    out
}

fn hello(session_id: u64) -> Vec<u8> {
    let h = Hello {
        protocol_version: PROTOCOL_VERSION,
        session_id,
        max_frame: 512,
    };
    wire(
        FrameKind::Hello,
        0,
        postcard::to_allocvec(&h).expect("encode"),
    )
}

fn data(seq: u16, msgs: &[HostMsg]) -> Vec<u8> {
    wire(
        FrameKind::Data,
        seq,
        postcard::to_allocvec(msgs).expect("encode"),
    )
}

fn prio(seq: u16, cmd: PriorityCmd) -> Vec<u8> {
    wire(
        FrameKind::Priority,
        seq,
        postcard::to_allocvec(&cmd).expect("encode"),
    )
}

fn drain(m: &mut MachineLink, now: Micros) -> Vec<Frame> {
    let mut d = Decoder::new();
    let mut out = Vec::new();
    while let Some(t) = m.poll_transmit(now) {
        for &b in &t.bytes {
            if let Some(Ok(f)) = d.push(b) {
                out.push(f);
            }
        }
    }
    out
}

#[test]
fn boot_announces_and_unsynced_answers() {
    let mut m = MachineLink::new(MachineLinkConfig::default(), Micros(0));
    let f = drain(&mut m, Micros(0));
    assert_eq!(f.len(), 1);
    assert_eq!(f[0].kind, FrameKind::Unsynced);
    m.handle_bytes(&data(0, &[HostMsg::Move(test_move(1, 0))]), Micros(10));
    assert_eq!(m.queue_len(), 0, "no session: moves are not accepted");
    let f = drain(&mut m, Micros(10));
    assert_eq!(f[0].kind, FrameKind::Unsynced);
}

#[test]
fn duplicated_frames_and_hellos_execute_once() {
    let now = Micros(0);
    let mut m = MachineLink::new(MachineLinkConfig::default(), now);
    m.handle_bytes(&hello(7), now);
    let f0 = data(
        0,
        &[
            HostMsg::Move(test_move(1, 0)),
            HostMsg::Move(test_move(1, 1)),
        ],
    );
    let f1 = data(1, &[HostMsg::Move(test_move(1, 2))]);
    m.handle_bytes(&f0, now);
    m.handle_bytes(&f0, now);
    m.handle_bytes(&hello(7), now); // duplicate Hello: same session, no reset
    m.handle_bytes(&f1, now);
    m.handle_bytes(&f0, now);
    m.handle_bytes(&f1, now);
    let mut got = Vec::new();
    while let Some(mv) = m.pop_move() {
        got.push(mv.index);
    }
    assert_eq!(got, [0, 1, 2]);
    let frames = drain(&mut m, now);
    let reply = frames
        .iter()
        .find(|f| f.kind == FrameKind::HelloReply)
        .expect("hello answered");
    assert_eq!(reply.kind, FrameKind::HelloReply);
    assert_eq!(frames.last().map(|f| f.ack), Some(2));
}

#[test]
fn emergency_stop_always_acts_and_stale_resume_is_ignored() {
    let now = Micros(0);
    let mut m = MachineLink::new(MachineLinkConfig::default(), now);
    m.handle_bytes(&hello(1), now);
    m.handle_bytes(&data(0, &[HostMsg::Move(test_move(1, 0))]), now);
    m.handle_bytes(&prio(1, PriorityCmd::FeedHold), now);
    assert_eq!(m.status().state, MachineState::Held);
    assert!(m.pop_move().is_none(), "held: nothing executes");
    m.handle_bytes(&prio(2, PriorityCmd::Resume), now);
    m.handle_bytes(&prio(3, PriorityCmd::EmergencyStop), now);
    assert_eq!(m.status().state, MachineState::EStopped);
    assert_eq!(m.queue_len(), 0);
    // A late duplicate of the resume must not undo the stop.
    m.handle_bytes(&prio(2, PriorityCmd::Resume), now);
    assert_eq!(m.status().state, MachineState::EStopped);
    // Moves arriving during the stop are discarded.
    m.handle_bytes(&data(1, &[HostMsg::Move(test_move(1, 1))]), now);
    assert_eq!(m.queue_len(), 0);
    assert_eq!(m.moves_discarded(), 1);
    // A repeated e-stop (old counter) still acts.
    m.handle_bytes(&prio(4, PriorityCmd::Resume), now);
    assert_eq!(m.status().state, MachineState::Idle);
    m.handle_bytes(&prio(3, PriorityCmd::EmergencyStop), now);
    assert_eq!(m.status().state, MachineState::EStopped);
    let acks: Vec<u16> = drain(&mut m, now)
        .iter()
        .filter(|f| f.kind == FrameKind::PriorityAck)
        .map(|f| f.seq)
        .collect();
    assert!(!acks.is_empty());
}

#[test]
fn credits_are_the_free_queue_slots() {
    let now = Micros(0);
    let cfg = MachineLinkConfig {
        machine: MachineDescription {
            queue_depth: 8,
            ..MachineDescription::default()
        },
        ..MachineLinkConfig::default()
    };
    let mut m = MachineLink::new(cfg, now);
    m.handle_bytes(&hello(1), now);
    let moves: Vec<HostMsg> = (0..5).map(|i| HostMsg::Move(test_move(1, i))).collect();
    m.handle_bytes(&data(0, &moves), now);
    let frames = drain(&mut m, now);
    assert_eq!(frames.last().map(|f| f.credits), Some(3));
    for _ in 0..5 {
        let _ = m.pop_move();
    }
    let frames = drain(&mut m, now);
    assert_eq!(
        frames.last().map(|f| f.credits),
        Some(8),
        "window update sent"
    );
}
