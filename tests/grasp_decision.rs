//! The grasp-or-observe decision on hand-made pose distributions (issue 4's scenarios).
//! Reference frame of the samples: z up, the table at z = 0.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use pregrasp::geometry::{Pose, PoseSamples};
use pregrasp::grasp::{
    CandidateView, DecisionQuery, FailureTest, Grasp, GraspObject, Gripper, Motion, SupportPlane, Verdict, decide,
    success_on_pose, suggest_view,
};
use pregrasp::mesh::{self, Mesh};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

fn shared() -> PathBuf {
    match std::env::var("PREGRASP_SHARED") {
        Ok(p) => PathBuf::from(p),
        Err(_) => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared"),
    }
}

fn ycb(name: &str) -> Mesh {
    Mesh::load(&shared().join("ycb").join(format!("{name}.ply"))).expect("YCB mesh in ../shared/ycb")
}

fn table() -> SupportPlane {
    SupportPlane {
        normal: [0.0, 0.0, 1.0],
        point_m: [0.0, 0.0, 0.0],
    }
}

/// The object upright on the table at (0.6, 0.1), its lowest point on z = 0.
fn standing(object: &GraspObject) -> Pose {
    let (lo, _) = object.extent_along(&Vector3::z());
    Pose::from_parts(Translation3::new(0.6, 0.1, -lo), UnitQuaternion::identity())
}

/// `estimate` rotated by `r` about its own origin (in reference axes), then shifted by `t`.
fn rotate_about_origin(estimate: &Pose, r: &UnitQuaternion<f64>, t: &Vector3<f64>) -> Pose {
    Pose::from_parts(
        Translation3::from(estimate.translation.vector + t),
        r * estimate.rotation,
    )
}

fn top_grasp(object: &GraspObject, depth_m: f64) -> Grasp {
    Grasp::new(object, &-Vector3::z(), &Vector3::x(), depth_m, "top, close x").expect("top grasp")
}

fn query(grasp: Option<Grasp>) -> DecisionQuery {
    DecisionQuery {
        n_samples: 1000,
        threshold: 0.9,
        grasp,
        support_plane: Some(table()),
        translation_std_m: None,
        reference_sees: true,
    }
}

#[test]
fn tiny_uncertainty_around_a_centred_can_grasps() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.5f64.to_radians(); 3], 1000, 1);
    let d = decide(&can, &gripper, &est, &samples, &query(None)).unwrap();
    assert_eq!(d.decision, Verdict::Grasp, "{:#?}", d.reasons);
    assert!(d.p_success > 0.99, "{}", d.p_success);
    assert!(d.ci95[0] >= 0.9 && d.ci95[0] <= d.p_success && d.ci95[1] >= d.p_success);
    assert_eq!(d.n_samples, 1000);
    assert!(!d.candidates.is_empty());
    // ranked best first; a grasp from below (into the table) is among them and scores 0
    assert!(
        d.candidates
            .windows(2)
            .all(|w| { w[0].n_samples > w[1].n_samples || w[0].p_success >= w[1].p_success })
    );
    assert_eq!(d.candidates[0].n_samples, 1000);
    assert_eq!(d.candidates[0].grasp, d.grasp);
    assert!(
        d.grasp.label.starts_with("top") || d.grasp.label.starts_with("side"),
        "{}",
        d.grasp.label
    );
    let from_below = d
        .candidates
        .iter()
        .find(|c| Vector3::from(c.grasp.approach_in_object).z > 0.9)
        .expect("a candidate approaching from below");
    assert_eq!(from_below.p_success, 0.0);
    assert!(
        from_below.grasp.label.starts_with("from below"),
        "{}",
        from_below.grasp.label
    );
    // the planned gripper pose works on the estimate itself
    assert!(success_on_pose(&can, &gripper, &d.reference_from_gripper, &est, Some(&table())).unwrap());
}

