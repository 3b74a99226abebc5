//! The decision scores its grasp on the samples with their rotation offsets scaled by
//! `SCORE_ROTATION_SHARE` (and translation offsets by `SCORE_TRANSLATION_SHARE`): when the
//! ground truth is drawn from that narrower distribution, the raw p_success is calibrated by
//! construction. The reliability table must show it, and `success_on_pose` on the drawn samples
//! must agree with the decision's own per-sample tests.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use pregrasp::geometry::{Pose, PoseSamples};
use pregrasp::grasp::decision::{SCORE_ROTATION_SHARE, SCORE_TRANSLATION_SHARE, drawn_towards};
use pregrasp::grasp::{
    CalibrationRecord, DecisionQuery, Grasp, GraspObject, Gripper, SupportPlane, calibration_report, decide,
    success_on_pose,
};
use pregrasp::mesh;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

fn draw(estimate: &Pose, t_std_m: f64, r_std_rad: f64, rng: &mut ChaCha8Rng) -> Pose {
    let std = Normal::new(0.0, 1.0).expect("unit normal");
    let t = Vector3::from_fn(|_, _| std.sample(rng) * t_std_m);
    let r = Vector3::from_fn(|_, _| std.sample(rng) * r_std_rad);
    Pose::from_parts(
        Translation3::from(estimate.translation.vector + t),
        UnitQuaternion::from_scaled_axis(r) * estimate.rotation,
    )
}

#[test]
fn predicted_p_matches_outcomes_on_truth_from_the_same_distribution() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&mesh::builtin("can").unwrap()).unwrap();
    let (lo, _) = can.extent_along(&Vector3::z());
    let est = Pose::from_parts(Translation3::new(0.5, 0.0, -lo), UnitQuaternion::identity());
    let plane = SupportPlane {
        normal: [0.0, 0.0, 1.0],
        point_m: [0.0; 3],
    };
    let grasp = Grasp::new(&can, &-Vector3::z(), &Vector3::x(), 0.03, "top").unwrap();
    let query = DecisionQuery {
        n_samples: 300,
        threshold: 0.9,
        grasp: Some(grasp),
        support_plane: Some(plane),
        translation_std_m: None,
        reference_sees: true,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let mut records = Vec::new();
    for frame in 0..150 {
        // spreads from tiny to far beyond the groove and the finger clearance
        let t_std = 0.001 + 0.02 * rng.random::<f64>();
        let r_std = 0.05 * rng.random::<f64>();
        let poses: Vec<Pose> = (0..300).map(|_| draw(&est, t_std, r_std, &mut rng)).collect();
        let samples = PoseSamples {
            poses: poses.clone(),
            effective_sample_size: 300.0,
        };
        let d = decide(&can, &gripper, &est, &samples, &query).unwrap();
        if frame < 3 {
            // the helper replays exactly the decision's tests on the drawn samples
            let drawn = drawn_towards(&poses, &est, SCORE_TRANSLATION_SHARE, SCORE_ROTATION_SHARE);
            let k = drawn
                .iter()
                .filter(|p| success_on_pose(&can, &gripper, &d.reference_from_gripper, p, Some(&plane)).unwrap())
                .count();
            assert!((k as f64 / 300.0 - d.p_success).abs() < 1e-12);
        }
        let truth = draw(
            &est,
            t_std * SCORE_TRANSLATION_SHARE,
            r_std * SCORE_ROTATION_SHARE,
            &mut rng,
        );
        let ok = d.success_on_pose(&can, &gripper, &truth, Some(&plane)).unwrap();
        records.push(CalibrationRecord::from_decision(&d, ok));
    }
    let report = calibration_report(&records);
    eprintln!("{}", serde_json::to_string(&report).unwrap());
    assert_eq!(report.n_decisions, 150);
    assert!(report.reliability.len() >= 4, "{:?}", report.reliability);
    assert!(report.ece < 0.12, "ECE {} {:?}", report.ece, report.reliability);
    assert!(
        report.grasp_rate > 0.05 && report.grasp_rate < 0.95,
        "{}",
        report.grasp_rate
    );
    // grasp only when the lower bound clears 0.9: few of those fail
    assert!(report.false_grasp_rate < 0.1, "{}", report.false_grasp_rate);
    assert!(records.iter().any(|r| !r.decided_grasp));
}
