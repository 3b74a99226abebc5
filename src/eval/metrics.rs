//! The paper's metrics (Table I) and the standard ones, per frame.
//!
//! Definitions (`shared/design/tracker-notes.md`, "Evaluation"):
//! - translation error: Euclidean distance between estimated and true position (m); also the
//!   L1 sum of the three axes' absolute errors;
//! - orientation error "summed over three axes": the L1 norm, in degrees, of the rotation
//!   vector (axis x angle) of `R_est^T * R_gt`; also the geodesic angle and a symmetry-aware
//!   geodesic angle (the minimum over the object's near-symmetries);
//! - translation standard deviation: given by the tracker (square root of the trace of the
//!   particles' weighted covariance), see [`translation_std_m`] for the definition;
//! - ADD: mean distance of the model points under the two poses; ADD-S: mean distance of each
//!   estimated model point to the nearest true model point; their AUC up to 0.10 m
//!   (YCB-Video papers), see [`auc`].

use crate::geometry::Pose;
use crate::mesh::Mesh;
use nalgebra::{Point3, UnitQuaternion, Vector3};

pub use crate::symmetry::{NEAR_SYMMETRY_THRESHOLD_M, Symmetries};
use rand::SeedableRng;

/// The upper limit of the ADD / ADD-S accuracy curves (YCB-Video convention).
pub const AUC_MAX_THRESHOLD_M: f64 = 0.10;

/// Number of model points used for ADD / ADD-S.
pub const DEFAULT_MODEL_POINTS: usize = 500;

/// Euclidean distance between the estimated and the true position (m).
pub fn translation_error_m(estimate: &Pose, truth: &Pose) -> f64 {
    (estimate.translation.vector - truth.translation.vector).norm()
}

/// Sum over the three axes of the absolute position error (m).
pub fn translation_error_l1_m(estimate: &Pose, truth: &Pose) -> f64 {
    (estimate.translation.vector - truth.translation.vector).abs().sum()
}

/// The paper's orientation error: the L1 norm (degrees) of the rotation vector of
/// `R_est^T * R_gt`.
pub fn orientation_error_l1_deg(estimate: &UnitQuaternion<f64>, truth: &UnitQuaternion<f64>) -> f64 {
    let delta = estimate.inverse() * truth;
    delta.scaled_axis().abs().sum().to_degrees()
}

/// Geodesic angle (degrees, in [0, 180]) between two rotations.
pub fn geodesic_error_deg(estimate: &UnitQuaternion<f64>, truth: &UnitQuaternion<f64>) -> f64 {
    estimate.angle_to(truth).to_degrees()
}

/// The square root of the trace of a weighted covariance of positions: the RMS distance of
/// the points from their weighted mean (m). Weights need not be normalised; `None` when they
/// sum to zero or the lists differ in length.
pub fn translation_std_m(positions_m: &[[f64; 3]], weights: &[f64]) -> Option<f64> {
    if positions_m.len() != weights.len() || positions_m.is_empty() {
        return None;
    }
    let total: f64 = weights.iter().sum();
    if total <= 0.0 || !total.is_finite() {
        return None;
    }
    let mut mean = Vector3::zeros();
    for (p, w) in positions_m.iter().zip(weights) {
        mean += Vector3::from(*p) * (*w / total);
    }
    let mut var = 0.0;
    for (p, w) in positions_m.iter().zip(weights) {
        var += (Vector3::from(*p) - mean).norm_squared() * (*w / total);
    }
    Some(var.sqrt())
}

/// Points on a model's surface (object frame), for ADD and ADD-S, and the surface itself.
#[derive(Clone)]
pub struct ModelPoints {
    pub points_m: Vec<Point3<f64>>,
    surface: parry3d::shape::TriMesh,
}

impl std::fmt::Debug for ModelPoints {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModelPoints")
            .field("points", &self.points_m.len())
            .finish()
    }
}