/// The same tight distribution while the robot's camera looks away: the rate is as high,
/// the answer `observe` (the pose in the robot's frame rests on odometry then).
#[test]
fn a_pose_the_reference_camera_does_not_see_is_not_grasped() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.5f64.to_radians(); 3], 1000, 1);
    let seen = decide(&can, &gripper, &est, &samples, &query(None)).unwrap();
    let unseen = DecisionQuery {
        reference_sees: false,
        ..query(None)
    };
    let d = decide(&can, &gripper, &est, &samples, &unseen).unwrap();
    assert_eq!(seen.decision, Verdict::Grasp);
    assert_eq!(d.decision, Verdict::Observe);
    assert!(!d.reference_sees && seen.reference_sees);
    assert_eq!(d.p_success_raw, seen.p_success_raw);
}

#[test]
fn few_effective_samples_widen_the_interval_and_block_the_grasp() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let mut samples = PoseSamples::gaussian(&est, [0.001; 3], [0.005; 3], 1000, 2);
    samples.effective_sample_size = 20.0;
    let d = decide(&can, &gripper, &est, &samples, &query(Some(top_grasp(&can, 0.03)))).unwrap();
    assert!(d.p_success > 0.99);
    assert!((d.effective_sample_size - 20.0).abs() < 1e-9);
    assert!(d.ci95[0] < 0.9);
    assert_eq!(d.decision, Verdict::Observe);
}

#[test]
fn translation_spread_beyond_the_finger_clearance_observes_and_names_the_closing_axis() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    // clearance per side (140 - 102) / 2 = 19 mm; spread 30 mm along reference x = gripper x
    let samples = PoseSamples::gaussian(&est, [0.03, 0.001, 0.001], [0.0; 3], 1000, 3);
    let grasp = top_grasp(&can, 0.03);
    let d = decide(&can, &gripper, &est, &samples, &query(Some(grasp))).unwrap();
    assert_eq!(d.decision, Verdict::Observe);
    assert!(d.p_success < 0.8, "{}", d.p_success);
    let top = &d.reasons[0];
    assert_eq!(top.test, FailureTest::Approach, "{:#?}", d.reasons);
    assert!(top.failure_share > 0.2);
    let driver = &top.drivers[0];
    assert_eq!(
        (driver.motion, driver.axis.as_str()),
        (Motion::Translation, "gripper_x"),
        "{:#?}",
        top.drivers
    );
    assert!(driver.failure_dependence > 0.3, "{driver:?}");
    // the closing axis is the reference x here
    assert!(driver.axis_in_reference[0].abs() > 0.99);
    let overall = d.driving_axes().next().unwrap();
    assert_eq!(overall.axis, "gripper_x");
    assert!(top.message.contains("gripper_x"), "{}", top.message);

    // the next-best view looks across x (from above), not along it
    let look_along_x = CandidateView {
        name: "along_x".into(),
        reference_from_camera: Pose::from_parts(
            Translation3::new(0.0, 0.1, 0.1),
            UnitQuaternion::rotation_between(&Vector3::z(), &Vector3::x()).unwrap(),
        ),
    };
    let look_down = CandidateView {
        name: "from_above".into(),
        reference_from_camera: Pose::from_parts(
            Translation3::new(0.6, 0.1, 1.0),
            UnitQuaternion::rotation_between(&Vector3::z(), &-Vector3::z())
                .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)),
        ),
    };
    let s = suggest_view(&d, &[look_along_x, look_down]).unwrap();
    assert_eq!(s.name, "from_above", "{s:?}");
}

