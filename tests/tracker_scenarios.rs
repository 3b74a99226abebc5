//! Tracker scenarios on synthetic rendered scenes (coarse 10-degree grid, 160 x 120 images).

mod tracker_support;

use nalgebra::{UnitQuaternion, Vector3};
use pregrasp::tracker::{CameraMount, TrackStatus, Tracker, TrackerConfig};
use std::collections::BTreeMap;
use tracker_support::*;

fn box_symmetries() -> Vec<UnitQuaternion<f64>> {
    // the built-in box: +x half coloured differently, so only the flip about x remains
    vec![UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)]
}

#[test]
fn single_camera_converges_on_a_rendered_box() {
    let mesh = pregrasp::mesh::builtin("box").unwrap();
    let cb = coarse_codebook(&mesh);
    let truth_world = on_table(&mesh, 0.05, 0.02, 0.6);
    let scene = Scene::new(vec![("box".into(), mesh.clone(), truth_world)]);
    let cam = look_at([-0.9, -0.3, 0.6], [0.0, 0.0, 0.08]);
    let mut cams = BTreeMap::new();
    cams.insert("ext1".to_string(), CameraMount::Stationary { world_from_camera: cam });
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, "ext1".into());
    tracker.add_object_model("box", mesh.clone(), cb);
    let truth = cam.inverse() * truth_world;
    for step in 0..8 {
        let f = frame("ext1", &cam, &scene, step == 0, true, 0.01, step);
        let rep = tracker.step(&[f], None).unwrap();
        let id = tracker.tracks()[0].id;
        let e = tracker.estimate(id).unwrap();
        let t = &tracker.tracks()[0];
        eprintln!(
            "step {step}: t_err {:.3} r_err {:.1} sim {:.3} status {:?} std {:.3} ent {:.2} loglik {:.2} total {:.3}s",
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
    assert!(rotation_error_deg(&e.reference_from_object.rotation, &truth.rotation, &box_symmetries()) < 20.0);
}
