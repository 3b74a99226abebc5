//! Crop features and the default encoder.
//!
//! # Features
//! A crop is a square around the (projected) object centre, sampled on a `F x F` grid
//! (`F = feature_px`) with 2 x 2 nearest-neighbour sub-samples per cell:
//! - depth, normalised `clamp((d - z) / box + 0.5, 0, 1)` (`z` the depth of the object centre,
//!   `box` the object's diameter). A missing reading (0) is *masked*, never read as "near". In
//!   codebook renders, an empty pixel is background and reads as far (1).
//! - colour on a `F/2 x F/2` grid, RGB in [0, 1] times `color_weight`, where the (denoised)
//!   depth cell under the sample says "object or nearer" (normalised < 1); far background
//!   reads as a neutral grey so that the clutter behind the object does not count. Masked
//!   where no depth sample is valid or the camera gives no colour. By default the object's
//!   cells are then turned into chromaticity ([`to_chromaticity`]): the light changes their
//!   brightness, not their hue.
//!
//! A far camera's depth is mostly noise against a small object (the paper's 5 % at 3 m is
//! 0.15 m per pixel, more than a mug's diameter): crops whose estimated noise
//! ([`depth_noise_sigma`]) is high are median-filtered ([`denoise_depth`]) before the colour
//! is gated by them. Without it, the object/background split and so the colour were random in
//! far views (measured on generated scenes: the orientation error halved with it).
//!
//! Masked values are replaced by the mean of the clean templates before encoding (the
//! least-informative value for a linear encoder).
//!
//! A support plane (table, floor) around the object is removed from observed crops before
//! encoding ([`suppress_support_plane`]): at the object's depth it would otherwise read as
//! object shape and colour, and a linear encoder does not learn to ignore it (measured on
//! generated scenes: the true bin ranked 90th to 1,304th at the true position with the table
//! in the crop, first without it).
//!
//! # The default encoder ([`LinearDenoisingEncoder`])
//! PCA of the clean templates gives the codes (128-d by default, centred by the template mean
//! so that cosine similarities are not all near 1). PCA of noisy copies would not denoise
//! (independent noise adds a constant to the covariance), so the observation side is a
//! *regression*: ridge regression from corrupted crops (noise, missing pixels, occluders,
//! clutter, a support plane touching the object then suppressed as in observed crops, shifted
//! and rescaled crops, exposure and white-balance changes) to the clean templates' codes.
//!
//! The codes are partially whitened (`CodebookConfig::whiten`, default 0.5): component `c` is
//! scaled by `var_c^(-whiten / 2)`. Plain PCA codes weigh the few large components (the
//! silhouette, which a 180-degree flip of a bottle or a box leaves unchanged) so heavily that
//! the colour detail that tells the flip apart barely moves the cosine (flipped templates at
//! 0.95-0.97); with 0.5 the true pose beat its flip in 71 % of generated views against 52 %.
//!
//! # Depth and colour, each with its own code (encoder v5)
//! With colour, the encoder is two of the above side by side ([`LinearDenoisingEncoder::fit_blocks`]):
//! the depth cells get 96 components and the colour cells 32 (`CodebookConfig::color_code_dim`),
//! each block reads only its own inputs and is normalised on its own ([`finish_codes`]), and
//! the similarity is the weighted mean of the two cosines, colour at 0.25
//! (`CodebookConfig::color_code_weight`). The tracker's log-likelihood is then a product of a
//! depth expert and a colour expert, and neither's norm decides how much it counts. In one code
//! of both, a real crop's colours (far from the mesh's vertex colours, under another light)
//! drowned what its depth said: on the real mug clip, four of eight encoder seeds ended with
//! the mug upside down (173-177 deg), none with the split codes. Measured on 64 generated lit
//! sequences (10-degree grid, every 5th frame), orientation error (L1 over the three axes) by
//! colour weight: 0.15: 52.5 deg, 0.25: 49.1, 0.5: 47.2; one code of both: 59.7. At 0.35 one
//! real seed of eight ended upside down, at 0.5 four did; 0.25 is the weight that keeps the
//! real clip and nearly all of the generated gain. 16 colour components instead of 32: 49.2.
//!
//! # The training set is streamed
//! PCA, whitening and the ridge regression need only sums over the training pairs: the Gram
//! matrices of the clean and of the corrupted crops and their cross term
//! ([`LinearDenoisingEncoder::fit_streamed`], chunks of 1,024 crops). So the number of crops
//! costs build time only: 36,000 by default (`CodebookConfig::n_train`), where 12,000 left the
//! real mug clip at the mercy of the draw (over eight training seeds: spin open 4 of 8 and one
//! track 57 deg off, against 7 of 8 and 12-16 deg in all eight). Measured with `pregrasp eval`
//! on one sequence, full grid, building the codebook first: peak RSS 0.93 GB with 36,000
//! crops streamed, 1.05 GB with 12,000 held in memory.

use crate::camera::{ColorImage, DepthImage, pixel_index};
use crate::tracker::TrackerError;
use nalgebra::{DMatrix, DMatrixView, DMatrixViewMut};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Version of the feature layout and of the default encoder (part of every codebook cache key).
pub const ENCODER_VERSION: u32 = 6;

/// Colour of far background in features (before `color_weight`).
const BACKGROUND_GREY: f32 = 0.5;
/// The steep plane fit: ring residuals noisier than this (normalised depth) are clutter, not
/// a plane.
const MAX_PLANE_SIGMA: f32 = 0.3;
/// The steep plane fit's lowest noise scale (normalised depth): the affine plane model is off
/// by about this much over a crop (perspective).
const MIN_PLANE_SIGMA: f32 = 0.03;
/// Sub-samples per feature cell side.
const SUBSAMPLES: usize = 2;

/// Layout of a feature vector.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FeatureLayout {
    pub feature_px: usize,
    pub use_color: bool,
    pub color_weight: f32,
    /// Colour cells hold chromaticity, not RGB ([`to_chromaticity`]).
    #[serde(default)]
    pub chromaticity: bool,
}

impl FeatureLayout {
    pub fn depth_len(&self) -> usize {
        self.feature_px * self.feature_px
    }
    pub fn color_px(&self) -> usize {
        (self.feature_px / 2).max(1)
    }
    pub fn color_len(&self) -> usize {
        if self.use_color {
            self.color_px() * self.color_px() * 3
        } else {
            0
        }
    }
    pub fn dim(&self) -> usize {
        self.depth_len() + self.color_len()
    }
    /// The depth cells (flat indices) under colour cell `(ci, cj)`: its `per x per` block, with
    /// `per = feature_px / color_px`.
    pub fn depth_cells_under(&self, ci: usize, cj: usize) -> impl Iterator<Item = usize> {
        let f = self.feature_px;
        let per = f / self.color_px();
        (0..per).flat_map(move |a| (0..per).map(move |b| (ci * per + a) * f + cj * per + b))
    }
}

/// Where and how to cut a crop out of an image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropParams {
    /// Crop centre, pixels (continuous coordinates: pixel `i` covers `[i, i + 1)`).
    pub centre_px: [f64; 2],
    /// Side of the square crop, pixels.
    pub side_px: f64,
    /// The crop is the image rotated by this angle about the centre (template in-plane bins).
    pub rotation_rad: f64,
    /// Depth of the object centre (m).
    pub z_centre_m: f64,
    /// Normalisation box (m).
    pub box_m: f64,
    /// Treat a zero depth (and pixels outside the image) as far background (renders) rather
    /// than as missing (sensors).
    pub zero_is_far: bool,
}

