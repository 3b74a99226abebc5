//! Background work of the service: the tracking worker (a dedicated thread that steps the tracker
//! whenever frames arrive), the codebook builder and the once-a-second stats publisher.
//!
//! The [`Engine`] (the tracker and what it was built from) sits behind a mutex in the state:
//! the worker holds it while stepping, decisions hold it only to draw samples.

use super::decisions::Drawn;
use super::error::ServiceError;
use super::events::ServiceEvent;
use super::ingest::FusionSet;
use super::tracks::{
    MAX_PRIOR_STD_M, MIN_PRIOR_STD_DEG, MIN_PRIOR_STD_M, ParticleInWorld, PriorPose, StartTrack, TrackState, TruthError,
};
use super::{Service, ServiceState};
use crate::geometry::Pose;
use crate::tracker::{CameraFrame, CameraMount, RobotOdometry, Tracker};
use rand::SeedableRng;
use std::collections::{BTreeMap, HashSet};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use std::time::Instant;

/// Handle on the background work; `shutdown` stops it.
pub struct Background {
    stop: Arc<AtomicBool>,
    stats: tokio::task::JoinHandle<()>,
    worker: Option<std::thread::JoinHandle<()>>,
    builder: Option<std::thread::JoinHandle<()>>,
    state: Service,
}

impl Background {
    /// Stops the worker and the stats task and waits for both (so that the store can be
    /// reopened afterwards).
    pub async fn shutdown(mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.state.wake.notify_all();
        self.stats.abort();
        let _ = (&mut self.stats).await;
        let threads: Vec<_> = self.worker.take().into_iter().chain(self.builder.take()).collect();
        let _ = tokio::task::spawn_blocking(move || {
            for t in threads {
                let _ = t.join();
            }
        })
        .await;
        // A final snapshot of the tracks.
        if let Err(e) = self.state.save_track_records() {
            tracing::warn!("saving track snapshots: {e}");
        }
        save_tracker_snapshot(&self.state);
    }
}

/// Starts the stats task (needs a tokio runtime) and the tracking worker thread.
pub fn start_background(state: &Service) -> Background {
    let stop = Arc::new(AtomicBool::new(false));
    let stats = super::events::spawn_stats_task(state.clone());
    let builder = super::codebooks::spawn_builder(state.clone(), stop.clone());
    let worker = {
        let (state, stop) = (state.clone(), stop.clone());
        std::thread::Builder::new()
            .name("pregrasp-tracking".into())
            .spawn(move || run_worker(state, stop))
            .ok()
    };
    Background {
        stop,
        stats,
        worker,
        builder,
        state: state.clone(),
    }
}

/// How often track snapshots are written to the store.
pub const SNAPSHOT_PERIOD: Duration = Duration::from_secs(2);
/// How often the tracker's own (larger) snapshot is written to the store.
pub const TRACKER_SNAPSHOT_PERIOD: Duration = Duration::from_secs(5);
/// Most particles per track in a view (display only).
pub const VIEW_MAX_PARTICLES: usize = 300;
/// Samples per track in a view.
pub const VIEW_SAMPLES: usize = 10;

/// The tracker and what it was built from.
pub struct Engine {
    pub tracker: Tracker,
    /// Camera set the tracker was built for.
    cameras: BTreeMap<String, CameraMount>,
    /// The robot camera in the base frame at the last step (the odometry's, else the
    /// registered mount's).
    base_from_reference: Option<Pose>,
    /// Per object the codebook in the tracker: (mesh hash, grid step, with colour).
    models: BTreeMap<String, (String, u32, bool)>,
    /// Stamp of the odometry given to the last step (odometry never goes back in time: a late
    /// frame of a stationary camera is fused at the robot's latest pose).
    odometry_stamp_ns: Option<i64>,
    rng: rand_chacha::ChaCha8Rng,
    /// Tracks of the previous run's snapshot whose models are not in the tracker yet.
    pending: Vec<crate::tracker::TrackSnapshot>,
    /// The ingest epoch the tracker was built in (the odometry's clock restarted after it).
    epoch: u64,
    /// Per object its exact symmetries (shape and colour) with the mesh hash they were measured
    /// on: ground-truth errors are shown modulo them. Measured on first use.
    symmetries: BTreeMap<String, (String, crate::symmetry::Symmetries)>,
}

