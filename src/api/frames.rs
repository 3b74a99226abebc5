//! Frame and odometry ingest, and each camera's latest images.
//!
//! `POST /cameras/{id}/frames` takes one camera image, either as JSON with base64 payloads or as
//! `multipart/form-data` with a `meta` part (the same JSON without the payloads) and `depth`
//! (and optionally `color`) file parts. Depth: a 16-bit grayscale PNG with `depth_scale`
//! (millimetres per unit, as in BOP: `depth_mm = value * depth_scale`), or raw 32-bit float
//! little-endian metres (`encoding = "f32le"`). Colour: PNG or JPEG. Sizes must match the
//! camera's intrinsics.

use super::AppState;
use super::error::{Accepted, ApiError};
use super::types::{ApiJson, DetectionDto, IntrinsicsDto, PoseDto};
use crate::camera::{ColorImage, DepthImage};
use crate::sensor::{CameraFrame, Detection};
use crate::service::ingest::{FrameReceipt, IngestedFrame, OdometryMsg, check_stamp};
use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::header;
use axum::response::IntoResponse;
use base64::Engine;
use serde::{Deserialize, Serialize};
use std::time::Instant;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// How the depth bytes are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum DepthEncoding {
    /// 16-bit grayscale PNG; `depth_mm = value * depth_scale`.
    #[default]
    Png16,
    /// Raw 32-bit float, little-endian, metres, row-major (width x height values).
    F32le,
}

/// Depth payload in a JSON frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct DepthPayload {
    #[serde(default)]
    pub encoding: DepthEncoding,
    /// Millimetres per PNG unit (BOP's `depth_scale`, default 1).
    pub depth_scale: Option<f64>,
    pub data_base64: String,
}

/// Colour payload in a JSON frame (PNG or JPEG).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct ColorPayload {
    pub data_base64: String,
}

/// One camera frame, JSON form.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameJson {
    /// Capture time, nanoseconds.
    pub stamp_ns: i64,
    pub depth: DepthPayload,
    pub color: Option<ColorPayload>,
    #[serde(default)]
    pub detections: Vec<DetectionDto>,
}

/// The `meta` part of a multipart frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameMeta {
    pub stamp_ns: i64,
    #[serde(default)]
    pub depth_encoding: DepthEncoding,
    pub depth_scale: Option<f64>,
    #[serde(default)]
    pub detections: Vec<DetectionDto>,
}

/// The answer to an accepted frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct FrameAccepted {
    pub camera: String,
    pub stamp_ns: i64,
    /// Frames waiting for the tracker after this one.
    pub queue_depth: usize,
    /// Waiting frames of this camera dropped to make room (drop-oldest policy).
    pub dropped: usize,
}

impl From<FrameReceipt> for FrameAccepted {
    fn from(r: FrameReceipt) -> Self {
        Self {
            camera: r.camera,
            stamp_ns: r.stamp_ns,
            queue_depth: r.queue_depth,
            dropped: r.dropped,
        }
    }
}

/// The answer to an accepted odometry message or ground truth.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct StampAccepted {
    pub stamp_ns: i64,
}

/// An odometry message like ROS `nav_msgs/Odometry` plus localisation.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct OdometryIn {
    pub stamp_ns: i64,
    /// `odom_from_base` with an optional row-major 6x6 covariance (x, y, z, rx, ry, rz).
    pub odom_from_base: PoseWithCovarianceDto,
    /// REP-105 `map -> odom` from the robot's localisation (default: identity).
    pub world_from_odom: Option<PoseDto>,
    /// Current `base_from_camera` of the robot camera (the arm moves it); default: as registered.
    pub base_from_camera: Option<PoseDto>,
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PoseWithCovarianceDto {
    pub pose: PoseDto,
    pub covariance: Option<Vec<f64>>,
}

/// The newest frame of a camera.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct LatestFrame {
    pub camera: String,
    pub stamp_ns: i64,
    pub detections: Vec<DetectionDto>,
    pub has_color: bool,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(post_frame))
        .routes(routes!(post_odometry))
        .routes(routes!(get_latest))
        .routes(routes!(get_latest_depth_png))
        .routes(routes!(get_latest_color_png))
}

fn decode_b64(what: &str, s: &str) -> Result<Vec<u8>, ApiError> {
    base64::engine::general_purpose::STANDARD
        .decode(s.trim())
        .map_err(|e| ApiError::Malformed(format!("{what}: not valid base64 ({e})")))
}

/// Largest depth accepted, metres (beyond it a reading is not a measurement).
pub const MAX_DEPTH_M: f64 = 1_000.0;

/// Largest `depth_scale` (millimetres per PNG unit): the largest 16-bit value stays within
/// [`MAX_DEPTH_M`].
pub const MAX_DEPTH_SCALE: f64 = MAX_DEPTH_M * 1000.0 / u16::MAX as f64;

