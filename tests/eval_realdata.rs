//! Issue 3's real-data check: on the 10 real frames of `shared/realdata/ycbv_video_0000/bop/`
//! the mug is tracked from its detection box to within 2 cm (translation) and 1 cm (ADD-S) by
//! the last frame (met: 1.8 cm / ADD-S 0.8 cm with the support-plane suppression), and its
//! rotation about its axis (handle hidden) is left ambiguous (not met yet: ignored test).

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use pregrasp::dataset::Sequence;
use pregrasp::eval::report::Mode;
use pregrasp::eval::run::{EvalConfig, ModelStore, SequenceOutcome, evaluate_sequence};
use pregrasp::render::Renderer;
use pregrasp::tracker::{CodebookConfig, TrackerConfig};
use std::path::PathBuf;

fn shared() -> PathBuf {
    std::env::var_os("PREGRASP_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
}

/// The evaluation of the real clip with the default tracker and a 10-degree grid.
fn evaluate_real_clip() -> SequenceOutcome {
    let seq = Sequence::open(&shared().join("realdata/ycbv_video_0000/bop")).expect("real sequence");
    let renderer = Renderer::new().expect("renderer");
    let tmp = tempfile::tempdir().expect("tempdir");
    let cfg = EvalConfig {
        mode: Mode::Multi,
        models_dir: None,
        cache_dir: Some(tmp.path().to_path_buf()),
        grid_step_deg: 10,
        codebook: CodebookConfig::default(),
        tracker: TrackerConfig::default(),
        detection_seed: 0,
        max_frames: None,
        frame_stride: 1,
        decide: None,
        only_target: false,
    };
    let mut store = ModelStore::default();
    evaluate_sequence(&seq, &renderer, &cfg, &mut store).expect("evaluate")
}

#[test]
fn real_mug_is_tracked_from_its_detection_box() {
    let out = evaluate_real_clip();
    let mug = out.traces.iter().find(|t| t.object == "025_mug").expect("mug trace");
    assert_eq!(mug.frames.len(), 10);
    let last = mug
        .frames
        .last()
        .and_then(|f| f.errors.as_ref())
        .expect("an estimate at the last frame");
    assert!(
        last.translation_error_m < 0.02,
        "translation error {:.4} m",
        last.translation_error_m
    );
    assert!(last.add_s_m < 0.01, "ADD-S {:.4} m", last.add_s_m);
}

#[test]
#[ignore = "not reached yet: the modes that share the mug's axis spread over 20 deg of spin at the last frame (10 deg grid, \
            tracker acc 78175ee, support-plane suppression), against the 30 deg asked; run with --ignored"]
fn real_mug_spin_about_its_axis_stays_open() {
    let out = evaluate_real_clip();
    // Ambiguity about the axis (the mesh's z, the mug's height): the distribution must keep
    // several spins about it rather than pick one angle with confidence. Modes with at least
    // 5 % of the mass, their z axes agreeing (within 25 degrees), their spins differing by at
    // least 30 degrees.
    let (_, est) = out
        .final_estimates
        .iter()
        .find(|(n, _)| n == "025_mug")
        .expect("mug estimate");
    let modes: Vec<UnitQuaternion<f64>> = est
        .rotation_modes
        .iter()
        .filter(|m| m.mass >= 0.05)
        .map(|m| {
            let q = m.rotation_xyzw;
            UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2]))
        })
        .collect();
    let axis = |q: &UnitQuaternion<f64>| q * Vector3::z();
    let spread = modes
        .iter()
        .flat_map(|a| modes.iter().map(move |b| (a, b)))
        .filter(|(a, b)| axis(a).angle(&axis(b)).to_degrees() < 25.0)
        .map(|(a, b)| a.angle_to(b).to_degrees())
        .fold(0.0f64, f64::max);
    assert!(
        spread >= 30.0,
        "rotation modes {:?} (entropy {:.2} nats): the spin about the axis should stay open, spread {spread:.1} deg",
        est.rotation_modes,
        est.rotation_entropy
    );
}
