//! `/tracks`: the tracked objects (current estimate, samples, history, stop) and
//! `/scene` (cameras, robot trajectory, support plane).

use super::AppState;
use super::error::ApiError;
use super::types::PoseDto;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, VecDeque};
use std::sync::RwLock;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// History points kept per track.
pub const MAX_HISTORY: usize = 600;

/// Range of a prior's position standard deviation, metres.
pub const MIN_PRIOR_STD_M: f64 = 1e-4;
pub const MAX_PRIOR_STD_M: f64 = 2.0;
/// Smallest standard deviation of a prior's rotation, degrees.
pub const MIN_PRIOR_STD_DEG: f64 = 0.01;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TrackStatusDto {
    Initialising,
    Tracking,
    Lost,
}

/// One Gaussian of the translation mixture (per camera), in the reference frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ComponentDto {
    pub camera: String,
    pub weight: f64,
    pub mean_m: [f64; 3],
    pub covariance_m2: [[f64; 3]; 3],
}

/// A mode of the rotation marginal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct RotationModeDto {
    pub rotation_xyzw: [f64; 4],
    pub mass: f64,
}

/// A particle for display (world frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ParticleDto {
    pub position_world_m: [f64; 3],
    pub camera: String,
    pub weight: f64,
}

/// Errors against ground truth (only when a ground-truth channel feeds the server).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct TruthDto {
    pub translation_error_m: f64,
    /// Geodesic angle to the nearest pose that looks like the truth: modulo the object's exact
    /// symmetries (shape and colour together).
    pub orientation_error_deg: f64,
}

/// The state of one track as the dashboard and planners see it.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct TrackView {
    pub id: u64,
    pub object_id: String,
    pub object_name: String,
    pub status: TrackStatusDto,
    pub stamp_ns: i64,
    /// The object in the reference (robot camera) frame.
    pub reference_from_object: PoseDto,
    pub world_from_object: PoseDto,
    pub translation_std_m: f64,
    pub rotation_entropy: f64,
    pub top_mode_mass: f64,
    /// Row-major 6x6 covariance (x, y, z, rx, ry, rz) like ROS `PoseWithCovariance`.
    pub covariance_6x6: Vec<f64>,
    pub components: Vec<ComponentDto>,
    pub rotation_modes: Vec<RotationModeDto>,
    pub particles: Vec<ParticleDto>,
    /// Up to 10 poses drawn from the distribution, world frame.
    pub samples_world: Vec<PoseDto>,
    #[schema(value_type = Option<Object>)]
    pub decision: Option<serde_json::Value>,
    pub truth: Option<TruthDto>,
    /// Milliseconds from receiving the newest fused frame to this estimate.
    pub ingest_to_estimate_ms: Option<f64>,
}

/// One point of a track's history.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct HistoryPoint {
    pub stamp_ns: i64,
    pub world_from_object: PoseDto,
    pub translation_std_m: f64,
    pub rotation_entropy: f64,
    pub status: TrackStatusDto,
    pub truth: Option<TruthDto>,
}

/// The published state of the tracking worker (what the read endpoints serve).
#[derive(Default)]
pub struct TrackBoard {
    pub views: BTreeMap<u64, TrackView>,
    pub history: BTreeMap<u64, VecDeque<HistoryPoint>>,
    /// Tracks stopped by a client (the worker drops them).
    pub stopped: Vec<u64>,
    /// Latest `world_from_reference` (robot camera) estimate.
    pub world_from_reference: Option<PoseDto>,
}

