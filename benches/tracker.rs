//! One filter step of the multi-view tracker at the paper's size: 110 particles (50 from the
//! robot camera, 30 from each of two external cameras), 3 views of 640 x 480 with depth and
//! colour, the full 37 x 72 x 72 grid, the robot driving as in an approach (along an arc, 2 cm
//! and 0.5 degrees of yaw per step, there and back in reverse over 30 steps, so that every step
//! rebuilds the robot camera's bin map; the robot camera's image is rendered at each of those
//! poses, so that the track stays converged however many steps criterion runs); a converged
//! step and a first step (a new track, uniform rotation prior); per-stage times; and, in the
//! same run, the plain f32
//! GEMM of the matching's size (330 x 128 by 128 x 191,808, the `gemm` crate on all threads)
//! for the ratio. Before criterion's own runs, steps and GEMMs alternate
//! (`PREGRASP_BENCH_PAIRS`, default 9; `PREGRASP_BENCH_TRACE=1` prints every step with the
//! estimate's error) and the medians are printed: per stage, the step, the
//! GEMM, and the step / GEMM ratio of each pair (the machine's load cancels out of it).
//!
//! Run: `WGPU_BACKEND=vulkan cargo bench --bench tracker -- --noplot` (the codebook is cached
//! under `target/tracker-bench-cache`; its build time is printed when it is built;
//! `PREGRASP_BENCH_SKIP_COARSE=1` skips the 10-degree build times; `PREGRASP_BENCH_DENSE=1`
//! also times the dense reference, every bin matched and kept). Mesh:
//! `PREGRASP_BENCH_MESH` (default the YCB cracker box from the shared folder, else the
//! built-in box). The peak resident memory after four steps tracking one object is printed
//! before the reference GEMM allocates its output. `PREGRASP_BENCH_TRACKER_CONFIG` names a JSON
//! file of tracker settings over the defaults (as `eval --tracker-config`).

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
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

/// The robot's odometry at step `i` of the bench's approach: along an arc, 2 cm forward and
/// 0.5 degrees of yaw per step, there and back (in reverse) over 30 steps from `start`.
fn approach(start: &RobotOdometry, i: usize) -> RobotOdometry {
    let step = Pose::from_parts(
        Translation3::new(0.02, 0.0, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.5f64.to_radians()),
    );
    let moved = (0..approach_phase(i)).fold(Pose::identity(), |p, _| p * step);
    RobotOdometry {
        stamp_ns: start.stamp_ns + i as i64 * 100_000_000,
        odom_from_base: start.odom_from_base * moved,
        ..*start
    }
}

/// Translation (m) and rotation (degrees) error of an estimate against the truth.
fn pose_errors(estimate: &Pose, truth: &Pose) -> (f64, f64) {
    (
        (estimate.translation.vector - truth.translation.vector).norm(),
        estimate.rotation.angle_to(&truth.rotation).to_degrees(),
    )
}

/// How far (in steps of 2 cm) the robot has driven at step `i` of the approach: 0..=30.
fn approach_phase(i: usize) -> usize {
    let phase = i % 60;
    if phase < 30 { phase } else { 60 - phase }
}

/// The frames without detections at every phase of the approach (the robot camera rendered
/// at the robot's pose, the stationary cameras' frames as they are) and the object's true pose
/// in the robot camera there.
struct ApproachFrames(Vec<(Vec<CameraFrame>, Pose)>);

impl ApproachFrames {
    fn at(&self, i: usize) -> &[CameraFrame] {
        &self.0[approach_phase(i)].0
    }
    fn truth(&self, i: usize) -> &Pose {
        &self.0[approach_phase(i)].1
    }
}

/// The scene: a tracker with one converged track, the frames without detections along the
/// approach (what later steps see), the frames with them (what a first step sees), the
/// odometry of the first pose and the peak resident memory after four steps (before the
/// approach's frames are rendered).
type Setup = (
    Tracker,
    ApproachFrames,
    Vec<CameraFrame>,
    RobotOdometry,
    Arc<Codebook>,
    f64,
);

