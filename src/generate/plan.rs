//! The scene and the motion of a generated sequence, before any rendering: the table, the
//! objects resting on it, the stationary cameras, the robot's true path, the arm, the wheel
//! odometry (Thrun's `sample_motion_model_odometry`) and the localisation's `world_from_odom`.
//!
//! World frame: the table top is the plane z = 0 (normal +z), the floor lies
//! [`TABLE_HEIGHT_M`] below it. The robot base frame is on the floor, x forward, y left, z up.

use crate::camera::Intrinsics;
use crate::dataset::{LocalisationSigma, OdometrySample};
use crate::geometry::Pose;
use crate::mesh::Mesh;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// Height of the table top above the floor, metres.
pub const TABLE_HEIGHT_M: f64 = 0.75;
/// Table top size (x, y), metres.
pub const TABLE_SIZE_M: [f64; 2] = [1.2, 0.8];
/// Table top thickness, metres.
pub const TABLE_THICKNESS_M: f64 = 0.04;
/// Gap kept between the footprints of two objects and to the table edge, metres.
pub const PLACEMENT_GAP_M: f64 = 0.03;
/// Distance of the stationary cameras from the objects, metres (drawn in +- 0.2 m around it).
pub const EXTERNAL_DISTANCE_M: f64 = 3.0;
/// Distance of the robot camera from the target at the first frame, metres.
pub const APPROACH_START_M: f64 = 3.0;
/// Distance of the robot camera from the target at the last frame, metres.
pub const APPROACH_END_M: f64 = 0.5;
/// The robot base keeps this far from the table edge (its footprint radius plus clearance).
pub const BASE_CLEARANCE_M: f64 = 0.35;
/// Share of the frames over which the base drives; afterwards only the arm moves.
pub const BASE_DRIVE_SHARE: f64 = 0.85;
/// Sequences shorter than this never get a look-away stretch (it would swallow them).
pub const MIN_FRAMES_FOR_LOOK_AWAY: u32 = 30;
/// A frame counts as looking away (reported in `look_away_frames`) once the pan reaches this
/// share of [`LOOK_AWAY_RAD`] (56 degrees: the target's centre is then well outside the field of view).
pub const LOOK_AWAY_REPORTED_SHARE: f64 = 0.8;
/// Look-away amplitude of the arm during an occlusion stretch, radians.
pub const LOOK_AWAY_RAD: f64 = 70.0 * PI / 180.0;

/// An object resting on the table.
#[derive(Debug, Clone)]
pub struct PlacedObject {
    /// Index into the model pool.
    pub model: usize,
    pub world_from_object: Pose,
    /// Radius of its footprint on the table around its origin, metres.
    pub footprint_radius_m: f64,
}

/// Poses of the robot over the frames (truth and what odometry/localisation report).
#[derive(Debug, Clone)]
pub struct RobotPlan {
    pub world_from_base: Vec<Pose>,
    pub base_from_camera: Vec<Pose>,
    pub odometry: Vec<OdometrySample>,
    /// Frames in which the arm looks away from the target (the occlusion stretch).
    pub look_away_frames: Vec<u32>,
}

/// Optical frame looking from `eye` at `target` with the world's +z up (x right, y down).
pub fn look_at(eye: &Point3<f64>, target: &Point3<f64>) -> Pose {
    crate::geometry::look_at(eye.coords.into(), target.coords.into())
}

fn planar(x: f64, y: f64, z: f64, yaw_rad: f64) -> Pose {
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_rad),
    )
}

fn yaw_of(p: &Pose) -> f64 {
    let r = p.rotation.to_rotation_matrix();
    r.matrix()[(1, 0)].atan2(r.matrix()[(0, 0)])
}

fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(TAU) - PI
}

