//! Rendering against analytic geometry. These tests need a graphics adapter; without a GPU
//! install Mesa's software Vulkan driver (`mesa-vulkan-drivers libvulkan1`); they fail (never
//! skip) when none is found.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use pregrasp::camera::{DepthImage, Intrinsics, pixel_index};
use pregrasp::geometry::{BinIndex, Pose, RotationGrid};
use pregrasp::mesh::{Mesh, builtin_box};
use pregrasp::render::{ClipRange, Renderer, SceneObject};
use std::sync::{Arc, OnceLock};

/// Depth agreement with analytic depth required at 1 m (a tenth of a millimetre).
const DEPTH_TOL_M: f32 = 1e-4;

fn renderer() -> Arc<Renderer> {
    static R: OnceLock<Arc<Renderer>> = OnceLock::new();
    R.get_or_init(|| {
        let r = Renderer::new().unwrap_or_else(|e| panic!("render tests need a graphics adapter: {e}"));
        eprintln!("render tests on {} (software: {})", r.adapter_name(), r.is_software());
        Arc::new(r)
    })
    .clone()
}

fn clip() -> ClipRange {
    ClipRange::new(0.05, 10.0).expect("valid clip range")
}

/// A square of side `side_m` in the plane z = 0 of its frame, centred at the origin.
fn square(side_m: f32, rgb: [u8; 3]) -> Mesh {
    let s = side_m / 2.0;
    Mesh::new(
        vec![[-s, -s, 0.0], [s, -s, 0.0], [s, s, 0.0], [-s, s, 0.0]],
        Some(vec![rgb; 4]),
        vec![[0, 1, 2], [0, 2, 3]],
    )
    .expect("valid square")
}

fn pixel_ray(k: &Intrinsics, x: u32, y: u32) -> Vector3<f64> {
    Vector3::new((x as f64 - k.cx()) / k.fx(), (y as f64 - k.cy()) / k.fy(), 1.0)
}

/// z-depth where the ray of pixel (x, y) meets the plane through `p0` with normal `n`.
fn plane_depth(k: &Intrinsics, x: u32, y: u32, p0: &Point3<f64>, n: &Vector3<f64>) -> f64 {
    let d = pixel_ray(k, x, y);
    n.dot(&p0.coords) / n.dot(&d)
}

#[test]
fn plane_facing_the_camera_has_analytic_depth() {
    let r = renderer();
    // Off-centre principal point on purpose: the projection must use cx, cy exactly.
    let k = Intrinsics::new(96, 72, [80.0, 0.0, 45.3, 0.0, 82.0, 38.7, 0.0, 0.0, 1.0]).unwrap();
    let mesh = r.upload_mesh(&square(0.6, [200, 100, 50])).unwrap();
    let pose = Isometry3::from_parts(Translation3::new(0.05, -0.03, 1.0), UnitQuaternion::identity());
    let obj = SceneObject {
        mesh,
        world_from_object: pose,
        instance_id: 3,
    };
    let out = r.render_scene(&k, &Pose::identity(), &[obj], clip()).unwrap();
    let mut covered = 0;
    for y in 0..k.height {
        for x in 0..k.width {
            let d = out.depth.get(x, y);
            // Where is the pixel centre on the plane z = 1?
            let p = pixel_ray(&k, x, y);
            let (px, py) = (p.x - 0.05, p.y + 0.03);
            let inside = px.abs() < 0.3 && py.abs() < 0.3;
            // Coverage is exact except within float noise of the edges.
            let margin = 1e-4;
            let certain = (px.abs() - 0.3).abs() > margin && (py.abs() - 0.3).abs() > margin;
            if certain {
                assert_eq!(d > 0.0, inside, "coverage at pixel ({x}, {y}): depth {d}");
            }
            if d > 0.0 {
                covered += 1;
                assert!((d - 1.0).abs() <= DEPTH_TOL_M, "depth {d} at ({x}, {y})");
                assert_eq!(out.instance[(y * k.width + x) as usize], 3);
            } else {
                assert_eq!(out.instance[(y * k.width + x) as usize], 0);
                assert_eq!(out.color.data[(y * k.width + x) as usize], [0, 0, 0]);
            }
        }
    }
    assert!(covered > 1000, "only {covered} pixels covered");
    // Headlight Lambert: near the optical axis the plane faces the light, colour ~ vertex colour.
    let c = out.color.data[(38 * k.width + 45) as usize];
    for (got, want) in c.iter().zip([200u8, 100, 50]) {
        assert!((*got as i32 - want as i32).abs() <= 3, "colour {c:?} at the centre");
    }
}

