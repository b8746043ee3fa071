//! The HTTP layer's rules, each on the router (`tower::ServiceExt::oneshot`) or, for
//! the WebSocket, on a real listener on 127.0.0.1:0.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{header, Request, StatusCode};
use http_body_util::BodyExt;
use tokio::sync::{broadcast, mpsc, watch};
use tower::ServiceExt;

use super::{router, Guard};
use crate::daemon::{Config, Control, Shared};

const TOKEN: &str = "0123456789abcdef0123";

/// A daemon's shared state on a temporary store, with a streamer that acknowledges
/// e-stops.
async fn shared(dir: &std::path::Path, max_request_bytes: usize) -> Arc<Shared> {
    shared_with(dir, |c| c.api.max_request_bytes = max_request_bytes).await
}

/// As [`shared`], `set` changing the configuration.
async fn shared_with(dir: &std::path::Path, set: impl FnOnce(&mut Config)) -> Arc<Shared> {
    let mut config = Config::from_toml("", "test").unwrap();
    config.api.max_request_bytes = 1 << 20;
    set(&mut config);
    config.api.idle_timeout_s = 2.0;
    config.state.dir = dir.to_path_buf();
    let (events, _) = mpsc::unbounded_channel();
    let opened = crate::daemon::store::start(dir.to_path_buf(), 1000, events)
        .await
        .unwrap();
    let (control, mut rx) = mpsc::channel(8);
    tokio::spawn(async move {
        while let Some(c) = rx.recv().await {
            if let Control::EStop(_, reply) = c {
                let _ = reply.send(Ok(crate::proto::EStopTiming {
                    written_after_us: 10,
                    acked_after_us: Some(20),
                }));
            }
        }
    });
    Arc::new(Shared {
        budget: crate::daemon::connections::Budget::new(&config.api),
        config,
        store: opened.stores,
        notify: broadcast::channel(64).0,
        machine: watch::channel(Default::default()).0,
        progress: watch::channel(None).0,
        control,
        port: "sim".into(),
        alive: Default::default(),
        stopping: Default::default(),
        log: watch::channel(Default::default()).0,
    })
}

fn loopback() -> Guard {
    Guard {
        token: None,
        loopback: true,
    }
}

fn beyond_loopback() -> Guard {
    Guard {
        token: Some(TOKEN.into()),
        loopback: false,
    }
}

const HOST: &str = "127.0.0.1:7125";

