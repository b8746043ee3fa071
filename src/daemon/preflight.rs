//! What a configuration that parses may still get wrong about this host: checked by
//! `edod --check-config` and by edod before it starts (before it takes its locks).
//!
//! Errors are what can only fail once edod runs: a socket path longer than a Unix
//! socket address holds, a socket group that does not exist, an unknown `sim.faults`
//! entry, a serial port that is not a character device, a line speed no serial line
//! runs at. Warnings are what may be right later: a serial port that does not exist
//! yet (a USB adapter not plugged in: edod waits for it), a line speed that is not a
//! standard rate.

use std::path::Path;

use super::config::{Config, SIM_PORT};

/// Longest socket path, bytes: `sun_path` holds 108 with the terminating NUL.
pub const MAX_SOCKET_PATH: usize = 107;

/// The standard line speeds (termios rates, and 250 000 that 3D-printer firmware uses).
pub const STANDARD_BAUDS: [u32; 28] = [
    50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19_200, 38_400, 57_600,
    115_200, 230_400, 250_000, 460_800, 500_000, 576_000, 921_600, 1_000_000, 1_500_000, 2_000_000,
    3_000_000, 4_000_000,
];

/// One finding: the dotted key, what is wrong, and whether edod cannot run with it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Finding {
    /// Dotted key (`api.group`).
    pub key: &'static str,
    /// What is wrong, for a person.
    pub message: String,
    /// An error (edod would fail) rather than a warning.
    pub error: bool,
}

impl std::fmt::Display for Finding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let level = if self.error { "error" } else { "warning" };
        write!(f, "{level}: {}: {}", self.key, self.message)
    }
}

fn error(key: &'static str, message: String) -> Finding {
    Finding {
        key,
        message,
        error: true,
    }
}

fn warning(key: &'static str, message: String) -> Finding {
    Finding {
        key,
        message,
        error: false,
    }
}

/// Every finding about `cfg` on this host, errors first.
pub fn check(cfg: &Config) -> Vec<Finding> {
    let mut found: Vec<Finding> = [
        socket_path(&cfg.api.socket),
        group(cfg.api.group.as_deref()),
        faults(cfg),
        port(&cfg.serial.port),
        baud(cfg.serial.baud),
        token_file(cfg),
    ]
    .into_iter()
    .flatten()
    .collect();
    found.sort_by_key(|f| !f.error);
    found
}

/// A token file that cannot be read, or holds no usable token.
fn token_file(cfg: &Config) -> Option<Finding> {
    if !cfg.http.enabled {
        return None;
    }
    cfg.http.token().err().map(|m| error("http.token_file", m))
}

fn socket_path(socket: &Path) -> Option<Finding> {
    let n = socket.as_os_str().len();
    (n > MAX_SOCKET_PATH).then(|| {
        error(
            "api.socket",
            format!(
                "{} is {n} bytes; a Unix socket path holds at most {MAX_SOCKET_PATH} \
                 (sun_path): choose a shorter one",
                socket.display()
            ),
        )
    })
}

fn group(group: Option<&str>) -> Option<Finding> {
    let g = group?;
    match nix::unistd::Group::from_name(g) {
        Ok(Some(_)) => None,
        Ok(None) => Some(error(
            "api.group",
            format!("no group {g:?} on this host (create it, or leave api.group out)"),
        )),
        Err(e) => Some(error(
            "api.group",
            format!("cannot look up group {g:?}: {e}"),
        )),
    }
}

fn faults(cfg: &Config) -> Option<Finding> {
    if cfg.serial.port != SIM_PORT {
        return None;
    }
    crate::link::sim_faults::Faults::parse(&cfg.sim.faults)
        .err()
        .map(|e| error("sim.faults", e.to_string()))
}

fn port(port: &str) -> Option<Finding> {
    if port == SIM_PORT {
        return None;
    }
    use std::os::unix::fs::FileTypeExt;
    match std::fs::metadata(port) {
        Ok(m) if m.file_type().is_char_device() => None,
        Ok(_) => Some(error(
            "serial.port",
            format!("{port} is not a serial device (not a character device)"),
        )),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Some(warning(
            "serial.port",
            format!(
                "port {port} does not exist (edod starts and waits for it: is the machine \
                 plugged in and the path right?)"
            ),
        )),
        Err(e) => Some(warning("serial.port", format!("port {port}: {e}"))),
    }
}

fn baud(baud: u32) -> Option<Finding> {
    if STANDARD_BAUDS.contains(&baud) {
        return None;
    }
    let (lo, hi) = (STANDARD_BAUDS[0], STANDARD_BAUDS[STANDARD_BAUDS.len() - 1]);
    if !(lo..=hi).contains(&baud) {
        return Some(error(
            "serial.baud",
            format!("{baud} is not a line speed a serial port runs at ({lo} to {hi}; usually 115200 or 250000)"),
        ));
    }
    Some(warning(
        "serial.baud",
        format!("{baud} is not a standard rate; many adapters refuse it or round it (usually 115200 or 250000)"),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn findings(text: &str) -> Vec<Finding> {
        check(&Config::from_toml(text, "t.toml").unwrap())
    }

    #[test]
    fn the_defaults_pass() {
        assert_eq!(findings(""), vec![]);
    }

    #[test]
    fn what_can_only_fail_is_an_error_naming_its_key() {
        let long = format!("/tmp/{}.sock", "s".repeat(110));
        for (text, key, says) in [
            (
                format!("[api]\nsocket = {long:?}"),
                "api.socket",
                "sun_path",
            ),
            (
                "[api]\ngroup = \"no-such-group-edo\"".to_string(),
                "api.group",
                "no group",
            ),
            (
                "[sim]\nfaults = \"drop=0.1,frobnicate=2\"".to_string(),
                "sim.faults",
                "frobnicate",
            ),
            ("[serial]\nbaud = 1".to_string(), "serial.baud", "1 is not"),
            (
                "[serial]\nport = \"/etc/hostname\"".to_string(),
                "serial.port",
                "not a serial device",
            ),
            (
                "[http]\nlisten = \"0.0.0.0:7125\"\ntoken_file = \"/nonexistent/edo-token\""
                    .to_string(),
                "http.token_file",
                "cannot read /nonexistent/edo-token",
            ),
        ] {
            let f = findings(&text);
            assert!(
                f.iter()
                    .any(|f| f.error && f.key == key && f.message.contains(says)),
                "{text}: {f:?}"
            );
        }
    }

    #[test]
    fn what_may_be_right_later_is_a_warning() {
        let f = findings("[serial]\nport = \"/dev/ttyEDOnone\"\nbaud = 74880");
        assert_eq!(f.len(), 2, "{f:?}");
        assert!(f.iter().all(|f| !f.error));
        assert!(f[0].message.contains("port /dev/ttyEDOnone does not exist"));
        assert!(f[1].message.contains("74880 is not a standard rate"));
        assert_eq!(
            findings("[serial]\nport = \"/dev/null\"\nbaud = 115200"),
            vec![]
        );
    }
}
