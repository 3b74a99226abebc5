//! What the service announces as it happens (new track states, decisions, frames, rates), on
//! a broadcast channel; `api::events` serves it as Server-Sent Events.

use super::Service;
use super::decisions::DecisionRecord;
use super::tracks::TrackState;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

/// Rates published once a second.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub step_rate_hz: f64,
    pub ingest_rate_hz: f64,
    pub queue_depth: usize,
    pub frames_stale: u64,
    pub frames_dropped: u64,
}

/// One event.
#[derive(Debug, Clone)]
pub enum ServiceEvent {
    /// A track's new state (after a step, or when a client started it).
    Track(Arc<TrackState>),
    /// A decision answered for a track.
    Decision {
        track_id: u64,
        decision: Arc<DecisionRecord>,
    },
    /// A frame was accepted.
    Frame {
        camera: String,
        stamp_ns: i64,
    },
    Stats(Stats),
}

/// Publishes `stats` once a second (needs a tokio runtime).
pub fn spawn_stats_task(service: Service) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut last = (
            service.metrics.steps.load(Ordering::Relaxed),
            service.metrics.frames_accepted.load(Ordering::Relaxed),
            std::time::Instant::now(),
        );
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        loop {
            tick.tick().await;
            let steps = service.metrics.steps.load(Ordering::Relaxed);
            let frames = service.metrics.frames_accepted.load(Ordering::Relaxed);
            let now = std::time::Instant::now();
            let dt = (now - last.2).as_secs_f64().max(1e-3);
            let stats = Stats {
                step_rate_hz: (steps - last.0) as f64 / dt,
                ingest_rate_hz: (frames - last.1) as f64 / dt,
                queue_depth: service.ingest().pending(),
                frames_stale: service.metrics.frames_stale.load(Ordering::Relaxed),
                frames_dropped: service.metrics.frames_dropped.load(Ordering::Relaxed),
            };
            *service.stats.lock().unwrap_or_else(|p| p.into_inner()) = stats.clone();
            service.publish(ServiceEvent::Stats(stats));
            last = (steps, frames, now);
        }
    })
}
