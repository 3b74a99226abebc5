//! Ingest: frames and odometry as domain types (`CameraFrame`, [`OdometryMsg`]) from any
//! transport, checked against the registry, into the fixed-lag buffer the tracking worker reads.
//!
//! Policy (stated once):
//! - Stamps are nanoseconds in `0..=MAX_STAMP_NS`; every difference of stamps is computed with
//!   checked arithmetic.
//! - The *newest stamp* is kept per camera (and for odometry). A frame whose stamp is older than
//!   its camera's newest, or the newest of any camera, minus `window_ns` is refused as stale (counted
//!   in `frames_stale`); so is a frame whose stamp this camera already sent. Late frames inside
//!   the window are accepted, in any order.
//! - A jump back by more than `clock_reset_ns` (default: the larger of the window and one
//!   second) is a restarted clock (a second replay, a simulation restart), as tf treats a
//!   backwards jump of ROS time: that camera's queue (or the odometry buffer) starts over and
//!   the message is accepted; odometry restarts bump [`IngestBuffer::epoch`] so that the worker
//!   starts its tracker over. A camera whose newest stamp is more than `clock_reset_ns` away
//!   from another camera's is on another clock and does not make that camera's frames stale.
//! - Accepted frames wait per camera, at most `max_pending` each; when a camera's queue is full
//!   its oldest waiting frame is dropped and counted (`frames_dropped`). Memory is bounded by
//!   `cameras x max_pending` frames; a deleted or replaced camera's queue is freed.
//! - Each tracker step takes, for every camera, its newest waiting frame within the window of
//!   the newest waiting frame of all cameras (older waiting frames of that camera are
//!   superseded: dropped and counted), so a slow tracker skips stale frames instead of falling
//!   behind. A frame is fused once.
//! - Odometry is kept in a bounded, time-sorted buffer and interpolated at each step's
//!   reference time (linear in translation, slerp in rotation).

use super::ServiceState;
use super::checks::shorten;
use super::error::ServiceError;
use super::events::ServiceEvent;
use crate::geometry::Pose;
use crate::sensor::{CameraFrame, Detection};
use nalgebra::{Isometry3, Translation3};
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

/// Most odometry samples kept.
pub const MAX_ODOMETRY_SAMPLES: usize = 4_096;

/// Latest accepted stamp: 2100-01-01T00:00:00Z in nanoseconds since the Unix epoch (leaves
/// headroom below `i64::MAX` for every sum and difference of stamps).
pub const MAX_STAMP_NS: i64 = 4_102_444_800_000_000_000;

/// Smallest backwards jump treated as a restarted clock.
pub const MIN_CLOCK_RESET_NS: i64 = 1_000_000_000;

/// One camera frame as received (checked against its camera), with its arrival time.
#[derive(Debug, Clone)]
pub struct IngestedFrame {
    pub frame: CameraFrame,
    /// When the server received it (for ingest-to-estimate latency).
    pub received: Instant,
}

impl std::ops::Deref for IngestedFrame {
    type Target = CameraFrame;
    fn deref(&self) -> &CameraFrame {
        &self.frame
    }
}

/// One odometry message.
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryMsg {
    pub stamp_ns: i64,
    pub odom_from_base: Pose,
    /// Row-major 6x6 covariance of `odom_from_base` (x, y, z, rx, ry, rz), as in ROS.
    pub covariance: Option<[f64; 36]>,
    pub world_from_odom: Pose,
    pub base_from_camera: Option<Pose>,
}

/// Why a frame was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IngestError {
    #[error(
        "frame stamp {stamp_ns} ns is {behind_ms:.1} ms behind the newest frame ({newest_ns} ns), outside the {window_ms:.1} ms window; it is not applied"
    )]
    TooOld {
        stamp_ns: i64,
        newest_ns: i64,
        behind_ms: f64,
        window_ms: f64,
    },
    #[error("camera '{camera}' already sent a frame stamped {stamp_ns} ns")]
    Duplicate { camera: String, stamp_ns: i64 },
    #[error("odometry stamp {stamp_ns} ns is more than the window behind the newest odometry ({newest_ns} ns)")]
    OdometryTooOld { stamp_ns: i64, newest_ns: i64 },
    #[error("stamp {stamp_ns} ns is outside 0..={MAX_STAMP_NS} ns")]
    BadStamp { stamp_ns: i64 },
}

