//! Translation from the depth image: the object at a track's mean position and top rotation
//! mode is rendered by the CPU rasteriser into a small crop of one view and registered to the
//! observed depth by point-to-plane Gauss-Newton steps over its translation (projective
//! association, robust to occluders and background). The result is a Gaussian on the
//! translation whose information comes from the surface normals the view sees: a can seen from
//! the side fixes its position across and along the ray, a box seen face-on only along its
//! face's normal. The crops' codes place an object to about a centimetre; its depth surface,
//! thousands of pixels, places it to millimetres where its shape allows.

use crate::camera::DepthImage;
use crate::camera::Intrinsics;
use crate::geometry::Pose;
use crate::mesh::Mesh;
use crate::render::raster;
use nalgebra::{Matrix3, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Parameters of the translation registration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RegistrationConfig {
    /// The registration's information is scaled by this before it updates what the track
    /// reports (0 turns the registration off; 1, the default). Neighbouring crop pixels share their noise (the sensor's and the crop's
    /// median downsampling), so the information of `N` inlier pixels read as independent
    /// overstates what they know; 1 takes them as independent.
    pub information_scale: f64,
    /// The track's top rotation mode must hold at least this share of its modes' mass. 0 (the
    /// default): the rotation's covariance, which spans the competing modes, widens the fit
    /// instead; a can's spin spreads its mass over many modes that all fit the same surface,
    /// and a share of a half kept the demo's can from ever registering.
    pub min_mode_share: f64,
    /// Largest side of the rendered crop, pixels.
    pub max_side_px: u32,
    /// Gauss-Newton steps (each renders the object once).
    pub iterations: u32,
    /// A pixel is an inlier while its residual lies within this many robust sigmas of the
    /// median residual (occluders and the background behind the object are not).
    pub inlier_sigmas: f64,
    /// Fewest inlier pixels for a view to count.
    pub min_inliers: usize,
    /// Smallest standard deviation (m) the registration claims along any direction of one
    /// view: the mesh and the sensor's calibration are not exact to a millimetre.
    pub min_std_m: f64,
    /// A view whose depth differences at the start have a robust sigma above this share of the
    /// object's diameter does not register it: its inlier gate would then take in the table
    /// and the background beside the object, which pull the fit off (the generated
    /// sequences' far views, 5 % depth noise per pixel).
    pub max_noise_rel: f64,
    /// Above this noise share the information is scaled by `(noise_ref_rel / noise)^2`: the
    /// background that a wider gate takes in biases the fit in proportion to the noise, which
    /// the residuals' own scale does not see.
    pub noise_ref_rel: f64,
    /// The rotation error's pull on the fit (`rotation_cov_object` of [`register_translation`])
    /// counts this many times its linearised covariance: the linearisation misses the
    /// association's own shift, and on the generated sequences it covered the truth in 0.60 of
    /// frames at 15 degrees of rotation error, 0.78 at four times (`examples/register_diag.rs`).
    pub rotation_pull_scale: f64,
    /// Smallest residual sigma per metre of range (a mesh's facets and a sensor's quantisation
    /// leave residuals even where the fit is exact; a sigma of a tenth of a millimetre would
    /// turn the slightest normal component into certainty).
    pub min_sigma_per_m: f64,
    /// A camera's last registration of a track keeps counting at the steps that bring no fit
    /// from that camera, for at most this long (seconds; 0: a step's own views only). Cameras
    /// are not synchronised: where each step brings one view, as in the service, a side view
    /// alone never fixes a can's height nor a top view its position along the ray, and the
    /// track reported its floor there. The kept fit moves with the robot's odometry and
    /// widens by its noise and by `carry_drift_m_per_s` (`Tracker` keeps one per camera, the
    /// newest).
    pub carry_max_age_s: f64,
    /// How fast a kept fit widens (metres of standard deviation per second): the drift a
    /// resting object may have had since, besides the odometry's noise.
    pub carry_drift_m_per_s: f64,
}

impl Default for RegistrationConfig {
    fn default() -> Self {
        Self {
            information_scale: 1.0,
            min_mode_share: 0.0,
            max_side_px: 64,
            iterations: 3,
            inlier_sigmas: 2.5,
            min_inliers: 40,
            min_std_m: 0.001,
            max_noise_rel: 0.15,
            noise_ref_rel: 0.05,
            rotation_pull_scale: 4.0,
            min_sigma_per_m: 0.002,
            carry_max_age_s: 0.5,
            carry_drift_m_per_s: 0.01,
        }
    }
}

/// One view's registration of a hypothesis: the translation to add to it (camera frame) and
/// the information of that estimate (camera frame, 1/m^2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Registration {
    pub delta_m: Vector3<f64>,
    pub information: Matrix3<f64>,
    /// Inlier pixels of the last step and the robust sigma of their residuals (m).
    pub inliers: usize,
    pub sigma_m: f64,
    /// The robust sigma of the depth differences at the first step, as a share of the
    /// object's diameter (see [`RegistrationConfig::max_noise_rel`]).
    pub noise_rel: f64,
}

