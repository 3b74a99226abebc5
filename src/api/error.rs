//! The one error type of the HTTP service. Every failure becomes an RFC 9457 problem document
//! (`application/problem+json`); this file is the only place where HTTP status codes appear.

use crate::grasp::GraspError;
use crate::service::ServiceError;
use axum::extract::multipart::{MultipartError, MultipartRejection};
use axum::extract::rejection::{BytesRejection, JsonRejection, PathRejection, QueryRejection};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// RFC 9457 problem details.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Problem {
    /// A URI naming the kind of problem (`urn:pregrasp:problem:<kind>`).
    #[serde(rename = "type")]
    pub type_uri: String,
    /// Short summary of the kind of problem.
    pub title: String,
    /// The HTTP status code.
    pub status: u16,
    /// What went wrong with this request and what to do about it.
    pub detail: String,
}

/// Every way a request can fail.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The body could not be parsed (malformed JSON, bad base64, undecodable image).
    #[error("{0}")]
    Malformed(String),
    /// The body parsed but its values are not acceptable (NaN, non-unit quaternion, size mismatch).
    #[error("{0}")]
    Invalid(String),
    #[error("{kind} '{id}' does not exist")]
    NotFound { kind: &'static str, id: String },
    /// The request conflicts with the current state (duplicate, in use).
    #[error("{0}")]
    Conflict(String),
    /// A frame older than the fixed-lag window (or a duplicate stamp): refused and counted.
    #[error("{0}")]
    Stale(String),
    #[error(
        "this request changes state and needs 'Authorization: Bearer <token>' (the server's --token or PREGRASP_TOKEN)"
    )]
    Unauthorized,
    #[error("request body is larger than the limit of {limit_bytes} bytes")]
    TooLarge { limit_bytes: usize },
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// The resource exists but cannot answer yet (codebook still building, track initialising).
    #[error("{0}")]
    NotReady(String),
    /// The ingest queue is full and the request cannot be taken (back-pressure).
    #[error("{0}")]
    Busy(String),
    /// A camera exists but has sent no frame (or no colour image) yet.
    #[error("{0}")]
    NoFrameYet(String),
    /// A configured cap (cameras, objects, tracks, ...) would be exceeded.
    #[error("{0}")]
    LimitReached(String),
    /// The route exists but not with this method; `allow` lists the methods it takes.
    #[error("method not allowed on this route (allowed: {allow})")]
    MethodNotAllowed { allow: String },
    /// The route is switched off in this server's configuration.
    #[error("{0}")]
    Disabled(String),
    /// The request's Host header names none of the server's allowed hosts.
    #[error("host '{0}' is not one of this server's names (see --allowed-host)")]
    MisdirectedHost(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl ApiError {
    pub fn internal(e: impl std::fmt::Display) -> Self {
        Self::Internal(e.to_string())
    }
    pub fn not_found(kind: &'static str, id: impl Into<String>) -> Self {
        Self::NotFound { kind, id: id.into() }
    }

    fn parts(&self) -> (StatusCode, &'static str, &'static str) {
        match self {
            Self::Malformed(_) => (StatusCode::BAD_REQUEST, "malformed", "Malformed request"),
            Self::Invalid(_) => (StatusCode::UNPROCESSABLE_ENTITY, "invalid", "Invalid value"),
            Self::NotFound { .. } => (StatusCode::NOT_FOUND, "not-found", "Not found"),
            Self::Conflict(_) => (StatusCode::CONFLICT, "conflict", "Conflict"),
            Self::Stale(_) => (StatusCode::CONFLICT, "stale-frame", "Frame outside the time window"),
            Self::Unauthorized => (StatusCode::UNAUTHORIZED, "unauthorized", "Unauthorized"),
            Self::TooLarge { .. } => (StatusCode::PAYLOAD_TOO_LARGE, "too-large", "Body too large"),
            Self::UnsupportedMediaType(_) => (
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "unsupported-media-type",
                "Unsupported media type",
            ),
            Self::NotReady(_) => (StatusCode::SERVICE_UNAVAILABLE, "not-ready", "Not ready yet"),
            Self::Busy(_) => (StatusCode::TOO_MANY_REQUESTS, "busy", "Ingest queue full"),
            Self::NoFrameYet(_) => (StatusCode::NOT_FOUND, "no-frame-yet", "No frame yet"),
            Self::LimitReached(_) => (StatusCode::CONFLICT, "limit-reached", "Limit reached"),
            Self::MethodNotAllowed { .. } => (
                StatusCode::METHOD_NOT_ALLOWED,
                "method-not-allowed",
                "Method not allowed",
            ),
            Self::Disabled(_) => (StatusCode::FORBIDDEN, "disabled", "Disabled"),
            Self::MisdirectedHost(_) => (StatusCode::MISDIRECTED_REQUEST, "misdirected", "Unknown host"),
            Self::Internal(_) => (StatusCode::INTERNAL_SERVER_ERROR, "internal", "Internal error"),
        }
    }

    /// The problem document this error is answered with.
    pub fn problem(&self) -> Problem {
        let (status, kind, title) = self.parts();
        Problem {
            type_uri: format!("urn:pregrasp:problem:{kind}"),
            title: title.to_string(),
            status: status.as_u16(),
            detail: self.to_string(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, _, _) = self.parts();
        // only a fault of the server is an error of the server's log: a 503 (not ready yet)
        // is an ordinary answer and any client can provoke it
        if matches!(self, Self::Internal(_)) {
            tracing::error!("{self}");
        }
        let body = serde_json::to_vec(&self.problem()).unwrap_or_default();
        let mut resp = (status, [(header::CONTENT_TYPE, "application/problem+json")], body).into_response();
        if let Self::MethodNotAllowed { allow } = &self
            && let Ok(v) = header::HeaderValue::from_str(allow)
        {
            resp.headers_mut().insert(header::ALLOW, v);
        }
        if let Self::Unauthorized = &self {
            resp.headers_mut()
                .insert(header::WWW_AUTHENTICATE, header::HeaderValue::from_static("Bearer"));
        }
        resp
    }
}

/// The body-size limit applied to every request (see `ApiConfig::max_body_bytes`); kept here
/// so that rejections can name it.
pub(crate) static BODY_LIMIT_BYTES: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

fn too_large() -> ApiError {
    ApiError::TooLarge {
        limit_bytes: BODY_LIMIT_BYTES.load(std::sync::atomic::Ordering::Relaxed),
    }
}

impl From<BytesRejection> for ApiError {
    fn from(r: BytesRejection) -> Self {
        if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
            too_large()
        } else {
            Self::Malformed(r.body_text())
        }
    }
}

impl From<JsonRejection> for ApiError {
    fn from(r: JsonRejection) -> Self {
        match r {
            JsonRejection::MissingJsonContentType(_) => {
                Self::UnsupportedMediaType("expected 'Content-Type: application/json'".to_string())
            }
            JsonRejection::JsonDataError(e) => Self::Invalid(e.body_text()),
            JsonRejection::JsonSyntaxError(e) => Self::Malformed(e.body_text()),
            JsonRejection::BytesRejection(e) => e.into(),
            other => {
                if other.status() == StatusCode::PAYLOAD_TOO_LARGE {
                    too_large()
                } else {
                    Self::Malformed(other.body_text())
                }
            }
        }
    }
}

impl From<MultipartError> for ApiError {
    fn from(e: MultipartError) -> Self {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            too_large()
        } else {
            Self::Malformed(e.body_text())
        }
    }
}

