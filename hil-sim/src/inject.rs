//! The fault injector of one direction, for both protocol ends: it splits the byte
//! stream into units, drops, duplicates, corrupts and delays them (seeded), and lets
//! them through in order. The unit is the protocol's: [`Frames`], the edo link's
//! 0x00-terminated frames (bit errors at a bit-error rate, delay and jitter), or
//! [`Lines`], G-code's `\n`-terminated lines (one changed byte per corrupted line, lost
//! `ok`s, a fixed delay). Each unit kind keeps its own order of seeded draws, so a seed
//! gives the same faults as it did before the two injectors were one.

use std::collections::VecDeque;

use edo::link::testkit::SimRng;

use crate::faults::Faults;
use crate::sim::{after_ms, Summary};

/// A unit longer than this is passed on as it is (no terminator came).
const MAX_UNIT_BYTES: usize = 4096;

/// What a unit is and the faults particular to it. The injector draws, in this order:
/// [`Unit::dropped`], [`Unit::corrupt_unit`], the duplicate, then per copy
/// [`Unit::corrupt_copy`] and [`Unit::due_at`].
pub(crate) trait Unit {
    /// The byte that ends a unit.
    const END: u8;

    /// Whether the unit is lost.
    fn dropped(&mut self, rng: &mut SimRng, unit: &[u8], f: &Faults) -> bool;

    /// Damage the unit before it is duplicated (both copies alike).
    fn corrupt_unit(
        &mut self,
        _rng: &mut SimRng,
        _unit: &mut [u8],
        _f: &Faults,
        _sum: &mut Summary,
    ) {
    }

    /// Damage one copy.
    fn corrupt_copy(
        &mut self,
        _rng: &mut SimRng,
        _copy: &mut [u8],
        _f: &Faults,
        _sum: &mut Summary,
    ) {
    }

    /// When a copy passed on at `now_us` is due; the copy ahead of it is due at `last_at`.
    fn due_at(&mut self, rng: &mut SimRng, now_us: u64, last_at: u64, f: &Faults) -> u64;
}

/// Splits a byte stream into units and applies the faults per unit, keeping order.
pub(crate) struct Injector<U> {
    rng: SimRng,
    /// The unit being read.
    cur: Vec<u8>,
    /// Units passed on, each with when it is due.
    queue: VecDeque<(u64, Vec<u8>)>,
    last_at: u64,
    unit: U,
}

impl<U: Unit> Injector<U> {
    /// An injector of `unit`s whose faults are drawn from `seed`.
    pub(crate) fn new(seed: u64, unit: U) -> Self {
        Self {
            rng: SimRng::new(seed),
            cur: Vec::new(),
            queue: VecDeque::new(),
            last_at: 0,
            unit,
        }
    }

    /// Bytes on the line at `now_us`: each unit they complete goes through the faults.
    pub(crate) fn push(&mut self, bytes: &[u8], now_us: u64, f: &Faults, sum: &mut Summary) {
        for &b in bytes {
            self.cur.push(b);
            if b == U::END || self.cur.len() > MAX_UNIT_BYTES {
                let unit = std::mem::take(&mut self.cur);
                self.inject(unit, now_us, f, sum);
            }
        }
    }

    /// One unit through the faults: dropped, or corrupted, copied and queued.
    fn inject(&mut self, mut unit: Vec<u8>, now_us: u64, f: &Faults, sum: &mut Summary) {
        if self.unit.dropped(&mut self.rng, &unit, f) {
            sum.frames_dropped += 1;
            return;
        }
        self.unit.corrupt_unit(&mut self.rng, &mut unit, f, sum);
        let copies = if self.rng.chance(f.dup) {
            sum.frames_duplicated += 1;
            2
        } else {
            1
        };
        for _ in 0..copies {
            let mut copy = unit.clone();
            self.unit.corrupt_copy(&mut self.rng, &mut copy, f, sum);
            let at = self.unit.due_at(&mut self.rng, now_us, self.last_at, f);
            self.last_at = at;
            self.queue.push_back((at, copy));
        }
    }

    /// The next unit due by `now_us`, in order.
    pub(crate) fn pop_due(&mut self, now_us: u64) -> Option<Vec<u8>> {
        if self.queue.front()?.0 <= now_us {
            self.queue.pop_front().map(|q| q.1)
        } else {
            None
        }
    }