/// Registers `camera_from_object` to one view's depth over its translation (see the module
/// docs). `rotation_cov_object` is the covariance of the hypothesis's rotation error (a rotation
/// vector in the object's frame, rad^2): a turned surface fits best a little off the true
/// position, by `H^-1 B dtheta` with `B = sum n (q x n)^T` over the fitted pixels (`q` the
/// surface point from the object's origin), so that covariance is added to the fit's own. A
/// can's spin moves no surface point along its normal and adds nothing. `None` when the object is outside the image, too few pixels agree, or the fit moves
/// the object by more than a third of its diameter (the association broke).
pub fn register_translation(
    mesh: &Mesh,
    intrinsics: &Intrinsics,
    depth: &DepthImage,
    camera_from_object: &Pose,
    diameter_m: f64,
    rotation_cov_object: &Matrix3<f64>,
    config: &RegistrationConfig,
) -> Option<Registration> {
    let centre = Point3::from(camera_from_object.translation.vector);
    if centre.z < 0.05 {
        return None;
    }
    let crop = crate::tracker::verify::crop_around(intrinsics, depth, &centre, diameter_m, config.max_side_px)?;
    let k = &crop.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    // per pixel the unit-depth ray
    let rays: Vec<Vector3<f64>> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            Vector3::new((x - k.cx()) / k.fx(), (y - k.cy()) / k.fy(), 1.0)
        })
        .collect();
    let mut delta = Vector3::zeros();
    let mut result = None;
    let mut noise_rel = f64::NAN;
    let gate_abs = 0.5 * diameter_m;
    for _ in 0..config.iterations.max(1) {
        let mut pose = *camera_from_object;
        pose.translation.vector += delta;
        let r = raster::render(k, &[(mesh, pose)], 0.02, [0, 0, 0]).depth.data_m;
        // residuals along the rendered surface's normal, with the normal
        let mut samples: Vec<(f64, f64, Vector3<f64>, Vector3<f64>)> = Vec::new();
        for y in 1..h.saturating_sub(1) {
            for x in 1..w.saturating_sub(1) {
                let i = y * w + x;
                let (d, o) = (r[i] as f64, crop.depth[i] as f64);
                if d <= 0.0 || o <= 0.0 || (o - d).abs() > gate_abs {
                    continue;
                }
                let (l, rr, u, dn) = (r[i - 1] as f64, r[i + 1] as f64, r[i - w] as f64, r[i + w] as f64);
                // central differences on one surface only: no neighbour off the object, and no
                // depth step (a kink in the depth, not a steep slope: a cap seen at a grazing
                // angle is what fixes a cylinder along its axis)
                let step = 0.05 * diameter_m;
                if [l, rr, u, dn].iter().any(|v| *v <= 0.0)
                    || (l + rr - 2.0 * d).abs() > step
                    || (u + dn - 2.0 * d).abs() > step
                {
                    continue;
                }
                let dx = rays[i + 1] * rr - rays[i - 1] * l;
                let dy = rays[i + w] * dn - rays[i - w] * u;
                let Some(mut n) = dx.cross(&dy).try_normalize(1e-12) else {
                    continue;
                };
                if n.dot(&rays[i]) > 0.0 {
                    n = -n;
                }
                samples.push((
                    o - d,
                    (o - d) * n.dot(&rays[i]),
                    n,
                    rays[i] * d - pose.translation.vector,
                ));
            }
        }
        if samples.len() < config.min_inliers {
            return None;
        }
        // robust centre and scale of the depth differences (median, MAD): occluders and the
        // background show there as depth steps of centimetres, at any surface slope
        let mut e: Vec<f64> = samples.iter().map(|s| s.0).collect();
        let mid = e.len() / 2;
        e.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
        let med = e[mid];
        let mut dev: Vec<f64> = samples.iter().map(|s| (s.0 - med).abs()).collect();
        dev.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
        let sigma = (1.4826 * dev[mid]).max(1e-4);
        if noise_rel.is_nan() {
            noise_rel = sigma / diameter_m;
            if noise_rel > config.max_noise_rel {
                return None;
            }
        }
        // never tighter than a tenth of the object: on a clean surface the MAD is a fraction of
        // a millimetre, and a tighter gate would drop the few pixels (a cap seen at a grazing
        // angle) that fix the direction the rest leave open
        let bound = (config.inlier_sigmas * sigma).max(0.1 * diameter_m);
        let (mut hm, mut g, mut inliers, mut ss) = (Matrix3::zeros(), Vector3::zeros(), 0usize, 0.0);
        let mut lever = Matrix3::zeros();
        for (diff, res, n, q) in &samples {
            if (diff - med).abs() <= bound {
                hm += n * n.transpose();
                g += n * *res;
                lever += n * q.cross(n).transpose();
                inliers += 1;
                ss += res * res;
            }
        }
        if inliers < config.min_inliers {
            return None;
        }
        // the inliers' residual scale along the normals (misfit included)
        let sigma = (ss / inliers as f64).sqrt().max(config.min_sigma_per_m * centre.z);
        // a step only along directions the surface constrains
        let eig = hm.symmetric_eigen();
        let mut step = Vector3::zeros();
        let top = eig.eigenvalues.max();
        for j in 0..3 {
            let lam = eig.eigenvalues[j];
            if lam > 1e-3 * top.max(1e-12) {
                let v = eig.eigenvectors.column(j);
                step += v * (v.dot(&g) / lam);
            }
        }
        delta += step;
        if delta.norm() > diameter_m / 3.0 {
            return None;
        }
        // covariance of this step's fit: the noise's along what the surface fixes (each
        // direction at least `min_std_m`; a metre where it fixes nothing), plus the rotation
        // error's pull `G cov G^T` with `G = H^-1 B`
        let var_cap = (config.min_std_m * config.min_std_m).max(1e-12);
        let deflate = (config.noise_ref_rel / noise_rel).powi(2).min(1.0);
        let (mut cov, mut h_pinv) = (Matrix3::zeros(), Matrix3::zeros());
        for j in 0..3 {
            let lam = eig.eigenvalues[j];
            let v = eig.eigenvectors.column(j);
            let known = lam > 1e-3 * top.max(1e-12);
            let var = if known {
                (sigma * sigma / (deflate * lam)).max(var_cap)
            } else {
                1.0
            };
            cov += v * v.transpose() * var;
            if known {
                h_pinv += v * v.transpose() / lam;
            }
        }
        let r = pose.rotation.to_rotation_matrix();
        let rot_cov = r.matrix() * rotation_cov_object * r.matrix().transpose();
        let gain = h_pinv * lever;
        cov += gain * rot_cov * gain.transpose() * config.rotation_pull_scale;
        let info = cov.try_inverse()?;
        let info = (info + info.transpose()) * 0.5;
        result = Some(Registration {
            delta_m: delta,
            information: info,
            inliers,
            sigma_m: sigma,
            noise_rel,
        });
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn scene() -> (Mesh, Intrinsics, Pose) {
        let mesh = crate::mesh::builtin_cylinder(0.033, 0.1, 48, [[200, 30, 30], [220, 220, 220]]);
        let k = Intrinsics::from_focal(640, 480, 600.0).expect("intrinsics");
        let pose = Pose::from_parts(
            Translation3::new(0.02, -0.01, 0.8),
            UnitQuaternion::from_euler_angles(1.2, 0.3, 0.1),
        );
        (mesh, k, pose)
    }

    /// The default registration of `placed`, with its rotation taken as exact.
    fn register_at(mesh: &Mesh, k: &Intrinsics, depth: &DepthImage, placed: &Pose) -> Registration {
        register_translation(
            mesh,
            k,
            depth,
            placed,
            mesh.diameter_m(),
            &Matrix3::zeros(),
            &RegistrationConfig::default(),
        )
        .expect("registration")
    }

    #[test]
    fn a_misplaced_cylinder_is_pulled_back_to_its_rendered_depth() {
        let (mesh, k, truth) = scene();
        let depth = raster::render(&k, &[(&mesh, truth)], 0.02, [0, 0, 0]).depth;
        let mut placed = truth;
        placed.translation.vector += Vector3::new(0.006, -0.004, 0.008);
        let reg = register_at(&mesh, &k, &depth, &placed);
        let after = placed.translation.vector + reg.delta_m - truth.translation.vector;
        // the side of a cylinder fixes its position across its axis; along the axis the fit
        // claims to know little, and what it claims covers what is left
        let eig = reg.information.symmetric_eigen();
        for j in 0..3 {
            let v = eig.eigenvectors.column(j);
            let std = 1.0 / eig.eigenvalues[j].max(1e-12).sqrt();
            assert!(
                v.dot(&after).abs() < (3.0 * std).max(0.0015),
                "{:.4} m left where {std:.4} m is claimed",
                v.dot(&after)
            );
        }
        let sure = (0..3).filter(|j| eig.eigenvalues[*j] > 1e5).count();
        assert!(sure >= 2, "{sure} directions known to 3 mm");
        assert!(reg.inliers > 500);
    }

    #[test]
    fn a_face_on_box_says_nothing_about_sliding_along_its_face() {
        let mesh = crate::mesh::builtin_box([0.1, 0.1, 0.02], [[200, 30, 30], [220, 220, 220]]);
        let k = Intrinsics::from_focal(640, 480, 600.0).expect("intrinsics");
        let truth = Pose::from_parts(Translation3::new(0.0, 0.0, 0.7), UnitQuaternion::identity());
        let depth = raster::render(&k, &[(&mesh, truth)], 0.02, [0, 0, 0]).depth;
        let mut placed = truth;
        placed.translation.vector += Vector3::new(0.0, 0.0, 0.01);
        let reg = register_at(&mesh, &k, &depth, &placed);
        // the face's normal (the ray) is known to the cap; sliding sideways is not known
        let along = reg.information[(2, 2)];
        let across = reg.information[(0, 0)].max(reg.information[(1, 1)]);
        assert!(along > 1e5, "information along the normal {along}");
        assert!(across < 1e-3 * along, "information across {across} against {along}");
        assert!((placed.translation.vector.z + reg.delta_m.z - 0.7).abs() < 0.001);
    }

    #[test]
    fn occluders_in_front_do_not_pull_the_fit() {
        let (mesh, k, truth) = scene();
        let mut depth = raster::render(&k, &[(&mesh, truth)], 0.02, [0, 0, 0]).depth;
        // a fifth of the object's pixels hidden by something 3 cm nearer (inside the absolute
        // gate: the robust one must reject it)
        let [u, _] = k.project(&Point3::from(truth.translation.vector)).expect("in view");
        for y in 0..depth.height {
            for x in 0..depth.width {
                let i = (y * depth.width + x) as usize;
                if depth.data_m[i] > 0.0 && (x as f64) < u - 15.0 {
                    depth.data_m[i] -= 0.03;
                }
            }
        }
        let mut placed = truth;
        placed.translation.vector += Vector3::new(-0.004, 0.003, 0.006);
        let reg = register_at(&mesh, &k, &depth, &placed);
        let after = placed.translation.vector + reg.delta_m - truth.translation.vector;
        assert!(after.norm() < 0.003, "left {:.4} m", after.norm());
    }
}
