//! Rendering throughput: batched 64x64 depth views of a 5,000-triangle mesh (codebooks) and a
//! 640x480 scene. Run: `WGPU_BACKEND=vulkan cargo bench --bench render`.
//!
//! Besides wall-clock time, the views are also measured in CPU time of the whole process (all
//! threads, including the software rasteriser's), which does not depend on how busy the machine
//! is: on a software adapter, views per CPU-second is about the views per second one otherwise
//! idle core gives.

use criterion::measurement::{Measurement, ValueFormatter};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use nalgebra::{Isometry3, Translation3};
use pregrasp::camera::Intrinsics;
use pregrasp::geometry::{Pose, RotationGrid};
use pregrasp::mesh::Mesh;
use pregrasp::render::{ClipRange, Renderer, SceneObject};
use std::hint::black_box;

/// An ellipsoid of `stacks` x `slices` quads (2 triangles each), about 20 cm across.
fn ellipsoid(stacks: u32, slices: u32) -> Mesh {
    let mut vertices = Vec::new();
    let mut colors = Vec::new();
    for i in 0..=stacks {
        let phi = std::f32::consts::PI * i as f32 / stacks as f32;
        for j in 0..slices {
            let theta = 2.0 * std::f32::consts::PI * j as f32 / slices as f32;
            vertices.push([
                0.10 * phi.sin() * theta.cos(),
                0.06 * phi.sin() * theta.sin(),
                0.08 * phi.cos(),
            ]);
            colors.push([(40 + i * 4) as u8, (200 - j * 3) as u8, 120]);
        }
    }
    let mut triangles = Vec::new();
    for i in 0..stacks {
        for j in 0..slices {
            let a = i * slices + j;
            let b = i * slices + (j + 1) % slices;
            let c = a + slices;
            let d = b + slices;
            triangles.push([a, b, d]);
            triangles.push([a, d, c]);
        }
    }
    Mesh::new(vertices, Some(colors), triangles).expect("valid ellipsoid")
}

fn poses(n: usize) -> Vec<Pose> {
    let grid = RotationGrid::new(5).expect("grid");
    let stride = grid.len() / n;
    (0..n)
        .map(|i| Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.5), grid.rotation(grid.unflat(i * stride))))
        .collect()
}

fn renderer() -> Renderer {
    let renderer = Renderer::new().expect("a graphics adapter (install mesa-vulkan-drivers without a GPU)");
    eprintln!(
        "adapter: {} (software: {})",
        renderer.adapter_name(),
        renderer.is_software()
    );
    renderer
}

/// Batched 64x64 views of a 5,000-triangle mesh, one atlas per iteration.
fn bench_views<M: Measurement>(c: &mut Criterion<M>, group: &str) {
    let renderer = renderer();
    let mesh_5k = ellipsoid(50, 50);
    assert_eq!(mesh_5k.triangles.len(), 5000);
    let mesh = renderer.upload_mesh(&mesh_5k).expect("upload");
    assert!(mesh.culls_back_faces());
    let clip = ClipRange::new(0.05, 5.0).expect("clip");
    let k64 = Intrinsics::from_focal(64, 64, 100.0).expect("intrinsics");
    let n = renderer.views_per_atlas(64, 64);
    let views = poses(n);

    let mut g = c.benchmark_group(group);
    g.sample_size(10);
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function(format!("depth_{n}_views"), |b| {
        b.iter(|| black_box(renderer.render_view_depths(&mesh, &k64, &views, clip).expect("render")))
    });
    g.bench_function(format!("depth_color_{n}_views"), |b| {
        b.iter(|| black_box(renderer.render_views(&mesh, &k64, &views, clip).expect("render")))
    });
    g.finish();
}

fn bench_views_wall(c: &mut Criterion) {
    bench_views(c, "views_64x64_5k_triangles");
}

fn bench_views_cpu(c: &mut Criterion<ProcessCpuTime>) {
    bench_views(c, "views_64x64_5k_triangles_cpu_time");
}