#[test]
fn tilted_plane_has_analytic_depth() {
    let r = renderer();
    let k = Intrinsics::from_focal(80, 60, 70.0).unwrap();
    let mesh = r.upload_mesh(&square(1.2, [255, 255, 255])).unwrap();
    let rot = UnitQuaternion::from_euler_angles(0.5, -0.35, 0.2);
    let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.0), rot);
    let n = rot * Vector3::z();
    let p0 = Point3::new(0.0, 0.0, 1.0);
    let obj = SceneObject {
        mesh,
        world_from_object: pose,
        instance_id: 1,
    };
    // A non-identity camera: the same relative pose must come out.
    let world_from_camera = Isometry3::from_parts(
        Translation3::new(0.3, -1.0, 2.0),
        UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
    );
    let obj_world = SceneObject {
        world_from_object: world_from_camera * obj.world_from_object,
        ..obj
    };
    let out = r
        .render_scene(&k, &world_from_camera.inverse(), &[obj_world], clip())
        .unwrap();
    let mut covered = 0;
    let mut worst = 0.0f64;
    for y in 0..k.height {
        for x in 0..k.width {
            let d = out.depth.get(x, y) as f64;
            if d > 0.0 {
                covered += 1;
                let want = plane_depth(&k, x, y, &p0, &n);
                worst = worst.max((d - want).abs());
            }
        }
    }
    assert!(covered > 2000, "only {covered} pixels covered");
    // Headlight Lambert on white: 255 (0.2 + 0.8 |n . ray|), flat over each triangle.
    let mut shaded = 0;
    for y in (4..k.height - 4).step_by(5) {
        for x in (4..k.width - 4).step_by(5) {
            let around = (x - 1..=x + 1).all(|xx| (y - 1..=y + 1).all(|yy| out.depth.get(xx, yy) > 0.0));
            if !around {
                continue; // derivatives at silhouettes use helper pixels
            }
            let ray = pixel_ray(&k, x, y).normalize();
            let want = 255.0 * (0.2 + 0.8 * n.dot(&ray).abs());
            let got = out.color.data[(y * k.width + x) as usize];
            for c in got {
                assert!(
                    (c as f64 - want).abs() <= 3.0,
                    "colour {got:?} at ({x}, {y}), expected {want:.1}"
                );
            }
            shaded += 1;
        }
    }
    assert!(shaded > 50, "only {shaded} shaded samples");
    eprintln!("tilted plane: {covered} pixels, worst depth error {worst:e} m");
    assert!(worst <= DEPTH_TOL_M as f64, "worst depth error {worst} m");
    // The depth-only path (z-buffer read back) meets the same bound on the same pixels.
    let mesh = r.upload_mesh(&square(1.2, [255, 255, 255])).unwrap();
    let z = r.render_view_depths(&mesh, &k, &[pose], clip()).unwrap();
    let mut worst_z = 0.0f64;
    for y in 0..k.height {
        for x in 0..k.width {
            let d = z[0].get(x, y) as f64;
            assert_eq!(d > 0.0, out.depth.get(x, y) > 0.0, "coverage at ({x}, {y})");
            if d > 0.0 {
                worst_z = worst_z.max((d - plane_depth(&k, x, y, &p0, &n)).abs());
            }
        }
    }
    eprintln!("tilted plane, depth only: worst depth error {worst_z:e} m");
    assert!(
        worst_z <= DEPTH_TOL_M as f64,
        "depth-only worst depth error {worst_z} m"
    );
}

