//! The host end of the link (sans-IO).

use std::collections::VecDeque;

use super::frame::{encode_frame, Decoder, Frame, FrameKind};
use super::msg::{
    FaultReport, Hello, HelloReply, HostMsg, MachineDescription, MachineMsg, MoveRef, PriorityCmd,
    Status, PROTOCOL_VERSION,
};
use super::stream::{decode_body, extend_seq, read_frames, Receiver, SendStream};
use super::{LinkConfig, LinkStats, Micros, Transmit};
use crate::machine::{Move, MoveError};

/// What the machine told us in the handshake.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MachineInfo {
    /// Machine's protocol version.
    pub protocol_version: u16,
    /// The machine, as its handshake described it.
    pub machine: MachineDescription,
    /// Largest frame the machine accepts.
    pub max_frame: u16,
    /// Status at handshake: the last executed move tells a restarted host where it is.
    pub status: Status,
}

/// Where the host end is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HostState {
    /// Sending Hello until the machine answers.
    Connecting,
    /// Streaming.
    Connected,
    /// The machine reset (or lost our session); nothing is streamed until
    /// [`Host::reconnect`]. Never resumes silently.
    Reset,
    /// The machine speaks another protocol version.
    Incompatible,
}

/// Something the caller must know.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum HostEvent {
    /// Handshake done.
    Connected(MachineInfo),
    /// A status report (in order, exactly once).
    Status(Status),
    /// A fault report.
    Fault(FaultReport),
    /// The machine rebooted (boot id changed) or lost our session. Moves queued or in
    /// flight were dropped; `last_executed` is the last move it reported executed.
    MachineReset {
        /// Boot id from the handshake.
        previous_boot_id: u64,
        /// Boot id the machine reports now.
        boot_id: u64,
        /// Last executed move reported before the reset.
        last_executed: Option<MoveRef>,
        /// Moves the host had queued or in flight and dropped.
        moves_dropped: u64,
    },
    /// No valid frame for `LinkConfig::link_timeout_us`.
    LinkLost {
        /// How long the line has been silent (µs).
        silent_us: u64,
    },
    /// Valid frames arrive again after `LinkLost` (same boot id, same session).
    LinkRestored,
    /// The machine confirmed a priority command.
    PriorityAcked(PriorityCmd),
    /// The machine's protocol version differs from ours.
    Incompatible {
        /// Version the machine speaks.
        machine_version: u16,
    },
}

/// Errors of the host API.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HostError {
    /// Moves can only be queued while connected.
    #[error("link is not connected (state {0:?})")]
    NotConnected(HostState),
    /// The move does not fit this machine.
    #[error(transparent)]
    Move(#[from] MoveError),
    /// The move did not encode.
    #[error("move {job_id}/{index} does not encode: {reason}")]
    Encode {
        /// Job id.
        job_id: u32,
        /// Index.
        index: u32,
        /// Encoder message.
        reason: String,
    },
}

#[derive(Debug)]
struct PriorityOut {
    seq: u64,
    cmd: PriorityCmd,
    next_send: Micros,
}

/// Host end of the link. See the module docs of [`crate::link`] for the driving loop.
#[derive(Debug)]
pub struct Host {
    cfg: LinkConfig,
    session_id: u64,
    state: HostState,
    decoder: Decoder,
    send: SendStream,
    recv: Receiver,
    events: VecDeque<HostEvent>,
    stats: LinkStats,
    info: Option<MachineInfo>,
    last_executed: Option<MoveRef>,
    last_rx: Micros,
    last_tx: Micros,
    link_lost: bool,
    next_hello: Micros,
    /// Sequence of the data frame that triggered the pending ack (Ack frame `seq`).
    prio: VecDeque<PriorityOut>,
    prio_next: u64,
    /// Reports we are willing to buffer (our credits to the machine).
    report_credits: u16,
}

impl Host {
    /// A host end that starts the handshake at `now`. `session_id` must differ between
    /// host runs (draw it from a random source or the wall clock in the driver).
    pub fn new(cfg: LinkConfig, session_id: u64, now: Micros) -> Self {
        let send = SendStream::new(&cfg);
        Self {
            cfg,
            session_id,
            state: HostState::Connecting,
            decoder: Decoder::new(),
            send,
            recv: Receiver::default(),
            events: VecDeque::new(),
            stats: LinkStats::default(),
            info: None,
            last_executed: None,
            last_rx: now,
            last_tx: now,
            link_lost: false,
            next_hello: now,
            prio: VecDeque::new(),
            prio_next: 1,
            report_credits: 1024,
        }
    }

