//! Crop features: a crop sampled around the (projected) object centre, and the preparation of
//! an observed crop before it is encoded.
//!
//! A crop is a square around the object centre, sampled on a `F x F` grid (`F = feature_px`)
//! with 2 x 2 nearest-neighbour sub-samples per cell ([`sample_crop`]):
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
//! is gated by them, so that the object/background split (and with it the colour) is not
//! random in far views.
//!
//! A support plane (table, floor) around the object is removed from observed crops before
//! encoding ([`suppress_support_plane`]): at the object's depth it would otherwise read as
//! object shape and colour, and a linear encoder does not learn to ignore it.
//!
//! Masked values are replaced by the mean of the clean templates before encoding (the
//! least-informative value for a linear encoder). Measured history: `docs/decisions.md`,
//! "Tracker: decisions moved from the code".

use crate::camera::{ColorImage, DepthImage, pixel_index};
use serde::{Deserialize, Serialize};

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
///
/// A sample's source pixel is `T_0(Rz(-theta) q)` for its offset `q` from the centre; the
/// products of each axis' offsets are computed once per crop (`SampleAxes`), and without a
/// rotation the pixel index is separable (one column per `x` offset, one row per `y` offset):
/// the same arithmetic as per sample, so the same pixels.
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
    let axes = SampleAxes::new(p, f, s, c, w, h);
    let mut valid = 0usize;
    for i in 0..f {
        for j in 0..f {
            let mut sum = 0.0f32;
            let mut n = 0;
            for si in 0..SUBSAMPLES {
                for sj in 0..SUBSAMPLES {
                    let v = match axes.src(i * SUBSAMPLES + si, j * SUBSAMPLES + sj) {
                        Some(k) => norm(depth.data_m[k]),
                        None => p.zero_is_far.then_some(1.0),
                    };
                    if let Some(v) = v {
                        sum += v;
                        n += 1;
                    }
                }
            }
            valid += usize::from(write_cell(out, mask, i * f + j, sum, n, 1.0));
        }
    }
    denoise_depth(layout, &mut out[..f * f], &mask[..f * f]);
    if layout.use_color {
        let fc = layout.color_px();
        let axes = SampleAxes::new(p, fc, s, c, w, h);
        // the depth cell under each colour sample, per axis
        let under: Vec<usize> = (0..fc * SUBSAMPLES)
            .map(|q| (q / SUBSAMPLES * f / fc + q % SUBSAMPLES * f / (fc * SUBSAMPLES)).min(f - 1))
            .collect();
        let base = layout.depth_len();
        for i in 0..fc {
            for j in 0..fc {
                let mut sum = [0.0f32; 3];
                let mut n = 0;
                for si in 0..SUBSAMPLES {
                    for sj in 0..SUBSAMPLES {
                        let (qi, qj) = (i * SUBSAMPLES + si, j * SUBSAMPLES + sj);
                        // object or background: the (denoised) depth cell under this sample,
                        // not the raw pixel (far cameras' per-pixel noise would flip it)
                        let dk = under[qi] * f + under[qj];
                        let d = (!mask[dk]).then(|| out[dk]);
                        if let Some(rgb) = sample_colour(d, axes.src(qi, qj), color) {
                            for ch in 0..3 {
                                sum[ch] += rgb[ch];
                            }
                            n += 1;
                        }
                    }
                }
                write_colour_cell(out, mask, base + (i * fc + j) * 3, sum, n, layout.color_weight);
            }
        }
    }
    valid as f64 / (f * f) as f64
}

/// One colour sample: the pixel's colour where the (normalised) depth cell under it `d` is the
/// object (below 1), the background grey where it is not or the pixel is outside the image;
/// `None` where the depth cell has no reading or there is no colour image.
#[inline(always)]
fn sample_colour(d: Option<f32>, pixel: Option<usize>, color: Option<&ColorImage>) -> Option<[f32; 3]> {
    let d = d?;
    let img = color?;
    Some(match pixel {
        Some(k) if d < 1.0 => {
            let c = img.data[k];
            [c[0] as f32 / 255.0, c[1] as f32 / 255.0, c[2] as f32 / 255.0]
        }
        _ => [BACKGROUND_GREY; 3],
    })
}

