//! Who may do what over HTTP (`docs/http.md`, Security), as pure checks of a request's
//! method, path, headers and query, so each rule is tested without a network.
//!
//! - A loopback bind answers only requests addressed to a loopback name (`Host`), so a
//!   web page whose DNS name is made to point at 127.0.0.1 (DNS rebinding) reaches
//!   nothing.
//! - A WebSocket upgrade or a POST that a browser sends from another origin (`Origin`
//!   not `http://` + the request's `Host`) is refused (403): no cross-site control of a
//!   printer. Clients that are not browsers send no `Origin` and are not concerned.
//! - With a token (`http.token_file`; required beyond loopback), every WebSocket upgrade
//!   and POST carries it, as `Authorization: Bearer TOKEN` or, for a browser's
//!   WebSocket, which cannot set headers, as `?token=TOKEN` (401 otherwise). Beyond
//!   loopback every read carries it too (the queue and the job files are the
//!   operator's) but for the page's own files ([`PAGE_FILES`]): the page asks for it.

use axum::http::{header, HeaderMap, Method, StatusCode};

/// The page's files: served to anyone who may reach the listener (they hold no data).
pub const PAGE_FILES: [&str; 3] = ["/", "/app.js", "/app.css"];

/// The rules of one listener.
#[derive(Debug, Clone)]
pub struct Guard {
    /// The token every state-changing request must carry, if any.
    pub token: Option<String>,
    /// The listener is bound to a loopback address.
    pub loopback: bool,
}

/// What a request is, for the rules.
pub struct Ask<'a> {
    /// Its method.
    pub method: &'a Method,
    /// Its path (`/websocket`, `/api/rpc`).
    pub path: &'a str,
    /// Its query string, if any.
    pub query: Option<&'a str>,
    /// Its headers.
    pub headers: &'a HeaderMap,
    /// The authority of an absolute-form request target (`GET http://host/path`), which
    /// HTTP/1.1 says stands for `Host`.
    pub authority: Option<&'a str>,
}

impl Ask<'_> {
    /// A request that can change the machine's or the queue's state: a POST, or a
    /// WebSocket (which carries every method).
    fn changes_state(&self) -> bool {
        *self.method != Method::GET && *self.method != Method::HEAD || self.path == "/websocket"
    }

    /// A request for one of the page's own files ([`PAGE_FILES`]); anything else is the
    /// API (`/api/...`, `/websocket`) or nothing.
    fn is_page_file(&self) -> bool {
        PAGE_FILES.contains(&self.path)
    }
}

/// Equal without telling how much of a secret matched by how long it took.
fn same_secret(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
}

fn header_str(headers: &HeaderMap, name: header::HeaderName) -> Option<&str> {
    headers.get(name).and_then(|v| v.to_str().ok())
}

