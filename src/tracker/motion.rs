//! Motion models (the paper's Eqs. 3 and 4).
//!
//! - Objects: Brownian motion of the translation (static objects that may be nudged).
//! - External cameras: static.
//! - The robot camera: moved by the base odometry through the odometry motion model of Thrun
//!   et al. (Probabilistic Robotics, `sample_motion_model_odometry`: a rotation, a translation,
//!   a rotation, each with noise growing with the motion, parameters alpha1..alpha4) on the
//!   planar part of the base motion, driving backwards as a negative translation; the arm's
//!   `base_from_camera` is taken as exact.

use crate::geometry::Pose;
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Noise of the odometry motion model (Thrun's alpha1..alpha4).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OdometryNoise {
    /// Rotation noise from rotation.
    pub alpha1: f64,
    /// Rotation noise from translation (rad per m).
    pub alpha2: f64,
    /// Translation noise from translation.
    pub alpha3: f64,
    /// Translation noise from rotation (m per rad).
    pub alpha4: f64,
}

impl Default for OdometryNoise {
    fn default() -> Self {
        Self {
            alpha1: 0.05,
            alpha2: 0.01,
            alpha3: 0.05,
            alpha4: 0.01,
        }
    }
}

fn yaw_of(q: &UnitQuaternion<f64>) -> f64 {
    let x = q * Vector3::x();
    x.y.atan2(x.x)
}

fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

fn normal(rng: &mut impl Rng, var: f64) -> f64 {
    if var <= 0.0 {
        return 0.0;
    }
    Normal::new(0.0, var.sqrt()).map(|n| n.sample(rng)).unwrap_or(0.0)
}

/// A noisy sample of the base motion `base_prev_from_base_cur` given the odometry readings
/// `odom_from_base` at the two times. The planar part (x, y, yaw in the odometry frame) is
/// perturbed as in `sample_motion_model_odometry`; the rest of the motion is kept exact.
pub fn sample_base_motion(
    odom_from_base_prev: &Pose,
    odom_from_base_cur: &Pose,
    noise: &OdometryNoise,
    rng: &mut impl Rng,
) -> Pose {
    let exact = odom_from_base_prev.inverse() * odom_from_base_cur;
    let (x0, y0) = (odom_from_base_prev.translation.x, odom_from_base_prev.translation.y);
    let (x1, y1) = (odom_from_base_cur.translation.x, odom_from_base_cur.translation.y);
    let th0 = yaw_of(&odom_from_base_prev.rotation);
    let th1 = yaw_of(&odom_from_base_cur.rotation);
    let mut trans = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt();
    let mut rot1 = if trans < 1e-6 {
        0.0
    } else {
        wrap((y1 - y0).atan2(x1 - x0) - th0)
    };
    // driving backwards is a negative translation, not a half turn, a translation and a half
    // turn back: those turns would draw heading noise of about a radian per step
    if rot1.abs() > PI / 2.0 {
        rot1 = wrap(rot1 - PI);
        trans = -trans;
    }
    let rot2 = wrap(th1 - th0 - rot1);
    let a = noise;
    let rot1_n = rot1 - normal(rng, a.alpha1 * rot1 * rot1 + a.alpha2 * trans * trans);
    let trans_n = trans - normal(rng, a.alpha3 * trans * trans + a.alpha4 * (rot1 * rot1 + rot2 * rot2));
    let rot2_n = rot2 - normal(rng, a.alpha1 * rot2 * rot2 + a.alpha2 * trans * trans);
    // the noisy planar motion, expressed in the previous base frame's planar coordinates
    let dx = trans_n * rot1_n.cos();
    let dy = trans_n * rot1_n.sin();
    let dyaw = rot1_n + rot2_n;
    // replace the planar part of the exact relative motion by the noisy one
    let exact_planar_yaw = wrap(th1 - th0);
    let yaw_fix = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), dyaw - exact_planar_yaw);
    let mut t = exact.translation.vector;
    // planar components of the exact relative motion in the previous base frame
    let exact_xy = Vector3::new(trans * rot1.cos(), trans * rot1.sin(), 0.0);
    let noisy_xy = Vector3::new(dx, dy, 0.0);
    t += noisy_xy - exact_xy;
    Pose::from_parts(Translation3::from(t), yaw_fix * exact.rotation)
}

