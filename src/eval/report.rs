//! Aggregation of per-frame metrics into `results.json` (Table I rows per target object,
//! their mean, the other tracked objects) and the Markdown table beside the paper's numbers.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;

use super::metrics::{AUC_MAX_THRESHOLD_M, auc};

/// Multi-view (all cameras) or the single-view baseline (the robot camera alone).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Multi,
    Single,
}

impl Mode {
    pub fn as_str(&self) -> &'static str {
        match self {
            Mode::Multi => "multi",
            Mode::Single => "single",
        }
    }
}

/// The errors of one estimate against the truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameErrors {
    pub translation_error_m: f64,
    pub translation_error_l1_m: f64,
    /// The paper's: L1 norm of the rotation vector of `R_est^T R_gt`, degrees.
    pub orientation_error_deg: f64,
    pub geodesic_error_deg: f64,
    pub symmetric_error_deg: f64,
    pub translation_std_m: f64,
    /// ln of the tracked mass of the bin holding the true orientation (`None`: not given).
    pub gt_orientation_loglik: Option<f64>,
    pub add_m: f64,
    pub add_s_m: f64,
    pub rotation_entropy: f64,
    /// Symmetry-aware angle under the shape's symmetries alone (colour ignored: what a depth
    /// camera cannot tell apart); `symmetric_error_deg` uses the exact ones (shape and colour).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape_symmetric_error_deg: Option<f64>,
    /// The truth's place in the tracked distribution (`eval::trust`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth_place: Option<TruthPlace>,
    /// The estimate's rotation (reference frame, x, y, z, w): pairs runs frame by frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimate_xyzw: Option<[f64; 4]>,
    /// The error as a rotation vector in the object frame (`truth^-1 * estimate`, radians):
    /// which turn the estimate is off by (a near-symmetry shows as a half turn about one axis).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_rotvec_object_rad: Option<[f64; 3]>,
    /// The translation error in the true object frame (`truth^-1 * (estimate - truth)`,
    /// metres): which way the estimate sits off the object (along its up axis, its long axis).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_translation_object_m: Option<[f64; 3]>,
}

/// The truth's place in the tracked distribution at one frame (`eval::trust`): the
/// probabilities that it lies in the 50 % and 90 % highest-density regions (ties broken at
/// random) and the 90 % region's volume.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthPlace {
    /// ln of the rotation marginal's density at the truth relative to the uniform
    /// distribution on SO(3), averaged over the exact symmetries; below 0: the truth is less
    /// likely than under a uniform distribution (confidently wrong).
    pub rotation_log_density: f64,
    pub rotation_truth_in_50: f64,
    pub rotation_truth_in_90: f64,
    /// Volume of the rotation's 90 % region as a fraction of SO(3) (uniform: 0.9).
    pub rotation_volume_90_so3_fraction: f64,
    /// The same test on the translation mixture (one Gaussian per camera component).
    pub translation_truth_in_50: Option<f64>,
    pub translation_truth_in_90: Option<f64>,
    pub translation_volume_90_m3: Option<f64>,
    /// The rotation histogram's entropy over the uniform distribution's on the same grid (1:
    /// as spread as uniform); `None` in runs written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation_entropy_ratio: Option<f64>,
    /// The error the distribution expects of the estimate's rotation: the mean angle (deg, up
    /// to the object's exact symmetries) from the estimate to the samples. Calibrated, its
    /// mean over frames matches that of `symmetric_error_deg`; `None` in older runs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation_expected_error_deg: Option<f64>,
}

impl TruthPlace {
    /// The truth is less likely than under a uniform rotation.
    pub fn below_uniform(&self) -> bool {
        self.rotation_log_density < 0.0
    }

    /// Confidently wrong (issue 19's definition): the truth below uniform while the entropy is
    /// under half of uniform's. A near-uniform distribution that barely misses the truth is
    /// honest, not confident; without a recorded entropy a frame below uniform counts.
    pub fn confidently_wrong(&self) -> bool {
        self.below_uniform() && self.rotation_entropy_ratio.is_none_or(|r| r < 0.5)
    }
}

/// The rotation part of a [`TrustRow`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RotationTrust {
    /// Mean over frames of the probability that the truth lies in the 50 % region.
    pub truth_in_50: f64,
    pub truth_in_90: f64,
    /// Median over frames of the 90 % region's volume, as a fraction of SO(3).
    pub median_volume_90_so3_fraction: f64,
    /// The same in steradian-radians (SO(3) is 8 pi^2 sr rad).
    pub median_volume_90_sr_rad: f64,
    /// Median over frames of ln(density at the truth / uniform's).
    pub median_log_density: f64,
    /// Mean over frames of the error the distribution expects of its estimate
    /// ([`TruthPlace::rotation_expected_error_deg`]); beside the row's mean
    /// `symmetric_error_deg` it says whether the spread in degrees covers the error.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_expected_error_deg: Option<f64>,
}

/// The translation part of a [`TrustRow`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TranslationTrust {
    pub truth_in_50: f64,
    pub truth_in_90: f64,
    /// Median over frames of the 90 % region's volume (m^3).
    pub median_volume_90_m3: f64,
}