    /// Whether no byte is held: no unit being read, none waiting to be due.
    pub(crate) fn is_empty(&self) -> bool {
        self.cur.is_empty() && self.queue.is_empty()
    }

    /// Lose what is on the line (a reset, an unplug).
    pub(crate) fn clear(&mut self) {
        self.queue.clear();
        self.cur.clear();
    }
}

/// The edo link's frames (0x00-terminated): drop, duplicate, bit errors at the
/// bit-error rate `corrupt` on every copy, delay plus jitter, never overtaking.
#[derive(Debug)]
pub(crate) struct Frames {
    /// Bits until the next error (`u64::MAX`: none drawn yet).
    bits_to_error: u64,
}

impl Frames {
    pub(crate) fn new() -> Self {
        Self {
            bits_to_error: u64::MAX,
        }
    }
}

/// Bits until the next error at bit-error rate `ber` (geometric).
fn next_error(rng: &mut SimRng, ber: f64) -> u64 {
    if ber <= 0.0 {
        return u64::MAX;
    }
    let u = rng.next_f64().max(f64::MIN_POSITIVE);
    (u.ln() / (1.0 - ber).ln()).floor().min(1e18) as u64
}

impl Unit for Frames {
    const END: u8 = 0;

    fn dropped(&mut self, rng: &mut SimRng, _unit: &[u8], f: &Faults) -> bool {
        rng.chance(f.drop)
    }

    fn corrupt_copy(&mut self, rng: &mut SimRng, copy: &mut [u8], f: &Faults, sum: &mut Summary) {
        // Drawn on the first copy only: the errors then run on across the copies.
        if self.bits_to_error == u64::MAX && f.corrupt > 0.0 {
            self.bits_to_error = next_error(rng, f.corrupt);
        }
        let bits = copy.len() as u64 * 8;
        let mut pos = 0u64;
        while f.corrupt > 0.0 && self.bits_to_error < bits - pos {
            pos += self.bits_to_error;
            if let Some(b) = copy.get_mut((pos / 8) as usize) {
                *b ^= 1 << (pos % 8);
                sum.bits_flipped += 1;
            }
            pos += 1;
            self.bits_to_error = next_error(rng, f.corrupt);
        }
        if self.bits_to_error != u64::MAX {
            self.bits_to_error -= (bits - pos).min(self.bits_to_error);
        }
    }

    fn due_at(&mut self, rng: &mut SimRng, now_us: u64, last_at: u64, f: &Faults) -> u64 {
        let jitter = if f.jitter_ms > 0 {
            rng.next_u64() % f.jitter_ms.saturating_mul(1000)
        } else {
            0
        };
        after_ms(now_us, f.delay_ms)
            .saturating_add(jitter)
            .max(last_at)
    }
}

/// G-code lines (`\n`-terminated): drop (and, towards the host, lost `ok`s), one byte
/// changed per corrupted line (`corrupt-line` towards the firmware, `corrupt-reply`
/// towards the host), duplicate, a fixed delay.
#[derive(Debug)]
pub(crate) struct Lines {
    /// Firmware -> host (replies) rather than host -> firmware (commands).
    to_host: bool,
}

impl Lines {
    /// The lines towards the firmware.
    pub(crate) fn to_firmware() -> Self {
        Self { to_host: false }
    }

    /// The firmware's replies.
    pub(crate) fn to_host() -> Self {
        Self { to_host: true }
    }
}

impl Unit for Lines {
    const END: u8 = b'\n';

    fn dropped(&mut self, rng: &mut SimRng, unit: &[u8], f: &Faults) -> bool {
        let is_ok = unit.starts_with(b"ok");
        rng.chance(f.drop) || (self.to_host && is_ok && rng.chance(f.drop_ok))
    }

    fn corrupt_unit(&mut self, rng: &mut SimRng, unit: &mut [u8], f: &Faults, sum: &mut Summary) {
        let corrupt = if self.to_host {
            f.corrupt_reply
        } else {
            f.corrupt_line
        };
        if rng.chance(corrupt) && corrupt_one_byte(rng, unit) {
            sum.bits_flipped += 1;
        }
    }

    fn due_at(&mut self, _rng: &mut SimRng, now_us: u64, _last_at: u64, f: &Faults) -> u64 {
        after_ms(now_us, f.delay_ms)
    }
}