/// Moves particle positions from the previous reference (robot camera) frame into the current
/// one, each with its own noisy sample of the base motion.
#[allow(clippy::too_many_arguments)]
pub fn move_with_odometry(
    positions_m: &mut [Vector3<f64>],
    odom_from_base_prev: &Pose,
    odom_from_base_cur: &Pose,
    base_from_camera_prev: &Pose,
    base_from_camera_cur: &Pose,
    noise: &OdometryNoise,
    rng: &mut impl Rng,
) {
    for p in positions_m.iter_mut() {
        let base_prev_from_base_cur = sample_base_motion(odom_from_base_prev, odom_from_base_cur, noise, rng);
        let prev_from_cur = base_from_camera_prev.inverse() * base_prev_from_base_cur * base_from_camera_cur;
        *p = prev_from_cur
            .inverse_transform_point(&nalgebra::Point3::from(*p))
            .coords;
    }
}

/// Covariance (current camera frame) of where a point fixed in the world, at `point_prev_m` in
/// the previous camera frame, lands in the current one under the odometry model's noise:
/// the spread that [`move_with_odometry`] gives the particles there. A fixed seed keeps it a
/// deterministic function of the motion, apart from the filter's random stream.
pub fn odometry_covariance_at(
    point_prev_m: &Vector3<f64>,
    odom_from_base_prev: &Pose,
    odom_from_base_cur: &Pose,
    base_from_camera_prev: &Pose,
    base_from_camera_cur: &Pose,
    noise: &OdometryNoise,
) -> nalgebra::Matrix3<f64> {
    use rand::SeedableRng;
    const DRAWS: usize = 64;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x0d0e);
    let mut moved = [*point_prev_m; DRAWS];
    move_with_odometry(
        &mut moved,
        odom_from_base_prev,
        odom_from_base_cur,
        base_from_camera_prev,
        base_from_camera_cur,
        noise,
        &mut rng,
    );
    let mean = moved.iter().sum::<Vector3<f64>>() / DRAWS as f64;
    moved
        .iter()
        .map(|p| (p - mean) * (p - mean).transpose())
        .sum::<nalgebra::Matrix3<f64>>()
        / (DRAWS - 1) as f64
}

