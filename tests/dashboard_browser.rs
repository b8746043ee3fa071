//! The web dashboard in a real browser (Debian's chromium through chromedriver, driven
//! by fantoccini): edod on hil-sim; a part too large for the machine previewed with its
//! warning and not submittable; the tooth crown submitted through the page after its
//! plan preview (each layer's SVG image, the layer chosen from the keyboard); progress
//! to done with the layer view and the machine's position updating while it prints;
//! pause and resume from the page; e-stop of a second job, confirmed by the machine's
//! acknowledgement; on a non-loopback bind, the page asking for the token and
//! connecting with it, token-less calls and reads and a cross-origin WebSocket refused.
//! Screenshots of the preview, the queue and the live layer view are saved under
//! `target/dashboard-screenshots/`.
//!
//! Skips, saying why, when chromedriver is not installed, unless `EDO_REQUIRE_PEERS` is
//! set, as `.ci/run` sets it (it installs `chromium chromium-driver`): then it fails.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::json;

const TOKEN: &str = "dashboard-test-token-0123456789";

#[path = "../benches/common/child.rs"]
mod child;
use child::{free_port, wait_http, Kill};

fn chromedriver() -> Option<PathBuf> {
    ["/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
}

/// edod on a simulated machine on `tty`, its dashboard on `listen`.
fn edod(dir: &Path, tty: &Path, listen: &str, token: bool) -> Kill {
    let token_line = if token {
        let f = dir.join("token");
        std::fs::write(&f, format!("{TOKEN}\n")).unwrap();
        format!("token_file = {:?}\n", f.display().to_string())
    } else {
        String::new()
    };
    let cfg = format!(
        "[serial]\nport = {:?}\n\
         [api]\nsocket = {:?}\n[state]\ndir = {:?}\n\
         [http]\nlisten = {listen:?}\n{token_line}",
        tty.display().to_string(),
        dir.join("edod.sock").display().to_string(),
        dir.join("state").display().to_string(),
    );
    let config = dir.join("edod.toml");
    std::fs::write(&config, cfg).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_edod"))
        .arg("--config")
        .arg(&config)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    Kill(child)
}

/// A raw HTTP request to 127.0.0.1:`port`; the status code.
fn http_status(port: u16, request: &str) -> u16 {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(request.as_bytes()).unwrap();
    let mut buf = [0u8; 64];
    let n = s.read(&mut buf).unwrap();
    let head = String::from_utf8_lossy(&buf[..n]).into_owned();
    head.split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

async fn wait_for<F, Fut>(what: &str, secs: u64, mut f: F)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let t = Instant::now();
    while !f().await {
        assert!(
            t.elapsed() < Duration::from_secs(secs),
            "timed out waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn text(c: &Client, css: &str) -> String {
    match c.find(Locator::Css(css)).await {
        Ok(e) => e.text().await.unwrap_or_default(),
        Err(_) => String::new(),
    }
}

async fn attr(c: &Client, css: &str, name: &str) -> Option<String> {
    c.find(Locator::Css(css))
        .await
        .ok()?
        .attr(name)
        .await
        .ok()?
}

/// Click `css`, finding it again if the page redrew it meanwhile.
/// `css`'s element scrolled to the middle of the window, as an operator scrolls to a
/// control before clicking it (WebDriver scrolls no element it deems in view, even one
/// under the page's sticky header).
async fn in_view(c: &Client, css: &str) -> Result<fantoccini::elements::Element, String> {
    let e = c.find(Locator::Css(css)).await.map_err(|e| e.to_string())?;
    let arg = serde_json::to_value(&e).map_err(|e| e.to_string())?;
    c.execute("arguments[0].scrollIntoView({block: 'center'});", vec![arg])
        .await
        .map_err(|e| e.to_string())?;
    Ok(e)
}

async fn click(c: &Client, css: &str) {
    let mut last = None;
    for _ in 0..20 {
        match in_view(c, css).await {
            Ok(e) => match e.click().await {
                Ok(()) => return,
                Err(err) => last = Some(err.to_string()),
            },
            Err(err) => last = Some(err.to_string()),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("cannot click {css}: {last:?}");
}

/// Choose `job` in the submit form and ask for its preview.
async fn choose_job(c: &Client, job: &Path) {
    c.find(Locator::Css("#job-file"))
        .await
        .unwrap()
        .send_keys(&job.display().to_string())
        .await
        .unwrap();
    click(c, "#preview-btn").await;
}

/// The layer (from 0) whose SVG image the preview shows, once the image has loaded.
async fn shown_layer(c: &Client) -> Option<u32> {
    let v = c
        .execute(
            "const i = document.getElementById('preview-image'); \
             return i.hidden || !i.complete || i.naturalWidth === 0 ? null : Number(i.dataset.layer);",
            vec![],
        )
        .await
        .ok()?;
    v.as_u64().map(|n| n as u32)
}

/// The page as docs/dashboard.md shows it, while a job prints: the active job at a
/// desktop's 1440 × 900 and a phone's 390 × 844, light and dark (in
/// target/dashboard-screenshots/, copied to docs/dashboard/ when the page changes).
async fn docs_screenshots(c: &Client, base: &str) {
    let (w0, h0) = c.get_window_size().await.unwrap();
    for (w, h, at) in [(1440, 900, "#live"), (390, 844, "#queue")] {
        c.set_window_size(w, h).await.unwrap();
        for theme in ["light", "dark"] {
            c.execute(&format!("applyTheme('{theme}');"), vec![])
                .await
                .unwrap();
            c.goto(&format!("{base}{at}")).await.unwrap();
            wait_for("the page drawn for its screenshot", 20, || async {
                c.execute(
                    "const stack = document.getElementById('stack'); \
                     const layer = document.getElementById('layer-view'); \
                     return document.readyState === 'complete' \
                       && document.getElementById('job-1') !== null \
                       && !!stack && (stack.dataset.layersDrawn || '') !== '' \
                       && !!layer && (layer.dataset.drawn || '') !== '';",
                    vec![],
                )
                .await
                .ok()
                    == Some(serde_json::Value::Bool(true))
            })
            .await;
            // Two animation frames: what the last one drew is painted.
            c.execute_async(
                "const done = arguments[0]; \
                 requestAnimationFrame(() => requestAnimationFrame(() => done(true)));",
                vec![],
            )
            .await
            .unwrap();
            screenshot(c, &format!("dashboard-{w}x{h}-{theme}.png")).await;
        }
    }
    c.execute("applyTheme('auto');", vec![]).await.unwrap();
    c.set_window_size(w0 as u32, h0 as u32).await.unwrap();
}

async fn screenshot(c: &Client, name: &str) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/dashboard-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    let png = c.screenshot().await.unwrap();
    std::fs::write(dir.join(name), png).unwrap();
}

async fn browser(driver_port: u16) -> Client {
    let caps = json!({
        "goog:chromeOptions": {
            "args": ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1000,1300"]
        }
    });
    let caps = caps.as_object().unwrap().clone();
    let t = Instant::now();
    loop {
        let connector = hyper_util::client::legacy::connect::HttpConnector::new();
        match ClientBuilder::new(connector)
            .capabilities(caps.clone())
            .connect(&format!("http://127.0.0.1:{driver_port}"))
            .await
        {
            Ok(c) => return c,
            Err(e) => {
                assert!(t.elapsed() < Duration::from_secs(20), "chromedriver: {e}");
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_in_a_real_browser() {
    let Some(driver) = chromedriver() else {
        let why = "chromedriver not installed (apt-get install chromium chromium-driver)";
        // `.ci/run` sets EDO_REQUIRE_PEERS: there a missing browser is a failure.
        assert!(
            std::env::var_os("EDO_REQUIRE_PEERS").is_none(),
            "EDO_REQUIRE_PEERS is set and {why}"
        );
        println!("SKIPPED the_dashboard_in_a_real_browser: {why}");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let _sim = hil_sim::spawn(hil_sim::SimConfig {
        link: Some(dir.path().join("tty")),
        speed: 5.0,
        seed: 1,
        ..hil_sim::SimConfig::default()
    })
    .unwrap();
    let port = free_port();
    let start_edod = || {
        edod(
            dir.path(),
            &dir.path().join("tty"),
            &format!("127.0.0.1:{port}"),
            false,
        )
    };
    let mut running = Some(start_edod());
    wait_http(port);
    let driver_port = free_port();
    let _driver = Kill(
        Command::new(driver)
            .arg(format!("--port={driver_port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let c = browser(driver_port).await;
    use futures_util::FutureExt;
    let driven = std::panic::AssertUnwindSafe(async {
        drive(&c, port).await;
        offline_and_back(&c, port, &mut running, start_edod).await;
        // Beyond loopback, with a token.
        let sub = dir.path().join("open");
        std::fs::create_dir_all(&sub).unwrap();
        let _sim = hil_sim::spawn(hil_sim::SimConfig {
            link: Some(sub.join("tty")),
            ..hil_sim::SimConfig::default()
        })
        .unwrap();
        let open = free_port();
        let _edod = edod(&sub, &sub.join("tty"), &format!("0.0.0.0:{open}"), true);
        wait_http(open);
        token_page(&c, open).await;
        refusals(open).await;
    })
    .catch_unwind()
    .await;
    // Close the browser whatever happened, then report.
    let _ = c.close().await;
    if let Err(p) = driven {
        std::panic::resume_unwind(p);
    }
}

/// Beyond loopback the page loads without the token, asks for it, and connects with it.
async fn token_page(c: &Client, port: u16) {
    c.goto(&format!("http://127.0.0.1:{port}/")).await.unwrap();
    wait_for("the page to ask for the token", 20, || async {
        attr(c, "#token-form", "hidden").await.is_none()
    })
    .await;
    let asked = text(c, "#link").await;
    assert!(asked.contains("token"), "{asked}");
    let field = c.find(Locator::Css("#token")).await.unwrap();
    field.send_keys(TOKEN).await.unwrap();
    field.send_keys("\u{E007}").await.unwrap();
    wait_for("the page to connect with the token", 20, || async {
        text(c, "#link").await.starts_with("connected")
    })
    .await;
}

async fn drive(c: &Client, port: u16) {
    let base = format!("http://127.0.0.1:{port}/");
    c.goto(&base).await.unwrap();
    wait_for("the page to connect", 20, || async {
        text(c, "#link").await.starts_with("connected")
    })
    .await;
    // On loopback without a token file no token is asked for (the form's own display
    // rule once showed it although hidden).
    let form = c.find(Locator::Css("#token-form")).await.unwrap();
    assert!(
        !form.is_displayed().await.unwrap(),
        "a token form on loopback"
    );

    // A job too large for the machine: its preview says so, and it cannot be confirmed.
    let too_big = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/paper-annulus.toml"),
    )
    .unwrap()
    .replace("radius = 30.0", "radius = 300.0");
    let too_big_file = std::env::temp_dir().join(format!("edo-too-big-{port}.toml"));
    std::fs::write(&too_big_file, too_big).unwrap();
    choose_job(c, &too_big_file).await;
    wait_for("the warning of a part that does not fit", 60, || async {
        text(c, "#preview-problems").await.contains("build volume")
    })
    .await;
    assert!(attr(c, "#confirm", "disabled").await.is_some());
    let _ = std::fs::remove_file(&too_big_file);
    click(c, "#discard").await;

    // Submit the tooth crown through the page: preview (a layer's SVG image, another
    // chosen from the keyboard), then confirm.
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/tooth-crown.toml");
    choose_job(c, &job).await;
    wait_for("the plan preview", 60, || async {
        text(c, "#preview-summary").await.contains("tooth-crown: ")
    })
    .await;
    let summary = text(c, "#preview-summary").await;
    assert!(!summary.contains("cannot be printed"), "{summary}");
    wait_for("layer 1's image", 30, || async {
        shown_layer(c).await == Some(0)
    })
    .await;
    c.find(Locator::Css("#preview-layer"))
        .await
        .unwrap()
        .send_keys("\u{E014}")
        .await
        .unwrap();
    wait_for("layer 2's image", 30, || async {
        shown_layer(c).await == Some(1)
    })
    .await;
    let out = text(c, "#preview-layer-out").await;
    assert!(out.starts_with("2 of "), "{out}");
    screenshot(c, "preview.png").await;
    click(c, "#confirm").await;
    wait_for("job 1 in the queue", 10, || async {
        c.find(Locator::Css("#job-1")).await.is_ok()
    })
    .await;

    // While it prints: the layer view is drawn and grows.
    wait_for("job 1 printing", 60, || async {
        attr(c, "#job-1", "data-state").await.as_deref() == Some("printing")
    })
    .await;
    wait_for("moves drawn over the layer", 60, || async {
        attr(c, "#layer-view", "data-drawn")
            .await
            .and_then(|d| d.parse::<u32>().ok())
            .unwrap_or(0)
            > 0
    })
    .await;
    let first = attr(c, "#layer-view", "data-executed")
        .await
        .unwrap_or_default();
    wait_for("the layer view to update", 30, || async {
        attr(c, "#layer-view", "data-executed")
            .await
            .unwrap_or_default()
            != first
    })
    .await;
    live_colours_are_the_previews(c, &job).await;
    // Progress by the planned machine time once edod has planned the job whole.
    wait_for("a percentage of the planned time", 60, || async {
        text(c, "#job-1 td[data-label=Progress]")
            .await
            .contains(" %")
    })
    .await;
    let bar = attr(c, "#active-progress", "value")
        .await
        .unwrap_or_default();
    assert!(bar.parse::<f64>().is_ok(), "progress bar value {bar:?}");
    // The stacked view draws the whole crown (its 4 layers), the current one marked.
    wait_for("the whole part stacked", 30, || async {
        attr(c, "#stack", "data-layers-drawn").await.as_deref() == Some("4")
    })
    .await;
    let current = attr(c, "#stack", "data-current").await.unwrap_or_default();
    assert!(
        current.parse::<u32>().is_ok(),
        "no current layer marked: {current:?}"
    );
    let inked = c
        .execute(
            "const c = document.getElementById('stack'); \
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
             let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n;",
            vec![],
        )
        .await
        .unwrap();
    assert!(
        inked.as_u64().unwrap_or(0) > 5000,
        "stacked view drew {inked} pixels"
    );
    // The console shows edod's log of the job.
    wait_for("the job's lines in the console", 20, || async {
        text(c, "#console").await.contains("job 1")
    })
    .await;
    docs_screenshots(c, &base).await;
    // The machine panel follows the print, written in place: the element found once
    // keeps reading the new position (it was once rebuilt on every status pushed, and
    // a reader holding it read nothing).
    let position = c.find(Locator::Css("#machine-position")).await.unwrap();
    let at = position.text().await.unwrap();
    assert!(at.starts_with("x "), "{at}");
    wait_for("the machine's position to change", 30, || async {
        position
            .text()
            .await
            .expect("the position was rebuilt, not updated in place")
            != at
    })
    .await;
    c.goto(&format!("{base}#live")).await.unwrap();
    screenshot(c, "live-layer.png").await;

    // Pause and resume from the page, as an operator clicks: the button found once and
    // clicked after progress has streamed in (the page once rebuilt every row on each
    // update, so such a click fell on a button no longer there).
    let pause = c
        .find(Locator::Css("#job-1 button[data-action=pause]"))
        .await
        .unwrap();
    // Every control shown is a touch target of at least 44 × 44 CSS px.
    let small = c
        .execute(
            "return [...document.querySelectorAll('button')]\
             .filter((b) => b.offsetParent !== null)\
             .map((b) => [b.textContent, b.getBoundingClientRect()])\
             .filter(([, r]) => r.width < 44 || r.height < 44)\
             .map(([t, r]) => t + ' ' + r.width + 'x' + r.height);",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(small, json!([]), "buttons under 44 px");
    let row = text(c, "#job-1").await;
    wait_for("progress to stream in", 20, || async {
        text(c, "#job-1").await != row
    })
    .await;
    // Scrolled to, as an operator scrolls to it (the same element, not found again).
    c.execute(
        "arguments[0].scrollIntoView({block: 'center'});",
        vec![serde_json::to_value(&pause).unwrap()],
    )
    .await
    .expect("the pause button was rebuilt under the pointer");
    pause
        .click()
        .await
        .expect("the pause button was rebuilt under the pointer");
    wait_for("job 1 paused", 20, || async {
        attr(c, "#job-1", "data-state").await.as_deref() == Some("paused")
    })
    .await;
    // The keyboard focus stays on the job's controls (its row is redrawn for the new
    // state, pause becoming resume: the focus goes there, not to the page's body).
    let focused = c
        .execute(
            "const a = document.activeElement; \
             return a.tagName + ' ' + (a.closest('tr') ? a.closest('tr').id : '') + ' ' + (a.dataset.action || '');",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(focused, json!("BUTTON job-1 resume"), "focus after pausing");
    // While paused the ETA holds still: it is planned time left at the pace measured
    // while printing, and a pause is not printing.
    // (The move under way when the pause came finishes first, and the ETA with it:
    // read once the machine reports it holds.)
    wait_for("the machine to hold", 20, || async {
        text(c, "#machine-state").await == "Held"
    })
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let eta = text(c, "#job-1 td[data-label=ETA]").await;
    assert!(eta.ends_with(" s"), "no ETA while paused: {eta:?}");
    tokio::time::sleep(Duration::from_millis(2500)).await;
    assert_eq!(
        text(c, "#job-1 td[data-label=ETA]").await,
        eta,
        "the ETA moved while paused"
    );
    click(c, "#job-1 button[data-action=resume]").await;
    wait_for("job 1 printing again", 20, || async {
        attr(c, "#job-1", "data-state").await.as_deref() == Some("printing")
    })
    .await;
    wait_for("job 1 done", 600, || async {
        attr(c, "#job-1", "data-state").await.as_deref() == Some("done")
    })
    .await;
    // Done: in the history, with when, how long and what it used.
    let finished = "#history-jobs #job-1";
    wait_for("job 1 in the history", 10, || async {
        c.find(Locator::Css(finished)).await.is_ok()
    })
    .await;
    let took = text(c, &format!("{finished} td[data-label=Duration]")).await;
    assert!(took.ends_with(" s"), "duration {took:?}");
    let material = text(c, &format!("{finished} td[data-label=Material]")).await;
    let used: f64 = material
        .split(' ')
        .filter_map(|w| w.parse::<f64>().ok())
        .sum();
    assert!(
        material.contains(" ml") && used > 0.0,
        "material {material:?}"
    );
    let moves = text(c, &format!("{finished} td[data-label=Moves]")).await;
    assert!(moves.contains(" of "), "moves {moves:?}");
    c.goto(&format!("{base}#history")).await.unwrap();
    screenshot(c, "history.png").await;

    // A second job, e-stopped from the page: the machine's acknowledgement is shown.
    choose_job(c, &job).await;
    wait_for("the second preview", 60, || async {
        attr(c, "#confirm", "disabled").await.is_none()
            && !text(c, "#preview-summary").await.is_empty()
    })
    .await;
    click(c, "#confirm").await;
    wait_for("job 2 printing", 60, || async {
        attr(c, "#job-2", "data-state").await.as_deref() == Some("printing")
    })
    .await;
    click(c, "#estop").await;
    wait_for("the e-stop acknowledgement", 10, || async {
        attr(c, "#estop-ack", "data-acked").await.is_some()
    })
    .await;
    let ack = text(c, "#estop-ack").await;
    assert!(ack.contains("acknowledged by the machine"), "{ack}");
    screenshot(c, "estop.png").await;

    // Cancel and delete ask first, naming the job; declined, nothing happens.
    wait_for("job 2 interrupted", 20, || async {
        attr(c, "#job-2", "data-state").await.as_deref() == Some("interrupted")
    })
    .await;
    let asked = answer_confirmation(c, "#job-2 button[data-action=cancel]", false).await;
    assert!(asked.contains("Cancel job 2"), "{asked}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        attr(c, "#job-2", "data-state").await.as_deref(),
        Some("interrupted")
    );
    answer_confirmation(c, "#job-2 button[data-action=cancel]", true).await;
    wait_for("job 2 cancelled", 20, || async {
        attr(c, "#job-2", "data-state").await.as_deref() == Some("cancelled")
    })
    .await;
    // A finished job printed again without its files: job 3, from job 2's; cancelled.
    click(c, "#job-2 button[data-action=reprint]").await;
    wait_for("job 3, job 2 again", 20, || async {
        c.find(Locator::Css("#jobs #job-3")).await.is_ok()
    })
    .await;
    let toasted = text(c, "#toasts").await;
    assert!(toasted.contains("queued again as job 3"), "{toasted}");
    answer_confirmation(c, "#job-3 button[data-action=cancel]", true).await;
    wait_for("job 3 cancelled", 30, || async {
        attr(c, "#job-3", "data-state").await.as_deref() == Some("cancelled")
    })
    .await;
    let asked = answer_confirmation(c, "#job-1 button[data-action=delete]", true).await;
    assert!(asked.contains("Delete job 1"), "{asked}");
    wait_for("job 1 deleted", 20, || async {
        c.find(Locator::Css("#job-1")).await.is_err()
    })
    .await;
}

/// The live view draws the layer's roads in the colours `edoctl plan --svg` gives them
/// (their designed composition), many of them across the crown's grading, not the
/// mix the syringes push (which once drew whole layers in one colour), and the
/// composition panel names the design, the predicted nozzle exit and the syringes.
async fn live_colours_are_the_previews(c: &Client, job: &Path) {
    let caption = text(c, "#layer-caption").await;
    let layer: usize = caption
        .strip_prefix("Layer ")
        .and_then(|r| r.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("caption {caption:?}"));
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_edoctl"))
        .args(["plan", "--quiet", "--svg"])
        .arg(dir.path())
        .arg(job)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut preview = String::new();
    for name in [
        format!("layer-{:04}.svg", layer - 1),
        format!("layer-{:04}-roads.svg", layer - 1),
    ] {
        preview += &std::fs::read_to_string(dir.path().join(name)).unwrap();
    }
    let live = c
        .execute(
            "return [...document.querySelectorAll('#layer-view > g:first-child line')]\
             .map((l) => l.getAttribute('stroke')).filter((s) => s !== '#bbb');",
            vec![],
        )
        .await
        .unwrap();
    let live: std::collections::BTreeSet<String> = serde_json::from_value(live).unwrap();
    assert!(live.len() >= 3, "layer {layer} drawn in {live:?}");
    for colour in &live {
        assert!(
            preview.contains(&format!("stroke=\"{colour}\"")),
            "layer {layer}: {colour} is no road's colour in the preview ({live:?})"
        );
    }
    let panel = text(c, "#composition").await;
    assert!(
        panel.contains("designed") && panel.contains("predicted to leave the nozzle"),
        "{panel}"
    );
}

/// edod killed (SIGKILL) while the page shows a printing job: within a second every
/// panel is greyed under a notice; once edod is back the page reads the state again
/// before showing it: the job interrupted, with the reason, and its resume works.
async fn offline_and_back(
    c: &Client,
    port: u16,
    running: &mut Option<Kill>,
    start_edod: impl FnOnce() -> Kill,
) {
    let job = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/tooth-crown.toml"),
    )
    .unwrap();
    let id = c
        .execute(
            "return call('job.submit', {job: arguments[0]}).then((r) => r.id);",
            vec![json!(job)],
        )
        .await
        .unwrap();
    let row = format!("#job-{}", id.as_u64().expect("a job id"));
    wait_for("the third job printing", 60, || async {
        attr(c, &row, "data-state").await.as_deref() == Some("printing")
    })
    .await;
    // The second job's e-stop notice went when a job printed again.
    let estop = c.find(Locator::Css("#estop-ack")).await.unwrap();
    assert!(
        !estop.is_displayed().await.unwrap(),
        "an e-stop notice outlived its cause"
    );
    drop(running.take());
    let killed = Instant::now();
    loop {
        let shown = c
            .find(Locator::Css("#offline"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap();
        if shown {
            break;
        }
        assert!(
            killed.elapsed() < Duration::from_secs(1),
            "no offline notice a second after edod was killed"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let notice = text(c, "#offline").await;
    assert!(notice.contains("not answering"), "{notice}");
    assert!(
        attr(c, "body", "class")
            .await
            .unwrap_or_default()
            .contains("offline"),
        "the panels are not greyed"
    );
    screenshot(c, "offline.png").await;
    *running = Some(start_edod());
    wait_http(port);
    wait_for("the notice to clear once edod is back", 30, || async {
        !c.find(Locator::Css("#offline"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap()
    })
    .await;
    assert_eq!(
        attr(c, &row, "data-state").await.as_deref(),
        Some("interrupted"),
        "the page shows the job as it was before edod died"
    );
    let said = text(c, &format!("{row} td.state")).await;
    assert!(said.starts_with("interrupted: "), "no reason: {said}");
    let active = text(c, "#active").await;
    assert!(!active.contains("): printing"), "{active}");
    // It holds the queue (edod restarted under it): the notice says so and what to do.
    wait_for("the held-queue notice", 10, || async {
        text(c, "#held-text").await.contains("The queue waits: job")
    })
    .await;
    screenshot(c, "held.png").await;
    let asked = answer_confirmation(c, &format!("{row} button[data-action=resume]"), true).await;
    assert!(asked.contains("interrupted"), "{asked}");
    wait_for("the third job printing again", 60, || async {
        matches!(
            attr(c, &row, "data-state").await.as_deref(),
            Some("printing" | "done")
        )
    })
    .await;
}

/// Click `css`, which asks for confirmation; the question, accepted or declined.
async fn answer_confirmation(c: &Client, css: &str, accept: bool) -> String {
    in_view(c, css).await.unwrap().click().await.unwrap();
    let mut asked = None;
    for _ in 0..50 {
        if let Ok(t) = c.get_alert_text().await {
            asked = Some(t);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let asked = asked.unwrap_or_else(|| panic!("{css} asked nothing"));
    if accept {
        c.accept_alert().await.unwrap();
    } else {
        c.dismiss_alert().await.unwrap();
    }
    asked
}

/// On a non-loopback bind: a token-less call or read, and a cross-origin WebSocket,
/// all refused; the page's own files served without the token.
async fn refusals(port: u16) {
    use tokio_tungstenite::tungstenite::{client::IntoClientRequest, Error};
    let read = |path: &str, auth: &str| {
        format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{auth}Connection: close\r\n\r\n")
    };
    let bearer = format!("Authorization: Bearer {TOKEN}\r\n");
    for path in ["/api/jobs", "/api/status", "/api/server"] {
        assert_eq!(
            http_status(port, &read(path, "")),
            401,
            "a token-less read of {path}"
        );
        assert_eq!(http_status(port, &read(path, &bearer)), 200, "{path}");
    }
    assert_eq!(http_status(port, &read("/", "")), 200, "the page");
    let call = r#"{"jsonrpc":"2.0","id":1,"method":"machine.estop"}"#;
    let post = |auth: &str| {
        format!(
            "POST /api/rpc HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{call}",
            call.len()
        )
    };
    assert_eq!(http_status(port, &post("")), 401, "a token-less call");
    assert_eq!(
        http_status(port, &post(&format!("Authorization: Bearer {TOKEN}\r\n"))),
        200
    );
    let mut req = format!("ws://127.0.0.1:{port}/websocket?token={TOKEN}")
        .into_client_request()
        .unwrap();
    req.headers_mut()
        .insert("origin", "http://evil.example".parse().unwrap());
    match tokio_tungstenite::connect_async(req).await {
        Err(Error::Http(r)) => assert_eq!(r.status().as_u16(), 403),
        other => panic!("a cross-origin WebSocket was not refused: {other:?}"),
    }
    match tokio_tungstenite::connect_async(format!("ws://127.0.0.1:{port}/websocket")).await {
        Err(Error::Http(r)) => assert_eq!(r.status().as_u16(), 401),
        other => panic!("a token-less WebSocket was not refused: {other:?}"),
    }
}
