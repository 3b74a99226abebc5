//! Rigid transforms, the rotation grid of the method, and allocentric <-> egocentric rotations.
//!
//! Conventions (stated once, used everywhere):
//! - A transform is named `target_from_source`: `world_from_camera * point_in_camera` gives the
//!   point in the world frame. [`Pose`] is an `Isometry3<f64>` (metres, radians).
//! - Quaternions are read and written as `[x, y, z, w]`.
//! - Camera frames are optical frames: x right, y down, z forward.
//!
//! # The rotation grid (the Euler convention)
//! A bin is `(elevation, azimuth, in-plane)`, each a multiple of the step (5 degrees by default:
//! 37 x 72 x 72 bins). The rotation of a bin is `camera_from_object`, built as
//! `R(e, a, theta) = Rz(theta) * V(e, a)^T` where `V(e, a)` (object_from_camera0) has as columns
//! the axes of a camera that sits on the viewing sphere at direction
//! `d = (sin e cos a, sin e sin a, cos e)` (object frame) and looks at the object's origin:
//! `z_c = -d`, `x_c = (-sin a, cos a, 0)`, `y_c = z_c x x_c`. Elevation 0 is the camera above the
//! object's +z pole. `theta` is a rotation about the camera's optical axis, so the 72 in-plane
//! bins of one viewpoint are 2-D rotations of one centred image.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// A rigid transform `target_from_source` in metres.
pub type Pose = Isometry3<f64>;

/// Tolerance on the norm of a quaternion given by a caller (1 +- this).
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GeometryError {
    #[error("{what} contains a non-finite number")]
    NonFinite { what: &'static str },
    #[error("quaternion [x, y, z, w] has norm {norm:.6}; it must be a unit quaternion (1 +- {tol})")]
    NonUnitQuaternion { norm: f64, tol: f64 },
    #[error("rotation matrix is not orthonormal with determinant +1")]
    NotARotation,
    #[error("grid step {step_deg} degrees must divide 180 and lie in 1..=90")]
    BadGridStep { step_deg: u32 },
}

/// A pose as it travels in files and over the wire: translation in metres, quaternion x, y, z, w.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseXyzw {
    pub rotation_xyzw: [f64; 4],
    pub translation_m: [f64; 3],
}

impl PoseXyzw {
    /// Checks finiteness and unit norm (renormalising within the tolerance).
    pub fn to_pose(&self) -> Result<Pose, GeometryError> {
        pose_from_xyzw(self.translation_m, self.rotation_xyzw)
    }
    pub fn from_pose(pose: &Pose) -> Self {
        let (translation_m, rotation_xyzw) = pose_to_xyzw(pose);
        Self {
            rotation_xyzw,
            translation_m,
        }
    }
    pub fn identity() -> Self {
        Self {
            rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
            translation_m: [0.0; 3],
        }
    }
}

/// Builds a pose from a translation (m) and a quaternion `[x, y, z, w]`, rejecting non-finite
/// numbers and quaternions whose norm is not 1 within [`QUATERNION_NORM_TOLERANCE`].
pub fn pose_from_xyzw(translation_m: [f64; 3], q_xyzw: [f64; 4]) -> Result<Pose, GeometryError> {
    if translation_m.iter().any(|v| !v.is_finite()) {
        return Err(GeometryError::NonFinite { what: "translation" });
    }
    Ok(Isometry3::from_parts(
        Translation3::new(translation_m[0], translation_m[1], translation_m[2]),
        quaternion_from_xyzw(q_xyzw)?,
    ))
}

/// A unit quaternion from `[x, y, z, w]`, checked as [`pose_from_xyzw`] does.
pub fn quaternion_from_xyzw(q: [f64; 4]) -> Result<UnitQuaternion<f64>, GeometryError> {
    if q.iter().any(|v| !v.is_finite()) {
        return Err(GeometryError::NonFinite { what: "quaternion" });
    }
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(GeometryError::NonUnitQuaternion {
            norm,
            tol: QUATERNION_NORM_TOLERANCE,
        });
    }
    Ok(UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        q[3], q[0], q[1], q[2],
    )))
}

