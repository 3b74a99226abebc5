//! Wire types shared by several resources (the HTTP layer's DTOs of domain types, each
//! converted once at the edge) and the JSON extractor whose rejections are problem documents.

use super::error::ApiError;
use crate::camera::Intrinsics;
use crate::geometry::{Pose, PoseXyzw};
use axum::extract::{FromRequest, Request};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// A rigid transform `target_from_source`: translation in metres, quaternion `[x, y, z, w]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PoseDto {
    pub rotation_xyzw: [f64; 4],
    pub translation_m: [f64; 3],
}

pub use crate::service::checks::MAX_POSITION_M;

impl PoseDto {
    /// Validates (finite numbers, unit quaternion, a position within [`MAX_POSITION_M`]) into a
    /// [`Pose`]; `what` names the field.
    pub fn to_pose(&self, what: &str) -> Result<Pose, ApiError> {
        let t = self.translation_m;
        if t.iter().all(|v| v.is_finite()) && nalgebra::Vector3::from(t).norm() > MAX_POSITION_M {
            return Err(ApiError::Invalid(format!(
                "{what}: translation {t:?} is farther than {MAX_POSITION_M} m from the origin"
            )));
        }
        PoseXyzw {
            rotation_xyzw: self.rotation_xyzw,
            translation_m: self.translation_m,
        }
        .to_pose()
        .map_err(|e| ApiError::Invalid(format!("{what}: {e}")))
    }
    pub fn from_pose(p: &Pose) -> Self {
        let x = PoseXyzw::from_pose(p);
        Self {
            rotation_xyzw: x.rotation_xyzw,
            translation_m: x.translation_m,
        }
    }
    pub fn identity() -> Self {
        Self::from_pose(&Pose::identity())
    }
}

/// Pinhole intrinsics like ROS `sensor_msgs/CameraInfo` (`k` row-major 3x3; `d` must be empty
/// or zero: rectify first).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsDto {
    pub width: u32,
    pub height: u32,
    pub k: [f64; 9],
}

impl IntrinsicsDto {
    pub fn to_intrinsics(&self) -> Result<Intrinsics, ApiError> {
        Intrinsics::new(self.width, self.height, self.k).map_err(|e| ApiError::Invalid(format!("intrinsics: {e}")))
    }
    pub fn from_intrinsics(i: &Intrinsics) -> Self {
        Self {
            width: i.width,
            height: i.height,
            k: i.k,
        }
    }
}

/// A 2-D detection of an object in one image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DetectionDto {
    /// The object's id (as registered under `/objects`).
    pub object: String,
    /// Box `[x, y, width, height]` in pixels.
    pub bbox_xywh_px: [f64; 4],
    pub score: f64,
}

impl From<DetectionDto> for crate::sensor::Detection {
    fn from(d: DetectionDto) -> Self {
        Self {
            object: d.object,
            bbox_xywh_px: d.bbox_xywh_px,
            score: d.score,
        }
    }
}

pub use crate::service::checks::{check_id, check_name, shorten};

/// `Json<T>` whose rejections are problem documents.
pub struct ApiJson<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;
    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let axum::Json(v) = axum::Json::<T>::from_request(req, state).await?;
        Ok(Self(v))
    }
}
