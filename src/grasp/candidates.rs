//! Grasps (the gripper pose relative to the object) and their generation along the object's
//! principal axes.

use super::{GraspError, GraspObject, Gripper};
use crate::geometry::Pose;
use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Least free space between each open pad and the object for a generated candidate.
pub const CANDIDATE_MIN_CLEARANCE_M: f64 = 0.004;
/// How far the palm stays from the object's surface at the deepest generated grasp.
pub const CANDIDATE_PALM_MARGIN_M: f64 = 0.008;

/// A grasp: where the gripper frame sits on the object. The gripper approaches along its +z
/// and closes along its x (see `gripper.rs`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Grasp {
    pub object_from_gripper: Pose,
    /// Approach direction (gripper +z) in the object frame.
    pub approach_in_object: [f64; 3],
    /// Closing axis (gripper x) in the object frame.
    pub closing_in_object: [f64; 3],
    /// Depth of the tool centre point past the object's surface that faces the palm.
    pub depth_m: f64,
    /// Width of the object's hull along the closing axis.
    pub width_m: f64,
    /// Human-readable name, e.g. `approach -a2, close a1` (a0 = longest principal axis).
    pub label: String,
}

impl Grasp {
    /// A grasp approaching along `approach` (object frame) and closing along `closing`
    /// (made orthogonal to the approach), centred on the object's hull across the closing
    /// plane, with the TCP `depth_m` past the first surface met along the approach.
    pub fn new(
        object: &GraspObject,
        approach: &Vector3<f64>,
        closing: &Vector3<f64>,
        depth_m: f64,
        label: &str,
    ) -> Result<Self, GraspError> {
        let z = approach
            .try_normalize(1e-9)
            .ok_or_else(|| GraspError::InvalidQuery("zero approach direction".into()))?;
        let x = (closing - z * closing.dot(&z))
            .try_normalize(1e-9)
            .ok_or_else(|| GraspError::InvalidQuery("closing axis parallel to the approach".into()))?;
        if !depth_m.is_finite() {
            return Err(GraspError::InvalidQuery(format!("depth_m must be finite, got {depth_m}")));
        }
        let y = z.cross(&x);
        let (x_lo, x_hi) = object.extent_along(&x);
        let (y_lo, y_hi) = object.extent_along(&y);
        let (z_lo, _) = object.extent_along(&z);
        let tcp = x * (x_lo + x_hi) * 0.5 + y * (y_lo + y_hi) * 0.5 + z * (z_lo + depth_m);
        let rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        Ok(Self {
            object_from_gripper: Pose::from_parts(
                Translation3::from(tcp),
                UnitQuaternion::from_rotation_matrix(&rot),
            ),
            approach_in_object: [z.x, z.y, z.z],
            closing_in_object: [x.x, x.y, x.z],
            depth_m,
            width_m: x_hi - x_lo,
            label: label.to_string(),
        })
    }

    /// A grasp from a gripper pose given by the caller: the other fields are measured on the
    /// object.
    pub fn from_pose(object: &GraspObject, object_from_gripper: Pose, label: &str) -> Self {
        let z = object_from_gripper.rotation * Vector3::z();
        let x = object_from_gripper.rotation * Vector3::x();
        let (x_lo, x_hi) = object.extent_along(&x);
        let (z_lo, _) = object.extent_along(&z);
        let depth_m = object_from_gripper.translation.vector.dot(&z) - z_lo;
        Self {
            object_from_gripper,
            approach_in_object: [z.x, z.y, z.z],
            closing_in_object: [x.x, x.y, x.z],
            depth_m,
            width_m: x_hi - x_lo,
            label: label.to_string(),
        }
    }

    /// The same grasp with the TCP moved `delta_m` further along the approach.
    pub fn deeper(&self, delta_m: f64) -> Self {
        let mut g = self.clone();
        let z = Vector3::from(self.approach_in_object);
        g.object_from_gripper.translation.vector += z * delta_m;
        g.depth_m += delta_m;
        g
    }
}

/// Candidate grasps along the object's principal axes: each of the 6 approach directions
/// (+- each axis) with each of the 2 other axes as closing axis, kept where the object's width
/// along the closing axis fits the stroke with [`CANDIDATE_MIN_CLEARANCE_M`] on each side.
/// The TCP goes to the middle of the object along the approach, or as deep as the fingers
/// reach. Top/side grasps relative to a table are among them; the decision ranks them.
pub fn generate_candidates(object: &GraspObject, gripper: &Gripper) -> Vec<Grasp> {
    let axes = object.principal_axes();
    let mut out = Vec::new();
    for i in 0..3 {
        let a: Vector3<f64> = axes.column(i).into();
        let (lo, hi) = object.extent_along(&a);
        let depth = ((hi - lo) * 0.5).min(gripper.reach_m() - CANDIDATE_PALM_MARGIN_M).max(0.0);
        for sign in [1.0, -1.0] {
            for j in 0..3 {
                if j == i {
                    continue;
                }
                let c: Vector3<f64> = axes.column(j).into();
                let (clo, chi) = object.extent_along(&c);
                if chi - clo + 2.0 * CANDIDATE_MIN_CLEARANCE_M > gripper.max_opening_m {
                    continue;
                }
                let label = format!(
                    "approach {}a{i}, close a{j}",
                    if sign > 0.0 { "+" } else { "-" }
                );
                if let Ok(g) = Grasp::new(object, &(a * sign), &c, depth, &label) {
                    out.push(g);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh;

    #[test]
    fn box_candidates_fit_the_stroke_and_sit_centred() {
        let m = mesh::builtin_box([0.16, 0.06, 0.21], [[1, 2, 3], [4, 5, 6]]);
        let o = GraspObject::new(&m).unwrap();
        let g = Gripper::default_parallel_jaw();
        let c = generate_candidates(&o, &g);
        // closing along y (0.06) from 4 approach directions (+-x, +-z); never along x or z
        assert_eq!(c.len(), 4, "{:?}", c.iter().map(|g| &g.label).collect::<Vec<_>>());
        for k in &c {
            assert!((k.width_m - 0.06).abs() < 1e-6);
            let x = k.object_from_gripper.rotation * Vector3::x();
            assert!(x.y.abs() > 0.999);
            let t = k.object_from_gripper.translation.vector;
            let z = Vector3::from(k.approach_in_object);
            // centred across, at the object's middle or the finger reach along the approach
            assert!((t - z * t.dot(&z)).norm() < 1e-6);
            assert!(k.depth_m <= g.reach_m());
        }
    }

    #[test]
    fn from_pose_measures_depth_and_width() {
        let m = mesh::builtin_cylinder(0.05, 0.14, 48, [[1, 2, 3], [4, 5, 6]]);
        let o = GraspObject::new(&m).unwrap();
        let top = Grasp::new(&o, &-Vector3::z(), &Vector3::x(), 0.03, "top").unwrap();
        let again = Grasp::from_pose(&o, top.object_from_gripper, "again");
        assert!((again.depth_m - 0.03).abs() < 1e-9);
        assert!((again.width_m - 0.1).abs() < 1e-3);
        // TCP 3 cm below the lid
        assert!((top.object_from_gripper.translation.vector.z - 0.04).abs() < 1e-9);
        assert!((top.deeper(0.01).object_from_gripper.translation.vector.z - 0.03).abs() < 1e-9);
    }
}