/// `(translation_m, [x, y, z, w])` of a pose.
pub fn pose_to_xyzw(pose: &Pose) -> ([f64; 3], [f64; 4]) {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    ([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

/// A pose from a row-major 3x3 rotation and a translation, as BOP files store them.
/// The rotation is re-orthonormalised; one that is far from a rotation is rejected.
pub fn pose_from_rt(r_row_major: &[f64; 9], t: [f64; 3]) -> Result<Pose, GeometryError> {
    if r_row_major.iter().chain(t.iter()).any(|v| !v.is_finite()) {
        return Err(GeometryError::NonFinite {
            what: "rotation matrix or translation",
        });
    }
    let m = Matrix3::from_row_slice(r_row_major);
    let should_be_identity = m.transpose() * m;
    if (should_be_identity - Matrix3::identity()).abs().max() > 1e-2 || m.determinant() < 0.0 {
        return Err(GeometryError::NotARotation);
    }
    let rot = Rotation3::from_matrix_eps(&m, 1e-9, 100, Rotation3::identity());
    Ok(Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_rotation_matrix(&rot),
    ))
}

/// Row-major 3x3 rotation and translation of a pose (BOP layout).
pub fn pose_to_rt(pose: &Pose) -> ([f64; 9], [f64; 3]) {
    let m = pose.rotation.to_rotation_matrix();
    let m = m.matrix();
    let mut r = [0.0; 9];
    for row in 0..3 {
        for col in 0..3 {
            r[row * 3 + col] = m[(row, col)];
        }
    }
    let t = pose.translation.vector;
    (r, [t.x, t.y, t.z])
}

/// Geodesic angle between two rotations, radians in [0, pi].
pub fn rotation_angle_rad(a: &UnitQuaternion<f64>, b: &UnitQuaternion<f64>) -> f64 {
    a.angle_to(b)
}

/// The rotation that takes the optical axis `(0, 0, 1)` onto the ray towards `point_in_camera`
/// (the shortest arc). Identity for a point on the axis or at the origin.
pub fn ray_rotation(point_in_camera: &Vector3<f64>) -> UnitQuaternion<f64> {
    let n = point_in_camera.norm();
    if n < 1e-12 {
        return UnitQuaternion::identity();
    }
    UnitQuaternion::rotation_between(&Vector3::z(), &(point_in_camera / n)).unwrap_or_else(UnitQuaternion::identity)
}

/// Egocentric `camera_from_object` rotation from an allocentric one (relative to the viewing
/// ray through `point_in_camera`): `R_ego = R_ray * R_allo`.
pub fn allocentric_to_egocentric(
    allocentric: &UnitQuaternion<f64>,
    point_in_camera: &Vector3<f64>,
) -> UnitQuaternion<f64> {
    ray_rotation(point_in_camera) * allocentric
}

/// Allocentric rotation from an egocentric `camera_from_object`: `R_allo = R_ray^-1 * R_ego`.
pub fn egocentric_to_allocentric(
    egocentric: &UnitQuaternion<f64>,
    point_in_camera: &Vector3<f64>,
) -> UnitQuaternion<f64> {
    ray_rotation(point_in_camera).inverse() * egocentric
}

/// Object poses drawn from a tracked distribution (the grasp decision's input), all in one
/// frame (`reference_from_object`). `effective_sample_size` is the number of independent
/// draws they are worth (draws from ~110 particles are not 1,000 independent observations).
#[derive(Debug, Clone, PartialEq)]
pub struct PoseSamples {
    pub poses: Vec<Pose>,
    pub effective_sample_size: f64,
}

impl PoseSamples {
    /// `n` independent poses around `center` (reference_from_object): Gaussian translation with
    /// `t_std_m` per reference axis, and a Gaussian rotation vector with `r_std_rad` per
    /// reference axis applied on the left, about the object's origin. Seeded; for tests,
    /// benchmarks and diagnostics of the decision without a tracker.
    pub fn gaussian(center: &Pose, t_std_m: [f64; 3], r_std_rad: [f64; 3], n: usize, seed: u64) -> Self {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut normal = |std: f64| std * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut rng);
        let poses = (0..n)
            .map(|_| {
                let t = Vector3::new(normal(t_std_m[0]), normal(t_std_m[1]), normal(t_std_m[2]));
                let r = Vector3::new(normal(r_std_rad[0]), normal(r_std_rad[1]), normal(r_std_rad[2]));
                Pose::from_parts(
                    Translation3::from(center.translation.vector + t),
                    UnitQuaternion::from_scaled_axis(r) * center.rotation,
                )
            })
            .collect();
        Self {
            poses,
            effective_sample_size: n as f64,
        }
    }
}

/// Indices of one bin of the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BinIndex {
    pub elevation: usize,
    pub azimuth: usize,
    pub inplane: usize,
}

