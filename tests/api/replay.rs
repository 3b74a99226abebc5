//! `pregrasp replay` against a server on port 0, with the real YCB-Video clip of the shared
//! data (one stationary camera, ten frames, ground truth).

use crate::spawn_app;
use pregrasp::tools::replay::ReplayArgs;
use std::path::PathBuf;

fn shared() -> PathBuf {
    std::env::var_os("PREGRASP_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_streams_a_sequence_and_asks_for_decisions() {
    let data = shared().join("realdata/ycbv_video_0000/bop");
    assert!(data.join("rig.json").is_file(), "missing {}", data.display());
    let app = spawn_app().await;
    let out = app.data_dir.join("answers.json");
    let args = ReplayArgs {
        data,
        server: app.url(""),
        rate: 0.0,
        token: None,
        out: Some(out.clone()),
        no_decisions: false,
    };
    let summary = pregrasp::tools::replay::run(args.clone()).await.expect("replay");
    assert_eq!(summary.frames_sent, 10, "{summary:?}");
    assert_eq!(summary.frames_refused, 0);
    assert_eq!(summary.robot_frames, 10, "one answer per reference frame");
    let cams = app.get_json("/cameras").await;
    assert_eq!(cams[0]["id"], "cam");
    assert_eq!(cams[0]["intrinsics"]["width"], 640);
    assert_eq!(app.get_json("/objects/025_mug").await["codebook"]["status"], "ready");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).expect("out file")).expect("json");
    assert_eq!(doc["robot_frames"].as_array().expect("frames").len(), 10);
    // The tracker runs behind the stream: by the end there is a track of the mug with ground
    // truth errors attached, and decisions were answered.
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(90);
    let mug = loop {
        let tracks = app.get_json("/tracks").await;
        if let Some(t) = tracks
            .as_array()
            .expect("tracks")
            .iter()
            .find(|t| t["object_id"] == "025_mug")
        {
            break t.clone();
        }
        assert!(tokio::time::Instant::now() < deadline, "no mug track: {tracks}");
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    };
    assert!(mug["truth"]["translation_error_m"].is_number(), "{mug}");
    // Decisions are asked at every reference frame that has a track (the stream may outrun
    // the tracker, so there may be none).
    assert!(summary.decisions <= summary.robot_frames * 2, "{summary:?}");

    // A second replay of the same sequence (its stamps start over) is taken whole.
    let again = pregrasp::tools::replay::run(args).await.expect("second replay");
    assert_eq!(again.frames_sent, 10, "{again:?}");
    assert_eq!(again.frames_refused, 0, "{again:?}");
}