/// Decoder allocations allowed beyond the pixels themselves (PNG/JPEG row buffers, tables).
const DECODER_SLACK_BYTES: u64 = 4 * 1024 * 1024;

/// Reads an image's size from its header (no decoding) and checks it against the camera's
/// intrinsics; then decodes with a memory limit of the expected pixels plus a small slack.
fn decode_checked(
    what: &str,
    bytes: &[u8],
    format: Option<image::ImageFormat>,
    bytes_per_px: u64,
    intr: &IntrinsicsDto,
) -> Result<image::DynamicImage, ApiError> {
    let reader = || -> Result<image::ImageReader<std::io::Cursor<&[u8]>>, ApiError> {
        let cursor = std::io::Cursor::new(bytes);
        match format {
            Some(f) => Ok(image::ImageReader::with_format(cursor, f)),
            None => image::ImageReader::new(cursor)
                .with_guessed_format()
                .map_err(|e| ApiError::Malformed(format!("{what}: {e}"))),
        }
    };
    let (w, h) = reader()?
        .into_dimensions()
        .map_err(|e| ApiError::Malformed(format!("{what} is not a readable image: {e}")))?;
    if (w, h) != (intr.width, intr.height) {
        return Err(ApiError::Invalid(format!(
            "{what} image is {w}x{h}, but the camera's intrinsics are {}x{}",
            intr.width, intr.height
        )));
    }
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(intr.width);
    limits.max_image_height = Some(intr.height);
    limits.max_alloc = Some(u64::from(w) * u64::from(h) * bytes_per_px + DECODER_SLACK_BYTES);
    let mut r = reader()?;
    r.limits(limits);
    r.decode()
        .map_err(|e| ApiError::Malformed(format!("{what} is not a readable image: {e}")))
}

/// Decodes a depth payload and checks it against the camera's size (before decoding) and
/// range (finite, at most [`MAX_DEPTH_M`]).
pub fn decode_depth(
    bytes: &[u8],
    encoding: DepthEncoding,
    depth_scale: Option<f64>,
    intr: &IntrinsicsDto,
) -> Result<DepthImage, ApiError> {
    let (w, h) = (intr.width, intr.height);
    match encoding {
        DepthEncoding::F32le => {
            let expected = w as usize * h as usize * 4;
            if bytes.len() != expected {
                return Err(ApiError::Invalid(format!(
                    "raw f32 depth has {} bytes; the camera is {w}x{h}, so {expected} bytes are expected",
                    bytes.len()
                )));
            }
            let data: Vec<f32> = bytes
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            if let Some(i) = data.iter().position(|v| f64::from(*v) > MAX_DEPTH_M) {
                return Err(ApiError::Invalid(format!(
                    "depth value {} m at index {i} is beyond {MAX_DEPTH_M} m",
                    data[i]
                )));
            }
            DepthImage::new(w, h, data).map_err(|e| ApiError::Invalid(format!("depth: {e}")))
        }
        DepthEncoding::Png16 => {
            let scale = depth_scale.unwrap_or(1.0);
            if !(scale.is_finite() && scale > 0.0 && scale <= MAX_DEPTH_SCALE) {
                return Err(ApiError::Invalid(format!(
                    "depth_scale (millimetres per unit) must be in (0, {MAX_DEPTH_SCALE:.2}] so that depth stays within {MAX_DEPTH_M} m, got {scale}"
                )));
            }
            let img = decode_checked("depth", bytes, Some(image::ImageFormat::Png), 2, intr)?;
            let image::DynamicImage::ImageLuma16(img) = img else {
                return Err(ApiError::Invalid(format!(
                    "depth PNG must be 16-bit grayscale, got {:?}",
                    img.color()
                )));
            };
            DepthImage::from_u16_mm(w, h, img.as_raw(), scale).map_err(|e| ApiError::Invalid(format!("depth: {e}")))
        }
    }
}

/// Decodes a PNG/JPEG colour image, its size checked against the camera's before decoding.
pub fn decode_color(bytes: &[u8], intr: &IntrinsicsDto) -> Result<ColorImage, ApiError> {
    // at most 16-bit RGBA while decoding
    let img = decode_checked("color", bytes, None, 8, intr)?.to_rgb8();
    let (w, h) = (img.width(), img.height());
    let data = img.into_raw().chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    ColorImage::new(w, h, data).map_err(|e| ApiError::Invalid(format!("color: {e}")))
}

/// Checks a stamp at the edge (see [`crate::service::ingest::MAX_STAMP_NS`]).
pub fn validate_stamp(what: &str, stamp_ns: i64) -> Result<(), ApiError> {
    check_stamp(stamp_ns).map_err(|e| ApiError::Invalid(format!("{what}: {e}")))
}

