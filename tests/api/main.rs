//! Integration tests of the HTTP service: one binary, one module per concern.
//! `spawn_app()` starts a server on 127.0.0.1:0 with a fresh data folder.

mod bad_requests;
mod hardening;
mod ingest;
mod openapi;
mod python_client;
mod registry;
mod replay;
mod tracking;

use pregrasp::api::{ApiConfig, AppState};
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::path::PathBuf;

pub struct TestApp {
    pub addr: SocketAddr,
    pub client: reqwest::Client,
    pub data_dir: PathBuf,
    pub token: Option<String>,
    pub state: AppState,
    pub config: ApiConfig,
    _tmp: Option<tempfile::TempDir>,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    server: Option<tokio::task::JoinHandle<()>>,
}

impl TestApp {
    pub fn url(&self, path: &str) -> String {
        format!("http://{}{}", self.addr, path)
    }
    pub fn api(&self, path: &str) -> String {
        self.url(&format!("/api/v1{path}"))
    }
    fn auth(&self, rb: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        match &self.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        }
    }
    pub async fn get(&self, path: &str) -> reqwest::Response {
        self.client.get(self.api(path)).send().await.expect("GET")
    }
    pub async fn get_json(&self, path: &str) -> Value {
        let r = self.get(path).await;
        assert!(r.status().is_success(), "GET {path}: {}", r.status());
        r.json().await.expect("json")
    }
    /// The Prometheus text of `/metrics`.
    pub async fn metrics_text(&self) -> String {
        let r = self
            .client
            .get(self.url("/metrics"))
            .send()
            .await
            .expect("GET /metrics");
        assert!(r.status().is_success(), "GET /metrics: {}", r.status());
        r.text().await.expect("metrics text")
    }
    pub async fn put_json(&self, path: &str, body: &Value) -> reqwest::Response {
        self.auth(self.client.put(self.api(path)).json(body))
            .send()
            .await
            .expect("PUT")
    }
    pub async fn post_json(&self, path: &str, body: &Value) -> reqwest::Response {
        self.auth(self.client.post(self.api(path)).json(body))
            .send()
            .await
            .expect("POST")
    }
    pub async fn put_bytes(&self, path: &str, content_type: &str, body: Vec<u8>) -> reqwest::Response {
        self.auth(
            self.client
                .put(self.api(path))
                .header("content-type", content_type)
                .body(body),
        )
        .send()
        .await
        .expect("PUT")
    }
    pub async fn post_raw(&self, path: &str, content_type: &str, body: Vec<u8>) -> reqwest::Response {
        self.auth(
            self.client
                .post(self.api(path))
                .header("content-type", content_type)
                .body(body),
        )
        .send()
        .await
        .expect("POST")
    }

    /// Stops the server and its background work (the data folder stays).
    pub async fn stop(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(h) = self.server.take() {
            h.await.expect("server task");
        }
    }

    /// Stops this server and starts a new one on the same data folder.
    pub async fn restart(mut self) -> TestApp {
        self.stop().await;
        let tmp = self._tmp.take();
        let config = self.config.clone();
        drop(self);
        let mut app = spawn_config(config).await;
        app._tmp = tmp;
        app
    }
}

pub async fn spawn_app() -> TestApp {
    spawn_app_configured(|_| {}).await
}

pub async fn spawn_app_with_token(token: &str) -> TestApp {
    let token = token.to_string();
    spawn_app_configured(move |c| c.token = Some(token)).await
}

/// A server on a fresh data folder with the test settings changed by `configure`.
pub async fn spawn_app_configured(configure: impl FnOnce(&mut ApiConfig)) -> TestApp {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut config = test_config(tmp.path().to_path_buf());
    configure(&mut config);
    let mut app = spawn_config(config).await;
    app._tmp = Some(tmp);
    app
}

/// The settings of a test server (small body limit, ground truth accepted).
pub fn test_config(data_dir: PathBuf) -> ApiConfig {
    let mut config = ApiConfig::new(data_dir);
    config.max_body_bytes = 4 * 1024 * 1024;
    config.service.window_ns = 300_000_000;
    config.service.accept_truth = true;
    config
}

async fn spawn_config(config: ApiConfig) -> TestApp {
    let state = AppState::open(config.clone()).expect("open state");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let st = state.clone();
    let server = tokio::spawn(async move {
        let bg = pregrasp::api::start_background(&st);
        pregrasp::api::serve_on(listener, st, async {
            let _ = rx.await;
        })
        .await
        .expect("serve");
        bg.shutdown().await;
    });
    TestApp {
        addr,
        client: reqwest::Client::new(),
        data_dir: config.service.data_dir.clone(),
        token: config.token.clone(),
        state,
        config,
        _tmp: None,
        shutdown: Some(tx),
        server: Some(server),
    }
}

/// A small camera: 64x48, f = 60 px.
pub fn camera_spec(robot: bool) -> Value {
    let pose = json!({"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 0.0, 0.0]});
    let mount = if robot {
        json!({"type": "robot", "base_from_camera": pose})
    } else {
        json!({"type": "stationary", "world_from_camera": pose})
    };
    json!({
        "intrinsics": {"width": 64, "height": 48, "k": [60.0, 0.0, 32.0, 0.0, 60.0, 24.0, 0.0, 0.0, 1.0]},
        "mount": mount
    })
}

/// A JSON frame with a constant raw f32 depth of `depth_m`.
pub fn frame_json(stamp_ns: i64, w: u32, h: u32, depth_m: f32) -> Value {
    use base64::Engine;
    let bytes: Vec<u8> = (0..w * h).flat_map(|_| depth_m.to_le_bytes()).collect();
    json!({
        "stamp_ns": stamp_ns,
        "depth": {"encoding": "f32le", "data_base64": base64::engine::general_purpose::STANDARD.encode(bytes)},
    })
}

/// Asserts a problem document with `status`; returns it.
pub async fn assert_problem(resp: reqwest::Response, status: u16) -> Value {
    assert_eq!(resp.status().as_u16(), status, "unexpected status");
    let ct = resp
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    assert!(ct.starts_with("application/problem+json"), "content type {ct}");
    let v: Value = resp.json().await.expect("problem json");
    assert_eq!(v["status"], status);
    assert!(v["detail"].as_str().is_some_and(|d| !d.is_empty()), "{v}");
    assert!(
        v["type"]
            .as_str()
            .is_some_and(|t| t.starts_with("urn:pregrasp:problem:"))
    );
    v
}
