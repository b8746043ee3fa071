//! The simulator's fault configuration: `hil-sim --faults key=value,...` and its run-time
//! command language. It lives in the core so that `edod --check-config` refuses an
//! unknown `sim.faults` entry before the simulator is started.

/// Every fault the simulator can inject. Rates are probabilities; `*_at` triggers fire
/// once. All default to "off".
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Faults {
    /// `corrupt=P`: bit-error rate on every data bit, both directions.
    pub corrupt: f64,
    /// `drop=P`: probability that a frame (bytes up to a 0x00) is dropped, both directions.
    pub drop: f64,
    /// `dup=P`: probability that a frame is delivered twice, both directions.
    pub dup: f64,
    /// `delay=MS`: fixed extra latency, both directions.
    pub delay_ms: u64,
    /// `jitter=MS`: uniform random extra latency 0..MS (order is kept, like a real line).
    pub jitter_ms: u64,
    /// `stall=S`: at S seconds after start, stop reading and answering ...
    pub stall_at_s: Option<f64>,
    /// `stall-for=MS`: ... for MS milliseconds (default 3000).
    pub stall_for_ms: u64,
    /// `reset-at=N`: reset after N executed moves (new boot id, queue lost, boot garbage).
    pub reset_at_moves: Option<u64>,
    /// `reset-after=S`: reset at S seconds after start.
    pub reset_after_s: Option<f64>,
    /// `unplug-at=S`: at S seconds close the pty (the host sees EIO/hang-up) ...
    pub unplug_at_s: Option<f64>,
    /// `unplug-for=MS`: ... and open a new one behind the same symlink after MS (default 1000).
    pub unplug_for_ms: u64,
    /// `empty-at=N`: syringe 0 runs empty at executed move N (fault SyringeEmpty).
    pub empty_at_moves: Option<u64>,
    /// `limit-at=N`: the X limit switch trips at executed move N (fault LimitHit).
    pub limit_at_moves: Option<u64>,
    /// `estop-at=N`: the operator presses the machine's e-stop at executed move N.
    pub estop_at_moves: Option<u64>,
    /// `corrupt-line=P` (G-code modes): probability that a line to the firmware has one
    /// byte corrupted, its framing kept (never its first byte, `*` or line end).
    pub corrupt_line: f64,
    /// `drop-ok=P` (G-code modes): probability that an `ok` line to the host is lost.
    pub drop_ok: f64,
    /// `corrupt-reply=P` (G-code modes): probability that a reply line to the host has
    /// one byte corrupted, its framing kept.
    pub corrupt_reply: f64,
    /// `resend=P` (G-code modes, Marlin): probability that a good numbered line is
    /// answered with a resend request (`Error:`, `Resend:`, `ok`) out of the blue.
    pub resend: f64,
    /// `busy=P` (G-code modes): probability, per executed move, of a busy period (the
    /// handler blocks; Marlin sends `busy: processing`) ...
    pub busy: f64,
    /// `busy-for=MS`: ... of MS milliseconds (default 3000).
    pub busy_for_ms: u64,
}

/// A bad `--faults` item.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FaultParseError {
    /// Not `key=value`.
    #[error("fault item {0:?} is not key=value (see hil-sim --help)")]
    NotKeyValue(String),
    /// Unknown key.
    #[error("unknown fault {0:?} (see hil-sim --help for the list)")]
    UnknownKey(String),
    /// Value does not parse or is out of range.
    #[error("fault {key}: value {value:?} is not valid: {why}")]
    BadValue {
        /// Key.
        key: String,
        /// Value given.
        value: String,
        /// What is expected.
        why: &'static str,
    },
}