/// Whether `host` (a `Host` header: name or address, optional port) names this machine's
/// loopback interface.
fn loopback_host(host: &str) -> bool {
    let name = if let Some(rest) = host.strip_prefix('[') {
        rest.split(']').next().unwrap_or("")
    } else {
        host.rsplit_once(':').map_or(host, |(n, _)| n)
    };
    let name = name.trim_end_matches('.').to_ascii_lowercase();
    name == "localhost"
        || name.ends_with(".localhost")
        || name
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

impl Guard {
    /// `Ok` if `ask` may go on; the status that refuses it otherwise, with the reason.
    pub fn check(&self, ask: &Ask) -> Result<(), (StatusCode, &'static str)> {
        // One `Host`, and an absolute-form target naming the same: otherwise which one
        // the rules below judged and which one a proxy or the page acted on may differ.
        if ask.headers.get_all(header::HOST).iter().count() > 1 {
            return Err((StatusCode::BAD_REQUEST, "more than one Host header"));
        }
        let host = header_str(ask.headers, header::HOST);
        if let Some(authority) = ask.authority {
            if !host.is_some_and(|h| h.eq_ignore_ascii_case(authority)) {
                return Err((
                    StatusCode::BAD_REQUEST,
                    "the request target names another host than the Host header",
                ));
            }
        }
        if self.loopback && !host.is_some_and(loopback_host) {
            return Err((
                StatusCode::FORBIDDEN,
                "edod listens on loopback only: address it as localhost or 127.0.0.1",
            ));
        }
        let changes_state = ask.changes_state();
        if changes_state {
            Self::same_origin(ask, host)?;
        }
        // Beyond loopback the token guards every call of the API, reads too; on
        // loopback (where a token is optional) the calls that change state.
        let guarded = changes_state || (!self.loopback && !ask.is_page_file());
        if let (true, Some(token)) = (guarded, &self.token) {
            if !self.carries(ask, token) {
                return Err((
                    StatusCode::UNAUTHORIZED,
                    "this call needs the token of http.token_file (Authorization: Bearer)",
                ));
            }
        }
        Ok(())
    }

    /// A WebSocket upgrade or a POST sent by a page of another origin is refused.
    fn same_origin(ask: &Ask, host: Option<&str>) -> Result<(), (StatusCode, &'static str)> {
        if let Some(origin) = header_str(ask.headers, header::ORIGIN) {
            let own = host.map(|h| format!("http://{h}"));
            if own.as_deref() != Some(origin) {
                return Err((
                    StatusCode::FORBIDDEN,
                    "a page of another origin may not control the printer",
                ));
            }
        }
        Ok(())
    }

    /// Whether `ask` carries `token` (header, or the query of a WebSocket upgrade).
    fn carries(&self, ask: &Ask, token: &str) -> bool {
        let bearer = header_str(ask.headers, header::AUTHORIZATION)
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim);
        let query = (ask.path == "/websocket")
            .then(|| {
                ask.query?
                    .split('&')
                    .find_map(|kv| kv.strip_prefix("token="))
            })
            .flatten();
        [bearer, query]
            .into_iter()
            .flatten()
            .any(|t| same_secret(t.as_bytes(), token.as_bytes()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    const TOKEN: &str = "0123456789abcdef0123";

    fn headers(pairs: &[(header::HeaderName, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(k.clone(), HeaderValue::from_str(v).unwrap());
        }
        h
    }

    fn check(g: &Guard, method: Method, path: &str, query: Option<&str>, h: &HeaderMap) -> u16 {
        let ask = Ask {
            method: &method,
            path,
            query,
            headers: h,
            authority: None,
        };
        g.check(&ask).map_or_else(|(s, _)| s.as_u16(), |()| 200)
    }

    /// Two `Host` headers, or an absolute-form target naming another host than `Host`
    /// (issue 41's probe: both were accepted): 400, whatever the listener.
    #[test]
    fn one_host_and_the_same_in_an_absolute_target() {
        for loopback in [true, false] {
            let g = Guard {
                token: None,
                loopback,
            };
            let mut two = headers(&[(header::HOST, "127.0.0.1:7125")]);
            two.append(header::HOST, HeaderValue::from_static("evil.example"));
            assert_eq!(check(&g, Method::GET, "/api/jobs", None, &two), 400);
            let one = headers(&[(header::HOST, "127.0.0.1:7125")]);
            let ask = |authority| Ask {
                method: &Method::GET,
                path: "/api/jobs",
                query: None,
                headers: &one,
                authority,
            };
            let refused = g.check(&ask(Some("evil.example"))).err().map(|(s, _)| s);
            assert_eq!(refused, Some(StatusCode::BAD_REQUEST));
            assert!(g.check(&ask(Some("127.0.0.1:7125"))).is_ok());
        }
    }

    #[test]
    fn a_loopback_bind_answers_loopback_names_only() {
        let g = Guard {
            token: None,
            loopback: true,
        };
        for host in [
            "127.0.0.1:7125",
            "localhost:7125",
            "[::1]:7125",
            "localhost",
        ] {
            let h = headers(&[(header::HOST, host)]);
            assert_eq!(check(&g, Method::GET, "/", None, &h), 200, "{host}");
        }
        for host in ["evil.example:7125", "192.168.1.5:7125"] {
            let h = headers(&[(header::HOST, host)]);
            assert_eq!(check(&g, Method::GET, "/", None, &h), 403, "{host}");
        }
        assert_eq!(check(&g, Method::GET, "/", None, &HeaderMap::new()), 403);
    }

    #[test]
    fn another_origin_may_not_post_or_open_a_websocket() {
        let g = Guard {
            token: None,
            loopback: true,
        };
        let own = headers(&[
            (header::HOST, "127.0.0.1:7125"),
            (header::ORIGIN, "http://127.0.0.1:7125"),
        ]);
        let other = headers(&[
            (header::HOST, "127.0.0.1:7125"),
            (header::ORIGIN, "http://evil.example"),
        ]);
        let script = headers(&[(header::HOST, "127.0.0.1:7125")]);
        assert_eq!(check(&g, Method::GET, "/websocket", None, &own), 200);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &own), 200);
        assert_eq!(check(&g, Method::GET, "/websocket", None, &other), 403);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &other), 403);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &script), 200);
        // Reads are not refused for their origin (a browser does not let the other
        // page read the answer).
        assert_eq!(check(&g, Method::GET, "/api/jobs", None, &other), 200);
    }

    #[test]
    fn with_a_token_every_state_changing_request_carries_it() {
        let g = Guard {
            token: Some(TOKEN.into()),
            loopback: false,
        };
        let host = (header::HOST, "printer.lan:7125");
        let none = headers(std::slice::from_ref(&host));
        let good = headers(&[
            host.clone(),
            (header::AUTHORIZATION, "Bearer 0123456789abcdef0123"),
        ]);
        let bad = headers(&[
            host.clone(),
            (header::AUTHORIZATION, "Bearer 0123456789abcdef0124"),
        ]);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &none), 401);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &bad), 401);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &good), 200);
        assert_eq!(check(&g, Method::GET, "/websocket", None, &none), 401);
        assert_eq!(check(&g, Method::GET, "/websocket", None, &good), 200);
        let q = format!("x=1&token={TOKEN}");
        assert_eq!(check(&g, Method::GET, "/websocket", Some(&q), &none), 200);
        // The query carries a token for the WebSocket alone.
        assert_eq!(check(&g, Method::POST, "/api/rpc", Some(&q), &none), 401);
        // Beyond loopback the reads of the API need it too; the page's files do not
        // (the page asks for the token); any host name is answered.
        for read in [
            "/api/status",
            "/api/jobs",
            "/api/jobs/1",
            "/api/server",
            "/api",
        ] {
            assert_eq!(check(&g, Method::GET, read, None, &none), 401, "{read}");
            assert_eq!(check(&g, Method::GET, read, None, &bad), 401, "{read}");
            assert_eq!(check(&g, Method::GET, read, None, &good), 200, "{read}");
        }
        // The query carries no token but for the WebSocket.
        assert_eq!(check(&g, Method::GET, "/api/jobs", Some(&q), &none), 401);
        for page in PAGE_FILES {
            assert_eq!(check(&g, Method::GET, page, None, &none), 200, "{page}");
        }
        // Whatever is not a page file is guarded, however it is spelled.
        for odd in ["//api/jobs", "/API/jobs", "/%61pi/jobs", "/nothing"] {
            assert_eq!(check(&g, Method::GET, odd, None, &none), 401, "{odd}");
        }
    }

    #[test]
    fn on_loopback_reads_need_no_token_even_with_one() {
        let g = Guard {
            token: Some(TOKEN.into()),
            loopback: true,
        };
        let none = headers(&[(header::HOST, "127.0.0.1:7125")]);
        assert_eq!(check(&g, Method::GET, "/api/jobs", None, &none), 200);
        assert_eq!(check(&g, Method::GET, "/api/status", None, &none), 200);
        assert_eq!(check(&g, Method::POST, "/api/rpc", None, &none), 401);
        let open = Guard {
            token: None,
            loopback: true,
        };
        assert_eq!(check(&open, Method::GET, "/api/jobs", None, &none), 200);
        assert_eq!(check(&open, Method::POST, "/api/rpc", None, &none), 200);
    }

    #[test]
    fn secrets_compare_whole() {
        assert!(same_secret(b"abc", b"abc"));
        assert!(!same_secret(b"abc", b"abd"));
        assert!(!same_secret(b"abc", b"abcd"));
        assert!(!same_secret(b"", b"a"));
    }
}
