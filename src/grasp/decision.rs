//! The grasp-or-observe decision: the per-sample tests, the Wilson interval on the effective
//! sample size, and the reasons (which test fails, which direction of uncertainty drives it).

use super::candidates::{Grasp, generate_candidates};
use super::{GraspError, GraspObject, Gripper, SupportPlane, convert};
use crate::geometry::{Pose, PoseSamples};
use nalgebra::{Point3, Vector3};
use parry3d::math::{Pose as PPose, Vector as PVector};
use parry3d::query::{self, ShapeCastOptions};
use parry3d::shape::{Cuboid, Shape};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Default number of pose samples.
pub const DEFAULT_N_SAMPLES: usize = 1000;
/// Default threshold on the lower bound of the 95% interval.
pub const DEFAULT_THRESHOLD: f64 = 0.9;
/// z of the normal distribution for a two-sided 95% interval.
const Z95: f64 = 1.959_963_984_540_054;
/// A pad contact counts as first contact when it comes this close after the finger's.
const FIRST_CONTACT_TOLERANCE_M: f32 = 0.0005;
/// The groove holds the contact when it touches this close after the full pad.
const GROOVE_TOLERANCE_M: f32 = 0.0001;
/// Two contact normals this close belong to one flat face.
const SAME_FACE_DEG: f64 = 0.5;
/// An axis of uncertainty is named as driving a failure above this correlation.
pub const DRIVER_MIN_CORRELATION: f64 = 0.1;

/// What the caller asks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecisionQuery {
    /// How many of the given samples to use (0 = all).
    pub n_samples: usize,
    /// Grasp only when the lower bound of the 95% interval on p_success reaches this.
    pub threshold: f64,
    /// The grasp to check; `None`: generate candidates and take the best.
    pub grasp: Option<Grasp>,
    /// The table, in the frame of the samples.
    pub support_plane: Option<SupportPlane>,
}

impl Default for DecisionQuery {
    fn default() -> Self {
        Self {
            n_samples: DEFAULT_N_SAMPLES,
            threshold: DEFAULT_THRESHOLD,
            grasp: None,
            support_plane: None,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Grasp,
    Observe,
}

/// The tests run on every sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureTest {
    /// The open gripper hits the object on its way in.
    Approach,
    /// A gripper part comes closer to the support plane than the clearance.
    Table,
    /// Closing does not bring both pads onto the object first.
    Contact,
    /// A pad contact lies outside the capture funnel (groove mouth / wall angle).
    Alignment,
}

impl FailureTest {
    pub const ALL: [FailureTest; 4] = [Self::Approach, Self::Table, Self::Contact, Self::Alignment];
    pub fn name(self) -> &'static str {
        match self {
            Self::Approach => "approach",
            Self::Table => "table",
            Self::Contact => "contact",
            Self::Alignment => "alignment",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Motion {
    Translation,
    Rotation,
}

/// One direction of the pose uncertainty, in the gripper frame of the planned grasp.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AxisDriver {
    pub motion: Motion,
    /// `gripper_x`, `gripper_y` or `gripper_z` (x = closing, z = approach).
    pub axis: String,
    /// The same axis in the reference (robot camera) frame.
    pub axis_in_reference: [f64; 3],
    /// Standard deviation of the samples' offset from the estimate along/about this axis
    /// (metres or radians).
    pub spread: f64,
    /// Correlation between failing and the size of the offset along/about this axis.
    pub failure_correlation: f64,
}

/// The share of samples failing one test and what drives it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reason {
    pub test: FailureTest,
    pub failure_share: f64,
    /// Axes whose offsets correlate with this failure (>= [`DRIVER_MIN_CORRELATION`]),
    /// strongest first.
    pub drivers: Vec<AxisDriver>,
    pub message: String,
}

/// A candidate grasp with its probability of success.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RankedGrasp {
    pub grasp: Grasp,
    pub p_success: f64,
    pub ci95: [f64; 2],
}

/// The answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Decision {
    pub decision: Verdict,
    pub p_success: f64,
    pub ci95: [f64; 2],
    pub n_samples: usize,
    pub effective_sample_size: f64,
    pub threshold: f64,
    pub grasp: Grasp,
    pub reference_from_gripper: Pose,
    /// One entry per test that fails on some sample, largest share first.
    pub reasons: Vec<Reason>,
    /// All six axes (3 translations, 3 rotations) with their correlation to failing overall,
    /// strongest first.
    pub uncertainty: Vec<AxisDriver>,
    /// The candidates evaluated (only when the query gave no grasp), best first.
    pub candidates: Vec<RankedGrasp>,
}

