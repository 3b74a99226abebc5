//! Browser tests of the live dashboard (`static/`): Debian's Chromium, headless, driven over
//! the DevTools protocol. The page exposes hooks on `<body>` (`data-connection`,
//! `data-updates`, `data-tracks`, `data-decision`, `data-particles-drawn`, `data-plot-points`,
//! `data-connects`) so the test can assert that real drawing happened.
//!
//! Chromium missing is a test failure with a clear message, never a silent skip.

mod cdp;
mod mock;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use cdp::{Browser, Page};

const WIDTH_PX: u32 = 1440;
const HEIGHT_PX: u32 = 900;
/// Generous: the first page load in a cold Chromium on a loaded 2-core machine is slow.
const WAIT: Duration = Duration::from_secs(60);
/// All of static/ together must stay small (no frameworks): a budget, not a measurement.
const PAGE_WEIGHT_BUDGET_BYTES: u64 = 200 * 1024;

/// One browser test at a time: each starts Chromium (and the demo its server) on a 2-core
/// machine, and the measured update rates should not depend on the other test.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

fn target_dir() -> PathBuf {
    // CARGO_TARGET_TMPDIR is <target>/tmp.
    Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("target"))
}

/// Bytes of every file served from static/ (what a browser downloads for one page view).
fn page_weight_bytes() -> u64 {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("static");
    std::fs::read_dir(&dir)
        .expect("static/ exists")
        .filter_map(Result::ok)
        .filter_map(|e| e.metadata().ok())
        .filter(|m| m.is_file())
        .map(|m| m.len())
        .sum()
}

/// Pixels of the 3D view brighter than its background (copied through a 2D canvas, so it works
/// for the WebGL and the Canvas 2D renderer alike).
async fn lit_pixels_3d(page: &mut Page) -> f64 {
    page.eval(
        "(() => { const c = document.getElementById('view3d');
           const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
           const x = t.getContext('2d'); x.drawImage(c, 0, 0);
           const px = x.getImageData(0, 0, t.width, t.height).data;
           let n = 0; for (let i = 0; i < px.length; i += 4) if (px[i] > 60 || px[i+1] > 60 || px[i+2] > 60) n++;
           return n; })()",
    )
    .await
    .expect("read 3D pixels")
    .as_f64()
    .unwrap_or(0.0)
}

async fn body_number(page: &mut Page, key: &str) -> f64 {
    let v = page
        .eval(&format!("Number(document.body.dataset.{key} ?? 0)"))
        .await
        .expect("evaluate hook");
    v.as_f64().unwrap_or(0.0)
}

/// Events handled by the page per second, counted over `window`.
async fn measure_update_rate_hz(page: &mut Page, window: Duration) -> f64 {
    let before = body_number(page, "updates").await;
    let t0 = Instant::now();
    tokio::time::sleep(window).await;
    let after = body_number(page, "updates").await;
    (after - before) / t0.elapsed().as_secs_f64()
}