#[test]
fn box_face_at_one_metre() {
    let r = renderer();
    let k = Intrinsics::from_focal(64, 64, 60.0).unwrap();
    let size = 0.3;
    let mesh = r
        .upload_mesh(&builtin_box([size, size, size], [[90, 90, 200], [200, 90, 90]]))
        .unwrap();
    // Rotated by 90 degrees about z (the face stays parallel to the image), front face at 1 m.
    let pose = Isometry3::from_parts(
        Translation3::new(0.0, 0.0, 1.0 + size / 2.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
    );
    let out = r
        .render_scene(
            &k,
            &Pose::identity(),
            &[SceneObject {
                mesh,
                world_from_object: pose,
                instance_id: 7,
            }],
            clip(),
        )
        .unwrap();
    let half = size / 2.0;
    let mut face = 0;
    for y in 0..k.height {
        for x in 0..k.width {
            let p = pixel_ray(&k, x, y); // at z = 1
            let d = out.depth.get(x, y);
            if p.x.abs() < half - 1e-4 && p.y.abs() < half - 1e-4 {
                face += 1;
                assert!((d - 1.0).abs() <= DEPTH_TOL_M, "face depth {d} at ({x}, {y})");
                assert_eq!(out.instance[(y * k.width + x) as usize], 7);
            } else if p.x.abs() > half + 1e-4 || p.y.abs() > half + 1e-4 {
                // The side faces lie behind the front face's outline (x / z shrinks with z), so
                // the silhouette is exactly the front face.
                assert_eq!(d, 0.0, "background expected at ({x}, {y})");
            }
            // So every covered pixel, edges included, is the front face.
            if d > 0.0 {
                assert!((d - 1.0).abs() <= DEPTH_TOL_M, "covered pixel ({x}, {y}) has depth {d}");
            }
        }
    }
    assert!(face > 200, "only {face} face pixels");
}

#[test]
fn instance_masks_follow_occlusion() {
    let r = renderer();
    let k = Intrinsics::from_focal(64, 48, 50.0).unwrap();
    let front = r.upload_mesh(&square(0.2, [255, 0, 0])).unwrap();
    let back = r.upload_mesh(&square(1.0, [0, 255, 0])).unwrap();
    let objects = [
        SceneObject {
            mesh: back,
            world_from_object: Isometry3::translation(0.0, 0.0, 2.0),
            instance_id: 2,
        },
        SceneObject {
            mesh: front,
            world_from_object: Isometry3::translation(0.0, 0.0, 1.0),
            instance_id: 9,
        },
    ];
    let out = r
        .render_scene_lit(&k, &Pose::identity(), &objects, clip(), [10, 20, 30], None)
        .unwrap();
    let at = |x: u32, y: u32| (y * k.width + x) as usize;
    // Centre: the near square.
    assert_eq!(out.instance[at(32, 24)], 9);
    assert!((out.depth.get(32, 24) - 1.0).abs() < DEPTH_TOL_M);
    // Beside the near square (|x| > 0.1 m at 1 m = 5 px) but on the far one (0.5 m at 2 m = 12.5 px).
    assert_eq!(out.instance[at(32 + 8, 24)], 2);
    assert!((out.depth.get(32 + 8, 24) - 2.0).abs() < DEPTH_TOL_M);
    // Corner: nothing, background colour.
    assert_eq!(out.instance[at(0, 0)], 0);
    assert_eq!(out.depth.get(0, 0), 0.0);
    assert_eq!(out.color.data[at(0, 0)], [10, 20, 30]);
    // Mask and depth agree everywhere.
    for (i, (&m, &d)) in out.instance.iter().zip(&out.depth.data_m).enumerate() {
        assert_eq!(m > 0, d > 0.0, "pixel {i}");
    }
    // Outside the clip range nothing is drawn.
    let near_only = r
        .render_scene(&k, &Pose::identity(), &objects, ClipRange::new(0.05, 1.5).unwrap())
        .unwrap();
    assert_eq!(near_only.instance[at(32 + 8, 24)], 0);
    assert_eq!(near_only.instance[at(32, 24)], 9);
}

fn mug_like() -> Mesh {
    pregrasp::mesh::builtin("mug").expect("built-in mug")
}

#[test]
fn batched_views_match_scene_renders() {
    let r = renderer();
    let k = Intrinsics::from_focal(40, 32, 45.0).unwrap();
    let mesh = r.upload_mesh(&mug_like()).unwrap();
    let grid = RotationGrid::new(30).unwrap();
    // More views than fit one atlas would be slow; a few dozen across rotations.
    let poses: Vec<Pose> = (0..grid.len())
        .step_by(grid.len() / 37)
        .map(|i| Isometry3::from_parts(Translation3::new(0.01, -0.02, 0.5), grid.rotation(grid.unflat(i))))
        .collect();
    let views = r.render_views(&mesh, &k, &poses, clip()).unwrap();
    let depths = r.render_view_depths(&mesh, &k, &poses, clip()).unwrap();
    assert_eq!(views.len(), poses.len());
    // The streaming forms give the same views in the same order.
    let mut streamed = Vec::new();
    r.for_each_view(&mesh, &k, &poses, clip(), |i, v| streamed.push((i, v)))
        .unwrap();
    assert!(streamed.iter().enumerate().all(|(j, (i, v))| j == *i && *v == views[j]));
    let mut streamed_depths = Vec::new();
    r.for_each_view_depth(&mesh, &k, &poses, clip(), |i, d| streamed_depths.push((i, d)))
        .unwrap();
    assert!(
        streamed_depths
            .iter()
            .enumerate()
            .all(|(j, (i, d))| j == *i && *d == depths[j])
    );
    for (i, pose) in poses.iter().enumerate() {
        let scene = r
            .render_scene(
                &k,
                &Pose::identity(),
                &[SceneObject {
                    mesh: mesh.clone(),
                    world_from_object: *pose,
                    instance_id: 1,
                }],
                clip(),
            )
            .unwrap();
        assert!(
            scene.depth.data_m.iter().filter(|d| **d > 0.0).count() > 20,
            "view {i} is empty"
        );
        let a = &views[i].depth.data_m;
        let b = &scene.depth.data_m;
        let cov = a.iter().zip(b).filter(|(x, y)| (**x > 0.0) != (**y > 0.0)).count();
        let maxd = a
            .iter()
            .zip(b)
            .filter(|(x, y)| **x > 0.0 && **y > 0.0)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        let col = views[i]
            .color
            .data
            .iter()
            .zip(&scene.color.data)
            .filter(|(x, y)| x != y)
            .count();
        // Viewport offsets in the atlas change the rasteriser's arithmetic only marginally
        // (measured on lavapipe: no coverage change, depth within 0.03 mm on grazing faces).
        assert!(cov * 100 <= a.len(), "view {i}: {cov} pixels change coverage");
        assert!(maxd <= DEPTH_TOL_M, "view {i}: depth differs by {maxd} m");
        assert!(col * 100 <= a.len(), "view {i}: {col} pixels change colour");
        // The depth-only path reads the z-buffer instead of the shaded R32Float target.
        let z = &depths[i].data_m;
        let zcov = z.iter().zip(a).filter(|(x, y)| (**x > 0.0) != (**y > 0.0)).count();
        let zmax = z
            .iter()
            .zip(a)
            .filter(|(x, y)| **x > 0.0 && **y > 0.0)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert_eq!(zcov, 0, "view {i}: depth-only coverage differs");
        assert!(zmax <= DEPTH_TOL_M, "view {i}: depth-only depth differs by {zmax} m");
    }
}

#[test]
fn views_are_chunked_across_atlases() {
    let r = renderer();
    // Large views so that a handful of them fill an atlas.
    let side = r.max_image_side_px().min(pregrasp::render::MAX_ATLAS_SIDE_PX) / 2 + 1;
    let k = Intrinsics::from_focal(side, 8, 8.0).unwrap();
    let per_atlas = r.views_per_atlas(side, 8);
    let mesh = r.upload_mesh(&square(0.5, [255, 255, 255])).unwrap();
    let n = per_atlas + 3;
    let poses: Vec<Pose> = (0..n)
        .map(|i| Isometry3::translation(0.0, 0.0, 1.0 + 0.01 * i as f64))
        .collect();
    let depths = r.render_view_depths(&mesh, &k, &poses, clip()).unwrap();
    assert_eq!(depths.len(), n);
    for (i, d) in depths.iter().enumerate() {
        let want = 1.0 + 0.01 * i as f32;
        let got = d.get(side / 2, 4);
        assert!((got - want).abs() < DEPTH_TOL_M, "view {i}: {got} vs {want}");
    }
}

/// Back faces of closed meshes are culled for speed; that must not change any render.
#[test]
fn culling_back_faces_changes_nothing() {
    let r = renderer();
    let k = Intrinsics::from_focal(64, 64, 90.0).unwrap();
    let mug = mug_like();
    let mut mixed = mug.clone();
    mixed.triangles.iter_mut().step_by(2).for_each(|t| t.swap(1, 2));
    let mut flipped = mug.clone();
    flipped.triangles.iter_mut().for_each(|t| t.swap(1, 2));
    let culled = r.upload_mesh(&mug).unwrap();
    let unculled = r.upload_mesh(&mixed).unwrap();
    let front_culled = r.upload_mesh(&flipped).unwrap();
    assert!(culled.culls_back_faces() && front_culled.culls_back_faces());
    assert!(!unculled.culls_back_faces());
    let grid = RotationGrid::new(30).unwrap();
    let poses: Vec<Pose> = (0..grid.len())
        .step_by(grid.len() / 23)
        .map(|i| Isometry3::from_parts(Translation3::new(0.0, 0.01, 0.4), grid.rotation(grid.unflat(i))))
        .collect();
    let two_sided = r.upload_mesh_two_sided(&mug).unwrap();
    assert!(!two_sided.culls_back_faces());
    let reference = r.render_view_depths(&unculled, &k, &poses, clip()).unwrap();
    for mesh in [&culled, &front_culled, &two_sided] {
        let got = r.render_view_depths(mesh, &k, &poses, clip()).unwrap();
        for (i, (a, b)) in got.iter().zip(&reference).enumerate() {
            let mut covered = 0;
            for (x, y) in a.data_m.iter().zip(&b.data_m) {
                assert_eq!(*x > 0.0, *y > 0.0, "view {i}: coverage changed by culling");
                assert!((x - y).abs() <= 1e-6, "view {i}: depth {x} vs {y}");
                covered += (*x > 0.0) as usize;
            }
            assert!(covered > 100, "view {i}: only {covered} pixels");
        }
    }
}

/// A camera inside a closed mesh sees its inside only when the mesh is uploaded two-sided.
#[test]
fn camera_inside_a_closed_mesh_needs_two_sided() {
    let r = renderer();
    let k = Intrinsics::from_focal(32, 32, 20.0).unwrap();
    let room = builtin_box([1.0, 1.0, 1.0], [[100, 100, 100], [150, 150, 150]]);
    let culled = r.upload_mesh(&room).unwrap();
    let two_sided = r.upload_mesh_two_sided(&room).unwrap();
    let inside = [Pose::identity()];
    let d = r.render_view_depths(&two_sided, &k, &inside, clip()).unwrap();
    assert!(
        (d[0].get(16, 16) - 0.5).abs() < DEPTH_TOL_M,
        "far wall at 0.5 m: {}",
        d[0].get(16, 16)
    );
    let d = r.render_view_depths(&culled, &k, &inside, clip()).unwrap();
    assert!(d[0].data_m.iter().all(|v| *v == 0.0), "culled walls seen from inside");
}

/// Views wider than an atlas still render, one per atlas.
#[test]
fn views_wider_than_an_atlas_render() {
    let r = renderer();
    let wide = pregrasp::render::MAX_ATLAS_SIDE_PX + 16;
    if wide > r.max_image_side_px() {
        return; // the device limit is the atlas side: nothing wider can be asked for
    }
    let k = Intrinsics::from_focal(wide, 4, 4.0).unwrap();
    assert_eq!(
        r.views_per_atlas(wide, 4),
        pregrasp::render::MAX_ATLAS_SIDE_PX as usize / 4
    );
    let mesh = r.upload_mesh(&square(0.5, [255, 255, 255])).unwrap();
    let d = r
        .render_view_depths(&mesh, &k, &[Isometry3::translation(0.0, 0.0, 1.5)], clip())
        .unwrap();
    assert!((d[0].get(wide / 2, 2) - 1.5).abs() < DEPTH_TOL_M);
    assert_eq!(d[0].get(0, 2), 0.0);
}

/// One renderer shared by threads gives the same images as used alone.
#[test]
fn renders_from_several_threads_agree() {
    let r = renderer();
    let k = Intrinsics::from_focal(48, 40, 50.0).unwrap();
    let mesh = r.upload_mesh(&mug_like()).unwrap();
    let grid = RotationGrid::new(30).unwrap();
    let poses: Vec<Pose> = (0..12)
        .map(|i| Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.45), grid.rotation(grid.unflat(i * 37))))
        .collect();
    let alone = r.render_view_depths(&mesh, &k, &poses, clip()).unwrap();
    let handles: Vec<_> = (0..3)
        .map(|_| {
            let (r, mesh, poses) = (r.clone(), mesh.clone(), poses.clone());
            std::thread::spawn(move || {
                (0..4)
                    .map(|_| r.render_view_depths(&mesh, &k, &poses, clip()).unwrap())
                    .collect::<Vec<_>>()
            })
        })
        .collect();
    for h in handles {
        for got in h.join().unwrap() {
            assert_eq!(got, alone);
        }
    }
}

