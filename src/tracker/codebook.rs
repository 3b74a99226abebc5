//! Codebooks: the codes of the object's appearance at every bin of the rotation grid.
//!
//! Only the `n_elevation x n_azimuth` viewpoints are rendered (object centred at
//! `render_distance_m`, square `render_px` images); the in-plane bins are 2-D rotations of the
//! centred crop (see [`crate::geometry`]: `R(e, a, theta) = Rz(theta) * V(e, a)^T`, so the
//! image at `theta` is the image at 0 rotated by `theta` about the centre).
//!
//! # Cache
//! One file per (mesh content, grid, encoder version, config): magic, format version, a JSON
//! header with the key, the payload (encoder and codes, little-endian f32) and a SHA-256 of
//! everything before it. A file whose checksum, header or key does not match is rebuilt.

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::geometry::{Pose, RotationGrid};
use crate::mesh::Mesh;
use crate::tracker::TrackerError;
use crate::tracker::crop::{CropParams, FeatureLayout, sample_crop, to_chromaticity};
use crate::tracker::encoder::{CodeBlock, CodeLayout, ENCODER_VERSION, Encoder, FnTraining, LinearDenoisingEncoder};
use nalgebra::{Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

const MAGIC: &[u8; 8] = b"PGCODEBK";
const FORMAT_VERSION: u32 = 5;

/// How a codebook is built.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CodebookConfig {
    /// Feature grid side (depth); colour uses half of it.
    pub feature_px: usize,
    /// Side of the rendered template images.
    pub render_px: usize,
    /// Distance of the object centre from the template camera.
    pub render_distance_m: f64,
    /// Crop side = `crop_margin * diameter`.
    pub crop_margin: f64,
    pub code_dim: usize,
    pub use_color: bool,
    pub color_weight: f32,
    /// Corrupted training crops for the ridge regression (36,000 by default: fewer leave the
    /// result at the mercy of which crops were drawn). The fit keeps only sums over the crops
    /// ([`LinearDenoisingEncoder::fit_streamed`]), so more crops cost build time, not memory.
    pub n_train: usize,
    pub ridge_lambda_rel: f64,
    pub seed: u64,
    /// Training crops' centre jitter, as a share of the crop side (each axis, uniform +-).
    pub crop_jitter_rel: f64,
    /// Share of training crops whose background is a support plane touching the object (a
    /// table seen from above: steep depth gradient, the table's colour).
    pub support_plane_prob: f64,
    /// Remove the support plane from crops before encoding
    /// ([`crate::tracker::crop::suppress_support_plane`]), observed and training crops alike.
    pub suppress_plane: bool,
    /// Partial whitening of the codes: each PCA component scaled by its variance to the
    /// power `-whiten / 2` (0: plain PCA, 1: full whitening; see the encoder's module docs).
    #[serde(default)]
    pub whiten: f64,
    /// What the colour cells hold (with `use_color`): chromaticity by default, so that the
    /// scene's lighting does not move the codes
    /// ([`crate::tracker::crop::to_chromaticity`]).
    #[serde(default)]
    pub color_features: ColorFeatures,
    /// With `use_color`: depth and colour get codes of their own, this many components of
    /// `code_dim` for the colour, and the similarity is the weighted mean of the two cosines
    /// (a product of experts, see [`crate::tracker::encoder::finish_codes`]). 0: one code of
    /// depth and colour together, where a real crop's colour, far from the mesh's, drowns what
    /// its depth says.
    #[serde(default = "default_color_code_dim")]
    pub color_code_dim: usize,
    /// Weight of the colour cosine in the similarity (the depth's is `1 - color_code_weight`).
    #[serde(default = "default_color_code_weight")]
    pub color_code_weight: f32,
    /// Also build the box-centred code table ([`Codebook::box_table`]). Derived from the
    /// tracker's settings where codebooks are requested
    /// ([`crate::tracker::TrackerConfig::codebook_config`]), not a setting of its own:
    /// left out of the serialised form (and so of the calibration map's settings hash); the
    /// cache keeps books with and without the table apart.
    #[serde(skip)]
    pub box_table: bool,
}

fn default_color_code_dim() -> usize {
    32
}

fn default_color_code_weight() -> f32 {
    0.25
}

/// The colour features of a codebook.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColorFeatures {
    /// Each cell's chromaticity: hue and saturation, not brightness (robust to lighting).
    #[default]
    Chromaticity,
    /// Each cell's RGB as rendered (shading included: only right under the templates' own
    /// headlight).
    Rgb,
}

impl Default for CodebookConfig {
    fn default() -> Self {
        Self {
            feature_px: 32,
            render_px: 64,
            render_distance_m: 1.0,
            crop_margin: 1.2,
            code_dim: 128,
            use_color: true,
            color_weight: 1.2,
            n_train: 36_000,
            ridge_lambda_rel: 1e-3,
            seed: 7,
            crop_jitter_rel: 0.06,
            support_plane_prob: 0.5,
            suppress_plane: true,
            whiten: 0.5,
            color_features: ColorFeatures::default(),
            color_code_dim: default_color_code_dim(),
            color_code_weight: default_color_code_weight(),
            box_table: false,
        }
    }
}

impl CodebookConfig {
    /// Small and fast (tests, a first codebook while the full one builds).
    pub fn coarse() -> Self {
        Self {
            feature_px: 16,
            render_px: 32,
            // 48 depth and 16 colour components, colour weighing more than in the full
            // codebook (whose depth cells are four times as many); the comparison that chose
            // them is in docs/decisions.md
            code_dim: 64,
            color_code_dim: 16,
            color_code_weight: 0.5,
            n_train: 3_000,
            ..Self::default()
        }
    }
    pub fn layout(&self) -> FeatureLayout {
        FeatureLayout {
            feature_px: self.feature_px,
            use_color: self.use_color,
            color_weight: self.color_weight,
            chromaticity: self.color_features == ColorFeatures::Chromaticity,
        }
    }
}

