//! 50 dashboards on a printing job: edod on hil-sim (a pty, in this process), its web
//! dashboard on 127.0.0.1; 50 WebSocket clients subscribe and read every notification
//! while a dry-run job prints; one more client measures the API round trip
//! (`machine.status` over the WebSocket, every 20 ms). Then: underruns (none allowed),
//! the round trip's p50/p99/max (issue 32: p99 < 5 ms), notifications each client read,
//! and the page's first load (its three files over loopback, fresh connections) and size.
//!
//! `cargo bench --bench dashboard` (about 1 min); `cargo test --benches` runs a short
//! version. Figures in benches/README.md.

use std::io::{Read, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use tokio_tungstenite::tungstenite::Message;

const CLIENTS: usize = 50;

#[path = "common/child.rs"]
mod child;
use child::{free_port, wait_http, Kill};

fn edod(dir: &Path, port: u16) -> Kill {
    let cfg = format!(
        "[serial]\nport = {:?}\n[api]\nsocket = {:?}\n[state]\ndir = {:?}\n\
         [planner]\ndry_run_moves_per_layer = 200\n[http]\nlisten = \"127.0.0.1:{port}\"\n",
        dir.join("tty").display().to_string(),
        dir.join("edod.sock").display().to_string(),
        dir.join("state").display().to_string(),
    );
    std::fs::write(dir.join("edod.toml"), cfg).expect("config written");
    Kill(
        Command::new(env!("CARGO_BIN_EXE_edod"))
            .arg("--config")
            .arg(dir.join("edod.toml"))
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .spawn()
            .expect("edod starts"),
    )
}

/// GET `path` on a fresh connection: the time to the last byte and the body's size.
fn get(port: u16, path: &str) -> (Duration, usize) {
    let t = Instant::now();
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).expect("connect");
    let req = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).expect("request");
    let mut out = Vec::new();
    s.read_to_end(&mut out).expect("response");
    let head = out
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map_or(0, |i| i + 4);
    (t.elapsed(), out.len() - head)
}

/// Send one JSON-RPC POST; the response body.
fn post(port: u16, body: &str) -> String {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).expect("connect");
    let req = format!(
        "POST /api/rpc HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).expect("request");
    let mut out = String::new();
    s.read_to_string(&mut out).expect("response");
    out
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted.get(i).copied().unwrap_or_default()
}

async fn dashboard(port: u16) -> usize {
    let url = format!("ws://127.0.0.1:{port}/websocket");
    let (mut ws, _) = tokio_tungstenite::connect_async(url)
        .await
        .expect("websocket");
    let sub = r#"{"jsonrpc":"2.0","id":1,"method":"subscribe"}"#;
    ws.send(Message::text(sub)).await.expect("subscribe");
    let mut seen = 0;
    while let Some(Ok(m)) = ws.next().await {
        let Ok(t) = m.into_text() else { continue };
        if t.contains("\"method\":\"notify_") {
            seen += 1;
        }
        if t.contains("\"state\":\"done\"") {
            break;
        }
    }
    seen
}

async fn prober(port: u16, until: tokio::sync::watch::Receiver<bool>) -> Vec<Duration> {
    let url = format!("ws://127.0.0.1:{port}/websocket");
    let (mut ws, _) = tokio_tungstenite::connect_async(url)
        .await
        .expect("websocket");
    let mut rtts = Vec::new();
    let mut id = 0u64;
    while !*until.borrow() {
        id += 1;
        let req = format!(r#"{{"jsonrpc":"2.0","id":{id},"method":"machine.status"}}"#);
        let t = Instant::now();
        ws.send(Message::text(req)).await.expect("send");
        let want = format!("\"id\":{id},");
        while let Some(Ok(m)) = ws.next().await {
            if m.into_text().is_ok_and(|t| t.contains(&want)) {
                break;
            }
        }
        rtts.push(t.elapsed());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    rtts
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let moves = if full { 6_000 } else { 600 };
    let dir = tempfile::tempdir().expect("temp dir");
    let _sim = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.path().join("tty")),
        speed: 20.0,
        ..hil_sim::SimConfig::default()
    })
    .expect("hil-sim starts");
    let port = free_port();
    let _edod = edod(dir.path(), port);
    wait_http(port);
    let mut load = Duration::ZERO;
    let mut size = 0;
    for path in ["/", "/app.js", "/app.css"] {
        let (d, n) = get(port, path);
        load += d;
        size += n;
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let (seen, rtts) = rt.block_on(async {
        let clients: Vec<_> = (0..CLIENTS).map(|_| tokio::spawn(dashboard(port))).collect();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let (stop, until) = tokio::sync::watch::channel(false);
        let probe = tokio::spawn(prober(port, until));
        let submit = format!(
            r#"{{"jsonrpc":"2.0","id":1,"method":"job.submit","params":{{"dry_run_moves":{moves}}}}}"#
        );
        let reply = tokio::task::spawn_blocking(move || post(port, &submit)).await.expect("post");
        assert!(reply.contains("\"queued\""), "{reply}");
        let mut seen = Vec::new();
        for c in clients {
            seen.push(c.await.expect("client"));
        }
        let _ = stop.send(true);
        (seen, probe.await.expect("prober"))
    });
    let status = post(
        port,
        r#"{"jsonrpc":"2.0","id":1,"method":"machine.status"}"#,
    );
    let underruns = status
        .split("\"underruns\":")
        .nth(1)
        .and_then(|s| s.split(|c: char| !c.is_ascii_digit()).next())
        .unwrap_or("?")
        .to_string();
    let mut sorted = rtts.clone();
    sorted.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1000.0;
    println!("{CLIENTS} WebSocket dashboards, a dry run of {moves} moves at sim speed 20");
    println!("| underruns | round trips | p50 | p99 | max | notifications per client (min..max) | first load | page size |");
    println!("|---|---|---|---|---|---|---|---|");
    println!(
        "| {underruns} | {} | {:.2} ms | {:.2} ms | {:.2} ms | {}..{} | {:.1} ms | {} B |",
        sorted.len(),
        ms(percentile(&sorted, 0.5)),
        ms(percentile(&sorted, 0.99)),
        ms(sorted.last().copied().unwrap_or_default()),
        seen.iter().min().unwrap_or(&0),
        seen.iter().max().unwrap_or(&0),
        ms(load),
        size
    );
    assert_eq!(underruns, "0", "queue underruns with {CLIENTS} dashboards");
}
