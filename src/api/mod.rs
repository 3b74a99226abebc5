//! The HTTP service (axum): registry of cameras, objects and grippers, frame and odometry
//! ingest, tracks, decisions, live events, metrics, OpenAPI and the embedded dashboard.
//!
//! Layout: one file per resource, each with its own `router()` built with utoipa-axum's
//! `OpenApiRouter`, so that the routes and the OpenAPI document come from the same
//! annotations. [`error::ApiError`] is the only place where HTTP status codes appear.
//! [`app`] builds the whole service from an [`AppState`]; [`serve_on`] runs it until a
//! shutdown signal.

pub mod cameras;
pub mod cli;
pub mod codebooks;
pub mod decisions;
pub mod demo;
pub mod error;
pub mod events;
pub mod frames;
pub mod grippers;
pub mod health;
pub mod ingest;
pub mod objects;
pub mod replay;
pub mod scene;
pub mod store;
pub mod tracks;
pub mod types;
pub mod worker;

pub use worker::start_background;

use crate::geometry;
use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use error::ApiError;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Instant;
use store::Store;
use tokio::sync::broadcast;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;

/// Settings of one server instance.
#[derive(Debug, Clone)]
pub struct ApiConfig {
    /// Folder of the embedded store and caches.
    pub data_dir: PathBuf,
    /// Bearer token required by every request that changes state (`None`: open).
    pub token: Option<String>,
    /// Largest request body, bytes (413 beyond).
    pub max_body_bytes: usize,
    /// Fusion window: each camera's latest frame no older than this behind the newest frame is
    /// fused; frames older than the newest minus this are refused (409) as stale.
    pub window_ns: i64,
    /// Unprocessed frames kept per camera before the oldest is dropped (the bounded queue).
    pub max_pending_per_camera: usize,
    /// A detection that matches no track opens a new one only while its object has fewer than
    /// this many live (not lost) tracks (the tracker's `max_tracks_per_object`): a detection
    /// starts a track, it does not duplicate one. Raise it for scenes with several instances
    /// of one object.
    pub max_live_tracks_per_object: usize,
    /// Tracker settings.
    pub tracker: crate::tracker::TrackerConfig,
    /// Codebook grids and settings (coarse first, then optionally fine).
    pub codebooks: codebooks::CodebookPlan,
}

impl ApiConfig {
    pub fn new(data_dir: PathBuf) -> Self {
        Self {
            data_dir,
            token: None,
            max_body_bytes: 32 * 1024 * 1024,
            window_ns: 300_000_000,
            max_pending_per_camera: 4,
            max_live_tracks_per_object: 1,
            tracker: crate::tracker::TrackerConfig::default(),
            codebooks: codebooks::CodebookPlan::default(),
        }
    }
}

/// Counters exported at `/metrics`.
#[derive(Default)]
pub struct Metrics {
    pub frames_accepted: AtomicU64,
    pub frames_stale: AtomicU64,
    pub frames_dropped: AtomicU64,
    pub odometry_accepted: AtomicU64,
    pub steps: AtomicU64,
    pub step_errors: AtomicU64,
    pub step_latency_us_sum: AtomicU64,
    pub last_step_latency_us: AtomicU64,
    pub decisions: AtomicU64,
    /// Decisions that read the worker's sample bank (no wait for the tracker).
    pub decisions_from_bank: AtomicU64,
    /// Decisions answered from an identical query in the same step.
    pub decisions_shared: AtomicU64,
    /// Size of the last tracker snapshot written to the store.
    pub tracker_snapshot_bytes: AtomicU64,
    pub requests_rejected: AtomicU64,
    /// Ingest-to-estimate latencies of the most recent frames, microseconds.
    pub ingest_to_estimate_us: Mutex<LatencyRing>,
}

/// The last [`LatencyRing::CAPACITY`] latencies (bounded), for quantiles.
#[derive(Default)]
pub struct LatencyRing {
    values_us: std::collections::VecDeque<u64>,
}