/// Renders many centred views of one object (the GPU renderer, or the CPU rasteriser).
pub trait ViewSource: Sync {
    /// Depth (0 = empty) and colour of the object at each `camera_from_object`.
    fn render(
        &self,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
    ) -> Result<Vec<(DepthImage, Option<ColorImage>)>, TrackerError>;
}

/// The CPU rasteriser as a view source (parallel over views).
pub struct CpuViews<'a>(pub &'a Mesh);

impl ViewSource for CpuViews<'_> {
    fn render(
        &self,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
    ) -> Result<Vec<(DepthImage, Option<ColorImage>)>, TrackerError> {
        Ok(camera_from_object
            .par_iter()
            .map(|p| {
                let img = crate::render::raster::render(intrinsics, &[(self.0, *p)], 0.01, [0, 0, 0]);
                (img.depth, Some(img.color))
            })
            .collect())
    }
}

/// Header of a cache file (also the cache key).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Header {
    mesh_hash: String,
    grid_step_deg: u32,
    encoder_version: u32,
    config: CodebookConfig,
    diameter_m: f64,
    input_dim: usize,
    code_dim: usize,
    n_bins: usize,
    /// The encoder's code blocks (empty: one code).
    blocks: Vec<CodeBlock>,
    /// Whether the box-centred table follows (the config's own flag is not serialised).
    box_table: bool,
}

/// Codebook rows stored as half floats: half the memory of f32, and a code's similarity to a
/// unit row moves by about 1e-4 (the likelihood's sigma is 0.06).
#[derive(Debug, Clone, PartialEq)]
pub struct Codes {
    dim: usize,
    values: Vec<half::f16>,
}

impl Codes {
    /// Rows of `dim` values from row-major f32.
    pub fn from_f32(values: &[f32], dim: usize) -> Self {
        use half::slice::HalfFloatSliceExt;
        let mut v = vec![half::f16::ZERO; values.len()];
        v.convert_from_f32_slice(values);
        Self { dim, values: v }
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.values.len().checked_div(self.dim).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Row `b` into `out` (`dim` values).
    #[inline]
    pub fn row_into(&self, b: usize, out: &mut [f32]) {
        use half::slice::HalfFloatSliceExt;
        self.values[b * self.dim..(b + 1) * self.dim].convert_to_f32_slice(out);
    }

    /// Rows `rows` into `out` (`rows.len() * dim` values, row after row): the gather of the
    /// matching, with one feature check for all rows and AVX-512's 16-lane conversion where the
    /// CPU has it (the conversion is exact: the same values as [`Codes::row_into`]).
    pub fn rows_into(&self, rows: &[u32], out: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx512f") {
            use half::slice::HalfFloatSliceExt;
            let bits: &[u16] = self.values.reinterpret_cast();
            // SAFETY: AVX-512F is present (checked above); the function reads and writes only
            // through bounds-checked slices.
            #[allow(unsafe_code)] // see Cargo.toml's lints
            unsafe {
                rows_into_avx512(bits, self.dim, rows, out);
            }
            return;
        }
        for (dst, r) in out.chunks_mut(self.dim).zip(rows) {
            self.row_into(*r as usize, dst);
        }
    }

    /// Every row, row-major f32.
    pub fn to_f32(&self) -> Vec<f32> {
        use half::slice::HalfFloatSliceExt;
        self.values.to_f32_vec()
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.values.len() * 2
    }
}

/// [`Codes::rows_into`] on AVX-512: 16 half floats to f32 per instruction.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn rows_into_avx512(bits: &[u16], dim: usize, rows: &[u32], out: &mut [f32]) {
    use std::arch::x86_64::{__m256i, _mm256_loadu_si256, _mm512_cvtph_ps, _mm512_storeu_ps};
    for (dst, r) in out.chunks_mut(dim).zip(rows) {
        let src = &bits[*r as usize * dim..(*r as usize + 1) * dim];
        let mut s16 = src.chunks_exact(16);
        let mut d16 = dst.chunks_exact_mut(16);
        for (s, d) in (&mut s16).zip(&mut d16) {
            // SAFETY: `s` holds 16 u16 (32 bytes) and `d` 16 f32 (64 bytes): both unaligned
            // accesses stay inside their slices.
            #[allow(unsafe_code)] // see Cargo.toml's lints
            unsafe {
                let h = _mm256_loadu_si256(s.as_ptr().cast::<__m256i>());
                _mm512_storeu_ps(d.as_mut_ptr(), _mm512_cvtph_ps(h));
            }
        }
        for (s, d) in s16.remainder().iter().zip(d16.into_remainder()) {
            *d = half::f16::from_bits(*s).to_f32();
        }
    }
}

/// The codes of one object at every bin of a grid.
#[derive(Debug, Clone)]
pub struct Codebook {
    pub grid: RotationGrid,
    pub config: CodebookConfig,
    pub mesh_hash: String,
    pub diameter_m: f64,
    pub encoder: LinearDenoisingEncoder,
    /// One unit row of `code_dim` values per bin.
    pub codes: Codes,
    /// Per viewpoint: median normalised depth of the template's central surface
    /// ([`crate::tracker::crop::central_median_depth`]; NaN when none).
    pub median_depth_norm: Vec<f32>,
    /// The box-centred table, built when [`CodebookConfig::box_table`] asks for it.
    pub box_table: Option<BoxTable>,
    /// Seconds the build took (0 when loaded from the cache).
    pub build_seconds: f64,
    /// True when it came from the cache.
    pub from_cache: bool,
}

