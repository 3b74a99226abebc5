//! The encoder from crop features ([`crate::tracker::crop`]) to codes, and the default one,
//! [`LinearDenoisingEncoder`].
//!
//! # The default encoder
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
//! the colour detail that tells the flip apart barely moves the cosine.
//!
//! # Depth and colour, each with its own code
//! With colour, the encoder is two of the above side by side ([`LinearDenoisingEncoder::fit_blocks`]):
//! the depth cells get 96 components and the colour cells 32 (`CodebookConfig::color_code_dim`),
//! each block reads only its own inputs and is normalised on its own ([`finish_codes`]), and
//! the similarity is the weighted mean of the two cosines, colour at 0.25
//! (`CodebookConfig::color_code_weight`). The tracker's log-likelihood is then a product of a
//! depth expert and a colour expert, and neither's norm decides how much it counts: in one code
//! of both, a real crop's colours (far from the mesh's vertex colours, under another light)
//! drown what its depth says.
//!
//! # The training set is streamed
//! PCA, whitening and the ridge regression need only sums over the training pairs: the Gram
//! matrices of the clean and of the corrupted crops and their cross term
//! ([`LinearDenoisingEncoder::fit_streamed`], chunks of 1,024 crops). So the number of crops
//! costs build time, not memory: 36,000 by default (`CodebookConfig::n_train`).
//!
//! Measured history (the whitening, the colour weight, the number of training crops):
//! `docs/decisions.md`, "Tracker: decisions moved from the code".

use crate::tracker::TrackerError;
use nalgebra::{DMatrix, DMatrixView, DMatrixViewMut};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// The crop features moved to [`crate::tracker::crop`]; these paths stay for callers.
pub use crate::tracker::crop::{
    CropParams, FeatureLayout, central_median_depth, denoise_depth, depth_noise_sigma, inpaint_depth, sample_crop,
    suppress_support_plane, suppress_support_plane_steep, to_chromaticity,
};

/// Version of the feature layout and of the default encoder (part of every codebook cache key).
pub const ENCODER_VERSION: u32 = 6;

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
        project_columns(w_t, self.code_dim, self.input_dim, x_centred, n, out);
    }
}

/// `out = W x` for the `k x d` matrix `w_t` and the `n` columns `x` (column-major, as `out`).
fn project_columns(w_t: &[f32], k: usize, d: usize, x_centred: &[f32], n: usize, out: &mut [f32]) {
    let gemm = |x: &[f32], out: &mut [f32], cols: usize| {
        let wv = DMatrixView::from_slice(w_t, k, d);
        let xv = DMatrixView::from_slice(x, d, cols);
        let mut ov = DMatrixViewMut::from_slice(out, k, cols);
        ov.gemm(1.0, &wv, &xv, 0.0);
    };
    // the columns (codes) in one block per thread: each output is the same sum as in one
    // product (matrixmultiply's depth blocking does not depend on the column count; every
    // block keeps more than nalgebra's `SMALL_DIM` columns, so none takes its naive loop)
    let parts = rayon::current_num_threads().min(n / PROJECT_MIN_COLUMNS).max(1);
    if parts == 1 {
        gemm(&x_centred[..n * d], &mut out[..n * k], n);
        return;
    }
    let mut blocks: Vec<(&[f32], &mut [f32], usize)> = Vec::with_capacity(parts);
    let (mut x, mut o) = (&x_centred[..n * d], &mut out[..n * k]);
    for i in 0..parts {
        let cols = n / parts + usize::from(i < n % parts);
        let (xa, xb) = x.split_at(cols * d);
        let (oa, ob) = o.split_at_mut(cols * k);
        blocks.push((xa, oa, cols));
        (x, o) = (xb, ob);
    }
    blocks.into_par_iter().for_each(|(x, o, cols)| gemm(x, o, cols));
}

/// Fewest codes in one thread's block of the projection (nalgebra multiplies matrices of at
/// most 5 columns with its own loop, whose sums differ from matrixmultiply's in the last bit).
const PROJECT_MIN_COLUMNS: usize = 16;

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
        // missing inputs take the clean mean; then centred on the observed mean (row by row,
        // in parallel: the same arithmetic per element)
        let mut xc = vec![0f32; n * d];
        xc.par_chunks_mut(d)
            .zip(x[..n * d].par_chunks(d).zip(mask[..n * d].par_chunks(d)))
            .for_each(|(dst, (xr, mr))| {
                for ((((o, &v), &m), &mc), &mo) in dst
                    .iter_mut()
                    .zip(xr)
                    .zip(mr)
                    .zip(&self.mean_clean)
                    .zip(&self.mean_observed)
                {
                    *o = (if m { mc } else { v }) - mo;
                }
            });
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

    #[test]
    fn projection_in_blocks_is_the_projection_in_one() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (k, d) = (24, 300);
        let w: Vec<f32> = (0..k * d).map(|_| rng.random::<f32>() - 0.5).collect();
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        for n in [1, 5, 6, 17, 47, 48, 110, 331] {
            let x: Vec<f32> = (0..n * d).map(|_| rng.random::<f32>() - 0.5).collect();
            let mut whole = vec![0f32; n * k];
            DMatrixViewMut::from_slice(&mut whole, k, n).gemm(
                1.0,
                &DMatrixView::from_slice(&w, k, d),
                &DMatrixView::from_slice(&x, d, n),
                0.0,
            );
            let mut blocks = vec![0f32; n * k];
            pool.install(|| project_columns(&w, k, d, &x, n, &mut blocks));
            assert!(
                whole.iter().zip(&blocks).all(|(a, b)| a.to_bits() == b.to_bits()),
                "n = {n}"
            );
        }
    }
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

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
