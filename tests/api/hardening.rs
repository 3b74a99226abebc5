//! Issue 16: no single request may stop the service, exhaust its memory or corrupt an object.
//! Each test sends the request that used to do harm and asserts the problem document and that
//! nothing stored or tracked changed.

use crate::{TestApp, assert_problem, camera_spec, frame_json, spawn_app, spawn_app_configured};
use base64::Engine as _;
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// What requests could change: the registry, the tracks, the scene and the intake counters.
async fn observable(app: &TestApp) -> Value {
    let mut objects = app.get_json("/objects").await;
    // the codebook builds in the background: its status is not what requests could change
    for o in objects.as_array_mut().into_iter().flatten() {
        o["codebook"] = Value::Null;
    }
    let metrics = app.metrics_text().await;
    let counter = |name: &str| {
        metrics
            .lines()
            .find(|l| l.starts_with(&format!("{name} ")))
            .and_then(|l| l.split_whitespace().nth(1))
            .map(String::from)
    };
    // (not the queue depth: the worker empties the queue at its own pace)
    let (odometry, newest_ns) = {
        let ingest = app.state.ingest();
        (ingest.odometry_len(), ingest.newest_ns())
    };
    json!({
        "cameras": app.get_json("/cameras").await,
        "objects": objects,
        "grippers": app.get_json("/grippers").await,
        "tracks": app.get_json("/tracks").await,
        "scene": app.get_json("/scene").await,
        "truth": app.state.truth.lock().expect("truth").len(),
        "frames_accepted": counter("pregrasp_frames_accepted_total"),
        "odometry_accepted": counter("pregrasp_odometry_accepted_total"),
        "odometry": odometry,
        "newest_ns": newest_ns,
    })
}

/// Waits until the worker has taken every waiting frame and finished its step.
async fn settle(app: &TestApp) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while app.state.ingest().pending() > 0 && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // the step runs under the engine's lock
    drop(app.state.engine.lock().expect("engine"));
    tokio::time::sleep(Duration::from_millis(50)).await;
    drop(app.state.engine.lock().expect("engine"));
}

/// Asserts that `resp` is a problem document with `status` and that nothing changed.
async fn refused(app: &TestApp, before: &Value, resp: reqwest::Response, status: u16, what: &str) {
    let p = assert_problem(resp, status).await;
    let after = observable(app).await;
    assert_eq!(&after, before, "{what} changed something ({p})");
}

