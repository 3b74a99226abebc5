//! The service's runtime, below the HTTP layer and free of it: the registry of validated
//! cameras, objects and grippers, frame and odometry ingest, the worker thread that owns the
//! tracker, codebook builds, the decision cache, the support plane and ground truth, events,
//! and the redb store. Everything here takes and returns domain types
//! (`crate::sensor::{CameraFrame, Detection, CameraMount}`, poses, `crate::grasp` types), so
//! that ingest paths other than HTTP (ROS 2 over Zenoh, bags) can feed it as `api` does.
//! Failures are [`ServiceError`]s; `api` turns them into problem documents.

pub mod checks;
pub mod codebooks;
pub mod decide;
pub mod decisions;
pub mod demo;
pub mod error;
pub mod events;
pub mod ingest;
pub mod registry;
pub mod scene;
pub mod store;
pub mod tracks;
pub mod worker;

pub use error::ServiceError;
pub use registry::Registry;
pub use worker::{Background, start_background};

use crate::geometry::Pose;
use crate::grasp::SupportPlane;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex, RwLock};
use std::time::Instant;
use store::Store;
use tokio::sync::broadcast;

/// Settings of the service (the HTTP layer adds its own).
#[derive(Debug, Clone)]
pub struct ServiceConfig {
    /// Folder of the embedded store and caches.
    pub data_dir: PathBuf,
    /// Fusion window: each camera's latest frame no older than this behind the newest frame is
    /// fused; frames older than the newest minus this are refused as stale.
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
    /// Caps on what clients can make the server hold.
    pub limits: Limits,
    /// Accept ground truth (for display: the demo, replays of generated data).
    pub accept_truth: bool,
    /// The calibration map of `p_success` (the one shipped with the binary by default); it is
    /// applied only where it was fitted for the running settings. `None`: no map, raw rates.
    pub calibration_map: Option<Arc<crate::grasp::CalibrationMap>>,
}

impl ServiceConfig {
    pub fn new(data_dir: PathBuf) -> Self {
        Self {
            data_dir,
            window_ns: 300_000_000,
            max_pending_per_camera: 4,
            max_live_tracks_per_object: 1,
            tracker: crate::tracker::TrackerConfig::default(),
            codebooks: codebooks::CodebookPlan::default(),
            limits: Limits::default(),
            accept_truth: false,
            calibration_map: shipped_calibration_map(),
        }
    }
}

/// The calibration map compiled into the binary (`None`, logged, if it does not parse; a
/// test keeps it parsing).
pub fn shipped_calibration_map() -> Option<Arc<crate::grasp::CalibrationMap>> {
    match crate::grasp::CalibrationMap::from_json(crate::grasp::calibrated::SHIPPED_MAP_JSON) {
        Ok(m) => Some(Arc::new(m)),
        Err(e) => {
            tracing::warn!("the shipped grasp calibration map is unreadable: {e}");
            None
        }
    }
}

/// Caps on what clients can make the server hold (each a `serve` option; see `/healthz`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
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

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_cameras: 16,
            max_camera_pixels: 3840 * 2160,
            max_objects: 32,
            max_grippers: 16,
            max_tracks_per_object: 4,
            max_tracks: 32,
            max_name_chars: 128,
            max_cached_codebooks: 64,
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
    /// Codebook builds abandoned because their object's mesh changed meanwhile.
    pub codebook_builds_cancelled: AtomicU64,
    /// Ingest-to-estimate latencies of the most recent frames, microseconds.
    pub ingest_to_estimate_us: Mutex<LatencyRing>,
    /// The tracker's stage timings summed over all steps.
    pub stage_seconds: Mutex<crate::tracker::StageTimings>,
    /// Time the worker held the tracker after its steps (views and decision sample banks), us.
    pub after_step_us_sum: AtomicU64,
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