/// Shared between handlers and the worker.
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
    /// Attaches the latest decision to a track's view.
    pub fn set_decision(&self, track_id: u64, decision: serde_json::Value) {
        if let Some(v) = self.board_mut().views.get_mut(&track_id) {
            v.decision = Some(decision);
        }
    }
    /// Publishes a new view of a track (and appends to its history).
    pub fn publish(&self, view: TrackView) {
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

/// Loads the saved track snapshots (their last published state; shown until the tracker
/// publishes a newer one).
pub(super) fn load(store: &super::store::Store, tracking: &Tracking) -> anyhow::Result<()> {
    let mut b = tracking.board_mut();
    for (_, view) in store.list::<TrackView>(super::store::Table::Tracks)? {
        b.views.insert(view.id, view);
    }
    Ok(())
}

/// The tracker snapshot saved by the last run, if any (an unreadable one is logged and
/// ignored: the tracks then restart from their next detections).
pub(super) fn load_tracker_snapshot(store: &super::store::Store) -> Option<crate::tracker::TrackerSnapshot> {
    let bytes = match store.get_bytes(super::store::Table::TrackerState, super::store::TRACKER_KEY) {
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

/// Forgets every track (the tracker starts over): the published views, their history, their
/// stored records (so that a restart does not bring them back) and their decision banks.
pub fn forget_all(state: &AppState) {
    let ids: Vec<u64> = {
        let mut b = state.tracking.board_mut();
        let ids = b.views.keys().copied().collect();
        b.views.clear();
        b.history.clear();
        b.world_from_reference = None;
        ids
    };
    for id in ids {
        if let Err(e) = state.store.delete(super::store::Table::Tracks, &id.to_string()) {
            tracing::warn!("forgetting track {id}: {e}");
        }
    }
    state.decision_cache.forget(None);
}

/// Saves every track's current view in one transaction (called periodically by the worker).
pub fn save_snapshots(state: &AppState) -> Result<(), ApiError> {
    let records: Vec<(String, Vec<u8>)> = state
        .tracking
        .board()
        .views
        .values()
        .map(|v| {
            // Compact: no particles or samples.
            let mut v = v.clone();
            v.particles.clear();
            v.samples_world.clear();
            (v.id.to_string(), serde_json::to_vec(&v).unwrap_or_default())
        })
        .collect();
    state.store.put_many(super::store::Table::Tracks, &records)?;
    Ok(())
}

/// Start tracking an object from what the caller already believes (a map, an earlier visit):
/// give the mean pose in the world frame or in the reference (robot camera) frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StartTrackRequest {
    pub object_id: String,
    pub world_from_object: Option<PoseDto>,
    pub reference_from_object: Option<PoseDto>,
    /// Standard deviation of the position per axis (default 0.05, 0.0001 to 2).
    pub translation_std_m: Option<f64>,
    /// Standard deviation of the rotation angle (degrees, 0.01 to 180); absent: any rotation.
    pub rotation_std_deg: Option<f64>,
}

#[utoipa::path(post, path = "/tracks", tag = "tracks", request_body = StartTrackRequest,
    responses((status = 201, body = TrackView), (status = 404, body = super::error::Problem),
        (status = 400, body = super::error::Problem),
        (status = 409, description = "No cameras registered, or a track cap is reached", body = super::error::Problem),
        (status = 415, body = super::error::Problem),
        (status = 422, body = super::error::Problem),
        (status = 503, description = "The object's codebook is still building", body = super::error::Problem)))]
async fn start_track(
    State(state): State<AppState>,
    super::types::ApiJson(req): super::types::ApiJson<StartTrackRequest>,
) -> Result<super::error::Created<TrackView>, ApiError> {
    if !state.registry().objects.contains_key(&req.object_id) {
        return Err(ApiError::not_found("object", req.object_id));
    }
    let world = req
        .world_from_object
        .map(|p| p.to_pose("world_from_object"))
        .transpose()?;
    let reference = req
        .reference_from_object
        .map(|p| p.to_pose("reference_from_object"))
        .transpose()?;
    if world.is_some() == reference.is_some() {
        return Err(ApiError::Invalid(
            "give exactly one of world_from_object and reference_from_object".into(),
        ));
    }
    let std_m = req.translation_std_m.unwrap_or(0.05);
    if !(MIN_PRIOR_STD_M..=MAX_PRIOR_STD_M).contains(&std_m) {
        return Err(ApiError::Invalid(format!(
            "translation_std_m must be in [{MIN_PRIOR_STD_M}, {MAX_PRIOR_STD_M}], got {std_m}"
        )));
    }
    let rot = match req.rotation_std_deg {
        Some(d) if (MIN_PRIOR_STD_DEG..=180.0).contains(&d) => Some(d.to_radians()),
        Some(d) => {
            return Err(ApiError::Invalid(format!(
                "rotation_std_deg must be in [{MIN_PRIOR_STD_DEG}, 180], got {d}"
            )));
        }
        None => None,
    };
    let object = req.object_id.clone();
    let view =
        tokio::task::spawn_blocking(move || super::worker::start_track(&state, &object, world, reference, std_m, rot))
            .await
            .map_err(ApiError::internal)??;
    Ok(super::error::Created(view))
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_tracks, start_track))
        .routes(routes!(get_track, stop_track))
        .routes(routes!(track_history))
        .routes(routes!(track_samples))
}

