//! `/grippers`: gripper models (typed mirrors of `crate::grasp::Gripper`).

use super::AppState;
use super::error::ApiError;
use super::types::ApiJson;
use crate::grasp::{Gripper, PadGeometry};
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub use crate::service::registry::DEFAULT_GRIPPER;

/// Finger pad geometry and its capture funnel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PadGeometryDto {
    /// Length of the pad along the approach axis, measured from the finger tip.
    pub length_m: f64,
    /// Thickness of the pad slab on the finger's inner face (its collision volume).
    pub thickness_m: f64,
    /// Half-width of the V-groove's mouth across the pad (along gripper y).
    pub groove_half_width_m: f64,
    /// Angle of the groove walls (and tip chamfer) from the pad plane.
    pub capture_angle_deg: f64,
}

/// A parallel-jaw gripper: the gripper frame has +z along the approach and x along the
/// closing direction (see `crate::grasp::Gripper`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GripperDto {
    pub name: String,
    /// Palm box size (x, y, z).
    pub palm_size_m: [f64; 3],
    /// Finger box: thickness (x), width (y), length (z).
    pub finger_size_m: [f64; 3],
    /// Largest distance between the pads (the stroke).
    pub max_opening_m: f64,
    /// Smallest distance between the pads (fully closed).
    pub min_opening_m: f64,
    pub pad: PadGeometryDto,
    /// Distance of the pre-grasp pose before the grasp pose along the approach axis.
    pub approach_distance_m: f64,
    /// Least distance between any gripper part and the support plane.
    pub table_clearance_m: f64,
}

impl From<&Gripper> for GripperDto {
    fn from(g: &Gripper) -> Self {
        Self {
            name: g.name.clone(),
            palm_size_m: g.palm_size_m,
            finger_size_m: g.finger_size_m,
            max_opening_m: g.max_opening_m,
            min_opening_m: g.min_opening_m,
            pad: PadGeometryDto {
                length_m: g.pad.length_m,
                thickness_m: g.pad.thickness_m,
                groove_half_width_m: g.pad.groove_half_width_m,
                capture_angle_deg: g.pad.capture_angle_deg,
            },
            approach_distance_m: g.approach_distance_m,
            table_clearance_m: g.table_clearance_m,
        }
    }
}

impl From<GripperDto> for Gripper {
    fn from(g: GripperDto) -> Self {
        Self {
            name: g.name,
            palm_size_m: g.palm_size_m,
            finger_size_m: g.finger_size_m,
            max_opening_m: g.max_opening_m,
            min_opening_m: g.min_opening_m,
            pad: PadGeometry {
                length_m: g.pad.length_m,
                thickness_m: g.pad.thickness_m,
                groove_half_width_m: g.pad.groove_half_width_m,
                capture_angle_deg: g.pad.capture_angle_deg,
            },
            approach_distance_m: g.approach_distance_m,
            table_clearance_m: g.table_clearance_m,
        }
    }
}

/// A registered gripper.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct GripperRecord {
    pub id: String,
    pub gripper: GripperDto,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_grippers))
        .routes(routes!(get_gripper, put_gripper, delete_gripper))
}

#[utoipa::path(get, path = "/grippers", tag = "grippers", responses((status = 200, body = [GripperRecord])))]
async fn list_grippers(State(state): State<AppState>) -> Json<Vec<GripperRecord>> {
    Json(
        state
            .registry()
            .grippers
            .iter()
            .map(|(id, g)| GripperRecord {
                id: id.clone(),
                gripper: g.into(),
            })
            .collect(),
    )
}

#[utoipa::path(get, path = "/grippers/{id}", tag = "grippers",
    params(("id" = String, Path, description = "Gripper id")),
    responses((status = 200, body = GripperRecord), (status = 404, body = super::error::Problem)))]
async fn get_gripper(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<GripperRecord>, ApiError> {
    let g = state.gripper(&id)?;
    Ok(Json(GripperRecord {
        id,
        gripper: (&g).into(),
    }))
}

#[utoipa::path(put, path = "/grippers/{id}", tag = "grippers",
    params(("id" = String, Path, description = "Gripper id")),
    request_body = GripperDto,
    responses((status = 200, body = GripperRecord), (status = 400, body = super::error::Problem),
        (status = 409, description = "The gripper cap is reached", body = super::error::Problem),
        (status = 415, body = super::error::Problem), (status = 422, body = super::error::Problem)))]
async fn put_gripper(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ApiJson(gripper): ApiJson<GripperDto>,
) -> Result<Json<GripperRecord>, ApiError> {
    let g = state.register_gripper(&id, gripper.into())?;
    Ok(Json(GripperRecord {
        id,
        gripper: (&g).into(),
    }))
}

#[utoipa::path(delete, path = "/grippers/{id}", tag = "grippers",
    params(("id" = String, Path, description = "Gripper id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn delete_gripper(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<super::error::Deleted, ApiError> {
    state.delete_gripper(&id)?;
    Ok(super::error::Deleted)
}
