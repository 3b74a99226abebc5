//! Reader and writer of multi-view sequences in the format of `shared/design/multiview-bop.md`:
//! one BOP scene per camera (`<camera>/scene_camera.json`, `scene_gt.json`,
//! `scene_gt_info.json`, `depth/`, `rgb/`, `mask_visib/`) plus `rig.json` and `odometry.json`.
//!
//! Units: the BOP files are in millimetres (`cam_t_w2c`, `cam_t_m2c`, depth values times
//! `depth_scale`); everything in memory is in metres ([`Pose`], [`DepthImage`]). `rig.json` and
//! `odometry.json` are in metres. `cam_R_w2c`/`cam_t_w2c` is `camera_from_world`; `cam_R_m2c`/
//! `cam_t_m2c` is `camera_from_object`.
//!
//! What a tracker may read (see the format doc): the stationary cameras' poses, the odometry,
//! depth/colour and [`Sequence::detections`]. The robot camera's pose, `scene_gt.json` and the
//! masks are ground truth for evaluation only.
//!
//! Extra fields we write into `scene_camera.json` besides BOP's: `stamp_ns` (capture time) and
//! `width`/`height` (image size; when absent, the reader takes it from the depth PNG).

use crate::camera::{CameraError, ColorImage, DepthImage, Intrinsics};
use crate::geometry::{GeometryError, Pose, PoseXyzw, pose_from_rt, pose_to_rt};
use crate::mesh::{Mesh, MeshError};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The `format` string of `rig.json`.
pub const RIG_FORMAT: &str = "pregrasp-multiview/1";
/// Detections come from boxes whose object is at least this visible (`visib_fract`).
pub const DETECTION_MIN_VISIB_FRACT: f64 = 0.1;
/// Standard deviation of the box jitter, as a fraction of the box size.
pub const DETECTION_JITTER_FRACTION: f64 = 0.05;
/// Probability that a detection is missing in a frame.
pub const DETECTION_MISS_PROBABILITY: f64 = 0.1;
/// Frame period assumed when a `scene_camera.json` entry has no `stamp_ns` (30 Hz).
pub const DEFAULT_FRAME_PERIOD_NS: i64 = 33_333_333;

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("cannot read {}: {source}", path.display())]
    Read { path: PathBuf, source: std::io::Error },
    #[error("cannot write {}: {source}", path.display())]
    Write { path: PathBuf, source: std::io::Error },
    #[error("malformed JSON in {}: {source}", path.display())]
    Json { path: PathBuf, source: serde_json::Error },
    #[error("cannot decode or encode image {}: {source}", path.display())]
    Image { path: PathBuf, source: image::ImageError },
    #[error("{}: {reason}", path.display())]
    Invalid { path: PathBuf, reason: String },
    #[error("{}: {source}", path.display())]
    Geometry { path: PathBuf, source: GeometryError },
    #[error("{}: {source}", path.display())]
    Camera { path: PathBuf, source: CameraError },
    #[error("cannot load mesh {}: {source}", path.display())]
    Mesh { path: PathBuf, source: MeshError },
    #[error("{} is not a sequence (no rig.json) and holds no sequences", .0.display())]
    NotASequence(PathBuf),
    #[error("sequence {} has no camera {camera:?}", root.display())]
    UnknownCamera { root: PathBuf, camera: String },
    #[error("camera {camera:?} of {} has no frame {frame}", root.display())]
    UnknownFrame { root: PathBuf, camera: String, frame: u32 },
    #[error("sequence {} has no object {object:?}", root.display())]
    UnknownObject { root: PathBuf, object: String },
}

pub type Result<T, E = DatasetError> = std::result::Result<T, E>;

// ---------------------------------------------------------------------------------------------
// rig.json

/// How a camera is mounted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mount {
    /// Calibrated, its `cam_R_w2c` known to the tracker.
    Stationary,
    /// On the robot; its pose is ground truth only, the tracker uses the odometry.
    Robot,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigCamera {
    pub mount: Mount,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigObject {
    pub obj_id: u32,
    pub name: String,
    /// Mesh path relative to the sequence folder.
    pub mesh: String,
}

/// A plane in the world frame (the table top).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Plane {
    pub normal: [f64; 3],
    pub point_m: [f64; 3],
}

/// Error of the localised pose `world_from_odom * odom_from_base` against the truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LocalisationSigma {
    pub translation_m: f64,
    pub rotation_rad: f64,
}

/// `rig.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rig {
    #[serde(default = "rig_format")]
    pub format: String,
    pub reference_camera: String,
    pub cameras: BTreeMap<String, RigCamera>,
    pub objects: Vec<RigObject>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_noise_relative_sigma: Option<f64>,
    /// Thrun's alpha1..alpha4 of the odometry motion model that produced the odometry.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odometry_noise_alpha: Option<[f64; 4]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub localisation_sigma: Option<LocalisationSigma>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub support_plane: Option<Plane>,
}

fn rig_format() -> String {
    RIG_FORMAT.to_string()
}