/// The codes of every bin with its template centred on the box of its silhouette (in the
/// crop's axes) instead of on the mesh's origin: what a crop centred on a detector's box is
/// matched against ([`crate::tracker::observation::ObservationConfig::box_codes`]).
#[derive(Debug, Clone)]
pub struct BoxTable {
    pub codes: Codes,
    /// Per bin: the central median normalised depth of the box-centred template (NaN: none).
    pub median_depth_norm: Vec<f32>,
}

impl Codebook {
    pub fn code_dim(&self) -> usize {
        self.encoder.code_dim
    }
    pub fn n_bins(&self) -> usize {
        self.grid.len()
    }
    pub fn layout(&self) -> FeatureLayout {
        self.config.layout()
    }
    /// Side of a crop at the object, metres.
    pub fn crop_side_m(&self) -> f64 {
        self.config.crop_margin * self.diameter_m
    }
    /// Depth normalisation box, metres.
    pub fn box_m(&self) -> f64 {
        self.diameter_m
    }
    /// The code table crops are matched against: the box-centred one for crops centred on a
    /// detector's box (when it was built), the origin-centred one otherwise.
    pub fn table(&self, box_centred: bool) -> &Codes {
        match (&self.box_table, box_centred) {
            (Some(b), true) => &b.codes,
            _ => &self.codes,
        }
    }
    /// The central median normalised depth of `bin`'s template in that table (NaN: none).
    pub fn central_depth_norm(&self, bin: usize, box_centred: bool) -> f32 {
        match (&self.box_table, box_centred) {
            (Some(b), true) => b.median_depth_norm[bin],
            _ => self.median_depth_norm[bin / self.grid.n_inplane()],
        }
    }
    /// The code of `bin`.
    pub fn code(&self, bin: usize) -> Vec<f32> {
        let mut out = vec![0f32; self.code_dim()];
        self.codes.row_into(bin, &mut out);
        out
    }

    /// The contract's entry point: renders with the GPU renderer (software Vulkan without a GPU).
    pub fn load_or_build(
        renderer: &crate::render::Renderer,
        mesh: &Mesh,
        grid: RotationGrid,
        config: &CodebookConfig,
        cache_dir: Option<&Path>,
    ) -> Result<Self, TrackerError> {
        let source = crate::tracker::codebook::RendererViews::new(renderer, mesh)?;
        Self::load_or_build_with(&source, mesh, grid, config, cache_dir)
    }

    /// Loads the cached codebook of this key, or builds it with `source` (and caches it).
    pub fn load_or_build_with(
        source: &dyn ViewSource,
        mesh: &Mesh,
        grid: RotationGrid,
        config: &CodebookConfig,
        cache_dir: Option<&Path>,
    ) -> Result<Self, TrackerError> {
        let hash = mesh.content_hash();
        if let Some(dir) = cache_dir {
            let path = cache_path(dir, &hash, grid, config);
            if path.exists() {
                match read_cache(&path, &hash, grid, config) {
                    Ok(cb) => return Ok(cb),
                    Err(e) => tracing::warn!("codebook cache rejected, rebuilding: {e}"),
                }
            }
        }
        let cb = Self::build(source, mesh, grid, config)?;
        if let Some(dir) = cache_dir {
            std::fs::create_dir_all(dir)?;
            write_cache(&cache_path(dir, &hash, grid, config), &cb)?;
        }
        Ok(cb)
    }

