//! The HTTP service (axum): registry of cameras, objects and grippers, frame and odometry
//! ingest, tracks, decisions, live events, metrics, OpenAPI and the embedded dashboard.
//!
//! Layout: one file per resource, each with its own `router()` built with utoipa-axum's
//! `OpenApiRouter`, so that the routes and the OpenAPI document come from the same
//! annotations. [`error::ApiError`] is the only place where HTTP status codes appear.
//! [`app`] builds the whole service from an [`AppState`]; [`serve_on`] runs it until a
//! shutdown signal.

//! The HTTP layer (axum) over the service: it extracts and validates each request, converts
//! its DTOs once into domain types, calls [`crate::service`], and converts the answer into a
//! typed response. Cameras, objects and grippers, frame and odometry ingest, tracks, decisions,
//! live events, metrics, OpenAPI and the embedded dashboard.
//!
//! Layout: one file per resource, each with its own `router()` built with utoipa-axum's
//! `OpenApiRouter`, so that the routes and the OpenAPI document come from the same
//! annotations. [`error::ApiError`] is the only place where HTTP status codes appear.
//! [`app`] builds the whole service from an [`AppState`]; [`serve_on`] runs it until a
//! shutdown signal.

pub mod cameras;
pub mod cli;
pub mod decisions;
pub mod error;
pub mod events;
pub mod frames;
pub mod grippers;
pub mod health;
pub mod objects;
pub mod scene;
pub mod tracks;
pub mod types;

use crate::service::{Background, Service, ServiceConfig, ServiceState};
use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use error::ApiError;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;

/// Settings of one server instance: the service's and the HTTP layer's own.
#[derive(Debug, Clone)]
pub struct ApiConfig {
    pub service: ServiceConfig,
    /// Bearer token required by every request that changes state (`None`: open).
    pub token: Option<String>,
    /// Largest request body, bytes (413 beyond).
    pub max_body_bytes: usize,
    /// Require the token for reads too (every route but `/healthz`).
    pub protect_reads: bool,
    /// Host names (with or without port) a request's `Host` may name; empty: any (no check).
    pub allowed_hosts: Vec<String>,
    /// Longest time to answer one request (not the event stream).
    pub request_timeout: std::time::Duration,
    /// Longest time a client may take to send a request's headers.
    pub header_read_timeout: std::time::Duration,
    /// Connections served at once (further ones wait in the listen backlog).
    pub max_connections: usize,
}

impl ApiConfig {
    pub fn new(data_dir: PathBuf) -> Self {
        Self {
            service: ServiceConfig::new(data_dir),
            token: None,
            max_body_bytes: 32 * 1024 * 1024,
            protect_reads: false,
            allowed_hosts: Vec::new(),
            request_timeout: std::time::Duration::from_secs(60),
            header_read_timeout: std::time::Duration::from_secs(10),
            max_connections: 256,
        }
    }
}

/// The state of the HTTP layer (cheap to clone): the service and the HTTP settings. It
/// dereferences to the service's state.
#[derive(Clone)]
pub struct AppState {
    pub service: Service,
    pub config: Arc<ApiConfig>,
}

impl std::ops::Deref for AppState {
    type Target = ServiceState;
    fn deref(&self) -> &ServiceState {
        &self.service
    }
}

impl AppState {
    /// Opens the service (store in `config.service.data_dir`).
    pub fn open(config: ApiConfig) -> anyhow::Result<Self> {
        error::BODY_LIMIT_BYTES.store(config.max_body_bytes, Ordering::Relaxed);
        let service = Service::open(config.service.clone())?;
        Ok(Self {
            service,
            config: Arc::new(config),
        })
    }
}