/// Checks that a stamp lies in `0..=MAX_STAMP_NS`.
pub fn check_stamp(stamp_ns: i64) -> Result<(), IngestError> {
    if (0..=MAX_STAMP_NS).contains(&stamp_ns) {
        Ok(())
    } else {
        Err(IngestError::BadStamp { stamp_ns })
    }
}

/// `later - earlier` in nanoseconds, `None` on overflow.
fn behind_ns(later: i64, earlier: i64) -> Option<i64> {
    later.checked_sub(earlier)
}

/// What a step fuses.
#[derive(Debug, Clone)]
pub struct FusionSet {
    pub frames: Vec<Arc<IngestedFrame>>,
    /// Frames superseded (dropped) when this set was taken.
    pub superseded: usize,
    /// The buffer's epoch when the set was taken (a set of an earlier epoch is not fused).
    pub epoch: u64,
}

#[derive(Default)]
struct CameraQueue {
    pending: VecDeque<Arc<IngestedFrame>>,
    /// Stamps already seen (recent ones, to refuse duplicates).
    recent_stamps: VecDeque<i64>,
    latest: Option<Arc<IngestedFrame>>,
    /// Newest stamp accepted from this camera.
    newest_ns: Option<i64>,
}

/// The buffer (kept behind a mutex in the app state).
pub struct IngestBuffer {
    window_ns: i64,
    clock_reset_ns: i64,
    max_pending: usize,
    cameras: BTreeMap<String, CameraQueue>,
    odometry: VecDeque<OdometryMsg>,
    epoch: u64,
    clock_resets: u64,
}

/// What happened to an accepted frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pushed {
    /// Waiting frames of the camera dropped to make room.
    pub dropped: usize,
    /// The frame restarted its camera's clock.
    pub clock_reset: bool,
}

impl IngestBuffer {
    pub fn new(window_ns: i64, max_pending: usize) -> Self {
        let window_ns = window_ns.clamp(0, MAX_STAMP_NS);
        Self {
            window_ns,
            clock_reset_ns: window_ns.max(MIN_CLOCK_RESET_NS),
            max_pending: max_pending.max(1),
            cameras: BTreeMap::new(),
            odometry: VecDeque::new(),
            epoch: 0,
            clock_resets: 0,
        }
    }

    pub fn window_ns(&self) -> i64 {
        self.window_ns
    }

    /// Bumped whenever the odometry starts over (a restarted clock, [`IngestBuffer::clear`]):
    /// the tracker must not carry the robot's motion across it.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Restarted clocks seen (cameras and odometry).
    pub fn clock_resets(&self) -> u64 {
        self.clock_resets
    }

    /// Frees a camera's queue and stamps (the camera was deleted or replaced).
    pub fn forget_camera(&mut self, camera: &str) {
        self.cameras.remove(camera);
    }

    /// Forgets every waiting frame, stamp and odometry sample (a new start, as the demo's
    /// loop); bumps the epoch.
    pub fn clear(&mut self) {
        self.cameras.clear();
        self.odometry.clear();
        self.epoch += 1;
    }

    /// Cameras with a queue (for tests and metrics).
    pub fn cameras_with_queue(&self) -> usize {
        self.cameras.len()
    }

    /// Odometry samples kept.
    pub fn odometry_len(&self) -> usize {
        self.odometry.len()
    }