impl Rig {
    pub fn object_by_id(&self, obj_id: u32) -> Option<&RigObject> {
        self.objects.iter().find(|o| o.obj_id == obj_id)
    }
    pub fn object_by_name(&self, name: &str) -> Option<&RigObject> {
        self.objects.iter().find(|o| o.name == name)
    }
    /// The name of an object id (`obj_000123` when the rig does not list it).
    pub fn object_name(&self, obj_id: u32) -> String {
        self.object_by_id(obj_id)
            .map(|o| o.name.clone())
            .unwrap_or_else(|| format!("obj_{obj_id:06}"))
    }
    /// The camera on the robot, if there is one.
    pub fn robot_camera(&self) -> Option<&str> {
        self.cameras
            .iter()
            .find(|(_, c)| c.mount == Mount::Robot)
            .map(|(n, _)| n.as_str())
    }
}

// ---------------------------------------------------------------------------------------------
// Per-camera BOP data

/// One frame of `scene_camera.json`, in metres.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMeta {
    /// Capture time; [`DEFAULT_FRAME_PERIOD_NS`] times the frame id when the file has none.
    pub stamp_ns: i64,
    pub intrinsics: Intrinsics,
    /// `depth_mm = png_value * depth_scale`.
    pub depth_scale: f64,
    /// `cam_R_w2c`/`cam_t_w2c`: calibration for a stationary camera, ground truth for the robot's.
    pub camera_from_world: Option<Pose>,
}

/// One ground-truth instance of `scene_gt.json` (evaluation only).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GtObject {
    pub obj_id: u32,
    pub camera_from_object: Pose,
}

/// One entry of `scene_gt_info.json` (BOP fields; all optional on reading).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct GtInfo {
    /// Box of the whole projected object (x, y, width, height px), clipped to the image.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bbox_obj: Option<[i64; 4]>,
    /// Box of the visible pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bbox_visib: Option<[i64; 4]>,
    /// Pixels of the object rendered alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub px_count_all: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub px_count_visib: Option<u64>,
    /// `px_count_visib / px_count_all`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub visib_fract: Option<f64>,
}

/// The BOP scene of one camera.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CameraStream {
    pub frames: BTreeMap<u32, FrameMeta>,
    pub gt: BTreeMap<u32, Vec<GtObject>>,
    pub gt_info: BTreeMap<u32, Vec<GtInfo>>,
}

/// Detections are the tracker's type: the stand-ins of [`Sequence::detections`] feed it directly.
pub use crate::sensor::Detection;

/// One entry of `odometry.json`, in memory (metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometrySample {
    pub stamp_ns: i64,
    /// Wheel odometry: drifts without bound.
    pub odom_from_base: Pose,
    /// The localisation's correction: `world_from_odom * odom_from_base` is the localised base.
    pub world_from_odom: Pose,
    /// The arm's forward kinematics, exact.
    pub base_from_camera: Pose,
}

impl OdometrySample {
    /// `world_from_odom * odom_from_base * base_from_camera`: the localised robot camera.
    pub fn world_from_camera(&self) -> Pose {
        self.world_from_odom * self.odom_from_base * self.base_from_camera
    }
}

// File layouts ---------------------------------------------------------------------------------

#[allow(non_snake_case)]
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SceneCameraEntry {
    cam_K: [f64; 9],
    #[serde(default = "one")]
    depth_scale: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    cam_R_w2c: Option<[f64; 9]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    cam_t_w2c: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    stamp_ns: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    width: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    height: Option<u32>,
}

fn one() -> f64 {
    1.0
}

#[allow(non_snake_case)]
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SceneGtEntry {
    obj_id: u32,
    cam_R_m2c: [f64; 9],
    cam_t_m2c: [f64; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct OdometryEntry {
    stamp_ns: i64,
    odom_from_base: PoseXyzw,
    world_from_odom: PoseXyzw,
    base_from_camera: PoseXyzw,
}

fn mm_to_m(t: [f64; 3]) -> [f64; 3] {
    [t[0] / 1000.0, t[1] / 1000.0, t[2] / 1000.0]
}

fn pose_from_bop(path: &Path, r: &[f64; 9], t_mm: [f64; 3]) -> Result<Pose> {
    pose_from_rt(r, mm_to_m(t_mm)).map_err(|source| DatasetError::Geometry {
        path: path.to_path_buf(),
        source,
    })
}

fn pose_to_bop(pose: &Pose) -> ([f64; 9], [f64; 3]) {
    let (r, t) = pose_to_rt(pose);
    (r, [t[0] * 1000.0, t[1] * 1000.0, t[2] * 1000.0])
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_slice(&bytes).map_err(|source| DatasetError::Json {
        path: path.to_path_buf(),
        source,
    })
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes = serde_json::to_vec_pretty(value).map_err(|source| DatasetError::Json {
        path: path.to_path_buf(),
        source,
    })?;
    std::fs::write(path, bytes).map_err(|source| DatasetError::Write {
        path: path.to_path_buf(),
        source,
    })
}

fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(|source| DatasetError::Write {
        path: path.to_path_buf(),
        source,
    })
}

// ---------------------------------------------------------------------------------------------
// Images

/// Writes a BOP depth PNG (uint16, `value = depth_mm / depth_scale`).
pub fn write_depth_png(path: &Path, depth: &DepthImage, depth_scale: f64) -> Result<()> {
    let data = depth.to_u16_mm(depth_scale);
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(depth.width, depth.height, data)
        .ok_or_else(|| invalid(path, "depth buffer does not match its size"))?;
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| DatasetError::Image {
            path: path.to_path_buf(),
            source,
        })
}

