//! What a decision is made of and kept in: the query ([`DecisionParams`]), the answer with
//! its context ([`DecisionRecord`]), the objects' solid shapes, and the decision cache (the
//! worker's sample banks and the answers shared within one step). `decide` runs them.

use super::ServiceState;
use super::error::ServiceError;
use super::registry::DEFAULT_GRIPPER;
use crate::geometry::{Pose, PoseSamples};
use crate::grasp::{self, GraspObject, SupportPlane};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Most samples a query may ask for.
pub const MAX_DECISION_SAMPLES: usize = 5_000;

/// What a planner asks about a track.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DecisionParams {
    /// Registered gripper id.
    pub gripper: String,
    /// The grasp to check (`object_from_gripper`); `None`: candidates are generated and the
    /// best is taken.
    pub object_from_gripper: Option<Pose>,
    /// The table in the world frame; `None`: the scene's support plane (if any).
    pub support_plane_world: Option<SupportPlane>,
    /// Poses drawn from the distribution.
    pub n_samples: usize,
    /// Grasp only when the lower end of the 95 % Wilson interval on p_success reaches this.
    pub threshold: f64,
}

impl Default for DecisionParams {
    fn default() -> Self {
        Self {
            gripper: DEFAULT_GRIPPER.to_string(),
            object_from_gripper: None,
            support_plane_world: None,
            n_samples: grasp::decision::DEFAULT_N_SAMPLES,
            threshold: grasp::decision::DEFAULT_THRESHOLD,
        }
    }
}

/// A decision with the context it was made in: the stamp of the distribution it used and the
/// frames that place its gripper pose (`decision.reference_from_gripper`, reference = the
/// robot camera) in the robot's base and in the world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionRecord {
    pub decision: grasp::Decision,
    /// Stamp of the estimate whose distribution the samples were drawn from.
    pub stamp_ns: i64,
    pub world_from_reference: Pose,
    /// The reference camera in the robot's base frame (`None` without a robot camera).
    pub base_from_reference: Option<Pose>,
}

impl DecisionRecord {
    /// The gripper in the reference (robot camera) frame.
    pub fn reference_from_gripper(&self) -> Pose {
        self.decision.reference_from_gripper
    }
    /// The gripper in the robot's base frame (`None` without a robot camera).
    pub fn base_from_gripper(&self) -> Option<Pose> {
        self.base_from_reference
            .map(|b| b * self.decision.reference_from_gripper)
    }
    /// The gripper in the world frame.
    pub fn world_from_gripper(&self) -> Pose {
        self.world_from_reference * self.decision.reference_from_gripper
    }
}

/// What the tracker gives a decision: the estimate and samples in the reference frame, with
/// the frames around it at the estimate's time.
#[derive(Clone)]
pub struct Drawn {
    pub track_id: u64,
    pub object_id: String,
    pub stamp_ns: i64,
    pub reference_from_object: Pose,
    pub samples: PoseSamples,
    pub world_from_reference: Pose,
    pub base_from_reference: Option<Pose>,
}

/// Solid shapes per mesh content hash (a convex decomposition takes up to a second; it is
/// built once even when many decisions ask for it at the same time).
#[derive(Default)]
pub struct GraspObjects(Mutex<HashMap<String, Arc<Mutex<Option<GraspObject>>>>>);

impl GraspObjects {
    pub fn get_or_build(&self, state: &ServiceState, object_id: &str) -> Result<GraspObject, ServiceError> {
        let (hash, mesh) = {
            let reg = state.registry();
            let o = reg
                .objects
                .get(object_id)
                .ok_or_else(|| ServiceError::not_found("object", object_id))?;
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
        let g = GraspObject::new(&mesh)?;
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

/// An answer shared within one step: (the bank's generation, the query's key, the answer).
type SharedAnswer = (u64, String, Arc<DecisionRecord>);

/// Decisions without waiting for the tracker: a planner's query reads the bank of samples
/// the worker drew after the latest step (taking the tracker's lock only for a track nobody
/// has asked about yet), and identical queries within one step share one answer.
#[derive(Default)]
pub struct DecisionCache {
    banks: Mutex<HashMap<u64, Arc<SampleBank>>>,
    /// Track -> (last query, most samples asked).
    interest: Mutex<HashMap<u64, (std::time::Instant, usize)>>,
    /// Track -> its last answer.
    answers: Mutex<HashMap<u64, SharedAnswer>>,
}

impl DecisionCache {
    pub(super) fn note_interest(&self, track_id: u64, n: usize) {
        let mut i = self.interest.lock().unwrap_or_else(|p| p.into_inner());
        let e = i.entry(track_id).or_insert((std::time::Instant::now(), n));
        e.0 = std::time::Instant::now();
        e.1 = e.1.max(n);
    }
    /// The latest bank of a track when it holds at least `n` samples.
    pub(super) fn bank(&self, track_id: u64, n: usize) -> Option<Arc<SampleBank>> {
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
    pub(super) fn answer(&self, track_id: u64, generation: u64, key: &str) -> Option<Arc<DecisionRecord>> {
        let a = self.answers.lock().unwrap_or_else(|p| p.into_inner());
        a.get(&track_id)
            .filter(|(g, k, _)| *g == generation && k == key)
            .map(|(_, _, v)| v.clone())
    }
    pub(super) fn store_answer(&self, track_id: u64, generation: u64, key: String, v: Arc<DecisionRecord>) {
        let mut a = self.answers.lock().unwrap_or_else(|p| p.into_inner());
        a.insert(track_id, (generation, key, v));
    }
}
