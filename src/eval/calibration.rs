//! Calibration of the grasp decision against the outcome on the true pose (`eval --decide`):
//! reliability per decile of predicted `p_success`, expected calibration error (overall, per
//! object, and leaving each object out), the Brier score beside the base-rate predictor's,
//! the grasp rate and false grasp rate (`grasp::calibration` computes those); recall within
//! reach; and per approach (one sequence's target) the first `grasp`: where it came and
//! whether it fails on the truth, with a Wilson upper bound on the per-approach failure rate.

use super::report::{DecisionBlock, FirstGrasp, ObjectDecisions, ReliabilityBin};
use crate::grasp::Gripper;
use crate::grasp::calibration::{CalibrationRecord, calibration_report, wilson_upper_95};
use crate::tracker::{CodebookConfig, TrackerConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Recall counts the frames where the robot camera is at most this far from the object (m):
/// close enough that a grasp is worth answering.
pub const RECALL_MAX_DISTANCE_M: f64 = 1.2;

/// One decision at one frame and its outcome on the true pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionOutcome {
    pub sequence: String,
    pub object: String,
    pub frame_id: u32,
    /// The reference camera's stamp of the step (ns); 0 in records of older runs.
    #[serde(default)]
    pub stamp_ns: i64,
    /// The answer's `p_success` (calibrated when the run had a map for its settings).
    pub p_success: f64,
    /// The decision said `grasp`.
    pub grasp: bool,
    /// The planned grasp succeeds on the true pose.
    pub success: bool,
    /// Which of the grasp's tests pass on the true pose (the approach, the table, the
    /// contact and the alignment): why a failing grasp fails. `None` in records of older runs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth_tests: Option<crate::grasp::PoseOutcome>,
    /// Distance from the robot camera (the reference camera in a rig without one) to the
    /// object's true position (m); `None` where the truth does not say.
    pub camera_distance_m: Option<f64>,
    /// What the distribution alone says at that frame (no truth): the inputs of a
    /// calibration fit. `None` in records of older runs.
    #[serde(default)]
    pub features: Option<DecisionFeatures>,
}

/// The raw answer and the distribution's own measures at one decision (nothing from the
/// truth), kept per frame so that a calibration map and a rule can be refitted without
/// running the tracker again.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionFeatures {
    /// Share of the samples on which the chosen grasp succeeds.
    pub p_raw: f64,
    /// Effective sample size of the samples (the tracker's particle weights).
    pub effective_sample_size: f64,
    /// The same decision on a second, independent draw of samples from the same tracker
    /// state: the spread that sampling and the choice of candidate alone cause.
    pub p_raw_repeat: Option<f64>,
    /// The second draw chose the same grasp candidate.
    pub repeat_same_grasp: Option<bool>,
    /// Label of the chosen candidate (a switch between frames moves p on its own).
    pub grasp_label: String,
    /// Mass of the largest rotation mode.
    pub top_mode_mass: Option<f64>,
    /// Entropy (nats) of the rotation histogram.
    pub rotation_entropy: f64,
    /// Cameras that gave evidence in the step.
    pub views_seeing: usize,
    /// The reference camera's latest frame showed the object, or the camera is stationary
    /// ([`crate::tracker::Tracker::reference_sees`]); the rule answers `observe` when not.
    /// `None` in records of older runs (no such check).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference_sees: Option<bool>,
    /// Distance from the reference camera to the *estimated* position (m).
    pub estimated_distance_m: f64,
    /// RMS distance of the particles from their mean (m).
    pub translation_std_m: f64,
}

