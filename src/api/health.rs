//! `/healthz`, `/metrics` (Prometheus text) and the embedded dashboard at `/`.

use super::AppState;
use super::error::ApiError;
use axum::Json;
use axum::extract::{Path, State};
use axum::http::header;
use axum::response::IntoResponse;
use include_dir::{Dir, include_dir};
use serde::{Deserialize, Serialize};
use std::fmt::Write;
use std::sync::atomic::Ordering;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

static DASHBOARD: Dir<'_> = include_dir!("$CARGO_MANIFEST_DIR/static");

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Health {
    pub status: String,
    pub uptime_s: f64,
    pub cameras: usize,
    pub objects: usize,
    pub tracks: usize,
    pub queue_depth: usize,
    /// The caps this server was started with (`serve --max-*`).
    pub limits: Limits,
}

/// Caps on what clients can make the server hold (each a `serve` option).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct Limits {
    /// Registered cameras.
    pub max_cameras: usize,
    /// Pixels of one camera image (width x height); frames wait in memory.
    pub max_camera_pixels: u64,
    /// Registered objects (each holds a mesh and its codebooks).
    pub max_objects: usize,
    /// Registered grippers.
    pub max_grippers: usize,
    /// Tracks of one object (started by clients or by detections).
    pub max_tracks_per_object: usize,
    /// Tracks in all.
    pub max_tracks: usize,
    /// Longest display name, characters (ids: 64).
    pub max_name_chars: usize,
    /// Codebook files kept in the cache folder (the least recently written go first).
    pub max_cached_codebooks: usize,
}

impl From<crate::service::Limits> for Limits {
    fn from(l: crate::service::Limits) -> Self {
        Self {
            max_cameras: l.max_cameras,
            max_camera_pixels: l.max_camera_pixels,
            max_objects: l.max_objects,
            max_grippers: l.max_grippers,
            max_tracks_per_object: l.max_tracks_per_object,
            max_tracks: l.max_tracks,
            max_name_chars: l.max_name_chars,
            max_cached_codebooks: l.max_cached_codebooks,
        }
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(healthz)).routes(routes!(metrics))
}

#[utoipa::path(get, path = "/healthz", tag = "health", responses((status = 200, body = Health)))]
async fn healthz(State(state): State<AppState>) -> Json<Health> {
    let (cameras, objects) = {
        let reg = state.registry();
        (reg.cameras.len(), reg.objects.len())
    };
    Json(Health {
        status: "ok".into(),
        uptime_s: state.started.elapsed().as_secs_f64(),
        cameras,
        objects,
        tracks: state.tracking.track_count(),
        queue_depth: state.ingest().pending(),
        limits: state.config.service.limits.into(),
    })
}

#[utoipa::path(get, path = "/metrics", tag = "health",
    responses((status = 200, description = "Prometheus text exposition", content_type = "text/plain")))]
