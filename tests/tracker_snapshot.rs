//! Tracks started from a caller's prior, and snapshots restored into a fresh tracker
//! (coarse 10-degree grid, 160 x 120 images).

#![allow(clippy::unwrap_used)] // test helpers: a failure is a test failure

mod tracker_support;

use pregrasp::tracker::{CameraMount, TrackPrior, TrackStatus, Tracker, TrackerConfig, TrackerSnapshot};
use std::collections::BTreeMap;
use tracker_support::*;

fn rig() -> (pregrasp::geometry::Pose, BTreeMap<String, CameraMount>) {
    let cam = look_at([-0.9, -0.3, 0.6], [0.0, 0.0, 0.08]);
    let mut cams = BTreeMap::new();
    cams.insert("ext1".to_string(), CameraMount::Stationary { world_from_camera: cam });
    (cam, cams)
}

/// A box on the table seen by one stationary camera, with a tracker that knows the box
/// (10-degree codebook); [`tracked_box`] has tracked it for 5 steps.
struct TrackedBox {
    mesh: pregrasp::mesh::Mesh,
    cb: std::sync::Arc<pregrasp::tracker::Codebook>,
    scene: Scene,
    cam: pregrasp::geometry::Pose,
    cams: BTreeMap<String, CameraMount>,
    truth: pregrasp::geometry::Pose,
    tracker: Tracker,
}

/// The toy camera (160 x 120) sees the box at about 27 px, where the size weighting (by area or
/// by diameter) would keep the track broad for many steps, and crops aimed at the detector's
/// box would leave its position to the box and depth terms alone; these tests are about
/// snapshots of a converged one.
fn config() -> TrackerConfig {
    let mut config = TrackerConfig::default();
    config.observation.full_size_px = 0.0;
    config.observation.full_area_px = 0.0;
    config.observation.box_crops_below_px = 0.0;
    config
}

fn untracked_box() -> TrackedBox {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.05, 0.02, 0.6);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let (cam, cams) = rig();
    let mut tracker = Tracker::new(config(), cams.clone(), "ext1".into());
    tracker.add_object_model("box", mesh.clone(), cb.clone());
    TrackedBox {
        truth: cam.inverse() * truth_world,
        mesh,
        cb,
        scene,
        cam,
        cams,
        tracker,
    }
}

fn tracked_box() -> TrackedBox {
    let mut b = untracked_box();
    for step in 0..5 {
        let f = frame("ext1", &b.cam, &b.scene, step == 0, true, 0.01, step);
        b.tracker.step(&[f], None).unwrap();
    }
    b
}

/// The model's codebook on another grid.
fn codebook_on(
    mesh: &pregrasp::mesh::Mesh,
    step_deg: u32,
    like: &pregrasp::tracker::Codebook,
) -> std::sync::Arc<pregrasp::tracker::Codebook> {
    std::sync::Arc::new(
        pregrasp::tracker::Codebook::build(
            &pregrasp::tracker::codebook::CpuViews(mesh),
            mesh,
            pregrasp::geometry::RotationGrid::new(step_deg).unwrap(),
            &like.config,
        )
        .unwrap(),
    )
}

#[test]
fn a_prior_starts_a_track_with_its_pose_and_spread_then_evidence_takes_over() {
    let TrackedBox {
        scene,
        cam,
        truth,
        mut tracker,
        ..
    } = untracked_box();
    // The prior: 4 cm off the truth, rotation 30 degrees off with a 20-degree spread.
    let mut prior_pose = truth;
    prior_pose.translation.vector += nalgebra::Vector3::new(0.04, 0.0, 0.0);
    prior_pose.rotation =
        nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), 30f64.to_radians()) * truth.rotation;
    let prior = TrackPrior {
        reference_from_object: prior_pose,
        translation_std_m: 0.02,
        rotation_std_rad: Some(20f64.to_radians()),
    };
    assert!(tracker.start_track("nope", &prior).is_err());
    let bad = TrackPrior {
        translation_std_m: f64::NAN,
        ..prior
    };
    assert!(tracker.start_track("box", &bad).is_err());
    assert!(tracker.tracks().is_empty(), "a refused prior leaves no track");

    let id = tracker.start_track("box", &prior).unwrap();
    assert_eq!(tracker.tracks()[0].status, TrackStatus::Initialising);
    let e = tracker.estimate(id).expect("an estimate at once");
    // The estimate is the prior: mean within 1.5 std / sqrt(n) of the given position,
    // spread ~ sqrt(3) x 2 cm, rotation at the prior's (within a bin).
    assert!(translation_error(&e.reference_from_object, &prior_pose) < 0.01);
    assert!(
        (e.translation_std_m - 0.02 * 3f64.sqrt()).abs() < 0.01,
        "{}",
        e.translation_std_m
    );
    assert!(
        e.reference_from_object
            .rotation
            .angle_to(&prior_pose.rotation)
            .to_degrees()
            < 10.0
    );
    // The prior's rotation is more likely than one 90 degrees away.
    let far = nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), 1.57) * prior_pose.rotation;
    assert!(
        tracker.orientation_loglik(id, &prior_pose.rotation).unwrap()
            > tracker.orientation_loglik(id, &far).unwrap() + 3.0
    );

    // Frames without detections: the prior's track is the one that gets the evidence.
    for step in 0..6 {
        let f = frame("ext1", &cam, &scene, false, true, 0.01, step);
        tracker.step(&[f], None).unwrap();
    }
    assert_eq!(tracker.tracks().len(), 1);
    let e = tracker.estimate(id).unwrap();
    assert_eq!(tracker.tracks()[0].status, TrackStatus::Tracking);
    let err = translation_error(&e.reference_from_object, &truth);
    assert!(err < 0.025, "after evidence: {err} m (the prior was 4 cm off)");
}

