//! `/scene`: what the dashboard draws around the tracks (cameras, robot path, support plane).

use super::AppState;
use super::cameras::MountDto;
use super::types::{IntrinsicsDto, PoseDto};
use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Most trajectory points served.
pub const MAX_TRAJECTORY_POINTS: usize = 500;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
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
    OpenApiRouter::new().routes(routes!(get_scene))
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
