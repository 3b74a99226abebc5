//! End to end: register over HTTP, stream a short rendered sequence (two stationary cameras,
//! one moving robot camera with odometry), check estimates and decisions against ground truth,
//! restart and find the registry and tracks intact.

use crate::{TestApp, spawn_app};
use base64::Engine as _;
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use pregrasp::camera::Intrinsics;
use pregrasp::geometry::Pose;
use pregrasp::mesh::Mesh;
use serde_json::{Value, json};
use std::time::Duration;

const W: u32 = 160;
const H: u32 = 120;
const F_PX: f64 = 150.0;
const MOVE: f64 = 1.0;

fn pose_json(p: &Pose) -> Value {
    let q = p.rotation.coords;
    let t = p.translation.vector;
    json!({"rotation_xyzw": [q.x, q.y, q.z, q.w], "translation_m": [t.x, t.y, t.z]})
}

fn pose_from_json(v: &Value) -> Pose {
    let q: Vec<f64> = v["rotation_xyzw"]
        .as_array()
        .expect("q")
        .iter()
        .filter_map(Value::as_f64)
        .collect();
    let t: Vec<f64> = v["translation_m"]
        .as_array()
        .expect("t")
        .iter()
        .filter_map(Value::as_f64)
        .collect();
    pregrasp::geometry::pose_from_xyzw([t[0], t[1], t[2]], [q[0], q[1], q[2], q[3]]).expect("pose")
}

use pregrasp::geometry::look_at;

struct Scene {
    object: Mesh,
    world_from_object: Pose,
    table: Mesh,
}

impl Scene {
    fn new() -> Self {
        let object = pregrasp::mesh::builtin("box").expect("box");
        let b = object.bounds();
        let world_from_object = Pose::from_parts(
            Translation3::new(0.05, 0.02, -b.min_m.z),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.6),
        );
        let mut table = pregrasp::mesh::builtin_box([2.0, 2.0, 0.02], [[120, 100, 80], [120, 100, 80]]);
        for v in &mut table.vertices_m {
            v[2] -= 0.01;
        }
        Self {
            object,
            world_from_object,
            table,
        }
    }

    /// A JSON frame (raw f32 depth, PNG colour, a detection from the instance mask).
    fn frame(&self, world_from_camera: &Pose, stamp_ns: i64) -> Value {
        let k = Intrinsics::from_focal(W, H, F_PX).expect("k");
        let cfw = world_from_camera.inverse();
        let img = pregrasp::tracker::raster::render(
            &k,
            &[(&self.object, cfw * self.world_from_object), (&self.table, cfw)],
            0.05,
            [30, 30, 30],
        );
        let depth: Vec<u8> = img.depth.data_m.iter().flat_map(|d| d.to_le_bytes()).collect();
        let raw: Vec<u8> = img.color.data.iter().flatten().copied().collect();
        let mut png = std::io::Cursor::new(Vec::new());
        image::RgbImage::from_raw(W, H, raw)
            .expect("rgb")
            .write_to(&mut png, image::ImageFormat::Png)
            .expect("png");
        let (mut x0, mut y0, mut x1, mut y1, mut n) = (u32::MAX, u32::MAX, 0, 0, 0);
        for y in 0..H {
            for x in 0..W {
                if img.instance[(y * W + x) as usize] == 1 {
                    (x0, y0, x1, y1, n) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y), n + 1);
                }
            }
        }
        let detections = if n > 20 {
            json!([{"object": "box", "bbox_xywh_px": [x0, y0, x1 - x0 + 1, y1 - y0 + 1], "score": 1.0}])
        } else {
            json!([])
        };
        let b64 = base64::engine::general_purpose::STANDARD;
        json!({
            "stamp_ns": stamp_ns,
            "depth": {"encoding": "f32le", "data_base64": b64.encode(depth)},
            "color": {"data_base64": b64.encode(png.into_inner())},
            "detections": detections,
        })
    }
}

fn camera_spec(mount: Value) -> Value {
    json!({
        "intrinsics": {"width": W, "height": H, "k": [F_PX, 0.0, W as f64 / 2.0, 0.0, F_PX, H as f64 / 2.0, 0.0, 0.0, 1.0]},
        "mount": mount,
    })
}

