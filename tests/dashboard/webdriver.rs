//! The dashboard test's browser: Debian's headless Chromium driven over WebDriver by
//! `fantoccini`, through Debian's `chromedriver` (package `chromium-driver`), started on a free
//! port for each test.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use anyhow::{Context, bail};
use fantoccini::actions::{
    Actions, InputSource, MOUSE_BUTTON_LEFT, MouseActions, PointerAction, WheelAction, WheelActions,
};
use fantoccini::{Client, ClientBuilder};
use hyper_util::client::legacy::connect::HttpConnector;
use serde_json::{Value, json};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};

/// Finds `name` at `$env_var`, else at the first of `defaults` that exists.
fn find_exe(env_var: &str, defaults: &[&str], what: &str) -> anyhow::Result<PathBuf> {
    let candidates: Vec<PathBuf> = match std::env::var_os(env_var) {
        Some(p) => vec![PathBuf::from(p)],
        None => defaults.iter().map(PathBuf::from).collect(),
    };
    candidates.into_iter().find(|p| p.exists()).with_context(|| {
        format!(
            "{what} not found (looked at ${env_var}, {}): the dashboard browser test needs it; \
             install it with `scripts/setup.sh --browser` (Debian packages `chromium`, \
             `chromium-driver`)",
            defaults.join(", ")
        )
    })
}

pub struct Browser {
    driver: Child,
    _profile: tempfile::TempDir,
    pub page: Page,
}

impl Browser {
    /// Starts chromedriver and, through it, headless Chromium with a fresh profile and a
    /// `width` x `height` viewport.
    pub async fn launch(width: u32, height: u32) -> anyhow::Result<Browser> {
        let chromium = find_exe(
            "PREGRASP_CHROMIUM",
            &["/usr/bin/chromium", "/usr/bin/chromium-browser"],
            "Chromium",
        )?;
        let driver_exe = find_exe("PREGRASP_CHROMEDRIVER", &["/usr/bin/chromedriver"], "chromedriver")?;
        let mut driver = Command::new(&driver_exe)
            .arg("--port=0")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("starting {}", driver_exe.display()))?;
        let mut lines = BufReader::new(driver.stdout.take().context("chromedriver stdout")?).lines();
        let port = tokio::time::timeout(Duration::from_secs(30), async {
            while let Some(line) = lines.next_line().await? {
                if let Some(p) = line.strip_prefix("ChromeDriver was started successfully on port ") {
                    return Ok(p.trim_end_matches('.').to_string());
                }
            }
            bail!("chromedriver exited before printing its port")
        })
        .await
        .context("timed out waiting for chromedriver's port")??;
        // Keep draining its output so that chromedriver never blocks on a full pipe.
        tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
        let profile = tempfile::tempdir()?;
        let caps = json!({
            "goog:chromeOptions": {
                "binary": chromium,
                "args": [
                    "--headless",
                    "--no-sandbox",
                    "--disable-gpu",
                    "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader",
                    "--disable-quic",
                    "--disable-background-networking",
                    "--disable-component-update",
                    "--disable-sync",
                    "--disable-dev-shm-usage",
                    "--hide-scrollbars",
                    "--mute-audio",
                    format!("--window-size={width},{height}"),
                    format!("--user-data-dir={}", profile.path().display()),
                ]
            }
        });
        let Value::Object(caps) = caps else {
            unreachable!("capabilities are an object")
        };
        let client = ClientBuilder::new(HttpConnector::new())
            .capabilities(caps)
            .connect(&format!("http://127.0.0.1:{port}"))
            .await
            .context("starting Chromium through chromedriver")?;
        let mut page = Page { client };
        page.set_viewport(width, height).await?;
        Ok(Browser {
            driver,
            _profile: profile,
            page,
        })
    }

    pub async fn close(mut self) {
        let _ = self.page.client.close().await;
        let _ = self.driver.kill().await;
    }
}

/// One WebDriver session with a page.
pub struct Page {
    client: Client,
}

impl Page {
    pub async fn navigate(&mut self, url: &str) -> anyhow::Result<()> {
        self.client
            .goto(url)
            .await
            .with_context(|| format!("navigating to {url}"))
    }

    /// Evaluates a JavaScript expression in the page (awaiting a promise) and returns its value
    /// as JSON.
    pub async fn eval(&mut self, expression: &str) -> anyhow::Result<Value> {
        self.client
            .execute(&format!("return ({expression});"), Vec::new())
            .await
            .with_context(|| format!("evaluating `{expression}`"))
    }

    /// Polls `expression` until it is truthy; returns its last value or fails with `what`.
    pub async fn wait_for(&mut self, expression: &str, timeout: Duration, what: &str) -> anyhow::Result<Value> {
        let deadline = tokio::time::Instant::now() + timeout;
        // Exceptions (e.g. no <body> yet while the page loads) count as "not yet".
        let guarded = format!("(() => {{ try {{ return ({expression}); }} catch (e) {{ return null; }} }})()");
        loop {
            let v = self.eval(&guarded).await?;
            let truthy = match &v {
                Value::Null => false,
                Value::Bool(b) => *b,
                Value::Number(n) => n.as_f64().is_some_and(|x| x != 0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return Ok(v);
            }
            if tokio::time::Instant::now() > deadline {
                let hooks = self
                    .eval("JSON.stringify({...document.body?.dataset, errors: document.documentElement.dataset.jsErrors})")
                    .await?;
                bail!("timed out after {timeout:?} waiting for {what} (`{expression}`); page hooks: {hooks}");
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// Resizes the window so that the page's viewport is `width` x `height` (the window's
    /// frame, which headless Chromium also simulates, is added on).
    pub async fn set_viewport(&mut self, width: u32, height: u32) -> anyhow::Result<()> {
        let frame = self
            .eval("[window.outerWidth - window.innerWidth, window.outerHeight - window.innerHeight]")
            .await?;
        let extra = |i: usize| frame[i].as_u64().and_then(|v| u32::try_from(v).ok()).unwrap_or(0);
        self.client
            .set_window_size(width + extra(0), height + extra(1))
            .await
            .context("resizing the window")
    }

    /// Presses the left button at (x, y), drags by `dx` pixels to the right and releases.
    pub async fn drag(&mut self, x: f64, y: f64, dx: f64) -> anyhow::Result<()> {
        let mouse = MouseActions::new("mouse".into())
            .then(PointerAction::MoveTo { duration: None, x, y })
            .then(PointerAction::Down {
                button: MOUSE_BUTTON_LEFT,
            })
            .then(PointerAction::MoveBy {
                duration: None,
                x: dx / 3.0,
                y: 0.0,
            })
            .then(PointerAction::MoveBy {
                duration: None,
                x: dx - dx / 3.0,
                y: 0.0,
            })
            .then(PointerAction::Up {
                button: MOUSE_BUTTON_LEFT,
            });
        self.client
            .perform_actions(Actions::from(mouse))
            .await
            .context("mouse drag")
    }

    /// Turns the mouse wheel by `delta_y` pixels over (x, y).
    pub async fn wheel(&mut self, x: i64, y: i64, delta_y: i64) -> anyhow::Result<()> {
        let wheel = WheelActions::new("wheel".into()).then(WheelAction::Scroll {
            duration: None,
            x,
            y,
            delta_x: 0,
            delta_y,
        });
        self.client
            .perform_actions(Actions::from(wheel))
            .await
            .context("mouse wheel")
    }

    pub async fn screenshot(&mut self, path: &Path) -> anyhow::Result<usize> {
        let bytes = self.client.screenshot().await.context("screenshot")?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, &bytes)?;
        Ok(bytes.len())
    }
}