    /// Accepts a frame (see the module's policy).
    pub fn push_frame(&mut self, frame: IngestedFrame) -> Result<Pushed, IngestError> {
        let stamp = frame.stamp_ns;
        check_stamp(stamp)?;
        let (window, reset) = (self.window_ns, self.clock_reset_ns);
        let own_newest = self.cameras.get(&frame.camera).and_then(|q| q.newest_ns);
        let clock_reset = own_newest.is_some_and(|n| behind_ns(n, stamp).is_none_or(|b| b > reset));
        // the newest stamp of every other camera on the same clock
        let others_newest = self
            .cameras
            .iter()
            .filter(|(id, _)| **id != frame.camera)
            .filter_map(|(_, q)| q.newest_ns)
            .filter(|n| behind_ns(*n, stamp).is_some_and(|b| b <= reset))
            .max();
        let newest = match (own_newest.filter(|_| !clock_reset), others_newest) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        };
        if let Some(newest) = newest
            && behind_ns(newest, stamp).is_none_or(|b| b > window)
        {
            return Err(IngestError::TooOld {
                stamp_ns: stamp,
                newest_ns: newest,
                behind_ms: newest.saturating_sub(stamp) as f64 * 1e-6,
                window_ms: window as f64 * 1e-6,
            });
        }
        let q = self.cameras.entry(frame.camera.clone()).or_default();
        if clock_reset {
            *q = CameraQueue::default();
            self.clock_resets += 1;
        }
        if q.recent_stamps.contains(&stamp) {
            return Err(IngestError::Duplicate {
                camera: frame.camera.clone(),
                stamp_ns: stamp,
            });
        }
        q.recent_stamps.push_back(stamp);
        if q.recent_stamps.len() > 64 {
            q.recent_stamps.pop_front();
        }
        q.newest_ns = Some(q.newest_ns.map_or(stamp, |n| n.max(stamp)));
        let frame = Arc::new(frame);
        if q.latest.as_ref().is_none_or(|l| l.stamp_ns < stamp) {
            q.latest = Some(frame.clone());
        }
        let pos = q.pending.partition_point(|f| f.stamp_ns < stamp);
        q.pending.insert(pos, frame);
        let mut dropped = 0;
        while q.pending.len() > self.max_pending {
            q.pending.pop_front();
            dropped += 1;
        }
        Ok(Pushed { dropped, clock_reset })
    }

    /// Frames waiting for the tracker (the queue depth).
    pub fn pending(&self) -> usize {
        self.cameras.values().map(|q| q.pending.len()).sum()
    }

    /// The newest frame received from a camera.
    pub fn latest(&self, camera: &str) -> Option<Arc<IngestedFrame>> {
        self.cameras.get(camera).and_then(|q| q.latest.clone())
    }

    /// The newest stamp of any camera.
    pub fn newest_ns(&self) -> Option<i64> {
        self.cameras.values().filter_map(|q| q.newest_ns).max()
    }

    /// Takes each camera's newest waiting frame within the window of the newest waiting frame
    /// (`None` when nothing waits).
    pub fn take_fusion_set(&mut self) -> Option<FusionSet> {
        let newest = self
            .cameras
            .values()
            .filter_map(|q| q.pending.back().map(|f| f.stamp_ns))
            .max()?;
        let mut frames = Vec::new();
        let mut superseded = 0;
        for q in self.cameras.values_mut() {
            if let Some(f) = q.pending.pop_back() {
                superseded += q.pending.len();
                q.pending.clear();
                if behind_ns(newest, f.stamp_ns).is_some_and(|b| b <= self.window_ns) {
                    frames.push(f);
                } else {
                    superseded += 1;
                }
            }
        }
        if frames.is_empty() && superseded == 0 {
            return None;
        }
        Some(FusionSet {
            frames,
            superseded,
            epoch: self.epoch,
        })
    }

    /// Accepts an odometry message (time-sorted insert; bounded); `Ok(true)` when it restarted
    /// the odometry's clock.
    pub fn push_odometry(&mut self, msg: OdometryMsg) -> Result<bool, IngestError> {
        check_stamp(msg.stamp_ns)?;
        let mut clock_reset = false;
        if let Some(last) = self.odometry.back() {
            match behind_ns(last.stamp_ns, msg.stamp_ns) {
                Some(b) if b <= self.window_ns => {}
                Some(b) if b <= self.clock_reset_ns => {
                    return Err(IngestError::OdometryTooOld {
                        stamp_ns: msg.stamp_ns,
                        newest_ns: last.stamp_ns,
                    });
                }
                _ => {
                    self.odometry.clear();
                    self.epoch += 1;
                    self.clock_resets += 1;
                    clock_reset = true;
                }
            }
        }
        let pos = self.odometry.partition_point(|m| m.stamp_ns <= msg.stamp_ns);
        if pos > 0 && self.odometry[pos - 1].stamp_ns == msg.stamp_ns {
            self.odometry[pos - 1] = msg;
        } else {
            self.odometry.insert(pos, msg);
        }
        while self.odometry.len() > MAX_ODOMETRY_SAMPLES {
            self.odometry.pop_front();
        }
        Ok(clock_reset)
    }

    /// Odometry at `stamp_ns`: interpolated between the two samples around it, or the nearest
    /// sample when `stamp_ns` lies outside but within the window; `None` otherwise.
    pub fn odometry_at(&self, stamp_ns: i64) -> Option<OdometryMsg> {
        let pos = self.odometry.partition_point(|m| m.stamp_ns <= stamp_ns);
        let before = pos.checked_sub(1).and_then(|i| self.odometry.get(i));
        let after = self.odometry.get(pos);
        match (before, after) {
            (Some(a), Some(b)) if b.stamp_ns > a.stamp_ns => {
                let span = behind_ns(b.stamp_ns, a.stamp_ns)? as f64;
                let t = behind_ns(stamp_ns, a.stamp_ns)? as f64 / span;
                Some(OdometryMsg {
                    stamp_ns,
                    odom_from_base: interpolate(&a.odom_from_base, &b.odom_from_base, t),
                    covariance: a.covariance,
                    world_from_odom: interpolate(&a.world_from_odom, &b.world_from_odom, t),
                    base_from_camera: match (a.base_from_camera, b.base_from_camera) {
                        (Some(x), Some(y)) => Some(interpolate(&x, &y, t)),
                        (x, y) => x.or(y),
                    },
                })
            }
            (Some(a), _) if behind_ns(stamp_ns, a.stamp_ns).is_some_and(|d| d <= self.window_ns) => Some(a.clone()),
            (None, Some(b)) if behind_ns(b.stamp_ns, stamp_ns).is_some_and(|d| d <= self.window_ns) => Some(b.clone()),
            _ => None,
        }
    }

    /// The recorded `world_from_base` positions (for the robot's trajectory), oldest first.
    pub fn trajectory_m(&self, max_points: usize) -> Vec<[f64; 3]> {
        let step = (self.odometry.len() / max_points.max(1)).max(1);
        self.odometry
            .iter()
            .step_by(step)
            .map(|m| {
                let p = (m.world_from_odom * m.odom_from_base).translation.vector;
                [p.x, p.y, p.z]
            })
            .collect()
    }
}

