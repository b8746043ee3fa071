//! The machine end of the link (sans-IO): owns the move queue, so that credits are exact
//! and every move is delivered to the executor exactly once.

use std::collections::VecDeque;

use super::frame::{encode_frame, Decoder, Frame, FrameKind};
use super::msg::{
    FaultKind, FaultReport, Hello, HelloReply, HostMsg, MachineDescription, MachineMsg,
    MachineState, MoveRef, PriorityCmd, Status, PROTOCOL_VERSION,
};
use super::stream::{decode_body, extend_seq, read_frames, Receiver, SendStream};
use super::{LinkConfig, LinkStats, Micros, Transmit};
use crate::machine::{Move, MoveKind, PositionUm};

/// What the machine end needs to know about its machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MachineLinkConfig {
    /// Timers and windows.
    pub link: LinkConfig,
    /// The machine, as its handshake describes it (the boot id drawn at every boot).
    pub machine: MachineDescription,
    /// Send a status report at most this often while executing (µs).
    pub report_interval_us: u64,
}

impl Default for MachineLinkConfig {
    fn default() -> Self {
        Self {
            link: LinkConfig::default(),
            machine: MachineDescription::default(),
            report_interval_us: 50_000,
        }
    }
}

/// Something the machine's firmware (or simulator) must act on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MachineEvent {
    /// A host completed the handshake (new session).
    Connected {
        /// The host's session id.
        session_id: u64,
    },
    /// A priority command: act now. The link has already applied its effect on the queue
    /// and the state (e-stop flushes the queue; hold stops `pop_move`).
    Priority(PriorityCmd),
    /// The host cleared latched faults.
    FaultsCleared,
    /// No valid frame from the host for the link timeout.
    HostLost,
    /// Frames from the host again.
    HostRestored,
}

/// Machine end of the link.
#[derive(Debug)]
pub struct MachineLink {
    cfg: MachineLinkConfig,
    session: Option<u64>,
    decoder: Decoder,
    send: SendStream,
    recv: Receiver,
    queue: VecDeque<Move>,
    status: Status,
    events: VecDeque<MachineEvent>,
    stats: LinkStats,
    last_rx: Micros,
    last_tx: Micros,
    host_lost: bool,
    /// Sequence of the data frame that triggered the pending ack (Ack frame `seq`).
    hello_reply_needed: bool,
    unsynced_needed: bool,
    prio_last: u64,
    prio_ack: Option<u16>,
    report_dirty: bool,
    report_urgent: bool,
    last_report: Micros,
    advertised_credits: u16,
    host_max_frame: usize,
    moves_discarded: u64,
}

