//! The reliable, in-order half of the link, used in both directions: a selective-repeat sender
//! with an RFC 6298 retransmission timer, fast retransmit, a window in frames, bytes and
//! credits; and a receiver that delivers each sequence number exactly once.

use std::collections::VecDeque;

use super::frame::{wire_len, Decoder, Frame, CRC_LEN, HEADER_LEN};
use super::{LinkConfig, LinkStats, Micros};

/// Extend a 16-bit wire sequence number to the 64-bit one nearest `reference`.
pub(crate) fn extend_seq(wire: u16, reference: u64) -> u64 {
    let base = reference & !0xFFFF;
    let cand = base | u64::from(wire);
    // Pick among cand - 2^16, cand, cand + 2^16 the one closest to reference.
    let mut best = cand;
    for c in [cand.wrapping_sub(1 << 16), cand.wrapping_add(1 << 16)] {
        if c.abs_diff(reference) < best.abs_diff(reference) {
            best = c;
        }
    }
    best
}

/// RFC 6298 round-trip estimator. All times in µs.
#[derive(Debug, Clone)]
pub(crate) struct Rtt {
    srtt_us: Option<u64>,
    rttvar_us: u64,
    rto_us: u64,
    min_rto_us: u64,
    max_rto_us: u64,
    granularity_us: u64,
}

impl Rtt {
    pub(crate) fn new(cfg: &LinkConfig) -> Self {
        Self {
            srtt_us: None,
            rttvar_us: 0,
            rto_us: cfg.initial_rto_us.clamp(cfg.min_rto_us, cfg.max_rto_us),
            min_rto_us: cfg.min_rto_us,
            max_rto_us: cfg.max_rto_us,
            granularity_us: cfg.clock_granularity_us,
        }
    }

    /// RFC 6298 §2.2/2.3: fold in a sample taken from a frame sent once (Karn).
    pub(crate) fn sample(&mut self, r_us: u64) {
        match self.srtt_us {
            None => {
                self.srtt_us = Some(r_us);
                self.rttvar_us = r_us / 2;
            }
            Some(srtt) => {
                self.rttvar_us = (3 * self.rttvar_us + srtt.abs_diff(r_us)) / 4;
                self.srtt_us = Some((7 * srtt + r_us) / 8);
            }
        }
        let srtt = self.srtt_us.unwrap_or(r_us);
        self.rto_us = (srtt + self.granularity_us.max(4 * self.rttvar_us))
            .clamp(self.min_rto_us, self.max_rto_us);
    }

    /// RFC 6298 §5.5: back off after a timeout.
    pub(crate) fn backoff(&mut self) {
        self.rto_us = (self.rto_us * 2).min(self.max_rto_us);
    }

    pub(crate) fn rto_us(&self) -> u64 {
        self.rto_us
    }

    pub(crate) fn srtt_us(&self) -> Option<u64> {
        self.srtt_us
    }

    pub(crate) fn rttvar_us(&self) -> u64 {
        self.rttvar_us
    }
}

#[derive(Debug)]
struct InFlight {
    seq: u64,
    body: Vec<u8>,
    wire_bytes: usize,
    payload_bytes: usize,
    /// Cumulative credit-consuming messages up to and including this frame.
    slots_end: u64,
    sent_at: Micros,
    /// Order of the latest transmission of this frame among all transmissions.
    tx_order: u64,
    retransmitted: bool,
    /// Queued for retransmission and not yet resent.
    queued: bool,
}

/// One encoded message waiting to be framed.
#[derive(Debug)]
struct Pending {
    bytes: Vec<u8>,
    slots: u64,
    /// Replaceable (a status snapshot superseded by a newer one).
    replaceable: bool,
}

/// A frame body the sender wants on the wire now.
#[derive(Debug)]
pub(crate) struct Outgoing {
    pub seq: u16,
    pub body: Vec<u8>,
}

/// What the sender learnt from an ack.
#[derive(Debug, Default, PartialEq, Eq)]
pub(crate) struct AckOutcome {
    /// Frames newly acknowledged.
    pub newly_acked: u64,
}

