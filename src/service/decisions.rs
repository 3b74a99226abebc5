//! What a decision is made of and kept in: the query ([`DecisionParams`]), the answer with
//! its context ([`DecisionRecord`]), the objects' solid shapes, and the decision cache (the
//! worker's sample banks and the answers shared within one step). `decide` runs them.

use super::ServiceState;
use super::error::ServiceError;
use super::registry::DEFAULT_GRIPPER;
use crate::geometry::{Pose, PoseSamples};
use crate::grasp::{self, AnswerSmoother, Calibration, CalibrationMap, GraspObject, Gripper, SupportPlane};
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
    /// The threshold of the rule in force (the calibration map's on its quantity, or without
    /// a map the raw rate's Wilson lower bound); `None`: the rule's own threshold.
    pub threshold: Option<f64>,
}

impl Default for DecisionParams {
    fn default() -> Self {
        Self {
            gripper: DEFAULT_GRIPPER.to_string(),
            object_from_gripper: None,
            support_plane_world: None,
            n_samples: grasp::decision::DEFAULT_N_SAMPLES,
            threshold: None,
        }
    }
}

/// A decision with the context it was made in: the stamp of the distribution it used and the
/// frames that place its gripper pose (`decision.reference_from_gripper`, reference = the
/// robot camera) in the robot's base and in the world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionRecord {
    /// The answer, calibrated and smoothed over the track's answers to this question when the
    /// calibration map was fitted for `settings_hash` (`decision.calibration` says which).
    pub decision: grasp::Decision,
    /// The settings hash of the configuration that answered (tracker, the object's codebook
    /// and grid, gripper): what a calibration map must be fitted for.
    #[serde(default)]
    pub settings_hash: String,
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
    /// The estimate's translation spread (what the calibration map's strata read).
    pub translation_std_m: f64,
    pub samples: PoseSamples,
    pub world_from_reference: Pose,
    pub base_from_reference: Option<Pose>,
    /// The reference camera's latest frame showed the object, or the camera is stationary
    /// ([`crate::tracker::Tracker::reference_sees`]); the answer is `observe` when not.
    pub reference_sees: bool,
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
    /// Track -> one answer smoother per question (the query's key with the settings hash):
    /// successive answers about a track are smoothed as the calibration map was fitted.
    smoothers: Mutex<HashMap<u64, HashMap<String, AnswerSmoother>>>,
}

/// Questions smoothed per track; beyond this the track's smoothers start over (a planner
/// asking ever new questions cannot grow the service's memory).
pub const MAX_SMOOTHERS_PER_TRACK: usize = 16;

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
    /// Forgets everything about a track (stopped) or every track (tracker rebuilt): its
    /// banks, shared answers and answer smoothers.
    pub fn forget(&self, track_id: Option<u64>) {
        let mut b = self.banks.lock().unwrap_or_else(|p| p.into_inner());
        let mut a = self.answers.lock().unwrap_or_else(|p| p.into_inner());
        let mut s = self.smoothers.lock().unwrap_or_else(|p| p.into_inner());
        match track_id {
            Some(id) => {
                b.remove(&id);
                a.remove(&id);
                s.remove(&id);
            }
            None => {
                b.clear();
                a.clear();
                s.clear();
            }
        }
    }
    /// Starts a track's answers over (the tracker re-initialised it from a detection): its
    /// past answers were about another distribution.
    pub fn restart_answers(&self, track_id: u64) {
        self.answers.lock().unwrap_or_else(|p| p.into_inner()).remove(&track_id);
        self.smoothers
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&track_id);
    }
    /// Smooths `decision` (taken on the distribution of `stamp_ns`) with the track's smoother
    /// for `question`, made with `calibration`'s time constant on first use.
    pub(super) fn smooth(
        &self,
        track_id: u64,
        question: &str,
        stamp_ns: i64,
        decision: &mut grasp::Decision,
        calibration: &Calibration,
    ) {
        let mut s = self.smoothers.lock().unwrap_or_else(|p| p.into_inner());
        let of_track = s.entry(track_id).or_default();
        if !of_track.contains_key(question) && of_track.len() >= MAX_SMOOTHERS_PER_TRACK {
            of_track.clear();
        }
        of_track
            .entry(question.to_string())
            .or_insert_with(|| calibration.smoother())
            .apply(stamp_ns, decision, calibration);
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

/// The calibration of each running configuration: the service's map (the one shipped with
/// the binary unless `serve --calibration-map` gave another) checked once per settings hash
/// (a gripper, an object's codebook), so that a stale map is logged once, not per answer.
pub struct Calibrations {
    map: Option<Arc<CalibrationMap>>,
    by_hash: Mutex<HashMap<String, Calibration>>,
}

/// Settings hashes remembered by [`Calibrations`] (grippers times codebooks; more start over).
const MAX_CALIBRATIONS: usize = 64;

impl Calibrations {
    pub fn new(map: Option<Arc<CalibrationMap>>) -> Self {
        if map.is_none() {
            tracing::warn!("no grasp calibration map: answers carry the raw rate");
        }
        Self {
            map,
            by_hash: Mutex::new(HashMap::new()),
        }
    }

    /// The calibration for a running configuration's settings hash: the map when it was
    /// fitted for it, else stale (or absent) with the raw rate.
    pub fn for_settings(&self, settings_hash: &str) -> Calibration {
        let mut c = self.by_hash.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(cal) = c.get(settings_hash) {
            return cal.clone();
        }
        if c.len() >= MAX_CALIBRATIONS {
            c.clear();
        }
        let cal = match &self.map {
            Some(m) => Calibration::checked(m.clone(), settings_hash),
            None => Calibration::raw("no calibration map loaded; p_success is the raw rate"),
        };
        c.insert(settings_hash.to_string(), cal.clone());
        cal
    }
}

impl ServiceState {
    /// The settings hash of the configuration answering about `object_id` with `gripper`: the
    /// tracker's settings, the codebook the object is tracked with (its grid: the coarse one
    /// until a finer one is built) and the gripper
    /// ([`crate::eval::calibration::calibration_settings_hash`]).
    pub fn decision_settings_hash(&self, object_id: &str, gripper: &Gripper) -> String {
        let plan = &self.config.codebooks;
        let (codebook, step_deg) = {
            let reg = self.registry();
            let object = reg.objects.get(object_id);
            let built = object.and_then(|o| self.codebooks.get(object_id, &o.info.content_hash, o.info.use_color));
            match (built, object) {
                (Some(cb), _) => (cb.config.clone(), cb.grid.step_deg()),
                (None, o) => (
                    crate::tracker::CodebookConfig {
                        use_color: plan.coarse.use_color && o.is_none_or(|o| o.info.use_color),
                        ..plan.coarse.clone()
                    },
                    plan.coarse_step_deg,
                ),
            }
        };
        crate::eval::calibration::calibration_settings_hash(&self.config.tracker, &codebook, step_deg, gripper)
    }
}