impl Engine {
    pub(super) fn new(state: &ServiceState) -> Option<Self> {
        let reg = state.registry();
        let reference = reg.reference_camera()?;
        let mounts: BTreeMap<String, CameraMount> = reg.cameras.iter().map(|(k, c)| (k.clone(), c.mount)).collect();
        let robot_base_from_camera = reg.robot_base_from_camera();
        // the one place the service's cap is enforced: matched detections still reach their
        // tracks (a camera joins a track at its first detection of it), unmatched ones open
        // no extra track
        let config = crate::tracker::TrackerConfig {
            max_tracks_per_object: state.config.max_live_tracks_per_object,
            ..state.config.tracker.clone()
        };
        let mut tracker = Tracker::new(config, mounts.clone(), reference);
        // The previous run's tracks come back as their models become ready (sync_models);
        // only tracks still listed (not stopped) are restored.
        let mut pending = Vec::new();
        if let Some(snap) = state.restored.lock().unwrap_or_else(|p| p.into_inner()).take() {
            match tracker.restore_frame(&snap) {
                Ok(()) => {
                    let listed = state.tracking.board();
                    pending = snap
                        .tracks
                        .into_iter()
                        .filter(|t| listed.views.contains_key(&t.track.id))
                        .collect();
                }
                Err(e) => tracing::warn!("tracker snapshot not restored: {e}"),
            }
        }
        Some(Self {
            tracker,
            cameras: mounts,
            base_from_reference: robot_base_from_camera,
            models: BTreeMap::new(),
            odometry_stamp_ns: None,
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(state.config.tracker.seed ^ 0x5eed),
            pending,
            epoch: state.ingest().epoch(),
            symmetries: BTreeMap::new(),
        })
    }

    /// Adds the objects whose codebooks became ready (or changed).
    pub(super) fn sync_models(&mut self, state: &ServiceState) {
        let objects: Vec<(String, String, bool, std::sync::Arc<crate::mesh::Mesh>)> = state
            .registry()
            .objects
            .values()
            .map(|o| {
                (
                    o.info.id.clone(),
                    o.info.content_hash.clone(),
                    o.info.use_color,
                    o.mesh.clone(),
                )
            })
            .collect();
        for (id, hash, use_color, mesh) in objects {
            let Some(cb) = state.codebooks.get(&id, &hash, use_color) else {
                continue;
            };
            let key = (hash.clone(), cb.grid.step_deg(), use_color);
            if self.models.get(&id) == Some(&key) {
                continue;
            }
            self.tracker.add_object_model(&id, (*mesh).clone(), cb);
            let (restore, keep): (Vec<_>, Vec<_>) = std::mem::take(&mut self.pending)
                .into_iter()
                .partition(|t| t.track.object == id);
            self.pending = keep;
            for t in restore {
                match self.tracker.restore_track(&t) {
                    Ok(()) => tracing::info!("restored track {} of {id}", t.track.id),
                    Err(e) => tracing::warn!("track {} not restored: {e}", t.track.id),
                }
            }
            self.models.insert(id, key);
        }
    }

    /// The exact symmetries of an object's model (measured once per mesh); none when the
    /// tracker has no model of that name.
    fn symmetries_of(&mut self, object: &str) -> crate::symmetry::Symmetries {
        let Some((hash, ..)) = self.models.get(object) else {
            return crate::symmetry::Symmetries::none();
        };
        if let Some((h, s)) = self.symmetries.get(object)
            && h == hash
        {
            return s.clone();
        }
        let s = self
            .tracker
            .model_mesh(object)
            .map_or_else(crate::symmetry::Symmetries::none, crate::symmetry::Symmetries::exact);
        self.symmetries.insert(object.to_string(), (hash.clone(), s.clone()));
        s
    }
}

impl ServiceState {
    /// Starts a track from a caller's prior (blocking: it may wait for the tracker); returns
    /// its first state.
    pub fn start_track(&self, start: &StartTrack) -> Result<TrackState, ServiceError> {
        if !self.registry().objects.contains_key(&start.object_id) {
            return Err(ServiceError::not_found("object", start.object_id.clone()));
        }
        let std_m = start.translation_std_m;
        if !(MIN_PRIOR_STD_M..=MAX_PRIOR_STD_M).contains(&std_m) {
            return Err(ServiceError::Invalid(format!(
                "translation_std_m must be in [{MIN_PRIOR_STD_M}, {MAX_PRIOR_STD_M}], got {std_m}"
            )));
        }
        match &start.pose {
            PriorPose::World { world_from_object } => {
                super::checks::check_pose("world_from_object", world_from_object)?
            }
            PriorPose::Reference { reference_from_object } => {
                super::checks::check_pose("reference_from_object", reference_from_object)?
            }
        }
        if let Some(d) = start.rotation_std_deg
            && !(MIN_PRIOR_STD_DEG..=180.0).contains(&d)
        {
            return Err(ServiceError::Invalid(format!(
                "rotation_std_deg must be in [{MIN_PRIOR_STD_DEG}, 180], got {d}"
            )));
        }
        start_track(self, start)
    }
}

