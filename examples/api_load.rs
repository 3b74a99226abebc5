//! Load and soak measurement of the HTTP service (run in release):
//!
//! ```text
//! cargo run --release --example api_load -- [SOAK_SECONDS=120] [DECISION_CLIENTS=50] [DECISIONS_PER_CLIENT=10]
//! ```
//!
//! 1. Starts a server in-process on 127.0.0.1:0 (fresh data folder), registers the demo scene
//!    (three objects, two stationary cameras, one robot camera) and waits for the codebooks.
//! 2. Streams three cameras at 10 Hz each over HTTP (multipart: 16-bit PNG depth + PNG colour +
//!    detections, the robot's odometry before each robot frame), out of phase, for the soak
//!    time; samples the process's resident memory every 10 s.
//! 3. Reports the server's ingest-to-estimate latency quantiles (from `/metrics`), the achieved
//!    step rate, dropped frames, and the memory samples.
//! 4. `DECISION_CLIENTS` concurrent clients each ask `DECISIONS_PER_CLIENT` decisions
//!    (default query: 1,000 samples) for the target's track, once mid-soak while the frames
//!    stream (how a planner meets it) and once after the stream stopped; reports p50/p99
//!    client latency of each.

use pregrasp::api::{ApiConfig, AppState};
use pregrasp::geometry::Pose;
use pregrasp::service::demo::{DemoScene, register};
use rand::SeedableRng;
use serde_json::{Value, json};
use std::sync::Arc;
use std::time::{Duration, Instant};

const CAMERA_HZ: f64 = 10.0;
/// Distinct robot poses pre-rendered (the robot drives back and forth along them).
const ROBOT_POSES: usize = 60;

fn rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

fn png16(d: &pregrasp::camera::DepthImage) -> Vec<u8> {
    let mm = d.to_u16_mm(1.0);
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(d.width, d.height, mm).expect("depth");
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png16");
    out.into_inner()
}

fn png_rgb(c: &pregrasp::camera::ColorImage) -> Vec<u8> {
    let raw: Vec<u8> = c.data.iter().flatten().copied().collect();
    let img = image::RgbImage::from_raw(c.width, c.height, raw).expect("rgb");
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("png");
    out.into_inner()
}

struct Encoded {
    depth: Vec<u8>,
    color: Vec<u8>,
    detections: Value,
}