    /// Builds a codebook (no cache).
    pub fn build(
        source: &dyn ViewSource,
        mesh: &Mesh,
        grid: RotationGrid,
        config: &CodebookConfig,
    ) -> Result<Self, TrackerError> {
        let t0 = Instant::now();
        if config.feature_px < 4 || config.render_px < config.feature_px || config.code_dim == 0 {
            return Err(TrackerError::Config(format!("bad codebook config {config:?}")));
        }
        let diameter_m = mesh.diameter_m();
        if diameter_m.is_nan() || diameter_m <= 0.0 {
            return Err(TrackerError::Config("mesh has zero diameter".into()));
        }
        let side_m = config.crop_margin * diameter_m;
        let f_render = config.render_px as f64 * config.render_distance_m / side_m;
        let k = Intrinsics::from_focal(config.render_px as u32, config.render_px as u32, f_render)
            .map_err(|e| TrackerError::Config(e.to_string()))?;
        let poses: Vec<Pose> = (0..grid.n_viewpoints())
            .map(|v| {
                Pose::from_parts(
                    Translation3::new(0.0, 0.0, config.render_distance_m),
                    grid.viewpoint_rotation(v),
                )
            })
            .collect();
        let views = source.render(&k, &poses)?;
        if views.len() != poses.len() {
            return Err(TrackerError::Render(format!(
                "{} views for {} poses",
                views.len(),
                poses.len()
            )));
        }
        let layout = config.layout();
        let d = layout.dim();
        let centre = [k.cx(), k.cy()];
        let template_at = |v: usize, theta: f64, centre: [f64; 2], out: &mut [f32], mask: &mut [bool]| {
            let p = CropParams {
                centre_px: centre,
                side_px: config.render_px as f64,
                rotation_rad: theta,
                z_centre_m: config.render_distance_m,
                box_m: diameter_m,
                zero_is_far: true,
            };
            let (dimg, cimg) = &views[v];
            sample_crop(&layout, dimg, cimg.as_ref(), &p, out, mask);
            to_chromaticity(&layout, out, mask);
        };
        let template =
            |v: usize, theta: f64, out: &mut [f32], mask: &mut [bool]| template_at(v, theta, centre, out, mask);

        // training set: clean templates at bins, corrupted crops of the same bins
        let n = config.n_train.max(64);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(config.seed);
        let jobs: Vec<(usize, usize, u64)> = (0..n)
            .map(|_| {
                (
                    rng.random_range(0..grid.n_viewpoints()),
                    rng.random_range(0..grid.n_inplane()),
                    rng.random(),
                )
            })
            .collect();
        let step = grid.step_rad();
        // the training pairs are made chunk by chunk as the fit reads them (the encoder's fit
        // keeps only sums over them), so the number of crops costs time, not memory
        let training = FnTraining {
            n,
            d,
            clean: |rows: std::ops::Range<usize>| -> Vec<f32> {
                let mut x = vec![0f32; rows.len() * d];
                x.par_chunks_mut(d).zip(&jobs[rows]).for_each(|(row, &(v, i, _))| {
                    let mut mask = vec![false; d];
                    template(v, i as f64 * step, row, &mut mask);
                });
                x
            },
            pairs: |rows: std::ops::Range<usize>| -> (Vec<f32>, Vec<f32>, Vec<bool>) {
                let m = rows.len();
                let (mut clean, mut noisy, mut nmask) = (vec![0f32; m * d], vec![0f32; m * d], vec![false; m * d]);
                clean
                    .par_chunks_mut(d)
                    .zip(noisy.par_chunks_mut(d))
                    .zip(nmask.par_chunks_mut(d))
                    .zip(&jobs[rows])
                    .for_each(|(((c, x), k), &(v, i, seed))| {
                        let mut mask = vec![false; d];
                        template(v, i as f64 * step, c, &mut mask);
                        let (noisy, noisy_mask) =
                            corrupt(&layout, &views[v], config, diameter_m, i as f64 * step, step, seed);
                        x.copy_from_slice(&noisy);
                        k.copy_from_slice(&noisy_mask);
                    });
                (clean, noisy, nmask)
            },
        };
        let split = layout.use_color && config.color_code_dim > 0;
        if split && (config.color_code_dim >= config.code_dim || !(0.0..1.0).contains(&config.color_code_weight)) {
            return Err(TrackerError::Config(format!(
                "colour code: {} of {} components at weight {}",
                config.color_code_dim, config.code_dim, config.color_code_weight
            )));
        }
        let (dl, cl) = (layout.depth_len(), layout.color_len());
        let parts = [
            (
                0,
                dl,
                config.code_dim - config.color_code_dim.min(config.code_dim),
                1.0 - config.color_code_weight,
            ),
            (dl, cl, config.color_code_dim, config.color_code_weight),
        ];
        let code_layout = if split {
            CodeLayout::Blocks(&parts)
        } else {
            CodeLayout::One {
                code_dim: config.code_dim,
            }
        };
        let encoder = LinearDenoisingEncoder::fit_streamed(
            &training,
            code_layout,
            config.ridge_lambda_rel,
            config.whiten,
            config.seed,
        )?;

        // codes of every bin, one viewpoint (all in-plane rotations) per task, each template
        // centred where `centre_of(viewpoint, theta)` says; with `medians`, the central median
        // depth of each template too
        let kd = encoder.code_dim;
        let ni = grid.n_inplane();
        let encode_bins = |centre_of: &(dyn Fn(usize, f64) -> [f64; 2] + Sync), medians: bool| {
            let mut codes = vec![0f32; grid.len() * kd];
            let med: Vec<Vec<f32>> = codes
                .par_chunks_mut(ni * kd)
                .enumerate()
                .map(|(v, out)| {
                    let mut x = vec![0f32; ni * d];
                    let mut mask = vec![false; d];
                    let mut m = Vec::new();
                    for i in 0..ni {
                        let theta = i as f64 * step;
                        let row = &mut x[i * d..(i + 1) * d];
                        template_at(v, theta, centre_of(v, theta), row, &mut mask);
                        if medians {
                            m.push(crate::tracker::crop::central_median_depth(&layout, row, &mask).unwrap_or(f32::NAN));
                        }
                    }
                    encoder.encode_templates(&x, ni, out);
                    m
                })
                .collect();
            (codes, med.concat())
        };
        let (codes, _) = encode_bins(&|_, _| centre, false);
        // the same bins with each template centred on its silhouette's box, when asked for
        let box_table = config.box_table.then(|| {
            let outlines: Vec<Vec<[f64; 2]>> = views
                .par_iter()
                .map(|(dimg, _)| outline_offsets(dimg, centre))
                .collect();
            let (box_codes, median_depth_norm) =
                encode_bins(&|v, theta| box_centre_px(&outlines[v], centre, theta), true);
            BoxTable {
                codes: Codes::from_f32(&box_codes, kd),
                median_depth_norm,
            }
        });
        let median_depth_norm: Vec<f32> = (0..grid.n_viewpoints())
            .into_par_iter()
            .map(|v| {
                let mut x = vec![0f32; d];
                let mut mask = vec![false; d];
                template(v, 0.0, &mut x, &mut mask);
                crate::tracker::crop::central_median_depth(&layout, &x, &mask).unwrap_or(f32::NAN)
            })
            .collect();
        Ok(Self {
            grid,
            config: config.clone(),
            mesh_hash: mesh.content_hash(),
            diameter_m,
            encoder,
            codes: Codes::from_f32(&codes, kd),
            median_depth_norm,
            box_table,
            build_seconds: t0.elapsed().as_secs_f64(),
            from_cache: false,
        })
    }
}

/// The offsets from `centre` (pixels) of the centres of a rendered view's silhouette pixels
/// that touch the background or the image's edge: all a rotated box of the silhouette reads.
fn outline_offsets(depth: &DepthImage, centre: [f64; 2]) -> Vec<[f64; 2]> {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let on = |x: usize, y: usize| depth.data_m[y * w + x] > 0.0;
    let mut out = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if on(x, y)
                && (x == 0
                    || y == 0
                    || x + 1 == w
                    || y + 1 == h
                    || !on(x - 1, y)
                    || !on(x + 1, y)
                    || !on(x, y - 1)
                    || !on(x, y + 1))
            {
                out.push([x as f64 - centre[0], y as f64 - centre[1]]);
            }
        }
    }
    out
}

