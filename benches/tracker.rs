//! One filter step of the multi-view tracker at the paper's size: 110 particles (50 from the
//! robot camera, 30 from each of two external cameras), 3 views of 640 x 480 with depth and
//! colour, the full 37 x 72 x 72 grid; per-stage times; and, in the same run, the plain f32
//! GEMM of the matching's size (330 x 128 by 128 x 191,808) for the ratio.
//!
//! Run: `WGPU_BACKEND=vulkan cargo bench --bench tracker` (the codebook is cached under
//! `target/tracker-bench-cache`; its build time is printed when it is built). Mesh:
//! `PREGRASP_BENCH_MESH` (default the YCB cracker box from the shared folder, else the
//! built-in box).

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{DMatrix, Translation3, UnitQuaternion, Vector3};
use pregrasp::camera::Intrinsics;
use pregrasp::geometry::{Pose, RotationGrid};
use pregrasp::mesh::Mesh;
use pregrasp::tracker::codebook::{CodebookConfig, CpuViews, RendererViews, ViewSource};
use pregrasp::tracker::observation::match_codes;
use pregrasp::tracker::{
    CameraFrame, CameraMount, Codebook, Detection, RobotOdometry, StageTimings, Tracker, TrackerConfig, raster,
};
use std::collections::BTreeMap;
use std::hint::black_box;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

fn shared() -> PathBuf {
    std::env::var("PREGRASP_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|_| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
}

fn mesh() -> Mesh {
    let path = std::env::var("PREGRASP_BENCH_MESH")
        .map(PathBuf::from)
        .unwrap_or_else(|_| shared().join("ycb/003_cracker_box.ply"));
    Mesh::load(&path).unwrap_or_else(|_| pregrasp::mesh::builtin("box").expect("built-in box"))
}

use pregrasp::geometry::look_at;

fn frame(
    name: &str,
    k: &Intrinsics,
    world_from_camera: &Pose,
    mesh: &Mesh,
    world_from_object: &Pose,
    table: &Mesh,
) -> CameraFrame {
    let cfw = world_from_camera.inverse();
    let img = raster::render(k, &[(mesh, cfw * world_from_object), (table, cfw)], 0.05, [40, 40, 40]);
    let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
    for y in 0..k.height {
        for x in 0..k.width {
            if img.instance[(y * k.width + x) as usize] == 1 {
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x);
                y1 = y1.max(y);
            }
        }
    }
    let detections = if x1 >= x0 && x0 != u32::MAX {
        vec![Detection {
            object: "obj".into(),
            bbox_xywh_px: [x0 as f64, y0 as f64, (x1 - x0 + 1) as f64, (y1 - y0 + 1) as f64],
            score: 1.0,
        }]
    } else {
        vec![]
    };
    CameraFrame {
        camera: name.into(),
        stamp_ns: 0,
        intrinsics: *k,
        depth: img.depth,
        color: Some(img.color),
        detections,
    }
}

fn codebook(mesh: &Mesh) -> Arc<Codebook> {
    let cache = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/tracker-bench-cache");
    let grid = RotationGrid::full();
    let cfg = CodebookConfig::default();
    let renderer = pregrasp::render::Renderer::new().ok();
    let t0 = Instant::now();
    let cb = match renderer.as_ref().and_then(|r| RendererViews::new(r, mesh).ok()) {
        Some(src) => {
            eprintln!(
                "codebook views: renderer {}",
                renderer.as_ref().map(|r| r.adapter_name()).unwrap_or_default()
            );
            Codebook::load_or_build_with(&src as &dyn ViewSource, mesh, grid, &cfg, Some(&cache))
        }
        None => {
            eprintln!("codebook views: CPU rasteriser");
            Codebook::load_or_build_with(&CpuViews(mesh), mesh, grid, &cfg, Some(&cache))
        }
    }
    .expect("codebook");
    if cb.from_cache {
        eprintln!("codebook loaded from cache in {:.2} s", t0.elapsed().as_secs_f64());
    } else {
        eprintln!(
            "codebook BUILT in {:.2} s ({} bins, {} triangles)",
            cb.build_seconds,
            cb.n_bins(),
            mesh.triangles.len()
        );
    }
    Arc::new(cb)
}

