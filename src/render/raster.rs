//! A small CPU rasteriser: a z-buffer render (depth, interpolated vertex colours, instance ids)
//! and a coverage-only silhouette, with the same triangle set-up and pixel convention as the GPU
//! renderer (pixel `(x, y)` sampled at its centre, `(x, y)` in pixel coordinates).
//!
//! The GPU renderer ([`crate::render::Renderer`]) does the real work; this one lets the tracker
//! be built and tested without any renderer, renders the demo's synthetic cameras cheaply, gives
//! the generator each object's silhouette "rendered alone" (BOP's `px_count_all`), and is the
//! ground truth that the renderer's views are checked against.

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::geometry::Pose;
use crate::mesh::Mesh;
use nalgebra::Point3;

/// Triangles with a vertex closer than this to the camera plane are left out of silhouettes,
/// metres.
pub const SILHOUETTE_NEAR_M: f64 = 0.01;

/// One rendered image.
#[derive(Debug, Clone)]
pub struct RasterImage {
    pub depth: DepthImage,
    pub color: ColorImage,
    /// 0 = background, else 1 + index of the object in the list given.
    pub instance: Vec<u16>,
}

/// Calls `f(x, y, [w0, w1, w2])` for every pixel of a `width` x `height` image whose centre lies
/// inside (or on an edge of) the projected triangle `s`, with its barycentric weights.
fn for_each_covered_pixel(s: [[f64; 2]; 3], width: usize, height: usize, mut f: impl FnMut(usize, usize, [f64; 3])) {
    let area = (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) - (s[2][0] - s[0][0]) * (s[1][1] - s[0][1]);
    if area.abs() < 1e-12 || width == 0 || height == 0 {
        return;
    }
    let (lo_x, hi_x) = (s[0][0].min(s[1][0]).min(s[2][0]), s[0][0].max(s[1][0]).max(s[2][0]));
    let (lo_y, hi_y) = (s[0][1].min(s[1][1]).min(s[2][1]), s[0][1].max(s[1][1]).max(s[2][1]));
    // pixels whose centre (at integer coordinates) the triangle's bounds hold
    if !(hi_x >= 0.0 && hi_y >= 0.0 && lo_x <= (width - 1) as f64 && lo_y <= (height - 1) as f64) {
        return;
    }
    let (x0, x1) = (
        lo_x.ceil().max(0.0) as usize,
        hi_x.floor().min((width - 1) as f64) as usize,
    );
    let (y0, y1) = (
        lo_y.ceil().max(0.0) as usize,
        hi_y.floor().min((height - 1) as f64) as usize,
    );
    for y in y0..=y1 {
        let py = y as f64;
        for x in x0..=x1 {
            let px = x as f64;
            let w0 = ((s[1][0] - px) * (s[2][1] - py) - (s[2][0] - px) * (s[1][1] - py)) / area;
            let w1 = ((s[2][0] - px) * (s[0][1] - py) - (s[0][0] - px) * (s[2][1] - py)) / area;
            let w2 = 1.0 - w0 - w1;
            if w0 >= 0.0 && w1 >= 0.0 && w2 >= 0.0 {
                f(x, y, [w0, w1, w2]);
            }
        }
    }
}

/// Renders `objects` (mesh, `camera_from_object`) into one image. Triangles with a vertex
/// nearer than `near_m` are skipped. Background depth is 0 (no reading), background colour
/// `background`.
pub fn render(intrinsics: &Intrinsics, objects: &[(&Mesh, Pose)], near_m: f64, background: [u8; 3]) -> RasterImage {
    let w = intrinsics.width as usize;
    let h = intrinsics.height as usize;
    let mut zbuf = vec![f32::INFINITY; w * h];
    let mut color = vec![background; w * h];
    let mut instance = vec![0u16; w * h];
    let (fx, fy, cx, cy) = (intrinsics.fx(), intrinsics.fy(), intrinsics.cx(), intrinsics.cy());
    for (oi, (mesh, camera_from_object)) in objects.iter().enumerate() {
        let cam: Vec<Point3<f64>> = mesh
            .vertices_m
            .iter()
            .map(|v| camera_from_object * Point3::new(v[0] as f64, v[1] as f64, v[2] as f64))
            .collect();
        for tri in &mesh.triangles {
            let p = tri.map(|i| cam[i as usize]);
            if p.iter().any(|q| q.z <= near_m) {
                continue;
            }
            let s = p.map(|q| [fx * q.x / q.z + cx, fy * q.y / q.z + cy]);
            let inv_z = p.map(|q| 1.0 / q.z);
            let cols = tri.map(|i| mesh.colors[i as usize]);
            for_each_covered_pixel(s, w, h, |x, y, bw| {
                let z = 1.0 / (bw[0] * inv_z[0] + bw[1] * inv_z[1] + bw[2] * inv_z[2]);
                let i = y * w + x;
                if (z as f32) < zbuf[i] {
                    zbuf[i] = z as f32;
                    color[i] = std::array::from_fn(|ch| {
                        let v = bw[0] * cols[0][ch] as f64 + bw[1] * cols[1][ch] as f64 + bw[2] * cols[2][ch] as f64;
                        v.round().clamp(0.0, 255.0) as u8
                    });
                    instance[i] = oi as u16 + 1;
                }
            });
        }
    }
    let data_m: Vec<f32> = zbuf.into_iter().map(|z| if z.is_finite() { z } else { 0.0 }).collect();
    RasterImage {
        depth: DepthImage {
            width: intrinsics.width,
            height: intrinsics.height,
            data_m,
        },
        color: ColorImage {
            width: intrinsics.width,
            height: intrinsics.height,
            data: color,
        },
        instance,
    }
}

