//! Frame codec shared by both ends: COBS framing with a `0x00` delimiter, a fixed 7-byte
//! header, a postcard body and a CRC-32C trailer (byte layout in `docs/protocol.md`).
//!
//! The decoder resynchronises after garbage at the next `0x00`, never holds more than
//! [`MAX_ENCODED_FRAME`] bytes, and never panics on any input.

use crc::{Crc, CRC_32_ISCSI};

/// Largest decoded frame (header + body + CRC) either end may send, in bytes. The
/// handshake negotiates a maximum at or below this. CRC-32C keeps Hamming distance 6 for
/// data words up to 5243 bits (655 bytes), so every frame up to this size has all 1–5 bit
/// errors detected (see `docs/protocol.md`).
pub const MAX_FRAME: usize = 640;
/// Bytes of the fixed header: kind, seq (u16 LE), ack (u16 LE), credits (u16 LE).
pub const HEADER_LEN: usize = 7;
/// Bytes of the CRC trailer.
pub const CRC_LEN: usize = 4;
/// Largest body of a frame of [`MAX_FRAME`] bytes.
pub const MAX_BODY: usize = MAX_FRAME - HEADER_LEN - CRC_LEN;
/// Largest COBS-encoded frame without its delimiter: at most 1 + len/254 overhead bytes.
pub const MAX_ENCODED_FRAME: usize = MAX_FRAME + 1 + MAX_FRAME / 254;
/// Most bytes a frame of `len` decoded bytes takes on the wire (COBS overhead + delimiter).
pub const fn wire_len(len: usize) -> usize {
    len + 1 + len / 254 + 1
}

/// CRC-32C (Castagnoli, reflected, init/xorout 0xFFFFFFFF), as used by iSCSI and ext4.
pub const CRC32C: Crc<u32> = Crc::<u32>::new(&CRC_32_ISCSI);

/// What a frame is for. The numeric values are the first header byte on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum FrameKind {
    /// Reliable, sequenced data: body is a postcard `Vec` of messages.
    Data = 1,
    /// Standalone cumulative ack + credits (no body).
    Ack = 2,
    /// Negative ack: the receiver saw a bad or out-of-order frame; `ack` is the next
    /// sequence it expects. Body empty.
    Nak = 3,
    /// Priority command (host to machine): e-stop, feed hold, resume. `seq` is the
    /// priority lane's own counter; body is a [`super::msg::PriorityCmd`].
    Priority = 4,
    /// Machine acknowledges priority command `seq`. Body empty.
    PriorityAck = 5,
    /// Host handshake request, body [`super::msg::Hello`].
    Hello = 6,
    /// Machine handshake reply, body [`super::msg::HelloReply`].
    HelloReply = 7,
    /// Liveness + ack refresh. Body: sender's boot id (machine) or session id (host), u64 LE.
    Heartbeat = 8,
    /// Machine has no session (it booted, or never saw a Hello): body is its boot id u64 LE.
    Unsynced = 9,
}

impl FrameKind {
    fn from_u8(b: u8) -> Option<Self> {
        Some(match b {
            1 => Self::Data,
            2 => Self::Ack,
            3 => Self::Nak,
            4 => Self::Priority,
            5 => Self::PriorityAck,
            6 => Self::Hello,
            7 => Self::HelloReply,
            8 => Self::Heartbeat,
            9 => Self::Unsynced,
            _ => return None,
        })
    }
}

/// A decoded frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// Frame kind.
    pub kind: FrameKind,
    /// Sequence number (low 16 bits) of a Data or Priority frame; 0 otherwise.
    pub seq: u16,
    /// Cumulative ack: the next sequence number the sender of this frame expects.
    pub ack: u16,
    /// Credits: free slots in the sender's receive queue (moves for the machine, reports
    /// for the host).
    pub credits: u16,
    /// Postcard body.
    pub body: Vec<u8>,
}

