//! `POST /tracks/{id}/decision`: grasp now or observe more? The request is converted once into
//! the service's [`DecisionParams`]; the answer, a [`DecisionRecord`], into a [`DecisionView`]
//! by the one conversion `From<&DecisionRecord>` below (new fields of `grasp::Decision` are
//! added there).

use super::AppState;
use super::error::ApiError;
use super::scene::PlaneDto;
use super::types::{ApiJson, PoseDto};
use crate::grasp;
use crate::service::decisions::{DecisionParams, DecisionRecord};
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub use crate::service::decisions::MAX_DECISION_SAMPLES;

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
    /// Poses drawn from the distribution (default 1,000, at most 5,000). The calibration map
    /// was fitted on answers of 1,000: fewer give the raw rate, uncalibrated (`calibration`
    /// says so), because a rate of fewer samples is more often high by luck.
    pub n_samples: Option<usize>,
    /// The threshold of the rule in force, in (0, 1]: on the calibrated `p_success` (or its
    /// lower bound) when the service's calibration map fits its settings, else on the lower
    /// end of the raw rate's 95 % Wilson interval. Absent: the rule's own (the map's, e.g.
    /// 0.92; 0.9 without a map). See the operation's description.
    pub threshold: Option<f64>,
}

impl DecisionRequest {
    /// The service's parameters, defaults filled in and poses validated.
    pub fn to_params(&self) -> Result<DecisionParams, ApiError> {
        let defaults = DecisionParams::default();
        Ok(DecisionParams {
            gripper: self.gripper.clone().unwrap_or(defaults.gripper),
            object_from_gripper: self
                .grasp
                .as_ref()
                .map(|g| g.object_from_gripper.to_pose("grasp.object_from_gripper"))
                .transpose()?,
            support_plane_world: self.support_plane.map(grasp::SupportPlane::from),
            n_samples: self.n_samples.unwrap_or(defaults.n_samples),
            threshold: self.threshold.or(defaults.threshold),
        })
    }
}

/// The answer: grasp now, or look more.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Grasp,
    Observe,
}

/// The tests run on every sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FailureTest {
    /// The open gripper hits the object on its way in.
    Approach,
    /// A gripper part comes closer to the support plane than the clearance.
    Table,
    /// Closing does not bring both pads onto the object first.
    Contact,
    /// A pad contact lies outside the capture funnel (groove mouth / wall angle).
    Alignment,
}

/// Translation or rotation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Motion {
    Translation,
    Rotation,
}

/// One direction of the pose uncertainty, in the gripper frame of the planned grasp.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AxisDriver {
    pub motion: Motion,
    /// `gripper_x`, `gripper_y` or `gripper_z` (x = closing, z = approach).
    pub axis: String,
    /// The same axis in the reference (robot camera) frame.
    pub axis_in_reference: [f64; 3],
    /// The same axis in the object's frame at the estimate.
    pub axis_in_object: [f64; 3],
    /// Standard deviation of the samples' offset from the estimate along/about this axis
    /// (metres or radians).
    pub spread: f64,
    /// How much of the uncertainty about failing this axis explains (0: independent, 1: the
    /// offset decides).
    pub failure_dependence: f64,
}

/// The share of samples failing one test and what drives it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Reason {
    pub test: FailureTest,
    pub failure_share: f64,
    /// Axes on whose offsets this failure depends, strongest first.
    pub drivers: Vec<AxisDriver>,
    pub message: String,
}

/// A grasp: where the gripper frame sits on the object (approach along gripper +z, closing
/// along x).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct GraspView {
    pub object_from_gripper: PoseDto,
    /// Approach direction (gripper +z) in the object frame.
    pub approach_in_object: [f64; 3],
    /// Closing axis (gripper x) in the object frame.
    pub closing_in_object: [f64; 3],
    /// Depth of the tool centre point past the object's surface that faces the palm.
    pub depth_m: f64,
    /// Width of the object's hull along the closing axis.
    pub width_m: f64,
    /// Human-readable name, e.g. `approach -a2, close a1` (a0 = longest principal axis);
    /// ending in `, placed` when the grasp was moved from the hull's centre to where pose noise
    /// fails it least.
    pub label: String,
}

