//! The OpenAPI document drives a real client: openapi-python-client (installed by
//! `scripts/setup.sh --python-client` into `target/openapi-client-venv`, pinned) generates a
//! Python client from `openapi/openapi.json`, and `python_client/check.py` calls a running
//! server through it: health, registry, a track started from a prior, its decision with its
//! context, and problem documents. Offline once the package is installed. A missing
//! installation is a failure with the command that fixes it, never a silent skip.

use crate::{camera_spec, spawn_app};
use pregrasp::geometry::Pose;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// The virtual environment with openapi-python-client (`PREGRASP_PYTHON_CLIENT_VENV`, else
/// `target/openapi-client-venv`).
fn venv() -> PathBuf {
    std::env::var_os("PREGRASP_PYTHON_CLIENT_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("target/openapi-client-venv"))
}

fn pose_json(p: &Pose) -> Value {
    serde_json::to_value(pregrasp::geometry::PoseXyzw::from_pose(p)).expect("pose")
}

fn pose_from_json(v: &Value) -> Pose {
    serde_json::from_value::<pregrasp::geometry::PoseXyzw>(v.clone())
        .expect("pose json")
        .to_pose()
        .expect("pose")
}

#[tokio::test]
async fn a_generated_python_client_calls_the_service() {
    let venv = venv();
    let generator = venv.join("bin/openapi-python-client");
    assert!(
        generator.is_file(),
        "{} is missing: run scripts/setup.sh --python-client (installs openapi-python-client into that virtual environment)",
        generator.display()
    );
    // generate the client from the document in the repository
    let out = tempfile::tempdir().expect("tempdir");
    let package = out.path().join("pregrasp_client");
    let spec = Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi/openapi.json");
    let gen_out = Command::new(&generator)
        .args(["generate", "--meta", "none", "--path"])
        .arg(&spec)
        .arg("--output-path")
        .arg(&package)
        .current_dir(out.path())
        .output()
        .expect("run openapi-python-client");
    let log = String::from_utf8_lossy(&gen_out.stdout).to_string() + &String::from_utf8_lossy(&gen_out.stderr);
    assert!(gen_out.status.success(), "openapi-python-client failed:\n{log}");
    assert!(
        package.join("api/decisions/post_decision.py").is_file(),
        "no decision call generated:\n{log}"
    );
    // every operation but the two PNG images is generated with its answers
    let skipped: Vec<&str> = log.lines().filter(|l| l.contains("will not be generated")).collect();
    assert!(
        skipped.is_empty(),
        "operations left out of the client: {skipped:?}\n{log}"
    );

    // a server with two cameras and the box, its codebook ready
    let app = spawn_app().await;
    assert_eq!(app.put_json("/cameras/ext1", &camera_spec(false)).await.status(), 200);
    assert_eq!(app.put_json("/cameras/robot", &camera_spec(true)).await.status(), 200);
    let mesh = pregrasp::mesh::builtin("box").expect("box");
    let r = app
        .put_bytes("/objects/box", "application/octet-stream", mesh.to_ply_bytes())
        .await;
    assert_eq!(r.status(), 200);
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let o = app.get_json("/objects/box").await;
        if o["codebook"]["status"] == "ready" {
            break;
        }
        assert_ne!(o["codebook"]["status"], "failed", "{o}");
        assert!(Instant::now() < deadline, "no codebook: {o}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    // the Python side: a track from a prior 0.6 m in front of the cameras, and its decision
    let world_from_object = Pose::from_parts(
        nalgebra::Translation3::new(0.0, 0.0, 0.6),
        nalgebra::UnitQuaternion::identity(),
    );
    let python = venv.join("bin/python");
    let base = format!("http://{}", app.addr);
    let prior = pose_json(&world_from_object).to_string();
    let run = tokio::task::spawn_blocking(move || {
        Command::new(python)
            .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/api/python_client/check.py"))
            .args([base.as_str(), "box", prior.as_str()])
            .env("PYTHONPATH", out.path())
            .env("PYTHONDONTWRITEBYTECODE", "1")
            .output()
            .expect("run python")
    })
    .await
    .expect("python task");
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "check.py failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let summary: Value = serde_json::from_str(stdout.lines().last().unwrap_or("")).expect("summary json");

    // what Python read is what the server says over plain HTTP
    assert_eq!(summary["health_status"], "ok");
    assert_eq!(summary["cameras"], json!(["ext1", "robot"]));
    assert_eq!(summary["object_hash"], mesh.content_hash().as_str());
    assert_eq!(summary["scene_cameras"], 2);
    assert_eq!(summary["missing_status"], 404);
    assert_eq!(summary["bad_status"], 422);
    let id = summary["track_id"].as_u64().expect("track id");
    let track = app.get_json(&format!("/tracks/{id}")).await;
    assert_eq!(summary["track_object"], "box");
    let decision = &track["decision"];
    assert_eq!(summary["verdict"], decision["decision"]);
    assert_eq!(summary["p_success"], decision["p_success"]);
    assert_eq!(summary["carried_p_success"], decision["p_success"]);
    assert_eq!(summary["stamp_ns"], decision["stamp_ns"]);
    assert_eq!(summary["calibration_state"], decision["calibration"]["state"]);
    assert_eq!(
        summary["running_settings_hash"],
        decision["calibration"]["running_settings_hash"]
    );
    assert_eq!(summary["rule_quantity"], decision["rule"]["quantity"]);
    assert_eq!(summary["rule_threshold"], 0.8);
    assert_eq!(summary["p_success_raw"], decision["p_success_raw"]);
    assert!(summary["n_candidates"].as_u64() > Some(0), "{summary}");
    // the decision's context: the gripper in the base is the robot camera's mount times the
    // gripper in the reference (robot camera) frame
    let base_from_camera = pose_from_json(&camera_spec(true)["mount"]["base_from_camera"]);
    let rfg = pose_from_json(&summary["reference_from_gripper"]);
    let bfg = pose_from_json(&summary["base_from_gripper"]);
    let expected = base_from_camera * rfg;
    assert!(
        (bfg.translation.vector - expected.translation.vector).norm() < 1e-9,
        "{summary}"
    );
    assert_eq!(summary["world_from_gripper"], decision["world_from_gripper"]);
}
