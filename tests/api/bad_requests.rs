//! A battery of bad requests: each answered with its 4xx problem document, nothing changed.

use crate::{TestApp, assert_problem, camera_spec, frame_json, spawn_app};
use serde_json::{Value, json};

async fn snapshot(app: &TestApp) -> (Value, Value, Value, Value) {
    let mut objects = app.get_json("/objects").await;
    // The codebook builds in the background: its status is not what the requests could change.
    for o in objects.as_array_mut().into_iter().flatten() {
        o["codebook"] = Value::Null;
    }
    (
        app.get_json("/cameras").await,
        objects,
        app.get_json("/grippers").await,
        app.get_json("/tracks").await,
    )
}

fn png16(w: u32, h: u32, value: u16) -> Vec<u8> {
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(w, h, image::Luma([value]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png");
    out.into_inner()
}

/// Registers the built-in can as object `can`.
async fn register_can(app: &TestApp) {
    let ply = pregrasp::mesh::builtin("can").expect("can").to_ply_bytes();
    let r = app.put_bytes("/objects/can", "application/octet-stream", ply).await;
    assert_eq!(r.status(), 200);
}

#[tokio::test]
async fn bad_requests_get_problem_documents_and_change_nothing() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    register_can(&app).await;
    assert_eq!(
        app.post_json("/cameras/ext1/frames", &frame_json(1_000_000_000, 64, 48, 0.8))
            .await
            .status(),
        202
    );
    let before = snapshot(&app).await;

    // Malformed JSON.
    let r = app
        .post_raw(
            "/cameras/ext1/frames",
            "application/json",
            b"{\"stamp_ns\": 1,".to_vec(),
        )
        .await;
    assert_problem(r, 400).await;
    let r = app
        .client
        .put(app.api("/cameras/ext2"))
        .header("content-type", "application/json")
        .body("{nope")
        .send()
        .await
        .expect("put");
    assert_problem(r, 400).await;
    // Wrong content types.
    let r = app
        .client
        .put(app.api("/cameras/ext2"))
        .header("content-type", "text/plain")
        .body(camera_spec(false).to_string())
        .send()
        .await
        .expect("put");
    assert_problem(r, 415).await;
    let r = app
        .post_raw("/cameras/ext1/frames", "text/csv", b"1,2,3".to_vec())
        .await;
    assert_problem(r, 415).await;
    let r = app.put_bytes("/objects/x", "image/png", b"ply".to_vec()).await;
    assert_problem(r, 415).await;
    // Non-unit quaternion, non-finite numbers, bad intrinsics, missing fields.
    let mut spec = camera_spec(false);
    spec["mount"]["world_from_camera"]["rotation_xyzw"] = json!([0.0, 0.0, 0.5, 0.5]);
    let p = assert_problem(app.put_json("/cameras/ext2", &spec).await, 422).await;
    assert!(p["detail"].as_str().expect("detail").contains("unit quaternion"), "{p}");
    let body = camera_spec(false)
        .to_string()
        .replace("[0.0,0.0,0.0]", "[1e999,0.0,0.0]");
    let r = app
        .client
        .put(app.api("/cameras/ext2"))
        .header("content-type", "application/json")
        .body(body)
        .send()
        .await
        .expect("put");
    // JSON has no NaN or infinity: an out-of-range number is malformed JSON.
    assert_problem(r, 400).await;
    let mut spec = camera_spec(false);
    spec["intrinsics"]["k"][0] = json!(-60.0);
    assert_problem(app.put_json("/cameras/ext2", &spec).await, 422).await;
    assert_problem(
        app.put_json("/cameras/ext2", &json!({"intrinsics": {"width": 64}}))
            .await,
        422,
    )
    .await;
    assert_problem(app.put_json("/cameras/bad%20id", &camera_spec(false)).await, 422).await;
    // Unknown ids.
    assert_problem(
        app.post_json("/cameras/nope/frames", &frame_json(2_000_000_000, 64, 48, 0.8))
            .await,
        404,
    )
    .await;
    assert_problem(app.get("/objects/nope").await, 404).await;
    assert_problem(app.get("/tracks/42").await, 404).await;
    assert_problem(app.get("/tracks/abc").await, 400).await;
    assert_problem(
        app.client.get(app.url("/no/such/route")).send().await.expect("get"),
        404,
    )
    .await;
    let r = app
        .client
        .delete(app.api("/grippers/nope"))
        .send()
        .await
        .expect("delete");
    assert_problem(r, 404).await;
    // Images whose size disagrees with the camera.
    assert_problem(
        app.post_json("/cameras/ext1/frames", &frame_json(1_010_000_000, 32, 48, 0.8))
            .await,
        422,
    )
    .await;
    let form = reqwest::multipart::Form::new()
        .text(
            "meta",
            json!({"stamp_ns": 1_020_000_000i64, "depth_scale": 1.0}).to_string(),
        )
        .part(
            "depth",
            reqwest::multipart::Part::bytes(png16(65, 48, 800)).file_name("d.png"),
        );
    let r = app
        .client
        .post(app.api("/cameras/ext1/frames"))
        .multipart(form)
        .send()
        .await
        .expect("post");
    let p = assert_problem(r, 422).await;
    assert!(p["detail"].as_str().expect("detail").contains("65x48"), "{p}");
    // Detections naming an unknown object, or with NaN-like boxes.
    let mut f = frame_json(1_030_000_000, 64, 48, 0.8);
    f["detections"] = json!([{"object": "ghost", "bbox_xywh_px": [1.0, 1.0, 5.0, 5.0], "score": 0.9}]);
    assert_problem(app.post_json("/cameras/ext1/frames", &f).await, 422).await;
    f["detections"] = json!([{"object": "can", "bbox_xywh_px": [1.0, 1.0, -5.0, 5.0], "score": 0.9}]);
    assert_problem(app.post_json("/cameras/ext1/frames", &f).await, 422).await;
    // NaN in a raw float depth image.
    let mut f = frame_json(1_035_000_000, 64, 48, f32::NAN);
    f["detections"] = json!([]);
    let p = assert_problem(app.post_json("/cameras/ext1/frames", &f).await, 422).await;
    assert!(p["detail"].as_str().expect("detail").contains("non-finite"), "{p}");
    // Bad base64.
    let mut f = frame_json(1_040_000_000, 64, 48, 0.8);
    f["depth"]["data_base64"] = json!("***");
    assert_problem(app.post_json("/cameras/ext1/frames", &f).await, 400).await;
    // Stale and duplicate stamps (the window is 300 ms; the newest frame is at 1 s).
    assert_eq!(
        app.post_json("/cameras/ext1/frames", &frame_json(1_500_000_000, 64, 48, 0.8))
            .await
            .status(),
        202
    );
    let p = assert_problem(
        app.post_json("/cameras/ext1/frames", &frame_json(1_100_000_000, 64, 48, 0.8))
            .await,
        409,
    )
    .await;
    assert!(p["detail"].as_str().expect("detail").contains("window"), "{p}");
    assert_problem(
        app.post_json("/cameras/ext1/frames", &frame_json(1_500_000_000, 64, 48, 0.8))
            .await,
        409,
    )
    .await;
    // Oversize body (limit 4 MiB in tests).
    let big = vec![b' '; 5 * 1024 * 1024];
    assert_problem(
        app.post_raw("/cameras/ext1/frames", "application/json", big.clone())
            .await,
        413,
    )
    .await;
    assert_problem(
        app.put_bytes("/objects/big", "application/octet-stream", big).await,
        413,
    )
    .await;
    // Broken meshes.
    let r = app
        .put_bytes(
            "/objects/broken?format=ply",
            "application/octet-stream",
            b"ply\nformat ascii 1.0\nelement vertex 3\n".to_vec(),
        )
        .await;
    assert!(r.status().is_client_error());
    assert_problem(r, 422).await;
    let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n".to_vec();
    assert_problem(app.put_bytes("/objects/broken?format=obj", "model/obj", obj).await, 422).await;
    let obj_mm = b"v 0 0 0\nv 100 0 0\nv 0 100 0\nf 1 2 3\n".to_vec();
    let p = assert_problem(
        app.put_bytes("/objects/broken?format=obj", "model/obj", obj_mm).await,
        422,
    )
    .await;
    assert!(p["detail"].as_str().expect("detail").contains("millimetres"), "{p}");
    assert_problem(
        app.put_bytes("/objects/broken", "application/octet-stream", b"garbage".to_vec())
            .await,
        400,
    )
    .await;
    // Odometry with a non-unit quaternion and a short covariance.
    let odo = json!({"stamp_ns": 1, "odom_from_base": {"pose": {"rotation_xyzw": [0.0, 0.0, 0.0, 2.0], "translation_m": [0.0, 0.0, 0.0]}}});
    assert_problem(app.post_json("/odometry", &odo).await, 422).await;
    let odo = json!({"stamp_ns": 1, "odom_from_base": {"pose": {"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 0.0, 0.0]}, "covariance": [1.0]}});
    assert_problem(app.post_json("/odometry", &odo).await, 422).await;

    // Nothing changed in the registry or the tracks.
    assert_eq!(snapshot(&app).await, before);
    let latest = app.get_json("/cameras/ext1/latest").await;
    assert_eq!(latest["stamp_ns"], 1_500_000_000i64);
    let metrics = app.metrics_text().await;
    assert!(metrics.contains("pregrasp_frames_stale_total 2"), "{metrics}");
}

#[tokio::test]
async fn a_prior_track_needs_cameras_and_a_known_object() {
    let app = spawn_app().await;
    let prior = json!({"object_id": "can", "world_from_object": {"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 0.0, 0.5]}});
    assert_problem(app.post_json("/tracks", &prior).await, 404).await;
    register_can(&app).await;
    let p = assert_problem(app.post_json("/tracks", &prior).await, 409).await;
    assert!(p["detail"].as_str().unwrap_or_default().contains("camera"), "{p}");
    assert!(app.get_json("/tracks").await.as_array().expect("tracks").is_empty());
}