impl ModelPoints {
    /// `n` points drawn uniformly over the surface with a fixed seed (reproducible).
    /// `None` for a mesh parry3d rejects (no triangles).
    pub fn from_mesh(mesh: &Mesh, n: usize) -> Option<Self> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let surface = mesh.to_parry()?;
        Some(Self {
            points_m: mesh.sample_surface(n, &mut rng),
            surface,
        })
    }

    /// ADD (m): mean distance between each model point under the estimate and under the truth.
    pub fn add_m(&self, estimate: &Pose, truth: &Pose) -> f64 {
        if self.points_m.is_empty() {
            return 0.0;
        }
        self.points_m
            .iter()
            .map(|p| (estimate * p - truth * p).norm())
            .sum::<f64>()
            / self.points_m.len() as f64
    }

    /// ADD-S (m): mean distance of each model point under the estimate to the nearest point
    /// of the model's surface under the truth. (Nearest *surface* point rather than nearest
    /// model vertex: a sparse point set would add its spacing, several millimetres, to every
    /// error.)
    pub fn add_s_m(&self, estimate: &Pose, truth: &Pose) -> f64 {
        self.mean_surface_distance_m(&(truth.inverse() * estimate))
    }

    /// Mean distance of the points moved by `surface_from_points` to the surface.
    fn mean_surface_distance_m(&self, surface_from_points: &Pose) -> f64 {
        use parry3d::query::PointQuery;
        if self.points_m.is_empty() {
            return 0.0;
        }
        let total: f64 = self
            .points_m
            .iter()
            .map(|p| {
                let q = surface_from_points * p;
                let v = parry3d::math::Vector::new(q.x as f32, q.y as f32, q.z as f32);
                (self.surface.distance_to_local_point(v, false) as f64).max(0.0)
            })
            .sum();
        total / self.points_m.len() as f64
    }
}

