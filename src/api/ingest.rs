//! The fixed-lag ingest buffer between the HTTP handlers and the tracking worker.
//!
//! Policy (stated once):
//! - The *newest stamp* is the latest capture time seen from any camera. A frame whose stamp is
//!   older than `newest - window_ns` is refused (409, counted in `frames_stale`); so is a frame
//!   whose stamp this camera already sent. Late frames inside the window are accepted, in any
//!   order.
//! - Accepted frames wait per camera, at most `max_pending` each; when a camera's queue is full
//!   its oldest waiting frame is dropped and counted (`frames_dropped`). Memory is bounded by
//!   `cameras x max_pending` frames.
//! - Each tracker step takes, for every camera, its newest waiting frame within the window
//!   (older waiting frames of that camera are superseded: dropped and counted), so a slow
//!   tracker skips stale frames instead of falling behind. A frame is fused once.
//! - Odometry is kept in a bounded, time-sorted buffer and interpolated at each step's
//!   reference time (linear in translation, slerp in rotation).

use crate::camera::{ColorImage, DepthImage};
use crate::geometry::Pose;
use nalgebra::{Isometry3, Translation3};
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use super::types::DetectionDto;

/// Most odometry samples kept.
pub const MAX_ODOMETRY_SAMPLES: usize = 4_096;

/// One camera image as received.
#[derive(Debug, Clone)]
pub struct IngestedFrame {
    pub camera: String,
    pub stamp_ns: i64,
    pub depth: DepthImage,
    pub color: Option<ColorImage>,
    pub detections: Vec<DetectionDto>,
    /// When the server received it (for ingest-to-estimate latency).
    pub received: Instant,
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
}

/// What a step fuses.
#[derive(Debug, Clone)]
pub struct FusionSet {
    pub frames: Vec<Arc<IngestedFrame>>,
    /// Frames superseded (dropped) when this set was taken.
    pub superseded: usize,
}

#[derive(Default)]
struct CameraQueue {
    pending: VecDeque<Arc<IngestedFrame>>,
    /// Stamps already seen (recent ones, to refuse duplicates).
    recent_stamps: VecDeque<i64>,
    latest: Option<Arc<IngestedFrame>>,
}

/// The buffer (kept behind a mutex in the app state).
pub struct IngestBuffer {
    window_ns: i64,
    max_pending: usize,
    newest_ns: Option<i64>,
    cameras: BTreeMap<String, CameraQueue>,
    odometry: VecDeque<OdometryMsg>,
}

impl IngestBuffer {
    pub fn new(window_ns: i64, max_pending: usize) -> Self {
        Self {
            window_ns,
            max_pending: max_pending.max(1),
            newest_ns: None,
            cameras: BTreeMap::new(),
            odometry: VecDeque::new(),
        }
    }

    pub fn window_ns(&self) -> i64 {
        self.window_ns
    }

    /// Accepts a frame; returns how many waiting frames were dropped to make room.
    pub fn push_frame(&mut self, frame: IngestedFrame) -> Result<usize, IngestError> {
        if let Some(newest) = self.newest_ns
            && frame.stamp_ns < newest - self.window_ns
        {
            return Err(IngestError::TooOld {
                stamp_ns: frame.stamp_ns,
                newest_ns: newest,
                behind_ms: (newest - frame.stamp_ns) as f64 * 1e-6,
                window_ms: self.window_ns as f64 * 1e-6,
            });
        }
        let q = self.cameras.entry(frame.camera.clone()).or_default();
        if q.recent_stamps.contains(&frame.stamp_ns) {
            return Err(IngestError::Duplicate {
                camera: frame.camera.clone(),
                stamp_ns: frame.stamp_ns,
            });
        }
        q.recent_stamps.push_back(frame.stamp_ns);
        if q.recent_stamps.len() > 64 {
            q.recent_stamps.pop_front();
        }
        self.newest_ns = Some(self.newest_ns.map_or(frame.stamp_ns, |n| n.max(frame.stamp_ns)));
        let frame = Arc::new(frame);
        if q.latest.as_ref().is_none_or(|l| l.stamp_ns < frame.stamp_ns) {
            q.latest = Some(frame.clone());
        }
        let pos = q.pending.partition_point(|f| f.stamp_ns < frame.stamp_ns);
        q.pending.insert(pos, frame);
        let mut dropped = 0;
        while q.pending.len() > self.max_pending {
            q.pending.pop_front();
            dropped += 1;
        }
        Ok(dropped)
    }

    /// Frames waiting for the tracker (the queue depth).
    pub fn pending(&self) -> usize {
        self.cameras.values().map(|q| q.pending.len()).sum()
    }

    /// The newest frame received from a camera.
    pub fn latest(&self, camera: &str) -> Option<Arc<IngestedFrame>> {
        self.cameras.get(camera).and_then(|q| q.latest.clone())
    }

    pub fn newest_ns(&self) -> Option<i64> {
        self.newest_ns
    }

    /// Takes each camera's newest waiting frame within the window (`None` when nothing waits).
    pub fn take_fusion_set(&mut self) -> Option<FusionSet> {
        let newest = self.newest_ns?;
        let mut frames = Vec::new();
        let mut superseded = 0;
        for q in self.cameras.values_mut() {
            if let Some(f) = q.pending.pop_back() {
                superseded += q.pending.len();
                q.pending.clear();
                if f.stamp_ns >= newest - self.window_ns {
                    frames.push(f);
                } else {
                    superseded += 1;
                }
            }
        }
        if frames.is_empty() && superseded == 0 {
            return None;
        }
        Some(FusionSet { frames, superseded })
    }

    /// Accepts an odometry message (time-sorted insert; bounded).
    pub fn push_odometry(&mut self, msg: OdometryMsg) -> Result<(), IngestError> {
        if let Some(last) = self.odometry.back()
            && msg.stamp_ns < last.stamp_ns - self.window_ns
        {
            return Err(IngestError::OdometryTooOld {
                stamp_ns: msg.stamp_ns,
                newest_ns: last.stamp_ns,
            });
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
        Ok(())
    }

    /// Odometry at `stamp_ns`: interpolated between the two samples around it, or the nearest
    /// sample when `stamp_ns` lies outside but within the window; `None` otherwise.
    pub fn odometry_at(&self, stamp_ns: i64) -> Option<OdometryMsg> {
        let pos = self.odometry.partition_point(|m| m.stamp_ns <= stamp_ns);
        let before = pos.checked_sub(1).and_then(|i| self.odometry.get(i));
        let after = self.odometry.get(pos);
        match (before, after) {
            (Some(a), Some(b)) if b.stamp_ns > a.stamp_ns => {
                let t = (stamp_ns - a.stamp_ns) as f64 / (b.stamp_ns - a.stamp_ns) as f64;
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
            (Some(a), _) if stamp_ns - a.stamp_ns <= self.window_ns => Some(a.clone()),
            (None, Some(b)) if b.stamp_ns - stamp_ns <= self.window_ns => Some(b.clone()),
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
            camera: camera.into(),
            stamp_ns,
            depth: DepthImage::zeros(2, 2),
            color: None,
            detections: vec![],
            received: Instant::now(),
        }
    }

    const MS: i64 = 1_000_000;

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
            dropped += b.push_frame(frame("a", i * 10 * MS)).unwrap();
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
