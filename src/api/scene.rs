//! `/scene`: what the dashboard draws around the tracks (cameras, robot path, support plane).

use super::AppState;
use super::error::ApiError;
use super::frames::StampAccepted;
use super::types::{ApiJson, IntrinsicsDto, PoseDto};
use crate::grasp::SupportPlane;
use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

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

impl From<PlaneDto> for SupportPlane {
    fn from(p: PlaneDto) -> Self {
        Self {
            normal: p.normal,
            point_m: p.point_m,
        }
    }
}

impl From<SupportPlane> for PlaneDto {
    fn from(p: SupportPlane) -> Self {
        Self {
            normal: p.normal,
            point_m: p.point_m,
        }
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(get_scene))
        .routes(routes!(put_support_plane))
        .routes(routes!(post_truth))
}

#[utoipa::path(put, path = "/scene/support_plane", tag = "scene",
    request_body(content = Option<PlaneDto>, description = "The table top in the world frame, or null"),
    responses((status = 200, body = Option<PlaneDto>), (status = 422, body = super::error::Problem)))]
async fn put_support_plane(
    State(state): State<AppState>,
    ApiJson(plane): ApiJson<Option<PlaneDto>>,
) -> Result<Json<Option<PlaneDto>>, ApiError> {
    let plane = state.set_support_plane(plane.map(SupportPlane::from))?;
    Ok(Json(plane.map(PlaneDto::from)))
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
    responses((status = 202, description = "Stored for display", body = StampAccepted),
        (status = 403, description = "The server was started without --accept-truth (or --demo)", body = super::error::Problem),
        (status = 422, body = super::error::Problem)))]
async fn post_truth(
    State(state): State<AppState>,
    ApiJson(t): ApiJson<TruthIn>,
) -> Result<super::error::Accepted<StampAccepted>, ApiError> {
    let objects = t
        .objects
        .iter()
        .map(|o| Ok((o.object.clone(), o.world_from_object.to_pose("world_from_object")?)))
        .collect::<Result<Vec<_>, ApiError>>()?;
    state.set_truth(t.stamp_ns, objects)?;
    Ok(super::error::Accepted(StampAccepted { stamp_ns: t.stamp_ns }))
}

#[utoipa::path(get, path = "/scene", tag = "scene", responses((status = 200, body = Scene)))]
async fn get_scene(State(state): State<AppState>) -> Json<Scene> {
    let scene = state.scene();
    let cameras = scene
        .cameras
        .into_iter()
        .map(|c| SceneCamera {
            id: c.camera.id.clone(),
            mount: if c.camera.is_robot() {
                MountKind::Robot
            } else {
                MountKind::Stationary
            },
            intrinsics: IntrinsicsDto::from_intrinsics(&c.camera.intrinsics),
            world_from_camera: c.world_from_camera.as_ref().map(PoseDto::from_pose),
            latest_stamp_ns: c.latest_stamp_ns,
        })
        .collect();
    Json(Scene {
        world_frame: "world".into(),
        support_plane: scene.support_plane.map(PlaneDto::from),
        cameras,
        robot_trajectory_m: scene.robot_trajectory_m,
    })
}
