//! `pregrasp serve --demo`: with no external files, the built-in objects (box, can, mug) on a
//! table, two stationary cameras and a robot camera driving towards the table, rendered on the
//! CPU and streamed into the server itself in real time (frames with detections, odometry), in
//! a loop. The ground-truth channel is filled so that the dashboard can plot errors (the
//! tracker never reads it), and a decision is asked for the target every second.
//!
//! The frames go through the same checks and ingest path as HTTP frames
//! ([`ServiceState::ingest_frame`]); only the network hop is skipped.

use super::decisions::DecisionParams;
use super::ingest::OdometryMsg;
use super::{Service, ServiceState};
use crate::camera::Intrinsics;
use crate::generate::sim::{Placed, SceneSim, visible_boxes};
use crate::geometry::Pose;
use crate::grasp::SupportPlane;
use crate::mesh::Mesh;
use crate::render::ClipRange;
use crate::sensor::{CameraFrame, CameraMount, Detection};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Image size of the demo cameras.
pub const DEMO_WIDTH_PX: u32 = 320;
pub const DEMO_HEIGHT_PX: u32 = 240;
pub const DEMO_FOCAL_PX: f64 = 300.0;
/// Frames per second of each camera.
pub const DEMO_CAMERA_HZ: f64 = 5.0;
/// One loop: the robot drives for this long, then waits.
pub const DEMO_DRIVE_S: f64 = 24.0;
pub const DEMO_PAUSE_S: f64 = 4.0;
/// Where the robot base starts and stops (world x; the table is centred at the origin).
pub const DEMO_START_X_M: f64 = -2.6;
pub const DEMO_STOP_X_M: f64 = -0.75;
/// The object the robot approaches (decisions are asked for it).
pub const DEMO_TARGET: &str = "can";
/// Relative depth noise (uniform, +-).
pub const DEMO_DEPTH_NOISE_REL: f64 = 0.01;
/// Minimum visible pixels for a detection.
pub const DEMO_MIN_DETECTION_PX: usize = 30;

pub use crate::geometry::look_at;

/// Background colour of the demo's cameras.
const DEMO_BACKGROUND_RGB: [u8; 3] = [40, 44, 52];

/// The demo world.
pub struct DemoScene {
    pub objects: Vec<(String, Mesh, Pose)>,
    pub table: Mesh,
    pub stationary: Vec<(String, Pose)>,
    pub base_from_camera: Pose,
    pub intrinsics: Intrinsics,
    /// The generator's scene simulator over the objects (instance ids 1..) and the table: wgpu
    /// (lavapipe without a GPU), the CPU rasteriser when wgpu has no adapter.
    sim: SceneSim,
}

impl DemoScene {
    pub fn new() -> anyhow::Result<Self> {
        let place = |name: &str, x: f64, y: f64, yaw: f64| -> anyhow::Result<(String, Mesh, Pose)> {
            let mesh = crate::mesh::builtin(name).ok_or_else(|| anyhow::anyhow!("no built-in {name}"))?;
            let z = -mesh.bounds().min_m.z;
            let pose = Pose::from_parts(
                Translation3::new(x, y, z),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            );
            Ok((name.to_string(), mesh, pose))
        };
        let mut table = crate::mesh::builtin_box([1.2, 0.8, 0.04], [[150, 120, 90], [150, 120, 90]]);
        for v in &mut table.vertices_m {
            v[2] -= 0.02;
        }
        let objects = vec![
            place("box", 0.05, -0.2, 0.6)?,
            place("can", -0.1, 0.05, 0.0)?,
            place("mug", 0.1, 0.22, 2.2)?,
        ];
        let placed = objects
            .iter()
            .map(|(_, mesh, pose)| Placed {
                mesh: Arc::new(mesh.clone()),
                world_from_object: *pose,
            })
            .collect();
        let props = vec![Placed {
            mesh: Arc::new(table.clone()),
            world_from_object: Pose::identity(),
        }];
        let sim = SceneSim::new(placed, props, ClipRange::new(0.05, 20.0)?, DEMO_BACKGROUND_RGB);
        Ok(Self {
            objects,
            table,
            stationary: vec![
                ("ext1".into(), look_at([-0.8, -0.9, 0.8], [0.0, 0.0, 0.05])),
                ("ext2".into(), look_at([0.7, -0.8, 0.9], [0.0, 0.0, 0.05])),
            ],
            base_from_camera: look_at([0.0, 0.0, 1.25], [1.0, 0.0, 0.55]),
            intrinsics: Intrinsics::from_focal(DEMO_WIDTH_PX, DEMO_HEIGHT_PX, DEMO_FOCAL_PX)?,
            sim,
        })
    }