async fn metrics(State(state): State<AppState>) -> impl IntoResponse {
    let m = &state.metrics;
    let mut s = String::new();
    let counters: [(&str, &str, &std::sync::atomic::AtomicU64); 11] = [
        ("pregrasp_frames_accepted_total", "Frames accepted", &m.frames_accepted),
        (
            "pregrasp_frames_stale_total",
            "Frames refused as older than the window or duplicate",
            &m.frames_stale,
        ),
        (
            "pregrasp_frames_dropped_total",
            "Accepted frames dropped unprocessed (queue full or superseded)",
            &m.frames_dropped,
        ),
        (
            "pregrasp_odometry_accepted_total",
            "Odometry messages accepted",
            &m.odometry_accepted,
        ),
        ("pregrasp_steps_total", "Tracker steps", &m.steps),
        (
            "pregrasp_step_errors_total",
            "Tracker steps that failed",
            &m.step_errors,
        ),
        ("pregrasp_decisions_total", "Decisions answered", &m.decisions),
        (
            "pregrasp_decisions_from_bank_total",
            "Decisions that read the samples drawn after the latest step",
            &m.decisions_from_bank,
        ),
        (
            "pregrasp_decisions_shared_total",
            "Decisions answered by an identical query of the same step",
            &m.decisions_shared,
        ),
        (
            "pregrasp_requests_rejected_total",
            "Requests answered with a 4xx",
            &m.requests_rejected,
        ),
        (
            "pregrasp_codebook_builds_cancelled_total",
            "Codebook builds abandoned because their object's mesh changed",
            &m.codebook_builds_cancelled,
        ),
    ];
    for (name, help, v) in counters {
        let v = v.load(Ordering::Relaxed);
        let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
    }
    let seconds_total = m.step_latency_us_sum.load(Ordering::Relaxed) as f64 * 1e-6;
    let _ = writeln!(
        s,
        "# HELP pregrasp_step_seconds_total Time spent in tracker steps\n# TYPE pregrasp_step_seconds_total counter\npregrasp_step_seconds_total {seconds_total}"
    );
    let stages = m.stage_seconds.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let _ = writeln!(
        s,
        "# HELP pregrasp_step_stage_seconds_total Time spent per stage of the tracker's steps\n# TYPE pregrasp_step_stage_seconds_total counter"
    );
    for (stage, seconds) in stages.stages() {
        let _ = writeln!(s, "pregrasp_step_stage_seconds_total{{stage=\"{stage}\"}} {seconds}");
    }
    let after_s = m.after_step_us_sum.load(Ordering::Relaxed) as f64 * 1e-6;
    let _ = writeln!(
        s,
        "# HELP pregrasp_after_step_seconds_total Time the worker held the tracker after its steps (views, decision samples)\n# TYPE pregrasp_after_step_seconds_total counter\npregrasp_after_step_seconds_total {after_s}"
    );
    let stats = state.stats.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let gauges: [(&str, &str, f64); 6] = [
        (
            "pregrasp_queue_depth",
            "Frames waiting for the tracker",
            state.ingest().pending() as f64,
        ),
        ("pregrasp_tracks", "Tracks", state.tracking.track_count() as f64),
        (
            "pregrasp_tracker_snapshot_bytes",
            "Size of the last tracker snapshot written to the store",
            m.tracker_snapshot_bytes.load(Ordering::Relaxed) as f64,
        ),
        (
            "pregrasp_step_rate_hz",
            "Achieved tracker steps per second (last second)",
            stats.step_rate_hz,
        ),
        (
            "pregrasp_ingest_rate_hz",
            "Frames accepted per second (last second)",
            stats.ingest_rate_hz,
        ),
        (
            "pregrasp_last_step_latency_seconds",
            "Latency of the last step",
            m.last_step_latency_us.load(Ordering::Relaxed) as f64 * 1e-6,
        ),
    ];
    for (name, help, v) in gauges {
        let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
    }
    {
        let name = "pregrasp_clock_resets_total";
        let v = state.ingest().clock_resets();
        let _ = writeln!(
            s,
            "# HELP {name} Restarted clocks (a camera's or the odometry's stamps jumped back)\n# TYPE {name} counter\n{name} {v}"
        );
        let l = state.config.service.limits;
        let name = "pregrasp_limit";
        let _ = writeln!(
            s,
            "# HELP {name} Caps of this server (serve --max-*)\n# TYPE {name} gauge"
        );
        for (what, v) in [
            ("cameras", l.max_cameras as f64),
            ("camera_pixels", l.max_camera_pixels as f64),
            ("objects", l.max_objects as f64),
            ("grippers", l.max_grippers as f64),
            ("tracks_per_object", l.max_tracks_per_object as f64),
            ("tracks", l.max_tracks as f64),
            ("name_chars", l.max_name_chars as f64),
            ("cached_codebooks", l.max_cached_codebooks as f64),
        ] {
            let _ = writeln!(s, "{name}{{what=\"{what}\"}} {v}");
        }
    }
    {
        let ring = m.ingest_to_estimate_us.lock().unwrap_or_else(|p| p.into_inner());
        let name = "pregrasp_ingest_to_estimate_seconds";
        let _ = writeln!(
            s,
            "# HELP {name} Time from receiving a frame to publishing the estimate that fused it (last {} frames)\n# TYPE {name} summary",
            crate::service::LatencyRing::CAPACITY
        );
        for q in [0.5, 0.9, 0.99] {
            if let Some(us) = ring.quantile_us(q) {
                let _ = writeln!(s, "{name}{{quantile=\"{q}\"}} {}", us as f64 * 1e-6);
            }
        }
        let _ = writeln!(s, "{name}_count {}", ring.len());
    }
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], s)
}

fn static_file(path: &str) -> Result<impl IntoResponse + use<>, ApiError> {
    let path = if path.is_empty() { "index.html" } else { path };
    let contents: Vec<u8> = match DASHBOARD.get_file(path) {
        Some(f) => f.contents().to_vec(),
        None if path == "index.html" => FALLBACK_INDEX.as_bytes().to_vec(),
        None => return Err(ApiError::not_found("file", path)),
    };
    let mime = match path.rsplit('.').next() {
        Some("html") => "text/html; charset=utf-8",
        Some("js") | Some("mjs") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("json") => "application/json",
        Some("svg") => "image/svg+xml",
        Some("png") => "image/png",
        _ => "application/octet-stream",
    };
    Ok(([(header::CONTENT_TYPE, mime)], contents))
}

const FALLBACK_INDEX: &str = "<!doctype html><title>pregrasp</title><h1>pregrasp</h1>\
<p>The dashboard is not in this build. See <a href=\"/docs\">/docs</a> for the API.</p>";

async fn index() -> Result<impl IntoResponse, ApiError> {
    static_file("index.html")
}

/// Unknown routes: a dashboard file for GET requests, else a 404 problem document.
pub async fn fallback(method: axum::http::Method, uri: axum::http::Uri) -> Result<impl IntoResponse, ApiError> {
    let path = uri.path().trim_start_matches('/');
    if method == axum::http::Method::GET && !path.starts_with("api/") && DASHBOARD.get_file(path).is_some() {
        return static_file(path);
    }
    Err(ApiError::not_found("route", uri.path()))
}

async fn asset(Path(path): Path<String>) -> Result<impl IntoResponse, ApiError> {
    static_file(&path)
}

/// The dashboard: `/` and the files of `static/`.
pub fn dashboard_router() -> axum::Router<AppState> {
    axum::Router::new()
        .route("/", axum::routing::get(index))
        .route("/static/{*path}", axum::routing::get(asset))
}