#[test]
fn lateral_spread_beyond_the_groove_fails_alignment_along_gripper_y() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    // the groove mouth is +-9 mm across the pad (gripper y = reference y for this grasp)
    let samples = PoseSamples::gaussian(&est, [0.001, 0.02, 0.001], [0.0; 3], 1000, 4);
    let d = decide(&can, &gripper, &est, &samples, &query(Some(top_grasp(&can, 0.03)))).unwrap();
    assert_eq!(d.decision, Verdict::Observe);
    let align = d
        .reasons
        .iter()
        .find(|r| r.test == FailureTest::Alignment)
        .expect("alignment fails");
    assert!(align.failure_share > 0.3, "{:#?}", d.reasons);
    assert_eq!(align.drivers[0].axis, "gripper_y");
    assert_eq!(align.drivers[0].motion, Motion::Translation);
    // the same spread within the groove passes
    let narrow = PoseSamples::gaussian(&est, [0.001, 0.003, 0.001], [0.0; 3], 1000, 5);
    let d = decide(&can, &gripper, &est, &narrow, &query(Some(top_grasp(&can, 0.03)))).unwrap();
    assert_eq!(d.decision, Verdict::Grasp, "{:#?}", d.reasons);
}

/// Rotations uniform in +-`half_range_rad` about the reference z through the object's origin.
fn spin_samples(estimate: &Pose, half_range_rad: f64, n: usize, seed: u64) -> PoseSamples {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let poses = (0..n)
        .map(|_| {
            let a = rng.random_range(-half_range_rad..half_range_rad);
            rotate_about_origin(
                estimate,
                &UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a),
                &Vector3::zeros(),
            )
        })
        .collect();
    PoseSamples {
        poses,
        effective_sample_size: n as f64,
    }
}

#[test]
fn rotation_about_the_cans_axis_grasps_about_the_cracker_boxs_long_axis_observes() {
    let gripper = Gripper::default_parallel_jaw();
    let spread = std::f64::consts::PI; // fully unknown about the vertical axis

    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let d = decide(&can, &gripper, &est, &spin_samples(&est, spread, 1000, 6), &query(None)).unwrap();
    assert_eq!(d.decision, Verdict::Grasp, "{:#?}", d.reasons);
    assert!(d.p_success > 0.97);

    // the cracker box stands on its small face: its long axis (z, 213 mm) is vertical
    let cracker = GraspObject::new(&ycb("003_cracker_box")).unwrap();
    let est = standing(&cracker);
    let d = decide(
        &cracker,
        &gripper,
        &est,
        &spin_samples(&est, spread, 1000, 7),
        &query(None),
    )
    .unwrap();
    assert_eq!(d.decision, Verdict::Observe);
    assert!(d.p_success < 0.6, "{}", d.p_success);
    let driver = d.driving_axes().next().expect("a driving axis");
    assert_eq!(driver.motion, Motion::Rotation, "{:#?}", d.uncertainty);
    // the rotation that drives it is about the vertical (reference z), the box's long axis
    assert!(driver.axis_in_reference[2].abs() > 0.99, "{driver:?}");
    assert!(driver.axis_in_object[2].abs() > 0.99, "{driver:?}");
    // rotation about the vertical is in-plane for a camera looking down: that view is best
    let side_view = CandidateView {
        name: "side".into(),
        reference_from_camera: Pose::from_parts(
            Translation3::new(0.0, 0.1, 0.1),
            UnitQuaternion::rotation_between(&Vector3::z(), &Vector3::x()).unwrap(),
        ),
    };
    let top_view = CandidateView {
        name: "top".into(),
        reference_from_camera: Pose::from_parts(
            Translation3::new(0.6, 0.1, 1.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        ),
    };
    assert_eq!(suggest_view(&d, &[side_view, top_view]).unwrap().name, "top");
    // but a small spread about the same axis still grasps: the flat pads square the box
    let d = decide(
        &cracker,
        &gripper,
        &est,
        &spin_samples(&est, 3f64.to_radians(), 1000, 8),
        &query(None),
    )
    .unwrap();
    assert_eq!(d.decision, Verdict::Grasp, "{:#?}", d.reasons);
}

#[test]
fn a_grasp_planned_too_low_fails_on_the_table() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let (z_lo, _) = can.extent_along(&Vector3::z());
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.003; 3], 500, 9);
    // side grasp: approach along object +x, close along y; the fingers' width is vertical
    let side = |tcp_height_m: f64| {
        let g = Grasp::new(&can, &Vector3::x(), &Vector3::y(), 0.03, "side").unwrap();
        let mut pose = g.object_from_gripper;
        pose.translation.vector.z = z_lo + tcp_height_m;
        Grasp::from_pose(&can, pose, "side")
    };
    let low = decide(&can, &gripper, &est, &samples, &query(Some(side(0.010)))).unwrap();
    assert_eq!(low.decision, Verdict::Observe);
    assert_eq!(low.p_success, 0.0);
    assert_eq!(low.reasons[0].test, FailureTest::Table, "{:#?}", low.reasons);
    assert_eq!(low.reasons[0].failure_share, 1.0);
    let ok = decide(&can, &gripper, &est, &samples, &query(Some(side(0.06)))).unwrap();
    assert_eq!(ok.decision, Verdict::Grasp, "{:#?}", ok.reasons);
    // without a table the low grasp is fine
    let mut q = query(Some(side(0.010)));
    q.support_plane = None;
    let no_table = decide(&can, &gripper, &est, &samples, &q).unwrap();
    assert!(no_table.reasons.iter().all(|r| r.test != FailureTest::Table));
    assert_eq!(no_table.decision, Verdict::Grasp, "{:#?}", no_table.reasons);
}

