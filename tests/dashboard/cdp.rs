//! A tiny Chrome DevTools Protocol client: starts Debian's Chromium headless with
//! `--remote-debugging-port=0`, reads the DevTools address it prints, and talks JSON-RPC to the
//! page over a minimal hand-written WebSocket (RFC 6455 client side: masked text frames out,
//! unmasked text/continuation/ping/close frames in). No extra crates needed.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use anyhow::{Context, bail};
use serde_json::{Value, json};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tokio::process::{Child, Command};

/// Where Chromium is looked for: `PREGRASP_CHROMIUM`, else Debian's `/usr/bin/chromium`.
pub fn chromium_path() -> anyhow::Result<PathBuf> {
    let candidates: Vec<PathBuf> = match std::env::var_os("PREGRASP_CHROMIUM") {
        Some(p) => vec![PathBuf::from(p)],
        None => vec![
            PathBuf::from("/usr/bin/chromium"),
            PathBuf::from("/usr/bin/chromium-browser"),
        ],
    };
    candidates.into_iter().find(|p| p.exists()).context(
        "Chromium not found (looked at $PREGRASP_CHROMIUM, /usr/bin/chromium, \
         /usr/bin/chromium-browser): the dashboard browser test needs it; install it with \
         `scripts/setup.sh --browser` (Debian package `chromium`)",
    )
}

pub struct Browser {
    child: Child,
    _profile: tempfile::TempDir,
    pub page: Page,
}

impl Browser {
    /// Starts headless Chromium with a fresh profile and attaches to its first page.
    pub async fn launch(width: u32, height: u32) -> anyhow::Result<Browser> {
        let exe = chromium_path()?;
        let profile = tempfile::tempdir()?;
        let mut child = Command::new(&exe)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--disable-quic",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-extensions",
                "--disable-dev-shm-usage",
                "--hide-scrollbars",
                "--mute-audio",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
                &format!("--window-size={width},{height}"),
                &format!("--user-data-dir={}", profile.path().display()),
                "about:blank",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("starting {}", exe.display()))?;
        let stderr = child.stderr.take().context("chromium stderr")?;
        let mut lines = BufReader::new(stderr).lines();
        let browser_ws = tokio::time::timeout(Duration::from_secs(30), async {
            while let Some(line) = lines.next_line().await? {
                if let Some(pos) = line.find("ws://") {
                    return Ok(line[pos..].trim().to_string());
                }
            }
            bail!("chromium exited before printing its DevTools address")
        })
        .await
        .context("timed out waiting for chromium's DevTools address")??;
        // Keep draining stderr so that Chromium never blocks on a full pipe.
        tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
        let http_base = browser_ws
            .trim_start_matches("ws://")
            .split('/')
            .next()
            .context("DevTools address")?
            .to_string();
        let page_ws = find_page(&http_base).await?;
        let mut page = Page::connect(&page_ws).await?;
        page.call(
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": width, "height": height, "deviceScaleFactor": 1, "mobile": false }),
        )
        .await?;
        Ok(Browser {
            child,
            _profile: profile,
            page,
        })
    }

    pub async fn close(mut self) {
        let _ = self.page.call("Browser.close", json!({})).await;
        let _ = tokio::time::timeout(Duration::from_secs(5), self.child.wait()).await;
        let _ = self.child.kill().await;
    }
}