/// A candidate grasp with its probability of success.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct RankedGrasp {
    pub grasp: GraspView,
    pub p_success: f64,
    pub ci95: [f64; 2],
    /// Samples it was evaluated on (fewer when screened out early).
    pub n_samples: usize,
}

/// Whether `p_success` went through a calibration map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationState {
    /// Through the map fitted for the running settings.
    Calibrated,
    /// The service's map was fitted for other settings (tracker, codebook, grid or gripper)
    /// and is refused: `p_success` is the raw rate, the rule the one without a map. Refit the
    /// map (`scripts/calibrate.sh`).
    Stale,
    /// No map: `p_success` is the raw rate, the rule the one without a map.
    Absent,
}

/// The calibration behind `p_success`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CalibrationView {
    pub state: CalibrationState,
    /// The settings hash the service's map was fitted for (absent without a map).
    pub map_settings_hash: Option<String>,
    /// The settings hash of the configuration that answered (tracker, the object's codebook
    /// and grid, gripper); the map is applied only when it equals `map_settings_hash`.
    pub running_settings_hash: String,
    /// Why the map was not applied (absent when calibrated).
    pub message: Option<String>,
}

/// What the rule compares with its threshold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum RuleQuantity {
    /// The calibrated `p_success`.
    Calibrated,
    /// The lower end of `ci95` (calibrated; never chosen by `pregrasp calibrate`, whose folds'
    /// maps are less certain than the map fitted on all the data).
    CalibratedLower,
    /// The lower end of `ci95_raw`, the raw rate's Wilson interval (the rule without a map).
    RawLower,
    /// The calibrated probability of the lower end of `ci95_raw`: the map's estimate, cautious
    /// for the samples drawn.
    CalibratedAtRawLower,
    /// `smoothing.p_success_raw_smoothed`, the raw rate smoothed over the track's answers. The
    /// map is monotone, so this threshold is one on `p_success` too, placed between the map's
    /// steps (`grasp` exactly where the calibrated probability is at least the map's value at
    /// the threshold).
    Raw,
}

/// The rule that gave `decision`: `grasp` when `quantity >= threshold` in `run_length`
/// successive answers about the track (answers on one tracker step count once).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct RuleView {
    pub quantity: RuleQuantity,
    pub threshold: f64,
    pub run_length: u32,
    /// The quantity's value in this answer (`grasp` needs it at or above `threshold` in
    /// `run_length` successive answers).
    pub value: f64,
}

/// How successive answers about the track were smoothed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SmoothingView {
    /// Time constant of the exponential average of the raw rate, seconds (0: this answer
    /// alone).
    pub time_constant_s: f64,
    /// The smoothed raw rate that the map was applied to.
    pub p_success_raw_smoothed: f64,
    /// This answer's own `p_success` before smoothing (calibrated when `calibration` says so).
    pub p_success_unsmoothed: f64,
    /// The smoothed translation spread of the track (m) that chose the map's stratum (absent:
    /// the map's pooled fit was read).
    pub translation_std_m_smoothed: Option<f64>,
    /// Successive answers, this one included, whose quantity reached the threshold.
    pub run: u32,
}