/// What every run checks, against the mock or the real service: connected, an object tracked
/// with a decision shown, particles drawn in 3D, a plot with data, no script errors.
async fn check_live_dashboard(page: &mut Page, base_url: &str) {
    page.navigate(&format!("{base_url}/")).await.expect("open dashboard");
    page.wait_for(
        "document.body.dataset.connection === 'live'",
        WAIT,
        "the event stream to connect",
    )
    .await
    .expect("connected");
    page.wait_for("Number(document.body.dataset.tracks) >= 1", WAIT, "a tracked object")
        .await
        .expect("tracked object");
    let decision = page
        .wait_for("document.body.dataset.decision", WAIT, "a decision")
        .await
        .expect("decision shown");
    let decision = decision.as_str().unwrap_or_default().to_string();
    assert!(
        decision == "grasp" || decision == "observe",
        "decision hook shows {decision:?}"
    );
    page.wait_for(
        "[...document.querySelectorAll('.track .verdict')].some(v => v.textContent === 'grasp' || v.textContent === 'observe')",
        WAIT,
        "the track list to show the verdict",
    )
    .await
    .expect("verdict listed");
    page.wait_for(
        "[...document.querySelectorAll('.track .calibration')].some(c => c.textContent.includes('raw '))",
        WAIT,
        "the track list to say what the probability is (calibrated or raw) beside the raw rate",
    )
    .await
    .expect("calibration state listed");
    page.wait_for(
        "Number(document.body.dataset.particlesDrawn) > 0",
        WAIT,
        "particles drawn in the 3D view",
    )
    .await
    .expect("particles drawn");
    page.wait_for(
        "Number(document.getElementById('plot-std').dataset.plotPoints) >= 2",
        WAIT,
        "the translation-std plot to have data",
    )
    .await
    .expect("plot has data");
    // The 3D canvas really has non-background pixels where drawing happened.
    let lit = lit_pixels_3d(page).await;
    assert!(lit > 500.0, "3D view drew almost nothing: {lit} lit pixels");
    let renderer = page
        .eval("document.body.dataset.renderer")
        .await
        .expect("renderer hook");
    eprintln!("3D renderer: {renderer}");
    let errors = page
        .eval("document.documentElement.dataset.jsErrors ?? ''")
        .await
        .expect("errors hook");
    assert_eq!(errors.as_str(), Some(""), "script errors in the page");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_shows_live_mock_service_and_reconnects() {
    let _one = ONE_AT_A_TIME.lock().await;
    let server = mock::spawn().await;
    let base_url = format!("http://{}", server.addr);
    let mut browser = Browser::launch(WIDTH_PX, HEIGHT_PX).await.expect("launch Chromium");
    let page = &mut browser.page;
    check_live_dashboard(page, &base_url).await;

    // Camera panels: an image arrived, detections and projected particles drawn over it.
    page.wait_for(
        "[...document.querySelectorAll('.camera-panel')].filter(f => f.dataset.imageLoaded === 'true' && Number(f.dataset.detections) > 0 && Number(f.dataset.particlesProjected) > 0).length >= 2",
        WAIT,
        "both camera panels with image, boxes and projected particles",
    )
    .await
    .expect("camera panels");
    // The mock publishes decisions that cross the threshold after ~3.5 s: the page follows.
    page.wait_for(
        "document.body.dataset.decision === 'grasp'",
        WAIT,
        "the decision to flip to grasp",
    )
    .await
    .expect("decision updates live");
    let truth_points = page
        .eval("Number(document.getElementById('plot-terr').dataset.plotPoints)")
        .await
        .expect("truth plot");
    assert!(
        truth_points.as_f64().unwrap_or(0.0) >= 2.0,
        "ground-truth error plot has data"
    );

    let rate = measure_update_rate_hz(page, Duration::from_secs(3)).await;
    // The mock sends 6 events per 100 ms tick (60/s); the page must keep up with most of it.
    assert!(rate > 20.0, "page handled only {rate:.1} events/s from the mock's 60/s");

    // Drop the event stream and refuse new ones for 3 s: the page shows the lost connection
    // and reconnects by itself once the service is back.
    let connects_before = body_number(page, "connects").await;
    let client = reqwest::Client::new();
    client
        .post(format!("{base_url}/mock/drop?down_ms=3000"))
        .send()
        .await
        .expect("drop streams");
    page.wait_for(
        "document.body.dataset.connection === 'reconnecting' && document.getElementById('connection').textContent.includes('lost')",
        WAIT,
        "the page to show the lost connection",
    )
    .await
    .expect("lost connection shown");
    page.wait_for(
        &format!(
            "Number(document.body.dataset.connects) > {connects_before} && document.body.dataset.connection === 'live'"
        ),
        WAIT,
        "the page to reconnect after the stream dropped",
    )
    .await
    .expect("reconnected");
    let updates = body_number(page, "updates").await;
    page.wait_for(
        &format!("Number(document.body.dataset.updates) > {updates}"),
        WAIT,
        "events after reconnecting",
    )
    .await
    .expect("events flow again");

    let shot = target_dir().join("dashboard-screenshot-mock.png");
    let bytes = page.screenshot(&shot).await.expect("screenshot");
    let reason = page
        .eval("document.querySelector('.track .reason').textContent")
        .await
        .expect("reason");
    assert!(
        reason
            .as_str()
            .is_some_and(|r| r.starts_with("Main reason: ") && r.contains("% of samples")),
        "main reason shown from decision.reasons: {reason}"
    );

    // The first camera's button switches its panel to the colour image.
    page.eval("document.querySelector('.camera-panel button').click()")
        .await
        .expect("click toggle");
    page.wait_for(
        "(() => { const f = document.querySelector('.camera-panel'); return f.querySelector('img').src.includes('color.png') && f.dataset.imageLoaded === 'true' && f.querySelector('.camera-title').textContent.endsWith('colour'); })()",
        WAIT,
        "the colour image in the first camera panel",
    )
    .await
    .expect("colour image");

    // Clicking the second object selects it; dragging and the wheel move the 3D camera.
    page.eval("document.querySelectorAll('.track')[1].click()")
        .await
        .expect("click track");
    page.wait_for(
        "document.querySelector('.track.selected')?.dataset.trackId === '2'",
        WAIT,
        "the clicked track to be selected",
    )
    .await
    .expect("selection");
    let orbit_before = page
        .eval("document.getElementById('view3d').dataset.orbit")
        .await
        .expect("orbit");
    let (x, y) = (700.0, 300.0);
    for (kind, dx, buttons) in [
        ("mousePressed", 0.0, 1),
        ("mouseMoved", 40.0, 1),
        ("mouseMoved", 120.0, 1),
        ("mouseReleased", 120.0, 0),
    ] {
        page.call(
            "Input.dispatchMouseEvent",
            serde_json::json!({ "type": kind, "x": x + dx, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 }),
        )
        .await
        .expect("mouse event");
    }
    page.call(
        "Input.dispatchMouseEvent",
        serde_json::json!({ "type": "mouseWheel", "x": x, "y": y, "deltaX": 0, "deltaY": 300 }),
    )
    .await
    .expect("wheel");
    let orbit_after = page
        .wait_for(
            &format!("(() => {{ const o = document.getElementById('view3d').dataset.orbit; return o !== {orbit_before} ? o : null; }})()"),
            WAIT,
            "the orbit camera to move",
        )
        .await
        .expect("orbit moved");
    eprintln!("orbit (yaw pitch distance): {orbit_before} -> {orbit_after}");

    // A 1366x768 laptop screen: everything fits without horizontal scrolling.
    page.call(
        "Emulation.setDeviceMetricsOverride",
        serde_json::json!({ "width": 1366, "height": 768, "deviceScaleFactor": 1, "mobile": false }),
    )
    .await
    .expect("resize");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let overflow = page
        .eval("document.documentElement.scrollWidth - window.innerWidth")
        .await
        .expect("layout width");
    assert!(
        overflow.as_f64().unwrap_or(1.0) <= 0.0,
        "page wider than a 1366 px screen by {overflow} px"
    );
    page.screenshot(&target_dir().join("dashboard-screenshot-mock-1366x768.png"))
        .await
        .expect("laptop screenshot");

    // Without WebGL the Canvas 2D fallback draws the same scene.
    page.navigate(&format!("{base_url}/?renderer=canvas2d"))
        .await
        .expect("reload with canvas2d");
    page.wait_for(
        "document.body.dataset.renderer === 'canvas2d'",
        WAIT,
        "the Canvas 2D renderer",
    )
    .await
    .expect("fallback");
    page.wait_for(
        "Number(document.body.dataset.particlesDrawn) > 0",
        WAIT,
        "particles drawn by the fallback",
    )
    .await
    .expect("fallback draws particles");
    let lit = lit_pixels_3d(page).await;
    assert!(lit > 500.0, "Canvas 2D fallback drew almost nothing: {lit} lit pixels");

    let weight = page_weight_bytes();
    eprintln!(
        "dashboard (mock service): page weight {weight} B, update rate seen by the page {rate:.1} events/s, \
         screenshot {} ({bytes} B)",
        shot.display()
    );
    assert!(weight < PAGE_WEIGHT_BUDGET_BYTES, "static/ weighs {weight} B");
    browser.close().await;
}

/// A free local port: bind port 0, read it, release it (the server binds it right after).
fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind a free port");
    l.local_addr().expect("local address").port()
}

