//! Tracker scenarios on synthetic rendered scenes (coarse 10-degree grid, 160 x 120 images).

#![allow(clippy::unwrap_used)] // test helpers: a failure is a test failure

mod tracker_support;

use nalgebra::{UnitQuaternion, Vector3};
use pregrasp::geometry::Pose;
use pregrasp::tracker::{CameraMount, Detection, RobotOdometry, TrackStatus, Tracker, TrackerConfig};
use std::collections::BTreeMap;
use tracker_support::*;

fn box_symmetries() -> Vec<UnitQuaternion<f64>> {
    // the built-in box: +x half coloured differently, so only the flip about x remains
    vec![UnitQuaternion::from_axis_angle(
        &Vector3::x_axis(),
        std::f64::consts::PI,
    )]
}

#[test]
fn single_camera_converges_on_a_rendered_box() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.05, 0.02, 0.6);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let cam = look_at([-0.9, -0.3, 0.6], [0.0, 0.0, 0.08]);
    let truth = cam.inverse() * truth_world;
    // one view of the box leaves near-equal answers (before the detector's box weighed the
    // first step: 18 and 27-37 degrees off over ten filter seeds, half each, the truth's bin
    // holding the same mass in both; with it 21 degrees in four of five seeds, 27 in one):
    // five seeds, each judged by the truth's likelihood, the answers by their bound
    let mut errors = Vec::new();
    for seed in 1..=5 {
        let mut cams = BTreeMap::new();
        cams.insert("ext1".to_string(), CameraMount::Stationary { world_from_camera: cam });
        let config = TrackerConfig {
            seed,
            ..TrackerConfig::default()
        };
        let mut tracker = Tracker::new(config, cams, "ext1".into());
        tracker.add_object_model("box", mesh.clone(), cb.clone());
        for step in 0..8 {
            let f = frame("ext1", &cam, &scene, step == 0, true, 0.01, step);
            let rep = tracker.step(&[f], None).unwrap();
            let id = tracker.tracks()[0].id;
            let e = tracker.estimate(id).unwrap();
            let t = &tracker.tracks()[0];
            eprintln!(
                "seed {seed} step {step}: t_err {:.3} r_err {:.1} sim {:?} status {:?} std {:.3} ent {:.2} loglik {:.2} total {:.3}s",
                translation_error(&e.reference_from_object, &truth),
                rotation_error_deg(&e.reference_from_object.rotation, &truth.rotation, &box_symmetries()),
                t.best_similarity,
                t.status,
                e.translation_std_m,
                e.rotation_entropy,
                tracker.orientation_loglik(id, &truth.rotation).unwrap(),
                rep.timings.total_s
            );
        }
        let id = tracker.tracks()[0].id;
        let e = tracker.estimate(id).unwrap();
        assert_eq!(tracker.tracks()[0].status, TrackStatus::Tracking);
        assert!(translation_error(&e.reference_from_object, &truth) < 0.03);
        // the true rotation's bin holds far more than a uniform share (ln(1 / 24,624) = -10.1)
        let ll = tracker.orientation_loglik(id, &truth.rotation).unwrap();
        assert!(ll > -8.0, "seed {seed}: log-likelihood of the truth {ll:.2}");
        errors.push(rotation_error_deg(
            &e.reference_from_object.rotation,
            &truth.rotation,
            &box_symmetries(),
        ));
    }
    assert!(errors.iter().all(|e| *e < 40.0), "{errors:?}");
    assert!(
        errors.iter().filter(|e| **e < 25.0).count() >= 3,
        "most seeds settle on the nearer answer: {errors:?}"
    );
}

/// Yaw error (degrees) of an estimate about the mug's own axis, and the error of the axis.
fn mug_errors(est: &UnitQuaternion<f64>, truth: &UnitQuaternion<f64>) -> (f64, f64) {
    let rel = truth.inverse() * est; // object_truth_from_object_est
    let axis_err = (rel * Vector3::z()).angle(&Vector3::z()).to_degrees();
    let x = rel * Vector3::x();
    let yaw = x.y.atan2(x.x).to_degrees().abs();
    (yaw, axis_err)
}