/// One byte of a line changed, its framing kept: not the first byte, a `*` or a line end,
/// and never into a line end or `;` (the checksum's blind spots, `docs/firmware.md`).
fn corrupt_one_byte(rng: &mut SimRng, line: &mut [u8]) -> bool {
    let eligible: Vec<usize> = (1..line.len())
        .filter(|&i| !matches!(line[i], b'\n' | b'\r' | b'*') && line[i - 1] != b'\n')
        .collect();
    if eligible.is_empty() {
        return false;
    }
    let i = eligible[(rng.next_u64() % eligible.len() as u64) as usize];
    loop {
        let b = line[i] ^ ((rng.next_u64() % 255 + 1) as u8);
        if !matches!(b, b'\n' | b'\r' | b';') {
            line[i] = b;
            return true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` chunks of a seeded byte stream, most ending a unit with `end`.
    fn stream(seed: u64, n: usize, end: u8) -> Vec<Vec<u8>> {
        let mut r = SimRng::new(seed);
        let mut chunks = Vec::new();
        for _ in 0..n {
            let len = (r.next_u64() % 200) as usize;
            let mut v: Vec<u8> = (0..len).map(|_| (r.next_u64() % 250) as u8 + 1).collect();
            if r.chance(0.8) {
                v.push(end);
            }
            if r.chance(0.3) {
                v.extend_from_slice(b"ok 12\n");
            }
            chunks.push(v);
        }
        chunks
    }

    /// Every unit out of `inj` for `chunks` (one ms apart), and the summary.
    fn run<U: Unit>(mut inj: Injector<U>, chunks: &[Vec<u8>], f: &Faults) -> (Vec<u8>, Summary) {
        let mut sum = Summary::default();
        let mut out = Vec::new();
        for (i, chunk) in chunks.iter().enumerate() {
            let now = i as u64 * 1000;
            inj.push(chunk, now, f, &mut sum);
            while let Some(u) = inj.pop_due(now) {
                out.extend(u);
            }
        }
        while let Some(u) = inj.pop_due(u64::MAX) {
            out.extend(u);
        }
        (out, sum)
    }

    fn digest(bytes: &[u8]) -> u64 {
        bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
            (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
        })
    }

    fn faults() -> Faults {
        Faults {
            drop: 0.1,
            dup: 0.2,
            corrupt: 1e-3,
            corrupt_line: 0.05,
            corrupt_reply: 0.05,
            drop_ok: 0.1,
            delay_ms: 2,
            jitter_ms: 3,
            ..Faults::default()
        }
    }

    /// A seed gives the same frame faults as it always did (tests count them).
    #[test]
    fn frame_faults_of_a_seed_stay_the_same() {
        let (out, sum) = run(
            Injector::new(7, Frames::new()),
            &stream(1, 300, 0),
            &faults(),
        );
        let counts = (sum.frames_dropped, sum.frames_duplicated, sum.bits_flipped);
        assert_eq!(counts, (35, 41, 284));
        assert_eq!((out.len(), digest(&out)), (32027, 0x4b82_0b9a_c90e_db5e));
    }

    /// A seed gives the same line faults as it always did, each way.
    #[test]
    fn line_faults_of_a_seed_stay_the_same() {
        for (unit, want) in [
            (
                Lines::to_firmware(),
                ((41, 77, 15), 32342, 0x2488_4b38_1b81_0abf),
            ),
            (
                Lines::to_host(),
                ((39, 69, 19), 33027, 0xa48d_4478_0afe_2020),
            ),
        ] {
            let (out, sum) = run(Injector::new(7, unit), &stream(2, 300, b'\n'), &faults());
            let counts = (sum.frames_dropped, sum.frames_duplicated, sum.bits_flipped);
            assert_eq!((counts, out.len(), digest(&out)), want);
        }
    }

    /// A corrupted line keeps its framing: one line in, one line out.
    #[test]
    fn a_corrupted_line_keeps_its_end() {
        let mut rng = SimRng::new(3);
        for _ in 0..1000 {
            let mut line = b"N12 G1 X10 Y20*87\n".to_vec();
            assert!(corrupt_one_byte(&mut rng, &mut line));
            assert_eq!(line.iter().filter(|&&b| b == b'\n').count(), 1);
            assert_eq!(line.last(), Some(&b'\n'));
            assert_eq!(line.first(), Some(&b'N'));
            assert!(!line.contains(&b';') && !line.contains(&b'\r'));
        }
    }
}
