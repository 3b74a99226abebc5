//! Verification of competing rotation hypotheses against a depth image: each hypothesis is
//! rendered by the CPU rasteriser into a small crop around the object and scored by its depth
//! residuals and its silhouette. Colour is left out (the light biases it); the codebook's
//! linear codes are what confused the modes in the first place, so the check uses the raw
//! geometry instead.

use crate::camera::{DepthImage, Intrinsics};
use crate::geometry::Pose;
use crate::mesh::Mesh;
use crate::render::raster;
use nalgebra::Point3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Parameters of the verification.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VerificationConfig {
    /// Modes holding at least this share of the modes' mass compete; verification runs when
    /// two or more do. 1 (the default) turns it off: on the tuning sequences it lowered the
    /// error but not the truth's log-likelihood, and on a shape-symmetric box it can favour a
    /// wrong turn (`docs/decisions.md`, issue 19); 0.1 turns it on.
    pub min_mode_mass: f64,
    /// At most this many modes are rendered per view.
    pub max_modes: usize,
    /// Largest side of the rendered crop, pixels (the view is scaled down to it).
    pub max_side_px: u32,
    /// Depth residual scale, metres, at 1 m (it grows linearly with the distance).
    pub depth_sigma_m: f64,
    /// Largest penalty of one pixel (a truncated squared residual, in units of sigma squared).
    pub truncation: f64,
    /// Largest penalty of a pixel whose observed surface lies in front of the hypothesis (an
    /// occluder: a neighbouring object hides part of it), in units of sigma squared.
    #[serde(default = "default_occlusion_truncation")]
    pub occlusion_truncation: f64,
    /// Crop pixels per independent observation (neighbouring residuals are correlated).
    pub pixels_per_observation: f64,
    /// A camera verifies a track again only once its direction to the track has turned by at
    /// least this much since it last did (0: every step). Successive frames from one viewpoint
    /// repeat the same misfit of a wrong shape, not independent evidence.
    #[serde(default)]
    pub min_view_change_deg: f64,
    /// A view verifies only when the object's diameter spans at least this many pixels at the
    /// track's mean (0: every view). In a far crop a mug's handle is a few pixels and the
    /// scorer compares noise; near, it tells the handle's side apart in almost every view.
    #[serde(default)]
    pub min_object_px: f64,
    /// Each mode is first registered to the view's depth over its translation
    /// ([`crate::tracker::register`]) and scored where it fits best. A mug turned about its
    /// body fits the depth 2-3 cm from the true position, so a shared position favours
    /// whichever mode the track's position came from, not the one the images show.
    #[serde(default, skip_serializing_if = "crate::tracker::observation::is_zero")]
    pub register_modes: bool,
}

impl Default for VerificationConfig {
    fn default() -> Self {
        Self {
            min_mode_mass: 1.0,
            max_modes: 3,
            max_side_px: 64,
            depth_sigma_m: 0.02,
            truncation: 4.0,
            occlusion_truncation: default_occlusion_truncation(),
            min_view_change_deg: 0.0,
            min_object_px: 0.0,
            pixels_per_observation: 64.0,
            register_modes: false,
        }
    }
}

fn default_occlusion_truncation() -> f64 {
    1.0
}

/// The crop of a view around an object: its intrinsics (scaled to at most `max_side` pixels)
/// and the observed depth there (the median of the source pixels each crop pixel covers).
pub(crate) struct Crop {
    pub(crate) intrinsics: Intrinsics,
    pub(crate) depth: Vec<f32>,
    /// Source pixel of the crop's pixel (0, 0) centre's top-left block corner, and the scale.
    origin: [f64; 2],
    scale: f64,
}

impl Crop {
    /// The source image position (pixel coordinates) of crop pixel `(x, y)`'s centre.
    fn source_of(&self, x: u32, y: u32) -> [f64; 2] {
        [
            self.origin[0] + (x as f64 + 0.5) / self.scale - 0.5,
            self.origin[1] + (y as f64 + 0.5) / self.scale - 0.5,
        ]
    }
}