    /// Start a fresh handshake (after [`HostEvent::MachineReset`] or link loss) with a new
    /// session id. Everything not yet acknowledged is dropped.
    pub fn reconnect(&mut self, session_id: u64, now: Micros) {
        let events = std::mem::take(&mut self.events);
        let stats = std::mem::take(&mut self.stats);
        let last = self.last_executed;
        *self = Host::new(self.cfg.clone(), session_id, now);
        self.events = events;
        self.stats = stats;
        self.last_executed = last;
    }

    /// Current state.
    pub fn state(&self) -> HostState {
        self.state
    }

    /// Handshake data, once connected.
    pub fn machine_info(&self) -> Option<&MachineInfo> {
        self.info.as_ref()
    }

    /// Last executed move the machine reported.
    pub fn last_executed(&self) -> Option<MoveRef> {
        self.last_executed
    }

    /// Whether the link is currently considered lost.
    pub fn is_link_lost(&self) -> bool {
        self.link_lost
    }

    /// Statistics, with the current RTT estimate.
    pub fn stats(&self) -> LinkStats {
        let mut s = self.stats.clone();
        s.srtt_us = self.send.rtt().srtt_us().unwrap_or(0);
        s.rttvar_us = self.send.rtt().rttvar_us();
        s.rto_us = self.send.rtt().rto_us();
        s
    }

    /// Messages queued but not yet framed.
    pub fn pending(&self) -> usize {
        self.send.pending_len()
    }

    /// Moves framed and sent but not yet acknowledged.
    pub fn moves_in_flight(&self) -> u64 {
        self.send.slots_in_flight()
    }

    /// Data frames sent but not yet acknowledged.
    pub fn frames_in_flight(&self) -> usize {
        self.send.unacked_len()
    }

    /// Queue a move. It goes out when the window and the machine's credits allow.
    pub fn send_move(&mut self, mv: Move) -> Result<(), HostError> {
        if self.state != HostState::Connected {
            return Err(HostError::NotConnected(self.state));
        }
        if let Some(info) = &self.info {
            mv.validate(info.machine.barrel_area_um2.len())?;
        }
        let (job_id, index) = (mv.job_id, mv.index);
        let bytes = postcard::to_allocvec(&HostMsg::Move(mv)).map_err(|e| HostError::Encode {
            job_id,
            index,
            reason: e.to_string(),
        })?;
        self.send.push(bytes, 1, false);
        Ok(())
    }

    /// Ask the machine for a status report.
    pub fn query(&mut self) -> Result<(), HostError> {
        self.send_msg(&HostMsg::Query)
    }

    /// Clear latched machine faults.
    pub fn clear_faults(&mut self) -> Result<(), HostError> {
        self.send_msg(&HostMsg::ClearFaults)
    }

    fn send_msg(&mut self, msg: &HostMsg) -> Result<(), HostError> {
        if self.state != HostState::Connected {
            return Err(HostError::NotConnected(self.state));
        }
        let bytes = postcard::to_allocvec(msg).map_err(|e| HostError::Encode {
            job_id: 0,
            index: 0,
            reason: e.to_string(),
        })?;
        self.send.push(bytes, 0, false);
        Ok(())
    }

    /// Send a priority command ahead of everything queued. It is repeated every RTO until
    /// the machine acknowledges it. An emergency stop also drops the moves still waiting
    /// in the host (returned: how many); moves already in flight are discarded by the
    /// machine.
    pub fn priority(&mut self, cmd: PriorityCmd, now: Micros) -> usize {
        let seq = self.prio_next;
        self.prio_next += 1;
        self.prio.push_back(PriorityOut {
            seq,
            cmd,
            next_send: now,
        });
        if cmd == PriorityCmd::EmergencyStop {
            self.send.drop_pending()
        } else {
            0
        }
    }

