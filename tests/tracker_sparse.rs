//! The sparse coarse-to-fine step against its dense reference (every bin matched and kept) on
//! rendered scenes (10-degree grid, 160 x 120 images): the same answers, a mode found outside
//! the active bins, and a state that stays small once converged.

#![allow(clippy::unwrap_used)] // test helpers: a failure is a test failure

mod tracker_support;

use nalgebra::{UnitQuaternion, Vector3};
use pregrasp::geometry::Pose;
use pregrasp::tracker::{CameraMount, Codebook, TrackPrior, TrackStatus, Tracker, TrackerConfig};
use std::collections::BTreeMap;
use std::sync::Arc;
use tracker_support::*;

fn box_symmetries() -> Vec<UnitQuaternion<f64>> {
    vec![UnitQuaternion::from_axis_angle(
        &Vector3::x_axis(),
        std::f64::consts::PI,
    )]
}

struct Setup {
    mesh: pregrasp::mesh::Mesh,
    cb: Arc<Codebook>,
    scene: Scene,
    cams: Vec<(String, Pose)>,
    truth_world: Pose,
}

fn setup() -> Setup {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.05, 0.02, 0.6);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let cams = vec![
        ("ext1".to_string(), look_at([-0.9, -0.3, 0.6], [0.0, 0.0, 0.08])),
        ("ext2".to_string(), look_at([0.5, -0.8, 0.7], [0.0, 0.0, 0.08])),
    ];
    Setup {
        mesh,
        cb,
        scene,
        cams,
        truth_world,
    }
}

fn tracker(s: &Setup, dense: bool) -> Tracker {
    let mut config = TrackerConfig::default();
    config.matching.dense = dense;
    let mounts: BTreeMap<String, CameraMount> = s
        .cams
        .iter()
        .map(|(n, p)| (n.clone(), CameraMount::Stationary { world_from_camera: *p }))
        .collect();
    let mut t = Tracker::new(config, mounts, "ext1".into());
    t.add_object_model("box", s.mesh.clone(), s.cb.clone());
    t
}

/// Steps a tracker through the same frames; returns per step (rotation error modulo the box's
/// symmetry in degrees, log-likelihood of the true rotation, active bins).
fn run(s: &Setup, t: &mut Tracker, steps: u64, detections_from: u64) -> Vec<(f64, f64, usize)> {
    let truth = s.cams[0].1.inverse() * s.truth_world;
    (0..steps)
        .map(|step| {
            let frames: Vec<_> = s
                .cams
                .iter()
                .map(|(n, p)| frame(n, p, &s.scene, step == detections_from, true, 0.01, step))
                .collect();
            let rep = t.step(&frames, None).unwrap();
            let id = t.tracks()[0].id;
            let e = t.estimate(id).unwrap();
            let err = rotation_error_deg(&e.reference_from_object.rotation, &truth.rotation, &box_symmetries());
            let ll = t.orientation_loglik(id, &truth.rotation).unwrap();
            eprintln!(
                "step {step}: r_err {err:.1} loglik {ll:.2} matched {} active {} total {:.3}s",
                rep.matched_bins, rep.active_bins, rep.timings.total_s
            );
            (err, ll, rep.active_bins)
        })
        .collect()
}

#[test]
fn sparse_and_dense_steps_give_the_same_answer() {
    let s = setup();
    let mut sparse = tracker(&s, false);
    let mut dense = tracker(&s, true);
    let a = run(&s, &mut sparse, 8, 0);
    let b = run(&s, &mut dense, 8, 0);
    let grid = s.cb.grid.len();
    let (ea, la, active) = *a.last().unwrap();
    let (eb, lb, _) = *b.last().unwrap();
    assert!(ea < 20.0 && eb < 20.0, "sparse {ea:.1} and dense {eb:.1} degrees");
    // the truth's log-likelihood agrees within a nat, or favours the sparse step
    assert!(la > lb - 1.0, "sparse {la:.2} vs dense {lb:.2}");
    // the converged state holds a small share of the grid
    assert!(active < grid / 4, "{active} of {grid} bins active");
    assert_eq!(sparse.tracks()[0].status, TrackStatus::Tracking);
}

#[test]
fn a_mode_outside_the_active_bins_is_found_by_the_coarse_pass() {
    let s = setup();
    let truth = s.cams[0].1.inverse() * s.truth_world;
    // a confident prior 90 degrees off: its mass sits far from the truth's bins
    let mut wrong = truth;
    wrong.rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 90f64.to_radians()) * truth.rotation;
    let prior = TrackPrior {
        reference_from_object: wrong,
        translation_std_m: 0.01,
        rotation_std_rad: Some(8f64.to_radians()),
    };
    let mut t = tracker(&s, false);
    t.start_track("box", &prior).unwrap();
    let first = t.estimate(t.tracks()[0].id).unwrap();
    assert!(
        rotation_error_deg(
            &first.reference_from_object.rotation,
            &truth.rotation,
            &box_symmetries()
        ) > 60.0
    );
    // no detections: the track exists already, only the images speak
    let steps = run(&s, &mut t, 8, u64::MAX);
    let (err, _, _) = *steps.last().unwrap();
    assert!(err < 20.0, "still {err:.1} degrees off after 8 steps");
}
