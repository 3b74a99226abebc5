//! End to end: generate a tiny sequence (coarse grid, small images, few frames), run
//! `pregrasp eval` in both modes, check `results.json`, and check that the multi-view tracker
//! beats the single-view baseline on a sequence built so that the robot camera sees little.

use pregrasp::dataset::{self, Sequence};
use pregrasp::eval::report::{Mode, Results};
use pregrasp::eval::run::{DecideConfig, EvalConfig, run_all};
use pregrasp::generate::{GenerateConfig, load_models, write_sequence};
use pregrasp::grasp::Gripper;
use pregrasp::render::Renderer;
use pregrasp::tracker::{CodebookConfig, TrackerConfig};
use std::path::Path;

const FRAMES: u32 = 10;
const GRID_STEP_DEG: u32 = 30;

fn config(mode: Mode, cache: &Path, decide: bool) -> EvalConfig {
    EvalConfig {
        mode,
        models_dir: None,
        cache_dir: Some(cache.to_path_buf()),
        grid_step_deg: GRID_STEP_DEG,
        codebook: CodebookConfig::default(),
        tracker: TrackerConfig::default(),
        detection_seed: 0,
        max_frames: None,
        frame_stride: 1,
        decide: decide.then(|| {
            let mut d = DecideConfig::new(Gripper::default_parallel_jaw());
            d.n_samples = 200;
            d
        }),
        only_target: false,
        trust_samples: pregrasp::eval::run::DEFAULT_TRUST_SAMPLES,
    }
}

/// Blinds the robot camera for all but the last `keep` frames: no depth readings there and no
/// detection boxes (as if its view were blocked). Ground truth stays for scoring.
fn blind_robot_camera(dir: &Path, keep: usize) {
    let mut seq = Sequence::open(dir).expect("generated sequence");
    let robot = seq.rig.robot_camera().expect("a robot camera").to_string();
    let ids: Vec<u32> = seq.cameras[&robot].frames.keys().copied().collect();
    let blind = &ids[..ids.len().saturating_sub(keep)];
    for &f in blind {
        let meta = seq.cameras[&robot].frames[&f].clone();
        let zeros = pregrasp::camera::DepthImage::zeros(meta.intrinsics.width, meta.intrinsics.height);
        dataset::write_depth_png(&seq.depth_path(&robot, f), &zeros, meta.depth_scale).expect("write depth");
        let rgb = seq.rgb_path(&robot, f);
        if rgb.is_file() {
            std::fs::remove_file(rgb).expect("remove rgb");
        }
        if let Some(info) = seq.cameras.get_mut(&robot).and_then(|c| c.gt_info.get_mut(&f)) {
            for i in info.iter_mut() {
                i.visib_fract = Some(0.0);
                i.px_count_visib = Some(0);
                i.bbox_visib = None;
            }
        }
    }
    seq.write_json().expect("rewrite json");
}

fn read_results(out: &Path) -> Results {
    let text = std::fs::read_to_string(out.join("results.json")).expect("results.json");
    serde_json::from_str(&text).expect("results.json parses")
}