/// A decision with its context: the stamp of the distribution it used and the gripper pose in
/// the reference (robot camera), robot base and world frames.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct DecisionView {
    pub decision: Verdict,
    /// The probability that the grasp succeeds: the calibration map applied to the raw rate
    /// smoothed over the track's recent answers when `calibration.state` is `calibrated`;
    /// otherwise the raw rate itself.
    pub p_success: f64,
    /// 95 % interval of `p_success` (calibrated: the smoothed raw interval through the map,
    /// widened by the fit's own uncertainty; otherwise `ci95_raw`).
    pub ci95: [f64; 2],
    /// This answer's share of the samples on which the grasp succeeds (the samples with their
    /// rotation offsets within the estimate's mode halved: see the decision's description).
    pub p_success_raw: f64,
    /// 95 % Wilson interval on `p_success_raw` over the effective sample size.
    pub ci95_raw: [f64; 2],
    /// The track's translation spread (m, RMS distance of its particles from their mean) at
    /// this answer: the map is fitted apart for tight and loose tracks.
    pub translation_std_m: Option<f64>,
    /// `false` when the reference (robot) camera's latest frame did not show the object (it
    /// looks away): its pose in that frame then rests on odometry and the robot's localisation, and
    /// the answer is `observe` whatever `p_success` says (held out, such answers of a high
    /// raw rate failed several times as often as the others). A stationary reference camera
    /// always counts as seeing.
    pub reference_sees: bool,
    pub calibration: CalibrationView,
    pub rule: RuleView,
    pub smoothing: SmoothingView,
    pub n_samples: usize,
    pub effective_sample_size: f64,
    /// The rule's threshold (`rule.threshold`).
    pub threshold: f64,
    /// Stamp of the estimate whose distribution the samples were drawn from, nanoseconds.
    pub stamp_ns: i64,
    pub grasp: GraspView,
    /// The gripper in the reference (robot camera) frame.
    pub reference_from_gripper: PoseDto,
    /// The gripper in the robot's base frame (absent without a robot camera).
    pub base_from_gripper: Option<PoseDto>,
    /// The gripper in the world frame.
    pub world_from_gripper: PoseDto,
    /// One entry per test that fails on some sample, largest share first.
    pub reasons: Vec<Reason>,
    /// All six axes (3 translations, 3 rotations) with the dependence of failing on them,
    /// strongest first.
    pub uncertainty: Vec<AxisDriver>,
    /// The candidates evaluated (only when the query gave no grasp), best first.
    pub candidates: Vec<RankedGrasp>,
}

impl From<&grasp::AxisDriver> for AxisDriver {
    fn from(a: &grasp::AxisDriver) -> Self {
        Self {
            motion: match a.motion {
                grasp::Motion::Translation => Motion::Translation,
                grasp::Motion::Rotation => Motion::Rotation,
            },
            axis: a.axis.clone(),
            axis_in_reference: a.axis_in_reference,
            axis_in_object: a.axis_in_object,
            spread: a.spread,
            failure_dependence: a.failure_dependence,
        }
    }
}

impl From<&grasp::Reason> for Reason {
    fn from(r: &grasp::Reason) -> Self {
        Self {
            test: match r.test {
                grasp::FailureTest::Approach => FailureTest::Approach,
                grasp::FailureTest::Table => FailureTest::Table,
                grasp::FailureTest::Contact => FailureTest::Contact,
                grasp::FailureTest::Alignment => FailureTest::Alignment,
            },
            failure_share: r.failure_share,
            drivers: r.drivers.iter().map(AxisDriver::from).collect(),
            message: r.message.clone(),
        }
    }
}

impl From<&grasp::Grasp> for GraspView {
    fn from(g: &grasp::Grasp) -> Self {
        Self {
            object_from_gripper: PoseDto::from_pose(&g.object_from_gripper),
            approach_in_object: g.approach_in_object,
            closing_in_object: g.closing_in_object,
            depth_m: g.depth_m,
            width_m: g.width_m,
            label: g.label.clone(),
        }
    }
}

impl From<&grasp::RankedGrasp> for RankedGrasp {
    fn from(r: &grasp::RankedGrasp) -> Self {
        Self {
            grasp: (&r.grasp).into(),
            p_success: r.p_success,
            ci95: r.ci95,
            n_samples: r.n_samples,
        }
    }
}

impl CalibrationView {
    fn new(status: &grasp::CalibrationStatus, running_settings_hash: &str) -> Self {
        let state = match status {
            grasp::CalibrationStatus::Calibrated { .. } => CalibrationState::Calibrated,
            grasp::CalibrationStatus::Stale { .. } => CalibrationState::Stale,
            grasp::CalibrationStatus::Absent { .. } => CalibrationState::Absent,
        };
        Self {
            state,
            map_settings_hash: status.map_settings_hash().map(str::to_string),
            running_settings_hash: running_settings_hash.to_string(),
            message: status.warning().map(str::to_string),
        }
    }
}

impl RuleView {
    fn new(r: &grasp::GraspRule, value: f64) -> Self {
        Self {
            quantity: match r.quantity {
                grasp::RuleQuantity::Calibrated => RuleQuantity::Calibrated,
                grasp::RuleQuantity::CalibratedLower => RuleQuantity::CalibratedLower,
                grasp::RuleQuantity::RawLower => RuleQuantity::RawLower,
                grasp::RuleQuantity::CalibratedAtRawLower => RuleQuantity::CalibratedAtRawLower,
                grasp::RuleQuantity::Raw => RuleQuantity::Raw,
            },
            threshold: r.threshold,
            run_length: r.run_length,
            value,
        }
    }
}

