//! `pregrasp replay`: streams a sequence (the generator's multi-view BOP format) into a running
//! server over HTTP exactly as a robot would: registration (objects, cameras, support plane),
//! then the frames of all cameras interleaved by capture time, the odometry before each robot
//! frame, detections with every frame, and (when the data has it) the ground-truth channel for
//! display. At every robot frame it asks for the tracks and a decision for each.

use crate::dataset::Sequence;
use crate::geometry::Pose;
use anyhow::Context;
use serde::Serialize;
use serde_json::{Value, json};
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Seed of the stand-in detections.
pub const DETECTION_SEED: u64 = 7;

/// What was sent, one entry per step in time.
#[derive(Debug, Clone)]
enum Item {
    Frame { camera: String, frame: u32 },
    Odometry { frame: u32 },
}

/// One answer of the server at a robot frame.
#[derive(Debug, Clone, Serialize)]
pub struct RobotFrameAnswer {
    pub frame: u32,
    pub stamp_ns: i64,
    pub tracks: Value,
    pub decisions: Vec<Value>,
}

/// Summary printed at the end (and the answers with `--out`).
#[derive(Debug, Clone, Serialize)]
pub struct ReplaySummary {
    pub sequence: String,
    pub frames_sent: usize,
    pub frames_refused: usize,
    pub odometry_sent: usize,
    pub robot_frames: usize,
    pub decisions: usize,
    pub grasp_decisions: usize,
    /// Mean over robot frames of the target's translation error against ground truth, metres
    /// (from the tracks' `truth` field), when available.
    pub mean_translation_error_m: Option<f64>,
    pub mean_orientation_error_deg: Option<f64>,
    pub wall_s: f64,
}

/// A pose as the API takes it (`{rotation_xyzw, translation_m}`).
fn pose_json(p: &Pose) -> Value {
    serde_json::to_value(crate::geometry::PoseXyzw::from_pose(p)).unwrap_or_default()
}

/// Options of `pregrasp replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    /// A sequence folder (the generator's multi-view BOP format).
    #[arg(long)]
    pub data: PathBuf,
    /// Server base URL.
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// Playback rate (1 = real time; 0 = as fast as the server takes it).
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// Bearer token.
    #[arg(long, env = "PREGRASP_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Write the answers (per robot frame: time, estimate, decision) as JSON.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Stream only: ask for no estimate or decision at each robot frame (a soak's streamer,
    /// whose planners ask on their own).
    #[arg(long)]
    pub no_decisions: bool,
}

/// `pregrasp replay`: streams the sequence and prints the summary.
pub fn cli(args: ReplayArgs) -> anyhow::Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    let summary = rt.block_on(run(args))?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
}

impl Client {
    fn req(&self, m: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let rb = self.http.request(m, format!("{}/api/v1{}", self.base, path));
        match &self.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        }
    }
    async fn check(rb: reqwest::RequestBuilder, what: &str) -> anyhow::Result<Value> {
        let r = rb.send().await.with_context(|| format!("{what}: request failed"))?;
        let status = r.status();
        let body: Value = r.json().await.unwrap_or(Value::Null);
        if !status.is_success() {
            anyhow::bail!("{what}: {status}: {}", body["detail"].as_str().unwrap_or(""));
        }
        Ok(body)
    }
}