/// The settings a calibration map is fitted for: the tracker's (its seed and the service's cap
/// on tracks per object left out: neither changes how a track's distribution behaves), the
/// codebooks', the rotation grid, the gripper and the decision's procedure
/// ([`crate::grasp::decision::DECISION_PROCEDURE_VERSION`]). Their hash
/// ([`crate::grasp::calibrated::settings_hash`]) is stored with the map. The number of samples
/// per decision is not part of them: the raw rate estimates the same share whatever the number.
pub fn calibration_settings(
    tracker: &TrackerConfig,
    codebook: &CodebookConfig,
    grid_step_deg: u32,
    gripper: &Gripper,
) -> serde_json::Value {
    let mut tracker = tracker.clone();
    tracker.seed = 0;
    tracker.max_tracks_per_object = 0;
    let mut codebook = codebook.clone();
    codebook.seed = 0;
    let mut tracker = serde_json::to_value(&tracker).unwrap_or_default();
    // settings added after the shipped map was fitted are left out at their defaults: that
    // map was fitted with the verification and the near blur off, where they have no effect
    let defaults = serde_json::to_value(TrackerConfig::default()).unwrap_or_default();
    for (parent, key) in [
        ("/verification", "occlusion_truncation"),
        ("/verification", "min_view_change_deg"),
        ("/verification", "min_object_px"),
        ("", "near_blur"),
    ] {
        let default = defaults.pointer(parent).and_then(|d| d.get(key)).cloned();
        if let Some(v) = tracker.pointer_mut(parent).and_then(|v| v.as_object_mut())
            && v.get(key).cloned() == default
        {
            v.remove(key);
        }
    }
    serde_json::json!({
        "tracker": tracker,
        "codebook": codebook,
        "grid_step_deg": grid_step_deg,
        "gripper": gripper,
        "decision_version": crate::grasp::decision::DECISION_PROCEDURE_VERSION,
    })
}

/// The hash of [`calibration_settings`]: what a running tracker compares with a map's.
pub fn calibration_settings_hash(
    tracker: &TrackerConfig,
    codebook: &CodebookConfig,
    grid_step_deg: u32,
    gripper: &Gripper,
) -> String {
    crate::grasp::calibrated::settings_hash(&calibration_settings(tracker, codebook, grid_step_deg, gripper))
}

/// The settings hash of `serve` as it tracks by default once its finer codebooks are built (the
/// default tracker, the full codebook on the 5-degree grid, the built-in gripper): the shipped
/// map must be fitted for it. Until an object's finer codebook is ready its answers carry the
/// raw rate and say `stale`.
pub fn service_settings_hash() -> String {
    calibration_settings_hash(
        &TrackerConfig::default(),
        &CodebookConfig::default(),
        SERVICE_GRID_STEP_DEG,
        &Gripper::default_parallel_jaw(),
    )
}

/// The grid `serve` tracks on by default once an object's finer codebook is built
/// (`--codebook-step-deg`'s default).
pub const SERVICE_GRID_STEP_DEG: u32 = 5;

/// `decisions.json` of an `eval --decide` run: every decision with its raw answer, the
/// distribution's measures and the outcome on the truth, and the settings they came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionRecords {
    pub settings_hash: String,
    pub settings: serde_json::Value,
    /// The data set evaluated (as given on the command line).
    pub data: String,
    /// Pose samples each decision drew (`eval --samples`); runs from before it was recorded
    /// drew eval's default.
    #[serde(default = "default_record_samples")]
    pub n_samples: usize,
    pub decisions: Vec<DecisionOutcome>,
}

fn default_record_samples() -> usize {
    crate::grasp::decision::DEFAULT_N_SAMPLES
}

fn records<'a>(outcomes: impl Iterator<Item = &'a DecisionOutcome>) -> Vec<CalibrationRecord> {
    outcomes
        .map(|o| CalibrationRecord {
            p_success: o.p_success,
            decided_grasp: o.grasp,
            succeeded: o.success,
        })
        .collect()
}

