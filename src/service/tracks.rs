//! The tracks as the service publishes them: each track's latest state (estimate, particles
//! for display, samples, last decision, errors against ground truth), its history, starting a
//! track from a caller's prior, stopping one, and their records in the store.

use super::ServiceState;
use super::decisions::DecisionRecord;
use super::error::ServiceError;
use super::store::{Store, Table, lenient, pose_xyzw};
use crate::geometry::Pose;
use crate::tracker::{Component, RotationMode, TrackStatus};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, RwLock};

/// History points kept per track.
pub const MAX_HISTORY: usize = 600;

/// Range of a prior's position standard deviation, metres.
pub const MIN_PRIOR_STD_M: f64 = 1e-4;
pub const MAX_PRIOR_STD_M: f64 = 2.0;
/// Default standard deviation of a prior's position, metres.
pub const DEFAULT_PRIOR_STD_M: f64 = 0.05;
/// Smallest standard deviation of a prior's rotation, degrees.
pub const MIN_PRIOR_STD_DEG: f64 = 0.01;

/// A particle for display (world frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParticleInWorld {
    pub position_world_m: [f64; 3],
    pub camera: String,
    pub weight: f64,
}

/// Errors of a track against ground truth (only when a ground-truth channel feeds the server).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthError {
    pub translation_error_m: f64,
    /// Geodesic angle to the nearest pose that looks like the truth: modulo the object's exact
    /// symmetries (shape and colour together).
    pub orientation_error_deg: f64,
}

/// The state of one track as published after a step (and stored, without particles and
/// samples, every few seconds).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrackState {
    pub id: u64,
    pub object_id: String,
    pub object_name: String,
    pub status: TrackStatus,
    pub stamp_ns: i64,
    /// The object in the reference (robot camera) frame.
    #[serde(with = "pose_xyzw")]
    pub reference_from_object: Pose,
    #[serde(with = "pose_xyzw")]
    pub world_from_object: Pose,
    pub translation_std_m: f64,
    pub rotation_entropy: f64,
    pub top_mode_mass: f64,
    /// Row-major 6x6 covariance (x, y, z, rx, ry, rz) like ROS `PoseWithCovariance`.
    pub covariance_6x6: Vec<f64>,
    /// The translation mixture, one component per camera, reference frame.
    pub components: Vec<Component>,
    pub rotation_modes: Vec<RotationMode>,
    #[serde(skip)]
    pub particles: Vec<ParticleInWorld>,
    /// A few poses drawn from the distribution, world frame.
    #[serde(skip)]
    pub samples_world: Vec<Pose>,
    /// The latest decision asked about this track.
    #[serde(default, deserialize_with = "lenient")]
    pub decision: Option<Arc<DecisionRecord>>,
    pub truth: Option<TruthError>,
    /// Milliseconds from receiving the newest fused frame to this estimate.
    pub ingest_to_estimate_ms: Option<f64>,
    /// When and why the tracker last started this track again.
    #[serde(default)]
    pub reinitialised: Option<crate::tracker::Reinitialisation>,
}

/// One point of a track's history.
#[derive(Debug, Clone, PartialEq)]
pub struct HistoryPoint {
    pub stamp_ns: i64,
    pub world_from_object: Pose,
    pub translation_std_m: f64,
    pub rotation_entropy: f64,
    pub status: TrackStatus,
    pub truth: Option<TruthError>,
}

/// The published state of the tracking worker (what the read calls serve).
#[derive(Default)]
pub struct TrackBoard {
    pub views: BTreeMap<u64, TrackState>,
    pub history: BTreeMap<u64, VecDeque<HistoryPoint>>,
    /// Tracks stopped by a client (the worker drops them).
    pub stopped: Vec<u64>,
    /// Latest `world_from_reference` (robot camera) estimate.
    pub world_from_reference: Option<Pose>,
}

/// Shared between callers and the worker.
#[derive(Default)]
pub struct Tracking {
    pub board: RwLock<TrackBoard>,
}

impl Tracking {
    pub fn board(&self) -> std::sync::RwLockReadGuard<'_, TrackBoard> {
        self.board.read().unwrap_or_else(|p| p.into_inner())
    }
    pub fn board_mut(&self) -> std::sync::RwLockWriteGuard<'_, TrackBoard> {
        self.board.write().unwrap_or_else(|p| p.into_inner())
    }
    pub fn track_count(&self) -> usize {
        self.board().views.len()
    }
    /// Attaches the latest decision to a track's state.
    pub fn set_decision(&self, track_id: u64, decision: Arc<DecisionRecord>) {
        if let Some(v) = self.board_mut().views.get_mut(&track_id) {
            v.decision = Some(decision);
        }
    }
    /// Publishes a new state of a track (and appends to its history).
    pub fn publish(&self, view: TrackState) {
        let mut b = self.board_mut();
        let h = b.history.entry(view.id).or_default();
        h.push_back(HistoryPoint {
            stamp_ns: view.stamp_ns,
            world_from_object: view.world_from_object,
            translation_std_m: view.translation_std_m,
            rotation_entropy: view.rotation_entropy,
            status: view.status,
            truth: view.truth.clone(),
        });
        while h.len() > MAX_HISTORY {
            h.pop_front();
        }
        b.views.insert(view.id, view);
    }
}

