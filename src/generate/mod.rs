//! The scene generator (`pregrasp generate`): multi-view sequences in the format of
//! `shared/design/multiview-bop.md`, reproducing the set-up of the paper (section V.A).
//!
//! A sequence: a table (a thin box, rendered but not tracked) on a floor, a random subset of
//! objects resting on it without overlap, two stationary external cameras about 3 m away, and
//! a robot camera on a base + arm that approaches one target object from about 3 m to 0.5 m
//! (the base drives on a curved path and stops at the table, the arm keeps extending), in some
//! sequences with a stretch in which the arm looks away so that the target leaves the robot
//! camera's view. Depth gets noise `N(0, (sigma d)^2)` per pixel. The odometry follows Thrun's
//! odometry motion model (it drifts); `world_from_odom` keeps the localised base within a small
//! bounded error of the truth ([`plan`]). `scene_gt_info` comes from the rendered instance mask
//! and each object's silhouette alone ([`crate::render::raster::silhouette`], [`gt_info`]).
//!
//! Library use: [`generate_sequence`] returns a sequence in memory (images included) for a
//! demo that replays it without touching disk; [`write_sequence`] streams one to disk.
//! The same seed gives the same sequence.

pub mod cli;
pub mod gt_info;
pub mod plan;
pub mod sim;

use crate::camera::{CameraError, ColorImage, DepthImage, Intrinsics};
use crate::dataset::{
    self, CameraStream, DatasetError, FrameMeta, GtInfo, GtObject, LocalisationSigma, Mount, OdometrySample, Plane,
    Rig, RigCamera, RigObject, Sequence, stream_seed,
};
use crate::geometry::Pose;
use crate::mesh::{self, Mesh, MeshError};
use crate::render::{ClipRange, RenderError, Renderer};
use crate::sensor::{CameraFrame, CameraMount, RobotOdometry};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Name of the robot camera (the reference camera) in generated rigs.
pub const ROBOT_CAMERA: &str = "robot";
/// Names of the stationary cameras in generated rigs.
pub const EXTERNAL_CAMERAS: [&str; 2] = ["ext1", "ext2"];
/// `depth_scale` of generated depth PNGs: 0.1 mm per unit (up to 6.5 m).
pub const DEPTH_SCALE: f64 = 0.1;
/// Clip range of generated images (the far plane keeps depth within the uint16 range).
pub const CLIP: ClipRange = ClipRange {
    near_m: 0.05,
    far_m: 6.5,
};
/// Smallest image side we generate, pixels.
pub const MIN_IMAGE_SIDE_PX: u32 = 16;
/// A random subset holds at most this many objects.
pub const MAX_RANDOM_OBJECTS: usize = 5;
/// Random subsets drawn before a layout error is reported.
const LAYOUT_ATTEMPTS: usize = 20;

