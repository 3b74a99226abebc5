//! Recovery when the cameras disagree with a track (see [`super::RecoveryConfig`]): each view's
//! detection of the track's object gives a position with its own uncertainty; a view agrees
//! when one of its detections lies inside the track's 99 % region, disagrees when none does.
//! Detections that another live track of the object holds are not this track's evidence, so a
//! second instance of the object cannot pull the track over while it is tracked itself; and the
//! disagreeing views must agree with each other (one place, seen twice) and outnumber the
//! supporting ones, and a recovery is followed by a cool-down, so two instances seen by
//! different cameras cannot make the track jump back and forth.

use super::{Model, TrackState, Tracker, TrackerConfig, detection_centre, normalise};
use crate::geometry::Pose;
use crate::tracker::{CameraFrame, Detection, ReinitReason, Reinitialisation, StepReport, TrackStatus};
use nalgebra::{Matrix3, Point3, Vector3};

/// Steps in a row that the cameras disagreed with a track, and steps left of its cool-down.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct Disagreement {
    pub steps: u32,
    pub cooldown: u32,
}

/// One view's detection as a position in the reference frame with its covariance.
struct Sighting {
    view: usize,
    position: Vector3<f64>,
    covariance: Matrix3<f64>,
}

/// Squared Mahalanobis distance of `d` under `cov` (infinite when `cov` is singular).
fn mahalanobis2(d: &Vector3<f64>, cov: &Matrix3<f64>) -> f64 {
    cov.try_inverse()
        .map_or(f64::INFINITY, |inv| (d.transpose() * inv * d)[(0, 0)])
}

impl Tracker {
    /// Whether `det` in `frame` holds track `si` (see [`detection_holds`]).
    pub(super) fn detection_holds(
        &self,
        si: usize,
        frame: &CameraFrame,
        det: &Detection,
        view_from_ref: &Pose,
    ) -> bool {
        detection_holds(&self.states[si], &self.models, &self.config, frame, det, view_from_ref)
    }

    /// The position of the object's centre that a detection implies (reference frame), with the
    /// covariance of the particles a detection spawns (box-centre jitter, depth spread).
    fn sighting(&self, mi: usize, frame: &CameraFrame, det: &Detection, view_from_ref: &Pose, view: usize) -> Sighting {
        let diameter = self.models[mi].codebook.diameter_m;
        let [_, _, bw, bh] = det.bbox_xywh_px;
        let (uv, z) = detection_centre(frame, det, diameter);
        let k = &frame.intrinsics;
        let p_view = k.unproject(uv, z).coords;
        // uniform jitter of +-j over the box: variance j^2 / 3, in metres at depth z
        let j = self.config.init_uv_jitter_rel;
        let sx = j * bw / 3f64.sqrt() * z / k.fx();
        let sy = j * bh / 3f64.sqrt() * z / k.fy();
        let sz = self.config.init_depth_sigma_m + 0.1 * diameter;
        // along the ray and across it: the depth spread lies along the ray
        let ray = p_view.normalize();
        let across = Matrix3::identity() - ray * ray.transpose();
        let lateral = sx.max(sy);
        let cov_view = across * (lateral * lateral) + ray * ray.transpose() * (sz * sz);
        let r = view_from_ref.rotation.inverse().to_rotation_matrix();
        let ref_from_view = view_from_ref.inverse();
        Sighting {
            view,
            position: (ref_from_view * Point3::from(p_view)).coords,
            covariance: r.matrix() * cov_view * r.matrix().transpose(),
        }
    }

