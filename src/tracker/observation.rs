//! The observation model of one view: crops around the projected particles, codes, cosine
//! similarities against the codebook (a chunked GEMM over all bins, on all cores), and the
//! per-bin log-likelihood.
//!
//! Likelihood (PoseRBPF, made robust for several views): with `c` the cosine similarity of a
//! particle's crop to a bin's code and `c_max` the best similarity of the *view* over all its
//! particles and bins, `ln L = -(1 - c / c_max)^2 / (2 sigma^2)`, floored at `loglik_floor`
//! so that one view can never take away more than a bounded factor (a view that disagrees
//! with the others tempers the fused distribution instead of wiping it out). A view whose
//! absolute best similarity is below `gate_similarity` does not see the object and adds
//! nothing. Particles that do not project into a gated view get the floor.
//!
//! A view's log-likelihood (and its floor) is scaled by its *evidence strength*,
//! `(best - gate) / (full - gate)` clamped to 0..1, with `best` its best absolute similarity.
//! The relative `c / c_max` alone ranks whatever a view sees with the same confidence, a crop
//! of noise included (a far camera seeing a thin object through depth noise larger than the
//! object), and multiplies that in at full strength. Measurements: `docs/decisions.md`
//! ("Tracker: decisions moved from the code"). The filter also scales it by the object's
//! apparent size ([`size_strength`]; "Issue 19, second round"; by the pixels its silhouette
//! covers when `full_area_px` is set, "Far views counted by the pixels the object covers");
//! `observe_view`, a diagnostic of one view, does not.

pub mod fuse;

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::tracker::codebook::Codebook;
use crate::tracker::crop::{CropParams, sample_crop};
use crate::tracker::encoder::Encoder;
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// A crop with fewer valid depth cells than this share is not used.
const MIN_VALID_SHARE: f64 = 0.25;
/// A crop whose support plane was removed is not used (no object there) when fewer than this
/// share of its depth cells are left in front of the plane.
const MIN_OBJECT_SHARE: f64 = 0.08;

/// Parameters of the observation model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObservationConfig {
    /// Sigma of the Gaussian on `c / c_max` around 1.
    pub sigma: f32,
    /// Lowest log-likelihood one view can give a bin.
    pub loglik_floor: f32,
    /// A view whose best absolute similarity is below this does not see the object (with the
    /// default codes, whitened at 0.5, a view that sees the object reaches 0.6-0.9).
    pub gate_similarity: f32,
    /// A view's log-likelihood is scaled by `(best - gate) / (full - gate)` (clamped to 0..1):
    /// a view that barely matches the object anywhere (a far camera seeing a thin object
    /// through depth noise) is weak evidence, not the confident ranking of noise that the
    /// relative `c / c_max` alone would make of it.
    #[serde(default = "default_full_similarity")]
    pub full_similarity: f32,
    /// Sigma (m) of the depth check at 1 m; it grows linearly with the distance.
    pub depth_sigma_m: f32,
    /// Lowest log term of the depth check per view.
    pub depth_floor: f32,
    /// Apparent size (px, the object's diameter at the particles' mean depth) from which a
    /// view counts at full strength; below it the view's log-likelihood is scaled by
    /// `(size / full_size_px)^2`, the share of the pixels a full-size crop would have: a far,
    /// small object is upsampled into a crop that looks confident but holds few pixels.
    /// Read only when [`Self::full_area_px`] is 0; 0 here too: no size weighting.
    #[serde(default = "default_full_size_px")]
    pub full_size_px: f32,
    /// Apparent area (px², the object's mean silhouette over all directions at the particles'
    /// mean depth, [`mean_silhouette_area_m2`]) from which a view counts at full strength;
    /// below it the view's log-likelihood is scaled by `area / full_area_px`, the share of
    /// the pixels a full-size crop would have. It counts a thin object (a banana) by the
    /// pixels it covers, not by its length. 0 (the default; left out of the serialised
    /// settings, so their hash is unchanged): off, [`Self::full_size_px`] applies instead.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub full_area_px: f32,
    /// The detector's boxes as evidence of where the object is ([`box_loglik`]); `None`: the
    /// boxes only start tracks and drive the recovery.
    #[serde(default = "default_detection_box")]
    pub detection_box: Option<DetectionBoxConfig>,
    /// A view in which the object spans fewer pixels than this ([`object_size_px`]) crops
    /// every particle on the ray through the centre of the detector's box of the object, at
    /// the particle's own depth ([`box_aimed`]), not at the particle's projection: at 25 px a
    /// particle a few centimetres off crops the object several pixels off centre, and such a
    /// crop matches wrong rotations. The view's rotation evidence is then the same for all
    /// particles; where they are comes from its box and depth terms. Without the box-centred
    /// templates ([`Self::box_codes`]), only for a mesh whose origin is near its bounding box's
    /// centre (a box centre sits on the silhouette). 60 by default; 0: every crop at its
    /// particle's projection.
    #[serde(default = "default_box_crops_below_px")]
    pub box_crops_below_px: f32,
    /// Match the crops aimed at a detector's box against the codebook's box-centred table
    /// ([`crate::tracker::codebook::BoxTable`]: each template centred on its silhouette's box, as the
    /// detector's box centres the object), not the origin-centred one (a banana's box centre
    /// lies up to a quarter of the crop off its origin); then any mesh is cropped at the box,
    /// wherever its origin lies. True by default; false: the origin-centred table, and
    /// codebooks are built without the box-centred one.
    #[serde(default = "default_true")]
    pub box_codes: bool,
    /// With the box codes: a view at or above `box_crops_below_px` is encoded twice, its crop
    /// aimed at the detector's box for the rotation's histograms and a crop at each particle
    /// for the particles' weights. Aimed crops take the turn that comes with a shift of a
    /// centimetre (a mug's body, a banana's ends) out of the rotation, but all particles then
    /// share one crop and the codes no longer say where the object is. A view whose box
    /// something nearer partly hides is not aimed ([`box_hides_object`]: the box is then the
    /// visible part's). False by default: on the real clip (the mug behind a block) it is still
    /// worse than without (`docs/decisions.md`, "Near views encoded twice").
    #[serde(default, skip_serializing_if = "is_zero")]
    pub near_box_rotation: bool,
}