/// Where in the view a crop at in-plane angle `theta` must be centred for the silhouette
/// (`outline`, offsets from `centre`) to sit in the middle of the crop's axis-aligned box, as a
/// detector's box centres it; `centre` itself for an empty silhouette. A crop sample at
/// offset `o` reads the view at `centre + M o`, `M = [[c, s], [-s, c]]` ([`sample_crop`]).
fn box_centre_px(outline: &[[f64; 2]], centre: [f64; 2], theta: f64) -> [f64; 2] {
    if outline.is_empty() {
        return centre;
    }
    let (s, c) = theta.sin_cos();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for u in outline {
        let o = [c * u[0] - s * u[1], s * u[0] + c * u[1]];
        for a in 0..2 {
            lo[a] = lo[a].min(o[a]);
            hi[a] = hi[a].max(o[a]);
        }
    }
    let b = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
    [centre[0] + c * b[0] + s * b[1], centre[1] - s * b[0] + c * b[1]]
}

/// A corrupted crop of view `view` at in-plane angle `theta`: shifted, rescaled, rotated within
/// the bin, depth offset and noise, missing pixels, an occluder, background clutter or a
/// support plane the object rests on (then suppressed as observed crops are), colour changes
/// or no colour at all.
fn corrupt(
    layout: &FeatureLayout,
    view: &(DepthImage, Option<ColorImage>),
    config: &CodebookConfig,
    box_m: f64,
    theta: f64,
    step_rad: f64,
    seed: u64,
) -> (Vec<f32>, Vec<bool>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let d = layout.dim();
    let f = layout.feature_px;
    let rp = config.render_px as f64;
    let mut x = vec![0f32; d];
    let mut mask = vec![false; d];
    let jit = config.crop_jitter_rel.abs();
    let p = CropParams {
        centre_px: [
            (rp - 1.0) / 2.0 + rng.random_range(-jit..=jit) * rp,
            (rp - 1.0) / 2.0 + rng.random_range(-jit..=jit) * rp,
        ],
        side_px: rp * rng.random_range(0.9..1.1),
        rotation_rad: theta + rng.random_range(-0.5..0.5) * step_rad,
        z_centre_m: config.render_distance_m + rng.random_range(-0.1..0.1) * box_m,
        box_m,
        zero_is_far: true,
    };
    sample_crop(layout, &view.0, view.1.as_ref(), &p, &mut x, &mut mask);
    let bg: Vec<bool> = x[..f * f].iter().map(|&v| v >= 1.0).collect();
    // a support plane touching the object (a table seen from above): its depth grows
    // steeply across the crop (a camera 30 degrees above a table sees about 2 boxes of depth
    // change over one crop side), it carries the table's colour, and the object rests on it
    let support = rng.random::<f64>() < config.support_plane_prob;
    let mut plane_color = [0f32; 3];
    let mut on_plane = vec![false; f * f];
    if support {
        let phi = rng.random_range(0.0..std::f32::consts::TAU);
        let g = rng.random_range(0.3..3.0f32);
        let (gu, gv) = (g * phi.cos(), g * phi.sin());
        let at = |k: usize| -> f32 {
            let (i, j) = (k / f, k % f);
            gu * ((j as f32 + 0.5) / f as f32 - 0.5) + gv * ((i as f32 + 0.5) / f as f32 - 0.5)
        };
        // offset: the plane touches the object's visible surface from behind (min gap 0)
        let mut c = f32::NEG_INFINITY;
        for k in 0..f * f {
            if !bg[k] && !mask[k] {
                c = c.max(x[k] - at(k));
            }
        }
        if c.is_finite() {
            let c = c + rng.random_range(0.0..0.05f32);
            for k in 0..f * f {
                if bg[k] {
                    let v = c + at(k);
                    if v < 1.0 {
                        x[k] = v.max(0.0);
                        on_plane[k] = true;
                    }
                }
            }
        }
        for ch in plane_color.iter_mut() {
            *ch = rng.random_range(0.1..0.9f32) * layout.color_weight;
        }
    }
    // background clutter: a tilted plane behind or around the object
    let clutter = !support && rng.random::<f64>() < 0.6;
    let (c0, gx, gy) = (
        rng.random_range(0.3..1.0f32),
        rng.random_range(-0.4..0.4f32),
        rng.random_range(-0.4..0.4f32),
    );
    let grey = rng.random_range(0.1..0.9f32) * layout.color_weight;
    if clutter {
        for i in 0..f {
            for j in 0..f {
                let k = i * f + j;
                if bg[k] {
                    let v = c0 + gx * (j as f32 / f as f32 - 0.5) + gy * (i as f32 / f as f32 - 0.5);
                    x[k] = v.clamp(0.0, 1.0);
                }
            }
        }
    }
    // depth noise, per cell: unclamped, then denoised and clamped as observed crops are (a far
    // camera's crop, filtered, lands in this range)
    let sigma = rng.random_range(0.0..0.35f32);
    if let Ok(noise) = Normal::new(0.0f32, sigma.max(1e-6)) {
        for v in x[..f * f].iter_mut() {
            if *v < 1.0 {
                *v += noise.sample(&mut rng);
            }
        }
    }
    crate::tracker::crop::denoise_depth(layout, &mut x[..f * f], &mask[..f * f]);
    // occluder: a near rectangle
    if rng.random::<f64>() < 0.4 {
        let (w, h) = (rng.random_range(f / 6..f / 2 + 1), rng.random_range(f / 6..f / 2 + 1));
        let (x0, y0) = (rng.random_range(0..f - w + 1), rng.random_range(0..f - h + 1));
        let v = rng.random_range(0.0..0.3f32);
        for i in y0..y0 + h {
            for j in x0..x0 + w {
                x[i * f + j] = v;
            }
        }
    }
    // missing depth readings, sometimes the whole background (nothing behind the object)
    let missing = rng.random_range(0.0..0.2f64);
    let no_background = !clutter && !support && rng.random::<f64>() < 0.5;
    for k in 0..f * f {
        if rng.random::<f64>() < missing || (no_background && bg[k]) {
            mask[k] = true;
        }
    }
    let mut has_color = layout.use_color;
    if layout.use_color {
        let base = layout.depth_len();
        if rng.random::<f64>() < 0.25 {
            has_color = false;
            mask[base..].fill(true);
        } else {
            // exposure and white balance: real cameras never reproduce the scan's texture
            // colours (the YCB-Video mug reads 1.7x redder than its mesh)
            let gain = rng.random_range(0.6..1.7f32);
            let balance: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.8..1.25f32));
            let fc = layout.color_px();
            for ci in 0..fc {
                for cj in 0..fc {
                    // depth cell under this colour cell (top-left of its 2 x 2 block)
                    let dk = (ci * f / fc) * f + cj * f / fc;
                    for (ch, pc) in plane_color.iter().enumerate() {
                        let k = base + (ci * fc + cj) * 3 + ch;
                        if no_background && bg[dk] {
                            mask[k] = true;
                        } else if on_plane[dk] {
                            x[k] = (pc * rng.random_range(0.9..1.1f32)).min(layout.color_weight);
                        } else if clutter && bg[dk] {
                            x[k] = grey;
                        } else {
                            x[k] = (x[k] * gain * balance[ch]).min(layout.color_weight);
                        }
                    }
                }
            }
        }
    }
    if config.suppress_plane {
        crate::tracker::crop::suppress_support_plane(layout, &mut x, &mask, has_color);
    }
    crate::tracker::crop::inpaint_depth(layout, &mut x, &mut mask, has_color);
    to_chromaticity(layout, &mut x, &mask);
    (x, mask)
}