#[test]
fn eval_writes_results_and_multi_view_beats_a_blind_robot_camera() {
    let renderer = Renderer::new().expect("renderer");
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let models = load_models(None, &["box".to_string()]).expect("builtin box");
    let mut g = GenerateConfig::new(models);
    g.frames = FRAMES;
    g.width = 160;
    g.height = 120;
    g.look_away_probability = 0.0;
    g.target = Some("box".into());
    write_sequence(&renderer, &g, 3, &data.join("seq0")).expect("generate");
    blind_robot_camera(&data.join("seq0"), 2);
    let cache = tmp.path().join("cache");

    // Multi-view, with decisions.
    let out_multi = tmp.path().join("multi");
    let multi = run_all(&data, &out_multi, &config(Mode::Multi, &cache, true), None).expect("eval multi");
    let on_disk = read_results(&out_multi);
    // JSON keeps floats to within the last bit; compare what matters.
    assert_eq!(on_disk.objects.len(), multi.objects.len());
    assert_eq!(on_disk.objects[0].name, multi.objects[0].name);
    assert_eq!(on_disk.objects[0].frames, multi.objects[0].frames);
    let close = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) => (a - b).abs() <= 1e-9 * a.abs().max(1.0),
        (None, None) => true,
        _ => false,
    };
    assert!(close(on_disk.mean.translation_error_m, multi.mean.translation_error_m));
    assert!(close(
        on_disk.mean.orientation_error_deg,
        multi.mean.orientation_error_deg
    ));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_multi.join("results.json")).expect("read")).expect("json");
    assert_eq!(json["mode"], "multi");
    assert!(json["objects"].is_array() && json["mean"].is_object() && json["others"].is_array());
    assert!(json["decision"]["reliability"].is_array(), "{}", json["decision"]);
    assert!(out_multi.join("table.md").is_file());
    // every decision with its raw answer and the distribution's measures, for `calibrate`
    let records: pregrasp::eval::calibration::DecisionRecords =
        serde_json::from_str(&std::fs::read_to_string(out_multi.join("decisions.json")).expect("decisions.json"))
            .expect("decision records");
    assert_eq!(records.settings_hash.len(), 64);
    assert_eq!(
        records.decisions.len(),
        json["decision"]["frames"].as_u64().expect("frames") as usize
    );
    assert!(records.decisions.iter().all(|d| {
        d.features
            .as_ref()
            .is_some_and(|f| (0.0..=1.0).contains(&f.p_raw) && f.effective_sample_size > 0.0)
    }));
    // and which of the grasp's tests the truth passes, which say whether it succeeds
    assert!(
        records
            .decisions
            .iter()
            .all(|d| d.truth_tests.is_some_and(|t| t.success() == d.success))
    );
    assert!(out_multi.join("plots/seq0.svg").is_file() && out_multi.join("plots/seq0.png").is_file());
    assert_eq!(multi.objects.len(), 1);
    let m = &multi.objects[0];
    assert_eq!(m.name, "box");
    assert_eq!(m.frames, FRAMES as usize);
    let cov_multi = m.coverage.expect("coverage");
    assert!(cov_multi >= 0.8, "multi-view coverage {cov_multi}");
    let t_multi = m.translation_error_m.expect("estimates");
    assert!(
        t_multi.is_finite() && t_multi < 0.25,
        "multi translation error {t_multi}"
    );
    let ll = m.gt_orientation_loglik.expect("loglik");
    assert!(ll.is_finite() && ll <= 0.0);
    let d = multi.decision.as_ref().expect("decision block");
    assert!((0.0..=1.0).contains(&d.grasp_rate) && d.ece >= 0.0 && d.ece <= 1.0);
    // The decision scores of issue 17, and the reliability diagram beside them.
    for k in [
        "ece",
        "brier",
        "brier_base_rate",
        "ece_by_object",
        "ece_leave_one_object_out",
        "recall",
        "first_grasp",
        "first_grasp_failure_upper_95",
    ] {
        assert!(
            json["decision"].get(k).is_some(),
            "decision.{k} missing: {}",
            json["decision"]
        );
    }
    assert!(d.brier >= 0.0 && d.brier <= 1.0 && d.brier_base_rate <= 0.25 + 1e-12);
    assert_eq!(d.approaches, 1, "one sequence, one target");
    assert_eq!(d.first_grasp.len(), 1);
    assert!(d.first_grasp_failure_upper_95 > 0.0 && d.first_grasp_failure_upper_95 <= 1.0);
    assert!(d.ece_by_object.contains_key("box"));
    assert!(out_multi.join("reliability.png").is_file());
    // The truth's place in the distribution, every frame with an estimate.
    let trust = m.trust.as_ref().expect("trust measures");
    assert_eq!(trust.frames, m.frames_with_estimate);
    for v in [
        trust.rotation.truth_in_50,
        trust.rotation.truth_in_90,
        trust.confidently_wrong,
    ] {
        assert!((0.0..=1.0).contains(&v), "{trust:?}");
    }
    assert!(trust.rotation.truth_in_50 <= trust.rotation.truth_in_90);
    assert!(
        trust.rotation.median_volume_90_so3_fraction > 0.0 && trust.rotation.median_volume_90_so3_fraction <= 1.0,
        "{trust:?}"
    );
    let tr = trust.translation.as_ref().expect("translation mixture");
    assert!(
        tr.truth_in_50 <= tr.truth_in_90 && tr.median_volume_90_m3 > 0.0,
        "{tr:?}"
    );
    for k in ["truth_in_50", "truth_in_90", "median_volume_90_so3_fraction"] {
        assert!(json["objects"][0]["trust"]["rotation"].get(k).is_some(), "{k}");
    }
    assert!(json["mean"]["trust"]["confidently_wrong"].is_number());
    // The error the distribution expects of its estimate follows its spread: a wide one (a 90 %
    // region of most of SO(3), as these few far frames leave it) expects tens of degrees, a
    // tight one a few; the estimate being one of its modes, below a uniform distribution's 126.5.
    let expected = trust.rotation.mean_expected_error_deg.expect("expected error");
    let wide = trust.rotation.median_volume_90_so3_fraction > 0.5;
    assert!(expected > 0.0 && expected < 126.5, "{trust:?}");
    assert!(if wide { expected > 45.0 } else { expected < 90.0 }, "{trust:?}");
    assert!(json["objects"][0]["trust"]["rotation"]["mean_expected_error_deg"].is_number());
    // The box's exact symmetries (its turn about x) are a subset of its shape's (three
    // turns): the error modulo the exact ones is never below the error modulo the shape's.
    let (sym, shape) = (
        m.symmetric_error_deg.expect("sym"),
        m.shape_symmetric_error_deg.expect("shape sym"),
    );
    assert!(shape <= sym + 1e-9, "shape {shape} vs exact {sym}");

    // Single-view: the robot camera alone, blind until the last frames.
    let out_single = tmp.path().join("single");
    let single = run_all(
        &data,
        &out_single,
        &config(Mode::Single, &cache, false),
        Some(&out_multi),
    )
    .expect("eval single");
    eprintln!("{}\n{}", multi.markdown(), single.markdown());
    assert_eq!(single.mode, Mode::Single);
    let s = &single.objects[0];
    let cov_single = s.coverage.expect("coverage");
    assert!(
        cov_single <= 0.3,
        "the robot camera saw the box for only 2 of {FRAMES} frames: {cov_single}"
    );
    assert!(cov_multi > cov_single);
    let auc_multi = m.add_s_auc_all_frames.expect("auc");
    let auc_single = s.add_s_auc_all_frames.expect("auc");
    assert!(
        auc_multi > auc_single,
        "ADD-S AUC over all frames: multi {auc_multi} vs single {auc_single}"
    );
    // The comparison plot holds both runs (the compared one dashed, in the legend as such), as
    // SVG and PNG.
    let svg = std::fs::read_to_string(out_single.join("plots/seq0.svg")).expect("svg");
    assert!(svg.contains("box single") && svg.contains("box (compared)"));
    let png = image::open(out_single.join("plots/seq0.png")).expect("png");
    assert!(png.width() > 0 && png.height() > 0);
}