fn run_mug(views: &[(&str, pregrasp::geometry::Pose)], steps: u64) -> (f64, f64, f64, f64, f64) {
    let mesh = pregrasp::mesh::builtin("mug").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.0, 0.0, std::f64::consts::PI);
    let scene = Scene::new(vec![("mug".into(), mesh.clone(), truth_world)]);
    let mut cams = BTreeMap::new();
    for (name, pose) in views {
        cams.insert(
            name.to_string(),
            CameraMount::Stationary {
                world_from_camera: *pose,
            },
        );
    }
    let reference = views[0].0.to_string();
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, reference);
    tracker.add_object_model("mug", mesh.clone(), cb);
    let truth = views[0].1.inverse() * truth_world;
    for step in 0..steps {
        let frames: Vec<_> = views
            .iter()
            .map(|(n, p)| frame(n, p, &scene, step == 0, true, 0.005, step * 7 + n.len() as u64))
            .collect();
        tracker.step(&frames, None).unwrap();
    }
    let id = tracker.tracks()[0].id;
    let e = tracker.estimate(id).unwrap();
    let (yaw, axis) = mug_errors(&e.reference_from_object.rotation, &truth.rotation);
    let ll = tracker.orientation_loglik(id, &truth.rotation).unwrap();
    let rot = |m: &pregrasp::tracker::RotationMode| {
        let q = m.rotation_xyzw;
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]))
    };
    eprintln!(
        "{} views: yaw err {yaw:.1} axis err {axis:.1} loglik {ll:.2} entropy {:.2} t_err {:.3} modes {:?}",
        views.len(),
        e.rotation_entropy,
        translation_error(&e.reference_from_object, &truth),
        e.rotation_modes
            .iter()
            .map(|m| {
                let (yaw, axis) = mug_errors(&rot(m), &truth.rotation);
                format!("{:.3} (yaw {yaw:.0}, axis {axis:.0})", m.mass)
            })
            .collect::<Vec<_>>()
    );
    // mass of the modes within 20 degrees (two 10-degree bins) of the top one (mode
    // clustering may split one hypothesis that straddles bin boundaries into modes 15-17
    // degrees apart)
    let top = rot(&e.rotation_modes[0]);
    let near_top: f64 = e
        .rotation_modes
        .iter()
        .filter(|m| rot(m).angle_to(&top).to_degrees() < 20.0)
        .map(|m| m.mass)
        .sum();
    (yaw, axis, ll, e.rotation_entropy, near_top)
}

/// The paper's Fig. 4: a mug whose handle is hidden from one camera; that camera alone cannot
/// tell the rotation about the mug's axis, a second camera that sees the handle can, and the
/// fused distribution is concentrated where the single view's is spread.
#[test]
fn second_view_resolves_the_hidden_handle() {
    // handle points to world -x; camera A looks from +x, 15 deg above the mug's middle, so
    // that the handle stays hidden behind the body (from 45 deg above, as before encoder v5,
    // its red top shows over the rim, and the colour's own code found it: single view 0.94 of
    // the mass near the top mode)
    let cam_a = look_at([0.45, 0.0, 0.16], [0.0, 0.0, 0.045]);
    let cam_b = look_at([0.0, -0.35, 0.4], [0.0, 0.0, 0.045]);
    let (_, _, ll_a, ent_a, top_a) = run_mug(&[("a", cam_a)], 5);
    let (yaw_ab, axis_ab, ll_ab, ent_ab, top_ab) = run_mug(&[("a", cam_a), ("b", cam_b)], 5);
    assert!(
        yaw_ab < 25.0 && axis_ab < 20.0,
        "fused estimate: yaw {yaw_ab} axis {axis_ab}"
    );
    // the single view spreads its mass over the hidden handle's positions (whichever it
    // happens to favour); the fused one concentrates it
    assert!(ent_a > ent_ab + 0.5, "single view entropy {ent_a} vs fused {ent_ab}");
    assert!(
        top_ab > top_a + 0.1,
        "mass within 20 deg of the top mode: fused {top_ab} vs single {top_a}"
    );
    // and the truth keeps a high likelihood in the fused distribution
    let uniform = -(pregrasp::geometry::RotationGrid::new(10).unwrap().len() as f64).ln();
    assert!(ll_ab > uniform + 3.0, "fused truth loglik {ll_ab} (single {ll_a})");
}

fn planar(x: f64, y: f64, yaw: f64) -> Pose {
    Pose::from_parts(
        nalgebra::Translation3::new(x, y, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
    )
}

fn odometry(odom_from_base: Pose, base_from_camera: Pose, step: i64) -> RobotOdometry {
    RobotOdometry {
        stamp_ns: step * 100_000_000,
        odom_from_base,
        world_from_odom: Pose::identity(),
        base_from_camera,
    }
}

/// Drives the robot camera (the reference frame) along `odom_from_base_at(step)` for 10 steps,
/// seeing the box only in the first 4 frames, so that only the odometry motion model (and the
/// re-binned rotation prior) keeps the estimate in the moving reference frame right; returns
/// the worst translation and rotation errors from step 2 on.
fn drive_blind(odom_from_base_at: impl Fn(i64) -> Pose) -> (f64, f64) {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 1.2, 0.1, 0.4);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let base_from_camera = look_at([0.1, 0.0, 0.6], [1.0, 0.0, 0.1]);
    let mut cams = BTreeMap::new();
    cams.insert("robot".to_string(), CameraMount::Robot { base_from_camera });
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, "robot".into());
    tracker.add_object_model("box", mesh.clone(), cb);
    let sym = box_symmetries();
    let mut worst_t: f64 = 0.0;
    let mut worst_r: f64 = 0.0;
    for step in 0..10i64 {
        let odom_from_base = odom_from_base_at(step);
        let world_from_camera = odom_from_base * base_from_camera;
        let frames = if step < 4 {
            vec![frame(
                "robot",
                &world_from_camera,
                &scene,
                step == 0,
                true,
                0.01,
                step as u64,
            )]
        } else {
            vec![]
        };
        tracker
            .step(&frames, Some(&odometry(odom_from_base, base_from_camera, step)))
            .unwrap();
        let truth = world_from_camera.inverse() * truth_world;
        let id = tracker.tracks()[0].id;
        let e = tracker.estimate(id).unwrap();
        let te = translation_error(&e.reference_from_object, &truth);
        let re = rotation_error_deg(&e.reference_from_object.rotation, &truth.rotation, &sym);
        eprintln!(
            "step {step}: t_err {te:.3} r_err {re:.1} std {:.3}",
            e.translation_std_m
        );
        if step >= 2 {
            worst_t = worst_t.max(te);
            worst_r = worst_r.max(re);
        }
        let w = tracker.world_from_reference();
        assert!((w.translation.vector - world_from_camera.translation.vector).norm() < 1e-9);
    }
    (worst_t, worst_r)
}