/// `pregrasp serve` as a child process with a fresh data folder, killed when dropped.
struct ServiceProcess {
    child: tokio::process::Child,
    log: PathBuf,
    base_url: String,
    _data_dir: tempfile::TempDir,
}

impl ServiceProcess {
    /// Starts `pregrasp serve --addr 127.0.0.1:<free port> --data-dir <tmp> <extra>` and waits
    /// for `/healthz`; `name` names the log file in the target folder.
    async fn start(extra: &[&str], name: &str) -> ServiceProcess {
        let port = free_port();
        let data_dir = tempfile::tempdir().expect("data dir");
        let log = target_dir().join(format!("dashboard-{name}-server.log"));
        let log_file = std::fs::File::create(&log).expect("server log file");
        let addr = format!("127.0.0.1:{port}");
        let data = data_dir.path().display().to_string();
        let mut args = vec!["serve", "--addr", addr.as_str(), "--data-dir", data.as_str()];
        args.extend_from_slice(extra);
        let child = tokio::process::Command::new(env!("CARGO_BIN_EXE_pregrasp"))
            .args(&args)
            .env(
                "WGPU_BACKEND",
                std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "vulkan".into()),
            )
            .stdin(std::process::Stdio::null())
            .stdout(log_file.try_clone().expect("log file"))
            .stderr(log_file)
            .kill_on_drop(true)
            .spawn()
            .expect("start pregrasp serve");
        let mut server = ServiceProcess {
            child,
            log,
            base_url: format!("http://{addr}"),
            _data_dir: data_dir,
        };
        server.wait_healthy(Duration::from_secs(180)).await;
        server
    }

    /// The binary embeds static/ at compile time: fail clearly if it serves other bytes than
    /// the files on disk (a stale build).
    async fn assert_serves_current_static_files(&self) {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("static");
        for entry in std::fs::read_dir(&dir).expect("static/").filter_map(Result::ok) {
            let name = entry.file_name().to_string_lossy().to_string();
            let on_disk = std::fs::read(entry.path()).expect("static file");
            let served = reqwest::get(format!("{}/{name}", self.base_url))
                .await
                .and_then(|r| r.error_for_status())
                .expect("GET static file")
                .bytes()
                .await
                .expect("body");
            assert!(
                served.as_ref() == on_disk.as_slice(),
                "the server's embedded static/{name} differs from the file on disk: rebuild the \
                 binary (include_dir does not track static/ on stable Rust)"
            );
        }
    }

    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(30)..].join("\n")
    }

    async fn wait_healthy(&mut self, timeout: Duration) {
        let deadline = Instant::now() + timeout;
        let url = format!("{}/healthz", self.base_url);
        loop {
            if let Ok(r) = reqwest::get(&url).await
                && r.status().is_success()
            {
                return;
            }
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!("pregrasp serve exited with {status}; log:\n{}", self.log_tail());
            }
            assert!(
                Instant::now() < deadline,
                "pregrasp serve not healthy after {timeout:?}; log:\n{}",
                self.log_tail()
            );
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_follows_pregrasp_serve_demo() {
    let _one = ONE_AT_A_TIME.lock().await;
    let server = ServiceProcess::start(&["--demo"], "demo").await;
    server.assert_serves_current_static_files().await;
    let mut browser = Browser::launch(WIDTH_PX, HEIGHT_PX).await.expect("launch Chromium");
    let page = &mut browser.page;
    check_live_dashboard(page, &server.base_url).await;

    // The real camera routes: a latest depth image, its detections and projected particles.
    page.wait_for(
        "[...document.querySelectorAll('.camera-panel')].some(f => f.dataset.imageLoaded === 'true' && Number(f.dataset.detections) > 0 && Number(f.dataset.particlesProjected) > 0)",
        WAIT,
        "a camera panel with image, detection boxes and projected particles",
    )
    .await
    .expect("camera panel from the real service");
    let track_updates_before = body_number(page, "trackUpdates").await;
    let window = Duration::from_secs(10);
    let t0 = Instant::now();
    let rate = measure_update_rate_hz(page, window).await;
    let track_rate = (body_number(page, "trackUpdates").await - track_updates_before) / t0.elapsed().as_secs_f64();
    let render_ms = body_number(page, "renderMs").await;
    let shot = target_dir().join("dashboard-screenshot.png");
    let bytes = page.screenshot(&shot).await.expect("screenshot");
    let weight = page_weight_bytes();
    eprintln!(
        "dashboard (pregrasp serve --demo): page weight {weight} B, update rate seen by the page \
         {rate:.1} events/s ({track_rate:.1} track events/s) over {window:?}, redraw {render_ms:.1} ms \
         (smoothed), screenshot {} ({bytes} B)",
        shot.display()
    );
    assert!(
        rate >= 2.0,
        "the demo must update the page at >= 2 Hz, saw {rate:.2} events/s; server log:\n{}",
        server.log_tail()
    );
    browser.close().await;
    drop(server);
}

/// The real service with no data: the embedded page loads, connects to the real event stream,
/// shows the service's stats and that nothing is tracked, without script errors.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_loads_from_real_service_without_data() {
    let _one = ONE_AT_A_TIME.lock().await;
    let server = ServiceProcess::start(&[], "empty").await;
    server.assert_serves_current_static_files().await;
    let mut browser = Browser::launch(WIDTH_PX, HEIGHT_PX).await.expect("launch Chromium");
    let page = &mut browser.page;
    page.navigate(&format!("{}/", server.base_url))
        .await
        .expect("open dashboard");
    page.wait_for(
        "document.body.dataset.connection === 'live'",
        WAIT,
        "the event stream to connect",
    )
    .await
    .expect("connected");
    page.wait_for(
        "document.getElementById('stats').textContent.includes('tracker')",
        WAIT,
        "the service's stats event",
    )
    .await
    .expect("stats shown");
    let empty = page
        .eval("document.body.dataset.tracks === '0' && !document.getElementById('no-tracks').hidden")
        .await
        .expect("empty state");
    assert_eq!(empty, serde_json::Value::Bool(true), "an empty service shows no tracks");
    let errors = page
        .eval("document.documentElement.dataset.jsErrors ?? ''")
        .await
        .expect("errors hook");
    assert_eq!(
        errors.as_str(),
        Some(""),
        "script errors in the page:\n{}",
        server.log_tail()
    );
    browser.close().await;
}

