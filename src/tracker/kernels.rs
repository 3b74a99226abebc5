//! The step's hot kernels over bin-major histograms (see [`crate::tracker::bins`] for the
//! layout): the matching GEMM, the separable wrap-around blur, a branch-free `exp`, the pull
//! gathers, and the run-time SIMD dispatch they run under. Each has a unit test against its
//! plain version.

use crate::geometry::RotationGrid;
use nalgebra::{DMatrixView, DMatrixViewMut};
use rayon::prelude::*;

/// `dst[b * m + p] = sum_k lhs[p * kd + k] * rhs[b * kd + k]` for `p < m`, `b < n`: the
/// similarities of `m` codes (rows of `lhs`) with `n` codebook codes (rows of `rhs`), written
/// bin-major. One thread (callers split the bins over threads). nalgebra's GEMM
/// (`matrixmultiply`) picks its kernel at run time: AVX-512 where the CPU has it, which the
/// `gemm` crate (without its `x86-v4` feature) does not use.
pub fn gemm_nt(dst: &mut [f32], lhs: &[f32], rhs: &[f32], m: usize, n: usize, kd: usize) {
    assert_eq!(dst.len(), m * n, "dst size");
    assert_eq!(lhs.len(), m * kd, "lhs size");
    assert_eq!(rhs.len(), n * kd, "rhs size");
    if m == 0 || n == 0 {
        return;
    }
    // nalgebra hands products with a side of at most 5 to a generic path that mis-indexes
    // strided views; such small products take the plain loop
    if m <= 8 || n <= 8 || kd <= 8 {
        for (b, row) in dst.chunks_mut(m).enumerate() {
            let c = &rhs[b * kd..(b + 1) * kd];
            for (p, d) in row.iter_mut().enumerate() {
                *d = lhs[p * kd..(p + 1) * kd].iter().zip(c).map(|(x, y)| x * y).sum();
            }
        }
        return;
    }
    let q = DMatrixView::from_slice_with_strides(lhs, m, kd, kd, 1);
    let c = DMatrixView::from_slice(rhs, kd, n);
    let mut s = DMatrixViewMut::from_slice(dst, m, n);
    s.gemm(1.0, &q, &c, 0.0);
}

/// Bins per matching task: the task's similarities (`n x 1,024` f32, 450 kB for 110
/// particles) are still in cache when its best values are taken.
const MATCH_CHUNK_BINS: usize = 1024;

/// Cosine similarities of `n` codes (row-major `n x kd`) with every code of `book` (row-major
/// `bins x kd`) into `out` (bin-major: `out[b * n + p]`, resized), chunked over all threads;
/// returns each particle's best similarity and the lowest bin that reaches it (`u32::MAX`
/// when none does, e.g. NaN codes).
pub fn match_best(codes: &[f32], book: &[f32], n: usize, kd: usize, out: &mut Vec<f32>) -> (Vec<f32>, Vec<u32>) {
    let nb = book.len().checked_div(kd).unwrap_or(0);
    out.resize(nb * n, 0.0);
    if n == 0 || nb == 0 {
        return (vec![f32::NEG_INFINITY; n], vec![u32::MAX; n]);
    }
    out.par_chunks_mut(MATCH_CHUNK_BINS * n)
        .enumerate()
        .map(|(c, chunk)| {
            let b0 = c * MATCH_CHUNK_BINS;
            let len = chunk.len() / n;
            gemm_nt(chunk, codes, &book[b0 * kd..(b0 + len) * kd], n, len, kd);
            let mut m = vec![f32::NEG_INFINITY; n];
            let mut a = vec![u32::MAX; n];
            with_wide_simd(
                #[inline(always)]
                || {
                    for (r, row) in chunk.chunks(n).enumerate() {
                        let b = (b0 + r) as u32;
                        for ((mi, ai), v) in m.iter_mut().zip(a.iter_mut()).zip(row) {
                            // strict: the lowest bin wins a tie
                            let better = *v > *mi;
                            *ai = if better { b } else { *ai };
                            *mi = if better { *v } else { *mi };
                        }
                    }
                },
            );
            (m, a)
        })
        .reduce(
            || (vec![f32::NEG_INFINITY; n], vec![u32::MAX; n]),
            |(mut m0, mut a0), (m1, a1)| {
                for p in 0..n {
                    if m1[p] > m0[p] || (m1[p] == m0[p] && a1[p] < a0[p]) {
                        m0[p] = m1[p];
                        a0[p] = a1[p];
                    }
                }
                (m0, a0)
            },
        )
}