/// A 640x480 scene of three 5,000-triangle objects: depth, colour and instance mask.
fn bench_scene(c: &mut Criterion) {
    let renderer = renderer();
    let mesh = renderer.upload_mesh(&ellipsoid(50, 50)).expect("upload");
    let clip = ClipRange::new(0.05, 5.0).expect("clip");
    let k640 = Intrinsics::from_focal(640, 480, 615.0).expect("intrinsics");
    let objects: Vec<SceneObject> = (0..3)
        .map(|i| SceneObject {
            mesh: mesh.clone(),
            world_from_object: Isometry3::translation(-0.25 + 0.25 * i as f64, 0.0, 1.0 + 0.2 * i as f64),
            instance_id: i + 1,
        })
        .collect();
    let mut g = c.benchmark_group("scene_640x480");
    g.sample_size(20);
    g.throughput(Throughput::Elements(1));
    g.bench_function("3_objects_15k_triangles", |b| {
        b.iter(|| {
            black_box(
                renderer
                    .render_scene(&k640, &Pose::identity(), &objects, clip)
                    .expect("render"),
            )
        })
    });
    g.finish();
}

/// CPU time (user + system) of the whole process, all threads, from `/proc/self/stat`
/// (10 ms ticks; one iteration here takes hundreds of milliseconds).
pub struct ProcessCpuTime;

fn process_cpu_ns() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat (Linux only)");
    // Fields after the command name (which is in parentheses and may contain spaces).
    let rest = &stat[stat.rfind(')').expect("stat format") + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line, 12 and 13 after the name.
    let ticks: f64 = fields[11].parse::<f64>().expect("utime") + fields[12].parse::<f64>().expect("stime");
    ticks * 1e9 / CLOCK_TICKS_PER_S
}

/// `sysconf(_SC_CLK_TCK)` is 100 on Linux.
const CLOCK_TICKS_PER_S: f64 = 100.0;

impl Measurement for ProcessCpuTime {
    type Intermediate = f64;
    type Value = f64;
    fn start(&self) -> f64 {
        process_cpu_ns()
    }
    fn end(&self, start: f64) -> f64 {
        process_cpu_ns() - start
    }
    fn add(&self, a: &f64, b: &f64) -> f64 {
        a + b
    }
    fn zero(&self) -> f64 {
        0.0
    }
    fn to_f64(&self, v: &f64) -> f64 {
        *v
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        &CpuFormatter
    }
}

struct CpuFormatter;

impl ValueFormatter for CpuFormatter {
    fn scale_values(&self, typical_ns: f64, values: &mut [f64]) -> &'static str {
        let (factor, unit) = if typical_ns < 1e6 {
            (1e-3, "µs cpu")
        } else if typical_ns < 1e9 {
            (1e-6, "ms cpu")
        } else {
            (1e-9, "s cpu")
        };
        values.iter_mut().for_each(|v| *v *= factor);
        unit
    }

    fn scale_throughputs(&self, _typical_ns: f64, throughput: &Throughput, values: &mut [f64]) -> &'static str {
        let per_iteration = match *throughput {
            Throughput::Elements(n) | Throughput::ElementsAndBytes { elements: n, .. } => n as f64,
            Throughput::Bytes(n) | Throughput::BytesDecimal(n) => n as f64,
            Throughput::Bits(n) => n as f64,
        };
        values.iter_mut().for_each(|v| *v = per_iteration * 1e9 / *v);
        "elem/cpu-s"
    }

    fn scale_for_machines(&self, _values: &mut [f64]) -> &'static str {
        "ns cpu"
    }
}

criterion_group!(wall, bench_views_wall, bench_scene);
criterion_group! {
    name = cpu;
    config = Criterion::default().with_measurement(ProcessCpuTime);
    targets = bench_views_cpu
}
criterion_main!(wall, cpu);