#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    #[error("unknown object {name:?}; available: {}", available.join(", "))]
    UnknownObject { name: String, available: Vec<String> },
    #[error("object {0:?} is listed twice")]
    DuplicateObject(String),
    #[error("cannot load mesh {}: {source}", path.display())]
    Mesh { path: PathBuf, source: MeshError },
    #[error("cannot read the models folder {}: {source}", path.display())]
    Models { path: PathBuf, source: std::io::Error },
    #[error("the models folder {} holds no PLY, OBJ or STL mesh", .0.display())]
    NoModels(PathBuf),
    #[error("invalid settings: {0}")]
    Settings(String),
    #[error("camera settings: {0}")]
    Camera(#[from] CameraError),
    #[error("cannot lay out the scene: {0}")]
    Layout(String),
    #[error("rendering failed: {0}")]
    Render(#[from] RenderError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("output {} already exists and is not empty; remove it or choose another --out", .0.display())]
    OutputExists(PathBuf),
    #[error("cannot write {}: {source}", path.display())]
    Write { path: PathBuf, source: std::io::Error },
}

pub type Result<T, E = GenerateError> = std::result::Result<T, E>;

/// A mesh the generator may place.
#[derive(Debug, Clone)]
pub struct ModelSpec {
    pub name: String,
    pub obj_id: u32,
    pub mesh: Mesh,
}

/// The models of `models_dir` (PLY/OBJ/STL files, named by their stem; `obj_id` from a BOP
/// `models_info.json` when the folder has one, else the 1-based position in name order), or
/// the built-in objects without a folder. `names` selects (and orders) models; empty = all.
pub fn load_models(models_dir: Option<&Path>, names: &[String]) -> Result<Vec<ModelSpec>> {
    for (i, n) in names.iter().enumerate() {
        if names[..i].contains(n) {
            return Err(GenerateError::DuplicateObject(n.clone()));
        }
    }
    // (name, obj_id, source)
    let available: Vec<(String, u32, Option<PathBuf>)> = match models_dir {
        None => mesh::BUILTIN_OBJECTS
            .iter()
            .enumerate()
            .map(|(i, n)| (n.to_string(), i as u32 + 1, None))
            .collect(),
        Some(dir) => {
            let entries = std::fs::read_dir(dir).map_err(|source| GenerateError::Models {
                path: dir.to_path_buf(),
                source,
            })?;
            let mut files = Vec::new();
            for e in entries {
                let p = e
                    .map_err(|source| GenerateError::Models {
                        path: dir.to_path_buf(),
                        source,
                    })?
                    .path();
                if p.is_file() && mesh::MeshFormat::from_path(&p).is_some() {
                    files.push(p);
                }
            }
            files.sort();
            if files.is_empty() {
                return Err(GenerateError::NoModels(dir.to_path_buf()));
            }
            let ids = models_info_ids(dir);
            files
                .into_iter()
                .enumerate()
                .map(|(i, p)| {
                    let name = p
                        .file_stem()
                        .map(|s| s.to_string_lossy().into_owned())
                        .unwrap_or_default();
                    let id = ids.get(&name).copied().unwrap_or(i as u32 + 1);
                    (name, id, Some(p))
                })
                .collect()
        }
    };
    let wanted: Vec<&(String, u32, Option<PathBuf>)> = if names.is_empty() {
        available.iter().collect()
    } else {
        names
            .iter()
            .map(|n| {
                available
                    .iter()
                    .find(|a| &a.0 == n)
                    .ok_or_else(|| GenerateError::UnknownObject {
                        name: n.clone(),
                        available: available.iter().map(|a| a.0.clone()).collect(),
                    })
            })
            .collect::<Result<_>>()?
    };
    wanted
        .into_iter()
        .map(|(name, obj_id, path)| {
            let mesh = match path {
                Some(p) => Mesh::load(p).map_err(|source| GenerateError::Mesh {
                    path: p.clone(),
                    source,
                })?,
                None => mesh::builtin(name).ok_or_else(|| GenerateError::UnknownObject {
                    name: name.clone(),
                    available: mesh::BUILTIN_OBJECTS.iter().map(|s| s.to_string()).collect(),
                })?,
            };
            Ok(ModelSpec {
                name: name.clone(),
                obj_id: *obj_id,
                mesh,
            })
        })
        .collect()
}

/// `name -> obj_id` from a BOP-style `models_info.json` (`{"<obj_id>": {"name": ...}}`); empty
/// when there is none or it does not parse.
fn models_info_ids(dir: &Path) -> BTreeMap<String, u32> {
    #[derive(serde::Deserialize)]
    struct Entry {
        name: Option<String>,
    }
    let Ok(bytes) = std::fs::read(dir.join("models_info.json")) else {
        return BTreeMap::new();
    };
    let Ok(map) = serde_json::from_slice::<BTreeMap<u32, Entry>>(&bytes) else {
        return BTreeMap::new();
    };
    map.into_iter().filter_map(|(id, e)| e.name.map(|n| (n, id))).collect()
}

/// Settings of one generated sequence.
#[derive(Debug, Clone)]
pub struct GenerateConfig {
    /// The pool of models.
    pub models: Vec<ModelSpec>,
    /// Place every model of the pool; otherwise a random subset of 2 (or all, if fewer) to
    /// [`MAX_RANDOM_OBJECTS`] of them.
    pub place_all: bool,
    /// The target object (must be placed); `None`: a random placed object.
    pub target: Option<String>,
    pub frames: u32,
    pub width: u32,
    pub height: u32,
    /// Relative depth noise sigma: `N(0, (sigma d)^2)` per pixel.
    pub depth_noise_relative_sigma: f64,
    /// Capture-time offset of each further camera (ext1: +1x, ext2: +2x), milliseconds.
    pub stagger_ms: f64,
    pub frame_period_ms: f64,
    /// Thrun's alpha1..alpha4.
    pub odometry_noise_alpha: [f64; 4],
    pub localisation_sigma: LocalisationSigma,
    /// Probability that the robot camera looks away from the target for a stretch of frames.
    pub look_away_probability: f64,
    /// Probability that a box (rendered, not tracked) stands on the table between the target
    /// and the robot camera's path, hiding the target from the robot camera for a stretch
    /// (skipped when it does not fit between the objects).
    pub occluder_probability: f64,
    /// Write colour images and visible masks as well as depth.
    pub write_rgb: bool,
    pub write_masks: bool,
    /// Light the scene from each camera (a headlight: how codebook templates are rendered)
    /// instead of a directional light from above, at an azimuth and an elevation (30-80
    /// degrees) drawn per sequence. With a headlight the shading seen by every camera is the
    /// templates' own, a cue no real camera gives (the real mug's shading matches none of its
    /// templates): an evaluation on headlit scenes rewards an encoder for relying on it.
    pub headlight: bool,
}

impl GenerateConfig {
    /// The paper's set-up: 100 frames, 640x480, 5 % depth noise, all models placed.
    pub fn new(models: Vec<ModelSpec>) -> Self {
        Self {
            models,
            place_all: true,
            target: None,
            frames: 100,
            width: 640,
            height: 480,
            depth_noise_relative_sigma: 0.05,
            stagger_ms: 0.0,
            frame_period_ms: 100.0,
            odometry_noise_alpha: [0.02, 0.002, 0.02, 0.002],
            localisation_sigma: LocalisationSigma {
                translation_m: 0.015,
                rotation_rad: 0.009,
            },
            look_away_probability: 0.5,
            occluder_probability: 0.0,
            write_rgb: true,
            write_masks: true,
            headlight: false,
        }
    }

    /// Rejects settings that cannot give a sequence.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(GenerateError::Settings(m));
        if self.models.is_empty() {
            return bad("no objects to place".into());
        }
        if self.frames == 0 {
            return bad("--frames must be at least 1".into());
        }
        if self.width < MIN_IMAGE_SIDE_PX || self.height < MIN_IMAGE_SIDE_PX {
            return bad(format!(
                "image {}x{} is too small (at least {MIN_IMAGE_SIDE_PX} px per side)",
                self.width, self.height
            ));
        }
        plan::generated_intrinsics(self.width, self.height)?;
        if !(self.depth_noise_relative_sigma.is_finite() && (0.0..=0.5).contains(&self.depth_noise_relative_sigma)) {
            return bad(format!(
                "--depth-noise {} must lie in [0, 0.5]",
                self.depth_noise_relative_sigma
            ));
        }
        if !(self.frame_period_ms.is_finite() && self.frame_period_ms > 0.0) {
            return bad(format!("frame period {} ms must be positive", self.frame_period_ms));
        }
        if !(self.stagger_ms.is_finite() && self.stagger_ms >= 0.0 && 2.0 * self.stagger_ms < self.frame_period_ms) {
            return bad(format!(
                "--stagger-ms {} must lie in [0, {}) (half the frame period)",
                self.stagger_ms,
                self.frame_period_ms / 2.0
            ));
        }
        for (what, p) in [
            ("look-away", self.look_away_probability),
            ("occluder", self.occluder_probability),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(format!("{what} probability {p} must lie in [0, 1]"));
            }
        }
        if self.odometry_noise_alpha.iter().any(|a| !a.is_finite() || *a < 0.0) {
            return bad("odometry noise alphas must be finite and >= 0".into());
        }
        let l = self.localisation_sigma;
        if !(l.translation_m.is_finite()
            && l.translation_m >= 0.0
            && l.rotation_rad.is_finite()
            && l.rotation_rad >= 0.0)
        {
            return bad("localisation sigmas must be finite and >= 0".into());
        }
        if let Some(t) = &self.target
            && !self.models.iter().any(|m| &m.name == t)
        {
            return Err(GenerateError::UnknownObject {
                name: t.clone(),
                available: self.models.iter().map(|m| m.name.clone()).collect(),
            });
        }
        Ok(())
    }
}