impl MachineLink {
    /// A freshly booted machine end. It announces itself with one Unsynced frame so an
    /// idle host learns of the reset at once.
    pub fn new(cfg: MachineLinkConfig, now: Micros) -> Self {
        let status = Status {
            remaining_nl: cfg.machine.capacity_nl.clone(),
            ..Status::default()
        };
        let send = SendStream::new(&cfg.link);
        Self {
            send,
            session: None,
            decoder: Decoder::new(),
            recv: Receiver::default(),
            queue: VecDeque::with_capacity(usize::from(cfg.machine.queue_depth)),
            status,
            events: VecDeque::new(),
            stats: LinkStats::default(),
            last_rx: now,
            last_tx: now,
            host_lost: false,
            hello_reply_needed: false,
            unsynced_needed: true,
            prio_last: 0,
            prio_ack: None,
            report_dirty: false,
            report_urgent: false,
            last_report: now,
            advertised_credits: 0,
            host_max_frame: cfg.link.max_frame,
            moves_discarded: 0,
            cfg,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &MachineLinkConfig {
        &self.cfg
    }

    /// Current status snapshot.
    pub fn status(&self) -> &Status {
        &self.status
    }

    /// Link statistics.
    pub fn stats(&self) -> LinkStats {
        let mut s = self.stats.clone();
        s.srtt_us = self.send.rtt().srtt_us().unwrap_or(0);
        s.rttvar_us = self.send.rtt().rttvar_us();
        s.rto_us = self.send.rtt().rto_us();
        s
    }

    /// Moves waiting in the queue.
    pub fn queue_len(&self) -> usize {
        self.queue.len()
    }

    /// Free queue slots (the credits the host gets).
    pub fn queue_free(&self) -> u16 {
        self.cfg
            .machine
            .queue_depth
            .saturating_sub(self.queue.len().min(u16::MAX as usize) as u16)
    }

    /// Moves discarded because they arrived during an emergency stop.
    pub fn moves_discarded(&self) -> u64 {
        self.moves_discarded
    }

    /// Whether a host session is established.
    pub fn is_synced(&self) -> bool {
        self.session.is_some()
    }

    /// Next event.
    pub fn poll_event(&mut self) -> Option<MachineEvent> {
        self.events.pop_front()
    }

    /// Next move to execute, unless held, e-stopped or faulted. Each move received is
    /// returned exactly once.
    pub fn pop_move(&mut self) -> Option<Move> {
        match self.status.state {
            MachineState::Held | MachineState::EStopped | MachineState::Faulted => return None,
            MachineState::Idle | MachineState::Running => {}
        }
        let m = self.queue.pop_front()?;
        if self.status.state == MachineState::Idle {
            self.set_state(MachineState::Running);
        }
        let free = self.queue_free();
        let step = (self.cfg.machine.queue_depth / 4).max(1);
        if self.advertised_credits == 0 || free >= self.advertised_credits.saturating_add(step) {
            self.recv.owe_ack();
        }
        Some(m)
    }

    /// The executor finished `mv`: update the report (position, remaining volumes) and
    /// check the order (a duplicate or a skipped index is counted in the status).
    pub fn move_done(&mut self, mv: &Move, position: PositionUm, remaining_nl: &[u32]) {
        let s = &mut self.status;
        if let Some(last) = s.last_executed {
            if last.job_id == mv.job_id {
                if mv.index <= last.index {
                    s.duplicates += 1;
                } else if mv.index > last.index + 1 {
                    s.gaps += 1;
                }
            }
        }
        s.last_executed = Some(MoveRef {
            job_id: mv.job_id,
            index: mv.index,
        });
        s.executed_total += 1;
        s.position = position;
        s.remaining_nl.clear();
        s.remaining_nl.extend_from_slice(remaining_nl);
        self.report_dirty = true;
        if matches!(mv.kind, MoveKind::LayerMark { .. } | MoveKind::Home) {
            self.report_urgent = true;
        }
        if self.queue.is_empty() && self.status.state == MachineState::Running {
            self.set_state(MachineState::Idle);
        }
    }

    /// Latch a fault, stop execution, and report it.
    pub fn fault(&mut self, kind: FaultKind) {
        self.status.faults |= kind.bit();
        let report = FaultReport {
            kind,
            at: self.status.last_executed,
        };
        if let Ok(bytes) = postcard::to_allocvec(&MachineMsg::Fault(report)) {
            self.send.push(bytes, 1, false);
        }
        if kind == FaultKind::EStopPressed {
            self.queue.clear();
            self.set_state(MachineState::EStopped);
        } else {
            self.set_state(MachineState::Faulted);
        }
    }

    fn set_state(&mut self, st: MachineState) {
        if self.status.state != st {
            self.status.state = st;
            self.report_dirty = true;
            self.report_urgent = true;
        }
    }

    /// Earliest time to call [`MachineLink::handle_timeout`].
    pub fn next_timeout(&self) -> Option<Micros> {
        let mut t: Option<Micros> = None;
        let mut consider = |x: Micros| t = Some(t.map_or(x, |t| t.min(x)));
        if self.session.is_some() {
            if let Some(d) = self.send.rto_deadline() {
                consider(d);
            }
            consider(self.last_tx.plus_us(self.cfg.link.heartbeat_interval_us));
            if !self.host_lost {
                consider(self.last_rx.plus_us(self.cfg.link.link_timeout_us));
            }
            if self.report_dirty {
                consider(self.last_report.plus_us(self.cfg.report_interval_us));
            }
        }
        t
    }

    /// Run timers.
    pub fn handle_timeout(&mut self, now: Micros) {
        if self.session.is_none() {
            return;
        }
        self.send.on_timeout(now, &mut self.stats);
        if !self.host_lost && now.since(self.last_rx) >= self.cfg.link.link_timeout_us {
            self.host_lost = true;
            self.events.push_back(MachineEvent::HostLost);
        }
    }

    /// Feed bytes from the port.
    pub fn handle_bytes(&mut self, bytes: &[u8], now: Micros) {
        for frame in read_frames(&mut self.decoder, bytes, &mut self.stats) {
            match frame {
                Some(f) => self.on_frame(f, now),
                None if self.session.is_some() => self.recv.on_corrupt(),
                None => {}
            }
        }
    }

    fn on_frame(&mut self, f: Frame, now: Micros) {
        self.last_rx = now;
        if self.host_lost {
            self.host_lost = false;
            self.events.push_back(MachineEvent::HostRestored);
        }
        match f.kind {
            FrameKind::Priority => {
                if let Ok(cmd) = postcard::from_bytes::<PriorityCmd>(&f.body) {
                    let seq = extend_seq(f.seq, self.prio_last);
                    // E-stop acts every time it is seen, whatever its number; hold and
                    // resume only when newer than the last one (a late duplicate of a
                    // resume must never undo a later stop).
                    if cmd == PriorityCmd::EmergencyStop || seq > self.prio_last {
                        self.apply_priority(cmd);
                    }
                    self.prio_last = self.prio_last.max(seq);
                    self.prio_ack = Some(f.seq);
                } else {
                    self.stats.frames_invalid += 1;
                }
            }
            FrameKind::Hello => {
                let Ok(hello) = postcard::from_bytes::<Hello>(&f.body) else {
                    self.stats.frames_invalid += 1;
                    return;
                };
                if self.session != Some(hello.session_id) {
                    // New session: fresh sequence spaces, the queue is kept.
                    self.session = Some(hello.session_id);
                    self.send = SendStream::new(&self.cfg.link);
                    self.recv.restart();
                    self.prio_last = 0;
                    self.host_max_frame = usize::from(hello.max_frame).min(super::MAX_FRAME);
                    self.send
                        .set_peer_limits(usize::from(u16::MAX), self.host_max_frame);
                    self.events.push_back(MachineEvent::Connected {
                        session_id: hello.session_id,
                    });
                }
                self.send
                    .on_ack(f.ack, f.credits, None, now, &mut self.stats);
                // Always answer, whatever the version: the host decides on a mismatch.
                self.hello_reply_needed = true;
            }
            _ if self.session.is_none() => {
                self.unsynced_needed = true;
            }
            FrameKind::Ack => {
                self.send
                    .on_ack(f.ack, f.credits, Some(f.seq), now, &mut self.stats);
            }
            FrameKind::Nak => {
                let trigger = (f.seq != f.ack).then_some(f.seq);
                self.send
                    .on_nak(f.ack, trigger, f.credits, now, &mut self.stats);
            }
            FrameKind::Heartbeat => {
                self.send
                    .on_ack(f.ack, f.credits, None, now, &mut self.stats);
            }
            FrameKind::Data => {
                self.send
                    .on_ack(f.ack, f.credits, None, now, &mut self.stats);
                for body in self.recv.on_data(f.seq, f.body, &mut self.stats) {
                    match decode_body::<HostMsg>(&body) {
                        Ok(msgs) => {
                            for m in msgs {
                                self.on_host_msg(m);
                            }
                        }
                        Err(_) => self.fault(FaultKind::BadMessage),
                    }
                }
            }
            // Machine-to-host kinds arriving here are ignored.
            FrameKind::PriorityAck | FrameKind::HelloReply | FrameKind::Unsynced => {}
        }
    }

    fn apply_priority(&mut self, cmd: PriorityCmd) {
        match cmd {
            PriorityCmd::EmergencyStop => {
                self.queue.clear();
                self.set_state(MachineState::EStopped);
                self.recv.owe_ack();
            }
            PriorityCmd::FeedHold => {
                if matches!(
                    self.status.state,
                    MachineState::Idle | MachineState::Running
                ) {
                    self.set_state(MachineState::Held);
                }
            }
            PriorityCmd::Resume => {
                if matches!(
                    self.status.state,
                    MachineState::Held | MachineState::EStopped
                ) {
                    self.set_state(if self.queue.is_empty() {
                        MachineState::Idle
                    } else {
                        MachineState::Running
                    });
                }
            }
        }
        self.events.push_back(MachineEvent::Priority(cmd));
    }

    fn on_host_msg(&mut self, m: HostMsg) {
        match m {
            HostMsg::Move(mv) => {
                if self.status.state == MachineState::EStopped {
                    self.moves_discarded += 1;
                } else if mv.validate(self.cfg.machine.barrel_area_um2.len()).is_err() {
                    self.fault(FaultKind::BadMove);
                } else if self.queue.len() >= usize::from(self.cfg.machine.queue_depth) {
                    self.fault(FaultKind::QueueOverflow);
                } else {
                    self.queue.push_back(mv);
                }
            }
            HostMsg::Query => {
                self.report_dirty = true;
                self.report_urgent = true;
            }
            HostMsg::ClearFaults => {
                self.status.faults = 0;
                if self.status.state == MachineState::Faulted {
                    self.set_state(MachineState::Idle);
                }
                self.events.push_back(MachineEvent::FaultsCleared);
            }
        }
    }

    fn frame(&mut self, kind: FrameKind, seq: u16, body: Vec<u8>, now: Micros) -> Transmit {
        let credits = self.queue_free();
        let frame = Frame {
            kind,
            seq,
            ack: self.recv.expected_wire(),
            credits,
            body,
        };
        let mut bytes = Vec::with_capacity(frame.body.len() + 16);
        encode_frame(&frame, &mut bytes);
        self.stats.bytes_sent += bytes.len() as u64;
        self.stats.frames_sent += 1;
        self.last_tx = now;
        self.advertised_credits = credits;
        self.recv.sent();
        Transmit { bytes, kind }
    }

    fn hello_reply(&self) -> HelloReply {
        let mut machine = self.cfg.machine.clone();
        while machine.identity.len() > 64 {
            machine.identity.pop();
        }
        let mut status = self.status.clone();
        status.queued = self.queue.len().min(u16::MAX as usize) as u16;
        HelloReply {
            protocol_version: PROTOCOL_VERSION,
            session_id: self.session.unwrap_or(0),
            machine,
            max_frame: self.cfg.link.max_frame.min(super::MAX_FRAME) as u16,
            status,
        }
    }

    /// Next frame to write, in priority order: priority ack, handshake, nak,
    /// retransmission/new report, ack, heartbeat.
    pub fn poll_transmit(&mut self, now: Micros) -> Option<Transmit> {
        self.handle_timeout(now);
        if let Some(seq) = self.prio_ack.take() {
            return Some(self.frame(FrameKind::PriorityAck, seq, Vec::new(), now));
        }
        if self.hello_reply_needed {
            self.hello_reply_needed = false;
            let body = postcard::to_allocvec(&self.hello_reply()).unwrap_or_default();
            return Some(self.frame(FrameKind::HelloReply, 0, body, now));
        }
        if self.session.is_none() {
            if self.unsynced_needed {
                self.unsynced_needed = false;
                let body = self.cfg.machine.boot_id.to_le_bytes().to_vec();
                return Some(self.frame(FrameKind::Unsynced, 0, body, now));
            }
            return None;
        }
        if let Some(seq) = self.recv.take_nak(&mut self.stats) {
            return Some(self.frame(FrameKind::Nak, seq, Vec::new(), now));
        }
        if self.report_dirty
            && (self.report_urgent || now.since(self.last_report) >= self.cfg.report_interval_us)
        {
            self.report_dirty = false;
            self.report_urgent = false;
            self.last_report = now;
            let mut status = self.status.clone();
            status.queued = self.queue.len().min(u16::MAX as usize) as u16;
            if let Ok(bytes) = postcard::to_allocvec(&MachineMsg::Status(status)) {
                self.send.push(bytes, 1, true);
            }
        }
        if let Some(out) = self.send.poll(now, &mut self.stats) {
            return Some(self.frame(FrameKind::Data, out.seq, out.body, now));
        }
        if let Some(seq) = self.recv.ack_owed() {
            return Some(self.frame(FrameKind::Ack, seq, Vec::new(), now));
        }
        if now.since(self.last_tx) >= self.cfg.link.heartbeat_interval_us {
            let body = self.cfg.machine.boot_id.to_le_bytes().to_vec();
            return Some(self.frame(FrameKind::Heartbeat, 0, body, now));
        }
        None
    }
}