#[utoipa::path(post, path = "/cameras/{id}/frames", tag = "ingest",
    params(("id" = String, Path, description = "Camera id")),
    request_body(content((FrameJson = "application/json"), (FrameMeta = "multipart/form-data")),
        description = "JSON with base64 payloads, or multipart with parts 'meta' (JSON), 'depth', 'color'"),
    responses((status = 202, body = FrameAccepted),
        (status = 400, body = super::error::Problem), (status = 404, body = super::error::Problem),
        (status = 409, description = "Older than the window or a duplicate stamp; counted, not applied", body = super::error::Problem),
        (status = 413, body = super::error::Problem), (status = 415, body = super::error::Problem),
        (status = 422, body = super::error::Problem)))]
async fn post_frame(
    State(state): State<AppState>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Accepted<FrameAccepted>, ApiError> {
    let received = Instant::now();
    let intrinsics = state
        .registry()
        .cameras
        .get(&id)
        .map(|c| c.intrinsics)
        .ok_or_else(|| ApiError::not_found("camera", id.clone()))?;
    let intr = IntrinsicsDto::from_intrinsics(&intrinsics);
    let ct = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let (stamp_ns, depth_bytes, encoding, scale, color_bytes, detections) = if ct.starts_with("application/json") {
        let ApiJson(f) = ApiJson::<FrameJson>::from_request(req, &state).await?;
        let depth = decode_b64("depth.data_base64", &f.depth.data_base64)?;
        let color = f
            .color
            .map(|c| decode_b64("color.data_base64", &c.data_base64))
            .transpose()?;
        (
            f.stamp_ns,
            depth,
            f.depth.encoding,
            f.depth.depth_scale,
            color,
            f.detections,
        )
    } else if ct.starts_with("multipart/form-data") {
        let mut mp = Multipart::from_request(req, &state).await?;
        let (mut meta, mut depth, mut color) = (None, None, None);
        while let Some(field) = mp.next_field().await? {
            let name = field.name().unwrap_or("").to_string();
            let bytes: Bytes = field.bytes().await?;
            match name.as_str() {
                "meta" => {
                    meta = Some(
                        serde_json::from_slice::<FrameMeta>(&bytes)
                            .map_err(|e| ApiError::Malformed(format!("meta part: {e}")))?,
                    )
                }
                "depth" => depth = Some(bytes.to_vec()),
                "color" => color = Some(bytes.to_vec()),
                other => return Err(ApiError::Malformed(format!("unexpected multipart part '{other}'"))),
            }
        }
        let meta = meta.ok_or_else(|| ApiError::Malformed("multipart frame needs a 'meta' part".into()))?;
        let depth = depth.ok_or_else(|| ApiError::Malformed("multipart frame needs a 'depth' part".into()))?;
        (
            meta.stamp_ns,
            depth,
            meta.depth_encoding,
            meta.depth_scale,
            color,
            meta.detections,
        )
    } else {
        return Err(ApiError::UnsupportedMediaType(format!(
            "a frame is application/json (base64 payloads) or multipart/form-data, not '{ct}'"
        )));
    };
    validate_stamp("stamp_ns", stamp_ns)?;
    let detections: Vec<Detection> = detections.into_iter().map(Detection::from).collect();
    state.check_detections(&detections, intr.width, intr.height)?;
    let frame = tokio::task::spawn_blocking(move || -> Result<CameraFrame, ApiError> {
        let depth = decode_depth(&depth_bytes, encoding, scale, &intr)?;
        let color = color_bytes.map(|b| decode_color(&b, &intr)).transpose()?;
        Ok(CameraFrame {
            camera: id,
            stamp_ns,
            intrinsics,
            depth,
            color,
            detections,
        })
    })
    .await
    .map_err(ApiError::internal)??;
    Ok(Accepted(state.ingest_frame(frame, received)?.into()))
}

/// Largest magnitude of an odometry covariance entry (m^2, rad^2).
pub const MAX_COVARIANCE: f64 = 1e6;

/// Validates an odometry message into the buffer's form.
pub fn validate_odometry(o: &OdometryIn) -> Result<OdometryMsg, ApiError> {
    validate_stamp("stamp_ns", o.stamp_ns)?;
    let plausible =
        |c: &[f64]| c.iter().all(|v| v.is_finite() && v.abs() <= MAX_COVARIANCE) && (0..6).all(|i| c[i * 7] >= 0.0);
    let covariance = match &o.odom_from_base.covariance {
        None => None,
        Some(c) if c.len() == 36 && plausible(c) => {
            let mut a = [0.0; 36];
            a.copy_from_slice(c);
            Some(a)
        }
        Some(c) => {
            return Err(ApiError::Invalid(format!(
                "odom_from_base.covariance must be 36 numbers of magnitude at most {MAX_COVARIANCE:e} (row-major 6x6, variances >= 0), got {} values",
                c.len()
            )));
        }
    };
    Ok(OdometryMsg {
        stamp_ns: o.stamp_ns,
        odom_from_base: o.odom_from_base.pose.to_pose("odom_from_base.pose")?,
        covariance,
        world_from_odom: match &o.world_from_odom {
            Some(p) => p.to_pose("world_from_odom")?,
            None => crate::geometry::Pose::identity(),
        },
        base_from_camera: o.base_from_camera.map(|p| p.to_pose("base_from_camera")).transpose()?,
    })
}

#[utoipa::path(post, path = "/odometry", tag = "ingest",
    request_body = OdometryIn,
    responses((status = 202, description = "Accepted", body = StampAccepted),
        (status = 409, description = "Older than the window behind the newest odometry", body = super::error::Problem),
        (status = 422, body = super::error::Problem)))]