/// Starts a track from a caller's prior (checked by [`ServiceState::start_track`]); returns
/// its first state.
fn start_track(state: &ServiceState, start: &StartTrack) -> Result<TrackState, ServiceError> {
    let object_id = start.object_id.as_str();
    let mut guard = state.engine.lock().unwrap_or_else(|p| p.into_inner());
    if guard.is_none() {
        *guard = Engine::new(state);
    }
    let engine = guard
        .as_mut()
        .ok_or_else(|| ServiceError::Conflict("no cameras are registered: register the cameras first".into()))?;
    engine.sync_models(state);
    if !engine.models.contains_key(object_id) {
        return Err(ServiceError::NotReady(format!(
            "object '{object_id}' has no codebook yet (see its codebook status)"
        )));
    }
    // checked under the engine's lock, so that concurrent starts cannot pass the caps together
    let limits = state.config.limits;
    let tracks = engine.tracker.tracks();
    let of_object = tracks.iter().filter(|t| t.object == object_id).count();
    if of_object >= limits.max_tracks_per_object || tracks.len() >= limits.max_tracks {
        return Err(ServiceError::LimitReached(format!(
            "this server keeps at most {} tracks per object and {} in all (--max-tracks-per-object, --max-tracks); '{object_id}' has {of_object}, there are {}: stop one first",
            limits.max_tracks_per_object,
            limits.max_tracks,
            tracks.len()
        )));
    }
    let reference_from_object = match start.pose {
        PriorPose::World { world_from_object } => engine.tracker.world_from_reference().inverse() * world_from_object,
        PriorPose::Reference { reference_from_object } => reference_from_object,
    };
    let prior = crate::tracker::TrackPrior {
        reference_from_object,
        translation_std_m: start.translation_std_m,
        rotation_std_rad: start.rotation_std_deg.map(f64::to_radians),
    };
    let id = engine
        .tracker
        .start_track(object_id, &prior)
        .map_err(|e| ServiceError::Invalid(format!("prior: {e}")))?;
    let view = views(state, engine, None, &HashSet::new(), Some(id))
        .into_iter()
        .find(|v| v.id == id)
        .ok_or_else(|| ServiceError::Internal(format!("track {id} has no view")))?;
    drop(guard);
    state.tracking.publish(view.clone());
    state.publish(ServiceEvent::Track(Arc::new(view.clone())));
    Ok(view)
}

/// Draws `n` poses from a track's distribution (reference frame) for a decision.
pub(super) fn draw_samples(state: &ServiceState, track_id: u64, n: usize) -> Result<Drawn, ServiceError> {
    let mut guard = state.engine.lock().unwrap_or_else(|p| p.into_inner());
    let known = state.tracking.board().views.contains_key(&track_id);
    if !known {
        return Err(ServiceError::not_found("track", track_id.to_string()));
    }
    // a restarted server answers about its restored tracks before the first frame arrives
    if guard.is_none() {
        *guard = Engine::new(state);
    }
    let engine = guard
        .as_mut()
        .ok_or_else(|| ServiceError::not_found("track", track_id.to_string()))?;
    engine.sync_models(state);
    if engine.pending.iter().any(|t| t.track.id == track_id) {
        return Err(ServiceError::NotReady(format!(
            "track {track_id} is restored once its object's codebook is ready"
        )));
    }
    let track = engine
        .tracker
        .tracks()
        .iter()
        .find(|t| t.id == track_id)
        .cloned()
        .ok_or_else(|| ServiceError::not_found("track", track_id.to_string()))?;
    let estimate = engine
        .tracker
        .estimate(track_id)
        .ok_or_else(|| ServiceError::NotReady(format!("track {track_id} has no estimate yet")))?;
    let samples = engine
        .tracker
        .sample_poses(track_id, n, &mut engine.rng)
        .ok_or_else(|| ServiceError::NotReady(format!("track {track_id} has no particles yet")))?;
    Ok(Drawn {
        track_id,
        object_id: track.object,
        stamp_ns: estimate.stamp_ns,
        reference_from_object: estimate.reference_from_object,
        translation_std_m: estimate.translation_std_m,
        samples,
        world_from_reference: engine.tracker.world_from_reference(),
        base_from_reference: engine.base_from_reference,
        reference_sees: engine.tracker.reference_sees(track_id).unwrap_or(true),
    })
}