/// How a detection's box weighs the particles of a view: a Gaussian on the distance (pixels)
/// from the projection of a particle to the box's centre, floored. The codes cannot tell the
/// object from a box-shaped neighbour at 3 m, nor the depth check an occluder's surface from
/// the object's; the box of the object in another view can.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DetectionBoxConfig {
    /// Standard deviation of the box's centre about the projection of the object's centre, as
    /// a share of the box's longer side (the visible box of a half-hidden object is off its
    /// centre, and a detector's box jitters).
    pub sigma_rel: f64,
    /// Lowest log-likelihood one view's box gives a particle (nats): a wrong detection or
    /// another instance's box costs a particle no more than this.
    pub floor: f64,
}

impl Default for DetectionBoxConfig {
    fn default() -> Self {
        Self {
            sigma_rel: 0.25,
            floor: -4.0,
        }
    }
}

fn default_box_crops_below_px() -> f32 {
    60.0
}

fn default_detection_box() -> Option<DetectionBoxConfig> {
    Some(DetectionBoxConfig::default())
}

impl Default for ObservationConfig {
    fn default() -> Self {
        Self {
            sigma: 0.06,
            loglik_floor: -12.0,
            gate_similarity: 0.45,
            full_similarity: default_full_similarity(),
            depth_sigma_m: 0.015,
            depth_floor: -6.0,
            full_size_px: default_full_size_px(),
            full_area_px: 0.0,
            detection_box: default_detection_box(),
            box_crops_below_px: default_box_crops_below_px(),
            box_codes: true,
            near_box_rotation: false,
        }
    }
}

/// Adds to `out` each particle's log-likelihood of one view's box of the object (centre and
/// sigma, as [`nearest_box`] finds it), scored at the projection of every particle
/// (`positions_in_view_m`, view frame). Nothing when the view has no box of the object.
pub fn box_loglik(
    intrinsics: &Intrinsics,
    object_box: Option<([f64; 2], f64)>,
    positions_in_view_m: &[Vector3<f64>],
    config: &DetectionBoxConfig,
    out: &mut [f32],
) {
    let Some((centre, sigma)) = object_box else {
        return;
    };
    for (p, o) in positions_in_view_m.iter().zip(out.iter_mut()) {
        let l = match intrinsics.project(&nalgebra::Point3::from(*p)) {
            Some(uv) => (-0.5 * d2(&centre, &uv, sigma)).max(config.floor),
            None => config.floor,
        };
        *o += l as f32;
    }
}

/// Squared distance from `uv` to `c` in units of `sigma`.
fn d2(c: &[f64; 2], uv: &[f64; 2], sigma: f64) -> f64 {
    ((uv[0] - c[0]).powi(2) + (uv[1] - c[1]).powi(2)) / (sigma * sigma)
}

/// The centre and sigma (`sigma_rel` of its longer side) of the detector's box of `object`
/// nearest, in its own sigmas, to the projection of the track's mean `mean_view_m`; `None`
/// when the view has no box of the object or the mean is behind the camera.
pub fn nearest_box(
    intrinsics: &Intrinsics,
    detections: &[crate::tracker::Detection],
    object: &str,
    mean_view_m: &Vector3<f64>,
    sigma_rel: f64,
) -> Option<([f64; 2], f64)> {
    let mean_uv = intrinsics.project(&nalgebra::Point3::from(*mean_view_m))?;
    detections
        .iter()
        .filter(|d| d.object == object && d.bbox_xywh_px[2] > 1.0 && d.bbox_xywh_px[3] > 1.0)
        .map(|d| (d.centre_px(), sigma_rel * d.bbox_xywh_px[2].max(d.bbox_xywh_px[3])))
        .min_by(|a, b| d2(&a.0, &mean_uv, a.1).total_cmp(&d2(&b.0, &mean_uv, b.1)))
}

/// Whether something nearer than the object hides part of the square of side `side_px` about
/// `centre_px` (a detector's box): more than a tenth of its 4 x 4 pixel blocks read a median
/// depth well in front of the object's front (`depth_m` its centre's, `diameter_m` across).
/// Such a box is the visible part's, and its centre is not the silhouette's.
pub fn box_hides_object(
    depth: &crate::camera::DepthImage,
    centre_px: [f64; 2],
    side_px: f64,
    depth_m: f64,
    diameter_m: f64,
) -> bool {
    let front = depth_m - 0.5 * diameter_m;
    let limit = (front - (0.08 * front).max(0.03)) as f32;
    let half = 0.5 * side_px;
    let (w, h) = (depth.width as i64, depth.height as i64);
    let x0 = ((centre_px[0] - half).floor() as i64).clamp(0, w);
    let x1 = ((centre_px[0] + half).ceil() as i64).clamp(0, w);
    let y0 = ((centre_px[1] - half).floor() as i64).clamp(0, h);
    let y1 = ((centre_px[1] + half).ceil() as i64).clamp(0, h);
    let (mut blocks, mut nearer) = (0usize, 0usize);
    let mut block = Vec::with_capacity(16);
    for by in (y0..y1).step_by(4) {
        for bx in (x0..x1).step_by(4) {
            block.clear();
            for y in by..(by + 4).min(y1) {
                for x in bx..(bx + 4).min(x1) {
                    let d = depth.get(x as u32, y as u32);
                    if d > 0.0 && d.is_finite() {
                        block.push(d);
                    }
                }
            }
            if block.len() < 8 {
                continue;
            }
            let mid = block.len() / 2;
            block.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
            blocks += 1;
            nearer += usize::from(block[mid] < limit);
        }
    }
    blocks > 0 && nearer * 10 > blocks
}

