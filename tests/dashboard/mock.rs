//! A stand-in for `pregrasp serve` with the routes and JSON shapes pinned in the team brief, so
//! that the dashboard can be tested against known data: two objects whose uncertainty shrinks
//! over time, a stationary and a robot camera, decisions that flip from observe to grasp, and an
//! event stream at 10 Hz. `POST /mock/drop` ends every open event stream (to test reconnects).

use std::convert::Infallible;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use futures::Stream;
use futures::StreamExt as _;
use nalgebra::{Isometry3, Vector3};
use serde_json::{Value, json};
use tokio::sync::watch;
use tower_http::services::ServeDir;

pub const TICK: Duration = Duration::from_millis(100);
const PARTICLES_PER_OBJECT: usize = 150;
const OBJECTS: [(u64, &str, &str, [f64; 3]); 2] = [
    (1, "obj_000005", "mustard_bottle", [0.10, 0.02, 0.095]),
    (2, "obj_000003", "tomato_can", [-0.12, 0.15, 0.05]),
];

#[derive(Clone)]
struct Mock {
    started: Instant,
    drop_streams: watch::Sender<u64>,
    /// While set and in the future, `/api/v1/events` answers 503 (the service "is down").
    down_until: Arc<Mutex<Option<Instant>>>,
}

impl Mock {
    fn tick(&self) -> u64 {
        (self.started.elapsed().as_millis() / TICK.as_millis()) as u64
    }
}

pub struct MockServer {
    pub addr: SocketAddr,
}

pub async fn spawn() -> MockServer {
    let static_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("static");
    let (drop_streams, _) = watch::channel(0u64);
    let mock = Mock {
        started: Instant::now(),
        drop_streams,
        down_until: Arc::new(Mutex::new(None)),
    };
    let app = Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/api/v1/scene", get(scene))
        .route("/api/v1/tracks", get(tracks))
        .route("/api/v1/tracks/{id}/history", get(history))
        .route("/api/v1/objects/{id}/mesh", get(mesh))
        .route("/api/v1/cameras/{id}/latest", get(camera_latest))
        .route("/api/v1/cameras/{id}/latest/{file}", get(camera_image))
        .route("/api/v1/events", get(events))
        .route("/mock/drop", post(drop_streams_handler))
        .fallback_service(ServeDir::new(static_dir))
        .with_state(mock);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind mock server");
    let addr = listener.local_addr().expect("mock address");
    tokio::spawn(async move { axum::serve(listener, app).await.expect("mock server") });
    MockServer { addr }
}

fn pose_json(p: &Isometry3<f64>) -> Value {
    let q = p.rotation.coords;
    let t = p.translation.vector;
    json!({ "rotation_xyzw": [q.x, q.y, q.z, q.w], "translation_m": [t.x, t.y, t.z] })
}

use pregrasp::geometry::look_at;

fn robot_eye(tick: u64) -> [f64; 3] {
    let s = (tick as f64 * 0.01).min(1.0);
    [-1.2 + 0.6 * s, -0.9 + 0.4 * s, 0.55]
}

fn intrinsics() -> Value {
    json!({ "width": 640, "height": 480, "k": [[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]] })
}

async fn scene(State(m): State<Mock>) -> Json<Value> {
    let tick = m.tick();
    let traj: Vec<[f64; 3]> = (0..=tick.min(100)).step_by(5).map(robot_eye).collect();
    Json(json!({
        "world_frame": "world",
        "support_plane": { "normal": [0.0, 0.0, 1.0], "point_m": [0.0, 0.0, 0.0] },
        "cameras": [
            { "id": "ext1", "mount": "stationary", "intrinsics": intrinsics(),
              "world_from_camera": pose_json(&look_at([0.9, -0.5, 0.7], [0.0, 0.05, 0.05])),
              "latest_stamp_ns": tick as i64 * 100_000_000 },
            { "id": "robot", "mount": "robot", "intrinsics": intrinsics(),
              "world_from_camera": pose_json(&look_at(robot_eye(tick), [0.0, 0.05, 0.05])),
              "latest_stamp_ns": tick as i64 * 100_000_000 },
        ],
        "robot_trajectory_m": traj,
    }))
}

