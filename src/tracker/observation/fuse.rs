//! The fused measurement update: every view's log-likelihood rows, pulled through their bin
//! maps, summed and applied to every particle's histogram in one pass over the bins (Eq. 6 and
//! the marginal of Eq. 7). It lives beside [`ViewEvidence`], whose rows it reads.

use crate::tracker::bins::GridTables;
use crate::tracker::kernels::{fast_exp, with_wide_simd};
use crate::tracker::observation::ViewEvidence;
use rayon::prelude::*;

/// view's bin `map[b]`; `None`: the identity).
pub type FusedView<'a> = (&'a ViewEvidence, Option<&'a [u32]>);

/// Bins per task of the fused passes (the per-particle sums are f32 within a chunk, f64 across).
const FUSE_CHUNK_BINS: usize = 1024;

/// The source bin of histogram bin `b` in a view.
#[inline(always)]
fn source_bin(map: Option<&[u32]>, b: usize) -> usize {
    match map {
        Some(m) => m[b] as usize,
        None => b,
    }
}

/// The fused log-likelihood of all views at histogram bin `b`, into `f` (`n` values).
#[inline(always)]
fn fused_row(views: &[FusedView], b: usize, n: usize, f: &mut [f32]) {
    for (v, (ev, map)) in views.iter().enumerate() {
        let s = source_bin(*map, b) * n;
        ev.loglik_row(&ev.sim[s..s + n], f, v == 0);
    }
}

/// Bins ahead whose similarity rows are prefetched: a pulled row lies anywhere in its view's
/// array, so without this every bin waits for its rows from memory (one bin is ~1,500
/// instructions, more than the out-of-order window, so the next rows' loads would not start).
const PREFETCH_BINS: usize = 4;

/// Asks the cache for the rows that histogram bin `b` will read.
#[inline(always)]
fn prefetch_rows(views: &[FusedView], b: usize, n: usize, n_bins: usize) {
    if b >= n_bins {
        return;
    }
    for (ev, map) in views {
        if map.is_some() {
            let s = source_bin(*map, b) * n;
            prefetch(&ev.sim[s..s + n]);
        }
    }
}

/// A hint to load `data` into the cache (no effect on results; a no-op off x86-64).
#[inline(always)]
fn prefetch(data: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        for line in data.chunks(16) {
            // SAFETY: a prefetch never faults and changes no state visible to the program; the
            // intrinsic is `unsafe` only because of its target feature, SSE, which every
            // x86-64 CPU has.
            #[allow(unsafe_code)] // the one exception (see Cargo.toml's lints)
            unsafe {
                _mm_prefetch::<_MM_HINT_T0>(line.as_ptr().cast::<i8>());
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = data;
}

/// Per particle, the largest fused log-likelihood over all bins (only needed when the sum of
/// the views' floors could leave `exp`'s range).
pub fn fused_loglik_max(views: &[FusedView], n: usize, n_bins: usize) -> Vec<f32> {
    (0..n_bins.div_ceil(FUSE_CHUNK_BINS))
        .into_par_iter()
        .map(|c| {
            with_wide_simd(
                #[inline(always)]
                || {
                    let mut m = vec![f32::NEG_INFINITY; n];
                    let mut f = vec![0f32; n];
                    for b in c * FUSE_CHUNK_BINS..((c + 1) * FUSE_CHUNK_BINS).min(n_bins) {
                        prefetch_rows(views, b + PREFETCH_BINS, n, n_bins);
                        fused_row(views, b, n, &mut f);
                        for (a, v) in m.iter_mut().zip(&f) {
                            *a = a.max(*v);
                        }
                    }
                    m
                },
            )
        })
        .reduce(
            || vec![f32::NEG_INFINITY; n],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x = x.max(y);
                }
                a
            },
        )
}