/// Selective-repeat sender.
#[derive(Debug)]
pub(crate) struct SendStream {
    next_seq: u64,
    una: u64,
    unacked: VecDeque<InFlight>,
    unacked_wire_bytes: usize,
    /// Frames to retransmit (selective repeat), oldest first.
    resend: VecDeque<u64>,
    pending: VecDeque<Pending>,
    pending_bytes: usize,
    rtt: Rtt,
    rto_deadline: Option<Micros>,
    dup_acks: u32,
    /// Counter of transmissions (first and repeated), to tell whether a nak was caused by a frame sent after a retransmission.
    tx_counter: u64,
    /// Current frame size limit: shrinks on loss, grows back on clean runs (adaptive
    /// framing, `docs/protocol.md` "Frame size").
    frame_budget: usize,
    min_frame: usize,
    clean_frames: u32,
    last_credits: u16,
    slots_sent: u64,
    slots_acked: u64,
    slot_limit: u64,
    max_frames: usize,
    max_bytes: usize,
    /// This end's own cap (`LinkConfig::max_bytes_in_flight`).
    own_max_bytes: usize,
    max_frame: usize,
    dup_ack_threshold: u32,
}

impl SendStream {
    pub(crate) fn new(cfg: &LinkConfig) -> Self {
        Self {
            next_seq: 0,
            una: 0,
            unacked: VecDeque::new(),
            unacked_wire_bytes: 0,
            resend: VecDeque::new(),
            pending: VecDeque::new(),
            pending_bytes: 0,
            rtt: Rtt::new(cfg),
            rto_deadline: None,
            dup_acks: 0,
            tx_counter: 0,
            frame_budget: cfg.max_frame,
            min_frame: cfg.min_frame.min(cfg.max_frame),
            clean_frames: 0,
            last_credits: 0,
            slots_sent: 0,
            slots_acked: 0,
            slot_limit: 0,
            max_frames: cfg.max_frames_in_flight.max(1),
            max_bytes: cfg.max_bytes_in_flight.max(1),
            own_max_bytes: cfg.max_bytes_in_flight.max(1),
            max_frame: cfg.max_frame,
            dup_ack_threshold: cfg.dup_ack_threshold,
        }
    }

    /// Set the peer's limits learnt in the handshake.
    pub(crate) fn set_peer_limits(&mut self, rx_buffer_bytes: usize, max_frame: usize) {
        self.max_bytes = rx_buffer_bytes.max(1).min(self.own_max_bytes);
        self.max_frame = self.max_frame.min(max_frame);
        self.frame_budget = self.frame_budget.min(self.max_frame);
        self.min_frame = self.min_frame.min(self.max_frame);
    }

    pub(crate) fn set_credits(&mut self, ack: u64, credits: u16) {
        // Credits count from the messages the receiver holds: everything before `ack`.
        let acked_slots = if ack == self.una {
            self.slots_acked
        } else {
            return;
        };
        self.slot_limit = acked_slots + u64::from(credits);
    }

    /// Queue an encoded message; `slots` = credits it consumes (1 for a move).
    pub(crate) fn push(&mut self, bytes: Vec<u8>, slots: u64, replaceable: bool) {
        if replaceable {
            if let Some(last) = self.pending.iter_mut().rev().find(|p| p.replaceable) {
                self.pending_bytes = self.pending_bytes - last.bytes.len() + bytes.len();
                last.bytes = bytes;
                return;
            }
        }
        self.pending_bytes += bytes.len();
        self.pending.push_back(Pending {
            bytes,
            slots,
            replaceable,
        });
    }

    pub(crate) fn pending_len(&self) -> usize {
        self.pending.len()
    }

    pub(crate) fn unacked_len(&self) -> usize {
        self.unacked.len()
    }

    /// Credit-consuming messages sent but not yet acknowledged.
    pub(crate) fn slots_in_flight(&self) -> u64 {
        self.slots_sent - self.slots_acked
    }

    /// Drop the messages not yet framed; returns how many.
    pub(crate) fn drop_pending(&mut self) -> usize {
        let n = self.pending.len();
        self.pending.clear();
        self.pending_bytes = 0;
        n
    }