/// Samples the features of one crop into `out` (length `layout.dim()`), masks into `mask`.
/// Returns the share of depth cells that are valid.
pub fn sample_crop(
    layout: &FeatureLayout,
    depth: &DepthImage,
    color: Option<&ColorImage>,
    p: &CropParams,
    out: &mut [f32],
    mask: &mut [bool],
) -> f64 {
    let f = layout.feature_px;
    let (w, h) = (depth.width as i64, depth.height as i64);
    let (s, c) = p.rotation_rad.sin_cos();
    // source pixel of a crop offset (in crop pixels from the centre)
    let src = |qx: f64, qy: f64| -> Option<usize> {
        // T_theta(q) = T_0(Rz(-theta) q)
        let x = p.centre_px[0] + c * qx + s * qy;
        let y = p.centre_px[1] - s * qx + c * qy;
        let (xi, yi) = (pixel_index(x), pixel_index(y));
        if xi < 0 || yi < 0 || xi >= w || yi >= h {
            None
        } else {
            Some((yi * w + xi) as usize)
        }
    };
    // unclamped here: the noise estimate and the median filter of [`denoise_depth`] need
    // the values beyond the normalisation box; it clamps
    let norm = |d: f32| -> Option<f32> {
        if d > 0.0 && d.is_finite() {
            Some(((d as f64 - p.z_centre_m) / p.box_m + 0.5) as f32)
        } else if p.zero_is_far {
            Some(1.0)
        } else {
            None
        }
    };
    let cell = p.side_px / f as f64;
    let mut valid = 0usize;
    for i in 0..f {
        for j in 0..f {
            let mut sum = 0.0f32;
            let mut n = 0;
            for si in 0..SUBSAMPLES {
                for sj in 0..SUBSAMPLES {
                    let qx = (j as f64 + (sj as f64 + 0.5) / SUBSAMPLES as f64) * cell - p.side_px / 2.0;
                    let qy = (i as f64 + (si as f64 + 0.5) / SUBSAMPLES as f64) * cell - p.side_px / 2.0;
                    let v = match src(qx, qy) {
                        Some(k) => norm(depth.data_m[k]),
                        None => p.zero_is_far.then_some(1.0),
                    };
                    if let Some(v) = v {
                        sum += v;
                        n += 1;
                    }
                }
            }
            let k = i * f + j;
            if n > 0 {
                out[k] = sum / n as f32;
                mask[k] = false;
                valid += 1;
            } else {
                out[k] = 0.0;
                mask[k] = true;
            }
        }
    }
    denoise_depth(layout, &mut out[..f * f], &mask[..f * f]);
    if layout.use_color {
        let fc = layout.color_px();
        let ccell = p.side_px / fc as f64;
        let base = layout.depth_len();
        for i in 0..fc {
            for j in 0..fc {
                let mut sum = [0.0f32; 3];
                let mut n = 0;
                for si in 0..SUBSAMPLES {
                    for sj in 0..SUBSAMPLES {
                        let qx = (j as f64 + (sj as f64 + 0.5) / SUBSAMPLES as f64) * ccell - p.side_px / 2.0;
                        let qy = (i as f64 + (si as f64 + 0.5) / SUBSAMPLES as f64) * ccell - p.side_px / 2.0;
                        let k = src(qx, qy);
                        // object or background: the (denoised) depth cell under this sample,
                        // not the raw pixel (far cameras' per-pixel noise would flip it)
                        let (di, dj) = (
                            (i * f / fc + si * f / (fc * SUBSAMPLES)).min(f - 1),
                            (j * f / fc + sj * f / (fc * SUBSAMPLES)).min(f - 1),
                        );
                        let d = (!mask[di * f + dj]).then(|| out[di * f + dj]);
                        let Some(d) = d else { continue };
                        let rgb = match (k, color) {
                            (Some(k), Some(img)) if d < 1.0 => {
                                let c = img.data[k];
                                [c[0] as f32 / 255.0, c[1] as f32 / 255.0, c[2] as f32 / 255.0]
                            }
                            (_, Some(_)) => [BACKGROUND_GREY; 3],
                            (_, None) => continue,
                        };
                        for ch in 0..3 {
                            sum[ch] += rgb[ch];
                        }
                        n += 1;
                    }
                }
                for (ch, sc) in sum.iter().enumerate() {
                    let k = base + (i * fc + j) * 3 + ch;
                    if n > 0 {
                        out[k] = sc / n as f32 * layout.color_weight;
                        mask[k] = false;
                    } else {
                        out[k] = 0.0;
                        mask[k] = true;
                    }
                }
            }
        }
    }
    valid as f64 / (f * f) as f64
}

/// Below this brightness (before `color_weight`, summed over the channels: a third of it
/// per channel) a colour cell's chromaticity fades to grey (see [`to_chromaticity`]).
const CHROMA_DARK: f32 = 0.15;

/// Turns every colour cell of a crop into its chromaticity (with `layout.chromaticity`): each
/// channel divided by the cell's brightness, scaled so that grey stays the background grey,
/// `c_ch = 3 g (v_ch + e) / (v_r + v_g + v_b + 3 e)` with `g` the background grey and `e` a
/// third of [`CHROMA_DARK`] (dark cells, whose hue is noise, fade to grey).
///
/// Why: shading is not a cue a codebook can rely on. Templates are lit by a headlight, real
/// scenes by lights elsewhere, and the brightness pattern over an object (not its hue) is what
/// changes with the light. Measured with raw RGB: on generated scenes lit from above (64
/// sequences, 10-degree grid) the orientation error was 88.5 degrees against 30.5 with the
/// templates' own headlight, and on the real mug the true pose ranked 24-443 of 24,624 bins.
/// With chromaticity: 59.7 degrees on the lit scenes (every 5th frame; 53.4 every frame) and
/// rank 4-44 on the real mug. The hue pattern that tells a box from its flip (the print)
/// survives any light.
/// A per-channel gain normalisation (exposure, white balance) alone did not help the real mug
/// (rank 39-273): its mismatch is the shading, not the mean colour.
///
/// Only the object's colour cells change (those over a depth cell that is object or nearer,
/// normalised depth < 1; a crop with fewer than three is left alone); grey would map to itself
/// anyway, masked cells stay masked. Applying it to every cell instead measured worse on the
/// real mug for the default encoder seed (the spin's modes spread over 19 degrees against 33;
/// one seed of a 10-frame clip, see `tests/eval_realdata.rs`). Applied to templates,
/// training crops and observed crops alike, after the support plane is removed.
pub fn to_chromaticity(layout: &FeatureLayout, x: &mut [f32], mask: &[bool]) {
    if !(layout.use_color && layout.chromaticity) {
        return;
    }
    let grey = BACKGROUND_GREY * layout.color_weight;
    let e = CHROMA_DARK / 3.0 * layout.color_weight;
    let base = layout.depth_len();
    let fc = layout.color_px();
    let cells: Vec<usize> = (0..fc * fc)
        .filter(|&c| !mask[base + c * 3] && layout.depth_cells_under(c / fc, c % fc).any(|k| !mask[k] && x[k] < 1.0))
        .collect();
    if cells.len() < 3 {
        return;
    }
    for c in cells {
        let k = base + c * 3;
        let sum = x[k] + x[k + 1] + x[k + 2];
        for ch in 0..3 {
            x[k + ch] = 3.0 * grey * (x[k + ch] + e) / (sum + 3.0 * e);
        }
    }
}

/// Normalised depth noise (per cell) above which [`denoise_depth`] filters.
const DENOISE_MIN_SIGMA: f32 = 0.25;

/// Robust noise level of a depth-cell grid: the median absolute second difference of three
/// horizontally adjacent valid cells, as a Gaussian sigma per cell. Second differences cancel
/// the slope of a surface (a table seen from above, a can's side), and edges are a minority of
/// the triples, so the median reads the sensor's noise rather than the scene's shape. `None`
/// with too few triples.
pub fn depth_noise_sigma(layout: &FeatureLayout, x: &[f32], mask: &[bool]) -> Option<f32> {
    let f = layout.feature_px;
    // (-1, 2): the object's depth band with room for noise, not the far background
    let ok = |k: usize| !mask[k] && x[k] > -1.0 && x[k] < 2.0;
    let mut d: Vec<f32> = Vec::with_capacity(f * f);
    for i in 0..f {
        for j in 1..f - 1 {
            let k = i * f + j;
            if ok(k - 1) && ok(k) && ok(k + 1) {
                d.push((x[k - 1] - 2.0 * x[k] + x[k + 1]).abs());
            }
        }
    }
    if d.len() < 16 {
        return None;
    }
    let m = d.len() / 2;
    d.select_nth_unstable_by(m, f32::total_cmp);
    // a - 2b + c of three N(0, s^2): sigma sqrt(6) s, median |.| 0.6745 sqrt(6) s
    Some(d[m] / (0.6745 * 6f32.sqrt()))
}

/// Denoises a grid of normalised depth cells in place, then clamps it to [0, 1].
///
/// A far camera's depth noise is large against a small object (5 % of 3 m is 0.15 m, more than
/// a mug's diameter), so its crops read as noise and their object/background split (which
/// gates the colour) is random. Where the estimated noise ([`depth_noise_sigma`]) exceeds
/// `DENOISE_MIN_SIGMA`, a median over a `(2r + 1)^2` window of valid cells replaces each cell,
/// `r` growing with the noise (1 up to 0.5, else 2). Clean renders are left as they are, so
/// the templates, the training crops and observed crops all go through the same function.
pub fn denoise_depth(layout: &FeatureLayout, x: &mut [f32], mask: &[bool]) {
    let f = layout.feature_px;
    let sigma = depth_noise_sigma(layout, x, mask).unwrap_or(0.0);
    if sigma > DENOISE_MIN_SIGMA {
        let r: i64 = if sigma > 0.5 { 2 } else { 1 };
        let src = x[..f * f].to_vec();
        let mut win: Vec<f32> = Vec::with_capacity(((2 * r + 1) * (2 * r + 1)) as usize);
        for i in 0..f as i64 {
            for j in 0..f as i64 {
                let k = (i * f as i64 + j) as usize;
                if mask[k] {
                    continue;
                }
                win.clear();
                for di in -r..=r {
                    for dj in -r..=r {
                        let (a, b) = (i + di, j + dj);
                        if a >= 0 && b >= 0 && a < f as i64 && b < f as i64 {
                            let kk = (a * f as i64 + b) as usize;
                            if !mask[kk] {
                                win.push(src[kk]);
                            }
                        }
                    }
                }
                let m = win.len() / 2;
                win.select_nth_unstable_by(m, f32::total_cmp);
                x[k] = win[m];
            }
        }
    }
    for v in x[..f * f].iter_mut() {
        *v = v.clamp(0.0, 1.0);
    }
}

