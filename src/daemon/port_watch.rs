//! The serial port's health as an operator sees it: when to try opening it again (with
//! back-off), what to log (once per distinct problem, then a reminder at most once a
//! minute), and the reason `machine.status` shows while the machine is not connected.
//! Pure: the caller passes the time and the OS error text.

use std::time::{Duration, Instant};

/// Back-off and warning settings.
#[derive(Debug, Clone, Copy)]
pub struct PortWatchOptions {
    /// First retry after a failed open.
    pub first_retry: Duration,
    /// Longest wait between retries.
    pub max_retry: Duration,
    /// The same problem is logged again at most this often.
    pub remind_every: Duration,
    /// An open port with no handshake for this long is reported.
    pub handshake_within: Duration,
}

impl Default for PortWatchOptions {
    fn default() -> Self {
        Self {
            first_retry: Duration::from_millis(300),
            max_retry: Duration::from_secs(5),
            remind_every: Duration::from_secs(60),
            handshake_within: Duration::from_secs(5),
        }
    }
}

/// What the caller should log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PortLog {
    /// A new problem, or a reminder of one that lasts (`tries` opens failed so far).
    Warn { message: String, tries: u32 },
    /// The port opened after the problem.
    Recovered { after_tries: u32 },
}

/// The port's health.
#[derive(Debug)]
pub struct PortWatch {
    opts: PortWatchOptions,
    port: String,
    baud: u32,
    failures: u32,
    next_try: Instant,
    problem: Option<String>,
    logged: Option<(String, Instant)>,
    opened_at: Option<Instant>,
    handshake_reported: bool,
}

impl PortWatch {
    /// A watch over `port` at `baud`, the first open due at `now`.
    pub fn new(opts: PortWatchOptions, port: &str, baud: u32, now: Instant) -> Self {
        Self {
            opts,
            port: port.to_string(),
            baud,
            failures: 0,
            next_try: now,
            problem: None,
            logged: None,
            opened_at: None,
            handshake_reported: false,
        }
    }

    /// Whether an open is due.
    pub fn open_due(&self, now: Instant) -> bool {
        self.opened_at.is_none() && now >= self.next_try
    }

    /// The open failed with `error` (the OS's words).
    pub fn open_failed(&mut self, error: &str, now: Instant) -> Option<PortLog> {
        self.failures = self.failures.saturating_add(1);
        let doublings = self.failures.saturating_sub(1).min(16);
        let wait = self
            .opts
            .first_retry
            .saturating_mul(1u32 << doublings)
            .min(self.opts.max_retry);
        self.next_try = now + wait;
        let problem = format!("port {}: {error}", self.port);
        self.problem = Some(problem.clone());
        self.log_once(problem, now)
    }

    /// The port opened.
    pub fn opened(&mut self, now: Instant) -> Option<PortLog> {
        let after_tries = std::mem::take(&mut self.failures);
        self.opened_at = Some(now);
        self.handshake_reported = false;
        self.problem = None;
        self.logged = None;
        (after_tries > 0).then_some(PortLog::Recovered { after_tries })
    }

    /// The port was lost (`why`): retry soon, from the first back-off step.
    pub fn lost(&mut self, why: &str, now: Instant) {
        self.opened_at = None;
        self.failures = 0;
        self.next_try = now + self.opts.first_retry;
        self.problem = Some(format!("port {}: {why}", self.port));
    }

    /// Called as time goes on with the port open: `connected` is whether the machine has
    /// answered the handshake. Reports an open port that stays silent.
    pub fn check_handshake(&mut self, connected: bool, now: Instant) -> Option<PortLog> {
        let opened_at = self.opened_at?;
        if connected {
            self.problem = None;
            self.handshake_reported = false;
            self.opened_at = Some(now);
            return None;
        }
        let silent = now.saturating_duration_since(opened_at);
        if silent < self.opts.handshake_within {
            return None;
        }
        let problem = format!(
            "port {} is open but the machine has not answered the handshake for {} s: \
             check serial.baud ({}) against the machine's, and machine.protocol",
            self.port,
            silent.as_secs(),
            self.baud
        );
        self.problem = Some(problem.clone());
        if self.handshake_reported {
            return None;
        }
        self.handshake_reported = true;
        Some(PortLog::Warn {
            message: problem,
            tries: 0,
        })
    }