/// Everything the service holds.
pub struct ServiceState {
    pub config: ServiceConfig,
    pub store: Store,
    pub registry: RwLock<Registry>,
    pub ingest: Mutex<ingest::IngestBuffer>,
    /// Signalled when frames arrive (the tracking worker waits on it).
    pub wake: std::sync::Condvar,
    pub events: broadcast::Sender<events::ServiceEvent>,
    pub metrics: Metrics,
    pub tracking: tracks::Tracking,
    pub grasp_objects: decisions::GraspObjects,
    pub decision_cache: decisions::DecisionCache,
    /// The calibration map checked per running configuration.
    pub calibrations: decisions::Calibrations,
    pub codebooks: codebooks::Codebooks,
    /// Decisions running at once (one per core).
    pub decision_slots: Arc<tokio::sync::Semaphore>,
    /// The tracker (built when the first frame arrives; rebuilt when the cameras change).
    pub engine: Mutex<Option<worker::Engine>>,
    /// The tracker snapshot read from the store at start, until the tracker takes it.
    pub restored: Mutex<Option<crate::tracker::TrackerSnapshot>>,
    /// The support plane (world frame, unit normal) when one is known (demo, replay of a rig
    /// with one).
    pub support_plane: Mutex<Option<SupportPlane>>,
    /// Ground truth for display only (`world_from_object` and its stamp per object id).
    pub truth: Mutex<BTreeMap<String, (i64, Pose)>>,
    /// The latest rates (updated once a second).
    pub stats: Mutex<events::Stats>,
    pub started: Instant,
    /// Set when the server begins its graceful shutdown (ends the event streams).
    pub shutting_down: tokio::sync::watch::Sender<bool>,
}

/// The service (cheap to clone).
#[derive(Clone)]
pub struct Service(pub Arc<ServiceState>);

impl std::ops::Deref for Service {
    type Target = ServiceState;
    fn deref(&self) -> &ServiceState {
        &self.0
    }
}

impl Service {
    /// Opens the store in `config.data_dir` and loads the registry and tracks from it.
    pub fn open(config: ServiceConfig) -> anyhow::Result<Self> {
        let store = Store::open(&config.data_dir)?;
        let registry = Registry::load(&store)?;
        let tracking = tracks::Tracking::default();
        tracks::load(&store, &tracking)?;
        let (events, _) = broadcast::channel(256);
        let ingest = ingest::IngestBuffer::new(config.window_ns, config.max_pending_per_camera);
        let support_plane = scene::load_support_plane(&store);
        let restored = tracks::load_tracker_snapshot(&store);
        let calibrations = decisions::Calibrations::new(config.calibration_map.clone());
        Ok(Self(Arc::new(ServiceState {
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
            calibrations,
            codebooks: codebooks::Codebooks::default(),
            decision_slots: Arc::new(tokio::sync::Semaphore::new(
                std::thread::available_parallelism().map_or(2, |n| n.get()),
            )),
            engine: Mutex::new(None),
            restored: Mutex::new(restored),
            support_plane: Mutex::new(support_plane),
            truth: Mutex::new(BTreeMap::new()),
            stats: Mutex::new(events::Stats::default()),
            started: Instant::now(),
            shutting_down: tokio::sync::watch::channel(false).0,
        })))
    }
}

impl ServiceState {
    pub fn registry(&self) -> std::sync::RwLockReadGuard<'_, Registry> {
        self.registry.read().unwrap_or_else(|p| p.into_inner())
    }
    pub fn registry_mut(&self) -> std::sync::RwLockWriteGuard<'_, Registry> {
        self.registry.write().unwrap_or_else(|p| p.into_inner())
    }
    pub fn ingest(&self) -> std::sync::MutexGuard<'_, ingest::IngestBuffer> {
        self.ingest.lock().unwrap_or_else(|p| p.into_inner())
    }
    pub fn publish(&self, e: events::ServiceEvent) {
        // No subscriber is not an error.
        let _ = self.events.send(e);
    }
    /// The support plane (world frame), when one is known.
    pub fn support_plane(&self) -> Option<SupportPlane> {
        *self.support_plane.lock().unwrap_or_else(|p| p.into_inner())
    }
}