/// Fills masked depth cells that are holes (valid on at least three of four sides, a few
/// passes) from their neighbours; all other missing cells read as far background (1), as in
/// the renders. A sensor's missing readings are mostly background with no return; a mean
/// imputation (or filling from any neighbour) would blur the silhouette. Colour cells with no
/// sample over far background read as background grey when the camera gives colour.
pub fn inpaint_depth(layout: &FeatureLayout, x: &mut [f32], mask: &mut [bool], has_color: bool) {
    let f = layout.feature_px;
    let mut missing: Vec<usize> = (0..f * f).filter(|&k| mask[k]).collect();
    let mut passes = 0;
    while !missing.is_empty() && passes < 3 {
        let mut filled = Vec::new();
        for &k in &missing {
            let (i, j) = (k / f, k % f);
            let mut sum = 0.0;
            let mut n = 0;
            for (di, dj) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (a, b) = (i as i64 + di, j as i64 + dj);
                if a >= 0 && b >= 0 && a < f as i64 && b < f as i64 {
                    let q = a as usize * f + b as usize;
                    if !mask[q] {
                        sum += x[q];
                        n += 1;
                    }
                }
            }
            // only holes (valid on three sides or more): the rest is background, read as far
            if n >= 3 {
                filled.push((k, sum / n as f32));
            }
        }
        if filled.is_empty() {
            break;
        }
        for (k, v) in &filled {
            x[*k] = *v;
            mask[*k] = false;
        }
        missing.retain(|k| mask[*k]);
        passes += 1;
    }
    for k in missing {
        x[k] = 1.0;
        mask[k] = false;
    }
    // colour cells with no sample whose depth is now far background read as background
    if layout.use_color && has_color {
        let fc = layout.color_px();
        let base = layout.depth_len();
        for ci in 0..fc {
            for cj in 0..fc {
                let k0 = base + (ci * fc + cj) * 3;
                if !mask[k0] {
                    continue;
                }
                let far = layout.depth_cells_under(ci, cj).all(|k| x[k] >= 1.0);
                if far {
                    for ch in 0..3 {
                        x[k0 + ch] = BACKGROUND_GREY * layout.color_weight;
                        mask[k0 + ch] = false;
                    }
                }
            }
        }
    }
}

/// Support-plane suppression: fits a plane to the crop's border ring (the object's bounding
/// circle leaves it free when the crop is centred) and turns every depth cell that lies on or
/// behind that plane into far background (1), as in the renders; colour cells over far depth
/// become background grey. A table or floor at the object's depth otherwise reads as object
/// shape to the linear encoder (issue 3's cause 1).
///
/// - Fit: least median of squares over deterministic triples of ring cells, refined by least
///   squares on the inliers (`|r| < 2.5 sigma`, sigma from the median residual). Needs at least
///   40 % of the ring to be in-range depth and to agree with the plane, else nothing is done
///   (no plane around the object: free space behind it reads far already; a table so steep
///   that it saturates most of the ring is left to the encoder, which is trained on such crops:
///   fitting those too measured worse, 75 against 58 degrees on the 16 generated sequences and
///   3.7 against 1.8 cm on the real mug).
/// - Test per cell: the residual to the plane averaged over the 3 x 3 neighbourhood (noise of
///   a single cell is large for far cameras) must not be in front of the plane by more than
///   `3 sigma / sqrt(neighbours)`. Where the camera gives colour, a cell within that band is
///   removed only if its colour is close to the ring's median colour too (the table's), so the
///   low parts of an object lying on the table keep their colour and shape; cells clearly
///   behind the plane (the floor beyond the table edge) go regardless of colour.
///
/// Works on features straight from [`sample_crop`] (masked cells untouched) and returns whether
/// a plane was found.
pub fn suppress_support_plane(layout: &FeatureLayout, x: &mut [f32], mask: &[bool], has_color: bool) -> bool {
    suppress_plane_impl(layout, x, mask, has_color, false)
}

/// [`suppress_support_plane`] that also fits a table so steep that it saturates most of the
/// ring (the ring's saturated cells then only score the plane) and allows for the affine
/// model's error over a crop (noise scale at least `MIN_PLANE_SIGMA`). Too eager for the
/// encoder's input (measured worse), it answers whether anything stands on the table at all:
/// see `observation::encode_particles`.
pub fn suppress_support_plane_steep(layout: &FeatureLayout, x: &mut [f32], mask: &[bool], has_color: bool) -> bool {
    suppress_plane_impl(layout, x, mask, has_color, true)
}

fn suppress_plane_impl(layout: &FeatureLayout, x: &mut [f32], mask: &[bool], has_color: bool, steep: bool) -> bool {
    let f = layout.feature_px;
    if f < 8 {
        return false;
    }
    let w = (f / 16).max(1);
    let coord = |k: usize| -> (f32, f32) {
        let (i, j) = (k / f, k % f);
        ((j as f32 + 0.5) / f as f32 - 0.5, (i as f32 + 0.5) / f as f32 - 0.5)
    };
    let ring: Vec<usize> = (0..f * f)
        .filter(|&k| {
            let (i, j) = (k / f, k % f);
            i < w || j < w || i >= f - w || j >= f - w
        })
        .collect();
    // valid ring cells; the in-range ones define planes, all of them score planes when
    // `steep` (against the clamped prediction), the in-range ones alone otherwise
    let all: Vec<(f32, f32, f32, usize)> = ring
        .iter()
        .filter(|&&k| !mask[k])
        .map(|&k| {
            let (u, v) = coord(k);
            (u, v, x[k], k)
        })
        .collect();
    let pts: Vec<(f32, f32, f32, usize)> = all.iter().filter(|p| p.2 > 0.0 && p.2 < 1.0).copied().collect();
    let need = if steep {
        (ring.len() * 3) / 20
    } else {
        (ring.len() * 2) / 5
    };
    if pts.len() < need.max(8) || (steep && all.len() < ring.len() / 2) {
        return false;
    }
    let scored = if steep { &all } else { &pts };
    let m = pts.len();
    let residuals = |pl: [f32; 3], out: &mut Vec<f32>| {
        out.clear();
        out.extend(scored.iter().map(|(u, v, z, _)| {
            let p = pl[0] + pl[1] * u + pl[2] * v;
            (z - if steep { p.clamp(0.0, 1.0) } else { p }).abs()
        }));
    };
    let mut buf = Vec::with_capacity(scored.len());
    let mut best: Option<([f32; 3], f32)> = None;
    // deterministic triples spread over the ring
    for t in 0..48usize {
        let a = (t * 7919) % m;
        let b = (a + m / 3 + t * 13) % m;
        let c = (a + 2 * m / 3 + t * 29) % m;
        let Some(pl) = plane_through(&pts[a], &pts[b], &pts[c]) else {
            continue;
        };
        residuals(pl, &mut buf);
        let mid = buf.len() / 2;
        buf.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
        let med = buf[mid];
        if best.is_none_or(|(_, bm)| med < bm) {
            best = Some((pl, med));
        }
    }
    let Some((pl, med)) = best else { return false };
    let sigma0 = if steep {
        // noise scale from the in-range cells (saturated ones fit exactly)
        let mut r_in: Vec<f32> = pts
            .iter()
            .map(|(u, v, z, _)| (z - (pl[0] + pl[1] * u + pl[2] * v)).abs())
            .collect();
        let mid = r_in.len() / 2;
        r_in.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
        (1.4826 * r_in[mid]).max(MIN_PLANE_SIGMA)
    } else {
        (1.4826 * med).max(0.01)
    };
    // least-squares refinement on the inliers
    let inl: Vec<&(f32, f32, f32, usize)> = pts
        .iter()
        .filter(|(u, v, z, _)| (z - (pl[0] + pl[1] * u + pl[2] * v)).abs() < 2.5 * sigma0)
        .collect();
    if inl.len() < need.max(8) || (steep && sigma0 > MAX_PLANE_SIGMA) {
        return false;
    }
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for (u, v, z, _) in &inl {
        let r = nalgebra::Vector3::new(1.0, *u as f64, *v as f64);
        ata += r * r.transpose();
        atb += r * *z as f64;
    }
    let Some(sol) = ata.try_inverse().map(|i| i * atb) else {
        return false;
    };
    let pl = [sol[0] as f32, sol[1] as f32, sol[2] as f32];
    let mut res: Vec<f32> = inl
        .iter()
        .map(|(u, v, z, _)| (z - (pl[0] + pl[1] * u + pl[2] * v)).abs())
        .collect();
    let mid = res.len() / 2;
    res.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
    let sigma = (1.4826 * res[mid]).max(if steep { MIN_PLANE_SIGMA } else { 0.01 });
    // the table's colour: per-channel median over the inlier ring cells' colour cells
    let fc = layout.color_px();
    let cbase = layout.depth_len();
    let per = (f / fc).max(1);
    let color_of = |k: usize| -> Option<[f32; 3]> {
        if !(layout.use_color && has_color) {
            return None;
        }
        let (i, j) = (k / f, k % f);
        let ck = cbase + ((i / per).min(fc - 1) * fc + (j / per).min(fc - 1)) * 3;
        if mask[ck] {
            return None;
        }
        Some([x[ck], x[ck + 1], x[ck + 2]])
    };
    let table_color: Option<[f32; 3]> = if layout.use_color && has_color {
        let cols: Vec<[f32; 3]> = inl.iter().filter_map(|(_, _, _, k)| color_of(*k)).collect();
        if cols.len() >= 8 {
            let mut c = [0f32; 3];
            for (ch, cv) in c.iter_mut().enumerate() {
                let mut v: Vec<f32> = cols.iter().map(|p| p[ch]).collect();
                let mid = v.len() / 2;
                v.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
                *cv = v[mid];
            }
            Some(c)
        } else {
            None
        }
    } else {
        None
    };
    let color_tol = 0.15 * layout.color_weight;
    // residual per cell (clamped plane: the features are clamped to [0, 1])
    let resid: Vec<Option<f32>> = (0..f * f)
        .map(|k| {
            if mask[k] {
                return None;
            }
            let (u, v) = coord(k);
            let p = (pl[0] + pl[1] * u + pl[2] * v).clamp(0.0, 1.0);
            Some(x[k] - p)
        })
        .collect();
    let mut remove = vec![false; f * f];
    for k in 0..f * f {
        if mask[k] || x[k] >= 1.0 {
            continue;
        }
        let (i, j) = ((k / f) as i64, (k % f) as i64);
        let (mut sum, mut n) = (0.0f32, 0usize);
        for di in -1..=1i64 {
            for dj in -1..=1i64 {
                let (a, b) = (i + di, j + dj);
                if a >= 0
                    && b >= 0
                    && a < f as i64
                    && b < f as i64
                    && let Some(r) = resid[a as usize * f + b as usize]
                {
                    sum += r;
                    n += 1;
                }
            }
        }
        if n == 0 {
            continue;
        }
        let r = sum / n as f32;
        let tol = 3.0 * sigma / (n as f32).sqrt();
        if r < -tol {
            continue; // clearly in front of the plane: object (or an occluder)
        }
        let behind = r > tol;
        let table_like = match (table_color, color_of(k)) {
            (Some(t), Some(c)) => (0..3).all(|ch| (c[ch] - t[ch]).abs() < color_tol),
            _ => true,
        };
        if behind || table_like {
            remove[k] = true;
        }
    }
    for (k, r) in remove.iter().enumerate() {
        if *r {
            x[k] = 1.0;
        }
    }
    if layout.use_color && has_color {
        for ci in 0..fc {
            for cj in 0..fc {
                let k0 = cbase + (ci * fc + cj) * 3;
                if mask[k0] {
                    continue;
                }
                let far = (0..per).all(|a| {
                    (0..per).all(|b| {
                        let k = (ci * per + a) * f + cj * per + b;
                        mask[k] || x[k] >= 1.0
                    })
                });
                let any_removed = (0..per).any(|a| (0..per).any(|b| remove[(ci * per + a) * f + cj * per + b]));
                if far && any_removed {
                    for ch in 0..3 {
                        x[k0 + ch] = BACKGROUND_GREY * layout.color_weight;
                    }
                }
            }
        }
    }
    true
}