/// The images of one camera frame (depth with noise).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameImages {
    pub depth: DepthImage,
    pub color: ColorImage,
    /// Visible mask per ground-truth instance (the order of `scene_gt`).
    pub masks: Vec<Vec<bool>>,
}

/// A generated sequence in memory.
#[derive(Debug, Clone)]
pub struct GeneratedSequence {
    /// Metadata, ground truth and odometry (`root` is empty until written).
    pub sequence: Sequence,
    /// The placed objects' meshes by name.
    pub meshes: BTreeMap<String, Mesh>,
    /// Per camera, per frame id.
    pub images: BTreeMap<String, BTreeMap<u32, FrameImages>>,
    /// The robot base's true pose per frame id (evaluation only).
    pub world_from_base_true: BTreeMap<u32, Pose>,
    /// Frames in which the robot camera looks away from the target.
    pub look_away_frames: Vec<u32>,
    /// The occluder box, if any: `world_from_box` and its size (x, y, z), metres.
    pub occluder: Option<(Pose, [f64; 3])>,
}

impl GeneratedSequence {
    /// What the tracker may know of the rig: the stationary cameras' calibration and the robot
    /// camera's arm pose at the first frame (later ones come with [`Self::robot_odometry`]).
    pub fn camera_mounts(&self) -> BTreeMap<String, CameraMount> {
        let mut out = BTreeMap::new();
        for (name, cam) in &self.sequence.rig.cameras {
            let mount = match cam.mount {
                Mount::Robot => {
                    let Some(first) = self.sequence.odometry.as_ref().and_then(|o| o.values().next()) else {
                        continue;
                    };
                    CameraMount::Robot {
                        base_from_camera: first.base_from_camera,
                    }
                }
                Mount::Stationary => {
                    let world_from_camera = self
                        .sequence
                        .cameras
                        .get(name)
                        .and_then(|c| c.frames.values().next())
                        .and_then(|f| f.camera_from_world)
                        .map(|p| p.inverse())
                        .unwrap_or_else(Pose::identity);
                    CameraMount::Stationary { world_from_camera }
                }
            };
            out.insert(name.clone(), mount);
        }
        out
    }