/// The tracker's premise: the in-plane bins of a centred view are 2-D image rotations.
#[test]
fn inplane_rotation_is_an_image_rotation() {
    let r = renderer();
    let n = 64;
    let k = Intrinsics::from_focal(n, n, 70.0).unwrap();
    let mesh = r
        .upload_mesh(&builtin_box([0.16, 0.10, 0.05], [[200, 200, 200], [50, 50, 50]]))
        .unwrap();
    let grid = RotationGrid::new(5).unwrap();
    let step = grid.step_rad();
    let pose = |inplane: usize| {
        let b = BinIndex {
            elevation: 7,
            azimuth: 11,
            inplane,
        };
        Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.45), grid.rotation(b))
    };
    let views = r
        .render_view_depths(&mesh, &k, &[pose(0), pose(1), pose(9)], clip())
        .unwrap();
    for (view, bins) in [(&views[1], 1.0), (&views[2], 9.0)] {
        let m = compare_rotated(&views[0], view, step * bins);
        eprintln!("{bins} bins: {m:?}");
        assert!(m.compared > 300, "too few object pixels: {m:?}");
        // Nearest-neighbour resampling differs only along silhouettes and creases.
        assert!(
            (m.coverage_mismatch as f64) < 0.03 * m.total as f64,
            "coverage changes at {bins} bins: {m:?}"
        );
        assert!(
            (m.bad as f64) < 0.05 * m.compared as f64,
            "depths differ at {bins} bins: {m:?}"
        );
    }
    // Not trivially true: rotating the image the other way matches much worse.
    let wrong = compare_rotated(&views[0], &views[2], -step * 9.0);
    let right = compare_rotated(&views[0], &views[2], step * 9.0);
    assert!(
        wrong.coverage_mismatch > 4 * right.coverage_mismatch.max(10),
        "the wrong direction matches too: {wrong:?} vs {right:?}"
    );
}