/// Each position moved, at its own depth, onto the ray through pixel `centre_px` (see
/// [`ObservationConfig::box_crops_below_px`]); positions behind the camera stay.
pub fn box_aimed(
    intrinsics: &Intrinsics,
    centre_px: [f64; 2],
    positions_in_view_m: &[Vector3<f64>],
) -> Vec<Vector3<f64>> {
    let ray = Vector3::new(
        (centre_px[0] - intrinsics.cx()) / intrinsics.fx(),
        (centre_px[1] - intrinsics.cy()) / intrinsics.fy(),
        1.0,
    );
    positions_in_view_m
        .iter()
        .map(|p| if p.z < MIN_RANGE_M { *p } else { ray * p.z })
        .collect()
}

/// A mesh's origin farther than this share of its diameter from the centre of its bounding
/// box (a mesh whose origin is its base) is not cropped at the detector's box.
const MAX_BOX_AIM_OFFSET_REL: f64 = 0.1;

/// Whether the origin of `mesh` (`diameter_m` across) lies near the centre of its bounding
/// box, where a detector's box centre falls: the condition for
/// [`ObservationConfig::box_crops_below_px`], since the codebook centres its crops on the
/// origin.
pub fn origin_near_box_centre(mesh: &crate::mesh::Mesh, diameter_m: f64) -> bool {
    mesh.bounds().center_m().norm() <= MAX_BOX_AIM_OFFSET_REL * diameter_m
}

/// How many pixels the object of `codebook` spans in a view at `depth_m` (its diameter over
/// the range; a range under 5 cm counts as 5 cm): what the size weighting and the
/// verification's near-view limit read.
pub fn object_size_px(codebook: &Codebook, intrinsics: &Intrinsics, depth_m: f64) -> f64 {
    codebook.box_m() * intrinsics.fx() / depth_m.max(MIN_RANGE_M)
}

/// How many pixels a silhouette of `area_m2` covers in a view at `depth_m` (the same 5 cm
/// floor on the range as [`object_size_px`]): what the area weighting reads.
pub fn object_area_px(area_m2: f64, intrinsics: &Intrinsics, depth_m: f64) -> f64 {
    area_m2 * intrinsics.fx() * intrinsics.fy() / depth_m.max(MIN_RANGE_M).powi(2)
}

/// The nearest range the apparent sizes are computed at.
const MIN_RANGE_M: f64 = 0.05;

/// How much of its log-likelihood a view counts with for an object `size_px` across that
/// covers `area_px` pixels (see [`ObservationConfig::full_area_px`] and
/// [`ObservationConfig::full_size_px`]).
pub fn size_strength(size_px: f32, area_px: f32, config: &ObservationConfig) -> f32 {
    if config.full_area_px > 0.0 {
        if !area_px.is_finite() {
            return 1.0;
        }
        return (area_px / config.full_area_px).clamp(0.0, 1.0);
    }
    if config.full_size_px <= 0.0 || !size_px.is_finite() {
        return 1.0;
    }
    (size_px / config.full_size_px).clamp(0.0, 1.0).powi(2)
}

/// The mean area (m²) of the silhouette of `mesh` over `n_directions` directions spread
/// evenly over the sphere (a Fibonacci lattice), each rasterised at 128 px from 20 diameters
/// away (near orthographic). For a convex body it is a quarter of its surface (Cauchy); a
/// thin or hollow one covers less than its diameter suggests.
pub fn mean_silhouette_area_m2(mesh: &crate::mesh::Mesh, n_directions: usize) -> f64 {
    const SIDE_PX: u32 = 128;
    let diameter_m = mesh.diameter_m();
    if diameter_m.is_nan() || diameter_m <= 0.0 || n_directions == 0 {
        return 0.0;
    }
    let distance_m = 20.0 * diameter_m;
    // the diameter spans 100 px of the 128
    let f_px = 100.0 * distance_m / diameter_m;
    let Ok(k) = Intrinsics::from_focal(SIDE_PX, SIDE_PX, f_px) else {
        return 0.0;
    };
    let centre = mesh.bounds().center_m();
    let pixel_m2 = (distance_m / f_px).powi(2);
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let total: f64 = (0..n_directions)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n_directions as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * i as f64;
            let dir = Vector3::new(r * a.cos(), r * a.sin(), z);
            let rotation = nalgebra::UnitQuaternion::rotation_between(&dir, &Vector3::z())
                .unwrap_or_else(|| nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
            let pose = crate::geometry::Pose::from_parts(
                nalgebra::Translation3::from(Vector3::new(0.0, 0.0, distance_m) - rotation * centre),
                rotation,
            );
            let covered = crate::render::raster::silhouette(mesh, &pose, &k)
                .iter()
                .filter(|c| **c)
                .count();
            covered as f64 * pixel_m2
        })
        .sum();
    total / n_directions as f64
}

fn default_full_similarity() -> f32 {
    0.85
}

fn default_full_size_px() -> f32 {
    90.0
}

/// Whether a setting is at zero, its "off" (left out of the serialised settings then).
fn default_true() -> bool {
    true
}

pub(crate) fn is_zero<T: Default + PartialEq>(x: &T) -> bool {
    *x == T::default()
}

