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
#[serde(deny_unknown_fields)]
pub struct PoseDto {
    pub rotation_xyzw: [f64; 4],
    pub translation_m: [f64; 3],
}

/// Farthest position accepted anywhere (poses, planes), metres from the frame's origin.
pub const MAX_POSITION_M: f64 = 1_000.0;

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

/// At most 64 characters of `s` for an error message (a client's string is not echoed whole).
pub fn shorten(s: &str) -> String {
    let mut out: String = s.chars().take(64).filter(|c| !c.is_control()).collect();
    if s.chars().count() > 64 {
        out.push_str("...");
    }
    out
}

/// Checks a display name: at most `max_chars` characters, no control characters.
pub fn check_name(name: &str, max_chars: usize) -> Result<(), ApiError> {
    if name.chars().count() > max_chars || name.chars().any(char::is_control) {
        return Err(ApiError::Invalid(format!(
            "name '{}' must be at most {max_chars} characters without control characters",
            shorten(name)
        )));
    }
    Ok(())
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
            "{kind} id '{}' must be 1-64 characters of A-Z, a-z, 0-9, '_', '-', '.'",
            shorten(id)
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