/// Writes a colour cell (three channels from `k0`): the mean of its `n` samples' `sum` times
/// `weight`, or a masked zero without samples.
#[inline(always)]
fn write_colour_cell(out: &mut [f32], mask: &mut [bool], k0: usize, sum: [f32; 3], n: usize, weight: f32) {
    for (ch, sc) in sum.iter().enumerate() {
        write_cell(out, mask, k0 + ch, *sc, n, weight);
    }
}

/// Writes cell `k`: the mean `sum / n` of its samples times `scale`, or a masked zero without
/// samples; whether it holds a value.
#[inline(always)]
fn write_cell(out: &mut [f32], mask: &mut [bool], k: usize, sum: f32, n: usize, scale: f32) -> bool {
    mask[k] = n == 0;
    out[k] = if n > 0 { sum / n as f32 * scale } else { 0.0 };
    n > 0
}

/// A pixel column (or row) per sample, `None` outside the image.
type PixelIndices = Vec<Option<i64>>;

/// The source pixels of a crop's `n x n` cells with their sub-samples, per axis: sample
/// `q = cell * SUBSAMPLES + sub` lies at the offset
/// `(cell + (sub + 0.5) / SUBSAMPLES) * side / n - side / 2` along each axis, and sample
/// `(qi, qj)` reads pixel `(cx + c ox[qj] + s oy[qi], cy - s ox[qj] + c oy[qi])` (`c, s` the
/// rotation's cosine and sine), summed in that order so that every sample reads the pixel it
/// read when each was computed on its own.
struct SampleAxes {
    /// Per `x` sample: `cx + c ox`, `cy - s ox`.
    col: Vec<(f64, f64)>,
    /// Per `y` sample: `s oy`, `c oy`.
    row: Vec<(f64, f64)>,
    /// Without a rotation (`s = 0`, `c = 1`): the pixel column per `x` sample and the row per
    /// `y` sample (`None`: outside the image); the rotation's terms are then zeros, which change
    /// no sum.
    separable: Option<(PixelIndices, PixelIndices)>,
    w: i64,
    h: i64,
}

impl SampleAxes {
    fn new(p: &CropParams, n: usize, s: f64, c: f64, w: i64, h: i64) -> Self {
        let cell = p.side_px / n as f64;
        let offsets: Vec<f64> = (0..n * SUBSAMPLES)
            .map(|q| {
                let (a, b) = (q / SUBSAMPLES, q % SUBSAMPLES);
                (a as f64 + (b as f64 + 0.5) / SUBSAMPLES as f64) * cell - p.side_px / 2.0
            })
            .collect();
        let col: Vec<(f64, f64)> = offsets
            .iter()
            .map(|o| (p.centre_px[0] + c * o, p.centre_px[1] - s * o))
            .collect();
        let row: Vec<(f64, f64)> = offsets.iter().map(|o| (s * o, c * o)).collect();
        let separable = (s == 0.0 && c == 1.0).then(|| {
            let inside = |v: f64, lim: i64| Some(pixel_index(v)).filter(|i| *i >= 0 && *i < lim);
            (
                col.iter().map(|(x, _)| inside(*x, w)).collect(),
                offsets.iter().map(|o| inside(p.centre_px[1] + o, h)).collect(),
            )
        });
        Self {
            col,
            row,
            separable,
            w,
            h,
        }
    }