#[test]
fn two_modes_box_and_its_turned_copy_p_reflects_both() {
    let gripper = Gripper::default_parallel_jaw();
    // 160 x 60 x 210 mm: only the 60 mm side fits the stroke
    let bx = GraspObject::new(&mesh::builtin("box").unwrap()).unwrap();
    let est = standing(&bx);
    let grasp = Grasp::new(&bx, &-Vector3::z(), &Vector3::y(), 0.03, "top, close y").unwrap();
    let turned = rotate_about_origin(
        &est,
        &UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
        &Vector3::zeros(),
    );
    let flipped = rotate_about_origin(
        &est,
        &UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        &Vector3::zeros(),
    );
    for (other, w_est, expect) in [(turned, 0.7, 0.7), (turned, 0.4, 0.4), (flipped, 0.5, 1.0)] {
        let a = PoseSamples::gaussian(&est, [0.001; 3], [0.005; 3], (1000.0 * w_est) as usize, 10);
        let b = PoseSamples::gaussian(&other, [0.001; 3], [0.005; 3], 1000 - a.poses.len(), 11);
        let mut poses = a.poses;
        poses.extend(b.poses);
        let samples = PoseSamples {
            poses,
            effective_sample_size: 1000.0,
        };
        let d = decide(&bx, &gripper, &est, &samples, &query(Some(grasp.clone()))).unwrap();
        assert!(
            (d.p_success - expect).abs() < 0.03,
            "p {} expected {expect}",
            d.p_success
        );
        if expect < 0.9 {
            assert_eq!(d.decision, Verdict::Observe);
            assert_eq!(d.reasons[0].test, FailureTest::Approach);
            assert!((d.reasons[0].failure_share - (1.0 - expect)).abs() < 0.03);
        } else {
            assert_eq!(d.decision, Verdict::Grasp);
        }
    }
}

#[test]
fn bad_queries_are_errors_not_panics() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&mesh::builtin("can").unwrap()).unwrap();
    let est = standing(&can);
    let empty = PoseSamples {
        poses: vec![],
        effective_sample_size: 0.0,
    };
    assert!(decide(&can, &gripper, &est, &empty, &query(None)).is_err());
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.0; 3], 10, 12);
    let mut q = query(None);
    q.threshold = 1.5;
    assert!(decide(&can, &gripper, &est, &samples, &q).is_err());
    let mut q = query(None);
    q.support_plane = Some(SupportPlane {
        normal: [0.0, 0.0, 0.0],
        point_m: [0.0; 3],
    });
    assert!(decide(&can, &gripper, &est, &samples, &q).is_err());
    let mut bad = samples.clone();
    bad.poses[3].translation.vector.x = f64::NAN;
    let err = decide(&can, &gripper, &est, &bad, &query(None)).unwrap_err();
    assert!(err.to_string().contains("sample 3"), "{err}");
    // an object wider than the stroke on every axis has no candidate
    let big = GraspObject::new(&mesh::builtin_box([0.2, 0.2, 0.2], [[1, 1, 1], [2, 2, 2]])).unwrap();
    assert!(decide(&big, &gripper, &standing(&big), &samples, &query(None)).is_err());
}