/// Most detections in one frame.
pub const MAX_DETECTIONS_PER_FRAME: usize = 256;

/// What happened to an accepted frame, as the service reports it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameReceipt {
    pub camera: String,
    pub stamp_ns: i64,
    /// Frames waiting for the tracker, all cameras.
    pub queue_depth: usize,
    /// Waiting frames of this camera dropped to make room.
    pub dropped: usize,
}

impl ServiceState {
    /// Checks a frame's detections: known objects, a score in 0..=1, a box of positive size
    /// inside the image.
    pub fn check_detections(&self, detections: &[Detection], width: u32, height: u32) -> Result<(), ServiceError> {
        if detections.len() > MAX_DETECTIONS_PER_FRAME {
            return Err(ServiceError::Invalid(format!(
                "a frame carries at most {MAX_DETECTIONS_PER_FRAME} detections, got {}",
                detections.len()
            )));
        }
        let reg = self.registry();
        let (w, h) = (f64::from(width), f64::from(height));
        for d in detections {
            if !reg.objects.contains_key(&d.object) {
                return Err(ServiceError::Invalid(format!(
                    "detection names unknown object '{}'",
                    shorten(&d.object)
                )));
            }
            let b = d.bbox_xywh_px;
            let inside = b.iter().all(|v| v.is_finite())
                && b[0] >= 0.0
                && b[1] >= 0.0
                && b[2] > 0.0
                && b[3] > 0.0
                && b[0] + b[2] <= w
                && b[1] + b[3] <= h;
            if !inside || !(0.0..=1.0).contains(&d.score) {
                return Err(ServiceError::Invalid(format!(
                    "detection of '{}' needs a box of positive size inside the {w}x{h} image and a score in 0..=1, got {b:?} score {}",
                    d.object, d.score
                )));
            }
        }
        Ok(())
    }