/// How far the distribution can be trusted, over the frames with an estimate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrustRow {
    /// Frames scored (with an estimate).
    pub frames: usize,
    pub rotation: RotationTrust,
    pub translation: Option<TranslationTrust>,
    /// Share of the scored frames that are confidently wrong ([`TruthPlace::confidently_wrong`]:
    /// the truth below uniform while the entropy is under half of uniform's).
    pub confidently_wrong: f64,
    /// Share of the scored frames whose truth is less likely under the tracked rotation than
    /// under a uniform one (log density below 0), however spread the distribution.
    #[serde(default)]
    pub below_uniform: f64,
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    Some(if v.len().is_multiple_of(2) {
        0.5 * (v[m - 1] + v[m])
    } else {
        v[m]
    })
}

impl TrustRow {
    /// Over the frames' places; `None` without any.
    pub fn from_places(places: &[&TruthPlace]) -> Option<Self> {
        if places.is_empty() {
            return None;
        }
        let n = places.len() as f64;
        let vol = median(places.iter().map(|p| p.rotation_volume_90_so3_fraction).collect())?;
        let translation: Vec<(f64, f64, f64)> = places
            .iter()
            .filter_map(|p| {
                Some((
                    p.translation_truth_in_50?,
                    p.translation_truth_in_90?,
                    p.translation_volume_90_m3?,
                ))
            })
            .collect();
        let tn = translation.len() as f64;
        Some(Self {
            frames: places.len(),
            rotation: RotationTrust {
                truth_in_50: places.iter().map(|p| p.rotation_truth_in_50).sum::<f64>() / n,
                truth_in_90: places.iter().map(|p| p.rotation_truth_in_90).sum::<f64>() / n,
                median_volume_90_so3_fraction: vol,
                median_volume_90_sr_rad: vol * super::trust::SO3_VOLUME_SR_RAD,
                median_log_density: median(places.iter().map(|p| p.rotation_log_density).collect())?,
                mean_expected_error_deg: mean_if_all(places.iter().map(|p| p.rotation_expected_error_deg)),
            },
            translation: (!translation.is_empty()).then(|| TranslationTrust {
                truth_in_50: translation.iter().map(|t| t.0).sum::<f64>() / tn,
                truth_in_90: translation.iter().map(|t| t.1).sum::<f64>() / tn,
                median_volume_90_m3: median(translation.iter().map(|t| t.2).collect()).unwrap_or(f64::NAN),
            }),
            confidently_wrong: places.iter().filter(|p| p.confidently_wrong()).count() as f64 / n,
            below_uniform: places.iter().filter(|p| p.below_uniform()).count() as f64 / n,
        })
    }

    /// The unweighted mean of rows (medians are averaged too); `None` without rows.
    pub fn mean_of(rows: &[&TrustRow]) -> Option<Self> {
        if rows.is_empty() {
            return None;
        }
        let n = rows.len() as f64;
        let m = |f: &dyn Fn(&TrustRow) -> f64| rows.iter().map(|r| f(r)).sum::<f64>() / n;
        let t: Vec<&TranslationTrust> = rows.iter().filter_map(|r| r.translation.as_ref()).collect();
        let tn = t.len() as f64;
        let tm = |f: &dyn Fn(&TranslationTrust) -> f64| t.iter().map(|r| f(r)).sum::<f64>() / tn;
        Some(Self {
            frames: rows.iter().map(|r| r.frames).sum(),
            rotation: RotationTrust {
                truth_in_50: m(&|r| r.rotation.truth_in_50),
                truth_in_90: m(&|r| r.rotation.truth_in_90),
                median_volume_90_so3_fraction: m(&|r| r.rotation.median_volume_90_so3_fraction),
                median_volume_90_sr_rad: m(&|r| r.rotation.median_volume_90_sr_rad),
                median_log_density: m(&|r| r.rotation.median_log_density),
                mean_expected_error_deg: mean_if_all(rows.iter().map(|r| r.rotation.mean_expected_error_deg)),
            },
            translation: (!t.is_empty()).then(|| TranslationTrust {
                truth_in_50: tm(&|r| r.truth_in_50),
                truth_in_90: tm(&|r| r.truth_in_90),
                median_volume_90_m3: tm(&|r| r.median_volume_90_m3),
            }),
            confidently_wrong: m(&|r| r.confidently_wrong),
            below_uniform: m(&|r| r.below_uniform),
        })
    }
}

/// One object at one time step of a sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameMetrics {
    pub frame_id: u32,
    pub stamp_ns: i64,
    /// `None` when the tracker had no estimate (not yet initialised, or lost).
    pub errors: Option<FrameErrors>,
}

/// One ground-truth object over one sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectTrace {
    pub sequence: String,
    pub object: String,
    /// The object is the sequence's target, or the sequence names none (a Table I row).
    pub table_row: bool,
    pub frames: Vec<FrameMetrics>,
}

