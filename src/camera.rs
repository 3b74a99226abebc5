//! Pinhole cameras (intrinsics as in ROS `sensor_msgs/CameraInfo`) and typed images.
//!
//! Camera frames are optical frames: x right, y down, z forward. Depth images hold z-depth in
//! metres along the optical axis; 0 means "no reading".
//!
//! Pixel coordinates follow BOP, OpenCV and ROS `CameraInfo`: the centre of pixel `(x, y)` is at
//! `(u, v) = (x, y)`, so pixel `(x, y)` covers `[x - 0.5, x + 0.5) x [y - 0.5, y + 0.5)` and `k`
//! is used as those tools give it. Integer bounding boxes (`[x, y, w, h]`) count pixels as BOP
//! does: columns `x .. x + w`, so they span `[x - 0.5, x + w - 0.5)` in pixel coordinates.

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Largest image side we accept (pixels).
pub const MAX_IMAGE_SIDE_PX: u32 = 8192;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("image size {width}x{height} is not allowed (1..={max} pixels per side)")]
    BadSize { width: u32, height: u32, max: u32 },
    #[error("intrinsics k must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] with finite fx, fy > 0; got {0:?}")]
    BadK([f64; 9]),
    #[error("non-zero distortion coefficients {0:?} are not supported yet: rectify the images first")]
    Distortion(Vec<f64>),
    #[error("image buffer has {got} values, expected {expected} ({width}x{height}x{channels})")]
    BufferSize {
        got: usize,
        expected: usize,
        width: u32,
        height: u32,
        channels: u32,
    },
    #[error("depth image contains a negative or non-finite value at pixel {index}")]
    BadDepth { index: usize },
}

/// Pinhole intrinsics like ROS `CameraInfo`: `k` row-major 3x3, `width`, `height`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub k: [f64; 9],
}

impl Intrinsics {
    /// Checks sizes and `k`; skew must be zero.
    pub fn new(width: u32, height: u32, k: [f64; 9]) -> Result<Self, CameraError> {
        if width == 0 || height == 0 || width > MAX_IMAGE_SIDE_PX || height > MAX_IMAGE_SIDE_PX {
            return Err(CameraError::BadSize {
                width,
                height,
                max: MAX_IMAGE_SIDE_PX,
            });
        }
        let ok = k.iter().all(|v| v.is_finite())
            && k[0] > 0.0
            && k[4] > 0.0
            && k[1] == 0.0
            && k[3] == 0.0
            && k[6] == 0.0
            && k[7] == 0.0
            && (k[8] - 1.0).abs() < 1e-9;
        if !ok {
            return Err(CameraError::BadK(k));
        }
        Ok(Self { width, height, k })
    }

    /// Like ROS `CameraInfo`: distortion `d` must be empty or all zeros.
    pub fn from_camera_info(width: u32, height: u32, k: [f64; 9], d: &[f64]) -> Result<Self, CameraError> {
        if d.iter().any(|v| *v != 0.0) {
            return Err(CameraError::Distortion(d.to_vec()));
        }
        Self::new(width, height, k)
    }

    /// Square pixels, principal point at the image centre (`(w - 1) / 2`, `(h - 1) / 2`: the
    /// middle of the pixel grid when pixel centres are at integers).
    pub fn from_focal(width: u32, height: u32, f_px: f64) -> Result<Self, CameraError> {
        Self::new(
            width,
            height,
            [
                f_px,
                0.0,
                (width as f64 - 1.0) / 2.0,
                0.0,
                f_px,
                (height as f64 - 1.0) / 2.0,
                0.0,
                0.0,
                1.0,
            ],
        )
    }

    pub fn fx(&self) -> f64 {
        self.k[0]
    }
    pub fn fy(&self) -> f64 {
        self.k[4]
    }
    pub fn cx(&self) -> f64 {
        self.k[2]
    }
    pub fn cy(&self) -> f64 {
        self.k[5]
    }