/// Registers everything and streams the sequence; returns the summary (and writes `--out`).
pub async fn run(args: ReplayArgs) -> anyhow::Result<ReplaySummary> {
    let seq = {
        let data = args.data.clone();
        tokio::task::spawn_blocking(move || Sequence::open(&data)).await??
    };
    let client = Client {
        http: reqwest::Client::builder().timeout(Duration::from_secs(60)).build()?,
        base: args.server.trim_end_matches('/').to_string(),
        token: args.token.clone(),
    };
    let started = Instant::now();
    register(&client, &seq).await?;
    wait_for_codebooks(&client).await?;
    let answers = stream(&client, &seq, args.rate, !args.no_decisions).await?;
    let mut summary = summarise(&seq, &answers.0, answers.1);
    summary.wall_s = started.elapsed().as_secs_f64();
    if let Some(out) = &args.out {
        let doc = json!({ "summary": summary, "robot_frames": answers.0 });
        std::fs::write(out, serde_json::to_vec_pretty(&doc)?).with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(summary)
}

async fn register(c: &Client, seq: &Sequence) -> anyhow::Result<()> {
    for o in &seq.rig.objects {
        let mesh = seq.load_mesh(&o.name)?;
        Client::check(
            c.req(
                reqwest::Method::PUT,
                &format!("/objects/{}?format=ply&name={}", o.name, o.name),
            )
            .header("content-type", "application/octet-stream")
            .body(mesh.to_ply_bytes()),
            &format!("registering object {}", o.name),
        )
        .await?;
    }
    let first_odometry = seq.odometry.as_ref().and_then(|o| o.values().next().copied());
    for (name, rig_cam) in &seq.rig.cameras {
        let stream = seq.camera(name)?;
        let Some((_, meta)) = stream.frames.iter().next() else {
            continue;
        };
        let mount = match rig_cam.mount {
            crate::dataset::Mount::Robot => {
                let base_from_camera = first_odometry
                    .map(|o| o.base_from_camera)
                    .unwrap_or_else(Pose::identity);
                json!({"type": "robot", "base_from_camera": pose_json(&base_from_camera)})
            }
            crate::dataset::Mount::Stationary => {
                let world_from_camera = meta
                    .camera_from_world
                    .map(|p| p.inverse())
                    .unwrap_or_else(Pose::identity);
                json!({"type": "stationary", "world_from_camera": pose_json(&world_from_camera)})
            }
        };
        let spec = json!({
            "intrinsics": {"width": meta.intrinsics.width, "height": meta.intrinsics.height, "k": meta.intrinsics.k},
            "mount": mount,
        });
        Client::check(
            c.req(reqwest::Method::PUT, &format!("/cameras/{name}")).json(&spec),
            &format!("registering camera {name}"),
        )
        .await?;
    }
    let plane = seq
        .rig
        .support_plane
        .map(|p| json!({"normal": p.normal, "point_m": p.point_m}))
        .unwrap_or(Value::Null);
    Client::check(
        c.req(reqwest::Method::PUT, "/scene/support_plane").json(&plane),
        "setting the support plane",
    )
    .await?;
    Ok(())
}

/// Waits until every object's codebook is ready (a robot would not stream before that).
async fn wait_for_codebooks(c: &Client) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(600);
    loop {
        let objects = Client::check(c.req(reqwest::Method::GET, "/objects"), "objects").await?;
        let list = objects.as_array().cloned().unwrap_or_default();
        if let Some(failed) = list.iter().find(|o| o["codebook"]["status"] == "failed") {
            anyhow::bail!("codebook of {} failed: {}", failed["id"], failed["codebook"]["error"]);
        }
        if list.iter().all(|o| o["codebook"]["status"] == "ready") {
            return Ok(());
        }
        if Instant::now() > deadline {
            anyhow::bail!("codebooks not ready after 10 minutes");
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// Ground truth of a time step for the display channel: `world_from_object` of every object
/// seen by a camera whose pose is known in the data (evaluation only; the tracker never sees it).
fn truth_of(seq: &Sequence, camera: &str, frame: u32) -> Option<Value> {
    let stream = seq.cameras.get(camera)?;
    let camera_from_world = stream.frames.get(&frame)?.camera_from_world?;
    let gt = stream.gt.get(&frame)?;
    let objects: Vec<Value> = gt
        .iter()
        .map(|g| {
            json!({
                "object": seq.rig.object_name(g.obj_id),
                "world_from_object": pose_json(&(camera_from_world.inverse() * g.camera_from_object)),
            })
        })
        .collect();
    Some(json!({"stamp_ns": stream.frames.get(&frame)?.stamp_ns, "objects": objects}))
}

fn multipart_frame(seq: &Sequence, camera: &str, frame: u32) -> anyhow::Result<reqwest::multipart::Form> {
    let meta = seq.frame(camera, frame)?;
    let depth = std::fs::read(seq.depth_path(camera, frame))?;
    let detections = seq.detections(camera, frame, DETECTION_SEED);
    let meta_json = json!({
        "stamp_ns": meta.stamp_ns,
        "depth_encoding": "png16",
        "depth_scale": meta.depth_scale,
        "detections": detections,
    });
    let mut form = reqwest::multipart::Form::new()
        .text("meta", meta_json.to_string())
        .part("depth", reqwest::multipart::Part::bytes(depth).file_name("depth.png"));
    let rgb = seq.rgb_path(camera, frame);
    if rgb.is_file() {
        form = form.part(
            "color",
            reqwest::multipart::Part::bytes(std::fs::read(rgb)?).file_name("rgb.png"),
        );
    }
    Ok(form)
}

async fn stream(
    c: &Client,
    seq: &Sequence,
    rate: f64,
    ask_each_frame: bool,
) -> anyhow::Result<(Vec<RobotFrameAnswer>, (usize, usize, usize))> {
    let robot = seq.rig.robot_camera().map(str::to_string);
    let mut items: Vec<(i64, u8, Item)> = Vec::new();
    for (name, s) in &seq.cameras {
        for (id, meta) in &s.frames {
            items.push((
                meta.stamp_ns,
                1,
                Item::Frame {
                    camera: name.clone(),
                    frame: *id,
                },
            ));
        }
    }
    if let Some(odo) = &seq.odometry {
        for (id, o) in odo {
            items.push((o.stamp_ns, 0, Item::Odometry { frame: *id }));
        }
    }
    items.sort_by_key(|a| (a.0, a.1));
    let t0 = items.first().map(|i| i.0).unwrap_or(0);
    let start = Instant::now();
    let (mut sent, mut refused, mut odometry_sent) = (0, 0, 0);
    let mut send_truth = true;
    let mut answers = Vec::new();
    let truth_camera = robot.clone().unwrap_or_else(|| seq.rig.reference_camera.clone());
    for (stamp_ns, _, item) in items {
        if rate > 0.0 {
            let due = Duration::from_secs_f64((stamp_ns - t0).max(0) as f64 * 1e-9 / rate);
            if let Some(wait) = due.checked_sub(start.elapsed()) {
                tokio::time::sleep(wait).await;
            }
        }
        match item {
            Item::Odometry { frame } => {
                let Some(o) = seq.odometry.as_ref().and_then(|m| m.get(&frame)) else {
                    continue;
                };
                let body = json!({
                    "stamp_ns": o.stamp_ns,
                    "odom_from_base": {"pose": pose_json(&o.odom_from_base)},
                    "world_from_odom": pose_json(&o.world_from_odom),
                    "base_from_camera": pose_json(&o.base_from_camera),
                });
                Client::check(c.req(reqwest::Method::POST, "/odometry").json(&body), "odometry").await?;
                odometry_sent += 1;
            }
            Item::Frame { camera, frame } => {
                if send_truth
                    && camera == truth_camera
                    && let Some(t) = truth_of(seq, &camera, frame)
                {
                    // a server without --accept-truth refuses the channel: stream without it
                    let r = c.req(reqwest::Method::POST, "/truth").json(&t).send().await?;
                    if r.status() == reqwest::StatusCode::FORBIDDEN {
                        tracing::info!("the server does not accept ground truth; streaming without it");
                        send_truth = false;
                    } else if !r.status().is_success() {
                        anyhow::bail!("ground truth: {}", r.status());
                    }
                }
                let form = multipart_frame(seq, &camera, frame)?;
                let r = c
                    .req(reqwest::Method::POST, &format!("/cameras/{camera}/frames"))
                    .multipart(form)
                    .send()
                    .await?;
                if r.status().is_success() {
                    sent += 1;
                } else {
                    refused += 1;
                    let body: Value = r.json().await.unwrap_or(Value::Null);
                    tracing::warn!("frame {camera}/{frame} refused: {}", body["detail"]);
                }
                if ask_each_frame
                    && (Some(&camera) == robot.as_ref() || (robot.is_none() && camera == seq.rig.reference_camera))
                {
                    answers.push(ask(c, seq, frame, stamp_ns).await?);
                }
            }
        }
    }
    Ok((answers, (sent, refused, odometry_sent)))
}

async fn ask(c: &Client, seq: &Sequence, frame: u32, stamp_ns: i64) -> anyhow::Result<RobotFrameAnswer> {
    let tracks = Client::check(c.req(reqwest::Method::GET, "/tracks"), "tracks").await?;
    let mut decisions = Vec::new();
    for t in tracks.as_array().into_iter().flatten() {
        let object = t["object_id"].as_str().unwrap_or("");
        if seq.rig.target.as_deref().is_some_and(|target| target != object) {
            continue;
        }
        let id = t["id"].as_u64().unwrap_or(0);
        let r = c
            .req(reqwest::Method::POST, &format!("/tracks/{id}/decision"))
            .json(&json!({"gripper": "default"}))
            .send()
            .await?;
        let status = r.status();
        let body: Value = r.json().await.unwrap_or(Value::Null);
        decisions.push(if status.is_success() {
            json!({"track_id": id, "object": object, "decision": body})
        } else {
            json!({"track_id": id, "object": object, "error": body["detail"]})
        });
    }
    // Keep the answer compact: no particles or samples.
    let tracks = Value::Array(
        tracks
            .as_array()
            .into_iter()
            .flatten()
            .map(|t| {
                json!({
                    "id": t["id"], "object_id": t["object_id"], "status": t["status"],
                    "stamp_ns": t["stamp_ns"], "world_from_object": t["world_from_object"],
                    "reference_from_object": t["reference_from_object"],
                    "translation_std_m": t["translation_std_m"], "rotation_entropy": t["rotation_entropy"],
                    "truth": t["truth"],
                })
            })
            .collect(),
    );
    Ok(RobotFrameAnswer {
        frame,
        stamp_ns,
        tracks,
        decisions,
    })
}

fn summarise(seq: &Sequence, answers: &[RobotFrameAnswer], counts: (usize, usize, usize)) -> ReplaySummary {
    let (mut te, mut oe) = (Vec::new(), Vec::new());
    for a in answers {
        for t in a.tracks.as_array().into_iter().flatten() {
            if seq.rig.target.as_deref().is_some_and(|target| t["object_id"] != target) {
                continue;
            }
            if let Some(x) = t["truth"]["translation_error_m"].as_f64() {
                te.push(x);
            }
            if let Some(x) = t["truth"]["orientation_error_deg"].as_f64() {
                oe.push(x);
            }
        }
    }
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let decisions: Vec<&Value> = answers.iter().flat_map(|a| a.decisions.iter()).collect();
    ReplaySummary {
        sequence: seq.root.display().to_string(),
        frames_sent: counts.0,
        frames_refused: counts.1,
        odometry_sent: counts.2,
        robot_frames: answers.len(),
        decisions: decisions.iter().filter(|d| d.get("decision").is_some()).count(),
        grasp_decisions: decisions
            .iter()
            .filter(|d| {
                d["decision"]["decision"]
                    .as_str()
                    .is_some_and(|v| v.eq_ignore_ascii_case("grasp"))
            })
            .count(),
        mean_translation_error_m: mean(&te),
        mean_orientation_error_deg: mean(&oe),
        wall_s: 0.0,
    }
}