/// A Table I row: means over the frames with an estimate, over all sequences of the object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricRow {
    pub name: String,
    pub sequences: usize,
    pub frames: usize,
    pub frames_with_estimate: usize,
    pub translation_error_m: Option<f64>,
    pub translation_error_l1_m: Option<f64>,
    pub orientation_error_deg: Option<f64>,
    pub geodesic_error_deg: Option<f64>,
    pub symmetric_error_deg: Option<f64>,
    /// Under the shape's symmetries alone (colour ignored).
    #[serde(default)]
    pub shape_symmetric_error_deg: Option<f64>,
    pub translation_std_m: Option<f64>,
    pub gt_orientation_loglik: Option<f64>,
    pub add_m: Option<f64>,
    pub add_s_m: Option<f64>,
    /// AUC of ADD up to 0.10 m over the frames with an estimate, in [0, 1].
    pub add_auc: Option<f64>,
    /// AUC of ADD-S up to 0.10 m over the frames with an estimate, in [0, 1].
    pub add_s_auc: Option<f64>,
    /// ADD-S AUC counting frames without an estimate as failures.
    pub add_s_auc_all_frames: Option<f64>,
    /// Share of frames with an estimate.
    pub coverage: Option<f64>,
    /// The truth's place in the distribution (`truth_in_50`, `truth_in_90`, the 90 % region
    /// volumes, `confidently_wrong`), over the frames with an estimate.
    #[serde(default)]
    pub trust: Option<TrustRow>,
}

/// The mean of values that are all present (`None` when any is missing, as in frames of
/// runs written before the value was recorded, or when there are none).
fn mean_if_all(values: impl Iterator<Item = Option<f64>>) -> Option<f64> {
    mean(values.collect::<Option<Vec<f64>>>()?.into_iter())
}

/// The mean of the finite values (`None` when there are none).
pub(crate) fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (mut s, mut n) = (0.0, 0usize);
    for v in values.filter(|v| v.is_finite()) {
        s += v;
        n += 1;
    }
    (n > 0).then(|| s / n as f64)
}

impl MetricRow {
    /// Pools the frames of `traces` (all of one object, or any set) into one row.
    pub fn from_traces(name: &str, traces: &[&ObjectTrace]) -> Self {
        let frames: Vec<&FrameMetrics> = traces.iter().flat_map(|t| t.frames.iter()).collect();
        let with: Vec<&FrameErrors> = frames.iter().filter_map(|f| f.errors.as_ref()).collect();
        let sequences: std::collections::BTreeSet<&str> = traces.iter().map(|t| t.sequence.as_str()).collect();
        let m = |f: fn(&FrameErrors) -> f64| mean(with.iter().map(|e| f(e)));
        let add: Vec<Option<f64>> = with.iter().map(|e| Some(e.add_m)).collect();
        let add_s: Vec<Option<f64>> = with.iter().map(|e| Some(e.add_s_m)).collect();
        let add_s_all: Vec<Option<f64>> = frames.iter().map(|f| f.errors.as_ref().map(|e| e.add_s_m)).collect();
        Self {
            name: name.to_string(),
            sequences: sequences.len(),
            frames: frames.len(),
            frames_with_estimate: with.len(),
            translation_error_m: m(|e| e.translation_error_m),
            translation_error_l1_m: m(|e| e.translation_error_l1_m),
            orientation_error_deg: m(|e| e.orientation_error_deg),
            geodesic_error_deg: m(|e| e.geodesic_error_deg),
            symmetric_error_deg: m(|e| e.symmetric_error_deg),
            shape_symmetric_error_deg: mean(with.iter().filter_map(|e| e.shape_symmetric_error_deg)),
            translation_std_m: m(|e| e.translation_std_m),
            gt_orientation_loglik: mean(with.iter().filter_map(|e| e.gt_orientation_loglik)),
            add_m: m(|e| e.add_m),
            add_s_m: m(|e| e.add_s_m),
            add_auc: auc(&add, AUC_MAX_THRESHOLD_M),
            add_s_auc: auc(&add_s, AUC_MAX_THRESHOLD_M),
            add_s_auc_all_frames: auc(&add_s_all, AUC_MAX_THRESHOLD_M),
            coverage: (!frames.is_empty()).then(|| with.len() as f64 / frames.len() as f64),
            trust: TrustRow::from_places(&with.iter().filter_map(|e| e.truth_place.as_ref()).collect::<Vec<_>>()),
        }
    }

    /// The unweighted mean of rows (as the paper's "Mean" row); counts are summed.
    pub fn mean_of(name: &str, rows: &[MetricRow]) -> Self {
        let m = |f: fn(&MetricRow) -> Option<f64>| mean(rows.iter().filter_map(f));
        Self {
            name: name.to_string(),
            sequences: rows.iter().map(|r| r.sequences).sum(),
            frames: rows.iter().map(|r| r.frames).sum(),
            frames_with_estimate: rows.iter().map(|r| r.frames_with_estimate).sum(),
            translation_error_m: m(|r| r.translation_error_m),
            translation_error_l1_m: m(|r| r.translation_error_l1_m),
            orientation_error_deg: m(|r| r.orientation_error_deg),
            geodesic_error_deg: m(|r| r.geodesic_error_deg),
            symmetric_error_deg: m(|r| r.symmetric_error_deg),
            shape_symmetric_error_deg: m(|r| r.shape_symmetric_error_deg),
            translation_std_m: m(|r| r.translation_std_m),
            gt_orientation_loglik: m(|r| r.gt_orientation_loglik),
            add_m: m(|r| r.add_m),
            add_s_m: m(|r| r.add_s_m),
            add_auc: m(|r| r.add_auc),
            add_s_auc: m(|r| r.add_s_auc),
            add_s_auc_all_frames: m(|r| r.add_s_auc_all_frames),
            coverage: m(|r| r.coverage),
            trust: TrustRow::mean_of(&rows.iter().filter_map(|r| r.trust.as_ref()).collect::<Vec<_>>()),
        }
    }
}