/// The plane `z = a + b u + c v` through three points, `None` when they are collinear.
fn plane_through(
    p: &(f32, f32, f32, usize),
    q: &(f32, f32, f32, usize),
    r: &(f32, f32, f32, usize),
) -> Option<[f32; 3]> {
    let m = nalgebra::Matrix3::new(1.0, p.0, p.1, 1.0, q.0, q.1, 1.0, r.0, r.1);
    let inv = m.try_inverse()?;
    let s = inv * nalgebra::Vector3::new(p.2, q.2, r.2);
    (s.iter().all(|v| v.is_finite()) && m.determinant().abs() > 1e-4).then(|| [s[0], s[1], s[2]])
}

/// Lower-quartile normalised depth of the central half of a crop's depth cells that lie strictly
/// inside the normalisation box (the object's visible surface near its centre); `None` when
/// no such cell is valid. Compared between an observed crop and its best template, it gives a
/// depth error in box units: `(observed - template) * box_m` metres.
pub fn central_median_depth(layout: &FeatureLayout, x: &[f32], mask: &[bool]) -> Option<f32> {
    let f = layout.feature_px;
    let mut v: Vec<f32> = Vec::with_capacity(f * f / 4);
    for i in f / 4..f - f / 4 {
        for j in f / 4..f - f / 4 {
            let k = i * f + j;
            if !mask[k] && x[k] > 0.0 && x[k] < 1.0 {
                v.push(x[k]);
            }
        }
    }
    if v.len() < 3 {
        return None;
    }
    // the lower quartile: the object's front surface; a table or wall behind the object only
    // adds larger values
    let q = v.len() / 4;
    v.select_nth_unstable_by(q, |a, b| a.total_cmp(b));
    Some(v[q])
}

/// An encoder from crop features to codes. Implementations must be usable from many threads.
pub trait Encoder: Send + Sync {
    fn input_dim(&self) -> usize;
    fn code_dim(&self) -> usize;
    /// Version string (part of the cache key).
    fn version(&self) -> String;
    /// Encodes `n` observed crops (`x` row-major `n x input_dim`, `mask` likewise: true =
    /// missing) into `out` (`n x code_dim`), ready to compare: the dot product of an
    /// observation's code with a template's code is their similarity (at most 1).
    fn encode_observations(&self, x: &[f32], mask: &[bool], n: usize, out: &mut [f32]);
    /// Encodes `n` clean templates (no missing values) into codebook codes (unit rows).
    fn encode_templates(&self, x: &[f32], n: usize, out: &mut [f32]) {
        let mask = vec![false; x.len()];
        self.encode_observations(x, &mask, n, out);
    }
}

/// One part of a split code: the inputs it reads, the code components it fills, and its
/// weight in the similarity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CodeBlock {
    /// First input (feature) and the number of inputs.
    pub input_start: usize,
    pub input_len: usize,
    /// First code component and the number of components.
    pub code_start: usize,
    pub code_len: usize,
    /// Weight of this block's cosine in the similarity (the blocks' weights sum to 1).
    pub weight: f32,
}

/// Turns raw codes (row-major `n x k`) into comparable ones. Without blocks, each row is
/// normalised. With blocks, each block of a row is normalised on its own and scaled by
/// `sqrt(weight)`: the dot product of two such rows is `sum_b w_b cos_b`, the weighted mean of
/// the blocks' cosine similarities, so a log-likelihood quadratic in it weighs each block's
/// evidence by `w_b` whatever the two blocks' norms. A block whose inputs are all missing in a
/// row (a camera without colour) is zeroed there and the row's other blocks are scaled by
/// `1 / sum of their weights`, so that the similarity stays the weighted mean of the blocks it has.
pub fn finish_codes(blocks: &[CodeBlock], mask: Option<&[bool]>, input_dim: usize, out: &mut [f32], k: usize) {
    if blocks.len() < 2 {
        normalise_rows(out, k);
        return;
    }
    let mut present = vec![true; blocks.len()];
    for (r, row) in out.chunks_mut(k).enumerate() {
        if let Some(m) = mask {
            for (p, b) in present.iter_mut().zip(blocks) {
                let start = r * input_dim + b.input_start;
                *p = !m[start..start + b.input_len].iter().all(|v| *v);
            }
        }
        let w_sum: f32 = blocks
            .iter()
            .zip(&present)
            .filter(|(_, p)| **p)
            .map(|(b, _)| b.weight)
            .sum();
        for (b, p) in blocks.iter().zip(&present) {
            let part = &mut row[b.code_start..b.code_start + b.code_len];
            let norm = part.iter().map(|v| v * v).sum::<f32>().sqrt();
            if !*p || norm <= 1e-12 || w_sum <= 0.0 {
                part.fill(0.0);
                continue;
            }
            let s = b.weight.sqrt() / w_sum / norm;
            for v in part.iter_mut() {
                *v *= s;
            }
        }
    }
}

/// PCA codes of clean templates + ridge-regression denoising of observed crops.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LinearDenoisingEncoder {
    pub input_dim: usize,
    pub code_dim: usize,
    /// Mean of the clean templates (imputation of masked values, centring of templates).
    pub mean_clean: Vec<f32>,
    /// Mean of the (imputed) corrupted training crops (centring of observations).
    pub mean_observed: Vec<f32>,
    /// PCA projection, column-major `code_dim x input_dim` (row `c` = component `c`).
    pub pca_t: Vec<f32>,
    /// Ridge map, column-major `code_dim x input_dim`.
    pub ridge_t: Vec<f32>,
    /// The code's blocks (empty: one code over all inputs; see [`finish_codes`]).
    #[serde(default)]
    pub blocks: Vec<CodeBlock>,
}

/// Top-`k` eigenvectors (columns) of a symmetric PSD matrix by subspace iteration.
fn top_eigenvectors(g: &DMatrix<f64>, k: usize, seed: u64) -> Result<DMatrix<f64>, TrackerError> {
    use rand::{Rng, SeedableRng};
    let d = g.nrows();
    let kk = (k + 16).min(d);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut q = DMatrix::<f64>::from_fn(d, kk, |_, _| rng.random::<f64>() - 0.5);
    for _ in 0..8 {
        let y = g * &q;
        q = y.qr().q();
    }
    let t = q.transpose() * g * &q;
    let eig = nalgebra::SymmetricEigen::try_new(t, 1e-12, 1000)
        .ok_or_else(|| TrackerError::Numerical("eigen decomposition did not converge".into()))?;
    let mut order: Vec<usize> = (0..kk).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let mut v = DMatrix::<f64>::zeros(kk, k.min(kk));
    for (c, &o) in order.iter().take(k.min(kk)).enumerate() {
        v.set_column(c, &eig.eigenvectors.column(o));
    }
    Ok(q * v)
}