    /// Takes one camera frame from any transport: the camera must be registered with the
    /// frame's intrinsics, the images must have its size and the detections must pass
    /// [`ServiceState::check_detections`]; then the frame is queued for the tracker (see the
    /// module's policy for stale frames and restarted clocks).
    pub fn ingest_frame(&self, frame: CameraFrame, received: Instant) -> Result<FrameReceipt, ServiceError> {
        check_stamp(frame.stamp_ns).map_err(|e| ServiceError::Invalid(format!("stamp_ns: {e}")))?;
        let intrinsics = self
            .registry()
            .cameras
            .get(&frame.camera)
            .map(|c| c.intrinsics)
            .ok_or_else(|| ServiceError::not_found("camera", frame.camera.clone()))?;
        if frame.intrinsics != intrinsics {
            return Err(ServiceError::Invalid(format!(
                "the frame's intrinsics differ from camera '{}''s registered ones",
                frame.camera
            )));
        }
        let (w, h) = (intrinsics.width, intrinsics.height);
        let sizes_ok = frame.depth.width == w
            && frame.depth.height == h
            && frame.color.as_ref().is_none_or(|c| c.width == w && c.height == h);
        if !sizes_ok {
            return Err(ServiceError::Invalid(format!(
                "images must be {w}x{h} like camera '{}'",
                frame.camera
            )));
        }
        self.check_detections(&frame.detections, w, h)?;
        let (camera, stamp_ns) = (frame.camera.clone(), frame.stamp_ns);
        let pushed = self.ingest().push_frame(IngestedFrame { frame, received });
        match pushed {
            Ok(Pushed { dropped, clock_reset }) => {
                if clock_reset {
                    tracing::info!(
                        "camera '{camera}' restarted its clock (stamp {stamp_ns} ns); its queue starts over"
                    );
                }
                self.metrics.frames_accepted.fetch_add(1, Ordering::Relaxed);
                self.metrics.frames_dropped.fetch_add(dropped as u64, Ordering::Relaxed);
                self.wake.notify_one();
                self.publish(ServiceEvent::Frame {
                    camera: camera.clone(),
                    stamp_ns,
                });
                Ok(FrameReceipt {
                    camera,
                    stamp_ns,
                    queue_depth: self.ingest().pending(),
                    dropped,
                })
            }
            Err(e @ (IngestError::TooOld { .. } | IngestError::Duplicate { .. })) => {
                self.metrics.frames_stale.fetch_add(1, Ordering::Relaxed);
                Err(ServiceError::Stale(e.to_string()))
            }
            Err(e @ IngestError::BadStamp { .. }) => Err(ServiceError::Invalid(e.to_string())),
            Err(e) => Err(ServiceError::Stale(e.to_string())),
        }
    }

    /// Takes one odometry message (checked stamp; a stamp far behind the newest restarts the
    /// odometry's clock and with it the tracks).
    pub fn ingest_odometry(&self, msg: OdometryMsg) -> Result<(), ServiceError> {
        let stamp_ns = msg.stamp_ns;
        super::checks::check_pose("odom_from_base", &msg.odom_from_base)?;
        super::checks::check_pose("world_from_odom", &msg.world_from_odom)?;
        if let Some(p) = &msg.base_from_camera {
            super::checks::check_pose("base_from_camera", p)?;
        }
        let reset = self.ingest().push_odometry(msg).map_err(|e| match e {
            IngestError::BadStamp { .. } => ServiceError::Invalid(e.to_string()),
            e => ServiceError::Stale(e.to_string()),
        })?;
        if reset {
            tracing::info!("odometry restarted its clock (stamp {stamp_ns} ns); tracking starts over");
        }
        self.metrics.odometry_accepted.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }
}