/// How much of its log-likelihood a view whose best similarity is `best` contributes (see
/// [`ObservationConfig::full_similarity`]): 0 at the gate, 1 from `full_similarity` up.
pub fn evidence_strength(best: f32, config: &ObservationConfig) -> f32 {
    let span = (config.full_similarity - config.gate_similarity).max(1e-6);
    ((best - config.gate_similarity) / span).clamp(0.0, 1.0)
}

/// What one view says about one object's particles.
#[derive(Debug, Clone)]
pub struct ViewEvidence {
    /// Cosine similarity per (view bin, particle), bin-major (only when the view is gated in);
    /// [`add_loglik`] turns it into the log-likelihood on the fly.
    pub sim: Vec<f32>,
    /// Per particle `1 / c_max` (0 for unusable crops).
    pub inv_best: Vec<f32>,
    /// `-1 / (2 sigma^2)`.
    pub k: f32,
    pub floor: f32,
    /// Log depth-consistency term per particle.
    pub depth_log: Vec<f32>,
    /// Best absolute similarity over valid particles and bins.
    pub best_similarity: f32,
    /// Particles whose crop was usable.
    pub valid: Vec<bool>,
    pub crops_s: f64,
    pub encoding_s: f64,
    pub matching_s: f64,
    pub likelihoods_s: f64,
}

/// One camera image with its intrinsics.
pub struct ViewImage<'a> {
    pub intrinsics: &'a Intrinsics,
    pub depth: &'a DepthImage,
    pub color: Option<&'a ColorImage>,
}

/// Crops and codes of particles at `positions_in_view_m`; returns (codes row-major `n x k`
/// unit rows, valid flags, central median normalised depth (NaN: none), crop seconds,
/// encoding seconds).
pub fn encode_particles(
    codebook: &Codebook,
    view: &ViewImage,
    positions_in_view_m: &[Vector3<f64>],
) -> (Vec<f32>, Vec<bool>, Vec<f32>, f64, f64) {
    let t0 = Instant::now();
    let layout = codebook.layout();
    let d = layout.dim();
    let f = layout.feature_px;
    let n = positions_in_view_m.len();
    let side_m = codebook.crop_side_m();
    let box_m = codebook.box_m();
    let suppress = codebook.config.suppress_plane;
    let k = view.intrinsics;
    let crops: Vec<(Vec<f32>, Vec<bool>, bool, f32)> = positions_in_view_m
        .par_iter()
        .map(|p| {
            let mut x = vec![0f32; d];
            let mut m = vec![true; d];
            if p.z < 0.05 {
                return (x, m, false, 0.0);
            }
            let uv = [k.fx() * p.x / p.z + k.cx(), k.fy() * p.y / p.z + k.cy()];
            if !k.contains(uv) {
                return (x, m, false, 0.0);
            }
            let params = CropParams {
                centre_px: uv,
                side_px: k.fx() * side_m / p.z,
                rotation_rad: 0.0,
                z_centre_m: p.z,
                box_m,
                zero_is_far: false,
            };
            let share = sample_crop(&layout, view.depth, view.color, &params, &mut x, &mut m);
            // depth consistency (below) reads the raw cells; the encoder gets inpainted ones
            let raw_x = x[..f * f].to_vec();
            let raw_m = m[..f * f].to_vec();
            let mut has_object = true;
            if suppress {
                // is anything standing on the table here? (the steep fit, on a copy: an empty
                // patch of table must not pass for an object seen edge-on)
                let mut probe = x[..f * f].to_vec();
                if crate::tracker::crop::suppress_support_plane_steep(&layout, &mut probe, &m, false) {
                    let near = (0..f * f).filter(|&c| !m[c] && probe[c] < 1.0).count();
                    has_object = near as f64 >= MIN_OBJECT_SHARE * (f * f) as f64;
                }
                crate::tracker::crop::suppress_support_plane(&layout, &mut x, &m, view.color.is_some());
            }
            crate::tracker::crop::inpaint_depth(&layout, &mut x, &mut m, view.color.is_some());
            crate::tracker::crop::to_chromaticity(&layout, &mut x, &m);
            // depth check input: the central surface of the raw crop
            let score = crate::tracker::crop::central_median_depth(&layout, &raw_x, &raw_m).unwrap_or(f32::NAN);
            (x, m, share >= MIN_VALID_SHARE && has_object, score)
        })
        .collect();
    let crops_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let mut x = Vec::with_capacity(n * d);
    let mut mask = Vec::with_capacity(n * d);
    let mut valid = Vec::with_capacity(n);
    let mut score = Vec::with_capacity(n);
    for (cx, cm, v, s) in crops {
        x.extend(cx);
        mask.extend(cm);
        valid.push(v);
        score.push(s);
    }
    let kd = codebook.code_dim();
    let mut codes = vec![0f32; n * kd];
    if n > 0 {
        codebook.encoder.encode_observations(&x, &mask, n, &mut codes);
    }
    for (p, v) in valid.iter().enumerate() {
        if !v {
            codes[p * kd..(p + 1) * kd].fill(0.0);
        }
    }
    (codes, valid, score, crops_s, t1.elapsed().as_secs_f64())
}

/// Cosine similarities of `n` unit codes (row-major `n x k`) with every codebook code, into
/// `out` (bin-major: `out[b * n + p]`), in chunks of bins over all threads; returns each
/// particle's best similarity and the (lowest) bin where it is reached, computed while each
/// chunk is still in cache (no extra pass over the `n x bins` array).
pub fn match_codes(codebook: &Codebook, codes: &[f32], n: usize, out: &mut Vec<f32>) -> (Vec<f32>, Vec<u32>) {
    let all: Vec<u32> = (0..codebook.n_bins() as u32).collect();
    crate::tracker::sparse::match_rows(codes, &codebook.codes, n, codebook.code_dim(), &all, out)
}