/// One bin of the reliability table: mean predicted `p_success` and observed success rate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    pub predicted: f64,
    pub observed: f64,
    pub count: usize,
}

/// Calibration of the grasp decision (`--decide`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionBlock {
    pub ece: f64,
    pub false_grasp_rate: Option<f64>,
    pub grasp_rate: f64,
    pub reliability: Vec<ReliabilityBin>,
    /// Frames with a decision.
    pub frames: usize,
    /// Of which answered `grasp`.
    pub n_grasp: usize,
    /// Share of those frames whose grasp succeeds on the true pose.
    pub true_success_rate: f64,
    pub threshold: f64,
    /// Brier score of `p_success` against the outcome on the true pose.
    #[serde(default)]
    pub brier: f64,
    /// Brier score of the base-rate predictor (the share of successes at every frame).
    #[serde(default)]
    pub brier_base_rate: f64,
    #[serde(default)]
    pub ece_by_object: BTreeMap<String, f64>,
    /// ECE over the frames of the other objects, per object left out.
    #[serde(default)]
    pub ece_leave_one_object_out: BTreeMap<String, f64>,
    /// Of the frames whose grasp succeeds on the true pose with the robot camera within
    /// `recall_max_distance_m`, the share answered `grasp` (`None`: no such frame).
    #[serde(default)]
    pub recall: Option<f64>,
    /// Those frames.
    #[serde(default)]
    pub recall_frames: usize,
    #[serde(default)]
    pub recall_max_distance_m: f64,
    /// Approaches (a sequence's target) with a decision.
    #[serde(default)]
    pub approaches: usize,
    /// Of which ever answered `grasp`.
    #[serde(default)]
    pub approaches_with_grasp: usize,
    /// Approaches whose first `grasp` fails on the true pose.
    #[serde(default)]
    pub first_grasp_failures: usize,
    /// `first_grasp_failures / approaches`.
    #[serde(default)]
    pub first_grasp_failure_rate: f64,
    /// 95 % Wilson upper bound on the per-approach failure rate.
    #[serde(default)]
    pub first_grasp_failure_upper_95: f64,
    #[serde(default)]
    pub median_first_grasp_distance_m: Option<f64>,
    /// Per approach: the first `grasp`.
    #[serde(default)]
    pub first_grasp: Vec<FirstGrasp>,
    /// The reliability diagram beside `results.json`.
    #[serde(default)]
    pub reliability_png: Option<String>,
    /// Per object: its `grasp` answers, how many fail, and its recall within reach.
    #[serde(default)]
    pub by_object: BTreeMap<String, ObjectDecisions>,
}

/// One object's share of a [`DecisionBlock`]: where the `grasp` answers and the recall come
/// from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectDecisions {
    pub frames: usize,
    pub n_grasp: usize,
    /// `grasp` answers whose grasp fails on the true pose.
    pub failing_grasps: usize,
    pub recall: Option<f64>,
    pub recall_frames: usize,
}

/// The first `grasp` of one approach (sequence and object).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FirstGrasp {
    pub sequence: String,
    pub object: String,
    /// `None`: the approach never got `grasp`.
    pub frame_id: Option<u32>,
    /// Robot camera to the object's true position at that frame (m).
    pub camera_distance_m: Option<f64>,
    /// The planned grasp fails on the true pose.
    pub fails_on_truth: Option<bool>,
}

/// Per sequence: what was run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequenceSummary {
    pub name: String,
    pub target: Option<String>,
    pub frames: usize,
    pub objects: Vec<String>,
    pub wall_s: f64,
    /// Seconds spent in the tracker's steps (the rest is loading, detection and scoring).
    #[serde(default)]
    pub step_s: f64,
    /// Track steps audited (`MatchingConfig::audit`) and those whose heaviest particle's
    /// likelihood peaked outside the matched bins.
    #[serde(default)]
    pub audited: usize,
    #[serde(default)]
    pub audit_outside: usize,
    /// Bins matched and active bins kept per step, summed over the tracks.
    #[serde(default)]
    pub matched_bins_per_step: f64,
    #[serde(default)]
    pub active_bins_per_step: f64,
    /// Track steps whose rotation modes were checked against the images, and the seconds the
    /// checks took (the step's `verification` stage).
    #[serde(default)]
    pub verified: usize,
    #[serde(default)]
    pub verification_s: f64,
}