/// Places every model of `chosen` on the table resting on one of the faces of its bounding
/// box (larger faces likelier), with a random yaw, without overlapping footprints.
/// `Err` with a reason when they do not fit.
pub fn place_objects(meshes: &[&Mesh], chosen: &[usize], rng: &mut ChaCha8Rng) -> Result<Vec<PlacedObject>, String> {
    let mut placed: Vec<PlacedObject> = Vec::new();
    for &model in chosen {
        let mesh = meshes[model];
        let ext = mesh.bounds().extents_m();
        // candidate down axes: +-x, +-y, +-z, weighted by the area of that face of the box
        let areas = [
            ext.y * ext.z,
            ext.y * ext.z,
            ext.x * ext.z,
            ext.x * ext.z,
            ext.x * ext.y,
            ext.x * ext.y,
        ];
        let total: f64 = areas.iter().sum();
        let mut pick = rng.random::<f64>() * total;
        let mut face = 5;
        for (i, a) in areas.iter().enumerate() {
            if pick < *a {
                face = i;
                break;
            }
            pick -= a;
        }
        let axis = Vector3::ith(face / 2, if face % 2 == 0 { 1.0 } else { -1.0 });
        // rotate that axis onto world -z
        let down = UnitQuaternion::rotation_between(&axis, &-Vector3::z())
            .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI));
        let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random::<f64>() * TAU);
        let rot = yaw * down;
        let mut min_z = f64::INFINITY;
        let mut radius: f64 = 0.0;
        for i in 0..mesh.vertices_m.len() as u32 {
            let p = rot * mesh.vertex(i);
            min_z = min_z.min(p.z);
            radius = radius.max(Vector2::new(p.x, p.y).norm());
        }
        let half =
            Vector2::new(TABLE_SIZE_M[0] / 2.0, TABLE_SIZE_M[1] / 2.0) - Vector2::repeat(radius + PLACEMENT_GAP_M);
        if half.x <= 0.0 || half.y <= 0.0 {
            return Err(format!(
                "an object of footprint radius {radius:.3} m does not fit on the table"
            ));
        }
        let mut found = None;
        for _ in 0..2000 {
            let xy = Vector2::new(rng.random_range(-half.x..half.x), rng.random_range(-half.y..half.y));
            let free = placed.iter().all(|o| {
                let t = o.world_from_object.translation.vector;
                (Vector2::new(t.x, t.y) - xy).norm() > o.footprint_radius_m + radius + PLACEMENT_GAP_M
            });
            if free {
                found = Some(xy);
                break;
            }
        }
        let xy = found.ok_or_else(|| {
            format!(
                "cannot place {} objects on the {:.1} x {:.1} m table without overlap",
                chosen.len(),
                TABLE_SIZE_M[0],
                TABLE_SIZE_M[1]
            )
        })?;
        placed.push(PlacedObject {
            model,
            world_from_object: Isometry3::from_parts(Translation3::new(xy.x, xy.y, -min_z), rot),
            footprint_radius_m: radius,
        });
    }
    Ok(placed)
}

/// Thickness of the occluder box, metres.
pub const OCCLUDER_THICKNESS_M: f64 = 0.03;
/// Gap between the target's footprint and the occluder, metres.
pub const OCCLUDER_DISTANCE_M: f64 = 0.2;
/// The occluder hides the whole target from sight lines below this elevation.
pub const OCCLUDER_HIDES_BELOW_RAD: f64 = 20.0 * PI / 180.0;

/// A box standing on the table between the target and the robot camera's early position:
/// [`OCCLUDER_DISTANCE_M`] in front of the target's footprint, wider than the target, and
/// taller than its top by as much as a sight line rising at [`OCCLUDER_HIDES_BELOW_RAD`]
/// gains over that distance. It hides the target from the robot camera while the camera is
/// far and low; as the arm rises (and the base turns) the target reappears. `None` when it
/// would overlap another object or leave the table. Returns `world_from_box` (box centred at
/// its origin) and its size.
pub fn place_occluder(
    meshes: &[&Mesh],
    placed: &[PlacedObject],
    target: &PlacedObject,
    robot_eyes: &[Point3<f64>],
    rng: &mut ChaCha8Rng,
) -> Option<(Pose, [f64; 3])> {
    if robot_eyes.is_empty() {
        return None;
    }
    let mesh = meshes[target.model];
    let top_z = (0..mesh.vertices_m.len() as u32)
        .map(|i| (target.world_from_object * mesh.vertex(i)).z)
        .fold(0.0, f64::max);
    let t = target.world_from_object.translation.vector;
    let r_t = target.footprint_radius_m;
    let width = 2.0 * r_t + 0.1;
    let n = robot_eyes.len();
    // nearer the target when there is no room further out
    for gap_m in [OCCLUDER_DISTANCE_M, 0.15, 0.1] {
        let d = r_t + gap_m;
        let size = [width, OCCLUDER_THICKNESS_M, top_z + d * OCCLUDER_HIDES_BELOW_RAD.tan()];
        let footprint = (width / 2.0).hypot(OCCLUDER_THICKNESS_M / 2.0);
        for _ in 0..10 {
            let k = ((n as f64) * rng.random_range(0.0..0.25)) as usize;
            let eye = robot_eyes[k.min(n - 1)];
            let dir = Vector2::new(eye.x - t.x, eye.y - t.y);
            if dir.norm() < 1e-6 {
                continue;
            }
            let dir = dir.normalize();
            let side = Vector2::new(-dir.y, dir.x);
            let c = Vector2::new(t.x, t.y) + dir * d;
            let on_table = [-1.0, 1.0].iter().all(|a| {
                [-1.0, 1.0].iter().all(|b| {
                    let corner = c + side * (a * width / 2.0) + dir * (b * OCCLUDER_THICKNESS_M / 2.0);
                    corner.x.abs() < TABLE_SIZE_M[0] / 2.0 && corner.y.abs() < TABLE_SIZE_M[1] / 2.0
                })
            });
            let free = placed.iter().filter(|o| !std::ptr::eq(*o, target)).all(|o| {
                let p = o.world_from_object.translation.vector;
                (Vector2::new(p.x, p.y) - c).norm() > o.footprint_radius_m + footprint + 0.01
            });
            if on_table && free {
                let yaw = dir.y.atan2(dir.x) + FRAC_PI_2;
                return Some((planar(c.x, c.y, size[2] / 2.0, yaw), size));
            }
        }
    }
    None
}