/// Recall within reach: of the frames whose grasp succeeds on the true pose with the robot
/// camera within [`RECALL_MAX_DISTANCE_M`], the share answered `grasp`; with that count.
pub fn recall<'a>(outcomes: impl IntoIterator<Item = &'a DecisionOutcome>) -> (Option<f64>, usize) {
    let eligible: Vec<&DecisionOutcome> = outcomes
        .into_iter()
        .filter(|o| o.success && o.camera_distance_m.is_some_and(|d| d <= RECALL_MAX_DISTANCE_M))
        .collect();
    let n = eligible.len();
    let answered = eligible.iter().filter(|o| o.grasp).count();
    ((n > 0).then(|| answered as f64 / n as f64), n)
}

/// The first `grasp` of each approach (sequence and object, in the order given, which is the
/// order of the steps); an approach that never got one is listed with no frame.
pub fn first_grasps(outcomes: &[DecisionOutcome]) -> Vec<FirstGrasp> {
    let mut by_approach: BTreeMap<(&str, &str), Option<&DecisionOutcome>> = BTreeMap::new();
    for o in outcomes {
        let slot = by_approach
            .entry((o.sequence.as_str(), o.object.as_str()))
            .or_insert(None);
        if slot.is_none() && o.grasp {
            *slot = Some(o);
        }
    }
    by_approach
        .into_iter()
        .map(|((sequence, object), first)| FirstGrasp {
            sequence: sequence.to_string(),
            object: object.to_string(),
            frame_id: first.map(|o| o.frame_id),
            camera_distance_m: first.and_then(|o| o.camera_distance_m),
            fails_on_truth: first.map(|o| !o.success),
        })
        .collect()
}