/// The Euler-bin grid over SO(3) (see the module docs for the convention).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct RotationGrid {
    step_deg: u32,
    n_elevation: usize,
    n_azimuth: usize,
    n_inplane: usize,
}

impl RotationGrid {
    /// The grid of the method: 5 degree bins, 37 x 72 x 72 = 191,808 bins.
    pub fn full() -> Self {
        Self::new(5).expect("5 divides 180")
    }

    /// A grid with `step_deg`-degree bins; the step must divide 180.
    pub fn new(step_deg: u32) -> Result<Self, GeometryError> {
        if step_deg == 0 || step_deg > 90 || 180 % step_deg != 0 {
            return Err(GeometryError::BadGridStep { step_deg });
        }
        let s = step_deg as usize;
        Ok(Self {
            step_deg,
            n_elevation: 180 / s + 1,
            n_azimuth: 360 / s,
            n_inplane: 360 / s,
        })
    }

    pub fn step_deg(&self) -> u32 {
        self.step_deg
    }
    pub fn step_rad(&self) -> f64 {
        (self.step_deg as f64).to_radians()
    }
    pub fn n_elevation(&self) -> usize {
        self.n_elevation
    }
    pub fn n_azimuth(&self) -> usize {
        self.n_azimuth
    }
    pub fn n_inplane(&self) -> usize {
        self.n_inplane
    }
    /// Number of viewpoints (elevation x azimuth): the views a codebook must render.
    pub fn n_viewpoints(&self) -> usize {
        self.n_elevation * self.n_azimuth
    }
    /// Total number of bins.
    pub fn len(&self) -> usize {
        self.n_elevation * self.n_azimuth * self.n_inplane
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Flat index, in-plane fastest: `(e * n_azimuth + a) * n_inplane + i`.
    pub fn flat(&self, b: BinIndex) -> usize {
        (b.elevation * self.n_azimuth + b.azimuth) * self.n_inplane + b.inplane
    }

    pub fn unflat(&self, idx: usize) -> BinIndex {
        let inplane = idx % self.n_inplane;
        let va = idx / self.n_inplane;
        BinIndex {
            elevation: va / self.n_azimuth,
            azimuth: va % self.n_azimuth,
            inplane,
        }
    }

    /// Angles (elevation, azimuth, in-plane) of a bin centre, radians.
    pub fn angles_rad(&self, b: BinIndex) -> (f64, f64, f64) {
        let s = self.step_rad();
        (b.elevation as f64 * s, b.azimuth as f64 * s, b.inplane as f64 * s)
    }

    /// `camera_from_object` rotation (allocentric) at the centre of a bin.
    pub fn rotation(&self, b: BinIndex) -> UnitQuaternion<f64> {
        let (e, a, t) = self.angles_rad(b);
        euler_to_rotation(e, a, t)
    }

    /// The viewpoint rotation (in-plane 0) of a viewpoint index `e * n_azimuth + a`.
    pub fn viewpoint_rotation(&self, viewpoint: usize) -> UnitQuaternion<f64> {
        let b = BinIndex {
            elevation: viewpoint / self.n_azimuth,
            azimuth: viewpoint % self.n_azimuth,
            inplane: 0,
        };
        self.rotation(b)
    }

    /// The bin whose centre is nearest in each Euler angle to the rotation.
    pub fn bin_of(&self, r: &UnitQuaternion<f64>) -> BinIndex {
        let (e, a, t) = rotation_to_euler(r);
        let s = self.step_rad();
        let elevation = ((e / s).round() as isize).clamp(0, self.n_elevation as isize - 1) as usize;
        let wrap = |x: f64, n: usize| -> usize { ((x / s).round() as isize).rem_euclid(n as isize) as usize };
        BinIndex {
            elevation,
            azimuth: wrap(a, self.n_azimuth),
            inplane: wrap(t, self.n_inplane),
        }
    }

    pub fn flat_of(&self, r: &UnitQuaternion<f64>) -> usize {
        self.flat(self.bin_of(r))
    }

    /// Neighbours at offsets -1, 0, +1 in each angle (the bin itself excluded): azimuth and
    /// in-plane wrap around; elevation is clamped at the poles (no wrap).
    pub fn neighbours(&self, b: BinIndex) -> Vec<BinIndex> {
        let mut out = Vec::with_capacity(26);
        for de in -1isize..=1 {
            let e = b.elevation as isize + de;
            if e < 0 || e >= self.n_elevation as isize {
                continue;
            }
            for da in -1isize..=1 {
                for di in -1isize..=1 {
                    if de == 0 && da == 0 && di == 0 {
                        continue;
                    }
                    out.push(BinIndex {
                        elevation: e as usize,
                        azimuth: (b.azimuth as isize + da).rem_euclid(self.n_azimuth as isize) as usize,
                        inplane: (b.inplane as isize + di).rem_euclid(self.n_inplane as isize) as usize,
                    });
                }
            }
        }
        out
    }

    /// Relative SO(3) volume of the bins of one elevation row (sums to 1 over all bins):
    /// proportional to the solid angle of the elevation band, half-width bands at the poles.
    /// Shannon entropy (nats) of the uniform distribution on SO(3) over this grid's bins: the
    /// largest entropy a rotation histogram on it can have.
    pub fn uniform_entropy(&self) -> f64 {
        let per_elevation = (self.n_azimuth * self.n_inplane) as f64;
        -self
            .elevation_volume_weights()
            .iter()
            .filter(|w| **w > 0.0)
            .map(|w| per_elevation * w * w.ln())
            .sum::<f64>()
    }

    pub fn elevation_volume_weights(&self) -> Vec<f64> {
        let s = self.step_rad();
        let mut w: Vec<f64> = (0..self.n_elevation)
            .map(|k| {
                let lo = ((k as f64 - 0.5) * s).max(0.0);
                let hi = ((k as f64 + 0.5) * s).min(PI);
                lo.cos() - hi.cos()
            })
            .collect();
        let total: f64 = w.iter().sum::<f64>() * (self.n_azimuth * self.n_inplane) as f64;
        for v in &mut w {
            *v /= total;
        }
        w
    }
}

/// `camera_from_object` for elevation `e`, azimuth `a`, in-plane `theta` (radians); see the
/// module docs.
pub fn euler_to_rotation(e: f64, a: f64, theta: f64) -> UnitQuaternion<f64> {
    let (se, ce) = e.sin_cos();
    let (sa, ca) = a.sin_cos();
    let d = Vector3::new(se * ca, se * sa, ce);
    let z_c = -d;
    let x_c = Vector3::new(-sa, ca, 0.0);
    let y_c = z_c.cross(&x_c);
    let object_from_camera0 = Matrix3::from_columns(&[x_c, y_c, z_c]);
    let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), theta);
    let m = rz.matrix() * object_from_camera0.transpose();
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m))
}

