//! Reading the firmware's side of the line: a bounded line assembler for the bytes, and
//! the classification of one reply line (`ok`, `Resend:`, `busy:`, `Error:`, banners, ...)
//! as Marlin, RepRapFirmware and Klipper print them (`docs/firmware.md`, "Replies").

/// Assembles reply lines from bytes with bounded memory.
#[derive(Debug)]
pub(crate) struct LineReader {
    buf: Vec<u8>,
    max_bytes: usize,
    /// Bytes dropped from the current over-long line (0 if it is not over-long).
    overflow_bytes: usize,
}

/// One item out of the [`LineReader`].
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum ReadItem {
    /// A complete line, without its `\n` and any `\r`.
    Line(Vec<u8>),
    /// The current line passed the limit: its bytes up to the next `\n` are dropped.
    OverlongStarted,
    /// An over-long line ended; it had this many bytes.
    OverlongEnded(usize),
}

impl LineReader {
    pub(crate) fn new(max_bytes: usize) -> Self {
        Self {
            buf: Vec::new(),
            max_bytes: max_bytes.max(1),
            overflow_bytes: 0,
        }
    }

    /// Bytes of a partial line held now (at most the limit: an over-long line is counted,
    /// not kept).
    #[cfg(test)]
    pub(crate) fn buffered_len(&self) -> usize {
        self.buf.len()
    }

    /// Forget a partial line (after a reset or reconnect).
    pub(crate) fn clear(&mut self) {
        self.buf.clear();
        self.overflow_bytes = 0;
    }

    /// Feed bytes; `out` gets every item they complete.
    pub(crate) fn push(&mut self, bytes: &[u8], out: &mut Vec<ReadItem>) {
        for &b in bytes {
            match b {
                b'\n' => {
                    if self.overflow_bytes > 0 {
                        out.push(ReadItem::OverlongEnded(self.overflow_bytes));
                        self.overflow_bytes = 0;
                        self.buf.clear();
                    } else {
                        out.push(ReadItem::Line(std::mem::take(&mut self.buf)));
                    }
                }
                b'\r' => {}
                _ if self.overflow_bytes > 0 => self.overflow_bytes += 1,
                _ if self.buf.len() >= self.max_bytes => {
                    self.overflow_bytes = self.buf.len() + 1;
                    self.buf = Vec::new();
                    out.push(ReadItem::OverlongStarted);
                }
                _ => self.buf.push(b),
            }
        }
    }
}

/// The fields of an `ok` line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct OkReply<'a> {
    /// ADVANCED_OK `N<n>`: the line acknowledged.
    pub n: Option<u32>,
    /// ADVANCED_OK `P<p>`: free planner blocks.
    pub p: Option<u16>,
    /// ADVANCED_OK `B<b>`: free command slots (Marlin reports one too few).
    pub b: Option<u16>,
    /// Everything after `ok` (Klipper's `M115` answer, Marlin's `M105` temperatures).
    pub rest: &'a str,
}