    /// Drop everything not yet acknowledged; returns (pending messages, unacked frames).
    pub(crate) fn clear(&mut self) -> (usize, usize) {
        let r = (self.pending.len(), self.unacked.len());
        self.pending.clear();
        self.pending_bytes = 0;
        self.una = self.next_seq;
        self.resend.clear();
        self.unacked.clear();
        self.unacked_wire_bytes = 0;
        self.slots_acked = self.slots_sent;
        self.rto_deadline = None;
        r
    }

    pub(crate) fn rtt(&self) -> &Rtt {
        &self.rtt
    }

    pub(crate) fn rto_deadline(&self) -> Option<Micros> {
        self.rto_deadline
    }

    fn can_send_new(&self) -> bool {
        let Some(first) = self.pending.front() else {
            return false;
        };
        if self.unacked.len() >= self.max_frames {
            return false;
        }
        if self.slots_sent + first.slots > self.slot_limit {
            return false;
        }
        let first_wire = wire_len(HEADER_LEN + 1 + first.bytes.len() + CRC_LEN);
        self.unacked.is_empty() || self.unacked_wire_bytes + first_wire <= self.max_bytes
    }

    /// Next frame body to transmit (retransmissions first), or `None`.
    pub(crate) fn poll(&mut self, now: Micros, stats: &mut LinkStats) -> Option<Outgoing> {
        while let Some(seq) = self.resend.pop_front() {
            if seq < self.una {
                continue; // acknowledged meanwhile
            }
            let Some(f) = self.unacked.get_mut((seq - self.una) as usize) else {
                continue;
            };
            f.queued = false;
            f.retransmitted = true;
            f.sent_at = now;
            self.tx_counter += 1;
            f.tx_order = self.tx_counter;
            stats.frames_retransmitted += 1;
            stats.bytes_retransmitted += f.wire_bytes as u64;
            if self.rto_deadline.is_none() {
                self.rto_deadline = Some(now.plus_us(self.rtt.rto_us()));
            }
            return Some(Outgoing {
                seq: f.seq as u16,
                body: f.body.clone(),
            });
        }
        if !self.can_send_new() {
            return None;
        }
        // Fill one frame: postcard Vec<Msg> = varint(count) ++ messages.
        let budget = self.frame_budget - HEADER_LEN - CRC_LEN;
        let mut msgs: Vec<Pending> = Vec::new();
        let mut size = 0usize;
        let mut slots = 0u64;
        while let Some(p) = self.pending.front() {
            let count_len = varint_len(msgs.len() as u64 + 1);
            if !msgs.is_empty() && count_len + size + p.bytes.len() > budget {
                break;
            }
            if self.slots_sent + slots + p.slots > self.slot_limit {
                break;
            }
            let wire_now = wire_len(HEADER_LEN + count_len + size + p.bytes.len() + CRC_LEN);
            if !msgs.is_empty()
                && !self.unacked.is_empty()
                && self.unacked_wire_bytes + wire_now > self.max_bytes
            {
                break;
            }
            let Some(p) = self.pending.pop_front() else {
                break;
            };
            self.pending_bytes -= p.bytes.len();
            size += p.bytes.len();
            slots += p.slots;
            msgs.push(p);
        }
        if msgs.is_empty() {
            return None;
        }
        let mut body = Vec::with_capacity(size + 2);
        write_varint(msgs.len() as u64, &mut body);
        for m in &msgs {
            body.extend_from_slice(&m.bytes);
        }
        let wire_bytes = wire_len(HEADER_LEN + body.len() + CRC_LEN);
        let seq = self.next_seq;
        self.next_seq += 1;
        self.slots_sent += slots;
        self.unacked_wire_bytes += wire_bytes;
        stats.payload_bytes_sent += size as u64;
        stats.messages_sent += msgs.len() as u64;
        self.unacked.push_back(InFlight {
            seq,
            body: body.clone(),
            wire_bytes,
            payload_bytes: size,
            slots_end: self.slots_sent,
            sent_at: now,
            tx_order: {
                self.tx_counter += 1;
                self.tx_counter
            },
            retransmitted: false,
            queued: false,
        });
        if self.rto_deadline.is_none() {
            self.rto_deadline = Some(now.plus_us(self.rtt.rto_us()));
        }
        Some(Outgoing {
            seq: seq as u16,
            body,
        })
    }

