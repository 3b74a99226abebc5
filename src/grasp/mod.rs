//! Grasp or observe: will the planned grasp work on the tracked pose distribution?
//!
//! The decision plans a parallel-jaw grasp on the current pose estimate and replays it on
//! object poses drawn from the tracked distribution (`crate::geometry::PoseSamples`). Every
//! sample is checked with parry3d against solid shapes (the object's convex hull or convex
//! decomposition) and the support plane:
//!
//! - `approach`: the open gripper (palm and both fingers) is swept from the pre-grasp pose along
//!   its approach axis (+z of the gripper frame) to the grasp pose without touching the object;
//! - `table`: palm and fingers keep a clearance above the support plane at both ends of the
//!   sweep (the motion is linear, so both ends bound the whole sweep);
//! - `contact`: closing the fingers along the closing axis (x) brings both pads onto the object
//!   (the object spans the closing region, within the stroke), before any other part of the
//!   finger touches it;
//! - `alignment`: the contacts lie inside the capture funnel of the pads (the V-groove and
//!   chamfers of [`PadGeometry`]), so that closing pushes the object into the aligned pose.
//!
//! Frames: every query is evaluated in the gripper frame of the planned grasp
//! (`gripper_from_object = reference_from_gripper^-1 * reference_from_object`). The gripper
//! frame has its origin at the tool centre point (the middle between the pad centres), x along
//! the closing axis, z along the approach axis (from the palm towards the finger tips).
//! nalgebra is our maths; parry3d (glam, f32) is only spoken inside [`convert`].
//!
//! Usage (the shape of a call; see `tests/grasp_decision.rs` for runnable ones):
//!
//! ```text
//! let object = GraspObject::new(&mesh)?;                 // hull or decomposition, cached
//! let gripper = Gripper::default_parallel_jaw();         // or Gripper::from_file(path)?
//! let query = DecisionQuery { support_plane: Some(table_in_reference), ..Default::default() };
//! let d = decide(&object, &gripper, &estimate.reference_from_object, &samples, &query)?;
//! // d.decision, d.p_success, d.ci95, d.reasons[i].{test, failure_share, drivers, message}
//! let ok = success_on_pose(&object, &gripper, &d.reference_from_gripper, &truth, Some(&plane))?;
//! let view = suggest_view(&d, &views);                   // which listed view to take next
//!
//! // calibrated: the shipped map, checked against the running settings' hash
//! // (eval::calibration::calibration_settings_hash); raw with a warning when stale
//! let calibration = Calibration::shipped(&settings_hash);
//! let query = DecisionQuery { threshold: calibration.rule().threshold, ..query };
//! let d = decide_calibrated(&object, &gripper, &estimate, &samples, &query, &calibration)?;
//! // d.p_success (calibrated), d.p_success_raw, d.ci95, d.ci95_raw, d.calibration, d.rule
//! let mut smoother = calibration.smoother();             // one per track, kept between steps
//! let mut d = d;
//! smoother.apply(step_stamp_ns, &mut d, &calibration);  // once per tracker step and question
//! // d.p_success, d.ci95, d.decision now smoothed; d.smoothing.{run, p_success_unsmoothed}
//! ```
//!
//! The rule (`calibrated.rs`): the raw rate is smoothed over the last answers about the track
//! (time constant of the map), put through a monotone map fitted on generated sequences
//! (isotonic regression of the outcome on the true pose), and `grasp` is answered when the
//! rule's quantity (the smoothed raw rate, the calibrated probability or a bound) clears its
//! threshold in a run of answers.
//! The map, its time constant and its rule are chosen by `pregrasp calibrate` (README, "The
//! grasp rule").
//!
//! Timing (`cargo bench --bench grasp`, one rayon thread, 1,000 samples, a fixed top grasp):
//! CPU time per decision 10.6 ms for the 4,539-triangle YCB can (convex hull, hill-climbing
//! support, see `hull.rs`) and 15.2 ms for the power drill (VHACD, 9 parts); about 8 ms for
//! the cracker box and 15-16 ms for the mug and the banana. The wall-clock medians on the
//! project's 2-core machine, shared with six other builds (load average about 13), were
//! 25-32 ms (can) and 39-61 ms (drill).
//!
//! Files: `gripper.rs` (the gripper model and its JSON), `object.rs` (solid shapes, cached per
//! mesh content hash), `hull.rs` (a convex hull with a hill-climbing support map),
//! `candidates.rs` (grasps and their generation), `decision.rs` (the per-sample tests, the
//! decision and its reasons), `calibrated.rs` (the calibration map, its settings hash, the
//! rule and the per-track smoother), `calibration.rs` (predicted vs observed), `view.rs`
//! (next-best-view suggestion), `convert.rs` (nalgebra <-> parry).

