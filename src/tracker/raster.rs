//! A small CPU z-buffer rasteriser: depth (z, metres) and interpolated vertex colours.
//!
//! The codebook normally renders with the GPU renderer ([`crate::render::Renderer`]); this one
//! exists so that the tracker can be built and tested with no renderer at all (tests, tiny
//! codebooks), and it is the ground truth that the renderer's codebook views are checked
//! against.

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::geometry::Pose;
use crate::mesh::Mesh;
use nalgebra::Point3;

/// One rendered image.
#[derive(Debug, Clone)]
pub struct RasterImage {
    pub depth: DepthImage,
    pub color: ColorImage,
    /// 0 = background, else 1 + index of the object in the list given.
    pub instance: Vec<u16>,
}

/// Renders `objects` (mesh, `camera_from_object`) into one image. Background depth is 0 (no
/// reading), background colour `background`.
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
            let p = [cam[tri[0] as usize], cam[tri[1] as usize], cam[tri[2] as usize]];
            if p.iter().any(|q| q.z <= near_m) {
                continue;
            }
            let s: Vec<[f64; 2]> = p.iter().map(|q| [fx * q.x / q.z + cx, fy * q.y / q.z + cy]).collect();
            let area = (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) - (s[2][0] - s[0][0]) * (s[1][1] - s[0][1]);
            if area.abs() < 1e-12 {
                continue;
            }
            // pixels whose centre (at integer coordinates) the triangle's bounds can hold
            let xmin = s.iter().map(|q| q[0]).fold(f64::INFINITY, f64::min).ceil().max(0.0) as usize;
            let xmax = s
                .iter()
                .map(|q| q[0])
                .fold(f64::NEG_INFINITY, f64::max)
                .floor()
                .min(w as f64 - 1.0);
            let ymin = s.iter().map(|q| q[1]).fold(f64::INFINITY, f64::min).ceil().max(0.0) as usize;
            let ymax = s
                .iter()
                .map(|q| q[1])
                .fold(f64::NEG_INFINITY, f64::max)
                .floor()
                .min(h as f64 - 1.0);
            if xmax < 0.0 || ymax < 0.0 {
                continue;
            }
            let (xmax, ymax) = (xmax as usize, ymax as usize);
            let inv_z = [1.0 / p[0].z, 1.0 / p[1].z, 1.0 / p[2].z];
            let cols = [
                mesh.colors[tri[0] as usize],
                mesh.colors[tri[1] as usize],
                mesh.colors[tri[2] as usize],
            ];
            for y in ymin..=ymax {
                let py = y as f64;
                for x in xmin..=xmax {
                    let px = x as f64;
                    let w0 = ((s[1][0] - px) * (s[2][1] - py) - (s[2][0] - px) * (s[1][1] - py)) / area;
                    let w1 = ((s[2][0] - px) * (s[0][1] - py) - (s[0][0] - px) * (s[2][1] - py)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                        continue;
                    }
                    let z = 1.0 / (w0 * inv_z[0] + w1 * inv_z[1] + w2 * inv_z[2]);
                    let i = y * w + x;
                    if (z as f32) < zbuf[i] {
                        zbuf[i] = z as f32;
                        let mut c = [0u8; 3];
                        for (ch, cv) in c.iter_mut().enumerate() {
                            let v = w0 * cols[0][ch] as f64 + w1 * cols[1][ch] as f64 + w2 * cols[2][ch] as f64;
                            *cv = v.round().clamp(0.0, 255.0) as u8;
                        }
                        color[i] = c;
                        instance[i] = oi as u16 + 1;
                    }
                }
            }
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

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
}