/// Inverse of [`euler_to_rotation`]: (elevation in [0, pi], azimuth in [0, 2pi), in-plane in
/// [0, 2pi)). At the poles the azimuth is not unique; the returned triple still maps back to
/// the same rotation.
pub fn rotation_to_euler(r: &UnitQuaternion<f64>) -> (f64, f64, f64) {
    let m = r.to_rotation_matrix();
    let m = m.matrix();
    // z_c expressed in the object frame is the third row of camera_from_object.
    let z_c = Vector3::new(m[(2, 0)], m[(2, 1)], m[(2, 2)]);
    let d = -z_c;
    let e = d.z.clamp(-1.0, 1.0).acos();
    let a = if d.x.abs() < 1e-12 && d.y.abs() < 1e-12 {
        0.0
    } else {
        d.y.atan2(d.x).rem_euclid(2.0 * PI)
    };
    let v = euler_to_rotation(e, a, 0.0);
    // Rz(theta) = R * V = R * (V^T)^-1, with V^T the rotation at theta = 0.
    let rz = r * v.inverse();
    let rzm = rz.to_rotation_matrix();
    let theta = rzm.matrix()[(1, 0)].atan2(rzm.matrix()[(0, 0)]).rem_euclid(2.0 * PI);
    (e, a, theta)
}