pub mod calibrated;
pub mod calibration;
pub mod candidates;
pub mod convert;
pub mod decision;
pub mod gripper;
pub mod hull;
pub mod object;
pub mod placement;
pub mod view;

pub use calibrated::{
    AnswerSmoother, Calibration, CalibrationMap, CalibrationStatus, GraspRule, RuleQuantity, SmoothedAnswer,
    SmoothingStatus,
};
pub use calibration::{CalibrationRecord, CalibrationReport, ReliabilityBin, calibration_report};
pub use candidates::{Grasp, generate_candidates};
pub use decision::{
    AxisDriver, Decision, DecisionQuery, FailureTest, Motion, PoseOutcome, RankedGrasp, Reason, Verdict, decide,
    decide_calibrated, evaluate_pose, success_on_pose, wilson_interval,
};
pub use gripper::{Gripper, PadGeometry};
pub use object::{GraspObject, SolidKind};
pub use placement::{cached_placements, placed_candidates, search_placements};
pub use view::{CandidateView, ViewSuggestion, suggest_view};

use serde::{Deserialize, Serialize};

/// Errors of the grasp module.
#[derive(Debug, thiserror::Error)]
pub enum GraspError {
    #[error("invalid gripper: {0}")]
    InvalidGripper(String),
    #[error("gripper JSON: {0}")]
    GripperJson(#[from] serde_json::Error),
    #[error("reading gripper file {path}: {source}")]
    GripperFile { path: String, source: std::io::Error },
    #[error("invalid object mesh: {0}")]
    InvalidMesh(String),
    #[error("invalid query: {0}")]
    InvalidQuery(String),
    #[error("no pose samples given")]
    NoSamples,
    #[error("no grasp candidate of the gripper fits the object: {0}")]
    NoCandidate(String),
    #[error("geometry query unsupported by parry3d: {0}")]
    Unsupported(String),
    #[error("calibration map: {0}")]
    Calibration(String),
    #[error("calibration map fitted for settings {map}, running {running}: refit it (`pregrasp calibrate`)")]
    StaleCalibration { map: String, running: String },
}

/// The plane the object stands on (the table), in the frame of the samples. `normal` points
/// away from the table (into the free space); it need not be unit length.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SupportPlane {
    pub normal: [f64; 3],
    pub point_m: [f64; 3],
}

impl SupportPlane {
    /// Unit normal and point, or an error for a zero or non-finite normal.
    pub fn unit(&self) -> Result<(nalgebra::Vector3<f64>, nalgebra::Point3<f64>), GraspError> {
        let n = nalgebra::Vector3::from(self.normal);
        let p = nalgebra::Point3::from(self.point_m);
        let norm = n.norm();
        if !norm.is_finite() || norm < 1e-9 || !p.coords.iter().all(|x| x.is_finite()) {
            return Err(GraspError::InvalidQuery(format!(
                "support plane needs a finite non-zero normal and a finite point, got {self:?}"
            )));
        }
        Ok((n / norm, p))
    }

    /// The same plane expressed in another frame: `target_from_source * self`.
    pub fn transformed(&self, target_from_source: &crate::geometry::Pose) -> SupportPlane {
        let n = target_from_source.rotation * nalgebra::Vector3::from(self.normal);
        let p = target_from_source * nalgebra::Point3::from(self.point_m);
        SupportPlane {
            normal: [n.x, n.y, n.z],
            point_m: [p.x, p.y, p.z],
        }
    }
}