    /// Counts the steps in a row that the cameras disagree with track `ti` and, after
    /// `RecoveryConfig::steps` of them, spawns the disagreeing views' particles again.
    pub(super) fn check_disagreement(
        &mut self,
        ti: usize,
        views: &[(&CameraFrame, Pose, usize)],
        report: &mut StepReport,
    ) {
        let cfg = self.config.recovery;
        let s = &self.states[ti];
        if s.n() == 0 || self.tracks[ti].status == TrackStatus::Lost {
            return;
        }
        let mi = s.model;
        let (mean, cov) = {
            let set = s.set(&self.models[mi].tables, self.config.spread);
            (set.mean_position(), set.translation_covariance().0)
        };
        let mut agreeing = 0usize;
        let mut disagreeing: Vec<Sighting> = Vec::new();
        for (k, (frame, view_from_ref, _)) in views.iter().enumerate() {
            let mut best: Option<(f64, Sighting)> = None;
            for det in frame.detections.iter().filter(|d| d.object == self.models[mi].name) {
                let [_, _, bw, bh] = det.bbox_xywh_px;
                if !(bw > 1.0 && bh > 1.0) {
                    continue;
                }
                let held_by_other = (0..self.states.len()).any(|o| {
                    o != ti
                        && self.states[o].model == mi
                        && self.tracks[o].status != TrackStatus::Lost
                        && self.detection_holds(o, frame, det, view_from_ref)
                });
                if held_by_other {
                    continue;
                }
                let sight = self.sighting(mi, frame, det, view_from_ref, k);
                let d2 = mahalanobis2(&(sight.position - mean), &(cov + sight.covariance));
                if best.as_ref().is_none_or(|b| d2 < b.0) {
                    best = Some((d2, sight));
                }
            }
            match best {
                Some((d2, _)) if d2 <= cfg.region_chi2 => agreeing += 1,
                Some((_, sight)) => disagreeing.push(sight),
                None => {}
            }
        }
        // the largest group of disagreeing views that agree with each other
        let group: Vec<usize> = (0..disagreeing.len())
            .map(|a| {
                (0..disagreeing.len())
                    .filter(|&b| {
                        let (x, y) = (&disagreeing[a], &disagreeing[b]);
                        a == b
                            || mahalanobis2(&(x.position - y.position), &(x.covariance + y.covariance))
                                <= cfg.region_chi2
                    })
                    .collect::<Vec<_>>()
            })
            .max_by_key(|g| g.len())
            .unwrap_or_default();
        let d = &mut self.states[ti].disagreement;
        d.cooldown = d.cooldown.saturating_sub(1);
        if group.len() >= 2 && group.len() >= agreeing {
            d.steps += 1;
        } else {
            d.steps = 0;
        }
        if d.steps < cfg.steps || d.cooldown > 0 {
            return;
        }
        let steps = d.steps;
        *d = Disagreement {
            steps: 0,
            cooldown: cfg.cooldown_steps,
        };
        let sightings: Vec<&Sighting> = group.iter().map(|&g| &disagreeing[g]).collect();
        let target: Vector3<f64> = sightings.iter().map(|s| s.position).sum::<Vector3<f64>>() / sightings.len() as f64;
        let mut cameras = Vec::new();
        let old_n = self.states[ti].n();
        let mut respawned_cams = Vec::new();
        for sight in &sightings {
            let (frame, view_from_ref, ci) = &views[sight.view];
            // the detection nearest the group's place in this view
            let Some(det) = frame
                .detections
                .iter()
                .filter(|d| d.object == self.models[mi].name && d.bbox_xywh_px[2] > 1.0 && d.bbox_xywh_px[3] > 1.0)
                .min_by(|a, b| {
                    let pa = self.sighting(mi, frame, a, view_from_ref, 0).position;
                    let pb = self.sighting(mi, frame, b, view_from_ref, 0).position;
                    (pa - target).norm().total_cmp(&(pb - target).norm())
                })
            else {
                continue;
            };
            let det = det.clone();
            let parts = self.init_particles(mi, frame, &det, view_from_ref, *ci);
            self.add_particles(ti, parts, *ci);
            respawned_cams.push(*ci);
            cameras.push(frame.camera.clone());
        }
        // the disagreeing views' old particles go; the new ones took the rotation belief
        let s = &mut self.states[ti];
        let keep: Vec<usize> = (0..s.n())
            .filter(|&i| i >= old_n || !respawned_cams.contains(&s.sources[i]))
            .collect();
        s.positions = keep.iter().map(|&i| s.positions[i]).collect();
        s.sources = keep.iter().map(|&i| s.sources[i]).collect();
        s.weights = keep.iter().map(|&i| s.weights[i]).collect();
        s.rot.resample(&keep);
        normalise(&mut s.weights);
        s.map_cache.clear();
        s.carried_fits.clear();
        let track = &mut self.tracks[ti];
        track.reinitialised = Some(Reinitialisation {
            stamp_ns: self.stamp_ns,
            reason: ReinitReason::CamerasDisagreed {
                cameras,
                offset_m: (target - mean).norm(),
                steps,
            },
        });
        report.tracks_reinitialised.push(track.id);
        self.refresh_estimate(ti);
    }
}

/// Whether `det` in `frame` holds the track of state `s`: the track's mean projects inside the
/// box grown by `association_margin_rel` of its side.
pub(super) fn detection_holds(
    s: &TrackState,
    models: &[Model],
    config: &TrackerConfig,
    frame: &CameraFrame,
    det: &Detection,
    view_from_ref: &Pose,
) -> bool {
    if s.n() == 0 {
        return false;
    }
    let [bx, by, bw, bh] = det.bbox_xywh_px;
    let margin = config.association_margin_rel;
    let m = s.set(&models[s.model].tables, config.spread).mean_position();
    let p = view_from_ref * Point3::from(m);
    // the box's edges are at bx - 0.5 and bx + bw - 0.5 in pixel coordinates
    match frame.intrinsics.project(&p).map(|[u, v]| [u + 0.5, v + 0.5]) {
        Some([u, v]) => {
            u >= bx - margin * bw
                && u <= bx + bw * (1.0 + margin)
                && v >= by - margin * bh
                && v <= by + bh * (1.0 + margin)
        }
        None => false,
    }
}
