//! Next-best view: which of the listed views would best observe the uncertainty that makes
//! the grasp fail.
//!
//! A camera pins down translation across its image well and translation along its optical
//! axis (depth) worst; it sees rotation about its optical axis (in-plane) best and rotation
//! about axes across the image worst. So a failure driven by translation along axis `a` is
//! best observed by a view whose optical axis is perpendicular to `a` (score `1 - (o.a)^2`),
//! a failure driven by rotation about `a` by a view looking along `a` (score `(o.a)^2`); the
//! scores are weighted by each axis's correlation with failing.

use super::decision::{Decision, Motion};
use crate::geometry::Pose;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// A view the robot could take (a camera, or a robot pose the caller lists).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandidateView {
    pub name: String,
    /// The camera (optical frame) in the reference frame of the decision.
    pub reference_from_camera: Pose,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewSuggestion {
    /// The best view.
    pub name: String,
    pub score: f64,
    /// Every view's score, in the order given.
    pub scores: Vec<(String, f64)>,
}

/// The view that best observes the failure-driving axes of `decision`, or `None` when no axis
/// drives the failures or no view is listed.
pub fn suggest_view(decision: &Decision, views: &[CandidateView]) -> Option<ViewSuggestion> {
    let drivers: Vec<_> = decision.driving_axes().collect();
    if drivers.is_empty() || views.is_empty() {
        return None;
    }
    let scores: Vec<(String, f64)> = views
        .iter()
        .map(|v| {
            let o = v.reference_from_camera.rotation * Vector3::z();
            let s = drivers
                .iter()
                .map(|d| {
                    let a = Vector3::from(d.axis_in_reference);
                    let c = o.dot(&a).powi(2);
                    d.failure_correlation
                        * match d.motion {
                            Motion::Translation => 1.0 - c,
                            Motion::Rotation => c,
                        }
                })
                .sum();
            (v.name.clone(), s)
        })
        .collect();
    let best = scores
        .iter()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .cloned()?;
    Some(ViewSuggestion {
        name: best.0,
        score: best.1,
        scores,
    })
}
