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
/// Slab positions for off-centre candidates step by this share of the finger width.
pub const SLAB_STEP_SHARE: f64 = 0.25;
/// Least number of surface samples in a slab for an off-centre candidate.
const SLAB_MIN_POINTS: usize = 10;
/// A second, shallower candidate sits at this share of the deepest depth (more room for the
/// palm when the pose is uncertain along the approach, less pad on the object).
pub const CANDIDATE_SHALLOW_SHARE: f64 = 0.6;

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
            return Err(GraspError::InvalidQuery(format!(
                "depth_m must be finite, got {depth_m}"
            )));
        }
        let y = z.cross(&x);
        let (x_lo, x_hi) = object.extent_along(&x);
        let (y_lo, y_hi) = object.extent_along(&y);
        let (z_lo, _) = object.extent_along(&z);
        let across = x * (x_lo + x_hi) * 0.5 + y * (y_lo + y_hi) * 0.5;
        Ok(Self::frame(object, x, y, z, across, z_lo, depth_m, x_hi - x_lo, label))
    }

    /// A grasp with its TCP at `across` (the object-frame point whose closing and lateral
    /// components place the TCP) and `depth_m` past `near_m` along the approach.
    #[allow(clippy::too_many_arguments)]
    fn frame(
        _object: &GraspObject,
        x: Vector3<f64>,
        y: Vector3<f64>,
        z: Vector3<f64>,
        across: Vector3<f64>,
        near_m: f64,
        depth_m: f64,
        width_m: f64,
        label: &str,
    ) -> Self {
        let across = across - z * across.dot(&z);
        let tcp = across + z * (near_m + depth_m);
        let rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        Self {
            object_from_gripper: Pose::from_parts(Translation3::from(tcp), UnitQuaternion::from_rotation_matrix(&rot)),
            approach_in_object: [z.x, z.y, z.z],
            closing_in_object: [x.x, x.y, x.z],
            depth_m,
            width_m,
            label: label.to_string(),
        }
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
/// reach, and (where different by more than 2 mm) to [`CANDIDATE_SHALLOW_SHARE`] of that.
/// Top/side grasps relative to a table are among them; the decision ranks them.
pub fn generate_candidates(object: &GraspObject, gripper: &Gripper) -> Vec<Grasp> {
    let axes = object.principal_axes();
    let mut out = Vec::new();
    for i in 0..3 {
        let a: Vector3<f64> = axes.column(i).into();
        let (lo, hi) = object.extent_along(&a);
        let deep = ((hi - lo) * 0.5)
            .min(gripper.reach_m() - CANDIDATE_PALM_MARGIN_M)
            .max(0.0);
        let shallow = ((gripper.reach_m() - CANDIDATE_PALM_MARGIN_M) * CANDIDATE_SHALLOW_SHARE).max(0.0);
        let depths: Vec<f64> = if deep - shallow > 0.002 {
            vec![deep, shallow]
        } else {
            vec![deep]
        };
        for sign in [1.0, -1.0] {
            for j in 0..3 {
                if j == i {
                    continue;
                }
                let c: Vector3<f64> = axes.column(j).into();
                let (clo, chi) = object.extent_along(&c);
                if chi - clo + 2.0 * CANDIDATE_MIN_CLEARANCE_M > gripper.max_opening_m {
                    if let Some(g) = off_centre(object, gripper, &(a * sign), &c, i, j) {
                        out.push(g);
                    }
                    continue;
                }
                for &depth in &depths {
                    let label = format!(
                        "approach {}a{i}, close a{j}, depth {:.0} mm",
                        if sign > 0.0 { "+" } else { "-" },
                        depth * 1e3
                    );
                    if let Ok(g) = Grasp::new(object, &(a * sign), &c, depth, &label) {
                        out.push(g);
                    }
                }
            }
        }
    }
    out
}

/// Where the whole object is too wide for the stroke along `c`, the slab the fingers sweep
/// (the finger width across the closing plane) may still fit: a handle, a neck. Among the
/// slabs (surface samples within half a finger width of a position along `approach x c`)
/// whose width along `c` fits, the one nearest the surface centroid is taken.
fn off_centre(
    object: &GraspObject,
    gripper: &Gripper,
    a: &Vector3<f64>,
    c: &Vector3<f64>,
    i: usize,
    j: usize,
) -> Option<Grasp> {
    let b = a.cross(c);
    let pts = object.surface_samples_m();
    if pts.is_empty() {
        return None;
    }
    let half = gripper.finger_size_m[1] * 0.5;
    let centroid = pts.iter().map(|p| p.coords.dot(&b)).sum::<f64>() / pts.len() as f64;
    let (b_lo, b_hi) = pts
        .iter()
        .map(|p| p.coords.dot(&b))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| (l.min(v), h.max(v)));
    let step = (gripper.finger_size_m[1] * SLAB_STEP_SHARE).max(1e-3);
    let mut best: Option<(f64, f64, f64, f64, f64, f64)> = None; // (score, b0, c_mid, a_near, a_far, width)
    let mut b0 = b_lo + half;
    while b0 <= b_hi - half + 1e-9 {
        let slab: Vec<_> = pts.iter().filter(|p| (p.coords.dot(&b) - b0).abs() <= half).collect();
        if slab.len() >= SLAB_MIN_POINTS {
            let range = |d: &Vector3<f64>| {
                slab.iter()
                    .map(|p| p.coords.dot(d))
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| (l.min(v), h.max(v)))
            };
            let (c_lo, c_hi) = range(c);
            let (a_lo, a_hi) = range(a);
            if c_hi - c_lo + 2.0 * CANDIDATE_MIN_CLEARANCE_M <= gripper.max_opening_m {
                let score = (b0 - centroid).abs();
                if best.is_none_or(|bst| score < bst.0) {
                    best = Some((score, b0, (c_lo + c_hi) * 0.5, a_lo, a_hi, c_hi - c_lo));
                }
            }
        }
        b0 += step;
    }
    let (_, b0, c_mid, a_near, a_far, width) = best?;
    let depth = ((a_far - a_near) * 0.5)
        .min(gripper.reach_m() - CANDIDATE_PALM_MARGIN_M)
        .max(0.0);
    let label = format!(
        "approach {}a{i}, close a{j}, off-centre {:.0} mm, depth {:.0} mm",
        if a.dot(&object.principal_axes().column(i)) > 0.0 {
            "+"
        } else {
            "-"
        },
        b0 * 1e3,
        depth * 1e3
    );
    Some(Grasp::frame(
        object,
        *c,
        b,
        *a,
        c * c_mid + b * b0,
        a_near,
        depth,
        width,
        &label,
    ))
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
        // closing along y (0.06) from 4 approach directions (+-x, +-z), 2 depths each; never
        // along x or z
        assert_eq!(c.len(), 8, "{:?}", c.iter().map(|g| &g.label).collect::<Vec<_>>());
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

    /// A hammer lying flat: a 160 mm head (along x) at y = 0.1 and a 30 mm handle along y.
    fn hammer() -> crate::mesh::Mesh {
        let head = mesh::builtin_box([0.16, 0.04, 0.03], [[1, 2, 3], [4, 5, 6]]);
        let handle = mesh::builtin_box([0.03, 0.2, 0.03], [[1, 2, 3], [4, 5, 6]]);
        let mut v = head.vertices_m.clone();
        for p in &mut v {
            p[1] += 0.1;
        }
        let n = v.len() as u32;
        v.extend(handle.vertices_m.iter().copied());
        let mut t = head.triangles.clone();
        t.extend(handle.triangles.iter().map(|t| [t[0] + n, t[1] + n, t[2] + n]));
        crate::mesh::Mesh::new(v, None, t).unwrap()
    }

    #[test]
    fn too_wide_overall_but_a_handle_fits_gives_an_off_centre_candidate() {
        let o = GraspObject::with_kind(&hammer(), crate::grasp::SolidKind::ConvexHull).unwrap();
        let g = Gripper::default_parallel_jaw();
        let c = generate_candidates(&o, &g);
        let off: Vec<_> = c.iter().filter(|k| k.label.contains("off-centre")).collect();
        assert!(!off.is_empty(), "{:?}", c.iter().map(|g| &g.label).collect::<Vec<_>>());
        // closing along x across the handle, away from the head
        let k = off
            .iter()
            .find(|k| Vector3::from(k.closing_in_object).x.abs() > 0.99)
            .expect("an off-centre grasp closing along x");
        assert!(k.width_m < 0.035, "{}", k.width_m);
        let t = k.object_from_gripper.translation.vector;
        assert!(t.y < 0.1 - 0.02 - g.finger_size_m[1] * 0.5 + 1e-6, "{t}");
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