/// Starts the service's background work (the tracking worker, codebook builds, stats).
pub fn start_background(state: &AppState) -> Background {
    crate::service::start_background(&state.service)
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "pregrasp",
        description = "Multi-view 6D pose distribution tracking and grasp-or-observe decisions. \
            State-changing requests need 'Authorization: Bearer <token>' when the server runs with a token. \
            Every error is an RFC 9457 problem document (application/problem+json).",
        license(name = "MIT")
    ),
    components(schemas(error::Problem))
)]
struct ApiDoc;

/// The error answers every operation can give (problem documents), beyond its own.
fn common_errors(has_body: bool) -> Vec<(&'static str, &'static str)> {
    let mut v: Vec<(&'static str, &'static str)> = vec![
        ("400", "Malformed request (body, path or query)"),
        ("401", "A token is required (state changes; reads with --protect-reads)"),
        ("421", "The Host header names none of the server's names"),
    ];
    if has_body {
        v.push(("403", "A state change sent by a web page of another origin"));
    }
    if has_body {
        v.extend([
            ("413", "Body too large"),
            ("415", "Unsupported content type"),
            ("422", "Invalid value"),
        ]);
    }
    v
}

/// Gives every answer a description, documents every error answer as what it is, an RFC 9457
/// problem document
/// (`application/problem+json` with the `Problem` schema), and adds the answers that every
/// operation can give (a malformed request, a missing token, a foreign Host).
fn document_errors(doc: &mut utoipa::openapi::OpenApi) {
    use utoipa::openapi::{Content, Ref, RefOr, ResponseBuilder};
    let problem = || Content::new(Some(Ref::from_schema_name("Problem")));
    for item in doc.paths.paths.values_mut() {
        let ops = [
            &mut item.get,
            &mut item.put,
            &mut item.post,
            &mut item.delete,
            &mut item.patch,
            &mut item.head,
            &mut item.options,
        ];
        for op in ops.into_iter().flatten() {
            for (status, description) in common_errors(op.request_body.is_some()) {
                op.responses
                    .responses
                    .entry(status.to_string())
                    .or_insert_with(|| RefOr::T(ResponseBuilder::new().description(description).build()));
            }
            for (status, response) in op.responses.responses.iter_mut() {
                let RefOr::T(r) = response else { continue };
                // OpenAPI 3.1 requires a description on every response (client generators
                // refuse a document without): the status's reason phrase when none was given
                if r.description.is_empty() {
                    r.description = status
                        .parse::<u16>()
                        .ok()
                        .and_then(|s| axum::http::StatusCode::from_u16(s).ok())
                        .and_then(|s| s.canonical_reason())
                        .unwrap_or("Answer")
                        .to_string();
                }
                if status.starts_with('4') || status.starts_with('5') {
                    r.content.clear();
                    r.content
                        .insert("application/problem+json".to_string(), problem().into());
                }
            }
        }
    }
}

/// The API routes (under `/api/v1`) with their OpenAPI document.
fn api_router() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .nest(
            "/api/v1",
            OpenApiRouter::new()
                .merge(cameras::router())
                .merge(objects::router())
                .merge(grippers::router())
                .merge(frames::router())
                .merge(tracks::router())
                .merge(decisions::router())
                .merge(scene::router())
                .merge(events::router()),
        )
        .merge(health::router())
}

/// The OpenAPI document of the service (the same one served at `/openapi.json`).
pub fn openapi() -> utoipa::openapi::OpenApi {
    let mut doc = api_router().into_openapi();
    document_errors(&mut doc);
    doc
}

/// Compares two byte strings in time that depends on their lengths only.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The token of an `Authorization: Bearer <token>` header (the scheme is case-insensitive).
fn bearer_token(headers: &axum::http::HeaderMap) -> Option<&str> {
    let v = headers.get(axum::http::header::AUTHORIZATION)?.to_str().ok()?;
    let (scheme, token) = v.trim().split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then_some(token.trim())
}

