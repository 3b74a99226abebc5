//! Is the predicted p_success honest? Predicted vs observed success (on the ground-truth pose)
//! per decile, the expected calibration error, the Brier score beside the base-rate
//! predictor's, the grasp rate and the false grasp rate; and the Wilson upper bound that a
//! failure rate over few approaches is quoted with.

use super::decision::{Decision, Verdict};
use serde::{Deserialize, Serialize};

/// Number of bins of the reliability table (deciles of the predicted p).
pub const N_BINS: usize = 10;

/// One decision with its outcome on the ground-truth pose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CalibrationRecord {
    pub p_success: f64,
    /// The decision said `grasp`.
    pub decided_grasp: bool,
    /// The planned grasp succeeds on the ground-truth pose (`success_on_pose`).
    pub succeeded: bool,
}

impl CalibrationRecord {
    pub fn from_decision(decision: &Decision, succeeded: bool) -> Self {
        Self {
            p_success: decision.p_success,
            decided_grasp: decision.decision == Verdict::Grasp,
            succeeded,
        }
    }
}

/// One non-empty decile.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    /// Mean predicted p_success in the bin.
    pub predicted: f64,
    /// Share of the bin's decisions that succeeded on the ground truth.
    pub observed: f64,
    pub count: usize,
}

/// The `decision` block of eval's results.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationReport {
    /// Expected calibration error: sum over bins of count/n * |predicted - observed|.
    pub ece: f64,
    /// Brier score: mean of `(p_success - succeeded)^2` (0 is perfect; 0.25 is a constant
    /// 0.5).
    #[serde(default)]
    pub brier: f64,
    /// Brier score of the base-rate predictor, which says the share of successes at every
    /// frame: `b (1 - b)`. A useful `p_success` scores below it.
    #[serde(default)]
    pub brier_base_rate: f64,
    /// Share of `grasp` answers whose grasp fails on the ground truth (0 when there are none).
    pub false_grasp_rate: f64,
    /// Share of decisions answered `grasp`.
    pub grasp_rate: f64,
    /// Non-empty deciles, lowest predicted first.
    pub reliability: Vec<ReliabilityBin>,
    pub n_decisions: usize,
    pub n_grasp: usize,
}