/// The robot camera drives and turns towards the object, blind after the first frames.
#[test]
fn odometry_moves_the_distribution_with_the_robot_camera() {
    let (worst_t, worst_r) = drive_blind(|step| planar(0.05 * step as f64, 0.01 * step as f64, 0.04 * step as f64));
    assert!(worst_t < 0.05, "translation error while driving blind {worst_t}");
    assert!(worst_r < 25.0, "rotation error while driving blind {worst_r}");
}

/// The robot drives towards the object, then backs away along the same line, blind: driving
/// backwards must not read as half turns (which drew about a radian of heading noise per step
/// and scattered the particles by the object's distance).
#[test]
fn a_robot_that_backs_away_keeps_its_track() {
    let (worst_t, worst_r) = drive_blind(|step| {
        let s = if step < 5 { step } else { 10 - step } as f64;
        planar(0.05 * s, 0.01 * s, 0.02 * s)
    });
    assert!(worst_t < 0.05, "translation error while backing away blind {worst_t}");
    assert!(worst_r < 25.0, "rotation error while backing away blind {worst_r}");
}

/// Two external cameras; one drops out, then both: the track stays and its uncertainty grows
/// instead of collapsing; it is not declared lost.
#[test]
fn a_camera_dropping_out_keeps_the_track() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.0, 0.0, -0.3);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let c1 = look_at([-0.8, 0.2, 0.6], [0.0, 0.0, 0.08]);
    let c2 = look_at([0.3, -0.8, 0.6], [0.0, 0.0, 0.08]);
    let mut cams = BTreeMap::new();
    cams.insert("ext1".to_string(), CameraMount::Stationary { world_from_camera: c1 });
    cams.insert("ext2".to_string(), CameraMount::Stationary { world_from_camera: c2 });
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, "ext1".into());
    tracker.add_object_model("box", mesh.clone(), cb);
    let truth = c1.inverse() * truth_world;
    let sym = box_symmetries();
    let mut std_before = 0.0;
    for step in 0..12u64 {
        let frames = match step {
            0..=3 => vec![
                frame("ext1", &c1, &scene, step == 0, true, 0.01, step),
                frame("ext2", &c2, &scene, step == 0, true, 0.01, 100 + step),
            ],
            4..=7 => vec![frame("ext2", &c2, &scene, false, true, 0.01, 100 + step)],
            _ => vec![],
        };
        tracker.step(&frames, None).unwrap();
        let t = &tracker.tracks()[0];
        let e = tracker.estimate(t.id).unwrap();
        let te = translation_error(&e.reference_from_object, &truth);
        let re = rotation_error_deg(&e.reference_from_object.rotation, &truth.rotation, &sym);
        eprintln!(
            "step {step}: t_err {te:.3} r_err {re:.1} std {:.4} seen_by {:?} comps {:?}",
            e.translation_std_m,
            t.seen_by,
            e.components.iter().map(|c| c.weight).collect::<Vec<_>>()
        );
        assert_eq!(tracker.tracks().len(), 1);
        assert_ne!(t.status, TrackStatus::Lost, "step {step}");
        if (2..=7).contains(&step) {
            assert!(te < 0.04, "step {step}: {te}");
            assert!(re < 25.0, "step {step}: {re}");
        }
        if step == 7 {
            std_before = e.translation_std_m;
            assert_eq!(e.components.len(), 2, "both cameras' components survive");
        }
        if step == 11 {
            assert!(e.translation_std_m > std_before, "uncertainty grows unseen");
            assert!(te < 0.06);
        }
    }
}