impl From<MultipartRejection> for ApiError {
    fn from(e: MultipartRejection) -> Self {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            too_large()
        } else {
            Self::Malformed(e.body_text())
        }
    }
}

impl From<PathRejection> for ApiError {
    fn from(r: PathRejection) -> Self {
        Self::Malformed(r.body_text())
    }
}

impl From<QueryRejection> for ApiError {
    fn from(r: QueryRejection) -> Self {
        Self::Malformed(r.body_text())
    }
}

/// The service's errors, each once into the answer it is: the status of every service and
/// grasp failure is chosen here.
impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        match e {
            ServiceError::Invalid(m) => Self::Invalid(m),
            ServiceError::NotFound { kind, id } => Self::NotFound { kind, id },
            ServiceError::Conflict(m) => Self::Conflict(m),
            ServiceError::Stale(m) => Self::Stale(m),
            ServiceError::NotReady(m) => Self::NotReady(m),
            ServiceError::NoFrameYet(m) => Self::NoFrameYet(m),
            ServiceError::LimitReached(m) => Self::LimitReached(m),
            ServiceError::Disabled(m) => Self::Disabled(m),
            ServiceError::Internal(m) => Self::Internal(m),
            ServiceError::Grasp(g) => {
                let detail = format!("decision: {g}");
                match g {
                    // the caller's query or gripper: an invalid value (422)
                    GraspError::InvalidGripper(_) | GraspError::GripperJson(_) | GraspError::InvalidQuery(_) => {
                        Self::Invalid(detail)
                    }
                    // the registered object and gripper cannot make a grasp: a conflict with
                    // what is registered (409), not a malformed request
                    GraspError::InvalidMesh(_) | GraspError::NoCandidate(_) => Self::Conflict(detail),
                    // the track has no samples to decide on yet (503)
                    GraspError::NoSamples => Self::NotReady(detail),
                    // a geometry query parry3d cannot answer, a file on the server: our fault
                    GraspError::Unsupported(_) | GraspError::GripperFile { .. } => Self::Internal(detail),
                    // the server's calibration map is broken or stale: our fault (the service
                    // falls back to the raw rate before it gets here)
                    GraspError::Calibration(_) | GraspError::StaleCalibration { .. } => Self::Internal(detail),
                }
            }
        }
    }
}

