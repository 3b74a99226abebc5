//! Crop features and the default encoder.
//!
//! # Features
//! A crop is a square around the (projected) object centre, sampled on a `F x F` grid
//! (`F = feature_px`) with 2 x 2 nearest-neighbour sub-samples per cell:
//! - depth, normalised `clamp((d - z) / box + 0.5, 0, 1)` (`z` the depth of the object centre,
//!   `box` the object's diameter). A missing reading (0) is *masked*, never read as "near". In
//!   codebook renders, an empty pixel is background and reads as far (1).
//! - colour on a `F/2 x F/2` grid, RGB in [0, 1] times `color_weight`, where the depth says
//!   "object or nearer" (normalised < 1); far background reads as a neutral grey so that the
//!   clutter behind the object does not count. Masked where no depth sample is valid or the
//!   camera gives no colour.
//!
//! Masked values are replaced by the mean of the clean templates before encoding (the
//! least-informative value for a linear encoder).
//!
//! # The default encoder ([`LinearDenoisingEncoder`])
//! PCA of the clean templates gives the codes (128-d by default, centred by the template mean
//! so that cosine similarities are not all near 1). PCA of noisy copies would not denoise
//! (independent noise adds a constant to the covariance), so the observation side is a
//! *regression*: ridge regression from corrupted crops (noise, missing pixels, occluders,
//! clutter, shifted and rescaled crops, colour changes) to the clean templates' codes.

use crate::camera::{ColorImage, DepthImage};
use crate::tracker::TrackerError;
use nalgebra::{DMatrix, DMatrixView, DMatrixViewMut};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Version of the feature layout and of the default encoder (part of every codebook cache key).
pub const ENCODER_VERSION: u32 = 1;

/// Colour of far background in features (before `color_weight`).
const BACKGROUND_GREY: f32 = 0.5;
/// Sub-samples per feature cell side.
const SUBSAMPLES: usize = 2;

/// Layout of a feature vector.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FeatureLayout {
    pub feature_px: usize,
    pub use_color: bool,
    pub color_weight: f32,
}