/// Builds the states of every (not stopped) track after a step, or of track `only`.
pub(super) fn views(
    state: &ServiceState,
    engine: &mut Engine,
    latency_ms: Option<f64>,
    stopped: &HashSet<u64>,
    only: Option<u64>,
) -> Vec<TrackState> {
    let world_from_reference = engine.tracker.world_from_reference();
    let names: BTreeMap<String, String> = state
        .registry()
        .objects
        .values()
        .map(|o| (o.info.id.clone(), o.info.name.clone()))
        .collect();
    let truth = state.truth.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let tracks: Vec<_> = engine.tracker.tracks().to_vec();
    let mut out = Vec::new();
    for t in tracks
        .iter()
        .filter(|t| !stopped.contains(&t.id) && only.is_none_or(|id| id == t.id))
    {
        let Some(e) = engine.tracker.estimate(t.id) else {
            continue;
        };
        let world_from_object = world_from_reference * e.reference_from_object;
        let particles = engine.tracker.particles(t.id).unwrap_or_default();
        let stride = particles.len().div_ceil(VIEW_MAX_PARTICLES).max(1);
        let particles = particles
            .iter()
            .step_by(stride)
            .map(|p| {
                let w = world_from_reference * nalgebra::Point3::from(p.position_in_reference_m);
                ParticleInWorld {
                    position_world_m: [w.x, w.y, w.z],
                    camera: p.camera.clone(),
                    weight: p.weight,
                }
            })
            .collect();
        let samples_world = engine
            .tracker
            .sample_poses(t.id, VIEW_SAMPLES, &mut engine.rng)
            .map(|s| s.poses.iter().map(|p| world_from_reference * p).collect())
            .unwrap_or_default();
        // the orientation error modulo the object's exact symmetries: a turn that changes
        // neither shape nor colour is no error, one the colour tells apart always is
        let truth = truth.get(&t.object).map(|(_, w)| TruthError {
            translation_error_m: (w.translation.vector - world_from_object.translation.vector).norm(),
            orientation_error_deg: engine
                .symmetries_of(&t.object)
                .error_deg(&world_from_object.rotation, &w.rotation),
        });
        let decision = state.tracking.board().views.get(&t.id).and_then(|v| v.decision.clone());
        out.push(TrackState {
            id: t.id,
            object_id: t.object.clone(),
            object_name: names.get(&t.object).cloned().unwrap_or_else(|| t.object.clone()),
            status: t.status,
            stamp_ns: e.stamp_ns,
            reference_from_object: e.reference_from_object,
            world_from_object,
            translation_std_m: e.translation_std_m,
            rotation_entropy: e.rotation_entropy,
            top_mode_mass: e.rotation_modes.iter().map(|m| m.mass).fold(0.0, f64::max),
            covariance_6x6: e.covariance_6x6.iter().flatten().copied().collect(),
            components: e.components.clone(),
            rotation_modes: e.rotation_modes.clone(),
            particles,
            samples_world,
            decision,
            truth,
            ingest_to_estimate_ms: latency_ms,
            reinitialised: t.reinitialised.clone(),
        });
    }
    out
}