/// The `decision` block of `results.json`; `None` without outcomes.
pub fn summarise(outcomes: &[DecisionOutcome], threshold: f64) -> Option<DecisionBlock> {
    if outcomes.is_empty() {
        return None;
    }
    let r = calibration_report(&records(outcomes.iter()));
    let objects: std::collections::BTreeSet<&str> = outcomes.iter().map(|o| o.object.as_str()).collect();
    let mut ece_by_object = BTreeMap::new();
    let mut ece_leave_one_object_out = BTreeMap::new();
    let mut by_object = BTreeMap::new();
    for obj in &objects {
        let own: Vec<&DecisionOutcome> = outcomes.iter().filter(|o| o.object == *obj).collect();
        let (recall, recall_frames) = recall(own.iter().copied());
        by_object.insert(
            obj.to_string(),
            ObjectDecisions {
                frames: own.len(),
                n_grasp: own.iter().filter(|o| o.grasp).count(),
                failing_grasps: own.iter().filter(|o| o.grasp && !o.success).count(),
                recall,
                recall_frames,
            },
        );
        ece_by_object.insert(obj.to_string(), calibration_report(&records(own.into_iter())).ece);
        let rest = records(outcomes.iter().filter(|o| o.object != *obj));
        if !rest.is_empty() {
            ece_leave_one_object_out.insert(obj.to_string(), calibration_report(&rest).ece);
        }
    }
    let (recall, recall_frames) = recall(outcomes);
    let first_grasp = first_grasps(outcomes);
    let approaches = first_grasp.len();
    let failures = first_grasp.iter().filter(|f| f.fails_on_truth == Some(true)).count();
    let mut distances: Vec<f64> = first_grasp.iter().filter_map(|f| f.camera_distance_m).collect();
    distances.sort_by(f64::total_cmp);
    let median_first_grasp_distance_m = match distances.len() {
        0 => None,
        n if n % 2 == 1 => Some(distances[n / 2]),
        n => Some(0.5 * (distances[n / 2 - 1] + distances[n / 2])),
    };
    Some(DecisionBlock {
        ece: r.ece,
        false_grasp_rate: (r.n_grasp > 0).then_some(r.false_grasp_rate),
        grasp_rate: r.grasp_rate,
        reliability: r
            .reliability
            .iter()
            .map(|b| ReliabilityBin {
                predicted: b.predicted,
                observed: b.observed,
                count: b.count,
            })
            .collect(),
        frames: r.n_decisions,
        n_grasp: r.n_grasp,
        true_success_rate: outcomes.iter().filter(|o| o.success).count() as f64 / outcomes.len() as f64,
        threshold,
        brier: r.brier,
        brier_base_rate: r.brier_base_rate,
        ece_by_object,
        ece_leave_one_object_out,
        recall,
        recall_frames,
        recall_max_distance_m: RECALL_MAX_DISTANCE_M,
        approaches,
        approaches_with_grasp: first_grasp.iter().filter(|f| f.frame_id.is_some()).count(),
        first_grasp_failures: failures,
        first_grasp_failure_rate: if approaches > 0 {
            failures as f64 / approaches as f64
        } else {
            0.0
        },
        first_grasp_failure_upper_95: wilson_upper_95(failures, approaches),
        median_first_grasp_distance_m,
        first_grasp,
        reliability_png: None,
        by_object,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn out(seq: &str, obj: &str, frame: u32, p: f64, grasp: bool, success: bool, d: f64) -> DecisionOutcome {
        DecisionOutcome {
            sequence: seq.into(),
            object: obj.into(),
            frame_id: frame,
            stamp_ns: i64::from(frame) * 100_000_000,
            p_success: p,
            grasp,
            success,
            truth_tests: None,
            camera_distance_m: Some(d),
            features: None,
        }
    }

    fn simple(p: f64, grasp: bool, success: bool) -> DecisionOutcome {
        out("s", "o", 0, p, grasp, success, 1.0)
    }

    #[test]
    fn the_shipped_map_is_fitted_for_the_running_settings() {
        // Fails when a tracker, codebook or gripper default changed since the map was fitted:
        // refit it with `pregrasp calibrate` (README, "The grasp rule").
        let map = crate::grasp::CalibrationMap::from_json(crate::grasp::calibrated::SHIPPED_MAP_JSON)
            .expect("the shipped map parses");
        let running = service_settings_hash();
        assert_eq!(
            map.settings_hash, running,
            "the shipped calibration map is stale: refit it (scripts/calibrate.sh)"
        );
        assert!(crate::grasp::Calibration::shipped(&running).map().is_some());
    }

    #[test]
    fn settings_hash_sees_the_tracker_codebook_grid_and_gripper_but_not_seeds() {
        let t = TrackerConfig::default();
        let c = CodebookConfig::coarse();
        let g = Gripper::default_parallel_jaw();
        let h = calibration_settings_hash(&t, &c, 10, &g);
        let mut t2 = t.clone();
        t2.seed += 1;
        t2.max_tracks_per_object = 1;
        let mut c2 = c.clone();
        c2.seed += 1;
        assert_eq!(h, calibration_settings_hash(&t2, &c2, 10, &g));
        let mut t3 = t.clone();
        t3.brownian_sigma_m *= 2.0;
        assert_ne!(h, calibration_settings_hash(&t3, &c, 10, &g));
        assert_ne!(h, calibration_settings_hash(&t, &CodebookConfig::default(), 10, &g));
        assert_ne!(h, calibration_settings_hash(&t, &c, 5, &g));
        let mut g2 = g.clone();
        g2.max_opening_m += 0.01;
        assert_ne!(h, calibration_settings_hash(&t, &c, 10, &g2));
        // the decision's procedure is part of them
        let settings = calibration_settings(&t, &c, 10, &g);
        assert_eq!(
            settings["decision_version"],
            crate::grasp::decision::DECISION_PROCEDURE_VERSION
        );
        let mut other = settings.clone();
        other["decision_version"] = serde_json::json!(crate::grasp::decision::DECISION_PROCEDURE_VERSION + 1);
        assert_ne!(h, crate::grasp::calibrated::settings_hash(&other));
        // the verification settings left out at their defaults still count when set
        let mut t4 = t.clone();
        t4.verification.occlusion_truncation = 0.5;
        assert_ne!(h, calibration_settings_hash(&t4, &c, 10, &g));
        let mut t5 = t.clone();
        t5.verification.min_view_change_deg = 10.0;
        assert_ne!(h, calibration_settings_hash(&t5, &c, 10, &g));
        let mut t7 = t.clone();
        t7.verification.min_object_px = 90.0;
        assert_ne!(h, calibration_settings_hash(&t7, &c, 10, &g));
        let mut t8 = t.clone();
        t8.near_blur = Some(crate::tracker::NearBlur {
            sigma_bins: 0.5,
            full_m: 1.0,
            until_m: 1.4,
            from_similarity: 0.85,
            full_similarity: 0.9,
        });
        assert_ne!(h, calibration_settings_hash(&t8, &c, 10, &g));
        // and so do the registration's
        let mut t6 = t.clone();
        t6.registration.information_scale = 0.5;
        assert_ne!(h, calibration_settings_hash(&t6, &c, 10, &g));
    }

    #[test]
    fn perfectly_calibrated_and_overconfident() {
        // p = 0.25 with 1 of 4 successes, p = 0.95 with 19 of 20: calibrated.
        let mut o = Vec::new();
        for i in 0..4 {
            o.push(simple(0.25, false, i == 0));
        }
        for i in 0..20 {
            o.push(simple(0.95, true, i != 0));
        }
        let b = summarise(&o, 0.9).expect("some");
        assert_relative_eq!(b.ece, 0.0, epsilon = 1e-12);
        assert_eq!(b.reliability.len(), 2);
        assert_relative_eq!(b.grasp_rate, 20.0 / 24.0, epsilon = 1e-12);
        assert_relative_eq!(b.false_grasp_rate.expect("grasps"), 0.05, epsilon = 1e-12);
        // Brier: 4 x (0.25 or 0.75)^2 ... by hand: (0.5625 + 3 x 0.0625 + 19 x 0.0025 + 0.9025) / 24.
        let brier = (0.5625 + 3.0 * 0.0625 + 19.0 * 0.0025 + 0.9025) / 24.0;
        assert_relative_eq!(b.brier, brier, epsilon = 1e-12);
        let base = 20.0 / 24.0;
        assert_relative_eq!(b.brier_base_rate, base * (1.0 - base), epsilon = 1e-12);
        assert!(b.brier < b.brier_base_rate);

        // Over-confident: says 0.95, succeeds half the time.
        let o: Vec<_> = (0..10).map(|i| simple(0.95, true, i % 2 == 0)).collect();
        let b = summarise(&o, 0.9).expect("some");
        assert_relative_eq!(b.ece, 0.45, epsilon = 1e-12);
        assert_relative_eq!(b.false_grasp_rate.expect("grasps"), 0.5, epsilon = 1e-12);
        assert!(b.brier > b.brier_base_rate, "worse than saying 0.5 every time");
        assert!(summarise(&[], 0.9).is_none());
        let none = summarise(&[simple(1.0, false, true)], 0.9).expect("some");
        assert_eq!(none.false_grasp_rate, None);
        assert_eq!(none.reliability[0].count, 1);
    }

    #[test]
    fn ece_per_object_and_leaving_each_out() {
        // can: calibrated (0.5, one of two succeeds); mug: says 0.9, always fails.
        let o = vec![
            out("s0", "can", 0, 0.5, false, true, 1.0),
            out("s0", "can", 1, 0.5, false, false, 1.0),
            out("s1", "mug", 0, 0.9, true, false, 1.0),
            out("s1", "mug", 1, 0.9, true, false, 1.0),
        ];
        let b = summarise(&o, 0.9).expect("some");
        assert_relative_eq!(b.ece_by_object["can"], 0.0, epsilon = 1e-12);
        assert_relative_eq!(b.ece_by_object["mug"], 0.9, epsilon = 1e-12);
        // Leaving the mug out leaves the calibrated can, and the other way round.
        assert_relative_eq!(b.ece_leave_one_object_out["mug"], 0.0, epsilon = 1e-12);
        assert_relative_eq!(b.ece_leave_one_object_out["can"], 0.9, epsilon = 1e-12);
        assert_relative_eq!(b.ece, 0.45, epsilon = 1e-12);
        // the mug's two answers are its grasps, both failing; the can never grasped
        assert_eq!((b.by_object["mug"].n_grasp, b.by_object["mug"].failing_grasps), (2, 2));
        assert_eq!((b.by_object["can"].n_grasp, b.by_object["can"].frames), (0, 2));
        assert_eq!(
            (b.by_object["can"].recall, b.by_object["can"].recall_frames),
            (Some(0.0), 1)
        );
        assert_eq!(b.by_object["mug"].recall, None);
    }

    #[test]
    fn recall_counts_successful_frames_within_reach() {
        let o = vec![
            // within reach and would succeed: 2 of 4 answered grasp
            out("s", "o", 0, 0.99, true, true, 0.5),
            out("s", "o", 1, 0.7, false, true, 1.0),
            out("s", "o", 2, 0.7, false, true, 1.2),
            out("s", "o", 3, 0.99, true, true, 0.8),
            // would fail: not in the denominator even when answered grasp
            out("s", "o", 4, 0.99, true, false, 0.5),
            // too far: not counted
            out("s", "o", 5, 0.7, false, true, 1.5),
            out("s", "o", 6, 0.99, true, true, 1.21),
        ];
        let (r, n) = recall(&o);
        assert_eq!(n, 4);
        assert_relative_eq!(r.expect("eligible"), 0.5, epsilon = 1e-12);
        let mut unknown = o[0].clone();
        unknown.camera_distance_m = None;
        assert_eq!(recall(&[unknown]), (None, 0));
    }

    #[test]
    fn first_grasp_per_approach_and_its_failure_bound() {
        let o = vec![
            // s0: first grasp at frame 2 (1.1 m), which fails on the truth; a later success
            // does not change it.
            out("s0", "can", 0, 0.3, false, true, 1.5),
            out("s0", "can", 2, 0.97, true, false, 1.1),
            out("s0", "can", 3, 0.99, true, true, 0.9),
            // s1: first grasp at frame 1 (0.8 m), succeeds.
            out("s1", "mug", 0, 0.2, false, false, 1.4),
            out("s1", "mug", 1, 0.99, true, true, 0.8),
            // s2: never grasps.
            out("s2", "box", 0, 0.5, false, true, 1.0),
        ];
        let f = first_grasps(&o);
        assert_eq!(f.len(), 3);
        assert_eq!(
            (f[0].frame_id, f[0].camera_distance_m, f[0].fails_on_truth),
            (Some(2), Some(1.1), Some(true))
        );
        assert_eq!(
            (f[1].frame_id, f[1].camera_distance_m, f[1].fails_on_truth),
            (Some(1), Some(0.8), Some(false))
        );
        assert_eq!((f[2].frame_id, f[2].fails_on_truth), (None, None));
        let b = summarise(&o, 0.9).expect("some");
        assert_eq!(
            (b.approaches, b.approaches_with_grasp, b.first_grasp_failures),
            (3, 2, 1)
        );
        assert_relative_eq!(b.first_grasp_failure_rate, 1.0 / 3.0, epsilon = 1e-12);
        assert_relative_eq!(
            b.first_grasp_failure_upper_95,
            crate::grasp::calibration::wilson_upper_95(1, 3),
            epsilon = 1e-12
        );
        assert!(b.first_grasp_failure_upper_95 > 0.75, "1 of 3 bounds little");
        assert_relative_eq!(b.median_first_grasp_distance_m.expect("two"), 0.95, epsilon = 1e-12);
        let json = serde_json::to_value(&b).expect("json");
        for k in [
            "ece",
            "brier",
            "brier_base_rate",
            "ece_by_object",
            "ece_leave_one_object_out",
            "recall",
            "first_grasp",
            "first_grasp_failure_upper_95",
        ] {
            assert!(json.get(k).is_some(), "{k}");
        }
    }
}