/// The answer to a successful DELETE (204, no body).
pub struct Deleted;

impl IntoResponse for Deleted {
    fn into_response(self) -> Response {
        StatusCode::NO_CONTENT.into_response()
    }
}

/// A new resource (201 with its JSON).
pub struct Created<T>(pub T);

impl<T: Serialize> IntoResponse for Created<T> {
    fn into_response(self) -> Response {
        (StatusCode::CREATED, axum::Json(self.0)).into_response()
    }
}

/// The answer to a request that was taken for later processing (202 with a JSON body).
pub struct Accepted<T>(pub T);

impl<T: Serialize> IntoResponse for Accepted<T> {
    fn into_response(self) -> Response {
        (StatusCode::ACCEPTED, axum::Json(self.0)).into_response()
    }
}

/// Maps a response produced outside our handlers (e.g. a body limit layer's 413, the router's
/// 405 with its `Allow` header) to a problem document; used by a middleware in `mod.rs`.
pub(crate) fn response_to_problem(resp: &Response) -> Option<ApiError> {
    match resp.status() {
        StatusCode::PAYLOAD_TOO_LARGE => Some(too_large()),
        StatusCode::METHOD_NOT_ALLOWED => Some(ApiError::MethodNotAllowed {
            allow: resp
                .headers()
                .get(header::ALLOW)
                .and_then(|v| v.to_str().ok())
                .unwrap_or("")
                .to_string(),
        }),
        StatusCode::UNSUPPORTED_MEDIA_TYPE => Some(ApiError::UnsupportedMediaType("unsupported content type".into())),
        StatusCode::NOT_FOUND => Some(ApiError::NotFound {
            kind: "route",
            id: String::new(),
        }),
        s if s.is_client_error() => Some(ApiError::Malformed(format!("request refused ({s})"))),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_service_and_grasp_error_has_its_status() {
        let status = |e: ServiceError| ApiError::from(e).problem().status;
        assert_eq!(status(ServiceError::not_found("track", "7")), 404);
        assert_eq!(status(ServiceError::Invalid("x".into())), 422);
        assert_eq!(status(ServiceError::Stale("x".into())), 409);
        assert_eq!(status(ServiceError::NotReady("x".into())), 503);
        assert_eq!(status(ServiceError::Grasp(GraspError::InvalidQuery("x".into()))), 422);
        assert_eq!(status(ServiceError::Grasp(GraspError::InvalidGripper("x".into()))), 422);
        assert_eq!(status(ServiceError::Grasp(GraspError::NoCandidate("x".into()))), 409);
        assert_eq!(status(ServiceError::Grasp(GraspError::InvalidMesh("x".into()))), 409);
        assert_eq!(status(ServiceError::Grasp(GraspError::NoSamples)), 503);
        assert_eq!(status(ServiceError::Grasp(GraspError::Unsupported("x".into()))), 500);
    }

    #[test]
    fn problem_documents_carry_status_and_detail() {
        let p = ApiError::not_found("camera", "ext9").problem();
        assert_eq!(p.status, 404);
        assert!(p.detail.contains("ext9"));
        assert_eq!(ApiError::Stale("old".into()).problem().status, 409);
        assert_eq!(ApiError::TooLarge { limit_bytes: 5 }.problem().status, 413);
    }
}