impl SmoothingView {
    /// The decision's smoothing, or for an answer that was not smoothed, itself alone.
    fn new(d: &grasp::Decision) -> Self {
        match &d.smoothing {
            Some(s) => Self {
                time_constant_s: s.time_constant_s,
                p_success_raw_smoothed: s.p_success_raw_smoothed,
                p_success_unsmoothed: s.p_success_unsmoothed,
                translation_std_m_smoothed: s.translation_std_m_smoothed,
                run: s.run,
            },
            None => Self {
                time_constant_s: 0.0,
                p_success_raw_smoothed: d.p_success_raw,
                p_success_unsmoothed: d.p_success,
                translation_std_m_smoothed: d.translation_std_m,
                run: u32::from(d.decision == grasp::Verdict::Grasp),
            },
        }
    }
}

/// The one conversion of a decision into its answer.
impl From<&DecisionRecord> for DecisionView {
    fn from(r: &DecisionRecord) -> Self {
        let d = &r.decision;
        Self {
            decision: match d.decision {
                grasp::Verdict::Grasp => Verdict::Grasp,
                grasp::Verdict::Observe => Verdict::Observe,
            },
            p_success: d.p_success,
            ci95: d.ci95,
            p_success_raw: d.p_success_raw,
            ci95_raw: d.ci95_raw,
            translation_std_m: d.translation_std_m,
            reference_sees: d.reference_sees,
            calibration: CalibrationView::new(&d.calibration, &r.settings_hash),
            rule: RuleView::new(&d.rule, d.rule_value),
            smoothing: SmoothingView::new(d),
            n_samples: d.n_samples,
            effective_sample_size: d.effective_sample_size,
            threshold: d.threshold,
            stamp_ns: r.stamp_ns,
            grasp: (&d.grasp).into(),
            reference_from_gripper: PoseDto::from_pose(&r.reference_from_gripper()),
            base_from_gripper: r.base_from_gripper().as_ref().map(PoseDto::from_pose),
            world_from_gripper: PoseDto::from_pose(&r.world_from_gripper()),
            reasons: d.reasons.iter().map(Reason::from).collect(),
            uncertainty: d.uncertainty.iter().map(AxisDriver::from).collect(),
            candidates: d.candidates.iter().map(RankedGrasp::from).collect(),
        }
    }
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(post_decision))
}