fn rpc(method: &str) -> String {
    format!(r#"{{"jsonrpc":"2.0","id":1,"method":"{method}"}}"#)
}

async fn send(app: axum::Router, req: Request<Body>) -> (StatusCode, String) {
    let r = app.oneshot(req).await.unwrap();
    let status = r.status();
    let body = r.into_body().collect().await.unwrap().to_bytes();
    (status, String::from_utf8_lossy(&body).into_owned())
}

fn post(path: &str) -> axum::http::request::Builder {
    Request::post(path).header(header::HOST, HOST)
}

#[tokio::test]
async fn the_page_is_served_small_and_unknown_paths_are_not_found() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(shared(dir.path(), 1 << 20).await, loopback());
    let get = |p: &str| {
        Request::get(p)
            .header(header::HOST, HOST)
            .body(Body::empty())
            .unwrap()
    };
    let (s, body) = send(app.clone(), get("/")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(body.contains("<html"), "{body}");
    assert!(
        body.len() + super::page::SCRIPT.len() + super::page::STYLE.len() < 500_000,
        "the page is over 500 kB"
    );
    for p in ["/app.js", "/app.css"] {
        assert_eq!(send(app.clone(), get(p)).await.0, StatusCode::OK, "{p}");
    }
    // Nothing a client sends names a file: these reach no file system.
    for p in [
        "/../../etc/passwd",
        "/etc/passwd",
        "/app.js/../../Cargo.toml",
        "/%2e%2e/x",
    ] {
        assert_eq!(
            send(app.clone(), get(p)).await.0,
            StatusCode::NOT_FOUND,
            "{p}"
        );
    }
    assert_eq!(
        send(app.clone(), get("/api/jobs/..%2F..%2Fetc")).await.0,
        StatusCode::BAD_REQUEST
    );
}

#[tokio::test]
async fn reads_answer_as_the_methods_they_name() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(shared(dir.path(), 1 << 20).await, beyond_loopback());
    let get = |p: &str| {
        Request::get(p)
            .header(header::HOST, "printer.lan")
            .header(header::AUTHORIZATION, format!("Bearer {TOKEN}"))
            .body(Body::empty())
            .unwrap()
    };
    let (s, body) = send(app.clone(), get("/api/jobs")).await;
    assert_eq!((s, body.as_str()), (StatusCode::OK, "[]"));
    let (s, body) = send(app.clone(), get("/api/status")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(body.contains("\"executed_total\":0"), "{body}");
    let (s, body) = send(app.clone(), get("/api/server")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(body.contains("\"token_required\":true"), "{body}");
    let (s, body) = send(app.clone(), get("/api/jobs/7")).await;
    assert_eq!(s, StatusCode::NOT_FOUND, "{body}");
    assert!(body.contains("-32001"), "{body}");
    assert_eq!(
        send(app.clone(), get("/api/jobs/7/layers/0")).await.0,
        StatusCode::NOT_FOUND
    );
}

#[tokio::test]
async fn beyond_loopback_a_call_without_the_token_is_refused_401() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(shared(dir.path(), 1 << 20).await, beyond_loopback());
    let call = |auth: Option<&str>| {
        let mut b = Request::post("/api/rpc").header(header::HOST, "printer.lan:7125");
        if let Some(a) = auth {
            b = b.header(header::AUTHORIZATION, a);
        }
        b.body(Body::from(rpc("machine.estop"))).unwrap()
    };
    assert_eq!(
        send(app.clone(), call(None)).await.0,
        StatusCode::UNAUTHORIZED
    );
    assert_eq!(
        send(app.clone(), call(Some("Bearer wrong-token-wrong-token")))
            .await
            .0,
        StatusCode::UNAUTHORIZED
    );
    let (s, body) = send(app.clone(), call(Some(&format!("Bearer {TOKEN}")))).await;
    assert_eq!(s, StatusCode::OK);
    assert!(body.contains("\"acked_after_us\":20"), "{body}");
}

#[tokio::test]
async fn beyond_loopback_reads_need_the_token_but_the_page_does_not() {
    let dir = tempfile::tempdir().unwrap();
    let shared = shared(dir.path(), 1 << 20).await;
    let get = |p: &str, auth: Option<&str>| {
        let mut b = Request::get(p).header(header::HOST, "printer.lan:7125");
        if let Some(a) = auth {
            b = b.header(header::AUTHORIZATION, a);
        }
        b.body(Body::empty()).unwrap()
    };
    let bearer = format!("Bearer {TOKEN}");
    let app = router(Arc::clone(&shared), beyond_loopback());
    for p in [
        "/api/server",
        "/api/status",
        "/api/jobs",
        "/api/jobs/1/layers/0",
    ] {
        let (s, body) = send(app.clone(), get(p, None)).await;
        assert_eq!(s, StatusCode::UNAUTHORIZED, "{p}: {body}");
        assert!(body.contains("http.token_file"), "{p}: {body}");
        let (s, _) = send(app.clone(), get(p, Some("Bearer not-the-token-at-all"))).await;
        assert_eq!(s, StatusCode::UNAUTHORIZED, "{p}");
    }
    let (s, body) = send(app.clone(), get("/api/jobs", Some(&bearer))).await;
    assert_eq!((s, body.as_str()), (StatusCode::OK, "[]"));
    // The page loads without the token, and asks for it.
    for p in ["/", "/app.js", "/app.css"] {
        assert_eq!(
            send(app.clone(), get(p, None)).await.0,
            StatusCode::OK,
            "{p}"
        );
    }
    // On loopback the reads stay open, with or without a token file.
    let on_loopback = Guard {
        token: Some(TOKEN.into()),
        loopback: true,
    };
    for guard in [loopback(), on_loopback] {
        let app = router(Arc::clone(&shared), guard);
        let r = Request::get("/api/jobs")
            .header(header::HOST, HOST)
            .body(Body::empty())
            .unwrap();
        assert_eq!(send(app, r).await, (StatusCode::OK, "[]".to_string()));
    }
}

#[tokio::test]
async fn a_post_from_another_origin_is_refused_403() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(shared(dir.path(), 1 << 20).await, loopback());
    let call = |origin: &str| {
        post("/api/rpc")
            .header(header::ORIGIN, origin)
            .body(Body::from(rpc("server.info")))
            .unwrap()
    };
    assert_eq!(
        send(app.clone(), call("http://evil.example")).await.0,
        StatusCode::FORBIDDEN
    );
    let (s, body) = send(app.clone(), call("http://127.0.0.1:7125")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(body.contains("\"name\":\"edod\""), "{body}");
    // DNS rebinding: the right origin under another name is refused too.
    let rebound = Request::post("/api/rpc")
        .header(header::HOST, "evil.example:7125")
        .header(header::ORIGIN, "http://evil.example:7125")
        .body(Body::from(rpc("machine.estop")))
        .unwrap();
    assert_eq!(send(app.clone(), rebound).await.0, StatusCode::FORBIDDEN);
}

#[tokio::test]
async fn a_body_over_the_request_limit_is_refused_413() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(shared(dir.path(), 4096).await, loopback());
    let big = format!(
        r#"{{"jsonrpc":"2.0","id":1,"method":"server.info","x":"{}"}}"#,
        "x".repeat(5000)
    );
    let r = post("/api/rpc").body(Body::from(big)).unwrap();
    assert_eq!(send(app.clone(), r).await.0, StatusCode::PAYLOAD_TOO_LARGE);
    let r = post("/api/preview")
        .body(Body::from(vec![b' '; 5000]))
        .unwrap();
    assert_eq!(send(app.clone(), r).await.0, StatusCode::PAYLOAD_TOO_LARGE);
}