impl Decision {
    /// The same tests on one object pose (e.g. ground truth) with this decision's gripper pose.
    pub fn success_on_pose(
        &self,
        object: &GraspObject,
        gripper: &Gripper,
        reference_from_object: &Pose,
        plane: Option<&SupportPlane>,
    ) -> bool {
        success_on_pose(object, gripper, &self.reference_from_gripper, reference_from_object, plane)
    }

    /// Axes driving the failures overall (correlation >= [`DRIVER_MIN_CORRELATION`]).
    pub fn driving_axes(&self) -> impl Iterator<Item = &AxisDriver> {
        self.uncertainty
            .iter()
            .filter(|a| a.failure_correlation >= DRIVER_MIN_CORRELATION)
    }
}

/// The result of the tests on one object pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct PoseOutcome {
    pub approach_clear: bool,
    pub table_clear: bool,
    pub contact: bool,
    pub aligned: bool,
}

impl PoseOutcome {
    pub fn success(&self) -> bool {
        self.approach_clear && self.table_clear && self.contact && self.aligned
    }
    pub fn failed(&self, test: FailureTest) -> bool {
        match test {
            FailureTest::Approach => !self.approach_clear,
            FailureTest::Table => !self.table_clear,
            FailureTest::Contact => !self.contact,
            FailureTest::Alignment => !self.aligned,
        }
    }
}

/// The gripper's parts as parry shapes at their places in the gripper frame.
struct GripperShapes {
    palm: Cuboid,
    finger: Cuboid,
    pad: Cuboid,
    groove: Cuboid,
    palm_pose: PPose,
    /// [+x, -x] at full opening.
    finger_pose: [PPose; 2],
    pad_pose: [PPose; 2],
    approach_m: f32,
    closing_travel_m: f32,
    cos_capture: f64,
}

impl GripperShapes {
    fn new(g: &Gripper) -> Self {
        let c = |v: Vector3<f64>| convert::vector_to_parry(&v);
        let at = |v: Vector3<f64>| PPose::from_translation(c(v));
        let (pad_half, pad_p) = g.pad_box(1.0, g.max_opening_m);
        let (_, pad_m) = g.pad_box(-1.0, g.max_opening_m);
        let mut groove_half = pad_half;
        groove_half.y = g.pad.groove_half_width_m;
        Self {
            palm: Cuboid::new(c(g.palm_half_extents())),
            finger: Cuboid::new(c(g.finger_half_extents())),
            pad: Cuboid::new(c(pad_half)),
            groove: Cuboid::new(c(groove_half)),
            palm_pose: at(g.palm_center()),
            finger_pose: [
                at(g.finger_center(1.0, g.max_opening_m)),
                at(g.finger_center(-1.0, g.max_opening_m)),
            ],
            pad_pose: [at(pad_p), at(pad_m)],
            approach_m: g.approach_distance_m as f32,
            closing_travel_m: (g.max_opening_m - g.min_opening_m) as f32,
            cos_capture: g.pad.capture_angle_deg.to_radians().cos(),
        }
    }

    /// Open gripper swept from `approach_m` before the grasp pose to it: any hit fails.
    fn approach_clear(&self, obj_pose: &PPose, obj: &dyn Shape) -> bool {
        let back = PVector::new(0.0, 0.0, -self.approach_m);
        let parts: [(&PPose, &Cuboid); 3] = [
            (&self.finger_pose[0], &self.finger),
            (&self.finger_pose[1], &self.finger),
            (&self.palm_pose, &self.palm),
        ];
        for (pose, shape) in parts {
            let hit = if self.approach_m > 0.0 {
                let start = pose.prepend_translation(back);
                let opts = ShapeCastOptions::with_max_time_of_impact(self.approach_m);
                query::cast_shapes(&start, PVector::Z, shape, obj_pose, PVector::ZERO, obj, opts)
                    .map(|h| h.is_some())
            } else {
                query::intersection_test(pose, shape, obj_pose, obj).map(|i| i.intersecting)
            };
            // an unsupported pair cannot be shown clear
            if hit.unwrap_or(true) {
                return false;
            }
        }
        true
    }