/// Two stationary cameras about [`EXTERNAL_DISTANCE_M`] from `centre`, 70-150 degrees apart
/// in azimuth, 20-35 degrees above the table, looking at it: `world_from_camera` each.
pub fn external_cameras(centre: &Point3<f64>, rng: &mut ChaCha8Rng) -> [Pose; 2] {
    let a1 = rng.random::<f64>() * TAU;
    let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
    let a2 = a1 + sign * rng.random_range(70f64..150.0).to_radians();
    [a1, a2].map(|a| {
        let d = EXTERNAL_DISTANCE_M + rng.random_range(-0.2..0.2);
        let el = rng.random_range(20f64..35.0).to_radians();
        let eye = centre + Vector3::new(d * el.cos() * a.cos(), d * el.cos() * a.sin(), d * el.sin());
        look_at(&eye, centre)
    })
}

/// Distance from `p` (inside the table top) along unit direction `dir` to the table's edge.
fn distance_to_table_edge(p: Vector2<f64>, dir: Vector2<f64>) -> f64 {
    let half = [TABLE_SIZE_M[0] / 2.0, TABLE_SIZE_M[1] / 2.0];
    let mut best = f64::INFINITY;
    for k in 0..2 {
        if dir[k].abs() > 1e-12 {
            let edge = half[k] * dir[k].signum();
            best = best.min((edge - p[k]) / dir[k]);
        }
    }
    best.max(0.0)
}

/// Settings of the robot's motion and sensing.
#[derive(Debug, Clone)]
pub struct RobotSettings {
    pub frames: u32,
    pub frame_period_ns: i64,
    pub odometry_noise_alpha: [f64; 4],
    pub localisation_sigma: LocalisationSigma,
    /// Probability that the sequence has a stretch in which the arm looks away.
    pub look_away_probability: f64,
}