/// One tracker step on a set of frames (the worker's, and the headless demo's in lockstep).
pub(super) fn step(state: &ServiceState, set: &FusionSet) {
    let mut guard = state.engine.lock().unwrap_or_else(|p| p.into_inner());
    // (Re)build the tracker when the cameras changed.
    let cameras_now: BTreeMap<String, CameraMount> = state
        .registry()
        .cameras
        .iter()
        .map(|(k, c)| (k.clone(), c.mount))
        .collect();
    let epoch = state.ingest().epoch();
    if set.epoch != epoch {
        // taken before a restart of the clock (or the demo's loop): it belongs to the last one
        return;
    }
    if guard.as_ref().is_some_and(|e| e.epoch != epoch) {
        // the odometry started over (a restarted clock, the demo's loop): as tf clears its
        // buffer, the tracker starts over rather than carry the robot's motion across the jump
        *guard = None;
        *state.restored.lock().unwrap_or_else(|p| p.into_inner()) = None;
        state.forget_all_tracks();
    }
    if guard.as_ref().is_none_or(|e| e.cameras != cameras_now) {
        // the tracks carry over to the new camera set (those of a removed camera do not)
        if let Some(old) = guard.as_ref() {
            let mut snap = old.tracker.snapshot();
            snap.tracks.extend(old.pending.iter().cloned());
            *state.restored.lock().unwrap_or_else(|p| p.into_inner()) = Some(snap);
        }
        *guard = Engine::new(state);
        state.decision_cache.forget(None);
    }
    let Some(engine) = guard.as_mut() else { return };
    engine.sync_models(state);
    // stopped tracks leave the tracker (a stop arriving during the step is filtered below
    // and removed at the next one)
    let stopped_before = std::mem::take(&mut state.tracking.board_mut().stopped);
    for id in stopped_before {
        engine.tracker.remove_track(id);
        engine.pending.retain(|t| t.track.id != id);
    }
    let frames: Vec<CameraFrame> = set.frames.iter().map(|f| f.frame.clone()).collect();
    if frames.is_empty() {
        return;
    }
    let stamp = frames.iter().map(|f| f.stamp_ns).max().unwrap_or(0);
    let robot_base_from_camera = cameras_now.values().find_map(|m| match m {
        CameraMount::Robot { base_from_camera } => Some(*base_from_camera),
        _ => None,
    });
    // odometry never goes back in time, except across a restarted camera clock
    let clock_reset_ns = state.config.window_ns.max(super::ingest::MIN_CLOCK_RESET_NS);
    let odometry_stamp = engine.odometry_stamp_ns.map_or(stamp, |s| {
        if s.checked_sub(stamp).is_none_or(|back| back > clock_reset_ns) {
            stamp
        } else {
            s.max(stamp)
        }
    });
    let odometry = robot_base_from_camera.and_then(|registered| {
        state.ingest().odometry_at(odometry_stamp).map(|o| RobotOdometry {
            stamp_ns: odometry_stamp,
            odom_from_base: o.odom_from_base,
            world_from_odom: o.world_from_odom,
            base_from_camera: o.base_from_camera.unwrap_or(registered),
        })
    });
    if let Some(o) = &odometry {
        engine.odometry_stamp_ns = Some(odometry_stamp);
        engine.base_from_reference = Some(o.base_from_camera);
    }
    // the scene's table top may change between steps (PUT /scene/support_plane)
    engine
        .tracker
        .set_support_normal(state.support_plane().map(|p| nalgebra::Vector3::from(p.normal)));
    let t0 = Instant::now();
    match engine.tracker.step(&frames, odometry.as_ref()) {
        Ok(report) => {
            // a track re-initialised from a detection is a new distribution under its old id:
            // its answers start over
            for id in &report.tracks_reinitialised {
                state.decision_cache.restart_answers(*id);
            }
            let m = &state.metrics;
            let us = t0.elapsed().as_micros() as u64;
            tracing::debug!(
                views = frames.len(),
                verified = report.verified,
                registered = report.registered,
                step_us = us,
                "tracker step"
            );
            m.steps.fetch_add(1, Ordering::Relaxed);
            m.step_latency_us_sum.fetch_add(us, Ordering::Relaxed);
            m.last_step_latency_us.store(us, Ordering::Relaxed);
            m.stage_seconds
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .accumulate(&report.timings);
        }
        Err(e) => {
            state.metrics.step_errors.fetch_add(1, Ordering::Relaxed);
            tracing::warn!("tracker step failed: {e}");
            return;
        }
    }
    let stopped: HashSet<u64> = state.tracking.board().stopped.iter().copied().collect();
    let newest_received = set.frames.iter().map(|f| f.received).max();
    let latency_ms = newest_received.map(|r| r.elapsed().as_secs_f64() * 1e3);
    let t_after = Instant::now();
    let views = views(state, engine, latency_ms, &stopped, None);
    refill_sample_banks(state, engine, &stopped);
    state
        .metrics
        .after_step_us_sum
        .fetch_add(t_after.elapsed().as_micros() as u64, Ordering::Relaxed);
    {
        let mut ring = state
            .metrics
            .ingest_to_estimate_us
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        for f in &set.frames {
            ring.push(f.received.elapsed().as_micros() as u64);
        }
    }
    state.tracking.board_mut().world_from_reference = Some(engine.tracker.world_from_reference());
    drop(guard);
    for v in views {
        state.tracking.publish(v.clone());
        state.publish(ServiceEvent::Track(Arc::new(v)));
    }
}