#[tokio::test]
async fn a_preview_names_what_a_submission_would_refuse() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(shared(dir.path(), 1 << 20).await, loopback());
    let job = std::fs::read_to_string("config/examples/paper-annulus.toml").unwrap();
    let body = serde_json::json!({ "job": job }).to_string();
    let (s, out) = send(
        app.clone(),
        post("/api/preview").body(Body::from(body)).unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{out}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["ok"], true, "{out:.300}");
    assert!(!v["layers"].as_array().unwrap().is_empty());
    assert!(v["view"]["moves"].as_array().unwrap().len() > 10);
    // Too large for the machine: named, not planned.
    let big = job.replace("radius = 30.0", "radius = 300.0");
    let body = serde_json::json!({ "job": big }).to_string();
    let (_, out) = send(
        app.clone(),
        post("/api/preview").body(Body::from(body)).unwrap(),
    )
    .await;
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["ok"], false, "{out:.300}");
    assert!(
        v["problems"].to_string().contains("build volume"),
        "{out:.300}"
    );
}

/// A real listener on 127.0.0.1:0 serving `guard`.
async fn listen(shared: Arc<Shared>, guard: Guard) -> std::net::SocketAddr {
    let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    tokio::spawn(super::serve(shared, super::Listening::new(l, guard)));
    addr
}

#[tokio::test]
async fn the_websocket_carries_the_methods_and_the_notifications() {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::Message;
    let dir = tempfile::tempdir().unwrap();
    let shared = shared(dir.path(), 1 << 20).await;
    let addr = listen(Arc::clone(&shared), loopback()).await;
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/websocket"))
        .await
        .unwrap();
    ws.send(Message::text(rpc("subscribe"))).await.unwrap();
    let reply = ws.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(reply.contains("notify_job_progress"), "{reply}");
    shared.notify(crate::proto::Event::MachineState(Default::default()));
    let pushed = ws.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(
        pushed.contains("\"method\":\"notify_machine_state\""),
        "{pushed}"
    );
    ws.send(Message::text(rpc("machine.estop"))).await.unwrap();
    let reply = ws.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(reply.contains("\"acked_after_us\":20"), "{reply}");
    // Over api.max_request_bytes: refused as on the socket, and the connection closed.
    ws.send(Message::text("x".repeat(2 << 20))).await.unwrap();
    let refusal = ws.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(refusal.contains("api.max_request_bytes"), "{refusal}");
    let end = ws.next().await;
    assert!(
        !matches!(end, Some(Ok(Message::Text(_)))),
        "still answering after a message over the limit: {end:?}"
    );
}

#[tokio::test]
async fn a_websocket_from_another_origin_or_without_the_token_is_refused() {
    use tokio_tungstenite::tungstenite::{client::IntoClientRequest, Error};
    let dir = tempfile::tempdir().unwrap();
    let shared = shared(dir.path(), 1 << 20).await;
    let addr = listen(Arc::clone(&shared), loopback()).await;
    let mut req = format!("ws://{addr}/websocket")
        .into_client_request()
        .unwrap();
    req.headers_mut()
        .insert(header::ORIGIN, "http://evil.example".parse().unwrap());
    match tokio_tungstenite::connect_async(req).await {
        Err(Error::Http(r)) => assert_eq!(r.status(), StatusCode::FORBIDDEN),
        other => panic!("cross-origin WebSocket not refused: {other:?}"),
    }
    let addr = listen(shared, beyond_loopback()).await;
    match tokio_tungstenite::connect_async(format!("ws://{addr}/websocket")).await {
        Err(Error::Http(r)) => assert_eq!(r.status(), StatusCode::UNAUTHORIZED),
        other => panic!("token-less WebSocket not refused: {other:?}"),
    }
    let with = format!("ws://{addr}/websocket?token={TOKEN}");
    assert!(tokio_tungstenite::connect_async(with).await.is_ok());
}