/// The robot's approach on `target` (world point, the target object's origin): the base drives
/// on a curved path (turning by up to 35 degrees around the target) from about 3 m to the
/// table's edge, then stops while the arm keeps extending until the camera is about 0.5 m from
/// the target; the camera keeps the target in view except during an optional look-away stretch.
pub fn robot_plan(target: &Point3<f64>, s: &RobotSettings, rng: &mut ChaCha8Rng) -> RobotPlan {
    let t2 = Vector2::new(target.x, target.y);
    // final direction from the target to the base, and the turn over the approach
    let phi1 = rng.random::<f64>() * TAU;
    let dphi = rng.random_range(-35f64..35.0).to_radians();
    let phi0 = phi1 - dphi;
    let el0 = rng.random_range(10f64..15.0).to_radians();
    let el1 = rng.random_range(35f64..45.0).to_radians();
    let h1 = APPROACH_END_M * el1.cos();
    let dir1 = Vector2::new(phi1.cos(), phi1.sin());
    let r1 = (distance_to_table_edge(t2, dir1) + BASE_CLEARANCE_M).max(h1 + 0.25);
    let reach1 = r1 - h1;
    let h0 = APPROACH_START_M * el0.cos();
    let reach0 = 0.3;
    let r0 = h0 + reach0;
    let lateral_amp = rng.random_range(0.02..0.05);
    let lateral_freq = rng.random_range(0.8..1.6);

    let n = s.frames.max(1);
    let look_away = n >= MIN_FRAMES_FOR_LOOK_AWAY && rng.random::<f64>() < s.look_away_probability;
    let (la_start, la_len) = if look_away {
        let len = (n as f64 * rng.random_range(0.15..0.25)).round().max(6.0);
        let start = (n as f64 * rng.random_range(0.3..0.5)).round();
        (start, len)
    } else {
        (0.0, 0.0)
    };
    let la_sign = if rng.random::<bool>() { 1.0 } else { -1.0 };

    let base_at = |u: f64| {
        let r = r0 + (r1 - r0) * u;
        let phi = phi0 + dphi * u;
        let e_r = Vector2::new(phi.cos(), phi.sin());
        let e_phi = Vector2::new(-phi.sin(), phi.cos());
        let p = t2 + e_r * r;
        // heading = direction of travel along the path (a differential drive)
        let d = e_r * (r1 - r0) + e_phi * (r * dphi);
        (p, d.y.atan2(d.x), phi, e_phi)
    };

    let mut world_from_base = Vec::new();
    let mut base_from_camera = Vec::new();
    let mut look_away_frames = Vec::new();
    for k in 0..n {
        let t = if n > 1 { k as f64 / (n - 1) as f64 } else { 1.0 };
        let ub = smoothstep(t / BASE_DRIVE_SHARE);
        let ua = smoothstep(t);
        let (p, heading, phi, e_phi) = base_at(ub);
        let wfb = planar(p.x, p.y, -TABLE_HEIGHT_M, heading);
        // camera: on the line from the target towards the base, reach in front of the base
        let r = r0 + (r1 - r0) * ub;
        let reach = reach0 + (reach1 - reach0) * ua;
        let h = r - reach;
        let el = el0 + (el1 - el0) * ua;
        let lateral = lateral_amp * (TAU * lateral_freq * t).sin();
        let c2 = t2 + Vector2::new(phi.cos(), phi.sin()) * h + e_phi * lateral;
        let eye = Point3::new(c2.x, c2.y, target.z + h * el.tan());
        // look-away: pan the view about the vertical by a smooth bump with a plateau
        let kf = k as f64;
        let bump = if look_away && kf >= la_start && kf <= la_start + la_len {
            let ramp = 3.0;
            let up = smoothstep((kf - la_start) / ramp);
            let down = smoothstep((la_start + la_len - kf) / ramp);
            up.min(down)
        } else {
            0.0
        };
        if bump > LOOK_AWAY_REPORTED_SHARE {
            look_away_frames.push(k);
        }
        let pan = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), la_sign * LOOK_AWAY_RAD * bump);
        let look_point = eye + pan * (target - eye);
        let wfc = look_at(&eye, &look_point);
        base_from_camera.push(wfb.inverse() * wfc);
        world_from_base.push(wfb);
    }
    let odometry = odometry(&world_from_base, &base_from_camera, s, rng);
    RobotPlan {
        world_from_base,
        base_from_camera,
        odometry,
        look_away_frames,
    }
}

