//! `[http]`: the web dashboard and its WebSocket (`docs/http.md`).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;

/// `[http]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HttpConfig {
    /// Serve the dashboard (default true).
    #[serde(default = "default_enabled")]
    pub enabled: bool,
    /// Address and port (default `127.0.0.1:7125`: loopback only).
    #[serde(default = "default_listen")]
    pub listen: String,
    /// A file holding the bearer token every state-changing call must carry; required
    /// when `listen` is not a loopback address (default none).
    #[serde(default)]
    pub token_file: Option<PathBuf>,
    /// Most plans kept for previews and layer views (default 8).
    #[serde(default = "default_plan_cache_entries")]
    pub plan_cache_entries: usize,
    /// Most bytes of layer views and SVG previews the kept plans hold (default 64 MiB).
    #[serde(default = "default_plan_cache_bytes")]
    pub plan_cache_bytes: usize,
    /// Longest one request plans a preview or a layer view, s (default 60); a later
    /// request goes on from where it stopped.
    #[serde(default = "default_plan_time_limit_s")]
    pub plan_time_limit_s: f64,
}

fn default_enabled() -> bool {
    true
}
fn default_listen() -> String {
    "127.0.0.1:7125".to_string()
}
fn default_plan_cache_entries() -> usize {
    8
}
fn default_plan_cache_bytes() -> usize {
    64 << 20
}
fn default_plan_time_limit_s() -> f64 {
    60.0
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            enabled: default_enabled(),
            listen: default_listen(),
            token_file: None,
            plan_cache_entries: default_plan_cache_entries(),
            plan_cache_bytes: default_plan_cache_bytes(),
            plan_time_limit_s: default_plan_time_limit_s(),
        }
    }
}

/// Shortest token accepted (bytes): guessing one must be hopeless.
pub const MIN_TOKEN_BYTES: usize = 16;

impl HttpConfig {
    /// `listen` as a socket address.
    pub fn listen_addr(&self) -> Result<SocketAddr, String> {
        self.listen.parse().map_err(|e| {
            format!(
                "{:?} is not an address and port such as \"127.0.0.1:7125\": {e}",
                self.listen
            )
        })
    }

    /// The dotted key and the problem of a `[http]` that cannot be used whatever the
    /// host: an unparsable address, or one beyond loopback without a token file.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !self.enabled {
            return Ok(());
        }
        let addr = self.listen_addr().map_err(|m| ("http.listen", m))?;
        if !(self.plan_time_limit_s.is_finite() && self.plan_time_limit_s > 0.0) {
            return Err((
                "http.plan_time_limit_s",
                format!(
                    "must be a positive number of seconds, got {}",
                    self.plan_time_limit_s
                ),
            ));
        }
        if self.plan_cache_entries == 0 {
            return Err((
                "http.plan_cache_entries",
                "must be at least 1 (a preview's layers are drawn from its kept plan)".into(),
            ));
        }
        if !addr.ip().is_loopback() && self.token_file.is_none() {
            return Err((
                "http.token_file",
                format!(
                    "http.listen = {:?} is reachable from other hosts: set a token file \
                     (every state-changing call must then carry its token)",
                    self.listen
                ),
            ));
        }
        Ok(())
    }

    /// The token from `token_file` (none without one), or what is wrong with the file.
    pub fn token(&self) -> Result<Option<String>, String> {
        self.token_file.as_deref().map(read_token).transpose()
    }
}

/// The token in `path`: its first line, trimmed, of at least [`MIN_TOKEN_BYTES`].
pub fn read_token(path: &Path) -> Result<String, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let token = text.lines().next().unwrap_or("").trim().to_string();
    if token.len() < MIN_TOKEN_BYTES {
        return Err(format!(
            "{}: the token must be at least {MIN_TOKEN_BYTES} characters on its first line",
            path.display()
        ));
    }
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(format!(
            "{}: the token must be printable ASCII without spaces",
            path.display()
        ));
    }
    Ok(token)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn http(listen: &str, token_file: Option<&str>) -> HttpConfig {
        HttpConfig {
            enabled: true,
            listen: listen.into(),
            token_file: token_file.map(PathBuf::from),
            ..HttpConfig::default()
        }
    }

    #[test]
    fn beyond_loopback_a_token_file_is_required() {
        assert!(http("127.0.0.1:7125", None).check().is_ok());
        assert!(http("[::1]:7125", None).check().is_ok());
        let (key, m) = http("0.0.0.0:7125", None).check().unwrap_err();
        assert_eq!(key, "http.token_file");
        assert!(m.contains("0.0.0.0:7125"), "{m}");
        assert!(http("0.0.0.0:7125", Some("/t")).check().is_ok());
        assert_eq!(
            http("localhost", None).check().unwrap_err().0,
            "http.listen"
        );
        let off = HttpConfig {
            enabled: false,
            ..http("nonsense", None)
        };
        assert!(off.check().is_ok());
        let no_plans = HttpConfig {
            plan_cache_entries: 0,
            ..http("127.0.0.1:7125", None)
        };
        assert_eq!(no_plans.check().unwrap_err().0, "http.plan_cache_entries");
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let no_time = HttpConfig {
                plan_time_limit_s: bad,
                ..http("127.0.0.1:7125", None)
            };
            assert_eq!(no_time.check().unwrap_err().0, "http.plan_time_limit_s");
        }
    }

    #[test]
    fn a_token_file_must_be_readable_and_long_enough() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("token");
        assert!(read_token(&f).unwrap_err().contains("cannot read"));
        std::fs::write(&f, "short\n").unwrap();
        assert!(read_token(&f).unwrap_err().contains("at least 16"));
        std::fs::write(&f, "0123456789abcdef0123\nignored\n").unwrap();
        assert_eq!(read_token(&f).unwrap(), "0123456789abcdef0123");
    }
}