/// Open a WebSocket on `addr` by hand (raw TCP): the stream after the 101 answer.
async fn raw_websocket(addr: std::net::SocketAddr) -> tokio::net::TcpStream {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let hello = format!(
        "GET /websocket HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    );
    s.write_all(hello.as_bytes()).await.unwrap();
    let mut head = Vec::new();
    while !head.ends_with(b"\r\n\r\n") {
        let mut b = [0u8; 1];
        assert_eq!(
            s.read(&mut b).await.unwrap(),
            1,
            "closed during the upgrade"
        );
        head.push(b[0]);
    }
    let head = String::from_utf8_lossy(&head);
    assert!(head.starts_with("HTTP/1.1 101"), "{head}");
    s
}

/// A message over `api.max_request_bytes` (64 kB here) is refused while it arrives:
/// the frame's header announces 1 MiB (within the WebSocket library's own limits), only
/// 4 kB follow, and edod answers the refusal and closes
/// at once (it would wait for the rest if it read messages whole before counting
/// them). Another dashboard is served on, before and after.
#[tokio::test]
async fn an_oversized_websocket_message_is_refused_as_it_arrives() {
    use futures_util::{SinkExt, StreamExt};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio_tungstenite::tungstenite::Message;
    let dir = tempfile::tempdir().unwrap();
    let shared = shared(dir.path(), 64 * 1024).await;
    let addr = listen(Arc::clone(&shared), loopback()).await;
    let (mut other, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/websocket"))
        .await
        .unwrap();
    other.send(Message::text(rpc("server.info"))).await.unwrap();
    let reply = other.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(reply.contains("\"name\":\"edod\""), "{reply}");

    let mut s = raw_websocket(addr).await;
    // FIN + text; masked, 64-bit length: 1 MiB announced.
    let mut frame = vec![0x81u8, 0x80 | 127];
    frame.extend_from_slice(&(1u64 << 20).to_be_bytes());
    frame.extend_from_slice(&[1, 2, 3, 4]);
    frame.extend(std::iter::repeat_n(b'x' ^ 1, 4096));
    s.write_all(&frame).await.unwrap();
    let mut answer = Vec::new();
    let read = tokio::time::timeout(
        std::time::Duration::from_secs(5),
        s.read_to_end(&mut answer),
    )
    .await;
    assert!(
        matches!(read, Ok(Ok(_))),
        "edod did not close the connection: it waits for the rest of the message"
    );
    let answer = String::from_utf8_lossy(&answer);
    assert!(answer.contains("api.max_request_bytes"), "{answer}");

    other
        .send(Message::text(rpc("machine.status")))
        .await
        .unwrap();
    let reply = other.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(reply.contains("\"executed_total\":0"), "{reply}");
}

fn annulus(radius_mm: f64) -> String {
    std::fs::read_to_string("config/examples/paper-annulus.toml")
        .unwrap()
        .replace("radius = 30.0", &format!("radius = {radius_mm:.1}"))
}

fn get(path: &str) -> Request<Body> {
    Request::get(path)
        .header(header::HOST, HOST)
        .body(Body::empty())
        .unwrap()
}

/// Preview `job`: the answer's JSON.
async fn preview_of(app: &axum::Router, job: &str) -> serde_json::Value {
    let body = serde_json::json!({ "job": job }).to_string();
    let (s, out) = send(
        app.clone(),
        post("/api/preview").body(Body::from(body)).unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{out:.300}");
    serde_json::from_str(&out).unwrap()
}

/// A preview past `http.plan_time_limit_s` answers with the layers planned, saying it
/// stopped; asked again it goes on from there (a layer at least each time). A request
/// given up (its client left, edod stopping) stops the same way.
#[tokio::test]
async fn a_preview_stops_at_its_time_limit_and_goes_on_when_asked_again() {
    let dir = tempfile::tempdir().unwrap();
    let sh = shared_with(dir.path(), |c| c.http.plan_time_limit_s = 1e-6).await;
    let app = super::app(Arc::clone(&sh), loopback());
    let routes = super::routes(Arc::clone(&app));
    let job = annulus(30.0).replace("height = 0.4", "height = 1.0");
    let first = preview_of(&routes, &job).await;
    assert_eq!(first["ok"], false, "{first:.300}");
    let said = first["problems"].to_string();
    assert!(said.contains("http.plan_time_limit_s"), "{said}");
    assert_eq!(first["layers"].as_array().unwrap().len(), 1, "{first:.300}");
    let second = preview_of(&routes, &job).await;
    assert_eq!(
        second["layers"].as_array().unwrap().len(),
        2,
        "{second:.300}"
    );
    assert_eq!(
        app.plans.cache.plans_made(),
        1,
        "went on, not planned again"
    );
    // edod stopping: the same, with its reason.
    sh.stopping
        .store(true, std::sync::atomic::Ordering::Relaxed);
    let third = preview_of(&routes, &job).await;
    assert_eq!(third["layers"].as_array().unwrap().len(), 3, "{third:.300}");
    assert!(
        third["problems"].to_string().contains("given up"),
        "{third:.300}"
    );
}

/// A preview's layers, its images and the layer views of the job once submitted come
/// from one plan: asked again, nothing is planned again.
#[tokio::test]
async fn a_preview_its_images_and_the_jobs_layer_views_share_one_plan() {
    let dir = tempfile::tempdir().unwrap();
    let app = super::app(shared(dir.path(), 1 << 20).await, loopback());
    let routes = super::routes(Arc::clone(&app));
    let made = || app.plans.cache.plans_made();
    let job = annulus(30.0);
    let v = preview_of(&routes, &job).await;
    assert_eq!(v["ok"], true, "{v:.300}");
    let id = v["id"].as_str().unwrap().to_string();
    assert_eq!(id.len(), 32, "{id}");
    let layers = v["layers"].as_array().unwrap().len();
    assert!(layers >= 2, "{v:.300}");
    assert_eq!(made(), 1);
    // What it takes: planned machine time (the layers' in all), material per
    // syringe, and where on the bed (the annulus of radius 30 centred on the bed).
    let time_s = v["time_s"].as_f64().unwrap();
    let layer_times: f64 = v["layers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["time_s"].as_f64().unwrap())
        .sum();
    assert!(
        time_s > 1.0 && (time_s - layer_times).abs() < 1e-6,
        "{time_s} {layer_times}"
    );
    let used: Vec<u64> = serde_json::from_value(v["used_nl"].clone()).unwrap();
    assert!(used.len() == 2 && used.iter().all(|&nl| nl > 0), "{used:?}");
    let (min, max) = (&v["extent_mm"]["min"], &v["extent_mm"]["max"]);
    let width_mm = max[0].as_f64().unwrap() - min[0].as_f64().unwrap();
    assert!((59.0..=61.0).contains(&width_mm), "{:?}", v["extent_mm"]);
    let centre_mm = (max[0].as_f64().unwrap() + min[0].as_f64().unwrap()) / 2.0;
    assert!((centre_mm - 100.0).abs() < 1.0, "{:?}", v["extent_mm"]);
    let again = preview_of(&routes, &job).await;
    assert_eq!(again["id"], v["id"]);
    assert_eq!(again["total_moves"], v["total_moves"]);
    for layer in 0..layers {
        let r = routes
            .clone()
            .oneshot(get(&format!("/api/previews/{id}/layers/{layer}")))
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK, "layer {layer}");
        assert_eq!(r.headers()[header::CONTENT_TYPE], "image/svg+xml");
        let svg = r.into_body().collect().await.unwrap().to_bytes();
        let svg = String::from_utf8_lossy(&svg);
        assert!(
            svg.starts_with("<svg") && svg.contains(&format!("layer {} z=", layer + 1)),
            "{svg:.200}"
        );
    }
    let (s, _) = send(
        routes.clone(),
        get(&format!("/api/previews/{id}/layers/{layers}")),
    )
    .await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "a layer past the last");
    // Submitted, the job's layer views come from the same plan.
    let submit = serde_json::json!({"jsonrpc": "2.0", "id": 1, "method": "job.submit", "params": {"job": job}});
    let (s, out) = send(
        routes.clone(),
        post("/api/rpc")
            .body(Body::from(submit.to_string()))
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    assert!(out.contains("\"id\":1"), "{out}");
    for layer in [1, 0] {
        let (s, out) = send(routes.clone(), get(&format!("/api/jobs/1/layers/{layer}"))).await;
        assert_eq!(s, StatusCode::OK, "{out:.300}");
        let view: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(view["layer"], layer);
        assert_eq!(view["layers"], layers);
        assert!(view["moves"].as_array().unwrap().len() > 10);
    }
    assert_eq!(made(), 1, "planned again");
    // Another job is another plan.
    let other = preview_of(&routes, &annulus(25.0)).await;
    assert_ne!(other["id"], v["id"]);
    assert_eq!(made(), 2);
    // An id never made, or not one.
    for bad in ["0123456789abcdef0123456789abcdef", "..%2F..%2Fetc", "zz"] {
        let (s, out) = send(
            routes.clone(),
            get(&format!("/api/previews/{bad}/layers/0")),
        )
        .await;
        assert_eq!(s, StatusCode::NOT_FOUND, "{bad}: {out}");
        assert!(out.contains("preview"), "{out}");
    }
}

/// The kept plans stay within `http.plan_cache_entries` and `http.plan_cache_bytes`:
/// the least recently used goes first; a layer past the byte bound is drawn from a plan
/// made again, not kept.
#[tokio::test]
async fn the_kept_plans_stay_within_their_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let two = shared_with(dir.path(), |c| {
        c.http.plan_cache_entries = 2;
    })
    .await;
    let app = super::app(two, loopback());
    let routes = super::routes(Arc::clone(&app));
    let cache = &app.plans.cache;
    let mut ids = Vec::new();
    for radius in [30.0, 28.0, 26.0] {
        ids.push(preview_of(&routes, &annulus(radius)).await["id"].clone());
        assert!(cache.held().0 <= 2, "{:?}", cache.held());
    }
    assert_eq!(cache.plans_made(), 3);
    let svg = |id: &serde_json::Value, layer: u32| {
        get(&format!(
            "/api/previews/{}/layers/{layer}",
            id.as_str().unwrap()
        ))
    };
    // The first, least recently used, is gone; the last two are kept.
    let (s, out) = send(routes.clone(), svg(&ids[0], 0)).await;
    assert_eq!(s, StatusCode::NOT_FOUND, "{out}");
    assert!(out.contains("preview the job again"), "{out}");
    for id in &ids[1..] {
        assert_eq!(send(routes.clone(), svg(id, 1)).await.0, StatusCode::OK);
    }
    assert_eq!(cache.plans_made(), 3);

    // Bytes: room for all but the last layer.
    let job = annulus(30.0);
    let full = {
        let dir = tempfile::tempdir().unwrap();
        let app = super::app(shared(dir.path(), 1 << 20).await, loopback());
        preview_of(&super::routes(Arc::clone(&app)), &job).await;
        app.plans.cache.held().1
    };
    let dir = tempfile::tempdir().unwrap();
    let tight = full - 33;
    let small = shared_with(dir.path(), |c| c.http.plan_cache_bytes = tight).await;
    let app = super::app(small, loopback());
    let routes = super::routes(Arc::clone(&app));
    let cache = &app.plans.cache;
    let v = preview_of(&routes, &job).await;
    let layers = v["layers"].as_array().unwrap().len() as u32;
    assert!(v["view"]["moves"].as_array().is_some(), "layer 0 kept");
    let (_, bytes) = cache.held();
    assert!(bytes <= tight, "{bytes} bytes held, bound {tight}");
    assert_eq!(cache.plans_made(), 1);
    // The last layer was not kept: planned again to draw it, and not kept either.
    let (s, out) = send(routes.clone(), svg(&v["id"], layers - 1)).await;
    assert_eq!(s, StatusCode::OK, "{out:.200}");
    assert!(out.starts_with("<svg"));
    assert_eq!(cache.plans_made(), 2);
    assert_eq!(cache.held().1, bytes);
    // The first was kept.
    assert_eq!(
        send(routes.clone(), svg(&v["id"], 0)).await.0,
        StatusCode::OK
    );
    assert_eq!(cache.plans_made(), 2);
}

/// `req` (an HTTP/1.1 request but its `Host` line, which is added; or nothing) written on a
/// new connection to `addr`; what edod answers until it closes the connection, and how
/// long that took (at most 10 s).
async fn exchange(addr: std::net::SocketAddr, req: &[u8]) -> (String, std::time::Duration) {
    let s = tokio::net::TcpStream::connect(addr).await.unwrap();
    exchange_on(s, addr, req).await
}

async fn exchange_on(
    mut s: tokio::net::TcpStream,
    addr: std::net::SocketAddr,
    req: &[u8],
) -> (String, std::time::Duration) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let t = std::time::Instant::now();
    let mut whole = Vec::new();
    if let Some(line_end) = req.windows(2).position(|w| w == b"\r\n") {
        whole.extend_from_slice(&req[..line_end + 2]);
        whole.extend_from_slice(format!("Host: {addr}\r\n").as_bytes());
        whole.extend_from_slice(&req[line_end + 2..]);
    }
    // edod may answer and close before all is written (a refused body).
    let _ = s.write_all(&whole).await;
    let mut answer = Vec::new();
    let read = tokio::time::timeout(
        std::time::Duration::from_secs(10),
        s.read_to_end(&mut answer),
    )
    .await;
    assert!(read.is_ok(), "edod did not close the connection");
    (String::from_utf8_lossy(&answer).into_owned(), t.elapsed())
}

fn rpc_post(method: &str) -> Vec<u8> {
    let body = rpc(method);
    format!(
        "POST /api/rpc HTTP/1.1\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

/// With every ordinary place taken by subscribed WebSockets, a new connection gets a
/// control place: it may stop the machine and read its status (the page's e-stop falls
/// back to `POST /api/rpc`), not open a WebSocket or ask anything else (503 naming
/// `api.max_clients`). An idle control connection gives its place to a newcomer.
#[tokio::test]
async fn beyond_max_clients_the_estop_and_status_still_get_through() {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::{Error, Message};
    let dir = tempfile::tempdir().unwrap();
    let shared = shared_with(dir.path(), |c| {
        c.api.max_clients = 2;
        c.api.control_clients = 1;
    })
    .await;
    let addr = listen(Arc::clone(&shared), loopback()).await;
    let mut sockets = Vec::new();
    for _ in 0..2 {
        let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/websocket"))
            .await
            .unwrap();
        ws.send(Message::text(rpc("subscribe"))).await.unwrap();
        ws.next().await.unwrap().unwrap();
        sockets.push(ws);
    }
    match tokio_tungstenite::connect_async(format!("ws://{addr}/websocket")).await {
        Err(Error::Http(r)) => assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE),
        other => panic!("a third WebSocket was not refused: {other:?}"),
    }
    let (estop, took) = exchange(addr, &rpc_post("machine.estop")).await;
    assert!(estop.starts_with("HTTP/1.1 200"), "{estop}");
    assert!(estop.contains("\"acked_after_us\":20"), "{estop}");
    eprintln!("e-stop by POST with every place taken: {took:?}");
    let (status, _) = exchange(
        addr,
        b"GET /api/status HTTP/1.1\r\nConnection: close\r\n\r\n",
    )
    .await;
    assert!(status.starts_with("HTTP/1.1 200"), "{status}");
    let (list, _) = exchange(addr, &rpc_post("job.list")).await;
    assert!(list.starts_with("HTTP/1.1 503"), "{list}");
    assert!(list.contains("api.max_clients = 2"), "{list}");
    let (jobs, _) = exchange(addr, b"GET /api/jobs HTTP/1.1\r\n\r\n").await;
    assert!(jobs.starts_with("HTTP/1.1 503"), "{jobs}");
    // An idle connection holds the one control place; a newcomer takes it.
    let idle = tokio::net::TcpStream::connect(addr).await.unwrap();
    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    let (estop, _) = exchange(addr, &rpc_post("machine.estop")).await;
    assert!(estop.starts_with("HTTP/1.1 200"), "{estop}");
    let (gone, took) = exchange_on(idle, addr, b"GET / HTTP/1.1\r\n\r\n").await;
    assert!(
        gone.is_empty() && took < std::time::Duration::from_secs(1),
        "{gone}"
    );
    // The WebSockets were served throughout.
    sockets[0]
        .send(Message::text(rpc("machine.status")))
        .await
        .unwrap();
    let reply = sockets[0]
        .next()
        .await
        .unwrap()
        .unwrap()
        .into_text()
        .unwrap();
    assert!(reply.contains("executed_total"), "{reply}");
}

/// A connection that sends nothing, or half a request head, or half a body, is closed
/// after `api.idle_timeout_s` (2 s here): the half body answered 408 naming it.
#[tokio::test]
async fn idle_and_half_sent_requests_are_closed_after_the_idle_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let shared = shared(dir.path(), 1 << 20).await;
    let addr = listen(Arc::clone(&shared), loopback()).await;
    let nothing = tokio::net::TcpStream::connect(addr).await.unwrap();
    let half_head = exchange(addr, b"GET /api/status HTTP/1.1\r\nAccept: */*");
    let half_body = exchange(
        addr,
        b"POST /api/rpc HTTP/1.1\r\nContent-Length: 100\r\n\r\n{\"jsonrpc\":",
    );
    let (nothing, half_head, half_body) =
        tokio::join!(exchange_on(nothing, addr, b""), half_head, half_body);
    for (what, (answer, took)) in [("nothing", &nothing), ("half a head", &half_head)] {
        assert!(answer.is_empty(), "{what}: {answer}");
        assert!(
            (1500..4000).contains(&took.as_millis()),
            "{what}: closed after {took:?}"
        );
    }
    let (answer, took) = half_body;
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(answer.contains("api.idle_timeout_s"), "{answer}");
    assert!((1500..4000).contains(&took.as_millis()), "{took:?}");
    // A keep-alive connection is served, then closed once idle.
    let (answer, took) = exchange(addr, b"GET /api/status HTTP/1.1\r\n\r\n").await;
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!((1500..4000).contains(&took.as_millis()), "{took:?}");
}

/// A body is counted against the memory budget as it arrives: with a 4 MiB budget and
/// one 3 MiB body half sent (held), a second is refused at once (503, naming
/// `api.memory_budget_bytes`) rather than read.
#[tokio::test]
async fn bodies_are_counted_against_the_memory_budget_as_they_arrive() {
    use tokio::io::AsyncWriteExt;
    let dir = tempfile::tempdir().unwrap();
    let shared = shared_with(dir.path(), |c| {
        c.api.max_request_bytes = 3 << 20;
        c.api.memory_budget_bytes = Some(4 << 20);
    })
    .await;
    let addr = listen(Arc::clone(&shared), loopback()).await;
    let head = format!(
        "POST /api/rpc HTTP/1.1\r\nHost: {addr}\r\nContent-Length: {}\r\n\r\n",
        3 << 20
    );
    let mut first = tokio::net::TcpStream::connect(addr).await.unwrap();
    first.write_all(head.as_bytes()).await.unwrap();
    first.write_all(&vec![b' '; 5 << 19]).await.unwrap();
    tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    let mut req = b"POST /api/rpc HTTP/1.1\r\nContent-Length: 3145728\r\n\r\n".to_vec();
    req.extend(std::iter::repeat_n(b' ', 5 << 19));
    let (answer, took) = exchange(addr, &req).await;
    assert!(answer.starts_with("HTTP/1.1 503"), "{answer}");
    assert!(
        answer.contains("api.memory_budget_bytes = 4.0 MiB"),
        "{answer}"
    );
    assert!(took < std::time::Duration::from_secs(1), "{took:?}");
    // Announced over api.max_request_bytes: 413 before a byte of it is read.
    let (answer, _) = exchange(
        addr,
        b"POST /api/preview HTTP/1.1\r\nContent-Length: 3145729\r\n\r\n",
    )
    .await;
    assert!(answer.starts_with("HTTP/1.1 413"), "{answer}");
    assert!(answer.contains("api.max_request_bytes"), "{answer}");
    drop(first);
}

/// The dashboard's preview of a mesh job that hangs in mid-air (a sphere on the bed):
/// a warning names the layers (it may still be submitted), and the low layers' images
/// fill the area resting on nothing red, the top ones do not.
#[tokio::test]
async fn a_previewed_overhang_is_drawn_red() {
    let dir = tempfile::tempdir().unwrap();
    let app = super::app(shared(dir.path(), 4 << 20).await, loopback());
    let routes = super::routes(Arc::clone(&app));
    let stl = crate::mesh::primitives::sphere(5.0, 64, 32)
        .to_binary_stl()
        .unwrap();
    let job =
        "name = \"ball\"\n[geometry]\nmesh = \"ball.stl\"\n[materials]\nnames = [\"A\", \"B\"]\n\
               [gradient]\ninner = [1.0, 0.0]\nouter = [0.0, 1.0]\n[process]\nr_mach = 2.0\n\
               nozzle = 0.4\nlayer = 0.2\nthin_regions = \"fill\"\n";
    let body = serde_json::json!({
        "job": job,
        "mesh_base64": crate::proto::mesh_bytes::base64_encode(&stl),
    })
    .to_string();
    let (s, out) = send(
        routes.clone(),
        post("/api/preview").body(Body::from(body)).unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{out:.300}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    // Submittable, with a warning naming the layers; each layer's area.
    assert_eq!(v["ok"], true, "{v:.300}");
    let w = v["warnings"][0].as_str().unwrap_or_default();
    assert!(
        w.contains("resting on nothing") && w.contains("layers 1-"),
        "{v:.400}"
    );
    assert!(v["layers"][1]["unsupported_area_mm2"].as_f64().unwrap() > 0.01);
    let id = v["id"].as_str().unwrap();
    let layers = v["layers"].as_array().unwrap().len();
    let image = |layer: usize| {
        let routes = routes.clone();
        let path = format!("/api/previews/{id}/layers/{layer}");
        async move { send(routes, get(&path)).await.1 }
    };
    let red = 5;
    let mut drawn = 0;
    for layer in 1..=red {
        drawn += usize::from(image(layer).await.contains(r#"<g id="unsupported""#));
    }
    assert!(drawn >= 3, "{drawn} of layers 1-{red} drawn red");
    assert!(!image(layers - 3).await.contains("unsupported"));
}

/// The layer view draws each road in its designed composition, the colour the SVG
/// preview gives it (not the mix the syringes are commanded, which runs the mixing
/// chamber's volume ahead of the nozzle), and gives what the chamber's model predicts
/// leaves the nozzle: on a machine whose mixing lead meets the design, the same.
#[tokio::test]
async fn the_layer_view_draws_the_design_and_the_predicted_nozzle_exit() {
    let dir = tempfile::tempdir().unwrap();
    let app = super::app(shared(dir.path(), 1 << 20).await, loopback());
    let routes = super::routes(Arc::clone(&app));
    let body = serde_json::json!({ "job": annulus(30.0) }).to_string();
    let (s, out) = send(
        routes.clone(),
        post("/api/preview?layer=1").body(Body::from(body)).unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{out:.300}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let id = v["id"].as_str().unwrap().to_string();
    let (s, svg) = send(routes.clone(), get(&format!("/api/previews/{id}/layers/1"))).await;
    assert_eq!(s, StatusCode::OK);
    let view = &v["view"];
    assert_eq!(view["layer"], 1, "{view:.300}");
    let mut colours = std::collections::BTreeSet::new();
    let (mut extrusions, mut exit_as_designed) = (0, 0);
    for m in view["moves"].as_array().unwrap() {
        let Some(colour) = m.get(2).and_then(|c| c.as_str()) else {
            continue;
        };
        extrusions += 1;
        assert!(
            svg.contains(&format!("\"{colour}\"")),
            "{colour} is not a colour of the preview's roads"
        );
        colours.insert(colour.to_string());
        let designed: Vec<f64> = serde_json::from_value(m[3].clone()).unwrap();
        // Nothing leaves the nozzle on a move that pushes nothing (a road's slanted
        // start): no prediction.
        let Ok(exit) = serde_json::from_value::<Vec<f64>>(m[5].clone()) else {
            continue;
        };
        let off = designed
            .iter()
            .zip(&exit)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        if off <= 0.02 {
            exit_as_designed += 1;
        }
    }
    // The annulus grades across its width: many compositions in one layer.
    assert!(colours.len() >= 5, "{colours:?}");
    assert!(
        exit_as_designed * 10 >= extrusions * 9,
        "{exit_as_designed} of {extrusions} extrusions leave the nozzle as designed"
    );
}