/// Why received bytes did not make a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// More than [`MAX_ENCODED_FRAME`] bytes without a delimiter; skipped to the next one.
    #[error("frame longer than {MAX_ENCODED_FRAME} bytes before a delimiter")]
    TooLong,
    /// A COBS code byte points past the end of the frame.
    #[error("invalid COBS encoding at byte {0}")]
    Cobs(usize),
    /// Fewer bytes than header + CRC.
    #[error("frame of {0} bytes is shorter than header + CRC")]
    TooShort(usize),
    /// CRC mismatch.
    #[error("CRC mismatch: frame says {stated:#010x}, computed {computed:#010x}")]
    Crc {
        /// CRC in the frame.
        stated: u32,
        /// CRC computed over the frame.
        computed: u32,
    },
    /// Unknown kind byte.
    #[error("unknown frame kind {0}")]
    Kind(u8),
}

/// Encode a frame into `out` (appending): COBS(header | body | CRC-32C) followed by 0x00.
pub fn encode_frame(frame: &Frame, out: &mut Vec<u8>) {
    let mut raw = Vec::with_capacity(HEADER_LEN + frame.body.len() + CRC_LEN);
    raw.push(frame.kind as u8);
    raw.extend_from_slice(&frame.seq.to_le_bytes());
    raw.extend_from_slice(&frame.ack.to_le_bytes());
    raw.extend_from_slice(&frame.credits.to_le_bytes());
    raw.extend_from_slice(&frame.body);
    let crc = CRC32C.checksum(&raw);
    raw.extend_from_slice(&crc.to_le_bytes());
    cobs_encode(&raw, out);
    out.push(0);
}

/// COBS-encode `data` (no delimiter) appending to `out`.
pub fn cobs_encode(data: &[u8], out: &mut Vec<u8>) {
    let mut code_at = out.len();
    out.push(0);
    let mut code: u8 = 1;
    for &b in data {
        if b == 0 {
            out[code_at] = code;
            code_at = out.len();
            out.push(0);
            code = 1;
        } else {
            out.push(b);
            code += 1;
            if code == 0xFF {
                out[code_at] = code;
                code_at = out.len();
                out.push(0);
                code = 1;
            }
        }
    }
    out[code_at] = code;
}

/// COBS-decode one frame (without delimiter).
pub fn cobs_decode(data: &[u8]) -> Result<Vec<u8>, FrameError> {
    let mut out = Vec::with_capacity(data.len());
    let mut i = 0;
    while i < data.len() {
        let code = data[i] as usize;
        if code == 0 || i + code > data.len() {
            return Err(FrameError::Cobs(i));
        }
        out.extend_from_slice(&data[i + 1..i + code]);
        i += code;
        if code < 0xFF && i < data.len() {
            out.push(0);
        }
    }
    Ok(out)
}

/// Parse a COBS-decoded frame: check length and CRC, split header and body.
pub fn parse_frame(raw: &[u8]) -> Result<Frame, FrameError> {
    if raw.len() < HEADER_LEN + CRC_LEN {
        return Err(FrameError::TooShort(raw.len()));
    }
    let (content, crc_bytes) = raw.split_at(raw.len() - CRC_LEN);
    let stated = u32::from_le_bytes([crc_bytes[0], crc_bytes[1], crc_bytes[2], crc_bytes[3]]);
    let computed = CRC32C.checksum(content);
    if stated != computed {
        return Err(FrameError::Crc { stated, computed });
    }
    let kind = FrameKind::from_u8(content[0]).ok_or(FrameError::Kind(content[0]))?;
    Ok(Frame {
        kind,
        seq: u16::from_le_bytes([content[1], content[2]]),
        ack: u16::from_le_bytes([content[3], content[4]]),
        credits: u16::from_le_bytes([content[5], content[6]]),
        body: content[HEADER_LEN..].to_vec(),
    })
}

/// Incremental frame decoder: feed it any chunking of the byte stream.
///
/// Memory is bounded by [`MAX_ENCODED_FRAME`]: an over-long run is reported once as
/// [`FrameError::TooLong`] and skipped up to the next delimiter.
#[derive(Debug, Default)]
pub struct Decoder {
    buf: Vec<u8>,
    overflow: bool,
}

