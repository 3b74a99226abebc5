//! Frame and odometry ingest: both encodings, latest images, scene, metrics, events.

use crate::{camera_spec, frame_json, spawn_app};
use serde_json::json;

fn png16(w: u32, h: u32, value: u16) -> Vec<u8> {
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(w, h, image::Luma([value]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png");
    out.into_inner()
}

fn jpeg(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_pixel(w, h, image::Rgb([200, 30, 40]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Jpeg).expect("jpeg");
    out.into_inner()
}

#[tokio::test]
async fn frames_in_both_encodings_are_taken_and_served_back() {
    let mut app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/robot", &camera_spec(true)).await.status(), 200);
    let mut events = app.client.get(app.api("/events")).send().await.expect("events");
    assert!(
        events.headers()["content-type"]
            .to_str()
            .expect("ct")
            .starts_with("text/event-stream")
    );

    let r = app
        .post_json("/cameras/ext1/frames", &frame_json(1_000_000_000, 64, 48, 0.75))
        .await;
    assert_eq!(r.status(), 202);
    let form = reqwest::multipart::Form::new()
        .text(
            "meta",
            json!({"stamp_ns": 1_050_000_000i64, "depth_scale": 0.1}).to_string(),
        )
        .part(
            "depth",
            reqwest::multipart::Part::bytes(png16(64, 48, 8000)).file_name("d.png"),
        )
        .part(
            "color",
            reqwest::multipart::Part::bytes(jpeg(64, 48)).file_name("c.jpg"),
        );
    let r = app
        .client
        .post(app.api("/cameras/robot/frames"))
        .multipart(form)
        .send()
        .await
        .expect("post");
    assert_eq!(r.status(), 202);
    let accepted: serde_json::Value = r.json().await.expect("json");
    assert_eq!(accepted["stamp_ns"], 1_050_000_000i64);

    let latest = app.get_json("/cameras/robot/latest").await;
    assert_eq!(latest["has_color"], true);
    let png = app.get("/cameras/robot/latest/color.png").await;
    assert_eq!(png.headers()["content-type"], "image/png");
    let img = image::load_from_memory(&png.bytes().await.expect("bytes"))
        .expect("decode")
        .to_rgb8();
    assert_eq!((img.width(), img.height()), (64, 48));
    let p = img.get_pixel(10, 10).0;
    assert!(p[0] > 150 && p[1] < 90, "{p:?}");
    let depth = app.get("/cameras/ext1/latest/depth.png").await;
    assert_eq!(depth.status(), 200);
    let img = image::load_from_memory(&depth.bytes().await.expect("bytes")).expect("decode");
    assert_eq!((img.width(), img.height()), (64, 48));
    // ext1 sent no colour.
    crate::assert_problem(app.get("/cameras/ext1/latest/color.png").await, 404).await;
    // The internal depth of the PNG frame: 8000 * 0.1 mm = 0.8 m.
    let f = app.state.ingest().latest("robot").expect("latest");
    assert!((f.depth.data_m[0] - 0.8).abs() < 1e-6, "{}", f.depth.data_m[0]);

    // Odometry: the robot trajectory appears in the scene.
    for (i, x) in [0.0, 0.5, 1.0].iter().enumerate() {
        let odo = json!({
            "stamp_ns": 1_000_000_000i64 + i as i64 * 100_000_000,
            "odom_from_base": {"pose": {"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [x, 0.0, 0.0]}},
            "world_from_odom": {"rotation_xyzw": [0.0, 0.0, 0.0, 1.0], "translation_m": [0.0, 2.0, 0.0]}
        });
        assert_eq!(app.post_json("/odometry", &odo).await.status(), 202);
    }
    let scene = app.get_json("/scene").await;
    assert_eq!(scene["world_frame"], "world");
    assert_eq!(
        scene["robot_trajectory_m"],
        json!([[0.0, 2.0, 0.0], [0.5, 2.0, 0.0], [1.0, 2.0, 0.0]])
    );
    let cams = scene["cameras"].as_array().expect("cams");
    assert_eq!(cams[0]["id"], "ext1");
    assert_eq!(cams[0]["mount"], "stationary");
    assert_eq!(cams[0]["latest_stamp_ns"], 1_000_000_000i64);
    assert_eq!(cams[1]["mount"], "robot");

    // The SSE stream carried the frame events.
    let mut seen = String::new();
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(5);
    while !seen.contains("\"camera\":\"robot\"") && tokio::time::Instant::now() < deadline {
        match tokio::time::timeout(std::time::Duration::from_secs(2), events.chunk()).await {
            Ok(Ok(Some(c))) => seen.push_str(&String::from_utf8_lossy(&c)),
            _ => break,
        }
    }
    assert!(seen.contains("event: frame"), "{seen}");
    assert!(seen.contains("\"camera\":\"robot\""), "{seen}");

    let metrics = app.metrics_text().await;
    assert!(metrics.contains("pregrasp_frames_accepted_total 2"), "{metrics}");
    assert!(metrics.contains("pregrasp_odometry_accepted_total 3"), "{metrics}");

    // Graceful shutdown ends the open event stream instead of waiting for it forever.
    tokio::time::timeout(std::time::Duration::from_secs(10), app.stop())
        .await
        .expect("shutdown with an open event stream");
    let rest = tokio::time::timeout(std::time::Duration::from_secs(5), async {
        while let Ok(Some(_)) = events.chunk().await {}
    })
    .await;
    assert!(rest.is_ok(), "the event stream ended");
}
