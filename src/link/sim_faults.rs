//! The faults `hil-sim` can inject, as `--faults key=value,...` names them: one
//! definition for the simulator and for edod, which checks `[sim] faults` when it loads
//! its configuration (an unknown fault is refused before the simulator is started).

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
            _ => return Err(FaultParseError::UnknownKey(key.to_string())),
        }
        Ok(())
    }
}