fn odometry(stamp_ns: i64, x_m: f64) -> Value {
    json!({
        "stamp_ns": stamp_ns,
        "odom_from_base": {"pose": {"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [x_m, 0.0, 0.0]}},
    })
}

fn png16(w: u32, h: u32, value: u16) -> Vec<u8> {
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(w, h, image::Luma([value]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png");
    out.into_inner()
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for b in bytes {
        crc ^= u32::from(*b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let mut body = kind.to_vec();
    body.extend_from_slice(data);
    out.extend_from_slice(&body);
    out.extend_from_slice(&crc32(&body).to_be_bytes());
}

/// A PNG whose header claims `w` x `h` 16-bit grayscale pixels (a decompression bomb's
/// header: decoding it would allocate w * h * 2 bytes).
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[16, 0, 0, 0, 0]);
    png_chunk(&mut out, b"IHDR", &ihdr);
    png_chunk(&mut out, b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

fn png_frame(stamp_ns: i64, png: &[u8], depth_scale: f64) -> Value {
    json!({
        "stamp_ns": stamp_ns,
        "depth": {"encoding": "png16", "depth_scale": depth_scale,
                  "data_base64": base64::engine::general_purpose::STANDARD.encode(png)},
    })
}

const S: i64 = 1_000_000_000;
const MS: i64 = 1_000_000;

// Finding 1: one timestamp stopped all intake; negative stamps were accepted.
#[tokio::test]
async fn absurd_stamps_are_refused_and_intake_goes_on() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/robot", &camera_spec(true)).await.status(), 200);
    assert_eq!(
        app.post_json("/cameras/ext1/frames", &frame_json(S, 64, 48, 0.8))
            .await
            .status(),
        202
    );
    assert_eq!(app.post_json("/odometry", &odometry(S, 0.0)).await.status(), 202);
    settle(&app).await;
    let before = observable(&app).await;
    for stamp in [i64::MAX, i64::MIN, -1, i64::MAX - 1] {
        let r = app
            .post_json("/cameras/ext1/frames", &frame_json(stamp, 64, 48, 0.8))
            .await;
        refused(&app, &before, r, 422, &format!("frame at {stamp}")).await;
        let r = app.post_json("/odometry", &odometry(stamp, 0.0)).await;
        refused(&app, &before, r, 422, &format!("odometry at {stamp}")).await;
    }
    // intake goes on for every camera
    for (cam, stamp) in [("ext1", S + 100 * MS), ("robot", S + 110 * MS)] {
        let r = app
            .post_json(&format!("/cameras/{cam}/frames"), &frame_json(stamp, 64, 48, 0.8))
            .await;
        assert_eq!(r.status(), 202, "{cam}");
    }
    assert_eq!(
        app.post_json("/odometry", &odometry(S + 100 * MS, 0.0)).await.status(),
        202
    );
}

// Finding 1: a far-future stamp inside the range held every camera back until a restart; a
// second replay (stamps from 0 again) and a simulation restart were refused.
#[tokio::test]
async fn a_restarted_clock_is_accepted_and_a_late_frame_is_still_stale() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/ext2", &camera_spec(false)).await.status(), 200);
    // a first run: 10 s to 11 s
    for i in 0..10 {
        let t = 10 * S + i * 100 * MS;
        assert_eq!(
            app.post_json("/odometry", &odometry(t, 0.1 * i as f64)).await.status(),
            202
        );
        for cam in ["ext1", "ext2"] {
            let r = app
                .post_json(&format!("/cameras/{cam}/frames"), &frame_json(t, 64, 48, 0.8))
                .await;
            assert_eq!(r.status(), 202);
        }
    }
    // late by more than the window, less than a restarted clock: stale, counted, not applied
    settle(&app).await;
    let before = observable(&app).await;
    let late = 10 * S + 900 * MS - 500 * MS;
    let r = app
        .post_json("/cameras/ext1/frames", &frame_json(late, 64, 48, 0.8))
        .await;
    assert_problem(r, 409).await;
    let r = app.post_json("/odometry", &odometry(late, 0.0)).await;
    assert_problem(r, 409).await;
    assert_eq!(observable(&app).await, before);
    // the second run starts at 0 again: every message is taken
    let epoch = app.state.ingest().epoch();
    for i in 0..10 {
        let t = i * 100 * MS;
        assert_eq!(
            app.post_json("/odometry", &odometry(t, 0.1 * i as f64)).await.status(),
            202,
            "odometry {i}"
        );
        for cam in ["ext1", "ext2"] {
            let r = app
                .post_json(&format!("/cameras/{cam}/frames"), &frame_json(t, 64, 48, 0.8))
                .await;
            assert_eq!(r.status(), 202, "{cam} {i}");
        }
    }
    assert_eq!(app.state.ingest().epoch(), epoch + 1, "the odometry restarted once");
    assert_eq!(app.state.ingest().newest_ns(), Some(900 * MS));
    let metrics = app.metrics_text().await;
    assert!(metrics.contains("pregrasp_clock_resets_total 3"), "{metrics}");
}

// Finding 2: images were decoded before their size was checked.
#[tokio::test]
async fn image_sizes_are_checked_from_the_header_before_decoding() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    let before = observable(&app).await;
    let bomb = png_claiming(15_000, 15_000);
    let t0 = Instant::now();
    let r = app.post_json("/cameras/ext1/frames", &png_frame(S, &bomb, 1.0)).await;
    let p = assert_problem(r, 422).await;
    assert!(p["detail"].as_str().is_some_and(|d| d.contains("15000x15000")), "{p}");
    assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
    assert_eq!(observable(&app).await, before);
    // a colour image of the wrong size, as JSON and as multipart
    let mut big = std::io::Cursor::new(Vec::new());
    image::RgbImage::new(640, 480)
        .write_to(&mut big, image::ImageFormat::Png)
        .expect("png");
    let mut frame = frame_json(S, 64, 48, 0.8);
    frame["color"] = json!({"data_base64": base64::engine::general_purpose::STANDARD.encode(big.get_ref())});
    let r = app.post_json("/cameras/ext1/frames", &frame).await;
    refused(&app, &before, r, 422, "a 640x480 colour image").await;
    let form = reqwest::multipart::Form::new()
        .part(
            "meta",
            reqwest::multipart::Part::text(json!({"stamp_ns": S}).to_string()),
        )
        .part("depth", reqwest::multipart::Part::bytes(bomb));
    let r = app
        .client
        .post(app.api("/cameras/ext1/frames"))
        .multipart(form)
        .send()
        .await
        .expect("post");
    refused(&app, &before, r, 422, "a multipart bomb").await;
    // the camera's own size still decodes
    let r = app
        .post_json("/cameras/ext1/frames", &png_frame(S, &png16(64, 48, 800), 1.0))
        .await;
    assert_eq!(r.status(), 202);
}

// Finding 3: frames of a deleted camera stayed queued; nothing capped cameras, names, truth.
#[tokio::test]
async fn queues_are_freed_and_caps_hold() {
    let app = spawn_app_configured(|c| {
        c.service.limits.max_cameras = 2;
        c.service.limits.max_name_chars = 16;
    })
    .await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    for i in 0..3 {
        let r = app
            .post_json("/cameras/ext1/frames", &frame_json(S + i * 10 * MS, 64, 48, 0.8))
            .await;
        assert_eq!(r.status(), 202);
    }
    assert!(app.state.ingest().latest("ext1").is_some());
    // replaced: the waiting frames (taken with the old intrinsics) go
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.state.ingest().pending(), 0);
    assert!(app.state.ingest().latest("ext1").is_none());
    let r = app.post_json("/cameras/ext1/frames", &frame_json(S, 64, 48, 0.8)).await;
    assert_eq!(r.status(), 202);
    // deleted: its queue is freed
    let r = app
        .client
        .delete(app.api("/cameras/ext1"))
        .send()
        .await
        .expect("delete");
    assert_eq!(r.status(), 204);
    assert_eq!(app.state.ingest().cameras_with_queue(), 0);

    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/ext2", &camera_spec(false)).await.status(), 200);
    let ply = pregrasp::mesh::builtin("box").expect("box").to_ply_bytes();
    assert_eq!(
        app.put_bytes("/objects/box", "application/octet-stream", ply.clone())
            .await
            .status(),
        200
    );
    let before = observable(&app).await;
    let r = app.put_json("/cameras/ext3", &camera_spec(false)).await;
    refused(&app, &before, r, 409, "a third camera").await;
    let mut huge = camera_spec(false);
    huge["intrinsics"] =
        json!({"width": 8192, "height": 8192, "k": [6000.0, 0.0, 4096.0, 0.0, 6000.0, 4096.0, 0.0, 0.0, 1.0]});
    let r = app.put_json("/cameras/ext1", &huge).await;
    refused(&app, &before, r, 409, "an 8192x8192 camera").await;
    let long = "n".repeat(10_000);
    let r = app
        .put_bytes(
            &format!("/objects/other?name={long}"),
            "application/octet-stream",
            ply.clone(),
        )
        .await;
    refused(&app, &before, r, 422, "a 100 kB name").await;
    let r = app
        .put_bytes(&format!("/objects/{}", "i".repeat(65)), "application/octet-stream", ply)
        .await;
    refused(&app, &before, r, 422, "a 65-character id").await;
    // ground truth only for registered objects
    let pose = json!({"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 0.0, 0.0]});
    let truth = json!({"stamp_ns": S, "objects": [{"object": "x".repeat(1000), "world_from_object": pose}]});
    let r = app.post_json("/truth", &truth).await;
    refused(&app, &before, r, 422, "truth of an unknown object").await;
    // the caps are visible
    let health = app.client.get(app.url("/healthz")).send().await.expect("healthz");
    let health: Value = health.json().await.expect("json");
    assert_eq!(health["limits"]["max_cameras"], 2);
    assert_eq!(health["limits"]["max_name_chars"], 16);
    assert!(app.metrics_text().await.contains("pregrasp_limit{what=\"cameras\"} 2"));
}

#[tokio::test]
async fn ground_truth_needs_the_option() {
    let app = spawn_app_configured(|c| c.service.accept_truth = false).await;
    let ply = pregrasp::mesh::builtin("box").expect("box").to_ply_bytes();
    assert_eq!(
        app.put_bytes("/objects/box", "application/octet-stream", ply)
            .await
            .status(),
        200
    );
    let before = observable(&app).await;
    let pose = json!({"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 0.0, 0.0]});
    let truth = json!({"stamp_ns": S, "objects": [{"object": "box", "world_from_object": pose}]});
    let r = app.post_json("/truth", &truth).await;
    refused(&app, &before, r, 403, "truth without --accept-truth").await;
}

// Finding 4: a build of a replaced mesh turned the object `ready` with the old codebook.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replaced_mesh_gets_its_own_codebook() {
    let app = spawn_app().await;
    let slow = pregrasp::mesh::builtin_cylinder(0.05, 0.2, 4_000, [[200, 30, 30], [30, 30, 200]]);
    let quick = pregrasp::mesh::builtin("box").expect("box");
    let r = app
        .put_bytes("/objects/obj", "application/octet-stream", slow.to_ply_bytes())
        .await;
    assert_eq!(r.status(), 200);
    // the build of the first mesh starts, then the mesh is replaced
    let deadline = Instant::now() + Duration::from_secs(30);
    while app.get_json("/objects/obj").await["codebook"]["status"] == "pending" && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let r = app
        .put_bytes("/objects/obj", "application/octet-stream", quick.to_ply_bytes())
        .await;
    assert_eq!(r.status(), 200);
    let hash = quick.content_hash();
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let o = app.get_json("/objects/obj").await;
        assert_eq!(o["content_hash"], hash.as_str());
        if o["codebook"]["status"] == "ready" {
            // ready means: ready with this mesh's codebook
            assert!(app.state.codebooks.get("obj", &hash, true).is_some(), "{o}");
            break;
        }
        assert_ne!(o["codebook"]["status"], "failed", "{o}");
        assert!(Instant::now() < deadline, "no codebook: {o}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

// Finding 5: finite but absurd numbers became NaN inside.
#[tokio::test]
async fn absurd_numbers_are_refused_at_the_edge() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/robot", &camera_spec(true)).await.status(), 200);
    let ply = pregrasp::mesh::builtin("box").expect("box").to_ply_bytes();
    assert_eq!(
        app.put_bytes("/objects/box", "application/octet-stream", ply)
            .await
            .status(),
        200
    );
    assert_eq!(
        app.post_json("/cameras/ext1/frames", &frame_json(S, 64, 48, 0.8))
            .await
            .status(),
        202
    );
    assert_eq!(app.post_json("/odometry", &odometry(S, 0.0)).await.status(), 202);
    settle(&app).await;
    let before = observable(&app).await;

    let far = json!({"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [1e308, 0.0, 1.1]});
    let mut cam = camera_spec(false);
    cam["mount"]["world_from_camera"] = far.clone();
    refused(
        &app,
        &before,
        app.put_json("/cameras/ext2", &cam).await,
        422,
        "a camera at 1e308 m",
    )
    .await;
    let mut cam = camera_spec(false);
    cam["intrinsics"]["k"] = json!([1e300, 0.0, 32.0, 0.0, 1e300, 24.0, 0.0, 0.0, 1.0]);
    refused(
        &app,
        &before,
        app.put_json("/cameras/ext2", &cam).await,
        422,
        "a focal length of 1e300",
    )
    .await;

    let t = S + 50 * MS;
    let r = app
        .post_json("/cameras/ext1/frames", &png_frame(t, &png16(64, 48, 800), 1e308))
        .await;
    refused(&app, &before, r, 422, "depth_scale 1e308").await;
    let r = app
        .post_json("/cameras/ext1/frames", &frame_json(t, 64, 48, 1e30))
        .await;
    refused(&app, &before, r, 422, "raw depth of 1e30 m").await;
    for (bbox, score) in [
        (json!([1e300, 0.0, 10.0, 10.0]), 0.9),
        (json!([0.0, 0.0, 10.0, 10.0]), 1e300),
        (json!([0.0, 0.0, 10.0, 10.0]), -0.1),
        (json!([60.0, 40.0, 10.0, 10.0]), 0.9),
        (json!([-5.0, 0.0, 10.0, 10.0]), 0.9),
        (json!([0.0, 0.0, 0.0, 10.0]), 0.9),
    ] {
        let mut f = frame_json(t, 64, 48, 0.8);
        f["detections"] = json!([{"object": "box", "bbox_xywh_px": bbox, "score": score}]);
        let r = app.post_json("/cameras/ext1/frames", &f).await;
        refused(&app, &before, r, 422, &format!("detection {bbox} {score}")).await;
    }

    let mut bad_odometry = Vec::new();
    bad_odometry.push((odometry(t, 1e308), "odometry at 1e308 m"));
    let mut o = odometry(t, 0.0);
    o["world_from_odom"] = far.clone();
    bad_odometry.push((o, "world_from_odom at 1e308 m"));
    let mut o = odometry(t, 0.0);
    o["odom_from_base"]["covariance"] = json!(vec![1e300; 36]);
    bad_odometry.push((o, "a covariance of 1e300"));
    let mut o = odometry(t, 0.0);
    o["base_from_camera"] = far.clone();
    bad_odometry.push((o, "base_from_camera at 1e308"));
    for (o, what) in bad_odometry {
        refused(&app, &before, app.post_json("/odometry", &o).await, 422, what).await;
    }

    let plane = json!({"normal": [0.0, 0.0, 1.0], "point_m": [0.0, 0.0, 1e300]});
    refused(
        &app,
        &before,
        app.put_json("/scene/support_plane", &plane).await,
        422,
        "a plane at 1e300",
    )
    .await;
    let truth = json!({"stamp_ns": t, "objects": [{"object": "box", "world_from_object": far}]});
    refused(
        &app,
        &before,
        app.post_json("/truth", &truth).await,
        422,
        "truth at 1e308",
    )
    .await;
    // a prior at 1e300 (checked before the codebook is asked for)
    let prior = json!({"object_id": "box", "world_from_object": {"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [1e300, 0.0, 0.0]}});
    refused(
        &app,
        &before,
        app.post_json("/tracks", &prior).await,
        422,
        "a prior at 1e300",
    )
    .await;
    let pose = json!({"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 0.0, 1.0]});
    for std in [
        json!({"translation_std_m": 1e-300}),
        json!({"translation_std_m": 1e300}),
        json!({"rotation_std_deg": 1e-300}),
    ] {
        let mut prior = json!({"object_id": "box", "world_from_object": pose});
        for (k, v) in std.as_object().expect("obj") {
            prior[k] = v.clone();
        }
        refused(
            &app,
            &before,
            app.post_json("/tracks", &prior).await,
            422,
            &format!("prior {std}"),
        )
        .await;
    }
    // a decision on a support plane at 1e300 (validated before the track is looked up)
    let d = json!({"support_plane": {"normal": [0.0, 0.0, 1.0], "point_m": [1e300, 0.0, 0.0]}});
    refused(
        &app,
        &before,
        app.post_json("/tracks/1/decision", &d).await,
        422,
        "a decision's plane",
    )
    .await;
}

// Finding 6: the support plane was not persisted.
#[tokio::test]
async fn the_support_plane_survives_a_restart() {
    let app = spawn_app().await;
    let plane = json!({"normal": [0.0, 0.0, 2.0], "point_m": [0.0, 0.0, 0.7]});
    assert_eq!(app.put_json("/scene/support_plane", &plane).await.status(), 200);
    let app = app.restart().await;
    let scene = app.get_json("/scene").await;
    assert_eq!(
        scene["support_plane"],
        json!({"normal": [0.0, 0.0, 1.0], "point_m": [0.0, 0.0, 0.7]})
    );
    assert_eq!(app.put_json("/scene/support_plane", &Value::Null).await.status(), 200);
    let app = app.restart().await;
    assert_eq!(app.get_json("/scene").await["support_plane"], Value::Null);
}

// Issue 17: a demo loop start clears everything that belongs to the last loop.
#[tokio::test]
async fn a_demo_loop_start_leaves_no_frame_or_odometry_behind() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/robot", &camera_spec(true)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    for i in 0..3 {
        let t = S + i * 50 * MS;
        assert_eq!(app.post_json("/odometry", &odometry(t, 1.85)).await.status(), 202);
        for cam in ["robot", "ext1"] {
            let r = app
                .post_json(&format!("/cameras/{cam}/frames"), &frame_json(t, 64, 48, 0.8))
                .await;
            assert_eq!(r.status(), 202);
        }
    }
    let epoch = app.state.ingest().epoch();
    pregrasp::service::demo::reset_tracking(&app.state);
    {
        let ingest = app.state.ingest();
        assert_eq!(ingest.pending(), 0, "no frame of the last loop waits");
        assert_eq!(ingest.odometry_len(), 0, "no odometry of the last loop is kept");
        assert_eq!(ingest.newest_ns(), None);
        assert!(ingest.latest("robot").is_none());
        assert!(ingest.odometry_at(S + 100 * MS).is_none());
        assert_eq!(ingest.epoch(), epoch + 1, "a set taken before the reset is not fused");
    }
    assert_eq!(app.get_json("/tracks").await, json!([]));
    // the next loop's stamps continue and are taken
    let t = S + 200 * MS;
    assert_eq!(app.post_json("/odometry", &odometry(t, 0.0)).await.status(), 202);
    let r = app
        .post_json("/cameras/robot/frames", &frame_json(t, 64, 48, 0.8))
        .await;
    assert_eq!(r.status(), 202);
}

// Finding 7: transport and authentication.
#[tokio::test]
async fn the_token_guards_writes_and_optionally_reads() {
    let app = spawn_app_configured(|c| {
        c.token = Some("s3cret".into());
        c.protect_reads = true;
    })
    .await;
    // the scheme is case-insensitive
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let r = app
            .client
            .put(app.api("/cameras/ext1"))
            .header("authorization", format!("{scheme} s3cret"))
            .json(&camera_spec(false))
            .send()
            .await
            .expect("put");
        assert_eq!(r.status(), 200, "{scheme}");
    }
    let before_cams = app.state.registry().cameras.len();
    for auth in [None, Some("Bearer s3cre"), Some("Bearer s3cret0"), Some("Basic s3cret")] {
        let mut rb = app.client.put(app.api("/cameras/ext2")).json(&camera_spec(false));
        if let Some(a) = auth {
            rb = rb.header("authorization", a);
        }
        let r = rb.send().await.expect("put");
        assert_eq!(
            r.headers().get("www-authenticate").map(|v| v.as_bytes()),
            Some(&b"Bearer"[..])
        );
        assert_problem(r, 401).await;
        // reads too
        let mut rb = app.client.get(app.api("/cameras/ext1/latest/depth.png"));
        if let Some(a) = auth {
            rb = rb.header("authorization", a);
        }
        assert_problem(rb.send().await.expect("get"), 401).await;
    }
    assert_eq!(app.state.registry().cameras.len(), before_cams);
    // /healthz stays open for probes
    let r = app.client.get(app.url("/healthz")).send().await.expect("healthz");
    assert_eq!(r.status(), 200);
}

#[tokio::test]
async fn rejections_are_problem_documents() {
    let app = spawn_app_configured(|c| c.allowed_hosts = vec!["localhost".into(), "127.0.0.1".into()]).await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    let before = observable(&app).await;
    // 405 with Allow
    let r = app
        .client
        .post(app.api("/cameras"))
        .json(&json!({}))
        .send()
        .await
        .expect("post");
    let allow = r
        .headers()
        .get("allow")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    assert!(
        allow.contains("GET"),
        "Allow: {allow} ({} {:?})",
        r.status(),
        r.headers()
    );
    refused(&app, &before, r, 405, "POST /cameras").await;
    // query rejections
    let r = app.get("/tracks/1/samples?n=-1").await;
    assert_problem(r, 400).await;
    let r = app
        .put_bytes("/objects/x?use_color=maybe", "application/octet-stream", vec![1, 2, 3])
        .await;
    refused(&app, &before, r, 400, "use_color=maybe").await;
    // unknown fields in camera and odometry bodies
    let mut cam = camera_spec(false);
    cam["colour"] = json!("red");
    refused(
        &app,
        &before,
        app.put_json("/cameras/ext2", &cam).await,
        422,
        "an unknown camera field",
    )
    .await;
    let mut o = odometry(S, 0.0);
    o["velocity"] = json!([0.0, 0.0, 0.0]);
    refused(
        &app,
        &before,
        app.post_json("/odometry", &o).await,
        422,
        "an unknown odometry field",
    )
    .await;
    // a camera that has sent no frame: 404, not 503
    for path in [
        "/cameras/ext1/latest",
        "/cameras/ext1/latest/depth.png",
        "/cameras/ext1/latest/color.png",
    ] {
        assert_problem(app.get(path).await, 404).await;
    }
    // a foreign Host (DNS rebinding)
    let r = app
        .client
        .get(app.api("/cameras"))
        .header("host", "evil.example:8080")
        .send()
        .await
        .expect("get");
    assert_problem(r, 421).await;
    // a web page of another origin posting a form (no preflight)
    let r = app
        .client
        .post(app.api("/cameras/ext1/frames"))
        .header("origin", "http://evil.example")
        .json(&frame_json(S, 64, 48, 0.8))
        .send()
        .await
        .expect("post");
    refused(&app, &before, r, 403, "a cross-origin frame").await;
    let r = app
        .client
        .get(app.api("/cameras"))
        .header("host", format!("localhost:{}", app.addr.port()))
        .send()
        .await
        .expect("get");
    assert_eq!(r.status(), 200);
}

#[tokio::test]
async fn a_client_that_stops_mid_header_is_disconnected() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let app = spawn_app_configured(|c| c.header_read_timeout = Duration::from_millis(500)).await;
    let mut s = tokio::net::TcpStream::connect(app.addr).await.expect("connect");
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        .await
        .expect("write");
    let t0 = Instant::now();
    let mut buf = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut buf)).await;
    assert!(read.is_ok(), "the connection stayed open");
    assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
}

#[tokio::test]
async fn connections_beyond_the_limit_wait() {
    let app = spawn_app_configured(|c| {
        c.max_connections = 1;
        c.header_read_timeout = Duration::from_secs(1);
    })
    .await;
    // an idle connection holds the only slot until the header-read timeout closes it
    let _idle = tokio::net::TcpStream::connect(app.addr).await.expect("connect");
    tokio::time::sleep(Duration::from_millis(100)).await;
    let t0 = Instant::now();
    let r = app.client.get(app.url("/healthz")).send().await.expect("healthz");
    assert_eq!(r.status(), 200);
    assert!(t0.elapsed() >= Duration::from_millis(500), "{:?}", t0.elapsed());
}
