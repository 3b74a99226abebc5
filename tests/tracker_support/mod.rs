//! Synthetic scenes for the tracker tests: meshes on a table, rendered by the CPU rasteriser,
//! with detections from the instance mask (the tests never read the truth into the filter
//! except through these rendered images and boxes).
#![allow(dead_code)] // each test binary uses a part of the helpers
#![allow(clippy::unwrap_used)] // test helpers: a failure is a test failure

use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use pregrasp::camera::{DepthImage, Intrinsics};
use pregrasp::geometry::{Pose, RotationGrid};
use pregrasp::mesh::Mesh;
use pregrasp::render::raster;
use pregrasp::tracker::codebook::{CodebookConfig, CpuViews};
use pregrasp::tracker::{CameraFrame, Codebook, Detection};
use rand::{Rng, SeedableRng};
use std::sync::Arc;

pub struct Scene {
    /// (model name, mesh, world_from_object)
    pub objects: Vec<(String, Mesh, Pose)>,
    pub table: Mesh,
}

impl Scene {
    pub fn new(objects: Vec<(String, Mesh, Pose)>) -> Self {
        // table top at z = 0 (world z up), 2 x 2 m
        let mut table = pregrasp::mesh::builtin_box([2.0, 2.0, 0.02], [[120, 100, 80], [120, 100, 80]]);
        for v in &mut table.vertices_m {
            v[2] -= 0.01;
        }
        Self { objects, table }
    }
}

pub fn intrinsics() -> Intrinsics {
    Intrinsics::from_focal(160, 120, 150.0).unwrap()
}

pub use pregrasp::geometry::look_at;

/// Renders the scene from a camera and builds a frame with detections of the visible objects.
pub fn frame(
    camera: &str,
    world_from_camera: &Pose,
    scene: &Scene,
    detections: bool,
    color: bool,
    noise_rel: f64,
    seed: u64,
) -> CameraFrame {
    let k = intrinsics();
    let cfw = world_from_camera.inverse();
    let mut list: Vec<(&Mesh, Pose)> = scene.objects.iter().map(|(_, m, p)| (m, cfw * p)).collect();
    list.push((&scene.table, cfw));
    let img = raster::render(&k, &list, 0.05, [30, 30, 30]);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let data_m: Vec<f32> = img
        .depth
        .data_m
        .iter()
        .map(|&d| {
            if d > 0.0 {
                d * (1.0 + (noise_rel * (rng.random::<f64>() * 2.0 - 1.0) * 1.7) as f32)
            } else {
                0.0
            }
        })
        .collect();
    let mut dets = Vec::new();
    if detections {
        for (oi, (name, _, _)) in scene.objects.iter().enumerate() {
            let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0u32, 0u32);
            let mut count = 0;
            for y in 0..k.height {
                for x in 0..k.width {
                    if img.instance[(y * k.width + x) as usize] == oi as u16 + 1 {
                        x0 = x0.min(x);
                        y0 = y0.min(y);
                        x1 = x1.max(x);
                        y1 = y1.max(y);
                        count += 1;
                    }
                }
            }
            if count > 20 {
                dets.push(Detection {
                    object: name.clone(),
                    bbox_xywh_px: [x0 as f64, y0 as f64, (x1 - x0 + 1) as f64, (y1 - y0 + 1) as f64],
                    score: 1.0,
                });
            }
        }
    }
    CameraFrame {
        camera: camera.to_string(),
        stamp_ns: 0,
        intrinsics: k,
        depth: DepthImage {
            width: k.width,
            height: k.height,
            data_m,
        },
        color: color.then_some(img.color),
        detections: dets,
    }
}

pub fn coarse_codebook(mesh: &Mesh) -> Arc<Codebook> {
    let grid = RotationGrid::new(10).unwrap();
    Arc::new(Codebook::build(&CpuViews(mesh), mesh, grid, &CodebookConfig::coarse()).unwrap())
}

/// Object standing on the table at (x, y), yawed by `yaw_rad` about world z.
pub fn on_table(mesh: &Mesh, x: f64, y: f64, yaw_rad: f64) -> Pose {
    let b = mesh.bounds();
    Pose::from_parts(
        Translation3::new(x, y, -b.min_m.z),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_rad),
    )
}

pub fn translation_error(est: &Pose, truth: &Pose) -> f64 {
    (est.translation.vector - truth.translation.vector).norm()
}

/// Smallest rotation angle between `est` and `truth * s` over the symmetries `s`.
pub fn rotation_error_deg(
    est: &UnitQuaternion<f64>,
    truth: &UnitQuaternion<f64>,
    symmetries: &[UnitQuaternion<f64>],
) -> f64 {
    let mut best = est.angle_to(truth);
    for s in symmetries {
        best = best.min(est.angle_to(&(truth * s)));
    }
    best.to_degrees()
}

pub fn point(p: &Pose) -> Point3<f64> {
    Point3::from(p.translation.vector)
}