fn setup() -> Setup {
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
    let base_from_camera = base_from_robot_camera();
    let odom_from_base = Pose::from_parts(Translation3::new(-1.5, 0.1, 0.0), UnitQuaternion::identity());
    let robot = odom_from_base * base_from_camera;
    let (ext1, ext2) = (ext1(), ext2());
    let mut tracker = fresh_tracker(&cb);
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
    let quiet = |f: &CameraFrame| CameraFrame {
        detections: vec![],
        ..f.clone()
    };
    let still: Vec<CameraFrame> = frames.iter().map(quiet).collect();
    let truth = robot.inverse() * world_from_object;
    for _ in 0..3 {
        tracker.step(&still, Some(&odo)).expect("step");
    }
    let peak_rss_mb = peak_rss_mb();
    let e = tracker.estimate(tracker.tracks()[0].id).expect("estimate");
    let (dt, dr) = pose_errors(&e.reference_from_object, &truth);
    eprintln!(
        "after 4 steps: translation error {dt:.3} m, rotation error {dr:.1} deg, std {:.3} m",
        e.translation_std_m
    );
    let approach_frames = ApproachFrames(
        (0..=30)
            .map(|i| {
                let robot_i = approach(&odo, i).odom_from_base * base_from_camera;
                let fr = frame("robot", &k, &robot_i, &mesh, &world_from_object, &table);
                if std::env::var("PREGRASP_BENCH_TRACE").is_ok() {
                    eprintln!(
                        "phase {i}: robot camera sees the object at {:?}",
                        fr.detections.first().map(|d| d.bbox_xywh_px)
                    );
                }
                let mut v = vec![quiet(&fr)];
                v.extend(still[1..].iter().cloned());
                (v, robot_i.inverse() * world_from_object)
            })
            .collect(),
    );
    (tracker, approach_frames, frames, odo, cb, peak_rss_mb)
}

fn base_from_robot_camera() -> Pose {
    look_at([0.0, 0.0, 1.0], [1.0, 0.0, 0.4])
}
fn ext1() -> Pose {
    look_at([0.8, -2.6, 1.6], [0.0, 0.0, 0.1])
}
fn ext2() -> Pose {
    look_at([0.9, 2.5, 1.5], [0.0, 0.0, 0.1])
}

/// The robot camera and the two stationary ones.
fn cameras() -> BTreeMap<String, CameraMount> {
    let mut cams = BTreeMap::new();
    cams.insert(
        "robot".to_string(),
        CameraMount::Robot {
            base_from_camera: base_from_robot_camera(),
        },
    );
    cams.insert(
        "ext1".to_string(),
        CameraMount::Stationary {
            world_from_camera: ext1(),
        },
    );
    cams.insert(
        "ext2".to_string(),
        CameraMount::Stationary {
            world_from_camera: ext2(),
        },
    );
    cams
}

/// The tracker's settings: the defaults, or a JSON file of settings over them named by
/// `PREGRASP_BENCH_TRACKER_CONFIG` (as `eval --tracker-config`), to time other settings.
fn tracker_config() -> TrackerConfig {
    pregrasp::eval::cli::tracker_config_from_env("PREGRASP_BENCH_TRACKER_CONFIG").unwrap_or_else(|e| panic!("{e}"))
}

/// A tracker over the bench's cameras with the object model and no track yet.
fn fresh_tracker(cb: &Arc<Codebook>) -> Tracker {
    let mut t = Tracker::new(tracker_config(), cameras(), "robot".into());
    t.add_object_model("obj", mesh(), cb.clone());
    t
}

/// A fresh tracker with `like`'s configuration.
fn fresh_tracker_like(like: &Tracker, cb: &Arc<Codebook>) -> Tracker {
    let mut t = Tracker::new(like.config().clone(), cameras(), "robot".into());
    t.add_object_model("obj", mesh(), cb.clone());
    t
}