    /// The flat index of the pixel under sample `(qi, qj)`, `None` outside the image.
    #[inline]
    fn src(&self, qi: usize, qj: usize) -> Option<usize> {
        let (xi, yi) = match &self.separable {
            Some((cols, rows)) => (cols[qj]?, rows[qi]?),
            None => (
                pixel_index(self.col[qj].0 + self.row[qi].0),
                pixel_index(self.col[qj].1 + self.row[qi].1),
            ),
        };
        (xi >= 0 && yi >= 0 && xi < self.w && yi < self.h).then(|| (yi * self.w + xi) as usize)
    }
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
/// changes with the light; the hue pattern that tells a box from its flip (the print)
/// survives any light. A per-channel gain (exposure, white balance) does not replace it: the
/// mismatch is the shading, not the mean colour.
///
/// Only the object's colour cells change (those over a depth cell that is object or nearer,
/// normalised depth < 1; a crop with fewer than three is left alone); grey would map to itself
/// anyway, masked cells stay masked. Applied to templates, training crops and observed crops
/// alike, after the support plane is removed. The measurements behind this:
/// `docs/decisions.md` ("Tracker: decisions moved from the code").
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
    let mut d = second_differences(layout, x, mask)?;
    let m = d.len() / 2;
    d.select_nth_unstable_by(m, f32::total_cmp);
    Some(d[m] / noise_per_median())
}

/// The median absolute second difference per Gaussian sigma: `a - 2b + c` of three
/// `N(0, s^2)` has sigma `sqrt(6) s`, and its median `|.|` is `0.6745 sqrt(6) s`.
fn noise_per_median() -> f32 {
    0.6745 * 6f32.sqrt()
}

/// The absolute second differences behind [`depth_noise_sigma`], `None` with fewer than 16.
fn second_differences(layout: &FeatureLayout, x: &[f32], mask: &[bool]) -> Option<Vec<f32>> {
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
    (d.len() >= 16).then_some(d)
}

/// The median filter's radius for a grid (see [`denoise_depth`]): `None` where
/// [`depth_noise_sigma`] is at most `DENOISE_MIN_SIGMA` (or unknown), 1 up to 0.5, else 2.
/// The median exceeds a threshold exactly when at most half of the differences (`m` of them,
/// `m` the median's rank) do not, so two counts answer without the selection.
fn denoise_radius(layout: &FeatureLayout, x: &[f32], mask: &[bool]) -> Option<i64> {
    let d = second_differences(layout, x, mask)?;
    let m = d.len() / 2;
    let k = noise_per_median();
    let exceeds = |t: f32| {
        let not_above = d
            .iter()
            .filter(|v| (**v / k).partial_cmp(&t) != Some(std::cmp::Ordering::Greater));
        not_above.count() <= m
    };
    exceeds(DENOISE_MIN_SIGMA).then(|| if exceeds(0.5) { 2 } else { 1 })
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
    if let Some(r) = denoise_radius(layout, x, mask) {
        let src = x[..f * f].to_vec();
        median_filter(&src, mask, f, r as usize, x);
    }
    for v in x[..f * f].iter_mut() {
        *v = v.clamp(0.0, 1.0);
    }
}

/// The median of the valid cells in each valid cell's `(2r + 1)^2` window (the upper one of an
/// even count, in `f32::total_cmp`'s order), written to `out`: a row at a time, every cell of
/// the row a lane of one sorting network over its window, on the integer keys of that order,
/// masked and outside cells entering as the largest key, so that a lane's median sits at half
/// its count of valid cells.
fn median_filter(src: &[f32], mask: &[bool], f: usize, r: usize, out: &mut [f32]) {
    // f32::total_cmp's key: an involution of the bits
    let key = |b: i32| b ^ ((((b >> 31) as u32) >> 1) as i32);
    let side = 2 * r + 1;
    let net = batcher_network((side * side).next_power_of_two());
    let mut v = vec![i32::MAX; net.width * f];
    let mut count = vec![0usize; f];
    for i in 0..f {
        v.fill(i32::MAX);
        count.fill(0);
        for (t, (a, b)) in (0..side).flat_map(|a| (0..side).map(move |b| (a, b))).enumerate() {
            // the window's cell (i + a - r, j + b - r) of every lane j
            let Some(row) = (i + a).checked_sub(r).filter(|row| *row < f) else {
                continue;
            };
            let lane = &mut v[t * f..(t + 1) * f];
            for j in r.saturating_sub(b)..(f + r).saturating_sub(b).min(f) {
                let k = row * f + j + b - r;
                if !mask[k] {
                    lane[j] = key(src[k].to_bits() as i32);
                    count[j] += 1;
                }
            }
        }
        sort_lanes(&net.pairs, &mut v, f);
        for j in 0..f {
            let k = i * f + j;
            if !mask[k] {
                out[k] = f32::from_bits(key(v[(count[j] / 2) * f + j]) as u32);
            }
        }
    }
}