    /// Process a cumulative ack (the next sequence the peer expects) and its credits.
    /// `pure_ack_trigger` is set for standalone Ack frames: the sequence number of the
    /// data frame that triggered the ack. It counts towards fast retransmit only when that
    /// frame lies beyond the ack (it arrived after a hole); acks of duplicates do not.
    pub(crate) fn on_ack(
        &mut self,
        wire_ack: u16,
        credits: u16,
        pure_ack_trigger: Option<u16>,
        now: Micros,
        stats: &mut LinkStats,
    ) -> AckOutcome {
        let ack = extend_seq(wire_ack, self.una);
        if ack < self.una || ack > self.next_seq {
            stats.acks_out_of_range += 1;
            return AckOutcome::default();
        }
        let mut out = AckOutcome::default();
        if ack > self.una {
            let mut newest_clean_sample = None;
            while self.una < ack {
                let Some(f) = self.unacked.pop_front() else {
                    break;
                };
                self.unacked_wire_bytes -= f.wire_bytes;
                self.slots_acked = f.slots_end;
                stats.payload_bytes_acked += f.payload_bytes as u64;
                if !f.retransmitted {
                    newest_clean_sample = Some(now.since(f.sent_at));
                    self.clean_frames += 1;
                    if self.clean_frames >= 16 {
                        // Additive increase after a clean run.
                        self.clean_frames = 0;
                        self.frame_budget = (self.frame_budget + 32).min(self.max_frame);
                    }
                }
                self.una += 1;
                out.newly_acked += 1;
            }
            if let Some(r) = newest_clean_sample {
                self.rtt.sample(r);
            }
            self.dup_acks = 0;
            self.rto_deadline = if self.unacked.is_empty() {
                None
            } else {
                Some(now.plus_us(self.rtt.rto_us()))
            };
        } else if pure_ack_trigger.is_some_and(|t| extend_seq(t, ack) > ack)
            && !self.unacked.is_empty()
            && credits == self.last_credits
        {
            // A duplicate ack: same ack, same window, no data (a window update is not
            // one), triggered by a frame after a hole (an ack of a duplicate is not one).
            self.dup_acks += 1;
            if self.dup_acks >= self.dup_ack_threshold {
                self.dup_acks = 0;
                if self.resend_if_lost(pure_ack_trigger, now) {
                    stats.fast_retransmits += 1;
                }
            }
        }
        self.set_credits(ack, credits);
        self.last_credits = credits;
        out
    }

    /// A nak: the peer expects `wire_ack`; `trigger` is the frame after the hole that
    /// made it send the nak (None for a nak caused by a corrupt frame).
    pub(crate) fn on_nak(
        &mut self,
        wire_ack: u16,
        trigger: Option<u16>,
        credits: u16,
        now: Micros,
        stats: &mut LinkStats,
    ) {
        stats.naks_received += 1;
        self.on_ack(wire_ack, credits, None, now, stats);
        self.resend_if_lost(trigger, now);
    }

    /// Selective repeat: resend the oldest unacked frame if it is lost. It is lost when
    /// the peer received a frame (`trigger`) that we transmitted after the latest
    /// transmission of the oldest one — the line keeps order, so that copy is gone. For a
    /// nak without trigger (corrupt frame) resend when the last copy is older than SRTT.
    /// Returns whether a resend was queued.
    fn resend_if_lost(&mut self, trigger: Option<u16>, now: Micros) -> bool {
        let una = self.una;
        let srtt = self.rtt.srtt_us().unwrap_or(0);
        let trigger_order = trigger.and_then(|t| {
            let t = extend_seq(t, una);
            (t > una && t < self.next_seq)
                .then(|| self.unacked.get((t - una) as usize).map(|f| f.tx_order))
                .flatten()
        });
        let Some(first) = self.unacked.front_mut() else {
            return false;
        };
        if first.queued {
            return false;
        }
        let lost = match trigger_order {
            Some(order) => order > first.tx_order,
            None => trigger.is_none() && now.since(first.sent_at) >= srtt,
        };
        if !lost {
            return false;
        }
        first.queued = true;
        self.resend.push_back(una);
        self.loss_seen();
        true
    }