/// The object is moved away while no detector runs: the track is declared lost, and the next
/// detection restarts it at the new place. Two instances of one model are two tracks.
#[test]
fn a_lost_track_is_reinitialised_from_the_next_detection() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let cam = look_at([-0.9, -0.2, 0.7], [0.0, 0.0, 0.08]);
    let mut cams = BTreeMap::new();
    cams.insert("ext1".to_string(), CameraMount::Stationary { world_from_camera: cam });
    // two instances of one object, each its own track
    let config = TrackerConfig {
        max_tracks_per_object: 0,
        ..TrackerConfig::default()
    };
    let mut tracker = Tracker::new(config, cams, "ext1".into());
    tracker.add_object_model("box", mesh.clone(), cb);
    let a = on_table(&mesh, 0.0, -0.2, 0.3);
    let b = on_table(&mesh, 0.0, 0.25, 1.2);
    let moved = on_table(&mesh, 0.35, -0.15, 0.3);
    let two = Scene::new(vec![("box".into(), mesh.clone(), a), ("box".into(), mesh.clone(), b)]);
    for step in 0..3u64 {
        tracker
            .step(&[frame("ext1", &cam, &two, step == 0, true, 0.01, step)], None)
            .unwrap();
    }
    assert_eq!(tracker.tracks().len(), 2, "two instances, two tracks");
    let find = |tracker: &Tracker, truth: &Pose| -> (u64, f64) {
        tracker
            .tracks()
            .iter()
            .map(|t| {
                (
                    t.id,
                    translation_error(&tracker.estimate(t.id).unwrap().reference_from_object, truth),
                )
            })
            .min_by(|x, y| x.1.total_cmp(&y.1))
            .unwrap()
    };
    let (id_a, err_a) = find(&tracker, &(cam.inverse() * a));
    let (id_b, err_b) = find(&tracker, &(cam.inverse() * b));
    assert!(id_a != id_b && err_a < 0.03 && err_b < 0.03, "{err_a} {err_b}");
    // instance a is carried away (out of sight of its particles); no detections
    let after = Scene::new(vec![
        ("box".into(), mesh.clone(), moved),
        ("box".into(), mesh.clone(), b),
    ]);
    let mut lost_at = None;
    for step in 3..12u64 {
        let rep = tracker
            .step(&[frame("ext1", &cam, &after, false, true, 0.01, step)], None)
            .unwrap();
        let t = tracker.tracks().iter().find(|t| t.id == id_a).unwrap();
        eprintln!("step {step}: status {:?} sim {:?}", t.status, t.best_similarity);
        if rep.tracks_lost.contains(&id_a) {
            lost_at = Some(step);
            break;
        }
    }
    assert!(lost_at.is_some(), "the moved instance is declared lost");
    assert_eq!(
        tracker.tracks().iter().find(|t| t.id == id_b).unwrap().status,
        TrackStatus::Tracking
    );
    // the next detections restart it
    let rep = tracker
        .step(&[frame("ext1", &cam, &after, true, true, 0.01, 50)], None)
        .unwrap();
    assert_eq!(rep.tracks_reinitialised, vec![id_a]);
    assert!(rep.tracks_created.is_empty());
    let f = frame("ext1", &cam, &after, true, true, 0.01, 50);
    eprintln!("detections {:?}", f.detections);
    for step in 51..54u64 {
        tracker
            .step(&[frame("ext1", &cam, &after, false, true, 0.01, step)], None)
            .unwrap();
        let e = tracker.estimate(id_a).unwrap();
        eprintln!(
            "step {step}: err {:.3} sim {:?} truth {:?} est {:?}",
            translation_error(&e.reference_from_object, &(cam.inverse() * moved)),
            tracker.tracks().iter().find(|t| t.id == id_a).unwrap().best_similarity,
            (cam.inverse() * moved).translation.vector.as_slice(),
            e.reference_from_object.translation.vector.as_slice()
        );
    }
    let t = tracker.tracks().iter().find(|t| t.id == id_a).unwrap();
    assert_eq!(t.status, TrackStatus::Tracking);
    let e = tracker.estimate(id_a).unwrap();
    let err = translation_error(&e.reference_from_object, &(cam.inverse() * moved));
    assert!(err < 0.03, "re-initialised track error {err}");
}