fn cache_path(dir: &Path, hash: &str, grid: RotationGrid, config: &CodebookConfig) -> PathBuf {
    let cfg = serde_json::to_string(config).unwrap_or_default();
    let mut h = Sha256::new();
    h.update(cfg.as_bytes());
    // a book with the box-centred table and one without are different files
    if config.box_table {
        h.update(b"box_table");
    }
    let ch: String = h.finalize().iter().take(6).map(|b| format!("{b:02x}")).collect();
    let short = &hash[..hash.len().min(16)];
    dir.join(format!(
        "codebook-{short}-g{}-e{ENCODER_VERSION}-{ch}.bin",
        grid.step_deg()
    ))
}

/// Writes through to a file while hashing what was written (the cache's checksum).
struct HashingWriter<W: Write> {
    inner: W,
    hasher: Sha256,
}

impl<W: Write> HashingWriter<W> {
    fn put(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.hasher.update(bytes);
        self.inner.write_all(bytes)
    }

    /// An array: its length (u64), then its values (f32), little-endian.
    fn put_f32s(&mut self, v: &[f32]) -> std::io::Result<()> {
        self.put(&(v.len() as u64).to_le_bytes())?;
        for chunk in v.chunks(16 * 1024) {
            let bytes: Vec<u8> = chunk.iter().flat_map(|x| x.to_le_bytes()).collect();
            self.put(&bytes)?;
        }
        Ok(())
    }
}

/// Reads from a file while hashing what was read; arrays go straight into their vectors, so a
/// load holds one copy of the codebook, not two.
struct HashingReader<R: Read> {
    inner: R,
    hasher: Sha256,
    /// Bytes left before the trailing checksum.
    left: u64,
}

impl<R: Read> HashingReader<R> {
    fn take(&mut self, out: &mut [u8]) -> Result<(), &'static str> {
        if out.len() as u64 > self.left {
            return Err("truncated");
        }
        self.inner.read_exact(out).map_err(|_| "truncated")?;
        self.hasher.update(&*out);
        self.left -= out.len() as u64;
        Ok(())
    }

    fn u32(&mut self) -> Result<u32, &'static str> {
        let mut b = [0u8; 4];
        self.take(&mut b)?;
        Ok(u32::from_le_bytes(b))
    }

    /// An array of exactly `expected` values (checked against the bytes left before allocating).
    /// An array of f32 read into half floats, 16,384 values at a time.
    fn f32s_as_f16(&mut self, expected: usize) -> Result<Vec<half::f16>, &'static str> {
        use half::slice::HalfFloatSliceExt;
        let mut b = [0u8; 8];
        self.take(&mut b)?;
        if u64::from_le_bytes(b) != expected as u64 {
            return Err("array size");
        }
        if (expected as u64).saturating_mul(4) > self.left {
            return Err("truncated");
        }
        let mut out = vec![half::f16::ZERO; expected];
        let mut buf = vec![0f32; 16 * 1024];
        for chunk in out.chunks_mut(16 * 1024) {
            let part = &mut buf[..chunk.len()];
            self.take(bytemuck::cast_slice_mut(part))?;
            for x in part.iter_mut() {
                *x = f32::from_bits(u32::from_le(x.to_bits()));
            }
            chunk.convert_from_f32_slice(part);
        }
        Ok(out)
    }

    fn f32s(&mut self, expected: usize) -> Result<Vec<f32>, &'static str> {
        let mut b = [0u8; 8];
        self.take(&mut b)?;
        if u64::from_le_bytes(b) != expected as u64 {
            return Err("array size");
        }
        if (expected as u64).saturating_mul(4) > self.left {
            return Err("truncated");
        }
        let mut v = vec![0f32; expected];
        self.take(bytemuck::cast_slice_mut(&mut v))?;
        for x in &mut v {
            *x = f32::from_bits(u32::from_le(x.to_bits()));
        }
        Ok(v)
    }
}