async fn post_odometry(
    State(state): State<AppState>,
    ApiJson(o): ApiJson<OdometryIn>,
) -> Result<Accepted<StampAccepted>, ApiError> {
    let msg = validate_odometry(&o)?;
    state.ingest_odometry(msg)?;
    Ok(Accepted(StampAccepted { stamp_ns: o.stamp_ns }))
}

fn latest(state: &AppState, id: &str) -> Result<std::sync::Arc<IngestedFrame>, ApiError> {
    if !state.registry().cameras.contains_key(id) {
        return Err(ApiError::not_found("camera", id));
    }
    state
        .ingest()
        .latest(id)
        .ok_or_else(|| ApiError::NoFrameYet(format!("camera '{id}' has sent no frame yet")))
}

#[utoipa::path(get, path = "/cameras/{id}/latest", tag = "ingest",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 200, body = LatestFrame),
        (status = 404, description = "No such camera, or it has sent no frame yet", body = super::error::Problem)))]
async fn get_latest(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<LatestFrame>, ApiError> {
    let f = latest(&state, &id)?;
    Ok(Json(LatestFrame {
        camera: id,
        stamp_ns: f.stamp_ns,
        detections: f
            .detections
            .iter()
            .map(|d| DetectionDto {
                object: d.object.clone(),
                bbox_xywh_px: d.bbox_xywh_px,
                score: d.score,
            })
            .collect(),
        has_color: f.color.is_some(),
    }))
}

fn png_response(img: image::RgbImage) -> Result<impl IntoResponse, ApiError> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .map_err(ApiError::internal)?;
    Ok((
        [(header::CONTENT_TYPE, "image/png"), (header::CACHE_CONTROL, "no-store")],
        out.into_inner(),
    ))
}

/// Colourises depth (near = warm, far = cool, no reading = black).
pub fn colourise_depth(d: &DepthImage) -> image::RgbImage {
    let valid: Vec<f32> = d.data_m.iter().copied().filter(|v| *v > 0.0).collect();
    let lo = valid.iter().copied().fold(f32::MAX, f32::min);
    let hi = valid.iter().copied().fold(0.0f32, f32::max);
    let span = (hi - lo).max(1e-6);
    let mut img = image::RgbImage::new(d.width, d.height);
    for (i, px) in img.pixels_mut().enumerate() {
        let v = d.data_m[i];
        if v > 0.0 {
            let t = ((v - lo) / span).clamp(0.0, 1.0);
            let r = (255.0 * (1.0 - t)) as u8;
            let g = (255.0 * (1.0 - (2.0 * t - 1.0).abs())) as u8;
            let b = (255.0 * t) as u8;
            *px = image::Rgb([r, g, b]);
        }
    }
    img
}

#[utoipa::path(get, path = "/cameras/{id}/latest/depth.png", tag = "ingest",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 200, description = "Colourised 8-bit depth", content_type = "image/png"),
        (status = 404, body = super::error::Problem)))]
async fn get_latest_depth_png(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    let f = latest(&state, &id)?;
    png_response(colourise_depth(&f.depth))
}

#[utoipa::path(get, path = "/cameras/{id}/latest/color.png", tag = "ingest",
    params(("id" = String, Path, description = "Camera id")),
    responses((status = 200, description = "Latest colour image", content_type = "image/png"),
        (status = 404, body = super::error::Problem)))]
async fn get_latest_color_png(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    let f = latest(&state, &id)?;
    let c = f
        .color
        .as_ref()
        .ok_or_else(|| ApiError::NoFrameYet(format!("camera '{id}' sent no colour image")))?;
    let raw: Vec<u8> = c.data.iter().flatten().copied().collect();
    let img =
        image::RgbImage::from_raw(c.width, c.height, raw).ok_or_else(|| ApiError::internal("colour buffer size"))?;
    png_response(img)
}