impl LatencyRing {
    pub const CAPACITY: usize = 20_000;
    pub fn push(&mut self, us: u64) {
        self.values_us.push_back(us);
        if self.values_us.len() > Self::CAPACITY {
            self.values_us.pop_front();
        }
    }
    pub fn len(&self) -> usize {
        self.values_us.len()
    }
    pub fn is_empty(&self) -> bool {
        self.values_us.is_empty()
    }
    /// The `q` quantile (0..=1), microseconds.
    pub fn quantile_us(&self, q: f64) -> Option<u64> {
        let mut v: Vec<u64> = self.values_us.iter().copied().collect();
        if v.is_empty() {
            return None;
        }
        v.sort_unstable();
        let i = ((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
        Some(v[i])
    }
}

/// What the registry knows (in memory; every change is also written to the store).
#[derive(Default)]
pub struct Registry {
    pub cameras: BTreeMap<String, cameras::Camera>,
    pub objects: BTreeMap<String, objects::ObjectEntry>,
    pub grippers: BTreeMap<String, serde_json::Value>,
    /// Bumped on every camera or object change (the tracking worker rebuilds on change).
    pub version: u64,
}

/// Everything the handlers share.
pub struct Shared {
    pub config: ApiConfig,
    pub store: Store,
    pub registry: RwLock<Registry>,
    pub ingest: Mutex<ingest::IngestBuffer>,
    /// Signalled when frames arrive (the tracking worker waits on it).
    pub wake: std::sync::Condvar,
    pub events: broadcast::Sender<events::ServerEvent>,
    pub metrics: Metrics,
    pub tracking: tracks::Tracking,
    pub grasp_objects: decisions::GraspObjects,
    pub decision_cache: decisions::DecisionCache,
    pub codebooks: codebooks::Codebooks,
    /// Decisions running at once (one per core).
    pub decision_slots: Arc<tokio::sync::Semaphore>,
    /// The tracker (built when the first frame arrives; rebuilt when the cameras change).
    pub engine: Mutex<Option<worker::Engine>>,
    /// The tracker snapshot read from the store at start, until the tracker takes it.
    pub restored: Mutex<Option<crate::tracker::TrackerSnapshot>>,
    /// The support plane (world frame) when one is known (demo, replay of a rig with one).
    pub support_plane: Mutex<Option<scene::PlaneDto>>,
    /// Ground truth for display only (`world_from_object` and its stamp per object id).
    pub truth: Mutex<BTreeMap<String, (i64, geometry::Pose)>>,
    /// The latest rates (updated once a second).
    pub stats: Mutex<events::Stats>,
    pub started: Instant,
    /// Set when the server begins its graceful shutdown (ends the event streams).
    pub shutting_down: tokio::sync::watch::Sender<bool>,
}

/// The state of the service (cheap to clone).
#[derive(Clone)]
pub struct AppState(pub Arc<Shared>);

impl std::ops::Deref for AppState {
    type Target = Shared;
    fn deref(&self) -> &Shared {
        &self.0
    }
}

impl AppState {
    /// Opens the store in `config.data_dir` and loads the registry from it.
    pub fn open(config: ApiConfig) -> anyhow::Result<Self> {
        let store = Store::open(&config.data_dir)?;
        let mut registry = Registry::default();
        cameras::load(&store, &mut registry)?;
        objects::load(&store, &mut registry)?;
        grippers::load(&store, &mut registry)?;
        let tracking = tracks::Tracking::default();
        tracks::load(&store, &tracking)?;
        let (events, _) = broadcast::channel(256);
        error::BODY_LIMIT_BYTES.store(config.max_body_bytes, Ordering::Relaxed);
        let ingest = ingest::IngestBuffer::new(config.window_ns, config.max_pending_per_camera);
        let restored = tracks::load_tracker_snapshot(&store);
        Ok(Self(Arc::new(Shared {
            config,
            store,
            registry: RwLock::new(registry),
            ingest: Mutex::new(ingest),
            wake: std::sync::Condvar::new(),
            events,
            metrics: Metrics::default(),
            tracking,
            grasp_objects: decisions::GraspObjects::default(),
            decision_cache: decisions::DecisionCache::default(),
            codebooks: codebooks::Codebooks::default(),
            decision_slots: Arc::new(tokio::sync::Semaphore::new(
                std::thread::available_parallelism().map_or(2, |n| n.get()),
            )),
            engine: Mutex::new(None),
            restored: Mutex::new(restored),
            support_plane: Mutex::new(None),
            truth: Mutex::new(BTreeMap::new()),
            stats: Mutex::new(events::Stats::default()),
            started: Instant::now(),
            shutting_down: tokio::sync::watch::channel(false).0,
        })))
    }

    pub fn registry(&self) -> std::sync::RwLockReadGuard<'_, Registry> {
        self.registry.read().unwrap_or_else(|p| p.into_inner())
    }
    pub fn registry_mut(&self) -> std::sync::RwLockWriteGuard<'_, Registry> {
        self.registry.write().unwrap_or_else(|p| p.into_inner())
    }
    pub fn ingest(&self) -> std::sync::MutexGuard<'_, ingest::IngestBuffer> {
        self.ingest.lock().unwrap_or_else(|p| p.into_inner())
    }
    pub fn publish(&self, e: events::ServerEvent) {
        // No subscriber is not an error.
        let _ = self.events.send(e);
    }
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
    api_router().into_openapi()
}