    /// The robot base at `t_s` into a loop (drives along +x, then waits).
    pub fn world_from_base(&self, t_s: f64) -> Pose {
        let s = (t_s / DEMO_DRIVE_S).clamp(0.0, 1.0);
        let s = s * s * (3.0 - 2.0 * s); // smooth start and stop
        let x = DEMO_START_X_M + (DEMO_STOP_X_M - DEMO_START_X_M) * s;
        Pose::from_parts(Translation3::new(x, 0.05, -0.75), UnitQuaternion::identity())
    }

    /// Renders one camera: depth with noise, colour, detections from the instance mask.
    pub fn render(&self, camera: &str, world_from_camera: &Pose, stamp_ns: i64, rng: &mut impl Rng) -> CameraFrame {
        let k = &self.intrinsics;
        let mut img = self
            .sim
            .render(super::codebooks::template_renderer(), k, world_from_camera);
        for d in &mut img.depth.data_m {
            if *d > 0.0 {
                *d *= 1.0 + (DEMO_DEPTH_NOISE_REL * (rng.random::<f64>() * 2.0 - 1.0)) as f32;
            }
        }
        let boxes = visible_boxes(&self.sim.visible_masks(&img), k.width);
        let detections = self
            .objects
            .iter()
            .zip(boxes)
            .filter(|(_, b)| b.px_count >= DEMO_MIN_DETECTION_PX as u64)
            .map(|((name, _, _), b)| Detection {
                object: name.clone(),
                bbox_xywh_px: b.bbox_xywh_px.map(|v| v as f64),
                score: 0.9,
            })
            .collect();
        CameraFrame {
            camera: camera.to_string(),
            stamp_ns,
            intrinsics: self.intrinsics,
            depth: img.depth,
            color: Some(img.color),
            detections,
        }
    }
}

/// Registers the demo's cameras, objects and support plane.
pub fn register(state: &ServiceState, scene: &DemoScene) -> anyhow::Result<()> {
    for (id, pose) in &scene.stationary {
        let mount = CameraMount::Stationary {
            world_from_camera: *pose,
        };
        state.register_camera(id, scene.intrinsics, mount)?;
    }
    let mount = CameraMount::Robot {
        base_from_camera: scene.base_from_camera,
    };
    state.register_camera("robot", scene.intrinsics, mount)?;
    for (name, mesh, _) in &scene.objects {
        let same = state
            .registry()
            .objects
            .get(name)
            .is_some_and(|o| o.info.content_hash == mesh.content_hash());
        if !same {
            state.register_object(name, name, mesh.clone(), true)?;
        }
    }
    *state.support_plane.lock().unwrap_or_else(|p| p.into_inner()) = Some(SupportPlane {
        normal: [0.0, 0.0, 1.0],
        point_m: [0.0, 0.0, 0.0],
    });
    let mut truth = state.truth.lock().unwrap_or_else(|p| p.into_inner());
    for (name, _, pose) in &scene.objects {
        truth.insert(name.clone(), (0, *pose));
    }
    Ok(())
}

/// Forgets everything that belongs to the last loop (the robot jumps back to the start of its
/// path at each loop): the tracks, the waiting frames, the odometry buffer and the newest
/// stamps, so that no step fuses a frame of the last loop or interpolates odometry across
/// the jump.
pub fn reset_tracking(state: &ServiceState) {
    let mut engine = state.engine.lock().unwrap_or_else(|p| p.into_inner());
    *engine = None;
    // under the engine's lock: the worker cannot step between the two
    state.ingest().clear();
    *state.restored.lock().unwrap_or_else(|p| p.into_inner()) = None;
    drop(engine);
    state.forget_all_tracks();
}

/// Registers the demo scene and starts streaming it (returns the streaming thread's stop flag).
pub fn start(state: Service) -> anyhow::Result<Arc<AtomicBool>> {
    let scene = DemoScene::new()?;
    register(&state, &scene)?;
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    std::thread::Builder::new()
        .name("pregrasp-demo".into())
        .spawn(move || run(state, scene, flag))?;
    Ok(stop)
}