/// The silhouette of `mesh` at `camera_from_object` (coverage only, no depth test): true where
/// some triangle covers the pixel centre. Triangles with a vertex nearer than
/// [`SILHOUETTE_NEAR_M`] are left out.
pub fn silhouette(mesh: &Mesh, camera_from_object: &Pose, k: &Intrinsics) -> Vec<bool> {
    let (w, h) = (k.width as usize, k.height as usize);
    let mut mask = vec![false; w * h];
    let projected: Vec<Option<[f64; 2]>> = (0..mesh.vertices_m.len() as u32)
        .map(|i| {
            let p = camera_from_object * mesh.vertex(i);
            if p.z < SILHOUETTE_NEAR_M { None } else { k.project(&p) }
        })
        .collect();
    for t in &mesh.triangles {
        let (Some(a), Some(b), Some(c)) = (
            projected[t[0] as usize],
            projected[t[1] as usize],
            projected[t[2] as usize],
        ) else {
            continue;
        };
        for_each_covered_pixel([a, b, c], w, h, |x, y, _| mask[y * w + x] = true);
    }
    mask
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    #[test]
    fn box_in_front_of_the_camera_has_the_right_depth_and_size() {
        let mesh = crate::mesh::builtin_box([0.2, 0.2, 0.2], [[200, 0, 0], [0, 200, 0]]);
        let k = Intrinsics::from_focal(64, 64, 64.0).unwrap();
        let pose = Pose::from_parts(Translation3::new(0.0, 0.0, 1.0), UnitQuaternion::identity());
        let img = render(&k, &[(&mesh, pose)], 0.01, [0, 0, 0]);
        let c = img.depth.get(32, 32);
        assert!((c - 0.9).abs() < 1e-3, "front face at 0.9 m, got {c}");
        // the front face spans 0.2 m at 0.9 m: 64 * 0.2 / 0.9 = 14.2 px
        let row: usize = (0..64).filter(|&x| img.depth.get(x, 32) > 0.0).count();
        assert!((13..=16).contains(&row), "width {row}");
        assert_eq!(img.instance[32 * 64 + 32], 1);
        assert_eq!(img.depth.get(0, 0), 0.0);
    }

    #[test]
    fn a_box_facing_the_camera_covers_its_projected_rectangle() {
        // a 0.2 x 0.1 m face at 1 m with f = 100 px: 20 x 10 px, centred on the principal
        // point (31.5, 23.5): pixel centres 22..=41 and 19..=28
        let mesh = crate::mesh::builtin_box([0.2, 0.1, 0.05], [[1, 1, 1], [2, 2, 2]]);
        let k = Intrinsics::from_focal(64, 48, 100.0).unwrap();
        let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.025), UnitQuaternion::identity());
        let m = silhouette(&mesh, &pose, &k);
        let n = m.iter().filter(|v| **v).count();
        // the back face (at 1.05 m) is smaller: the front face's 20 x 10 dominates
        assert_eq!(n, 20 * 10, "{n} px");
        assert!(m[19 * 64 + 22] && m[28 * 64 + 41] && !m[18 * 64 + 22] && !m[19 * 64 + 42]);
        // the z-buffer render covers the same pixels
        let img = render(&k, &[(&mesh, pose)], 0.01, [0, 0, 0]);
        let covered: Vec<bool> = img.instance.iter().map(|i| *i > 0).collect();
        assert_eq!(covered, m);
        // behind the camera: nothing
        let behind = Isometry3::from_parts(Translation3::new(0.0, 0.0, -1.0), UnitQuaternion::identity());
        assert!(!silhouette(&mesh, &behind, &k).iter().any(|v| *v));
    }
}