/// A view that disagrees with the others (its extrinsics are off by a quarter turn about its
/// optical axis, so it sees the object but reports its rotation turned) must not wipe out the
/// distribution: the two agreeing views win, and the truth keeps a sensible likelihood.
#[test]
fn a_conflicting_view_does_not_wipe_out_the_distribution() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.0, 0.0, 0.5);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let ca = look_at([-0.8, -0.3, 0.6], [0.0, 0.0, 0.1]);
    let cbm = look_at([0.2, -0.85, 0.6], [0.0, 0.0, 0.1]);
    let cc = look_at([0.2, 0.85, 0.6], [0.0, 0.0, 0.1]);
    // what the tracker believes about camera c: turned by 90 degrees about its optical axis
    let cc_wrong = cc
        * Pose::from_parts(
            nalgebra::Translation3::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
        );
    let run = |floor: f32| -> (f64, f64) {
        let mut cams = BTreeMap::new();
        cams.insert("a".to_string(), CameraMount::Stationary { world_from_camera: ca });
        cams.insert("b".to_string(), CameraMount::Stationary { world_from_camera: cbm });
        cams.insert(
            "c".to_string(),
            CameraMount::Stationary {
                world_from_camera: cc_wrong,
            },
        );
        let mut cfg = TrackerConfig::default();
        cfg.observation.loglik_floor = floor;
        let mut tracker = Tracker::new(cfg, cams, "a".into());
        tracker.add_object_model("box", mesh.clone(), cb.clone());
        for step in 0..4u64 {
            // camera c's image is rendered from where it really is, named with the wrong pose
            let mut fc = frame("c", &cc, &scene, false, true, 0.01, 200 + step);
            fc.camera = "c".into();
            let frames = vec![
                frame("a", &ca, &scene, step == 0, true, 0.01, step),
                frame("b", &cbm, &scene, step == 0, true, 0.01, 100 + step),
                fc,
            ];
            tracker.step(&frames, None).unwrap();
        }
        let truth = ca.inverse() * truth_world;
        let id = tracker.tracks()[0].id;
        let e = tracker.estimate(id).unwrap();
        let re = rotation_error_deg(&e.reference_from_object.rotation, &truth.rotation, &box_symmetries());
        let ll = tracker.orientation_loglik(id, &truth.rotation).unwrap();
        eprintln!(
            "floor {floor}: rotation error {re:.1} deg, truth loglik {ll:.2}, seen by {:?}",
            tracker.tracks()[0].seen_by
        );
        (re, ll)
    };
    let (re, ll) = run(TrackerConfig::default().observation.loglik_floor);
    let uniform = -(pregrasp::geometry::RotationGrid::new(10).unwrap().len() as f64).ln();
    assert!(re < 25.0, "the agreeing views win: {re}");
    assert!(
        ll > uniform,
        "the truth keeps more than uniform mass: {ll} vs {uniform}"
    );
    // without the floor the conflicting view costs the truth far more
    let (_, ll_nofloor) = run(-1e6);
    assert!(ll > ll_nofloor + 1.0, "floored {ll} vs unfloored {ll_nofloor}");
}

#[test]
fn a_detection_that_matches_no_track_opens_one_only_below_the_cap() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let cam = look_at([-0.9, -0.2, 0.7], [0.0, 0.0, 0.08]);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), on_table(&mesh, 0.0, 0.0, 0.3))]);
    let tracks_after = |cap: usize| -> usize {
        let mut cams = BTreeMap::new();
        cams.insert("ext1".to_string(), CameraMount::Stationary { world_from_camera: cam });
        let config = TrackerConfig {
            max_tracks_per_object: cap,
            ..TrackerConfig::default()
        };
        let mut tracker = Tracker::new(config, cams, "ext1".into());
        tracker.add_object_model("box", mesh.clone(), cb.clone());
        for step in 0..3u64 {
            tracker
                .step(&[frame("ext1", &cam, &scene, step == 0, true, 0.01, step)], None)
                .unwrap();
        }
        assert_eq!(tracker.tracks().len(), 1);
        // a second box reported far from the tracked one (a detector's false positive, or a
        // camera that disagrees on where the object is)
        let mut f = frame("ext1", &cam, &scene, true, true, 0.01, 3);
        f.detections.push(Detection {
            object: "box".into(),
            bbox_xywh_px: [4.0, 4.0, 20.0, 20.0],
            score: 1.0,
        });
        tracker.step(&[f], None).unwrap();
        tracker.tracks().len()
    };
    assert_eq!(tracks_after(0), 2, "no cap: a new instance");
    assert_eq!(tracks_after(1), 1, "cap 1: the object keeps one track");
}

