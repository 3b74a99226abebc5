//! A decision with 1,000 samples against a YCB mesh of ~4,500-4,800 triangles (convex hull),
//! on one core. Target: <= 25 ms median. Also the whole choice among the generated candidates
//! (the service's default, no grasp given) on the mug, and the one-time search that places the
//! mug's candidates where they keep their margin (`grasp::placement`).
//!
//! `cargo bench --bench grasp`
//!
//! Two groups: `wall` (criterion's default clock) and `cpu` (CPU time of the process, summed
//! over its threads from /proc/self/task/*/schedstat, in ns): on a machine shared with other
//! builds the wall clock mostly measures the queue for the cores.

use criterion::measurement::{Measurement, ValueFormatter};
use criterion::{BenchmarkGroup, Criterion, Throughput, criterion_group, criterion_main};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use pregrasp::geometry::{Pose, PoseSamples};
use pregrasp::grasp::{DecisionQuery, Grasp, GraspObject, Gripper, SupportPlane, decide, search_placements};
use pregrasp::mesh::Mesh;
use std::hint::black_box;
use std::path::{Path, PathBuf};

fn shared() -> PathBuf {
    match std::env::var("PREGRASP_SHARED") {
        Ok(p) => PathBuf::from(p),
        Err(_) => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared"),
    }
}

/// CPU time of this process (all threads), ns; 0 where /proc is missing.
fn process_cpu_ns() -> u64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0;
    };
    dir.filter_map(|e| e.ok())
        .filter_map(|e| std::fs::read_to_string(e.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next().and_then(|v| v.parse::<u64>().ok()))
        .sum()
}

struct ProcessCpuTime;

struct NsFormatter;

impl ValueFormatter for NsFormatter {
    fn scale_values(&self, typical_ns: f64, values: &mut [f64]) -> &'static str {
        let (factor, unit) = if typical_ns < 1e3 {
            (1.0, "ns cpu")
        } else if typical_ns < 1e6 {
            (1e-3, "µs cpu")
        } else if typical_ns < 1e9 {
            (1e-6, "ms cpu")
        } else {
            (1e-9, "s cpu")
        };
        for v in values {
            *v *= factor;
        }
        unit
    }
    fn scale_throughputs(&self, _typical: f64, _throughput: &Throughput, _values: &mut [f64]) -> &'static str {
        "n/a"
    }
    fn scale_for_machines(&self, _values: &mut [f64]) -> &'static str {
        "ns"
    }
}

impl Measurement for ProcessCpuTime {
    type Intermediate = u64;
    type Value = u64;
    fn start(&self) -> u64 {
        process_cpu_ns()
    }
    fn end(&self, i: u64) -> u64 {
        process_cpu_ns().saturating_sub(i)
    }
    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }
    fn zero(&self) -> u64 {
        0
    }
    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        &NsFormatter
    }
}

fn bench_wall(c: &mut Criterion) {
    let mut g = c.benchmark_group("wall");
    bench(&mut g);
    g.finish();
}

fn bench_cpu(c: &mut Criterion<ProcessCpuTime>) {
    let mut g = c.benchmark_group("cpu");
    bench(&mut g);
    g.finish();
}

fn bench<M: Measurement>(c: &mut BenchmarkGroup<'_, M>) {
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
        let s = PoseSamples::gaussian(&estimate, [0.01; 3], [0.05; 3], 1000, 1);
        let grasp = Grasp::new(&object, &-Vector3::z(), &Vector3::x(), 0.03, "top").expect("grasp");
        let query = DecisionQuery {
            n_samples: 1000,
            threshold: 0.9,
            grasp: Some(grasp),
            support_plane: Some(SupportPlane {
                normal: [0.0, 0.0, 1.0],
                point_m: [0.0, 0.0, 0.0],
            }),
            translation_std_m: None,
            reference_sees: true,
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
    // the whole choice: every candidate screened on 200 samples, the best three evaluated on
    // all of them (the mug 3 mm off)
    let mesh = Mesh::load(&shared().join("ycb").join("025_mug.ply")).expect("YCB mesh");
    let object = GraspObject::new(&mesh).expect("solid");
    let (lo, _) = object.extent_along(&Vector3::z());
    let estimate = Pose::from_parts(Translation3::new(0.6, 0.1, -lo), UnitQuaternion::identity());
    let s = PoseSamples::gaussian(&estimate, [0.003; 3], [0.0; 3], 1000, 1);
    let query = DecisionQuery {
        n_samples: 1000,
        threshold: 0.9,
        grasp: None,
        support_plane: Some(SupportPlane {
            normal: [0.0, 0.0, 1.0],
            point_m: [0.0, 0.0, 0.0],
        }),
        translation_std_m: None,
        reference_sees: true,
    };
    c.bench_function("choose_among_candidates_1000_samples_025_mug", |b| {
        b.iter(|| pool.install(|| decide(&object, &gripper, &estimate, black_box(&s), &query).expect("decision")))
    });
    // the one-time search that places the candidates (cached per solid and gripper after it)
    c.bench_function("place_candidates_025_mug", |b| {
        b.iter(|| pool.install(|| search_placements(black_box(&object), &gripper).expect("placements")))
    });
}

criterion_group! {
    name = wall;
    config = Criterion::default().sample_size(20);
    targets = bench_wall
}
criterion_group! {
    name = cpu;
    config = Criterion::default().with_measurement(ProcessCpuTime).sample_size(20);
    targets = bench_cpu
}
criterion_main!(wall, cpu);