pub(crate) fn crop_around(
    k: &Intrinsics,
    depth: &DepthImage,
    centre: &Point3<f64>,
    diameter_m: f64,
    max_side: u32,
) -> Option<Crop> {
    let [u, v] = k.project(centre)?;
    let half = 0.8 * diameter_m * k.fx().max(k.fy()) / centre.z;
    let (x0, y0) = ((u - half).floor().max(0.0), (v - half).floor().max(0.0));
    let (x1, y1) = (
        (u + half).ceil().min(k.width as f64 - 1.0),
        (v + half).ceil().min(k.height as f64 - 1.0),
    );
    if !(x1 > x0 + 2.0 && y1 > y0 + 2.0) {
        return None;
    }
    let (w_src, h_src) = (x1 - x0 + 1.0, y1 - y0 + 1.0);
    let s = (max_side as f64 / w_src.max(h_src)).min(1.0);
    let (w, h) = ((w_src * s).ceil().max(1.0) as u32, (h_src * s).ceil().max(1.0) as u32);
    // pixel centres at integers: a crop pixel x covers source [x0 + x / s - 0.5, x0 + (x + 1) / s - 0.5)
    let kk = [
        k.fx() * s,
        0.0,
        (k.cx() - x0 + 0.5) * s - 0.5,
        0.0,
        k.fy() * s,
        (k.cy() - y0 + 0.5) * s - 0.5,
        0.0,
        0.0,
        1.0,
    ];
    let intrinsics = Intrinsics::new(w, h, kk).ok()?;
    let mut out = vec![0f32; (w * h) as usize];
    let mut block = Vec::new();
    for y in 0..h {
        for x in 0..w {
            block.clear();
            let (sx0, sx1) = (x0 + x as f64 / s, (x0 + (x + 1) as f64 / s).min(x1 + 1.0));
            let (sy0, sy1) = (y0 + y as f64 / s, (y0 + (y + 1) as f64 / s).min(y1 + 1.0));
            let mut sy = sy0.floor();
            while sy < sy1 {
                let mut sx = sx0.floor();
                while sx < sx1 {
                    let d = depth.get(sx as u32, sy as u32);
                    if d > 0.0 && d.is_finite() {
                        block.push(d);
                    }
                    sx += 1.0;
                }
                sy += 1.0;
            }
            if !block.is_empty() {
                let mid = block.len() / 2;
                block.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
                out[(y * w + x) as usize] = block[mid];
            }
        }
    }
    Some(Crop {
        intrinsics,
        depth: out,
        origin: [x0, y0],
        scale: s,
    })
}

/// One view as the verification reads it.
pub struct DepthView<'a> {
    pub intrinsics: &'a Intrinsics,
    pub depth: &'a DepthImage,
    /// The track's detection in this view, BOP's `[x, y, width, height]` (pixels).
    pub object_box_px: Option<[f64; 4]>,
}

/// Moves each hypothesis (camera from object) to where its surface fits the view's depth
/// ([`crate::tracker::register::register_translation`], the hypothesis's rotation taken as
/// exact but for `rotation_var`, a bin's quantisation, rad^2 per axis); a hypothesis that does
/// not register stays where it is. A mug turned about its body fits the depth 2-3 cm from the
/// true pose, so scored at one shared position the modes are judged by where the track's
/// particles happen to sit, not by the images (`VerificationConfig::register_modes`).
pub fn register_hypotheses(
    mesh: &Mesh,
    intrinsics: &Intrinsics,
    depth: &DepthImage,
    camera_from_object: &mut [Pose],
    diameter_m: f64,
    rotation_var: f64,
    config: &crate::tracker::register::RegistrationConfig,
) {
    let rotation_cov = nalgebra::Matrix3::identity() * rotation_var;
    camera_from_object.par_iter_mut().for_each(|pose| {
        if let Some(reg) = crate::tracker::register::register_translation(
            mesh,
            intrinsics,
            depth,
            pose,
            diameter_m,
            &rotation_cov,
            config,
        ) {
            pose.translation.vector += reg.delta_m;
        }
    });
}