#[test]
fn a_second_camera_joins_the_track_at_its_first_detection_under_the_cap() {
    // The service caps tracks per object at one and steps whenever any camera has a frame, so
    // a second camera's first detection of a box usually arrives after the first camera has
    // already made the track `Tracking`. It must add that camera's component to the track
    // (one component per camera), not be dropped and not open a second track.
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let cam1 = look_at([-0.9, -0.2, 0.7], [0.0, 0.0, 0.08]);
    let cam2 = look_at([0.3, -0.9, 0.7], [0.0, 0.0, 0.08]);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), on_table(&mesh, 0.0, 0.0, 0.3))]);
    let mut cams = BTreeMap::new();
    cams.insert(
        "ext1".to_string(),
        CameraMount::Stationary {
            world_from_camera: cam1,
        },
    );
    cams.insert(
        "ext2".to_string(),
        CameraMount::Stationary {
            world_from_camera: cam2,
        },
    );
    let config = TrackerConfig {
        max_tracks_per_object: 1,
        ..TrackerConfig::default()
    };
    let mut tracker = Tracker::new(config, cams, "ext1".into());
    tracker.add_object_model("box", mesh.clone(), cb);
    tracker
        .step(&[frame("ext1", &cam1, &scene, true, true, 0.01, 0)], None)
        .unwrap();
    assert_eq!(tracker.tracks().len(), 1);
    let id = tracker.tracks()[0].id;
    let cameras = |t: &Tracker| -> Vec<String> {
        t.estimate(id)
            .unwrap()
            .components
            .iter()
            .map(|c| c.camera.clone())
            .collect()
    };
    assert_eq!(cameras(&tracker), vec!["ext1".to_string()]);
    tracker
        .step(
            &[
                frame("ext1", &cam1, &scene, true, true, 0.01, 1),
                frame("ext2", &cam2, &scene, true, true, 0.01, 1),
            ],
            None,
        )
        .unwrap();
    assert_eq!(tracker.tracks().len(), 1, "one box, one track");
    let joined = cameras(&tracker);
    assert!(joined.contains(&"ext2".to_string()), "ext2 joined: {joined:?}");
    assert!(joined.contains(&"ext1".to_string()), "ext1 kept: {joined:?}");
    // both cameras' evidence moved the track, which stays on the box
    let truth = on_table(&mesh, 0.0, 0.0, 0.3);
    for s in 2..5u64 {
        tracker
            .step(
                &[
                    frame("ext1", &cam1, &scene, true, true, 0.01, s),
                    frame("ext2", &cam2, &scene, true, true, 0.01, s),
                ],
                None,
            )
            .unwrap();
    }
    assert_eq!(tracker.tracks().len(), 1);
    let est = tracker.estimate(id).unwrap();
    let ref_from_world = cam1.inverse();
    let err = translation_error(&est.reference_from_object, &(ref_from_world * truth));
    assert!(err < 0.03, "translation error {err} m");
    assert!(
        tracker.tracks()[0].seen_by.len() == 2,
        "{:?}",
        tracker.tracks()[0].seen_by
    );
}

/// Distinct particle positions of a track right after a step: resampling copies the parents
/// it keeps, so this counts the particles that survived the step's weights.
fn survivors(tracker: &Tracker, id: u64) -> usize {
    let mut seen: Vec<[u64; 3]> = tracker
        .particles(id)
        .unwrap()
        .iter()
        .map(|p| p.position_in_reference_m.map(f64::to_bits))
        .collect();
    seen.sort_unstable();
    seen.dedup();
    seen.len()
}

/// Survivors per step (steps 1..5) of a box track fed by one camera, or by it and `copies - 1`
/// more cameras at the same pose with the same images (the same evidence counted
/// `copies` times). The particles start widely spread so that their weights differ.
fn survivors_with_duplicated_view(tempering: f64, copies: usize) -> Vec<usize> {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let cam = look_at([-0.9, -0.2, 0.7], [0.0, 0.0, 0.08]);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), on_table(&mesh, 0.0, 0.0, 0.3))]);
    let names: Vec<String> = (0..copies).map(|i| format!("cam{i}")).collect();
    let cams: BTreeMap<String, CameraMount> = names
        .iter()
        .map(|n| (n.clone(), CameraMount::Stationary { world_from_camera: cam }))
        .collect();
    let config = TrackerConfig {
        view_weight_tempering: tempering,
        init_uv_jitter_rel: 0.3,
        init_depth_sigma_m: 0.06,
        // survivors are told apart by their positions: no regularising jitter
        spread: pregrasp::tracker::SpreadConfig::NONE,
        // the weights' tempering alone: turn mixing flattens every particle's marginal (with it
        // the counts were 168 / 164 / 133, the same order, a narrower margin), and the first
        // view's box, the only one, would weigh the first step apart from the copies' evidence
        // (with it 167 / 170 / 138)
        turn_share: 0.0,
        // the crops at the particles: aimed at the box (the toy box spans under 60 px), every
        // particle would get the same crop and the copies' evidence would not tell them apart
        observation: pregrasp::tracker::observation::ObservationConfig {
            detection_box: None,
            box_crops_below_px: 0.0,
            ..Default::default()
        },
        ..TrackerConfig::default()
    };
    let mut tracker = Tracker::new(config, cams, names[0].clone());
    tracker.add_object_model("box", mesh.clone(), cb);
    let mut out = Vec::new();
    for s in 0..5u64 {
        let first = frame(&names[0], &cam, &scene, s == 0, true, 0.02, s);
        // the copies never detect, so they add no particles: only their evidence
        let frames: Vec<_> = names
            .iter()
            .enumerate()
            .map(|(i, n)| pregrasp::tracker::CameraFrame {
                camera: n.clone(),
                detections: if i == 0 { first.detections.clone() } else { vec![] },
                ..first.clone()
            })
            .collect();
        tracker.step(&frames, None).unwrap();
        if s > 0 {
            out.push(survivors(&tracker, tracker.tracks()[0].id));
        }
    }
    out
}