    /// (contact, aligned) when the fingers close on the object.
    fn closing(&self, obj_pose: &PPose, obj: &dyn Shape) -> (bool, bool) {
        let opts = ShapeCastOptions::with_max_time_of_impact(self.closing_travel_m);
        let mut aligned = true;
        for (k, side) in [1.0f32, -1.0].into_iter().enumerate() {
            let vel = PVector::new(-side, 0.0, 0.0);
            let cast = |pose: &PPose, shape: &Cuboid| {
                query::cast_shapes(pose, vel, shape, obj_pose, PVector::ZERO, obj, opts)
                    .ok()
                    .flatten()
            };
            let Some(pad) = cast(&self.pad_pose[k], &self.pad) else {
                return (false, false);
            };
            if pad.time_of_impact <= 0.0 {
                // already touching or inside at full opening: not a closing contact
                return (false, false);
            }
            let Some(finger) = cast(&self.finger_pose[k], &self.finger) else {
                return (false, false);
            };
            if pad.time_of_impact > finger.time_of_impact + FIRST_CONTACT_TOLERANCE_M {
                return (false, false);
            }
            if !aligned {
                continue;
            }
            // object normal at the pad contact, gripper frame; it must face the pad (+side x)
            let n_pad = obj_pose.rotation * pad.normal2;
            let outward = Vector3::new(side as f64, 0.0, 0.0);
            let n_pad = convert::vector_from_parry(n_pad);
            if n_pad.normalize().dot(&outward) < self.cos_capture {
                aligned = false;
                continue;
            }
            let groove = cast(&self.pad_pose[k], &self.groove);
            aligned = match groove {
                None => false,
                Some(gr) if gr.time_of_impact <= pad.time_of_impact + GROOVE_TOLERANCE_M => true,
                Some(gr) => {
                    // the pad met a flat face at its edge: it squares the face onto itself
                    let n_gr = convert::vector_from_parry(obj_pose.rotation * gr.normal2);
                    n_gr.normalize().dot(&n_pad.normalize()) >= SAME_FACE_DEG.to_radians().cos()
                }
            };
        }
        (true, aligned)
    }
}

/// Least signed distance of the gripper's parts (open, at the grasp pose and at the pre-grasp
/// pose) to the plane, gripper frame.
fn table_clearance_m(g: &Gripper, plane_in_gripper: &SupportPlane) -> Result<f64, GraspError> {
    let (n, p) = plane_in_gripper.unit()?;
    let boxes = [
        (g.palm_center(), g.palm_half_extents()),
        (g.finger_center(1.0, g.max_opening_m), g.finger_half_extents()),
        (g.finger_center(-1.0, g.max_opening_m), g.finger_half_extents()),
    ];
    let mut least = f64::INFINITY;
    for shift in [0.0, -g.approach_distance_m] {
        for (c, h) in boxes {
            let centre = Point3::from(c + Vector3::new(0.0, 0.0, shift));
            // lowest corner along n: centre - sum |n_i| h_i
            let reach = n.x.abs() * h.x + n.y.abs() * h.y + n.z.abs() * h.z;
            least = least.min((centre - p).dot(&n) - reach);
        }
    }
    Ok(least)
}

fn evaluate_in_gripper(
    shapes: &GripperShapes,
    object: &GraspObject,
    gripper_from_object: &Pose,
    table_clear: bool,
) -> PoseOutcome {
    let obj_pose = convert::pose_to_parry(gripper_from_object);
    let obj: &dyn Shape = &**object.shape();
    let approach_clear = shapes.approach_clear(&obj_pose, obj);
    let (contact, aligned) = shapes.closing(&obj_pose, obj);
    PoseOutcome {
        approach_clear,
        table_clear,
        contact,
        aligned: contact && aligned,
    }
}

/// All tests on one object pose with a planned gripper pose (both in the reference frame).
pub fn evaluate_pose(
    object: &GraspObject,
    gripper: &Gripper,
    reference_from_gripper: &Pose,
    reference_from_object: &Pose,
    plane: Option<&SupportPlane>,
) -> Result<PoseOutcome, GraspError> {
    let shapes = GripperShapes::new(gripper);
    let gripper_from_reference = reference_from_gripper.inverse();
    let table_clear = match plane {
        Some(pl) => {
            table_clearance_m(gripper, &pl.transformed(&gripper_from_reference))?
                >= gripper.table_clearance_m
        }
        None => true,
    };
    Ok(evaluate_in_gripper(
        &shapes,
        object,
        &(gripper_from_reference * reference_from_object),
        table_clear,
    ))
}