/// `results.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Results {
    pub mode: Mode,
    /// Table I rows: one per target object (in a sequence without a target, every object).
    pub objects: Vec<MetricRow>,
    /// The mean of `objects`.
    pub mean: MetricRow,
    /// Every other tracked object.
    pub others: Vec<MetricRow>,
    pub sequences: Vec<SequenceSummary>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decision: Option<DecisionBlock>,
    /// Free-form settings of the run (grid step, particle counts, ...).
    #[serde(default)]
    pub settings: BTreeMap<String, serde_json::Value>,
}

impl Results {
    /// Groups traces into Table I rows (by object name) and others.
    pub fn from_traces(mode: Mode, traces: &[ObjectTrace], sequences: Vec<SequenceSummary>) -> Self {
        let group = |table_row: bool| -> Vec<MetricRow> {
            let mut by_name: BTreeMap<&str, Vec<&ObjectTrace>> = BTreeMap::new();
            for t in traces.iter().filter(|t| t.table_row == table_row) {
                by_name.entry(t.object.as_str()).or_default().push(t);
            }
            by_name.iter().map(|(n, ts)| MetricRow::from_traces(n, ts)).collect()
        };
        let objects = group(true);
        let others = group(false);
        let mean = MetricRow::mean_of("mean", &objects);
        Self {
            mode,
            objects,
            mean,
            others,
            sequences,
            decision: None,
            settings: BTreeMap::new(),
        }
    }

    /// The Markdown table beside the paper's numbers.
    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let mode = self.mode.as_str();
        let _ = writeln!(s, "# pregrasp eval: {mode}-view\n");
        let _ = writeln!(
            s,
            "Per object as in Table I of the paper (`shared/seed/`), ours beside the paper's \
             {mode}-view column. Means over the frames with an estimate; coverage is the share of frames \
             with one. Orientation error is the paper's L1 norm of the rotation vector (degrees); geodesic \
             and symmetry-aware angles follow.\n"
        );
        let _ = writeln!(
            s,
            "| object | seq | frames | transl. err (m) | paper | orient. err (deg) | paper | transl. std (m) | paper | loglik GT | paper | geodesic (deg) | sym. (deg) | ADD (m) | ADD-S (m) | ADD-S AUC | coverage |"
        );
        let _ = writeln!(
            s,
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        let rows = self.objects.iter().chain(std::iter::once(&self.mean));
        for r in rows {
            let paper = paper_row(&r.name, self.mode);
            let p = |k: usize, digits: usize| paper.map_or("-".to_string(), |v| format!("{:.*}", digits, v[k]));
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                r.name,
                r.sequences,
                r.frames,
                fmt(r.translation_error_m, 4),
                p(0, 4),
                fmt(r.orientation_error_deg, 2),
                p(1, 2),
                fmt(r.translation_std_m, 4),
                p(2, 4),
                fmt(r.gt_orientation_loglik, 2),
                p(3, 2),
                fmt(r.geodesic_error_deg, 2),
                fmt(r.symmetric_error_deg, 2),
                fmt(r.add_m, 4),
                fmt(r.add_s_m, 4),
                fmt(r.add_s_auc, 3),
                fmt(r.coverage, 3),
            );
        }
        if self.objects.iter().any(|r| r.trust.is_some()) {
            let _ = writeln!(
                s,
                "\n## The truth's place in the distribution\n\nOver the frames with an estimate: the share \
                 of frames whose truth lies in the 50 % / 90 % highest-density region (ties broken at random: \
                 a uniform distribution scores 0.5 / 0.9), the median volume of the 90 % region (rotation: \
                 fraction of SO(3), uniform 0.9; translation: cm^3), and the share of frames whose true \
                 rotation is less likely than under a uniform distribution (confidently wrong). Rotations \
                 modulo the exact (shape and colour) symmetries; `expected` is the mean angle from the \
                 estimate to the distribution's samples, which a calibrated tracker matches with `sym.`\n"
            );
            let _ = writeln!(
                s,
                "| object | frames | rot. in 50 | rot. in 90 | rot. vol. 90 (SO(3)) | transl. in 50 | transl. in 90 | transl. vol. 90 (cm^3) | confidently wrong | below uniform | sym. (deg) | expected (deg) | shape sym. (deg) |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|---|---|");
            for r in self.objects.iter().chain(std::iter::once(&self.mean)) {
                let Some(t) = &r.trust else { continue };
                let tr = t.translation.as_ref();
                let _ = writeln!(
                    s,
                    "| {} | {} | {:.3} | {:.3} | {:.2e} | {} | {} | {} | {:.3} | {:.3} | {} | {} | {} |",
                    r.name,
                    t.frames,
                    t.rotation.truth_in_50,
                    t.rotation.truth_in_90,
                    t.rotation.median_volume_90_so3_fraction,
                    fmt(tr.map(|x| x.truth_in_50), 3),
                    fmt(tr.map(|x| x.truth_in_90), 3),
                    fmt(tr.map(|x| x.median_volume_90_m3 * 1e6), 2),
                    t.confidently_wrong,
                    t.below_uniform,
                    fmt(r.symmetric_error_deg, 2),
                    fmt(t.rotation.mean_expected_error_deg, 2),
                    fmt(r.shape_symmetric_error_deg, 2),
                );
            }
        }
        if !self.others.is_empty() {
            let _ = writeln!(s, "\nOther tracked objects (not the sequence's target):\n");
            let _ = writeln!(
                s,
                "| object | seq | frames | transl. err (m) | orient. err (deg) | sym. (deg) | transl. std (m) | loglik GT | ADD-S (m) | ADD-S AUC | coverage |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|");
            for r in &self.others {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                    r.name,
                    r.sequences,
                    r.frames,
                    fmt(r.translation_error_m, 4),
                    fmt(r.orientation_error_deg, 2),
                    fmt(r.symmetric_error_deg, 2),
                    fmt(r.translation_std_m, 4),
                    fmt(r.gt_orientation_loglik, 2),
                    fmt(r.add_s_m, 4),
                    fmt(r.add_s_auc, 3),
                    fmt(r.coverage, 3),
                );
            }
        }
        if let Some(d) = &self.decision {
            let _ = writeln!(
                s,
                "\n## Grasp decision calibration\n\nframes {}, threshold {:.2}, grasp rate {:.3}, false grasp rate {}, \
                 ECE {:.4}, success on the true pose {:.3}\n",
                d.frames,
                d.threshold,
                d.grasp_rate,
                fmt(d.false_grasp_rate, 4),
                d.ece,
                d.true_success_rate
            );
            let _ = writeln!(
                s,
                "Brier {:.4} (base rate {:.4}); recall {} of {} frames that would succeed within {:.1} m; \
                 approaches {}, with a grasp {}, first grasp fails in {} (rate {:.3}, 95 % Wilson upper bound \
                 {:.3}); median distance of the first grasp {} m\n",
                d.brier,
                d.brier_base_rate,
                fmt(d.recall, 3),
                d.recall_frames,
                d.recall_max_distance_m,
                d.approaches,
                d.approaches_with_grasp,
                d.first_grasp_failures,
                d.first_grasp_failure_rate,
                d.first_grasp_failure_upper_95,
                fmt(d.median_first_grasp_distance_m, 2),
            );
            if !d.ece_by_object.is_empty() {
                let _ = writeln!(s, "| object | ECE | ECE leaving it out |\n|---|---|---|");
                for (o, e) in &d.ece_by_object {
                    let _ = writeln!(
                        s,
                        "| {o} | {e:.4} | {} |",
                        fmt(d.ece_leave_one_object_out.get(o).copied(), 4)
                    );
                }
                let _ = writeln!(s);
            }
            let _ = writeln!(s, "| predicted | observed | count |\n|---|---|---|");
            for b in &d.reliability {
                let _ = writeln!(s, "| {:.3} | {:.3} | {} |", b.predicted, b.observed, b.count);
            }
        }
        let _ = writeln!(
            s,
            "\nNot like for like: the paper initialised its particles around the true position and used a \
             trained auto-encoder on photo-real renders; here tracks start from jittered detection boxes \
             and the encoder is learned from the mesh's own renders, and the sequences are our generator's."
        );
        s
    }
}