/// The evidence of one view from its particles' similarities (`sim`, `rows x n`, moved into
/// the result), each particle's best similarity `best_per_particle` and the codebook bin where
/// it is reached (`arg`, `u32::MAX`: none), or `None` when the view does not see the object
/// (no usable crop, or best similarity below the gate). `c_max` is the best similarity over
/// the valid particles and the matched bins.
#[allow(clippy::too_many_arguments)]
pub fn view_evidence(
    codebook: &Codebook,
    sim: &mut Vec<f32>,
    best_per_particle: &[f32],
    arg: &[u32],
    valid: &[bool],
    central_depth: &[f32],
    positions_in_view_m: &[Vector3<f64>],
    config: &ObservationConfig,
    box_centred: bool,
) -> Option<ViewEvidence> {
    let n = positions_in_view_m.len();
    let best = best_per_particle
        .iter()
        .zip(valid)
        .filter(|(_, v)| **v)
        .map(|(b, _)| *b)
        .fold(f32::NEG_INFINITY, f32::max);
    if best.is_nan() || best < config.gate_similarity {
        return None;
    }
    let strength = evidence_strength(best, config);
    // per particle 1 / c_max; 0 for unusable crops, whose r = 1 then lands on the floor
    let inv_best: Vec<f32> = valid.iter().map(|v| if *v { 1.0 / best } else { 0.0 }).collect();
    // depth check (PoseRBPF renders at the mean pose; we compare the crop's central surface
    // depth with that of the particle's best template): error (m) = (observed - template) * box
    let box_m = codebook.box_m() as f32;
    let depth_log: Vec<f32> = (0..n)
        .map(|p| {
            if !valid[p] || arg[p] == u32::MAX {
                return config.depth_floor;
            }
            let tmpl = codebook.central_depth_norm(arg[p] as usize, box_centred);
            let obs = central_depth[p];
            if !obs.is_finite() || !tmpl.is_finite() {
                return config.depth_floor;
            }
            let err_m = (obs - tmpl) * box_m;
            let sigma = config.depth_sigma_m * (positions_in_view_m[p].z as f32).max(0.3);
            (-0.5 * err_m * err_m / (sigma * sigma)).max(config.depth_floor)
        })
        .collect();
    Some(ViewEvidence {
        sim: std::mem::take(sim),
        inv_best,
        k: -0.5 / (config.sigma * config.sigma) * strength,
        floor: config.loglik_floor * strength,
        depth_log,
        best_similarity: best,
        valid: valid.to_vec(),
        crops_s: 0.0,
        encoding_s: 0.0,
        matching_s: 0.0,
        likelihoods_s: 0.0,
    })
}

/// The evidence of one view for particles at `positions_in_view_m` against every bin of the
/// codebook (the dense matching), or `None` when the view does not see the object. `sim` is
/// a reusable buffer (moved into the result).
pub fn observe_view(
    codebook: &Codebook,
    view: &ViewImage,
    positions_in_view_m: &[Vector3<f64>],
    config: &ObservationConfig,
    sim: &mut Vec<f32>,
) -> Option<ViewEvidence> {
    let n = positions_in_view_m.len();
    let (codes, valid, score, crops_s, encoding_s) = encode_particles(codebook, view, positions_in_view_m);
    if !valid.iter().any(|v| *v) {
        return None;
    }
    let t0 = Instant::now();
    let (mx, arg) = match_codes(codebook, &codes, n, sim);
    let matching_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let mut ev = view_evidence(
        codebook,
        sim,
        &mx,
        &arg,
        &valid,
        &score,
        positions_in_view_m,
        config,
        false,
    )?;
    ev.crops_s = crops_s;
    ev.encoding_s = encoding_s;
    ev.matching_s = matching_s;
    ev.likelihoods_s = t1.elapsed().as_secs_f64();
    Some(ev)
}

/// The log-likelihood one view gives a bin, from the cosine similarity `c` of the particle's
/// crop to the bin's code: `max(k (1 - c inv)^2, floor)` with `inv = 1 / c_max` and
/// `k = -1 / (2 sigma^2)`. The one place of the formula: [`add_loglik`] and the fused update
/// ([`fuse::fuse_update`]) both call it.
#[inline(always)]
pub fn view_loglik(c: f32, inv: f32, k: f32, floor: f32) -> f32 {
    let x = 1.0 - c * inv;
    (k * x * x).max(floor)
}

impl ViewEvidence {
    /// This view's log-likelihood ([`view_loglik`]) of every particle at one view bin, whose
    /// similarities are `sim_row` (`n` values), written into `out` (`assign`) or added to it.
    #[inline(always)]
    pub fn loglik_row(&self, sim_row: &[f32], out: &mut [f32], assign: bool) {
        let (k, floor) = (self.k, self.floor);
        if assign {
            for ((d, s), i) in out.iter_mut().zip(sim_row).zip(&self.inv_best) {
                *d = view_loglik(*s, *i, k, floor);
            }
        } else {
            for ((d, s), i) in out.iter_mut().zip(sim_row).zip(&self.inv_best) {
                *d += view_loglik(*s, *i, k, floor);
            }
        }
    }
}