/// Requests that change state need the bearer token when one is configured.
async fn require_token(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let changes_state = !matches!(*req.method(), Method::GET | Method::HEAD | Method::OPTIONS);
    if let (true, Some(token)) = (changes_state, state.config.token.as_deref()) {
        let given = req
            .headers()
            .get(axum::http::header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        if given != Some(token) {
            state.metrics.requests_rejected.fetch_add(1, Ordering::Relaxed);
            return ApiError::Unauthorized.into_response();
        }
    }
    next.run(req).await
}

/// Turns bare error responses made outside our handlers (method not allowed, ...) into problem
/// documents, and counts rejected requests.
async fn problem_everywhere(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let resp = next.run(req).await;
    let status = resp.status();
    if status.is_client_error() {
        state.metrics.requests_rejected.fetch_add(1, Ordering::Relaxed);
        let is_problem = resp
            .headers()
            .get(axum::http::header::CONTENT_TYPE)
            .is_some_and(|v| v.as_bytes().starts_with(b"application/problem+json"));
        if !is_problem && let Some(e) = error::status_to_problem(status) {
            return e.into_response();
        }
    }
    resp
}

/// The whole service: API, OpenAPI document and docs, health, metrics, dashboard.
pub fn app(state: AppState) -> Router {
    let (router, openapi) = api_router().split_for_parts();
    let docs = utoipa_swagger_ui::SwaggerUi::new("/docs").url("/openapi.json", openapi);
    router
        .merge(docs)
        .merge(health::dashboard_router())
        .fallback(health::fallback)
        .layer(axum::middleware::from_fn_with_state(state.clone(), require_token))
        .layer(axum::middleware::from_fn_with_state(state.clone(), problem_everywhere))
        .layer(DefaultBodyLimit::max(state.config.max_body_bytes))
        .with_state(state)
}

/// Serves `app(state)` on `listener` until `shutdown` resolves (graceful: in-flight requests
/// finish, SSE streams end).
pub async fn serve_on(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let flag = state.shutting_down.clone();
    let shutdown = async move {
        shutdown.await;
        // Event streams never end by themselves: end them so that the drain can finish.
        flag.send_replace(true);
    };
    axum::serve(listener, app(state)).with_graceful_shutdown(shutdown).await
}
