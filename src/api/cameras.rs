//! `/cameras`: registration of the cameras (intrinsics like ROS `CameraInfo`, mount).

use super::AppState;
use super::error::ApiError;
use super::types::{ApiJson, IntrinsicsDto, PoseDto};
use crate::sensor::CameraMount;
use crate::service;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// How a camera is mounted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum MountDto {
    /// Fixed in the world.
    Stationary { world_from_camera: PoseDto },
    /// On the robot (moves with the base; `base_from_camera` changes with the arm and can be
    /// updated with each odometry message).
    Robot { base_from_camera: PoseDto },
}

/// What a client sends to register a camera.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub intrinsics: IntrinsicsDto,
    pub mount: MountDto,
}

/// A registered camera.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Camera {
    pub id: String,
    pub intrinsics: IntrinsicsDto,
    pub mount: MountDto,
}

impl MountDto {
    /// Validates the pose into a domain mount.
    pub fn to_mount(&self) -> Result<CameraMount, ApiError> {
        Ok(match self {
            Self::Stationary { world_from_camera } => CameraMount::Stationary {
                world_from_camera: world_from_camera.to_pose("mount.world_from_camera")?,
            },
            Self::Robot { base_from_camera } => CameraMount::Robot {
                base_from_camera: base_from_camera.to_pose("mount.base_from_camera")?,
            },
        })
    }
    pub fn from_mount(m: &CameraMount) -> Self {
        match m {
            CameraMount::Stationary { world_from_camera } => Self::Stationary {
                world_from_camera: PoseDto::from_pose(world_from_camera),
            },
            CameraMount::Robot { base_from_camera } => Self::Robot {
                base_from_camera: PoseDto::from_pose(base_from_camera),
            },
        }
    }
}

impl From<&service::registry::Camera> for Camera {
    fn from(c: &service::registry::Camera) -> Self {
        Self {
            id: c.id.clone(),
            intrinsics: IntrinsicsDto::from_intrinsics(&c.intrinsics),
            mount: MountDto::from_mount(&c.mount),
        }
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_cameras))
        .routes(routes!(get_camera, put_camera, delete_camera))
}

#[utoipa::path(get, path = "/cameras", tag = "cameras",
    responses((status = 200, description = "All cameras", body = [Camera])))]
async fn list_cameras(State(state): State<AppState>) -> Json<Vec<Camera>> {
    Json(state.registry().cameras.values().map(Camera::from).collect())
}

#[utoipa::path(get, path = "/cameras/{id}", tag = "cameras",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 200, body = Camera), (status = 404, body = super::error::Problem)))]
async fn get_camera(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<Camera>, ApiError> {
    state
        .registry()
        .cameras
        .get(&id)
        .map(|c| Json(Camera::from(c)))
        .ok_or_else(|| ApiError::not_found("camera", id))
}

#[utoipa::path(put, path = "/cameras/{id}", tag = "cameras",
    params(("id" = String, Path, description = "Camera id")),
    request_body = CameraSpec,
    responses((status = 200, body = Camera), (status = 400, body = super::error::Problem),
        (status = 409, description = "A second robot camera, or the camera cap is reached", body = super::error::Problem),
        (status = 415, body = super::error::Problem), (status = 422, body = super::error::Problem)))]
async fn put_camera(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ApiJson(spec): ApiJson<CameraSpec>,
) -> Result<Json<Camera>, ApiError> {
    let intrinsics = spec.intrinsics.to_intrinsics()?;
    let mount = spec.mount.to_mount()?;
    let cam = state.register_camera(&id, intrinsics, mount)?;
    Ok(Json(Camera::from(&cam)))
}

#[utoipa::path(delete, path = "/cameras/{id}", tag = "cameras",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn delete_camera(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<super::error::Deleted, ApiError> {
    state.delete_camera(&id)?;
    Ok(super::error::Deleted)
}