/// `a` at t = 0, `b` at t = 1.
pub fn interpolate(a: &Pose, b: &Pose, t: f64) -> Pose {
    let tr = a.translation.vector.lerp(&b.translation.vector, t);
    let rot = a.rotation.try_slerp(&b.rotation, t, 1e-9).unwrap_or(a.rotation);
    Isometry3::from_parts(Translation3::from(tr), rot)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn frame(camera: &str, stamp_ns: i64) -> IngestedFrame {
        IngestedFrame {
            frame: CameraFrame {
                camera: camera.into(),
                stamp_ns,
                intrinsics: crate::camera::Intrinsics::new(2, 2, [2.0, 0.0, 1.0, 0.0, 2.0, 1.0, 0.0, 0.0, 1.0])
                    .expect("intrinsics"),
                depth: crate::camera::DepthImage::zeros(2, 2),
                color: None,
                detections: vec![],
            },
            received: Instant::now(),
        }
    }

    const MS: i64 = 1_000_000;

    /// The service takes frames and odometry as domain types, checked as HTTP's are: a second
    /// transport (a ROS bridge) needs no DTO.
    #[test]
    fn the_service_checks_domain_frames_and_odometry_against_its_registry() {
        use crate::camera::{DepthImage, Intrinsics};
        use crate::sensor::CameraMount;
        use crate::service::{Service, ServiceConfig, ServiceError};
        let tmp = tempfile::tempdir().unwrap();
        let service = Service::open(ServiceConfig::new(tmp.path().to_path_buf())).unwrap();
        let k = Intrinsics::from_focal(8, 6, 10.0).unwrap();
        let mount = CameraMount::Stationary {
            world_from_camera: Pose::identity(),
        };
        service.register_camera("ext1", k, mount).unwrap();
        let frame = |camera: &str, w: u32, dets: Vec<Detection>| CameraFrame {
            camera: camera.into(),
            stamp_ns: 1_000 * MS,
            intrinsics: Intrinsics::from_focal(w, 6, 10.0).unwrap(),
            depth: DepthImage::zeros(w, 6),
            color: None,
            detections: dets,
        };
        let now = Instant::now();
        assert!(matches!(
            service.ingest_frame(frame("nope", 8, vec![]), now),
            Err(ServiceError::NotFound { .. })
        ));
        assert!(matches!(
            service.ingest_frame(frame("ext1", 10, vec![]), now),
            Err(ServiceError::Invalid(_))
        ));
        let unknown = Detection {
            object: "mug".into(),
            bbox_xywh_px: [0.0, 0.0, 2.0, 2.0],
            score: 0.5,
        };
        assert!(matches!(
            service.ingest_frame(frame("ext1", 8, vec![unknown]), now),
            Err(ServiceError::Invalid(_))
        ));
        let receipt = service.ingest_frame(frame("ext1", 8, vec![]), now).unwrap();
        assert_eq!((receipt.queue_depth, receipt.dropped), (1, 0));
        let far = OdometryMsg {
            stamp_ns: 1_000 * MS,
            odom_from_base: Isometry3::translation(2_000.0, 0.0, 0.0),
            covariance: None,
            world_from_odom: Pose::identity(),
            base_from_camera: None,
        };
        assert!(matches!(
            service.ingest_odometry(far.clone()),
            Err(ServiceError::Invalid(_))
        ));
        let near = OdometryMsg {
            odom_from_base: Pose::identity(),
            ..far
        };
        service.ingest_odometry(near).unwrap();
        assert_eq!(service.ingest().odometry_len(), 1);
    }

    #[test]
    fn late_frames_inside_the_window_are_taken_older_ones_refused() {
        let mut b = IngestBuffer::new(100 * MS, 4);
        b.push_frame(frame("a", 1000 * MS)).unwrap();
        // 50 ms late from another camera: inside the window.
        b.push_frame(frame("b", 950 * MS)).unwrap();
        // 150 ms late: refused.
        assert!(matches!(
            b.push_frame(frame("b", 850 * MS)),
            Err(IngestError::TooOld { .. })
        ));
        // Duplicate stamp: refused.
        assert!(matches!(
            b.push_frame(frame("a", 1000 * MS)),
            Err(IngestError::Duplicate { .. })
        ));
        let set = b.take_fusion_set().unwrap();
        let stamps: Vec<i64> = set.frames.iter().map(|f| f.stamp_ns / MS).collect();
        assert_eq!(stamps, vec![1000, 950]);
        assert!(b.take_fusion_set().is_none(), "a frame is fused once");
    }

    #[test]
    fn the_queue_is_bounded_and_stale_frames_are_superseded() {
        let mut b = IngestBuffer::new(1000 * MS, 3);
        let mut dropped = 0;
        for i in 0..10 {
            dropped += b.push_frame(frame("a", i * 10 * MS)).unwrap().dropped;
        }
        assert_eq!(dropped, 7);
        assert_eq!(b.pending(), 3);
        let set = b.take_fusion_set().unwrap();
        assert_eq!(set.frames.len(), 1);
        assert_eq!(set.frames[0].stamp_ns, 90 * MS);
        assert_eq!(set.superseded, 2);
        assert_eq!(b.pending(), 0);
    }

    #[test]
    fn stamps_out_of_range_are_refused_and_a_restarted_clock_starts_over() {
        let mut b = IngestBuffer::new(100 * MS, 4);
        for bad in [-1, i64::MIN, i64::MAX, MAX_STAMP_NS + 1] {
            assert!(matches!(
                b.push_frame(frame("a", bad)),
                Err(IngestError::BadStamp { .. })
            ));
        }
        // a far-future stamp inside the range holds back only its own camera, until its clock
        // restarts
        b.push_frame(frame("a", MAX_STAMP_NS)).unwrap();
        assert!(b.push_frame(frame("b", 5_000 * MS)).is_ok());
        let p = b.push_frame(frame("a", 5_000 * MS)).unwrap();
        assert!(p.clock_reset);
        assert_eq!(b.newest_ns(), Some(5_000 * MS));
        assert_eq!(b.clock_resets(), 1);
        // odometry: late inside the reset span is stale, far back starts over (a new epoch)
        let odo = |t: i64| OdometryMsg {
            stamp_ns: t,
            odom_from_base: Pose::identity(),
            covariance: None,
            world_from_odom: Pose::identity(),
            base_from_camera: None,
        };
        assert_eq!(b.push_odometry(odo(10_000 * MS)), Ok(false));
        assert!(matches!(
            b.push_odometry(odo(9_500 * MS)),
            Err(IngestError::OdometryTooOld { .. })
        ));
        assert_eq!(b.push_odometry(odo(0)), Ok(true));
        assert_eq!(b.epoch(), 1);
        assert_eq!(b.odometry_len(), 1);
        // no overflow at the ends of the range
        assert!(b.odometry_at(MAX_STAMP_NS).is_none());
        assert!(b.odometry_at(i64::MIN).is_none());
        assert!(b.odometry_at(0).is_some());
    }

    #[test]
    fn odometry_is_interpolated_between_samples() {
        let mut b = IngestBuffer::new(100 * MS, 4);
        let pose = |x: f64, yaw: f64| {
            Isometry3::from_parts(
                Translation3::new(x, 0.0, 0.0),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            )
        };
        for (t, x, yaw) in [(0, 0.0, 0.0), (100, 1.0, 0.2)] {
            b.push_odometry(OdometryMsg {
                stamp_ns: t * MS,
                odom_from_base: pose(x, yaw),
                covariance: None,
                world_from_odom: Pose::identity(),
                base_from_camera: None,
            })
            .unwrap();
        }
        let m = b.odometry_at(25 * MS).unwrap();
        assert!((m.odom_from_base.translation.x - 0.25).abs() < 1e-9);
        assert!((m.odom_from_base.rotation.angle() - 0.05).abs() < 1e-9);
        assert!(b.odometry_at(500 * MS).is_none());
        assert!(b.odometry_at(150 * MS).is_some());
    }
}