    /// One time step as the tracker takes it: every camera's noisy depth, colour and stand-in
    /// detections ([`Sequence::detections`] with `detection_seed`), sorted by capture time.
    pub fn camera_frames(&self, frame: u32, detection_seed: u64) -> Vec<CameraFrame> {
        let mut out: Vec<CameraFrame> = self
            .images
            .iter()
            .filter_map(|(cam, frames)| {
                let img = frames.get(&frame)?;
                let meta = self.sequence.cameras.get(cam)?.frames.get(&frame)?;
                Some(CameraFrame {
                    camera: cam.clone(),
                    stamp_ns: meta.stamp_ns,
                    intrinsics: meta.intrinsics,
                    depth: img.depth.clone(),
                    color: Some(img.color.clone()),
                    detections: self.sequence.detections(cam, frame, detection_seed),
                })
            })
            .collect();
        out.sort_by_key(|f| f.stamp_ns);
        out
    }

    /// The robot's odometry at a time step (no ground truth in it).
    pub fn robot_odometry(&self, frame: u32) -> Option<RobotOdometry> {
        let o = self.sequence.odometry.as_ref()?.get(&frame)?;
        Some(RobotOdometry {
            stamp_ns: o.stamp_ns,
            odom_from_base: o.odom_from_base,
            world_from_odom: o.world_from_odom,
            base_from_camera: o.base_from_camera,
        })
    }

    /// Writes the sequence into `dir` (created; meshes into `dir/models/`).
    pub fn write(&self, dir: &Path) -> Result<()> {
        let mut seq = self.sequence.clone();
        seq.root = dir.to_path_buf();
        seq.write_json()?;
        write_meshes(dir, &seq.rig, &self.meshes)?;
        for (cam, frames) in &self.images {
            for (frame, img) in frames {
                write_frame_images(&seq, cam, *frame, img, true, true)?;
            }
        }
        Ok(())
    }
}

/// Per frame id: capture stamp and `world_from_camera`.
type FramePoses = BTreeMap<u32, (i64, Pose)>;

/// Everything decided before rendering.
struct Prepared<'a> {
    config: &'a GenerateConfig,
    seed: u64,
    rig: Rig,
    /// The placed objects' models, in `scene_gt` order.
    models: Vec<&'a ModelSpec>,
    world_from_object: Vec<Pose>,
    /// The scene (objects, table, occluder, floor) and its light.
    scene: sim::SceneSim,
    /// Per camera: intrinsics, and per frame id the stamp and `world_from_camera`.
    cameras: BTreeMap<String, (Intrinsics, FramePoses)>,
    odometry: BTreeMap<u32, OdometrySample>,
    world_from_base_true: BTreeMap<u32, Pose>,
    look_away_frames: Vec<u32>,
    occluder: Option<(Pose, [f64; 3])>,
}

fn table_mesh() -> Mesh {
    let mut m = mesh::builtin_box(
        [plan::TABLE_SIZE_M[0], plan::TABLE_SIZE_M[1], plan::TABLE_THICKNESS_M],
        [[150, 110, 70], [150, 110, 70]],
    );
    for (c, v) in m.colors.iter_mut().zip(&m.vertices_m) {
        // a little grain so the colour image is not flat
        let g = ((v[0] * 37.0).sin() * 12.0) as i16;
        *c = c.map(|x| (x as i16 + g).clamp(0, 255) as u8);
    }
    m
}

/// The floor is tiled with boxes of this side (meshes may not exceed `MAX_EXTENT_M`), metres.
const FLOOR_TILE_M: f64 = 2.0;
/// Tiles per side of the floor (an 8 x 8 m floor around the table).
const FLOOR_TILES: i32 = 4;

fn floor_tile(dark: bool) -> Mesh {
    let c = if dark { [100, 100, 108] } else { [125, 122, 118] };
    mesh::builtin_box([FLOOR_TILE_M, FLOOR_TILE_M, 0.02], [c, c])
}