#[test]
fn repeated_evidence_does_not_collapse_the_particle_weights() {
    // Views multiply their rotation evidence (Eq. 6), but their weights on translation
    // particles are not independent: counted eight times at full strength, the same evidence
    // makes the weights eight times as peaked in log space and fewer particles survive each
    // resampling. Tempered by the number of views (the default), they stay as peaked as one
    // view's.
    let one: usize = survivors_with_duplicated_view(1.0, 1).iter().sum();
    let eight: usize = survivors_with_duplicated_view(1.0, 8).iter().sum();
    let eight_plain: usize = survivors_with_duplicated_view(0.0, 8).iter().sum();
    eprintln!("survivors over 4 steps: one view {one}, eight copies {eight}, eight copies untempered {eight_plain}");
    assert!(
        eight as f64 >= 0.8 * one as f64,
        "tempered: {eight} survivors with eight copies of the view against {one} with one"
    );
    // measured: one view 164, eight copies 165, untempered 129 (earlier trackers: 152 / 160 /
    // 117; before the spawn depth moved to the box's lower quartile: 149 / 157 / 102)
    assert!(
        (eight_plain as f64) < 0.8 * one.min(eight) as f64,
        "untempered, repeated evidence should thin the particles: {eight_plain} against {one}"
    );
}

/// Whether the robot's camera sees a track comes from its own frames: a step without one
/// keeps the answer (cameras publish at their own rates), a frame that looks away makes it
/// `false`, and seeing the object again makes it `true` (the grasp decision answers `observe`
/// in between).
#[test]
fn the_reference_camera_sees_a_track_only_in_frames_that_show_it() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 1.2, 0.1, 0.4);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let base_from_camera = look_at([0.1, 0.0, 0.6], [1.0, 0.0, 0.1]);
    let looking_away = look_at([0.1, 0.0, 0.6], [-1.0, 0.5, 0.1]);
    let mut cams = BTreeMap::new();
    cams.insert("robot".to_string(), CameraMount::Robot { base_from_camera });
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, "robot".into());
    tracker.add_object_model("box", mesh.clone(), cb);
    let mut seen = Vec::new();
    for step in 0..7i64 {
        // 0-2: sees the box; 3: no frame; 4-5: the camera turned away; 6: sees it again
        let camera = if (4..=5).contains(&step) {
            looking_away
        } else {
            base_from_camera
        };
        let frames = match step {
            3 => vec![],
            _ => vec![frame(
                "robot",
                &camera,
                &scene,
                step == 0 || step == 6,
                true,
                0.01,
                step as u64,
            )],
        };
        let odom = RobotOdometry {
            base_from_camera: camera,
            ..odometry(Pose::identity(), base_from_camera, step)
        };
        tracker.step(&frames, Some(&odom)).unwrap();
        let id = tracker.tracks()[0].id;
        seen.push(tracker.reference_sees(id).expect("a track"));
    }
    assert_eq!(seen, [true, true, true, true, false, false, true]);
}

/// A mug 20 px across, 1 m away: a particle 2 cm to the side crops it a few pixels off centre,
/// and its code is another view's; aimed at the detector's box (at each particle's own depth),
/// every particle's crop is the mug's own (`observation.box_crops_below_px`).
#[test]
fn crops_aimed_at_the_box_read_a_small_far_mug_as_its_own_crop() {
    use pregrasp::tracker::observation::{ViewImage, box_aimed, encode_particles, nearest_box, object_size_px};
    // the origin moved to the box's centre, as the YCB meshes have it
    let mut mesh = pregrasp::mesh::builtin("mug").unwrap();
    let c = mesh.bounds().center_m();
    for v in &mut mesh.vertices_m {
        for k in 0..3 {
            v[k] -= c[k] as f32;
        }
    }
    let cb = coarse_codebook(&mesh);
    let world_from_mug = on_table(&mesh, 0.0, 0.0, 0.5);
    let scene = Scene::new(vec![("mug".into(), mesh.clone(), world_from_mug)]);
    let cam = look_at([0.0, -1.0, 0.35], [0.0, 0.0, 0.045]);
    let f = frame("a", &cam, &scene, true, true, 0.01, 3);
    let truth = (cam.inverse() * world_from_mug).translation.vector;
    let k = &f.intrinsics;
    assert!(object_size_px(&cb, k, truth.z) < 30.0, "a small mug");
    let positions: Vec<Vector3<f64>> = [
        Vector3::zeros(),
        Vector3::new(0.02, 0.0, 0.0),
        Vector3::new(0.0, -0.02, 0.0),
        Vector3::new(-0.015, 0.015, 0.05),
    ]
    .iter()
    .map(|o| truth + o)
    .collect();
    let img = ViewImage {
        intrinsics: k,
        depth: &f.depth,
        color: f.color.as_ref(),
    };
    let (at_particles, ..) = encode_particles(&cb, &img, &positions);
    let (centre, _) = nearest_box(k, &f.detections, "mug", &positions[1], 0.25).expect("the mug's box");
    let (aimed, valid, ..) = encode_particles(&cb, &img, &box_aimed(k, centre, &positions));
    assert!(valid.iter().all(|v| *v));
    let kd = cb.code_dim();
    let cos = |a: &[f32], i: usize, b: &[f32], j: usize| -> f32 {
        let (x, y) = (&a[i * kd..(i + 1) * kd], &b[j * kd..(j + 1) * kd]);
        let dot: f32 = x.iter().zip(y).map(|(p, q)| p * q).sum();
        let n = |v: &[f32]| v.iter().map(|p| p * p).sum::<f32>().sqrt();
        dot / (n(x) * n(y))
    };
    for p in 1..positions.len() {
        let off = cos(&at_particles, p, &at_particles, 0);
        let on = cos(&aimed, p, &at_particles, 0);
        eprintln!("particle {p}: at its projection {off:.3}, aimed {on:.3}");
        // the deeper particle crops at its own scale and depth, a little off the truth's
        assert!(on > 0.8, "particle {p}: aimed crop's code against the truth's {on}");
        assert!(
            on > off + 0.2,
            "particle {p}: aimed {on} against its own projection {off}"
        );
    }
}

