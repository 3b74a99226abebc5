//! A decision with 1,000 samples against a YCB mesh of ~4,500-4,800 triangles (convex hull),
//! on one core. Target: <= 25 ms median.
//!
//! `cargo bench --bench grasp`

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use pregrasp::geometry::{Pose, PoseSamples};
use pregrasp::grasp::{DecisionQuery, Grasp, GraspObject, Gripper, SupportPlane, decide};
use pregrasp::mesh::Mesh;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::hint::black_box;
use std::path::{Path, PathBuf};

fn shared() -> PathBuf {
    match std::env::var("PREGRASP_SHARED") {
        Ok(p) => PathBuf::from(p),
        Err(_) => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared"),
    }
}

fn samples(estimate: &Pose, n: usize) -> PoseSamples {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let std = Normal::new(0.0, 1.0).expect("unit normal");
    let poses = (0..n)
        .map(|_| {
            let t = Vector3::from_fn(|_, _| std.sample(&mut rng) * 0.01);
            let r = Vector3::from_fn(|_, _| std.sample(&mut rng) * 0.05);
            Pose::from_parts(
                Translation3::from(estimate.translation.vector + t),
                UnitQuaternion::from_scaled_axis(r) * estimate.rotation,
            )
        })
        .collect();
    PoseSamples {
        poses,
        effective_sample_size: n as f64,
    }
}

fn bench(c: &mut Criterion) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("one-thread pool");
    let gripper = Gripper::default_parallel_jaw();
    for name in ["002_master_chef_can", "035_power_drill"] {
        let mesh = Mesh::load(&shared().join("ycb").join(format!("{name}.ply"))).expect("YCB mesh");
        let object = GraspObject::new(&mesh).expect("solid");
        let (lo, _) = object.extent_along(&Vector3::z());
        let estimate = Pose::from_parts(Translation3::new(0.6, 0.1, -lo), UnitQuaternion::identity());
        let s = samples(&estimate, 1000);
        let grasp = Grasp::new(&object, &-Vector3::z(), &Vector3::x(), 0.03, "top").expect("grasp");
        let query = DecisionQuery {
            n_samples: 1000,
            threshold: 0.9,
            grasp: Some(grasp),
            support_plane: Some(SupportPlane {
                normal: [0.0, 0.0, 1.0],
                point_m: [0.0, 0.0, 0.0],
            }),
        };
        let label = format!(
            "decide_1000_samples_{name}_{}tri_{:?}_{}parts",
            mesh.triangles.len(),
            object.kind(),
            object.n_parts()
        );
        c.bench_function(&label, |b| {
            b.iter(|| pool.install(|| decide(&object, &gripper, &estimate, black_box(&s), &query).expect("decision")))
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
