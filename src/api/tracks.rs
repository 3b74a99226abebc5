//! `/tracks`: the tracked objects (current estimate, samples, history, start, stop).

use super::AppState;
use super::decisions::DecisionView;
use super::error::ApiError;
use super::types::PoseDto;
use crate::service::decisions::MAX_DECISION_SAMPLES;
use crate::service::tracks::{self as service_tracks, PriorPose, StartTrack, TrackState};
use crate::tracker::TrackStatus;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

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
    /// The latest decision asked about this track.
    pub decision: Option<DecisionView>,
    pub truth: Option<TruthDto>,
    /// Milliseconds from receiving the newest fused frame to this estimate.
    pub ingest_to_estimate_ms: Option<f64>,
    /// When and why the tracker last started this track again (none: never).
    pub reinitialised: Option<ReinitialisationDto>,
}

/// When and why a track started again.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct ReinitialisationDto {
    /// Stamp of the step that started it again.
    pub stamp_ns: i64,
    pub reason: ReinitReasonDto,
}

/// Why a track started again.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ReinitReasonDto {
    /// The track was lost and this camera's detection of its object started it again.
    Redetected { camera: String },
    /// These cameras' detections agreed with each other and lay outside the track's 99 %
    /// region (its covariance plus the detections' own uncertainty) for `steps` steps in a
    /// row, while no more cameras supported the track: their particles were spawned again
    /// from their detections, `offset_m` from the track's mean; the rotation belief was kept.
    CamerasDisagreed {
        cameras: Vec<String>,
        offset_m: f64,
        steps: u32,
    },
}

impl From<&crate::tracker::Reinitialisation> for ReinitialisationDto {
    fn from(r: &crate::tracker::Reinitialisation) -> Self {
        use crate::tracker::ReinitReason;
        Self {
            stamp_ns: r.stamp_ns,
            reason: match &r.reason {
                ReinitReason::Redetected { camera } => ReinitReasonDto::Redetected { camera: camera.clone() },
                ReinitReason::CamerasDisagreed {
                    cameras,
                    offset_m,
                    steps,
                } => ReinitReasonDto::CamerasDisagreed {
                    cameras: cameras.clone(),
                    offset_m: *offset_m,
                    steps: *steps,
                },
            },
        }
    }
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

impl From<TrackStatus> for TrackStatusDto {
    fn from(s: TrackStatus) -> Self {
        match s {
            TrackStatus::Initialising => Self::Initialising,
            TrackStatus::Tracking => Self::Tracking,
            TrackStatus::Lost => Self::Lost,
        }
    }
}

impl From<&service_tracks::TruthError> for TruthDto {
    fn from(t: &service_tracks::TruthError) -> Self {
        Self {
            translation_error_m: t.translation_error_m,
            orientation_error_deg: t.orientation_error_deg,
        }
    }
}

impl From<&TrackState> for TrackView {
    fn from(t: &TrackState) -> Self {
        Self {
            id: t.id,
            object_id: t.object_id.clone(),
            object_name: t.object_name.clone(),
            status: t.status.into(),
            stamp_ns: t.stamp_ns,
            reference_from_object: PoseDto::from_pose(&t.reference_from_object),
            world_from_object: PoseDto::from_pose(&t.world_from_object),
            translation_std_m: t.translation_std_m,
            rotation_entropy: t.rotation_entropy,
            top_mode_mass: t.top_mode_mass,
            covariance_6x6: t.covariance_6x6.clone(),
            components: t
                .components
                .iter()
                .map(|c| ComponentDto {
                    camera: c.camera.clone(),
                    weight: c.weight,
                    mean_m: c.mean_m,
                    covariance_m2: c.covariance_m2,
                })
                .collect(),
            rotation_modes: t
                .rotation_modes
                .iter()
                .map(|m| RotationModeDto {
                    rotation_xyzw: m.rotation_xyzw,
                    mass: m.mass,
                })
                .collect(),
            particles: t
                .particles
                .iter()
                .map(|p| ParticleDto {
                    position_world_m: p.position_world_m,
                    camera: p.camera.clone(),
                    weight: p.weight,
                })
                .collect(),
            samples_world: t.samples_world.iter().map(PoseDto::from_pose).collect(),
            decision: t.decision.as_deref().map(DecisionView::from),
            truth: t.truth.as_ref().map(TruthDto::from),
            ingest_to_estimate_ms: t.ingest_to_estimate_ms,
            reinitialised: t.reinitialised.as_ref().map(ReinitialisationDto::from),
        }
    }
}

impl From<&service_tracks::HistoryPoint> for HistoryPoint {
    fn from(h: &service_tracks::HistoryPoint) -> Self {
        Self {
            stamp_ns: h.stamp_ns,
            world_from_object: PoseDto::from_pose(&h.world_from_object),
            translation_std_m: h.translation_std_m,
            rotation_entropy: h.rotation_entropy,
            status: h.status.into(),
            truth: h.truth.as_ref().map(TruthDto::from),
        }
    }
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
    let pose = match (&req.world_from_object, &req.reference_from_object) {
        (Some(w), None) => PriorPose::World {
            world_from_object: w.to_pose("world_from_object")?,
        },
        (None, Some(r)) => PriorPose::Reference {
            reference_from_object: r.to_pose("reference_from_object")?,
        },
        _ => {
            return Err(ApiError::Invalid(
                "give exactly one of world_from_object and reference_from_object".into(),
            ));
        }
    };
    let start = StartTrack {
        object_id: req.object_id,
        pose,
        translation_std_m: req.translation_std_m.unwrap_or(service_tracks::DEFAULT_PRIOR_STD_M),
        rotation_std_deg: req.rotation_std_deg,
    };
    let service = state.service.clone();
    let view = tokio::task::spawn_blocking(move || service.start_track(&start))
        .await
        .map_err(ApiError::internal)??;
    Ok(super::error::Created(TrackView::from(&view)))
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
#[into_params(parameter_in = Query)]
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
    if n == 0 || n > MAX_DECISION_SAMPLES {
        return Err(ApiError::Invalid(format!(
            "n must be in 1..={MAX_DECISION_SAMPLES}, got {n}"
        )));
    }
    let service = state.service.clone();
    let drawn = tokio::task::spawn_blocking(move || service.draw_samples(id, n))
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
    Json(state.tracks().iter().map(TrackView::from).collect())
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
    Ok(Json(TrackView::from(&state.track(id)?)))
}

#[utoipa::path(get, path = "/tracks/{id}/history", tag = "tracks",
    params(("id" = u64, Path, description = "Track id")),
    responses((status = 200, body = [HistoryPoint]), (status = 404, body = super::error::Problem)))]
async fn track_history(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Vec<HistoryPoint>>, ApiError> {
    let id = parse_id(&id)?;
    Ok(Json(state.track_history(id)?.iter().map(HistoryPoint::from).collect()))
}

#[utoipa::path(delete, path = "/tracks/{id}", tag = "tracks",
    params(("id" = u64, Path, description = "Track id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn stop_track(State(state): State<AppState>, Path(id): Path<String>) -> Result<super::error::Deleted, ApiError> {
    let id = parse_id(&id)?;
    state.stop_track(id)?;
    Ok(super::error::Deleted)
}