/// Training pairs for [`LinearDenoisingEncoder::fit_streamed`], read in chunks so that the
/// training set is never held whole (36,000 crops of 1,792 features would be 0.6 GB).
pub trait TrainingPairs: Sync {
    /// Number of pairs.
    fn len(&self) -> usize;
    /// No pairs at all.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Features per row.
    fn dim(&self) -> usize;
    /// The clean rows of `rows` (row-major `rows.len() x dim`).
    fn clean(&self, rows: Range<usize>) -> Vec<f32>;
    /// The clean rows, the corrupted rows and the corrupted rows' mask (true = missing) of
    /// `rows`. Must give the same clean rows as [`Self::clean`].
    fn pairs(&self, rows: Range<usize>) -> (Vec<f32>, Vec<f32>, Vec<bool>);
}

/// Training pairs held in memory (row-major `n x d`).
pub struct SliceTraining<'a> {
    pub clean: &'a [f32],
    pub corrupted: &'a [f32],
    pub corrupted_mask: &'a [bool],
    pub n: usize,
    pub d: usize,
}

impl<'a> SliceTraining<'a> {
    /// Checks that the three buffers hold `n` rows of `d`.
    pub fn new(
        clean: &'a [f32],
        corrupted: &'a [f32],
        corrupted_mask: &'a [bool],
        n: usize,
        d: usize,
    ) -> Result<Self, TrackerError> {
        if clean.len() != n * d || corrupted.len() != n * d || corrupted_mask.len() != n * d {
            return Err(TrackerError::Config(format!("encoder fit: bad sizes (n {n}, d {d})")));
        }
        Ok(Self {
            clean,
            corrupted,
            corrupted_mask,
            n,
            d,
        })
    }
}

impl TrainingPairs for SliceTraining<'_> {
    fn len(&self) -> usize {
        self.n
    }
    fn dim(&self) -> usize {
        self.d
    }
    fn clean(&self, rows: Range<usize>) -> Vec<f32> {
        self.clean[rows.start * self.d..rows.end * self.d].to_vec()
    }
    fn pairs(&self, rows: Range<usize>) -> (Vec<f32>, Vec<f32>, Vec<bool>) {
        let r = rows.start * self.d..rows.end * self.d;
        (
            self.clean[r.clone()].to_vec(),
            self.corrupted[r.clone()].to_vec(),
            self.corrupted_mask[r].to_vec(),
        )
    }
}

/// Training pairs made on demand by two functions of a range of rows.
pub struct FnTraining<C, P> {
    pub n: usize,
    pub d: usize,
    pub clean: C,
    pub pairs: P,
}

impl<C, P> TrainingPairs for FnTraining<C, P>
where
    C: Fn(Range<usize>) -> Vec<f32> + Sync,
    P: Fn(Range<usize>) -> (Vec<f32>, Vec<f32>, Vec<bool>) + Sync,
{
    fn len(&self) -> usize {
        self.n
    }
    fn dim(&self) -> usize {
        self.d
    }
    fn clean(&self, rows: Range<usize>) -> Vec<f32> {
        (self.clean)(rows)
    }
    fn pairs(&self, rows: Range<usize>) -> (Vec<f32>, Vec<f32>, Vec<bool>) {
        (self.pairs)(rows)
    }
}

/// How the code is laid out: one code over all inputs, or blocks side by side (input start,
/// input length, code length, weight; see [`finish_codes`]).
#[derive(Debug, Clone, Copy)]
pub enum CodeLayout<'a> {
    One { code_dim: usize },
    Blocks(&'a [(usize, usize, usize, f32)]),
}

/// Rows of training pairs per chunk of the streamed fit.
const FIT_CHUNK: usize = 1024;
/// The corrupted crops are accumulated around this value (their mean is not known before the
/// pass), which keeps the Gram matrix's subtraction of the mean well conditioned.
const FIT_SHIFT: f32 = 0.5;

/// Sums over the training pairs for one block of `l` inputs: with `c` the clean row minus the
/// clean mean and `o` the imputed corrupted row minus [`FIT_SHIFT`]: `sum c c^T`, `sum o o^T`,
/// `sum o c^T`, `sum o`, `sum c`.
struct BlockSums {
    cc: DMatrix<f64>,
    oo: DMatrix<f64>,
    oc: DMatrix<f64>,
    sum_o: Vec<f64>,
    sum_c: Vec<f64>,
}

impl BlockSums {
    fn zeros(l: usize) -> Self {
        Self {
            cc: DMatrix::zeros(l, l),
            oo: DMatrix::zeros(l, l),
            oc: DMatrix::zeros(l, l),
            sum_o: vec![0.0; l],
            sum_c: vec![0.0; l],
        }
    }
}

/// `a * b^T` of two column-major `l x m` matrices (f32; the caller sums chunks in f64).
fn outer_sum(a: &[f32], b: &[f32], l: usize, m: usize) -> DMatrix<f32> {
    let av = DMatrixView::from_slice(a, l, m);
    let bt = DMatrixView::from_slice_with_strides(b, m, l, l, 1);
    let mut g = DMatrix::<f32>::zeros(l, l);
    g.gemm(1.0, &av, &bt, 0.0);
    g
}

impl LinearDenoisingEncoder {
    /// Fits the encoder: `clean` and `corrupted` are row-major `n x d` (the same templates,
    /// clean and corrupted), `corrupted_mask` marks missing values of the corrupted crops.
    /// `ridge_lambda_rel` scales the ridge penalty by the mean diagonal of the Gram matrix.
    #[allow(clippy::too_many_arguments)] // the sizes travel with the flat buffers
    pub fn fit(
        clean: &[f32],
        corrupted: &[f32],
        corrupted_mask: &[bool],
        n: usize,
        d: usize,
        code_dim: usize,
        ridge_lambda_rel: f64,
        whiten: f64,
        seed: u64,
    ) -> Result<Self, TrackerError> {
        let data = SliceTraining::new(clean, corrupted, corrupted_mask, n, d)?;
        Self::fit_streamed(&data, CodeLayout::One { code_dim }, ridge_lambda_rel, whiten, seed)
    }

    /// Fits one encoder per block of inputs (`parts`: input start, input length, code length,
    /// weight) and puts them side by side: block `b`'s code reads only its own inputs (a
    /// product of experts, see [`finish_codes`]). Arguments otherwise as [`Self::fit`].
    #[allow(clippy::too_many_arguments)] // the sizes travel with the flat buffers
    pub fn fit_blocks(
        clean: &[f32],
        corrupted: &[f32],
        corrupted_mask: &[bool],
        n: usize,
        d: usize,
        parts: &[(usize, usize, usize, f32)],
        ridge_lambda_rel: f64,
        whiten: f64,
        seed: u64,
    ) -> Result<Self, TrackerError> {
        let data = SliceTraining::new(clean, corrupted, corrupted_mask, n, d)?;
        Self::fit_streamed(&data, CodeLayout::Blocks(parts), ridge_lambda_rel, whiten, seed)
    }

