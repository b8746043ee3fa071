//! The reliable, in-order half of the link, used in both directions: a go-back-N sender
//! with an RFC 6298 retransmission timer, fast retransmit, a window in frames, bytes and
//! credits; and a receiver that delivers each sequence number exactly once.

use std::collections::VecDeque;

use super::frame::{wire_len, CRC_LEN, HEADER_LEN};
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

/// Go-back-N sender.
#[derive(Debug)]
pub(crate) struct SendStream {
    next_seq: u64,
    una: u64,
    unacked: VecDeque<InFlight>,
    unacked_wire_bytes: usize,
    resend_next: u64,
    pending: VecDeque<Pending>,
    pending_bytes: usize,
    rtt: Rtt,
    rto_deadline: Option<Micros>,
    dup_acks: u32,
    /// While `una < recover`, a go-back is already under way: ignore further naks.
    recover: u64,
    /// Counter of transmissions (first and repeated), to order naks against go-backs.
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
            resend_next: 0,
            pending: VecDeque::new(),
            pending_bytes: 0,
            rtt: Rtt::new(cfg),
            rto_deadline: None,
            dup_acks: 0,
            recover: 0,
            tx_counter: 0,
            frame_budget: cfg.max_frame,
            min_frame: cfg.min_frame.min(cfg.max_frame),
            clean_frames: 0,
            last_credits: 0,
            slots_sent: 0,
            slots_acked: 0,
            slot_limit: 0,
            max_frames: cfg.max_frames_in_flight.max(1),
            max_bytes: usize::MAX,
            max_frame: cfg.max_frame,
            dup_ack_threshold: cfg.dup_ack_threshold,
        }
    }

    /// Set the peer's limits learnt in the handshake.
    pub(crate) fn set_peer_limits(&mut self, rx_buffer_bytes: usize, max_frame: usize) {
        self.max_bytes = rx_buffer_bytes.max(1);
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
        self.resend_next = self.next_seq;
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
        if self.resend_next < self.next_seq {
            let idx = (self.resend_next - self.una) as usize;
            let f = self.unacked.get_mut(idx)?;
            f.retransmitted = true;
            f.sent_at = now;
            self.tx_counter += 1;
            f.tx_order = self.tx_counter;
            self.resend_next += 1;
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
        self.resend_next = self.next_seq;
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
            self.resend_next = self.resend_next.max(self.una);
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
                if self.go_back() {
                    stats.fast_retransmits += 1;
                }
            }
        }
        self.set_credits(ack, credits);
        self.last_credits = credits;
        out
    }

    /// A nak: the peer expects `wire_ack` and saw a bad frame or a frame after a gap.
    /// The receiver sends at most one nak per round of transmissions (it sees a new round
    /// when sequence numbers go backwards), so every nak means "resend from `ack`" —
    /// unless a go-back is already pending and has not resent anything yet.
    pub(crate) fn on_nak(
        &mut self,
        wire_ack: u16,
        credits: u16,
        now: Micros,
        stats: &mut LinkStats,
    ) {
        stats.naks_received += 1;
        self.on_ack(wire_ack, credits, None, now, stats);
        if !self.unacked.is_empty() && self.resend_next > self.una {
            self.go_back_now();
        }
    }

    /// Start resending from the oldest unacked frame, unless a go-back covering it is
    /// already in progress. Returns whether it went back.
    fn go_back(&mut self) -> bool {
        if self.una < self.recover {
            return false;
        }
        self.go_back_now();
        true
    }

    fn go_back_now(&mut self) {
        self.recover = self.next_seq;
        self.resend_next = self.una;
        self.clean_frames = 0;
        // Multiplicative decrease of the frame size: on a noisy line shorter frames
        // are hit less often and cost less to resend.
        self.frame_budget = (self.frame_budget * 3 / 4).max(self.min_frame);
    }

    /// The retransmission timer expired: back off and go back N.
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
        self.go_back_now();
        self.rto_deadline = Some(now.plus_us(self.rtt.rto_us()));
    }
}

/// Outcome of a received Data frame.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Arrival {
    /// The next frame in order: deliver its body.
    InOrder,
    /// Already delivered: discard, re-ack.
    Duplicate,
    /// A frame after a gap: discard; nak if this is the first of its round.
    Gap {
        /// Send a nak.
        send_nak: bool,
    },
}

/// In-order receiver.
#[derive(Debug, Default)]
pub(crate) struct RecvStream {
    expected: u64,
    nak_sent_for: Option<u64>,
    last_gap_seq: Option<u64>,
}

impl RecvStream {
    pub(crate) fn expected_wire(&self) -> u16 {
        self.expected as u16
    }

    pub(crate) fn on_data(&mut self, wire_seq: u16) -> Arrival {
        let seq = extend_seq(wire_seq, self.expected);
        if seq == self.expected {
            self.expected += 1;
            self.nak_sent_for = None;
            self.last_gap_seq = None;
            Arrival::InOrder
        } else if seq < self.expected {
            Arrival::Duplicate
        } else {
            // A new round of transmissions shows as sequence numbers going backwards.
            let rewind = self.last_gap_seq.is_some_and(|g| seq <= g);
            self.last_gap_seq = Some(seq);
            let send_nak = rewind || self.nak_sent_for != Some(self.expected);
            self.nak_sent_for = Some(self.expected);
            Arrival::Gap { send_nak }
        }
    }

    /// A frame failed its CRC: nak once per expected sequence.
    pub(crate) fn on_corrupt(&mut self) -> bool {
        let send = self.nak_sent_for != Some(self.expected);
        self.nak_sent_for = Some(self.expected);
        send
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
}