async fn wait_for<F: Fn(&Value) -> bool>(app: &TestApp, path: &str, what: &str, ok: F) -> Value {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        let v = app.get_json(path).await;
        if ok(&v) {
            return v;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "timed out waiting for {what}: {v}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replayed_scene_is_tracked_decided_and_survives_restart() {
    let app = spawn_app().await;
    let scene = Scene::new();
    let ext1 = look_at([-0.9, -0.3, 0.6], [0.0, 0.0, 0.08]);
    let ext2 = look_at([0.3, -0.9, 0.7], [0.0, 0.0, 0.08]);
    // The robot: base on the floor driving towards the table along +x; camera 1.2 m up.
    let base_from_camera = look_at([0.0, 0.0, 1.2], [1.0, 0.0, 0.7]);

    assert_eq!(
        app.put_json(
            "/cameras/ext1",
            &camera_spec(json!({"type": "stationary", "world_from_camera": pose_json(&ext1)}))
        )
        .await
        .status(),
        200
    );
    assert_eq!(
        app.put_json(
            "/cameras/ext2",
            &camera_spec(json!({"type": "stationary", "world_from_camera": pose_json(&ext2)}))
        )
        .await
        .status(),
        200
    );
    assert_eq!(
        app.put_json(
            "/cameras/robot",
            &camera_spec(json!({"type": "robot", "base_from_camera": pose_json(&base_from_camera)}))
        )
        .await
        .status(),
        200
    );
    let ply = scene.object.to_ply_bytes();
    assert_eq!(
        app.put_bytes("/objects/box?name=Box", "application/octet-stream", ply)
            .await
            .status(),
        200
    );
    let plane = json!({"normal": [0.0, 0.0, 1.0], "point_m": [0.0, 0.0, 0.0]});
    assert_eq!(app.put_json("/scene/support_plane", &plane).await.status(), 200);
    wait_for(&app, "/objects/box", "the coarse codebook", |v| {
        v["codebook"]["status"] == "ready"
    })
    .await;

    let truth = json!({"stamp_ns": 0, "objects": [{"object": "box", "world_from_object": pose_json(&scene.world_from_object)}]});
    assert_eq!(app.post_json("/truth", &truth).await.status(), 202);

    let rig = Rig {
        ext1,
        ext2,
        base_from_camera,
    };
    for i in 0..10i64 {
        rig.send_round(&app, &scene, i).await;
        // Let the tracker keep up (a robot streams at 10 Hz).
        let t = round_stamp(i);
        wait_for(&app, "/tracks", "a step", |v| {
            i < 2
                || v.as_array()
                    .is_some_and(|a| a.iter().any(|tr| tr["stamp_ns"].as_i64() >= Some(t_minus(t))))
        })
        .await;
    }
    let tracks = app.get_json("/tracks").await;
    let tracks = tracks.as_array().expect("tracks");
    // Every camera's first detection may open a track; the tracker merges or loses the extra
    // ones over time. The best-converged track (smallest spread) must be on the truth.
    for t in tracks {
        eprintln!(
            "track {} status {} std {:.3} truth {} components {}",
            t["id"],
            t["status"],
            t["translation_std_m"].as_f64().unwrap_or(f64::NAN),
            t["truth"],
            t["components"]
                .as_array()
                .map(|c| c
                    .iter()
                    .map(|c| format!("{}:{:.2}", c["camera"], c["weight"].as_f64().unwrap_or(0.0)))
                    .collect::<Vec<_>>()
                    .join(","))
                .unwrap_or_default()
        );
    }
    assert!(!tracks.is_empty());
    assert!(tracks.iter().all(|t| t["object_id"] == "box"));
    let t = tracks
        .iter()
        .min_by(|a, b| {
            a["translation_std_m"]
                .as_f64()
                .partial_cmp(&b["translation_std_m"].as_f64())
                .expect("finite")
        })
        .expect("a track");
    assert_eq!(t["object_id"], "box");
    assert_eq!(t["object_name"], "Box");
    assert_eq!(t["status"], "tracking");
    let est = pose_from_json(&t["world_from_object"]);
    let err_m = (est.translation.vector - scene.world_from_object.translation.vector).norm();
    assert!(err_m < 0.03, "translation error {err_m} m");
    let truth_err = t["truth"]["translation_error_m"].as_f64().expect("truth error");
    assert!((truth_err - err_m).abs() < 1e-6);
    assert!(!t["particles"].as_array().expect("particles").is_empty());
    assert_eq!(t["samples_world"].as_array().expect("samples").len(), 10);
    assert_eq!(t["covariance_6x6"].as_array().expect("cov").len(), 36);
    // The robot camera's estimated pose is where the robot put it.
    let scene_doc = app.get_json("/scene").await;
    let robot = scene_doc["cameras"]
        .as_array()
        .expect("cams")
        .iter()
        .find(|c| c["id"] == "robot")
        .expect("robot")
        .clone();
    let wfc = pose_from_json(&robot["world_from_camera"]);
    let expected = world_from_base(9) * base_from_camera;
    assert!((wfc.translation.vector - expected.translation.vector).norm() < 1e-6);

    // Samples from the distribution, in both frames.
    let samples = app.get_json(&format!("/tracks/{}/samples?n=50", t["id"])).await;
    assert_eq!(samples["world_from_object"].as_array().expect("samples").len(), 50);
    let near = samples["world_from_object"]
        .as_array()
        .expect("samples")
        .iter()
        .filter(|p| (pose_from_json(p).translation.vector - scene.world_from_object.translation.vector).norm() < 0.05)
        .count();
    assert!(near >= 40, "{near} of 50 samples within 5 cm of the truth");
    crate::assert_problem(app.get(&format!("/tracks/{}/samples?n=0", t["id"])).await, 422).await;
    let history = app.get_json(&format!("/tracks/{}/history", t["id"])).await;
    assert!(history.as_array().expect("history").len() >= 3);

    // A decision with the default gripper and the table.
    let id = t["id"].as_u64().expect("id");
    let r = app
        .post_json(
            &format!("/tracks/{id}/decision"),
            &json!({"n_samples": 200, "threshold": 0.8}),
        )
        .await;
    assert_eq!(r.status(), 200);
    let d: Value = r.json().await.expect("decision");
    let p = d["p_success"].as_f64().expect("p");
    assert!((0.0..=1.0).contains(&p));
    let verdict = d["decision"].as_str().expect("verdict");
    assert!(verdict == "grasp" || verdict == "observe");
    // `grasp` exactly when the rule in force (the calibrated one when the map fits the running
    // settings, else the raw rate's Wilson lower bound) held for its run of answers
    let rule = &d["rule"];
    assert_eq!(rule["threshold"], 0.8, "{d}");
    let quantity = rule["value"].as_f64().expect("the rule's value");
    match rule["quantity"].as_str().expect("quantity") {
        "calibrated" => assert_eq!(d["p_success"].as_f64(), Some(quantity), "{d}"),
        "calibrated_lower" => assert_eq!(d["ci95"][0].as_f64(), Some(quantity), "{d}"),
        "raw_lower" => assert_eq!(d["ci95_raw"][0].as_f64(), Some(quantity), "{d}"),
        // the map at the raw interval's lower end: at most the calibrated probability
        "calibrated_at_raw_lower" => assert!(quantity <= d["p_success"].as_f64().expect("p") + 1e-12, "{d}"),
        other => panic!("rule quantity {other}"),
    }
    let run = d["smoothing"]["run"].as_u64().expect("run");
    assert_eq!(run > 0, quantity >= 0.8, "{d}");
    assert_eq!(
        verdict == "grasp",
        run >= rule["run_length"].as_u64().expect("run_length"),
        "{d}"
    );
    let calibrated = d["calibration"]["state"] == "calibrated";
    assert_eq!(
        calibrated,
        d["calibration"]["map_settings_hash"] == d["calibration"]["running_settings_hash"],
        "{d}"
    );
    if !calibrated {
        assert_eq!(d["p_success"], d["p_success_raw"], "{d}");
        assert!(d["calibration"]["message"].is_string(), "{d}");
    }
    // The track's translation spread, which picks the map's stratum, comes with the answer and
    // agrees with the track's own; unsmoothed it is the one the map read.
    let spread = d["translation_std_m"].as_f64().expect("translation_std_m");
    let track = app.get_json(&format!("/tracks/{id}")).await;
    assert!(spread > 0.0 && spread < 0.5, "{d}");
    if d["smoothing"]["time_constant_s"] == 0.0 {
        assert_eq!(
            d["smoothing"]["translation_std_m_smoothed"].as_f64(),
            Some(spread),
            "{d}"
        );
    }
    assert!(track["translation_std_m"].is_number(), "{track}");
    // The gripper is placed on the estimate: within the object's reach of the truth.
    let wfg = pose_from_json(&d["world_from_gripper"]);
    assert!((wfg.translation.vector - scene.world_from_object.translation.vector).norm() < 0.3);
    // Its context: the stamp of the distribution it used, and the one gripper pose in the
    // reference (robot camera), base and world frames.
    let stamp = d["stamp_ns"].as_i64().expect("stamp_ns");
    // (a step that fuses only a late external frame has that frame's stamp)
    assert!((round_stamp(9) - 300_000_000..=round_stamp(9)).contains(&stamp), "{d}");
    let rfg = pose_from_json(&d["reference_from_gripper"]);
    let bfg = pose_from_json(&d["base_from_gripper"]);
    let close = |a: &Pose, b: &Pose| {
        (a.translation.vector - b.translation.vector).norm() < 1e-6 && a.rotation.angle_to(&b.rotation) < 1e-6
    };
    assert!(close(&bfg, &(base_from_camera * rfg)), "{d}");
    assert!(close(&wfg, &(world_from_base(9) * bfg)), "{d}");
    assert!(app.get_json(&format!("/tracks/{id}")).await["decision"]["p_success"].is_number());
    // That query made the track watched: after the next step the worker draws its samples,
    // decisions read them without waiting for the tracker, and identical queries within one
    // step share one answer.
    rig.send_round(&app, &scene, 10).await;
    wait_for(&app, &format!("/tracks/{id}"), "a step", |v| {
        v["stamp_ns"].as_i64() >= Some(t_minus(round_stamp(10)))
    })
    .await;
    // the late external frames of the round may step the tracker again: wait for quiet
    let mut steps = metric(&app.metrics_text().await, "pregrasp_steps_total");
    loop {
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
        let now = metric(&app.metrics_text().await, "pregrasp_steps_total");
        if now == steps {
            break;
        }
        steps = now;
    }
    let query = json!({"n_samples": 200, "threshold": 0.8});
    let a: Value = app
        .post_json(&format!("/tracks/{id}/decision"), &query)
        .await
        .json()
        .await
        .expect("decision");
    let b: Value = app
        .post_json(&format!("/tracks/{id}/decision"), &query)
        .await
        .json()
        .await
        .expect("decision");
    assert_eq!(a, b, "one step, one query: one answer");
    let metrics = app.metrics_text().await;
    assert!(
        metric(&metrics, "pregrasp_decisions_from_bank_total") >= 2.0,
        "{metrics}"
    );
    assert!(metric(&metrics, "pregrasp_decisions_shared_total") >= 1.0, "{metrics}");
    // Bad decision queries change nothing.
    crate::assert_problem(
        app.post_json(&format!("/tracks/{id}/decision"), &json!({"threshold": 1.5}))
            .await,
        422,
    )
    .await;
    crate::assert_problem(app.post_json("/tracks/999/decision", &json!({})).await, 404).await;
    crate::assert_problem(
        app.post_json(&format!("/tracks/{id}/decision"), &json!({"gripper": "nope"}))
            .await,
        404,
    )
    .await;
    crate::assert_problem(
        app.post_json(&format!("/tracks/{id}/decision"), &json!({"bogus": 1}))
            .await,
        422,
    )
    .await;

    let metrics = app.metrics_text().await;
    assert!(
        metrics.contains("pregrasp_ingest_to_estimate_seconds{quantile=\"0.5\"}"),
        "{metrics}"
    );

    // Restart: registry and tracks intact.
    let app = app.restart().await;
    assert_eq!(app.get_json("/cameras").await.as_array().expect("cams").len(), 3);
    assert_eq!(app.get_json("/objects/box").await["name"], "Box");
    let after = app.get_json(&format!("/tracks/{id}")).await;
    assert_eq!(after["object_id"], "box");
    let est2 = pose_from_json(&after["world_from_object"]);
    assert!((est2.translation.vector - est.translation.vector).norm() < 0.05);
    // The codebook comes back from the cache.
    wait_for(&app, "/objects/box", "the cached codebook", |v| {
        v["codebook"]["status"] == "ready"
    })
    .await;
    // The restored track answers a decision before any new frame arrives.
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        let r = app
            .post_json(&format!("/tracks/{id}/decision"), &json!({"n_samples": 200}))
            .await;
        if r.status() == 200 {
            break;
        }
        // at most "not ready" while its model is restored, never "not found"
        let p = crate::assert_problem(r, 503).await;
        assert!(
            std::time::Instant::now() < deadline,
            "restored track not answering: {p}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // The tracker's state came back too: the next frames update the same track (no new one
    // from the detections), and it is still on the truth.
    let before_restart = track_ids(&app).await;
    rig.send_round(&app, &scene, 11).await;
    let after = wait_for(&app, &format!("/tracks/{id}"), "a step after the restart", |v| {
        v["stamp_ns"].as_i64() >= Some(t_minus(round_stamp(11)))
    })
    .await;
    assert_eq!(after["status"], "tracking");
    let restored = pose_from_json(&after["world_from_object"]);
    let err_m = (restored.translation.vector - scene.world_from_object.translation.vector).norm();
    assert!(err_m < 0.03, "after the restart: {err_m} m");
    let ids = track_ids(&app).await;
    assert_eq!(ids, before_restart, "no new track after the restart");

    // A track from a caller's prior: 3 cm off the truth, 30 degrees of rotation spread.
    let mut prior_pose = scene.world_from_object;
    prior_pose.translation.vector.x += 0.03;
    let r = app
        .post_json(
            "/tracks",
            &json!({"object_id": "box", "world_from_object": pose_json(&prior_pose), "translation_std_m": 0.02, "rotation_std_deg": 30.0}),
        )
        .await;
    assert_eq!(r.status(), 201);
    let started: Value = r.json().await.expect("track");
    let new_id = started["id"].as_u64().expect("id");
    assert!(!ids.contains(&new_id));
    assert_eq!(started["status"], "initialising");
    let p = pose_from_json(&started["world_from_object"]);
    assert!((p.translation.vector - prior_pose.translation.vector).norm() < 0.01);
    assert!(p.rotation.angle_to(&prior_pose.rotation).to_degrees() < 15.0);
    assert_eq!(app.get_json(&format!("/tracks/{new_id}")).await["id"], new_id);
    // Bad priors change nothing.
    let n_tracks = app.get_json("/tracks").await.as_array().expect("tracks").len();
    let good = pose_json(&prior_pose);
    for (body, status) in [
        (json!({"object_id": "nope", "world_from_object": good}), 404),
        (json!({"object_id": "box"}), 422),
        (
            json!({"object_id": "box", "world_from_object": good, "reference_from_object": good}),
            422,
        ),
        (
            json!({"object_id": "box", "world_from_object": good, "translation_std_m": -1.0}),
            422,
        ),
        (
            json!({"object_id": "box", "world_from_object": good, "rotation_std_deg": 400.0}),
            422,
        ),
        (
            json!({"object_id": "box", "world_from_object": {"rotation_xyzw": [0.0, 0.0, 0.0, 2.0], "translation_m": [0.0, 0.0, 0.0]}}),
            422,
        ),
        (json!({"object_id": "box", "world_from_object": good, "extra": 1}), 422),
    ] {
        crate::assert_problem(app.post_json("/tracks", &body).await, status).await;
    }
    assert_eq!(
        app.get_json("/tracks").await.as_array().expect("tracks").len(),
        n_tracks
    );

    // Ground-truth errors are modulo the object's exact symmetries: the box's +x half has the
    // second colour, so a turn of 180 degrees about x looks the same (no error) and one about z
    // does not (an error of about 180 degrees).
    let half_turn = |axis: nalgebra::Unit<Vector3<f64>>| UnitQuaternion::from_axis_angle(&axis, std::f64::consts::PI);
    for (i, turn, flipped_is_error) in [
        (12, half_turn(Vector3::x_axis()), false),
        (13, half_turn(Vector3::z_axis()), true),
    ] {
        let mut turned = scene.world_from_object;
        turned.rotation *= turn;
        let truth = json!({"stamp_ns": round_stamp(i), "objects": [{"object": "box", "world_from_object": pose_json(&turned)}]});
        assert_eq!(app.post_json("/truth", &truth).await.status(), 202);
        rig.send_round(&app, &scene, i).await;
        let v = wait_for(&app, &format!("/tracks/{id}"), "a step after the truth turned", |v| {
            v["stamp_ns"].as_i64() >= Some(t_minus(round_stamp(i)))
        })
        .await;
        let est = pose_from_json(&v["world_from_object"]);
        // the track stays on the truth or on its exact twin (the half turn about x): the two
        // look the same, and the filter may settle on either
        let truth_rotation = scene.world_from_object.rotation;
        let on_truth_deg = est
            .rotation
            .angle_to(&truth_rotation)
            .min(est.rotation.angle_to(&(truth_rotation * half_turn(Vector3::x_axis()))))
            .to_degrees();
        assert!(on_truth_deg < 30.0, "the track left the truth: {on_truth_deg} deg");
        // the box's exact symmetries: the identity and the half turn about x
        let x_turned = turned.rotation * half_turn(Vector3::x_axis());
        let expected = est
            .rotation
            .angle_to(&turned.rotation)
            .min(est.rotation.angle_to(&x_turned))
            .to_degrees();
        let reported = v["truth"]["orientation_error_deg"].as_f64().expect("orientation error");
        assert!(
            (reported - expected).abs() < 1e-6,
            "{reported} deg, expected {expected}"
        );
        if flipped_is_error {
            assert!(reported > 150.0, "a turn the colour tells apart: {reported} deg");
        } else {
            assert!(reported < 30.0, "an exact symmetry: {reported} deg");
        }
    }

    // Tracks a client starts are capped per object (4 by default): the one beyond is refused
    // with a problem document and the tracks stay as they were.
    let cap = app.config.service.limits.max_tracks_per_object;
    let mut refused = None;
    for _ in 0..cap + 1 {
        let before = track_ids(&app).await;
        let r = app
            .post_json(
                "/tracks",
                &json!({"object_id": "box", "world_from_object": pose_json(&prior_pose), "translation_std_m": 0.02}),
            )
            .await;
        if r.status() == 409 {
            let p = crate::assert_problem(r, 409).await;
            assert_eq!(track_ids(&app).await, before, "a refused track changes nothing");
            refused = Some(p);
            break;
        }
        assert_eq!(r.status(), 201);
    }
    let p = refused.expect("the cap refuses a track");
    assert!(p["type"].as_str().is_some_and(|t| t.contains("limit-reached")), "{p}");
    let box_tracks = app
        .get_json("/tracks")
        .await
        .as_array()
        .expect("tracks")
        .iter()
        .filter(|t| t["object_id"] == "box" && t["status"] != "lost")
        .count();
    assert!(box_tracks <= cap, "{box_tracks} live tracks of one object, cap {cap}");

    // Stopping a track.
    let r = app
        .client
        .delete(app.api(&format!("/tracks/{id}")))
        .send()
        .await
        .expect("delete");
    assert_eq!(r.status(), 204);
    crate::assert_problem(app.get(&format!("/tracks/{id}")).await, 404).await;
}

struct Rig {
    ext1: Pose,
    ext2: Pose,
    base_from_camera: Pose,
}

fn world_from_base(i: i64) -> Pose {
    Pose::from_parts(
        Translation3::new(-1.4 + 0.03 * i as f64 * MOVE, 0.1, -0.75),
        UnitQuaternion::identity(),
    )
}

fn round_stamp(i: i64) -> i64 {
    1_000_000_000 + i * 100_000_000
}

impl Rig {
    /// Round `i` of the replay: odometry, then the robot's frame and the two external cameras
    /// out of step (ext2 20 ms late, ext1 40 ms late, inside the 300 ms window).
    async fn send_round(&self, app: &TestApp, scene: &Scene, i: i64) {
        let t = round_stamp(i);
        let odo = json!({
            "stamp_ns": t,
            "odom_from_base": {"pose": pose_json(&world_from_base(i))},
            "world_from_odom": pose_json(&Pose::identity()),
        });
        assert_eq!(app.post_json("/odometry", &odo).await.status(), 202);
        let robot_frame = scene.frame(&(world_from_base(i) * self.base_from_camera), t);
        assert_eq!(app.post_json("/cameras/robot/frames", &robot_frame).await.status(), 202);
        let f2 = scene.frame(&self.ext2, t - 20_000_000);
        assert_eq!(app.post_json("/cameras/ext2/frames", &f2).await.status(), 202);
        let f1 = scene.frame(&self.ext1, t - 40_000_000);
        assert_eq!(app.post_json("/cameras/ext1/frames", &f1).await.status(), 202);
    }
}

async fn track_ids(app: &TestApp) -> Vec<u64> {
    let tracks = app.get_json("/tracks").await;
    tracks
        .as_array()
        .expect("tracks")
        .iter()
        .filter_map(|t| t["id"].as_u64())
        .collect()
}

/// The value of a metric without labels in Prometheus text.
fn metric(text: &str, name: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|r| r.strip_prefix(' ')))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or(f64::NAN)
}

/// The stamp the tracker has reached when it fused the frames of step `t` (the robot frame is
/// the newest).
fn t_minus(t: i64) -> i64 {
    t - 50_000_000
}