impl Faults {
    /// Parse `corrupt=1e-4,drop=0.01,...` (empty string = no faults).
    pub fn parse(spec: &str) -> Result<Self, FaultParseError> {
        let mut f = Faults {
            stall_for_ms: 3000,
            unplug_for_ms: 1000,
            busy_for_ms: 3000,
            ..Faults::default()
        };
        for item in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            f.apply(item)?;
        }
        Ok(f)
    }

    /// Apply one `key=value` item.
    pub fn apply(&mut self, item: &str) -> Result<(), FaultParseError> {
        let (key, value) = item
            .split_once('=')
            .ok_or_else(|| FaultParseError::NotKeyValue(item.to_string()))?;
        let (key, value) = (key.trim(), value.trim());
        let bad = |why| FaultParseError::BadValue {
            key: key.to_string(),
            value: value.to_string(),
            why,
        };
        let prob = || -> Result<f64, FaultParseError> {
            let p: f64 = value.parse().map_err(|_| bad("a probability"))?;
            if (0.0..=1.0).contains(&p) {
                Ok(p)
            } else {
                Err(bad("a probability in 0..=1"))
            }
        };
        let int = || {
            value
                .parse::<u64>()
                .map_err(|_| bad("a non-negative integer"))
        };
        let secs = || -> Result<f64, FaultParseError> {
            let s: f64 = value.parse().map_err(|_| bad("seconds"))?;
            if s.is_finite() && s >= 0.0 {
                Ok(s)
            } else {
                Err(bad("seconds >= 0"))
            }
        };
        match key {
            "corrupt" => self.corrupt = prob()?,
            "drop" => self.drop = prob()?,
            "dup" => self.dup = prob()?,
            "delay" => self.delay_ms = int()?,
            "jitter" => self.jitter_ms = int()?,
            "stall" => self.stall_at_s = Some(secs()?),
            "stall-for" => self.stall_for_ms = int()?,
            "reset-at" => self.reset_at_moves = Some(int()?),
            "reset-after" => self.reset_after_s = Some(secs()?),
            "unplug-at" => self.unplug_at_s = Some(secs()?),
            "unplug-for" => self.unplug_for_ms = int()?,
            "empty-at" => self.empty_at_moves = Some(int()?),
            "limit-at" => self.limit_at_moves = Some(int()?),
            "estop-at" => self.estop_at_moves = Some(int()?),
            "corrupt-line" => self.corrupt_line = prob()?,
            "drop-ok" => self.drop_ok = prob()?,
            "corrupt-reply" => self.corrupt_reply = prob()?,
            "resend" => self.resend = prob()?,
            "busy" => self.busy = prob()?,
            "busy-for" => self.busy_for_ms = int()?,
            _ => return Err(FaultParseError::UnknownKey(key.to_string())),
        }
        Ok(())
    }
}

/// The `--help` text for `--faults` and run-time commands.
pub const FAULTS_HELP: &str = "\
FAULTS (--faults key=value,...; all off by default):
  corrupt=P       bit-error rate on every data bit, both directions (e.g. 1e-4)
  drop=P          probability a frame (bytes up to a 0x00) is dropped, both directions
  dup=P           probability a frame is delivered twice, both directions
  delay=MS        fixed extra latency, both directions
  jitter=MS       random extra latency 0..MS (byte order is kept, like a real line)
  stall=S         at S seconds stop reading and answering for stall-for (default 3000 ms)
  stall-for=MS    length of a stall
  reset-at=N      reset after N executed moves: boot garbage, new boot id, queue lost
  reset-after=S   reset at S seconds
  unplug-at=S     close the pty at S seconds and open a new one behind --link after
                  unplug-for (default 1000 ms)
  unplug-for=MS   length of an unplug
  empty-at=N      syringe 0 runs empty at executed move N (fault SyringeEmpty)
  limit-at=N      X limit switch trips at executed move N (fault LimitHit)
  estop-at=N      the machine's e-stop button is pressed at executed move N
  corrupt-line=P  (--gcode) a line to the firmware has one byte corrupted, framing kept
  drop-ok=P       (--gcode) an `ok` line to the host is lost
  corrupt-reply=P (--gcode) a reply line to the host has one byte corrupted, framing kept
  resend=P        (--gcode, Marlin) a good numbered line is answered with a resend request
  busy=P          (--gcode) per executed move, a busy period of busy-for (default 3000
                  ms): the firmware reads nothing, Marlin sends `busy: processing`
  busy-for=MS     length of a busy period
  In --gcode modes `drop` loses whole lines and `dup` repeats them; `corrupt` and
  `jitter` are not used (the line faults above replace them).

RUN-TIME COMMANDS (one per line on stdin, unless --no-stdin):
  any fault item above, e.g. `drop=0.05`  change that fault now
  reset | unplug | stall MS | estop | empty N | limit AXIS
  clear           clear all rate faults (corrupt, drop, dup, delay, jitter)
  status          print the machine status as a JSON line on stderr
";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_issue_example() {
        let f = Faults::parse("corrupt=1e-4,drop=0.01,dup=0.001,reset-at=5000").unwrap();
        assert_eq!(f.corrupt, 1e-4);
        assert_eq!(f.drop, 0.01);
        assert_eq!(f.dup, 0.001);
        assert_eq!(f.reset_at_moves, Some(5000));
        assert!(Faults::parse("drop=2").is_err());
        assert!(Faults::parse("nope=1").is_err());
        assert!(Faults::parse("drop").is_err());
        assert_eq!(Faults::parse("").unwrap().stall_for_ms, 3000);
    }
}
