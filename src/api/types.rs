//! Wire types shared by several resources (the HTTP layer's DTOs of domain types) and the JSON
//! extractor whose rejections are problem documents.

use super::error::ApiError;
use crate::camera::Intrinsics;
use crate::geometry::{Pose, PoseXyzw};
use axum::extract::{FromRequest, Request};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// A rigid transform `target_from_source`: translation in metres, quaternion `[x, y, z, w]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct PoseDto {
    pub rotation_xyzw: [f64; 4],
    pub translation_m: [f64; 3],
}

impl PoseDto {
    /// Validates (finite numbers, unit quaternion) into a [`Pose`]; `what` names the field.
    pub fn to_pose(&self, what: &str) -> Result<Pose, ApiError> {
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
pub struct DetectionDto {
    /// The object's id (as registered under `/objects`).
    pub object: String,
    /// Box `[x, y, width, height]` in pixels.
    pub bbox_xywh_px: [f64; 4],
    pub score: f64,
}

/// Checks that an id is usable in a URL path and as a store key.
pub fn check_id(kind: &str, id: &str) -> Result<(), ApiError> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '.');
    if ok {
        Ok(())
    } else {
        Err(ApiError::Invalid(format!(
            "{kind} id '{id}' must be 1-64 characters of A-Z, a-z, 0-9, '_', '-', '.'"
        )))
    }
}

/// `Json<T>` whose rejections are problem documents.
pub struct ApiJson<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;
    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let axum::Json(v) = axum::Json::<T>::from_request(req, state).await?;
        Ok(Self(v))
    }
}