    fn loss_seen(&mut self) {
        self.clean_frames = 0;
        // Multiplicative decrease of the frame size: on a noisy line shorter frames
        // are hit less often and cost less to resend.
        self.frame_budget = (self.frame_budget * 3 / 4).max(self.min_frame);
    }

    /// The retransmission timer expired: back off and resend the oldest frame.
    pub(crate) fn on_timeout(&mut self, now: Micros, stats: &mut LinkStats) {
        let Some(deadline) = self.rto_deadline else {
            return;
        };
        if now < deadline {
            return;
        }
        if self.unacked.is_empty() {
            self.rto_deadline = None;
            return;
        }
        stats.timeouts += 1;
        self.rtt.backoff();
        // Resend the oldest frame; naks for later holes follow once it arrives.
        if let Some(first) = self.unacked.front_mut() {
            if !first.queued {
                first.queued = true;
                self.resend.push_front(self.una);
            }
        }
        self.loss_seen();
        self.rto_deadline = Some(now.plus_us(self.rtt.rto_us()));
    }
}

/// Outcome of a received Data frame.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Arrival {
    /// Bodies to deliver, in order: the frame and any buffered frames it completes.
    Deliver(Vec<Vec<u8>>),
    /// Already delivered: discard, re-ack.
    Duplicate,
    /// A frame after a hole: buffered (if room); nak if this is the first for this hole,
    /// otherwise a duplicate ack.
    Gap {
        /// Send a nak.
        send_nak: bool,
    },
}

/// Frames after a hole the receiver keeps (≥ `LinkConfig::max_frames_in_flight`).
pub(crate) const REORDER_FRAMES: u64 = 64;

/// In-order receiver with a reorder buffer (selective repeat).
#[derive(Debug, Default)]
pub(crate) struct RecvStream {
    expected: u64,
    nak_sent_for: Option<u64>,
    buffer: std::collections::BTreeMap<u64, Vec<u8>>,
}

impl RecvStream {
    pub(crate) fn expected_wire(&self) -> u16 {
        self.expected as u16
    }

    pub(crate) fn on_data(&mut self, wire_seq: u16, body: Vec<u8>) -> Arrival {
        let seq = extend_seq(wire_seq, self.expected);
        if seq == self.expected {
            let mut out = vec![body];
            self.expected += 1;
            while let Some(b) = self.buffer.remove(&self.expected) {
                out.push(b);
                self.expected += 1;
            }
            self.nak_sent_for = None;
            Arrival::Deliver(out)
        } else if seq < self.expected {
            Arrival::Duplicate
        } else {
            if seq - self.expected < REORDER_FRAMES {
                self.buffer.entry(seq).or_insert(body);
            }
            let send_nak = self.nak_sent_for != Some(self.expected);
            self.nak_sent_for = Some(self.expected);
            Arrival::Gap { send_nak }
        }
    }

    /// After a delivery: if frames wait behind a new hole, the nak trigger (the highest
    /// buffered sequence) to ask for the hole at once.
    pub(crate) fn hole_trigger(&mut self) -> Option<u16> {
        let last = *self.buffer.keys().next_back()?;
        self.nak_sent_for = Some(self.expected);
        Some(last as u16)
    }

    /// A frame failed its CRC: nak once per expected sequence.
    pub(crate) fn on_corrupt(&mut self) -> bool {
        let send = self.nak_sent_for != Some(self.expected);
        self.nak_sent_for = Some(self.expected);
        send
    }
}