fn coarse_build_times(mesh: &Mesh) {
    let grid = RotationGrid::new(10).expect("10 divides 180");
    for (name, cfg) in [
        ("default features", CodebookConfig::default()),
        ("coarse features", CodebookConfig::coarse()),
    ] {
        let t0 = Instant::now();
        let renderer = pregrasp::render::Renderer::new().ok();
        let cb = match renderer.as_ref().and_then(|r| RendererViews::new(r, mesh).ok()) {
            Some(src) => Codebook::build(&src, mesh, grid, &cfg),
            None => Codebook::build(&CpuViews(mesh), mesh, grid, &cfg),
        }
        .expect("coarse codebook");
        eprintln!(
            "codebook 10-degree grid, {name}: {} bins built in {:.2} s (wall incl. renderer start {:.2} s)",
            cb.n_bins(),
            cb.build_seconds,
            t0.elapsed().as_secs_f64()
        );
    }
}

fn setup() -> (Tracker, Vec<CameraFrame>, RobotOdometry, Arc<Codebook>) {
    let mesh = mesh();
    if std::env::var("PREGRASP_BENCH_SKIP_COARSE").is_err() {
        coarse_build_times(&mesh);
    }
    let cb = codebook(&mesh);
    let mut table = pregrasp::mesh::builtin_box([4.0, 4.0, 0.02], [[120, 100, 80], [120, 100, 80]]);
    for v in &mut table.vertices_m {
        v[2] -= 0.01;
    }
    let b = mesh.bounds();
    let world_from_object = Pose::from_parts(
        Translation3::new(0.0, 0.0, -b.min_m.z),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7),
    );
    let k = Intrinsics::from_focal(640, 480, 525.0).expect("intrinsics");
    let base_from_camera = look_at([0.0, 0.0, 1.0], [1.0, 0.0, 0.4]);
    let odom_from_base = Pose::from_parts(Translation3::new(-1.5, 0.1, 0.0), UnitQuaternion::identity());
    let robot = odom_from_base * base_from_camera;
    let ext1 = look_at([0.8, -2.6, 1.6], [0.0, 0.0, 0.1]);
    let ext2 = look_at([0.9, 2.5, 1.5], [0.0, 0.0, 0.1]);
    let mut cams = BTreeMap::new();
    cams.insert("robot".to_string(), CameraMount::Robot { base_from_camera });
    cams.insert(
        "ext1".to_string(),
        CameraMount::Stationary {
            world_from_camera: ext1,
        },
    );
    cams.insert(
        "ext2".to_string(),
        CameraMount::Stationary {
            world_from_camera: ext2,
        },
    );
    let mut tracker = Tracker::new(TrackerConfig::default(), cams, "robot".into());
    tracker.add_object_model("obj", mesh.clone(), cb.clone());
    let frames = vec![
        frame("robot", &k, &robot, &mesh, &world_from_object, &table),
        frame("ext1", &k, &ext1, &mesh, &world_from_object, &table),
        frame("ext2", &k, &ext2, &mesh, &world_from_object, &table),
    ];
    let odo = RobotOdometry {
        stamp_ns: 0,
        odom_from_base,
        world_from_odom: Pose::identity(),
        base_from_camera,
    };
    tracker.step(&frames, Some(&odo)).expect("first step");
    let n: usize = tracker.particles(tracker.tracks()[0].id).map(|p| p.len()).unwrap_or(0);
    eprintln!("tracks {}, particles {n}", tracker.tracks().len());
    let quiet: Vec<CameraFrame> = frames
        .into_iter()
        .map(|f| CameraFrame {
            detections: vec![],
            ..f
        })
        .collect();
    let truth = robot.inverse() * world_from_object;
    for _ in 0..3 {
        tracker.step(&quiet, Some(&odo)).expect("step");
    }
    let e = tracker.estimate(tracker.tracks()[0].id).expect("estimate");
    eprintln!(
        "after 4 steps: translation error {:.3} m, rotation error {:.1} deg, std {:.3} m",
        (e.reference_from_object.translation.vector - truth.translation.vector).norm(),
        e.reference_from_object.rotation.angle_to(&truth.rotation).to_degrees(),
        e.translation_std_m
    );
    (tracker, quiet, odo, cb)
}

