//! Registration over HTTP and persistence across a restart.

use crate::{assert_problem, camera_spec, spawn_app, spawn_app_with_token};
use serde_json::json;

#[tokio::test]
async fn registry_survives_a_restart() {
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/robot", &camera_spec(true)).await.status(), 200);
    let ply = pregrasp::mesh::builtin("box").expect("box").to_ply_bytes();
    let r = app
        .put_bytes("/objects/box?name=Red%20box", "application/octet-stream", ply)
        .await;
    assert_eq!(r.status(), 200);
    let info: serde_json::Value = r.json().await.expect("json");
    assert_eq!(info["name"], "Red box");
    assert_eq!(info["n_triangles"], 12);
    assert!((info["diameter_m"].as_f64().expect("diameter") - 0.2727).abs() < 0.01);
    let mut gripper = app.get_json("/grippers/default").await["gripper"].clone();
    gripper["max_opening_m"] = json!(0.1);
    let r = app.put_json("/grippers/pj", &gripper).await;
    assert_eq!(r.status(), 200);
    crate::assert_problem(app.put_json("/grippers/bad", &json!({"stroke_m": 0.14})).await, 422).await;

    let mesh = app.get_json("/objects/box/mesh").await;
    assert_eq!(mesh["triangles"].as_array().expect("tris").len(), 12);

    let app = app.restart().await;
    let cams = app.get_json("/cameras").await;
    let ids: Vec<&str> = cams
        .as_array()
        .expect("list")
        .iter()
        .filter_map(|c| c["id"].as_str())
        .collect();
    assert_eq!(ids, vec!["ext1", "robot"]);
    assert_eq!(cams[1]["mount"]["type"], "robot");
    let obj = app.get_json("/objects/box").await;
    assert_eq!(obj["name"], "Red box");
    assert_eq!(app.get_json("/grippers/pj").await["gripper"]["max_opening_m"], 0.1);
    assert_eq!(app.get_json("/grippers").await.as_array().expect("list").len(), 2);

    // Deleting is persisted too.
    let r = app
        .client
        .delete(app.api("/cameras/ext1"))
        .send()
        .await
        .expect("delete");
    assert_eq!(r.status(), 204);
    let app = app.restart().await;
    assert_eq!(app.get_json("/cameras").await.as_array().expect("list").len(), 1);
    assert_problem(app.get("/cameras/ext1").await, 404).await;
}

#[tokio::test]
async fn state_changes_need_the_token_reads_do_not() {
    let app = spawn_app_with_token("s3cret").await;
    let r = app
        .client
        .put(app.api("/cameras/ext1"))
        .json(&camera_spec(false))
        .send()
        .await
        .expect("put");
    assert_problem(r, 401).await;
    let r = app
        .client
        .put(app.api("/cameras/ext1"))
        .bearer_auth("wrong")
        .json(&camera_spec(false))
        .send()
        .await
        .expect("put");
    assert_problem(r, 401).await;
    assert_eq!(app.get_json("/cameras").await.as_array().expect("list").len(), 0);
    // With the token (the helper adds it).
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    let health: serde_json::Value = app
        .client
        .get(app.url("/healthz"))
        .send()
        .await
        .expect("h")
        .json()
        .await
        .expect("j");
    assert_eq!(health["status"], "ok");
    assert_eq!(health["cameras"], 1);
}

#[tokio::test]
async fn an_object_registered_without_colour_gets_a_depth_only_codebook() {
    // A mesh whose colours do not match the cameras' (an untextured CAD model, a scan under
    // other light) is registered with `use_color=false`: its codebook comes from depth alone,
    // and the choice survives a restart.
    let app = spawn_app().await;
    let ply = pregrasp::mesh::builtin("box").expect("box").to_ply_bytes();
    let r = app
        .put_bytes("/objects/cad?use_color=false", "application/octet-stream", ply.clone())
        .await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.json::<serde_json::Value>().await.expect("json")["use_color"], false);
    let r = app.put_bytes("/objects/scan", "application/octet-stream", ply).await;
    assert_eq!(r.json::<serde_json::Value>().await.expect("json")["use_color"], true);
    crate::assert_problem(
        app.put_bytes(
            "/objects/bad?use_color=maybe",
            "application/octet-stream",
            vec![1, 2, 3],
        )
        .await,
        400,
    )
    .await;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    loop {
        let cad = app.get_json("/objects/cad").await;
        let scan = app.get_json("/objects/scan").await;
        if cad["codebook"]["status"] == "ready" && scan["codebook"]["status"] == "ready" {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "codebooks not ready: {cad} {scan}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    let app = app.restart().await;
    assert_eq!(app.get_json("/objects/cad").await["use_color"], false);
    assert_eq!(app.get_json("/objects/scan").await["use_color"], true);
}