/// Runs the network `pairs` on `v`, `f` lanes per input (input `t` at `v[t * f..(t + 1) * f]`),
/// compiled for the widest integer min and max the CPU has (the same result on each).
fn sort_lanes(pairs: &[(u16, u16)], v: &mut [i32], f: usize) {
    crate::tracker::bins::with_wide_simd(
        #[inline(always)]
        || sort_lanes_generic(pairs, v, f),
    );
}

#[inline(always)]
fn sort_lanes_generic(pairs: &[(u16, u16)], v: &mut [i32], f: usize) {
    for &(p, q) in pairs {
        let (lo, hi) = v.split_at_mut(q as usize * f);
        let a = &mut lo[p as usize * f..(p as usize + 1) * f];
        let b = &mut hi[..f];
        for (x, y) in a.iter_mut().zip(b.iter_mut()) {
            let (s, t) = (*x, *y);
            *x = s.min(t);
            *y = s.max(t);
        }
    }
}

/// A sorting network (Batcher's odd-even merge sort) of `width` inputs, a power of two:
/// compare-exchanges `(p, q)`, `p < q`, in order.
struct SortingNetwork {
    width: usize,
    pairs: Vec<(u16, u16)>,
}

/// The network of `width` inputs, built once per width.
fn batcher_network(width: usize) -> &'static SortingNetwork {
    static NETWORKS: std::sync::OnceLock<Vec<SortingNetwork>> = std::sync::OnceLock::new();
    let nets = NETWORKS.get_or_init(|| (0..=6).map(|e| build_batcher(1 << e)).collect());
    &nets[width.trailing_zeros() as usize]
}