/// Whether the grasp planned at `reference_from_gripper` succeeds on the object at
/// `reference_from_object` (eval uses it on ground truth). An invalid plane counts as failure.
pub fn success_on_pose(
    object: &GraspObject,
    gripper: &Gripper,
    reference_from_gripper: &Pose,
    reference_from_object: &Pose,
    plane: Option<&SupportPlane>,
) -> bool {
    evaluate_pose(object, gripper, reference_from_gripper, reference_from_object, plane)
        .map(|o| o.success())
        .unwrap_or(false)
}

/// Wilson score interval for a proportion `p` observed on `n` (possibly fractional) trials.
pub fn wilson_interval(p: f64, n: f64) -> [f64; 2] {
    if !(n > 0.0) || !p.is_finite() {
        return [0.0, 1.0];
    }
    let z2 = Z95 * Z95;
    let denom = 1.0 + z2 / n;
    let centre = (p + z2 / (2.0 * n)) / denom;
    let half = Z95 * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt() / denom;
    [(centre - half).max(0.0), (centre + half).min(1.0)]
}

struct Evaluated {
    outcomes: Vec<PoseOutcome>,
    reference_from_gripper: Pose,
}

fn evaluate_grasp(
    object: &GraspObject,
    gripper: &Gripper,
    shapes: &GripperShapes,
    estimate: &Pose,
    poses: &[Pose],
    grasp: &Grasp,
    plane: Option<&SupportPlane>,
) -> Result<Evaluated, GraspError> {
    let reference_from_gripper = estimate * grasp.object_from_gripper;
    let gripper_from_reference = reference_from_gripper.inverse();
    let table_clear = match plane {
        Some(pl) => {
            table_clearance_m(gripper, &pl.transformed(&gripper_from_reference))?
                >= gripper.table_clearance_m
        }
        None => true,
    };
    let outcomes = poses
        .par_iter()
        .map(|p| evaluate_in_gripper(shapes, object, &(gripper_from_reference * p), table_clear))
        .collect();
    Ok(Evaluated {
        outcomes,
        reference_from_gripper,
    })
}

