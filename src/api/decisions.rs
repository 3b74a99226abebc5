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
    /// Grasp only when the lower end of the 95 % Wilson interval on p_success (over the
    /// samples' effective sample size) reaches this (default 0.9; see the operation's description).
    pub threshold: Option<f64>,
}

/// What the tracker gives a decision: the estimate and samples in the reference frame.
#[derive(Clone)]
pub struct Drawn {
    pub track_id: u64,
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

/// How long a track stays "watched" after a decision query: while watched, the tracking
/// worker draws a bank of samples for it right after every step.
pub const BANK_INTEREST: std::time::Duration = std::time::Duration::from_secs(30);

/// Samples drawn by the tracking worker right after a step (`generation` = its step count).
pub struct SampleBank {
    pub generation: u64,
    pub drawn: Drawn,
}

/// Decisions without waiting for the tracker: a planner's query reads the bank of samples
/// the worker drew after the latest step (taking the tracker's lock only for a track nobody
/// has asked about yet), and identical queries within one step share one answer.
#[derive(Default)]
pub struct DecisionCache {
    banks: Mutex<HashMap<u64, Arc<SampleBank>>>,
    /// Track -> (last query, most samples asked).
    interest: Mutex<HashMap<u64, (std::time::Instant, usize)>>,
    /// Track -> (generation, query key, answer).
    answers: Mutex<HashMap<u64, (u64, String, serde_json::Value)>>,
}

impl DecisionCache {
    fn note_interest(&self, track_id: u64, n: usize) {
        let mut i = self.interest.lock().unwrap_or_else(|p| p.into_inner());
        let e = i.entry(track_id).or_insert((std::time::Instant::now(), n));
        e.0 = std::time::Instant::now();
        e.1 = e.1.max(n);
    }
    /// The latest bank of a track when it holds at least `n` samples.
    fn bank(&self, track_id: u64, n: usize) -> Option<Arc<SampleBank>> {
        let b = self.banks.lock().unwrap_or_else(|p| p.into_inner());
        b.get(&track_id).filter(|b| b.drawn.samples.poses.len() >= n).cloned()
    }
    /// Tracks watched now, with the samples to draw for each (forgets the stale ones).
    pub fn watched(&self) -> Vec<(u64, usize)> {
        let mut i = self.interest.lock().unwrap_or_else(|p| p.into_inner());
        i.retain(|_, (t, _)| t.elapsed() < BANK_INTEREST);
        i.iter().map(|(k, (_, n))| (*k, *n)).collect()
    }
    /// Replaces the banks (the worker, after a step); tracks not given lose theirs.
    pub fn set_banks(&self, banks: Vec<SampleBank>) {
        let mut b = self.banks.lock().unwrap_or_else(|p| p.into_inner());
        b.clear();
        for bank in banks {
            b.insert(bank.drawn.track_id, Arc::new(bank));
        }
    }
    /// Forgets everything about a track (stopped) or every track (tracker rebuilt).
    pub fn forget(&self, track_id: Option<u64>) {
        let mut b = self.banks.lock().unwrap_or_else(|p| p.into_inner());
        let mut a = self.answers.lock().unwrap_or_else(|p| p.into_inner());
        match track_id {
            Some(id) => {
                b.remove(&id);
                a.remove(&id);
            }
            None => {
                b.clear();
                a.clear();
            }
        }
    }
    fn answer(&self, track_id: u64, generation: u64, key: &str) -> Option<serde_json::Value> {
        let a = self.answers.lock().unwrap_or_else(|p| p.into_inner());
        a.get(&track_id)
            .filter(|(g, k, _)| *g == generation && k == key)
            .map(|(_, _, v)| v.clone())
    }
    fn store_answer(&self, track_id: u64, generation: u64, key: String, v: serde_json::Value) {
        let mut a = self.answers.lock().unwrap_or_else(|p| p.into_inner());
        a.insert(track_id, (generation, key, v));
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
    if !state.tracking.board().views.contains_key(&track_id) {
        return Err(ApiError::not_found("track", track_id.to_string()));
    }
    state.decision_cache.note_interest(track_id, n);
    let bank = state.decision_cache.bank(track_id, n);
    // identical queries within one step share one answer (the samples are the same)
    let key = serde_json::to_string(&(req, &gripper)).unwrap_or_default();
    if let Some(b) = &bank
        && let Some(v) = state.decision_cache.answer(track_id, b.generation, &key)
    {
        state.metrics.decisions.fetch_add(1, Ordering::Relaxed);
        state.metrics.decisions_from_bank.fetch_add(1, Ordering::Relaxed);
        state.metrics.decisions_shared.fetch_add(1, Ordering::Relaxed);
        return Ok(v);
    }
    let drawn = match &bank {
        Some(b) => {
            state.metrics.decisions_from_bank.fetch_add(1, Ordering::Relaxed);
            let mut d = b.drawn.clone();
            d.samples.poses.truncate(n);
            d.samples.effective_sample_size = d.samples.effective_sample_size.min(n as f64);
            d
        }
        None => super::worker::draw_samples(state, track_id, n)?,
    };
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
    if let Some(b) = &bank {
        state
            .decision_cache
            .store_answer(track_id, b.generation, key, view.clone());
    }
    state.metrics.decisions.fetch_add(1, Ordering::Relaxed);
    state.tracking.set_decision(track_id, view.clone());
    state.publish(ServerEvent::Decision {
        track_id,
        decision: view.clone(),
    });
    Ok(view)
}

/// Grasp now, or look more?
///
/// Poses drawn from the track's distribution are checked against the gripper; `p_success` is
/// the share of samples on which the grasp succeeds. The answer is `grasp` when the lower end
/// of the 95 % Wilson interval on `p_success`, taken over the samples' effective sample size
/// (ESS, at most the tracker's 110 particles however many samples are drawn), reaches
/// `threshold`. With the default 0.9 that needs a sampled rate of at least 0.956 at ESS 110,
/// 0.983 at ESS 50, 0.942 at ESS 200: the rule is conservative by construction, and an
/// answer of `observe` with `p_success` near 0.9 means "not sure enough yet", not "will fail".
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