fn prepare<'a>(renderer: &Renderer, config: &'a GenerateConfig, seed: u64) -> Result<Prepared<'a>> {
    config.validate()?;
    let intrinsics = plan::generated_intrinsics(config.width, config.height)?;
    // which objects, which target; a random subset that does not fit is drawn again
    let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[b"objects"]));
    let mut place_rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[b"placement"]));
    let n = config.models.len();
    let meshes: Vec<&Mesh> = config.models.iter().map(|m| &m.mesh).collect();
    let wanted_target = config
        .target
        .as_ref()
        .and_then(|t| config.models.iter().position(|m| &m.name == t));
    let attempts = if config.place_all { 1 } else { LAYOUT_ATTEMPTS };
    let mut last_error = String::new();
    let mut layout = None;
    for _ in 0..attempts {
        let mut chosen: Vec<usize> = (0..n).collect();
        if !config.place_all {
            chosen.shuffle(&mut rng);
            let k = rng.random_range(n.min(2)..=n.min(MAX_RANDOM_OBJECTS));
            chosen.truncate(k);
        }
        let target_index = match wanted_target {
            Some(i) => {
                if !chosen.contains(&i) {
                    chosen.pop();
                    chosen.push(i);
                }
                i
            }
            None => chosen[rng.random_range(0..chosen.len())],
        };
        chosen.sort_unstable();
        match plan::place_objects(&meshes, &chosen, &mut place_rng) {
            Ok(placed) => {
                layout = Some((placed, target_index));
                break;
            }
            Err(e) => last_error = e,
        }
    }
    let (placed, target_index) = layout.ok_or(GenerateError::Layout(last_error))?;
    let models: Vec<&ModelSpec> = placed.iter().map(|p| &config.models[p.model]).collect();
    let world_from_object: Vec<Pose> = placed.iter().map(|p| p.world_from_object).collect();
    let target_pos = placed
        .iter()
        .find(|p| p.model == target_index)
        .map(|p| {
            let c = config.models[p.model].mesh.bounds().center_m();
            p.world_from_object * Point3::from(c)
        })
        .ok_or_else(|| GenerateError::Layout("the target was not placed".into()))?;
    let centre = Point3::from(
        placed
            .iter()
            .map(|p| p.world_from_object.translation.vector)
            .sum::<nalgebra::Vector3<f64>>()
            / placed.len() as f64,
    );

    let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[b"cameras"]));
    let ext = plan::external_cameras(&centre, &mut rng);
    let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[b"robot"]));
    let period_ns = (config.frame_period_ms * 1e6).round() as i64;
    let robot = plan::robot_plan(
        &target_pos,
        &plan::RobotSettings {
            frames: config.frames,
            frame_period_ns: period_ns,
            odometry_noise_alpha: config.odometry_noise_alpha,
            localisation_sigma: config.localisation_sigma,
            look_away_probability: config.look_away_probability,
        },
        &mut rng,
    );

    let stagger_ns = (config.stagger_ms * 1e6).round() as i64;
    let mut cameras = BTreeMap::new();
    let robot_frames: BTreeMap<u32, (i64, Pose)> = (0..config.frames)
        .map(|k| {
            let i = k as usize;
            (
                k,
                (
                    k as i64 * period_ns,
                    robot.world_from_base[i] * robot.base_from_camera[i],
                ),
            )
        })
        .collect();
    cameras.insert(ROBOT_CAMERA.to_string(), (intrinsics, robot_frames));
    for (j, (name, wfc)) in EXTERNAL_CAMERAS.iter().zip(ext).enumerate() {
        let frames = (0..config.frames)
            .map(|k| (k, (k as i64 * period_ns + (j as i64 + 1) * stagger_ns, wfc)))
            .collect();
        cameras.insert(name.to_string(), (intrinsics, frames));
    }

    let mut rig_cameras = BTreeMap::new();
    rig_cameras.insert(ROBOT_CAMERA.to_string(), RigCamera { mount: Mount::Robot });
    for name in EXTERNAL_CAMERAS {
        rig_cameras.insert(
            name.to_string(),
            RigCamera {
                mount: Mount::Stationary,
            },
        );
    }
    let rig = Rig {
        format: dataset::RIG_FORMAT.to_string(),
        reference_camera: ROBOT_CAMERA.to_string(),
        cameras: rig_cameras,
        objects: models
            .iter()
            .map(|m| RigObject {
                obj_id: m.obj_id,
                name: m.name.clone(),
                mesh: format!("models/{}.ply", m.name),
            })
            .collect(),
        target: Some(config.models[target_index].name.clone()),
        depth_noise_relative_sigma: Some(config.depth_noise_relative_sigma),
        odometry_noise_alpha: Some(config.odometry_noise_alpha),
        localisation_sigma: Some(config.localisation_sigma),
        support_plane: Some(Plane {
            normal: [0.0, 0.0, 1.0],
            point_m: [0.0, 0.0, 0.0],
        }),
    };

    let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[b"occluder"]));
    let occluder = if rng.random::<f64>() < config.occluder_probability {
        let target_placed = placed
            .iter()
            .find(|p| p.model == target_index)
            .ok_or_else(|| GenerateError::Layout("the target was not placed".into()))?;
        let robot_eyes: Vec<Point3<f64>> = robot
            .world_from_base
            .iter()
            .zip(&robot.base_from_camera)
            .map(|(b, c)| Point3::from((b * c).translation.vector))
            .collect();
        plan::place_occluder(&meshes, &placed, target_placed, &robot_eyes, &mut rng)
    } else {
        None
    };

    // the scene to render: objects first (instance ids from 1), then table, occluder and floor
    // (id 0: not tracked)
    let objects = models
        .iter()
        .zip(&world_from_object)
        .map(|(m, wfo)| sim::Placed {
            mesh: Arc::new(m.mesh.clone()),
            world_from_object: *wfo,
        })
        .collect();
    let mut props = vec![sim::Placed {
        mesh: Arc::new(table_mesh()),
        world_from_object: translation(0.0, 0.0, -plan::TABLE_THICKNESS_M / 2.0),
    }];
    if let Some((pose, size)) = &occluder {
        props.push(sim::Placed {
            mesh: Arc::new(mesh::builtin_box(*size, [[60, 110, 170], [200, 200, 200]])),
            world_from_object: *pose,
        });
    }
    let tiles = [Arc::new(floor_tile(false)), Arc::new(floor_tile(true))];
    for i in 0..FLOOR_TILES {
        for j in 0..FLOOR_TILES {
            let offset = (FLOOR_TILES as f64 - 1.0) / 2.0;
            props.push(sim::Placed {
                mesh: tiles[((i + j) % 2) as usize].clone(),
                world_from_object: translation(
                    (i as f64 - offset) * FLOOR_TILE_M,
                    (j as f64 - offset) * FLOOR_TILE_M,
                    -plan::TABLE_HEIGHT_M - 0.01,
                ),
            });
        }
    }
    let mut scene = sim::SceneSim::new(objects, props, CLIP, [0, 0, 0]);

    // the light: its own stream, so that the scene is the same with a headlight
    let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(seed, &[b"light"]));
    scene.towards_light_in_world = (!config.headlight).then(|| {
        let elevation = rng.random_range(30f64..80.0).to_radians();
        let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
        Vector3::new(
            elevation.cos() * azimuth.cos(),
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
        )
    });
    scene.upload(renderer)?;

    let odometry = robot.odometry.iter().enumerate().map(|(k, o)| (k as u32, *o)).collect();
    let world_from_base_true = robot
        .world_from_base
        .iter()
        .enumerate()
        .map(|(k, p)| (k as u32, *p))
        .collect();
    Ok(Prepared {
        config,
        seed,
        rig,
        models,
        world_from_object,
        scene,
        cameras,
        odometry,
        world_from_base_true,
        look_away_frames: robot.look_away_frames,
        occluder,
    })
}