fn stages(tracker: &mut Tracker, frames: &[CameraFrame], odo: &RobotOdometry) {
    let n = 5;
    let mut sum = StageTimings::default();
    for _ in 0..n {
        let t = tracker.step(frames, Some(odo)).expect("step").timings;
        sum.motion_s += t.motion_s;
        sum.crops_s += t.crops_s;
        sum.encoding_s += t.encoding_s;
        sum.matching_s += t.matching_s;
        sum.likelihoods_s += t.likelihoods_s;
        sum.fusion_s += t.fusion_s;
        sum.blur_s += t.blur_s;
        sum.resampling_s += t.resampling_s;
        sum.estimates_s += t.estimates_s;
        sum.total_s += t.total_s;
    }
    let ms = |v: f64| v / n as f64 * 1e3;
    eprintln!(
        "stage means over {n} steps (ms): motion {:.1}, crops {:.1}, encoding {:.1}, matching {:.1}, likelihoods {:.1}, fusion {:.1}, blur {:.1}, resampling {:.1}, estimates {:.1}, total {:.1}",
        ms(sum.motion_s),
        ms(sum.crops_s),
        ms(sum.encoding_s),
        ms(sum.matching_s),
        ms(sum.likelihoods_s),
        ms(sum.fusion_s),
        ms(sum.blur_s),
        ms(sum.resampling_s),
        ms(sum.estimates_s),
        ms(sum.total_s)
    );
}

/// Peak resident memory of this process so far (Linux `VmHWM`), MB.
fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<f64>().ok()))
        })
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

fn bench(c: &mut Criterion) {
    let (mut tracker, frames, odo, cb) = setup();
    stages(&mut tracker, &frames, &odo);
    let mut g = c.benchmark_group("tracker");
    g.sample_size(10);
    g.bench_function("filter_step_110p_3views_640x480_full_grid", |b| {
        b.iter(|| black_box(tracker.step(&frames, Some(&odo)).expect("step")))
    });
    eprintln!(
        "peak RSS while tracking (before the GEMM comparison allocates its 253 MB outputs): {:.0} MB",
        peak_rss_mb()
    );
    // the matching's GEMM alone: 330 unit codes against the whole codebook, chunked over threads
    let k = cb.code_dim();
    let mut codes: Vec<f32> = (0..330 * k)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    pregrasp::tracker::encoder::normalise_rows(&mut codes, k);
    let mut out = Vec::new();
    g.bench_function("gemm_330x128_by_128x191808_chunked", |b| {
        b.iter(|| {
            match_codes(&cb, &codes, 330, &mut out);
            black_box(out.len())
        })
    });
    // one plain matrixmultiply call (one thread)
    let q = DMatrix::<f32>::from_row_slice(330, k, &codes);
    let cm = DMatrix::<f32>::from_column_slice(k, cb.n_bins(), &cb.codes);
    let mut s = DMatrix::<f32>::zeros(330, cb.n_bins());
    g.bench_function("gemm_330x128_by_128x191808_plain_one_call", |b| {
        b.iter(|| {
            s.gemm(1.0, &q, &cm, 0.0);
            black_box(s[(0, 0)])
        })
    });
    g.finish();
}

fn bench_and_report(c: &mut Criterion) {
    bench(c);
}

criterion_group!(benches, bench_and_report);
criterion_main!(benches);