/// Plans the grasp on `estimate` (reference_from_object) and checks it on the samples.
///
/// With `query.grasp == None`, the candidates of [`generate_candidates`] are evaluated on the
/// same samples and the one with the highest p_success is chosen (all are returned, ranked).
/// `p_success` is the share of samples passing every test; its 95% Wilson interval uses the
/// effective sample size (scaled to the samples used, at most their number). The verdict is
/// `Grasp` only when the interval's lower bound reaches `query.threshold`.
pub fn decide(
    object: &GraspObject,
    gripper: &Gripper,
    estimate: &Pose,
    samples: &PoseSamples,
    query: &DecisionQuery,
) -> Result<Decision, GraspError> {
    gripper.validate()?;
    if !(query.threshold > 0.0 && query.threshold <= 1.0) {
        return Err(GraspError::InvalidQuery(format!(
            "threshold must be in (0, 1], got {}",
            query.threshold
        )));
    }
    if samples.poses.is_empty() {
        return Err(GraspError::NoSamples);
    }
    if let Some(pl) = &query.support_plane {
        pl.unit()?;
    }
    let n = if query.n_samples == 0 {
        samples.poses.len()
    } else {
        query.n_samples.min(samples.poses.len())
    };
    let poses = &samples.poses[..n];
    let ess = if samples.effective_sample_size.is_finite() && samples.effective_sample_size > 0.0 {
        (samples.effective_sample_size * n as f64 / samples.poses.len() as f64).min(n as f64)
    } else {
        n as f64
    };
    let shapes = GripperShapes::new(gripper);
    let plane = query.support_plane.as_ref();

    let (grasp, eval, candidates) = match &query.grasp {
        Some(g) => {
            let e = evaluate_grasp(object, gripper, &shapes, estimate, poses, g, plane)?;
            (g.clone(), e, Vec::new())
        }
        None => {
            let cands = generate_candidates(object, gripper);
            if cands.is_empty() {
                return Err(GraspError::NoCandidate(format!(
                    "every principal width exceeds the stroke of {} m",
                    gripper.max_opening_m
                )));
            }
            let mut ranked: Vec<(RankedGrasp, Evaluated)> = Vec::new();
            for g in cands {
                let e = evaluate_grasp(object, gripper, &shapes, estimate, poses, &g, plane)?;
                let p = share(&e.outcomes, |o| o.success());
                ranked.push((
                    RankedGrasp {
                        grasp: g,
                        p_success: p,
                        ci95: wilson_interval(p, ess),
                    },
                    e,
                ));
            }
            ranked.sort_by(|a, b| b.0.p_success.total_cmp(&a.0.p_success));
            let list: Vec<RankedGrasp> = ranked.iter().map(|(r, _)| r.clone()).collect();
            let (best, e) = ranked.swap_remove(0);
            (best.grasp, e, list)
        }
    };

    let p = share(&eval.outcomes, |o| o.success());
    let ci95 = wilson_interval(p, ess);
    let offsets = offsets_in_gripper(&eval.reference_from_gripper, estimate, poses);
    let reasons = reasons(&eval.outcomes, &offsets, &eval.reference_from_gripper);
    let failed: Vec<bool> = eval.outcomes.iter().map(|o| !o.success()).collect();
    let mut uncertainty = axis_drivers(&failed, &offsets, &eval.reference_from_gripper);
    uncertainty.sort_by(|a, b| b.failure_correlation.total_cmp(&a.failure_correlation));
    Ok(Decision {
        decision: if ci95[0] >= query.threshold {
            Verdict::Grasp
        } else {
            Verdict::Observe
        },
        p_success: p,
        ci95,
        n_samples: n,
        effective_sample_size: ess,
        threshold: query.threshold,
        grasp,
        reference_from_gripper: eval.reference_from_gripper,
        reasons,
        uncertainty,
        candidates,
    })
}

fn share(outcomes: &[PoseOutcome], f: impl Fn(&PoseOutcome) -> bool) -> f64 {
    if outcomes.is_empty() {
        return 0.0;
    }
    outcomes.iter().filter(|o| f(o)).count() as f64 / outcomes.len() as f64
}

/// Per sample: [translation x, y, z, rotation x, y, z] of the sample relative to the estimate,
/// in the gripper frame (translation of the object's origin; rotation vector of
/// R_sample * R_estimate^-1).
fn offsets_in_gripper(reference_from_gripper: &Pose, estimate: &Pose, poses: &[Pose]) -> Vec<[f64; 6]> {
    let g_from_r = reference_from_gripper.inverse();
    let planned = g_from_r * estimate;
    poses
        .iter()
        .map(|p| {
            let s = g_from_r * p;
            let t = s.translation.vector - planned.translation.vector;
            let r = (s.rotation * planned.rotation.inverse()).scaled_axis();
            [t.x, t.y, t.z, r.x, r.y, r.z]
        })
        .collect()
}

fn axis_drivers(failed: &[bool], offsets: &[[f64; 6]], reference_from_gripper: &Pose) -> Vec<AxisDriver> {
    (0..6)
        .map(|a| {
            let mags: Vec<f64> = offsets.iter().map(|o| o[a].abs()).collect();
            let vals: Vec<f64> = offsets.iter().map(|o| o[a]).collect();
            let axis = Vector3::ith(a % 3, 1.0);
            let r = reference_from_gripper.rotation * axis;
            AxisDriver {
                motion: if a < 3 { Motion::Translation } else { Motion::Rotation },
                axis: ["gripper_x", "gripper_y", "gripper_z"][a % 3].to_string(),
                axis_in_reference: [r.x, r.y, r.z],
                spread: std_dev(&vals),
                failure_correlation: point_biserial(failed, &mags),
            }
        })
        .collect()
}

fn std_dev(v: &[f64]) -> f64 {
    if v.len() < 2 {
        return 0.0;
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64).sqrt()
}