#[test]
fn a_snapshot_restores_tracks_into_a_fresh_tracker_even_on_another_grid() {
    let TrackedBox {
        mesh,
        cb,
        scene,
        cam,
        cams,
        tracker,
        ..
    } = tracked_box();
    let id = tracker.tracks()[0].id;
    let before = tracker.estimate(id).unwrap();
    let snap = tracker.snapshot();
    // compact: far below the full state (bins x particles floats)
    let bytes = serde_json::to_vec(&snap).unwrap();
    let full = cb.grid.len() * tracker.particles(id).unwrap().len() * 4;
    assert!(
        bytes.len() * 20 < full,
        "{} bytes vs a full state of {full}",
        bytes.len()
    );
    let snap: TrackerSnapshot = serde_json::from_slice(&bytes).unwrap();

    // Same grid: the same estimate (up to resampling: the step's estimate is taken before
    // its resampling, the snapshot after).
    let mut fresh = Tracker::new(config(), cams.clone(), "ext1".into());
    assert!(fresh.restore_track(&snap.tracks[0]).is_err(), "no model yet");
    fresh.add_object_model("box", mesh.clone(), cb.clone());
    fresh.restore_frame(&snap).unwrap();
    fresh.restore_track(&snap.tracks[0]).unwrap();
    let after = fresh.estimate(id).unwrap();
    let (a, b) = (&fresh.tracks()[0], &tracker.tracks()[0]);
    assert_eq!(
        (a.id, &a.object, a.status, a.stamp_ns),
        (b.id, &b.object, b.status, b.stamp_ns)
    );
    let moved_m = translation_error(&after.reference_from_object, &before.reference_from_object);
    assert!(moved_m < 0.003, "{moved_m}");
    assert!(
        after
            .reference_from_object
            .rotation
            .angle_to(&before.reference_from_object.rotation)
            .to_degrees()
            < 3.0,
        "rotation moved on restore"
    );
    assert!((after.rotation_entropy - before.rotation_entropy).abs() < 0.2);
    // It keeps tracking, and a new track gets a new id.
    let f = frame("ext1", &cam, &scene, false, true, 0.01, 9);
    fresh.step(&[f], None).unwrap();
    assert_eq!(fresh.tracks().len(), 1);
    assert_eq!(fresh.tracks()[0].status, TrackStatus::Tracking);

    // Another grid (15 degrees): the mass moves to the nearest bins.
    let coarse = codebook_on(&mesh, 15, &cb);
    let mut other = Tracker::new(config(), cams, "ext1".into());
    other.add_object_model("box", mesh.clone(), coarse);
    other.restore_frame(&snap).unwrap();
    other.restore_track(&snap.tracks[0]).unwrap();
    let moved = other.estimate(id).unwrap();
    assert!(
        moved
            .reference_from_object
            .rotation
            .angle_to(&before.reference_from_object.rotation)
            .to_degrees()
            < 12.0
    );

    // Broken snapshots are refused and change nothing.
    let mut broken = snap.tracks[0].clone();
    broken.weights.pop();
    assert!(other.restore_track(&broken).is_err());
    let mut broken = snap.tracks[0].clone();
    broken.rotation_bins.push((u32::MAX, 1.0));
    assert!(other.restore_track(&broken).is_err());
    let mut broken = snap.tracks[0].clone();
    broken.sources[0] = "nowhere".into();
    assert!(other.restore_track(&broken).is_err());
    assert_eq!(other.estimate(id).unwrap(), moved);
    let mut v2 = snap.clone();
    v2.version += 1;
    assert!(other.restore_frame(&v2).is_err());
}

#[test]
fn a_finer_codebook_carries_the_tracks_over_instead_of_restarting_them() {
    let TrackedBox {
        mesh,
        cb,
        scene,
        cam,
        truth,
        mut tracker,
        ..
    } = tracked_box();
    let id = tracker.tracks()[0].id;
    let before = tracker.estimate(id).unwrap();
    // another grid arrives for the same model (8 degrees here, to stay fast)
    let other = codebook_on(&mesh, 9, &cb);
    tracker.add_object_model("box", mesh.clone(), other);
    assert_eq!(tracker.tracks().len(), 1);
    assert_eq!(
        tracker.tracks()[0].status,
        TrackStatus::Tracking,
        "carried over, not restarted"
    );
    let carried = tracker.estimate(id).unwrap();
    assert!(translation_error(&carried.reference_from_object, &before.reference_from_object) < 0.003);
    assert!(
        carried
            .reference_from_object
            .rotation
            .angle_to(&before.reference_from_object.rotation)
            .to_degrees()
            < 10.0
    );
    // and it keeps tracking on the new grid (no detections: the same track must take them)
    for step in 5..8 {
        let f = frame("ext1", &cam, &scene, false, true, 0.01, step);
        tracker.step(&[f], None).unwrap();
    }
    assert_eq!(tracker.tracks().len(), 1);
    assert_eq!(tracker.tracks()[0].status, TrackStatus::Tracking);
    let e = tracker.estimate(id).unwrap();
    assert!(translation_error(&e.reference_from_object, &truth) < 0.03);
}