#[test]
fn pads_above_the_object_fail_contact_and_a_palm_too_deep_fails_the_approach() {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.003; 3], 300, 13);
    // TCP 3 cm above the lid: the pads (35 mm long) close on air
    let d = decide(&can, &gripper, &est, &samples, &query(Some(top_grasp(&can, -0.03)))).unwrap();
    assert_eq!(d.p_success, 0.0);
    assert_eq!(d.reasons[0].test, FailureTest::Contact, "{:#?}", d.reasons);
    assert_eq!(d.reasons[0].failure_share, 1.0);
    // TCP deeper than the fingers reach: the palm lands on the lid
    let deep = top_grasp(&can, gripper.reach_m() + 0.01);
    let d = decide(&can, &gripper, &est, &samples, &query(Some(deep))).unwrap();
    assert_eq!(d.p_success, 0.0);
    assert_eq!(d.reasons[0].test, FailureTest::Approach, "{:#?}", d.reasons);
}

#[test]
fn a_flat_object_gets_its_top_grasp_lifted_clear_of_the_table() {
    let gripper = Gripper::default_parallel_jaw();
    // 3 cm thin: a grasp to the middle would put the finger tips into the table
    let flat = GraspObject::new(&mesh::builtin_box([0.16, 0.12, 0.03], [[1, 1, 1], [2, 2, 2]])).unwrap();
    let est = standing(&flat);
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.003; 3], 300, 14);
    let d = decide(&flat, &gripper, &est, &samples, &query(None)).unwrap();
    assert_eq!(d.decision, Verdict::Grasp, "{:#?}", d.reasons);
    assert!(d.grasp.label.contains("lifted"), "{}", d.grasp.label);
    // the top grasp is lifted: its finger tips end above the table by the clearance, the pads
    // still on the box
    let top = d
        .candidates
        .iter()
        .find(|c| c.grasp.label.starts_with("top"))
        .expect("a top candidate");
    assert!(top.grasp.label.contains("lifted"), "{}", top.grasp.label);
    let reference_from_gripper = est * top.grasp.object_from_gripper;
    let tip = reference_from_gripper * nalgebra::Point3::new(0.0, 0.0, gripper.tip_z_m());
    assert!(tip.z >= gripper.table_clearance_m, "{}", tip.z);
    assert!(top.grasp.depth_m > 0.0 && top.grasp.depth_m < 0.015);
    assert!(top.p_success > 0.95, "{}", top.p_success);
}

/// A map that says a raw rate of 0.9 and above succeeds 97 % of the time, below that 40 %.
fn test_map(hash: &str) -> pregrasp::grasp::CalibrationMap {
    use pregrasp::grasp::calibrated::{IsotonicBlock, MAP_VERSION};
    use pregrasp::grasp::{GraspRule, RuleQuantity};
    pregrasp::grasp::CalibrationMap {
        version: MAP_VERSION,
        settings_hash: hash.into(),
        settings: serde_json::json!({}),
        fitted_at: "2026-12-02T00:00:00Z".into(),
        fitted_on: vec!["hand-made".into()],
        n_decisions: 1000,
        n_successes: 685,
        n_approaches: 10,
        n_samples: None,
        blocks: vec![
            IsotonicBlock {
                raw_lo: 0.0,
                raw_hi: 0.89,
                raw_mean: 0.5,
                count: 500,
                successes: 200,
            },
            IsotonicBlock {
                raw_lo: 0.9,
                raw_hi: 1.0,
                raw_mean: 0.95,
                count: 500,
                successes: 485,
            },
        ],
        rule: GraspRule {
            quantity: RuleQuantity::Calibrated,
            threshold: 0.95,
            run_length: 1,
        },
        smoothing_time_constant_s: 0.0,
        min_block_count: 20,
        spread_strata: Vec::new(),
    }
}