/// The plain f32 GEMM of the matching's size with the `gemm` crate, one call on all threads:
/// `dst (rows x bins, column-major) = codes (rows x k, row-major) * book^T`.
fn plain_gemm(dst: &mut [f32], codes: &[f32], book: &[f32], rows: usize, k: usize) {
    let bins = book.len() / k;
    assert_eq!(dst.len(), rows * bins);
    assert_eq!(codes.len(), rows * k);
    // SAFETY: the slices hold exactly the matrices the strides address (checked above) and
    // `dst` does not alias the inputs; `read_dst = false`.
    #[allow(unsafe_code)] // the reference GEMM calls the gemm crate directly
    unsafe {
        gemm::gemm(
            rows,
            bins,
            k,
            dst.as_mut_ptr(),
            rows as isize,
            1,
            false,
            codes.as_ptr(),
            1,
            k as isize,
            book.as_ptr(),
            k as isize,
            1,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::Rayon(rayon::current_num_threads()),
        );
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// Steps interleaved with the reference GEMM (330 x 128 by 128 x bins), so that both see the
/// same machine load: per-stage medians, the step's and the GEMM's medians, and the median of
/// the per-pair ratios step / GEMM.
fn stages(
    tracker: &mut Tracker,
    converged: &ApproachFrames,
    first_frames: &[CameraFrame],
    odo: &RobotOdometry,
    cb: &Arc<Codebook>,
    first: bool,
) {
    let n = std::env::var("PREGRASP_BENCH_PAIRS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(9usize);
    let k = cb.code_dim();
    let mut codes: Vec<f32> = (0..330 * k)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    pregrasp::tracker::encoder::normalise_rows(&mut codes, k);
    let book = cb.codes.to_f32();
    let mut dst = vec![0f32; 330 * cb.n_bins()];
    plain_gemm(&mut dst, &codes, &book, 330, k); // touch the pages once
    let mut all: Vec<StageTimings> = Vec::new();
    let mut bins: Vec<(f64, f64)> = Vec::new();
    let mut gemm_s = Vec::new();
    let mut ratio = Vec::new();
    for i in 0..n {
        let report = if first {
            // a new track every time: the detections spawn particles with uniform histograms
            *tracker = fresh_tracker_like(tracker, cb);
            tracker.step(first_frames, Some(odo)).expect("first step")
        } else {
            tracker
                .step(converged.at(i + 1), Some(&approach(odo, i + 1)))
                .expect("step")
        };
        bins.push((report.matched_bins as f64, report.active_bins as f64));
        let t = report.timings;
        if std::env::var("PREGRASP_BENCH_TRACE").is_ok() {
            let truth = converged.truth(i + 1);
            let (dt, dr) = tracker
                .estimate(tracker.tracks()[0].id)
                .map(|e| pose_errors(&e.reference_from_object, truth))
                .unwrap_or((f64::NAN, f64::NAN));
            eprintln!(
                "step {i} (phase {}): error {dt:.3} m {dr:.1} deg; total {:.1} ms, crops {:.1}, matching {:.1}, fusion {:.1}, matched {}, active {}",
                approach_phase(i + 1),
                t.total_s * 1e3,
                t.crops_s * 1e3,
                t.matching_s * 1e3,
                t.fusion_s * 1e3,
                report.matched_bins,
                report.active_bins
            );
        }
        let t0 = Instant::now();
        plain_gemm(&mut dst, &codes, &book, 330, k);
        let g = t0.elapsed().as_secs_f64();
        black_box(dst[0]);
        ratio.push(t.total_s / g);
        gemm_s.push(g);
        all.push(t);
    }
    let med = |f: &dyn Fn(&StageTimings) -> f64| median(&mut all.iter().map(f).collect::<Vec<f64>>()) * 1e3;
    eprintln!("{} steps:", if first { "first" } else { "converged, moving robot," });
    eprintln!(
        "stage medians over {n} steps (ms): motion {:.1}, crops {:.1}, encoding {:.1}, matching {:.1}, likelihoods {:.1}, fusion {:.1}, blur {:.1}, resampling {:.1}, estimates {:.1}, verification {:.1}, registration {:.1}, total {:.1}",
        med(&|t| t.motion_s),
        med(&|t| t.crops_s),
        med(&|t| t.encoding_s),
        med(&|t| t.matching_s),
        med(&|t| t.likelihoods_s),
        med(&|t| t.fusion_s),
        med(&|t| t.blur_s),
        med(&|t| t.resampling_s),
        med(&|t| t.estimates_s),
        med(&|t| t.verification_s),
        med(&|t| t.registration_s),
        med(&|t| t.total_s)
    );
    eprintln!(
        "matched bins per step (median) {:.0}, active bins after the step {:.0} ({} matching)",
        median(&mut bins.iter().map(|b| b.0).collect::<Vec<f64>>()),
        median(&mut bins.iter().map(|b| b.1).collect::<Vec<f64>>()),
        if tracker.config().matching.dense {
            "dense"
        } else {
            "sparse"
        }
    );
    let mut totals: Vec<f64> = all.iter().map(|t| t.total_s * 1e3).collect();
    totals.sort_by(f64::total_cmp);
    eprintln!(
        "step {:.1} ms (min {:.1}, max {:.1}); gemm crate GEMM 330x{k} by {k}x{} on {} threads {:.1} ms (min {:.1}); step / GEMM median of pairs {:.2}",
        median(&mut totals.clone()),
        totals[0],
        totals[totals.len() - 1],
        cb.n_bins(),
        rayon::current_num_threads(),
        median(&mut gemm_s.clone()) * 1e3,
        gemm_s.iter().cloned().fold(f64::INFINITY, f64::min) * 1e3,
        median(&mut ratio)
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
    let (mut tracker, along, with_detections, odo, cb, rss_mb) = setup();
    eprintln!("peak RSS after 4 steps tracking one object (codebook loaded or built in this process): {rss_mb:.0} MB");
    stages(&mut tracker, &along, &with_detections, &odo, &cb, false);
    let mut first = fresh_tracker(&cb);
    stages(&mut first, &along, &with_detections, &odo, &cb, true);
    drop(first);
    if std::env::var("PREGRASP_BENCH_DENSE").is_ok_and(|v| v == "1") {
        // the dense reference: every bin matched and kept
        let mut config = tracker.config().clone();
        config.matching.dense = true;
        let mut dense = Tracker::new(config, cameras(), "robot".into());
        dense.add_object_model("obj", mesh(), cb.clone());
        dense.step(&with_detections, Some(&odo)).expect("dense first step");
        for _ in 0..3 {
            dense.step(along.at(0), Some(&odo)).expect("dense step");
        }
        stages(&mut dense, &along, &with_detections, &odo, &cb, false);
        stages(&mut dense, &along, &with_detections, &odo, &cb, true);
    }
    let mut g = c.benchmark_group("tracker");
    g.sample_size(10);
    let mut i = 100;
    g.bench_function("filter_step_110p_3views_640x480_full_grid_moving_robot", |b| {
        b.iter(|| {
            i += 1;
            black_box(tracker.step(along.at(i), Some(&approach(&odo, i))).expect("step"))
        })
    });
    g.bench_function("filter_first_step_3views_640x480_full_grid", |b| {
        b.iter_batched(
            || fresh_tracker(&cb),
            |mut t| black_box(t.step(&with_detections, Some(&odo)).expect("first step")),
            BatchSize::PerIteration,
        )
    });
    // the matching alone (330 codes against the whole codebook, with each code's best bin),
    // and the plain GEMM of its size (the `gemm` crate, one call on all threads)
    let k = cb.code_dim();
    let mut codes: Vec<f32> = (0..330 * k)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    pregrasp::tracker::encoder::normalise_rows(&mut codes, k);
    let mut out = Vec::new();
    g.bench_function("match_codes_330_by_191808", |b| {
        b.iter(|| {
            let best = match_codes(&cb, &codes, 330, &mut out);
            black_box(best.0[0])
        })
    });
    drop(out);
    let book = cb.codes.to_f32();
    let mut dst = vec![0f32; 330 * cb.n_bins()];
    g.bench_function("gemm_crate_330x128_by_128x191808", |b| {
        b.iter(|| {
            plain_gemm(&mut dst, &codes, &book, 330, k);
            black_box(dst[0])
        })
    });
    g.finish();
}

fn bench_and_report(c: &mut Criterion) {
    bench(c);
}

criterion_group!(benches, bench_and_report);
criterion_main!(benches);