fn run(state: Service, scene: DemoScene, stop: Arc<AtomicBool>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let t_start = Instant::now();
    let period_s = 1.0 / DEMO_CAMERA_HZ;
    let loop_s = DEMO_DRIVE_S + DEMO_PAUSE_S;
    // Each camera fires at its own phase within the period (the cameras are not synchronised).
    let cameras: Vec<(String, Option<Pose>, f64)> = std::iter::once(("robot".to_string(), None, 0.0))
        .chain(
            scene
                .stationary
                .iter()
                .enumerate()
                .map(|(i, (id, p))| (id.clone(), Some(*p), (i as f64 + 1.0) / 3.0 * period_s)),
        )
        .collect();
    let mut tick: u64 = 0;
    let mut loop_index = 0u64;
    let mut last_decision = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        for (camera, stationary, phase) in &cameras {
            let due_s = tick as f64 * period_s + phase;
            let now_s = t_start.elapsed().as_secs_f64();
            if due_s > now_s {
                std::thread::sleep(Duration::from_secs_f64(due_s - now_s));
            }
            if stop.load(Ordering::Relaxed) {
                return;
            }
            let this_loop = (due_s / loop_s) as u64;
            if this_loop != loop_index {
                loop_index = this_loop;
                reset_tracking(&state);
            }
            let t_loop = due_s - loop_index as f64 * loop_s;
            let stamp_ns = (due_s * 1e9) as i64;
            let world_from_camera = match stationary {
                Some(p) => *p,
                None => {
                    let world_from_base = scene.world_from_base(t_loop);
                    let odometry = OdometryMsg {
                        stamp_ns,
                        odom_from_base: world_from_base,
                        covariance: None,
                        world_from_odom: Pose::identity(),
                        base_from_camera: Some(scene.base_from_camera),
                    };
                    if let Err(e) = state.ingest_odometry(odometry) {
                        tracing::debug!("demo odometry refused: {e}");
                    }
                    world_from_base * scene.base_from_camera
                }
            };
            let frame = scene.render(camera, &world_from_camera, stamp_ns, &mut rng);
            if let Err(e) = state.ingest_frame(frame, Instant::now()) {
                tracing::debug!("demo frame refused: {e}");
            }
        }
        tick += 1;
        if last_decision.elapsed() >= Duration::from_secs(1) {
            last_decision = Instant::now();
            for id in target_tracks(&state) {
                // as many samples as the calibration map was fitted on (the API's default)
                let params = DecisionParams::default();
                if let Err(e) = state.decide(id, &params) {
                    tracing::debug!("demo decision for track {id}: {e}");
                }
            }
        }
    }
}

/// Options of `pregrasp demo-loops`: the demo's decision loop, run headless without a server.
#[derive(Debug, Clone, clap::Args)]
pub struct HeadlessArgs {
    /// Loops of the robot's drive (24 s drive, 4 s wait each).
    #[arg(long, default_value_t = 10)]
    pub loops: usize,
    /// Data folder (store and codebook cache; the cache makes later runs start at once).
    #[arg(long)]
    pub data_dir: Option<std::path::PathBuf>,
    /// Grid step of the finer codebook built after the coarse 10-degree one (as `serve`; the
    /// default is `serve`'s, the configuration the shipped calibration map is fitted for); 10
    /// keeps the coarse one.
    #[arg(long, default_value_t = super::codebooks::CodebookPlan::SERVE_FINE_STEP_DEG)]
    pub codebook_step_deg: u32,
    /// A calibration map to answer with instead of the shipped one.
    #[arg(long)]
    pub calibration_map: Option<std::path::PathBuf>,
    /// Seed of the depth noise.
    #[arg(long, default_value_t = 11)]
    pub seed: u64,
    /// Write every decision and the loops' outcomes here (JSON).
    #[arg(long)]
    pub out: Option<std::path::PathBuf>,
    /// A JSON file of tracker settings over the defaults, as `eval --tracker-config` takes
    /// (the shipped map then answers `stale` unless it was fitted for them).
    #[arg(long)]
    pub tracker_config: Option<std::path::PathBuf>,
}