/// Requests that change state (and with `protect_reads` every request but `/healthz`) need the
/// bearer token when one is configured.
async fn require_token(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let changes_state = !matches!(*req.method(), Method::GET | Method::HEAD | Method::OPTIONS);
    let needs_token = changes_state || (state.config.protect_reads && req.uri().path() != "/healthz");
    if let (true, Some(token)) = (needs_token, state.config.token.as_deref()) {
        let ok = bearer_token(req.headers()).is_some_and(|given| constant_time_eq(given.as_bytes(), token.as_bytes()));
        if !ok {
            return ApiError::Unauthorized.into_response();
        }
    }
    next.run(req).await
}

/// Refuses requests whose `Host` is not one of the server's names (DNS rebinding: a web page
/// of another origin that resolves its own name to this address), and state changes sent by a
/// web page of another origin (`Origin`).
async fn check_host(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let allowed = &state.config.allowed_hosts;
    if !allowed.is_empty() {
        let host = req
            .headers()
            .get(axum::http::header::HOST)
            .and_then(|v| v.to_str().ok())
            .or_else(|| req.uri().authority().map(|a| a.as_str()))
            .unwrap_or("")
            .to_ascii_lowercase();
        if !host_allowed(&host, allowed) {
            return ApiError::MisdirectedHost(types::shorten(&host)).into_response();
        }
        // a web page of another origin may send a "simple" POST (a form, no preflight): a
        // state change whose Origin is not one of the server's names is refused
        let changes_state = !matches!(*req.method(), Method::GET | Method::HEAD | Method::OPTIONS);
        let origin = req
            .headers()
            .get(axum::http::header::ORIGIN)
            .and_then(|v| v.to_str().ok())
            .map(|o| o.to_ascii_lowercase());
        if let (true, Some(origin)) = (changes_state, origin) {
            let origin_host = origin.split_once("://").map_or(origin.as_str(), |(_, h)| h);
            if !host_allowed(origin_host, allowed) {
                return ApiError::Disabled(format!(
                    "state changes from the web origin '{}' are refused",
                    types::shorten(&origin)
                ))
                .into_response();
            }
        }
    }
    next.run(req).await
}

/// Whether `host` (`name` or `name:port`) is in `allowed` (entries `name` match any port).
pub fn host_allowed(host: &str, allowed: &[String]) -> bool {
    let name = match host.rsplit_once(':') {
        // an IPv6 literal keeps its brackets: "[::1]:8080" -> "[::1]"
        Some((n, port)) if !port.contains(']') && port.chars().all(|c| c.is_ascii_digit()) => n,
        _ => host,
    };
    allowed
        .iter()
        .any(|a| a.eq_ignore_ascii_case(host) || a.eq_ignore_ascii_case(name))
}

/// Ends a request that takes longer than `request_timeout` with a 503 (the event stream, which
/// never ends by design, is exempt).
async fn request_timeout(State(state): State<AppState>, req: Request, next: Next) -> Response {
    if req.uri().path().ends_with("/events") {
        return next.run(req).await;
    }
    let limit = state.config.request_timeout;
    match tokio::time::timeout(limit, next.run(req)).await {
        Ok(resp) => resp,
        Err(_) => ApiError::NotReady(format!(
            "the request took longer than {:.0} s and was abandoned",
            limit.as_secs_f64()
        ))
        .into_response(),
    }
}

