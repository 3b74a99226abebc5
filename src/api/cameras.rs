//! `/cameras`: registration of the cameras (intrinsics like ROS `CameraInfo`, mount).

use super::error::ApiError;
use super::store::{Store, Table};
use super::types::{ApiJson, IntrinsicsDto, PoseDto, check_id};
use super::{AppState, Registry};
use axum::Json;
use axum::extract::{Path, State};
use axum::response::IntoResponse;
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

impl Camera {
    pub fn is_robot(&self) -> bool {
        matches!(self.mount, MountDto::Robot { .. })
    }
}

/// The reference camera of the tracker: the first robot camera, else the first camera.
pub fn reference_camera(reg: &Registry) -> Option<String> {
    reg.cameras
        .values()
        .find(|c| c.is_robot())
        .or_else(|| reg.cameras.values().next())
        .map(|c| c.id.clone())
}

pub(super) fn load(store: &Store, reg: &mut Registry) -> anyhow::Result<()> {
    for (id, cam) in store.list::<Camera>(Table::Cameras)? {
        reg.cameras.insert(id, cam);
    }
    Ok(())
}

pub fn router() -> OpenApiRouter<super::AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_cameras))
        .routes(routes!(get_camera, put_camera, delete_camera))
}

/// Validates a camera spec (intrinsics, poses) into a record.
pub fn validate(id: &str, spec: CameraSpec) -> Result<Camera, ApiError> {
    check_id("camera", id)?;
    spec.intrinsics.to_intrinsics()?;
    let k = &spec.intrinsics.k;
    let (w, h) = (f64::from(spec.intrinsics.width), f64::from(spec.intrinsics.height));
    // a focal length up to 100 image widths, a principal point within an image of the image
    let plausible = k[0] <= 100.0 * w && k[4] <= 100.0 * h && k[2].abs() <= 2.0 * w && k[5].abs() <= 2.0 * h;
    if !plausible {
        return Err(ApiError::Invalid(format!(
            "intrinsics: focal lengths must be at most 100 image sizes and the principal point within the image's neighbourhood, got k = {k:?}"
        )));
    }
    match &spec.mount {
        MountDto::Stationary { world_from_camera } => {
            world_from_camera.to_pose("mount.world_from_camera")?;
        }
        MountDto::Robot { base_from_camera } => {
            base_from_camera.to_pose("mount.base_from_camera")?;
        }
    }
    Ok(Camera {
        id: id.to_string(),
        intrinsics: spec.intrinsics,
        mount: spec.mount,
    })
}

/// Registers (or replaces) a camera in the registry and the store; a replaced camera's waiting
/// frames are freed (they were taken with the old intrinsics).
pub fn register(state: &AppState, cam: Camera) -> Result<(), ApiError> {
    let limits = state.config.limits;
    let px = u64::from(cam.intrinsics.width) * u64::from(cam.intrinsics.height);
    if px > limits.max_camera_pixels {
        return Err(ApiError::LimitReached(format!(
            "camera '{}' is {}x{} = {px} pixels; this server takes at most {} (--max-camera-pixels)",
            cam.id, cam.intrinsics.width, cam.intrinsics.height, limits.max_camera_pixels
        )));
    }
    let mut reg = state.registry_mut();
    if cam.is_robot() && reg.cameras.values().any(|c| c.is_robot() && c.id != cam.id) {
        return Err(ApiError::Conflict(
            "only one robot camera is supported; delete the other robot camera first".into(),
        ));
    }
    if !reg.cameras.contains_key(&cam.id) && reg.cameras.len() >= limits.max_cameras {
        return Err(ApiError::LimitReached(format!(
            "this server takes at most {} cameras (--max-cameras); delete one first",
            limits.max_cameras
        )));
    }
    state.store.put(Table::Cameras, &cam.id, &cam)?;
    state.ingest().forget_camera(&cam.id);
    reg.cameras.insert(cam.id.clone(), cam);
    reg.version += 1;
    Ok(())
}

#[utoipa::path(get, path = "/cameras", tag = "cameras",
    responses((status = 200, description = "All cameras", body = [Camera])))]
async fn list_cameras(State(state): State<AppState>) -> Json<Vec<Camera>> {
    Json(state.registry().cameras.values().cloned().collect())
}

#[utoipa::path(get, path = "/cameras/{id}", tag = "cameras",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 200, body = Camera), (status = 404, body = super::error::Problem)))]
async fn get_camera(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<Camera>, ApiError> {
    state
        .registry()
        .cameras
        .get(&id)
        .cloned()
        .map(Json)
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
) -> Result<impl IntoResponse, ApiError> {
    let cam = validate(&id, spec)?;
    register(&state, cam.clone())?;
    Ok(Json(cam))
}

#[utoipa::path(delete, path = "/cameras/{id}", tag = "cameras",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn delete_camera(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<super::error::Deleted, ApiError> {
    let mut reg = state.registry_mut();
    if !reg.cameras.contains_key(&id) {
        return Err(ApiError::not_found("camera", id));
    }
    state.store.delete(Table::Cameras, &id)?;
    state.ingest().forget_camera(&id);
    reg.cameras.remove(&id);
    reg.version += 1;
    Ok(super::error::Deleted)
}