    /// Earliest time the caller must call [`Host::handle_timeout`] (or `poll_transmit`).
    pub fn next_timeout(&self) -> Option<Micros> {
        let mut t: Option<Micros> = None;
        let mut consider = |x: Micros| t = Some(t.map_or(x, |t| t.min(x)));
        for p in &self.prio {
            consider(p.next_send);
        }
        match self.state {
            HostState::Connecting => consider(self.next_hello),
            HostState::Connected => {
                if let Some(d) = self.send.rto_deadline() {
                    consider(d);
                }
                consider(self.last_tx.plus_us(self.cfg.heartbeat_interval_us));
                if !self.link_lost {
                    consider(self.last_rx.plus_us(self.cfg.link_timeout_us));
                }
            }
            HostState::Reset | HostState::Incompatible => {}
        }
        t
    }

    /// Run timers: retransmission timeout, link-loss detection.
    pub fn handle_timeout(&mut self, now: Micros) {
        if self.state != HostState::Connected {
            return;
        }
        self.send.on_timeout(now, &mut self.stats);
        let silent = now.since(self.last_rx);
        if !self.link_lost && silent >= self.cfg.link_timeout_us {
            self.link_lost = true;
            self.events
                .push_back(HostEvent::LinkLost { silent_us: silent });
        }
    }

    /// Next event for the caller.
    pub fn poll_event(&mut self) -> Option<HostEvent> {
        self.events.pop_front()
    }

    /// Feed bytes read from the port.
    pub fn handle_bytes(&mut self, bytes: &[u8], now: Micros) {
        for frame in read_frames(&mut self.decoder, bytes, &mut self.stats) {
            match frame {
                Some(f) => self.on_frame(f, now),
                None if self.state == HostState::Connected => self.recv.on_corrupt(),
                None => {}
            }
        }
    }

    fn machine_reset(&mut self, boot_id: u64) {
        let previous_boot_id = self.info.as_ref().map_or(0, |i| i.machine.boot_id);
        let in_flight = self.send.slots_in_flight();
        let (pending, _) = self.send.clear();
        self.state = HostState::Reset;
        self.prio.retain(|p| p.cmd == PriorityCmd::EmergencyStop);
        self.events.push_back(HostEvent::MachineReset {
            previous_boot_id,
            boot_id,
            last_executed: self.last_executed,
            moves_dropped: pending as u64 + in_flight,
        });
    }

    fn on_frame(&mut self, f: Frame, now: Micros) {
        self.last_rx = now;
        if self.link_lost && self.state == HostState::Connected {
            self.link_lost = false;
            self.events.push_back(HostEvent::LinkRestored);
        }
        match f.kind {
            FrameKind::HelloReply => self.on_hello_reply(&f, now),
            FrameKind::Unsynced | FrameKind::Heartbeat => {
                let boot_id = read_u64(&f.body);
                let known = self.info.as_ref().map(|i| i.machine.boot_id);
                match (self.state, f.kind) {
                    (HostState::Connected, FrameKind::Unsynced) => {
                        self.machine_reset(boot_id.unwrap_or(0));
                    }
                    (HostState::Connected, _) => {
                        if boot_id.is_some() && boot_id != known {
                            self.machine_reset(boot_id.unwrap_or(0));
                        } else {
                            self.send
                                .on_ack(f.ack, f.credits, None, now, &mut self.stats);
                        }
                    }
                    _ => {}
                }
            }
            FrameKind::PriorityAck => {
                let acked = extend_seq(f.seq, self.prio_next.saturating_sub(1));
                while let Some(p) = self.prio.front() {
                    if p.seq <= acked {
                        let cmd = p.cmd;
                        self.prio.pop_front();
                        self.events.push_back(HostEvent::PriorityAcked(cmd));
                    } else {
                        break;
                    }
                }
            }
            FrameKind::Ack if self.state == HostState::Connected => {
                self.send
                    .on_ack(f.ack, f.credits, Some(f.seq), now, &mut self.stats);
            }
            FrameKind::Nak if self.state == HostState::Connected => {
                let trigger = (f.seq != f.ack).then_some(f.seq);
                self.send
                    .on_nak(f.ack, trigger, f.credits, now, &mut self.stats);
            }
            FrameKind::Data if self.state == HostState::Connected => {
                self.send
                    .on_ack(f.ack, f.credits, None, now, &mut self.stats);
                for body in self.recv.on_data(f.seq, f.body, &mut self.stats) {
                    match decode_body::<MachineMsg>(&body) {
                        Ok(msgs) => {
                            for m in msgs {
                                self.on_machine_msg(m);
                            }
                        }
                        Err(_) => self.stats.frames_invalid += 1,
                    }
                }
            }
            // Frames a host never receives, or not in this state: ignore.
            _ => {}
        }
    }