/// One decision of a headless loop, checked on the true pose.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct HeadlessDecision {
    pub loop_index: usize,
    /// Seconds into the loop (the robot stops at [`DEMO_DRIVE_S`]).
    pub t_s: f64,
    /// From the robot camera to the can's true position, metres.
    pub distance_m: f64,
    pub grasp: bool,
    pub p_success: f64,
    pub p_success_raw: f64,
    /// The planned grasp succeeds on the can's true pose.
    pub succeeds_on_truth: bool,
    /// `calibrated`, `stale` or `absent`.
    pub calibration: String,
    /// The test most samples fail and its share (why `p_success_raw` is not 1).
    pub top_reason: Option<(String, f64)>,
    /// What drives that test's failures: per axis, `translation gripper_y` and the like, the
    /// samples' spread along it (metres or radians), the failure's dependence on it (0-1) and
    /// the axis in the object's frame (a can's axis is its z).
    pub top_drivers: Vec<(String, f64, f64, [f64; 3])>,
    /// The track's error against the truth at its last step: metres, degrees (modulo the
    /// can's exact symmetries).
    pub truth_error: Option<(f64, f64)>,
    /// The distribution the answer sampled: its translation std (metres, RMS over the axes),
    /// rotation entropy (nats) and top rotation mode's mass.
    pub spread: Option<(f64, f64, f64)>,
}

/// What one loop gave the target.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LoopOutcome {
    pub loop_index: usize,
    pub decisions: usize,
    /// The first `grasp` answer of the loop.
    pub first_grasp: Option<HeadlessDecision>,
    pub grasps: usize,
    /// `grasp` answers whose grasp fails on the true pose.
    pub grasps_failing_on_truth: usize,
}

