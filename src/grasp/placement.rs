//! Candidates moved to where they keep their margin: each grasp of [`generate_candidates`] is
//! shifted across the pads, along the approach and turned about the approach while that makes
//! it succeed on more poses of a fixed, object-centred noise (a few millimetres and degrees).
//!
//! The candidates centre the gripper on the object's hull, which puts a mug's body or a drill's
//! handle near a pad's edge, outside the groove that centres it: at 3 mm of translation noise
//! such a grasp fails on about half the poses where one moved by a few millimetres fails on a
//! tenth. The moves are chosen on the object and the gripper alone, never on a track's samples
//! (a tracked distribution holds about a hundred particles; moves chosen on them fit those poses
//! rather than their uncertainty), and a move is kept only where a second, independent draw
//! confirms its gain. The placed grasps join the centred ones; the decision ranks all of them on
//! the track's samples as before. Computed once per object solid and gripper, then cached.

use super::candidates::{Grasp, generate_candidates};
use super::decision::Planning;
use super::{GraspError, GraspObject, Gripper};
use crate::geometry::{Pose, PoseSamples};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// Per-axis standard deviation of the translation noise the placement is chosen under.
pub const PLACEMENT_NOISE_M: f64 = 0.004;
/// Per-axis standard deviation (of the rotation vector) of its rotation noise.
pub const PLACEMENT_NOISE_RAD: f64 = 0.0524;
/// Poses per draw (the search's and the confirming one).
pub const PLACEMENT_SAMPLES: usize = 300;
/// A placed grasp is kept when it beats its centred one by this share on the second draw.
pub const PLACEMENT_MIN_GAIN: f64 = 0.03;
/// Moves per step: across the pads (gripper y), along the approach (gripper z), about the
/// approach.
const MOVE_ACROSS_M: f64 = 0.003;
const MOVE_ALONG_M: f64 = 0.004;
const MOVE_TURN_RAD: f64 = 0.105;
/// Greedy steps at most (a move of at most this many steps in each direction).
const MAX_STEPS: usize = 5;
/// Seeds of the two draws.
const SEARCH_SEED: u64 = 0x9e37;
const CONFIRM_SEED: u64 = 0x7f4a;

type Key = (String, String);
/// One slot per solid and gripper, locked while its search runs: a second caller waits for
/// the first one's result instead of searching again.
type Slot = Arc<Mutex<Option<Arc<Vec<Grasp>>>>>;
type Cache = Mutex<HashMap<Key, Slot>>;
/// Solid and gripper pairs kept; past it the finished ones are dropped (and searched again
/// when asked), so that a server whose meshes are replaced for months does not grow.
const MAX_CACHED: usize = 256;

fn cache() -> &'static Cache {
    static CACHE: OnceLock<Cache> = OnceLock::new();
    CACHE.get_or_init(|| Mutex::new(HashMap::new()))
}

/// The centred candidates of [`generate_candidates`] followed by the placed ones that kept
/// their gain (labelled `..., placed`). Cached per object solid and gripper.
pub fn placed_candidates(object: &GraspObject, gripper: &Gripper) -> Result<Arc<Vec<Grasp>>, GraspError> {
    let slot = {
        let mut map = cache().lock().unwrap_or_else(|e| e.into_inner());
        let key = key(object, gripper);
        if !map.contains_key(&key) && map.len() >= MAX_CACHED {
            // a slot whose search runs is locked: it stays
            map.retain(|_, s| s.try_lock().is_err());
        }
        map.entry(key).or_default().clone()
    };
    let mut slot = slot.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(all) = slot.as_ref() {
        return Ok(all.clone());
    }
    let all = Arc::new(search_placements(object, gripper)?);
    *slot = Some(all.clone());
    Ok(all)
}

/// What [`placed_candidates`] has cached for this solid and gripper, without searching (and
/// `None` while a search for them runs).
pub fn cached_placements(object: &GraspObject, gripper: &Gripper) -> Option<Arc<Vec<Grasp>>> {
    let slot = cache()
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .get(&key(object, gripper))?
        .clone();
    slot.try_lock().ok()?.clone()
}

fn key(object: &GraspObject, gripper: &Gripper) -> Key {
    (
        format!("{}/{:?}", object.content_hash(), object.kind()),
        gripper.to_json(),
    )
}

/// [`placed_candidates`] without the cache: the centred candidates and the search (what the
/// first decision about an object pays; `cargo bench --bench grasp -- place`).
pub fn search_placements(object: &GraspObject, gripper: &Gripper) -> Result<Vec<Grasp>, GraspError> {
    let mut all = generate_candidates(object, gripper);
    let placed = place(object, gripper, &all)?;
    all.extend(placed);
    Ok(all)
}