    fn on_hello_reply(&mut self, f: &Frame, now: Micros) {
        let Ok(reply) = postcard::from_bytes::<HelloReply>(&f.body) else {
            self.stats.frames_invalid += 1;
            return;
        };
        if reply.session_id != self.session_id {
            return; // an answer to an older session
        }
        if self.state == HostState::Connected {
            // A duplicate reply; a changed boot id means a reset.
            if self.info.as_ref().map(|i| i.machine.boot_id) != Some(reply.machine.boot_id) {
                self.machine_reset(reply.machine.boot_id);
            }
            return;
        }
        if self.state != HostState::Connecting {
            return;
        }
        if reply.protocol_version != PROTOCOL_VERSION {
            self.state = HostState::Incompatible;
            self.events.push_back(HostEvent::Incompatible {
                machine_version: reply.protocol_version,
            });
            return;
        }
        self.send.set_peer_limits(
            reply.machine.rx_buffer_bytes as usize,
            usize::from(reply.max_frame).min(super::MAX_FRAME),
        );
        self.send
            .on_ack(f.ack, f.credits, None, now, &mut self.stats);
        self.last_executed = reply.status.last_executed;
        let info = MachineInfo {
            protocol_version: reply.protocol_version,
            machine: reply.machine,
            max_frame: reply.max_frame,
            status: reply.status,
        };
        self.info = Some(info.clone());
        self.state = HostState::Connected;
        self.events.push_back(HostEvent::Connected(info));
    }

    fn on_machine_msg(&mut self, m: MachineMsg) {
        match m {
            MachineMsg::Status(s) => {
                if s.last_executed.is_some() {
                    self.last_executed = s.last_executed;
                }
                self.events.push_back(HostEvent::Status(s));
            }
            MachineMsg::Fault(f) => self.events.push_back(HostEvent::Fault(f)),
        }
    }

    fn frame(&mut self, kind: FrameKind, seq: u16, body: Vec<u8>, now: Micros) -> Transmit {
        let credits = self
            .report_credits
            .saturating_sub(self.events.len().min(u16::MAX as usize) as u16);
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
        self.recv.sent();
        Transmit { bytes, kind }
    }

    /// Next frame to write to the port, in priority order: priority lane, handshake,
    /// nak, retransmissions, new data, ack, heartbeat.
    pub fn poll_transmit(&mut self, now: Micros) -> Option<Transmit> {
        self.handle_timeout(now);
        let rto = self.send.rtt().rto_us();
        if let Some(p) = self.prio.iter_mut().find(|p| p.next_send <= now) {
            p.next_send = now.plus_us(rto);
            let (seq, cmd) = (p.seq as u16, p.cmd);
            let body = postcard::to_allocvec(&cmd).unwrap_or_default();
            return Some(self.frame(FrameKind::Priority, seq, body, now));
        }
        match self.state {
            HostState::Connecting => {
                if now >= self.next_hello {
                    self.next_hello = now.plus_us(self.cfg.hello_interval_us);
                    let hello = Hello {
                        protocol_version: PROTOCOL_VERSION,
                        session_id: self.session_id,
                        max_frame: self.cfg.max_frame as u16,
                    };
                    let body = postcard::to_allocvec(&hello).unwrap_or_default();
                    return Some(self.frame(FrameKind::Hello, 0, body, now));
                }
                None
            }
            HostState::Connected => {
                if let Some(seq) = self.recv.take_nak(&mut self.stats) {
                    return Some(self.frame(FrameKind::Nak, seq, Vec::new(), now));
                }
                if let Some(out) = self.send.poll(now, &mut self.stats) {
                    return Some(self.frame(FrameKind::Data, out.seq, out.body, now));
                }
                if let Some(seq) = self.recv.ack_owed() {
                    return Some(self.frame(FrameKind::Ack, seq, Vec::new(), now));
                }
                if now.since(self.last_tx) >= self.cfg.heartbeat_interval_us {
                    let body = self.session_id.to_le_bytes().to_vec();
                    return Some(self.frame(FrameKind::Heartbeat, 0, body, now));
                }
                None
            }
            HostState::Reset | HostState::Incompatible => None,
        }
    }
}

fn read_u64(body: &[u8]) -> Option<u64> {
    let b: [u8; 8] = body.get(..8)?.try_into().ok()?;
    Some(u64::from_le_bytes(b))
}
