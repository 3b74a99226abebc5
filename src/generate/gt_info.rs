//! BOP's `scene_gt_info` fields (boxes, pixel counts, visible fraction) from an object's
//! silhouette rendered alone ([`crate::render::raster::silhouette`]) and its visible mask.

use crate::dataset::GtInfo;

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

    #[test]
    fn boxes_and_fractions_of_a_silhouette() {
        // a 20 x 10 px rectangle with its top-left pixel at (22, 19) in a 64 x 48 image
        let m: Vec<bool> = (0..64 * 48)
            .map(|i| (22..42).contains(&(i % 64)) && (19..29).contains(&(i / 64)))
            .collect();
        assert_eq!(bbox_of(&m, 64), [22, 19, 20, 10]);
        let half: Vec<bool> = m.iter().enumerate().map(|(i, v)| *v && i % 64 < 32).collect();
        let info = gt_info(&m, &half, 64);
        assert_eq!(info.px_count_all, Some(200));
        assert_eq!(info.px_count_visib, Some(100));
        assert_eq!(info.visib_fract, Some(0.5));
        assert_eq!(info.bbox_visib, Some([22, 19, 10, 10]));
        let e = vec![false; 64 * 48];
        assert_eq!(gt_info(&e, &e, 64).bbox_obj, Some([-1, -1, -1, -1]));
        assert_eq!(gt_info(&e, &e, 64).visib_fract, Some(0.0));
    }
}
