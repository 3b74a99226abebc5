//! `/grippers`: gripper models (the JSON of `crate::grasp::Gripper`).

use super::error::ApiError;
use super::store::{Store, Table};
use super::types::{ApiJson, check_id};
use super::{AppState, Registry};
use crate::grasp::Gripper;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// A registered gripper.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct GripperRecord {
    pub id: String,
    /// The gripper model (see `crate::grasp::Gripper`).
    #[schema(value_type = Object)]
    pub gripper: serde_json::Value,
}

pub(super) fn load(store: &Store, reg: &mut Registry) -> anyhow::Result<()> {
    for (id, g) in store.list::<serde_json::Value>(Table::Grippers)? {
        reg.grippers.insert(id, g);
    }
    if !reg.grippers.contains_key(DEFAULT_GRIPPER) {
        let g = serde_json::to_value(Gripper::default_parallel_jaw())?;
        store.put(Table::Grippers, DEFAULT_GRIPPER, &g)?;
        reg.grippers.insert(DEFAULT_GRIPPER.to_string(), g);
    }
    Ok(())
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_grippers))
        .routes(routes!(get_gripper, put_gripper, delete_gripper))
}

/// Id of the gripper every server has (the default parallel-jaw gripper).
pub const DEFAULT_GRIPPER: &str = "default";

/// Checks a gripper document (the fields of `crate::grasp::Gripper`, all required, nothing
/// else) and its geometry; returns it normalised.
pub fn validate(value: serde_json::Value) -> Result<serde_json::Value, ApiError> {
    let g: Gripper = serde_json::from_value(value).map_err(|e| ApiError::Invalid(format!("gripper: {e}")))?;
    g.validate().map_err(|e| ApiError::Invalid(e.to_string()))?;
    serde_json::to_value(&g).map_err(ApiError::internal)
}

/// The gripper model of a registered id.
pub fn gripper(state: &AppState, id: &str) -> Result<Gripper, ApiError> {
    let v = state
        .registry()
        .grippers
        .get(id)
        .cloned()
        .ok_or_else(|| ApiError::not_found("gripper", id))?;
    serde_json::from_value(v).map_err(|e| ApiError::Internal(format!("stored gripper {id}: {e}")))
}

/// Registers (or replaces) a gripper.
pub fn register(state: &AppState, id: &str, gripper: serde_json::Value) -> Result<GripperRecord, ApiError> {
    check_id("gripper", id)?;
    let gripper = validate(gripper)?;
    let mut reg = state.registry_mut();
    let max = state.config.limits.max_grippers;
    if !reg.grippers.contains_key(id) && reg.grippers.len() >= max {
        return Err(ApiError::LimitReached(format!(
            "this server takes at most {max} grippers (--max-grippers); delete one first"
        )));
    }
    state.store.put(Table::Grippers, id, &gripper)?;
    reg.grippers.insert(id.to_string(), gripper.clone());
    Ok(GripperRecord {
        id: id.to_string(),
        gripper,
    })
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
                gripper: g.clone(),
            })
            .collect(),
    )
}

#[utoipa::path(get, path = "/grippers/{id}", tag = "grippers",
    params(("id" = String, Path, description = "Gripper id")),
    responses((status = 200, body = GripperRecord), (status = 404, body = super::error::Problem)))]
async fn get_gripper(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<GripperRecord>, ApiError> {
    let reg = state.registry();
    let g = reg
        .grippers
        .get(&id)
        .ok_or_else(|| ApiError::not_found("gripper", id.clone()))?;
    Ok(Json(GripperRecord { id, gripper: g.clone() }))
}

#[utoipa::path(put, path = "/grippers/{id}", tag = "grippers",
    params(("id" = String, Path, description = "Gripper id")),
    request_body(content = Object, description = "The gripper model"),
    responses((status = 200, body = GripperRecord), (status = 400, body = super::error::Problem),
        (status = 409, description = "The gripper cap is reached", body = super::error::Problem),
        (status = 415, body = super::error::Problem), (status = 422, body = super::error::Problem)))]
async fn put_gripper(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ApiJson(gripper): ApiJson<serde_json::Value>,
) -> Result<Json<GripperRecord>, ApiError> {
    Ok(Json(register(&state, &id, gripper)?))
}

#[utoipa::path(delete, path = "/grippers/{id}", tag = "grippers",
    params(("id" = String, Path, description = "Gripper id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn delete_gripper(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<super::error::Deleted, ApiError> {
    let mut reg = state.registry_mut();
    if !reg.grippers.contains_key(&id) {
        return Err(ApiError::not_found("gripper", id));
    }
    state.store.delete(Table::Grippers, &id)?;
    reg.grippers.remove(&id);
    Ok(super::error::Deleted)
}
