//! The registry: cameras, objects and grippers as validated domain types, kept in memory and
//! written to the store on every change. Ids and names are checked here, so that every ingest
//! path (HTTP, a ROS bridge) gets the same rules.

use super::checks::{check_id, check_name, check_pose};
use super::error::ServiceError;
use super::store::{Store, Table};
use super::{Limits, ServiceState};
use crate::camera::Intrinsics;
use crate::geometry::{Pose, PoseXyzw};
use crate::grasp::Gripper;
use crate::mesh::{Mesh, MeshFormat};
use crate::sensor::CameraMount;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Id of the gripper every server has (the default parallel-jaw gripper).
pub const DEFAULT_GRIPPER: &str = "default";

/// A registered camera: validated intrinsics and mount.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub id: String,
    pub intrinsics: Intrinsics,
    pub mount: CameraMount,
}

impl Camera {
    pub fn is_robot(&self) -> bool {
        matches!(self.mount, CameraMount::Robot { .. })
    }
    /// `base_from_camera` of a robot camera.
    pub fn base_from_camera(&self) -> Option<Pose> {
        match self.mount {
            CameraMount::Robot { base_from_camera } => Some(base_from_camera),
            CameraMount::Stationary { .. } => None,
        }
    }
}

/// State of an object's codebook.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CodebookState {
    Pending,
    Building,
    Ready,
    Failed,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CodebookStatus {
    pub status: CodebookState,
    /// 0..=1.
    pub progress: f64,
    /// Rotation grid step of the codebook being built or ready (degrees).
    pub grid_step_deg: Option<u32>,
    /// Why the build failed.
    pub error: Option<String>,
}

impl CodebookStatus {
    pub fn pending() -> Self {
        Self {
            status: CodebookState::Pending,
            progress: 0.0,
            grid_step_deg: None,
            error: None,
        }
    }
}

/// A registered object's record (stored as JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectInfo {
    pub id: String,
    /// Display name.
    pub name: String,
    pub n_vertices: usize,
    pub n_triangles: usize,
    pub diameter_m: f64,
    /// SHA-256 of the geometry (the key of the codebook cache).
    pub content_hash: String,
    /// Whether the codebook uses the mesh's colours (false: depth alone, for a mesh whose
    /// colours do not match the cameras').
    #[serde(default = "default_use_color")]
    pub use_color: bool,
    pub codebook: CodebookStatus,
}

fn default_use_color() -> bool {
    true
}

/// An object in memory: its record and mesh.
#[derive(Debug, Clone)]
pub struct ObjectEntry {
    pub info: ObjectInfo,
    pub mesh: Arc<Mesh>,
}

/// What the registry knows (in memory; every change is also written to the store).
#[derive(Default)]
pub struct Registry {
    pub cameras: BTreeMap<String, Camera>,
    pub objects: BTreeMap<String, ObjectEntry>,
    pub grippers: BTreeMap<String, Gripper>,
    /// Bumped on every camera or object change (the tracking worker rebuilds on change).
    pub version: u64,
}

/// A camera as the store keeps it: the JSON of earlier versions (poses as
/// `{rotation_xyzw, translation_m}`), so that existing data folders load.
#[derive(Serialize, Deserialize)]
struct StoredCamera {
    id: String,
    intrinsics: Intrinsics,
    mount: StoredMount,
}

#[derive(Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
enum StoredMount {
    Stationary { world_from_camera: PoseXyzw },
    Robot { base_from_camera: PoseXyzw },
}

impl StoredCamera {
    fn from_camera(c: &Camera) -> Self {
        Self {
            id: c.id.clone(),
            intrinsics: c.intrinsics,
            mount: match c.mount {
                CameraMount::Stationary { world_from_camera } => StoredMount::Stationary {
                    world_from_camera: PoseXyzw::from_pose(&world_from_camera),
                },
                CameraMount::Robot { base_from_camera } => StoredMount::Robot {
                    base_from_camera: PoseXyzw::from_pose(&base_from_camera),
                },
            },
        }
    }
    fn to_camera(&self) -> Result<Camera, ServiceError> {
        let mount = match &self.mount {
            StoredMount::Stationary { world_from_camera } => CameraMount::Stationary {
                world_from_camera: world_from_camera.to_pose().map_err(invalid("world_from_camera"))?,
            },
            StoredMount::Robot { base_from_camera } => CameraMount::Robot {
                base_from_camera: base_from_camera.to_pose().map_err(invalid("base_from_camera"))?,
            },
        };
        let intrinsics = Intrinsics::new(self.intrinsics.width, self.intrinsics.height, self.intrinsics.k)
            .map_err(invalid("intrinsics"))?;
        Ok(Camera {
            id: self.id.clone(),
            intrinsics,
            mount,
        })
    }
}

fn invalid<E: std::fmt::Display>(what: &'static str) -> impl Fn(E) -> ServiceError {
    move |e| ServiceError::Invalid(format!("{what}: {e}"))
}