/// Loads the saved track records (their last published state; shown until the tracker
/// publishes a newer one).
pub(super) fn load(store: &Store, tracking: &Tracking) -> anyhow::Result<()> {
    let mut b = tracking.board_mut();
    for (_, view) in store.list::<TrackState>(Table::Tracks)? {
        b.views.insert(view.id, view);
    }
    Ok(())
}

/// The tracker snapshot saved by the last run, if any (an unreadable one is logged and
/// ignored: the tracks then restart from their next detections).
pub(super) fn load_tracker_snapshot(store: &Store) -> Option<crate::tracker::TrackerSnapshot> {
    let bytes = match store.get_bytes(Table::TrackerState, super::store::TRACKER_KEY) {
        Ok(b) => b?,
        Err(e) => {
            tracing::warn!("reading the tracker snapshot: {e}");
            return None;
        }
    };
    match serde_json::from_slice::<crate::tracker::TrackerSnapshot>(&bytes) {
        Ok(s) if s.version == crate::tracker::filter::SNAPSHOT_VERSION => Some(s),
        Ok(s) => {
            tracing::warn!("tracker snapshot of version {} ignored", s.version);
            None
        }
        Err(e) => {
            tracing::warn!("tracker snapshot unreadable, ignored: {e}");
            None
        }
    }
}

/// A caller's prior for a new track: the mean pose in the world or the reference frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PriorPose {
    World { world_from_object: Pose },
    Reference { reference_from_object: Pose },
}

/// What a caller believes about an object before the cameras see it (a map, an earlier visit).
#[derive(Debug, Clone, PartialEq)]
pub struct StartTrack {
    pub object_id: String,
    pub pose: PriorPose,
    /// Standard deviation of the position per axis, metres.
    pub translation_std_m: f64,
    /// Standard deviation of the rotation angle, degrees; `None`: any rotation.
    pub rotation_std_deg: Option<f64>,
}

impl ServiceState {
    /// Forgets every track (the tracker starts over): the published states, their history,
    /// their stored records (so that a restart does not bring them back) and their decision
    /// banks.
    pub fn forget_all_tracks(&self) {
        let ids: Vec<u64> = {
            let mut b = self.tracking.board_mut();
            let ids = b.views.keys().copied().collect();
            b.views.clear();
            b.history.clear();
            b.world_from_reference = None;
            ids
        };
        for id in ids {
            if let Err(e) = self.store.delete(Table::Tracks, &id.to_string()) {
                tracing::warn!("forgetting track {id}: {e}");
            }
        }
        self.decision_cache.forget(None);
    }

    /// Saves every track's current state in one transaction (called periodically by the
    /// worker).
    pub fn save_track_records(&self) -> Result<(), ServiceError> {
        let records: Vec<(String, Vec<u8>)> = self
            .tracking
            .board()
            .views
            .values()
            .map(|v| (v.id.to_string(), serde_json::to_vec(v).unwrap_or_default()))
            .collect();
        self.store.put_many(Table::Tracks, &records)?;
        Ok(())
    }

    /// A track's latest state.
    pub fn track(&self, id: u64) -> Result<TrackState, ServiceError> {
        self.tracking
            .board()
            .views
            .get(&id)
            .cloned()
            .ok_or_else(|| ServiceError::not_found("track", id.to_string()))
    }

    /// Every track's latest state.
    pub fn tracks(&self) -> Vec<TrackState> {
        self.tracking.board().views.values().cloned().collect()
    }

    /// A track's history, oldest first.
    pub fn track_history(&self, id: u64) -> Result<Vec<HistoryPoint>, ServiceError> {
        self.tracking
            .board()
            .history
            .get(&id)
            .map(|h| h.iter().cloned().collect())
            .ok_or_else(|| ServiceError::not_found("track", id.to_string()))
    }

    /// Stops a track: it leaves the published states at once and the tracker at its next
    /// step.
    pub fn stop_track(&self, id: u64) -> Result<(), ServiceError> {
        let mut b = self.tracking.board_mut();
        if b.views.remove(&id).is_none() {
            return Err(ServiceError::not_found("track", id.to_string()));
        }
        b.history.remove(&id);
        b.stopped.push(id);
        drop(b);
        self.decision_cache.forget(Some(id));
        self.store.delete(Table::Tracks, &id.to_string())?;
        Ok(())
    }
}