/// Developer tool, not part of the suite: screenshots a dashboard that is already running, e.g.
/// `PREGRASP_DASHBOARD_URL=http://127.0.0.1:8080 cargo test --test dashboard -- --ignored
/// screenshot_running`, after waiting `PREGRASP_DASHBOARD_WAIT_S` (default 10) seconds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs a running service at $PREGRASP_DASHBOARD_URL"]
async fn screenshot_running_dashboard() {
    let url = std::env::var("PREGRASP_DASHBOARD_URL").expect("set PREGRASP_DASHBOARD_URL");
    let wait_s: u64 = std::env::var("PREGRASP_DASHBOARD_WAIT_S")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10);
    let mut browser = Browser::launch(WIDTH_PX, HEIGHT_PX).await.expect("launch Chromium");
    let page = &mut browser.page;
    page.navigate(&format!("{url}/")).await.expect("open dashboard");
    tokio::time::sleep(Duration::from_secs(wait_s)).await;
    let hooks = page
        .eval("JSON.stringify({...document.body.dataset, errors: document.documentElement.dataset.jsErrors})")
        .await
        .expect("hooks");
    let shot = target_dir().join("dashboard-screenshot-running.png");
    page.screenshot(&shot).await.expect("screenshot");
    eprintln!("hooks: {hooks}\nscreenshot: {}", shot.display());
    browser.close().await;
}