fn translation(x: f64, y: f64, z: f64) -> Pose {
    Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::identity())
}

/// A noiseless render of one camera pose with its ground truth.
struct CleanFrame {
    depth: DepthImage,
    color: ColorImage,
    masks: Vec<Vec<bool>>,
    gt: Vec<GtObject>,
    gt_info: Vec<GtInfo>,
}

impl Prepared<'_> {
    fn clean(&self, renderer: &Renderer, intrinsics: &Intrinsics, world_from_camera: &Pose) -> Result<CleanFrame> {
        // the scene was uploaded in `prepare`
        let r = self.scene.render_gpu(renderer, intrinsics, world_from_camera)?;
        let camera_from_world = world_from_camera.inverse();
        let masks = self.scene.visible_masks(&r);
        let mut gt = Vec::with_capacity(self.models.len());
        let mut gt_info = Vec::with_capacity(self.models.len());
        for ((m, wfo), visible) in self.models.iter().zip(&self.world_from_object).zip(&masks) {
            let camera_from_object = camera_from_world * wfo;
            let alone = crate::render::raster::silhouette(&m.mesh, &camera_from_object, intrinsics);
            gt_info.push(gt_info::gt_info(&alone, visible, intrinsics.width));
            gt.push(GtObject {
                obj_id: m.obj_id,
                camera_from_object,
            });
        }
        Ok(CleanFrame {
            depth: r.depth,
            color: r.color,
            masks,
            gt,
            gt_info,
        })
    }

    /// Depth with `N(0, (sigma d)^2)` noise, seeded per camera and frame.
    fn noisy_depth(&self, clean: &DepthImage, camera: &str, frame: u32) -> DepthImage {
        let sigma = self.config.depth_noise_relative_sigma;
        if sigma == 0.0 {
            return clean.clone();
        }
        let mut rng = ChaCha8Rng::seed_from_u64(stream_seed(
            self.seed,
            &[b"depth", camera.as_bytes(), &frame.to_le_bytes()],
        ));
        let max_m = (u16::MAX as f64 * DEPTH_SCALE / 1000.0) as f32;
        let data_m = clean
            .data_m
            .iter()
            .map(|&d| {
                if d > 0.0 {
                    let n: f64 = StandardNormal.sample(&mut rng);
                    ((d as f64 * (1.0 + sigma * n)) as f32).clamp(0.0, max_m)
                } else {
                    0.0
                }
            })
            .collect();
        DepthImage {
            width: clean.width,
            height: clean.height,
            data_m,
        }
    }

    /// Renders every camera frame (stationary cameras once), calling `sink` for each in
    /// parallel; returns the per-camera BOP metadata and ground truth.
    fn render_all<F>(&self, renderer: &Renderer, sink: F) -> Result<BTreeMap<String, CameraStream>>
    where
        F: Fn(&str, u32, FrameImages) -> Result<()> + Sync,
    {
        let mut streams = BTreeMap::new();
        for (name, (intrinsics, frames)) in &self.cameras {
            let stationary = self.rig.cameras.get(name).map(|c| c.mount) == Some(Mount::Stationary);
            let fixed = if stationary {
                match frames.values().next() {
                    Some((_, wfc)) => Some(self.clean(renderer, intrinsics, wfc)?),
                    None => None,
                }
            } else {
                None
            };
            let results: Vec<(u32, Vec<GtObject>, Vec<GtInfo>)> = frames
                .par_iter()
                .map(|(frame, (_, wfc))| {
                    let owned;
                    let clean = match &fixed {
                        Some(c) => c,
                        None => {
                            owned = self.clean(renderer, intrinsics, wfc)?;
                            &owned
                        }
                    };
                    let images = FrameImages {
                        depth: self.noisy_depth(&clean.depth, name, *frame),
                        color: clean.color.clone(),
                        masks: clean.masks.clone(),
                    };
                    sink(name, *frame, images)?;
                    Ok((*frame, clean.gt.clone(), clean.gt_info.clone()))
                })
                .collect::<Result<_>>()?;
            let mut stream = CameraStream::default();
            for (frame, gt, info) in results {
                let (stamp_ns, wfc) = frames[&frame];
                stream.frames.insert(
                    frame,
                    FrameMeta {
                        stamp_ns,
                        intrinsics: *intrinsics,
                        depth_scale: DEPTH_SCALE,
                        camera_from_world: Some(wfc.inverse()),
                    },
                );
                stream.gt.insert(frame, gt);
                stream.gt_info.insert(frame, info);
            }
            streams.insert(name.clone(), stream);
        }
        Ok(streams)
    }

    fn sequence(&self, root: PathBuf, cameras: BTreeMap<String, CameraStream>) -> Sequence {
        Sequence {
            root,
            rig: self.rig.clone(),
            cameras,
            odometry: Some(self.odometry.clone()),
        }
    }

    fn meshes(&self) -> BTreeMap<String, Mesh> {
        self.models.iter().map(|m| (m.name.clone(), m.mesh.clone())).collect()
    }
}