/// Area under the accuracy-threshold curve from 0 to `max_m`, normalised to [0, 1]:
/// `(1 / max) * integral_0^max share(err < t) dt`, which equals the mean of
/// `1 - min(err, max) / max`. Errors that are `None` (no estimate) count as failures.
pub fn auc(errors_m: &[Option<f64>], max_m: f64) -> Option<f64> {
    if errors_m.is_empty() || max_m <= 0.0 {
        return None;
    }
    let s: f64 = errors_m
        .iter()
        .map(|e| match e {
            Some(e) if e.is_finite() => 1.0 - e.clamp(0.0, max_m) / max_m,
            _ => 0.0,
        })
        .sum();
    Some(s / errors_m.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use nalgebra::{Isometry3, Translation3, Unit};

    use crate::testing::shared_dir;

    fn pose(t: [f64; 3], q: UnitQuaternion<f64>) -> Pose {
        Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), q)
    }

    #[test]
    fn identity_gives_zero_errors() {
        let p = pose([0.1, -0.2, 1.5], UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0));
        assert_eq!(translation_error_m(&p, &p), 0.0);
        assert_relative_eq!(orientation_error_l1_deg(&p.rotation, &p.rotation), 0.0, epsilon = 1e-9);
        assert_relative_eq!(geodesic_error_deg(&p.rotation, &p.rotation), 0.0, epsilon = 1e-6);
        let mp = ModelPoints::from_mesh(&crate::mesh::builtin("mug").expect("builtin"), 200).expect("mesh");
        assert_relative_eq!(mp.add_m(&p, &p), 0.0, epsilon = 1e-12);
        assert_relative_eq!(mp.add_s_m(&p, &p), 0.0, epsilon = 1e-6);
    }

    #[test]
    fn known_translation_and_rotation() {
        let truth = pose([0.0, 0.0, 1.0], UnitQuaternion::identity());
        let est = pose([0.03, -0.04, 1.0], UnitQuaternion::identity());
        assert_relative_eq!(translation_error_m(&est, &truth), 0.05, epsilon = 1e-12);
        assert_relative_eq!(translation_error_l1_m(&est, &truth), 0.07, epsilon = 1e-12);
        // 30 degrees about the axis (1, 1, 0)/sqrt 2: rotation vector components 30/sqrt2 each.
        let axis = Unit::new_normalize(Vector3::new(1.0, 1.0, 0.0));
        let r = UnitQuaternion::from_axis_angle(&axis, 30f64.to_radians());
        assert_relative_eq!(
            geodesic_error_deg(&r, &UnitQuaternion::identity()),
            30.0,
            epsilon = 1e-9
        );
        assert_relative_eq!(
            orientation_error_l1_deg(&r, &UnitQuaternion::identity()),
            2.0 * 30.0 / 2f64.sqrt(),
            epsilon = 1e-9
        );
        // About a single axis, L1 = geodesic.
        let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.5);
        assert_relative_eq!(
            orientation_error_l1_deg(&rz, &UnitQuaternion::identity()),
            0.5f64.to_degrees(),
            epsilon = 1e-9
        );
        // ADD of a pure translation is its length.
        let mp = ModelPoints::from_mesh(&crate::mesh::builtin("box").expect("builtin"), 100).expect("mesh");
        assert_relative_eq!(mp.add_m(&est, &truth), 0.05, epsilon = 1e-9);
    }

    #[test]
    fn symmetric_flip_of_a_box() {
        let sym = Symmetries::for_ycb("003_cracker_box").expect("known");
        assert_eq!(sym.discrete.len(), 4, "identity and three 180 degree flips");
        let truth = UnitQuaternion::from_euler_angles(0.2, 0.1, -0.4);
        let flip = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
        let est = truth * flip;
        assert_relative_eq!(geodesic_error_deg(&est, &truth), 180.0, epsilon = 1e-6);
        assert!(sym.error_deg(&est, &truth) < 1e-6);
        // A 90 degree turn about z is no symmetry of the cracker box.
        let quarter = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
        assert_relative_eq!(sym.error_deg(&(truth * quarter), &truth), 90.0, epsilon = 1e-6);
        // The mug has none.
        let mug = Symmetries::for_ycb("025_mug").expect("known");
        assert_relative_eq!(mug.error_deg(&est, &truth), 180.0, epsilon = 1e-6);
    }

    #[test]
    fn continuous_symmetry_of_the_can() {
        let sym = Symmetries::for_ycb("002_master_chef_can").expect("known");
        assert!(sym.continuous_axis.is_some());
        let truth = UnitQuaternion::from_euler_angles(0.5, 0.0, 0.3);
        let spin = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 1.234);
        assert!(sym.error_deg(&(truth * spin), &truth) < 1e-6);
        let upside_down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        assert!(sym.error_deg(&(truth * upside_down), &truth) < 1e-6);
        let tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 10f64.to_radians());
        assert_relative_eq!(sym.error_deg(&(truth * tilt), &truth), 10.0, epsilon = 1e-6);
    }

    #[test]
    fn symmetries_measured_from_meshes() {
        let can = Symmetries::from_mesh(
            &crate::mesh::builtin("can").expect("builtin"),
            NEAR_SYMMETRY_THRESHOLD_M,
        );
        assert_eq!(can.continuous_axis.map(|a| a.into_inner()), Some(Vector3::z()));
        // The YCB mug (a real scan with an open top and a large handle) has none.
        let ycb_mug = crate::mesh::Mesh::load(&shared_dir().join("ycb/025_mug.ply")).expect("ycb mug");
        let mug = Symmetries::from_mesh(&ycb_mug, NEAR_SYMMETRY_THRESHOLD_M);
        assert!(mug.continuous_axis.is_none());
        assert_eq!(mug.discrete.len(), 1, "{:?}", mug.discrete);
        let bx = Symmetries::from_mesh(
            &crate::mesh::builtin("box").expect("builtin"),
            NEAR_SYMMETRY_THRESHOLD_M,
        );
        assert!(bx.continuous_axis.is_none());
        assert_eq!(bx.discrete.len(), 4);
    }

    #[test]
    fn add_s_forgives_a_symmetric_flip_and_add_does_not() {
        let mesh = crate::mesh::builtin("can").expect("builtin");
        let mp = ModelPoints::from_mesh(&mesh, 400).expect("mesh");
        let truth = pose([0.0, 0.0, 1.0], UnitQuaternion::identity());
        let est = pose(
            [0.0, 0.0, 1.0],
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 1.0),
        );
        assert!(mp.add_m(&est, &truth) > 0.02);
        assert!(mp.add_s_m(&est, &truth) < 0.002, "{}", mp.add_s_m(&est, &truth));
    }

    #[test]
    fn std_and_auc() {
        let s = translation_std_m(&[[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]], &[1.0, 1.0]).expect("valid");
        assert_relative_eq!(s, 0.1, epsilon = 1e-12);
        assert!(translation_std_m(&[[0.0; 3]], &[0.0]).is_none());
        let a = auc(&[Some(0.0), Some(0.05), Some(0.2), None], 0.1).expect("non-empty");
        assert_relative_eq!(a, (1.0 + 0.5 + 0.0 + 0.0) / 4.0, epsilon = 1e-12);
    }
}