/// Runs the demo's loops in simulated time without a server: every camera frame is ingested
/// as in the live demo and stepped at once (lockstep: no frame is dropped for want of CPU), a
/// decision is asked for the target every second as the live demo does, and each answer's
/// grasp is checked on the true pose. The codebooks are built first (by the service's
/// builder).
pub fn run_headless(args: &HeadlessArgs) -> anyhow::Result<Vec<LoopOutcome>> {
    let data_dir = args
        .data_dir
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("pregrasp-demo-loops"));
    let mut config = super::ServiceConfig::new(data_dir);
    config.accept_truth = true;
    crate::geometry::RotationGrid::new(args.codebook_step_deg)?;
    config.codebooks = super::codebooks::CodebookPlan::with_fine_step(args.codebook_step_deg);
    if let Some(path) = &args.tracker_config {
        config.tracker = crate::eval::cli::tracker_config_from_file(path)?;
    }
    if let Some(path) = &args.calibration_map {
        let text = std::fs::read_to_string(path)?;
        config.calibration_map = Some(Arc::new(crate::grasp::CalibrationMap::from_json(&text)?));
    }
    let state = Service::open(config)?;
    // a fresh start: no track or tracker state of an earlier run
    *state.restored.lock().unwrap_or_else(|p| p.into_inner()) = None;
    state.forget_all_tracks();
    let scene = DemoScene::new()?;
    register(&state, &scene)?;
    let stop = Arc::new(AtomicBool::new(false));
    let builder = super::codebooks::spawn_builder(state.clone(), stop.clone());
    let t0 = Instant::now();
    loop {
        let reg = state.registry();
        let failed: Vec<String> = reg
            .objects
            .values()
            .filter(|o| o.info.codebook.status == super::registry::CodebookState::Failed)
            .map(|o| format!("{}: {:?}", o.info.id, o.info.codebook.error))
            .collect();
        anyhow::ensure!(failed.is_empty(), "codebook builds failed: {failed:?}");
        // every stage built (progress counts the stages done)
        let done = reg.objects.values().all(|o| {
            o.info.codebook.status == super::registry::CodebookState::Ready && o.info.codebook.progress >= 1.0 - 1e-9
        });
        drop(reg);
        if done {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    tracing::info!("codebooks ready after {:.0} s", t0.elapsed().as_secs_f64());
    stop.store(true, Ordering::Relaxed);
    if let Some(b) = builder {
        let _ = b.join();
    }
    let truth = scene
        .objects
        .iter()
        .find(|(name, _, _)| name == DEMO_TARGET)
        .map(|(_, _, pose)| *pose)
        .ok_or_else(|| anyhow::anyhow!("no {DEMO_TARGET} in the demo scene"))?;
    let object = state.grasp_objects.get_or_build(&state, DEMO_TARGET)?;
    let gripper = state.gripper(super::registry::DEFAULT_GRIPPER)?;
    let plane_world = state.support_plane();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let period_s = 1.0 / DEMO_CAMERA_HZ;
    let loop_s = DEMO_DRIVE_S + DEMO_PAUSE_S;
    let ticks = (loop_s / period_s).round() as u64;
    let mut outcomes = Vec::new();
    let mut all = Vec::new();
    for loop_index in 0..args.loops {
        reset_tracking(&state);
        let loop_start_s = loop_index as f64 * loop_s + 1.0;
        let mut outcome = LoopOutcome {
            loop_index,
            decisions: 0,
            first_grasp: None,
            grasps: 0,
            grasps_failing_on_truth: 0,
        };
        let mut next_decision_s = 1.0;
        for tick in 0..ticks {
            for (i, camera) in ["robot", "ext1", "ext2"].into_iter().enumerate() {
                let t_loop = tick as f64 * period_s + i as f64 / 3.0 * period_s;
                let stamp_ns = ((loop_start_s + t_loop) * 1e9) as i64;
                let world_from_camera = if camera == "robot" {
                    let world_from_base = scene.world_from_base(t_loop);
                    state.ingest_odometry(OdometryMsg {
                        stamp_ns,
                        odom_from_base: world_from_base,
                        covariance: None,
                        world_from_odom: Pose::identity(),
                        base_from_camera: Some(scene.base_from_camera),
                    })?;
                    world_from_base * scene.base_from_camera
                } else {
                    scene
                        .stationary
                        .iter()
                        .find(|(id, _)| id == camera)
                        .map(|(_, p)| *p)
                        .unwrap_or_else(Pose::identity)
                };
                let frame = scene.render(camera, &world_from_camera, stamp_ns, &mut rng);
                state.ingest_frame(frame, Instant::now())?;
                loop {
                    let set = state.ingest().take_fusion_set();
                    match set {
                        Some(set) if !set.frames.is_empty() => super::worker::step(&state, &set),
                        Some(_) => {}
                        None => break,
                    }
                }
                if t_loop < next_decision_s {
                    continue;
                }
                next_decision_s += 1.0;
                for id in target_tracks(&state) {
                    let params = DecisionParams::default();
                    let record = match state.decide(id, &params) {
                        Ok(r) => r,
                        Err(e) => {
                            tracing::debug!("headless decision for track {id}: {e}");
                            continue;
                        }
                    };
                    let reference_from_world = record.world_from_reference.inverse();
                    let plane = plane_world.map(|p| p.transformed(&reference_from_world));
                    let succeeds = record.decision.success_on_pose(
                        &object,
                        &gripper,
                        &(reference_from_world * truth),
                        plane.as_ref(),
                    )?;
                    let track = state.track(id).ok();
                    let d = HeadlessDecision {
                        loop_index,
                        t_s: t_loop,
                        distance_m: (record.world_from_reference.translation.vector - truth.translation.vector).norm(),
                        grasp: record.decision.decision == crate::grasp::Verdict::Grasp,
                        p_success: record.decision.p_success,
                        p_success_raw: record.decision.p_success_raw,
                        succeeds_on_truth: succeeds,
                        calibration: match record.decision.calibration {
                            crate::grasp::CalibrationStatus::Calibrated { .. } => "calibrated",
                            crate::grasp::CalibrationStatus::Stale { .. } => "stale",
                            crate::grasp::CalibrationStatus::Absent { .. } => "absent",
                        }
                        .into(),
                        top_reason: record
                            .decision
                            .reasons
                            .first()
                            .map(|r| (format!("{:?}", r.test).to_lowercase(), r.failure_share)),
                        top_drivers: record.decision.reasons.first().map_or_else(Vec::new, |r| {
                            r.drivers
                                .iter()
                                .map(|a| {
                                    let motion = match a.motion {
                                        crate::grasp::Motion::Translation => "translation",
                                        crate::grasp::Motion::Rotation => "rotation",
                                    };
                                    (
                                        format!("{motion} {}", a.axis),
                                        a.spread,
                                        a.failure_dependence,
                                        a.axis_in_object,
                                    )
                                })
                                .collect()
                        }),
                        truth_error: track
                            .as_ref()
                            .and_then(|t| t.truth.as_ref())
                            .map(|e| (e.translation_error_m, e.orientation_error_deg)),
                        spread: track
                            .as_ref()
                            .map(|t| (t.translation_std_m, t.rotation_entropy, t.top_mode_mass)),
                    };
                    outcome.decisions += 1;
                    if d.grasp {
                        outcome.grasps += 1;
                        outcome.grasps_failing_on_truth += usize::from(!d.succeeds_on_truth);
                        if outcome.first_grasp.is_none() {
                            outcome.first_grasp = Some(d.clone());
                        }
                    }
                    all.push(d);
                }
            }
        }
        println!("{}", loop_line(&outcome));
        outcomes.push(outcome);
    }
    println!("{}", summary_line(&outcomes));
    if let Some(path) = &args.out {
        let json = serde_json::json!({"loops": outcomes, "decisions": all});
        std::fs::write(path, serde_json::to_vec_pretty(&json)?)?;
    }
    Ok(outcomes)
}

/// One line per loop: the first `grasp` (when, how far, whether it works on the truth).
pub fn loop_line(o: &LoopOutcome) -> String {
    let first = match &o.first_grasp {
        Some(d) => format!(
            "first grasp at {:.1} s{}, {:.2} m from the {DEMO_TARGET}, p_success {:.3} (raw {:.3}, {}), on the truth: {}",
            d.t_s,
            if d.t_s <= DEMO_DRIVE_S {
                ""
            } else {
                " (after the robot stopped)"
            },
            d.distance_m,
            d.p_success,
            d.p_success_raw,
            d.calibration,
            if d.succeeds_on_truth { "succeeds" } else { "FAILS" }
        ),
        None => "no grasp".into(),
    };
    format!(
        "loop {}: {first}; {} grasp answers of {} ({} failing on the truth)",
        o.loop_index, o.grasps, o.decisions, o.grasps_failing_on_truth
    )
}

/// The loops together: issue 20's measure (a `grasp` in most loops, none failing).
pub fn summary_line(outcomes: &[LoopOutcome]) -> String {
    let with_grasp = outcomes.iter().filter(|o| o.first_grasp.is_some()).count();
    let before_stop = outcomes
        .iter()
        .filter(|o| o.first_grasp.as_ref().is_some_and(|d| d.t_s <= DEMO_DRIVE_S))
        .count();
    let grasps: usize = outcomes.iter().map(|o| o.grasps).sum();
    let failing: usize = outcomes.iter().map(|o| o.grasps_failing_on_truth).sum();
    format!(
        "loops with a grasp for the {DEMO_TARGET}: {with_grasp} of {} ({before_stop} before the robot stopped); grasp answers failing on the truth: {failing} of {grasps}",
        outcomes.len()
    )
}

/// The ids of the demo target's tracks on the board.
fn target_tracks(state: &ServiceState) -> Vec<u64> {
    state
        .tracking
        .board()
        .views
        .values()
        .filter(|v| v.object_id == DEMO_TARGET)
        .map(|v| v.id)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_camera_sees_the_target_with_a_detection_at_the_end_of_the_drive() {
        let scene = DemoScene::new().unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let robot = scene.world_from_base(DEMO_DRIVE_S) * scene.base_from_camera;
        let mut views = vec![("robot".to_string(), robot)];
        views.extend(scene.stationary.iter().cloned());
        for (id, pose) in views {
            let f = scene.render(&id, &pose, 0, &mut rng);
            assert!(
                f.detections.iter().any(|d| d.object == DEMO_TARGET),
                "{id} does not see the {DEMO_TARGET}: {:?}",
                f.detections
            );
            let valid = f.depth.data_m.iter().filter(|d| **d > 0.0).count();
            assert!(valid > 1000, "{id}: {valid} depth readings");
        }
        // At the start the robot is far away but the table is in view.
        let far = scene.world_from_base(0.0) * scene.base_from_camera;
        let f = scene.render("robot", &far, 0, &mut rng);
        assert!(f.depth.data_m.iter().any(|d| *d > 0.0));
    }
}