impl Decoder {
    /// A decoder expecting the start of a frame.
    pub fn new() -> Self {
        Self {
            buf: Vec::with_capacity(MAX_ENCODED_FRAME),
            overflow: false,
        }
    }

    /// Push one byte; returns a result when the byte completes a frame (a delimiter).
    /// Empty frames (two delimiters in a row, used for line idle/resync) return `None`.
    pub fn push(&mut self, byte: u8) -> Option<Result<Frame, FrameError>> {
        if byte != 0 {
            if self.overflow {
                return None;
            }
            if self.buf.len() >= MAX_ENCODED_FRAME {
                self.overflow = true;
                self.buf.clear();
                return Some(Err(FrameError::TooLong));
            }
            self.buf.push(byte);
            return None;
        }
        if self.overflow {
            self.overflow = false;
            return None;
        }
        if self.buf.is_empty() {
            return None;
        }
        let res = cobs_decode(&self.buf).and_then(|raw| parse_frame(&raw));
        self.buf.clear();
        Some(res)
    }

    /// Bytes held waiting for a delimiter.
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(body: Vec<u8>) -> Frame {
        Frame {
            kind: FrameKind::Data,
            seq: 0x1234,
            ack: 0xFF00,
            credits: 7,
            body,
        }
    }

    #[test]
    fn roundtrip_various_bodies() {
        for body in [
            vec![],
            vec![0],
            vec![0; 300],
            (0..=255u8).collect(),
            vec![1; MAX_BODY],
            (0..MAX_BODY).map(|i| (i % 7) as u8).collect(),
        ] {
            let f = frame(body);
            let mut wire = Vec::new();
            encode_frame(&f, &mut wire);
            assert!(wire.len() <= wire_len(HEADER_LEN + f.body.len() + CRC_LEN));
            assert_eq!(wire.iter().filter(|&&b| b == 0).count(), 1);
            let mut d = Decoder::new();
            let mut got = None;
            for &b in &wire {
                if let Some(r) = d.push(b) {
                    got = Some(r);
                }
            }
            assert_eq!(got, Some(Ok(f)));
        }
    }

    #[test]
    fn resync_after_garbage_and_crc_errors() {
        let f = frame(vec![9, 0, 9]);
        // Garbage that ends without a delimiter spoils the frame it runs into; the
        // frame after is received again.
        let mut wire = vec![0x55, 0x12, 0x00, 0xff, 0xff];
        encode_frame(&f, &mut wire);
        encode_frame(&f, &mut wire);
        let mut bad = Vec::new();
        encode_frame(&f, &mut bad);
        bad[3] ^= 0x10;
        wire.extend_from_slice(&bad);
        encode_frame(&f, &mut wire);
        let mut d = Decoder::new();
        let results: Vec<_> = wire.iter().filter_map(|&b| d.push(b)).collect();
        assert_eq!(results.len(), 5);
        assert!(results[0].is_err());
        assert!(results[1].is_err());
        assert_eq!(results[2], Ok(f.clone()));
        assert!(matches!(results[3], Err(FrameError::Crc { .. })));
        assert_eq!(results[4], Ok(f));
    }

    #[test]
    fn overlong_is_bounded() {
        let mut d = Decoder::new();
        let mut errors = 0;
        for _ in 0..10 * MAX_ENCODED_FRAME {
            if let Some(Err(_)) = d.push(1) {
                errors += 1;
            }
            assert!(d.buffered() <= MAX_ENCODED_FRAME);
        }
        assert_eq!(errors, 1);
        assert_eq!(d.push(0), None);
        let mut wire = Vec::new();
        encode_frame(&frame(vec![]), &mut wire);
        let r: Vec<_> = wire.iter().filter_map(|&b| d.push(b)).collect();
        assert_eq!(r, vec![Ok(frame(vec![]))]);
    }
}