/// `world_from_camera` of a camera at `eye` looking at `target`, with the world's +z up: the
/// optical axis (z) points at the target, x is image right, y image down. Looking straight
/// down or up, x is the world's x.
pub fn look_at(eye: [f64; 3], target: [f64; 3]) -> Pose {
    let eye = Vector3::from(eye);
    let z = (Vector3::from(target) - eye).normalize();
    let mut x = z.cross(&Vector3::z());
    if x.norm() < 1e-9 {
        x = Vector3::x();
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(Translation3::from(eye), UnitQuaternion::from_rotation_matrix(&r))
}

/// A unit vector axis; convenience for tests and callers.
pub fn axis(v: Vector3<f64>) -> Unit<Vector3<f64>> {
    Unit::new_normalize(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use rand::{Rng, SeedableRng};

    fn random_rotation(rng: &mut impl Rng) -> UnitQuaternion<f64> {
        let q = nalgebra::Quaternion::new(
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
        );
        UnitQuaternion::from_quaternion(q)
    }

    #[test]
    fn euler_round_trip_random_rotations() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..1000 {
            let r = random_rotation(&mut rng);
            let (e, a, t) = rotation_to_euler(&r);
            let back = euler_to_rotation(e, a, t);
            assert!(r.angle_to(&back) < 1e-9, "round trip error {}", r.angle_to(&back));
        }
    }

    #[test]
    fn bin_of_centre_is_itself_and_random_rotations_land_within_half_a_bin() {
        let grid = RotationGrid::new(10).unwrap();
        for idx in (0..grid.len()).step_by(37) {
            let b = grid.unflat(idx);
            let r = grid.rotation(b);
            let back = grid.rotation(grid.bin_of(&r));
            // at the poles several bins share a rotation: compare rotations, not indices
            assert!(r.angle_to(&back) < 1e-9);
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let mut worst: f64 = 0.0;
        for _ in 0..2000 {
            let r = random_rotation(&mut rng);
            let c = grid.rotation(grid.bin_of(&r));
            worst = worst.max(r.angle_to(&c));
        }
        // half-diagonal of a 10 degree cube is about 8.7 degrees (plus pole effects)
        assert!(worst.to_degrees() < 12.0, "worst {}", worst.to_degrees());
    }

    #[test]
    fn full_grid_has_the_papers_size() {
        let g = RotationGrid::full();
        assert_eq!((g.n_elevation(), g.n_azimuth(), g.n_inplane()), (37, 72, 72));
        assert_eq!(g.len(), 191_808);
        assert_eq!(g.n_viewpoints(), 2664);
        assert!(RotationGrid::new(7).is_err());
    }

    #[test]
    fn neighbours_wrap_azimuth_and_inplane_but_not_elevation() {
        let g = RotationGrid::new(30).unwrap();
        let n = g.neighbours(BinIndex {
            elevation: 0,
            azimuth: 0,
            inplane: 0,
        });
        assert_eq!(n.len(), 17); // 2 elevation rows x 9 - itself
        assert!(n.iter().any(|b| b.azimuth == g.n_azimuth() - 1));
        assert!(n.iter().any(|b| b.inplane == g.n_inplane() - 1));
        assert!(n.iter().all(|b| b.elevation <= 1));
    }

    #[test]
    fn volume_weights_sum_to_one_and_peak_at_the_equator() {
        let g = RotationGrid::full();
        let w = g.elevation_volume_weights();
        let sum: f64 = w.iter().sum::<f64>() * (g.n_azimuth() * g.n_inplane()) as f64;
        assert_relative_eq!(sum, 1.0, epsilon = 1e-12);
        assert!(w[18] > w[1] && w[1] > w[0]);
    }

    #[test]
    fn the_uniform_entropy_is_just_below_ln_of_the_bins() {
        let g = RotationGrid::full();
        let h = g.uniform_entropy();
        let ln_n = ((g.n_elevation() * g.n_azimuth() * g.n_inplane()) as f64).ln();
        assert!(h < ln_n && h > ln_n - 0.5, "{h} vs ln N {ln_n}");
    }

    #[test]
    fn elevation_zero_looks_down_the_object_z_axis() {
        let r = euler_to_rotation(0.0, 0.0, 0.0);
        // object +z points towards the camera: in the camera frame it is -z
        let z_in_cam = r * Vector3::z();
        assert_relative_eq!(z_in_cam, -Vector3::z(), epsilon = 1e-12);
    }

    #[test]
    fn allocentric_round_trip_and_on_axis_identity() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let r = random_rotation(&mut rng);
        let p = Vector3::new(0.4, -0.2, 1.5);
        let ego = allocentric_to_egocentric(&r, &p);
        assert!(egocentric_to_allocentric(&ego, &p).angle_to(&r) < 1e-12);
        let on_axis = allocentric_to_egocentric(&r, &Vector3::new(0.0, 0.0, 2.0));
        assert!(on_axis.angle_to(&r) < 1e-12);
        // the ray rotation maps the optical axis onto the ray
        let ray = ray_rotation(&p) * Vector3::z();
        assert_relative_eq!(ray, p.normalize(), epsilon = 1e-12);
    }

    #[test]
    fn look_at_points_the_optical_axis_at_the_target_with_y_down() {
        let world_from_camera = look_at([1.0, 0.0, 1.0], [0.0, 0.0, 0.0]);
        let target_in_camera = world_from_camera.inverse() * nalgebra::Point3::origin();
        assert_relative_eq!(
            target_in_camera.coords,
            Vector3::new(0.0, 0.0, 2f64.sqrt()),
            epsilon = 1e-12
        );
        // image down (y) has a negative world z component: the world's up is up in the image
        assert!((world_from_camera.rotation * Vector3::y()).z < 0.0);
        let straight_down = look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0]);
        assert_relative_eq!(straight_down.rotation * Vector3::z(), -Vector3::z(), epsilon = 1e-12);
    }

    #[test]
    fn quaternion_checks() {
        assert!(pose_from_xyzw([0.0; 3], [0.0, 0.0, 0.0, 1.0]).is_ok());
        assert!(matches!(
            pose_from_xyzw([0.0; 3], [0.0, 0.0, 0.0, 2.0]),
            Err(GeometryError::NonUnitQuaternion { .. })
        ));
        assert!(matches!(
            pose_from_xyzw([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            Err(GeometryError::NonFinite { .. })
        ));
        let p = pose_from_xyzw([1.0, 2.0, 3.0], [0.0, 0.0, (0.5f64).sqrt(), (0.5f64).sqrt()]).unwrap();
        let (t, q) = pose_to_xyzw(&p);
        assert_eq!(t, [1.0, 2.0, 3.0]);
        assert_relative_eq!(q[2], (0.5f64).sqrt(), epsilon = 1e-12);
        let (r, t2) = pose_to_rt(&p);
        let p2 = pose_from_rt(&r, t2).unwrap();
        assert!(p2.rotation.angle_to(&p.rotation) < 1e-7);
        assert!(pose_from_rt(&[2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], [0.0; 3]).is_err());
    }

    #[test]
    fn gaussian_pose_samples_have_the_asked_spread_per_axis_and_repeat_by_seed() {
        let center = Pose::from_parts(
            Translation3::new(0.5, -0.2, 1.0),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1),
        );
        let s = PoseSamples::gaussian(&center, [0.001, 0.01, 0.0], [0.0, 0.0, 0.1], 4000, 7);
        assert_eq!((s.poses.len(), s.effective_sample_size), (4000, 4000.0));
        let rms = |f: &dyn Fn(&Pose) -> f64| (s.poses.iter().map(|p| f(p).powi(2)).sum::<f64>() / 4000.0).sqrt();
        let d = |i: usize| move |p: &Pose| p.translation.vector[i] - center.translation.vector[i];
        assert!((rms(&d(0)) - 0.001).abs() < 1e-4 && (rms(&d(1)) - 0.01).abs() < 1e-3 && rms(&d(2)) == 0.0);
        // the rotation is about the reference z alone, applied on the left
        let turn = |p: &Pose| (p.rotation * center.rotation.inverse()).scaled_axis();
        assert!((rms(&|p: &Pose| turn(p).z) - 0.1).abs() < 0.01);
        assert!(rms(&|p: &Pose| turn(p).x) < 1e-9 && rms(&|p: &Pose| turn(p).y) < 1e-9);
        assert_eq!(
            s,
            PoseSamples::gaussian(&center, [0.001, 0.01, 0.0], [0.0, 0.0, 0.1], 4000, 7)
        );
        assert_ne!(
            s,
            PoseSamples::gaussian(&center, [0.001, 0.01, 0.0], [0.0, 0.0, 0.1], 4000, 8)
        );
    }
}
