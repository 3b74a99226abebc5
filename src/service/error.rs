//! The one error type of the service. It names what went wrong, not how a transport answers
//! it: `api::error` maps each variant (and each grasp error) to an HTTP status.

use crate::grasp::GraspError;

/// Every way a service call can fail.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A value is not acceptable (an id, a name, a box outside the image, a prior's spread).
    #[error("{0}")]
    Invalid(String),
    #[error("{kind} '{id}' does not exist")]
    NotFound { kind: &'static str, id: String },
    /// The call conflicts with the current state (a second robot camera, no cameras yet).
    #[error("{0}")]
    Conflict(String),
    /// A frame or odometry message older than the fixed-lag window (or a repeated stamp).
    #[error("{0}")]
    Stale(String),
    /// The resource exists but cannot answer yet (codebook still building, no estimate yet).
    #[error("{0}")]
    NotReady(String),
    /// A camera exists but has sent no frame (or no colour image) yet.
    #[error("{0}")]
    NoFrameYet(String),
    /// A configured cap (cameras, objects, tracks, ...) would be exceeded.
    #[error("{0}")]
    LimitReached(String),
    /// The call is switched off in this server's configuration (ground truth).
    #[error("{0}")]
    Disabled(String),
    /// The grasp decision failed (bad query, a gripper that fits no grasp, ...).
    #[error("decision: {0}")]
    Grasp(#[from] GraspError),
    #[error("internal error: {0}")]
    Internal(String),
}

impl ServiceError {
    pub fn internal(e: impl std::fmt::Display) -> Self {
        Self::Internal(e.to_string())
    }
    pub fn not_found(kind: &'static str, id: impl Into<String>) -> Self {
        Self::NotFound { kind, id: id.into() }
    }
}

impl From<redb::Error> for ServiceError {
    fn from(e: redb::Error) -> Self {
        Self::Internal(format!("store: {e}"))
    }
}