/// A normalised 1-D Gaussian kernel of `2 * radius + 1` taps.
pub fn gaussian_kernel(radius: usize, sigma_bins: f64) -> Vec<f32> {
    let mut k: Vec<f64> = (0..=2 * radius)
        .map(|i| {
            let x = i as f64 - radius as f64;
            (-0.5 * x * x / (sigma_bins * sigma_bins).max(1e-12)).exp()
        })
        .collect();
    let s: f64 = k.iter().sum();
    for v in &mut k {
        *v /= s;
    }
    k.into_iter().map(|v| v as f32).collect()
}

/// Lanes of the blur's register accumulators.
const BLUR_LANES: usize = 16;

/// `dst[i] = sum_t w[t] * src[offsets[t] + i]`, accumulated in tap order from 0 (the same
/// rounding as adding one tap at a time), with the running sums in registers. `dst` must not
/// overlap `src`: the last block is aligned to the end of `dst` and may recompute (identically)
/// values of the block before it, so that no element takes a scalar path.
#[inline(always)]
fn weighted_rows(dst: &mut [f32], src: &[f32], offsets: &[usize], w: &[f32]) {
    let len = dst.len();
    if len < BLUR_LANES {
        for (j, d) in dst.iter_mut().enumerate() {
            let mut a = 0f32;
            for (&o, &wt) in offsets.iter().zip(w) {
                a += wt * src[o + j];
            }
            *d = a;
        }
        return;
    }
    let mut i = 0;
    loop {
        let mut acc = [0f32; BLUR_LANES];
        for (&o, &wt) in offsets.iter().zip(w) {
            let s = &src[o + i..o + i + BLUR_LANES];
            for (a, v) in acc.iter_mut().zip(s) {
                *a += wt * v;
            }
        }
        dst[i..i + BLUR_LANES].copy_from_slice(&acc);
        if i + BLUR_LANES == len {
            break;
        }
        i = (i + BLUR_LANES).min(len - BLUR_LANES);
    }
}

/// Runs `f` compiled for the widest SIMD instruction set the CPU has (AVX2 + FMA, or
/// AVX-512), detected at run time: the loops inlined into it vectorise to that width. The
/// arithmetic is the same (no fused multiply-adds are formed), so results are identical.
#[inline(always)]
pub fn with_wide_simd<R>(f: impl FnOnce() -> R) -> R {
    struct Op<F>(F);
    impl<R, F: FnOnce() -> R> pulp::WithSimd for Op<F> {
        type Output = R;
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) -> R {
            (self.0)()
        }
    }
    pulp::Arch::new().dispatch(Op(f))
}