/// Log-scores of hypotheses `camera_from_object` (one object, poses that differ in rotation)
/// against one view's depth image; higher is better, comparable between the hypotheses only.
/// Each hypothesis is rendered once and slid over the crop (the track's mean position is off by
/// its error, a few pixels at crop size) and along the ray (its median depth to the observed
/// object's), and scored at its best placement over every crop pixel: a covered pixel costs
/// its truncated squared depth residual (truncated lower where the observed surface is in
/// front: an occluder), an uncovered pixel the truncation when the observed surface there
/// lies within the object's depth range and inside the track's detection box (grown by a
/// tenth; something the hypothesis does not explain). A slide across the ray costs its length
/// under `placement_sigma_m` (the track's translation spread per axis) as a Gaussian prior:
/// slid freely, a half-turned hypothesis shifted by a quarter of the object fits the depth
/// about as often as the true pose does (`examples/verify_diag.rs`). `placement_sigma_m <= 0`:
/// no slide. `None` when the object is outside the image.
pub fn score_hypotheses(
    mesh: &Mesh,
    view: &DepthView,
    camera_from_object: &[Pose],
    diameter_m: f64,
    placement_sigma_m: f64,
    config: &VerificationConfig,
) -> Option<Vec<f64>> {
    let (k, depth, object_box_px) = (view.intrinsics, view.depth, view.object_box_px);
    let first = camera_from_object.first()?;
    let centre = Point3::from(first.translation.vector);
    if centre.z < 0.05 {
        return None;
    }
    let crop = crop_around(k, depth, &centre, diameter_m, config.max_side_px)?;
    let (w, h) = (crop.intrinsics.width as i64, crop.intrinsics.height as i64);
    let sigma = config.depth_sigma_m * centre.z.max(0.1);
    let (near, far) = (centre.z - 0.6 * diameter_m, centre.z + 0.6 * diameter_m);
    let t = config.truncation;
    let t_occ = config.occlusion_truncation.min(t);
    // the detection's box (grown by a tenth of its side): what lies outside it at the
    // object's depth is another object, not one a hypothesis must explain
    let in_box = |x: u32, y: u32| match object_box_px {
        Some([bx, by, bw, bh]) => {
            let [u, v] = crop.source_of(x, y);
            let (mx, my) = (0.1 * bw, 0.1 * bh);
            u >= bx - 0.5 - mx && u <= bx + bw - 0.5 + mx && v >= by - 0.5 - my && v <= by + bh - 0.5 + my
        }
        None => true,
    };
    let object_like: Vec<bool> = crop
        .depth
        .iter()
        .enumerate()
        .map(|(i, o)| {
            let (x, y) = ((i as i64 % w) as u32, (i as i64 / w) as u32);
            (*o as f64) > near && (*o as f64) < far && in_box(x, y)
        })
        .collect();
    let median = |mut v: Vec<f64>| -> Option<f64> {
        if v.is_empty() {
            return None;
        }
        let mid = v.len() / 2;
        v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
        Some(v[mid])
    };
    let observed = median(
        crop.depth
            .iter()
            .zip(&object_like)
            .filter(|(_, l)| **l)
            .map(|(o, _)| *o as f64)
            .collect(),
    );
    // no slide without a placement spread
    let reach = if placement_sigma_m > 0.0 {
        (w.max(h) / 6).max(2)
    } else {
        0
    };
    let (m_per_px_x, m_per_px_y) = (centre.z / crop.intrinsics.fx(), centre.z / crop.intrinsics.fy());
    let inv_two_var = if reach > 0 {
        1.0 / (2.0 * placement_sigma_m * placement_sigma_m)
    } else {
        0.0
    };
    let scores = camera_from_object
        .iter()
        .map(|p| {
            let r = raster::render(&crop.intrinsics, &[(mesh, *p)], 0.02, [0, 0, 0])
                .depth
                .data_m;
            let rendered = median(r.iter().filter(|d| **d > 0.0).map(|d| *d as f64).collect());
            let offset = match (observed, rendered) {
                (Some(o), Some(d)) => (o - d).clamp(-0.5 * diameter_m, 0.5 * diameter_m),
                _ => 0.0,
            };
            let cost_at = |dx: i64, dy: i64| -> f64 {
                let mut cost = 0.0;
                for y in 0..h {
                    for x in 0..w {
                        let i = (y * w + x) as usize;
                        let (sx, sy) = (x - dx, y - dy);
                        let d = if sx >= 0 && sy >= 0 && sx < w && sy < h {
                            r[(sy * w + sx) as usize] as f64
                        } else {
                            0.0
                        };
                        let o = crop.depth[i] as f64;
                        cost += if d > 0.0 {
                            if o > 0.0 {
                                let r = (o - d - offset) / sigma;
                                (r * r).min(if r < 0.0 { t_occ } else { t })
                            } else {
                                0.0
                            }
                        } else if object_like[i] {
                            t
                        } else {
                            0.0
                        };
                    }
                }
                cost
            };
            let ppo = config.pixels_per_observation.max(1.0);
            let mut best = f64::INFINITY;
            let mut dy = -reach;
            while dy <= reach {
                let mut dx = -reach;
                while dx <= reach {
                    let (sx_m, sy_m) = (dx as f64 * m_per_px_x, dy as f64 * m_per_px_y);
                    best = best.min(cost_at(dx, dy) / ppo + (sx_m * sx_m + sy_m * sy_m) * inv_two_var);
                    dx += 2;
                }
                dy += 2;
            }
            -best
        })
        .collect();
    Some(scores)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    /// An L-shaped object: two boxes, so a half turn changes its depth and silhouette.
    fn l_shape() -> Mesh {
        let mut mesh = crate::mesh::builtin_box([0.12, 0.04, 0.04], [[200, 0, 0], [200, 0, 0]]);
        let mut arm = crate::mesh::builtin_box([0.04, 0.04, 0.10], [[200, 0, 0], [200, 0, 0]]);
        for v in &mut arm.vertices_m {
            v[0] += 0.04;
            v[2] += 0.07;
        }
        let base = mesh.vertices_m.len() as u32;
        mesh.vertices_m.extend(arm.vertices_m);
        mesh.colors.extend(arm.colors);
        mesh.triangles.extend(arm.triangles.iter().map(|t| t.map(|i| i + base)));
        mesh
    }

    #[test]
    fn the_rendered_truth_outscores_a_turned_hypothesis() {
        let mesh = l_shape();
        let k = Intrinsics::from_focal(320, 240, 300.0).unwrap();
        let truth = Pose::from_parts(
            Translation3::new(0.02, -0.01, 0.8),
            UnitQuaternion::from_euler_angles(0.4, 0.3, 0.2),
        );
        let img = raster::render(&k, &[(&mesh, truth)], 0.02, [0, 0, 0]);
        let flipped = Pose::from_parts(
            truth.translation,
            truth.rotation * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
        );
        let view = DepthView {
            intrinsics: &k,
            depth: &img.depth,
            object_box_px: None,
        };
        let s = score_hypotheses(
            &mesh,
            &view,
            &[truth, flipped],
            0.16,
            0.01,
            &VerificationConfig::default(),
        )
        .unwrap();
        assert!(s[0] > s[1] + 5.0, "{s:?}");
        // the same with the truth second: the order of the hypotheses does not matter
        let s2 = score_hypotheses(
            &mesh,
            &view,
            &[flipped, truth],
            0.16,
            0.01,
            &VerificationConfig::default(),
        )
        .unwrap();
        assert!(
            (s2[1] - s[0]).abs() < 1e-9 && (s2[0] - s[1]).abs() < 1e-9,
            "{s:?} {s2:?}"
        );
    }

    #[test]
    fn sliding_a_hypothesis_back_into_place_costs_its_distance_under_the_placement_spread() {
        // the same pose drawn 3 cm to the side of the track's mean: with a 1 cm placement
        // spread the slide that fits it back costs about 3^2 / 2 = 4.5 nats; with a loose
        // spread it costs only the slide grid's misfit, and without a spread there is no slide
        let mesh = l_shape();
        let k = Intrinsics::from_focal(320, 240, 300.0).unwrap();
        let truth = Pose::from_parts(
            Translation3::new(0.0, 0.0, 0.8),
            UnitQuaternion::from_euler_angles(0.4, 0.3, 0.2),
        );
        let img = raster::render(&k, &[(&mesh, truth)], 0.02, [0, 0, 0]);
        let score = |shift_m: f64, sigma_m: f64| {
            let mut p = truth;
            p.translation.vector.x += shift_m;
            // the crop is centred on the first hypothesis: keep it at the mean
            let view = DepthView {
                intrinsics: &k,
                depth: &img.depth,
                object_box_px: None,
            };
            score_hypotheses(&mesh, &view, &[truth, p], 0.16, sigma_m, &VerificationConfig::default()).unwrap()
        };
        let tight = score(0.03, 0.01);
        let loose = score(0.03, 1.0);
        let fixed = score(0.03, 0.0);
        let paid = tight[0] - tight[1];
        assert!((2.5..7.0).contains(&paid), "tight {tight:?}");
        assert!(
            (loose[0] - loose[1]).abs() < 0.5 * paid,
            "loose {loose:?} tight {tight:?}"
        );
        assert!(fixed[0] - fixed[1] > paid, "fixed {fixed:?} tight {tight:?}");
    }

    #[test]
    fn each_mode_of_a_turned_mug_is_scored_where_it_fits() {
        // the built-in mug with its origin moved 1.2 cm towards the handle (as the YCB mesh's
        // box centre is): turned by 136 degrees about its body axis, the mug fits the same
        // body 2.2 cm away, which is where a track's particles may sit
        let mut mesh = crate::mesh::builtin_mug();
        for v in &mut mesh.vertices_m {
            v[0] -= 0.012;
        }
        let body_axis = Vector3::new(-0.012, 0.0, 0.0);
        let k = Intrinsics::from_focal(320, 240, 300.0).unwrap();
        // seen from 0.5 m, a little from above, the handle to the side
        let rotation = UnitQuaternion::from_euler_angles(-1.9, 0.0, 0.3);
        let truth = Pose::from_parts(Translation3::new(0.01, 0.0, 0.5), rotation);
        let img = raster::render(&k, &[(&mesh, truth)], 0.02, [0, 0, 0]);
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 136f64.to_radians());
        let twin_rotation = rotation * turn;
        // the twin's body where the truth's is: t' = t + R (c - turn c)
        let twin_t = truth.translation.vector + rotation * (body_axis - turn * body_axis);
        assert!((twin_t - truth.translation.vector).norm() > 0.02);
        // the track sits at the twin's place: scored there, the true rotation pays for the
        // slide back to where it fits
        let at_twin = |q: UnitQuaternion<f64>| Pose::from_parts(Translation3::from(twin_t), q);
        let view = DepthView {
            intrinsics: &k,
            depth: &img.depth,
            object_box_px: None,
        };
        let config = VerificationConfig {
            max_side_px: 128,
            ..VerificationConfig::default()
        };
        let shared = score_hypotheses(
            &mesh,
            &view,
            &[at_twin(rotation), at_twin(twin_rotation)],
            0.13,
            0.005,
            &config,
        )
        .unwrap();
        let mut placed = [at_twin(rotation), at_twin(twin_rotation)];
        let reg = crate::tracker::register::RegistrationConfig::default();
        register_hypotheses(&mesh, &k, &img.depth, &mut placed, 0.13, 0.0, &reg);
        // each mode registered to where it fits: the true rotation back onto the truth
        assert!(
            (placed[0].translation.vector - truth.translation.vector).norm() < 0.006,
            "{:?}",
            placed[0].translation
        );
        assert!(
            (placed[1].translation.vector - twin_t).norm() < 0.01,
            "{:?}",
            placed[1].translation
        );
        let own = score_hypotheses(&mesh, &view, &placed, 0.13, 0.005, &config).unwrap();
        // where each fits, the truth pays no slide: both score higher, the truth far higher
        assert!(
            own[0] > shared[0] + 5.0 && own[1] >= shared[1],
            "shared {shared:?} own {own:?}"
        );
        assert!(own[0] > own[1] + 20.0, "where each fits the truth wins: {own:?}");
    }
}