impl Registry {
    /// Reads the cameras, objects and grippers of the store (a record that no longer
    /// validates is logged and skipped); adds the default gripper when missing.
    pub fn load(store: &Store) -> anyhow::Result<Self> {
        let mut reg = Self::default();
        for (id, cam) in store.list::<StoredCamera>(Table::Cameras)? {
            match cam.to_camera() {
                Ok(c) => {
                    reg.cameras.insert(id, c);
                }
                Err(e) => tracing::warn!("stored camera {id} skipped: {e}"),
            }
        }
        for (id, mut info) in store.list::<ObjectInfo>(Table::Objects)? {
            let Some(bytes) = store.get_bytes(Table::Meshes, &id)? else {
                tracing::warn!("object {id} has no stored mesh; skipped");
                continue;
            };
            let mesh = Mesh::from_bytes(&bytes, MeshFormat::Ply)?;
            // Codebooks are rebuilt (or loaded from the cache folder) after a restart.
            info.codebook = CodebookStatus::pending();
            reg.objects.insert(
                id,
                ObjectEntry {
                    info,
                    mesh: Arc::new(mesh),
                },
            );
        }
        for (id, g) in store.list::<Gripper>(Table::Grippers)? {
            match g.validate() {
                Ok(()) => {
                    reg.grippers.insert(id, g);
                }
                Err(e) => tracing::warn!("stored gripper {id} skipped: {e}"),
            }
        }
        if !reg.grippers.contains_key(DEFAULT_GRIPPER) {
            let g = Gripper::default_parallel_jaw();
            store.put(Table::Grippers, DEFAULT_GRIPPER, &g)?;
            reg.grippers.insert(DEFAULT_GRIPPER.to_string(), g);
        }
        Ok(reg)
    }

    /// The reference camera of the tracker: the first robot camera, else the first camera.
    pub fn reference_camera(&self) -> Option<String> {
        self.cameras
            .values()
            .find(|c| c.is_robot())
            .or_else(|| self.cameras.values().next())
            .map(|c| c.id.clone())
    }

    /// The registered robot camera's `base_from_camera`, when there is one.
    pub fn robot_base_from_camera(&self) -> Option<Pose> {
        self.cameras.values().find_map(Camera::base_from_camera)
    }
}

/// Checks that intrinsics are plausible for a camera: a focal length up to 100 image widths, a
/// principal point within an image of the image.
fn check_plausible(i: &Intrinsics) -> Result<(), ServiceError> {
    let k = &i.k;
    let (w, h) = (f64::from(i.width), f64::from(i.height));
    let plausible = k[0] <= 100.0 * w && k[4] <= 100.0 * h && k[2].abs() <= 2.0 * w && k[5].abs() <= 2.0 * h;
    if plausible {
        Ok(())
    } else {
        Err(ServiceError::Invalid(format!(
            "intrinsics: focal lengths must be at most 100 image sizes and the principal point within the image's neighbourhood, got k = {k:?}"
        )))
    }
}

impl ServiceState {
    fn limits(&self) -> Limits {
        self.config.limits
    }

    /// Registers (or replaces) a camera in the registry and the store; a replaced camera's
    /// waiting frames are freed (they were taken with the old intrinsics).
    pub fn register_camera(
        &self,
        id: &str,
        intrinsics: Intrinsics,
        mount: CameraMount,
    ) -> Result<Camera, ServiceError> {
        check_id("camera", id)?;
        check_plausible(&intrinsics)?;
        match &mount {
            CameraMount::Stationary { world_from_camera } => check_pose("mount.world_from_camera", world_from_camera)?,
            CameraMount::Robot { base_from_camera } => check_pose("mount.base_from_camera", base_from_camera)?,
        }
        let cam = Camera {
            id: id.to_string(),
            intrinsics,
            mount,
        };
        let limits = self.limits();
        let px = u64::from(intrinsics.width) * u64::from(intrinsics.height);
        if px > limits.max_camera_pixels {
            return Err(ServiceError::LimitReached(format!(
                "camera '{id}' is {}x{} = {px} pixels; this server takes at most {} (--max-camera-pixels)",
                intrinsics.width, intrinsics.height, limits.max_camera_pixels
            )));
        }
        let mut reg = self.registry_mut();
        if cam.is_robot() && reg.cameras.values().any(|c| c.is_robot() && c.id != cam.id) {
            return Err(ServiceError::Conflict(
                "only one robot camera is supported; delete the other robot camera first".into(),
            ));
        }
        if !reg.cameras.contains_key(id) && reg.cameras.len() >= limits.max_cameras {
            return Err(ServiceError::LimitReached(format!(
                "this server takes at most {} cameras (--max-cameras); delete one first",
                limits.max_cameras
            )));
        }
        self.store.put(Table::Cameras, id, &StoredCamera::from_camera(&cam))?;
        self.ingest().forget_camera(id);
        reg.cameras.insert(cam.id.clone(), cam.clone());
        reg.version += 1;
        Ok(cam)
    }