/// Grasp now, or look more?
///
/// Poses drawn from the track's distribution are checked against the gripper: the candidates
/// are ranked on them as drawn, and the chosen grasp is scored on the same samples with every
/// rotation offset within 0.5 rad of the estimate halved along its geodesic (other modes, such
/// as a handle's other turn, kept). Where grasps are decided the tracked rotation spread is
/// wider than the error, and on held-out sequences that rate tells succeeding grasps from
/// failing ones better. `p_success_raw` is the share of those samples on which the grasp
/// succeeds, with its 95 % Wilson interval `ci95_raw` over the samples' effective sample size
/// (ESS, at most the tracker's particles however many samples are drawn); it is not a
/// probability until the map below reads it.
///
/// **Calibrated (`calibration.state` = `calibrated`)**: the service's calibration map was fitted
/// (`scripts/calibrate.sh`) for the settings hash of the configuration answering
/// (`calibration.running_settings_hash`). Successive answers about the track are smoothed: an
/// answer `dt` seconds after the last moves the smoothed raw rate `r` by the weight
/// `w = 1 - exp(-dt / smoothing.time_constant_s)`, `r <- r + w * (p_success_raw - r)`, and
/// the ends of `ci95_raw` likewise (with the shipped map's 0.5 s and a step every 0.2 s, `w` =
/// 0.33: a raw rate jumping between 0.62 and 0.95 moves `r` by 0.33 * 0.33 / (2 - 0.33) = 0.065
/// per answer; a planner asking once a second gets `w` = 0.86, its answers hardly smoothed).
/// `p_success` is the map at `r`: the isotonic fit of the outcome on the true pose against the
/// smoothed raw rate on generated sequences, linear between its blocks' (mean raw rate,
/// observed success rate) points. The shipped map reads (0.7984, 0.9016), (0.8841, 0.9501),
/// (0.9461, 0.9643), (0.9563, 0.9667), (0.9579, 0.9833), (0.9672, 0.9887): at r = 0.95,
/// `p_success` = 0.9643 + (0.95 - 0.9461) / (0.9563 - 0.9461) * (0.9667 - 0.9643) = 0.9652.
/// The answer is `grasp` when `rule.quantity` reaches `rule.threshold` in `rule.run_length`
/// successive answers (answers on one tracker step count once; `smoothing.run` counts them;
/// `rule.value` is the quantity's value). The shipped rule is `calibrated_at_raw_lower >=
/// 0.93` in 1 answer: the map read at the lower end of the smoothed `ci95_raw`, which the map
/// lifts to 0.93 from 0.8486. With the samples' ESS at 60 (a near track's particles), r = 0.94
/// has its Wilson lower end at 0.8495, where the map reads 0.9305: `grasp`; r = 0.935 has
/// 0.8429 (0.9268): `observe`. At ESS 300, r = 0.889 is enough: the fewer independent samples
/// behind a rate, the more the rule asks of it. Of the fitting data's answers with a given
/// `p_success`, about that share succeeded on the true pose; `ci95` is the smoothed raw
/// interval through the map, widened by the map's own uncertainty (its blocks' Wilson
/// intervals). The rule was chosen by its failures on the fitting approaches' out-of-fold
/// answers (each quarter answered by a map fitted on the other three): at most 1 % of its
/// `grasp` answers failing in at least 80 % of resamples of the approaches, at most one of
/// their 224 first `grasp` answers failing, then the highest recall within 1.2 m. On the
/// fitting data 0.75 % of its answers failed out of fold (1 % kept in 88 % of the resamples,
/// 1 first `grasp` failing); on 128 approaches it never saw (seeds 2500 and 2700), 0.64 % (20
/// of 3,110), and 2 of their 79 first `grasp` answers failed (one a sugar box tracked 20
/// degrees and 2 cm off).
///
/// **Stale or absent map (`calibration.state` = `stale` / `absent`)**: `p_success` is the raw
/// rate itself, `ci95` its Wilson interval, nothing is smoothed, and the rule is the one before
/// calibration: `grasp` when the lower end of `ci95_raw` reaches `threshold` (default 0.9). That
/// needs a sampled rate of at least 0.956 at ESS 110, 0.983 at ESS 50, 0.942 at ESS 200: the
/// rule is conservative by construction, and an answer of `observe` with `p_success` near 0.9
/// means "not sure enough yet", not "will fail". A stale map is never applied: its probabilities
/// describe another tracker.
#[utoipa::path(post, path = "/tracks/{id}/decision", tag = "decisions",
    params(("id" = u64, Path, description = "Track id")),
    request_body = DecisionRequest,
    responses((status = 200, description = "The decision with the stamp of the distribution it used and the gripper in the reference, base and world frames", body = DecisionView),
        (status = 404, description = "No such track or gripper", body = super::error::Problem),
        (status = 409, description = "No grasp of this gripper fits the object, or its mesh cannot be grasped", body = super::error::Problem),
        (status = 422, body = super::error::Problem),
        (status = 503, description = "The track has no distribution yet", body = super::error::Problem)))]