#[test]
fn a_calibrated_answer_carries_the_raw_rate_beside_the_mapped_one() {
    use pregrasp::grasp::{Calibration, RuleQuantity, decide_calibrated};
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    // few effective samples: the raw rule (Wilson lower bound >= 0.9) observes
    let mut samples = PoseSamples::gaussian(&est, [0.001; 3], [0.005; 3], 1000, 2);
    samples.effective_sample_size = 20.0;
    let grasp = Some(top_grasp(&can, 0.03));
    let raw = decide(&can, &gripper, &est, &samples, &query(grasp.clone())).unwrap();
    assert_eq!(raw.decision, Verdict::Observe);
    assert!(matches!(
        raw.calibration,
        pregrasp::grasp::CalibrationStatus::Absent { .. }
    ));
    assert_eq!(raw.p_success, raw.p_success_raw);
    assert_eq!(raw.ci95, raw.ci95_raw);

    let text = serde_json::to_string(&test_map("running")).unwrap();
    let cal = Calibration::load(&text, "running");
    let mut q = query(grasp.clone());
    q.threshold = cal.rule().threshold;
    let d = decide_calibrated(&can, &gripper, &est, &samples, &q, &cal).unwrap();
    assert_eq!(d.p_success_raw, raw.p_success_raw);
    assert_eq!(d.ci95_raw, raw.ci95_raw);
    let m = cal.map().unwrap();
    assert!((d.p_success - m.apply(d.p_success_raw, None)).abs() < 1e-12);
    assert!(d.ci95[0] <= d.p_success && d.p_success <= d.ci95[1]);
    assert!(d.calibration.is_calibrated() && d.calibration.map_settings_hash() == Some("running"));
    assert_eq!(d.rule.quantity, RuleQuantity::Calibrated);
    // the map's 0.97 clears its rule's 0.95 where the raw Wilson bound did not clear 0.9
    assert_eq!(d.decision, Verdict::Grasp, "{} {:?}", d.p_success, d.ci95);
    let json = serde_json::to_value(&d).unwrap();
    for k in ["p_success", "p_success_raw", "ci95", "ci95_raw", "calibration", "rule"] {
        assert!(json.get(k).is_some(), "{k}");
    }

    // a map fitted for other settings: the raw answer and the raw rule, with the warning
    let stale = Calibration::load(&text, "changed tracker");
    let s = decide_calibrated(&can, &gripper, &est, &samples, &query(grasp), &stale).unwrap();
    assert_eq!(s.decision, Verdict::Observe);
    assert_eq!(s.p_success, s.p_success_raw);
    assert!(matches!(
        s.calibration,
        pregrasp::grasp::CalibrationStatus::Stale { .. }
    ));
    assert!(s.calibration.warning().unwrap().contains("changed tracker"));
}

#[test]
fn a_run_rule_grasps_only_through_the_tracks_smoother() {
    use pregrasp::grasp::{Calibration, decide_calibrated};
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).unwrap();
    let est = standing(&can);
    let samples = PoseSamples::gaussian(&est, [0.001; 3], [0.005; 3], 1000, 3);
    let mut map = test_map("running");
    map.rule.run_length = 2;
    map.smoothing_time_constant_s = 1.0;
    let cal = Calibration::load(&serde_json::to_string(&map).unwrap(), "running");
    let mut q = query(Some(top_grasp(&can, 0.03)));
    q.threshold = cal.rule().threshold;
    let one = decide_calibrated(&can, &gripper, &est, &samples, &q, &cal).unwrap();
    // one answer clears 0.95 but is not a run of two
    assert!(one.p_success >= 0.95, "{}", one.p_success);
    assert_eq!(one.decision, Verdict::Observe);
    assert!(one.smoothing.is_none());
    let mut smoother = cal.smoother();
    let mut first = one.clone();
    smoother.apply(0, &mut first, &cal);
    assert_eq!(first.decision, Verdict::Observe);
    let s = first.smoothing.expect("smoothed");
    assert_eq!((s.run, s.time_constant_s), (1, 1.0));
    assert_eq!(s.p_success_unsmoothed, one.p_success);
    // the same question at the next step completes the run; the raw rate stays the answer's own
    let mut second = one.clone();
    smoother.apply(100_000_000, &mut second, &cal);
    assert_eq!(second.decision, Verdict::Grasp);
    assert_eq!(second.smoothing.expect("smoothed").run, 2);
    assert_eq!(second.p_success_raw, one.p_success_raw);
}