/// Bytes read from the port into frames, the same for both ends: each frame they
/// complete, in order, or `None` for one that failed to decode; counted in `stats`.
pub(crate) fn read_frames(
    decoder: &mut Decoder,
    bytes: &[u8],
    stats: &mut LinkStats,
) -> Vec<Option<Frame>> {
    stats.bytes_received += bytes.len() as u64;
    let mut frames = Vec::new();
    let mut frame_bytes = 0u64;
    for &b in bytes {
        frame_bytes += 1;
        match decoder.push(b) {
            None => continue,
            Some(Ok(f)) => {
                stats.frames_received += 1;
                frames.push(Some(f));
            }
            Some(Err(_)) => {
                stats.frames_invalid += 1;
                stats.bytes_invalid += frame_bytes;
                frames.push(None);
            }
        }
        frame_bytes = 0;
    }
    frames
}

/// What one end of the link received and owes for it, the same for both ends: the
/// in-order stream, and the ack and nak it has to send. Each end keeps one and asks it
/// for the frames it owes when it transmits.
#[derive(Debug, Default)]
pub(crate) struct Receiver {
    stream: RecvStream,
    ack_owed: bool,
    /// The sequence the owed ack names: the last data frame received.
    ack_trigger: u16,
    nak_owed: bool,
    /// The sequence the owed nak names: the frame after a gap; none for a bad frame
    /// (the nak then names the expected sequence).
    nak_trigger: Option<u16>,
}

impl Receiver {
    /// The next sequence expected, on the wire (every frame's `ack`).
    pub(crate) fn expected_wire(&self) -> u16 {
        self.stream.expected_wire()
    }

    /// A new session: fresh sequence space (what is owed stays owed, as it always did).
    pub(crate) fn restart(&mut self) {
        self.stream = RecvStream::default();
    }

    /// A frame failed to decode while a session is up: a nak, once per expected frame.
    pub(crate) fn on_corrupt(&mut self) {
        if self.stream.on_corrupt() {
            self.nak_trigger = None;
            self.nak_owed = true;
        }
    }

    /// A data frame: the bodies it brings into order (none for a duplicate or a frame
    /// after a gap), the ack and nak it calls for owed.
    pub(crate) fn on_data(
        &mut self,
        seq: u16,
        body: Vec<u8>,
        stats: &mut LinkStats,
    ) -> Vec<Vec<u8>> {
        self.ack_trigger = seq;
        match self.stream.on_data(seq, body) {
            Arrival::Deliver(bodies) => {
                self.ack_owed = true;
                if let Some(t) = self.stream.hole_trigger() {
                    self.nak_trigger = Some(t);
                    self.nak_owed = true;
                }
                bodies
            }
            Arrival::Duplicate => {
                stats.frames_duplicate += 1;
                self.ack_owed = true;
                Vec::new()
            }
            Arrival::Gap { send_nak } => {
                stats.frames_out_of_order += 1;
                if send_nak {
                    self.nak_trigger = Some(seq);
                    self.nak_owed = true;
                } else {
                    self.ack_owed = true; // a duplicate ack
                }
                Vec::new()
            }
        }
    }

    /// Owe an ack for something other than data (credits freed, a priority command).
    pub(crate) fn owe_ack(&mut self) {
        self.ack_owed = true;
    }

    /// The nak owed, taken: its sequence (the frame after the gap, or the expected one
    /// when the nak is for a bad frame).
    pub(crate) fn take_nak(&mut self, stats: &mut LinkStats) -> Option<u16> {
        if !std::mem::take(&mut self.nak_owed) {
            return None;
        }
        stats.naks_sent += 1;
        Some(self.nak_trigger.take().unwrap_or(self.expected_wire()))
    }

    /// The ack owed: its sequence. Any frame sent carries the ack ([`Receiver::sent`]).
    pub(crate) fn ack_owed(&self) -> Option<u16> {
        self.ack_owed.then_some(self.ack_trigger)
    }

    /// A frame went out: it carried the ack.
    pub(crate) fn sent(&mut self) {
        self.ack_owed = false;
    }
}

pub(crate) fn varint_len(mut v: u64) -> usize {
    let mut n = 1;
    while v >= 0x80 {
        v >>= 7;
        n += 1;
    }
    n
}