    /// The fit from sums over the training pairs, read in chunks of [`FIT_CHUNK`] rows (each
    /// chunk made and multiplied on all threads): a pass over the clean rows for their mean
    /// (the imputation of missing values needs it before the second pass), then one over the
    /// pairs for the Gram matrices of the clean and the corrupted rows and their cross term.
    /// PCA, whitening and the ridge regression need nothing else, so memory does not grow with
    /// the number of training crops.
    pub fn fit_streamed(
        data: &dyn TrainingPairs,
        layout: CodeLayout,
        ridge_lambda_rel: f64,
        whiten: f64,
        seed: u64,
    ) -> Result<Self, TrackerError> {
        let (n, d) = (data.len(), data.dim());
        let one;
        let parts: &[(usize, usize, usize, f32)] = match layout {
            CodeLayout::One { code_dim } => {
                one = [(0, d, code_dim, 1.0)];
                &one
            }
            CodeLayout::Blocks(p) => p,
        };
        let w_total: f32 = parts.iter().map(|p| p.3).sum();
        let positive = |w: f32| w.is_finite() && w > 0.0;
        if n < 2 || d == 0 {
            return Err(TrackerError::Config(format!("encoder fit: bad sizes (n {n}, d {d})")));
        }
        if parts.is_empty()
            || parts
                .iter()
                .any(|&(s, l, k, w)| l == 0 || k == 0 || s + l > d || !positive(w))
            || !positive(w_total)
        {
            return Err(TrackerError::Config(format!("encoder fit: bad blocks {parts:?}")));
        }
        let chunks: Vec<Range<usize>> = (0..n).step_by(FIT_CHUNK).map(|a| a..(a + FIT_CHUNK).min(n)).collect();
        let add = |mut a: Vec<f64>, b: Vec<f64>| {
            for (x, y) in a.iter_mut().zip(&b) {
                *x += y;
            }
            a
        };
        let sum_clean = chunks
            .par_iter()
            .map(|r| {
                let x = data.clean(r.clone());
                let mut s = vec![0f64; d];
                for row in x.chunks(d) {
                    for (a, b) in s.iter_mut().zip(row) {
                        *a += *b as f64;
                    }
                }
                s
            })
            .reduce(|| vec![0f64; d], add);
        let mean_clean: Vec<f32> = sum_clean.iter().map(|v| (v / n as f64) as f32).collect();
        // one chunk at a time (its pairs made on all threads, its three products run side by
        // side): parallel chunks would each hold their own sums and data
        let mut sums: Vec<BlockSums> = parts.iter().map(|p| BlockSums::zeros(p.1)).collect();
        for r in &chunks {
            let (clean, noisy, mask) = data.pairs(r.clone());
            let m = r.len();
            for (acc, &(s, l, _, _)) in sums.iter_mut().zip(parts) {
                // column-major l x m: column `row` is the row's block
                let mut xc = vec![0f32; l * m];
                let mut xo = vec![0f32; l * m];
                for row in 0..m {
                    for j in 0..l {
                        let i = row * d + s + j;
                        let mc = mean_clean[s + j];
                        let (c, o) = (clean[i] - mc, if mask[i] { mc } else { noisy[i] } - FIT_SHIFT);
                        xc[row * l + j] = c;
                        xo[row * l + j] = o;
                        acc.sum_c[j] += c as f64;
                        acc.sum_o[j] += o as f64;
                    }
                }
                let (cc, (oo, oc)) = rayon::join(
                    || outer_sum(&xc, &xc, l, m),
                    || rayon::join(|| outer_sum(&xo, &xo, l, m), || outer_sum(&xo, &xc, l, m)),
                );
                for (a, b) in [(&mut acc.cc, cc), (&mut acc.oo, oo), (&mut acc.oc, oc)] {
                    for (x, y) in a.iter_mut().zip(b.iter()) {
                        *x += *y as f64;
                    }
                }
            }
        }

        let k_total: usize = parts.iter().map(|&(_, l, k, _)| k.min(l)).sum();
        let mut out = Self {
            input_dim: d,
            code_dim: k_total,
            mean_clean: mean_clean.clone(),
            mean_observed: vec![0.0; d],
            pca_t: vec![0.0; k_total * d],
            ridge_t: vec![0.0; k_total * d],
            blocks: Vec::with_capacity(parts.len()),
        };
        let nn = n as f64;
        let mut c0 = 0;
        for (b, (sums, &(s, l, k_req, w))) in sums.into_iter().zip(parts).enumerate() {
            let k = k_req.min(l);
            let p = top_eigenvectors(&sums.cc, k, seed.wrapping_add(b as u64))?; // l x k
            // partial whitening: component c scaled by (var_c / var_0)^(-whiten / 2)
            let var: Vec<f64> = (0..k)
                .map(|c| {
                    let v = p.column(c);
                    (v.transpose() * &sums.cc * v)[(0, 0)] / nn
                })
                .collect();
            let v0 = var[0].max(1e-12);
            let mut ps = p;
            if whiten > 0.0 {
                for (c, v) in var.iter().enumerate() {
                    ps.column_mut(c).scale_mut((v.max(1e-12) / v0).powf(-0.5 * whiten));
                }
            }
            // the corrupted rows' mean and their centred Gram matrix
            let delta: Vec<f64> = sums.sum_o.iter().map(|v| v / nn).collect();
            let dv = nalgebra::DVector::from_vec(delta.clone());
            let mut gt = &sums.oo - (&dv * dv.transpose()) * nn;
            // sum (o - delta) c^T = sum o c^T - delta (sum c)^T, times the (scaled) components
            let sc = nalgebra::DVector::from_vec(sums.sum_c.clone());
            let cross = (&sums.oc - &dv * sc.transpose()) * &ps; // l x k
            let lambda = ridge_lambda_rel * gt.trace() / l as f64 + 1e-9;
            for i in 0..l {
                gt[(i, i)] += lambda;
            }
            let chol = gt
                .cholesky()
                .ok_or_else(|| TrackerError::Numerical("ridge system is not positive definite".into()))?;
            let wmat = chol.solve(&cross); // l x k
            for (j, dj) in delta.iter().enumerate() {
                out.mean_observed[s + j] = FIT_SHIFT + *dj as f32;
            }
            // column-major k_total x d: element (c, i) at i * k_total + c
            for i in 0..l {
                for c in 0..k {
                    out.pca_t[(s + i) * k_total + c0 + c] = ps[(i, c)] as f32;
                    out.ridge_t[(s + i) * k_total + c0 + c] = wmat[(i, c)] as f32;
                }
            }
            out.blocks.push(CodeBlock {
                input_start: s,
                input_len: l,
                code_start: c0,
                code_len: k,
                weight: w / w_total,
            });
            c0 += k;
        }
        if matches!(layout, CodeLayout::One { .. }) {
            out.blocks.clear();
        }
        Ok(out)
    }

    fn project(&self, w_t: &[f32], x_centred: &[f32], n: usize, out: &mut [f32]) {
        let wv = DMatrixView::from_slice(w_t, self.code_dim, self.input_dim);
        let xv = DMatrixView::from_slice(x_centred, self.input_dim, n);
        let mut ov = DMatrixViewMut::from_slice(&mut out[..n * self.code_dim], self.code_dim, n);
        ov.gemm(1.0, &wv, &xv, 0.0);
    }
}

impl Encoder for LinearDenoisingEncoder {
    fn input_dim(&self) -> usize {
        self.input_dim
    }
    fn code_dim(&self) -> usize {
        self.code_dim
    }
    fn version(&self) -> String {
        format!("linear-denoising-v{ENCODER_VERSION}")
    }
    fn encode_observations(&self, x: &[f32], mask: &[bool], n: usize, out: &mut [f32]) {
        let d = self.input_dim;
        let xc: Vec<f32> = x[..n * d]
            .iter()
            .zip(&mask[..n * d])
            .enumerate()
            .map(|(i, (&v, &m))| {
                let j = i % d;
                (if m { self.mean_clean[j] } else { v }) - self.mean_observed[j]
            })
            .collect();
        self.project(&self.ridge_t, &xc, n, out);
        finish_codes(
            &self.blocks,
            Some(&mask[..n * d]),
            d,
            &mut out[..n * self.code_dim],
            self.code_dim,
        );
    }
    // Templates go through the same denoising map as observations (the default trait method):
    // a clean crop then matches its own bin exactly, and the noise the map suppresses is
    // suppressed on both sides of the cosine.
}

impl LinearDenoisingEncoder {
    /// Plain PCA codes of clean features (diagnostics, and the regression's targets).
    pub fn pca_codes(&self, x: &[f32], n: usize, out: &mut [f32]) {
        let d = self.input_dim;
        let xc: Vec<f32> = x[..n * d]
            .iter()
            .enumerate()
            .map(|(i, &v)| v - self.mean_clean[i % d])
            .collect();
        self.project(&self.pca_t, &xc, n, out);
    }
}