/// Generates one sequence in memory (all images held: about 3.5 MB per camera frame at
/// 640x480; use smaller images or fewer frames for long demos).
pub fn generate_sequence(renderer: &Renderer, config: &GenerateConfig, seed: u64) -> Result<GeneratedSequence> {
    let prep = prepare(renderer, config, seed)?;
    let images = std::sync::Mutex::new(BTreeMap::<String, BTreeMap<u32, FrameImages>>::new());
    let cameras = prep.render_all(renderer, |cam, frame, img| {
        images
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(cam.to_string())
            .or_default()
            .insert(frame, img);
        Ok(())
    })?;
    Ok(GeneratedSequence {
        sequence: prep.sequence(PathBuf::new(), cameras),
        meshes: prep.meshes(),
        images: images.into_inner().unwrap_or_else(|e| e.into_inner()),
        world_from_base_true: prep.world_from_base_true.clone(),
        look_away_frames: prep.look_away_frames.clone(),
        occluder: prep.occluder,
    })
}

/// Generates one sequence straight into `dir` (created), frames rendered and written in
/// parallel. Returns the sequence as [`Sequence::open`] would read it.
pub fn write_sequence(renderer: &Renderer, config: &GenerateConfig, seed: u64, dir: &Path) -> Result<Sequence> {
    let prep = prepare(renderer, config, seed)?;
    // folders first (the JSON comes last, once the ground truth is known)
    let empty = prep.sequence(dir.to_path_buf(), BTreeMap::new());
    for cam in prep.rig.cameras.keys() {
        for sub in ["depth", "rgb", "mask_visib"] {
            let p = dir.join(cam).join(sub);
            std::fs::create_dir_all(&p).map_err(|source| GenerateError::Write { path: p, source })?;
        }
    }
    let cameras = prep.render_all(renderer, |cam, frame, img| {
        write_frame_images(&empty, cam, frame, &img, config.write_rgb, config.write_masks)
    })?;
    let seq = prep.sequence(dir.to_path_buf(), cameras);
    seq.write_json()?;
    write_meshes(dir, &seq.rig, &prep.meshes())?;
    Ok(seq)
}