async fn post_decision(
    State(state): State<AppState>,
    Path(id): Path<String>,
    ApiJson(req): ApiJson<DecisionRequest>,
) -> Result<Json<DecisionView>, ApiError> {
    let id: u64 = id
        .parse()
        .map_err(|_| ApiError::Malformed(format!("track id '{id}' is not a non-negative integer")))?;
    let params = req.to_params()?;
    // At most one decision per core at a time (a fair queue), so that a burst of clients
    // neither thrashes the cores nor starves the tracker.
    let _permit = state
        .decision_slots
        .clone()
        .acquire_owned()
        .await
        .map_err(ApiError::internal)?;
    let service = state.service.clone();
    let record = tokio::task::spawn_blocking(move || service.decide(id, &params))
        .await
        .map_err(ApiError::internal)??;
    Ok(Json(DecisionView::from(&*record)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Pose, PoseSamples};
    use crate::grasp::calibrated::{CalibrationMap, GraspRule, IsotonicBlock, MAP_VERSION};
    use std::sync::Arc;

    /// The answer about a can sampled exactly at its estimate (raw rate 1), through `calibration`.
    fn record(calibration: &grasp::Calibration, running: &str) -> DecisionRecord {
        let object = grasp::GraspObject::new(&crate::mesh::builtin("can").expect("can")).expect("solid");
        let gripper = grasp::Gripper::default_parallel_jaw();
        let estimate = Pose::translation(0.0, 0.0, 0.6);
        let samples = PoseSamples {
            poses: vec![estimate; 50],
            effective_sample_size: 50.0,
        };
        let query = grasp::DecisionQuery {
            n_samples: 50,
            threshold: calibration.rule().threshold,
            grasp: None,
            support_plane: None,
            translation_std_m: None,
            reference_sees: true,
        };
        let mut d =
            grasp::decide_calibrated(&object, &gripper, &estimate, &samples, &query, calibration).expect("decision");
        calibration.smoother().apply(0, &mut d, calibration);
        DecisionRecord {
            decision: d,
            settings_hash: running.into(),
            stamp_ns: 0,
            world_from_reference: Pose::identity(),
            base_from_reference: None,
        }
    }

    #[test]
    fn the_answer_names_its_calibration_and_rule() {
        let map = CalibrationMap {
            version: MAP_VERSION,
            settings_hash: "fitted".into(),
            settings: serde_json::json!({}),
            fitted_at: "2026-12-02T00:00:00Z".into(),
            fitted_on: vec!["test".into()],
            n_decisions: 100,
            n_successes: 90,
            n_approaches: 1,
            n_samples: None,
            blocks: vec![IsotonicBlock {
                raw_lo: 0.0,
                raw_hi: 1.0,
                raw_mean: 0.5,
                count: 100,
                successes: 90,
            }],
            rule: GraspRule {
                quantity: grasp::RuleQuantity::Calibrated,
                threshold: 0.85,
                run_length: 2,
            },
            smoothing_time_constant_s: 1.5,
            min_block_count: 20,
            spread_strata: Vec::new(),
        };
        let map = Arc::new(map);

        let fitted = DecisionView::from(&record(&grasp::Calibration::checked(map.clone(), "fitted"), "fitted"));
        assert_eq!(fitted.calibration.state, CalibrationState::Calibrated);
        assert_eq!(fitted.calibration.map_settings_hash.as_deref(), Some("fitted"));
        assert_eq!(fitted.calibration.running_settings_hash, "fitted");
        assert_eq!(fitted.calibration.message, None);
        assert_eq!((fitted.p_success, fitted.p_success_raw), (0.9, 1.0));
        assert_eq!(
            fitted.rule,
            RuleView {
                quantity: RuleQuantity::Calibrated,
                threshold: 0.85,
                run_length: 2,
                // the calibrated probability itself
                value: 0.9,
            }
        );
        assert_eq!((fitted.smoothing.time_constant_s, fitted.smoothing.run), (1.5, 1));
        // one answer over the threshold is not yet the run of two
        assert_eq!(fitted.decision, Verdict::Observe);

        let stale = DecisionView::from(&record(&grasp::Calibration::checked(map, "running"), "running"));
        assert_eq!(stale.calibration.state, CalibrationState::Stale);
        assert_eq!(stale.calibration.map_settings_hash.as_deref(), Some("fitted"));
        assert_eq!(stale.calibration.running_settings_hash, "running");
        assert!(
            stale
                .calibration
                .message
                .as_deref()
                .is_some_and(|m| m.contains("refit"))
        );
        assert_eq!((stale.p_success, stale.p_success_raw), (1.0, 1.0));
        assert_eq!(stale.rule.quantity, RuleQuantity::RawLower);
        assert_eq!(stale.smoothing.time_constant_s, 0.0);
        // the raw rule: the Wilson lower bound of 50 of 50 successes is 0.929 >= 0.9
        assert_eq!(stale.decision, Verdict::Grasp);

        let absent = DecisionView::from(&record(&grasp::Calibration::raw("no map"), "running"));
        assert_eq!(absent.calibration.state, CalibrationState::Absent);
        assert_eq!(absent.calibration.map_settings_hash, None);
    }
}