/// Normalises each row of a row-major `n x k` matrix to unit length (zero rows stay zero).
pub fn normalise_rows(x: &mut [f32], k: usize) {
    for row in x.chunks_mut(k) {
        let n: f32 = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        if n > 1e-12 {
            for v in row.iter_mut() {
                *v /= n;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// A 32 x 32 crop: a tilted table (depth grows `slope` boxes across the crop, with noise)
    /// and a block standing on it in the centre, in front of the table by 0.1..0.4 box.
    fn table_crop(
        with_color: bool,
        noise: f32,
        seed: u64,
        slope: f32,
    ) -> (FeatureLayout, Vec<f32>, Vec<bool>, Vec<bool>) {
        let layout = FeatureLayout {
            feature_px: 32,
            use_color: with_color,
            color_weight: 0.7,
            chromaticity: false,
        };
        let f = 32;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n = Normal::new(0.0f32, noise.max(1e-6)).unwrap();
        let mut x = vec![0f32; layout.dim()];
        let mask = vec![false; layout.dim()];
        let mut object = vec![false; f * f];
        for i in 0..f {
            for j in 0..f {
                let v = (i as f32 + 0.5) / f as f32 - 0.5;
                let table = 0.5 - slope * v; // nearer at the bottom of the image
                let k = i * f + j;
                let inside = (10..22).contains(&i) && (11..21).contains(&j);
                object[k] = inside;
                let z = if inside {
                    table - 0.1 - 0.3 * (i as f32 - 10.0) / 12.0
                } else {
                    table
                };
                x[k] = (z + n.sample(&mut rng)).clamp(0.0, 1.0);
            }
        }
        if with_color {
            let fc = layout.color_px();
            for ci in 0..fc {
                for cj in 0..fc {
                    let k = (2 * ci) * f + 2 * cj;
                    let c = if object[k] { [0.9, 0.8, 0.1] } else { [0.5, 0.3, 0.2] };
                    for ch in 0..3 {
                        x[f * f + (ci * fc + cj) * 3 + ch] = c[ch] * 0.7;
                    }
                }
            }
        }
        (layout, x, mask, object)
    }

    /// A 32 x 32 depth grid (unclamped, normalised): a block at 0.3 in front of a plane at
    /// 0.7, plus Gaussian noise.
    fn block_cells(noise: f32, seed: u64) -> (FeatureLayout, Vec<f32>, Vec<f32>) {
        let layout = FeatureLayout {
            feature_px: 32,
            use_color: false,
            color_weight: 1.0,
            chromaticity: false,
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n = Normal::new(0.0f32, noise.max(1e-6)).unwrap();
        let truth: Vec<f32> = (0..32 * 32)
            .map(|k| {
                let (i, j) = (k / 32, k % 32);
                if (8..24).contains(&i) && (10..22).contains(&j) {
                    0.3
                } else {
                    0.7
                }
            })
            .collect();
        let noisy = truth.iter().map(|t| t + n.sample(&mut rng)).collect();
        (layout, truth, noisy)
    }

    fn rms(a: &[f32], b: &[f32]) -> f32 {
        (a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>() / a.len() as f32).sqrt()
    }

    #[test]
    fn depth_noise_is_estimated_despite_the_edges() {
        for sigma in [0.1f32, 0.4, 0.9] {
            let (layout, _, noisy) = block_cells(sigma, 5);
            let est = depth_noise_sigma(&layout, &noisy, &[false; 1024]).unwrap();
            assert!((est / sigma - 1.0).abs() < 0.25, "sigma {sigma}: estimated {est}");
        }
        let (layout, truth, _) = block_cells(0.0, 5);
        assert!(depth_noise_sigma(&layout, &truth, &[false; 1024]).unwrap() < 0.01);
    }

    #[test]
    fn far_camera_noise_is_filtered_and_clean_crops_are_left_alone() {
        let mask = [false; 1024];
        for (sigma, max_ratio) in [(0.4f32, 0.6f32), (0.9, 0.55)] {
            let (layout, truth, mut x) = block_cells(sigma, 11);
            let clamped_truth: Vec<f32> = truth.iter().map(|v| v.clamp(0.0, 1.0)).collect();
            let before = rms(&x.iter().map(|v| v.clamp(0.0, 1.0)).collect::<Vec<_>>(), &clamped_truth);
            denoise_depth(&layout, &mut x, &mask);
            assert!(x.iter().all(|v| (0.0..=1.0).contains(v)));
            let after = rms(&x, &clamped_truth);
            assert!(after < max_ratio * before, "sigma {sigma}: rms {before} -> {after}");
        }
        // a clean render (sharp edges, no noise) and a near camera's crop are left as they are
        for sigma in [0.0f32, 0.1] {
            let (layout, _, noisy) = block_cells(sigma, 1);
            let mut x = noisy.clone();
            denoise_depth(&layout, &mut x, &mask);
            let clamped: Vec<f32> = noisy.iter().map(|v| v.clamp(0.0, 1.0)).collect();
            assert_eq!(x, clamped, "sigma {sigma}");
        }
    }

    #[test]
    fn colour_of_a_small_far_object_survives_its_depth_noise() {
        // a 0.13 m object 3 m away, 5 % depth noise (1.15 boxes per pixel): the colour cells
        // over the object must read the object's colour, not the background grey
        let (w, h) = (64u32, 64u32);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let noise = Normal::new(0.0f32, 0.15).unwrap();
        let mut depth = DepthImage {
            width: w,
            height: h,
            data_m: vec![0.0; (w * h) as usize],
        };
        let mut color = ColorImage {
            width: w,
            height: h,
            data: vec![[40, 40, 40]; (w * h) as usize],
        };
        for y in 0..h {
            for x in 0..w {
                let k = (y * w + x) as usize;
                let object = (24..40).contains(&x) && (24..40).contains(&y);
                let z = if object { 3.0 } else { 3.6 };
                depth.data_m[k] = z + noise.sample(&mut rng);
                if object {
                    color.data[k] = [230, 30, 30];
                }
            }
        }
        let layout = FeatureLayout {
            feature_px: 32,
            use_color: true,
            color_weight: 1.0,
            chromaticity: false,
        };
        let p = CropParams {
            centre_px: [32.0, 32.0],
            side_px: 32.0,
            rotation_rad: 0.0,
            z_centre_m: 3.0,
            box_m: 0.13,
            zero_is_far: false,
        };
        let mut x = vec![0f32; layout.dim()];
        let mut m = vec![false; layout.dim()];
        sample_crop(&layout, &depth, Some(&color), &p, &mut x, &mut m);
        let fc = layout.color_px();
        let base = layout.depth_len();
        // colour cells well inside the object (the object spans cells 4..12 of 16)
        let (mut red, mut all) = (0, 0);
        for ci in 5..11 {
            for cj in 5..11 {
                all += 1;
                // the object's red is 0.9; a grey (0.5) sub-sample in the cell pulls it below
                if x[base + (ci * fc + cj) * 3] > 0.85 {
                    red += 1;
                }
            }
        }
        assert!(
            red as f64 > 0.8 * all as f64,
            "{red} of {all} object colour cells read the object"
        );
    }

    #[test]
    fn support_plane_is_removed_and_the_object_kept() {
        for (with_color, noise) in [(false, 0.02), (true, 0.02), (true, 0.15)] {
            let (layout, mut x, mask, object) = table_crop(with_color, noise, 3, 0.9);
            assert!(suppress_support_plane(&layout, &mut x, &mask, with_color));
            let f = 32;
            let table_cells: Vec<usize> = (0..f * f).filter(|&k| !object[k]).collect();
            // table cells near the object's bottom edge are allowed to stay (its contact line)
            let removed = table_cells.iter().filter(|&&k| x[k] >= 1.0).count();
            let kept = (0..f * f).filter(|&k| object[k] && x[k] < 1.0).count();
            let n_obj = object.iter().filter(|o| **o).count();
            assert!(
                removed as f64 > 0.9 * table_cells.len() as f64,
                "colour {with_color} noise {noise}: {removed} of {} table cells removed",
                table_cells.len()
            );
            assert!(
                kept as f64 > 0.8 * n_obj as f64,
                "colour {with_color} noise {noise}: {kept} of {n_obj} object cells kept"
            );
            if with_color {
                // the table's colour became background grey, the object's colour stayed
                let fc = layout.color_px();
                let c_table = f * f;
                assert_eq!(x[c_table], BACKGROUND_GREY * 0.7);
                let c_obj = f * f + (8 * fc + 8) * 3;
                assert!((x[c_obj] - 0.9 * 0.7).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn a_steep_table_is_found_by_the_steep_fit_only() {
        // 2 boxes of depth over the crop: most of the ring saturates near or far
        let (layout, x, mask, object) = table_crop(false, 0.02, 5, 2.0);
        let mut flat = x.clone();
        assert!(!suppress_support_plane(&layout, &mut flat, &mask, false));
        let mut steep = x.clone();
        assert!(suppress_support_plane_steep(&layout, &mut steep, &mask, false));
        let f = 32;
        let table_left = (0..f * f).filter(|&k| !object[k] && steep[k] < 1.0).count();
        let object_kept = (0..f * f).filter(|&k| object[k] && steep[k] < 1.0).count();
        assert!(table_left < 60, "{table_left} of about 900 table cells left");
        assert!(object_kept > 60, "{object_kept} object cells kept");
    }

    #[test]
    fn no_plane_in_free_space() {
        // the object in front of far background: the ring reads far, nothing is fitted
        let (layout, mut x, mask, object) = table_crop(false, 0.0, 1, 0.9);
        for (k, o) in object.iter().enumerate() {
            if !o {
                x[k] = 1.0;
            }
        }
        let before = x.clone();
        assert!(!suppress_support_plane(&layout, &mut x, &mask, false));
        assert_eq!(x, before);
    }

    #[test]
    fn ridge_encoder_denoises_where_pca_of_the_noisy_input_does_not() {
        // signals on a 3-d subspace of a 40-d space, observed with strong noise on half the
        // coordinates and with missing values
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (n, d, k) = (3000, 40, 3);
        let basis: Vec<Vec<f32>> = (0..k)
            .map(|_| (0..d).map(|_| rng.random::<f32>() - 0.5).collect())
            .collect();
        let noise = Normal::new(0.0f32, 0.6).unwrap();
        let mut clean = vec![0f32; n * d];
        let mut noisy = vec![0f32; n * d];
        let mut mask = vec![false; n * d];
        for i in 0..n {
            let c: Vec<f32> = (0..k).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect();
            for j in 0..d {
                let v: f32 = (0..k).map(|q| c[q] * basis[q][j]).sum::<f32>() + 0.5;
                clean[i * d + j] = v;
                noisy[i * d + j] = if j % 2 == 0 { v + noise.sample(&mut rng) } else { v };
                mask[i * d + j] = rng.random::<f32>() < 0.1;
            }
        }
        let enc = LinearDenoisingEncoder::fit(&clean, &noisy, &mask, n, d, k, 1e-3, 0.0, 1).unwrap();
        let mut zc = vec![0f32; n * k];
        let mut zn = vec![0f32; n * k];
        enc.pca_codes(&clean, n, &mut zc);
        enc.encode_observations(&noisy, &mask, n, &mut zn);
        normalise_rows(&mut zc, k);
        normalise_rows(&mut zn, k);
        let cos: f32 = (0..n)
            .map(|i| (0..k).map(|q| zc[i * k + q] * zn[i * k + q]).sum::<f32>())
            .sum::<f32>()
            / n as f32;
        // plain PCA projection of the noisy input, for comparison
        let mut zp = vec![0f32; n * k];
        let imputed: Vec<f32> = noisy
            .iter()
            .zip(&mask)
            .enumerate()
            .map(|(i, (&v, &m))| if m { enc.mean_clean[i % d] } else { v })
            .collect();
        enc.pca_codes(&imputed, n, &mut zp);
        normalise_rows(&mut zp, k);
        let cos_pca: f32 = (0..n)
            .map(|i| (0..k).map(|q| zc[i * k + q] * zp[i * k + q]).sum::<f32>())
            .sum::<f32>()
            / n as f32;
        assert!(cos > 0.9, "ridge codes agree with clean codes: {cos}");
        assert!(cos > cos_pca + 0.03, "ridge {cos} vs pca {cos_pca}");
    }

    #[test]
    fn whitened_codes_tell_apart_templates_that_differ_only_in_detail() {
        // templates = a large shared "silhouette" component (varying strength) plus a small
        // "detail" component of either sign (a flipped bottle: same outline, other label)
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let (n, d, k) = (2000, 30, 4);
        let basis: Vec<Vec<f32>> = (0..k)
            .map(|_| (0..d).map(|_| rng.random::<f32>() - 0.5).collect())
            .collect();
        let scales = [3.0f32, 2.0, 1.0, 0.15];
        let template = |c: &[f32]| -> Vec<f32> {
            (0..d)
                .map(|j| (0..k).map(|q| scales[q] * c[q] * basis[q][j]).sum::<f32>())
                .collect()
        };
        let clean: Vec<f32> = (0..n)
            .flat_map(|_| {
                let c: Vec<f32> = (0..k).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect();
                template(&c)
            })
            .collect();
        let mask = vec![false; n * d];
        // a template and its "flip": the detail component negated
        let pair: Vec<f32> = [template(&[0.6, -0.4, 0.3, 0.8]), template(&[0.6, -0.4, 0.3, -0.8])].concat();
        let cos_of = |whiten: f64| -> f32 {
            let enc = LinearDenoisingEncoder::fit(&clean, &clean, &mask, n, d, k, 1e-3, whiten, 1).unwrap();
            let mut z = vec![0f32; 2 * k];
            enc.encode_templates(&pair, 2, &mut z);
            normalise_rows(&mut z, k);
            (0..k).map(|q| z[q] * z[k + q]).sum()
        };
        let (plain, half, full) = (cos_of(0.0), cos_of(0.5), cos_of(1.0));
        assert!(plain > 0.95, "plain PCA codes barely see the detail: {plain}");
        assert!(
            half < plain - 0.05 && full < half,
            "whitening 0 / 0.5 / 1: {plain} / {half} / {full}"
        );
    }

    fn dot(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }

    fn cosine(a: &[f32], b: &[f32]) -> f32 {
        dot(a, b) / (dot(a, a).sqrt() * dot(b, b).sqrt())
    }

    #[test]
    fn split_codes_compare_as_the_weighted_mean_of_their_blocks_cosines() {
        // depth: inputs 0..3 -> components 0..2; colour: inputs 3..5 -> components 2..5
        let blocks = [
            CodeBlock {
                input_start: 0,
                input_len: 3,
                code_start: 0,
                code_len: 2,
                weight: 0.75,
            },
            CodeBlock {
                input_start: 3,
                input_len: 2,
                code_start: 2,
                code_len: 3,
                weight: 0.25,
            },
        ];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let raw: Vec<f32> = (0..10).map(|_| rng.random::<f32>() - 0.5).collect();
        let (obs, tmpl) = (&raw[..5], &raw[5..]);
        let expected = 0.75 * cosine(&obs[..2], &tmpl[..2]) + 0.25 * cosine(&obs[2..], &tmpl[2..]);
        let mut t = tmpl.to_vec();
        finish_codes(&blocks, None, 5, &mut t, 5);
        assert!((dot(&t, &t) - 1.0).abs() < 1e-5, "templates are unit rows");
        let mut o = obs.to_vec();
        finish_codes(&blocks, None, 5, &mut o, 5);
        assert!((dot(&o, &t) - expected).abs() < 1e-5, "{} vs {expected}", dot(&o, &t));
        // a colour code 100 times longer (a real crop's colours far from the mesh's) weighs
        // no more: the similarity is unchanged
        let mut loud = obs.to_vec();
        loud[2..].iter_mut().for_each(|v| *v *= 100.0);
        finish_codes(&blocks, None, 5, &mut loud, 5);
        assert!((dot(&loud, &t) - expected).abs() < 1e-4);
        // a camera without colour (its colour inputs all missing): the depth cosine alone
        let mask = [false, true, false, true, true];
        let mut depth_only = obs.to_vec();
        finish_codes(&blocks, Some(&mask), 5, &mut depth_only, 5);
        assert!(depth_only[2..].iter().all(|v| *v == 0.0));
        let cos_depth = cosine(&obs[..2], &tmpl[..2]);
        assert!((dot(&depth_only, &t) - cos_depth).abs() < 1e-5);
    }

    #[test]
    fn a_split_encoders_depth_code_does_not_read_the_colour() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (n, d) = (500, 12);
        let clean: Vec<f32> = (0..n * d).map(|_| rng.random::<f32>()).collect();
        let noisy: Vec<f32> = clean.iter().map(|v| v + 0.1 * (rng.random::<f32>() - 0.5)).collect();
        let mask = vec![false; n * d];
        let parts = [(0, 8, 4, 0.7), (8, 4, 2, 0.3)];
        let enc = LinearDenoisingEncoder::fit_blocks(&clean, &noisy, &mask, n, d, &parts, 1e-3, 0.5, 1).unwrap();
        assert_eq!(enc.code_dim, 6);
        assert_eq!(enc.blocks.len(), 2);
        let x = clean[..d].to_vec();
        let mut y = x.clone();
        y[8..].iter_mut().for_each(|v| *v = 1.0 - *v);
        let (mut cx, mut cy) = (vec![0f32; 6], vec![0f32; 6]);
        enc.encode_observations(&x, &mask[..d], 1, &mut cx);
        enc.encode_observations(&y, &mask[..d], 1, &mut cy);
        for c in 0..4 {
            assert!(
                (cx[c] - cy[c]).abs() < 1e-6,
                "depth component {c}: {} vs {}",
                cx[c],
                cy[c]
            );
        }
        assert!(
            (0..2).any(|c| (cx[4 + c] - cy[4 + c]).abs() > 1e-3),
            "the colour code reads the colour"
        );
        // bad blocks are refused
        assert!(
            LinearDenoisingEncoder::fit_blocks(&clean, &noisy, &mask, n, d, &[(8, 8, 4, 1.0)], 1e-3, 0.5, 1).is_err()
        );
        assert!(
            LinearDenoisingEncoder::fit_blocks(&clean, &noisy, &mask, n, d, &[(0, 8, 4, 0.0)], 1e-3, 0.5, 1).is_err()
        );
    }

    #[test]
    fn the_streamed_fit_reads_pairs_made_on_demand_as_if_held() {
        // 2,500 pairs: two full chunks and a partial one; rows made from their index
        let (n, d) = (2500, 20);
        let row = |r: usize| -> (Vec<f32>, Vec<f32>, Vec<bool>) {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(r as u64);
            let clean: Vec<f32> = (0..d)
                .map(|j| ((r * (j + 1)) % 7) as f32 * 0.1 + rng.random::<f32>() * 0.2)
                .collect();
            let noisy: Vec<f32> = clean.iter().map(|v| v + 0.1 * (rng.random::<f32>() - 0.5)).collect();
            let mask: Vec<bool> = (0..d).map(|_| rng.random::<f32>() < 0.1).collect();
            (clean, noisy, mask)
        };
        let (mut clean, mut noisy, mut mask) = (Vec::new(), Vec::new(), Vec::new());
        for r in 0..n {
            let (c, x, m) = row(r);
            clean.extend(c);
            noisy.extend(x);
            mask.extend(m);
        }
        let held = LinearDenoisingEncoder::fit(&clean, &noisy, &mask, n, d, 6, 1e-3, 0.5, 3).unwrap();
        let made = FnTraining {
            n,
            d,
            clean: |rows: Range<usize>| rows.flat_map(|r| row(r).0).collect(),
            pairs: |rows: Range<usize>| {
                let (mut c, mut x, mut m) = (Vec::new(), Vec::new(), Vec::new());
                for r in rows {
                    let (a, b, k) = row(r);
                    c.extend(a);
                    x.extend(b);
                    m.extend(k);
                }
                (c, x, m)
            },
        };
        let streamed =
            LinearDenoisingEncoder::fit_streamed(&made, CodeLayout::One { code_dim: 6 }, 1e-3, 0.5, 3).unwrap();
        assert_eq!(held.pca_t, streamed.pca_t);
        assert_eq!(held.ridge_t, streamed.ridge_t);
        // the observed mean is the mean of the imputed corrupted rows
        for j in 0..d {
            let m: f64 = (0..n)
                .map(|r| if mask[r * d + j] { held.mean_clean[j] } else { noisy[r * d + j] } as f64)
                .sum::<f64>()
                / n as f64;
            assert!((held.mean_observed[j] as f64 - m).abs() < 1e-5, "column {j}");
        }
    }
}