/// Brownian motion: independent Gaussian steps of `sigma_m` per axis.
pub fn brownian(positions_m: &mut [Vector3<f64>], sigma_m: f64, rng: &mut impl Rng) {
    if sigma_m <= 0.0 {
        return;
    }
    let Ok(n) = Normal::new(0.0, sigma_m) else { return };
    for p in positions_m.iter_mut() {
        *p += Vector3::new(n.sample(rng), n.sample(rng), n.sample(rng));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn planar(x: f64, y: f64, yaw: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, y, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
        )
    }

    #[test]
    fn zero_noise_reproduces_the_odometry_and_noise_scales_with_motion() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let a = planar(1.0, 2.0, 0.3);
        let b = planar(1.5, 2.4, 0.6);
        let exact = a.inverse() * b;
        let zero = OdometryNoise {
            alpha1: 0.0,
            alpha2: 0.0,
            alpha3: 0.0,
            alpha4: 0.0,
        };
        let s = sample_base_motion(&a, &b, &zero, &mut rng);
        assert!((s.translation.vector - exact.translation.vector).norm() < 1e-9);
        assert!(s.rotation.angle_to(&exact.rotation) < 1e-9);
        // with noise: spread grows with the distance travelled
        let spread = |b: &Pose, rng: &mut rand_chacha::ChaCha8Rng| -> f64 {
            let ex = a.inverse() * b;
            (0..400)
                .map(|_| {
                    (sample_base_motion(&a, b, &OdometryNoise::default(), rng)
                        .translation
                        .vector
                        - ex.translation.vector)
                        .norm()
                })
                .sum::<f64>()
                / 400.0
        };
        let near = spread(&planar(1.1, 2.0, 0.3), &mut rng);
        let far = spread(&planar(3.0, 2.0, 0.3), &mut rng);
        assert!(far > 5.0 * near, "near {near} far {far}");
    }

    #[test]
    fn driving_backwards_draws_the_heading_noise_of_driving_forwards() {
        // 2 cm along a gentle arc, forwards and backwards: the sampled heading change must
        // spread alike (as a half turn there and back, it spread by about a radian)
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let a = planar(1.0, 2.0, 0.3);
        let step = planar(0.02, 0.0, 0.5f64.to_radians());
        let yaw_spread_deg = |b: &Pose, rng: &mut rand_chacha::ChaCha8Rng| -> f64 {
            let exact = a.inverse() * b;
            let errs: Vec<f64> = (0..2000)
                .map(|_| {
                    sample_base_motion(&a, b, &OdometryNoise::default(), rng)
                        .rotation
                        .angle_to(&exact.rotation)
                })
                .collect();
            (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64)
                .sqrt()
                .to_degrees()
        };
        let forwards = yaw_spread_deg(&(a * step), &mut rng);
        let backwards = yaw_spread_deg(&(a * step.inverse()), &mut rng);
        assert!(forwards < 1.0, "forwards {forwards} deg");
        assert!(
            backwards < 1.5 * forwards,
            "backwards {backwards} deg, forwards {forwards} deg"
        );
    }

    #[test]
    fn the_odometry_spread_at_a_point_grows_with_the_motion_and_the_range() {
        let base_from_camera = Pose::from_parts(
            Translation3::new(0.2, 0.0, 1.0),
            UnitQuaternion::from_euler_angles(-PI / 2.0, 0.0, -PI / 2.0),
        );
        let a = planar(0.0, 0.0, 0.0);
        let spread = |b: &Pose, z: f64| {
            odometry_covariance_at(
                &Vector3::new(0.0, 0.0, z),
                &a,
                b,
                &base_from_camera,
                &base_from_camera,
                &OdometryNoise::default(),
            )
            .trace()
            .sqrt()
        };
        assert_eq!(spread(&a, 1.0), 0.0, "no motion, no noise");
        let (short, long) = (
            spread(&planar(0.05, 0.0, 0.0), 1.0),
            spread(&planar(0.2, 0.0, 0.0), 1.0),
        );
        assert!(short > 0.0 && long > 2.0 * short, "5 cm: {short} m, 20 cm: {long} m");
        // the heading's noise moves a far point more than a near one
        assert!(spread(&planar(0.2, 0.0, 0.0), 3.0) > long);
    }

    #[test]
    fn a_static_point_stays_put_in_the_world_when_the_camera_moves() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let base_from_camera = Pose::from_parts(
            Translation3::new(0.2, 0.0, 1.0),
            UnitQuaternion::from_euler_angles(-PI / 2.0, 0.0, -PI / 2.0),
        );
        let a = planar(0.0, 0.0, 0.0);
        let b = planar(0.5, 0.1, 0.2);
        let world_point = Vector3::new(3.0, 0.5, 0.4);
        let cam_a = a * base_from_camera;
        let cam_b = b * base_from_camera;
        let mut p = vec![cam_a.inverse() * nalgebra::Point3::from(world_point); 1]
            .into_iter()
            .map(|q| q.coords)
            .collect::<Vec<_>>();
        let zero = OdometryNoise {
            alpha1: 0.0,
            alpha2: 0.0,
            alpha3: 0.0,
            alpha4: 0.0,
        };
        move_with_odometry(&mut p, &a, &b, &base_from_camera, &base_from_camera, &zero, &mut rng);
        let expected = (cam_b.inverse() * nalgebra::Point3::from(world_point)).coords;
        assert!((p[0] - expected).norm() < 1e-9, "{:?} vs {:?}", p[0], expected);
    }
}