#[derive(Debug)]
struct RotationMatch {
    total: usize,
    coverage_mismatch: usize,
    compared: usize,
    bad: usize,
}

/// Compares `rotated` with `base` rotated in the image by `theta_rad` about the image centre
/// (u right, v down): rotated(p) = base(R(-theta) (p - c) + c), nearest neighbour.
fn compare_rotated(base: &DepthImage, rotated: &DepthImage, theta_rad: f64) -> RotationMatch {
    let n = base.width;
    // the principal point of `from_focal`: the middle of the pixel grid, pixel centres at integers
    let c = (n as f64 - 1.0) / 2.0;
    let (s, co) = theta_rad.sin_cos();
    let mut m = RotationMatch {
        total: 0,
        coverage_mismatch: 0,
        compared: 0,
        bad: 0,
    };
    for y in 2..n - 2 {
        for x in 2..n - 2 {
            let (du, dv) = (x as f64 - c, y as f64 - c);
            let su = co * du + s * dv + c;
            let sv = -s * du + co * dv + c;
            let (sx, sy) = (pixel_index(su), pixel_index(sv));
            if sx < 0 || sy < 0 || sx >= n as i64 || sy >= n as i64 {
                continue;
            }
            let a = rotated.get(x, y);
            let b = base.get(sx as u32, sy as u32);
            m.total += 1;
            if (a > 0.0) != (b > 0.0) {
                m.coverage_mismatch += 1;
            } else if a > 0.0 {
                m.compared += 1;
                if (a - b).abs() > 0.01 {
                    m.bad += 1;
                }
            }
        }
    }
    m
}