fn fmt(v: Option<f64>, digits: usize) -> String {
    v.map_or("-".to_string(), |v| format!("{v:.digits$}"))
}

/// The paper's Table I, per object: (multi, single) x (translation error m, orientation error
/// deg, translation std m, log-likelihood).
pub const PAPER_TABLE_I: [(&str, [f64; 4], [f64; 4]); 9] = [
    (
        "003_cracker_box",
        [0.0121, 6.33, 0.0781, -6.91],
        [0.0172, 18.60, 0.0583, -11.09],
    ),
    (
        "006_mustard_bottle",
        [0.0251, 10.68, 0.1191, -7.15],
        [0.0621, 93.48, 0.0601, -10.97],
    ),
    (
        "025_mug",
        [0.0495, 15.69, 0.1370, -13.70],
        [0.0778, 130.28, 0.1151, -17.22],
    ),
    (
        "004_sugar_box",
        [0.0411, 9.50, 0.2065, -11.25],
        [0.0954, 32.47, 0.0785, -13.53],
    ),
    (
        "011_banana",
        [0.0800, 15.85, 0.1640, -14.92],
        [0.1937, 97.95, 0.1495, -17.63],
    ),
    (
        "002_master_chef_can",
        [0.0066, 6.23, 0.0737, -8.35],
        [0.0065, 87.06, 0.0318, -11.35],
    ),
    (
        "021_bleach_cleanser",
        [0.0955, 57.44, 0.2375, -13.65],
        [0.2774, 152.70, 0.2991, -16.89],
    ),
    (
        "035_power_drill",
        [0.0561, 17.36, 0.0837, -11.19],
        [0.3125, 23.97, 0.0444, -12.74],
    ),
    ("mean", [0.0457, 17.38, 0.1374, -10.89], [0.1303, 79.56, 0.1046, -13.92]),
];