/// Pearson correlation between a 0/1 indicator and a value (0 when either is constant).
fn point_biserial(flag: &[bool], x: &[f64]) -> f64 {
    let n = x.len() as f64;
    if n < 2.0 {
        return 0.0;
    }
    let fm = flag.iter().filter(|&&f| f).count() as f64 / n;
    let xm = x.iter().sum::<f64>() / n;
    let (mut cov, mut vx) = (0.0, 0.0);
    for (f, v) in flag.iter().zip(x) {
        let df = if *f { 1.0 } else { 0.0 } - fm;
        cov += df * (v - xm);
        vx += (v - xm) * (v - xm);
    }
    let vf = fm * (1.0 - fm) * n;
    if vf <= 1e-12 || vx <= 1e-18 {
        return 0.0;
    }
    cov / (vf * vx).sqrt()
}

fn reasons(outcomes: &[PoseOutcome], offsets: &[[f64; 6]], reference_from_gripper: &Pose) -> Vec<Reason> {
    let mut out: Vec<Reason> = FailureTest::ALL
        .iter()
        .filter_map(|&test| {
            let failed: Vec<bool> = outcomes.iter().map(|o| o.failed(test)).collect();
            let s = failed.iter().filter(|&&f| f).count() as f64 / outcomes.len().max(1) as f64;
            if s == 0.0 {
                return None;
            }
            let mut drivers: Vec<AxisDriver> = axis_drivers(&failed, offsets, reference_from_gripper)
                .into_iter()
                .filter(|d| d.failure_correlation >= DRIVER_MIN_CORRELATION)
                .collect();
            drivers.sort_by(|a, b| b.failure_correlation.total_cmp(&a.failure_correlation));
            let what = match test {
                FailureTest::Approach => "the open gripper hits the object on the approach",
                FailureTest::Table => "the gripper comes too close to the support plane",
                FailureTest::Contact => "closing does not put both pads on the object",
                FailureTest::Alignment => "a pad contact lies outside the capture funnel",
            };
            let by = if drivers.is_empty() {
                String::new()
            } else {
                let names: Vec<String> = drivers
                    .iter()
                    .map(|d| {
                        format!(
                            "{} {} {}",
                            match d.motion {
                                Motion::Translation => "translation along",
                                Motion::Rotation => "rotation about",
                            },
                            d.axis,
                            match d.motion {
                                Motion::Translation => format!("(spread {:.1} mm)", d.spread * 1e3),
                                Motion::Rotation => format!("(spread {:.1} deg)", d.spread.to_degrees()),
                            }
                        )
                    })
                    .collect();
                format!("; driven by {}", names.join(", "))
            };
            Some(Reason {
                test,
                failure_share: s,
                drivers,
                message: format!("{:.1}% of samples: {what}{by}", s * 100.0),
            })
        })
        .collect();
    out.sort_by(|a, b| b.failure_share.total_cmp(&a.failure_share));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_matches_known_values() {
        // p = 0.5, n = 100: 0.4038 .. 0.5962
        let [lo, hi] = wilson_interval(0.5, 100.0);
        assert!((lo - 0.4038).abs() < 1e-3 && (hi - 0.5962).abs() < 1e-3, "{lo} {hi}");
        // all successes on 1,000 vs on 30 effective samples
        assert!(wilson_interval(1.0, 1000.0)[0] > 0.99);
        assert!(wilson_interval(1.0, 30.0)[0] < 0.9);
        assert_eq!(wilson_interval(0.7, 0.0), [0.0, 1.0]);
    }

    #[test]
    fn point_biserial_sees_the_failing_side() {
        let x: Vec<f64> = (0..100).map(|i| i as f64).collect();
        let f: Vec<bool> = (0..100).map(|i| i > 70).collect();
        assert!(point_biserial(&f, &x) > 0.6);
        let g: Vec<bool> = (0..100).map(|i| i % 2 == 0).collect();
        assert!(point_biserial(&g, &x).abs() < 0.1);
        assert_eq!(point_biserial(&[true; 3], &[1.0, 2.0, 3.0]), 0.0);
    }

    #[test]
    fn table_clearance_of_a_top_grasp() {
        let g = Gripper::default_parallel_jaw();
        // table 1 cm below the finger tips, normal towards the palm (-z)
        let plane = SupportPlane {
            normal: [0.0, 0.0, -1.0],
            point_m: [0.0, 0.0, g.tip_z_m() + 0.01],
        };
        let c = table_clearance_m(&g, &plane).unwrap();
        assert!((c - 0.01).abs() < 1e-9, "{c}");
    }
}