/// Adds a view's log-likelihood ([`view_loglik`]) into `dst` (bin-major, `n` per bin), pulling
/// through `map` (`dst[b] += ll[map[b]]`; `None`: the identity). With `assign`, `dst` is
/// overwritten instead (the first view of a step: no zeroing pass). The fused update does this
/// for all views at once; this is its plain reference.
pub fn add_loglik(dst: &mut [f32], ev: &ViewEvidence, map: Option<&[u32]>, n: usize, assign: bool) {
    dst.par_chunks_mut(n * 1024).enumerate().for_each(|(c, chunk)| {
        let b0 = c * 1024;
        for (r, row) in chunk.chunks_mut(n).enumerate() {
            let src_b = match map {
                Some(m) => m[b0 + r] as usize,
                None => b0 + r,
            };
            ev.loglik_row(&ev.sim[src_b * n..(src_b + 1) * n], row, assign);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 200 x 200 depth image of a surface at 1 m, with a block at 0.8 m over the columns
    /// from `hidden_from` on, and a deterministic relative noise of `noise`.
    fn occluded_depth(hidden_from: u32, noise: f32) -> DepthImage {
        let data = (0..200u32 * 200)
            .map(|i| {
                let (x, y) = (i % 200, i / 200);
                let base = if x >= hidden_from { 0.8 } else { 1.0 };
                // a hash in [-1, 1]: noise without a generator
                let h = ((x.wrapping_mul(73_856_093) ^ y.wrapping_mul(19_349_663)) % 2001) as f32 / 1000.0 - 1.0;
                base * (1.0 + noise * h)
            })
            .collect();
        DepthImage::new(200, 200, data).unwrap()
    }

    #[test]
    fn a_box_partly_behind_a_nearer_surface_is_not_the_object_s_own() {
        // the object's centre at 1.05 m, 0.1 m across: its front at 1.0 m
        let hides = |depth: &DepthImage| box_hides_object(depth, [100.0, 100.0], 80.0, 1.05, 0.1);
        assert!(!hides(&occluded_depth(200, 0.0)), "nothing in front");
        assert!(!hides(&occluded_depth(200, 0.05)), "noise alone");
        assert!(hides(&occluded_depth(110, 0.05)), "a block over a third of the box");
        assert!(!hides(&occluded_depth(138, 0.0)), "a block beside the box");
    }

    #[test]
    fn a_particle_is_scored_by_the_distance_of_its_projection_to_the_object_s_box() {
        let k = Intrinsics::new(640, 480, [600.0, 0.0, 319.5, 0.0, 600.0, 239.5, 0.0, 0.0, 1.0]).unwrap();
        let cfg = DetectionBoxConfig {
            sigma_rel: 0.25,
            floor: -4.0,
        };
        let det = |object: &str, x: f64| crate::tracker::Detection {
            object: object.into(),
            bbox_xywh_px: [x, 220.0, 40.0, 40.0],
            score: 1.0,
        };
        // the object's box is centred at pixel (319.5, 239.5), its sigma 10 px; a bowl's
        // box elsewhere is no evidence of the mug
        let dets = [det("mug", 300.0), det("bowl", 100.0)];
        let at_px = |u: f64| Vector3::new((u - 319.5) / 600.0 * 2.0, 0.0, 2.0);
        let parts = [at_px(319.5), at_px(339.5), at_px(419.5), Vector3::new(0.0, 0.0, -1.0)];
        let mut out = vec![1.0f32; 4];
        let mug = nearest_box(&k, &dets, "mug", &at_px(319.5), cfg.sigma_rel);
        box_loglik(&k, mug, &parts, &cfg, &mut out);
        assert!((out[0] - 1.0).abs() < 1e-6, "at the centre: nothing taken, {}", out[0]);
        assert!(
            (out[1] - (1.0 - 2.0)).abs() < 1e-4,
            "two sigmas off: -2 nats, {}",
            out[1]
        );
        assert_eq!(out[2], 1.0 - 4.0, "far off: the floor");
        assert_eq!(out[3], 1.0 - 4.0, "behind the camera: the floor");
        // no box of the object: nothing
        let mut none = vec![0.0f32; 4];
        let can = nearest_box(&k, &dets, "can", &at_px(319.5), cfg.sigma_rel);
        box_loglik(&k, can, &parts, &cfg, &mut none);
        assert_eq!(none, vec![0.0; 4]);
    }

    #[test]
    fn of_two_boxes_of_the_object_the_one_nearest_the_track_counts() {
        let k = Intrinsics::new(640, 480, [600.0, 0.0, 319.5, 0.0, 600.0, 239.5, 0.0, 0.0, 1.0]).unwrap();
        let cfg = DetectionBoxConfig::default();
        let det = |x: f64| crate::tracker::Detection {
            object: "mug".into(),
            bbox_xywh_px: [x, 220.0, 40.0, 40.0],
            score: 1.0,
        };
        // two mugs, boxes centred at u = 119.5 and u = 519.5: the track near the second is
        // scored by the second, so a particle on the first mug pays the floor
        let dets = [det(100.0), det(500.0)];
        let at_px = |u: f64| Vector3::new((u - 319.5) / 600.0, 0.0, 1.0);
        let mut out = vec![0.0f32; 2];
        let nearest = nearest_box(&k, &dets, "mug", &at_px(510.0), cfg.sigma_rel);
        box_loglik(&k, nearest, &[at_px(519.5), at_px(119.5)], &cfg, &mut out);
        assert!(out[0].abs() < 1e-6, "{}", out[0]);
        assert_eq!(out[1] as f64, cfg.floor);
    }

    #[test]
    fn box_aimed_crops_sit_on_the_box_centre_at_each_particle_s_depth() {
        let k = Intrinsics::new(640, 480, [615.0, 0.0, 319.5, 0.0, 615.0, 239.5, 0.0, 0.0, 1.0]).unwrap();
        let mug = |x: f64| crate::tracker::Detection {
            object: "mug".into(),
            bbox_xywh_px: [x, 230.0, 24.0, 20.0],
            score: 1.0,
        };
        // a mug 3 m away, boxed at (412, 240); the track's mean 4 cm off projects 8 px away
        let dets = [mug(100.0), mug(400.0)];
        let mean = Vector3::new((420.0 - 319.5) / 615.0 * 3.0, 0.0, 3.0);
        let (centre, sigma) = nearest_box(&k, &dets, "mug", &mean, 0.25).expect("a box of the mug");
        assert_eq!(centre, [411.5, 239.5], "the box nearer the track");
        assert_eq!(sigma, 6.0);
        assert!(nearest_box(&k, &dets, "can", &mean, 0.25).is_none());
        let parts = [
            mean,
            mean + Vector3::new(0.05, -0.03, 0.2),
            Vector3::new(0.0, 0.0, -1.0),
        ];
        let aimed = box_aimed(&k, centre, &parts);
        for (a, p) in aimed.iter().zip(&parts).take(2) {
            let uv = k.project(&nalgebra::Point3::from(*a)).expect("in front");
            assert!(
                (uv[0] - centre[0]).abs() < 1e-9 && (uv[1] - centre[1]).abs() < 1e-9,
                "{uv:?}"
            );
            assert_eq!(a.z, p.z, "each particle keeps its depth (its crop's scale)");
        }
        assert_eq!(aimed[2], parts[2], "behind the camera: unchanged");
    }

    #[test]
    fn only_a_mesh_centred_on_its_box_is_cropped_at_the_detector_s_box() {
        let mut mesh = crate::mesh::builtin_mug();
        let c = mesh.bounds().center_m();
        for v in &mut mesh.vertices_m {
            for k in 0..3 {
                v[k] -= c[k] as f32;
            }
        }
        assert!(origin_near_box_centre(&mesh, 0.14));
        // the origin at its base, 4.5 cm below the centre: its box centre is not where the
        // codebook's crops are centred
        for v in &mut mesh.vertices_m {
            v[2] += 0.045;
        }
        assert!(!origin_near_box_centre(&mesh, 0.14));
    }

    #[test]
    fn small_far_objects_are_weaker_evidence() {
        let off = ObservationConfig {
            full_size_px: 0.0,
            full_area_px: 0.0,
            ..Default::default()
        };
        assert_eq!(size_strength(10.0, 1.0, &off), 1.0, "0 and 0 turn it off");
        let c = ObservationConfig {
            full_size_px: 100.0,
            ..off
        };
        assert_eq!(size_strength(100.0, 0.0, &c), 1.0);
        assert_eq!(size_strength(400.0, 0.0, &c), 1.0);
        // half the size holds a quarter of the pixels
        assert!((size_strength(50.0, 0.0, &c) - 0.25).abs() < 1e-6);
        assert!(size_strength(20.0, 0.0, &c) < size_strength(40.0, 0.0, &c));
        assert_eq!(size_strength(f32::NAN, 0.0, &c), 1.0);
        // by area, when set, whatever the diameter
        let a = ObservationConfig {
            full_area_px: 2000.0,
            ..c
        };
        assert_eq!(size_strength(10.0, 4000.0, &a), 1.0);
        assert!((size_strength(400.0, 500.0, &a) - 0.25).abs() < 1e-6);
        assert_eq!(size_strength(10.0, f32::NAN, &a), 1.0);
    }

    #[test]
    fn the_mean_silhouette_of_a_box_is_a_quarter_of_its_surface() {
        // a convex body's mean projected area is a quarter of its surface (Cauchy)
        let (x, y, z) = (0.2, 0.1, 0.05);
        let mesh = crate::mesh::builtin_box([x, y, z], [[200; 3], [100; 3]]);
        let expected = 2.0 * (x * y + y * z + x * z) / 4.0;
        let got = mean_silhouette_area_m2(&mesh, 256);
        assert!((got / expected - 1.0).abs() < 0.03, "{got} vs {expected}");
        // a thin rod covers far less than its length squared suggests
        let rod = crate::mesh::builtin_box([0.2, 0.01, 0.01], [[200; 3], [100; 3]]);
        assert!(mean_silhouette_area_m2(&rod, 64) < 0.15 * mean_silhouette_area_m2(&mesh, 64));
    }

    #[test]
    fn weak_matches_are_weak_evidence() {
        let c = ObservationConfig::default();
        assert_eq!(evidence_strength(c.gate_similarity, &c), 0.0);
        assert_eq!(evidence_strength(c.full_similarity, &c), 1.0);
        assert_eq!(evidence_strength(0.99, &c), 1.0);
        let mid = evidence_strength(0.5 * (c.gate_similarity + c.full_similarity), &c);
        assert!((mid - 0.5).abs() < 1e-5, "{mid}");
        // the contrast a view makes between a good and a poor bin shrinks with its strength
        let contrast = |best: f32| {
            let s = evidence_strength(best, &c);
            let (k, floor) = (-0.5 / (c.sigma * c.sigma) * s, c.loglik_floor * s);
            view_loglik(best, 1.0 / best, k, floor) - view_loglik(0.9 * best, 1.0 / best, k, floor)
        };
        assert!(
            contrast(0.55) < 0.5 * contrast(0.9),
            "{} vs {}",
            contrast(0.55),
            contrast(0.9)
        );
    }

    /// `encode_particles` as it was: one crop per particle with the per-sample reference of
    /// `sample_crop`, every step on its own copy.
    fn encode_particles_reference(
        codebook: &Codebook,
        view: &ViewImage,
        positions_in_view_m: &[Vector3<f64>],
    ) -> (Vec<f32>, Vec<bool>, Vec<f32>) {
        use crate::tracker::crop;
        let layout = codebook.layout();
        let (d, f) = (layout.dim(), layout.feature_px);
        let k = view.intrinsics;
        let (mut x, mut mask, mut valid, mut score) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for p in positions_in_view_m {
            let mut cx = vec![0f32; d];
            let mut cm = vec![true; d];
            let uv = [k.fx() * p.x / p.z + k.cx(), k.fy() * p.y / p.z + k.cy()];
            if p.z < 0.05 || !k.contains(uv) {
                x.extend(cx);
                mask.extend(cm);
                valid.push(false);
                score.push(0.0);
                continue;
            }
            let params = CropParams {
                centre_px: uv,
                side_px: k.fx() * codebook.crop_side_m() / p.z,
                rotation_rad: 0.0,
                z_centre_m: p.z,
                box_m: codebook.box_m(),
                zero_is_far: false,
            };
            let share = crop::sample_crop_reference(&layout, view.depth, view.color, &params, &mut cx, &mut cm);
            let raw_x = cx[..f * f].to_vec();
            let raw_m = cm[..f * f].to_vec();
            let mut has_object = true;
            if codebook.config.suppress_plane {
                let mut probe = cx[..f * f].to_vec();
                if crop::suppress_support_plane_steep(&layout, &mut probe, &cm, false) {
                    let near = (0..f * f).filter(|&c| !cm[c] && probe[c] < 1.0).count();
                    has_object = near as f64 >= MIN_OBJECT_SHARE * (f * f) as f64;
                }
                crop::suppress_support_plane(&layout, &mut cx, &cm, view.color.is_some());
            }
            crop::inpaint_depth(&layout, &mut cx, &mut cm, view.color.is_some());
            crop::to_chromaticity(&layout, &mut cx, &cm);
            x.extend(cx);
            mask.extend(cm);
            valid.push(share >= MIN_VALID_SHARE && has_object);
            score.push(crop::central_median_depth(&layout, &raw_x, &raw_m).unwrap_or(f32::NAN));
        }
        let (n, kd) = (positions_in_view_m.len(), codebook.code_dim());
        let mut codes = vec![0f32; n * kd];
        codebook.encoder.encode_observations(&x, &mask, n, &mut codes);
        for (p, v) in valid.iter().enumerate() {
            if !v {
                codes[p * kd..(p + 1) * kd].fill(0.0);
            }
        }
        (codes, valid, score)
    }

    #[test]
    fn particle_codes_match_the_per_particle_reference_on_a_rendered_scene() {
        use crate::geometry::{Pose, RotationGrid, look_at};
        use crate::tracker::codebook::{CodebookConfig, CpuViews};
        use nalgebra::{Translation3, UnitQuaternion};
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mesh = crate::mesh::builtin("box").expect("built-in box");
        let config = CodebookConfig {
            render_px: 64,
            code_dim: 16,
            color_code_dim: 4,
            n_train: 300,
            ..CodebookConfig::default()
        };
        let codebook =
            Codebook::build(&CpuViews(&mesh), &mesh, RotationGrid::new(30).expect("grid"), &config).expect("codebook");
        let mut table = crate::mesh::builtin_box([4.0, 4.0, 0.02], [[120, 100, 80], [120, 100, 80]]);
        for v in &mut table.vertices_m {
            v[2] -= 0.01;
        }
        let b = mesh.bounds();
        let world_from_object = Pose::from_parts(
            Translation3::new(0.0, 0.0, -b.min_m.z),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7),
        );
        let k = Intrinsics::from_focal(320, 240, 260.0).expect("intrinsics");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        // a near view and a far one with 5 % depth noise and missing readings (the denoised path)
        for (eye, noise) in [([-0.9, 0.1, 0.8], 0.0f32), ([0.8, -2.6, 1.6], 0.05)] {
            let world_from_camera = look_at(eye, [0.0, 0.0, 0.1]);
            let cfw = world_from_camera.inverse();
            let mut img = crate::render::raster::render(
                &k,
                &[(&mesh, cfw * world_from_object), (&table, cfw)],
                0.05,
                [40, 40, 40],
            );
            let gauss = Normal::new(0.0f32, 1.0).expect("normal");
            for (i, d) in img.depth.data_m.iter_mut().enumerate() {
                if noise > 0.0 {
                    *d = if i % 13 == 0 {
                        0.0
                    } else {
                        *d * (1.0 + noise * gauss.sample(&mut rng))
                    };
                }
            }
            let view = ViewImage {
                intrinsics: &k,
                depth: &img.depth,
                color: Some(&img.color),
            };
            let centre = (cfw * world_from_object).translation.vector;
            let jitter = Normal::new(0.0, 0.03).expect("normal");
            let mut positions: Vec<Vector3<f64>> = (0..110)
                .map(|_| centre + Vector3::from_fn(|_, _| jitter.sample(&mut rng)))
                .collect();
            // off the image, behind the camera, at the image's edge
            positions.push(Vector3::new(5.0, 0.0, 1.0));
            positions.push(Vector3::new(0.0, 0.0, -1.0));
            positions.push(Vector3::new(centre.x + 0.6 * centre.z, centre.y, centre.z));
            for with_color in [true, false] {
                let view = ViewImage {
                    color: if with_color { view.color } else { None },
                    ..view
                };
                let (codes, valid, score, _, _) = encode_particles(&codebook, &view, &positions);
                let (codes0, valid0, score0) = encode_particles_reference(&codebook, &view, &positions);
                assert_eq!(valid, valid0, "eye {eye:?}, colour {with_color}");
                assert!(valid.iter().filter(|v| **v).count() > 50, "eye {eye:?}: {valid:?}");
                for (p, (a, b)) in score.iter().zip(&score0).enumerate() {
                    assert!(
                        a.to_bits() == b.to_bits() || (!valid[p] && a.is_nan() == b.is_nan()),
                        "{p}: {a} {b}"
                    );
                }
                for (i, (a, b)) in codes.iter().zip(&codes0).enumerate() {
                    assert!(
                        (a - b).abs() <= 1e-6,
                        "eye {eye:?}, colour {with_color}, code value {i}: {a} vs {b}"
                    );
                }
            }
        }
    }
}