/// The page's pose and pinhole maths (static/math.js), run in the browser: a point the mock's
/// stationary camera looks at projects to the principal point, unprojection inverts
/// projection, and composing a pose with its inverse gives the identity.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_math_matches_the_camera_conventions() {
    let _one = ONE_AT_A_TIME.lock().await;
    let server = mock::spawn().await;
    let base_url = format!("http://{}", server.addr);
    let mut browser = Browser::launch(800, 600).await.expect("launch Chromium");
    let page = &mut browser.page;
    page.navigate(&format!("{base_url}/")).await.expect("open dashboard");
    page.wait_for("document.body?.dataset.connection === 'live'", WAIT, "the page")
        .await
        .expect("page loaded");
    let result = page
        .eval(
            "(async () => {
               const m = await import('/math.js');
               const scene = await (await fetch('/api/v1/scene')).json();
               const cam = scene.cameras.find((c) => c.id === 'ext1');
               const worldFromCamera = m.parsePose(cam.world_from_camera);
               const k = cam.intrinsics.k;
               const target = m.transformPoint(m.invertPose(worldFromCamera), [0.0, 0.05, 0.05]);
               const uv = m.projectPixel(k, target);
               const back = m.unprojectPixel(k, 100.5, 400.25, 0.8);
               const uv2 = m.projectPixel(k, back);
               const id = m.composePose(worldFromCamera, m.invertPose(worldFromCamera));
               const behind = m.projectPixel(k, [0.1, 0.1, -1.0]);
               const uvFlat = m.projectPixel(k.flat(), target); // the service sends k flat, row-major
               return { uv, uvFlat, uv2, depth: target[2], idT: id.t, idQ: id.q, behind };
             })()",
        )
        .await
        .expect("math module");
    let num = |v: &serde_json::Value| v.as_f64().expect("number");
    let uv = &result["uv"];
    assert!(
        (num(&uv[0]) - 320.0).abs() < 1e-6 && (num(&uv[1]) - 240.0).abs() < 1e-6,
        "look-at target projects to the principal point: {uv}"
    );
    assert_eq!(result["uvFlat"], result["uv"], "flat and nested k give the same pixel");
    assert!(num(&result["depth"]) > 0.0, "target in front of the camera");
    let uv2 = &result["uv2"];
    assert!(
        (num(&uv2[0]) - 100.5).abs() < 1e-9 && (num(&uv2[1]) - 400.25).abs() < 1e-9,
        "unproject then project: {uv2}"
    );
    for i in 0..3 {
        assert!(
            num(&result["idT"][i]).abs() < 1e-9,
            "pose * inverse has no translation: {result}"
        );
    }
    assert!(
        (num(&result["idQ"][3]).abs() - 1.0).abs() < 1e-9,
        "pose * inverse has no rotation: {result}"
    );
    assert!(result["behind"].is_null(), "points behind the camera do not project");
    browser.close().await;
}