fn write_frame_images(
    seq: &Sequence,
    camera: &str,
    frame: u32,
    img: &FrameImages,
    rgb: bool,
    masks: bool,
) -> Result<()> {
    dataset::write_depth_png(&seq.depth_path(camera, frame), &img.depth, DEPTH_SCALE)?;
    if rgb {
        dataset::write_rgb_png(&seq.rgb_path(camera, frame), &img.color)?;
    }
    if masks {
        for (i, m) in img.masks.iter().enumerate() {
            dataset::write_mask_png(&seq.mask_path(camera, frame, i), img.depth.width, img.depth.height, m)?;
        }
    }
    Ok(())
}

fn write_meshes(dir: &Path, rig: &Rig, meshes: &BTreeMap<String, Mesh>) -> Result<()> {
    for o in &rig.objects {
        let Some(m) = meshes.get(&o.name) else { continue };
        let path = dir.join(&o.mesh);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|source| GenerateError::Write {
                path: parent.to_path_buf(),
                source,
            })?;
        }
        std::fs::write(&path, m.to_ply_bytes()).map_err(|source| GenerateError::Write { path, source })?;
    }
    Ok(())
}

/// Writes `n` sequences (`000000`, `000001`, ...) into `out` atomically: everything goes into
/// a temporary folder next to `out` that is renamed at the end (removed on error). `out` must
/// not exist or be empty. Sequence `i` gets the seed `stream_seed(seed, ["sequence", i])` and,
/// when `targets` is not empty, the target `targets[i % len]`.
pub fn write_sequences(
    renderer: &Renderer,
    config: &GenerateConfig,
    n: u32,
    seed: u64,
    targets: &[String],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    if n == 0 {
        return Err(GenerateError::Settings("--sequences must be at least 1".into()));
    }
    config.validate()?;
    let mut configs = Vec::new();
    for i in 0..n {
        let mut c = config.clone();
        if !targets.is_empty() {
            c.target = Some(targets[i as usize % targets.len()].clone());
        }
        c.validate()?;
        configs.push(c);
    }
    if out.exists() {
        let empty = out.is_dir()
            && std::fs::read_dir(out)
                .map_err(|source| GenerateError::Write {
                    path: out.to_path_buf(),
                    source,
                })?
                .next()
                .is_none();
        if !empty {
            return Err(GenerateError::OutputExists(out.to_path_buf()));
        }
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|source| GenerateError::Write {
        path: parent.clone(),
        source,
    })?;
    let name = out
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = tempfile::Builder::new()
        .prefix(&format!(".{name}.tmp-"))
        .tempdir_in(&parent)
        .map_err(|source| GenerateError::Write {
            path: parent.clone(),
            source,
        })?;
    let mut dirs = Vec::new();
    for (i, c) in configs.iter().enumerate() {
        let seq_name = format!("{i:06}");
        let s = stream_seed(seed, &[b"sequence", &(i as u64).to_le_bytes()]);
        tracing::info!(sequence = %seq_name, target = ?c.target, "generating");
        write_sequence(renderer, c, s, &tmp.path().join(&seq_name))?;
        dirs.push(out.join(seq_name));
    }
    if out.exists() {
        std::fs::remove_dir(out).map_err(|source| GenerateError::Write {
            path: out.to_path_buf(),
            source,
        })?;
    }
    let kept = tmp.keep();
    std::fs::rename(&kept, out).map_err(|source| {
        let _ = std::fs::remove_dir_all(&kept);
        GenerateError::Write {
            path: out.to_path_buf(),
            source,
        }
    })?;
    Ok(dirs)
}
