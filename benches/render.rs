//! Rendering throughput: batched 64x64 depth views of a 5,000-triangle mesh (codebooks) and a
//! 640x480 scene. Run: `WGPU_BACKEND=vulkan cargo bench --bench render`.

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

fn bench_render(c: &mut Criterion) {
    let renderer = Renderer::new().expect("a graphics adapter (install mesa-vulkan-drivers without a GPU)");
    eprintln!("adapter: {} (software: {})", renderer.adapter_name(), renderer.is_software());
    let mesh_5k = ellipsoid(50, 50);
    assert_eq!(mesh_5k.triangles.len(), 5000);
    let mesh = renderer.upload_mesh(&mesh_5k).expect("upload");
    let clip = ClipRange::new(0.05, 5.0).expect("clip");
    let k64 = Intrinsics::from_focal(64, 64, 100.0).expect("intrinsics");
    let n = renderer.views_per_atlas(64, 64);
    let views = poses(n);

    let mut g = c.benchmark_group("views_64x64_5k_triangles");
    g.sample_size(10);
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function(format!("depth_{n}_views"), |b| {
        b.iter(|| black_box(renderer.render_view_depths(&mesh, &k64, &views, clip).expect("render")))
    });
    g.bench_function(format!("depth_color_{n}_views"), |b| {
        b.iter(|| black_box(renderer.render_views(&mesh, &k64, &views, clip).expect("render")))
    });
    g.finish();

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
        b.iter(|| black_box(renderer.render_scene(&k640, &Pose::identity(), &objects, clip).expect("render")))
    });
    g.finish();
}

criterion_group!(benches, bench_render);
criterion_main!(benches);