/// The placed grasps of `centred` that gained on the confirming draw: per approach and
/// closing axis, the best placed grasp when it beats the best centred one of those axes (a
/// deep and a shallow candidate share them) by [`PLACEMENT_MIN_GAIN`].
fn place(object: &GraspObject, gripper: &Gripper, centred: &[Grasp]) -> Result<Vec<Grasp>, GraspError> {
    let origin = Pose::identity();
    let draw = |seed| {
        PoseSamples::gaussian(
            &origin,
            [PLACEMENT_NOISE_M; 3],
            [PLACEMENT_NOISE_RAD; 3],
            PLACEMENT_SAMPLES,
            seed,
        )
        .poses
    };
    let (search, confirm) = (draw(SEARCH_SEED), draw(CONFIRM_SEED));
    let planning = Planning::new(object, gripper, &origin, None);
    let mut groups: Vec<AxisGroup> = Vec::new();
    for g in centred {
        let mut best = g.object_from_gripper;
        let mut best_k = planning.count_successes(&search, g)?;
        for _ in 0..MAX_STEPS {
            let mut step: Option<(Pose, usize)> = None;
            for m in moves() {
                let pose = best * m;
                let k = planning.count_successes(&search, &Grasp::from_pose(object, pose, &g.label))?;
                if k > step.map_or(best_k, |s| s.1) {
                    step = Some((pose, k));
                }
            }
            match step {
                Some((pose, k)) => (best, best_k) = (pose, k),
                None => break,
            }
        }
        let at = match groups
            .iter()
            .position(|a| a.approach == g.approach_in_object && a.closing == g.closing_in_object)
        {
            Some(i) => i,
            None => {
                groups.push(AxisGroup {
                    approach: g.approach_in_object,
                    closing: g.closing_in_object,
                    centred_successes: 0,
                    placed: None,
                });
                groups.len() - 1
            }
        };
        let group = &mut groups[at];
        group.centred_successes = group.centred_successes.max(planning.count_successes(&confirm, g)?);
        if best != g.object_from_gripper {
            let placed = Grasp::from_pose(object, best, &format!("{}, placed", g.label));
            let k = planning.count_successes(&confirm, &placed)?;
            if group.placed.as_ref().is_none_or(|(_, b)| k > *b) {
                group.placed = Some((placed, k));
            }
        }
    }
    let min_gain = PLACEMENT_MIN_GAIN * confirm.len() as f64;
    Ok(groups
        .into_iter()
        .filter_map(|a| {
            let centred = a.centred_successes as f64;
            a.placed.filter(|(_, k)| *k as f64 - centred >= min_gain)
        })
        .map(|(g, _)| g)
        .collect())
}

/// The candidates of one approach and closing axis on the confirming draw: the best centred
/// one's successes and the best placed grasp with its successes.
struct AxisGroup {
    approach: [f64; 3],
    closing: [f64; 3],
    centred_successes: usize,
    placed: Option<(Grasp, usize)>,
}

/// One step of each move, both ways, in the gripper frame (applied on the right).
fn moves() -> [Pose; 6] {
    let shift = |v: Vector3<f64>| Pose::from_parts(Translation3::from(v), UnitQuaternion::identity());
    let turn = |a: f64| {
        Pose::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_scaled_axis(Vector3::z() * a),
        )
    };
    [
        shift(Vector3::y() * MOVE_ACROSS_M),
        shift(-Vector3::y() * MOVE_ACROSS_M),
        shift(Vector3::z() * MOVE_ALONG_M),
        shift(-Vector3::z() * MOVE_ALONG_M),
        turn(MOVE_TURN_RAD),
        turn(-MOVE_TURN_RAD),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rate(object: &GraspObject, gripper: &Gripper, g: &Grasp, seed: u64) -> f64 {
        let origin = Pose::identity();
        let poses = PoseSamples::gaussian(&origin, [0.003; 3], [0.0; 3], 400, seed).poses;
        let planning = Planning::new(object, gripper, &origin, None);
        planning.count_successes(&poses, g).expect("count") as f64 / poses.len() as f64
    }

    /// The built-in mug: its handle puts the hull's centre off the body's axis.
    fn mug() -> GraspObject {
        GraspObject::new(&crate::mesh::builtin_mug()).expect("solid")
    }

    #[test]
    fn a_grasp_off_its_robust_spot_is_placed_back() {
        let gripper = Gripper::default_parallel_jaw();
        let object = mug();
        let all = placed_candidates(&object, &gripper).expect("candidates");
        let centred = generate_candidates(&object, &gripper);
        assert!(all.len() > centred.len(), "some grasp gained by moving");
        assert_eq!(
            &all[..centred.len()],
            &centred[..],
            "the centred ones come first, unchanged"
        );
        // on a draw neither choice saw, the best placed grasp beats the best centred one
        let best = |gs: &[Grasp]| gs.iter().map(|g| rate(&object, &gripper, g, 11)).fold(0.0, f64::max);
        let (c, p) = (best(&centred), best(&all[centred.len()..]));
        assert!(p > c + 0.05, "placed {p} vs centred {c}");
        // cached: the same list, not a new search
        assert!(Arc::ptr_eq(&all, &placed_candidates(&object, &gripper).expect("again")));
    }

    #[test]
    fn a_placed_grasp_keeps_its_gain_on_poses_it_never_saw() {
        let gripper = Gripper::default_parallel_jaw();
        let origin = Pose::identity();
        let unseen = PoseSamples::gaussian(&origin, [PLACEMENT_NOISE_M; 3], [PLACEMENT_NOISE_RAD; 3], 600, 23).poses;
        for object in [
            mug(),
            GraspObject::new(&crate::mesh::builtin("box").expect("box")).expect("box"),
            GraspObject::new(&crate::mesh::builtin("can").expect("can")).expect("can"),
        ] {
            let planning = Planning::new(&object, &gripper, &origin, None);
            let rate = |g: &Grasp| planning.count_successes(&unseen, g).expect("count") as f64 / unseen.len() as f64;
            let all = placed_candidates(&object, &gripper).expect("candidates");
            let centred = generate_candidates(&object, &gripper);
            for p in &all[centred.len()..] {
                let same_axes = centred.iter().filter(|c| {
                    c.approach_in_object == p.approach_in_object && c.closing_in_object == p.closing_in_object
                });
                let best = same_axes.map(&rate).fold(0.0, f64::max);
                assert!(rate(p) >= best, "{}: {} against {best}", p.label, rate(p));
            }
        }
    }
}
