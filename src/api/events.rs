//! `/events`: Server-Sent Events for the dashboard and for planners that prefer push.
//! Events: `track` (a TrackView), `decision` (`{track_id, decision}`), `frame`
//! (`{camera, stamp_ns}`), `stats` (`{step_rate_hz, ingest_rate_hz, queue_depth}`).

use super::AppState;
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures::Stream;
use serde::{Deserialize, Serialize};
use std::convert::Infallible;
use std::sync::atomic::Ordering;
use std::time::Duration;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::BroadcastStream;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Rates published once a second.
#[derive(Debug, Clone, Default, Serialize, Deserialize, ToSchema)]
pub struct Stats {
    pub step_rate_hz: f64,
    pub ingest_rate_hz: f64,
    pub queue_depth: usize,
    pub frames_stale: u64,
    pub frames_dropped: u64,
}

/// One event of the stream.
#[derive(Debug, Clone)]
pub enum ServerEvent {
    Track(serde_json::Value),
    Decision { track_id: u64, decision: serde_json::Value },
    Frame { camera: String, stamp_ns: i64 },
    Stats(Stats),
}

impl ServerEvent {
    fn to_sse(&self) -> Event {
        let (name, data) = match self {
            Self::Track(v) => ("track", v.clone()),
            Self::Decision { track_id, decision } => (
                "decision",
                serde_json::json!({ "track_id": track_id, "decision": decision }),
            ),
            Self::Frame { camera, stamp_ns } => {
                ("frame", serde_json::json!({ "camera": camera, "stamp_ns": stamp_ns }))
            }
            Self::Stats(s) => ("stats", serde_json::to_value(s).unwrap_or_default()),
        };
        Event::default().event(name).data(data.to_string())
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(events))
}

#[utoipa::path(get, path = "/events", tag = "events",
    responses((status = 200, description = "text/event-stream of track, decision, frame and stats events", content_type = "text/event-stream")))]
async fn events(State(state): State<AppState>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    // A slow client misses events (lagged) rather than holding memory.
    let mut shutdown = state.shutting_down.subscribe();
    let events = BroadcastStream::new(state.events.subscribe()).filter_map(|e| e.ok().map(|e| Ok(e.to_sse())));
    let stream = futures::StreamExt::take_until(events, async move {
        let _ = shutdown.wait_for(|v| *v).await;
    });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

/// Publishes `stats` once a second until the state is dropped by every other owner.
pub fn spawn_stats_task(state: AppState) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut last = (
            state.metrics.steps.load(Ordering::Relaxed),
            state.metrics.frames_accepted.load(Ordering::Relaxed),
            std::time::Instant::now(),
        );
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        loop {
            tick.tick().await;
            let steps = state.metrics.steps.load(Ordering::Relaxed);
            let frames = state.metrics.frames_accepted.load(Ordering::Relaxed);
            let now = std::time::Instant::now();
            let dt = (now - last.2).as_secs_f64().max(1e-3);
            let stats = Stats {
                step_rate_hz: (steps - last.0) as f64 / dt,
                ingest_rate_hz: (frames - last.1) as f64 / dt,
                queue_depth: state.ingest().pending(),
                frames_stale: state.metrics.frames_stale.load(Ordering::Relaxed),
                frames_dropped: state.metrics.frames_dropped.load(Ordering::Relaxed),
            };
            *state.stats.lock().unwrap_or_else(|p| p.into_inner()) = stats.clone();
            state.publish(ServerEvent::Stats(stats));
            last = (steps, frames, now);
        }
    })
}