/// Thrun's `sample_motion_model_odometry` applied to the true planar motion between frames:
/// the odometry integrates noisy increments (it drifts). `world_from_odom` is chosen so that
/// the localised base `world_from_odom * odom_from_base` is the truth times a small planar error
/// that follows an AR(1) process with the standard deviations of `localisation_sigma`, clipped
/// to [`LOCALISATION_CLIP_SIGMAS`] of them.
fn odometry(
    world_from_base: &[Pose],
    base_from_camera: &[Pose],
    s: &RobotSettings,
    rng: &mut ChaCha8Rng,
) -> Vec<OdometrySample> {
    let a = s.odometry_noise_alpha;
    let std_normal = Normal::new(0.0, 1.0).expect("unit normal");
    let mut sample = |variance: f64| -> f64 { variance.max(0.0).sqrt() * std_normal.sample(rng) };
    let mut out = Vec::with_capacity(world_from_base.len());
    // odometry pose (x, y, theta) in the odom frame; the odom frame starts at the first base pose
    let mut odo = [0.0f64; 3];
    let mut err = [0.0f64; 3];
    let rho: f64 = 0.9;
    let innovation = (1.0 - rho * rho).sqrt();
    let sig = [
        s.localisation_sigma.translation_m,
        s.localisation_sigma.translation_m,
        s.localisation_sigma.rotation_rad,
    ];
    for (k, wfb) in world_from_base.iter().enumerate() {
        if k > 0 {
            let prev = &world_from_base[k - 1];
            let (x0, y0, th0) = (prev.translation.x, prev.translation.y, yaw_of(prev));
            let (x1, y1, th1) = (wfb.translation.x, wfb.translation.y, yaw_of(wfb));
            let trans = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt();
            let rot1 = if trans > 1e-9 {
                wrap((y1 - y0).atan2(x1 - x0) - th0)
            } else {
                0.0
            };
            let rot2 = wrap(th1 - th0 - rot1);
            let rot1_hat = rot1 - sample(a[0] * rot1 * rot1 + a[1] * trans * trans);
            let trans_hat = trans - sample(a[2] * trans * trans + a[3] * (rot1 * rot1 + rot2 * rot2));
            let rot2_hat = rot2 - sample(a[0] * rot2 * rot2 + a[1] * trans * trans);
            odo[0] += trans_hat * (odo[2] + rot1_hat).cos();
            odo[1] += trans_hat * (odo[2] + rot1_hat).sin();
            odo[2] = wrap(odo[2] + rot1_hat + rot2_hat);
        }
        for i in 0..3 {
            let fresh = if k == 0 { 1.0 } else { innovation };
            err[i] = (rho * err[i] * if k == 0 { 0.0 } else { 1.0 } + fresh * sample(sig[i] * sig[i]))
                .clamp(-LOCALISATION_CLIP_SIGMAS * sig[i], LOCALISATION_CLIP_SIGMAS * sig[i]);
        }
        let odom_from_base = planar(odo[0], odo[1], 0.0, odo[2]);
        let localised = wfb * planar(err[0], err[1], 0.0, err[2]);
        let world_from_odom = localised * odom_from_base.inverse();
        out.push(OdometrySample {
            stamp_ns: k as i64 * s.frame_period_ns,
            odom_from_base,
            world_from_odom,
            base_from_camera: base_from_camera[k],
        });
    }
    out
}

/// The localisation error is clipped to this many standard deviations per component.
pub const LOCALISATION_CLIP_SIGMAS: f64 = 2.5;