fn build_batcher(n: usize) -> SortingNetwork {
    let mut pairs = Vec::new();
    let mut p = 1;
    while p < n {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < n {
                for i in 0..k.min(n - j - k) {
                    if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                        pairs.push(((i + j) as u16, (i + j + k) as u16));
                    }
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    SortingNetwork { width: n, pairs }
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
/// shape to the linear encoder.
///
/// - Fit: least median of squares over deterministic triples of ring cells, refined by least
///   squares on the inliers (`|r| < 2.5 sigma`, sigma from the median residual). Needs at least
///   40 % of the ring to be in-range depth and to agree with the plane, else nothing is done
///   (no plane around the object: free space behind it reads far already; a table so steep
///   that it saturates most of the ring is left to the encoder, which is trained on such crops
///   and did better than a fit of those too: `docs/decisions.md`, "Tracker: decisions moved
///   from the code").
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
/// encoder's input, it answers whether anything stands on the table at all:
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
    // a cell's centre along one axis, in [-0.5, 0.5]; `coord` gives (u, v) of cell `k`
    let cell_centre = |c: usize| (c as f32 + 0.5) / f as f32 - 0.5;
    let coord = |k: usize| -> (f32, f32) { (cell_centre(k % f), cell_centre(k / f)) };
    // the cells within `w` of the border, ascending
    let mut ring: Vec<usize> = Vec::with_capacity(4 * w * f);
    for i in 0..f {
        if i < w || i >= f - w {
            ring.extend(i * f..(i + 1) * f);
        } else {
            ring.extend(i * f..i * f + w);
            ring.extend((i + 1) * f - w..(i + 1) * f);
        }
    }
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
    let best = least_median_plane(&pts, scored, steep);
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
    let mut resid: Vec<Option<f32>> = Vec::with_capacity(f * f);
    for i in 0..f {
        let v = cell_centre(i);
        for j in 0..f {
            let k = i * f + j;
            resid.push((!mask[k]).then(|| {
                let u = cell_centre(j);
                x[k] - (pl[0] + pl[1] * u + pl[2] * v).clamp(0.0, 1.0)
            }));
        }
    }
    let mut remove = vec![false; f * f];
    for k in 0..f * f {
        if mask[k] || x[k] >= 1.0 {
            continue;
        }
        let (i, j) = (k / f, k % f);
        let (mut sum, mut n) = (0.0f32, 0usize);
        for a in i.saturating_sub(1)..(i + 2).min(f) {
            for b in j.saturating_sub(1)..(j + 2).min(f) {
                if let Some(r) = resid[a * f + b] {
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

/// The least-median-of-squares plane of a crop's ring: of the planes through 48 deterministic
/// triples of `pts` (in-range ring cells), the first with the lowest median absolute residual
/// over `scored` (against the clamped prediction when `steep`), with that median. A candidate
/// is rejected by counting the residuals below the best median so far (its median is lower only
/// if more than half of them are), so most candidates need no selection; the answer is the same
/// as with one.
fn least_median_plane(
    pts: &[(f32, f32, f32, usize)],
    scored: &[(f32, f32, f32, usize)],
    steep: bool,
) -> Option<([f32; 3], f32)> {
    let m = pts.len();
    // one array per coordinate, so that the residuals of a candidate vectorise
    let su: Vec<f32> = scored.iter().map(|p| p.0).collect();
    let sv: Vec<f32> = scored.iter().map(|p| p.1).collect();
    let sz: Vec<f32> = scored.iter().map(|p| p.2).collect();
    let residuals = |pl: [f32; 3], out: &mut Vec<f32>| {
        out.resize(scored.len(), 0.0);
        for (((r, u), v), z) in out.iter_mut().zip(&su).zip(&sv).zip(&sz) {
            let p = pl[0] + pl[1] * u + pl[2] * v;
            *r = (z - if steep { p.clamp(0.0, 1.0) } else { p }).abs();
        }
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
        if let Some((_, bm)) = best
            && buf.iter().filter(|r| **r < bm).count() <= mid
        {
            continue;
        }
        buf.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
        let med = buf[mid];
        if best.is_none_or(|(_, bm)| med < bm) {
            best = Some((pl, med));
        }
    }
    best
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

#[cfg(test)]
/// The per-sample `sample_crop` as it was before its axes were tabulated: the reference
/// that the tabulated one must match bit for bit.
pub(crate) fn sample_crop_reference(
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
            valid += usize::from(write_cell(out, mask, i * f + j, sum, n, 1.0));
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
                        if let Some(rgb) = sample_colour(d, k, color) {
                            for ch in 0..3 {
                                sum[ch] += rgb[ch];
                            }
                            n += 1;
                        }
                    }
                }
                write_colour_cell(out, mask, base + (i * fc + j) * 3, sum, n, layout.color_weight);
            }
        }
    }
    valid as f64 / (f * f) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
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

    /// The candidate loop of the plane fit as it was (one residual array of tuples, a selection
    /// per candidate): the reference of [`least_median_plane`].
    fn least_median_plane_reference(
        pts: &[(f32, f32, f32, usize)],
        scored: &[(f32, f32, f32, usize)],
        steep: bool,
    ) -> Option<([f32; 3], f32)> {
        let m = pts.len();
        let mut best: Option<([f32; 3], f32)> = None;
        for t in 0..48usize {
            let a = (t * 7919) % m;
            let b = (a + m / 3 + t * 13) % m;
            let c = (a + 2 * m / 3 + t * 29) % m;
            let Some(pl) = plane_through(&pts[a], &pts[b], &pts[c]) else {
                continue;
            };
            let mut buf: Vec<f32> = scored
                .iter()
                .map(|(u, v, z, _)| {
                    let p = pl[0] + pl[1] * u + pl[2] * v;
                    (z - if steep { p.clamp(0.0, 1.0) } else { p }).abs()
                })
                .collect();
            let mid = buf.len() / 2;
            buf.select_nth_unstable_by(mid, |p, q| p.total_cmp(q));
            let med = buf[mid];
            if best.is_none_or(|(_, bm)| med < bm) {
                best = Some((pl, med));
            }
        }
        best
    }

    #[test]
    fn pruned_least_median_plane_is_the_plain_one() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        for trial in 0..500 {
            let n = rng.random_range(8..300);
            let (a, b, c) = (
                rng.random_range(-0.5f32..1.5),
                rng.random_range(-2.0f32..2.0),
                rng.random_range(-2.0f32..2.0),
            );
            let outliers = rng.random_range(0.0..0.7);
            let noise = [0.0f32, 0.01, 0.2][trial % 3];
            let all: Vec<(f32, f32, f32, usize)> = (0..n)
                .map(|k| {
                    let (u, v) = (rng.random_range(-0.5f32..0.5), rng.random_range(-0.5f32..0.5));
                    let z = if rng.random_bool(outliers) {
                        rng.random_range(-1.0f32..2.0)
                    } else {
                        a + b * u + c * v + noise * rng.random_range(-1.0f32..1.0)
                    };
                    // quantised depths make ties between candidates' medians
                    let z = if trial % 4 == 0 { (z * 8.0).round() / 8.0 } else { z };
                    (u, v, z, k)
                })
                .collect();
            let pts: Vec<(f32, f32, f32, usize)> = all.iter().filter(|p| p.2 > 0.0 && p.2 < 1.0).copied().collect();
            if pts.len() < 3 {
                continue;
            }
            for steep in [false, true] {
                let scored = if steep { &all } else { &pts };
                let bits = |r: Option<([f32; 3], f32)>| r.map(|(p, m)| (p.map(f32::to_bits), m.to_bits()));
                assert_eq!(
                    bits(least_median_plane(&pts, scored, steep)),
                    bits(least_median_plane_reference(&pts, scored, steep)),
                    "trial {trial}, steep {steep}"
                );
            }
        }
    }

    #[test]
    fn denoise_radius_is_what_the_noise_estimate_says() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(33);
        let mut radii = [0usize; 3];
        for trial in 0..600 {
            let layout = FeatureLayout {
                feature_px: [32, 8, 4][trial % 3],
                use_color: false,
                color_weight: 1.0,
                chromaticity: false,
            };
            let sigma = rng.random_range(0.0f32..0.8);
            let (_, _, x) = block_cells(sigma, trial as u64);
            let f = layout.feature_px;
            // a sub-grid, quantised so that medians sit on the thresholds too, some cells masked
            let x: Vec<f32> = (0..f * f)
                .map(|k| {
                    let v = x[(k / f) * 32 + k % f];
                    if trial % 5 == 0 { (v * 16.0).round() / 16.0 } else { v }
                })
                .collect();
            let mask: Vec<bool> = (0..f * f).map(|_| rng.random_bool(0.1)).collect();
            let sigma = depth_noise_sigma(&layout, &x, &mask).unwrap_or(0.0);
            let want = (sigma > DENOISE_MIN_SIGMA).then_some(if sigma > 0.5 { 2 } else { 1 });
            let got = denoise_radius(&layout, &x, &mask);
            assert_eq!(got, want, "trial {trial}: sigma {sigma}");
            radii[got.unwrap_or(0) as usize] += 1;
        }
        assert!(radii.iter().all(|n| *n > 20), "{radii:?}");
    }

    #[test]
    fn tabulated_axes_sample_what_the_per_sample_maths_did() {
        use rand::Rng;
        let (w, h) = (97u32, 71u32);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let depth = DepthImage {
            width: w,
            height: h,
            data_m: (0..w * h)
                .map(|_| {
                    if rng.random_bool(0.1) {
                        0.0
                    } else {
                        rng.random_range(0.5f32..2.0)
                    }
                })
                .collect(),
        };
        let color = ColorImage {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|_| [rng.random::<u8>(), rng.random::<u8>(), rng.random::<u8>()])
                .collect(),
        };
        for trial in 0..400 {
            let layout = FeatureLayout {
                feature_px: [32, 16, 8][trial % 3],
                use_color: trial % 5 != 0,
                color_weight: 0.7,
                chromaticity: false,
            };
            let rotation_rad = match trial % 4 {
                0 | 1 => 0.0,
                2 => -0.0,
                _ => rng.random_range(-3.2..3.2),
            };
            let p = CropParams {
                centre_px: [rng.random_range(-20.0..117.0), rng.random_range(-20.0..91.0)],
                side_px: rng.random_range(3.0..120.0),
                rotation_rad,
                z_centre_m: rng.random_range(0.5..2.0),
                box_m: rng.random_range(0.05..0.4),
                zero_is_far: trial % 7 == 0,
            };
            let img = (trial % 6 != 1).then_some(&color);
            let (mut x0, mut m0) = (vec![0f32; layout.dim()], vec![false; layout.dim()]);
            let (mut x1, mut m1) = (vec![0f32; layout.dim()], vec![false; layout.dim()]);
            let s0 = sample_crop_reference(&layout, &depth, img, &p, &mut x0, &mut m0);
            let s1 = sample_crop(&layout, &depth, img, &p, &mut x1, &mut m1);
            assert_eq!(s0.to_bits(), s1.to_bits(), "trial {trial}");
            assert_eq!(m0, m1, "trial {trial}");
            let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<u32>>();
            assert_eq!(bits(&x0), bits(&x1), "trial {trial}: {p:?}");
        }
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

    /// The median filter as it was written first: a selection per cell.
    fn median_filter_reference(src: &[f32], mask: &[bool], f: usize, r: i64, out: &mut [f32]) {
        let mut win: Vec<f32> = Vec::new();
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
                out[k] = win[m];
            }
        }
    }

    #[test]
    fn batcher_networks_sort() {
        use rand::Rng;
        // every binary input of 16 (the 0-1 principle) and random inputs of 32 and 64
        let net = build_batcher(16);
        for bits in 0u32..1 << 16 {
            let mut v: Vec<u8> = (0..16).map(|b| ((bits >> b) & 1) as u8).collect();
            for &(p, q) in &net.pairs {
                if v[q as usize] < v[p as usize] {
                    v.swap(p as usize, q as usize);
                }
            }
            assert!(v.windows(2).all(|w| w[0] <= w[1]), "{bits:b}");
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        for n in [1usize, 2, 4, 8, 32, 64] {
            let net = build_batcher(n);
            for _ in 0..2000 {
                let mut v: Vec<i32> = (0..n).map(|_| rng.random_range(0..20)).collect();
                for &(p, q) in &net.pairs {
                    if v[q as usize] < v[p as usize] {
                        v.swap(p as usize, q as usize);
                    }
                }
                assert!(v.windows(2).all(|w| w[0] <= w[1]), "n {n}");
            }
        }
    }

    #[test]
    fn sorting_lanes_is_the_same_on_every_instruction_set() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for (width, f) in [(16usize, 32usize), (32, 32), (32, 7), (16, 1)] {
            let net = build_batcher(width);
            let v: Vec<i32> = (0..width * f).map(|_| rng.random_range(-50..50)).collect();
            let (mut a, mut b) = (v.clone(), v);
            sort_lanes(&net.pairs, &mut a, f);
            sort_lanes_generic(&net.pairs, &mut b, f);
            assert_eq!(a, b);
            for j in 0..f {
                assert!((1..width).all(|t| a[(t - 1) * f + j] <= a[t * f + j]));
            }
        }
    }

    #[test]
    fn median_filter_is_the_selection_per_cell() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
        for trial in 0..400 {
            let f = [32usize, 8, 4, 3, 1][trial % 5];
            let r = 1 + trial % 2;
            let holes = [0.0, 0.1, 0.5, 0.95][trial % 4];
            let src: Vec<f32> = (0..f * f)
                .map(|_| {
                    let v = rng.random_range(-3.0f32..4.0);
                    // quantised so that windows hold ties
                    if trial % 3 == 0 { (v * 4.0).round() / 4.0 } else { v }
                })
                .collect();
            let mask: Vec<bool> = (0..f * f).map(|_| rng.random_bool(holes)).collect();
            let mut want = vec![f32::NAN; f * f];
            let mut got = vec![f32::NAN; f * f];
            median_filter_reference(&src, &mask, f, r as i64, &mut want);
            median_filter(&src, &mask, f, r, &mut got);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "trial {trial}: f {f}, r {r}");
        }
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
}