/// Query of `/tracks/{id}/samples`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
pub struct SamplesQuery {
    /// How many poses (1..=5,000; default 100).
    pub n: Option<usize>,
}

/// Poses drawn from a track's distribution.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct SamplesView {
    pub track_id: u64,
    pub effective_sample_size: f64,
    /// In the reference (robot camera) frame.
    pub reference_from_object: Vec<PoseDto>,
    pub world_from_object: Vec<PoseDto>,
}

#[utoipa::path(get, path = "/tracks/{id}/samples", tag = "tracks",
    params(("id" = u64, Path, description = "Track id"), SamplesQuery),
    responses((status = 200, body = SamplesView), (status = 400, body = super::error::Problem),
        (status = 404, body = super::error::Problem),
        (status = 422, body = super::error::Problem), (status = 503, body = super::error::Problem)))]
async fn track_samples(
    State(state): State<AppState>,
    Path(id): Path<String>,
    q: Result<axum::extract::Query<SamplesQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<SamplesView>, ApiError> {
    let axum::extract::Query(q) = q?;
    let id = parse_id(&id)?;
    let n = q.n.unwrap_or(100);
    if n == 0 || n > super::decisions::MAX_DECISION_SAMPLES {
        return Err(ApiError::Invalid(format!(
            "n must be in 1..={}, got {n}",
            super::decisions::MAX_DECISION_SAMPLES
        )));
    }
    let drawn = tokio::task::spawn_blocking(move || super::worker::draw_samples(&state, id, n))
        .await
        .map_err(ApiError::internal)??;
    Ok(Json(SamplesView {
        track_id: id,
        effective_sample_size: drawn.samples.effective_sample_size,
        reference_from_object: drawn.samples.poses.iter().map(PoseDto::from_pose).collect(),
        world_from_object: drawn
            .samples
            .poses
            .iter()
            .map(|p| PoseDto::from_pose(&(drawn.world_from_reference * p)))
            .collect(),
    }))
}

#[utoipa::path(get, path = "/tracks", tag = "tracks", responses((status = 200, body = [TrackView])))]
async fn list_tracks(State(state): State<AppState>) -> Json<Vec<TrackView>> {
    Json(state.tracking.board().views.values().cloned().collect())
}

fn parse_id(id: &str) -> Result<u64, ApiError> {
    id.parse()
        .map_err(|_| ApiError::Malformed(format!("track id '{id}' is not a non-negative integer")))
}

#[utoipa::path(get, path = "/tracks/{id}", tag = "tracks",
    params(("id" = u64, Path, description = "Track id")),
    responses((status = 200, body = TrackView), (status = 404, body = super::error::Problem)))]
async fn get_track(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<TrackView>, ApiError> {
    let id = parse_id(&id)?;
    state
        .tracking
        .board()
        .views
        .get(&id)
        .cloned()
        .map(Json)
        .ok_or_else(|| ApiError::not_found("track", id.to_string()))
}

#[utoipa::path(get, path = "/tracks/{id}/history", tag = "tracks",
    params(("id" = u64, Path, description = "Track id")),
    responses((status = 200, body = [HistoryPoint]), (status = 404, body = super::error::Problem)))]
async fn track_history(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Vec<HistoryPoint>>, ApiError> {
    let id = parse_id(&id)?;
    state
        .tracking
        .board()
        .history
        .get(&id)
        .map(|h| Json(h.iter().cloned().collect()))
        .ok_or_else(|| ApiError::not_found("track", id.to_string()))
}

#[utoipa::path(delete, path = "/tracks/{id}", tag = "tracks",
    params(("id" = u64, Path, description = "Track id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn stop_track(State(state): State<AppState>, Path(id): Path<String>) -> Result<super::error::Deleted, ApiError> {
    let id = parse_id(&id)?;
    let mut b = state.tracking.board_mut();
    if b.views.remove(&id).is_none() {
        return Err(ApiError::not_found("track", id.to_string()));
    }
    b.history.remove(&id);
    b.stopped.push(id);
    drop(b);
    state.decision_cache.forget(Some(id));
    state.store.delete(super::store::Table::Tracks, &id.to_string())?;
    Ok(super::error::Deleted)
}