/// The report over a set of records (an empty set gives zeros and no bins).
pub fn calibration_report(records: &[CalibrationRecord]) -> CalibrationReport {
    let n = records.len();
    let mut sum_p = [0.0f64; N_BINS];
    let mut sum_ok = [0usize; N_BINS];
    let mut count = [0usize; N_BINS];
    for r in records {
        let p = if r.p_success.is_finite() {
            r.p_success.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let b = ((p * N_BINS as f64) as usize).min(N_BINS - 1);
        sum_p[b] += p;
        sum_ok[b] += r.succeeded as usize;
        count[b] += 1;
    }
    let reliability: Vec<ReliabilityBin> = (0..N_BINS)
        .filter(|&b| count[b] > 0)
        .map(|b| ReliabilityBin {
            predicted: sum_p[b] / count[b] as f64,
            observed: sum_ok[b] as f64 / count[b] as f64,
            count: count[b],
        })
        .collect();
    let ece = if n == 0 {
        0.0
    } else {
        reliability
            .iter()
            .map(|b| b.count as f64 / n as f64 * (b.predicted - b.observed).abs())
            .sum()
    };
    let (brier, brier_base_rate) = brier_scores(records);
    let n_grasp = records.iter().filter(|r| r.decided_grasp).count();
    let false_grasps = records.iter().filter(|r| r.decided_grasp && !r.succeeded).count();
    CalibrationReport {
        ece,
        brier,
        brier_base_rate,
        false_grasp_rate: if n_grasp == 0 {
            0.0
        } else {
            false_grasps as f64 / n_grasp as f64
        },
        grasp_rate: if n == 0 { 0.0 } else { n_grasp as f64 / n as f64 },
        reliability,
        n_decisions: n,
        n_grasp,
    }
}

/// The predicted p clamped to [0, 1] (a non-finite one counts as 0), as the bins read it.
fn clamped(p: f64) -> f64 {
    if p.is_finite() { p.clamp(0.0, 1.0) } else { 0.0 }
}

/// (Brier score, base-rate predictor's Brier score) of a set of records; zeros when empty.
pub fn brier_scores(records: &[CalibrationRecord]) -> (f64, f64) {
    if records.is_empty() {
        return (0.0, 0.0);
    }
    let n = records.len() as f64;
    let y = |r: &CalibrationRecord| if r.succeeded { 1.0 } else { 0.0 };
    let brier = records
        .iter()
        .map(|r| (clamped(r.p_success) - y(r)).powi(2))
        .sum::<f64>()
        / n;
    let base = records.iter().map(y).sum::<f64>() / n;
    (brier, base * (1.0 - base))
}

/// The 95 % Wilson upper bound on a rate of `failures` in `n` trials (1 when `n` is 0): what
/// a failure rate over few approaches may really be.
pub fn wilson_upper_95(failures: usize, n: usize) -> f64 {
    if n == 0 {
        return 1.0;
    }
    super::decision::wilson_interval(failures as f64 / n as f64, n as f64)[1]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(p: f64, grasp: bool, ok: bool) -> CalibrationRecord {
        CalibrationRecord {
            p_success: p,
            decided_grasp: grasp,
            succeeded: ok,
        }
    }

    #[test]
    fn perfectly_calibrated_predictions_have_small_ece() {
        // in the 0.2 bin 1 of 5 succeeds, in the 0.8 bin 4 of 5
        let mut r = Vec::new();
        for i in 0..5 {
            r.push(rec(0.2, false, i == 0));
            r.push(rec(0.8, false, i != 0));
        }
        let c = calibration_report(&r);
        assert_eq!(c.reliability.len(), 2);
        assert!(c.ece < 1e-12, "{}", c.ece);
        assert_eq!(c.reliability[0].count, 5);
        assert!((c.reliability[1].observed - 0.8).abs() < 1e-12);
    }

    #[test]
    fn overconfident_predictions_and_false_grasps_are_counted() {
        let r = vec![
            rec(0.95, true, true),
            rec(0.95, true, false),
            rec(0.99, true, false),
            rec(0.3, false, true),
        ];
        let c = calibration_report(&r);
        assert_eq!(c.n_grasp, 3);
        assert!((c.grasp_rate - 0.75).abs() < 1e-12);
        assert!((c.false_grasp_rate - 2.0 / 3.0).abs() < 1e-12);
        // bin 9: predicted 0.9633, observed 1/3; bin 3: predicted 0.3, observed 1
        let expect = 0.75 * (0.963_333_333 - 1.0 / 3.0) + 0.25 * 0.7;
        assert!((c.ece - expect).abs() < 1e-6, "{} vs {expect}", c.ece);
        // p = 1.0 lands in the last decile
        assert_eq!(calibration_report(&[rec(1.0, true, true)]).reliability[0].count, 1);
        let empty = calibration_report(&[]);
        assert_eq!((empty.ece, empty.grasp_rate, empty.reliability.len()), (0.0, 0.0, 0));
    }

    #[test]
    fn brier_against_the_base_rate() {
        // Half succeed. A perfect predictor scores 0, the base rate 0.25, a constant 0.5
        // 0.25 too, a predictor that says the opposite 1.
        let perfect = [rec(1.0, true, true), rec(0.0, false, false)];
        assert_eq!(brier_scores(&perfect), (0.0, 0.25));
        let constant = [rec(0.5, false, true), rec(0.5, false, false)];
        assert_eq!(brier_scores(&constant), (0.25, 0.25));
        let opposite = [rec(0.0, false, true), rec(1.0, true, false)];
        assert_eq!(brier_scores(&opposite), (1.0, 0.25));
        // 3 of 4 succeed, predicted 0.9 each: Brier (3 * 0.01 + 0.81) / 4, base 0.1875.
        let r = [
            rec(0.9, true, true),
            rec(0.9, true, true),
            rec(0.9, true, true),
            rec(0.9, true, false),
        ];
        let (b, base) = brier_scores(&r);
        assert!((b - 0.21).abs() < 1e-12 && (base - 0.1875).abs() < 1e-12, "{b} {base}");
        let c = calibration_report(&r);
        assert!((c.brier - 0.21).abs() < 1e-12 && (c.brier_base_rate - 0.1875).abs() < 1e-12);
        assert_eq!(brier_scores(&[]), (0.0, 0.0));
    }

    #[test]
    fn wilson_upper_bounds_of_few_approaches() {
        // 0 of 64: z^2 / (n + z^2) = 0.0566; 2 of 64: 0.1070 (Wilson's formula by hand).
        assert!(
            (wilson_upper_95(0, 64) - 0.056_62).abs() < 1e-4,
            "{}",
            wilson_upper_95(0, 64)
        );
        assert!(
            (wilson_upper_95(2, 64) - 0.106_97).abs() < 1e-4,
            "{}",
            wilson_upper_95(2, 64)
        );
        assert!(wilson_upper_95(2, 64) > 2.0 / 64.0);
        assert_eq!(wilson_upper_95(0, 0), 1.0);
        assert!((wilson_upper_95(10, 10) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn report_serialises_with_the_agreed_keys() {
        let c = calibration_report(&[rec(0.5, false, true)]);
        let v = serde_json::to_value(&c).unwrap();
        for k in [
            "ece",
            "brier",
            "brier_base_rate",
            "false_grasp_rate",
            "grasp_rate",
            "reliability",
        ] {
            assert!(v.get(k).is_some(), "{k}");
        }
        let b = &v["reliability"][0];
        assert!(b.get("predicted").is_some() && b.get("observed").is_some() && b.get("count").is_some());
    }
}