fn write_varint(mut v: u64, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Split a Data body (postcard `Vec<T>`) into messages.
pub(crate) fn decode_body<T: serde::de::DeserializeOwned>(
    body: &[u8],
) -> Result<Vec<T>, postcard::Error> {
    postcard::from_bytes(body)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seq_extension_wraps() {
        assert_eq!(extend_seq(5, 0), 5);
        assert_eq!(extend_seq(0xFFFF, 0x1_0002), 0xFFFF);
        assert_eq!(extend_seq(2, 0xFFFE), 0x1_0002);
        assert_eq!(extend_seq(0x8000, 0), 0x8000);
    }

    #[test]
    fn rto_follows_rfc6298() {
        let cfg = LinkConfig::default();
        let mut r = Rtt::new(&cfg);
        r.sample(10_000);
        assert_eq!(r.srtt_us(), Some(10_000));
        assert_eq!(r.rto_us(), 30_000); // 10 ms + 4 * 5 ms
        for _ in 0..50 {
            r.sample(1_000);
        }
        assert_eq!(r.rto_us(), cfg.min_rto_us);
        for _ in 0..20 {
            r.backoff();
        }
        assert_eq!(r.rto_us(), cfg.max_rto_us);
    }

    #[test]
    fn body_is_a_postcard_vec() {
        let cfg = LinkConfig::default();
        let mut s = SendStream::new(&cfg);
        s.set_peer_limits(4096, 640);
        s.set_credits(0, 100);
        for i in 0..3u32 {
            s.push(postcard::to_allocvec(&i).unwrap(), 1, false);
        }
        let mut stats = LinkStats::default();
        let out = s.poll(Micros(0), &mut stats).unwrap();
        let v: Vec<u32> = decode_body(&out.body).unwrap();
        assert_eq!(v, [0, 1, 2]);
    }

    #[test]
    fn one_loss_costs_one_resend() {
        let cfg = LinkConfig::default();
        let mut s = SendStream::new(&cfg);
        s.set_peer_limits(1 << 20, 128);
        s.set_credits(0, 1000);
        let mut stats = LinkStats::default();
        for i in 0..40u32 {
            s.push(postcard::to_allocvec(&[i; 20]).unwrap(), 1, false);
        }
        let sent: Vec<u16> = (0..5)
            .map(|k| s.poll(Micros(k), &mut stats).unwrap().seq)
            .collect();
        assert_eq!(sent, [0, 1, 2, 3, 4]);
        // Frame 1 lost: the peer acks 1 and naks with trigger 2, then dup-acks 3 and 4.
        s.on_ack(1, 1000, None, Micros(10), &mut stats);
        s.on_nak(1, Some(2), 1000, Micros(11), &mut stats);
        assert_eq!(s.poll(Micros(12), &mut stats).unwrap().seq, 1);
        // Naks caused by frames sent before the resend do not resend again.
        s.on_nak(1, Some(3), 1000, Micros(13), &mut stats);
        s.on_ack(1, 1000, Some(4), Micros(13), &mut stats);
        assert_eq!(s.poll(Micros(14), &mut stats).unwrap().seq, 5);
        assert_eq!(stats.frames_retransmitted, 1);
    }

    #[test]
    fn receiver_reorders_and_delivers_once() {
        let mut r = RecvStream::default();
        assert_eq!(r.on_data(0, vec![0]), Arrival::Deliver(vec![vec![0]]));
        assert_eq!(r.on_data(2, vec![2]), Arrival::Gap { send_nak: true });
        assert_eq!(r.on_data(3, vec![3]), Arrival::Gap { send_nak: false });
        assert_eq!(r.on_data(2, vec![2]), Arrival::Gap { send_nak: false });
        assert_eq!(
            r.on_data(1, vec![1]),
            Arrival::Deliver(vec![vec![1], vec![2], vec![3]])
        );
        assert_eq!(r.hole_trigger(), None);
        assert_eq!(r.on_data(3, vec![3]), Arrival::Duplicate);
        assert_eq!(r.expected_wire(), 4);
    }
}