fn write_cache(path: &Path, cb: &Codebook) -> Result<(), TrackerError> {
    let header = Header {
        mesh_hash: cb.mesh_hash.clone(),
        grid_step_deg: cb.grid.step_deg(),
        encoder_version: ENCODER_VERSION,
        config: cb.config.clone(),
        diameter_m: cb.diameter_m,
        input_dim: cb.encoder.input_dim,
        code_dim: cb.encoder.code_dim,
        n_bins: cb.grid.len(),
        blocks: cb.encoder.blocks.clone(),
        box_table: cb.box_table.is_some(),
    };
    let hj = serde_json::to_vec(&header).map_err(|e| TrackerError::Config(e.to_string()))?;
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    let mut w = HashingWriter {
        inner: BufWriter::new(File::create(&tmp)?),
        hasher: Sha256::new(),
    };
    w.put(MAGIC)?;
    w.put(&FORMAT_VERSION.to_le_bytes())?;
    w.put(&(hj.len() as u32).to_le_bytes())?;
    w.put(&hj)?;
    for v in [
        &cb.encoder.mean_clean,
        &cb.encoder.mean_observed,
        &cb.encoder.pca_t,
        &cb.encoder.ridge_t,
        &cb.codes.to_f32(),
        &cb.median_depth_norm,
    ] {
        w.put_f32s(v)?;
    }
    // the box-centred table, or two empty arrays without it
    w.put_f32s(&cb.box_table.as_ref().map(|b| b.codes.to_f32()).unwrap_or_default())?;
    w.put_f32s(cb.box_table.as_ref().map_or(&[], |b| &b.median_depth_norm))?;
    let sum = w.hasher.finalize();
    w.inner.write_all(&sum)?;
    w.inner.into_inner().map_err(|e| e.into_error())?.sync_all()?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// Maximum header size in a cache file (bytes): the JSON of the configuration and blocks.
const MAX_HEADER_BYTES: usize = 1 << 20;

fn read_cache(path: &Path, hash: &str, grid: RotationGrid, config: &CodebookConfig) -> Result<Codebook, TrackerError> {
    let bad = |why: &str| TrackerError::BadCache {
        path: path.display().to_string(),
        why: why.to_string(),
    };
    let file = File::open(path)?;
    let len = file.metadata()?.len();
    if len < (MAGIC.len() + 8 + 32) as u64 {
        return Err(bad("no magic"));
    }
    let mut r = HashingReader {
        inner: BufReader::new(file),
        hasher: Sha256::new(),
        left: len - 32,
    };
    let mut magic = [0u8; 8];
    r.take(&mut magic).map_err(bad)?;
    if &magic != MAGIC {
        return Err(bad("no magic"));
    }
    if r.u32().map_err(bad)? != FORMAT_VERSION {
        return Err(bad("format version"));
    }
    let hl = r.u32().map_err(bad)? as usize;
    if hl > MAX_HEADER_BYTES {
        return Err(bad("header too large"));
    }
    let mut hj = vec![0u8; hl];
    r.take(&mut hj).map_err(|_| bad("truncated header"))?;
    let mut header: Header = serde_json::from_slice(&hj).map_err(|e| bad(&e.to_string()))?;
    header.config.box_table = header.box_table;
    if header.mesh_hash != hash
        || header.grid_step_deg != grid.step_deg()
        || header.encoder_version != ENCODER_VERSION
        || &header.config != config
        || header.n_bins != grid.len()
    {
        return Err(bad("stale key"));
    }
    let (d, k) = (header.input_dim, header.code_dim);
    if header
        .blocks
        .iter()
        .any(|b| b.input_start + b.input_len > d || b.code_start + b.code_len > k || !b.weight.is_finite())
    {
        return Err(bad("code blocks out of range"));
    }
    let box_bins = if header.box_table { header.n_bins } else { 0 };
    let sizes = [
        d,
        d,
        d.saturating_mul(k),
        d.saturating_mul(k),
        header.n_bins.saturating_mul(k),
        grid.n_viewpoints(),
        box_bins.saturating_mul(k),
        box_bins,
    ];
    // the two code tables (indices 4 and 6) go to half floats chunk by chunk: no full f32 copy
    let mut arrays = Vec::with_capacity(sizes.len());
    let mut tables = [
        Codes {
            dim: k,
            values: Vec::new(),
        },
        Codes {
            dim: k,
            values: Vec::new(),
        },
    ];
    for (i, n) in sizes.into_iter().enumerate() {
        if i == 4 || i == 6 {
            tables[usize::from(i == 6)].values = r.f32s_as_f16(n).map_err(bad)?;
            arrays.push(Vec::new());
        } else {
            arrays.push(r.f32s(n).map_err(bad)?);
        }
    }
    if r.left != 0 {
        return Err(bad("trailing bytes"));
    }
    let mut sum = [0u8; 32];
    r.inner.read_exact(&mut sum).map_err(|_| bad("truncated"))?;
    if r.hasher.finalize().as_slice() != sum {
        return Err(bad("checksum mismatch"));
    }
    let [
        mean_clean,
        mean_observed,
        pca_t,
        ridge_t,
        _,
        median_depth_norm,
        _,
        box_median_depth_norm,
    ]: [Vec<f32>; 8] = arrays.try_into().map_err(|_| bad("arrays"))?;
    let [codes, box_codes] = tables;
    if codes.values.iter().chain(&box_codes.values).any(|v| !v.is_finite()) {
        return Err(bad("non-finite codes"));
    }
    let box_table = header.box_table.then_some(BoxTable {
        codes: box_codes,
        median_depth_norm: box_median_depth_norm,
    });
    Ok(Codebook {
        grid,
        config: header.config,
        mesh_hash: header.mesh_hash,
        diameter_m: header.diameter_m,
        encoder: LinearDenoisingEncoder {
            input_dim: d,
            code_dim: k,
            mean_clean,
            mean_observed,
            pca_t,
            ridge_t,
            blocks: header.blocks,
        },
        codes,
        median_depth_norm,
        box_table,
        build_seconds: 0.0,
        from_cache: true,
    })
}

/// The GPU renderer as a view source.
pub struct RendererViews<'a> {
    renderer: &'a crate::render::Renderer,
    mesh: crate::render::MeshHandle,
}

