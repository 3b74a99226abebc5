//! Background work of a server: the tracking worker (a dedicated thread that owns the tracker
//! and steps whenever frames arrive) and the once-a-second stats publisher.

use super::AppState;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Handle on the background work; `shutdown` stops it.
pub struct Background {
    stop: Arc<AtomicBool>,
    stats: tokio::task::JoinHandle<()>,
    worker: Option<std::thread::JoinHandle<()>>,
    state: AppState,
}

impl Background {
    /// Stops the worker and the stats task and waits for both (so that the store can be
    /// reopened afterwards).
    pub async fn shutdown(mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.state.wake.notify_all();
        self.stats.abort();
        let _ = (&mut self.stats).await;
        if let Some(w) = self.worker.take() {
            let _ = tokio::task::spawn_blocking(move || w.join()).await;
        }
    }
}

/// Starts the stats task (needs a tokio runtime) and the tracking worker thread.
pub fn start_background(state: &AppState) -> Background {
    let stop = Arc::new(AtomicBool::new(false));
    let stats = super::events::spawn_stats_task(state.clone());
    let worker = {
        let (state, stop) = (state.clone(), stop.clone());
        std::thread::Builder::new()
            .name("pregrasp-tracking".into())
            .spawn(move || run_worker(state, stop))
            .ok()
    };
    Background {
        stop,
        stats,
        worker,
        state: state.clone(),
    }
}

fn run_worker(state: AppState, stop: Arc<AtomicBool>) {
    while !stop.load(Ordering::Relaxed) {
        let set = {
            let mut ingest = state.ingest();
            loop {
                if stop.load(Ordering::Relaxed) {
                    return;
                }
                if let Some(set) = ingest.take_fusion_set() {
                    break set;
                }
                ingest = state
                    .wake
                    .wait_timeout(ingest, Duration::from_millis(200))
                    .map(|(g, _)| g)
                    .unwrap_or_else(|p| p.into_inner().0);
            }
        };
        state
            .metrics
            .frames_dropped
            .fetch_add(set.superseded as u64, Ordering::Relaxed);
        if set.frames.is_empty() {
            continue;
        }
        let _ = set;
    }
}

/// Draws `n` poses from a track's distribution (reference frame) for a decision.
pub fn draw_samples(
    state: &AppState,
    track_id: u64,
    n: usize,
) -> Result<super::decisions::Drawn, super::error::ApiError> {
    let _ = (n, state.tracking.board().views.get(&track_id));
    Err(super::error::ApiError::NotReady(
        "the tracker is not wired in yet".into(),
    ))
}