    /// Pixel coordinates (u right, v down; the centre of pixel `(x, y)` at `(x, y)`) of a point
    /// in the camera frame; `None` behind the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<[f64; 2]> {
        if p.z <= 1e-9 || !p.z.is_finite() {
            return None;
        }
        Some([self.fx() * p.x / p.z + self.cx(), self.fy() * p.y / p.z + self.cy()])
    }

    /// True when the pixel coordinates lie inside the image (on some pixel's area).
    pub fn contains(&self, uv: [f64; 2]) -> bool {
        uv[0] >= -0.5 && uv[1] >= -0.5 && uv[0] < self.width as f64 - 0.5 && uv[1] < self.height as f64 - 0.5
    }

    /// The pixel `(x, y)` whose area holds the pixel coordinates `uv`; `None` outside the image.
    pub fn pixel_at(&self, uv: [f64; 2]) -> Option<(u32, u32)> {
        self.contains(uv)
            .then(|| (pixel_index(uv[0]) as u32, pixel_index(uv[1]) as u32))
    }

    /// The point at pixel `(u, v)` with z-depth `depth_m`.
    pub fn unproject(&self, uv: [f64; 2], depth_m: f64) -> Point3<f64> {
        Point3::new(
            (uv[0] - self.cx()) / self.fx() * depth_m,
            (uv[1] - self.cy()) / self.fy() * depth_m,
            depth_m,
        )
    }

    /// Unit ray through a pixel.
    pub fn ray(&self, uv: [f64; 2]) -> Vector3<f64> {
        self.unproject(uv, 1.0).coords.normalize()
    }

    /// Intrinsics of the same camera at another resolution: the image's edges stay where they
    /// are, so the principal point maps as `(c + 0.5) s - 0.5` with pixel centres at integers.
    pub fn scaled(&self, width: u32, height: u32) -> Result<Self, CameraError> {
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        let k = self.k;
        Self::new(
            width,
            height,
            [
                k[0] * sx,
                0.0,
                (k[2] + 0.5) * sx - 0.5,
                0.0,
                k[4] * sy,
                (k[5] + 0.5) * sy - 0.5,
                0.0,
                0.0,
                1.0,
            ],
        )
    }
}

/// The index of the pixel whose area holds the pixel coordinate `c` (pixel centres at
/// integers, so this rounds half up); may be negative or past the image.
pub fn pixel_index(c: f64) -> i64 {
    (c + 0.5).floor() as i64
}

/// A z-depth image in metres, row-major; 0 means no reading.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub data_m: Vec<f32>,
}

impl DepthImage {
    pub fn new(width: u32, height: u32, data_m: Vec<f32>) -> Result<Self, CameraError> {
        check_len(data_m.len(), width, height, 1)?;
        if let Some(index) = data_m.iter().position(|v| !v.is_finite() || *v < 0.0) {
            return Err(CameraError::BadDepth { index });
        }
        Ok(Self { width, height, data_m })
    }
    pub fn zeros(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data_m: vec![0.0; (width * height) as usize],
        }
    }
    pub fn get(&self, x: u32, y: u32) -> f32 {
        self.data_m[(y * self.width + x) as usize]
    }
    /// From BOP's uint16 (`depth_mm = value * depth_scale`).
    pub fn from_u16_mm(width: u32, height: u32, data: &[u16], depth_scale: f64) -> Result<Self, CameraError> {
        check_len(data.len(), width, height, 1)?;
        Ok(Self {
            width,
            height,
            data_m: data.iter().map(|&v| (v as f64 * depth_scale / 1000.0) as f32).collect(),
        })
    }
    /// To BOP's uint16 (`value = depth_mm / depth_scale`, saturating).
    pub fn to_u16_mm(&self, depth_scale: f64) -> Vec<u16> {
        self.data_m
            .iter()
            .map(|&d| ((d as f64 * 1000.0 / depth_scale).round()).clamp(0.0, u16::MAX as f64) as u16)
            .collect()
    }
}

/// An 8-bit RGB image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<[u8; 3]>,
}

impl ColorImage {
    pub fn new(width: u32, height: u32, data: Vec<[u8; 3]>) -> Result<Self, CameraError> {
        check_len(data.len(), width, height, 1)?;
        Ok(Self { width, height, data })
    }
    pub fn filled(width: u32, height: u32, rgb: [u8; 3]) -> Self {
        Self {
            width,
            height,
            data: vec![rgb; (width * height) as usize],
        }
    }
}

fn check_len(got: usize, width: u32, height: u32, channels: u32) -> Result<(), CameraError> {
    let expected = width as usize * height as usize * channels as usize;
    if got != expected {
        return Err(CameraError::BufferSize {
            got,
            expected,
            width,
            height,
            channels,
        });
    }
    Ok(())
}