    pub fn delete_camera(&self, id: &str) -> Result<(), ServiceError> {
        let mut reg = self.registry_mut();
        if !reg.cameras.contains_key(id) {
            return Err(ServiceError::not_found("camera", id));
        }
        self.store.delete(Table::Cameras, id)?;
        self.ingest().forget_camera(id);
        reg.cameras.remove(id);
        reg.version += 1;
        Ok(())
    }

    /// Registers (or replaces) an object: store first, then memory. `use_color`: see
    /// [`ObjectInfo::use_color`].
    pub fn register_object(
        &self,
        id: &str,
        name: &str,
        mesh: Mesh,
        use_color: bool,
    ) -> Result<ObjectInfo, ServiceError> {
        check_id("object", id)?;
        check_name(name, self.limits().max_name_chars)?;
        mesh.validate().map_err(invalid("mesh"))?;
        let mut info = ObjectInfo {
            id: id.to_string(),
            name: name.to_string(),
            n_vertices: mesh.vertices_m.len(),
            n_triangles: mesh.triangles.len(),
            diameter_m: mesh.diameter_m(),
            content_hash: mesh.content_hash(),
            use_color,
            codebook: CodebookStatus::pending(),
        };
        let mut reg = self.registry_mut();
        let max = self.limits().max_objects;
        if !reg.objects.contains_key(id) && reg.objects.len() >= max {
            return Err(ServiceError::LimitReached(format!(
                "this server takes at most {max} objects (--max-objects); delete one first"
            )));
        }
        // the same mesh again (a replay registering its objects) keeps its codebook; a failed
        // build is tried again
        if let Some(old) = reg.objects.get(id)
            && old.info.content_hash == info.content_hash
            && old.info.use_color == info.use_color
            && old.info.codebook.status != CodebookState::Failed
        {
            info.codebook = old.info.codebook.clone();
        }
        self.store.put_bytes(Table::Meshes, id, &mesh.to_ply_bytes())?;
        self.store.put(Table::Objects, id, &info)?;
        reg.objects.insert(
            id.to_string(),
            ObjectEntry {
                info: info.clone(),
                mesh: Arc::new(mesh),
            },
        );
        reg.version += 1;
        Ok(info)
    }

    pub fn delete_object(&self, id: &str) -> Result<(), ServiceError> {
        let mut reg = self.registry_mut();
        if !reg.objects.contains_key(id) {
            return Err(ServiceError::not_found("object", id));
        }
        self.store.delete(Table::Objects, id)?;
        self.store.delete(Table::Meshes, id)?;
        reg.objects.remove(id);
        reg.version += 1;
        drop(reg);
        self.codebooks.forget(id);
        self.truth.lock().unwrap_or_else(|p| p.into_inner()).remove(id);
        Ok(())
    }

    /// Updates an object's codebook status (memory only: statuses are recomputed after a
    /// restart) when the object still has the mesh `content_hash` and colour choice
    /// `use_color` the status is about; returns whether it did (a replaced mesh has a new build
    /// ahead of it).
    pub fn set_codebook_status(&self, id: &str, content_hash: &str, use_color: bool, status: CodebookStatus) -> bool {
        match self.registry_mut().objects.get_mut(id) {
            Some(o) if o.info.content_hash == content_hash && o.info.use_color == use_color => {
                o.info.codebook = status;
                true
            }
            _ => false,
        }
    }

    /// Registers (or replaces) a gripper after checking its geometry.
    pub fn register_gripper(&self, id: &str, gripper: Gripper) -> Result<Gripper, ServiceError> {
        check_id("gripper", id)?;
        gripper.validate().map_err(|e| ServiceError::Invalid(e.to_string()))?;
        let mut reg = self.registry_mut();
        let max = self.limits().max_grippers;
        if !reg.grippers.contains_key(id) && reg.grippers.len() >= max {
            return Err(ServiceError::LimitReached(format!(
                "this server takes at most {max} grippers (--max-grippers); delete one first"
            )));
        }
        self.store.put(Table::Grippers, id, &gripper)?;
        reg.grippers.insert(id.to_string(), gripper.clone());
        Ok(gripper)
    }

    pub fn delete_gripper(&self, id: &str) -> Result<(), ServiceError> {
        let mut reg = self.registry_mut();
        if !reg.grippers.contains_key(id) {
            return Err(ServiceError::not_found("gripper", id));
        }
        self.store.delete(Table::Grippers, id)?;
        reg.grippers.remove(id);
        Ok(())
    }

    /// The gripper model of a registered id.
    pub fn gripper(&self, id: &str) -> Result<Gripper, ServiceError> {
        self.registry()
            .grippers
            .get(id)
            .cloned()
            .ok_or_else(|| ServiceError::not_found("gripper", id))
    }
}