fn pose_json(p: &Pose) -> Value {
    serde_json::to_value(pregrasp::api::types::PoseDto::from_pose(p)).expect("pose")
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Client latencies of one decision load.
struct DecisionLoad {
    track: u64,
    clients: usize,
    per_client: usize,
    latencies_ms: Vec<f64>,
    failed: usize,
    wall_s: f64,
}

impl DecisionLoad {
    fn print(mut self, when: &str) {
        println!(
            "== decisions {when}: {} concurrent clients x {} (default query, 1,000 samples), track {}",
            self.clients, self.per_client, self.track
        );
        if self.latencies_ms.is_empty() {
            println!("all {} decisions failed", self.failed);
            return;
        }
        let n = self.latencies_ms.len();
        println!(
            "ok {n}, failed {}; p50 {:.0} ms, p99 {:.0} ms, max {:.0} ms; {:.1} decisions/s",
            self.failed,
            quantile(&mut self.latencies_ms, 0.5),
            quantile(&mut self.latencies_ms, 0.99),
            quantile(&mut self.latencies_ms, 1.0),
            n as f64 / self.wall_s
        );
    }
}

/// `clients` concurrent clients each ask `per_client` decisions for the target's track.
async fn decision_load(
    http: &reqwest::Client,
    base: &str,
    clients: usize,
    per_client: usize,
) -> anyhow::Result<Option<DecisionLoad>> {
    let tracks: Value = http.get(format!("{base}/tracks")).send().await?.json().await?;
    let Some(id) = tracks
        .as_array()
        .into_iter()
        .flatten()
        .find(|t| t["object_id"] == pregrasp::service::demo::DEMO_TARGET)
        .and_then(|t| t["id"].as_u64())
    else {
        return Ok(None);
    };
    let t_dec = Instant::now();
    let mut tasks = Vec::new();
    for _ in 0..clients {
        let (http, base) = (http.clone(), base.to_string());
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            let mut failed = 0;
            for _ in 0..per_client {
                let t = Instant::now();
                match http
                    .post(format!("{base}/tracks/{id}/decision"))
                    .json(&json!({}))
                    .send()
                    .await
                {
                    Ok(r) if r.status().is_success() => {
                        let _ = r.bytes().await;
                        lat.push(t.elapsed().as_secs_f64() * 1e3);
                    }
                    _ => failed += 1,
                }
            }
            (lat, failed)
        }));
    }
    let mut latencies_ms = Vec::new();
    let mut failed = 0;
    for t in tasks {
        let (l, f) = t.await?;
        latencies_ms.extend(l);
        failed += f;
    }
    Ok(Some(DecisionLoad {
        track: id,
        clients,
        per_client,
        latencies_ms,
        failed,
        wall_s: t_dec.elapsed().as_secs_f64(),
    }))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args: Vec<f64> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let soak_s = args.first().copied().unwrap_or(120.0);
    let clients = args.get(1).copied().unwrap_or(50.0) as usize;
    let per_client = args.get(2).copied().unwrap_or(10.0) as usize;

    let tmp = tempfile::tempdir()?;
    let state = AppState::open(ApiConfig::new(tmp.path().to_path_buf()))?;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let root = format!("http://{}", listener.local_addr()?);
    let base = format!("{root}/api/v1");
    let bg = pregrasp::api::start_background(&state);
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(pregrasp::api::serve_on(listener, state.clone(), async {
        let _ = rx.await;
    }));

    let scene = DemoScene::new()?;
    register(&state, &scene)?;
    let http = reqwest::Client::new();
    let t_cb = Instant::now();
    loop {
        let objects: Value = http.get(format!("{base}/objects")).send().await?.json().await?;
        if objects
            .as_array()
            .is_some_and(|a| a.iter().all(|o| o["codebook"]["status"] == "ready"))
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    eprintln!("codebooks ready in {:.1} s", t_cb.elapsed().as_secs_f64());

    // Pre-render and encode: the robot at ROBOT_POSES points of its drive, the stationary
    // cameras once each (the scene is static).
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let encode = |f: pregrasp::sensor::CameraFrame| Encoded {
        depth: png16(&f.depth),
        color: png_rgb(f.color.as_ref().expect("color")),
        detections: serde_json::to_value(&f.detections).expect("dets"),
    };
    let robot_path: Vec<Pose> = (0..ROBOT_POSES)
        .map(|i| scene.world_from_base(pregrasp::service::demo::DEMO_DRIVE_S * i as f64 / (ROBOT_POSES - 1) as f64))
        .collect();
    let robot_frames: Vec<Encoded> = robot_path
        .iter()
        .map(|wfb| encode(scene.render("robot", &(wfb * scene.base_from_camera), 0, &mut rng)))
        .collect();
    let stationary: Vec<(String, Encoded)> = scene
        .stationary
        .iter()
        .map(|(id, p)| (id.clone(), encode(scene.render(id, p, 0, &mut rng))))
        .collect();
    let robot_frames = Arc::new(robot_frames);
    let stationary = Arc::new(stationary);
    let robot_path = Arc::new(robot_path);

    let rss_start = rss_mib();
    let t0 = Instant::now();
    let period = Duration::from_secs_f64(1.0 / CAMERA_HZ);
    let mut senders = Vec::new();
    for cam in 0..3usize {
        let (http, base) = (http.clone(), base.clone());
        let (robot_frames, stationary, robot_path) = (robot_frames.clone(), stationary.clone(), robot_path.clone());
        senders.push(tokio::spawn(async move {
            let phase = period.mul_f64(cam as f64 / 3.0);
            let mut refused = 0usize;
            let mut sent = 0usize;
            let mut k: u64 = 0;
            loop {
                let due = phase + period.mul_f64(k as f64);
                if due.as_secs_f64() > soak_s {
                    break;
                }
                if let Some(wait) = due.checked_sub(t0.elapsed()) {
                    tokio::time::sleep(wait).await;
                }
                let stamp_ns = due.as_nanos() as i64 + 1_000_000_000;
                let (name, enc) = if cam == 0 {
                    // Back and forth along the path.
                    let n = ROBOT_POSES as u64;
                    let i = (k % (2 * n - 2)) as usize;
                    let i = if i < ROBOT_POSES { i } else { 2 * ROBOT_POSES - 2 - i };
                    let odo = json!({
                        "stamp_ns": stamp_ns,
                        "odom_from_base": {"pose": pose_json(&robot_path[i])},
                    });
                    let _ = http.post(format!("{base}/odometry")).json(&odo).send().await;
                    ("robot".to_string(), &robot_frames[i])
                } else {
                    (stationary[cam - 1].0.clone(), &stationary[cam - 1].1)
                };
                let meta = json!({"stamp_ns": stamp_ns, "depth_scale": 1.0, "detections": enc.detections});
                let form = reqwest::multipart::Form::new()
                    .text("meta", meta.to_string())
                    .part(
                        "depth",
                        reqwest::multipart::Part::bytes(enc.depth.clone()).file_name("d.png"),
                    )
                    .part(
                        "color",
                        reqwest::multipart::Part::bytes(enc.color.clone()).file_name("c.png"),
                    );
                match http
                    .post(format!("{base}/cameras/{name}/frames"))
                    .multipart(form)
                    .send()
                    .await
                {
                    Ok(r) if r.status().is_success() => sent += 1,
                    _ => refused += 1,
                }
                k += 1;
            }
            (sent, refused)
        }));
    }
    let during = {
        let (http, base) = (http.clone(), base.clone());
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_secs_f64((soak_s / 2.0).min(60.0))).await;
            decision_load(&http, &base, clients, per_client).await
        })
    };
    let mut rss_samples = vec![(0.0, rss_start)];
    while t0.elapsed().as_secs_f64() < soak_s {
        tokio::time::sleep(Duration::from_secs(10)).await;
        rss_samples.push((t0.elapsed().as_secs_f64(), rss_mib()));
    }
    let (mut sent, mut refused) = (0, 0);
    for s in senders {
        let (a, b) = s.await?;
        sent += a;
        refused += b;
    }
    let metrics = http.get(format!("{root}/metrics")).send().await?.text().await?;
    let metric = |name: &str| -> Option<f64> {
        metrics
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.rsplit(' ').next()?.parse().ok())
    };
    let steps = metric("pregrasp_steps_total ").unwrap_or(0.0);
    println!("== soak: 3 cameras x {CAMERA_HZ} Hz for {soak_s:.0} s");
    println!(
        "frames sent {sent}, refused {refused}; tracker steps {steps} ({:.2} steps/s)",
        steps / soak_s
    );
    println!(
        "frames dropped by the queue policy: {}",
        metric("pregrasp_frames_dropped_total ").unwrap_or(f64::NAN)
    );
    for q in ["0.5", "0.9", "0.99"] {
        let v = metric(&format!("pregrasp_ingest_to_estimate_seconds{{quantile=\"{q}\"}}")).unwrap_or(f64::NAN);
        println!(
            "ingest-to-estimate p{}: {:.1} ms",
            (q.parse::<f64>().unwrap_or(0.0) * 100.0).round(),
            v * 1e3
        );
    }
    println!(
        "mean step time {:.1} ms",
        metric("pregrasp_step_seconds_total ").unwrap_or(f64::NAN) / steps.max(1.0) * 1e3
    );
    println!(
        "resident memory (MiB) at t s: {}",
        rss_samples
            .iter()
            .map(|(t, m)| format!("{t:.0}:{m:.0}"))
            .collect::<Vec<_>>()
            .join(" ")
    );

    // Decisions under concurrent load while the frames stream (started mid-soak), then again
    // after the stream stopped.
    if let Some(during) = during.await?? {
        during.print(&format!("while 3 cameras stream at {CAMERA_HZ} Hz"));
    } else {
        println!("no track of the target mid-soak: no decision load while streaming");
    }
    match decision_load(&http, &base, clients, per_client).await? {
        Some(after) => after.print("after the stream stopped"),
        None => println!("no track of the target: no decision load"),
    }
    let _ = tx.send(());
    server.await??;
    bg.shutdown().await;
    Ok(())
}