/// One reply line, classified.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Reply<'a> {
    Empty,
    Ok(OkReply<'a>),
    /// `Resend: n`, `Resend:n`, `rs n`, `rs N:n`, `Resend: Nn`.
    Resend(u32),
    /// A line that starts like a resend request but carries no valid line number.
    BadResend(&'a str),
    /// `busy: processing` (Marlin host keepalive, also as `echo:busy: ...`).
    Busy(&'a str),
    /// Marlin `NO_TIMEOUTS`: queue empty and no serial data.
    Wait,
    /// `Error:...`; `last_line` from a trailing `Last Line: <n>` (Marlin's line errors).
    Error {
        text: &'a str,
        last_line: Option<u32>,
    },
    /// Klipper `!! ...`.
    KlipperError(&'a str),
    /// Klipper `// Klipper state: <state>`.
    KlipperState(&'a str),
    /// `//action:<text>`.
    Action(&'a str),
    /// Marlin's first boot line.
    Start,
    /// Marlin's reset reason lines (`PowerUp`, ` External Reset`, ...).
    ResetReason(&'a str),
    /// A JSON object (RRF `M409` answers).
    Json(&'a str),
    /// `echo:...`, `// ...`, and every other line.
    Echo(&'a str),
}

const RESET_REASONS: [&str; 5] = [
    "PowerUp",
    "External Reset",
    "Brown out Reset",
    "Watchdog Reset",
    "Software Reset",
];

/// Classify a reply line (without its line end).
pub(crate) fn parse(line: &str) -> Reply<'_> {
    let t = line.trim();
    if t.is_empty() {
        return Reply::Empty;
    }
    if t == "ok" || t.starts_with("ok ") {
        return Reply::Ok(parse_ok(t[2..].trim()));
    }
    if let Some(rest) = strip_prefix_ci(t, "resend").or_else(|| strip_rs(t)) {
        return match parse_resend_number(rest) {
            Some(n) => Reply::Resend(n),
            None => Reply::BadResend(t),
        };
    }
    if let Some(rest) = strip_prefix_ci(t, "echo:busy:").or_else(|| strip_prefix_ci(t, "busy:")) {
        return Reply::Busy(rest.trim());
    }
    if t == "wait" {
        return Reply::Wait;
    }
    if let Some(rest) = strip_prefix_ci(t, "error:") {
        let text = rest.trim();
        return Reply::Error {
            text,
            last_line: last_line_of(text),
        };
    }
    if let Some(rest) = t.strip_prefix("!!") {
        return Reply::KlipperError(rest.trim());
    }
    if let Some(rest) = t.strip_prefix("// Klipper state:") {
        return Reply::KlipperState(rest.trim());
    }
    if let Some(rest) = t.strip_prefix("//action:") {
        return Reply::Action(rest.trim());
    }
    if t == "start" {
        return Reply::Start;
    }
    if RESET_REASONS.contains(&t) {
        return Reply::ResetReason(t);
    }
    if t.starts_with('{') {
        return Reply::Json(t);
    }
    if let Some(rest) = strip_prefix_ci(t, "echo:").or_else(|| t.strip_prefix("//")) {
        return Reply::Echo(rest.trim());
    }
    Reply::Echo(t)
}

fn strip_prefix_ci<'a>(s: &'a str, prefix: &str) -> Option<&'a str> {
    let head = s.get(..prefix.len())?;
    head.eq_ignore_ascii_case(prefix)
        .then(|| &s[prefix.len()..])
}

/// `rs <n>` / `rs N:<n>` (RepRapFirmware 1.x–3.0, Printrun-style firmwares).
fn strip_rs(s: &str) -> Option<&str> {
    let rest = strip_prefix_ci(s, "rs")?;
    rest.starts_with(' ').then_some(rest)
}

/// The number of a resend request: optional `:`, spaces, optional `N` or `N:`, digits,
/// then nothing but spaces. Strict, so a corrupted line is not read as a request.
fn parse_resend_number(rest: &str) -> Option<u32> {
    let r = rest.trim_start_matches(':').trim();
    let r = r
        .strip_prefix("N:")
        .or_else(|| r.strip_prefix('N'))
        .unwrap_or(r)
        .trim_start();
    if r.is_empty() || !r.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    r.parse().ok()
}

/// `... Last Line: <n>` at the end of a Marlin line error.
fn last_line_of(text: &str) -> Option<u32> {
    let at = text.rfind("Last Line:")?;
    let digits = text[at + "Last Line:".len()..].trim();
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

fn parse_ok(rest: &str) -> OkReply<'_> {
    let mut ok = OkReply {
        rest,
        ..OkReply::default()
    };
    for word in rest.split_ascii_whitespace() {
        let (letter, digits) = word.split_at(1.min(word.len()));
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        match letter {
            "N" => ok.n = digits.parse().ok(),
            "P" => ok.p = digits.parse().ok(),
            "B" => ok.b = digits.parse().ok(),
            _ => {}
        }
    }
    ok
}

/// `KEY:value` pairs of an `M115` answer (`FIRMWARE_NAME:Marlin 2.1.2 SOURCE_CODE_URL:...`;
/// RRF puts a space after the colon). Keys are upper-case words.
pub(crate) fn m115_fields(line: &str) -> Vec<(String, String)> {
    let bytes = line.as_bytes();
    let mut starts = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let at_word_start = i == 0 || bytes[i - 1] == b' ';
        if at_word_start {
            let mut j = i;
            while j < bytes.len() && (bytes[j].is_ascii_uppercase() || bytes[j] == b'_') {
                j += 1;
            }
            if j > i + 1 && j < bytes.len() && bytes[j] == b':' {
                starts.push((i, j));
                i = j + 1;
                continue;
            }
        }
        i += 1;
    }
    let mut fields = Vec::new();
    for (k, &(key_start, colon)) in starts.iter().enumerate() {
        let end = starts.get(k + 1).map_or(line.len(), |next| next.0);
        fields.push((
            line[key_start..colon].to_string(),
            line[colon + 1..end].trim().to_string(),
        ));
    }
    fields
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lines(reader: &mut LineReader, bytes: &[u8]) -> Vec<ReadItem> {
        let mut out = Vec::new();
        reader.push(bytes, &mut out);
        out
    }

    #[test]
    fn reader_splits_lines_and_strips_cr() {
        let mut r = LineReader::new(64);
        assert_eq!(
            lines(&mut r, b"ok\r\nResend: 4\nec"),
            vec![
                ReadItem::Line(b"ok".to_vec()),
                ReadItem::Line(b"Resend: 4".to_vec())
            ]
        );
        assert_eq!(
            lines(&mut r, b"ho:x\n"),
            vec![ReadItem::Line(b"echo:x".to_vec())]
        );
    }

    #[test]
    fn reader_bounds_an_unterminated_megabyte_line() {
        let mut r = LineReader::new(100);
        let big = vec![b'x'; 1 << 20];
        assert_eq!(lines(&mut r, &big), vec![ReadItem::OverlongStarted]);
        assert!(r.buf.capacity() <= 100);
        assert_eq!(
            lines(&mut r, b"yy\nok\n"),
            vec![
                ReadItem::OverlongEnded((1 << 20) + 2),
                ReadItem::Line(b"ok".to_vec())
            ]
        );
    }

    #[test]
    fn ok_forms() {
        assert_eq!(parse("ok"), Reply::Ok(OkReply::default()));
        let Reply::Ok(ok) = parse("ok N12 P15 B3") else {
            panic!("not ok")
        };
        assert_eq!((ok.n, ok.p, ok.b), (Some(12), Some(15), Some(3)));
        let Reply::Ok(ok) = parse("ok T:20.00 /0.00 B:20.00 /0.00 @:0 B@:0") else {
            panic!("not ok")
        };
        assert_eq!((ok.n, ok.p, ok.b), (None, None, None));
        let Reply::Ok(ok) = parse("ok FIRMWARE_NAME:Klipper FIRMWARE_VERSION:v0.12.0") else {
            panic!("not ok")
        };
        assert_eq!(ok.rest, "FIRMWARE_NAME:Klipper FIRMWARE_VERSION:v0.12.0");
        assert_eq!(parse("okay"), Reply::Echo("okay"));
    }

    #[test]
    fn resend_forms() {
        for s in [
            "Resend: 42",
            "Resend:42",
            "resend: N42",
            "rs 42",
            "rs N:42",
            "Resend: 42 ",
        ] {
            assert_eq!(parse(s), Reply::Resend(42), "{s}");
        }
        assert_eq!(parse("Resend: 4x2"), Reply::BadResend("Resend: 4x2"));
        assert_eq!(parse("Resend:"), Reply::BadResend("Resend:"));
        assert_eq!(parse("rsvp"), Reply::Echo("rsvp"));
    }

    #[test]
    fn errors_busy_and_banners() {
        assert_eq!(
            parse("Error:checksum mismatch, Last Line: 41"),
            Reply::Error {
                text: "checksum mismatch, Last Line: 41",
                last_line: Some(41)
            }
        );
        assert_eq!(
            parse("Error:Line Number is not Last Line Number+1, Last Line: 7"),
            Reply::Error {
                text: "Line Number is not Last Line Number+1, Last Line: 7",
                last_line: Some(7)
            }
        );
        assert_eq!(
            parse("Error:Printer halted. kill() called!"),
            Reply::Error {
                text: "Printer halted. kill() called!",
                last_line: None
            }
        );
        assert_eq!(parse("echo:busy: processing"), Reply::Busy("processing"));
        assert_eq!(
            parse("busy: paused for user"),
            Reply::Busy("paused for user")
        );
        assert_eq!(parse("wait"), Reply::Wait);
        assert_eq!(parse("start"), Reply::Start);
        assert_eq!(
            parse(" External Reset"),
            Reply::ResetReason("External Reset")
        );
        assert_eq!(
            parse("!! Move out of range"),
            Reply::KlipperError("Move out of range")
        );
        assert_eq!(
            parse("// Klipper state: Ready"),
            Reply::KlipperState("Ready")
        );
        assert_eq!(parse("//action:pause"), Reply::Action("pause"));
        assert_eq!(
            parse("echo:Unknown command: \"G999\""),
            Reply::Echo("Unknown command: \"G999\"")
        );
        assert_eq!(parse("// probe at 1,2"), Reply::Echo("probe at 1,2"));
        assert_eq!(
            parse("{\"key\":\"inputs\"}"),
            Reply::Json("{\"key\":\"inputs\"}")
        );
        assert_eq!(parse("T:20.0 /0.0"), Reply::Echo("T:20.0 /0.0"));
        assert_eq!(parse("  "), Reply::Empty);
    }

    #[test]
    fn m115_fields_marlin_rrf_klipper() {
        let f = m115_fields("FIRMWARE_NAME:Marlin 2.1.2.1 (Jun 1 2023) SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin PROTOCOL_VERSION:1.0");
        assert_eq!(
            f[0],
            ("FIRMWARE_NAME".into(), "Marlin 2.1.2.1 (Jun 1 2023)".into())
        );
        assert_eq!(f[2], ("PROTOCOL_VERSION".into(), "1.0".into()));
        let f =
            m115_fields("FIRMWARE_NAME: RepRapFirmware for Duet 3 MB6HC FIRMWARE_VERSION: 3.5.1");
        assert_eq!(f[0].1, "RepRapFirmware for Duet 3 MB6HC");
        assert_eq!(f[1], ("FIRMWARE_VERSION".into(), "3.5.1".into()));
    }
}