/// Writes an 8-bit RGB PNG.
pub fn write_rgb_png(path: &Path, color: &ColorImage) -> Result<()> {
    let data: Vec<u8> = color.data.iter().flatten().copied().collect();
    let img = image::RgbImage::from_raw(color.width, color.height, data)
        .ok_or_else(|| invalid(path, "colour buffer does not match its size"))?;
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| DatasetError::Image {
            path: path.to_path_buf(),
            source,
        })
}

/// Writes a BOP mask PNG (8-bit, 255 where `mask` is true).
pub fn write_mask_png(path: &Path, width: u32, height: u32, mask: &[bool]) -> Result<()> {
    let data: Vec<u8> = mask.iter().map(|&m| if m { 255 } else { 0 }).collect();
    let img = image::GrayImage::from_raw(width, height, data)
        .ok_or_else(|| invalid(path, "mask buffer does not match its size"))?;
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| DatasetError::Image {
            path: path.to_path_buf(),
            source,
        })
}

fn decode(path: &Path) -> Result<image::DynamicImage> {
    image::ImageReader::open(path)
        .map_err(|source| DatasetError::Read {
            path: path.to_path_buf(),
            source,
        })?
        .with_guessed_format()
        .map_err(|source| DatasetError::Read {
            path: path.to_path_buf(),
            source,
        })?
        .decode()
        .map_err(|source| DatasetError::Image {
            path: path.to_path_buf(),
            source,
        })
}

/// Reads a BOP depth PNG into metres.
pub fn read_depth_png(path: &Path, depth_scale: f64) -> Result<DepthImage> {
    let img = decode(path)?;
    if !matches!(img, image::DynamicImage::ImageLuma16(_)) {
        return Err(invalid(path, "depth PNG must be 16-bit grey"));
    }
    let img = img.into_luma16();
    DepthImage::from_u16_mm(img.width(), img.height(), img.as_raw(), depth_scale).map_err(|source| {
        DatasetError::Camera {
            path: path.to_path_buf(),
            source,
        }
    })
}

