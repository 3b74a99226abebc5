//! The tracker step's kernels alone, at the paper's size (110 particles, the full 37 x 72 x 72
//! grid), each beside its plain reference: the blur, the fused update of three views, and the
//! matching of 110 codes with each code's best bin taken while each chunk is in cache (against
//! the GEMM in chunks followed by a separate max pass); and the support prior's factors of a
//! step's matched bins.
//!
//! Run: `cargo bench --bench kernels -- --noplot`. Random data: no codebook or renderer needed.

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use nalgebra::{DMatrixView, DMatrixViewMut, UnitQuaternion};
use pregrasp::geometry::RotationGrid;
use pregrasp::tracker::bins::{GridTables, blur, blur_reference, gaussian_kernel, match_best};
use pregrasp::tracker::observation::fuse::{FusedView, fuse_update};
use pregrasp::tracker::observation::{ViewEvidence, add_loglik};
use pregrasp::tracker::support::{RestingFaces, SupportConfig, SupportPrior};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use std::hint::black_box;

const N: usize = 110;

fn random(len: usize, rng: &mut impl Rng) -> Vec<f32> {
    (0..len).map(|_| rng.random::<f32>()).collect()
}

fn evidence(nb: usize, rng: &mut impl Rng) -> ViewEvidence {
    ViewEvidence {
        sim: (0..nb * N).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect(),
        inv_best: vec![1.0 / 0.95; N],
        k: -0.5 / (0.06f32 * 0.06),
        floor: -12.0,
        depth_log: vec![0.0; N],
        best_similarity: 0.95,
        valid: vec![true; N],
        crops_s: 0.0,
        encoding_s: 0.0,
        matching_s: 0.0,
        likelihoods_s: 0.0,
    }
}

fn kernels(c: &mut Criterion) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let grid = RotationGrid::full();
    let nb = grid.len();
    let tables = GridTables::new(grid);
    let mut g = c.benchmark_group("kernels");
    g.sample_size(10);

    let kernel = gaussian_kernel(2, 1.0);
    let mut h = random(nb * N, &mut rng);
    let mut scratch = vec![0f32; nb * N];
    g.bench_function("blur_110p_full_grid", |b| {
        b.iter(|| {
            blur(&grid, &mut h, N, &kernel, &mut scratch);
            black_box(h[0])
        })
    });
    g.bench_function("blur_reference_110p_full_grid", |b| {
        b.iter(|| {
            blur_reference(&grid, &mut h, N, &kernel, &mut scratch);
            black_box(h[0])
        })
    });

    let views = [evidence(nb, &mut rng), evidence(nb, &mut rng), evidence(nb, &mut rng)];
    let map1 = tables.pull_map(&UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1));
    let map2 = tables.pull_map(&UnitQuaternion::from_euler_angles(-1.0, 0.4, 0.2));
    let fused_views: Vec<FusedView> = vec![(&views[0], None), (&views[1], Some(&map1)), (&views[2], Some(&map2))];
    let fmax = vec![0f32; N];
    let h0 = random(nb * N, &mut rng);
    g.bench_function("fuse_update_3views_110p_full_grid", |b| {
        b.iter_batched_ref(
            || h0.clone(),
            |h| black_box(fuse_update(h, &fused_views, N, &tables, 1e-3, &fmax)),
            BatchSize::LargeInput,
        )
    });
    // the previous update: one add_loglik per view into a fused array, then one pass
    let mut fused = vec![0f32; nb * N];
    g.bench_function("fuse_update_reference_3views_110p_full_grid", |b| {
        b.iter_batched_ref(
            || h0.clone(),
            |h| {
                for (v, (ev, map)) in fused_views.iter().enumerate() {
                    add_loglik(&mut fused, ev, *map, N, v == 0);
                }
                let sums: Vec<f32> = h
                    .par_chunks_mut(N * 1024)
                    .zip(fused.par_chunks(N * 1024))
                    .map(|(hc, fc)| {
                        let mut acc = vec![0f32; N];
                        for (hr, fr) in hc.chunks_mut(N).zip(fc.chunks(N)) {
                            for ((h, f), a) in hr.iter_mut().zip(fr).zip(acc.iter_mut()) {
                                *h = h.max(1e-9) * pregrasp::tracker::bins::fast_exp(*f);
                                *a += *h;
                            }
                        }
                        acc
                    })
                    .reduce(|| vec![0f32; N], |a, b| a.iter().zip(&b).map(|(x, y)| x + y).collect());
                black_box(sums)
            },
            BatchSize::LargeInput,
        )
    });
    drop(fused);

    let kd = 128;
    let book = random(nb * kd, &mut rng);
    let codes = random(N * kd, &mut rng);
    let mut out = Vec::new();
    g.bench_function("match_best_110_by_191808", |b| {
        b.iter(|| black_box(match_best(&codes, &book, N, kd, &mut out)))
    });
    g.bench_function("match_nalgebra_then_max_110_by_191808", |b| {
        b.iter(|| {
            out.resize(nb * N, 0.0);
            let qt = DMatrixView::from_slice_with_strides(&codes, N, kd, kd, 1);
            out.par_chunks_mut(4096 * N).enumerate().for_each(|(c, chunk)| {
                let b0 = c * 4096;
                let len = chunk.len() / N;
                let cv = DMatrixView::from_slice(&book[b0 * kd..(b0 + len) * kd], kd, len);
                let mut sv = DMatrixViewMut::from_slice(chunk, N, len);
                sv.gemm(1.0, &qt, &cv, 0.0);
            });
            let mx = out
                .par_chunks(N * 1024)
                .map(|chunk| {
                    let mut m = vec![f32::NEG_INFINITY; N];
                    for row in chunk.chunks(N) {
                        for (a, v) in m.iter_mut().zip(row) {
                            *a = a.max(*v);
                        }
                    }
                    m
                })
                .reduce(
                    || vec![f32::NEG_INFINITY; N],
                    |a, b| a.iter().zip(&b).map(|(x, y)| x.max(*y)).collect(),
                );
            black_box(mx)
        })
    });

    // the support prior's factors: 30,000 matched bins (a step's matched set is 7,000-50,000
    // on the full grid) of a cylinder whose hull rests on 48 side faces, its ends and its box
    let cylinder = pregrasp::mesh::builtin_cylinder(0.05, 0.14, 48, [[200, 0, 0], [0, 0, 200]]);
    let faces = RestingFaces::of_mesh(&cylinder, true).expect("cylinder");
    let prior = SupportPrior::new(&faces, &SupportConfig::default());
    let bins: Vec<u32> = (0..30_000).map(|_| rng.random_range(0..nb as u32)).collect();
    let ray = UnitQuaternion::from_euler_angles(0.2, -0.3, 0.1)
        .to_rotation_matrix()
        .into_inner();
    let down = nalgebra::Vector3::new(0.0, 0.8, 0.6);
    g.bench_function("support_factors_30000_bins_cylinder", |b| {
        b.iter(|| black_box(prior.factors(&tables, &bins, &ray, &down)))
    });
    g.finish();
}

criterion_group!(benches, kernels);
criterion_main!(benches);
