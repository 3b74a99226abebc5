//! Ground truth for scoring (never for the filter): true object poses in the reference
//! camera's frame at a time step, and the association of tracks to true instances.

use crate::dataset::Sequence;
use crate::geometry::Pose;

/// One true object instance at a time step, in the reference frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TrueObject {
    pub obj_id: u32,
    pub name: String,
    /// Index of the instance among those of the same `obj_id` (0 for the first).
    pub instance: usize,
    pub reference_from_object: Pose,
}

/// The true `reference_from_world` at a frame: the reference camera's `cam_R_w2c` (ground
/// truth for a robot camera, calibration for a stationary one), `None` where it has none.
pub fn reference_from_world(seq: &Sequence, frame: u32) -> Option<Pose> {
    seq.cameras
        .get(&seq.rig.reference_camera)?
        .frames
        .get(&frame)?
        .camera_from_world
}

/// Distance (m) from the robot camera (the reference camera in a rig without one) to a point
/// given in the reference frame at `frame`: through the robot camera's and the reference
/// camera's true poses when they differ; `None` where those are not known.
pub fn camera_distance_m(seq: &Sequence, frame: u32, reference_from_object: &Pose) -> Option<f64> {
    let robot = seq.rig.robot_camera().unwrap_or(seq.rig.reference_camera.as_str());
    let point = reference_from_object.translation.vector;
    if robot == seq.rig.reference_camera {
        return Some(point.norm());
    }
    let robot_from_world = seq.cameras.get(robot)?.frames.get(&frame)?.camera_from_world?;
    let robot_from_reference = robot_from_world * reference_from_world(seq, frame)?.inverse();
    Some((robot_from_reference * nalgebra::Point3::from(point)).coords.norm())
}

/// True poses of every object at a frame in the reference camera's frame: from the reference
/// camera's `scene_gt.json` when it has the frame, else from another camera's ground truth
/// moved through the world frame (that camera's calibration and the reference camera's true
/// pose). Empty when neither is possible.
pub fn objects_in_reference(seq: &Sequence, frame: u32) -> Vec<TrueObject> {
    let reference = &seq.rig.reference_camera;
    let from_list = |list: &[crate::dataset::GtObject], reference_from_camera: Pose| {
        let mut seen: std::collections::BTreeMap<u32, usize> = Default::default();
        list.iter()
            .map(|g| {
                let k = seen.entry(g.obj_id).or_insert(0);
                let instance = *k;
                *k += 1;
                TrueObject {
                    obj_id: g.obj_id,
                    name: seq.rig.object_name(g.obj_id),
                    instance,
                    reference_from_object: reference_from_camera * g.camera_from_object,
                }
            })
            .collect::<Vec<_>>()
    };
    if let Some(list) = seq.cameras.get(reference).and_then(|c| c.gt.get(&frame)) {
        return from_list(list, Pose::identity());
    }
    let Some(reference_from_world) = reference_from_world(seq, frame) else {
        return Vec::new();
    };
    for (name, cam) in &seq.cameras {
        if name == reference {
            continue;
        }
        let (Some(list), Some(camera_from_world)) = (
            cam.gt.get(&frame),
            cam.frames.get(&frame).and_then(|f| f.camera_from_world),
        ) else {
            continue;
        };
        return from_list(list, reference_from_world * camera_from_world.inverse());
    }
    Vec::new()
}

/// Greedy one-to-one association of estimates to true instances by position: repeatedly the
/// closest remaining (estimate, truth) pair. Returns for each truth the index of its estimate.
/// (Scoring only: the association reads ground truth, the filter never does.)
pub fn associate(estimates_m: &[[f64; 3]], truths_m: &[[f64; 3]]) -> Vec<Option<usize>> {
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (i, e) in estimates_m.iter().enumerate() {
        for (j, t) in truths_m.iter().enumerate() {
            let d = (0..3).map(|k| (e[k] - t[k]).powi(2)).sum::<f64>();
            pairs.push((d, i, j));
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out = vec![None; truths_m.len()];
    let mut used = vec![false; estimates_m.len()];
    for (_, i, j) in pairs {
        if !used[i] && out[j].is_none() {
            used[i] = true;
            out[j] = Some(i);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn greedy_association_is_one_to_one() {
        let est = [[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [3.0, 0.0, 0.0]];
        let truth = [[0.45, 0.0, 1.0], [0.05, 0.0, 1.0]];
        assert_eq!(associate(&est, &truth), vec![Some(1), Some(0)]);
        assert_eq!(associate(&[], &truth), vec![None, None]);
        assert_eq!(associate(&est[..1], &truth), vec![None, Some(0)]);
    }

    #[test]
    fn real_sequence_truth_is_in_the_reference_camera() {
        let shared = crate::testing::shared_dir();
        let seq = Sequence::open(&shared.join("realdata/ycbv_video_0000/bop")).expect("real data");
        let objs = objects_in_reference(&seq, 1);
        assert_eq!(objs.len(), 1);
        assert_eq!(objs[0].name, "025_mug");
        // cam_t_m2c of frame 1 is (62.7, -26.4, 622.2) mm.
        let t = objs[0].reference_from_object.translation.vector;
        assert!((t.z - 0.6222).abs() < 1e-3 && (t.x - 0.0627).abs() < 1e-3, "{t:?}");
        assert!(objects_in_reference(&seq, 999).is_empty());
        // One camera: the distance is the object's from it.
        let d = camera_distance_m(&seq, 1, &objs[0].reference_from_object).expect("distance");
        assert!((d - t.norm()).abs() < 1e-12 && d > 0.6, "{d}");
    }
}