/// A mug whose origin is the middle of its body, not of its box, seen with its handle to the
/// side (the box's centre a tenth of the crop off the origin's projection) and cropped at the
/// detector's box: its crop is its own template centred on the box of its silhouette, so the
/// box-centred code table matches the true rotation far better than the origin-centred one
/// (`observation.box_codes`).
#[test]
fn a_crop_at_the_box_matches_the_box_centred_template_of_its_rotation() {
    use pregrasp::geometry::ray_rotation;
    use pregrasp::tracker::observation::{ViewImage, box_aimed, encode_particles, nearest_box};
    let mesh = pregrasp::mesh::builtin("mug").unwrap();
    let b = mesh.bounds();
    let offset = b.center_m().norm() / mesh.diameter_m();
    assert!(
        offset > 0.05,
        "the origin {offset} of the diameter off the box's centre"
    );
    let cb = pregrasp::tracker::Codebook::build(
        &pregrasp::tracker::codebook::CpuViews(&mesh),
        &mesh,
        pregrasp::geometry::RotationGrid::new(10).unwrap(),
        &pregrasp::tracker::CodebookConfig {
            box_table: true,
            ..pregrasp::tracker::CodebookConfig::coarse()
        },
    )
    .unwrap();
    let world_from_mug = on_table(&mesh, 0.0, 0.0, 0.0);
    let scene = Scene::new(vec![("mug".into(), mesh.clone(), world_from_mug)]);
    let cam = look_at([0.0, -0.6, 0.3], [0.0, 0.0, 0.045]);
    let f = frame("a", &cam, &scene, true, true, 0.0, 3);
    let view_from_mug = cam.inverse() * world_from_mug;
    let truth = view_from_mug.translation.vector;
    let k = &f.intrinsics;
    let img = ViewImage {
        intrinsics: k,
        depth: &f.depth,
        color: f.color.as_ref(),
    };
    let (centre, _) = nearest_box(k, &f.detections, "mug", &truth, 0.25).expect("the mug's box");
    let uv = k.project(&nalgebra::Point3::from(truth)).unwrap();
    let side_px = k.fx() * cb.crop_side_m() / truth.z;
    assert!(
        (centre[0] - uv[0]).abs() > 0.08 * side_px,
        "box centre {centre:?}, origin at {uv:?}"
    );
    let (code, valid, ..) = encode_particles(&cb, &img, &box_aimed(k, centre, &[truth]));
    assert!(valid[0]);
    let true_bin = cb
        .grid
        .flat_of(&(ray_rotation(&truth).inverse() * view_from_mug.rotation));
    let kd = cb.code_dim();
    let cos = |table: &pregrasp::tracker::codebook::Codes, bin: usize| -> f32 {
        let mut row = vec![0f32; kd];
        table.row_into(bin, &mut row);
        row.iter().zip(&code).map(|(a, b)| a * b).sum()
    };
    let rank = |box_centred: bool| {
        let t = cb.table(box_centred);
        let c = cos(t, true_bin);
        (c, (0..cb.n_bins()).filter(|b| cos(t, *b) > c).count())
    };
    let (on_origin, origin_rank) = rank(false);
    let (on_box, box_rank) = rank(true);
    eprintln!(
        "true bin: origin-centred {on_origin:.3} (rank {origin_rank}), box-centred {on_box:.3} (rank {box_rank})"
    );
    assert!(
        on_box > on_origin + 0.3,
        "box-centred {on_box} against origin-centred {on_origin}"
    );
    assert!(box_rank < origin_rank, "rank {box_rank} against {origin_rank}");
}