    /// Why the machine is not connected, for `machine.status` (none while it is, or
    /// before anything went wrong).
    pub fn problem(&self) -> Option<&str> {
        self.problem.as_deref()
    }

    /// Log a problem the first time it is seen, then at most every `remind_every`.
    fn log_once(&mut self, problem: String, now: Instant) -> Option<PortLog> {
        let due = match &self.logged {
            Some((last, at)) => {
                *last != problem || now.saturating_duration_since(*at) >= self.opts.remind_every
            }
            None => true,
        };
        if !due {
            return None;
        }
        self.logged = Some((problem.clone(), now));
        Some(PortLog::Warn {
            message: problem,
            tries: self.failures,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn watch(t0: Instant) -> PortWatch {
        PortWatch::new(PortWatchOptions::default(), "/dev/ttyACM0", 115_200, t0)
    }

    #[test]
    fn a_missing_port_is_warned_once_retried_with_back_off_and_named_in_the_status() {
        let t0 = Instant::now();
        let mut w = watch(t0);
        assert!(w.open_due(t0));
        let first = w.open_failed("No such file or directory", t0);
        assert_eq!(
            first,
            Some(PortLog::Warn {
                message: "port /dev/ttyACM0: No such file or directory".into(),
                tries: 1
            })
        );
        assert_eq!(
            w.problem(),
            Some("port /dev/ttyACM0: No such file or directory")
        );
        // Back-off: 0.3, 0.6, 1.2, 2.4, 4.8, then 5 s; nothing more logged in a minute.
        let mut t = t0;
        let mut waits = Vec::new();
        for _ in 0..8 {
            let due = (1..=10_000)
                .map(|ms| t + Duration::from_millis(ms))
                .find(|&at| w.open_due(at))
                .unwrap();
            waits.push(due.duration_since(t).as_millis());
            t = due;
            assert_eq!(w.open_failed("No such file or directory", t), None);
        }
        assert_eq!(waits, [300, 600, 1200, 2400, 4800, 5000, 5000, 5000]);
        // A minute after the first warning, a reminder with the count.
        let later = t0 + Duration::from_secs(61);
        assert!(matches!(
            w.open_failed("No such file or directory", later),
            Some(PortLog::Warn { tries: 10, .. })
        ));
        // Another error is logged at once.
        assert!(matches!(
            w.open_failed("Permission denied", later),
            Some(PortLog::Warn { tries: 11, .. })
        ));
        assert_eq!(
            w.opened(later),
            Some(PortLog::Recovered { after_tries: 11 })
        );
        assert_eq!(w.problem(), None);
        assert!(!w.open_due(later + Duration::from_secs(60)));
    }

    #[test]
    fn an_open_port_without_a_handshake_is_reported_once_and_cleared_by_one() {
        let t0 = Instant::now();
        let mut w = watch(t0);
        assert_eq!(w.opened(t0), None);
        assert_eq!(w.check_handshake(false, t0 + Duration::from_secs(4)), None);
        assert_eq!(w.problem(), None);
        let log = w.check_handshake(false, t0 + Duration::from_secs(5));
        let Some(PortLog::Warn { message, .. }) = log else {
            panic!("{log:?}")
        };
        assert!(
            message.contains("has not answered the handshake for 5 s"),
            "{message}"
        );
        assert!(message.contains("serial.baud (115200)"), "{message}");
        assert_eq!(w.check_handshake(false, t0 + Duration::from_secs(9)), None);
        assert!(w.problem().unwrap().contains("9 s"));
        assert_eq!(w.check_handshake(true, t0 + Duration::from_secs(10)), None);
        assert_eq!(w.problem(), None);
        // Lost: retried soon, named.
        w.lost("end of file", t0 + Duration::from_secs(20));
        assert_eq!(w.problem(), Some("port /dev/ttyACM0: end of file"));
        assert!(w.open_due(t0 + Duration::from_millis(20_300)));
    }
}