impl<'a> RendererViews<'a> {
    pub fn new(renderer: &'a crate::render::Renderer, mesh: &Mesh) -> Result<Self, TrackerError> {
        let handle = renderer
            .upload_mesh(mesh)
            .map_err(|e| TrackerError::Render(e.to_string()))?;
        Ok(Self { renderer, mesh: handle })
    }
}

impl ViewSource for RendererViews<'_> {
    fn render(
        &self,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
    ) -> Result<Vec<(DepthImage, Option<ColorImage>)>, TrackerError> {
        let clip = crate::render::ClipRange::new(0.01, 100.0).map_err(|e| TrackerError::Render(e.to_string()))?;
        let views = self
            .renderer
            .render_views(&self.mesh, intrinsics, camera_from_object, clip)
            .map_err(|e| TrackerError::Render(e.to_string()))?;
        Ok(views.into_iter().map(|v| (v.depth, Some(v.color))).collect())
    }
}

/// Rotation of a grid viewpoint, for callers that render templates themselves.
pub fn viewpoint_pose(grid: &RotationGrid, viewpoint: usize, distance_m: f64) -> Pose {
    Pose::from_parts(
        Translation3::new(0.0, 0.0, distance_m),
        grid.viewpoint_rotation(viewpoint) * UnitQuaternion::identity(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A crop centred where [`box_centre_px`] says has the silhouette's extremes at equal
    /// distances from its centre along both of its axes, at any in-plane angle.
    #[test]
    fn a_box_centred_crop_has_the_silhouette_in_its_middle() {
        // an L of pixels off the centre of a 64 px view
        let (w, h) = (64usize, 64usize);
        let mut data = vec![0f32; w * h];
        for y in 10..40 {
            for x in 36..44 {
                data[y * w + x] = 1.0;
            }
        }
        for y in 32..40 {
            for x in 44..60 {
                data[y * w + x] = 1.0;
            }
        }
        let depth = DepthImage::new(w as u32, h as u32, data).unwrap();
        let centre = [31.5, 31.5];
        let outline = outline_offsets(&depth, centre);
        assert!(!outline.is_empty());
        assert_eq!(
            box_centre_px(&outline, centre, 0.0),
            [(36.0 + 59.0) / 2.0, (10.0 + 39.0) / 2.0]
        );
        for theta in [0.3f64, 1.0, 2.5, 4.0] {
            let c = box_centre_px(&outline, centre, theta);
            let (s, co) = theta.sin_cos();
            // the crop offset of a view pixel p about the crop centre c: M^T (p - c)
            let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
            for y in 0..h {
                for x in 0..w {
                    if depth.data_m[y * w + x] > 0.0 {
                        let u = [x as f64 - c[0], y as f64 - c[1]];
                        let o = [co * u[0] - s * u[1], s * u[0] + co * u[1]];
                        for a in 0..2 {
                            lo[a] = lo[a].min(o[a]);
                            hi[a] = hi[a].max(o[a]);
                        }
                    }
                }
            }
            for a in 0..2 {
                assert!(
                    (lo[a] + hi[a]).abs() < 1e-9,
                    "theta {theta}, axis {a}: {} to {}",
                    lo[a],
                    hi[a]
                );
            }
            // and the crop the sampler takes there has the silhouette's cells in its middle
            let layout = CodebookConfig::default().layout();
            let f = layout.feature_px;
            let (mut out, mut mask) = (vec![0f32; layout.dim()], vec![false; layout.dim()]);
            let p = CropParams {
                centre_px: c,
                side_px: 64.0,
                rotation_rad: theta,
                z_centre_m: 1.0,
                box_m: 1.0,
                zero_is_far: true,
            };
            sample_crop(&layout, &depth, None, &p, &mut out, &mut mask);
            let cells: Vec<(usize, usize)> = (0..f * f).filter(|&i| out[i] < 0.75).map(|i| (i / f, i % f)).collect();
            let span = |a: fn(&(usize, usize)) -> usize| {
                let v: Vec<usize> = cells.iter().map(a).collect();
                (v.iter().min().copied().unwrap_or(0) + v.iter().max().copied().unwrap_or(0)) as f64
            };
            for (axis, sum) in [("rows", span(|c| c.0)), ("columns", span(|c| c.1))] {
                assert!(
                    (sum - (f - 1) as f64).abs() <= 2.0,
                    "theta {theta}: the {axis} span {sum} of {}",
                    f - 1
                );
            }
        }
    }

    #[test]
    fn gathered_rows_are_the_rows_one_by_one() {
        // every half float that is not a NaN, in rows of widths with and without a remainder
        let all: Vec<half::f16> = (0..=u16::MAX)
            .map(half::f16::from_bits)
            .filter(|v| !v.is_nan())
            .collect();
        for dim in [16, 24, 40, 7] {
            let n = all.len() / dim;
            let codes = Codes {
                dim,
                values: all[..n * dim].to_vec(),
            };
            let rows: Vec<u32> = (0..n as u32).rev().step_by(3).collect();
            let mut got = vec![0f32; rows.len() * dim];
            codes.rows_into(&rows, &mut got);
            let mut want = vec![0f32; dim];
            for (g, r) in got.chunks(dim).zip(&rows) {
                codes.row_into(*r as usize, &mut want);
                assert!(
                    g.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()),
                    "dim {dim}, row {r}"
                );
            }
        }
    }
}