/// Back-projects every pixel with a reading into camera-frame points (metres).
pub fn backproject(depth: &DepthImage, intrinsics: &Intrinsics) -> Vec<Point3<f64>> {
    let mut out = Vec::new();
    for y in 0..depth.height {
        for x in 0..depth.width {
            let d = depth.get(x, y);
            if d > 0.0 {
                out.push(intrinsics.unproject([x as f64, y as f64], d as f64));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn cam() -> Intrinsics {
        Intrinsics::from_focal(640, 480, 615.0).unwrap()
    }

    #[test]
    fn project_unproject_round_trip() {
        let c = cam();
        let p = Point3::new(0.1, -0.2, 1.3);
        let uv = c.project(&p).unwrap();
        let back = c.unproject(uv, 1.3);
        assert_relative_eq!(back, p, epsilon = 1e-12);
        assert!(c.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn rejects_distortion_bad_k_and_sizes() {
        let k = cam().k;
        assert!(matches!(
            Intrinsics::from_camera_info(640, 480, k, &[0.1, 0.0]),
            Err(CameraError::Distortion(_))
        ));
        assert!(Intrinsics::from_camera_info(640, 480, k, &[0.0; 5]).is_ok());
        let mut bad = k;
        bad[0] = -1.0;
        assert!(Intrinsics::new(640, 480, bad).is_err());
        bad = k;
        bad[4] = f64::NAN;
        assert!(Intrinsics::new(640, 480, bad).is_err());
        assert!(Intrinsics::new(0, 480, k).is_err());
    }

    #[test]
    fn depth_images_check_their_buffers() {
        assert!(DepthImage::new(2, 2, vec![0.0; 3]).is_err());
        assert!(DepthImage::new(2, 2, vec![0.0, 1.0, f32::NAN, 0.0]).is_err());
        let d = DepthImage::from_u16_mm(2, 1, &[1000, 0], 1.0).unwrap();
        assert_eq!(d.data_m, vec![1.0, 0.0]);
        assert_eq!(d.to_u16_mm(0.1), vec![10000, 0]);
    }

    #[test]
    fn pixel_centres_are_at_integers_as_in_bop_and_opencv() {
        let c = Intrinsics::from_focal(640, 480, 615.0).unwrap();
        assert_eq!((c.cx(), c.cy()), (319.5, 239.5));
        // the optical axis passes through the middle of the pixel grid
        assert_eq!(c.project(&Point3::new(0.0, 0.0, 1.0)).unwrap(), [319.5, 239.5]);
        // a point on the ray through pixel (0, 0)'s centre lands at (0, 0), which is in pixel (0, 0)
        let p = c.unproject([0.0, 0.0], 2.0);
        let uv = c.project(&p).unwrap();
        assert_relative_eq!(uv[0], 0.0, epsilon = 1e-9);
        assert_eq!(c.pixel_at(uv), Some((0, 0)));
        // pixel (0, 0) spans [-0.5, 0.5)
        assert_eq!(c.pixel_at([-0.49, 0.49]), Some((0, 0)));
        assert_eq!(c.pixel_at([0.5, -0.5]), Some((1, 0)));
        assert_eq!(c.pixel_at([-0.51, 0.0]), None);
        assert_eq!(c.pixel_at([639.49, 479.49]), Some((639, 479)));
        assert_eq!(c.pixel_at([639.5, 0.0]), None);
        assert_eq!(pixel_index(-0.6), -1);
    }

    #[test]
    fn scaling_keeps_the_image_edges() {
        let c = Intrinsics::from_focal(640, 480, 615.0).unwrap();
        let half = c.scaled(320, 240).unwrap();
        // from_focal's centre maps to the smaller image's centre
        assert_relative_eq!(half.cx(), 159.5, epsilon = 1e-12);
        assert_relative_eq!(half.cy(), 119.5, epsilon = 1e-12);
        // a ray through the left edge of pixel 0 (u = -0.5) still hits the left edge
        let p = c.unproject([-0.5, 100.0], 1.0);
        assert_relative_eq!(half.project(&p).unwrap()[0], -0.5, epsilon = 1e-9);
        let back = half.scaled(640, 480).unwrap();
        assert_relative_eq!(back.cx(), c.cx(), epsilon = 1e-12);
    }

    #[test]
    fn backprojected_plane_is_flat() {
        let c = Intrinsics::from_focal(8, 6, 10.0).unwrap();
        let d = DepthImage::new(8, 6, vec![2.0; 48]).unwrap();
        let pts = backproject(&d, &c);
        assert_eq!(pts.len(), 48);
        assert!(pts.iter().all(|p| (p.z - 2.0).abs() < 1e-12));
    }
}
