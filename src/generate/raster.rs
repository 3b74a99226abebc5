//! CPU silhouettes of a mesh (coverage only, no depth test) and the BOP `scene_gt_info` fields
//! computed from them and from the rendered instance mask.
//!
//! The silhouette of an object "rendered alone" is the union of its projected triangles, so no
//! depth buffer is needed; pixels are sampled at their centres (`(x, y)` in pixel coordinates,
//! as BOP, OpenCV and [`crate::camera::Intrinsics::project`] have them) like the GPU's rasteriser.

use crate::camera::Intrinsics;
use crate::dataset::GtInfo;
use crate::geometry::Pose;
use crate::mesh::Mesh;

/// Triangles with a vertex closer than this to the camera plane are skipped, metres.
pub const SILHOUETTE_NEAR_M: f64 = 0.01;

/// The silhouette of `mesh` at `camera_from_object`: true where some triangle covers the
/// pixel centre.
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
        let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        if area.abs() < 1e-12 {
            continue;
        }
        let s = area.signum();
        let min_x = a[0].min(b[0]).min(c[0]);
        let max_x = a[0].max(b[0]).max(c[0]);
        let min_y = a[1].min(b[1]).min(c[1]);
        let max_y = a[1].max(b[1]).max(c[1]);
        if max_x < -0.5 || max_y < -0.5 || min_x >= w as f64 - 0.5 || min_y >= h as f64 - 0.5 {
            continue;
        }
        // pixels whose centre (x, y) lies in [min_x, max_x] x [min_y, max_y]
        let x0 = min_x.ceil().max(0.0) as usize;
        let x1 = (max_x.floor() as i64).min(w as i64 - 1);
        let y0 = min_y.ceil().max(0.0) as usize;
        let y1 = (max_y.floor() as i64).min(h as i64 - 1);
        if x1 < x0 as i64 || y1 < y0 as i64 {
            continue;
        }
        let edge =
            |p: [f64; 2], q: [f64; 2], x: f64, y: f64| ((q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0])) * s;
        for y in y0..=y1 as usize {
            let py = y as f64;
            let row = &mut mask[y * w..(y + 1) * w];
            for (x, m) in row.iter_mut().enumerate().take(x1 as usize + 1).skip(x0) {
                if *m {
                    continue;
                }
                let px = x as f64;
                if edge(a, b, px, py) >= 0.0 && edge(b, c, px, py) >= 0.0 && edge(c, a, px, py) >= 0.0 {
                    *m = true;
                }
            }
        }
    }
    mask
}

/// `[x, y, width, height]` of the true pixels, `[-1, -1, -1, -1]` when there are none (BOP).
pub fn bbox_of(mask: &[bool], width: u32) -> [i64; 4] {
    let w = width as usize;
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0usize, 0usize);
    for (i, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        let (x, y) = (i % w, i / w);
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if x0 == usize::MAX {
        return [-1, -1, -1, -1];
    }
    [x0 as i64, y0 as i64, (x1 - x0 + 1) as i64, (y1 - y0 + 1) as i64]
}

/// BOP `scene_gt_info` of one instance from its silhouette alone and its visible mask.
pub fn gt_info(alone: &[bool], visible: &[bool], width: u32) -> GtInfo {
    let all = alone.iter().filter(|m| **m).count() as u64;
    let visib = visible.iter().filter(|m| **m).count() as u64;
    GtInfo {
        bbox_obj: Some(bbox_of(alone, width)),
        bbox_visib: Some(bbox_of(visible, width)),
        px_count_all: Some(all),
        px_count_visib: Some(visib),
        visib_fract: Some(if all == 0 {
            0.0
        } else {
            (visib as f64 / all as f64).min(1.0)
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    #[test]
    fn a_box_facing_the_camera_covers_its_projected_rectangle() {
        // a 0.2 x 0.1 m face at 1 m with f = 100 px: 20 x 10 px
        let mesh = crate::mesh::builtin_box([0.2, 0.1, 0.05], [[1, 1, 1], [2, 2, 2]]);
        let k = Intrinsics::from_focal(64, 48, 100.0).unwrap();
        let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.025), UnitQuaternion::identity());
        let m = silhouette(&mesh, &pose, &k);
        let n = m.iter().filter(|v| **v).count();
        // the back face (at 1.05 m) is smaller: the front face's 20 x 10 dominates
        assert_eq!(n, 20 * 10, "{n} px");
        assert_eq!(bbox_of(&m, 64), [22, 19, 20, 10]);
        let half: Vec<bool> = m.iter().enumerate().map(|(i, v)| *v && i % 64 < 32).collect();
        let info = gt_info(&m, &half, 64);
        assert_eq!(info.px_count_visib, Some(100));
        assert_eq!(info.visib_fract, Some(0.5));
        assert_eq!(info.bbox_visib, Some([22, 19, 10, 10]));
        // behind the camera: nothing
        let behind = Isometry3::from_parts(Translation3::new(0.0, 0.0, -1.0), UnitQuaternion::identity());
        let e = silhouette(&mesh, &behind, &k);
        assert!(!e.iter().any(|v| *v));
        assert_eq!(gt_info(&e, &e, 64).bbox_obj, Some([-1, -1, -1, -1]));
        assert_eq!(gt_info(&e, &e, 64).visib_fract, Some(0.0));
    }
}