std::thread_local! {
    /// Per-thread work space of [`blur`] (its ring of blurred slabs), kept between calls so
    /// that its pages are not faulted in again at every step.
    static BLUR_WORK: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Per elevation row `j`, the kernel's weight that lands on rows that exist: the elevation
/// blur divides row `j`'s taps by it, so each source row keeps its mass at the poles.
pub fn elevation_row_sums(kernel: &[f32], ne: usize) -> Vec<f32> {
    let r = (kernel.len() / 2) as isize;
    (0..ne as isize)
        .map(|j| {
            kernel
                .iter()
                .enumerate()
                .filter(|(k, _)| {
                    let e = j - (*k as isize - r);
                    e >= 0 && e < ne as isize
                })
                .map(|(_, w)| *w)
                .sum()
        })
        .collect()
}

/// Separable Gaussian blur of `n_p` histograms (bin-major layout) with `kernel`: azimuth and
/// in-plane wrap around (they are angles), elevation is truncated at the poles with the kernel
/// renormalised so that each source row keeps its mass. `scratch` is resized as needed and
/// reused between calls (the result may end up in either buffer's allocation).
///
/// One streaming sweep per block of elevation rows (a few blocks per thread): each source
/// slab (one elevation, 72 x 72 bins x `n_p`) is read once and blurred in-plane and in azimuth
/// into a ring of `taps` slabs held in cache, and each output slab is the elevation-weighted
/// sum of the ring, written once into `scratch`; the buffers then swap. The histograms thus
/// cross memory once each way (the pass-per-axis version crossed it three times), and each
/// output is summed in registers over the taps. Bitwise equal to [`blur_reference`].
pub fn blur(grid: &RotationGrid, h: &mut Vec<f32>, n_p: usize, kernel: &[f32], scratch: &mut Vec<f32>) {
    let ne = grid.n_elevation();
    let na = grid.n_azimuth();
    let ni = grid.n_inplane();
    assert_eq!(h.len(), ne * na * ni * n_p, "histogram size");
    if n_p == 0 {
        return;
    }
    let taps = kernel.len();
    let r = taps / 2;
    let row_len = ni * n_p;
    let slab = na * row_len;
    // wrap-around source offsets per output index, `taps` each
    let wrapped = |len: usize, unit: usize| -> Vec<usize> {
        (0..len)
            .flat_map(|i| {
                (0..taps).map(move |k| (i as isize + k as isize - r as isize).rem_euclid(len as isize) as usize * unit)
            })
            .collect()
    };
    let inplane_offsets = wrapped(ni, n_p);
    let azimuth_offsets = wrapped(na, row_len);
    let row_sums = elevation_row_sums(kernel, ne);
    scratch.resize(h.len(), 0.0);
    let src: &[f32] = h;
    let blocks = (rayon::current_num_threads() * 2).clamp(1, ne);
    let per = ne.div_ceil(blocks);
    scratch.par_chunks_mut(per * slab).enumerate().for_each(|(t, out)| {
        BLUR_WORK.with_borrow_mut(|work| {
            // ring of `taps` in-plane and azimuth blurred slabs, plus one slab between the two
            work.resize((taps + 1) * slab, 0.0);
            let (ring, tmp) = work.split_at_mut(taps * slab);
            let e0 = t * per;
            let e1 = (e0 + per).min(ne);
            let mut next = e0.saturating_sub(r);
            let mut offsets = Vec::with_capacity(taps);
            let mut w = Vec::with_capacity(taps);
            for e in e0..e1 {
                // source slabs up to e + r; slab j lives in slot j % taps (the slot it
                // overwrites held slab j - taps < e - r, which no output from e on reads)
                while next < (e + r + 1).min(ne) {
                    let slot = &mut ring[(next % taps) * slab..(next % taps + 1) * slab];
                    let src_slab = &src[next * slab..(next + 1) * slab];
                    with_wide_simd(
                        #[inline(always)]
                        || {
                            for (a, tmp_row) in tmp.chunks_mut(row_len).enumerate() {
                                let src_row = &src_slab[a * row_len..(a + 1) * row_len];
                                for (i, dst) in tmp_row.chunks_mut(n_p).enumerate() {
                                    weighted_rows(dst, src_row, &inplane_offsets[i * taps..(i + 1) * taps], kernel);
                                }
                            }
                            for (a, dst) in slot.chunks_mut(row_len).enumerate() {
                                weighted_rows(dst, tmp, &azimuth_offsets[a * taps..(a + 1) * taps], kernel);
                            }
                        },
                    );
                    next += 1;
                }
                offsets.clear();
                w.clear();
                for (k, &wk) in kernel.iter().enumerate() {
                    let j = e as isize + k as isize - r as isize;
                    if j < 0 || j >= ne as isize {
                        continue;
                    }
                    let j = j as usize;
                    offsets.push((j % taps) * slab);
                    w.push(wk / row_sums[j]);
                }
                let dst = &mut out[(e - e0) * slab..(e - e0 + 1) * slab];
                with_wide_simd(
                    #[inline(always)]
                    || {
                        // row by row, so that the offsets stay those of whole rows
                        for (a, dst_row) in dst.chunks_mut(row_len).enumerate() {
                            let base = a * row_len;
                            let ring_rows: &[f32] = &ring[base..];
                            weighted_rows(dst_row, ring_rows, &offsets, &w);
                        }
                    },
                );
            }
        })
    });
    std::mem::swap(h, scratch);
}

/// The straightforward blur (one tap at a time, each into memory): the reference that tests
/// and `benches/kernels.rs` compare [`blur`] with.
pub fn blur_reference(grid: &RotationGrid, h: &mut Vec<f32>, n_p: usize, kernel: &[f32], scratch: &mut Vec<f32>) {
    let ne = grid.n_elevation();
    let na = grid.n_azimuth();
    let ni = grid.n_inplane();
    assert_eq!(h.len(), ne * na * ni * n_p, "histogram size");
    let r = (kernel.len() / 2) as isize;
    let slab = na * ni * n_p;
    // in-plane and azimuth passes, one elevation slab at a time (wrap-around)
    h.par_chunks_mut(slab).for_each(|slab_h| {
        let mut tmp = slab_h.to_vec();
        // in-plane: rows of ni * n_p
        for a in 0..na {
            let row = &mut slab_h[a * ni * n_p..(a + 1) * ni * n_p];
            let src = &tmp[a * ni * n_p..(a + 1) * ni * n_p];
            for i in 0..ni {
                let dst = &mut row[i * n_p..(i + 1) * n_p];
                dst.fill(0.0);
                for (k, &w) in kernel.iter().enumerate() {
                    let j = (i as isize + k as isize - r).rem_euclid(ni as isize) as usize;
                    let s = &src[j * n_p..(j + 1) * n_p];
                    for (d, v) in dst.iter_mut().zip(s) {
                        *d += w * v;
                    }
                }
            }
        }
        tmp.copy_from_slice(slab_h);
        // azimuth: stride ni * n_p
        let row_len = ni * n_p;
        for a in 0..na {
            let dst = &mut slab_h[a * row_len..(a + 1) * row_len];
            dst.fill(0.0);
            for (k, &w) in kernel.iter().enumerate() {
                let j = (a as isize + k as isize - r).rem_euclid(na as isize) as usize;
                let s = &tmp[j * row_len..(j + 1) * row_len];
                for (d, v) in dst.iter_mut().zip(s) {
                    *d += w * v;
                }
            }
        }
    });
    // elevation pass (truncated, renormalised): from h into scratch, then swap the buffers
    scratch.resize(h.len(), 0.0);
    std::mem::swap(h, scratch);
    let src: &[f32] = scratch;
    let row_sums = elevation_row_sums(kernel, ne);
    let row_sum = |j: isize| -> f32 { row_sums[j as usize] };
    h.par_chunks_mut(slab).enumerate().for_each(|(e, dst)| {
        dst.fill(0.0);
        for (k, &w) in kernel.iter().enumerate() {
            let j = e as isize + k as isize - r;
            if j < 0 || j >= ne as isize {
                continue;
            }
            let w = w / row_sum(j);
            let s = &src[j as usize * slab..(j as usize + 1) * slab];
            for (d, v) in dst.iter_mut().zip(s) {
                *d += w * v;
            }
        }
    });
}

/// `t.floor()` for `|t| < 2^22`, with float operations only: without SSE4.1 (the default
/// x86-64 target) `floor` is a library call per lane, which kept [`fast_exp`]'s loops scalar.
#[inline(always)]
fn floor_small(t: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0; // 1.5 * 2^23: adding and subtracting it rounds to an integer
    let r = (t + ROUND) - ROUND;
    if r > t { r - 1.0 } else { r }
}

/// `exp(x)` for `x <= 0` in f32, branch-free so that loops over it vectorise (relative error
/// below 1e-5 on [-87, 0], clamped below -87). The fused update evaluates 21 million of these per
/// object and step; the library `expf` is a scalar call.
#[inline(always)]
pub fn fast_exp(x: f32) -> f32 {
    let x = x.max(-87.0);
    let t = x * std::f32::consts::LOG2_E;
    let i = floor_small(t);
    let f = t - i; // [0, 1)
    // 2^f on [0, 1): degree-6 polynomial (Taylor of e^(f ln 2) is accurate enough here)
    let l = std::f32::consts::LN_2;
    let y = f * l;
    let p = 1.0 + y * (1.0 + y * (0.5 + y * (1.0 / 6.0 + y * (1.0 / 24.0 + y * (1.0 / 120.0 + y * (1.0 / 720.0))))));
    let bits = ((i as i32 + 127).max(0) as u32) << 23;
    p * f32::from_bits(bits)
}

/// One view of the fused update: its evidence and its pull map (histogram bin `b` reads the
/// Gathers `src` (bin-major, `n_p` per bin) through a pull map and adds it into `dst`:
/// `dst[b][p] += src[map[b]][p]`.
pub fn add_pulled(dst: &mut [f32], src: &[f32], map: &[u32], n_p: usize) {
    dst.par_chunks_mut(n_p * 1024).enumerate().for_each(|(c, chunk)| {
        let b0 = c * 1024;
        for (k, row) in chunk.chunks_mut(n_p).enumerate() {
            let s = map[b0 + k] as usize * n_p;
            for (d, v) in row.iter_mut().zip(&src[s..s + n_p]) {
                *d += v;
            }
        }
    });
}

/// `dst[b][p] = src[map[b]][p]` (re-binning a prior).
pub fn pull(dst: &mut [f32], src: &[f32], map: &[u32], n_p: usize) {
    dst.par_chunks_mut(n_p * 1024).enumerate().for_each(|(c, chunk)| {
        let b0 = c * 1024;
        for (k, row) in chunk.chunks_mut(n_p).enumerate() {
            let s = map[b0 + k] as usize * n_p;
            row.copy_from_slice(&src[s..s + n_p]);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn floor_small_is_floor() {
        let mut t = -300.0f32;
        while t < 300.0 {
            assert_eq!(floor_small(t), t.floor(), "{t}");
            t += 0.000_913;
        }
        for t in [
            0.0f32,
            -1.0,
            -125.5,
            -0.5,
            0.5,
            -1e-30,
            1e-30,
            4_194_303.5,
            -4_194_303.5,
        ] {
            assert_eq!(floor_small(t), t.floor(), "{t}");
        }
    }

    #[test]
    fn fast_exp_is_accurate() {
        let mut x = -87.0f32;
        while x <= 0.0 {
            let a = fast_exp(x);
            let b = x.exp();
            assert!((a - b).abs() <= 1e-5 * b + 1e-37, "{x}: {a} vs {b}");
            x += 0.0137;
        }
        assert_eq!(fast_exp(-200.0), fast_exp(-87.0));
    }

    #[test]
    fn gemm_nt_matches_the_plain_product() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (m, n, kd) in [(7, 37, 13), (110, 300, 128), (1, 1, 1), (110, 3, 128), (9, 9, 9)] {
            let lhs: Vec<f32> = (0..m * kd).map(|_| rng.random::<f32>() - 0.5).collect();
            let rhs: Vec<f32> = (0..n * kd).map(|_| rng.random::<f32>() - 0.5).collect();
            let mut dst = vec![f32::NAN; m * n];
            gemm_nt(&mut dst, &lhs, &rhs, m, n, kd);
            for b in 0..n {
                for p in 0..m {
                    let want: f32 = (0..kd).map(|k| lhs[p * kd + k] * rhs[b * kd + k]).sum();
                    assert!((dst[b * m + p] - want).abs() < 1e-4, "{m}x{n}x{kd} at ({b},{p})");
                }
            }
        }
    }

    #[test]
    fn match_best_finds_each_particles_best_bin() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        let (n, kd, nb) = (9, 16, 2500); // more than two chunks of bins
        let mut book: Vec<f32> = (0..nb * kd).map(|_| rng.random::<f32>() - 0.5).collect();
        crate::tracker::encoder::normalise_rows(&mut book, kd);
        let mut codes: Vec<f32> = (0..n * kd).map(|_| rng.random::<f32>() - 0.5).collect();
        // particle 0 equals bin 1,700 exactly; particle 1 is all zeros (every bin ties at 0)
        codes[..kd].copy_from_slice(&book[1700 * kd..1701 * kd]);
        codes[kd..2 * kd].fill(0.0);
        crate::tracker::encoder::normalise_rows(&mut codes, kd);
        let mut out = Vec::new();
        let (mx, arg) = match_best(&codes, &book, n, kd, &mut out);
        assert_eq!(out.len(), nb * n);
        for p in 0..n {
            let (mut wm, mut wa) = (f32::NEG_INFINITY, 0);
            for b in 0..nb {
                let v = out[b * n + p];
                if v > wm {
                    (wm, wa) = (v, b);
                }
            }
            assert_eq!(mx[p], wm, "particle {p}");
            assert_eq!(arg[p] as usize, wa, "particle {p}");
        }
        assert_eq!(arg[0], 1700);
        assert!((mx[0] - 1.0).abs() < 1e-5);
        assert_eq!((arg[1], mx[1]), (0, 0.0));
    }

    #[test]
    fn blur_matches_the_straightforward_version() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(14);
        // 30 degrees: 12 azimuth rows (tasks of 6 rows); 110 particles: 6 full lanes and a tail
        for (step, n_p, radius) in [(30, 110, 2), (15, 3, 1), (45, 17, 3)] {
            let grid = RotationGrid::new(step).unwrap();
            let h0: Vec<f32> = (0..grid.len() * n_p).map(|_| rng.random::<f32>()).collect();
            let k = gaussian_kernel(radius, 1.0);
            let (mut a, mut b) = (h0.clone(), h0.clone());
            let (mut sa, mut sb) = (Vec::new(), Vec::new());
            blur(&grid, &mut a, n_p, &k, &mut sa);
            blur_reference(&grid, &mut b, n_p, &k, &mut sb);
            assert_eq!(a, b, "grid {step}, {n_p} particles, radius {radius}");
            // and again with the buffers in use
            blur(&grid, &mut a, n_p, &k, &mut sa);
            blur_reference(&grid, &mut b, n_p, &k, &mut sb);
            assert_eq!(a, b);
        }
    }

    #[test]
    fn blur_preserves_mass_and_wraps() {
        let grid = RotationGrid::new(30).unwrap();
        let n_p = 3;
        let mut h = vec![0f32; grid.len() * n_p];
        let b = grid.flat(crate::geometry::BinIndex {
            elevation: 3,
            azimuth: 0,
            inplane: 0,
        });
        h[b * n_p + 1] = 1.0;
        let k = gaussian_kernel(2, 1.0);
        let mut scratch = Vec::new();
        blur(&grid, &mut h, n_p, &k, &mut scratch);
        let mass: f32 = (0..grid.len()).map(|b| h[b * n_p + 1]).sum();
        assert!((mass - 1.0).abs() < 1e-5);
        let other: f32 = (0..grid.len()).map(|b| h[b * n_p]).sum();
        assert_eq!(other, 0.0);
        // the wrapped neighbour (azimuth n-1, in-plane n-1) received mass
        let w = grid.flat(crate::geometry::BinIndex {
            elevation: 3,
            azimuth: grid.n_azimuth() - 1,
            inplane: grid.n_inplane() - 1,
        });
        assert!(h[w * n_p + 1] > 0.01);
        let c = h[b * n_p + 1];
        assert!(
            (h[w * n_p + 1]
                - h[grid.flat(crate::geometry::BinIndex {
                    elevation: 3,
                    azimuth: 1,
                    inplane: 1
                }) * n_p
                    + 1])
                .abs()
                < 1e-6
        );
        assert!(c > h[w * n_p + 1]);
    }
}
