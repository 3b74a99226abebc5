//! What the sensors deliver: camera frames with their detections, camera mounts and the
//! robot's odometry. Below the tracker, so that `dataset` and `generate` need no filter.

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::geometry::Pose;
use serde::{Deserialize, Serialize};

/// A 2-D detection of one object model in one image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Detection {
    /// Name of the object model.
    pub object: String,
    /// `[x, y, width, height]` in pixels, counted as BOP's `bbox_visib`: the box covers pixel
    /// columns `x .. x + width` and rows `y .. y + height`.
    pub bbox_xywh_px: [f64; 4],
    pub score: f64,
}

impl Detection {
    /// The box's centre in pixel coordinates (pixel (0, 0) centred at (0, 0)): the box covers
    /// pixel columns `x .. x + width`, so its centre is at `x + width / 2 - 0.5`.
    pub fn centre_px(&self) -> [f64; 2] {
        let [x, y, w, h] = self.bbox_xywh_px;
        [x + w / 2.0 - 0.5, y + h / 2.0 - 0.5]
    }
}

/// One camera's frame at one time.
#[derive(Debug, Clone)]
pub struct CameraFrame {
    pub camera: String,
    pub stamp_ns: i64,
    pub intrinsics: Intrinsics,
    pub depth: DepthImage,
    pub color: Option<ColorImage>,
    pub detections: Vec<Detection>,
}

/// How a camera is mounted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum CameraMount {
    Stationary { world_from_camera: Pose },
    Robot { base_from_camera: Pose },
}

/// Odometry of the robot at one time (the robot camera's pose is
/// `world_from_odom * odom_from_base * base_from_camera`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RobotOdometry {
    pub stamp_ns: i64,
    pub odom_from_base: Pose,
    pub world_from_odom: Pose,
    pub base_from_camera: Pose,
}
