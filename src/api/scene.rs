//! `/scene`: what the dashboard draws around the tracks (cameras, robot path, support plane).

use super::AppState;
use super::cameras::MountDto;
use super::error::ApiError;
use super::types::{ApiJson, IntrinsicsDto, PoseDto};
use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Most trajectory points served.
pub const MAX_TRAJECTORY_POINTS: usize = 500;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PlaneDto {
    pub normal: [f64; 3],
    pub point_m: [f64; 3],
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum MountKind {
    Stationary,
    Robot,
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct SceneCamera {
    pub id: String,
    pub mount: MountKind,
    pub intrinsics: IntrinsicsDto,
    /// Fixed for stationary cameras; the latest estimate for the robot camera (null before one).
    pub world_from_camera: Option<PoseDto>,
    pub latest_stamp_ns: Option<i64>,
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Scene {
    pub world_frame: String,
    pub support_plane: Option<PlaneDto>,
    pub cameras: Vec<SceneCamera>,
    /// Robot base positions in the world frame, oldest first.
    pub robot_trajectory_m: Vec<[f64; 3]>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(get_scene))
        .routes(routes!(put_support_plane))
        .routes(routes!(post_truth))
}

/// The support plane saved by the last run (an unreadable one is logged and ignored).
pub(super) fn load_support_plane(store: &super::store::Store) -> Option<PlaneDto> {
    let bytes = store
        .get_bytes(super::store::Table::Scene, super::store::SUPPORT_PLANE_KEY)
        .map_err(|e| tracing::warn!("reading the support plane: {e}"))
        .ok()??;
    serde_json::from_slice::<PlaneDto>(&bytes)
        .map_err(|e| tracing::warn!("support plane unreadable, ignored: {e}"))
        .ok()
        .and_then(|p| validate_plane(&p).ok())
}

/// Sets the support plane, in memory and in the store.
pub fn set_support_plane(state: &AppState, plane: Option<PlaneDto>) -> Result<(), ApiError> {
    let (table, key) = (super::store::Table::Scene, super::store::SUPPORT_PLANE_KEY);
    match &plane {
        Some(p) => state.store.put(table, key, p)?,
        None => {
            state.store.delete(table, key)?;
        }
    }
    *state.support_plane.lock().unwrap_or_else(|p| p.into_inner()) = plane;
    Ok(())
}

/// Checks a plane (finite, non-zero normal, a point within [`super::types::MAX_POSITION_M`])
/// and normalises its normal.
pub fn validate_plane(p: &PlaneDto) -> Result<PlaneDto, ApiError> {
    let n = nalgebra::Vector3::from(p.normal);
    let ok = p.normal.iter().chain(&p.point_m).all(|v| v.is_finite())
        && n.norm() > 1e-9
        && nalgebra::Vector3::from(p.point_m).norm() <= super::types::MAX_POSITION_M;
    if !ok {
        return Err(ApiError::Invalid(format!(
            "support plane needs finite numbers, a non-zero normal and a point within {} m",
            super::types::MAX_POSITION_M
        )));
    }
    let n = n.normalize();
    Ok(PlaneDto {
        normal: [n.x, n.y, n.z],
        point_m: p.point_m,
    })
}

#[utoipa::path(put, path = "/scene/support_plane", tag = "scene",
    request_body(content = Option<PlaneDto>, description = "The table top in the world frame, or null"),
    responses((status = 200, body = Option<PlaneDto>), (status = 422, body = super::error::Problem)))]
async fn put_support_plane(
    State(state): State<AppState>,
    ApiJson(plane): ApiJson<Option<PlaneDto>>,
) -> Result<Json<Option<PlaneDto>>, ApiError> {
    let plane = plane.as_ref().map(validate_plane).transpose()?;
    set_support_plane(&state, plane)?;
    Ok(Json(plane))
}

/// One object's true pose.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct TruthObject {
    /// Object id.
    pub object: String,
    pub world_from_object: PoseDto,
}

/// Ground truth for display (the demo, replays of generated data). The tracker never reads it;
/// it only fills the `truth` field of track views so that the dashboard can plot errors.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TruthIn {
    pub stamp_ns: i64,
    pub objects: Vec<TruthObject>,
}

#[utoipa::path(post, path = "/truth", tag = "scene",
    request_body = TruthIn,
    responses((status = 202, description = "Stored for display"),
        (status = 403, description = "The server was started without --accept-truth (or --demo)", body = super::error::Problem),
        (status = 422, body = super::error::Problem)))]
async fn post_truth(
    State(state): State<AppState>,
    ApiJson(t): ApiJson<TruthIn>,
) -> Result<super::error::Accepted<serde_json::Value>, ApiError> {
    if !state.config.accept_truth {
        return Err(ApiError::Disabled(
            "this server does not accept ground truth (start it with --accept-truth or --demo)".into(),
        ));
    }
    super::frames::validate_stamp("stamp_ns", t.stamp_ns)?;
    let mut poses = Vec::with_capacity(t.objects.len());
    {
        // one entry per registered object: the map stays as small as the registry
        let reg = state.registry();
        for o in &t.objects {
            if !reg.objects.contains_key(&o.object) {
                return Err(ApiError::Invalid(format!(
                    "ground truth names unknown object '{}'",
                    super::types::shorten(&o.object)
                )));
            }
            poses.push((o.object.clone(), o.world_from_object.to_pose("world_from_object")?));
        }
    }
    let mut truth = state.truth.lock().unwrap_or_else(|p| p.into_inner());
    for (object, pose) in poses {
        truth.insert(object, (t.stamp_ns, pose));
    }
    Ok(super::error::Accepted(serde_json::json!({"stamp_ns": t.stamp_ns})))
}

#[utoipa::path(get, path = "/scene", tag = "scene", responses((status = 200, body = Scene)))]
async fn get_scene(State(state): State<AppState>) -> Json<Scene> {
    let world_from_reference = state.tracking.board().world_from_reference;
    let cams: Vec<_> = state.registry().cameras.values().cloned().collect();
    let support_plane = *state.support_plane.lock().unwrap_or_else(|p| p.into_inner());
    let ingest = state.ingest();
    let cameras = cams
        .into_iter()
        .map(|c| {
            let (mount, world_from_camera) = match c.mount {
                MountDto::Stationary { world_from_camera } => (MountKind::Stationary, Some(world_from_camera)),
                MountDto::Robot { .. } => (MountKind::Robot, world_from_reference),
            };
            SceneCamera {
                latest_stamp_ns: ingest.latest(&c.id).map(|f| f.stamp_ns),
                id: c.id,
                mount,
                intrinsics: c.intrinsics,
                world_from_camera,
            }
        })
        .collect();
    Json(Scene {
        world_frame: "world".into(),
        support_plane,
        cameras,
        robot_trajectory_m: ingest.trajectory_m(MAX_TRAJECTORY_POINTS),
    })
}