/// The measurement update of every particle's histogram by every view, in ONE pass over the
/// bins (Eq. 6 and the marginal of Eq. 7): for histogram bin `b` and particle `p`,
/// `f = sum_v ll_v(map_v[b], p)` (each view's [`ViewEvidence::loglik_row`], pulled through its
/// map), `hist[b][p] = max(hist[b][p], floor_rel * volume(b)) * exp(f - fmax[p])`. Returns
/// each particle's sum of the new histogram (f32 within 1,024-bin chunks, f64 across).
/// Same arithmetic, in the same order, as [`crate::tracker::observation::add_loglik`] per view
/// followed by one pass over the fused array, without writing or reading that array.
pub fn fuse_update(
    hist: &mut [f32],
    views: &[FusedView],
    n: usize,
    tables: &GridTables,
    floor_rel: f32,
    fmax: &[f32],
) -> Vec<f64> {
    assert_eq!(hist.len(), tables.grid.len() * n, "histogram size");
    assert_eq!(fmax.len(), n, "fmax size");
    if n == 0 {
        return Vec::new();
    }
    hist.par_chunks_mut(n * FUSE_CHUNK_BINS)
        .enumerate()
        .map(|(c, hc)| {
            with_wide_simd(
                #[inline(always)]
                || {
                    let mut acc = vec![0f32; n];
                    let mut f = vec![0f32; n];
                    let n_bins = tables.grid.len();
                    for r in 0..PREFETCH_BINS {
                        prefetch_rows(views, c * FUSE_CHUNK_BINS + r, n, n_bins);
                    }
                    for (r, hrow) in hc.chunks_mut(n).enumerate() {
                        let b = c * FUSE_CHUNK_BINS + r;
                        prefetch_rows(views, b + PREFETCH_BINS, n, n_bins);
                        fused_row(views, b, n, &mut f);
                        let floor = floor_rel * tables.volume(b) as f32;
                        for (((h, f), m), a) in hrow.iter_mut().zip(&f).zip(fmax).zip(acc.iter_mut()) {
                            let v = h.max(floor) * fast_exp(f - m);
                            *h = v;
                            *a += v;
                        }
                    }
                    acc.into_iter().map(f64::from).collect::<Vec<f64>>()
                },
            )
        })
        .reduce(
            || vec![0f64; n],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::RotationGrid;
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng};

    #[test]
    fn fused_update_matches_the_per_view_reference() {
        use crate::tracker::observation::add_loglik;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(13);
        let grid = RotationGrid::new(15).unwrap();
        let tables = GridTables::new(grid);
        let (n, nb) = (6, grid.len());
        let view = |rng: &mut rand_chacha::ChaCha8Rng, best: f32| ViewEvidence {
            sim: (0..nb * n).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect(),
            inv_best: (0..n).map(|p| if p == 2 { 0.0 } else { 1.0 / best }).collect(),
            k: -0.5 / (0.06f32 * 0.06),
            floor: -12.0,
            depth_log: vec![0.0; n],
            best_similarity: best,
            valid: vec![true; n],
            crops_s: 0.0,
            encoding_s: 0.0,
            matching_s: 0.0,
            likelihoods_s: 0.0,
        };
        let views = [view(&mut rng, 0.97), view(&mut rng, 0.99), view(&mut rng, 0.9)];
        let map1 = tables.pull_map(&UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1));
        let map2 = tables.pull_map(&UnitQuaternion::from_euler_angles(-1.0, 0.4, 0.2));
        let fused_views: Vec<FusedView> = vec![(&views[0], None), (&views[1], Some(&map1)), (&views[2], Some(&map2))];
        let prior: Vec<f32> = (0..nb * n).map(|_| rng.random::<f32>() * 1e-3).collect();
        let floor_rel = 0.2f32;
        for fmax in [vec![0f32; n], fused_loglik_max(&fused_views, n, nb)] {
            // reference: one add_loglik per view into a fused array, then one plain pass
            let mut fused = vec![0f32; nb * n];
            for (v, (ev, map)) in fused_views.iter().enumerate() {
                add_loglik(&mut fused, ev, *map, n, v == 0);
            }
            let mut want = prior.clone();
            let mut want_sums = vec![0f64; n];
            for b in 0..nb {
                let floor = floor_rel * tables.volume(b) as f32;
                for p in 0..n {
                    let h = &mut want[b * n + p];
                    *h = h.max(floor) * fast_exp(fused[b * n + p] - fmax[p]);
                    want_sums[p] += *h as f64;
                }
            }
            let mut got = prior.clone();
            let sums = fuse_update(&mut got, &fused_views, n, &tables, floor_rel, &fmax);
            assert_eq!(got, want, "the same arithmetic in the same order");
            for p in 0..n {
                assert!((sums[p] - want_sums[p]).abs() <= 1e-5 * want_sums[p], "sum {p}");
            }
        }
        // the max pass finds each particle's largest fused value
        let m = fused_loglik_max(&fused_views, n, nb);
        let mut fused = vec![0f32; nb * n];
        for (v, (ev, map)) in fused_views.iter().enumerate() {
            add_loglik(&mut fused, ev, *map, n, v == 0);
        }
        for p in 0..n {
            let want = (0..nb).map(|b| fused[b * n + p]).fold(f32::NEG_INFINITY, f32::max);
            assert_eq!(m[p], want);
        }
    }
}