async fn find_page(http_base: &str) -> anyhow::Result<String> {
    let url = format!("http://{http_base}/json/list");
    for _ in 0..50 {
        if let Ok(resp) = reqwest::get(&url).await
            && let Ok(list) = resp.json::<Vec<Value>>().await
            && let Some(ws) = list
                .iter()
                .find(|t| t["type"] == "page")
                .and_then(|t| t["webSocketDebuggerUrl"].as_str())
        {
            return Ok(ws.to_string());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    bail!("no page target at {url}")
}

/// One DevTools session with a page.
pub struct Page {
    ws: WebSocket,
    next_id: u64,
}

impl Page {
    async fn connect(ws_url: &str) -> anyhow::Result<Page> {
        Ok(Page {
            ws: WebSocket::connect(ws_url).await?,
            next_id: 1,
        })
    }

    /// Sends one command and waits for its answer (events in between are dropped).
    pub async fn call(&mut self, method: &str, params: Value) -> anyhow::Result<Value> {
        let id = self.next_id;
        self.next_id += 1;
        self.ws
            .send_text(&json!({ "id": id, "method": method, "params": params }).to_string())
            .await?;
        loop {
            let msg: Value = serde_json::from_str(&self.ws.recv_text().await?)?;
            if msg["id"].as_u64() == Some(id) {
                if let Some(err) = msg.get("error") {
                    bail!("{method} failed: {err}");
                }
                return Ok(msg["result"].clone());
            }
        }
    }

    pub async fn navigate(&mut self, url: &str) -> anyhow::Result<()> {
        let r = self.call("Page.navigate", json!({ "url": url })).await?;
        if let Some(e) = r.get("errorText").and_then(Value::as_str) {
            bail!("navigating to {url}: {e}");
        }
        Ok(())
    }

    /// Evaluates a JavaScript expression in the page and returns its value as JSON.
    pub async fn eval(&mut self, expression: &str) -> anyhow::Result<Value> {
        let r = self
            .call(
                "Runtime.evaluate",
                json!({ "expression": expression, "returnByValue": true, "awaitPromise": true }),
            )
            .await?;
        if let Some(ex) = r.get("exceptionDetails") {
            bail!("evaluating `{expression}`: {ex}");
        }
        Ok(r["result"]["value"].clone())
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

    pub async fn screenshot(&mut self, path: &Path) -> anyhow::Result<usize> {
        use base64::Engine as _;
        let r = self.call("Page.captureScreenshot", json!({ "format": "png" })).await?;
        let data = r["data"].as_str().context("screenshot data")?;
        let bytes = base64::engine::general_purpose::STANDARD.decode(data)?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, &bytes)?;
        Ok(bytes.len())
    }
}

/// Client side of a WebSocket connection on plain TCP (enough for a local DevTools endpoint).
struct WebSocket {
    stream: TcpStream,
}

const OP_CONTINUATION: u8 = 0x0;
const OP_TEXT: u8 = 0x1;
const OP_CLOSE: u8 = 0x8;
const OP_PING: u8 = 0x9;
const OP_PONG: u8 = 0xA;

impl WebSocket {
    async fn connect(url: &str) -> anyhow::Result<WebSocket> {
        let rest = url.strip_prefix("ws://").context("only ws:// URLs are supported")?;
        let (host, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
        let mut stream = TcpStream::connect(host).await?;
        stream.set_nodelay(true)?;
        let request = format!(
            "GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Key: cHJlZ3Jhc3AtZGFzaGJvYXJk\r\nSec-WebSocket-Version: 13\r\n\r\n"
        );
        stream.write_all(request.as_bytes()).await?;
        // Read the response head byte by byte so that no frame bytes are consumed.
        let mut head = Vec::new();
        while !head.ends_with(b"\r\n\r\n") {
            let b = stream.read_u8().await?;
            head.push(b);
            if head.len() > 16 * 1024 {
                bail!("WebSocket handshake response too long");
            }
        }
        let head = String::from_utf8_lossy(&head);
        if !head.starts_with("HTTP/1.1 101") {
            bail!("WebSocket handshake refused: {head}");
        }
        Ok(WebSocket { stream })
    }

    async fn send_frame(&mut self, opcode: u8, payload: &[u8]) -> anyhow::Result<()> {
        let mut frame = Vec::with_capacity(payload.len() + 14);
        frame.push(0x80 | opcode);
        let len = payload.len();
        if len < 126 {
            frame.push(0x80 | len as u8);
        } else if len <= usize::from(u16::MAX) {
            frame.push(0x80 | 126);
            frame.extend_from_slice(&(len as u16).to_be_bytes());
        } else {
            frame.push(0x80 | 127);
            frame.extend_from_slice(&(len as u64).to_be_bytes());
        }
        let mask = [0x37, 0xfa, 0x21, 0x3d];
        frame.extend_from_slice(&mask);
        frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        self.stream.write_all(&frame).await?;
        Ok(())
    }

    async fn send_text(&mut self, text: &str) -> anyhow::Result<()> {
        self.send_frame(OP_TEXT, text.as_bytes()).await
    }

    /// Receives the next complete text message, answering pings on the way.
    async fn recv_text(&mut self) -> anyhow::Result<String> {
        let mut message = Vec::new();
        loop {
            let b0 = self.stream.read_u8().await?;
            let b1 = self.stream.read_u8().await?;
            let fin = b0 & 0x80 != 0;
            let opcode = b0 & 0x0f;
            let masked = b1 & 0x80 != 0;
            let len = match b1 & 0x7f {
                126 => u64::from(self.stream.read_u16().await?),
                127 => self.stream.read_u64().await?,
                n => u64::from(n),
            };
            let mut mask = [0u8; 4];
            if masked {
                self.stream.read_exact(&mut mask).await?;
            }
            let mut payload = vec![0u8; usize::try_from(len)?];
            self.stream.read_exact(&mut payload).await?;
            if masked {
                for (i, b) in payload.iter_mut().enumerate() {
                    *b ^= mask[i % 4];
                }
            }
            match opcode {
                OP_TEXT | OP_CONTINUATION => {
                    message.extend_from_slice(&payload);
                    if fin {
                        return Ok(String::from_utf8(message)?);
                    }
                }
                OP_PING => self.send_frame(OP_PONG, &payload).await?,
                OP_CLOSE => bail!("DevTools closed the WebSocket"),
                _ => {}
            }
        }
    }
}