/// The paper's numbers for an object (or "mean") and mode.
pub fn paper_row(name: &str, mode: Mode) -> Option<[f64; 4]> {
    PAPER_TABLE_I
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, m, s)| match mode {
            Mode::Multi => *m,
            Mode::Single => *s,
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn errors(t: f64, o: f64) -> FrameErrors {
        FrameErrors {
            translation_error_m: t,
            translation_error_l1_m: t,
            orientation_error_deg: o,
            geodesic_error_deg: o,
            symmetric_error_deg: o,
            translation_std_m: 0.01,
            gt_orientation_loglik: Some(-5.0),
            add_m: t,
            add_s_m: t,
            rotation_entropy: 1.0,
            shape_symmetric_error_deg: None,
            truth_place: None,
            estimate_xyzw: None,
            error_rotvec_object_rad: None,
            error_translation_object_m: None,
        }
    }

    fn trace(seq: &str, obj: &str, row: bool, errs: &[Option<(f64, f64)>]) -> ObjectTrace {
        ObjectTrace {
            sequence: seq.into(),
            object: obj.into(),
            table_row: row,
            frames: errs
                .iter()
                .enumerate()
                .map(|(i, e)| FrameMetrics {
                    frame_id: i as u32,
                    stamp_ns: i as i64 * 100_000_000,
                    errors: e.map(|(t, o)| errors(t, o)),
                })
                .collect(),
        }
    }

    #[test]
    fn rows_pool_frames_and_mean_averages_rows() {
        let traces = vec![
            trace(
                "s0",
                "003_cracker_box",
                true,
                &[None, Some((0.02, 10.0)), Some((0.04, 20.0))],
            ),
            trace("s1", "003_cracker_box", true, &[Some((0.06, 30.0))]),
            trace("s2", "025_mug", true, &[Some((0.10, 90.0)), Some((0.20, 90.0))]),
            trace("s2", "011_banana", false, &[Some((0.5, 1.0))]),
        ];
        let r = Results::from_traces(Mode::Multi, &traces, vec![]);
        assert_eq!(r.objects.len(), 2);
        assert_eq!(r.others.len(), 1);
        let cracker = &r.objects[0];
        assert_eq!(cracker.name, "003_cracker_box");
        assert_eq!(
            (cracker.sequences, cracker.frames, cracker.frames_with_estimate),
            (2, 4, 3)
        );
        assert_relative_eq!(cracker.translation_error_m.expect("some"), 0.04, epsilon = 1e-12);
        assert_relative_eq!(cracker.coverage.expect("some"), 0.75, epsilon = 1e-12);
        // AUC over frames with an estimate: errors 0.02, 0.04, 0.06 -> (0.8 + 0.6 + 0.4) / 3.
        assert_relative_eq!(cracker.add_s_auc.expect("some"), 0.6, epsilon = 1e-12);
        assert_relative_eq!(cracker.add_s_auc_all_frames.expect("some"), 0.45, epsilon = 1e-12);
        // Mean of the two rows, not of the pooled frames.
        assert_relative_eq!(
            r.mean.translation_error_m.expect("some"),
            (0.04 + 0.15) / 2.0,
            epsilon = 1e-12
        );
        assert_relative_eq!(
            r.mean.orientation_error_deg.expect("some"),
            (20.0 + 90.0) / 2.0,
            epsilon = 1e-12
        );
        assert_eq!(r.mean.frames, 6);

        let json = serde_json::to_value(&r).expect("serialise");
        assert_eq!(json["mode"], "multi");
        for key in [
            "name",
            "sequences",
            "frames",
            "translation_error_m",
            "orientation_error_deg",
            "geodesic_error_deg",
            "translation_std_m",
            "gt_orientation_loglik",
            "add_s_auc",
            "coverage",
        ] {
            assert!(json["objects"][0].get(key).is_some(), "missing {key}");
            assert!(json["mean"].get(key).is_some(), "missing mean.{key}");
        }
        assert_eq!(json["others"][0]["name"], "011_banana");
        assert!(json.get("decision").is_none());
        let back: Results = serde_json::from_value(json).expect("round trip");
        assert_eq!(back, r);

        let md = r.markdown();
        assert!(md.contains("| 003_cracker_box | 2 | 4 | 0.0400 | 0.0121 |"), "{md}");
        assert!(md.contains("| mean |"));
        assert!(md.contains("0.0457"), "paper mean beside ours");
    }

    fn place(log_density: f64, in_50: f64, in_90: f64, volume: f64, translation: Option<f64>) -> TruthPlace {
        TruthPlace {
            rotation_log_density: log_density,
            rotation_truth_in_50: in_50,
            rotation_truth_in_90: in_90,
            rotation_volume_90_so3_fraction: volume,
            translation_truth_in_50: translation.map(|_| 0.0),
            translation_truth_in_90: translation.map(|_| 1.0),
            translation_volume_90_m3: translation,
            rotation_entropy_ratio: None,
            rotation_expected_error_deg: None,
        }
    }

    #[test]
    fn the_expected_error_is_averaged_only_over_frames_that_all_have_it() {
        let a = TruthPlace {
            rotation_expected_error_deg: Some(10.0),
            ..place(1.0, 1.0, 1.0, 0.1, None)
        };
        let b = TruthPlace {
            rotation_expected_error_deg: Some(30.0),
            ..place(1.0, 1.0, 1.0, 0.1, None)
        };
        let old = place(1.0, 1.0, 1.0, 0.1, None);
        let row = TrustRow::from_places(&[&a, &b]).expect("frames");
        assert_eq!(row.rotation.mean_expected_error_deg, Some(20.0));
        let mixed = TrustRow::from_places(&[&a, &old]).expect("frames");
        assert_eq!(
            mixed.rotation.mean_expected_error_deg, None,
            "an older run's frames have none"
        );
        let mean = TrustRow::mean_of(&[&row, &row]).expect("rows");
        assert_eq!(mean.rotation.mean_expected_error_deg, Some(20.0));
    }

    #[test]
    fn a_spread_distribution_that_misses_the_truth_is_not_confidently_wrong() {
        let spread = TruthPlace {
            rotation_entropy_ratio: Some(0.9),
            ..place(-0.1, 0.0, 1.0, 0.8, None)
        };
        let sharp = TruthPlace {
            rotation_entropy_ratio: Some(0.3),
            ..place(-0.1, 0.0, 0.0, 1e-3, None)
        };
        let right = TruthPlace {
            rotation_entropy_ratio: Some(0.3),
            ..place(5.0, 1.0, 1.0, 1e-3, None)
        };
        assert!(spread.below_uniform() && !spread.confidently_wrong());
        assert!(sharp.below_uniform() && sharp.confidently_wrong());
        assert!(!right.below_uniform() && !right.confidently_wrong());
        let row = TrustRow::from_places(&[&spread, &sharp, &right]).expect("frames");
        assert_relative_eq!(row.confidently_wrong, 1.0 / 3.0, epsilon = 1e-12);
        assert_relative_eq!(row.below_uniform, 2.0 / 3.0, epsilon = 1e-12);
    }

    #[test]
    fn trust_rows_average_coverage_take_median_volumes_and_count_confidently_wrong() {
        // A uniform frame (log density 0: not below uniform), a sharp right one, a sharp wrong
        // one (below uniform) and one without a translation mixture.
        let places = [
            place(0.0, 0.5, 0.9, 0.9, Some(1e-3)),
            place(8.0, 0.5, 0.9, 1e-4, Some(1e-6)),
            place(-20.0, 0.0, 0.0, 1e-4, Some(2e-6)),
            place(-1.0, 0.0, 1.0, 1e-2, None),
        ];
        let row = TrustRow::from_places(&places.iter().collect::<Vec<_>>()).expect("frames");
        assert_eq!(row.frames, 4);
        assert_relative_eq!(row.rotation.truth_in_50, 0.25, epsilon = 1e-12);
        assert_relative_eq!(row.rotation.truth_in_90, 0.7, epsilon = 1e-12);
        assert_relative_eq!(
            row.rotation.median_volume_90_so3_fraction,
            (1e-4 + 1e-2) / 2.0,
            epsilon = 1e-15
        );
        assert_relative_eq!(
            row.rotation.median_volume_90_sr_rad,
            row.rotation.median_volume_90_so3_fraction * 8.0 * std::f64::consts::PI.powi(2),
            epsilon = 1e-12
        );
        assert_relative_eq!(row.rotation.median_log_density, -0.5, epsilon = 1e-12);
        assert_relative_eq!(row.confidently_wrong, 0.5, epsilon = 1e-12);
        assert_relative_eq!(row.below_uniform, 0.5, epsilon = 1e-12);
        let t = row.translation.as_ref().expect("three frames with a mixture");
        assert_relative_eq!(t.median_volume_90_m3, 2e-6, epsilon = 1e-15);
        assert_relative_eq!(t.truth_in_90, 1.0, epsilon = 1e-12);
        assert!(TrustRow::from_places(&[]).is_none());
        // The mean row averages the objects' rows.
        let other = TrustRow::from_places(&[&place(1.0, 1.0, 1.0, 0.5, None)]).expect("one");
        let mean = TrustRow::mean_of(&[&row, &other]).expect("two");
        assert_eq!(mean.frames, 5);
        assert_relative_eq!(mean.confidently_wrong, 0.25, epsilon = 1e-12);
        assert_relative_eq!(mean.rotation.truth_in_90, 0.85, epsilon = 1e-12);
        assert_relative_eq!(
            mean.translation.expect("one row has it").median_volume_90_m3,
            2e-6,
            epsilon = 1e-15
        );
    }

    #[test]
    fn an_object_never_estimated_has_no_errors_but_zero_coverage() {
        let traces = vec![trace("s0", "025_mug", true, &[None, None])];
        let r = Results::from_traces(Mode::Single, &traces, vec![]);
        assert_eq!(r.objects[0].translation_error_m, None);
        assert_eq!(r.objects[0].coverage, Some(0.0));
        assert_eq!(r.objects[0].add_s_auc_all_frames, Some(0.0));
        let json = serde_json::to_string(&r).expect("serialise");
        assert!(!json.contains("NaN"));
        assert!(r.markdown().contains("| 025_mug | 1 | 2 | - | 0.0778 |"));
    }
}