#[test]
fn bad_inputs_are_errors() {
    let r = renderer();
    let k = Intrinsics::from_focal(16, 16, 10.0).unwrap();
    let mesh = r.upload_mesh(&square(0.5, [1, 2, 3])).unwrap();
    let bad_clip = ClipRange {
        near_m: 2.0,
        far_m: 1.0,
    };
    assert!(r.render_view_depths(&mesh, &k, &[Pose::identity()], bad_clip).is_err());
    let nan_pose = Isometry3::translation(f64::NAN, 0.0, 1.0);
    assert!(r.render_view_depths(&mesh, &k, &[nan_pose], clip()).is_err());
    // No views: nothing rendered, no error.
    assert!(r.render_views(&mesh, &k, &[], clip()).unwrap().is_empty());
    // No objects: an empty scene.
    let empty = r.render_scene(&k, &Pose::identity(), &[], clip()).unwrap();
    assert!(empty.depth.data_m.iter().all(|d| *d == 0.0));
}

/// Lambert shading: a square facing the camera is lit fully by a headlight, by
/// `0.2 + 0.8 cos(angle)` of a directional light at `angle` to its normal, by the 20 % ambient
/// alone when the light is behind it; the light is given in the world frame and turned into
/// each camera's.
#[test]
fn directional_light_shades_by_the_angle_to_the_normal() {
    let r = renderer();
    let k = Intrinsics::from_focal(64, 48, 60.0).unwrap();
    let mesh = r.upload_mesh(&square(0.8, [200, 200, 200])).unwrap();
    // the camera looks along the world's -x: camera_from_world turns world directions
    let world_from_camera = Isometry3::from_parts(
        Translation3::new(1.0, 0.0, 0.0),
        UnitQuaternion::face_towards(&Vector3::new(-1.0, 0.0, 0.0), &Vector3::new(0.0, 0.0, -1.0)),
    );
    let camera_from_world = world_from_camera.inverse();
    // the square's normal (its z) points at the camera (world +x)
    let world_from_square = Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::face_towards(&Vector3::new(1.0, 0.0, 0.0), &Vector3::new(0.0, 0.0, 1.0)),
    );
    let scene = [SceneObject {
        mesh: mesh.clone(),
        world_from_object: world_from_square,
        instance_id: 1,
    }];
    let centre = |light: Option<Vector3<f64>>| -> f64 {
        let out = r
            .render_scene_lit(&k, &camera_from_world, &scene, clip(), [0, 0, 0], light)
            .unwrap();
        assert_eq!(out.instance[24 * 64 + 32], 1, "the square covers the centre");
        out.color.data[24 * 64 + 32][0] as f64
    };
    let head = centre(None);
    assert!((head - 200.0).abs() <= 2.0, "headlight {head}");
    for deg in [0.0f64, 60.0] {
        let l = Vector3::new(deg.to_radians().cos(), 0.0, deg.to_radians().sin());
        let got = centre(Some(l));
        let want = 200.0 * (0.2 + 0.8 * deg.to_radians().cos());
        assert!((got - want).abs() <= 3.0, "light at {deg} deg: {got} against {want}");
    }
    let behind = centre(Some(Vector3::new(-1.0, 0.0, 0.2)));
    assert!((behind - 40.0).abs() <= 2.0, "light behind: {behind}");
}
