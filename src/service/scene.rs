//! What the service knows about the scene beyond the tracks: the support plane (the table, in
//! the world frame), ground truth for display, and the cameras' places for drawing.

use super::ServiceState;
use super::checks::{check_pose, shorten};
use super::error::ServiceError;
use super::ingest::check_stamp;
use super::store::{SUPPORT_PLANE_KEY, Store, Table};
use crate::geometry::Pose;
use crate::grasp::SupportPlane;
use crate::sensor::CameraMount;

pub use super::checks::MAX_POSITION_M;

/// Most trajectory points served.
pub const MAX_TRAJECTORY_POINTS: usize = 500;

/// Checks a plane (finite, non-zero normal, a point within [`MAX_POSITION_M`]) and normalises
/// its normal.
pub fn validate_plane(p: &SupportPlane) -> Result<SupportPlane, ServiceError> {
    let n = nalgebra::Vector3::from(p.normal);
    let ok = p.normal.iter().chain(&p.point_m).all(|v| v.is_finite())
        && n.norm() > 1e-9
        && nalgebra::Vector3::from(p.point_m).norm() <= MAX_POSITION_M;
    if !ok {
        return Err(ServiceError::Invalid(format!(
            "support plane needs finite numbers, a non-zero normal and a point within {MAX_POSITION_M} m"
        )));
    }
    let n = n.normalize();
    Ok(SupportPlane {
        normal: [n.x, n.y, n.z],
        point_m: p.point_m,
    })
}

/// The support plane saved by the last run (an unreadable one is logged and ignored).
pub(super) fn load_support_plane(store: &Store) -> Option<SupportPlane> {
    let bytes = store
        .get_bytes(Table::Scene, SUPPORT_PLANE_KEY)
        .map_err(|e| tracing::warn!("reading the support plane: {e}"))
        .ok()??;
    serde_json::from_slice::<SupportPlane>(&bytes)
        .map_err(|e| tracing::warn!("support plane unreadable, ignored: {e}"))
        .ok()
        .and_then(|p| validate_plane(&p).ok())
}

/// A camera's place for drawing.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPlace {
    pub camera: super::registry::Camera,
    /// Fixed for stationary cameras; the latest estimate for the robot camera.
    pub world_from_camera: Option<Pose>,
    pub latest_stamp_ns: Option<i64>,
}

/// What the dashboard draws around the tracks.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneState {
    pub support_plane: Option<SupportPlane>,
    pub cameras: Vec<CameraPlace>,
    /// Robot base positions in the world frame, oldest first.
    pub robot_trajectory_m: Vec<[f64; 3]>,
}

impl ServiceState {
    /// Sets (or clears) the support plane, in memory and in the store; returns it normalised.
    pub fn set_support_plane(&self, plane: Option<SupportPlane>) -> Result<Option<SupportPlane>, ServiceError> {
        let plane = plane.as_ref().map(validate_plane).transpose()?;
        match &plane {
            Some(p) => self.store.put(Table::Scene, SUPPORT_PLANE_KEY, p)?,
            None => {
                self.store.delete(Table::Scene, SUPPORT_PLANE_KEY)?;
            }
        }
        *self.support_plane.lock().unwrap_or_else(|p| p.into_inner()) = plane;
        Ok(plane)
    }

    /// Takes ground truth for display (`world_from_object` per registered object id); the
    /// tracker never reads it.
    pub fn set_truth(&self, stamp_ns: i64, objects: Vec<(String, Pose)>) -> Result<(), ServiceError> {
        if !self.config.accept_truth {
            return Err(ServiceError::Disabled(
                "this server does not accept ground truth (start it with --accept-truth or --demo)".into(),
            ));
        }
        check_stamp(stamp_ns).map_err(|e| ServiceError::Invalid(format!("stamp_ns: {e}")))?;
        for (o, pose) in &objects {
            check_pose(&format!("world_from_object of '{}'", shorten(o)), pose)?;
        }
        {
            // one entry per registered object: the map stays as small as the registry
            let reg = self.registry();
            if let Some((o, _)) = objects.iter().find(|(o, _)| !reg.objects.contains_key(o)) {
                return Err(ServiceError::Invalid(format!(
                    "ground truth names unknown object '{}'",
                    shorten(o)
                )));
            }
        }
        let mut truth = self.truth.lock().unwrap_or_else(|p| p.into_inner());
        for (object, pose) in objects {
            truth.insert(object, (stamp_ns, pose));
        }
        Ok(())
    }

    /// The cameras' places, the support plane and the robot's path.
    pub fn scene(&self) -> SceneState {
        let world_from_reference = self.tracking.board().world_from_reference;
        let cams: Vec<_> = self.registry().cameras.values().cloned().collect();
        let support_plane = self.support_plane();
        let ingest = self.ingest();
        let cameras = cams
            .into_iter()
            .map(|c| CameraPlace {
                world_from_camera: match c.mount {
                    CameraMount::Stationary { world_from_camera } => Some(world_from_camera),
                    CameraMount::Robot { .. } => world_from_reference,
                },
                latest_stamp_ns: ingest.latest(&c.id).map(|f| f.stamp_ns),
                camera: c,
            })
            .collect();
        SceneState {
            support_plane,
            cameras,
            robot_trajectory_m: ingest.trajectory_m(MAX_TRAJECTORY_POINTS),
        }
    }
}
