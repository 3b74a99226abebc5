//! The 10 real YCB-Video frames of the shared folder: the mug is tracked from its detection box
//! (the data set's `bbox_visib`, used only to start the track) with a coarse codebook built from
//! its mesh alone. The ground truth is read only to score the result.

#![allow(clippy::unwrap_used)] // test helpers: a failure is a test failure

use nalgebra::Point3;
use pregrasp::camera::{ColorImage, DepthImage, Intrinsics};
use pregrasp::geometry::{Pose, RotationGrid, pose_from_rt};
use pregrasp::mesh::Mesh;
use pregrasp::tracker::codebook::{CodebookConfig, CpuViews};
use pregrasp::tracker::{CameraFrame, CameraMount, Codebook, Detection, Tracker, TrackerConfig};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

fn shared() -> PathBuf {
    std::env::var("PREGRASP_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|_| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
}

fn json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn f64s(v: &serde_json::Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

#[test]
fn real_mug_is_tracked_from_its_detection_box() {
    let root = shared().join("realdata/ycbv_video_0000/bop");
    if !root.exists() {
        eprintln!("no real data at {}; skipped", root.display());
        return;
    }
    let cam = root.join("cam");
    let scene_camera = json(&cam.join("scene_camera.json"));
    let gt = json(&cam.join("scene_gt.json"));
    let gt_info = json(&cam.join("scene_gt_info.json"));
    let mesh = Mesh::load(&root.join("models/025_mug.ply")).unwrap();
    let grid = RotationGrid::new(10).unwrap();
    let cb = Arc::new(Codebook::build(&CpuViews(&mesh), &mesh, grid, &CodebookConfig::coarse()).unwrap());
    let mut cams = BTreeMap::new();
    cams.insert(
        "cam".to_string(),
        CameraMount::Stationary {
            world_from_camera: Pose::identity(),
        },
    );
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, "cam".into());
    tracker.add_object_model("025_mug", mesh.clone(), cb);
    let mut frames: Vec<u32> = scene_camera
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.parse().unwrap())
        .collect();
    frames.sort_unstable();
    let pts: Vec<Point3<f64>> = (0..mesh.vertices_m.len() as u32)
        .step_by(3)
        .map(|i| mesh.vertex(i))
        .collect();
    let mut last = (f64::NAN, f64::NAN);
    for (i, f) in frames.iter().enumerate() {
        let key = f.to_string();
        let sc = &scene_camera[&key];
        let k: [f64; 9] = f64s(&sc["cam_K"]).try_into().unwrap();
        let depth_png = image::open(cam.join(format!("depth/{f:06}.png")))
            .unwrap()
            .into_luma16();
        let (w, h) = depth_png.dimensions();
        let intrinsics = Intrinsics::new(w, h, k).unwrap();
        let depth = DepthImage::from_u16_mm(w, h, depth_png.as_raw(), sc["depth_scale"].as_f64().unwrap()).unwrap();
        let rgb = image::open(cam.join(format!("rgb/{f:06}.png"))).unwrap().into_rgb8();
        let color = ColorImage::new(w, h, rgb.pixels().map(|p| p.0).collect()).unwrap();
        let detections = if i == 0 {
            let b = f64s(&gt_info[&key][0]["bbox_visib"]);
            vec![Detection {
                object: "025_mug".into(),
                bbox_xywh_px: [b[0], b[1], b[2], b[3]],
                score: 1.0,
            }]
        } else {
            vec![]
        };
        let frame = CameraFrame {
            camera: "cam".into(),
            stamp_ns: *f as i64,
            intrinsics,
            depth,
            color: Some(color),
            detections,
        };
        tracker.step(&[frame], None).unwrap();
        let g = &gt[&key][0];
        let r: [f64; 9] = f64s(&g["cam_R_m2c"]).try_into().unwrap();
        let t = f64s(&g["cam_t_m2c"]);
        let truth = pose_from_rt(&r, [t[0] / 1000.0, t[1] / 1000.0, t[2] / 1000.0]).unwrap();
        let id = tracker.tracks()[0].id;
        let e = tracker.estimate(id).unwrap();
        let est = e.reference_from_object;
        let t_err = (est.translation.vector - truth.translation.vector).norm();
        let moved_est: Vec<Point3<f64>> = pts.iter().map(|p| est * p).collect();
        let add_s = pts
            .iter()
            .map(|p| {
                let q = truth * p;
                moved_est.iter().map(|m| (m - q).norm()).fold(f64::INFINITY, f64::min)
            })
            .sum::<f64>()
            / pts.len() as f64;
        eprintln!(
            "frame {f}: err vec {:?} translation error {t_err:.4} m, ADD-S {add_s:.4} m, rotation error {:.1} deg, entropy {:.2}, modes {:?}, sim {:?}",
            (est.translation.vector - truth.translation.vector)
                .as_slice()
                .iter()
                .map(|v| (v * 1000.0).round() / 1000.0)
                .collect::<Vec<_>>(),
            est.rotation.angle_to(&truth.rotation).to_degrees(),
            e.rotation_entropy,
            e.rotation_modes
                .iter()
                .take(4)
                .map(|m| (m.mass * 100.0).round() / 100.0)
                .collect::<Vec<_>>(),
            tracker.tracks()[0].best_similarity
        );
        last = (t_err, add_s);
    }
    // The target is 0.02 m / 0.01 m (met with the default codebook: see
    // tests/eval_realdata.rs). This test's coarse codebook (10-degree grid, 16 x 16 features)
    // guards the same level with some margin. The real mug's colours do not match its mesh's,
    // so no orientation fits well (`eval_realdata::real_mug_true_pose_is_likely_in_each_frame`)
    // and the last frame's error depends on which near-fit the track settles on: 0.0175-0.026 m
    // over encoder variants; with the evidence strength (weak matches weigh less) 0.0126 m /
    // ADD-S 0.0094 m.
    assert!(last.0 < 0.025, "translation error at the last frame {}", last.0);
    assert!(last.1 < 0.012, "ADD-S at the last frame {}", last.1);
}