/// The methods the OpenAPI document lists for a concrete path (`{param}` matches any one
/// segment), as an `Allow` header value.
fn allowed_methods(path: &str) -> String {
    static ROUTES: std::sync::OnceLock<Vec<(Vec<String>, Vec<&'static str>)>> = std::sync::OnceLock::new();
    let routes = ROUTES.get_or_init(|| {
        openapi()
            .paths
            .paths
            .iter()
            .map(|(template, item)| {
                let mut methods = Vec::new();
                for (m, op) in [
                    ("GET", &item.get),
                    ("HEAD", &item.get),
                    ("PUT", &item.put),
                    ("POST", &item.post),
                    ("DELETE", &item.delete),
                    ("PATCH", &item.patch),
                ] {
                    if op.is_some() {
                        methods.push(m);
                    }
                }
                (template.split('/').map(String::from).collect(), methods)
            })
            .collect()
    });
    let segments: Vec<&str> = path.split('/').collect();
    routes
        .iter()
        .find(|(template, _)| {
            template.len() == segments.len()
                && template
                    .iter()
                    .zip(&segments)
                    .all(|(t, s)| (t.starts_with('{') && t.ends_with('}')) || t == s)
        })
        .map(|(_, methods)| methods.join(","))
        .unwrap_or_default()
}

/// Turns bare error responses made outside our handlers (method not allowed, ...) into problem
/// documents, and counts rejected requests.
async fn problem_everywhere(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let path = req.uri().path().to_string();
    let resp = next.run(req).await;
    let status = resp.status();
    if status.is_client_error() {
        state.metrics.requests_rejected.fetch_add(1, Ordering::Relaxed);
        let is_problem = resp
            .headers()
            .get(axum::http::header::CONTENT_TYPE)
            .is_some_and(|v| v.as_bytes().starts_with(b"application/problem+json"));
        if !is_problem && let Some(mut e) = error::response_to_problem(&resp) {
            if let ApiError::MethodNotAllowed { allow } = &mut e
                && allow.is_empty()
            {
                *allow = allowed_methods(&path);
            }
            return e.into_response();
        }
    }
    resp
}

/// The whole service: API, OpenAPI document and docs, health, metrics, dashboard.
pub fn app(state: AppState) -> Router {
    let (router, mut openapi) = api_router().split_for_parts();
    document_errors(&mut openapi);
    let docs = utoipa_swagger_ui::SwaggerUi::new("/docs").url("/openapi.json", openapi);
    router
        .merge(docs)
        .merge(health::dashboard_router())
        .fallback(health::fallback)
        .layer(axum::middleware::from_fn_with_state(state.clone(), request_timeout))
        .layer(axum::middleware::from_fn_with_state(state.clone(), require_token))
        .layer(axum::middleware::from_fn_with_state(state.clone(), check_host))
        .layer(axum::middleware::from_fn_with_state(state.clone(), problem_everywhere))
        .layer(DefaultBodyLimit::max(state.config.max_body_bytes))
        .with_state(state)
}

/// Longest wait for open connections to finish after a shutdown signal.
pub const SHUTDOWN_DRAIN: std::time::Duration = std::time::Duration::from_secs(30);

/// Serves `app(state)` on `listener` until `shutdown` resolves (graceful: in-flight requests
/// finish, SSE streams end). HTTP/1.1 with a header-read timeout and at most
/// `max_connections` connections at once (further ones wait in the listen backlog).
pub async fn serve_on(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    use hyper_util::rt::{TokioIo, TokioTimer};
    let flag = state.shutting_down.clone();
    let header_read_timeout = state.config.header_read_timeout;
    let slots = Arc::new(tokio::sync::Semaphore::new(state.config.max_connections.max(1)));
    let router = app(state);
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let permit = tokio::select! {
            p = slots.clone().acquire_owned() => p.map_err(std::io::Error::other)?,
            () = &mut shutdown => break,
        };
        let (stream, _) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // out of file descriptors and the like: wait rather than spin
                    tracing::warn!("accept: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let service = hyper_util::service::TowerToHyperService::new(router.clone());
        let mut builder = hyper::server::conn::http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(header_read_timeout);
        let conn = graceful.watch(builder.serve_connection(TokioIo::new(stream), service));
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                tracing::debug!("connection: {e}");
            }
            drop(permit);
        });
    }
    drop(listener);
    // Event streams never end by themselves: end them so that the drain can finish.
    flag.send_replace(true);
    if tokio::time::timeout(SHUTDOWN_DRAIN, graceful.shutdown()).await.is_err() {
        tracing::warn!("connections still open after {} s; closing", SHUTDOWN_DRAIN.as_secs());
    }
    Ok(())
}