/// Draws the sample banks of the tracks planners asked about lately (see
/// [`super::decisions::DecisionCache`]): decisions then read them without the tracker's lock.
fn refill_sample_banks(state: &ServiceState, engine: &mut Engine, stopped: &HashSet<u64>) {
    let generation = state.metrics.steps.load(Ordering::Relaxed);
    let world_from_reference = engine.tracker.world_from_reference();
    let mut banks = Vec::new();
    for (track_id, n) in state.decision_cache.watched() {
        if stopped.contains(&track_id) {
            continue;
        }
        let Some(object_id) = engine
            .tracker
            .tracks()
            .iter()
            .find(|t| t.id == track_id)
            .map(|t| t.object.clone())
        else {
            continue;
        };
        let (Some(estimate), Some(samples)) = (
            engine.tracker.estimate(track_id),
            engine.tracker.sample_poses(track_id, n, &mut engine.rng),
        ) else {
            continue;
        };
        banks.push(super::decisions::SampleBank {
            generation,
            drawn: Drawn {
                track_id,
                object_id,
                stamp_ns: estimate.stamp_ns,
                reference_from_object: estimate.reference_from_object,
                translation_std_m: estimate.translation_std_m,
                samples,
                world_from_reference,
                base_from_reference: engine.base_from_reference,
                reference_sees: engine.tracker.reference_sees(track_id).unwrap_or(true),
            },
        });
    }
    state.decision_cache.set_banks(banks);
}

/// Writes the tracker's compact snapshot (with the restored tracks still waiting for their
/// models, so that a restart before the codebooks are ready loses nothing).
pub fn save_tracker_snapshot(state: &ServiceState) {
    let snap = {
        let guard = state.engine.lock().unwrap_or_else(|p| p.into_inner());
        let Some(engine) = guard.as_ref() else { return };
        let mut snap = engine.tracker.snapshot();
        snap.tracks.extend(engine.pending.iter().cloned());
        snap
    };
    let bytes = match serde_json::to_vec(&snap) {
        Ok(b) => b,
        Err(e) => {
            tracing::warn!("tracker snapshot: {e}");
            return;
        }
    };
    state
        .metrics
        .tracker_snapshot_bytes
        .store(bytes.len() as u64, Ordering::Relaxed);
    if let Err(e) = state
        .store
        .put_bytes(super::store::Table::TrackerState, super::store::TRACKER_KEY, &bytes)
    {
        tracing::warn!("saving the tracker snapshot: {e}");
    }
}

/// Without frames, builds the tracker from the previous run's snapshot and restores its tracks
/// as their codebooks become ready, so that decisions about them are answered at once.
fn restore_while_idle(state: &ServiceState) {
    let waiting = state.restored.lock().unwrap_or_else(|p| p.into_inner()).is_some();
    let mut guard = state.engine.lock().unwrap_or_else(|p| p.into_inner());
    if guard.is_none() && waiting {
        *guard = Engine::new(state);
    }
    if let Some(engine) = guard.as_mut()
        && !engine.pending.is_empty()
    {
        engine.sync_models(state);
    }
}

fn run_worker(state: Service, stop: Arc<AtomicBool>) {
    let mut last_snapshot = Instant::now();
    let mut last_tracker_snapshot = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        let set = {
            let mut ingest = state.ingest();
            loop {
                if stop.load(Ordering::Relaxed) {
                    return;
                }
                if let Some(set) = ingest.take_fusion_set() {
                    break Some(set);
                }
                let (g, timeout) = state
                    .wake
                    .wait_timeout(ingest, Duration::from_millis(200))
                    .unwrap_or_else(|p| p.into_inner());
                ingest = g;
                if timeout.timed_out() {
                    break None;
                }
            }
        };
        match set {
            Some(set) => {
                state
                    .metrics
                    .frames_dropped
                    .fetch_add(set.superseded as u64, Ordering::Relaxed);
                if !set.frames.is_empty() {
                    step(&state, &set);
                }
            }
            None => restore_while_idle(&state),
        }
        if last_snapshot.elapsed() >= SNAPSHOT_PERIOD {
            last_snapshot = Instant::now();
            if let Err(e) = state.save_track_records() {
                tracing::warn!("saving track snapshots: {e}");
            }
        }
        if last_tracker_snapshot.elapsed() >= TRACKER_SNAPSHOT_PERIOD {
            last_tracker_snapshot = Instant::now();
            save_tracker_snapshot(&state);
        }
    }
}
