//! Calibration of the grasp decision against the outcome on the true pose: reliability per
//! decile of predicted `p_success`, expected calibration error, grasp rate, false grasp rate
//! (computed by `grasp::calibration`; this file collects the outcomes and shapes the block).

use super::report::{DecisionBlock, ReliabilityBin};
use crate::grasp::calibration::{CalibrationRecord, calibration_report};

/// One decision at one frame and its outcome on the true pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DecisionOutcome {
    pub p_success: f64,
    /// The decision said `grasp`.
    pub grasp: bool,
    /// The planned grasp succeeds on the true pose.
    pub success: bool,
}

/// The `decision` block of `results.json` (the statistics are `grasp::calibration`'s);
/// `None` without outcomes.
pub fn summarise(outcomes: &[DecisionOutcome], threshold: f64) -> Option<DecisionBlock> {
    if outcomes.is_empty() {
        return None;
    }
    let records: Vec<CalibrationRecord> = outcomes
        .iter()
        .map(|o| CalibrationRecord {
            p_success: o.p_success,
            decided_grasp: o.grasp,
            succeeded: o.success,
        })
        .collect();
    let r = calibration_report(&records);
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
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn perfectly_calibrated_and_overconfident() {
        // p = 0.25 with 1 of 4 successes, p = 0.95 with 19 of 20: calibrated.
        let mut o = Vec::new();
        for i in 0..4 {
            o.push(DecisionOutcome {
                p_success: 0.25,
                grasp: false,
                success: i == 0,
            });
        }
        for i in 0..20 {
            o.push(DecisionOutcome {
                p_success: 0.95,
                grasp: true,
                success: i != 0,
            });
        }
        let b = summarise(&o, 0.9).expect("some");
        assert_relative_eq!(b.ece, 0.0, epsilon = 1e-12);
        assert_eq!(b.reliability.len(), 2);
        assert_relative_eq!(b.grasp_rate, 20.0 / 24.0, epsilon = 1e-12);
        assert_relative_eq!(b.false_grasp_rate.expect("grasps"), 0.05, epsilon = 1e-12);

        // Over-confident: says 0.95, succeeds half the time.
        let o: Vec<_> = (0..10)
            .map(|i| DecisionOutcome {
                p_success: 0.95,
                grasp: true,
                success: i % 2 == 0,
            })
            .collect();
        let b = summarise(&o, 0.9).expect("some");
        assert_relative_eq!(b.ece, 0.45, epsilon = 1e-12);
        assert_relative_eq!(b.false_grasp_rate.expect("grasps"), 0.5, epsilon = 1e-12);
        assert!(summarise(&[], 0.9).is_none());
        let none = summarise(
            &[DecisionOutcome {
                p_success: 1.0,
                grasp: false,
                success: true,
            }],
            0.9,
        )
        .expect("some");
        assert_eq!(none.false_grasp_rate, None);
        assert_eq!(none.reliability[0].count, 1);
    }
}