/// Reads an RGB PNG (any 8-bit colour type is converted to RGB).
pub fn read_rgb_png(path: &Path) -> Result<ColorImage> {
    let img = decode(path)?.into_rgb8();
    let (w, h) = (img.width(), img.height());
    let data = img.pixels().map(|p| p.0).collect();
    ColorImage::new(w, h, data).map_err(|source| DatasetError::Camera {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads a mask PNG (non-zero = inside) as `(width, height, mask)`.
pub fn read_mask_png(path: &Path) -> Result<(u32, u32, Vec<bool>)> {
    let img = decode(path)?.into_luma8();
    Ok((img.width(), img.height(), img.as_raw().iter().map(|&v| v > 0).collect()))
}

fn invalid(path: &Path, reason: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

// ---------------------------------------------------------------------------------------------
// Sequence

/// A multi-view sequence: `rig.json`, one BOP scene per camera, optional `odometry.json`.
/// Images are loaded on demand.
#[derive(Debug, Clone, PartialEq)]
pub struct Sequence {
    pub root: PathBuf,
    pub rig: Rig,
    pub cameras: BTreeMap<String, CameraStream>,
    /// Per frame id of the robot camera; `None` when there is no `odometry.json`.
    pub odometry: Option<BTreeMap<u32, OdometrySample>>,
}

/// `dir` itself when it is a sequence (has `rig.json`), else its sub-folders that are
/// sequences, sorted by name.
pub fn find_sequences(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.join("rig.json").is_file() {
        return Ok(vec![dir.to_path_buf()]);
    }
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Read {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|source| DatasetError::Read {
            path: dir.to_path_buf(),
            source,
        })?;
        let p = entry.path();
        if p.is_dir() && p.join("rig.json").is_file() {
            out.push(p);
        }
    }
    if out.is_empty() {
        return Err(DatasetError::NotASequence(dir.to_path_buf()));
    }
    out.sort();
    Ok(out)
}

impl Sequence {
    /// Reads the JSON files of a sequence (not the images).
    pub fn open(root: &Path) -> Result<Self> {
        let rig_path = root.join("rig.json");
        if !rig_path.is_file() {
            return Err(DatasetError::NotASequence(root.to_path_buf()));
        }
        let rig: Rig = read_json(&rig_path)?;
        if rig.format != RIG_FORMAT {
            return Err(invalid(
                &rig_path,
                format!("format {:?} is not {RIG_FORMAT:?}", rig.format),
            ));
        }
        if !rig.cameras.contains_key(&rig.reference_camera) {
            return Err(invalid(
                &rig_path,
                format!("reference_camera {:?} is not among the cameras", rig.reference_camera),
            ));
        }
        if let Some(t) = &rig.target
            && rig.object_by_name(t).is_none()
        {
            return Err(invalid(&rig_path, format!("target {t:?} is not among the objects")));
        }
        let mut cameras = BTreeMap::new();
        for name in rig.cameras.keys() {
            cameras.insert(name.clone(), read_camera(&root.join(name))?);
        }
        let odo_path = root.join("odometry.json");
        let odometry = if odo_path.is_file() {
            let raw: BTreeMap<u32, OdometryEntry> = read_json(&odo_path)?;
            let geo = |source| DatasetError::Geometry {
                path: odo_path.clone(),
                source,
            };
            let mut out = BTreeMap::new();
            for (k, e) in raw {
                out.insert(
                    k,
                    OdometrySample {
                        stamp_ns: e.stamp_ns,
                        odom_from_base: e.odom_from_base.to_pose().map_err(geo)?,
                        world_from_odom: e.world_from_odom.to_pose().map_err(geo)?,
                        base_from_camera: e.base_from_camera.to_pose().map_err(geo)?,
                    },
                );
            }
            Some(out)
        } else {
            if rig.robot_camera().is_some() {
                return Err(invalid(
                    &odo_path,
                    "the rig has a robot camera but there is no odometry.json",
                ));
            }
            None
        };
        Ok(Self {
            root: root.to_path_buf(),
            rig,
            cameras,
            odometry,
        })
    }

    /// Writes `rig.json`, `odometry.json` and every camera's JSON files under `self.root`
    /// (creating the folders). Images are written with [`write_depth_png`] and friends at
    /// [`Sequence::depth_path`], [`Sequence::rgb_path`], [`Sequence::mask_path`].
    pub fn write_json(&self) -> Result<()> {
        create_dir(&self.root)?;
        write_json(&self.root.join("rig.json"), &self.rig)?;
        if let Some(odo) = &self.odometry {
            let raw: BTreeMap<u32, OdometryEntry> = odo
                .iter()
                .map(|(k, s)| {
                    (
                        *k,
                        OdometryEntry {
                            stamp_ns: s.stamp_ns,
                            odom_from_base: PoseXyzw::from_pose(&s.odom_from_base),
                            world_from_odom: PoseXyzw::from_pose(&s.world_from_odom),
                            base_from_camera: PoseXyzw::from_pose(&s.base_from_camera),
                        },
                    )
                })
                .collect();
            write_json(&self.root.join("odometry.json"), &raw)?;
        }
        for (name, cam) in &self.cameras {
            write_camera(&self.root.join(name), cam)?;
        }
        Ok(())
    }

    pub fn camera(&self, camera: &str) -> Result<&CameraStream> {
        self.cameras.get(camera).ok_or_else(|| DatasetError::UnknownCamera {
            root: self.root.clone(),
            camera: camera.to_string(),
        })
    }

    pub fn frame(&self, camera: &str, frame: u32) -> Result<&FrameMeta> {
        self.camera(camera)?
            .frames
            .get(&frame)
            .ok_or_else(|| DatasetError::UnknownFrame {
                root: self.root.clone(),
                camera: camera.to_string(),
                frame,
            })
    }

    /// Frame ids of all cameras together (time steps), sorted.
    pub fn frame_ids(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self.cameras.values().flat_map(|c| c.frames.keys().copied()).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }

    pub fn depth_path(&self, camera: &str, frame: u32) -> PathBuf {
        self.root.join(camera).join("depth").join(format!("{frame:06}.png"))
    }
    pub fn rgb_path(&self, camera: &str, frame: u32) -> PathBuf {
        self.root.join(camera).join("rgb").join(format!("{frame:06}.png"))
    }
    /// Mask of the `gt_index`-th ground-truth instance of a frame.
    pub fn mask_path(&self, camera: &str, frame: u32, gt_index: usize) -> PathBuf {
        self.root
            .join(camera)
            .join("mask_visib")
            .join(format!("{frame:06}_{gt_index:06}.png"))
    }

    /// The depth image of a frame, metres.
    pub fn load_depth(&self, camera: &str, frame: u32) -> Result<DepthImage> {
        let meta = self.frame(camera, frame)?;
        let path = self.depth_path(camera, frame);
        let depth = read_depth_png(&path, meta.depth_scale)?;
        if depth.width != meta.intrinsics.width || depth.height != meta.intrinsics.height {
            return Err(invalid(
                &path,
                format!(
                    "image is {}x{} but scene_camera.json says {}x{}",
                    depth.width, depth.height, meta.intrinsics.width, meta.intrinsics.height
                ),
            ));
        }
        Ok(depth)
    }

    /// The colour image of a frame, `None` when the sequence has none.
    pub fn load_rgb(&self, camera: &str, frame: u32) -> Result<Option<ColorImage>> {
        self.frame(camera, frame)?;
        let path = self.rgb_path(camera, frame);
        if !path.is_file() {
            return Ok(None);
        }
        read_rgb_png(&path).map(Some)
    }

    /// The visible mask of a ground-truth instance (evaluation only), `None` when absent.
    pub fn load_mask(&self, camera: &str, frame: u32, gt_index: usize) -> Result<Option<Vec<bool>>> {
        self.frame(camera, frame)?;
        let path = self.mask_path(camera, frame, gt_index);
        if !path.is_file() {
            return Ok(None);
        }
        let (_, _, m) = read_mask_png(&path)?;
        Ok(Some(m))
    }

    /// Absolute path of an object's mesh.
    pub fn mesh_path(&self, object: &str) -> Result<PathBuf> {
        let o = self
            .rig
            .object_by_name(object)
            .ok_or_else(|| DatasetError::UnknownObject {
                root: self.root.clone(),
                object: object.to_string(),
            })?;
        Ok(self.root.join(&o.mesh))
    }

    /// Loads an object's mesh (metres).
    pub fn load_mesh(&self, object: &str) -> Result<Mesh> {
        let path = self.mesh_path(object)?;
        Mesh::load(&path).map_err(|source| DatasetError::Mesh { path, source })
    }

    /// Stand-in detections of a frame: the `bbox_visib` boxes of objects with
    /// `visib_fract` > [`DETECTION_MIN_VISIB_FRACT`] (without `visib_fract`: `px_count_visib` >
    /// 0), each centre and size jittered by [`DETECTION_JITTER_FRACTION`] of the box size and
    /// each missing with probability [`DETECTION_MISS_PROBABILITY`]. Deterministic in
    /// `(seed, camera, frame)`. Empty for an unknown camera or frame.
    pub fn detections(&self, camera: &str, frame: u32, seed: u64) -> Vec<Detection> {
        let Some(cam) = self.cameras.get(camera) else {
            return Vec::new();
        };
        let (Some(gt), Some(info)) = (cam.gt.get(&frame), cam.gt_info.get(&frame)) else {
            return Vec::new();
        };
        let meta = cam.frames.get(&frame);
        let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[camera.as_bytes(), &frame.to_le_bytes()]));
        let unit = Normal::new(0.0, 1.0).expect("unit normal");
        let mut out = Vec::new();
        for (g, i) in gt.iter().zip(info) {
            // draw the same numbers for every instance so one instance's fate does not shift
            // the others'
            let miss: f64 = rng.random();
            let n: [f64; 4] = std::array::from_fn(|_| unit.sample(&mut rng));
            let visible = match (i.visib_fract, i.px_count_visib) {
                (Some(f), _) => f > DETECTION_MIN_VISIB_FRACT,
                (None, Some(px)) => px > 0,
                (None, None) => false,
            };
            let Some(b) = i.bbox_visib else { continue };
            if !visible || b[2] <= 0 || b[3] <= 0 || miss < DETECTION_MISS_PROBABILITY {
                continue;
            }
            let (w, h) = (b[2] as f64, b[3] as f64);
            let cx = b[0] as f64 + w / 2.0 + n[0] * DETECTION_JITTER_FRACTION * w;
            let cy = b[1] as f64 + h / 2.0 + n[1] * DETECTION_JITTER_FRACTION * h;
            let w2 = (w * (1.0 + n[2] * DETECTION_JITTER_FRACTION)).max(1.0);
            let h2 = (h * (1.0 + n[3] * DETECTION_JITTER_FRACTION)).max(1.0);
            let mut x0 = cx - w2 / 2.0;
            let mut y0 = cy - h2 / 2.0;
            let mut x1 = cx + w2 / 2.0;
            let mut y1 = cy + h2 / 2.0;
            if let Some(m) = meta {
                x0 = x0.clamp(0.0, m.intrinsics.width as f64);
                x1 = x1.clamp(0.0, m.intrinsics.width as f64);
                y0 = y0.clamp(0.0, m.intrinsics.height as f64);
                y1 = y1.clamp(0.0, m.intrinsics.height as f64);
            }
            if x1 - x0 < 1.0 || y1 - y0 < 1.0 {
                continue;
            }
            let jitter = (n.iter().map(|v| v * v).sum::<f64>() / 4.0).sqrt();
            out.push(Detection {
                object: self.rig.object_name(g.obj_id),
                bbox_xywh_px: [x0, y0, x1 - x0, y1 - y0],
                score: (1.0 - 0.1 * jitter).clamp(0.5, 1.0),
            });
        }
        out
    }
}

/// A seed for one stream of random numbers: FNV-1a over the seed and the parts (stable across
/// platforms and Rust versions, unlike `DefaultHasher`).
pub fn stream_seed(seed: u64, parts: &[&[u8]]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut feed = |bytes: &[u8]| {
        for &b in bytes {
            h ^= b as u64;
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    feed(&seed.to_le_bytes());
    for p in parts {
        feed(&(p.len() as u64).to_le_bytes());
        feed(p);
    }
    h
}

fn read_camera(dir: &Path) -> Result<CameraStream> {
    let sc_path = dir.join("scene_camera.json");
    let raw: BTreeMap<u32, SceneCameraEntry> = read_json(&sc_path)?;
    let mut frames = BTreeMap::new();
    let mut size_from_png: Option<(u32, u32)> = None;
    for (frame, e) in raw {
        let (width, height) = match (e.width, e.height) {
            (Some(w), Some(h)) => (w, h),
            _ => match size_from_png {
                Some(s) => s,
                None => {
                    let png = dir.join("depth").join(format!("{frame:06}.png"));
                    let s = image::image_dimensions(&png).map_err(|source| DatasetError::Image {
                        path: png.clone(),
                        source,
                    })?;
                    size_from_png = Some(s);
                    s
                }
            },
        };
        let intrinsics = Intrinsics::new(width, height, e.cam_K).map_err(|source| DatasetError::Camera {
            path: sc_path.clone(),
            source,
        })?;
        if !(e.depth_scale.is_finite() && e.depth_scale > 0.0) {
            return Err(invalid(
                &sc_path,
                format!("frame {frame}: depth_scale {} must be positive", e.depth_scale),
            ));
        }
        let camera_from_world = match (e.cam_R_w2c, e.cam_t_w2c) {
            (Some(r), Some(t)) => Some(pose_from_bop(&sc_path, &r, t)?),
            (None, None) => None,
            _ => {
                return Err(invalid(
                    &sc_path,
                    format!("frame {frame}: cam_R_w2c and cam_t_w2c must come together"),
                ));
            }
        };
        frames.insert(
            frame,
            FrameMeta {
                stamp_ns: e.stamp_ns.unwrap_or(frame as i64 * DEFAULT_FRAME_PERIOD_NS),
                intrinsics,
                depth_scale: e.depth_scale,
                camera_from_world,
            },
        );
    }
    let gt_path = dir.join("scene_gt.json");
    let mut gt = BTreeMap::new();
    if gt_path.is_file() {
        let raw: BTreeMap<u32, Vec<SceneGtEntry>> = read_json(&gt_path)?;
        for (frame, list) in raw {
            let objs = list
                .iter()
                .map(|e| {
                    Ok(GtObject {
                        obj_id: e.obj_id,
                        camera_from_object: pose_from_bop(&gt_path, &e.cam_R_m2c, e.cam_t_m2c)?,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            gt.insert(frame, objs);
        }
    }
    let info_path = dir.join("scene_gt_info.json");
    let gt_info: BTreeMap<u32, Vec<GtInfo>> = if info_path.is_file() {
        read_json(&info_path)?
    } else {
        BTreeMap::new()
    };
    for (frame, info) in &gt_info {
        let n_gt = gt.get(frame).map_or(0, Vec::len);
        if info.len() != n_gt {
            return Err(invalid(
                &info_path,
                format!("frame {frame}: {} entries but scene_gt.json has {n_gt}", info.len()),
            ));
        }
    }
    Ok(CameraStream { frames, gt, gt_info })
}

fn write_camera(dir: &Path, cam: &CameraStream) -> Result<()> {
    create_dir(dir)?;
    let sc: BTreeMap<u32, SceneCameraEntry> = cam
        .frames
        .iter()
        .map(|(k, f)| {
            let (r, t) = match &f.camera_from_world {
                Some(p) => {
                    let (r, t) = pose_to_bop(p);
                    (Some(r), Some(t))
                }
                None => (None, None),
            };
            (
                *k,
                SceneCameraEntry {
                    cam_K: f.intrinsics.k,
                    depth_scale: f.depth_scale,
                    cam_R_w2c: r,
                    cam_t_w2c: t,
                    stamp_ns: Some(f.stamp_ns),
                    width: Some(f.intrinsics.width),
                    height: Some(f.intrinsics.height),
                },
            )
        })
        .collect();
    write_json(&dir.join("scene_camera.json"), &sc)?;
    let gt: BTreeMap<u32, Vec<SceneGtEntry>> = cam
        .gt
        .iter()
        .map(|(k, list)| {
            (
                *k,
                list.iter()
                    .map(|g| {
                        let (r, t) = pose_to_bop(&g.camera_from_object);
                        SceneGtEntry {
                            obj_id: g.obj_id,
                            cam_R_m2c: r,
                            cam_t_m2c: t,
                        }
                    })
                    .collect(),
            )
        })
        .collect();
    write_json(&dir.join("scene_gt.json"), &gt)?;
    write_json(&dir.join("scene_gt_info.json"), &cam.gt_info)?;
    for sub in ["depth", "rgb", "mask_visib"] {
        create_dir(&dir.join(sub))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose_from_xyzw;

    use crate::testing::shared_dir as shared;

    fn pose(t: [f64; 3], q: [f64; 4]) -> Pose {
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        pose_from_xyzw(t, [q[0] / n, q[1] / n, q[2] / n, q[3] / n]).unwrap()
    }

    fn close(a: &Pose, b: &Pose) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9 && a.rotation.angle_to(&b.rotation) < 1e-6
    }

    #[test]
    fn reads_the_real_ycbv_scene() {
        let root = shared().join("realdata/ycbv_video_0000/bop");
        assert_eq!(find_sequences(&root).unwrap(), vec![root.clone()]);
        let seq = Sequence::open(&root).unwrap();
        assert_eq!(seq.rig.reference_camera, "cam");
        assert!(seq.odometry.is_none());
        let cam = seq.camera("cam").unwrap();
        assert_eq!(cam.frames.len(), 10);
        assert_eq!(seq.frame_ids(), (1..=10).collect::<Vec<_>>());
        let f1 = seq.frame("cam", 1).unwrap();
        assert_eq!(f1.depth_scale, 0.1);
        assert_eq!((f1.intrinsics.width, f1.intrinsics.height), (640, 480));
        assert!((f1.intrinsics.fx() - 1066.778).abs() < 1e-9);
        assert_eq!(f1.stamp_ns, 0);
        assert!(f1.camera_from_world.is_some());
        let gt = &cam.gt[&1];
        assert_eq!(gt.len(), 1);
        assert_eq!(seq.rig.object_name(gt[0].obj_id), "025_mug");
        let z = gt[0].camera_from_object.translation.vector.z;
        assert!((z - 0.622).abs() < 0.001, "mug at {z} m");
        // the depth at the mug's pixels agrees with the ground truth (metres, scale 0.1 mm)
        let depth = seq.load_depth("cam", 1).unwrap();
        let mask = seq.load_mask("cam", 1, 0).unwrap().unwrap();
        let mut d: Vec<f32> = depth
            .data_m
            .iter()
            .zip(&mask)
            .filter(|(d, m)| **m && **d > 0.0)
            .map(|(d, _)| *d)
            .collect();
        d.sort_by(f32::total_cmp);
        let median = d[d.len() / 2] as f64;
        assert!((median - z).abs() < 0.06, "median depth {median} vs object z {z}");
        let rgb = seq.load_rgb("cam", 1).unwrap().unwrap();
        assert_eq!(rgb.data.len(), 640 * 480);
        let mesh = seq.load_mesh("025_mug").unwrap();
        assert!(mesh.diameter_m() > 0.1 && mesh.diameter_m() < 0.2);
        // detections exist (px_count_visib only) and follow the seed
        let all: usize = (1..=10).map(|f| seq.detections("cam", f, 3).len()).sum();
        assert!((5..=10).contains(&all), "{all} detections in 10 frames");
        assert_eq!(seq.detections("cam", 2, 3), seq.detections("cam", 2, 3));
    }

    fn sample_sequence(root: &Path) -> Sequence {
        let k = Intrinsics::from_focal(32, 24, 30.0).unwrap();
        let mut cameras = BTreeMap::new();
        for (ci, name) in ["ext1", "robot"].iter().enumerate() {
            let mut cam = CameraStream::default();
            for f in 0..3u32 {
                let cfw = pose([0.1 * f as f64, -0.2, 3.0 + ci as f64], [0.1, 0.2 * f as f64, 0.3, 0.9]);
                cam.frames.insert(
                    f,
                    FrameMeta {
                        stamp_ns: f as i64 * 100_000_000 + ci as i64 * 7_000_000,
                        intrinsics: k,
                        depth_scale: 0.1,
                        camera_from_world: Some(cfw),
                    },
                );
                cam.gt.insert(
                    f,
                    vec![
                        GtObject {
                            obj_id: 2,
                            camera_from_object: pose([0.01, 0.02, 1.5 + f as f64], [0.5, -0.2, 0.1, 0.8]),
                        },
                        GtObject {
                            obj_id: 14,
                            camera_from_object: pose([-0.3, 0.1, 2.0], [0.0, 0.0, 0.0, 1.0]),
                        },
                    ],
                );
                cam.gt_info.insert(
                    f,
                    vec![
                        GtInfo {
                            bbox_obj: Some([1, 2, 10, 12]),
                            bbox_visib: Some([1, 2, 9, 12]),
                            px_count_all: Some(100),
                            px_count_visib: Some(90),
                            visib_fract: Some(0.9),
                        },
                        GtInfo {
                            bbox_obj: Some([20, 2, 5, 5]),
                            bbox_visib: Some([0, 0, 0, 0]),
                            px_count_all: Some(20),
                            px_count_visib: Some(0),
                            visib_fract: Some(0.0),
                        },
                    ],
                );
            }
            cameras.insert(name.to_string(), cam);
        }
        let mut odometry = BTreeMap::new();
        for f in 0..3u32 {
            odometry.insert(
                f,
                OdometrySample {
                    stamp_ns: f as i64 * 100_000_000,
                    odom_from_base: pose([f as f64, 0.5, 0.0], [0.0, 0.0, 0.1 * f as f64, 1.0]),
                    world_from_odom: pose([1.0, 2.0, 0.0], [0.0, 0.0, 0.3, 1.0]),
                    base_from_camera: pose([0.3, 0.0, 1.2], [0.5, -0.5, 0.5, -0.5]),
                },
            );
        }
        let mut rig_cameras = BTreeMap::new();
        rig_cameras.insert(
            "ext1".to_string(),
            RigCamera {
                mount: Mount::Stationary,
            },
        );
        rig_cameras.insert("robot".to_string(), RigCamera { mount: Mount::Robot });
        Sequence {
            root: root.to_path_buf(),
            rig: Rig {
                format: RIG_FORMAT.into(),
                reference_camera: "robot".into(),
                cameras: rig_cameras,
                objects: vec![
                    RigObject {
                        obj_id: 2,
                        name: "box".into(),
                        mesh: "models/box.ply".into(),
                    },
                    RigObject {
                        obj_id: 14,
                        name: "mug".into(),
                        mesh: "models/mug.ply".into(),
                    },
                ],
                target: Some("box".into()),
                depth_noise_relative_sigma: Some(0.05),
                odometry_noise_alpha: Some([0.02, 0.002, 0.02, 0.002]),
                localisation_sigma: Some(LocalisationSigma {
                    translation_m: 0.015,
                    rotation_rad: 0.009,
                }),
                support_plane: Some(Plane {
                    normal: [0.0, 0.0, 1.0],
                    point_m: [0.0, 0.0, 0.0],
                }),
            },
            cameras,
            odometry: Some(odometry),
        }
    }

    #[test]
    fn round_trip_write_read_is_equal() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("seq");
        let seq = sample_sequence(&root);
        seq.write_json().unwrap();
        let k = seq.cameras["robot"].frames[&0].intrinsics;
        let depth = DepthImage::new(
            k.width,
            k.height,
            (0..k.width * k.height)
                .map(|i| if i % 7 == 0 { 0.0 } else { 0.5 + i as f32 * 1e-3 })
                .collect(),
        )
        .unwrap();
        let color = ColorImage::new(
            k.width,
            k.height,
            (0..k.width * k.height).map(|i| [i as u8, (i / 3) as u8, 7]).collect(),
        )
        .unwrap();
        let mask: Vec<bool> = (0..k.width * k.height).map(|i| i % 5 == 0).collect();
        write_depth_png(&seq.depth_path("robot", 1), &depth, 0.1).unwrap();
        write_rgb_png(&seq.rgb_path("robot", 1), &color).unwrap();
        write_mask_png(&seq.mask_path("robot", 1, 0), k.width, k.height, &mask).unwrap();
        crate::mesh::builtin("box").unwrap();
        std::fs::create_dir_all(root.join("models")).unwrap();
        std::fs::write(
            root.join("models/box.ply"),
            crate::mesh::builtin("box").unwrap().to_ply_bytes(),
        )
        .unwrap();

        assert_eq!(find_sequences(dir.path()).unwrap(), vec![root.clone()]);
        let back = Sequence::open(&root).unwrap();
        assert_eq!(back.rig, seq.rig);
        assert_eq!(
            back.cameras.keys().collect::<Vec<_>>(),
            seq.cameras.keys().collect::<Vec<_>>()
        );
        for (name, cam) in &seq.cameras {
            let b = &back.cameras[name];
            assert_eq!(b.gt_info, cam.gt_info);
            assert_eq!(b.frames.len(), cam.frames.len());
            for (f, m) in &cam.frames {
                let bm = &b.frames[f];
                assert_eq!(
                    (bm.stamp_ns, bm.intrinsics, bm.depth_scale),
                    (m.stamp_ns, m.intrinsics, m.depth_scale)
                );
                assert!(close(&bm.camera_from_world.unwrap(), &m.camera_from_world.unwrap()));
                for (g, bg) in cam.gt[f].iter().zip(&b.gt[f]) {
                    assert_eq!(g.obj_id, bg.obj_id);
                    assert!(close(&g.camera_from_object, &bg.camera_from_object));
                }
            }
        }
        let (o, bo) = (seq.odometry.as_ref().unwrap(), back.odometry.as_ref().unwrap());
        assert_eq!(o.len(), bo.len());
        for (k, s) in o {
            let b = &bo[k];
            assert_eq!(s.stamp_ns, b.stamp_ns);
            assert!(close(&s.odom_from_base, &b.odom_from_base));
            assert!(close(&s.world_from_odom, &b.world_from_odom));
            assert!(close(&s.base_from_camera, &b.base_from_camera));
            assert!(close(&s.world_from_camera(), &b.world_from_camera()));
        }
        // images: depth to 0.1 mm, colour and mask exactly
        let d = back.load_depth("robot", 1).unwrap();
        for (a, b) in depth.data_m.iter().zip(&d.data_m) {
            assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        }
        assert_eq!(back.load_rgb("robot", 1).unwrap().unwrap(), color);
        assert_eq!(back.load_mask("robot", 1, 0).unwrap().unwrap(), mask);
        assert_eq!(back.load_rgb("robot", 2).unwrap(), None);
        assert!(back.load_mesh("box").is_ok());
        assert!(matches!(back.load_mesh("mug"), Err(DatasetError::Mesh { .. })));
        assert!(matches!(
            back.load_mesh("nope"),
            Err(DatasetError::UnknownObject { .. })
        ));
        assert!(matches!(
            back.load_depth("ext9", 1),
            Err(DatasetError::UnknownCamera { .. })
        ));
        assert!(matches!(
            back.load_depth("robot", 9),
            Err(DatasetError::UnknownFrame { .. })
        ));
        assert!(matches!(back.load_depth("ext1", 1), Err(DatasetError::Read { .. })));
    }

    #[test]
    fn detections_follow_the_format_rules() {
        let seq = sample_sequence(Path::new("/nonexistent"));
        // the invisible second object never shows; the first is missing in ~10% of draws and
        // jittered by ~5% of its size
        let mut n = 0;
        let mut shifts = Vec::new();
        for seed in 0..400u64 {
            let d = seq.detections("robot", 1, seed);
            assert!(d.len() <= 1);
            for det in d {
                assert_eq!(det.object, "box");
                n += 1;
                shifts.push((det.bbox_xywh_px[0] + det.bbox_xywh_px[2] / 2.0 - (1.0 + 4.5)) / 9.0);
            }
        }
        assert!((330..=390).contains(&n), "{n} of 400 present");
        let sd = (shifts.iter().map(|s| s * s).sum::<f64>() / shifts.len() as f64).sqrt();
        assert!(sd > 0.02 && sd < 0.1, "jitter sd {sd} of the box width");
        assert_eq!(seq.detections("robot", 1, 5), seq.detections("robot", 1, 5));
        assert!(seq.detections("robot", 99, 5).is_empty());
        assert!(seq.detections("nope", 1, 5).is_empty());
    }

    #[test]
    fn bad_inputs_give_errors_with_paths() {
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(find_sequences(dir.path()), Err(DatasetError::NotASequence(_))));
        let root = dir.path().join("s");
        let seq = sample_sequence(&root);
        seq.write_json().unwrap();
        std::fs::write(root.join("robot/scene_gt.json"), "{ not json").unwrap();
        let e = Sequence::open(&root).unwrap_err();
        assert!(matches!(e, DatasetError::Json { .. }));
        assert!(e.to_string().contains("robot/scene_gt.json"), "{e}");
        seq.write_json().unwrap();
        std::fs::remove_file(root.join("odometry.json")).unwrap();
        assert!(matches!(Sequence::open(&root), Err(DatasetError::Invalid { .. })));
        let mut bad = seq.clone();
        bad.rig.target = Some("nothing".into());
        bad.write_json().unwrap();
        assert!(Sequence::open(&root).unwrap_err().to_string().contains("target"));
    }
}