/// The upright can under top grasps `depths_mm` deep, tilted about its own origin in steps of
/// 0.1 degree up to `max_steps` of them about the gripper's closing (x) and pad (y) axes: the
/// tilts at which the grasp fails on the can.
fn can_tilts_failing(depths_mm: &[u32], max_steps: i32) -> Vec<String> {
    let gripper = Gripper::default_parallel_jaw();
    let can = GraspObject::new(&ycb("002_master_chef_can")).expect("the can's mesh");
    let est = standing(&can);
    let samples = PoseSamples::gaussian(&est, [0.0; 3], [0.0; 3], 100, 1);
    let mut failing = Vec::new();
    for &depth_mm in depths_mm {
        let depth_m = f64::from(depth_mm) * 1e-3;
        let d = decide(&can, &gripper, &est, &samples, &query(Some(top_grasp(&can, depth_m)))).expect("decision");
        assert_eq!(d.p_success_raw, 1.0, "{}", d.grasp.label);
        for (name, axis_in_gripper) in [("x", Vector3::x()), ("y", Vector3::y())] {
            let axis = nalgebra::Unit::new_normalize(d.reference_from_gripper.rotation * axis_in_gripper);
            for step in -max_steps..=max_steps {
                let tilt_deg = f64::from(step) * 0.1;
                let r = UnitQuaternion::from_axis_angle(&axis, tilt_deg.to_radians());
                let tilted = rotate_about_origin(&est, &r, &Vector3::zeros());
                if !success_on_pose(&can, &gripper, &d.reference_from_gripper, &tilted, Some(&table())).expect("tested")
                {
                    failing.push(format!("{depth_mm} mm, {tilt_deg:+.1} deg about gripper {name}"));
                }
            }
        }
    }
    failing
}

#[test]
fn a_can_grasped_with_its_rim_at_the_pads_edge_keeps_the_grasp_when_tilted_a_little() {
    // Top grasps of the upright can 20 and 21 mm deep put the lid's rim at the pads' edge.
    // Tilted up to 2 degrees, the grasp must hold throughout: a rim meeting the finger a
    // fraction of a millimetre beyond the pad is held by the pad. Without the margin at the
    // pad's edge the contact test failed these grasps at -1.8 to -1.5 degrees about x and
    // -0.2 about y (20 mm), and -1.3 to -1.2 about y (21 mm), with success on both sides.
    let failing = can_tilts_failing(&[20, 21], 20);
    assert!(failing.is_empty(), "{failing:?}");
}

#[test]
fn a_can_grasped_on_its_scanned_facets_keeps_the_grasp_when_tilted_a_little() {
    // Top grasps of the upright can 10-30 mm deep, tilted up to 1.5 degrees, must hold
    // throughout: where the pad meets the can off its groove, the scan's facets under the pad
    // and the groove differ by a few degrees on what is one face of the real can, and the pad
    // squares such a face. With one face asked to lie within 0.5 degrees, the 11 mm grasp
    // failed at -1.1 degrees about y.
    let depths_mm: Vec<u32> = (10..=30).collect();
    let failing = can_tilts_failing(&depths_mm, 15);
    assert!(failing.is_empty(), "{failing:?}");
}
