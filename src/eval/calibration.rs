//! Calibration of the grasp decision against the outcome on the true pose: reliability per
//! decile of predicted `p_success`, expected calibration error, grasp rate, false grasp rate.

use super::report::{DecisionBlock, ReliabilityBin};

/// One decision at one frame and its outcome on the true pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DecisionOutcome {
    pub p_success: f64,
    /// The decision said `grasp`.
    pub grasp: bool,
    /// The planned grasp succeeds on the true pose.
    pub success: bool,
}

/// The `decision` block of `results.json`; `None` without outcomes.
pub fn summarise(outcomes: &[DecisionOutcome], threshold: f64) -> Option<DecisionBlock> {
    if outcomes.is_empty() {
        return None;
    }
    let n = outcomes.len() as f64;
    let mut bins: Vec<(f64, usize, usize)> = vec![(0.0, 0, 0); 10];
    for o in outcomes {
        let k = ((o.p_success.clamp(0.0, 1.0) * 10.0).floor() as usize).min(9);
        bins[k].0 += o.p_success;
        bins[k].1 += usize::from(o.success);
        bins[k].2 += 1;
    }
    let reliability: Vec<ReliabilityBin> = bins
        .iter()
        .filter(|b| b.2 > 0)
        .map(|&(p, s, c)| ReliabilityBin {
            predicted: p / c as f64,
            observed: s as f64 / c as f64,
            count: c,
        })
        .collect();
    let ece = reliability
        .iter()
        .map(|b| b.count as f64 / n * (b.predicted - b.observed).abs())
        .sum();
    let grasps: Vec<&DecisionOutcome> = outcomes.iter().filter(|o| o.grasp).collect();
    Some(DecisionBlock {
        ece,
        false_grasp_rate: (!grasps.is_empty())
            .then(|| grasps.iter().filter(|o| !o.success).count() as f64 / grasps.len() as f64),
        grasp_rate: grasps.len() as f64 / n,
        reliability,
        frames: outcomes.len(),
        true_success_rate: outcomes.iter().filter(|o| o.success).count() as f64 / n,
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