/// Intrinsics of a generated camera: focal length 615 px at 640 px width (a common RGB-D
/// camera), scaled with the width; principal point at the centre.
pub fn generated_intrinsics(width: u32, height: u32) -> Result<Intrinsics, crate::camera::CameraError> {
    Intrinsics::from_focal(width, height, 615.0 * width as f64 / 640.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn settings(frames: u32) -> RobotSettings {
        RobotSettings {
            frames,
            frame_period_ns: 100_000_000,
            odometry_noise_alpha: [0.02, 0.002, 0.02, 0.002],
            localisation_sigma: LocalisationSigma {
                translation_m: 0.015,
                rotation_rad: 0.009,
            },
            look_away_probability: 1.0,
        }
    }

    #[test]
    fn look_at_points_the_optical_axis_at_the_target_with_y_down() {
        let eye = Point3::new(3.0, 0.0, 1.0);
        let p = look_at(&eye, &Point3::origin());
        let in_cam = p.inverse() * Point3::origin();
        assert!(in_cam.x.abs() < 1e-12 && in_cam.y.abs() < 1e-12 && in_cam.z > 3.0);
        // world up is image up (negative y)
        let up = p.inverse_transform_vector(&Vector3::z());
        assert!(up.y < -0.9);
    }

    #[test]
    fn objects_rest_on_the_table_without_overlap() {
        let meshes: Vec<Mesh> = ["box", "can", "mug"]
            .iter()
            .map(|n| crate::mesh::builtin(n).unwrap())
            .collect();
        let refs: Vec<&Mesh> = meshes.iter().collect();
        for seed in 0..20 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let placed = place_objects(&refs, &[0, 1, 2], &mut rng).unwrap();
            for (i, o) in placed.iter().enumerate() {
                let m = refs[o.model];
                let min_z = (0..m.vertices_m.len() as u32)
                    .map(|v| (o.world_from_object * m.vertex(v)).z)
                    .fold(f64::INFINITY, f64::min);
                assert!(min_z.abs() < 1e-9, "object rests at {min_z}");
                // resting on a face: one box axis is vertical
                let up = o.world_from_object.rotation.inverse() * Vector3::z();
                assert!(up.abs().max() > 1.0 - 1e-9);
                for q in &placed[i + 1..] {
                    let d = (o.world_from_object.translation.vector - q.world_from_object.translation.vector).xy();
                    assert!(d.norm() > o.footprint_radius_m + q.footprint_radius_m);
                }
                let t = o.world_from_object.translation.vector;
                assert!(t.x.abs() + o.footprint_radius_m < TABLE_SIZE_M[0] / 2.0);
                assert!(t.y.abs() + o.footprint_radius_m < TABLE_SIZE_M[1] / 2.0);
            }
        }
        let too_many: Vec<usize> = vec![0; 40];
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        assert!(place_objects(&refs, &too_many, &mut rng).is_err());
    }

    #[test]
    fn robot_approaches_from_3m_to_half_a_metre_keeping_the_target_in_view() {
        let target = Point3::new(0.2, -0.1, 0.05);
        let k640 = generated_intrinsics(640, 480).unwrap();
        for seed in 0..30 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let plan = robot_plan(&target, &settings(100), &mut rng);
            let wfc: Vec<Pose> = plan
                .world_from_base
                .iter()
                .zip(&plan.base_from_camera)
                .map(|(b, c)| b * c)
                .collect();
            let d0 = (wfc[0].translation.vector - target.coords).norm();
            let d1 = (wfc[99].translation.vector - target.coords).norm();
            assert!((d0 - APPROACH_START_M).abs() < 0.1, "start {d0}");
            assert!((d1 - APPROACH_END_M).abs() < 0.1, "end {d1}");
            assert!(!plan.look_away_frames.is_empty());
            for (k, p) in wfc.iter().enumerate() {
                let in_cam = p.inverse() * target;
                let off_axis = in_cam.coords.angle(&Vector3::z());
                if plan.look_away_frames.contains(&(k as u32)) {
                    // the target's centre projects at least 60 px outside the image
                    let uv = k640.project(&in_cam);
                    let outside =
                        uv.is_none_or(|[u, v]| !(-60.0..=700.0).contains(&u) || !(-60.0..=540.0).contains(&v));
                    assert!(outside, "frame {k}: target at {uv:?} while looking away");
                } else if plan.look_away_frames.iter().all(|&f| (f as i64 - k as i64).abs() > 4) {
                    // (the pan ramps over 3 frames on either side of the reported stretch)
                    assert!(off_axis < 0.45, "frame {k}: target {off_axis} rad off axis");
                }
            }
            // base and arm both move; the base stays off the table at the end
            let b0 = plan.world_from_base[0].translation.vector;
            let b1 = plan.world_from_base[99].translation.vector;
            assert!((b0 - b1).norm() > 1.5);
            let a0 = plan.base_from_camera[0].translation.vector;
            let a1 = plan.base_from_camera[99].translation.vector;
            assert!((a0 - a1).norm() > 0.05);
            assert!(b1.x.abs() > TABLE_SIZE_M[0] / 2.0 + 0.2 || b1.y.abs() > TABLE_SIZE_M[1] / 2.0 + 0.2);
        }
    }

    #[test]
    fn odometry_drifts_but_localisation_stays_bounded() {
        let target = Point3::new(0.0, 0.0, 0.05);
        let s = settings(100);
        let mut max_drift: f64 = 0.0;
        for seed in 0..5 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let plan = robot_plan(&target, &s, &mut rng);
            let first = plan.world_from_base[0];
            for (k, o) in plan.odometry.iter().enumerate() {
                let truth = plan.world_from_base[k];
                // odometry against the true motion since the start
                let true_rel = first.inverse() * truth;
                max_drift = max_drift.max((o.odom_from_base.translation.vector - true_rel.translation.vector).norm());
                // localised pose within the clip bound
                let loc = o.world_from_odom * o.odom_from_base;
                let e = truth.inverse() * loc;
                let bound_t = LOCALISATION_CLIP_SIGMAS * s.localisation_sigma.translation_m * 2f64.sqrt() + 1e-9;
                assert!(
                    e.translation.vector.norm() <= bound_t,
                    "{}",
                    e.translation.vector.norm()
                );
                assert!(e.rotation.angle() <= LOCALISATION_CLIP_SIGMAS * s.localisation_sigma.rotation_rad + 1e-9);
                assert_eq!(o.stamp_ns, k as i64 * s.frame_period_ns);
            }
        }
        assert!(max_drift > 0.02, "odometry drift only {max_drift} m");
    }
}