impl FeatureLayout {
    pub fn depth_len(&self) -> usize {
        self.feature_px * self.feature_px
    }
    pub fn color_px(&self) -> usize {
        (self.feature_px / 2).max(1)
    }
    pub fn color_len(&self) -> usize {
        if self.use_color { self.color_px() * self.color_px() * 3 } else { 0 }
    }
    pub fn dim(&self) -> usize {
        self.depth_len() + self.color_len()
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
        let (xi, yi) = (x.floor() as i64, y.floor() as i64);
        if xi < 0 || yi < 0 || xi >= w || yi >= h {
            None
        } else {
            Some((yi * w + xi) as usize)
        }
    };
    let norm = |d: f32| -> Option<f32> {
        if d > 0.0 && d.is_finite() {
            Some((((d as f64 - p.z_centre_m) / p.box_m + 0.5).clamp(0.0, 1.0)) as f32)
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
                        let d = match k {
                            Some(k) => norm(depth.data_m[k]),
                            None => p.zero_is_far.then_some(1.0),
                        };
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
                for ch in 0..3 {
                    let k = base + (i * fc + j) * 3 + ch;
                    if n > 0 {
                        out[k] = sum[ch] / n as f32 * layout.color_weight;
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

/// An encoder from crop features to codes. Implementations must be usable from many threads.
pub trait Encoder: Send + Sync {
    fn input_dim(&self) -> usize;
    fn code_dim(&self) -> usize;
    /// Version string (part of the cache key).
    fn version(&self) -> String;
    /// Encodes `n` observed crops (`x` row-major `n x input_dim`, `mask` likewise: true =
    /// missing) into `out` (`n x code_dim`, not normalised).
    fn encode_observations(&self, x: &[f32], mask: &[bool], n: usize, out: &mut [f32]);
    /// Encodes `n` clean templates (no missing values) into codebook codes.
    fn encode_templates(&self, x: &[f32], n: usize, out: &mut [f32]) {
        let mask = vec![false; x.len()];
        self.encode_observations(x, &mask, n, out);
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
}

/// `A * A^T` of a column-major `d x n` matrix, split over threads by columns.
fn gram(a: &[f32], d: usize, n: usize) -> DMatrix<f64> {
    let threads = rayon::current_num_threads().max(1);
    let per = n.div_ceil(threads).max(1);
    let parts: Vec<DMatrix<f32>> = a
        .par_chunks(per * d)
        .map(|chunk| {
            let m = chunk.len() / d;
            let av = DMatrixView::from_slice(chunk, d, m);
            let at = DMatrixView::from_slice_with_strides(chunk, m, d, d, 1);
            let mut g = DMatrix::<f32>::zeros(d, d);
            g.gemm(1.0, &av, &at, 0.0);
            g
        })
        .collect();
    let mut g = DMatrix::<f64>::zeros(d, d);
    for p in parts {
        g += p.map(|v| v as f64);
    }
    g
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

impl LinearDenoisingEncoder {
    /// Fits the encoder: `clean` and `corrupted` are row-major `n x d` (the same templates,
    /// clean and corrupted), `corrupted_mask` marks missing values of the corrupted crops.
    /// `ridge_lambda_rel` scales the ridge penalty by the mean diagonal of the Gram matrix.
    pub fn fit(
        clean: &[f32],
        corrupted: &[f32],
        corrupted_mask: &[bool],
        n: usize,
        d: usize,
        code_dim: usize,
        ridge_lambda_rel: f64,
        seed: u64,
    ) -> Result<Self, TrackerError> {
        if n < 2 || clean.len() != n * d || corrupted.len() != n * d || corrupted_mask.len() != n * d {
            return Err(TrackerError::Config(format!("encoder fit: bad sizes (n {n}, d {d})")));
        }
        let k = code_dim.min(d);
        let mean = |x: &[f32]| -> Vec<f32> {
            let mut m = vec![0f64; d];
            for row in x.chunks(d) {
                for (a, b) in m.iter_mut().zip(row) {
                    *a += *b as f64;
                }
            }
            m.into_iter().map(|v| (v / n as f64) as f32).collect()
        };
        let mean_clean = mean(clean);
        let a: Vec<f32> = clean
            .par_chunks(d)
            .flat_map_iter(|row| row.iter().zip(&mean_clean).map(|(x, m)| x - m).collect::<Vec<_>>())
            .collect();
        let g = gram(&a, d, n);
        let p = top_eigenvectors(&g, k, seed)?; // d x k
        let p32 = p.map(|v| v as f32);
        // clean codes Z = P^T A  (k x n)
        let pt = p32.transpose();
        let av = DMatrixView::from_slice(&a, d, n);
        let z = &pt * av;
        drop(a);
        // corrupted, imputed and centred
        let imputed: Vec<f32> = corrupted
            .iter()
            .zip(corrupted_mask)
            .enumerate()
            .map(|(i, (&x, &m))| if m { mean_clean[i % d] } else { x })
            .collect();
        let mean_observed = mean(&imputed);
        let at: Vec<f32> = imputed
            .par_chunks(d)
            .flat_map_iter(|row| row.iter().zip(&mean_observed).map(|(x, m)| x - m).collect::<Vec<_>>())
            .collect();
        drop(imputed);
        let mut gt = gram(&at, d, n);
        let atv = DMatrixView::from_slice(&at, d, n);
        // cross term  A~ Z^T  (d x k)
        let zt = DMatrixView::from_slice_with_strides(z.as_slice(), n, k, k, 1);
        let mut cross = DMatrix::<f32>::zeros(d, k);
        cross.gemm(1.0, &atv, &zt, 0.0);
        let lambda = ridge_lambda_rel * gt.trace() / d as f64 + 1e-9;
        for i in 0..d {
            gt[(i, i)] += lambda;
        }
        let chol = gt
            .cholesky()
            .ok_or_else(|| TrackerError::Numerical("ridge system is not positive definite".into()))?;
        let w = chol.solve(&cross.map(|v| v as f64)); // d x k
        Ok(Self {
            input_dim: d,
            code_dim: k,
            mean_clean,
            mean_observed,
            pca_t: pt.as_slice().to_vec(),
            ridge_t: w.transpose().map(|v| v as f32).as_slice().to_vec(),
        })
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
    }
    fn encode_templates(&self, x: &[f32], n: usize, out: &mut [f32]) {
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

    #[test]
    fn ridge_encoder_denoises_where_pca_of_the_noisy_input_does_not() {
        // signals on a 3-d subspace of a 40-d space, observed with strong noise on half the
        // coordinates and with missing values
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (n, d, k) = (3000, 40, 3);
        let basis: Vec<Vec<f32>> = (0..k).map(|_| (0..d).map(|_| rng.random::<f32>() - 0.5).collect()).collect();
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
        let enc = LinearDenoisingEncoder::fit(&clean, &noisy, &mask, n, d, k, 1e-3, 1).unwrap();
        let mut zc = vec![0f32; n * k];
        let mut zn = vec![0f32; n * k];
        enc.encode_templates(&clean, n, &mut zc);
        enc.encode_observations(&noisy, &mask, n, &mut zn);
        normalise_rows(&mut zc, k);
        normalise_rows(&mut zn, k);
        let cos: f32 =
            (0..n).map(|i| (0..k).map(|q| zc[i * k + q] * zn[i * k + q]).sum::<f32>()).sum::<f32>() / n as f32;
        // plain PCA projection of the noisy input, for comparison
        let mut zp = vec![0f32; n * k];
        let imputed: Vec<f32> =
            noisy.iter().zip(&mask).enumerate().map(|(i, (&v, &m))| if m { enc.mean_clean[i % d] } else { v }).collect();
        enc.encode_templates(&imputed, n, &mut zp);
        normalise_rows(&mut zp, k);
        let cos_pca: f32 =
            (0..n).map(|i| (0..k).map(|q| zc[i * k + q] * zp[i * k + q]).sum::<f32>()).sum::<f32>() / n as f32;
        assert!(cos > 0.9, "ridge codes agree with clean codes: {cos}");
        assert!(cos > cos_pca + 0.03, "ridge {cos} vs pca {cos_pca}");
    }
}
