//! `POST /tracks/{id}/decision`: grasp now or observe more? Draws poses from the track's
//! distribution and calls `crate::grasp::decide`.

use super::AppState;
use super::error::ApiError;
use super::events::ServerEvent;
use super::scene::{PlaneDto, validate_plane};
use super::types::{ApiJson, PoseDto};
use crate::geometry::{Pose, PoseSamples};
use crate::grasp::{self, DecisionQuery, Grasp, GraspObject, Gripper, SupportPlane};
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Most samples a query may ask for.
pub const MAX_DECISION_SAMPLES: usize = 5_000;

/// A grasp given by the caller (object frame).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct GraspIn {
    pub object_from_gripper: PoseDto,
}

/// A decision query.
#[derive(Debug, Clone, Default, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DecisionRequest {
    /// Registered gripper id (default `default`, the built-in parallel-jaw gripper).
    pub gripper: Option<String>,
    /// The grasp to check; absent: candidates are generated and the best is taken.
    pub grasp: Option<GraspIn>,
    /// The table in the world frame; absent: the scene's support plane (if any).
    pub support_plane: Option<PlaneDto>,
    /// Poses drawn from the distribution (default 1,000, at most 5,000).
    pub n_samples: Option<usize>,
    /// Grasp only when the lower end of the 95% interval on p_success reaches this (default 0.9).
    pub threshold: Option<f64>,
}

/// What the tracker gives a decision: the estimate and samples in the reference frame.
pub struct Drawn {
    pub object_id: String,
    pub reference_from_object: Pose,
    pub samples: PoseSamples,
    pub world_from_reference: Pose,
}

/// Solid shapes per mesh content hash (a convex decomposition takes up to a second; it is
/// built once even when many decisions ask for it at the same time).
#[derive(Default)]
pub struct GraspObjects(Mutex<HashMap<String, Arc<Mutex<Option<GraspObject>>>>>);

impl GraspObjects {
    pub fn get_or_build(&self, state: &AppState, object_id: &str) -> Result<GraspObject, ApiError> {
        let (hash, mesh) = {
            let reg = state.registry();
            let o = reg
                .objects
                .get(object_id)
                .ok_or_else(|| ApiError::not_found("object", object_id))?;
            (o.info.content_hash.clone(), o.mesh.clone())
        };
        let slot = self
            .0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(hash)
            .or_default()
            .clone();
        let mut slot = slot.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(g) = slot.as_ref() {
            return Ok(g.clone());
        }
        let g = GraspObject::new(&mesh).map_err(|e| ApiError::Invalid(format!("object '{object_id}': {e}")))?;
        *slot = Some(g.clone());
        Ok(g)
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(post_decision))
}

/// A decision with its poses as `{rotation_xyzw, translation_m}` and the gripper in the world.
pub fn decision_view(d: &grasp::Decision, world_from_reference: &Pose) -> serde_json::Value {
    let mut v = serde_json::to_value(d).unwrap_or_default();
    let pose = |p: &Pose| serde_json::to_value(PoseDto::from_pose(p)).unwrap_or_default();
    v["reference_from_gripper"] = pose(&d.reference_from_gripper);
    v["world_from_gripper"] = pose(&(world_from_reference * d.reference_from_gripper));
    v["grasp"]["object_from_gripper"] = pose(&d.grasp.object_from_gripper);
    if let Some(cands) = v["candidates"].as_array_mut() {
        for (c, r) in cands.iter_mut().zip(&d.candidates) {
            c["grasp"]["object_from_gripper"] = pose(&r.grasp.object_from_gripper);
        }
    }
    v
}

/// Runs a decision for a track (blocking: call from a blocking context).
pub fn decide_blocking(state: &AppState, track_id: u64, req: &DecisionRequest) -> Result<serde_json::Value, ApiError> {
    let gripper_id = req.gripper.as_deref().unwrap_or(super::grippers::DEFAULT_GRIPPER);
    let gripper: Gripper = super::grippers::gripper(state, gripper_id)?;
    let n = req.n_samples.unwrap_or(grasp::decision::DEFAULT_N_SAMPLES);
    if n == 0 || n > MAX_DECISION_SAMPLES {
        return Err(ApiError::Invalid(format!(
            "n_samples must be in 1..={MAX_DECISION_SAMPLES}, got {n}"
        )));
    }
    let threshold = req.threshold.unwrap_or(grasp::decision::DEFAULT_THRESHOLD);
    if !(threshold > 0.0 && threshold <= 1.0) {
        return Err(ApiError::Invalid(format!(
            "threshold must be in (0, 1], got {threshold}"
        )));
    }
    let plane_world = match &req.support_plane {
        Some(p) => Some(validate_plane(p)?),
        None => *state.support_plane.lock().unwrap_or_else(|p| p.into_inner()),
    };
    let grasp_pose = req
        .grasp
        .as_ref()
        .map(|g| g.object_from_gripper.to_pose("grasp.object_from_gripper"))
        .transpose()?;
    let drawn = super::worker::draw_samples(state, track_id, n)?;
    let object = state.grasp_objects.get_or_build(state, &drawn.object_id)?;
    let support_plane = plane_world.map(|p| {
        SupportPlane {
            normal: p.normal,
            point_m: p.point_m,
        }
        .transformed(&drawn.world_from_reference.inverse())
    });
    let query = DecisionQuery {
        n_samples: n,
        threshold,
        grasp: grasp_pose.map(|p| Grasp::from_pose(&object, p, "client")),
        support_plane,
    };
    let d = grasp::decide(&object, &gripper, &drawn.reference_from_object, &drawn.samples, &query)
        .map_err(|e| ApiError::Invalid(format!("decision: {e}")))?;
    let view = decision_view(&d, &drawn.world_from_reference);
    state.metrics.decisions.fetch_add(1, Ordering::Relaxed);
    state.tracking.set_decision(track_id, view.clone());
    state.publish(ServerEvent::Decision {
        track_id,
        decision: view.clone(),
    });
    Ok(view)
}

#[utoipa::path(post, path = "/tracks/{id}/decision", tag = "decisions",
    params(("id" = u64, Path, description = "Track id")),
    request_body = DecisionRequest,
    responses((status = 200, description = "The decision of crate::grasp (verdict, p_success, ci95, reasons, grasp, reference_from_gripper, world_from_gripper)", body = Object),
        (status = 404, body = super::error::Problem), (status = 422, body = super::error::Problem),
        (status = 503, description = "The track has no distribution yet", body = super::error::Problem)))]
async fn post_decision(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ApiJson(req): ApiJson<DecisionRequest>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let id: u64 = id
        .parse()
        .map_err(|_| ApiError::Malformed(format!("track id '{id}' is not a non-negative integer")))?;
    // At most one decision per core at a time (a fair queue), so that a burst of clients
    // neither thrashes the cores nor starves the tracker.
    let _permit = state
        .decision_slots
        .clone()
        .acquire_owned()
        .await
        .map_err(ApiError::internal)?;
    let v = tokio::task::spawn_blocking(move || decide_blocking(&state, id, &req))
        .await
        .map_err(ApiError::internal)??;
    Ok(Json(v))
}