/// Deterministic pseudo-random numbers in [-1, 1] (an LCG), so the mock needs no RNG state.
fn noise(seed: u64) -> f64 {
    let x = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    ((x >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

fn track_view(index: usize, tick: u64) -> Value {
    let (id, object_id, name, center) = OBJECTS[index];
    // The second object converges more slowly (seen less well): its clock runs at 60 %.
    let progress = tick as f64 * [1.0, 0.6][index];
    let std_m = 0.04 * (-progress / 40.0).exp() + 0.003;
    let yaw = 0.4 + index as f64;
    let world_from_object = Isometry3::new(Vector3::from(center), Vector3::new(0.0, 0.0, yaw));
    let world_from_reference = look_at(robot_eye(tick), [0.0, 0.05, 0.05]);
    let reference_from_object = world_from_reference.inverse() * world_from_object;
    let particles: Vec<Value> = (0..PARTICLES_PER_OBJECT)
        .map(|i| {
            let s = (tick * 1000 + i as u64) * 3 + index as u64 * 7_777_777;
            let p = [
                center[0] + std_m * 1.7 * noise(s),
                center[1] + std_m * 1.7 * noise(s + 1),
                center[2] + std_m * 1.7 * noise(s + 2),
            ];
            json!({ "position_world_m": p, "camera": if i % 3 == 0 { "robot" } else { "ext1" },
                    "weight": 1.0 / PARTICLES_PER_OBJECT as f64 })
        })
        .collect();
    let samples: Vec<Value> = (0..5)
        .map(|i| {
            let s = tick * 100 + i;
            let d = Isometry3::new(
                Vector3::new(noise(s), noise(s + 1), noise(s + 2)) * std_m,
                Vector3::new(0.0, 0.0, 0.3 * noise(s + 3) * std_m / 0.04),
            );
            pose_json(&(world_from_object * d))
        })
        .collect();
    let p_success = 1.0 - (-progress / 25.0).exp() * 0.9;
    let object_from_gripper = Isometry3::new(
        Vector3::new(0.0, 0.0, 0.02),
        Vector3::new(std::f64::consts::FRAC_PI_2, 0.0, 0.0),
    );
    // Poses inside the decision come as nalgebra serialises them (the grasp module's types).
    let na_pose = |p: &Isometry3<f64>| serde_json::to_value(p).expect("pose json");
    let failing = 1.0 - p_success;
    let decision = json!({
        "decision": if p_success >= 0.8 { "grasp" } else { "observe" },
        "p_success": p_success,
        "ci95": [(p_success - 0.05).max(0.0), (p_success + 0.05).min(1.0)],
        "p_success_raw": 0.9 * p_success,
        "calibration": { "state": "calibrated", "map_settings_hash": "mock", "running_settings_hash": "mock" },
        "n_samples": 200, "effective_sample_size": 180.0, "threshold": 0.8,
        "grasp": { "object_from_gripper": na_pose(&object_from_gripper), "approach_in_object": [0.0, -1.0, 0.0],
                   "closing_in_object": [1.0, 0.0, 0.0], "depth_m": 0.02, "width_m": 0.07, "label": "approach -a1, close a0" },
        "reference_from_gripper": na_pose(&(reference_from_object * object_from_gripper)),
        "reasons": [
            { "test": "contact", "failure_share": 0.6 * failing, "drivers": [],
              "message": format!("{:.1}% of samples: a pad misses the object", 60.0 * failing) },
            { "test": "approach", "failure_share": 0.4 * failing, "drivers": [],
              "message": format!("{:.1}% of samples: the open gripper hits the object", 40.0 * failing) },
        ],
        "uncertainty": [
            { "motion": "translation", "axis": "gripper_x", "axis_in_reference": [1.0, 0.0, 0.0],
              "spread": std_m, "failure_correlation": 0.55 },
        ],
        "candidates": [],
    });
    json!({
        "id": id, "object_id": object_id, "object_name": name,
        "status": if tick < 5 { "initialising" } else { "tracking" },
        "stamp_ns": tick as i64 * 100_000_000,
        "reference_from_object": pose_json(&reference_from_object),
        "world_from_object": pose_json(&world_from_object),
        "translation_std_m": std_m,
        "rotation_entropy": 3.0 * (-progress / 30.0).exp() + 0.2,
        "top_mode_mass": 1.0 - 0.8 * (-progress / 30.0).exp(),
        "components": [{ "camera": "ext1", "weight": 1.0, "mean_m": center,
                         "covariance_m2": [[std_m * std_m, 0.0, 0.0], [0.0, std_m * std_m, 0.0], [0.0, 0.0, std_m * std_m]] }],
        "particles": particles,
        "samples_world": samples,
        "decision": decision,
        "truth": { "translation_error_m": std_m * 0.8, "orientation_error_deg": 20.0 * (-progress / 30.0).exp() + 1.0 },
    })
}

async fn tracks(State(m): State<Mock>) -> Json<Value> {
    let tick = m.tick();
    Json(Value::Array((0..OBJECTS.len()).map(|i| track_view(i, tick)).collect()))
}

/// One point per tick so far, like the service's ring buffer of past estimates.
async fn history(State(m): State<Mock>, Path(id): Path<u64>) -> Response {
    let Some(index) = OBJECTS.iter().position(|o| o.0 == id) else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let points: Vec<Value> = (0..m.tick())
        .map(|tick| {
            let t = track_view(index, tick);
            json!({ "stamp_ns": t["stamp_ns"], "world_from_object": t["world_from_object"],
                    "translation_std_m": t["translation_std_m"], "rotation_entropy": t["rotation_entropy"],
                    "status": t["status"], "truth": t["truth"] })
        })
        .collect();
    Json(Value::Array(points)).into_response()
}

async fn mesh(Path(id): Path<String>) -> Response {
    let Some(&(_, _, name, _)) = OBJECTS.iter().find(|o| o.1 == id) else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let (hx, hy, hz) = if name == "tomato_can" {
        (0.035, 0.035, 0.05)
    } else {
        (0.045, 0.03, 0.095)
    };
    let v: Vec<[f64; 3]> = (0..8)
        .map(|i| {
            [
                if i & 1 == 0 { -hx } else { hx },
                if i & 2 == 0 { -hy } else { hy },
                if i & 4 == 0 { -hz } else { hz },
            ]
        })
        .collect();
    let t = [
        [0, 2, 1],
        [1, 2, 3],
        [4, 5, 6],
        [5, 7, 6],
        [0, 1, 4],
        [1, 5, 4],
        [2, 6, 3],
        [3, 6, 7],
        [0, 4, 2],
        [2, 4, 6],
        [1, 3, 5],
        [3, 7, 5],
    ];
    Json(json!({ "vertices_m": v, "triangles": t })).into_response()
}

async fn camera_latest(State(m): State<Mock>, Path(id): Path<String>) -> Response {
    if id != "ext1" && id != "robot" {
        return StatusCode::NOT_FOUND.into_response();
    }
    let tick = m.tick();
    Json(json!({
        "stamp_ns": tick as i64 * 100_000_000,
        "detections": [
            { "object": "obj_000005", "bbox_xywh_px": [300.0, 180.0, 90.0, 140.0], "score": 0.93 },
            { "object": "obj_000003", "bbox_xywh_px": [180.0, 220.0, 70.0, 80.0], "score": 0.81 },
        ],
    }))
    .into_response()
}

async fn camera_image(Path((id, file)): Path<(String, String)>) -> Response {
    if (id != "ext1" && id != "robot") || (file != "depth.png" && file != "color.png") {
        return StatusCode::NOT_FOUND.into_response();
    }
    let depth = file == "depth.png";
    let img = image::RgbImage::from_fn(160, 120, |x, y| {
        let v = ((x + y) * 255 / 280) as u8;
        if depth {
            image::Rgb([v, v / 2, 255 - v])
        } else {
            image::Rgb([90 + v / 3, 80, 70 + (y as u8)])
        }
    });
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("png");
    ([(header::CONTENT_TYPE, "image/png")], png).into_response()
}

#[derive(serde::Deserialize)]
struct DropQuery {
    /// Refuse new event streams for this long after dropping the open ones.
    down_ms: Option<u64>,
}

async fn drop_streams_handler(State(m): State<Mock>, Query(q): Query<DropQuery>) -> StatusCode {
    if let Some(ms) = q.down_ms {
        *m.down_until.lock().expect("lock") = Some(Instant::now() + Duration::from_millis(ms));
    }
    m.drop_streams.send_modify(|g| *g += 1);
    StatusCode::NO_CONTENT
}

async fn events(State(m): State<Mock>) -> Response {
    let down = m.down_until.lock().expect("lock").is_some_and(|t| Instant::now() < t);
    if down {
        return StatusCode::SERVICE_UNAVAILABLE.into_response();
    }
    event_stream(m).into_response()
}

fn event_stream(m: Mock) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let mut dropped = m.drop_streams.subscribe();
    dropped.mark_unchanged();
    let mut interval = tokio::time::interval(TICK);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let stream = futures::stream::unfold((m, interval, dropped), |(m, mut interval, mut dropped)| async move {
        tokio::select! {
            _ = interval.tick() => {}
            _ = dropped.changed() => return None,
        }
        let tick = m.tick();
        let mut batch = Vec::new();
        for i in 0..OBJECTS.len() {
            let t = track_view(i, tick);
            batch.push(
                Event::default()
                    .event("decision")
                    .data(json!({ "track_id": t["id"], "decision": t["decision"] }).to_string()),
            );
            batch.push(Event::default().event("track").data(t.to_string()));
        }
        for cam in ["ext1", "robot"] {
            batch.push(
                Event::default()
                    .event("frame")
                    .data(json!({ "camera": cam, "stamp_ns": tick as i64 * 100_000_000 }).to_string()),
            );
        }
        if tick % 10 == 0 {
            batch.push(
                Event::default()
                    .event("stats")
                    .data(json!({ "step_rate_hz": 10.0, "ingest_rate_hz": 20.0, "queue_depth": 0 }).to_string()),
            );
        }
        Some((futures::stream::iter(batch.into_iter().map(Ok)), (m, interval, dropped)))
    })
    .flatten();
    Sse::new(stream).keep_alive(KeepAlive::default())
}
